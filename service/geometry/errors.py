"""The one exception the geometry raises for inputs it cannot calibrate from."""


class CalibrationError(ValueError):
    """No valid calibration exists for the input; the message says why."""
