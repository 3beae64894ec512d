"""A frame's result (positions, pair distances, violations) from its people and a calibration (pure).

Shared by the synchronous `POST .../distances` endpoint, the measuring job and `posemetry analyze`, so that a
frame's stored result, an on-demand measurement of the same people and an offline run are computed by the same
code. No I/O and no store: callers read the calibration and the people, and write the outcome back
(service.frames.service does that for stored frames).

A measuring job hands a whole chunk of frames to `measure_frames`: the geometry places and measures all their people
in one vectorised pass (service.geometry.measure.measure_many) and only the documents are built frame by frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pydantic_core

from service.domain import PersonIn, StoredCentres, ViolationIn, centres, track_id_of
from service.frames.schemas import FrameResult
from service.geometry import Calibration, Measurements, measure_many
from service.geometry.priors import DEFAULT_HEIGHT_STD_M

# Shoulder height of the people who are not calibration evidence, for placing them from their shoulders: a fraction
# of the camera's standing prior, and its 1-sigma in metres. Seated: an adult's shoulders are ~0.59 m above the
# seat (seated acromion height, 50th percentile) on a ~0.45 m seat, ~1.03 m above the floor against 1.32 m standing,
# with seats from stools to low sofas (+-0.12 m). Lower body not seen: standing or seated, nobody can tell, so the
# standing prior with a sigma that reaches a seated person's shoulders (0.3 m).
SEATED_HEIGHT_FRACTION = 0.78
SEATED_HEIGHT_STD_M = 0.12
PARTIAL_HEIGHT_STD_M = 0.3
# Pixel sigma of a box-bottom contact (service.frames.keypoints.place_from_boxes), as a fraction of a standing
# person's shoulder-to-ankle length in pixels at their place: measured on Town Centre (docs/benchmarks/pose.md).
BOX_CONTACT_STD_FRACTION = 0.06

_NAN_POINT = (math.nan, math.nan)


@dataclass(frozen=True)
class FrameComputation:
    """What measuring a frame produced: the result (encoded, as `frames.result` stores it) and the violation rows.

    The document is built from plain numbers, in FrameResult's shape, and encoded at once: in Rust (pydantic-core),
    five times faster than the json module for a frame's 190 pairs, with non-finite numbers already None. A
    FrameResult model is made only where one is needed (an HTTP answer, the offline writers): validating 190 pairs
    per frame in the worker cost as much as measuring them, and proved nothing the tests do not. Encoding at once
    drops each frame's dicts before the next frame's are built: a chunk's documents alive together (ten thousand
    dicts) made the garbage collector's passes cost more than building them.
    """

    encoded: str
    violations: list[ViolationIn]

    @property
    def result(self) -> FrameResult:
        return FrameResult.model_validate_json(self.encoded)

    def result_json(self) -> str:
        return self.encoded


def _ground_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(right, forward) unit vectors on the ground: the viewing direction projected onto it, and its right."""
    forward = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, normal)
    return right, forward


def _shoulder_priors(people: Sequence[StoredCentres | PersonIn]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each person's shoulder height (fraction of the prior) and its sigma, and the sigma of their ground contact
    (fraction of their standing height in pixels: not 0 for a box-bottom contact), from the pose's verdict."""
    scale = np.ones(len(people))
    std_m = np.full(len(people), DEFAULT_HEIGHT_STD_M)
    contact = np.zeros(len(people))
    for index, person in enumerate(people):
        if person.placed_from_box:
            contact[index] = BOX_CONTACT_STD_FRACTION
        elif person.posture == "seated":
            scale[index], std_m[index] = SEATED_HEIGHT_FRACTION, SEATED_HEIGHT_STD_M
        elif person.posture == "partial":
            std_m[index] = PARTIAL_HEIGHT_STD_M
    return scale, std_m, contact


def _placed_from(person: StoredCentres | PersonIn, has_bottom: bool) -> str:
    """`ankles`, `box` (the detector box's bottom, service.frames.keypoints.place_from_boxes) or `shoulders`."""
    if not has_bottom:
        return "shoulders"
    return "box" if person.placed_from_box else "ankles"


def measure_people(
    people: Sequence[StoredCentres | PersonIn],
    cal: Calibration,
    *,
    distance_threshold_m: float,
    calibration_version: int = 0,
    noise_px: float | None = None,
    calibration_grade: str | None = None,
) -> FrameComputation:
    """Place every person (ankles when seen, else shoulders), measure all pairs i < j, and flag violations.

    Everyone who can be placed counts, evidence or not: a seated person, or one whose lower body is hidden, is
    placed from whatever the pose trusted (their ankles, else their shoulders at a seated or uncertain height, see
    `_shoulder_priors`), with the wider sigma that implies, and takes part in violations. Only a static "person"
    (found where nothing has moved for a long time, cameras.static_spots) never does.

    A pair is a violation when its distance is strictly below `distance_threshold_m`; pairs involving a person
    who could not be placed (no shoulder and no ankle, or a ray missing the ground) have null distances and are
    never violations. `noise_px` is the keypoint noise for the distance uncertainties (default: the one the
    calibration estimated). With a calibration graded `unreliable` the pairs are measured but none is a
    violation: its verdicts are not trusted, so they raise no events and no alerts (`alerts_suppressed`).
    """
    return measure_frames(
        [people],
        cal,
        distance_threshold_m=distance_threshold_m,
        calibration_version=calibration_version,
        noise_px=noise_px,
        calibration_grade=calibration_grade,
    )[0]


def measure_frames(
    frames: Sequence[Sequence[StoredCentres | PersonIn]],
    cal: Calibration,
    *,
    distance_threshold_m: float,
    calibration_version: int = 0,
    noise_px: float | None = None,
    calibration_grade: str | None = None,
) -> list[FrameComputation]:
    """Each frame's people measured as `measure_people` does, all frames in one geometric pass (a measuring job's
    chunk); pairs are formed within a frame only. One person the geometry refuses raises for the whole call: the
    caller retries frame by frame to fail only that frame (service.frames.service.frame_outcomes)."""
    everyone = [person for people in frames for person in people]
    points = [centres(person) for person in everyone]
    tops = np.array([s if s is not None else _NAN_POINT for s, _ in points], dtype=float).reshape(-1, 2)
    bottoms = np.array([a if a is not None else _NAN_POINT for _, a in points], dtype=float).reshape(-1, 2)
    scale, std_m, contact = _shoulder_priors(everyone)
    m = measure_many(
        cal,
        tops,
        bottoms,
        [len(people) for people in frames],
        noise_px=noise_px,
        height_std_m=std_m,
        height_scale=scale,
        contact_std_fraction=contact,
    )
    foot = -cal.rho * cal.normal  # the point on the ground straight below the camera
    right, forward = _ground_axes(cal.normal)
    positions = m.points_bottom
    placed = np.all(np.isfinite(positions), axis=1)
    # Per person and per pair as plain Python values for the whole chunk; each frame's document takes its slices.
    static = [bool(person.static) for person in everyone]
    placed_from = [
        _placed_from(person, bottom is not None) if is_placed else None
        for person, (_, bottom), is_placed in zip(everyone, points, placed.tolist(), strict=True)
    ]
    point_m = positions.tolist()
    pair_m, pair_std_m = _pair_values(m)
    static_rows = np.array(static, dtype=bool)
    # A static "person" (a mannequin, cameras.static_spots) is measured like anyone but raises no violation.
    with np.errstate(invalid="ignore"):
        close = (m.distances_m < distance_threshold_m) & ~static_rows[m.first] & ~static_rows[m.second]
    close_at = np.flatnonzero(close)
    close_starts = np.searchsorted(close_at, m.pair_starts).tolist()
    close_at_list = close_at.tolist()
    pair_frame_start = np.repeat(m.frame_starts[:-1], np.diff(m.pair_starts))
    local_first, local_second = (m.first - pair_frame_start).tolist(), (m.second - pair_frame_start).tolist()
    frame_starts, pair_starts = m.frame_starts.tolist(), m.pair_starts.tolist()
    computations = []
    for f in range(len(frames)):
        n0, p0, p1 = frame_starts[f], pair_starts[f], pair_starts[f + 1]
        # A matrix product per frame, not one for the chunk: BLAS rounds a row differently with the number of rows,
        # and a frame's result must not depend on the chunk it was measured in.
        offset = positions[n0 : frame_starts[f + 1]] - foot
        ground = np.stack((offset @ right, offset @ forward), -1).tolist()
        people = [
            {
                "index": index,
                "placed_from": placed_from[row],
                "ground_m": ground[index] if placed_from[row] else None,
                "point_m": point_m[row] if placed_from[row] else None,
                "static": static[row],
                "track_id": track_id_of(person),
            }
            for index, (row, person) in enumerate(enumerate(frames[f], n0))
        ]
        # Pairs i < j, from plain Python values: a frame of 20 people has 190 pairs.
        pairs = [
            {"i": i, "j": j, "distance_m": d, "distance_std_m": sd}
            for i, j, d, sd in zip(
                local_first[p0:p1], local_second[p0:p1], pair_m[p0:p1], pair_std_m[p0:p1], strict=True
            )
        ]
        violating = [pairs[k - p0] for k in close_at_list[close_starts[f] : close_starts[f + 1]]]
        computations.append(
            _computation(people, pairs, violating, distance_threshold_m, calibration_version, calibration_grade)
        )
    return computations


def _pair_values(m: Measurements) -> tuple[list[float | None], list[float | None]]:
    """Every pair's distance and sigma as plain values, None where unknown (an unplaced person, a sigma that is
    not finite): the few unknowns are patched into the lists rather than tested pair by pair."""
    known = np.isfinite(m.distances_m)
    distances: list[float | None] = m.distances_m.tolist()
    stds: list[float | None] = m.distance_std_m.tolist()
    for k in np.flatnonzero(~known).tolist():
        distances[k] = None
    for k in np.flatnonzero(~(known & np.isfinite(m.distance_std_m))).tolist():
        stds[k] = None
    return distances, stds


def _computation(
    people: list[dict[str, Any]],
    pairs: list[dict[str, Any]],
    close: list[dict[str, Any]],
    distance_threshold_m: float,
    calibration_version: int,
    calibration_grade: str | None,
) -> FrameComputation:
    """One frame's document and violation rows from its people, pairs and the pairs under the threshold."""
    suppressed = None
    if calibration_grade == "unreliable":
        if close:
            suppressed = f"{len(close)} pairs under the threshold, but the calibration is graded unreliable"
        close = []
    violations = [
        ViolationIn(
            person_i=p["i"],
            person_j=p["j"],
            distance_m=p["distance_m"],
            distance_std_m=p["distance_std_m"],
            ground_i_m=_ground_of(people[p["i"]]),
            ground_j_m=_ground_of(people[p["j"]]),
            track_id_i=people[p["i"]]["track_id"],
            track_id_j=people[p["j"]]["track_id"],
        )
        for p in close
    ]
    document = {
        "calibration_version": calibration_version,
        "distance_threshold_m": distance_threshold_m,
        "people": people,
        "pairs": pairs,
        "violations": close,
        "calibration_grade": calibration_grade,
        "alerts_suppressed": suppressed,
    }
    return FrameComputation(pydantic_core.to_json(document, inf_nan_mode="null").decode(), violations)


def _ground_of(person: dict[str, Any]) -> tuple[float, float] | None:
    ground = person["ground_m"]
    return None if ground is None else (ground[0], ground[1])
