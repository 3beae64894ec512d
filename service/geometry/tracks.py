"""Which observations are the same person: linking people across frames by where they stand and how they move.

Calibration's height prior is a statement about individuals: each person has one height, drawn from the
population. A person walking through thirty frames is thirty observations but one draw of a height; solved as
thirty independent people, a few individuals who happen to be short and walk near the camera bend the horizon
and the reported sigma shrinks as if there were thirty times more evidence (the Oxford Town Centre clip: 433
observations of about 45 individuals, tilt 2.4 deg too steep with a 0.26 deg sigma; with one height per
individual 0.9 deg). `link_tracks` recovers the individuals from the observations' times and positions alone,
without a calibration (it runs before there is one).

Linking, frame by frame in time order: each observation joins at most one track, one-to-one (Hungarian
assignment), if it passes every gate below; otherwise it starts a track. Pixels become metres locally through
the person's size: a person of segment length l pixels and height h metres who moves d metres *sideways*
moves d l / h pixels. Moving in *depth* they move far less: the foot's image motion is foreshortened by about
tan(alpha), alpha the depression of the foot ray below the horizon (0.22 for a person 35 m from a camera 7.8 m
up), and it runs along the person's own segment (towards the vertical vanishing point). An isotropic gate in
units of l / h therefore admits ~1 / tan(alpha) times the walking speed in depth: on the Town Centre clip it
joined a person who vanished with a stranger appearing 6.2 m nearer 0.44 s later (14 m/s), 87 observations
forced onto one height. The gates:

* speed (every link): within `max_speed_m_s` of the track's last position, isotropically in units of l / h,
  plus keypoint jitter; sizes within `max_size_ratio` (a tall and a short person crossing paths stay apart);
* velocity (a track with a velocity): a walker keeps its velocity. The track's image velocity is fitted over
  its last VELOCITY_WINDOW_S (or the gap, if longer), and the link must fall near the constant-velocity
  prediction: within keypoint jitter propagated through the fit, plus the ankle centre's surge over a stride
  (GAIT_M) and a bounded acceleration (MAX_ACCEL_M_S2: a walker turning or stopping) in metres. The
  prediction carries the walker's own depth motion, so only the deviation from it is gated. A velocity
  measured over T seconds is trusted over a gap of at most MAX_EXTRAPOLATION x T;
* no velocity (a single sighting, or a gap too long for the velocity's span): within SINGLE_SPEED_M_S (a
  walking pace: without a velocity to check, a link is a guess, made only for walkers) of the last position,
  across a gap of at most SINGLE_MAX_GAP_S. Without a velocity a person who reappears cannot be told from a
  stranger who appears near where they were, and the chance of such a stranger grows with the gate's area,
  i.e. with the gap squared.

Both of the last two gates are ellipses: metres seen along the segment are depth metres, foreshortened by
tan(alpha), so along the segment only ALONG_SEGMENT_SHARE of the metres' pixels is allowed (tan(alpha) <= 0.5:
people more than two camera heights away, most of a surveillance view); keypoint jitter, in pixels, is allowed
in full both ways. On steeper views this misses some links of fast walkers, which costs independence, not bias.

A wrong link merges two people into one height, a missed one only leaves one person's pieces independent: the
gates are set for the first to be rare.

Frames seconds apart (an image camera posting every 2 s) defeat every motion gate: without a velocity a person
who reappears cannot be told from a stranger by position. With appearance descriptors (service.geometry.appearance:
colour histograms of torso and legs, from the image pipeline) a second, long-gap stage runs after linking: tracks
in order of their first time, matched one-to-one (Hungarian) to chains of tracks that ended more than max_gap_s and
at most LONG_MAX_GAP_S before (someone crossing the view), when the appearance distance is under
MAX_APPEARANCE_DISTANCE, the ankle centre moved within a LONG_SPEED_M_S walk (sideways metres in l / h, generous
in depth) and the sizes are within max_size_ratio. A chain only grows at its end, so it never holds two tracks
that share a frame time. Town Centre's 22 clip frames posted 2 s apart: the solve's 105 inliers were 105
"individuals" before, 43 after; 99.2 % of the linked pairs are one annotated person (the two wrong ones: two
people in dark coats walking together; docs/benchmarks/camera-model.md). People without descriptors (posted
keypoints) are linked by motion alone, exactly as without the stage.

Most camera systems run a tracker and know which detection is which person: a client posting keypoints may give
each person its tracker's id (`client_tracks`). Those ids are the client's authority: observations sharing an id
are one individual (their tracks are united at the end), and neither motion nor appearance links an observation
with an id to a track or chain holding another id. Only an id's sightings more than CLIENT_MAX_GAP_S apart, with
none between, are taken for two individuals: a tracker that restarts numbers its people from 1 again, and a reused
id would merge two people's heights (a bias), whereas splitting one person who was out of view for a minute only
counts them twice (a little independence). Observations without an id
link as before, to each other and to tracks with an id; without any id the labels are exactly those of linking
without ids. Ids are one camera's and one calibration epoch's, as a sample is.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .appearance import appearance_distances, decode_descriptors
from .priors import DEFAULT_HEIGHT_M

# A brisk walk is 1.5-2 m/s; 3 m/s leaves room for a jog.
MAX_SPEED_M_S = 3.0
# The longest gap across which a track with a velocity is continued.
MAX_GAP_S = 1.0
# Without a velocity: a walking pace, across a short gap.
SINGLE_MAX_GAP_S = 0.5
SINGLE_SPEED_M_S = 2.0
# Along the segment (image motion = depth motion x tan(alpha)), this share of a gate's metres in pixels.
ALONG_SEGMENT_SHARE = 0.5
MAX_SIZE_RATIO = 1.25
# Pose-model jitter of a difference of two observations' ankle centres, as a share of the segment length. On
# Town Centre the ankle centre scatters by 0.4-0.7 % of the segment per coordinate from frame to frame (robust,
# from second differences), with heavier tails (a foot taken for another's): 5 % is ~5 sigma of a difference.
_JITTER_FRACTION = 0.05
# The velocity gate. Walkers turn and stop at up to ~2 m/s^2 (a 90 deg turn at 1.4 m/s in a second); the ankle
# centre advances in surges (each ankle stands still while the other swings), up to ~0.1 m from a steady walk.
VELOCITY_WINDOW_S = 0.5
MAX_ACCEL_M_S2 = 2.0
# A velocity fitted over T seconds is trusted over a gap of at most this many T.
MAX_EXTRAPOLATION = 2.0
GAIT_M = 0.1
# The long-gap stage (module docstring). Someone crossing Town Centre's view (about 30 m of street at 1.4 m/s) is in
# it for about 20 s: a camera posting every few seconds sees them in a handful of frames spread over that.
LONG_MAX_GAP_S = 30.0
LONG_SPEED_M_S = 2.0
# Appearance distance (service.geometry.appearance, the larger of torso's and legs') under which two pieces are one
# person. Town Centre's clip frames, detections matched to the annotated pedestrians (docs/benchmarks/camera-model.md):
# one person across frames up to 5 s apart median 0.26, strangers median 0.89 (1st percentile 0.40); under 0.27,
# 2 of 4979 stranger pairs (two people in dark coats walking together) and 308 of 572 one-person pairs.
MAX_APPEARANCE_DISTANCE = 0.27
APPEARANCE_SIGHTINGS = 5
# Client track ids: sightings of one id further apart than this, with none between, are two individuals (a tracker
# restarting reuses its ids). Longer than the long-gap stage's reach: an id links what appearance could not.
CLIENT_MAX_GAP_S = 60.0
# Frame times are floats (25 frames of 0.04 s are 1.0000000000000002 s): time limits hold to a microsecond.
_TIME_TOLERANCE_S = 1e-6
# Possible repeats (`possible_repeats`, for the sigma only): every link the motion gates allow across gaps of up to
# REPEAT_MAX_GAP_S, a sighting without a velocity included, within a walk of REPEAT_MAX_SPAN_S through the view.
REPEAT_MAX_GAP_S = 5.0
REPEAT_MAX_SPAN_S = LONG_MAX_GAP_S


def link_tracks(
    times_s: ArrayLike,
    tops_px: ArrayLike,
    bottoms_px: ArrayLike,
    *,
    height_m: float = DEFAULT_HEIGHT_M,
    max_speed_m_s: float = MAX_SPEED_M_S,
    max_gap_s: float = MAX_GAP_S,
    max_size_ratio: float = MAX_SIZE_RATIO,
    single_max_gap_s: float = SINGLE_MAX_GAP_S,
    max_span_s: float = math.inf,
    appearance: Sequence[bytes | None] | None = None,
    max_long_gap_s: float = LONG_MAX_GAP_S,
    max_appearance_distance: float = MAX_APPEARANCE_DISTANCE,
    client_tracks: Sequence[str | None] | None = None,
) -> np.ndarray:
    """(n,) integer track labels (0, 1, ...): equal labels are the same person seen at different times.

    times_s gives each observation's frame time; observations with equal times are in one frame and never
    linked to each other. Non-finite rows get a track of their own. `single_max_gap_s` is the no-velocity gate's
    longest gap, and a track whose first sighting is more than `max_span_s` old is continued no further.
    `appearance`, each observation's descriptor (service.geometry.appearance) or None, enables the long-gap stage;
    without any descriptor the labels are those of linking by motion alone. `client_tracks`, each observation's
    client track id or None, unites each id's observations and keeps different ids apart (module docstring); without
    any id it changes nothing.
    """
    times = np.asarray(times_s, dtype=np.float64).reshape(-1)
    tops = np.asarray(tops_px, dtype=np.float64).reshape(-1, 2)
    bottoms = np.asarray(bottoms_px, dtype=np.float64).reshape(-1, 2)
    n = len(times)
    if tops.shape != (n, 2) or bottoms.shape != (n, 2):
        raise ValueError(f"times, tops and bottoms must describe the same {n} observations")
    segment = tops - bottoms
    length = np.hypot(*segment.T)
    valid = np.isfinite(times) & np.all(np.isfinite(tops), 1) & np.all(np.isfinite(bottoms), 1) & (length > 0)
    gates = _Gates(times, bottoms, segment, length, height_m, max_speed_m_s, max_size_ratio, single_max_gap_s)
    client = _client_codes(client_tracks, times)
    labels = np.full(n, -1)
    members: list[list[int]] = []  # per track: its observations in time order
    member_times: list[list[float]] = []  # per track: their times (increasing: one observation per frame time)
    last_seen = np.zeros(n, dtype=np.intp)  # per track (at most n): its latest observation
    last_time = np.full(n, -np.inf)  # per track: that observation's time
    first_time = np.full(n, np.inf)  # per track: its first observation's time
    track_client = np.full(n, -1)  # per track: the code of its client id, -1 while it has none
    by_time = np.flatnonzero(valid)
    by_time = by_time[np.argsort(times[by_time], kind="stable")]
    frame_times, starts = np.unique(times[by_time], return_index=True)
    for t, current in zip(frame_times.tolist(), np.split(by_time, starts[1:]), strict=True):
        assigned = np.zeros(len(current), dtype=bool)
        since = t - last_time[: len(members)]
        young = t - first_time[: len(members)] <= max_span_s + _TIME_TOLERANCE_S
        live = np.flatnonzero((since > 0.0) & (since <= max_gap_s + _TIME_TOLERANCE_S) & young)
        if len(live):
            cost = gates.costs([members[k] for k in live], [member_times[k] for k in live], last_seen[live], current)
            if client is not None:
                cost[_other_clients(track_client[live], client[current])] = np.inf
            finite = np.isfinite(cost)
            rows, cols = linear_sum_assignment(np.where(finite, cost, 1e9)) if finite.any() else ((), ())
            for r, c in zip(rows, cols, strict=True):
                if finite[r, c]:
                    labels[current[c]] = live[r]
                    members[live[r]].append(int(current[c]))
                    member_times[live[r]].append(t)
                    last_seen[live[r]] = current[c]
                    last_time[live[r]] = t
                    assigned[c] = True
                    if client is not None:
                        track_client[live[r]] = max(track_client[live[r]], client[current[c]])
        for c in np.flatnonzero(~assigned):
            labels[current[c]] = len(members)
            last_time[len(members)] = first_time[len(members)] = t
            last_seen[len(members)] = current[c]
            if client is not None:
                track_client[len(members)] = client[current[c]]
            members.append([int(current[c])])
            member_times.append([t])
    unlabelled = labels < 0
    labels[unlabelled] = len(members) + np.arange(int(unlabelled.sum()))
    if appearance is not None:
        if len(appearance) != n:
            raise ValueError(f"appearance must hold one descriptor (or None) per observation ({n})")
        roots, described = decode_descriptors(list(appearance))
        if described.any():
            joins = _LongGaps(gates, roots, described, max_long_gap_s, max_appearance_distance)
            joinable = [k for k, track in enumerate(members) if described[track].any()]
            labels = joins.join(
                [members[k] for k in joinable],
                labels,
                max_gap_s,
                None if client is None else track_client[joinable],
            )
    if client is not None:
        labels = _unite_clients(labels, np.where(valid, client, -1))
    return labels


def possible_repeats(
    times_s: ArrayLike,
    tops_px: ArrayLike,
    bottoms_px: ArrayLike,
    tracks: ArrayLike,
    *,
    height_m: float = DEFAULT_HEIGHT_M,
    client_tracks: Sequence[str | None] | None = None,
) -> np.ndarray:
    """(n,) labels of the individuals the observations could be, for the sigma: `tracks` (link_tracks' individuals)
    united with every link the motion gates allow across gaps of up to REPEAT_MAX_GAP_S, a sighting without a
    velocity included, along walks of at most REPEAT_MAX_SPAN_S. Different client ids stay apart.

    link_tracks links only what it can tell from a stranger, so frames seconds apart (a client posting one frame a
    second or less, a solve's sample of a few of a long stream's frames) leave one walker's sightings unlinked, and
    each counts as an independent draw of a height: the sigma shrinks as if there were several times more people
    (on the realistic simulator, frames 2 s apart: the normal covered on 89 % of cameras instead of 95 %). Taking
    every possible repeat for one person instead is wrong about some strangers, which only widens the sigma: more
    than half of these links join strangers, yet the coverage comes back to that of the true individuals
    (docs/benchmarks/camera-model.md). The estimate keeps link_tracks' individuals: a wrong link there is a bias.
    """
    loose = link_tracks(
        times_s,
        tops_px,
        bottoms_px,
        height_m=height_m,
        max_gap_s=REPEAT_MAX_GAP_S,
        single_max_gap_s=REPEAT_MAX_GAP_S,
        max_span_s=REPEAT_MAX_SPAN_S,
        client_tracks=client_tracks,
    )
    return united(np.asarray(tracks).reshape(-1), loose)


def united(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) labels 0, 1, ... of the finest grouping coarser than both labellings: observations sharing a label in
    either are in one group."""
    n = len(a)
    _, first_a, of_a = np.unique(a, return_index=True, return_inverse=True)
    _, first_b, of_b = np.unique(b, return_index=True, return_inverse=True)
    rows = np.arange(n)
    edges = coo_matrix(
        (np.ones(2 * n), (np.r_[rows, rows], np.r_[first_a[of_a.ravel()], first_b[of_b.ravel()]])), shape=(n, n)
    )
    return connected_components(edges, directed=False)[1]


def _client_codes(client_tracks: Sequence[str | None] | None, times: np.ndarray) -> np.ndarray | None:
    """(n,) a code per individual the client ids name (0, 1, ...), -1 where none; None when no observation has an
    id, so that linking without ids takes exactly the path it took before ids existed. One id's sightings split
    into several codes where CLIENT_MAX_GAP_S passes without one (module docstring)."""
    if client_tracks is None:
        return None
    n = len(times)
    if len(client_tracks) != n:
        raise ValueError(f"client_tracks must hold one id (or None) per observation ({n})")
    by_id: dict[str, list[int]] = {}
    for index, key in enumerate(client_tracks):
        if key is not None:
            by_id.setdefault(key, []).append(index)
    if not by_id:
        return None
    client = np.full(n, -1)
    code = 0
    for rows in by_id.values():
        ordered = np.array(rows)[np.argsort(times[rows], kind="stable")]
        # A non-finite time cannot be placed in the id's sequence: it stays with the segment before it.
        step = np.diff(times[ordered])
        starts = np.concatenate(([True], np.nan_to_num(step, nan=0.0) > CLIENT_MAX_GAP_S + _TIME_TOLERANCE_S))
        client[ordered] = code + np.cumsum(starts) - 1
        code += int(starts.sum())
    return client


def _other_clients(tracks: np.ndarray, observations: np.ndarray) -> np.ndarray:
    """(tracks, observations) True where both hold a client id and the ids differ: a link the client forbids."""
    return (tracks[:, None] >= 0) & (observations[None, :] >= 0) & (tracks[:, None] != observations[None, :])


def _unite_clients(labels: np.ndarray, client: np.ndarray) -> np.ndarray:
    """`labels` with every label holding a client id merged with the others holding it, renumbered 0, 1, ...

    Linking never puts two ids under one label, so each label maps to at most one id and the union is a lookup."""
    coded = np.flatnonzero(client >= 0)
    if not len(coded):
        return labels
    root = np.arange(int(labels.max()) + 1)
    first: dict[int, int] = {}
    for label, code in zip(labels[coded].tolist(), client[coded].tolist(), strict=True):
        root[label] = first.setdefault(code, label)
    return np.unique(root[labels], return_inverse=True)[1].reshape(-1)


class _Gates:
    """The gates of the module docstring for every live track against one frame's observations at once.

    One frame's links are judged together, as (tracks, observations) arrays: a solve links a sample of a couple of
    thousand people over hundreds of frame times, and judging each track on its own cost most of a solve's time in
    numpy's per-call overhead.
    """

    def __init__(
        self,
        times: np.ndarray,
        bottoms: np.ndarray,
        segment: np.ndarray,
        length: np.ndarray,
        height_m: float,
        max_speed_m_s: float,
        max_size_ratio: float,
        single_max_gap_s: float = SINGLE_MAX_GAP_S,
    ) -> None:
        self.times, self.bottoms, self.length = times, bottoms, length
        with np.errstate(divide="ignore", invalid="ignore"):  # invalid rows (zero length) never join a track
            self.along_unit = segment / length[:, None]
        # A last row of zeros pads the velocity's windows: padded terms add nothing to the window's sums.
        self.padding = len(times)
        self.padded_times, self.padded_bottoms = np.append(times, 0.0), np.vstack([bottoms, np.zeros((1, 2))])
        self.height_m, self.max_speed_m_s = height_m, max_speed_m_s
        self.max_size_ratio, self.single_max_gap_s = max_size_ratio, single_max_gap_s

    def costs(
        self, tracks: list[list[int]], track_times: list[list[float]], last: np.ndarray, current: np.ndarray
    ) -> np.ndarray:
        """(tracks, observations) gated distances in units of the allowance; inf where the link is impossible.

        `track_times` are the tracks' observations' times and `last` their latest observations. All of `current`
        are in one frame, so the gap since each track's last observation is one number per track (the caller
        passes live tracks only: 0 < gap <= link_tracks' max_gap_s).
        """
        gap = self.times[current[0]] - self.times[last]
        last_length, current_length = self.length[last][:, None], self.length[current][None, :]
        size = 0.5 * (last_length + current_length)
        metre_px = size / self.height_m  # pixels per metre about each pair of observations
        move = self.bottoms[current][None, :, :] - self.bottoms[last][:, None, :]
        ratio = np.maximum(last_length, current_length) / np.minimum(last_length, current_length)
        jitter = _JITTER_FRACTION * size
        distance = np.sqrt(move[:, :, 0] ** 2 + move[:, :, 1] ** 2)
        ok = (distance <= self.max_speed_m_s * gap[:, None] * metre_px + jitter) & (ratio <= self.max_size_ratio)
        cost = np.full(move.shape[:2], np.inf)
        # Only tracks that pass the plain speed and size gates for some observation are judged further: in a
        # solve's sample most live tracks pass none, and their windows cost most of the linking's time.
        candidates = np.flatnonzero(ok.any(axis=1))
        if not len(candidates):
            return cost
        # Each track's observations of the last max(VELOCITY_WINDOW_S, gap) seconds (its times increase).
        latest = self.times[last[candidates]]
        since = (latest - np.maximum(VELOCITY_WINDOW_S, gap[candidates]) - _TIME_TOLERANCE_S).tolist()
        windows = [tracks[r][bisect_left(track_times[r], s) :] for r, s in zip(candidates.tolist(), since, strict=True)]
        span = latest - self.times[[window[0] for window in windows]]
        sizes = np.array([len(window) for window in windows])
        fitted = (sizes >= 2) & (gap[candidates] <= MAX_EXTRAPOLATION * span + _TIME_TOLERANCE_S)
        single = ~fitted & (gap[candidates] <= self.single_max_gap_s + _TIME_TOLERANCE_S)
        if fitted.any():
            rows = candidates[fitted]
            residual, fit_jitter, allowed_m = self._from_velocity(
                [window for window, f in zip(windows, fitted, strict=True) if f], current
            )
            cost[rows] = self._ellipse(
                last[rows], residual, allowed_m[:, None] * metre_px[rows], jitter[rows] * fit_jitter[:, None]
            )
        if single.any():
            rows = candidates[single]
            reach_px = SINGLE_SPEED_M_S * gap[rows, None] * metre_px[rows]
            cost[rows] = self._ellipse(last[rows], move[rows], reach_px, jitter[rows])
        return np.where(ok & (cost <= 1.0), cost, np.inf)

    def _from_velocity(
        self, windows: list[list[int]], current: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per track: the constant-velocity prediction's miss of each observation (a least-squares line through
        the window's ankle centres), the keypoint jitter through the fit relative to that of a difference of two
        observations, and the metres a walker may stray from the line: the gait's surge and a bounded
        acceleration. Windows of unequal length are padded in front with the row of zeros."""
        count = np.array([len(window) for window in windows])
        width = int(count.max())
        index = np.array([[self.padding] * (width - len(window)) + window for window in windows])
        mask = np.arange(width)[None, :] >= (width - count)[:, None]
        t = self.padded_times[index]
        centre = t.sum(axis=1) / count
        offset = np.where(mask, t - centre[:, None], 0.0)
        spread = (offset**2).sum(axis=1)
        points = self.padded_bottoms[index]
        mean = points.sum(axis=1) / count[:, None]
        velocity = (offset[:, :, None] * (points - mean[:, None, :])).sum(axis=1) / spread[:, None]
        tau = self.times[current[0]] - centre
        residual = self.bottoms[current][None, :, :] - (mean + tau[:, None] * velocity)[:, None, :]
        fit_jitter = np.sqrt((1.0 + 1.0 / count + tau**2 / spread) / 2.0)
        return residual, fit_jitter, GAIT_M + 0.5 * MAX_ACCEL_M_S2 * tau**2

    def _ellipse(
        self, last: np.ndarray, move_px: np.ndarray, reach_px: np.ndarray, jitter_px: np.ndarray
    ) -> np.ndarray:
        """|move| against reach + jitter across the segment, ALONG_SEGMENT_SHARE x reach + jitter along it: ground
        metres seen along the segment are depth metres, foreshortened by tan(alpha)."""
        along_unit = self.along_unit[last]
        along = (move_px * along_unit[:, None, :]).sum(axis=2)
        across = move_px[:, :, 1] * along_unit[:, None, 0] - move_px[:, :, 0] * along_unit[:, None, 1]
        return np.hypot(along / (ALONG_SEGMENT_SHARE * reach_px + jitter_px), across / (reach_px + jitter_px))


class _LongGaps:
    """The long-gap stage (module docstring): whole tracks joined by appearance across gaps longer than linking's."""

    def __init__(
        self,
        gates: _Gates,
        roots: np.ndarray,
        described: np.ndarray,
        max_long_gap_s: float,
        max_appearance_distance: float,
    ) -> None:
        self.gates, self.roots, self.described = gates, roots, described
        self.max_long_gap_s, self.max_distance = max_long_gap_s, max_appearance_distance

    def join(
        self, tracks: list[list[int]], labels: np.ndarray, min_gap_s: float, clients: np.ndarray | None = None
    ) -> np.ndarray:
        """`labels` with tracks (lists of observations in time order, each with a descriptor) joined into chains.

        Tracks are taken in order of their first time; those starting together are matched one-to-one
        (Hungarian, by appearance distance) to the chains that ended more than `min_gap_s` and at most
        max_long_gap_s before, so a chain never holds two tracks that share a frame time. `clients`, each track's
        client id code (-1: none), keeps tracks of different ids in different chains. Labels are renumbered only
        when something was joined."""
        if len(tracks) < 2:
            return labels
        times, described = self.gates.times, self.described
        chain_of = list(range(len(tracks)))  # track -> its chain (the index of the chain's first track)
        chain_client = np.full(len(tracks), -1) if clients is None else clients.copy()  # per chain head
        # Open chains: first track -> (last observation, the last APPEARANCE_SIGHTINGS described observations).
        chains: dict[int, tuple[int, list[int]]] = {}
        ends = [(track[-1], [i for i in track if described[i]][-APPEARANCE_SIGHTINGS:]) for track in tracks]
        beginnings = [(track[0], [i for i in track if described[i]][:APPEARANCE_SIGHTINGS]) for track in tracks]
        joined = False
        starts = np.array([times[track[0]] for track in tracks])
        for t in np.unique(starts):
            arriving = np.flatnonzero(starts == t)
            for head in [h for h, (last, _) in chains.items() if t - times[last] > self.max_long_gap_s]:
                del chains[head]  # ended too long ago to be joined by anything later
            heads = [h for h, (last, _) in chains.items() if t - times[last] > min_gap_s + _TIME_TOLERANCE_S]
            if heads:
                cost = self._costs([chains[h] for h in heads], [beginnings[k] for k in arriving])
                if clients is not None:
                    cost[_other_clients(chain_client[heads], clients[arriving])] = np.inf
                rows, cols = linear_sum_assignment(np.where(np.isfinite(cost), cost, 1e9))
                for r, c in zip(rows, cols, strict=True):
                    if np.isfinite(cost[r, c]):
                        k = arriving[c]
                        tail = (chains[heads[r]][1] + ends[k][1])[-APPEARANCE_SIGHTINGS:]
                        chains[heads[r]] = (ends[k][0], tail)
                        chain_of[k] = heads[r]
                        chain_client[heads[r]] = max(chain_client[heads[r]], chain_client[k])
                        joined = True
            for k in arriving:
                if chain_of[k] == k:
                    chains[k] = ends[k]
        if not joined:
            return labels
        relabelled = labels.copy()
        for k, track in enumerate(tracks):
            relabelled[track] = labels[tracks[chain_of[k]][0]]
        return np.unique(relabelled, return_inverse=True)[1].reshape(-1)

    def _costs(self, chains: list[tuple[int, list[int]]], arriving: list[tuple[int, list[int]]]) -> np.ndarray:
        """(chains, arriving tracks) appearance distances where the gates pass; chains as (last observation, last
        described ones), tracks as (first observation, first described ones). The distance of a chain and a track
        is the median over pairs of the chain's last and the track's first APPEARANCE_SIGHTINGS described
        observations: the nearest in time look the most alike (a person turning shows another side), and the
        median shrugs off one bad descriptor (a neighbour's coat in the crop). The gates: within a walk of
        LONG_SPEED_M_S over the gap (sideways metres in units of l / h, the larger of the two sizes, plus keypoint
        jitter: generous in depth), sizes within the gates' max_size_ratio, and a distance under the threshold;
        inf elsewhere."""
        g = self.gates
        last = np.array([chain[0] for chain in chains])
        first = np.array([track[0] for track in arriving])
        gap = g.times[first][None, :] - g.times[last][:, None]
        last_length, first_length = g.length[last][:, None], g.length[first][None, :]
        size = np.maximum(last_length, first_length)
        reach = LONG_SPEED_M_S * gap * size / g.height_m + _JITTER_FRACTION * size
        move = np.linalg.norm(g.bottoms[first][None, :, :] - g.bottoms[last][:, None, :], axis=2)
        ratio = size / np.minimum(last_length, first_length)
        ok = (move <= reach) & (ratio <= g.max_size_ratio)
        cost = np.full(ok.shape, np.inf)
        pairs = np.nonzero(ok)
        if not len(pairs[0]):
            return cost
        # One distance matrix for the frame: every chain's tail against every arriving track's head, padded to
        # APPEARANCE_SIGHTINGS each (padding is NaN), then the median of each gated pair's block at once.
        tails = _padded([chain[1] for chain in chains])
        heads = _padded([track[1] for track in arriving])
        distance = appearance_distances(self.roots[tails.reshape(-1)], self.roots[heads.reshape(-1)])
        distance[tails.reshape(-1) < 0, :] = np.nan
        distance[:, heads.reshape(-1) < 0] = np.nan
        blocks = distance.reshape(len(chains), APPEARANCE_SIGHTINGS, len(arriving), APPEARANCE_SIGHTINGS)
        gated = blocks.transpose(0, 2, 1, 3)[pairs].reshape(len(pairs[0]), -1)
        described = ~np.all(np.isnan(gated), axis=1)
        median = np.full(len(gated), np.inf)
        median[described] = np.nanmedian(gated[described], axis=1)
        within = median <= self.max_distance
        cost[pairs[0][within], pairs[1][within]] = median[within]
        return cost


def _padded(sightings: list[list[int]]) -> np.ndarray:
    """(len, APPEARANCE_SIGHTINGS) observation indices, -1 where a list is shorter."""
    out = np.full((len(sightings), APPEARANCE_SIGHTINGS), -1)
    for row, indices in enumerate(sightings):
        out[row, : len(indices)] = indices
    return out
