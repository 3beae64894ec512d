"""posemetry: camera auto-calibration and physical distances from human pose."""

__version__ = "0.1.0"
