"""`posemetry analyze` applies the service's static-spot rule: a still "person" (a mannequin) is no evidence."""

from __future__ import annotations

import numpy as np

from service.analyze.analysis import AnalyzedFrame, Evidence
from service.analyze.run import mark_static
from service.cameras.static_rule import FORGET_AFTER_S, static_in_recording
from service.domain import PersonIn
from service.frames.keypoints import STATIC_REASON

MANNEQUIN = (100.0, 200.0, 160.0, 380.0)


def _person(box: tuple[float, float, float, float]) -> PersonIn:
    left, top, right, bottom = box
    centre = (left + right) / 2
    return PersonIn(shoulder_px=(centre, top + 30.0), ankle_px=(centre, bottom - 5.0), box_px=box)


def _recording(frames: int, fps: float = 25.0) -> list[AnalyzedFrame]:
    """A mannequin jittering by a pixel in every frame, a walker crossing at 1 m/s (6 px a frame)."""
    rng = np.random.default_rng(0)
    out = []
    for k in range(frames):
        left, top, right, bottom = (np.array(MANNEQUIN) + rng.normal(0.0, 1.0, 4)).tolist()
        still = (left, top, right, bottom)
        walker = (600.0 + 6 * k, 300.0, 660.0 + 6 * k, 480.0)
        out.append(AnalyzedFrame(k, k / fps, None, [_person(still), _person(walker)]))
    return out


def test_a_still_spot_is_no_evidence_once_it_has_stood_for_the_static_time() -> None:
    frames = _recording(100)  # 4 s
    marked = mark_static(frames, static_after_s=3.0)
    # Every sighting of the mannequin, the first ones too (the recording is known whole); never the walker.
    assert all(f.people[0].unusable_reason == STATIC_REASON for f in marked)
    assert all(f.people[1].unusable_reason is None for f in marked)
    assert len(Evidence.of(frames)) == 200 and len(Evidence.of(marked)) == 100
    # Not yet static: it stood for less than the static time.
    assert all(p.unusable_reason is None for f in mark_static(frames, static_after_s=5.0) for p in f.people)
    # Without frame times (a folder of images) nothing can be judged still for long.
    timeless = [AnalyzedFrame(f.index, None, None, f.people) for f in frames]
    assert mark_static(timeless, static_after_s=3.0) == timeless


def test_a_spot_unseen_for_the_forget_time_starts_again() -> None:
    times = [0.0, 1.0, 2.0, 2.0 + FORGET_AFTER_S + 1.0, 3.0 + FORGET_AFTER_S]
    boxes = [[MANNEQUIN]] * len(times)
    assert static_in_recording(times, boxes, 2.0) == [[True], [True], [True], [False], [False]]
    assert static_in_recording(times[:3], [[MANNEQUIN], [None], [MANNEQUIN]], 2.0) == [[False], [False], [False]]
