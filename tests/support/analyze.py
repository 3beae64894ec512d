"""`posemetry analyze` as a user types it (in-process, output captured), and the real Town Centre clip it runs on."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from click.testing import Result
from typer.testing import CliRunner

from service.cli import app
from tests.support.shared import TOWN_CENTRE

TOWN_VIDEO = TOWN_CENTRE / "TownCentreXVID_clip126.mp4"
TOWN_CALIBRATION = TOWN_CENTRE / "TownCentre-calibration-ci.txt"


def analyze(*args: str | Path) -> Result:
    """`posemetry analyze ARGS` in-process; stdout and stderr captured."""
    return CliRunner().invoke(app, ["analyze", *(str(a) for a in args)])


def write_image(path: Path, size_px: tuple[int, int] = (320, 240), value: int = 90) -> Path:
    image = np.full((size_px[1], size_px[0], 3), value, dtype=np.uint8)
    ok, data = cv2.imencode(path.suffix, image)
    assert ok
    path.write_bytes(data.tobytes())
    return path
