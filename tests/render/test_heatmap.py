"""Heat map of violations: density peaks where they happened, time buckets count them right."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import cv2
import numpy as np
import pytest

from service.render.ground import GroundFrame
from service.render.heatmap import (
    COLORMAP,
    ViolationPoint,
    bucket_counts,
    density_map,
    render_heatmap,
    tick_text,
    time_ticks,
)
from service.render.topdown import TopDownView, render_topdown
from tests.render.scenes import calibration_of, tilted_scene

T0 = datetime(2026, 3, 1, 9, 0, 30, tzinfo=UTC)
HOT = cv2.applyColorMap(np.array([[255]], np.uint8), COLORMAP)[0, 0]


def _cluster(
    n: int, centre: tuple[float, float], spread: float, seed: int, minutes: float = 0.0
) -> list[ViolationPoint]:
    rng = np.random.default_rng(seed)
    pts = rng.normal(centre, spread, (n, 2))
    return [
        ViolationPoint(T0 + timedelta(minutes=minutes, seconds=0.2 * k), (float(p[0]), float(p[1])))
        for k, p in enumerate(pts)
    ]


def test_violation_is_located_at_the_pair_midpoint():
    v = ViolationPoint.between(T0, (1.0, 2.0), (3.0, 6.0))
    assert v.ground_m == (2.0, 4.0)


def test_density_peaks_at_the_cluster_and_keeps_its_mass():
    view = TopDownView(401, 401, (0.0, 5.0), 0.05)
    points = np.array([v.ground_m for v in _cluster(200, (3.0, 8.0), 0.3, 0) + _cluster(40, (-4.0, 2.0), 0.3, 1)])
    d = density_map(points, view, sigma_m=0.4)
    y, x = np.unravel_index(np.argmax(d), d.shape)
    np.testing.assert_allclose(view.to_ground([x, y]), (3.0, 8.0), atol=0.15)
    assert d.sum() * view.metres_per_px**2 == pytest.approx(240, rel=1e-3)
    # Peak of N points with spread s and kernel sigma: N / (2 pi (s^2 + sigma^2)) per m^2.
    assert d.max() == pytest.approx(200 / (2 * np.pi * (0.3**2 + 0.4**2)), rel=0.15)


def test_bucket_counts_are_aligned_and_exact():
    start = datetime(2026, 3, 1, 9, 0, 30, tzinfo=UTC)
    end = datetime(2026, 3, 1, 9, 4, 0, tzinfo=UTC)
    times = [
        datetime(2026, 3, 1, 9, 0, 10, tzinfo=UTC),  # before the window: not counted
        datetime(2026, 3, 1, 9, 0, 30, tzinfo=UTC),
        datetime(2026, 3, 1, 9, 0, 59, 999000, tzinfo=UTC),
        datetime(2026, 3, 1, 9, 1, 0, tzinfo=UTC),
        datetime(2026, 3, 1, 9, 3, 59, tzinfo=UTC),
        datetime(2026, 3, 1, 9, 4, 0, tzinfo=UTC),  # end is exclusive
    ]
    starts, counts = bucket_counts(times, start, end, 60)
    assert starts[0] == datetime(2026, 3, 1, 9, 0, tzinfo=UTC)  # bucket containing the start, minute-aligned
    assert counts == [2, 1, 0, 1]
    starts, counts = bucket_counts(times, start, end, 3600)
    assert starts == [datetime(2026, 3, 1, 9, 0, tzinfo=UTC)] and counts == [4]
    with pytest.raises(ValueError):
        bucket_counts(times, start, end, 0)


def test_heatmap_picture_has_its_peak_where_the_violations_were():
    view = TopDownView(401, 301, (0.0, 5.0), 0.05)
    violations = _cluster(150, (3.0, 7.0), 0.2, 0) + _cluster(20, (-5.0, 2.0), 0.2, 1, minutes=3)
    out = render_heatmap(violations, view=view, bucket="minute", sigma_m=0.4)
    assert out.shape[1] == 401 and out.shape[0] > 301
    peak = np.rint(view.to_pixels([3.0, 7.0])).astype(int)
    assert np.all(np.abs(out[peak[1], peak[0]].astype(int) - HOT) < 60)
    hot = np.all(np.abs(out[:301, :340].astype(int) - HOT) < 40, axis=2)  # left of the legend
    ys, xs = np.nonzero(hot)
    assert len(xs) > 0
    np.testing.assert_allclose(view.to_ground([xs.mean(), ys.mean()]), (3.0, 7.0), atol=0.2)
    # The strip: 4 one-minute buckets (9:00..9:03), bars in the first and the last only.
    strip = out[301:]
    bars = np.all(np.abs(strip.astype(int) - (60, 140, 250)) < 5, axis=2)
    columns = bars.any(axis=0)
    quarter = 401 // 4
    assert columns[10 : quarter - 10].all() and columns[-quarter + 10 : -10].all()
    assert not columns[quarter + 10 : 3 * quarter - 10].any()
    # The first bar (150 events) is taller than the last (20).
    assert bars[:, 20].sum() > 3 * bars[:, -20].sum()


def test_heatmap_on_a_camera_frame_puts_the_peak_at_the_projected_spot():
    scene = tilted_scene(3)
    cal = calibration_of(scene)
    frame_px = np.full((scene.image_size[1], scene.image_size[0], 3), 110, np.uint8)
    violations = _cluster(200, (1.0, 8.0), 0.2, 0)
    out = render_heatmap(violations, background=frame_px, calibration=cal, sigma_m=0.4)
    hot = np.all(np.abs(out[: frame_px.shape[0], :1150].astype(int) - HOT) < 40, axis=2)  # left of the legend
    ys, xs = np.nonzero(hot)
    expected = GroundFrame.from_calibration(cal).ground_to_pixels(np.array([1.0, 8.0]))
    assert len(xs) > 0
    np.testing.assert_allclose((np.median(xs), np.median(ys)), expected, atol=6)
    # Above the horizon (left of the legend) the frame is untouched.
    assert np.all(out[:100, :640] == 110)


def test_heatmap_on_a_top_down_background_and_empty_inputs():
    view = TopDownView(300, 200, (0.0, 5.0), 0.05)
    background = render_topdown([], [], 1.8288, view=view)
    out = render_heatmap(_cluster(30, (0.0, 5.0), 0.2, 0), background=background, view=view)
    assert out.shape[:2][1] == 300
    with pytest.raises(ValueError):
        render_heatmap([], background=background)
    empty = render_heatmap([], size_px=(320, 240))
    assert empty.shape[1] == 320 and empty.shape[0] > 240


@pytest.mark.parametrize("size", [1, (640, 480), (1920, 1080), (480, 800)])
def test_odd_sizes_do_not_crash(size):
    out = render_heatmap(_cluster(10, (0.0, 3.0), 1.0, 0), size_px=size, bucket="hour")
    w = size if isinstance(size, int) else size[0]
    assert out.shape[1] == w and out.dtype == np.uint8


def test_wide_kernels_on_large_maps_match_the_direct_density():
    view = TopDownView(960, 540, (0.0, 5.0), 0.01)  # sigma 0.8 m = 80 px: computed on a coarser raster
    points = np.array([v.ground_m for v in _cluster(50, (1.0, 6.0), 0.5, 3)])
    coarse = density_map(points, view, sigma_m=0.8)
    x, y = np.meshgrid(np.arange(0, 960, 37), np.arange(0, 540, 29))
    ground = view.to_ground(np.stack((x, y), -1))
    d2 = np.sum((ground[..., None, :] - points) ** 2, axis=-1)
    direct = np.sum(np.exp(-d2 / (2 * 0.8**2)), axis=-1) / (2 * np.pi * 0.8**2)
    np.testing.assert_allclose(coarse[y, x], direct, atol=0.01 * direct.max())


def test_the_time_axis_is_dated() -> None:
    """A day-long window must not read like an hour: its ends carry dates, ticks mark the hours between, dated where
    the day changes."""
    start, end = datetime(2026, 11, 23, 23, 0, tzinfo=UTC), datetime(2026, 11, 24, 23, 0, tzinfo=UTC)
    step, ticks = time_ticks(start, end, 800, 130)
    assert step in (6 * 3600, 12 * 3600) and ticks[0] == datetime(2026, 11, 24, 0, 0, tzinfo=UTC)
    assert all(start < t < end for t in ticks) and all(t.timestamp() % step == 0 for t in ticks)
    hour_step, hour_ticks = time_ticks(start, start + timedelta(hours=1), 800, 130)
    assert hour_step == 900 and len(hour_ticks) == 3  # 23:15, 23:30, 23:45
    assert tick_text(ticks[0], step, None) == "24 Nov 00:00"
    assert tick_text(ticks[0] + timedelta(hours=6), step, ticks[0]) == "06:00"
    assert tick_text(datetime(2026, 11, 25, tzinfo=UTC), 86400, None) == "25 Nov"


def test_a_day_and_an_hour_draw_different_axes() -> None:
    """Before, both windows ended in '23:00 ... 23:00 UTC' labels that differed in nothing."""
    end = datetime(2026, 11, 24, 23, 0, tzinfo=UTC)
    points = [ViolationPoint(end - timedelta(minutes=30), (0.0, 5.0))]
    day = render_heatmap(points, start=end - timedelta(days=1), end=end, bucket="hour", size_px=600)
    hour = render_heatmap(points, start=end - timedelta(hours=1), end=end, bucket="hour", size_px=600)
    axis = slice(-30, None)
    assert np.any(day[axis] != hour[axis])


def test_an_empty_window_says_so() -> None:
    end = datetime(2026, 11, 24, 23, 0, tzinfo=UTC)
    empty = render_heatmap([], start=end - timedelta(days=1), end=end, bucket="hour", size_px=400)
    one = render_heatmap(
        [ViolationPoint(end - timedelta(hours=2), (0.0, 0.0))], start=end - timedelta(days=1), end=end, bucket="hour",
        size_px=400, view=TopDownView(400, 400, (20.0, 20.0), 0.05),
    )  # fmt: skip
    # The message in the middle of the map: light text on the dark label box.
    middle = empty[180:220, 100:300]
    assert (middle.max(axis=2) > 200).sum() > 100
    assert (one[180:220, 100:300].max(axis=2) > 200).sum() == 0
