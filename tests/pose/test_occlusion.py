"""Masking a nearer person out of a hidden person's crop (service/pose/occlusion.py): arithmetic and rules, no models.

The real-inference check (Town Centre frames 48 and 54) is in test_occlusion_pose.py.
"""

from __future__ import annotations

import numpy as np

from service.pose.assess import Assessment
from service.pose.movenet import CropWindow, crop_window, extract_crop
from service.pose.occlusion import (
    MASK_FILL,
    Hidden,
    accept,
    drawn_to_feet_in_front,
    fill_boxes,
    is_copy,
    nearer_people,
    needs_reading,
)

from .conftest import POSE

# Town Centre frame 48 (uncalibrated plan): the woman in red, and the woman walking behind her, whose box is amodal
# (it ends 6 px above the red woman's, at her guessed feet).
RED = (1642.0, 803.0, 1759.0, 1005.0)
BEHIND = (1698.0, 728.0, 1778.0, 999.0)

POSE_BOX = np.array([460.0, 290.0, 540.0, 515.0])


def test_fill_covers_the_pixels_whose_centres_the_box_holds_and_only_inside_the_square() -> None:
    square = np.full((10, 10, 3), 200, dtype=np.uint8)
    # The square's top-left pixel is image pixel (100, 50); the box covers image columns 97..102, rows 55..56.
    fill_boxes(square, 100, 50, np.array([[96.6, 54.6, 102.4, 56.6]]))
    filled = (square == MASK_FILL).all(axis=2)
    expected = np.zeros((10, 10), dtype=bool)
    expected[5:7, 0:2] = True  # columns 100, 101 of the image (97..99 lie left of the square), rows 55, 56
    assert (filled == expected).all()


def test_a_box_outside_the_square_changes_nothing() -> None:
    square = np.full((4, 4, 3), 7, dtype=np.uint8)
    fill_boxes(square, 0, 0, np.array([[10.0, 10.0, 20.0, 20.0], [-9.0, -9.0, -1.0, 3.0]]))
    assert (square == 7).all()


def test_a_masked_crop_is_black_over_the_box_and_the_image_is_untouched() -> None:
    image = np.full((100, 100, 3), 255, dtype=np.uint8)
    window = CropWindow(x0=20, y0=20, side=40)
    crop = extract_crop(image, window, 40, np.array([[40.0, 40.0, 60.0, 60.0]]))
    assert (crop[20:, 20:] == MASK_FILL).all() and (crop[:20] == 255).all() and (crop[:, :20] == 255).all()
    assert (image == 255).all()
    assert (extract_crop(image, window, 40) == 255).all()


def test_a_masked_crop_at_the_image_edge_keeps_its_black_padding() -> None:
    image = np.full((100, 100, 3), 255, dtype=np.uint8)
    window = crop_window((80.0, 10.0, 100.0, 50.0))  # reaches past the right edge
    crop = extract_crop(image, window, window.side, np.array([[0.0, 0.0, 85.0, 100.0]]))
    right = 100 - window.x0
    assert (crop[:, right:] == 0).all() and (crop[:, 85 - window.x0 : right] == 255).all()
    assert (crop[:, : 85 - window.x0] == MASK_FILL).all()


def test_the_woman_in_red_is_in_front_of_the_woman_behind_her_and_not_the_reverse() -> None:
    boxes = np.array([RED, BEHIND])
    assert nearer_people(boxes, 1).tolist() == [0]
    assert nearer_people(boxes, 0).size == 0


def test_side_by_side_people_a_second_box_of_one_person_and_a_far_box_are_not_in_front() -> None:
    own = np.array([500.0, 300.0, 560.0, 500.0])
    side_by_side = own + (40.0, 2.0, 40.0, 2.0)  # tops level: nobody's head shows above the other
    upper_body = np.array([500.0, 302.0, 560.0, 420.0])  # shares the top and ends higher: the same person
    beyond = own + (0.0, -60.0, 0.0, -60.0)  # further away: higher at both ends
    apart = own + (70.0, 40.0, 70.0, 40.0)  # lower, but barely overlapping
    boxes = np.array([own, side_by_side, upper_body, beyond, apart])
    assert nearer_people(boxes, 0).size == 0


def test_a_copy_is_the_same_pose_within_five_percent_and_a_neighbour_is_not() -> None:
    scores = np.full(17, 0.8)
    jitter = POSE + np.random.default_rng(0).normal(0, 1.5, POSE.shape)
    assert is_copy(POSE, scores, POSE_BOX, jitter, scores, POSE_BOX + (-70, -5, -70, -5))
    neighbour = POSE + (50.0, 4.0)
    assert not is_copy(POSE, scores, POSE_BOX, neighbour, scores, POSE_BOX + (50, 4, 50, 4))
    unsure = np.full(17, 0.1)
    assert not is_copy(POSE, unsure, POSE_BOX, jitter, unsure, POSE_BOX)


def _assessment(posture: str) -> Assessment:
    return Assessment(trusted=np.ones(17, dtype=bool), posture=posture, occluded=np.zeros(17, dtype=bool))  # type: ignore[arg-type]


def test_only_a_lost_reading_with_someone_nearer_is_read_again() -> None:
    boxes = np.array([RED, BEHIND, (100.0, 100.0, 160.0, 300.0)])
    red_pose = POSE - POSE[5:7].mean(axis=0) + (1710.0, 857.0)
    own_pose = POSE - POSE[5:7].mean(axis=0) + (1742.0, 775.0)
    scores = np.full((3, 17), 0.8)
    keypoints = np.stack([red_pose, red_pose + 1.0, POSE])  # the woman behind read as the woman in red
    stood = [_assessment("partial"), _assessment("partial"), _assessment("unknown")]
    hidden = needs_reading(boxes, keypoints, scores, stood)
    assert [(h.index, h.nearer.tolist()) for h in hidden] == [(1, [0])]  # the lone person 2 has nobody to mask
    keypoints[1] = own_pose  # her own pose, read well: left alone
    assert needs_reading(boxes, keypoints, scores, stood) == []
    stood[1] = _assessment("unknown")  # her shoulders not trusted: worth another look
    assert [h.index for h in needs_reading(boxes, keypoints, scores, stood)] == [1]


def test_a_masked_reading_is_kept_only_when_it_is_her_own_confident_pose() -> None:
    boxes = np.array([RED, BEHIND])
    red_pose = POSE - POSE[5:7].mean(axis=0) + (1710.0, 857.0)
    frame_keypoints = np.stack([red_pose, red_pose + 1.0])
    frame_scores = np.full((2, 17), 0.8)
    hidden = Hidden(1, np.array([0]))
    own = POSE - POSE[5:7].mean(axis=0) + (1742.0, 775.0)
    scores = np.full(17, 0.8)
    assert accept(hidden, own, scores, boxes, frame_keypoints, frame_scores)
    weak = scores.copy()
    weak[6] = 0.2
    assert not accept(hidden, own, weak, boxes, frame_keypoints, frame_scores)  # a shoulder not confident
    assert not accept(hidden, red_pose + 2.0, scores, boxes, frame_keypoints, frame_scores)  # still the red woman
    in_the_fill = POSE - POSE[5:7].mean(axis=0) + (1700.0, 900.0)  # shoulders guessed inside the masked box
    assert not accept(hidden, in_the_fill, scores, boxes, frame_keypoints, frame_scores)


def test_a_box_ending_level_with_a_nearer_persons_box_was_drawn_to_hidden_feet() -> None:
    assert drawn_to_feet_in_front(BEHIND, np.array([RED]))  # ends 6 px above the woman in red's box
    # A walker beside a nearer one (steep atrium): the nearer box begins lower and ends clearly lower: his own feet.
    walker = (1000.0, 600.0, 1060.0, 760.0)
    beside = (1040.0, 630.0, 1100.0, 800.0)
    assert nearer_people(np.array([walker, beside]), 0).tolist() == [1]  # worth masking when his pose is lost
    assert not drawn_to_feet_in_front(walker, np.array([beside]))  # but his box bottom is a contact
    assert not drawn_to_feet_in_front(RED, np.array([BEHIND]))  # the one in front is nobody's hidden part
