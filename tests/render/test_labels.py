"""Label placement: whatever the crowd, no two placed labels overlap, none leaves the picture or covers what must
stay visible, and labels that find no room are reported rather than drawn on top of others."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.frames.schemas import PairDistance
from service.render.labels import Box, box_at, place_labels
from service.render.overlay import PersonMark
from service.render.style import Style
from service.render.topdown import TopDownView, fit_view, render_topdown, topdown_layout

BOUNDS = Box(0, 0, 399, 299)
sizes = st.tuples(st.integers(1, 120), st.integers(1, 40))
points = st.tuples(st.floats(-50, 450), st.floats(-50, 350))
boxes = st.builds(
    lambda x, y, w, h: Box(x, y, x + w, y + h),
    st.integers(0, 380),
    st.integers(0, 280),
    st.integers(0, 60),
    st.integers(0, 40),
)


def assert_valid(placed: list[Box | None], bounds: Box, obstacles: list[Box], gap_px: int = 1) -> None:
    chosen = [box for box in placed if box is not None]
    for k, box in enumerate(chosen):
        assert box.inside(bounds), box
        assert not any(box.intersects(o) for o in obstacles), box
        assert not any(box.intersects(other, gap_px) for other in chosen[k + 1 :]), box


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(sizes, points), max_size=40), st.lists(boxes, max_size=6))
def test_placed_labels_never_overlap(labels: list, obstacles: list[Box]) -> None:
    placed = place_labels([s for s, _ in labels], [a for _, a in labels], BOUNDS, obstacles)
    assert len(placed) == len(labels)
    assert_valid(placed, BOUNDS, obstacles)


def test_labels_with_room_sit_on_their_anchors_and_a_crowd_spreads_out() -> None:
    far_apart = place_labels([(40, 12)] * 3, [(50, 50), (200, 50), (350, 250)], BOUNDS)
    assert [box.centre for box in far_apart if box] == [(49.5, 49.5), (199.5, 49.5), (349.5, 249.5)]
    # Ten labels on one point: all placed around it while there is room, none overlapping.
    crowd = place_labels([(40, 12)] * 10, [(200.0, 150.0)] * 10, BOUNDS)
    assert all(box is not None for box in crowd)
    assert_valid(crowd, BOUNDS, [])
    assert max(np.hypot(box.centre[0] - 200, box.centre[1] - 150) for box in crowd if box) < 80


def test_a_label_with_no_room_is_left_out() -> None:
    tiny = Box(0, 0, 59, 19)
    placed = place_labels([(40, 12)] * 3, [(30.0, 10.0)] * 3, tiny)
    assert placed[0] is not None and placed[1:] == [None, None]


def test_box_at_is_centred_to_the_pixel() -> None:
    assert box_at((10.0, 10.0), (5, 3)) == Box(8, 8, 12, 10)


def crowded(seed: int, n: int, spread_m: float) -> tuple[list[PersonMark], list[PairDistance]]:
    rng = np.random.default_rng(seed)
    ground = rng.normal((0.0, 8.0), spread_m, (n, 2))
    people = [PersonMark(i, (float(u), float(v))) for i, (u, v) in enumerate(ground)]
    pairs = [
        PairDistance(i=i, j=j, distance_m=float(np.linalg.norm(ground[i] - ground[j])), distance_std_m=0.05)
        for i in range(n)
        for j in range(i + 1, n)
    ]
    return people, pairs


def test_crowded_maps_never_overlap_their_labels() -> None:
    """Synthetic crowds from sparse to packed, at three map sizes: labels clear of each other, of the title, the
    note and the scale bar, and of every person's dot; the closest pairs are the ones labelled."""
    for seed, n, spread_m in [(0, 6, 3.0), (1, 15, 2.0), (2, 25, 1.5), (3, 40, 1.0), (4, 60, 2.5)]:
        people, pairs = crowded(seed, n, spread_m)
        for size in (300, 640, 1000):
            view = fit_view([p.ground_m for p in people], size)
            style = Style.for_size(size, size)
            layout = topdown_layout(people, pairs, 1.8288, view, style)
            assert len(layout.labels) == len(layout.close) > 0
            assert_valid([found.box for found in layout.labels], Box(0, 0, size - 1, size - 1), layout.reserved)
            distances = [float(p.distance_m or 0) for p in layout.close]
            assert distances == sorted(distances)
            shown = [k for k, found in enumerate(layout.labels) if found.box is not None]
            assert shown and shown[0] == 0  # the closest pair is always labelled
            render_topdown(people, pairs, 1.8288, view=view)  # and it draws


def test_people_beyond_the_map_are_arrows_at_its_edge_and_counted() -> None:
    view = TopDownView(401, 401, (0.0, 5.0), 0.025)  # 10 m square around (0, 5)
    people = [PersonMark(0, (0.0, 5.0)), PersonMark(1, (0.0, 40.0)), PersonMark(2, (-30.0, 5.0))]
    layout = topdown_layout(people, [], 1.8288, view, Style.for_size(401, 401))
    assert layout.on_map == [0] and layout.off_map == [1, 2]
    bare = render_topdown(people[:1], [], 1.8288, view=view, threshold_circles=False)
    drawn = render_topdown(people, [], 1.8288, view=view, threshold_circles=False)
    changed = np.any(drawn != bare, axis=2)
    # An arrow at the top edge (person 1, straight ahead), one at the left edge (person 2), and the note.
    area = layout.area
    assert changed[area.y0 - 2 : area.y0 + 25, 190:211].any()
    assert changed[190:211, area.x0 - 2 : area.x0 + 25].any()
    assert changed[-25:, 250:].any()
    assert not changed[100:300, 100:300].any()


def test_the_title_heads_the_map() -> None:
    people, pairs = crowded(5, 8, 2.0)
    view = fit_view([p.ground_m for p in people], 640)
    plain = render_topdown(people, pairs, 1.8288, view=view)
    titled = render_topdown(people, pairs, 1.8288, view=view, title="camera lobby   2026-11-22 10:00:00 UTC")
    band = Style.for_size(640, 640)
    changed = np.any(plain != titled, axis=2)
    rows = np.nonzero(changed.any(axis=1))[0]
    assert rows.size and rows.max() <= 2 * band.pad_px + 30  # only the top line changed
    assert changed[:, 300:].any()  # a long line, not a stub
