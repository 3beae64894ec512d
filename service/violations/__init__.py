"""Violations: counts of close pairs per minute or hour and the heat map (routes, schemas), and violation events in
the store (repository; a measured frame's events are written with its result)."""
