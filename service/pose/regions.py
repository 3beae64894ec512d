"""Where the person detector looks, and at what scale: the plan of detector regions for one frame (pure numpy).

RTMDet-nano finds people reliably only in a window of apparent sizes. Measured on the Oxford Town Centre clip (all
22 frames run at nine scales, 1 800 annotated people fully in view, `bench/recall.py`): recall is 0.49 for people
16-24 px tall in the detector's input, 0.81 at 24-32, 0.89 at 32-64 and 0.93-0.97 from 64 to 320 px, falling
again above. A 1080p frame letterboxed to 640 px (scale 1/3) puts a 60 px person at 20 px: invisible. So each
part of the frame should be seen at the scale that makes its people 64-256 px tall (`FAVOURITE_PX`).

Three plans:
- Uncalibrated (`uncalibrated_plan`): nothing is known about where people are or how tall they appear, so every
  camera gets the same passes over the whole frame (`UNCALIBRATED_SCALES`: the whole frame at 640 px, which finds
  near people whole, plus the whole frame at native resolution, which lifts 50-100 px people into the window).
- Observed (`observed_plan`): no calibration, but whole people at enough rows say how tall people appear where
  (`sizes_from_people`: on one ground plane, in proportion to the feet's distance below the horizon line): the
  usable people of the camera's latest frames, or those the frame's own 640 px pass found. The frame's other rows
  are then searched in bands as a calibration would have them searched, for about half the fixed passes' pixels.
- Calibrated (`calibrated_plan`): a calibration (K, ground normal N, camera height rho, the height prior) predicts
  how tall a standing person appears with their feet at any pixel: project the ground point under the pixel and
  the point a stature above it. Feet rows are grouped into horizontal bands in which that height varies by at most
  `BAND_RATIO`; each band is searched at the scale that makes its smallest standing person `TARGET_PX` tall (a
  seated person, ~0.65 of that, is still in the window), over the rows its people can occupy (feet rows plus the
  tallest person's height above them). Rows whose ground lies above the horizon, or whose people would stay below
  `MIN_VISIBLE_PX` even at the largest scale, hold no findable person and are skipped.

Each region owns the people whose anchor (the box's bottom centre: the feet) lies in its `core`; detections anchored
elsewhere, or touching an edge the region shares with the rest of the frame (a person cut by the region), are left
to the region that sees them whole. Regions larger than `MAX_TILE_INPUT_PX` of detector input are split into
overlapping tiles (memory; a 3840 px wide tensor is legal but needs ~1 GB of activations), the overlap at least
the largest person expected, so that every person lies whole in the tile that owns them.

The planner uses only the calibration's public fields (fx, fy, cx, cy, normal, rho, height_m); lens distortion is
ignored: it moves apparent heights by a few per cent at the frame's edges, well inside a band's margins.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Final

import numpy as np
from scipy.optimize import least_squares

if TYPE_CHECKING:
    from service.geometry import Calibration

STRIDE_PX: Final = 32
"""The detector's coarsest feature stride: every input side is padded to a multiple of it."""
FAVOURITE_PX: Final = (64.0, 256.0)
"""Apparent person heights (detector input px) at which RTMDet-nano's recall is on its plateau (module docstring)."""
TARGET_PX: Final = 96.0
"""A band's smallest standing person is brought to this height: seated people (~0.65 of it) stay >= 62 px."""
BAND_RATIO: Final = 1.6
"""Largest ratio of standing heights inside one band: 96 px at its far edge, ~155 px at its near edge."""
MIN_SCALE: Final = 0.2
MAX_SCALE: Final = 2.0
"""Scales (detector px per image px) a plan may use. Upsampling beyond 2x adds pixels, not detail (measured: the
atrium's seated people are found as often at 2x as at 1.5x, with three times the false positives of 1x)."""
MIN_VISIBLE_PX: Final = 16.0
"""Standing people shorter than this in the image are not searched for: even at MAX_SCALE they would be 32 px
tall in the detector's input, where its recall drops below ~0.85."""
MAX_TILE_INPUT_PX: Final = 1536
"""Longest side of one detector input; larger regions are tiled."""
HEAD_TOP_PER_SHOULDER: Final = 1.28
"""Stature over ankle-to-shoulder height (the calibration's height prior): ~1.69 m / 1.32 m for adults."""
MAX_SPREAD: Final = 1.25 * FAVOURITE_PX[1] / TARGET_PX
"""Largest ratio of person sizes one band may hold: from the target to the end of the detector's plateau (320 px)."""
SHOULDER_WIDTH_M: Final = 0.45
"""An adult's shoulder width: the smallest a person appears, seen from straight above."""
FOOT_MARGIN: Final = 0.12
"""Rows below a band's lowest feet row it still reads, as a fraction of the person height there (box bottoms
scatter below the predicted feet: shoes, long coats, calibration error)."""
HEAD_MARGIN: Final = 1.2
"""A band's rows reach this many tallest-person heights above its highest feet row (taller people, arms up)."""
WIDTH_PER_HEIGHT: Final = 0.5
"""Half a person's box width (arms, bags, bicycles) as a fraction of their height: how far beyond the feet box the
regions reach sideways."""
BUDGET_PX: Final = 300_000
"""Detector input pixels a calibrated plan may spend per frame (~100 ms of CPU here; the plain 640 x 384 pass is
246 000): see `calibrated_plan`."""
MIN_TARGET_PX: Final = 40.0
"""The budget never shrinks the target below this (conditional recall ~0.91 at 32-48 px, 0.84 at 28-32)."""
UNCALIBRATED_SCALES: Final = (1 / 3, 2 / 3)
"""The uncalibrated policy: whole-frame passes (scale relative to a 1920 px wide frame; see `uncalibrated_plan`)."""
EDGE_INPUT_PX: Final = 2.0
"""A box within this many detector pixels of an edge the region shares with the rest of the frame is cut by it."""
_ROW_STEP_PX: Final = 4
_COLUMNS: Final = 17


SizeOf = Callable[[np.ndarray], np.ndarray]
"""How large a standing person appears (px) with their feet at each of (N, 2) pixels; NaN where none can stand."""

SIZE_PLANE_MIN_PEOPLE: Final = 6
"""Fewest whole people a frame's first pass must find before their sizes plan the rest of its search."""
SIZE_PLANE_MIN_SPREAD: Final = 0.15
"""Their feet must span at least this share of the image height (one row of people says nothing about the others)."""
SIZE_PLANE_MAX_ROLL_DEG: Final = 15.0
"""A horizon rolled further is not a camera watching a floor (or the first pass's people are not on one)."""
SIZE_PLANE_MAX_MISFIT: Final = 0.15
"""Median relative misfit of their heights to the plane, above which the frame gets the fixed policy."""
OBSERVED_BUDGET_PX: Final = 600_000
"""Detector input pixels the bands of an uncalibrated frame may spend (`observed_plan`), twice a calibrated plan's:
the sizes are a plane through one frame's people, not a calibration. On the Town Centre clip (198 annotated people
fully in view) the bands found 192, 191, 195 and 193 of them at 300 000, 375 000, 450 000 and 600 000 (the fixed
passes and their second look 194 with 1 440 000): the same within the plan-to-plan noise of about two people. At
450 000 a band of frame 12 boxed two people at once (the man behind the sign board and the man above him) and the
merge kept that box over the upper man's own (tests/pose/test_occlusion_recall.py); at 600 000 it did not, and since
merge.py's rule 4 (a box too tall to be one person is nobody's whole body) neither does 450 000."""


@dataclass(frozen=True)
class Region:
    """A rectangle of the image (x0 <= x < x1, y0 <= y < y1) given to the detector at `scale`."""

    x0: int
    y0: int
    x1: int
    y1: int
    scale: float
    """Detector input pixels per image pixel."""
    core: tuple[float, float, float, float]
    """left, top, right, bottom (image px): detections whose feet (bottom centre of the box) lie here are this
    region's; the others belong to a region that sees them whole."""
    shared_edges: tuple[bool, bool, bool, bool] = (False, False, False, False)
    """left, top, right, bottom: whether that edge lies inside the frame (a box touching it is cut by the region)."""
    whole_frame: bool = False
    """Part of a pass over the whole frame (the benchmark's detector/tiling split counts the first such pass as the
    detector and everything else as tiling)."""

    @property
    def input_size(self) -> tuple[int, int]:
        """(width, height) of the resized region, before padding to the stride."""
        return max(1, round((self.x1 - self.x0) * self.scale)), max(1, round((self.y1 - self.y0) * self.scale))

    @property
    def input_pixels(self) -> int:
        """Pixels of the padded detector input: what the region costs (detector time is linear in it)."""
        width, height = self.input_size
        return ceil_to(width, STRIDE_PX) * ceil_to(height, STRIDE_PX)

    def owns(self, boxes_xyxy: np.ndarray) -> np.ndarray:
        """(N,) bool: which image-pixel boxes found in this region are its own (anchored in the core, not cut)."""
        boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
        cx, bottom = (boxes[:, 0] + boxes[:, 2]) / 2, boxes[:, 3]
        left, top, right, low = self.core
        mine = (cx >= left) & (cx < right) & (bottom >= top) & (bottom < low)
        cut_left, cut_top, cut_right, cut_bottom = self.shared_edges
        tolerance = EDGE_INPUT_PX / self.scale
        if cut_left:
            mine &= boxes[:, 0] > self.x0 + tolerance
        if cut_top:
            mine &= boxes[:, 1] > self.y0 + tolerance
        if cut_right:
            mine &= boxes[:, 2] < self.x1 - tolerance
        if cut_bottom:
            mine &= boxes[:, 3] < self.y1 - tolerance
        return mine


def ceil_to(value: int, multiple: int) -> int:
    """The smallest multiple of `multiple` not below `value`."""
    return -(-value // multiple) * multiple


def plan_cost(regions: Sequence[Region]) -> int:
    """Total detector input pixels of a plan (its detector time is about 165 ms of CPU per million on this host)."""
    return sum(region.input_pixels for region in regions)


def _splits(lo: int, hi: int, tile: int, overlap: int) -> list[tuple[int, int]]:
    """Overlapping [a, b) intervals of length <= tile covering [lo, hi), neighbours sharing >= overlap."""
    length = hi - lo
    if length <= tile:
        return [(lo, hi)]
    overlap = min(overlap, tile // 2)
    count = math.ceil((length - overlap) / (tile - overlap))
    step = (length - tile) / (count - 1)
    return [(lo + round(i * step), lo + round(i * step) + tile) for i in range(count)]


def tiles(
    box: tuple[int, int, int, int],
    scale: float,
    image_size_px: tuple[int, int],
    overlap_px: float,
    core: tuple[float, float, float, float] | None = None,
    *,
    whole_frame: bool = False,
) -> list[Region]:
    """The rectangle `box` at `scale`, split into tiles of at most MAX_TILE_INPUT_PX input pixels a side.

    Neighbouring tiles share at least `overlap_px` image pixels (the largest person expected there). Columns are
    owned up to the middle of each overlap: a person narrower than the overlap lies whole in the tile that holds
    their centre. Feet rows are owned by the upper tile down to just above its bottom edge: a person shorter than
    the overlap whose feet lie below that is whole in the lower tile. `core` bounds the rectangle's ownership (a
    band's feet rows).
    """
    width_px, height_px = image_size_px
    x0, y0, x1, y1 = box
    core = core if core is not None else (float(x0), float(y0), float(x1), float(y1))
    tile_px = max(STRIDE_PX, int(MAX_TILE_INPUT_PX / scale))
    overlap = math.ceil(overlap_px)
    columns, rows = _splits(x0, x1, tile_px, overlap), _splits(y0, y1, tile_px, overlap)
    edge = EDGE_INPUT_PX / scale
    row_bounds = [core[1]] + [by - edge for _, by in rows[:-1]] + [core[3]]
    regions = []
    for i, (ax, bx) in enumerate(columns):
        left = core[0] if i == 0 else (columns[i - 1][1] + ax) / 2
        right = core[2] if i == len(columns) - 1 else (bx + columns[i + 1][0]) / 2
        for j, (ay, by) in enumerate(rows):
            top, bottom = max(core[1], row_bounds[j]), min(core[3], row_bounds[j + 1])
            shared = (ax > 0, ay > 0, bx < width_px, by < height_px)
            regions.append(Region(ax, ay, bx, by, scale, (left, top, right, bottom), shared, whole_frame=whole_frame))
    return regions


def uncalibrated_plan(
    image_size_px: tuple[int, int], scales: Sequence[float] = UNCALIBRATED_SCALES, *, base_input_px: int | None = None
) -> list[Region]:
    """Whole-frame passes for a camera without a calibration (see the module docstring).

    Scales are stated for a 1920 px wide frame and applied to the frame's longer side, so a 1280 x 720 camera gets
    the same detector inputs as a 1920 x 1080 one. `base_input_px` replaces the first (coarsest) pass by the frame
    letterboxed to that many pixels (the service's `detector_input_px` setting).
    """
    width_px, height_px = image_size_px
    longer = max(width_px, height_px)
    plan: list[Region] = []
    for k, nominal in enumerate(sorted(scales)):
        scale = nominal * 1920 / longer
        if k == 0 and base_input_px is not None:
            scale = base_input_px / longer
        overlap = 0.35 * height_px  # the tallest person a whole-frame pass expects: a third of the frame
        plan += tiles((0, 0, width_px, height_px), scale, image_size_px, overlap, whole_frame=True)
    return plan


def sizes_from_people(boxes_xyxy: np.ndarray, image_size_px: tuple[int, int]) -> SizeOf | None:
    """A camera's person size by where the feet are, from the people one detector pass found, or None when they do
    not say.

    People standing on one ground plane appear as tall as their feet lie below the horizon line (both go as one over
    their distance: the classical single-view relation), so their height is a plane over the image, h = a y + c x + b,
    zero on the horizon; c is the camera's roll (a rolled camera's horizon is a slanted line). Exact for a level
    camera; a tilted one bends it by a few per cent over the rows a surveillance view shows people in. A frame's
    plain pass finds the nearer people whole, and a robust fit of their box heights (soft-L1 on relative misfits: a
    seated person or a child among them does not tip it) predicts the sizes of the far ones it missed, which is what
    a calibration tells `calibrated_plan`. Boxes touching the top or bottom edge are cut people and left out. None
    with fewer than SIZE_PLANE_MIN_PEOPLE, feet within SIZE_PLANE_MIN_SPREAD of the height, people who do not shrink
    towards the top of the frame, a horizon rolled by more than SIZE_PLANE_MAX_ROLL_DEG, or heights that scatter
    about the plane by more than SIZE_PLANE_MAX_MISFIT.
    """
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    height_px = float(image_size_px[1])
    heights, feet_rows = boxes[:, 3] - boxes[:, 1], boxes[:, 3]
    whole = (boxes[:, 1] > EDGE_INPUT_PX) & (feet_rows < height_px - EDGE_INPUT_PX) & (heights > 0)
    heights, feet_rows, feet_columns = heights[whole], feet_rows[whole], ((boxes[:, 0] + boxes[:, 2]) / 2)[whole]
    if len(heights) < SIZE_PLANE_MIN_PEOPLE or np.ptp(feet_rows) < SIZE_PLANE_MIN_SPREAD * height_px:
        return None
    # Rows and columns in units of the image height: the plane's coefficients are then pixels of person height.
    design = np.c_[feet_rows / height_px, feet_columns / height_px, np.ones(len(heights))]
    start = np.linalg.lstsq(design / heights[:, None], np.ones(len(heights)), rcond=None)[0]
    plane = least_squares(lambda p: design @ p / heights - 1.0, start, loss="soft_l1", f_scale=0.05).x
    along_rows, along_columns = float(plane[0]), float(plane[1])
    if not along_rows > 0 or abs(along_columns) > math.tan(math.radians(SIZE_PLANE_MAX_ROLL_DEG)) * along_rows:
        return None
    if np.median(np.abs(design @ plane / heights - 1.0)) > SIZE_PLANE_MAX_MISFIT:
        return None

    def size_of(feet_px: np.ndarray) -> np.ndarray:
        feet = np.asarray(feet_px, dtype=np.float64).reshape(-1, 2) / height_px
        sizes = np.c_[feet[:, 1], feet[:, 0], np.ones(len(feet))] @ plane
        return np.where(sizes > 0, sizes, np.nan)

    return size_of


def observed_plan(
    size_of: SizeOf, image_size_px: tuple[int, int], budget_px: float = OBSERVED_BUDGET_PX
) -> list[Region] | None:
    """calibrated_plan's bands for a camera without a calibration, sized by its people (`sizes_from_people`); None
    when the bands would have to leave rows out to keep to OBSERVED_BUDGET_PX (a view of many small people: the
    fixed passes look at all of it)."""
    return _banded_plan(size_of, image_size_px, None, budget_px, TARGET_PX, BAND_RATIO, whole=True)


def standing_height_px(calibration: Calibration, feet_px: np.ndarray) -> np.ndarray:
    """(N,) apparent height (rows) of a standing person of the prior stature with feet at each (N, 2) pixel.

    NaN where the pixel's ray does not meet the ground in front of the camera (at or above the horizon), or where
    the head top would lie behind the camera.
    """
    return _standing(calibration, feet_px)[0]


def person_size_px(calibration: Calibration, feet_px: np.ndarray) -> np.ndarray:
    """(N,) how large a standing person with feet at each pixel appears: the length of their projected body
    (feet to head, in any direction), or their shoulders' width where that is larger (seen from straight above,
    near the nadir of a steep camera, a person is a head and shoulders). NaN where there is no ground."""
    return _standing(calibration, feet_px)[1]


def _standing(calibration: Calibration, feet_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    feet = np.asarray(feet_px, dtype=np.float64).reshape(-1, 2)
    normal = np.asarray(calibration.normal, dtype=np.float64)
    rays = np.c_[(feet[:, 0] - calibration.cx) / calibration.fx, (feet[:, 1] - calibration.cy) / calibration.fy]
    rays = np.c_[rays, np.ones(len(rays))]
    along = rays @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(along < -1e-9, -calibration.rho / along, np.nan)
        ground = rays * depth[:, None]
        head = ground + normal * (calibration.height_m * HEAD_TOP_PER_SHOULDER)
        in_front = head[:, 2] > 1e-6
        head_x = np.where(in_front, calibration.fx * head[:, 0] / head[:, 2] + calibration.cx, np.nan)
        head_y = np.where(in_front, calibration.fy * head[:, 1] / head[:, 2] + calibration.cy, np.nan)
        width = calibration.fx * SHOULDER_WIDTH_M / ground[:, 2]
    extent = feet[:, 1] - head_y
    size = np.fmax(np.hypot(feet[:, 0] - head_x, extent), width)
    return extent, np.where(np.isfinite(extent), size, np.nan)


@dataclass(frozen=True)
class _Band:
    feet_top: int
    feet_bottom: int
    scale: float
    tallest_px: float
    head_top: float
    """The highest row a standing person with feet in the band reaches, HEAD_MARGIN included."""


def _row_heights(
    size_of: SizeOf, feet_box: tuple[float, float, float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, smallest, tallest) person size (`size_of`, e.g. `person_size_px`) over _COLUMNS columns of each feet
    row of the box.

    NaN where the row has no ground.

    The box may reach below the image: people there show their upper body.
    """
    left, top, right, bottom = feet_box
    columns = np.linspace(left, right, _COLUMNS)
    rows = np.arange(math.floor(top), math.ceil(bottom), _ROW_STEP_PX, dtype=np.float64)
    # Each sampled row stands for the feet rows down to the next one: both ends are sampled.
    ends = np.concatenate([rows, rows + _ROW_STEP_PX])
    grid = np.stack(np.meshgrid(columns, ends), -1).reshape(-1, 2)
    sizes = size_of(grid).reshape(2, len(rows), len(columns))
    sizes = np.where(sizes > 0, sizes, np.nan).transpose(1, 0, 2).reshape(len(rows), -1)
    seen = np.isfinite(sizes).any(axis=1)
    smallest = np.full(len(rows), np.nan)
    tallest = np.full(len(rows), np.nan)
    smallest[seen] = np.nanmin(sizes[seen], axis=1)
    tallest[seen] = np.nanmax(sizes[seen], axis=1)
    return rows, smallest, tallest


def _bands(
    rows: np.ndarray, smallest: np.ndarray, tallest: np.ndarray, target_px: float, band_ratio: float
) -> list[_Band]:
    """Feet rows grouped, from the bottom of the frame up, into bands whose standing heights stay within
    `band_ratio` (or that are all too small for the target even at MAX_SCALE: one band at MAX_SCALE), nearest first.
    Rows with no findable person (above the horizon, or everyone under MIN_VISIBLE_PX) end a band."""
    findable = np.isfinite(tallest) & (tallest >= MIN_VISIBLE_PX)
    # In a rolled or wide view a row's heights vary across it: the row is searched where its people are findable.
    smallest = np.where(findable, np.fmax(smallest, MIN_VISIBLE_PX), np.nan)
    bands: list[_Band] = []
    k = len(rows) - 1
    while k >= 0:
        if not findable[k]:
            k -= 1
            continue
        bottom, low_h, high_h = k, smallest[k], tallest[k]
        # A row can itself span a range of sizes (near a steep camera's nadir, or rolled): the band adds at most
        # band_ratio to the spread of its first row, within the detector's window (a row wider than the window on
        # its own is a band of its own: horizontal bands cannot split it).
        ratio = min(band_ratio * high_h / low_h, max(high_h / low_h, MAX_SPREAD))
        while k - 1 >= 0 and findable[k - 1]:
            candidate_low, candidate_high = min(low_h, smallest[k - 1]), max(high_h, tallest[k - 1])
            # People too small for the target even at MAX_SCALE share one band while they stay small, and people
            # too large for it even at MIN_SCALE while they stay large.
            all_small = candidate_high * MAX_SCALE <= target_px * band_ratio
            all_large = candidate_low * MIN_SCALE >= target_px
            if candidate_high > ratio * candidate_low and not (all_small or all_large):
                break
            low_h, high_h = candidate_low, candidate_high
            k -= 1
        scale = float(np.clip(target_px / low_h, MIN_SCALE, MAX_SCALE))
        head_top = float(np.min(rows[k : bottom + 1] - HEAD_MARGIN * tallest[k : bottom + 1]))
        bands.append(_Band(int(rows[k]), int(rows[bottom]) + _ROW_STEP_PX, scale, float(high_h), head_top))
        k -= 1
    return bands


def calibrated_plan(
    calibration: Calibration,
    image_size_px: tuple[int, int] | None = None,
    *,
    feet_box_px: tuple[float, float, float, float] | None = None,
    budget_px: float = BUDGET_PX,
    target_px: float = TARGET_PX,
    band_ratio: float = BAND_RATIO,
) -> list[Region]:
    """Bands of feet rows, each at the scale that makes its smallest standing person `target_px` tall.

    `image_size_px` defaults to the calibration's own. `feet_box_px` (left, top, right, bottom) limits the search to
    people whose feet lie in it: where a fixed camera's people have been seen (its evidence), which on a steep view
    is a fraction of the frame (walls and windows hold no floor); default: the whole frame and the people cut by
    its bottom edge. Rows above the horizon, or whose standing people would be shorter than MIN_VISIBLE_PX, are not
    searched, except inside a given feet box: people were seen there, so the calibration is wrong about them, and
    those rows get the uncalibrated policy's finer pass. When the plan costs more than `budget_px` detector input
    pixels, the target shrinks (never below MIN_TARGET_PX) until it fits: every band keeps the same apparent person
    size, which spends the budget evenly on the recall curve; if even that is too much, the farthest bands (the
    smallest people, the worst recall per pixel) are dropped, and a last band too costly on its own is searched at
    the scale the budget allows. A calibration that leaves nothing to search gets the
    uncalibrated plan.
    """
    if image_size_px is None:
        image_size_px = (round(calibration.image_size[0]), round(calibration.image_size[1]))
    plan = _banded_plan(
        lambda feet: person_size_px(calibration, feet), image_size_px, feet_box_px, budget_px, target_px, band_ratio
    )
    return plan or uncalibrated_plan(image_size_px)


def _banded_plan(
    size_of: SizeOf,
    image_size_px: tuple[int, int],
    feet_box_px: tuple[float, float, float, float] | None,
    budget_px: float,
    target_px: float,
    band_ratio: float,
    *,
    whole: bool = False,
) -> list[Region] | None:
    """calibrated_plan's bands for any prediction of a standing person's size by where their feet are; `whole`:
    None rather than a plan that leaves findable rows out to keep to the budget."""
    width_px, height_px = image_size_px
    box = feet_box_px if feet_box_px is not None else (0.0, 0.0, float(width_px), 1.5 * height_px)
    rows, smallest, tallest = _row_heights(size_of, box)
    # Feet so far below the frame that even the head is out of view, or so high that half the body is above it.
    off_frame = ~((rows - tallest < height_px) & (rows - 0.5 * smallest > 0))
    smallest[off_frame], tallest[off_frame] = np.nan, np.nan
    bands = _bands(rows, smallest, tallest, target_px, band_ratio)
    while _bands_cost(bands, box, image_size_px) > budget_px and target_px > MIN_TARGET_PX:
        target_px = max(MIN_TARGET_PX, target_px * 0.9)
        bands = _bands(rows, smallest, tallest, target_px, band_ratio)
    if whole and _bands_cost(bands, box, image_size_px) > budget_px:
        return None
    while len(bands) > 1 and _bands_cost(bands, box, image_size_px) > budget_px:
        bands = bands[:-1]
    while bands and _bands_cost(bands, box, image_size_px) > budget_px and bands[0].scale > MIN_SCALE:
        # One band left and still too costly (a steep view whose every row is near): below the target, to budget.
        shrink = math.sqrt(budget_px / _bands_cost(bands, box, image_size_px)) * 0.98
        bands = [replace(bands[0], scale=max(MIN_SCALE, bands[0].scale * shrink))]
    plan = [region for band in bands for region in _band_regions(band, box, image_size_px)]
    if feet_box_px is not None:
        plan += _unsearched_rows(bands, box, image_size_px)
    return plan


def _bands_cost(bands: Sequence[_Band], feet_box: tuple[float, float, float, float], size: tuple[int, int]) -> int:
    return plan_cost([region for band in bands for region in _band_regions(band, feet_box, size)])


def _band_regions(band: _Band, feet_box: tuple[float, float, float, float], size: tuple[int, int]) -> list[Region]:
    """The band's rectangle (feet rows, heads above, people's width beside the feet box), tiled."""
    width_px, height_px = size
    half_width = WIDTH_PER_HEIGHT * band.tallest_px
    left = max(0, math.floor(feet_box[0] - half_width))
    right = min(width_px, math.ceil(feet_box[2] + half_width))
    top = max(0, math.floor(band.head_top))
    bottom = min(height_px, math.ceil(band.feet_bottom + FOOT_MARGIN * band.tallest_px))
    if bottom - top < 2 or right - left < 2:
        return []
    core = (float(feet_box[0]), float(band.feet_top), float(feet_box[2]), float(band.feet_bottom))
    return tiles((left, top, right, bottom), band.scale, size, band.tallest_px * HEAD_MARGIN, core)


def _unsearched_rows(
    bands: Sequence[_Band], feet_box: tuple[float, float, float, float], size: tuple[int, int]
) -> list[Region]:
    """The feet box's rows above every band, at the uncalibrated policy's finest scale (see calibrated_plan)."""
    width_px, height_px = size
    first_band_row = min((band.feet_top for band in bands), default=math.ceil(feet_box[3]))
    if first_band_row <= feet_box[1] + _ROW_STEP_PX:
        return []
    scale = max(UNCALIBRATED_SCALES) * 1920 / max(size)
    overlap = 0.35 * height_px
    top = max(0, math.floor(feet_box[1] - overlap))
    bottom = min(height_px, math.ceil(first_band_row + 0.1 * height_px))
    left, right = (
        max(0, math.floor(feet_box[0] - 0.1 * width_px)),
        min(width_px, math.ceil(feet_box[2] + 0.1 * width_px)),
    )
    core = (float(feet_box[0]), float(feet_box[1]), float(feet_box[2]), float(first_band_row))
    return tiles((left, top, right, bottom), scale, size, overlap, core)


ZOOM_BUDGET_PX: Final = 500_000
"""Detector input pixels a second look may spend per frame (the uncalibrated policy's passes cost 1 190 000)."""
ZOOM_NEIGHBOURHOOD: Final = 1.5
"""A second look covers each small person's box grown by this many of their heights on every side: people come in
groups (a table of seated people around the one standing person the first passes found)."""


def zoom_regions(
    boxes_xyxy: np.ndarray, seen_at_scale: float, image_size_px: tuple[int, int], *, budget_px: float = ZOOM_BUDGET_PX
) -> list[Region]:
    """A second look, at the detector's favourite size, around the people a pass found too small for it.

    People below FAVOURITE_PX[0] in the finest pass (`seen_at_scale`) were found on the steep part of the recall
    curve, where as many are missed as found: around them (ZOOM_NEIGHBOURHOOD), at the scale that brings the
    median of them to TARGET_PX (at most MAX_SCALE), the detector looks again. Overlapping neighbourhoods are
    searched as one region; when the regions cost more than `budget_px`, the scale shrinks until they fit. The
    uncalibrated policy's answer to seated and far people, where a calibration would say where they are.
    """
    width_px, height_px = image_size_px
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    heights = boxes[:, 3] - boxes[:, 1]
    small = boxes[(heights * seen_at_scale < FAVOURITE_PX[0]) & (heights > 1.0)]
    if not len(small):
        return []
    grow = ZOOM_NEIGHBOURHOOD * (small[:, 3] - small[:, 1])[:, None] * np.array([-1.0, -1.0, 1.0, 1.0])
    areas = [list(area) for area in np.clip(small + grow, 0, [width_px, height_px, width_px, height_px])]
    members = [[h] for h in (small[:, 3] - small[:, 1])]
    merged = True
    while merged:  # union of overlapping neighbourhoods, until none overlap
        merged = False
        for i in range(len(areas)):
            for j in range(i + 1, len(areas)):
                a, b = areas[i], areas[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    areas[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                    members[i] += members.pop(j)
                    areas.pop(j)
                    merged = True
                    break
            if merged:
                break
    scales = [float(np.clip(TARGET_PX / np.median(m), seen_at_scale, MAX_SCALE)) for m in members]
    while True:
        plan = [
            region
            for area, scale, m in zip(areas, scales, members, strict=True)
            for region in tiles(
                (math.floor(area[0]), math.floor(area[1]), math.ceil(area[2]), math.ceil(area[3])),
                scale,
                image_size_px,
                2.0 * max(m),
            )
        ]
        if plan_cost(plan) <= budget_px or max(scales) <= seen_at_scale * 1.05:
            return plan if max(scales) > seen_at_scale * 1.05 else []
        scales = [max(seen_at_scale, s * 0.9) for s in scales]
