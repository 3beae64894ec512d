"""Which stored observations are independent evidence: one person standing still is one person, not hundreds.

Calibration treats every observation as an independent draw of a person's shoulder-over-ankle segment. A fixed
camera breaks that in two ways: someone who stands still (waiting at a door) is seen in hundreds of frames with
the same pixels, and a static false detection (a mannequin in a shop window, a poster) is "seen" in every frame.
Either then outweighs dozens of real passers-by, and a static false positive that happens to look plausible
drags the solution (seen on the Oxford Town Centre clip: one mannequin in 82 frames moved fx by 10 % and the
ground normal by 1.7 degrees). Collapsing repeats keeps one observation per place and pose: anything whose
shoulder and ankle both lie within `radius_px` of an observation already kept is a repeat. Walking people move
several pixels between frames, so their observations survive; still ones collapse to one.

`solve_evidence` is the one path from pooled evidence to a camera, shared by the calibration worker and
`posemetry analyze`: collapse repeats, optionally cap with a spatially balanced sample, calibrate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .calibrate import calibrate
from .calibration import Calibration
from .errors import CalibrationError
from .problem import CalibrationProblem, SolveOptions
from .tracks import link_tracks, possible_repeats

# Pose-model jitter on a still person is 1-3 px at 1080p; this is comfortably above it as a share of the image.
DEFAULT_RADIUS_FRACTION = 0.002


def repeat_radius_px(image_size_px: tuple[float, float]) -> float:
    """The default radius for an image: DEFAULT_RADIUS_FRACTION of its diagonal (4.4 px at 1920x1080)."""
    return DEFAULT_RADIUS_FRACTION * float(np.hypot(*image_size_px))


def collapse_repeats(tops_px: np.ndarray, bottoms_px: np.ndarray, radius_px: float) -> np.ndarray:
    """Indices (ascending) of the observations to keep: the first of every group of repeats, in input order.

    A repeat is within `radius_px` of a kept observation in every coordinate of both points (Chebyshev distance
    on the 4-vector shoulder x, y, ankle x, y), so two people who merely share a spot but differ in height or lean
    are both kept. Rows with non-finite coordinates are kept as they are (the caller's validation handles them).
    """
    points = np.hstack([np.asarray(tops_px, dtype=float), np.asarray(bottoms_px, dtype=float)])
    n = len(points)
    if n == 0 or radius_px <= 0:
        return np.arange(n)
    finite = np.all(np.isfinite(points), axis=1)
    finite_index = np.flatnonzero(finite)
    # Greedy in input order over the pairs within the radius (i < j): a kept observation suppresses its later
    # neighbours, a suppressed one suppresses nothing. Only observations with a neighbour enter the loop (a loop
    # over all of a solve's 2000 cost 5.7 ms, this 1.8).
    pairs = cKDTree(points[finite]).query_pairs(radius_px, p=np.inf, output_type="ndarray")
    suppressed = np.zeros(len(finite_index), dtype=bool)
    if len(pairs):
        pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
        firsts, starts = np.unique(pairs[:, 0], return_index=True)
        for first, later in zip(firsts.tolist(), np.split(pairs[:, 1], starts[1:]), strict=True):
            if not suppressed[first]:
                suppressed[later] = True
    keep = np.ones(n, dtype=bool)
    keep[finite_index[suppressed]] = False
    return np.flatnonzero(keep)


# The sampling grid over the image (columns, rows), by ankle centre. The store keys every stored person by these
# cells and samples on them too (service.calibration.evidence), so a solve in the workers and one in
# `posemetry analyze` see evidence spread the same way.
SAMPLE_GRID = (8, 8)


def grid_cells(
    points_px: np.ndarray, image_size_px: tuple[float, float], grid: tuple[int, int] = SAMPLE_GRID
) -> np.ndarray:
    """The grid cell (row * columns + column) of each point; points outside the image go to the nearest edge cell,
    and a coordinate that is not finite counts as 0."""
    points = np.asarray(points_px, dtype=float).reshape(-1, 2)
    cols, rows = grid
    width, height = float(image_size_px[0]), float(image_size_px[1])
    finite = np.all(np.isfinite(points), axis=1)
    col = np.clip(np.floor(np.where(finite, points[:, 0], 0.0) / width * cols), 0, cols - 1).astype(int)
    row = np.clip(np.floor(np.where(finite, points[:, 1], 0.0) / height * rows), 0, rows - 1).astype(int)
    return row * cols + col


def balanced_sample(
    bottoms_px: np.ndarray,
    image_size_px: tuple[float, float],
    cap: int,
    *,
    seed: int = 0,
    grid: tuple[int, int] = SAMPLE_GRID,
) -> np.ndarray:
    """Indices (ascending) of at most `cap` observations spread as evenly over the image grid as the data allow.

    The in-memory twin of the store's `sample_evidence`: every cell (by ankle centre) contributes equally and
    cells with fewer people than their share give the remainder to the others, so a solve stays fast on a long
    video and is not dominated by the one spot where people crowd or linger. Random within a cell, reproducible
    for a seed. Everything is kept when there are no more than `cap` observations.
    """
    points = np.asarray(bottoms_px, dtype=float).reshape(-1, 2)
    n = len(points)
    if cap < 1:
        raise ValueError(f"cap must be positive, got {cap}")
    if n <= cap:
        return np.arange(n)
    cols, rows = grid
    cell = grid_cells(points, image_size_px, grid)
    rng = np.random.default_rng(seed)
    # Rank of each observation within its cell, in a random order: taking everything of rank < level from every
    # cell is the water-filling; the last level is filled at random across cells.
    order = rng.permutation(n)
    by_cell = order[np.argsort(cell[order], kind="stable")]
    starts = np.searchsorted(cell[by_cell], np.arange(rows * cols))
    rank = np.empty(n, dtype=int)
    rank[by_cell] = np.arange(n) - starts[cell[by_cell]]
    counts = np.bincount(cell, minlength=rows * cols)
    level = 0
    while np.minimum(counts, level + 1).sum() <= cap:
        level += 1
    chosen = np.flatnonzero(rank < level)
    remainder = np.flatnonzero(rank == level)
    extra = rng.choice(remainder, size=cap - len(chosen), replace=False)
    return np.sort(np.concatenate([chosen, extra]))


@dataclass(frozen=True)
class EvidenceSolve:
    """What solving on a body of evidence produced: the camera, or why there is none."""

    used: np.ndarray
    """Indices into the evidence of the observations solved on (repeats collapsed, capped), ascending."""
    calibration: Calibration | None
    error: str | None = None

    @property
    def people_used(self) -> int:
        return len(self.used)

    def inlier_mask(self, evidence_count: int) -> np.ndarray:
        """(evidence_count,) bool: the observations the solved camera kept as inliers."""
        mask = np.zeros(evidence_count, dtype=bool)
        if self.calibration is not None:
            mask[self.used[np.asarray(self.calibration.inliers, dtype=bool)]] = True
        return mask


def solve_evidence(
    tops_px: np.ndarray,
    bottoms_px: np.ndarray,
    problem: CalibrationProblem,
    options: SolveOptions | None = None,
    *,
    cap: int | None = None,
    times_s: np.ndarray | None = None,
    appearance: Sequence[bytes | None] | None = None,
    client_tracks: Sequence[str | None] | None = None,
) -> EvidenceSolve:
    """Calibrate once on usable observations pooled from many frames: the one path from evidence to a camera.

    With `times_s` (each observation's frame time), observations are first linked into individuals
    (service.geometry.tracks), so one person seen in many frames has one height; `appearance` (each observation's
    descriptor or None) also links them across gaps of seconds (a camera posting an image every few seconds), and
    `client_tracks` (each observation's client track id or None: a keypoint client's tracker) makes each id one
    individual (across gaps of up to a minute); the sigma is the one with one height per individual they could be
    (`possible_repeats`: frames seconds apart leave one walker's sightings unlinked). Repeats are collapsed (see the
    module docstring), then, with `cap`, a spatially balanced sample of at most `cap` is drawn from what remains
    (`balanced_sample`, seeded by options.seed), and `calibrate` runs on it. A solve that cannot produce a camera
    returns its reason instead of raising, because callers record failures with the evidence they were given (the
    calibration worker keeps them in the history; `posemetry analyze` reports them).
    """
    options = SolveOptions() if options is None else options
    tops = np.asarray(tops_px, dtype=float).reshape(-1, 2)
    bottoms = np.asarray(bottoms_px, dtype=float).reshape(-1, 2)
    if times_s is None and client_tracks is not None:
        raise ValueError("client_tracks link observations with their frame times: pass times_s too")
    tracks = repeats = None
    if times_s is not None:
        tracks = link_tracks(
            times_s, tops, bottoms, height_m=problem.height_m, appearance=appearance, client_tracks=client_tracks
        )
        repeats = possible_repeats(
            times_s, tops, bottoms, tracks, height_m=problem.height_m, client_tracks=client_tracks
        )
    image_size_px = problem.image_size_px
    used = collapse_repeats(tops, bottoms, repeat_radius_px(image_size_px))
    if cap is not None:
        used = used[balanced_sample(bottoms[used], image_size_px, cap, seed=options.seed or 0)]
    try:
        solution = calibrate(
            tops[used],
            bottoms[used],
            problem,
            options,
            tracks=None if tracks is None else tracks[used],
            repeats=None if repeats is None else repeats[used],
        )
    except CalibrationError as exc:
        return EvidenceSolve(used, None, str(exc))
    return EvidenceSolve(used, solution)
