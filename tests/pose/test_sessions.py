"""The two runtimes behind one session interface: OpenVINO computes what onnxruntime does (float32), is safe to
call from the crop pool's threads, and its bfloat16 keypoints stay within the float model's own jitter."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest

from service.pose import sessions
from service.pose.model_files import LIGHTNING
from service.pose.movenet import INPUT_NAME, OUTPUT_NAME, MoveNet, crop_window, read_people
from service.pose.pipeline import TopDownPose
from service.pose.sessions import OpenVINOSession, make_session, native_bf16, resolve_runtime


def _crops(count: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (count, 1, 192, 192, 3)).astype(np.int32)


def test_auto_is_openvino_exactly_where_the_cpu_has_native_bfloat16() -> None:
    assert resolve_runtime("auto") == ("openvino" if native_bf16() else "onnxruntime")
    assert resolve_runtime("onnxruntime") == "onnxruntime"
    assert resolve_runtime("openvino") == "openvino"


def test_openvino_in_float32_computes_what_onnxruntime_does(model_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """On a CPU without native bfloat16 (as this one pretends to be), `openvino` computes in float32: what
    onnxruntime computes, to float rounding."""
    monkeypatch.setattr(sessions, "native_bf16", lambda: False)
    path = model_dir / LIGHTNING.file_name
    reference = make_session(path, 1)
    exact = make_session(path, 1, runtime="openvino")
    assert isinstance(reference, ort.InferenceSession) and isinstance(exact, OpenVINOSession)
    assert [i.name for i in exact.get_inputs()] == [INPUT_NAME]
    for crop in _crops(3):
        want = reference.run([OUTPUT_NAME], {INPUT_NAME: crop})[0]
        got = exact.run([OUTPUT_NAME], {INPUT_NAME: crop})[0]
        assert got.shape == want.shape == (1, 1, 17, 3)
        assert np.allclose(got, want, rtol=0.0, atol=1e-4)


def test_concurrent_callers_each_get_their_own_answer(model_dir: Path) -> None:
    """Two threads at once on one session with two streams: every answer is the one a lone call gives."""
    session = make_session(model_dir / LIGHTNING.file_name, 1, runtime="openvino", streams=2)
    crops = _crops(12, seed=1)
    alone = [session.run([OUTPUT_NAME], {INPUT_NAME: c})[0] for c in crops]
    with ThreadPoolExecutor(2) as pool:
        together = list(pool.map(lambda c: session.run([OUTPUT_NAME], {INPUT_NAME: c})[0], crops))
    for a, b in zip(alone, together, strict=True):
        assert np.array_equal(a, b)


def test_the_detector_runs_on_onnxruntime_in_float32_whatever_the_pose_runtime(model_dir: Path) -> None:
    estimator = TopDownPose(model_dir, "lightning", pose_runtime="openvino")
    assert isinstance(estimator.detector.session, ort.InferenceSession)
    assert estimator.movenets["lightning"].runtime == "openvino"


@pytest.mark.skipif(not native_bf16(), reason="this CPU has no native bfloat16: auto runs onnxruntime in float32")
def test_bfloat16_keypoints_move_no_more_than_a_one_pixel_crop_shift_moves_the_float_model(
    model_dir: Path, town_frames: dict[int, np.ndarray]
) -> None:
    """bfloat16 is worth its speed only while it perturbs the keypoints no more than the float model's own response
    to a negligible change of its input, a crop one pixel off (measured: 1.86 against 1.85 px mean at the 192 px
    input); INT8 moved them twice as far and was not used (docs/benchmarks/pose.md)."""
    path = model_dir / LIGHTNING.file_name
    f32 = MoveNet(path, "lightning", runtime="onnxruntime")
    bf16 = MoveNet(path, "lightning", runtime="openvino")
    estimator = TopDownPose(model_dir, "lightning", pose_runtime="onnxruntime")
    moved_bf16: list[np.ndarray] = []
    moved_shift: list[np.ndarray] = []
    for number in (0, 60, 120):
        image = town_frames[number]
        boxes = estimator.detect(image)[0].boxes_xyxy_px
        base = read_people(image, boxes, [f32] * len(boxes))
        other = read_people(image, boxes, [bf16] * len(boxes))
        shifted = read_people(image, boxes + 1.0, [f32] * len(boxes))
        for k, box in enumerate(boxes):
            seen = base.scores[k] > 0.3
            scale = 192 / crop_window(box).side  # image pixels to the model's input pixels
            for moved, read in ((moved_bf16, other), (moved_shift, shifted)):
                moved.append(np.linalg.norm(read.keypoints_px[k][seen] - base.keypoints_px[k][seen], axis=1) * scale)
    bf16_px, shift_px = np.concatenate(moved_bf16), np.concatenate(moved_shift)
    assert len(bf16_px) > 300
    assert bf16_px.mean() < 1.15 * shift_px.mean(), (bf16_px.mean(), shift_px.mean())
    p95 = np.percentile(bf16_px, 95), np.percentile(shift_px, 95)
    assert p95[0] < 1.15 * p95[1], p95


def test_a_forking_worker_runs_onnxruntime_and_refuses_openvino(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sessions, "_forked_jobs", False)
    sessions.serve_forked_jobs()
    assert resolve_runtime("auto") == "onnxruntime"
    with pytest.raises(ValueError, match="--fork"):
        resolve_runtime("openvino")


def test_an_openvino_session_refuses_to_run_in_a_forked_child_instead_of_hanging(model_dir: Path) -> None:
    session = make_session(model_dir / LIGHTNING.file_name, 1, runtime="openvino")
    crop = _crops(1)[0]
    session.run([OUTPUT_NAME], {INPUT_NAME: crop})  # its threads exist, in this process
    pid = os.fork()
    if pid == 0:  # the child: exit 3 if refused, 4 if it ran, never hang (the parent kills it after 30 s)
        try:
            session.run([OUTPUT_NAME], {INPUT_NAME: crop})
            os._exit(4)
        except RuntimeError:
            os._exit(3)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            assert os.waitstatus_to_exitcode(status) == 3
            return
        time.sleep(0.05)
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    pytest.fail("the forked child hung in the OpenVINO session")


_FIRST_INFERENCE_RACE = """
import sys, threading
from pathlib import Path
import numpy as np
from service.pose.sessions import make_session
session = make_session(Path(sys.argv[1]), 1, runtime="openvino", streams=4)
feed = {session.get_inputs()[0].name: np.zeros((1, 192, 192, 3), np.int32)}
barrier = threading.Barrier(4)
def first() -> None:
    barrier.wait()
    session.run(None, feed)
threads = [threading.Thread(target=first) for _ in range(4)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
"""


def test_a_fresh_process_s_first_inferences_on_several_threads_at_once_do_not_deadlock(model_dir: Path) -> None:
    """A pose worker's first frame runs its crops on the pool's threads at once. Before the first inference ran
    alone, about a quarter of fresh processes doing this with four threads hung for good (OpenVINO's numpy bridge
    is initialised on first use); 24 processes, two at a time, each given 30 s, all finish."""
    model = str(model_dir / LIGHTNING.file_name)
    hung = 0
    for _ in range(12):
        pair = [
            subprocess.Popen([sys.executable, "-c", _FIRST_INFERENCE_RACE, model], stderr=subprocess.PIPE)
            for _ in range(2)
        ]
        for process in pair:
            try:
                _, stderr = process.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.communicate()
                hung += 1
                continue
            assert process.returncode == 0, stderr.decode()
    assert hung == 0, f"{hung} of 24 fresh processes deadlocked in their first inferences"
