"""One box per person from several regions and scales (service/pose/merge.py): pure box arithmetic."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.pose.merge import merge_boxes


def test_the_same_person_seen_at_two_scales_is_one_box() -> None:
    boxes = np.array([[100.0, 100.0, 160.0, 300.0], [102.0, 98.0, 161.0, 303.0], [400.0, 100.0, 460.0, 300.0]])
    merged, scores = merge_boxes(boxes, np.array([0.6, 0.8, 0.5]))
    assert len(merged) == 2
    np.testing.assert_allclose(merged[0], boxes[1])  # the more confident view
    assert scores.tolist() == [0.8, 0.5]


def test_a_person_seen_faintly_in_two_regions_outweighs_one_seen_once() -> None:
    """Votes (rule 1): two regions at 0.25 fuse to 1 - 0.75^2 = 0.44 and pass a 0.3 threshold; the same two boxes
    from one region are one vote (0.25, dropped), and so is a lone 0.28."""
    person = np.array([[100.0, 100.0, 160.0, 300.0], [104.0, 96.0, 162.0, 304.0]])
    lone = np.array([[600.0, 100.0, 660.0, 300.0]])
    boxes, scores = np.vstack([person, lone]), np.array([0.25, 0.25, 0.28])
    merged, fused = merge_boxes(boxes, scores, np.array([0, 1, 0]), threshold=0.3)
    np.testing.assert_allclose(merged, person[:1])
    np.testing.assert_allclose(fused, [1 - 0.75**2])
    merged, _ = merge_boxes(boxes, scores, np.array([0, 0, 1]), threshold=0.3)
    assert len(merged) == 0
    merged, fused = merge_boxes(boxes, scores, np.array([0, 1, 2]), threshold=0.2)
    assert len(merged) == 2 and fused.tolist() == sorted(fused.tolist(), reverse=True)


def test_an_upper_body_box_inside_a_whole_body_box_is_merged_into_it() -> None:
    """A cyclist's whole-body box and upper-body box (IoU ~0.5, so NMS alone keeps both): one person, the outer box
    (it reaches the feet), with the better score."""
    whole = [900.0, 400.0, 1000.0, 700.0]
    upper = [905.0, 402.0, 990.0, 560.0]
    merged, scores = merge_boxes(np.array([upper, whole]), np.array([0.7, 0.5]))
    assert len(merged) == 1
    np.testing.assert_allclose(merged[0], whole)
    assert scores[0] == 0.7


def _plane(feet_px: np.ndarray) -> np.ndarray:
    """A size plane like Town Centre's near its right edge: 184 px tall with feet at row 471, zero at row -90."""
    return (np.asarray(feet_px, dtype=float)[:, 1] + 90.0) * 184.0 / 561.0


# Town Centre frame 12, three regions' boxes near the right edge (a plan sized by the frame's own people, 450 000
# pixels): the man walking past (two regions), the man behind the sign board below him (three boxes, two regions),
# and one box over both, 299 px tall where a person stands 184 px.
_FRAME_12 = np.array(
    [
        [1809.0, 173.0, 1883.0, 347.0],
        [1803.0, 279.0, 1881.0, 492.0],
        [1807.0, 287.0, 1881.0, 486.0],
        [1805.0, 172.0, 1884.0, 471.0],
        [1813.0, 283.0, 1880.0, 417.0],
        [1805.0, 172.0, 1881.0, 346.0],
    ]
)
_FRAME_12_SCORES = np.array([0.61, 0.25, 0.32, 0.28, 0.26, 0.70])
_FRAME_12_REGIONS = np.array([0, 0, 1, 1, 1, 2])


def test_a_box_of_two_people_one_above_the_other_is_nobodys_whole_body() -> None:
    """Rule 4: the box over both men overlaps the upper man's own boxes most and holds them, sharing their top, so
    rule 1 took it for his whole body down to hidden feet; it then covered the hidden man too (two boxes over him).
    With the sizes known it is too tall for one person: each man keeps his own box."""
    merged, _ = merge_boxes(_FRAME_12, _FRAME_12_SCORES, _FRAME_12_REGIONS, threshold=0.3, size_of=_plane)
    assert merged.tolist() == [[1805.0, 172.0, 1881.0, 346.0], [1807.0, 287.0, 1881.0, 486.0]]
    merged, _ = merge_boxes(_FRAME_12, _FRAME_12_SCORES, _FRAME_12_REGIONS, threshold=0.3)
    assert merged.tolist()[0] == [1805.0, 172.0, 1884.0, 471.0]  # without sizes: the old answer


def test_a_hidden_persons_whole_body_keeps_its_extent_where_sizes_are_known() -> None:
    """A whole-body vote as tall as a person at its feet is still the person's extent (rule 1), and one taller
    than STACKED times that is not."""
    upper = [1600.0, 700.0, 1700.0, 900.0]  # IoU 0.57 with the whole body: one person for rule 1
    whole = [1598.0, 702.0, 1702.0, 1040.0]  # 338 px, feet at row 1040
    boxes, scores = np.array([upper, whole]), np.array([0.47, 0.33])
    merged, _ = merge_boxes(boxes, scores, size_of=lambda feet: np.full(len(feet), 330.0))
    assert merged.tolist() == [whole]
    merged, _ = merge_boxes(boxes, scores, size_of=lambda feet: np.full(len(feet), 330.0 / 1.5))
    assert merged.tolist() == [upper]


def test_a_child_in_front_of_an_adult_is_kept() -> None:
    adult = [500.0, 300.0, 600.0, 600.0]
    child = [520.0, 450.0, 580.0, 610.0]  # mostly inside the adult's box, but not sharing its top
    merged, _ = merge_boxes(np.array([adult, child]), np.array([0.8, 0.6]))
    assert len(merged) == 2


def test_a_loose_box_around_a_group_is_dropped_and_its_people_kept() -> None:
    group = [100.0, 100.0, 400.0, 300.0]
    people = [[110.0, 105.0, 170.0, 260.0], [200.0, 150.0, 260.0, 290.0], [300.0, 120.0, 360.0, 280.0]]
    merged, scores = merge_boxes(np.array([group, *people]), np.array([0.31, 0.5, 0.45, 0.4]))
    assert len(merged) == 3 and 0.31 not in scores.tolist()


def test_a_loose_box_over_two_people_votes_for_the_one_it_fits() -> None:
    """Town Centre frame 12: a man behind a sign board (0.25 in one region) and a man walking past above him
    (0.65); another region's loose box spans both (IoU 0.63 with the first, 0.51 with the second). It is the
    hidden man's second vote (1 - 0.75^2 = 0.44 >= 0.3), not a vote for the confident man beside him."""
    hidden = [1803.0, 279.0, 1881.0, 492.0]
    walking = [1809.0, 173.0, 1882.0, 343.0]
    loose = [1805.0, 173.0, 1882.0, 487.0]
    merged, fused = merge_boxes(
        np.array([walking, hidden, loose]), np.array([0.65, 0.25, 0.25]), np.array([0, 0, 1]), threshold=0.3
    )
    assert len(merged) == 2
    np.testing.assert_allclose(merged[1], hidden)
    np.testing.assert_allclose(fused, [0.65, 1 - 0.75**2])


def test_a_hidden_persons_whole_body_vote_gives_their_box_its_extent() -> None:
    """Town Centre frame 48: the woman behind the woman in red is boxed to her upper body (0.47) and, in two
    regions, to her whole body down to her hidden feet (0.33, 0.30; IoU >= 0.5 with the upper body, same top).
    One person, fused score, with the whole body's extent (the feet the geometry measures from); a box of about
    the same extent (a jitter) does not move the kept box."""
    upper = [1697.0, 727.0, 1776.0, 896.0]
    whole = [1695.0, 725.0, 1780.0, 1000.0]
    merged, fused = merge_boxes(
        np.array([upper, whole, whole]), np.array([0.47, 0.33, 0.30]), np.array([0, 1, 2]), threshold=0.3
    )
    assert len(merged) == 1
    np.testing.assert_allclose(merged[0], whole)
    np.testing.assert_allclose(fused, [1 - 0.53 * 0.67 * 0.70])
    jitter = [1695.0, 725.0, 1778.0, 905.0]
    merged, _ = merge_boxes(np.array([upper, jitter]), np.array([0.47, 0.33]), np.array([0, 1]))
    np.testing.assert_allclose(merged[0], upper)


boxes = st.tuples(
    st.floats(0, 1800), st.floats(0, 1000), st.floats(8, 200), st.floats(16, 400), st.floats(0.3, 1.0)
).map(lambda t: (t[0], t[1], t[0] + t[2], t[1] + t[3], t[4]))


@settings(max_examples=200, deadline=None)
@given(st.lists(boxes, max_size=25))
def test_merging_is_a_sorted_subset_and_idempotent(found: list[tuple[float, ...]]) -> None:
    data = np.array(found, dtype=np.float64).reshape(-1, 5)
    merged, scores = merge_boxes(data[:, :4], data[:, 4])
    assert len(merged) <= len(data) and list(scores) == sorted(scores, reverse=True)
    originals = {tuple(row) for row in data[:, :4]}
    assert all(tuple(box) in originals for box in merged)
    again, again_scores = merge_boxes(merged, scores)
    np.testing.assert_array_equal(again, merged)
    np.testing.assert_array_equal(again_scores, scores)
