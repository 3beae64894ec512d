"""Which observations are the same person: linking people across frames by where they stand.

Calibration's height prior is a statement about individuals: each person has one height, drawn from the
population. A person walking through thirty frames is thirty observations but one draw of a height; solved as
thirty independent people, a few individuals who happen to be short and walk near the camera bend the horizon
and the reported sigma shrinks as if there were thirty times more evidence (the Oxford Town Centre clip: 433
observations of about 45 individuals, tilt 2.4 deg too steep with a 0.26 deg sigma; with one height per
individual 0.9 deg). `link_tracks` recovers the individuals from the observations' times and positions alone.

Linking, frame by frame in time order: each observation joins the track whose last observation is the
closest in the image (ankle centre), one-to-one (Hungarian assignment), if it is near enough to have walked
there and of a similar size; otherwise it starts a track. "Near enough" scales with the person's size in
the image, which is what converts pixels to metres locally: a person of segment length l pixels and height h
metres moving at v m/s covers at most v dt l / h pixels in dt seconds. A link is only made across a gap of at
most `max_gap_s`, and sizes must agree within `max_size_ratio` (a tall and a short person crossing paths are
not merged). A wrong link merges two people into one height, a missed one leaves them independent: the gates
are set for the first to be rare, since merging is the error that biases.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import linear_sum_assignment

from .priors import DEFAULT_HEIGHT_M

# A brisk walk is 1.5-2 m/s; 3 m/s leaves room for a jog and for keypoint jitter at high frame rates.
MAX_SPEED_M_S = 3.0
MAX_GAP_S = 1.0
MAX_SIZE_RATIO = 1.25
# Pose-model jitter between frames, as a share of the person's segment length, allowed on top of the motion.
_JITTER_FRACTION = 0.05


def link_tracks(
    times_s: ArrayLike,
    tops_px: ArrayLike,
    bottoms_px: ArrayLike,
    *,
    height_m: float = DEFAULT_HEIGHT_M,
    max_speed_m_s: float = MAX_SPEED_M_S,
    max_gap_s: float = MAX_GAP_S,
    max_size_ratio: float = MAX_SIZE_RATIO,
) -> np.ndarray:
    """(n,) integer track labels (0, 1, ...): equal labels are the same person seen at different times.

    times_s gives each observation's frame time; observations with equal times are in one frame and never
    linked to each other. Non-finite rows get a track of their own.
    """
    times = np.asarray(times_s, dtype=np.float64).reshape(-1)
    tops = np.asarray(tops_px, dtype=np.float64).reshape(-1, 2)
    bottoms = np.asarray(bottoms_px, dtype=np.float64).reshape(-1, 2)
    n = len(times)
    if tops.shape != (n, 2) or bottoms.shape != (n, 2):
        raise ValueError(f"times, tops and bottoms must describe the same {n} observations")
    length = np.hypot(*(tops - bottoms).T)
    valid = np.isfinite(times) & np.all(np.isfinite(tops), 1) & np.all(np.isfinite(bottoms), 1) & (length > 0)
    labels = np.full(n, -1)
    last = np.zeros(0, dtype=int)  # per track: its latest observation
    valid_times = times[valid]
    for t in np.unique(valid_times):
        current = np.flatnonzero(valid & (times == t))
        assigned = np.zeros(len(current), dtype=bool)
        live = last[(t - times[last] <= max_gap_s) & (times[last] < t)] if len(last) else last
        if len(live) and len(current):
            cost = _link_costs(live, current, times, bottoms, length, height_m, max_speed_m_s, max_size_ratio)
            rows, cols = linear_sum_assignment(np.where(np.isfinite(cost), cost, 1e9))
            for r, c in zip(rows, cols, strict=True):
                if np.isfinite(cost[r, c]):
                    labels[current[c]] = labels[live[r]]
                    last[labels[live[r]]] = current[c]
                    assigned[c] = True
        for c in np.flatnonzero(~assigned):
            labels[current[c]] = len(last)
            last = np.append(last, current[c])
    unlabelled = labels < 0
    labels[unlabelled] = len(last) + np.arange(int(unlabelled.sum()))
    return labels


def _link_costs(
    live: np.ndarray,
    current: np.ndarray,
    times: np.ndarray,
    bottoms: np.ndarray,
    length: np.ndarray,
    height_m: float,
    max_speed_m_s: float,
    max_size_ratio: float,
) -> np.ndarray:
    """(tracks, observations) gated distances in units of the allowed move; inf where a link is impossible."""
    distance = np.linalg.norm(bottoms[live][:, None, :] - bottoms[current][None, :, :], axis=-1)
    size = 0.5 * (length[live][:, None] + length[current][None, :])
    dt = times[current][None, :] - times[live][:, None]
    allowed = (max_speed_m_s * dt / height_m + _JITTER_FRACTION) * size
    ratio = np.maximum(length[live][:, None], length[current][None, :]) / np.minimum(
        length[live][:, None], length[current][None, :]
    )
    cost = distance / allowed
    return np.where((cost <= 1.0) & (ratio <= max_size_ratio), cost, np.inf)
