"""A measuring job's chunk: its frames measured in one pass give each frame the result it gets alone.

`measure_frames` (one geometric pass for a chunk) against `measure_people` of each frame: the stored JSON is the
same text, the violations the same rows. Frames of 0 and 1 person, unplaceable, seated, partly seen, box-placed and
static people, and an unreliable grade, are in the random chunks. And through the job's `frame_outcomes`: a frame
whose people the geometry refuses fails alone, its neighbours are measured.
"""

from __future__ import annotations

import json
import uuid
from dataclasses import replace
from datetime import UTC, datetime
from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.domain import POSTURES, PersonIn
from service.frames.measure import (
    BOX_CONTACT_STD_FRACTION,
    PARTIAL_HEIGHT_STD_M,
    SEATED_HEIGHT_FRACTION,
    SEATED_HEIGHT_STD_M,
    measure_frames,
    measure_people,
)
from service.frames.service import frame_outcomes
from service.geometry import DEFAULT_HEIGHT_STD_M, Uncertainty, measure
from service.store.models import Camera, Frame
from tests.render.scenes import calibration_of, tilted_scene, version_of

THRESHOLD_M = 1.8288
SCENE = tilted_scene(n_people=4)
CAL = replace(
    calibration_of(SCENE),
    uncertainty=Uncertainty(
        fx_px=20.0,
        fy_px=20.0,
        normal_deg=0.8,
        rho_m=0.05,
        covariance=np.diag([20.0, 20.0, 0.01, 0.01, 0.05, 5.0, 5.0, 0.01]) ** 2,
        noise_px=1.2,
    ),
)


def _frames(seed: int, sizes: list[int]) -> list[list[PersonIn]]:
    """Frames of `sizes` people crowded into a few metres (so that some pairs are violations), of every kind."""
    rng = np.random.default_rng(seed)
    frames = []
    for size in sizes:
        people = []
        for _ in range(size):
            bottom = (float(rng.uniform(500, 800)), float(rng.uniform(450, 650)))
            top = (bottom[0] + float(rng.normal(0, 3)), bottom[1] - float(rng.uniform(80, 140)))
            seen = rng.integers(0, 5)
            posture = rng.integers(0, len(POSTURES) + 1)  # the last: posted keypoints, no posture
            people.append(
                PersonIn(
                    shoulder_px=None if seen == 0 else top,
                    ankle_px=None if seen in (0, 1) else bottom,
                    unusable_reason=None if posture == 0 else "not evidence",
                    track_id=f"t{rng.integers(0, 100)}" if seen == 3 else None,
                    posture=POSTURES[posture] if posture < len(POSTURES) else None,
                    placed_from_box=bool(rng.integers(0, 4) == 0),
                    static=bool(rng.integers(0, 5) == 0),
                )
            )
        frames.append(people)
    return frames


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.integers(0, 9), min_size=1, max_size=6),
    st.integers(0, 2**31),
    st.sampled_from([None, "good", "unreliable"]),
    st.booleans(),
)
def test_a_chunk_gives_each_frame_its_result_alone(
    sizes: list[int], seed: int, grade: str | None, with_uncertainty: bool
) -> None:
    cal = CAL if with_uncertainty else calibration_of(SCENE)
    frames = _frames(seed, sizes)
    options = {"distance_threshold_m": THRESHOLD_M, "calibration_version": 4, "calibration_grade": grade}
    chunk = measure_frames(frames, cal, **options)
    assert len(chunk) == len(frames)
    for people, together in zip(frames, chunk, strict=True):
        alone = measure_people(people, cal, **options)
        assert together.result_json() == alone.result_json()
        assert together.violations == alone.violations


@settings(max_examples=20, deadline=None)
@given(st.lists(st.integers(0, 9), min_size=1, max_size=4), st.integers(0, 2**31))
def test_pairs_and_violations_are_the_geometry_s_distances_within_each_frame(sizes: list[int], seed: int) -> None:
    """The documents hold, for each frame, the distances `measure` gives its people (null where unknown), and the
    violations are the pairs under the threshold without a static person."""
    frames = _frames(seed, sizes)
    for people, computation in zip(frames, measure_frames(frames, CAL, distance_threshold_m=THRESHOLD_M), strict=True):
        document = json.loads(computation.result_json())
        n = len(people)
        assert [p["index"] for p in document["people"]] == list(range(n))
        assert len(document["pairs"]) == n * (n - 1) // 2
        if n == 0:
            continue
        tops = [p.shoulder_px or (np.nan, np.nan) for p in people]
        bottoms = [p.ankle_px or (np.nan, np.nan) for p in people]
        m = measure(CAL, tops, bottoms, **_priors(people))
        static = [p.static for p in people]
        expected_violations = []
        for pair in document["pairs"]:
            i, j = pair["i"], pair["j"]
            distance = m.distances_m[i, j]
            if np.isfinite(distance):
                assert pair["distance_m"] == distance and pair["distance_std_m"] == m.distance_std_m[i, j]
                if distance < THRESHOLD_M and not (static[i] or static[j]):
                    expected_violations.append(pair)
            else:
                assert pair["distance_m"] is None and pair["distance_std_m"] is None
        assert document["violations"] == expected_violations
        assert [(v.person_i, v.person_j) for v in computation.violations] == [
            (p["i"], p["j"]) for p in expected_violations
        ]


def _priors(people: list[PersonIn]) -> dict[str, np.ndarray]:
    """The posture priors service.frames.measure gives each person, restated from its constants."""
    box = [p.placed_from_box for p in people]
    seated = [not p.placed_from_box and p.posture == "seated" for p in people]
    partial = [not p.placed_from_box and p.posture == "partial" for p in people]
    return {
        "height_scale": np.where(seated, SEATED_HEIGHT_FRACTION, 1.0),
        "height_std_m": np.where(
            seated, SEATED_HEIGHT_STD_M, np.where(partial, PARTIAL_HEIGHT_STD_M, DEFAULT_HEIGHT_STD_M)
        ),
        "contact_std_fraction": np.where(box, BOX_CONTACT_STD_FRACTION, 0.0),
    }


def test_a_frame_the_geometry_refuses_fails_alone() -> None:
    """A stored person the geometry cannot read (here a coordinate that is no number) fails their frame only."""
    camera = Camera(id="cam-c", image_width_px=1280, image_height_px=720, distance_threshold_m=THRESHOLD_M)
    calibration = version_of(calibration_of(SCENE))
    t0 = datetime(2026, 3, 1, tzinfo=UTC)
    frames = [Frame(id=uuid.uuid4(), camera_id="cam-c", timestamp=t0) for _ in range(3)]
    people = [[_row(p) for p in frame] for frame in _frames(7, [3, 2, 4])]
    people[1][1].shoulder_x_px = "not a number"
    outcomes = frame_outcomes(frames, people, camera, calibration)
    assert [o.status for o in outcomes] == ["done", "failed", "done"]
    assert "not a number" in (outcomes[1].error or "")
    for index in (0, 2):
        alone = frame_outcomes([frames[index]], [people[index]], camera, calibration)[0]
        assert outcomes[index] == alone and outcomes[index].result is not None


def _row(person: PersonIn) -> SimpleNamespace:
    """A stored person as service.frames.repository.frames_points reads it."""
    shoulder, ankle = person.shoulder_px, person.ankle_px
    return SimpleNamespace(
        shoulder_x_px=None if shoulder is None else shoulder[0],
        shoulder_y_px=None if shoulder is None else shoulder[1],
        ankle_x_px=None if ankle is None else ankle[0],
        ankle_y_px=None if ankle is None else ankle[1],
        unusable_reason=person.unusable_reason,
        client_track_id=None,
        posture=person.posture,
        placed_from_box=person.placed_from_box,
        static=person.static,
    )
