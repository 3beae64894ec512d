"""Calibration: a camera's status, history, forced re-solve and reset (routes, schemas), when a solve is due, the
solve on a balanced sample of the stored evidence and whether it becomes current (service, the calibration job's
work), calibration versions in the store (repository) and the evidence sampling (evidence)."""
