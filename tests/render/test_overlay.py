"""The annotated frame: grid only below the horizon, boxes coloured by the threshold, labelled nearest links."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.frames.schemas import PairDistance
from service.render.grid import SIX_FEET_M
from service.render.ground import GroundFrame
from service.render.overlay import (
    PersonMark,
    box_from_keypoints,
    marks_from_result,
    nearest_neighbours,
    render_overlay,
    violators,
)
from service.render.style import DARK, GREEN, RED, Style
from service.store.models import Observation, pack_keypoints
from tests.render.scenes import calibration_of, people_of, result_of, tilted_scene

GREY = 110


def _grey(width: int, height: int) -> np.ndarray:
    return np.full((height, width, 3), GREY, np.uint8)


@pytest.fixture(scope="module")
def scene():
    return tilted_scene(3)


@pytest.fixture(scope="module")
def cal(scene):
    return calibration_of(scene)


def _is(color: np.ndarray, expected: tuple[int, int, int], tol: int = 40) -> bool:
    return bool(np.all(np.abs(color.astype(int) - np.array(expected)) <= tol))


@pytest.mark.parametrize("cell_m", [1.0, SIX_FEET_M])
def test_nothing_is_drawn_above_the_horizon(scene, cal, cell_m):
    width, height = scene.image_size
    out = render_overlay(_grey(width, height), cal, [], [], 1.8288, grid_cell_m=cell_m)
    frame = GroundFrame.from_calibration(cal)
    rows = np.arange(height)[:, None]
    horizon = frame.horizon_y(np.arange(width) + 0.5)[None, :]
    assert 0 < horizon.min() and horizon.max() < height  # the horizon crosses the picture
    changed = np.any(out != GREY, axis=2)
    above = rows < horizon
    assert not np.any(changed & above)
    # ... and the grid is there below it, and is cyan-ish (blue and green over red).
    assert np.count_nonzero(changed & ~above) > 0.03 * width * height
    drawn = out[changed]
    assert np.mean(drawn[:, 0].astype(int) - drawn[:, 2]) > 20


def _three_people() -> tuple[list[PersonMark], list[PairDistance]]:
    marks = [
        PersonMark(0, (0.0, 5.0), (200.0, 400.0), (170.0, 250.0, 230.0, 410.0)),
        PersonMark(1, (1.0, 5.0), (320.0, 400.0), (290.0, 250.0, 350.0, 410.0)),
        PersonMark(2, (6.0, 5.0), (520.0, 400.0), (490.0, 250.0, 550.0, 410.0)),
    ]
    pairs = [
        PairDistance(i=0, j=1, distance_m=1.0, distance_std_m=0.1),
        PairDistance(i=0, j=2, distance_m=6.0, distance_std_m=0.1),
        PairDistance(i=1, j=2, distance_m=5.0, distance_std_m=0.1),
    ]
    return marks, pairs


def test_boxes_are_red_in_a_close_pair_and_green_otherwise():
    marks, pairs = _three_people()
    out = render_overlay(_grey(640, 480), None, marks, pairs, 1.8288)
    assert violators(pairs, 1.8288) == {0, 1}
    # Middle of each box's left edge (x0, (y0 + y1) / 2).
    assert _is(out[330, 170], RED) and _is(out[330, 290], RED)
    assert _is(out[330, 490], GREEN)
    # Threshold is strict: at exactly 1.0 m threshold, pair (0, 1) is not a violation.
    out = render_overlay(_grey(640, 480), None, marks, pairs, 1.0)
    assert _is(out[330, 170], GREEN)


def test_nearest_neighbour_links_are_drawn_and_labelled():
    marks, pairs = _three_people()
    assert nearest_neighbours(pairs, [0, 1, 2]) == [(0, 1, 1.0), (1, 2, 5.0)]
    out = render_overlay(_grey(640, 480), None, marks, pairs, 1.8288)
    for x0, x1 in ((200, 320), (320, 520)):
        mid = ((x0 + x1) // 2, 400)
        patch = out[mid[1] - 8 : mid[1] + 9, mid[0] - 20 : mid[0] + 21]
        dark = np.all(np.abs(patch.astype(int) - DARK) <= 3, axis=2)
        bright = patch.max(axis=2) > 180  # label text
        assert dark.mean() > 0.3 and bright.any()
    # Along the link, away from the label: the link's colour (red under the threshold).
    assert _is(out[400, 215], RED, tol=60)
    # Without person 1, 0 and 2 are each other's nearest neighbours.
    assert nearest_neighbours(pairs, [0, 2]) == [(0, 2, 6.0)]


def test_marks_from_result_place_shoulder_only_people_at_their_ground_point(scene, cal):
    people = people_of(scene, hide_ankles=(1, 4))
    result = result_of(scene, people, 1.8288)
    marks = marks_from_result(result, people, cal)
    assert [m.index for m in marks] == list(range(len(people)))
    for i, m in enumerate(marks):
        # Exact scene, true heights = prior: the projected ground point is the true ankle pixel.
        np.testing.assert_allclose(m.foot_px, scene.bottoms_px[i], atol=1e-6)
        assert m.box_px is not None and m.box_px[1] < scene.tops_px[i][1] and m.box_px[3] > scene.bottoms_px[i][1]
        np.testing.assert_allclose(m.ground_m, result.people[i].ground_m)
    # Shoulder-only people are drawn: their box edge is coloured.
    width, height = scene.image_size
    out = render_overlay(_grey(width, height), cal, marks, result.pairs, 1.8288)
    red = violators(result.pairs, 1.8288)
    for i in (1, 4):
        x0, y0, _, y1 = marks[i].box_px
        colour = out[round((y0 + y1) / 2), round(x0)]
        assert _is(colour, RED if i in red else GREEN, tol=60)


def test_marks_without_calibration_or_ankles_fall_back_to_shoulder_markers(scene):
    people = people_of(scene, hide_ankles=(0,))
    result = result_of(scene, people, 1.8288)
    marks = marks_from_result(result, people, None)
    assert marks[0].foot_px is None and marks[0].box_px is None and marks[0].shoulder_px is not None
    out = render_overlay(_grey(*scene.image_size), None, marks[:1], [], 1.8288)
    x, y = (round(v) for v in marks[0].shoulder_px)
    assert _is(out[y, x], GREEN)


def test_box_from_keypoints_ignores_unconfident_points():
    keypoints = [[100.0, 100.0, 0.9], [120.0, 200.0, 0.9], [110.0, 300.0, 0.8], [900.0, 900.0, 0.1]] + [
        [0.0, 0.0, 0.0]
    ] * 13
    x0, y0, x1, y1 = box_from_keypoints(keypoints)
    assert (x0, y0, x1, y1) == pytest.approx((80.0, 76.0, 140.0, 310.0))
    assert box_from_keypoints([[0.0, 0.0, 0.0]] * 17) is None


@pytest.mark.parametrize("size", [(1, 1), (2, 3), (640, 480), (1920, 1080), (720, 1280)])
def test_odd_image_sizes_do_not_crash(cal, size):
    marks, pairs = _three_people()
    out = render_overlay(_grey(*size), cal, marks, pairs, 1.8288, grid_cell_m=1.0)
    assert out.shape == (size[1], size[0], 3) and out.dtype == np.uint8
    grey_only = render_overlay(np.full((size[1], size[0]), 50, np.uint8), cal, [], [], 1.8288, grid_cell_m=SIX_FEET_M)
    assert grey_only.shape == (size[1], size[0], 3)


def test_input_image_is_not_modified(cal):
    image = _grey(320, 180)
    render_overlay(image, cal, *_three_people(), 1.8288)
    assert np.all(image == GREY)


def test_labels_scale_with_the_image():
    def digit_height(style: Style) -> int:
        return cv2.getTextSize("1.42 m", cv2.FONT_HERSHEY_SIMPLEX, style.font_scale, style.font_thickness)[0][1]

    small, large = Style.for_size(640, 480), Style.for_size(1920, 1080)
    assert digit_height(small) >= 11 and digit_height(large) >= 24
    assert large.font_thickness >= 2 and large.line_px > small.line_px


def test_marks_from_stored_observations_use_detector_boxes_then_keypoints(scene, cal):
    people = people_of(scene)[:3]
    result = result_of(scene, people, 1.8288)
    keypoints = [[0.0, 0.0, 0.0]] * 17
    keypoints[0] = [500.0, 100.0, 0.9]
    keypoints[15] = [480.0, 300.0, 0.9]
    keypoints[16] = [520.0, 300.0, 0.9]
    rows = [
        Observation(
            shoulder_x_px=p.shoulder_px[0],
            shoulder_y_px=p.shoulder_px[1],
            ankle_x_px=p.ankle_px[0],
            ankle_y_px=p.ankle_px[1],
            keypoints_f32=pack_keypoints(keypoints) if i < 2 else None,
        )
        for i, p in enumerate(people)
    ]
    rows[1].box_left_px, rows[1].box_top_px, rows[1].box_right_px, rows[1].box_bottom_px = (10.0, 20.0, 30.0, 40.0)
    marks = marks_from_result(result, rows, cal)
    assert marks[0].box_px == pytest.approx((480 - 20.0, 100 - 24.0, 520 + 20.0, 300 + 10.0))
    assert marks[1].box_px == (10.0, 20.0, 30.0, 40.0)
    assert marks[2].box_px is not None and marks[2].box_px[1] < people[2].shoulder_px[1]
    assert [m.foot_px for m in marks] == [p.ankle_px for p in people]
