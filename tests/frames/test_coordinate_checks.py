"""The keypoint coordinate check: its one-pass fast path must refuse exactly what the point-by-point check does."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.frames.schemas import PersonObservation
from service.frames.service import COORDINATE_MARGIN_FRACTION, people_for_camera
from service.http.problems import ProblemError
from service.settings import Settings
from service.store.models import Camera

WIDTH_PX, HEIGHT_PX = 640, 480
CAMERA = Camera(id="cam", image_width_px=WIDTH_PX, image_height_px=HEIGHT_PX)
SETTINGS = Settings(max_people_per_frame=50)
# Coordinates that land on, just inside and just outside the accepted band [-margin, size + margin].
EDGES_X = [-COORDINATE_MARGIN_FRACTION * WIDTH_PX, (1 + COORDINATE_MARGIN_FRACTION) * WIDTH_PX]
EDGES_Y = [-COORDINATE_MARGIN_FRACTION * HEIGHT_PX, (1 + COORDINATE_MARGIN_FRACTION) * HEIGHT_PX]


def _coordinate(edges: list[float], size_px: int) -> st.SearchStrategy[float]:
    near_edges = st.sampled_from(edges).flatmap(lambda e: st.sampled_from([e - 0.01, e, e + 0.01]))
    return near_edges | st.floats(-size_px, 2 * size_px, allow_nan=False)


keypoint = st.tuples(_coordinate(EDGES_X, WIDTH_PX), _coordinate(EDGES_Y, HEIGHT_PX), st.sampled_from([0.0, 0.2, 0.9]))
person = st.lists(keypoint, min_size=17, max_size=17)


def _far_outside(x: float, y: float) -> bool:
    return not (EDGES_X[0] <= x <= EDGES_X[1] and EDGES_Y[0] <= y <= EDGES_Y[1])


@settings(max_examples=300, deadline=None)
@given(st.lists(person, min_size=1, max_size=4))
def test_a_frame_is_refused_exactly_when_a_keypoint_is_far_outside(people: list[list[tuple]]) -> None:
    posted = [PersonObservation(keypoints=[list(k) for k in keypoints]) for keypoints in people]
    bad = [
        f"body.people[{i}].keypoints[{k}]"
        for i, keypoints in enumerate(people)
        for k, (x, y, _score) in enumerate(keypoints)
        if _far_outside(x, y)  # whatever the score: a score of 0 is no licence for an unstorable number
    ]
    if not bad:
        rows = people_for_camera(posted, CAMERA, SETTINGS)
        assert [row.keypoints for row in rows] == [p.keypoints for p in posted]
        return
    with pytest.raises(ProblemError) as refused:
        people_for_camera(posted, CAMERA, SETTINGS)
    assert refused.value.status == 422
    assert [error["field"] for error in refused.value.extensions["errors"]] == bad
