"""The one error `posemetry analyze` shows its user: a problem they can act on, in one line, never a traceback."""

from __future__ import annotations


class AnalyzeError(Exception):
    """Bad input or a run that cannot finish (no people, no calibration); the message is shown as is."""
