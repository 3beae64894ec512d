"""Has the camera moved? A sequential test on the people of every measured frame (pure numpy/scipy, no I/O).

What people can see of a camera. A standing person is a vertical segment on the ground; the calibration predicts
where it points (at the vertical vanishing point v = K N) and how tall it looks for where it stands (which depends
on the horizon, the line N . K^-1 x = 0). So each usable person gives two residuals against the calibration:

- direction: how far the shoulder centre lies from the line through the ankle centre and v (pixels);
- height: the log of the person's implied height, relative to the frame's typical adult (scale-free).

A camera that turns or zooms moves v and the horizon, and both residuals shift in a spatially structured way; the
detector estimates that shift as three numbers, theta = (log focal scale, two tilts of the ground normal), by a
Gauss-Newton step per frame. What it cannot see, and need not: a pure pan about the vertical through the camera
(K, N and rho unchanged: people's geometry is identical, distances stay right), a sideways shift of the camera
(the same), and a change of camera height alone (indistinguishable from a taller crowd; every height is measured
relative to the frame's typical adult). Children, sitting people and odd detections give large height residuals but
ordinary directions: direction residuals are clipped (Huber), and a height more than HEIGHT_REJECT_Z standard
deviations short says nothing at all (a redescending score on that side only), so neither one odd person nor a
school class passing as a group moves the test. The frame's typical adult is a robust location started at the
calibration's own prediction (person height / camera height) and refined on the people near it, so a frame that is half
children keeps the adults' location instead of the median's.

The test. Per frame the clipped score s_k = -sum J' psi(z) and information I_k = sum J'J (J: the standardised
Jacobian of the residuals in theta) are kept for the last WINDOW_FRAMES frames; older frames are pooled into a
reference (forgotten slowly). The reference estimates the camera's offset from the calibration before any change
(a calibration is never exact, and real people are not the model), and for every candidate change point j in the
window a generalised likelihood ratio compares frames j..n with everything before j:

    u = S_after - I_after I_before^-1 S_before,   g_j = u' [kappa (I_after + I_after I_before^-1 I_after)]^-1 u / phi

g_j is chi-square with 3 degrees of freedom for a fixed j when nothing changed; an alarm is raised when
max_j g_j exceeds THRESHOLD, and the maximising j is the change point (the first frame of the new view). kappa
corrects for the clipping; phi >= 1 is the variance inflation measured on the reference itself (the same people
walk through many frames, so frames are not independent). THRESHOLD sets the false-alarm rate: see
`bench/movement.py` and README (Camera movement) for how it was chosen and what it gives.

Everything here works on the public calibration values (fx, fy, cx, cy, normal), so it follows the geometry
package's API without depending on its internals.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, fields, replace

import numpy as np
from scipy.stats import chi2, norm

from service.geometry.vec import FloatArray

PARAMETERS = ("log_focal_scale", "tilt_1_rad", "tilt_2_rad")
HUBER_C = 2.0
# E[psi(z)^2] and E[psi'(z)] for z ~ N(0, 1): the score's variance and slope under the clipping.
_TAIL = 2 * norm.sf(HUBER_C)
HUBER_KAPPA = float((1 - _TAIL) - 2 * HUBER_C * norm.pdf(HUBER_C) + HUBER_C**2 * _TAIL)
HUBER_GAMMA = float(1 - _TAIL)
# A person shorter than the calibration expects by more than this many standard deviations is a child, a sitting
# person or a detection error, not evidence about the camera (about 1 in 32 000 adults under the model); taller
# ones are clipped like directions, not rejected, since no crowd is that much taller and a camera that tilted or
# zoomed makes half its people look taller, which is most of what a large move shows. The score's variance and
# slope above are the Huber ones: the rejection changes them by less than 0.1 %.
HEIGHT_REJECT_Z = 4.0
# Finite-difference steps: theta, and pixels for the keypoint-noise propagation.
_THETA_STEP = 1e-6
_PIXEL_STEP = 0.05
# People whose segment is shorter than this are too small to say anything (a pose model's far, tiny people).
MIN_SEGMENT_PX = 8.0


@dataclass(frozen=True)
class ReferenceCamera:
    """The camera residuals are computed against: intrinsics and the unit ground normal (camera frame, up)."""

    fx: float
    fy: float
    cx: float
    cy: float
    normal: tuple[float, float, float]
    noise_px: float
    height_spread: float
    """Relative spread of people's heights (std / mean) in the height residuals."""
    log_height: float = 0.0
    """log(person height / camera height): the implied height (in camera heights) the calibration expects."""
    lean_rad: float = np.radians(2.0)
    """Spread of people's lean from the vertical (and of the pose model's shoulder-over-ankle bias)."""

    @classmethod
    def of(
        cls,
        intrinsics_px: tuple[float, float, float, float],
        normal: tuple[float, float, float],
        *,
        rho_m: float,
        person_height_m: float,
        height_std_m: float,
        noise_px: float | None,
    ) -> ReferenceCamera:
        """The reference for a solved camera: (fx, fy, cx, cy), its ground normal and height, the people's prior
        height and spread, and the keypoint noise the solve measured (1 px when it measured none)."""
        unit = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
        return cls(
            *(float(v) for v in intrinsics_px),
            normal=(float(unit[0]), float(unit[1]), float(unit[2])),
            noise_px=float(noise_px) if noise_px else 1.0,
            height_spread=height_std_m / person_height_m,
            log_height=float(np.log(person_height_m / rho_m)),
        )

    def tangent_basis(self) -> tuple[FloatArray, FloatArray]:
        """Two unit vectors perpendicular to the normal: the tilts theta[1], theta[2] move the normal along them."""
        n = np.asarray(self.normal, dtype=float)
        axis = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
        e1 = axis - (axis @ n) * n
        e1 /= np.linalg.norm(e1)
        return e1, np.cross(n, e1)

    def shifted(self, theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(fx, fy, normal) of the camera moved by theta, for a stack of thetas (..., 3)."""
        theta = np.asarray(theta, dtype=float)
        e1, e2 = self.tangent_basis()
        scale = np.exp(theta[..., 0])
        normal = np.asarray(self.normal) + theta[..., 1:2] * e1 + theta[..., 2:3] * e2
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        return self.fx * scale, self.fy * scale, normal

    def offset_of(self, fx: float, fy: float, normal: FloatArray) -> FloatArray:
        """theta of another camera relative to this one (its inverse of `shifted`)."""
        e1, e2 = self.tangent_basis()
        n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
        along = n @ np.asarray(self.normal)
        return np.array([0.5 * np.log(fx * fy / (self.fx * self.fy)), (n @ e1) / along, (n @ e2) / along])


def _residuals(camera: ReferenceCamera, theta: FloatArray, tops: FloatArray, bottoms: FloatArray) -> FloatArray:
    """(..., P, 2) direction residual (px) and log implied height of P people, for thetas (..., 3).

    The implied height is in units of the camera height (rho = 1): only differences between people are used.
    NaN where a person cannot be read (ankle at or above the horizon, a segment pointing away from v).
    """
    fx, fy, normal = camera.shifted(theta)
    fx, fy = np.asarray(fx)[..., None], np.asarray(fy)[..., None]
    n = normal[..., None, :]
    v = np.stack((fx * n[..., 0] + camera.cx * n[..., 2], fy * n[..., 1] + camera.cy * n[..., 2], n[..., 2]), -1)
    b = np.concatenate((bottoms, np.ones(bottoms.shape[:-1] + (1,))), -1)
    t = np.concatenate((tops, np.ones(tops.shape[:-1] + (1,))), -1)
    line = np.cross(b, v)
    direction = np.sum(line * t, -1) / np.hypot(line[..., 0], line[..., 1])

    # The ankle's ground point at camera height 1: X_b = s K^-1 b with s = -1 / (N . K^-1 b); the height is where
    # the shoulder's ray passes closest to the vertical X_b + h N.
    def ray(p: FloatArray) -> FloatArray:
        x, y = (p[..., 0] - camera.cx) / fx, (p[..., 1] - camera.cy) / fy
        return np.stack((x, y, np.ones_like(x)), -1)

    ray_b, ray_t = ray(b), ray(t)
    along = np.sum(ray_b * n, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ground = ray_b * np.where(along < 0, -1.0 / along, np.nan)[..., None]
        nr, rr = np.sum(ray_t * n, -1), np.sum(ray_t * ray_t, -1)
        nx, rx = np.sum(ground * n, -1), np.sum(ray_t * ground, -1)
        height = (-nx * rr + nr * rx) / (rr - nr * nr)
        log_height = np.where(height > 0, np.log(height), np.nan)
    return np.stack((direction, log_height), -1)


@dataclass(frozen=True)
class FrameEvidence:
    """What one frame says about the camera's offset theta from the reference camera."""

    score: FloatArray  # (3,)
    information: FloatArray  # (3, 3)
    people: int


EMPTY_EVIDENCE = FrameEvidence(np.zeros(3), np.zeros((3, 3)), 0)


def _huber(z: FloatArray) -> FloatArray:
    return np.clip(z, -HUBER_C, HUBER_C)


def _adult_heights(
    log_heights: FloatArray, sigma: FloatArray, frame_index: np.ndarray, frames: int, expected: float
) -> FloatArray:
    """Per frame, the log implied height of its typical adult: from the calibration's expectation, a few steps
    of a mean over the people within HEIGHT_REJECT_Z of the current location (children, sitting people and a
    group of them are left out once the location is the adults'); frames with no one near keep the expectation."""
    centre = np.full(frames, float(expected))
    for _ in range(3):
        near = np.abs(log_heights - centre[frame_index]) <= HEIGHT_REJECT_Z * sigma
        w = np.where(near, 1.0 / sigma**2, 0.0)
        total = np.bincount(frame_index, w, minlength=frames)
        mean = np.bincount(frame_index, w * np.where(near, log_heights, 0.0), minlength=frames)
        centre = np.where(total > 0, mean / np.maximum(total, 1e-300), centre)
    return centre


def frames_evidence(
    camera: ReferenceCamera, tops_px: FloatArray, bottoms_px: FloatArray, frame_index: np.ndarray, frames: int
) -> list[FrameEvidence]:
    """Per-frame evidence for `frames` frames whose people are given together (frame_index: each person's frame).

    One vectorised pass over every person of a measuring job's batch: the residuals, their derivatives in theta
    (forward differences) and in the four pixel coordinates (keypoint noise), then sums per frame.
    """
    tops = np.asarray(tops_px, dtype=float).reshape(-1, 2)
    bottoms = np.asarray(bottoms_px, dtype=float).reshape(-1, 2)
    frame_index = np.asarray(frame_index, dtype=int)
    if len(tops) == 0:
        return [EMPTY_EVIDENCE] * frames
    long_enough = np.hypot(*(tops - bottoms).T) >= MIN_SEGMENT_PX
    tops, bottoms, frame_index = tops[long_enough], bottoms[long_enough], frame_index[long_enough]
    thetas = np.vstack((np.zeros(3), _THETA_STEP * np.eye(3)))
    r = _residuals(camera, thetas, tops[None], bottoms[None])  # (4, P, 2)
    base, jacobian = r[0], (r[1:] - r[0]) / _THETA_STEP  # (P, 2), (3, P, 2)
    # Keypoint noise through each residual: sum over the four pixel coordinates of the squared derivative.
    variance = np.zeros_like(base)
    for which in range(4):
        t, b = tops.copy(), bottoms.copy()
        (t if which < 2 else b)[:, which % 2] += _PIXEL_STEP
        moved = _residuals(camera, np.zeros((1, 3)), t[None], b[None])[0]
        variance += ((moved - base) / _PIXEL_STEP) ** 2
    # Person-level spread: a lean moves the shoulders sideways by lean x segment length; heights vary.
    length = np.hypot(*(tops - bottoms).T)
    person = np.stack(((camera.lean_rad * length) ** 2, np.full(len(length), camera.height_spread**2)), -1)
    sigma = np.sqrt(camera.noise_px**2 * variance + person)
    ok = np.all(np.isfinite(base), -1) & np.all(np.isfinite(jacobian), axis=(0, 2)) & np.all(sigma > 0, -1)
    base, jacobian, sigma, frame_index = base[ok], jacobian[:, ok], sigma[ok], frame_index[ok]
    # Heights are relative to the frame's typical adult: subtract the per-frame location from the residual and
    # its (inverse-variance weighted) mean from the Jacobian, which profiles the nuisance out.
    weights = 1.0 / sigma[:, 1] ** 2
    centre = _adult_heights(base[:, 1], sigma[:, 1], frame_index, frames, camera.log_height)
    base = base.copy()
    base[:, 1] -= centre[frame_index]
    total_w = np.bincount(frame_index, weights, minlength=frames)
    jacobian = jacobian.copy()
    for p in range(3):
        mean = np.bincount(frame_index, weights * jacobian[p, :, 1], minlength=frames) / np.maximum(total_w, 1e-300)
        jacobian[p, :, 1] -= mean[frame_index]
    counts = np.bincount(frame_index, minlength=frames)
    singles = counts[frame_index] < 2  # one person: no height relative to others
    jacobian[:, singles, 1] = 0.0
    z = base / sigma
    zj = jacobian / sigma[None]  # (3, P, 2) standardised Jacobian
    scores = np.zeros((frames, 3))
    information = np.zeros((frames, 3, 3))
    psi = np.stack((_huber(z[:, 0]), np.where(z[:, 1] >= -HEIGHT_REJECT_Z, _huber(z[:, 1]), 0.0)), -1)
    person_score = -np.einsum("qpc,pc->pq", zj, psi)  # (P, 3)
    person_info = np.einsum("qpc,rpc->pqr", zj, zj)  # (P, 3, 3)
    np.add.at(scores, frame_index, person_score)
    np.add.at(information, frame_index, person_info)
    return [FrameEvidence(scores[k], information[k], int(counts[k])) for k in range(frames)]


WINDOW_FRAMES = 64
# Window lengths whose variance inflation is tracked; a candidate window uses the next tracked length up.
LENGTHS = (1, 2, 4, 8, 16, 32, 64)
MIN_REFERENCE_FRAMES = 30
MIN_FRAMES_AFTER = 3
REFERENCE_HALF_LIFE_FRAMES = 3600.0
INFLATION_HALF_LIFE_FRAMES = 3600.0
# The inflation before the reference has said anything, and its weight in windows. The same person seen in every
# frame of a window would give m; the street of bench.movement (2 fps, people in view for about 30 s, persistent
# leans) measured 0.6-0.7 at m = 1, 1.5-2.1 at m = 4, 4.3-6.2 at m = 16 and 9-12 at m = 64 over 25 minutes: the
# prior lies above all of them.
PRIOR_INFLATION = tuple(1.2 + 0.2 * m for m in LENGTHS)
PRIOR_WEIGHT = 20.0
# Set on measured false alarms (`posemetry bench movement`, README): the highest statistic of a static street camera
# over 50 minutes ranged from 17 to 32.5 in eight runs (30 gave 2 false moves in 2.4 hours); moves that matter reach
# 40-60 within seconds.
THRESHOLD = 38.0
# g_j within this of the best (chi-square(3) at 99 %), or at least this share of it, is in the change point's
# confidence set.
CHANGE_POINT_MARGIN = float(chi2.ppf(0.99, 3))
CHANGE_POINT_SHARE = 0.5
# The largest change of theta (log focal scale, tilts in radians) a newer calibration may bring for the test to be
# moved onto it rather than started again: 5 % in focal length, 2.9 degrees of tilt (second-order error 0.1 %).
# Solves of one epoch differ by more only while they rest on few people; a solve that pools a move's first frames
# with thousands before it moves far less.
REBASE_LIMIT = 0.05
# The test's parameters hold no principal point, so a rebase cannot move the scores onto a newer calibration whose
# principal point moved (the geometry estimates it, with a prior of 9 % of the image height, and an epoch's first
# solves on a few dozen people place it tens of pixels from later ones): beyond this share of the focal length the
# test starts again. On a static street with a first reference whose cy was 45-80 px off (f = 1400 px), rebasing
# raised false moves in 1-2 of 8 runs; at 20-30 px in none.
REBASE_PRINCIPAL_POINT_LIMIT = 0.015


@dataclass(frozen=True)
class Alarm:
    """A detected move: the change point (the first frame judged to be from the new view) and the statistic."""

    frame_id: bytes
    timestamp_s: float
    statistic: float
    offset: FloatArray
    """The estimated change of theta at the change point (log focal scale, tilts in radians)."""


def _inverse_sqrt(matrices: FloatArray) -> FloatArray:
    """Pseudo-inverse square roots of a stack of symmetric positive semi-definite matrices."""
    values, vectors = np.linalg.eigh(matrices)
    floor = 1e-10 * np.maximum(values[..., -1:], 1e-300)
    inv = np.where(values > floor, 1.0 / np.sqrt(np.maximum(values, floor)), 0.0)
    return np.einsum("...ij,...j,...kj->...ik", vectors, inv, vectors)


def _length_slot(m: np.ndarray) -> np.ndarray:
    return np.searchsorted(np.asarray(LENGTHS), m)


@dataclass
class MovementMonitor:
    """The sequential test's state for one camera and epoch (see the module doc).

    `scores`/`information` keep the last 2 x WINDOW_FRAMES frames: the newest WINDOW_FRAMES are the test window,
    the older ones are already part of the reference and serve to measure the variance inflation of windows.
    """

    camera: ReferenceCamera
    ref_score: FloatArray
    ref_information: FloatArray
    ref_frames: float
    inflation_sum: FloatArray  # (len(LENGTHS), 3, 3): forgotten sums of whitened window scores' outer products
    inflation_weight: FloatArray  # (len(LENGTHS),)
    scores: FloatArray  # (n, 3), oldest first
    information: FloatArray  # (n, 3, 3)
    frame_ids: list[bytes]
    timestamps_s: FloatArray
    last_statistic: float = 0.0

    @classmethod
    def start(cls, camera: ReferenceCamera) -> MovementMonitor:
        k = len(LENGTHS)
        return cls(
            camera,
            np.zeros(3),
            np.zeros((3, 3)),
            0.0,
            np.zeros((k, 3, 3)),
            np.zeros(k),
            np.zeros((0, 3)),
            np.zeros((0, 3, 3)),
            [],
            np.zeros(0),
        )

    def to_bytes(self) -> bytes:
        """The whole state, its reference camera included, as bytes to keep between measuring jobs."""
        arrays = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("camera", "frame_ids")}
        c = self.camera
        camera = np.array([c.fx, c.fy, c.cx, c.cy, *c.normal, c.noise_px, c.height_spread, c.lean_rad, c.log_height])
        buffer = io.BytesIO()
        np.savez(buffer, camera=camera, frame_ids=np.array([i.hex() for i in self.frame_ids], dtype=str), **arrays)
        return buffer.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> MovementMonitor:
        with np.load(io.BytesIO(data), allow_pickle=False) as stored:
            values = {name: stored[name] for name in stored.files}
        fx, fy, cx, cy, n0, n1, n2, noise, spread, lean, log_height = (float(v) for v in values.pop("camera"))
        camera = ReferenceCamera(fx, fy, cx, cy, (n0, n1, n2), noise, spread, log_height, lean)
        frame_ids = [bytes.fromhex(str(i)) for i in values.pop("frame_ids")]
        values["ref_frames"] = float(values["ref_frames"])
        values["last_statistic"] = float(values["last_statistic"])
        return cls(camera=camera, frame_ids=frame_ids, **values)

    def rebased(self, camera: ReferenceCamera) -> MovementMonitor:
        """The same test against another reference camera (a newer calibration of the same epoch).

        Starting again would build the new reference from whatever frames come next, which absorbs a move made
        just before the new version became current. Instead every kept score is moved to the new reference: to
        first order a score is gamma I (theta - theta_ref), so a reference shifted by d takes gamma I d off each
        (the information and the variance-inflation windows, centred already, stay as they are). First order only
        holds for a small shift: a reference further than REBASE_LIMIT from the new one (the rough first solves of
        an epoch, tens of people), or whose principal point moved (REBASE_PRINCIPAL_POINT_LIMIT), is dropped and the
        test starts again.
        """
        d = self.camera.offset_of(camera.fx, camera.fy, np.asarray(camera.normal))
        old = self.camera
        principal_point_shift = max(abs(camera.cx - old.cx) / camera.fx, abs(camera.cy - old.cy) / camera.fy)
        if np.max(np.abs(d)) > REBASE_LIMIT or principal_point_shift > REBASE_PRINCIPAL_POINT_LIMIT:
            return MovementMonitor.start(camera)
        return replace(
            self,
            camera=camera,
            ref_score=self.ref_score - HUBER_GAMMA * self.ref_information @ d,
            scores=self.scores - HUBER_GAMMA * self.information @ d,
        )

    @property
    def window_start(self) -> int:
        return max(0, len(self.scores) - WINDOW_FRAMES)

    def reference_offset(self) -> FloatArray:
        """The camera's offset from the reference camera before the window (scores' units: gamma x theta)."""
        return np.linalg.pinv(self.ref_information, rcond=1e-10, hermitian=True) @ self.ref_score

    def inflation(self) -> FloatArray:
        """(len(LENGTHS), 3, 3) variance inflation of window sums, whitened: the prior blended with measurements,
        never below the identity (the test is never more sensitive than independent frames would allow)."""
        prior = np.asarray(PRIOR_INFLATION)[:, None, None] * np.eye(3)
        blended = (PRIOR_WEIGHT * prior + self.inflation_sum) / (PRIOR_WEIGHT + self.inflation_weight)[:, None, None]
        values, vectors = np.linalg.eigh(blended)
        return np.einsum("...ij,...j,...kj->...ik", vectors, np.maximum(values, 1.0), vectors)

    def _measure_inflation(self, ends: np.ndarray) -> None:
        """Whitened sums of the windows of every tracked length that end at history positions `ends` (frames that
        just joined the reference), centred on the reference's offset; folded into the forgotten sums."""
        offset = self.reference_offset()
        cum_s = np.concatenate((np.zeros((1, 3)), np.cumsum(self.scores, 0)))
        cum_i = np.concatenate((np.zeros((1, 3, 3)), np.cumsum(self.information, 0)))
        slots, stops, starts = [], [], []
        for slot, m in enumerate(LENGTHS):
            usable = ends[ends + 1 >= m]
            slots += [slot] * len(usable)
            stops.append(usable + 1)
            starts.append(usable + 1 - m)
        if not slots:
            return
        stop, start, slot_of = np.concatenate(stops), np.concatenate(starts), np.asarray(slots)
        s = cum_s[stop] - cum_s[start]
        i = cum_i[stop] - cum_i[start]
        w = np.einsum("kab,kb->ka", _inverse_sqrt(HUBER_KAPPA * i), s - i @ offset)
        # Windows of length m overlap their neighbours: each counts 1/m, so the weight counts independent windows.
        # Forgetting runs per frame: a window ending `age` frames before the newest leaving frame is worth decay^age.
        decay = 0.5 ** (1.0 / INFLATION_HALF_LIFE_FRAMES)
        lengths = np.asarray(LENGTHS)[slot_of]
        weights = decay ** (ends[-1] + 1 - stop).astype(float) / lengths
        total = decay ** len(ends)
        self.inflation_sum *= total
        self.inflation_weight *= total
        np.add.at(self.inflation_sum, slot_of, weights[:, None, None] * w[:, :, None] * w[:, None, :])
        np.add.at(self.inflation_weight, slot_of, weights)

    def statistic(self) -> tuple[float, int]:
        """(max_j g_j over candidates with MIN_FRAMES_AFTER frames after them, the change point): (0, -1) when
        untestable. A camera that moved stays moved, while a single odd frame (a burst of bad detections) does not,
        hence the minimum.

        The change point is the earliest candidate whose g_j comes within CHANGE_POINT_MARGIN of the best, or
        reaches CHANGE_POINT_SHARE of it (whichever reaches further back): a generous confidence set for the first
        frame of the new view, dated at its start. Frames of a large move saturate
        the clipped scores, so g_j is flat over the frames after the move and its maximum alone can land well
        after it; frames dated after the change point are measured again in the new epoch, so erring early costs
        a few frames of the old view re-measured, erring late would leave new-view frames measured with the old
        calibration."""
        g, lengths, positions = self._candidates()
        if len(g) == 0:
            return 0.0, -1
        sustained = lengths >= MIN_FRAMES_AFTER
        if not sustained.any():
            return 0.0, -1
        near_best = np.flatnonzero(g >= min(g.max() - CHANGE_POINT_MARGIN, CHANGE_POINT_SHARE * g.max()))
        return float(g[sustained].max()), int(positions[near_best[0]])

    def _candidates(self) -> tuple[FloatArray, np.ndarray, np.ndarray]:
        """g_j, the window length after j, and j's history position, for every testable candidate j."""
        first = self.window_start
        scores, information = self.scores[first:], self.information[first:]
        n = len(scores)
        at = np.flatnonzero(self.ref_frames + np.arange(n) >= MIN_REFERENCE_FRAMES)
        if len(at) == 0:
            return np.zeros(0), np.zeros(0, int), np.zeros(0, int)
        after_s = np.cumsum(scores[::-1], 0)[::-1][at]
        after_i = np.cumsum(information[::-1], 0)[::-1][at]
        before_s = (self.ref_score + np.concatenate((np.zeros((1, 3)), np.cumsum(scores, 0)[:-1])))[at]
        before_i = (self.ref_information + np.concatenate((np.zeros((1, 3, 3)), np.cumsum(information, 0)[:-1])))[at]
        lengths = n - at
        before_inv = np.linalg.inv(before_i)
        u = after_s - np.einsum("jab,jbc,jc->ja", after_i, before_inv, before_s)
        # Var(u) = kappa [A^1/2 Phi(m) A^1/2 + A B^-1 Var(S_B) B^-1 A] (A after, B before): the second term, the
        # reference's own noise, is small once B >> A; its inflation is taken as the longest window's.
        phi = self.inflation()
        values, vectors = np.linalg.eigh(after_i)
        half = np.einsum("...ij,...j,...kj->...ik", vectors, np.sqrt(np.maximum(values, 0.0)), vectors)
        covariance = half @ phi[_length_slot(lengths)] @ half
        covariance += after_i @ before_inv @ after_i * (np.trace(phi[-1]) / 3.0)
        # u lies in the range of A, so a ridge on the null space of a rank-deficient A (few people) changes nothing.
        ridge = (1e-9 * np.trace(covariance, axis1=1, axis2=2) + 1e-300)[:, None, None] * np.eye(3)
        g = np.einsum("ja,ja->j", u, np.linalg.solve(HUBER_KAPPA * (covariance + ridge), u[..., None])[..., 0])
        return g, lengths, first + at

    def offset_after(self, position: int) -> FloatArray:
        """The estimated change of theta from the frames before history position `position` to those after."""
        scores, information = self.scores[position:], self.information[position:]
        before_s = self.ref_score + self.scores[self.window_start : position].sum(0)
        before_i = self.ref_information + self.information[self.window_start : position].sum(0)
        after_i = information.sum(0)
        u = scores.sum(0) - after_i @ np.linalg.solve(before_i, before_s)
        return np.linalg.pinv(after_i, rcond=1e-10, hermitian=True) @ u / HUBER_GAMMA

    def observe(self, evidence: list[FrameEvidence], frame_ids: list[bytes], timestamps_s: list[float]) -> Alarm | None:
        """Add a batch of measured frames (oldest first) and test once; an Alarm when the test crosses THRESHOLD
        (the caller then starts a new monitor). Frames without usable people are skipped."""
        kept = [k for k, e in enumerate(evidence) if e.people > 0]
        if not kept:
            return None
        self.scores = np.vstack((self.scores, np.array([evidence[k].score for k in kept])))
        self.information = np.concatenate((self.information, np.array([evidence[k].information for k in kept])))
        self.frame_ids += [frame_ids[k] for k in kept]
        self.timestamps_s = np.concatenate((self.timestamps_s, np.array([timestamps_s[k] for k in kept], float)))
        leaving = np.arange(len(self.scores) - len(kept) - WINDOW_FRAMES, len(self.scores) - WINDOW_FRAMES)
        leaving = leaving[leaving >= 0]
        if len(leaving):
            # Frames leaving the window join the reference, which forgets slowly (REFERENCE_HALF_LIFE_FRAMES).
            forget = 0.5 ** (1.0 / REFERENCE_HALF_LIFE_FRAMES)
            powers = forget ** np.arange(len(leaving) - 1, -1, -1.0)
            decay = forget ** len(leaving)
            self.ref_score = decay * self.ref_score + powers @ self.scores[leaving]
            leaving_information = np.einsum("k,kab->ab", powers, self.information[leaving])
            self.ref_information = decay * self.ref_information + leaving_information
            self.ref_frames = decay * self.ref_frames + powers.sum()
            if self.ref_frames >= MIN_REFERENCE_FRAMES:
                self._measure_inflation(leaving)
        keep = len(self.scores) - 2 * WINDOW_FRAMES
        if keep > 0:
            self.scores, self.information = self.scores[keep:], self.information[keep:]
            self.frame_ids = self.frame_ids[keep:]
            self.timestamps_s = self.timestamps_s[keep:]
        g, j = self.statistic()
        self.last_statistic = g
        if g <= THRESHOLD:
            return None
        return Alarm(self.frame_ids[j], float(self.timestamps_s[j]), g, self.offset_after(j))
