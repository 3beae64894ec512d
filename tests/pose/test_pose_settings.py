"""The pose settings: defaults, environment overrides and the validation an operator relies on."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from service.settings import Settings


def test_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("MODEL_DIR", "POSE_MODEL", "POSE_RUNTIME", "DETECTOR_INPUT_PX", "INFERENCE_THREADS"):
        monkeypatch.delenv(f"POSEMETRY_{name}", raising=False)
    settings = Settings()
    assert settings.pose_model == "auto" and settings.pose_runtime == "auto" and settings.detector_input_px == 640
    assert settings.inference_threads is None
    assert settings.model_dir == Path("~/.cache/posemetry/models")


def test_environment_overrides(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("POSEMETRY_MODEL_DIR", str(tmp_path))
    monkeypatch.setenv("POSEMETRY_POSE_MODEL", "lightning")
    monkeypatch.setenv("POSEMETRY_POSE_RUNTIME", "onnxruntime")
    monkeypatch.setenv("POSEMETRY_DETECTOR_INPUT_PX", "416")
    monkeypatch.setenv("POSEMETRY_INFERENCE_THREADS", "1")
    settings = Settings()
    assert (settings.model_dir, settings.pose_model, settings.detector_input_px, settings.inference_threads) == (
        tmp_path,
        "lightning",
        416,
        1,
    )
    assert settings.pose_runtime == "onnxruntime"


@pytest.mark.parametrize(
    "override",
    [{"pose_model": "multipose"}, {"pose_runtime": "tensorrt"}, {"detector_input_px": 500}, {"inference_threads": 0}],
)
def test_invalid_values_are_rejected(override: dict[str, object]) -> None:
    with pytest.raises(ValidationError):
        Settings(**override)
