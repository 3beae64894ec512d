"""Where and when a camera's violations happened: a density map on the ground and a count per time bucket.

The map answers "which spot needs re-arranging" (a queue, a doorway), the strip "at what time of day";
both come from violation events alone (timestamp and ground position), so a window of stored events is enough.
Density is in violations per square metre of ground: splatting in metres, not pixels, keeps a busy spot far
from the camera as hot as the same spot near it, which a heat map in image space would not.
Time buckets are aligned to multiples of their width in Unix seconds, like the store's per-minute and
per-hour counts (`epoch_s / width * width`), so the strip agrees with the API's counts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime

import cv2
import numpy as np
from numpy.typing import ArrayLike

from service.geometry.calibration import Calibration
from service.geometry.vec import FloatArray

from .ground import GroundFrame
from .labels import Box
from .style import DARK, GREY, WHITE, Style, label, label_size, text_height
from .topdown import BACKGROUND, TopDownView, draw_ground_grid, draw_scale_bar, fit_view

COLORMAP = cv2.COLORMAP_INFERNO
BUCKETS_S = {"minute": 60, "hour": 3600, "day": 86400}
# Density below this fraction of the peak fades out linearly to transparent.
_FADE_IN = 0.08
# Density rasters keep at least this many pixels per sigma (see density_map).
_MIN_SIGMA_PX = 6
GREY_TEXT = (200, 200, 200)


@dataclass(frozen=True)
class ViolationPoint:
    """One violation event reduced to when and where: the ground midpoint (metres) of the two people."""

    timestamp: datetime
    ground_m: tuple[float, float]

    @classmethod
    def between(cls, timestamp: datetime, a_m: Sequence[float], b_m: Sequence[float]) -> ViolationPoint:
        """The event of a pair at ground positions a and b: located at their midpoint."""
        return cls(timestamp, ((a_m[0] + b_m[0]) / 2.0, (a_m[1] + b_m[1]) / 2.0))


def _epoch(t: datetime) -> float:
    return (t if t.tzinfo is not None else t.replace(tzinfo=UTC)).timestamp()


def bucket_counts(
    timestamps: Sequence[datetime], start: datetime, end: datetime, bucket_s: int
) -> tuple[list[datetime], list[int]]:
    """(bucket starts, counts) over [start, end): buckets aligned to multiples of `bucket_s` since the epoch.

    The first bucket is the one containing `start`; events outside [start, end) are not counted. Naive
    datetimes are taken as UTC.
    """
    if bucket_s <= 0:
        raise ValueError(f"bucket width must be positive, got {bucket_s!r}")
    t0, t1 = _epoch(start), _epoch(end)
    first = math.floor(t0 / bucket_s) * bucket_s
    n = max(1, math.ceil((t1 - first) / bucket_s))
    counts = [0] * n
    for t in timestamps:
        e = _epoch(t)
        if t0 <= e < t1:
            counts[int((math.floor(e) - first) // bucket_s)] += 1
    starts = [datetime.fromtimestamp(first + k * bucket_s, UTC) for k in range(n)]
    return starts, counts


def density_map(points_m: ArrayLike, view: TopDownView, sigma_m: float = 0.5) -> FloatArray:
    """(H, W) density in violations per m^2 on the view's pixels: each point a 2-D Gaussian of `sigma_m`.

    Points are splatted bilinearly onto pixels and blurred (separable, mass-preserving), which equals summing
    Gaussians to second order in the pixel size and costs O(pixels) instead of O(points x pixels). When sigma
    spans many pixels the density is computed on a coarser raster (still at least 6 pixels per sigma, so
    smooth) and interpolated: a 1080p map with a wide kernel would otherwise take seconds.
    """
    if not sigma_m > 0:
        raise ValueError(f"sigma must be positive, got {sigma_m!r}")
    factor = max(1, int(sigma_m / view.metres_per_px // _MIN_SIGMA_PX))
    if factor == 1:
        return _splat(points_m, view, sigma_m)
    coarse = TopDownView(
        view.width_px // factor + 3, view.height_px // factor + 3, view.centre_m, view.metres_per_px * factor
    )
    density = _splat(points_m, coarse, sigma_m)
    # Fine pixel x -> coarse pixel x / f + ((Wc - 1) - (W - 1) / f) / 2, the same ground point; same for y.
    ox = ((coarse.width_px - 1) - (view.width_px - 1) / factor) / 2
    oy = ((coarse.height_px - 1) - (view.height_px - 1) / factor) / 2
    affine = np.array([[1 / factor, 0.0, ox], [0.0, 1 / factor, oy]])
    return cv2.warpAffine(
        density,
        affine,
        (view.width_px, view.height_px),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
    )


def _splat(points_m: ArrayLike, view: TopDownView, sigma_m: float) -> FloatArray:
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 2)
    p = p[np.all(np.isfinite(p), axis=1)]
    hist = np.zeros((view.height_px, view.width_px), dtype=np.float64)
    if len(p):
        # Bilinear splatting: each point's unit mass goes to its 4 nearest pixels, so its centre of mass is exact.
        px = view.to_pixels(p)
        base = np.floor(px).astype(np.int64)
        frac = px - base
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            x, y = base[:, 0] + dx, base[:, 1] + dy
            w = (frac[:, 0] if dx else 1 - frac[:, 0]) * (frac[:, 1] if dy else 1 - frac[:, 1])
            inside = (x >= 0) & (x < view.width_px) & (y >= 0) & (y < view.height_px)
            np.add.at(hist, (y[inside], x[inside]), w[inside])
    sigma_px = max(sigma_m / view.metres_per_px, 0.5)
    blurred = cv2.GaussianBlur(hist, (0, 0), sigma_px, borderType=cv2.BORDER_CONSTANT)
    return blurred / view.metres_per_px**2


def colorize(density: FloatArray, peak: float) -> tuple[np.ndarray, FloatArray]:
    """(BGR colours, alpha in [0, 1]) for a density: colour map on density / peak, transparent where it is low."""
    level = np.clip(density / peak, 0.0, 1.0) if peak > 0 else np.zeros_like(density)
    colours = cv2.applyColorMap(np.rint(level * 255).astype(np.uint8), COLORMAP)
    # Opacity grows smoothly from nothing (no hard edge around a blob) to 0.9 at the peak; the colour map's
    # near-black low end would otherwise smudge the background wherever a few events were scattered.
    alpha = 0.9 * np.sqrt(level) * np.clip(level / _FADE_IN, 0.0, 1.0)
    return colours, alpha


def _blend(image: np.ndarray, colours: np.ndarray, alpha: FloatArray) -> None:
    a = alpha[..., None].astype(np.float32)
    image[...] = np.rint(image.astype(np.float32) * (1 - a) + colours.astype(np.float32) * a).astype(np.uint8)


def _legend(image: np.ndarray, style: Style, peak: float) -> None:
    """A vertical colour bar at the top right, labelled on its left with the peak density, 0 and the unit."""
    h, w = image.shape[:2]
    line_h = text_height(style)
    bar_w = max(style.marker_px * 2, 6)
    x1 = w - 2 * style.pad_px
    x0 = x1 - bar_w
    y0 = 2 * style.pad_px + line_h
    y1 = min(y0 + max(int(0.35 * h), 2 * line_h), h - 2 * style.pad_px)
    if x0 < 0 or y1 - y0 < 2:
        return
    ramp = np.linspace(255, 0, y1 - y0).astype(np.uint8)[:, None].repeat(bar_w, axis=1)
    image[y0:y1, x0:x1] = cv2.applyColorMap(ramp, COLORMAP)
    cv2.rectangle(image, (x0 - 1, y0 - 1), (x1, y1), WHITE, 1)
    label(image, "violations per m^2", (x1, y0 - style.pad_px), style, align="bottomright")
    label(image, f"{peak:.2g}", (x0 - style.pad_px, y0), style, align="topright")
    label(image, "0", (x0 - style.pad_px, y1), style, align="bottomright")


def _bucket_name(bucket_s: int) -> str:
    """'min', '10 min', 'hour', '6 h', 'day' or '45 s': the unit of the strip's counts."""
    names = {60: "min", 3600: "hour", 86400: "day"}
    if bucket_s in names:
        return names[bucket_s]
    if bucket_s % 3600 == 0:
        return f"{bucket_s // 3600} h"
    if bucket_s % 60 == 0:
        return f"{bucket_s // 60} min"
    return f"{bucket_s} s"


# Tick spacings the time axis chooses from (seconds): the finest that leaves room for every label.
_TICK_STEPS_S = (60, 300, 600, 900, 1800, 3600, 7200, 10800, 21600, 43200, 86400, 172800, 604800, 2419200)


def tick_text(t: datetime, step_s: int, previous: datetime | None) -> str:
    """'14:00', or with the date where the day changes ('25 Nov 00:00'); whole days as '25 Nov'."""
    if step_s >= 86400:
        return t.strftime("%d %b")
    return t.strftime("%H:%M" if previous is not None and previous.date() == t.date() else "%d %b %H:%M")


def time_ticks(start: datetime, end: datetime, width_px: int, label_px: int) -> tuple[int, list[datetime]]:
    """(step in s, tick instants in (start, end)): UTC-aligned multiples of the finest step whose ticks stay at least
    one and a half label widths apart on a `width_px` axis."""
    t0, t1 = _epoch(start), _epoch(end)
    span = max(t1 - t0, 1.0)
    step = next((s for s in _TICK_STEPS_S if span / s * 1.5 * label_px <= width_px), _TICK_STEPS_S[-1])
    first = math.floor(t0 / step) * step + step
    count = max(0, math.ceil((t1 - first) / step))
    return step, [datetime.fromtimestamp(first + k * step, UTC) for k in range(count)]


def draw_time_strip(
    image: np.ndarray,
    starts: Sequence[datetime],
    counts: Sequence[int],
    bucket_s: int,
    style: Style,
    *,
    end: datetime | None = None,
    title: str | None = None,
) -> None:
    """Bars of counts per bucket across the strip (in place): a header with the title, the total and the peak; below
    the bars a time axis with the window's ends dated in full and ticks between them (dated where the day changes),
    so a day-long window never reads like an hour. `end` is the window's end (default: the last bucket's)."""
    h, w = image.shape[:2]
    image[...] = DARK
    line_h = text_height(style)
    top = line_h + style.pad_px
    bottom = h - line_h - style.pad_px
    n = len(counts)
    peak = max(max(counts, default=0), 1)
    for k, c in enumerate(counts):
        if c <= 0:
            continue
        x0 = int(np.floor(k * w / n))
        x1 = max(int(np.floor((k + 1) * w / n)) - 1, x0)
        y0 = bottom - round((bottom - top) * c / peak)
        cv2.rectangle(image, (x0, y0), (x1, bottom), (60, 140, 250), -1)
    cv2.line(image, (0, bottom), (w - 1, bottom), GREY, 1)
    total = sum(counts)
    header = f"{total} violation{'s' * (total != 1)}, max {max(counts, default=0)} per {_bucket_name(bucket_s)}"
    label(image, f"{title}   {header}" if title else header, (0, 0), style, align="topleft")
    if not starts:
        return
    first = starts[0]
    last = end or datetime.fromtimestamp(starts[-1].timestamp() + bucket_s, UTC)
    t0, t1 = _epoch(first), _epoch(last)
    date_format = "%Y-%m-%d %H:%M" if bucket_s < 86400 else "%Y-%m-%d"
    ends = [
        label(image, first.strftime(date_format), (0, h), style, align="bottomleft"),
        label(image, last.strftime(date_format) + " UTC", (w, h), style, align="bottomright"),
    ]
    taken = [Box(*box) for box in ends]
    step, ticks = time_ticks(first, last, w, label_size("25 Nov 00:00", style)[0])
    previous = first  # the start's label is dated: a tick on its day needs only the time
    for t in ticks:
        x = (t.timestamp() - t0) / max(t1 - t0, 1e-9) * (w - 1)
        cv2.line(image, (round(x), bottom), (round(x), bottom + style.pad_px), GREY, 1)
        text = tick_text(t, step, previous)
        size = label_size(text, style)
        box = Box(round(x - size[0] / 2), h - size[1], round(x - size[0] / 2) + size[0] - 1, h - 1)
        if box.x0 >= 0 and box.x1 < w and not any(box.intersects(other, style.pad_px) for other in taken):
            label(image, text, (box.x0, box.y0), style, color=GREY_TEXT, align="topleft")
            taken.append(box)
            previous = t


def render_heatmap(
    violations: Sequence[ViolationPoint],
    *,
    start: datetime | None = None,
    end: datetime | None = None,
    bucket: str | int = "minute",
    size_px: int | tuple[int, int] = 800,
    sigma_m: float = 0.5,
    view: TopDownView | None = None,
    background: np.ndarray | None = None,
    calibration: Calibration | None = None,
    grid_m: float = 1.0,
    title: str | None = None,
) -> np.ndarray:
    """The heat map picture (BGR): density of violations on the ground above, counts per time bucket below, on a
    dated time axis; `title` (the camera) heads the strip. A window without violations says so on the map.

    Window: [start, end), by default from the first to just past the last violation; events outside it are
    ignored. `bucket`: "minute", "hour", "day" or a width in seconds. Background of the map:
    - none: a top-down grid (metres) fitted to the violations, or `view` if given;
    - `background` + `calibration`: a camera frame; the ground density is drawn in perspective on it;
    - `background` + `view` (no calibration): a top-down picture drawn with that view (e.g. render_topdown's).
    """
    bucket_s = BUCKETS_S[bucket] if isinstance(bucket, str) else int(bucket)
    times = [v.timestamp for v in violations]
    if start is None:
        start = min(times) if times else datetime.fromtimestamp(0, UTC)
    if end is None:
        end = datetime.fromtimestamp(_epoch(max(times)) + 1e-3, UTC) if times else start
    t0, t1 = _epoch(start), _epoch(end)
    points = np.array([v.ground_m for v in violations if t0 <= _epoch(v.timestamp) < t1], dtype=float).reshape(-1, 2)

    if background is not None and calibration is not None:
        panel = _on_camera_frame(background, calibration, points, sigma_m)
    else:
        if view is None:
            if background is not None:
                raise ValueError("a top-down background needs the `view` it was drawn with")
            view = fit_view(points, size_px, margin_m=3 * sigma_m + 1.0)
        panel = _on_top_down(view, points, sigma_m, background, grid_m)

    h, w = panel.shape[:2]
    style = Style.for_size(w, max(h, 480))
    strip_h = max(round(0.22 * h), 3 * text_height(style) + 24)
    strip = np.zeros((strip_h, w, 3), dtype=np.uint8)
    starts, counts = bucket_counts([v.timestamp for v in violations], start, end, bucket_s)
    draw_time_strip(strip, starts, counts, bucket_s, style, end=end, title=title)
    if len(points) == 0:
        label(panel, "no violations in this window", (w / 2, h / 2), style)
    return np.vstack((panel, strip))


def _on_top_down(
    view: TopDownView, points: FloatArray, sigma_m: float, background: np.ndarray | None, grid_m: float
) -> np.ndarray:
    style = Style.for_size(view.width_px, view.height_px)
    if background is not None:
        if background.shape[:2] != (view.height_px, view.width_px):
            raise ValueError("the top-down background must have the view's size")
        image = np.ascontiguousarray(background[..., :3], dtype=np.uint8).copy()
    else:
        image = np.empty((view.height_px, view.width_px, 3), dtype=np.uint8)
        image[...] = BACKGROUND
        draw_ground_grid(image, view, style, grid_m)
    density = density_map(points, view, sigma_m)
    peak = float(density.max())
    _blend(image, *colorize(density, peak))
    if background is None:
        draw_scale_bar(image, view, style)
    if peak > 0:
        _legend(image, style, peak)
    return image


def _raster_for(points: FloatArray, sigma_m: float, max_side_px: int = 2048) -> TopDownView:
    """A ground raster over the violations (plus 4 sigma) at 4 pixels per sigma, or coarser if that is too big."""
    if len(points) == 0:
        return TopDownView(8, 8, (0.0, 0.0), sigma_m)
    lo, hi = points.min(axis=0) - 4 * sigma_m, points.max(axis=0) + 4 * sigma_m
    span = hi - lo
    mpp = max(sigma_m / 4, float(span.max()) / max_side_px)
    w, h = (int(np.ceil(s / mpp)) + 1 for s in span)
    centre = (lo + hi) / 2
    return TopDownView(w, h, (float(centre[0]), float(centre[1])), mpp)


def _on_camera_frame(frame_bgr: np.ndarray, calibration: Calibration, points: FloatArray, sigma_m: float) -> np.ndarray:
    """Density computed on a ground raster, then looked up at every below-horizon pixel's ground point."""
    image = np.ascontiguousarray(frame_bgr[..., :3], dtype=np.uint8).copy()
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    h, w = image.shape[:2]
    style = Style.for_size(w, h)
    frame = GroundFrame.from_calibration(calibration, (w, h))
    raster = _raster_for(points, sigma_m)
    density = density_map(points, raster, sigma_m)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    ground = frame.pixels_to_ground(np.stack((xs, ys), -1))
    where = raster.to_pixels(ground).astype(np.float32)
    where[~np.isfinite(where)] = -1e6
    sampled = cv2.remap(
        density.astype(np.float32), where[..., 0], where[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
    )
    peak = float(density.max())
    _blend(image, *colorize(sampled, peak))
    if peak > 0:
        _legend(image, style, peak)
    return image
