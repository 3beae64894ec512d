"""The model registry refuses missing, truncated and altered files, and says which ones and how to get them."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from service.pose import model_files
from service.pose.model_files import (
    DETECTOR,
    LIGHTNING,
    REGISTRY,
    THUNDER,
    ModelFilesError,
    resolve_choice,
    resolve_models,
)


def _copy(model_dir: Path, target: Path, *specs: model_files.ModelFile) -> None:
    for spec in specs:
        shutil.copyfile(model_dir / spec.file_name, target / spec.file_name)


def test_good_files_resolve(model_dir: Path) -> None:
    paths = resolve_models(model_dir, "lightning")
    assert paths.detector == model_dir / DETECTOR.file_name
    assert paths.pose == model_dir / LIGHTNING.file_name


def test_missing_files_are_all_named_with_directory_and_fix(tmp_path: Path) -> None:
    with pytest.raises(ModelFilesError) as caught:
        resolve_models(tmp_path, "thunder")
    message = str(caught.value)
    assert DETECTOR.file_name in message and THUNDER.file_name in message
    assert LIGHTNING.file_name not in message  # only what this pipeline needs
    assert str(tmp_path) in message
    assert f"posemetry models fetch --dir {tmp_path}" in message
    assert caught.value.problems == {DETECTOR.file_name: "missing", THUNDER.file_name: "missing"}


def test_one_flipped_byte_is_caught(model_dir: Path, tmp_path: Path) -> None:
    _copy(model_dir, tmp_path, DETECTOR, LIGHTNING)
    path = tmp_path / LIGHTNING.file_name
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01  # same size: only the checksum can tell
    path.write_bytes(bytes(data))
    with pytest.raises(ModelFilesError) as caught:
        resolve_models(tmp_path, "lightning")
    assert list(caught.value.problems) == [LIGHTNING.file_name]
    assert "sha256" in caught.value.problems[LIGHTNING.file_name]


def test_truncated_file_is_caught_by_size(model_dir: Path, tmp_path: Path) -> None:
    _copy(model_dir, tmp_path, LIGHTNING)
    (tmp_path / DETECTOR.file_name).write_bytes((model_dir / DETECTOR.file_name).read_bytes()[:1000])
    with pytest.raises(ModelFilesError) as caught:
        resolve_models(tmp_path, "lightning")
    assert "size 1000 bytes" in caught.value.problems[DETECTOR.file_name]


def test_replaced_file_is_hashed_again(model_dir: Path, tmp_path: Path) -> None:
    """The per-process hash cache must not vouch for a file that changed on disk after it was checked."""
    _copy(model_dir, tmp_path, DETECTOR, LIGHTNING)
    resolve_models(tmp_path, "lightning")
    path = tmp_path / DETECTOR.file_name
    data = bytearray(path.read_bytes())
    data[100] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ModelFilesError):
        resolve_models(tmp_path, "lightning")


def test_unknown_pose_model_is_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown pose model"):
        resolve_models(tmp_path, "multipose")  # type: ignore[arg-type]


def test_registry_is_complete() -> None:
    assert set(REGISTRY) == {"detector", "thunder", "lightning"}
    for spec in REGISTRY.values():
        assert len(spec.sha256) == 64 and spec.size_bytes > 1_000_000 and spec.licence == "Apache-2.0"


def test_auto_needs_both_movenets_and_names_every_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ModelFilesError) as caught:
        resolve_choice(tmp_path, "auto")
    assert set(caught.value.problems) == {DETECTOR.file_name, THUNDER.file_name, LIGHTNING.file_name}
    with pytest.raises(ValueError, match="unknown pose model"):
        resolve_choice(tmp_path, "multipose")  # type: ignore[arg-type]
