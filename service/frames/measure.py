"""A frame's result (positions, pair distances, violations) from its people and a calibration (pure).

Shared by the synchronous `POST .../distances` endpoint, the measuring job and `posemetry analyze`, so that a
frame's stored result, an on-demand measurement of the same people and an offline run are computed by the same
code. No I/O and no store: callers read the calibration and the people, and write the outcome back
(service.frames.service does that for stored frames).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pydantic_core

from service.domain import PersonIn, StoredCentres, ViolationIn, centres, track_id_of
from service.frames.keypoints import BOX_REASON, PARTIAL_REASON, SEATED_REASON, STATIC_REASON
from service.frames.schemas import FrameResult
from service.geometry import Calibration, measure
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
    """What measuring a frame produced: the result (as a JSON-ready document) and the violation rows for the store.

    The document is built here from plain numbers, in FrameResult's shape; the worker stores it as it is, and a
    FrameResult model is made only where one is needed (an HTTP answer, the offline writers). Validating 190
    pairs per frame in the worker cost as much as measuring them, and proved nothing the tests do not.
    """

    document: dict[str, Any]
    violations: list[ViolationIn]

    @property
    def result(self) -> FrameResult:
        return FrameResult.model_validate(self.document)

    def result_json(self) -> str:
        """The result as stored in `frames.result`, encoded now: in Rust (pydantic-core), five times faster than the
        json module for a frame's 190 pairs. Non-finite numbers are already None; any left would be null."""
        return pydantic_core.to_json(self.document, inf_nan_mode="null").decode()


def _ground_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(right, forward) unit vectors on the ground: the viewing direction projected onto it, and its right."""
    forward = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, normal)
    return right, forward


def _shoulder_priors(people: Sequence[StoredCentres | PersonIn]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each person's shoulder height (fraction of the prior) and its sigma, and the sigma of their ground contact
    (fraction of their standing height in pixels: not 0 for a box-bottom contact), from the verdict on them."""
    scale = np.ones(len(people))
    std_m = np.full(len(people), DEFAULT_HEIGHT_STD_M)
    contact = np.zeros(len(people))
    for index, person in enumerate(people):
        reason = person.unusable_reason or ""
        if _from_box(reason):
            contact[index] = BOX_CONTACT_STD_FRACTION
        elif reason.startswith(SEATED_REASON):
            scale[index], std_m[index] = SEATED_HEIGHT_FRACTION, SEATED_HEIGHT_STD_M
        elif reason.startswith(PARTIAL_REASON):
            std_m[index] = PARTIAL_HEIGHT_STD_M
    return scale, std_m, contact


def _placed_from(person: StoredCentres | PersonIn, has_bottom: bool) -> str:
    """`ankles`, `box` (the detector box's bottom, service.frames.keypoints.place_from_boxes) or `shoulders`."""
    if not has_bottom:
        return "shoulders"
    return "box" if _from_box(person.unusable_reason or "") else "ankles"


def _from_box(reason: str) -> bool:
    """Whether the verdict says the person stands on their box's bottom (also when flagged static after it)."""
    return reason.startswith(BOX_REASON) or reason.startswith(f"{STATIC_REASON}; {BOX_REASON}")


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
    points = [centres(person) for person in people]
    tops = np.array([s if s is not None else _NAN_POINT for s, _ in points], dtype=float).reshape(-1, 2)
    bottoms = np.array([a if a is not None else _NAN_POINT for _, a in points], dtype=float).reshape(-1, 2)
    n = len(points)
    if n:
        scale, std_m, contact = _shoulder_priors(people)
        m = measure(
            cal, tops, bottoms, noise_px=noise_px, height_std_m=std_m, height_scale=scale, contact_std_fraction=contact
        )
        positions, distances, stds = m.points_bottom, m.distances_m, m.distance_std_m
    else:
        positions, distances, stds = np.zeros((0, 3)), np.zeros((0, 0)), np.zeros((0, 0))
    foot = -cal.rho * cal.normal  # the point on the ground straight below the camera
    right, forward = _ground_axes(cal.normal)
    placed = np.all(np.isfinite(positions), axis=1)
    static = [(person.unusable_reason or "").startswith(STATIC_REASON) for person in people]
    ground = np.stack(((positions - foot) @ right, (positions - foot) @ forward), -1)
    placed_people = [
        {
            "index": index,
            "placed_from": _placed_from(people[index], points[index][1] is not None) if is_placed else None,
            "ground_m": ground_m if is_placed else None,
            "point_m": point_m if is_placed else None,
            "static": still,
            "track_id": track_id_of(person),
        }
        for index, (person, is_placed, ground_m, point_m, still) in enumerate(
            zip(people, placed.tolist(), ground.tolist(), positions.tolist(), static, strict=True)
        )
    ]
    # Pairs i < j, from plain Python values: a frame of 20 people has 190 pairs.
    first, second = np.triu_indices(n, 1)
    pair_m, pair_std_m = distances[first, second], stds[first, second]
    known = np.isfinite(pair_m)
    pairs = [
        {"i": i, "j": j, "distance_m": d if ok else None, "distance_std_m": sd if ok and math.isfinite(sd) else None}
        for i, j, d, sd, ok in zip(
            first.tolist(), second.tolist(), pair_m.tolist(), pair_std_m.tolist(), known.tolist(), strict=True
        )
    ]
    # A static "person" (a mannequin, cameras.static_spots) is measured like anyone but raises no violation.
    close = [
        pair
        for pair in pairs
        if pair["distance_m"] is not None
        and pair["distance_m"] < distance_threshold_m
        and not (static[pair["i"]] or static[pair["j"]])
    ]
    suppressed = None
    if calibration_grade == "unreliable":
        if close:
            suppressed = f"{len(close)} pairs under the threshold, but the calibration is graded unreliable"
        close = []
    violations = [
        ViolationIn(person_i=p["i"], person_j=p["j"], distance_m=p["distance_m"], distance_std_m=p["distance_std_m"])
        for p in close
    ]
    document = {
        "calibration_version": calibration_version,
        "distance_threshold_m": distance_threshold_m,
        "people": placed_people,
        "pairs": pairs,
        "violations": close,
        "calibration_grade": calibration_grade,
        "alerts_suppressed": suppressed,
    }
    return FrameComputation(document=document, violations=violations)
