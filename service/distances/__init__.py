"""Distances on demand: `POST .../distances` measures posted people with the camera's current calibration, storing
nothing (routes, schemas); the measuring itself is the frames room's (service.frames.measure)."""
