"""The generative model the refinement fits: what a camera with its nuisances makes of upright people.

Everything is in frame-normalised coordinates (service.geometry.camera.ImageFrame, centred on the image
centre or on a given principal point, scaled by (W + H) / 4). Observation o of individual t(o):

    a_o          latent ankle-centre keypoint (distorted, as the pose model would report it without noise)
    u_o          = c + U_k(a_o - c)                 undistorted by the division model about the principal point c
    X_B          = -rho / (N . r) r,  r = ((u_o - c)_x / fx, (u_o - c)_y / fy, 1)     the ankle on the plane
    X_T          = X_B + h_t N                      the shoulder centre straight above it
    s_o          = c + D_k(fx X_T,x / Z, fy X_T,y / Z)       its distorted image
    d_o          = R(a_t) (s_o - a_o)                  the segment turned by the individual's lean a_t
    top_o        = a_o + d_o + beta d_o / |d_o|         plus the pose model's bias along the body

and the measured ankle and shoulder centres are a_o and top_o plus Gaussian noise: sigma on the ankle,
sqrt(sigma^2 + (lambda l_o)^2) on the shoulder, where l_o is the segment's length (walking people lean, so the
shoulders scatter in proportion to the person's size). Each individual also has a lean a_t ~ N(0, lambda_t),
shared by their observations (a walking posture does not change from frame to frame, so thirty observations
of one leaning person are one draw of a lean, like one draw of a height): the image segment from a_o to s_o
turned about the ankle by a_t radians. A lean along the segment is a height change (the height absorbs it),
so the turn is the lean's only free part.

The lean is an angle in the image, not in the world, on purpose. Its spread lambda_t is measured in the image
(the direction residuals over segment length, posterior.estimate_noise_and_lean), and people leave one
direction of the camera undetermined: the principal point's offset across the horizon, traded against f and
the tilt, keeps the vertical vanishing point, the horizon and every person's image. A world lean's image size
depends on that direction (a vertical's image foreshortens with the angle between the ray and the vertical, a
sideways lean does not), so a prior on world radians has a gradient along the flat direction: the fit shrinks
every individual's lean by steepening the view, until the principal point's prior stops it. On a street crowd
seen at 2 fps for three minutes (bench.moving_camera: 35 people with 2 degree leans, linked into 133 tracks)
that pulled f 9 % short and cy 135 px up. In the image the prior costs the same for every camera along the
flat direction, so it cannot pull. The price is small: a constant world lean seen across the view turns its
image by a slightly varying angle, and the per-observation noise keeps the rest.

Heights h_t = mu (1 + delta_t), delta_t ~ N(0, sigma_h / mu0), belong to individuals, not to observations: one
person seen in thirty frames is one draw of a height, not thirty (on the Oxford Town Centre clip a few short
people walking near the camera otherwise tilt the whole ground by 2 degrees). The spread is relative on
purpose: people's images fix only h / rho, so scaling rho and every height together changes no residual, and
an absolute spread would reward the smaller world (a jointly fitted scale then shrinks by the fitted heights'
relative variance times the mean-height prior's information: 8 % on a 100-person scene). With delta relative
only mu's prior (or a known camera height) sets the scale.

Camera parameters theta, each present only when it is estimated (`Layout`):

    log_f, aspect    fx = e^log_f, fy = fx e^aspect (square pixels: fy/fx is never exactly 1; a consider
                     parameter, so fx = fy is reported with the aspect's prior in the covariance)
    log_fy           instead of aspect when fx and fy are free
    cx, cy           principal point offset from the frame's centre, with a prior unless given
    t1, t2           the normal N = normalise(N0 + t1 e1 + t2 e2) around the starting normal
    log_rho          rho: the camera's height above the plane of the ankle keypoints
    k                division-model distortion about c: estimated when the evidence selects it, otherwise a
                     consider parameter with the prior of a distortion too small to detect
    bias             beta, the pose model's keypoint bias along the body (normalised units), with a prior;
                     a consider parameter (Layout.considered): held at 0, its prior carried in the covariance
    log_mu           the population's mean height, mu = mu0 e^log_mu, with a prior

People alone determine only the vertical vanishing point, the horizon and h / rho (see
service.geometry.observability): the priors on the principal point, aspect, bias and mean height are what
makes the fit well posed, and they carry their spread into every covariance instead of being assumed away.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .vec import FloatArray, cross

PARAMETER_ORDER = ("log_f", "log_fy", "aspect", "cx", "cy", "t1", "t2", "log_rho", "k", "bias", "log_mu")


def tangent_basis(normal: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors orthogonal to normal and to each other."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = cross(normal, helper)
    t1 /= np.linalg.norm(t1)
    return t1, cross(normal, t1)


@dataclass(frozen=True)
class Priors:
    """Gaussian priors (1-sigma) on the nuisance parameters, in the model's units; None: not estimated."""

    principal_point_n: float | None
    aspect: float | None
    bias_n: float | None
    distortion_k: float | None  # spread of undetected division-model distortion; None: no lens beyond the given
    log_mean_height: float | None  # None: the mean height is exact
    height_std_rel: float  # individual heights' spread relative to the mean
    lean_rad: float = 0.0  # spread of individuals' lean, an angle in the image (radians); 0: not modelled
    # (metres above the ankle plane, 1-sigma): an installer-known camera height, already minus the ankle height.
    camera_height_m: tuple[float, float] | None = None


@dataclass
class Layout:
    """Which parameters theta holds, their prior widths, and the values of those held fixed."""

    names: tuple[str, ...]
    prior_std: FloatArray  # per entry of theta; inf where there is no prior
    fixed: dict[str, float] = field(default_factory=dict)
    # Parameters held at their prior mean (0) in the estimate but carried in the covariance ("consider"
    # parameters): nearly degenerate with others, they would otherwise soak up any unmodelled trend.
    considered: frozenset[str] = frozenset()

    def __post_init__(self) -> None:
        self.index = {name: i for i, name in enumerate(self.names)}
        self.estimated = np.array([name not in self.considered for name in self.names], dtype=bool)

    @classmethod
    def build(cls, equal_focal: bool, focal_n: tuple[float, float] | None, priors: Priors, estimate_k: bool) -> Layout:
        names: list[str] = []
        std: list[float] = []
        fixed: dict[str, float] = {}

        def add(name: str, prior: float | None = None) -> None:
            names.append(name)
            std.append(np.inf if prior is None else prior)

        if focal_n is not None:
            fixed["log_f"], fixed["log_fy"] = float(np.log(focal_n[0])), float(np.log(focal_n[1]))
        elif equal_focal:
            add("log_f")
            if priors.aspect is not None:
                add("aspect", priors.aspect)
        else:
            add("log_f")
            add("log_fy")
        if priors.principal_point_n is not None:
            add("cx", priors.principal_point_n)
            add("cy", priors.principal_point_n)
        add("t1")
        add("t2")
        add("log_rho")
        if estimate_k:
            add("k")
        elif priors.distortion_k is not None:
            add("k", priors.distortion_k)
        if priors.bias_n is not None:
            add("bias", priors.bias_n)
        if priors.log_mean_height is not None:
            add("log_mu", priors.log_mean_height)
        considered = {"bias", "aspect"} | (set() if estimate_k else {"k"})
        return cls(tuple(names), np.array(std), fixed, frozenset(considered & set(names)))

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        """A box that keeps the search physical (and exp() finite) on hopeless inputs."""
        box = {
            "log_f": (np.log(0.02), np.log(200.0)),
            "log_fy": (np.log(0.02), np.log(200.0)),
            "aspect": (-0.5, 0.5),
            "cx": (-2.0, 2.0),
            "cy": (-2.0, 2.0),
            "t1": (-2.0, 2.0),
            "t2": (-2.0, 2.0),
            "log_rho": (np.log(1e-3), np.log(1e5)),
            "k": (-1.0, 1.0),
            "bias": (-0.5, 0.5),
            "log_mu": (-1.0, 1.0),
        }
        lower, upper = zip(*(box[name] for name in self.names), strict=True) if self.names else ((), ())
        return np.array(lower, dtype=np.float64), np.array(upper, dtype=np.float64)

    def value(self, theta: FloatArray, name: str) -> FloatArray:
        """(K,) values of one parameter over a batch of theta rows (K, p); its fixed value (or 0) if absent."""
        if name in self.index:
            return theta[:, self.index[name]]
        return np.full(len(theta), self.fixed.get(name, 0.0))


@dataclass(frozen=True)
class CameraBatch:
    """K cameras (one per row of theta), shaped to broadcast against (K, n) observation arrays."""

    fx: FloatArray  # (K, 1)
    fy: FloatArray
    c: FloatArray  # (K, 1, 2)
    normal: FloatArray  # (K, 1, 3)
    rho: FloatArray  # (K, 1)
    k: FloatArray  # (K, 1)
    bias: FloatArray  # (K, 1)
    mu: FloatArray  # (K, 1)


def unpack(layout: Layout, theta: FloatArray, normal0: FloatArray, mu0: float) -> CameraBatch:
    """Cameras for a (K, p) batch of parameter rows."""
    e1, e2 = tangent_basis(normal0)
    log_f = layout.value(theta, "log_f")
    if "log_fy" in layout.index or "log_fy" in layout.fixed:
        log_fy = layout.value(theta, "log_fy")
    else:
        log_fy = log_f + layout.value(theta, "aspect")
    n = normal0 + layout.value(theta, "t1")[:, None] * e1 + layout.value(theta, "t2")[:, None] * e2
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    col = np.stack((layout.value(theta, "cx"), layout.value(theta, "cy")), -1)
    return CameraBatch(
        fx=np.exp(log_f)[:, None],
        fy=np.exp(log_fy)[:, None],
        c=col[:, None, :],
        normal=n[:, None, :],
        rho=np.exp(layout.value(theta, "log_rho"))[:, None],
        k=layout.value(theta, "k")[:, None],
        bias=layout.value(theta, "bias")[:, None],
        mu=mu0 * np.exp(layout.value(theta, "log_mu"))[:, None],
    )


@dataclass(frozen=True)
class _Pass:
    """One forward pass through the model with the intermediates the chain rule reuses (`_chain`): the
    Jacobians cost a few more array operations on these instead of another evaluation per parameter."""

    rel: FloatArray  # (K, n, 2) latent ankle about the principal point
    sq_rel: FloatArray  # (K, n, 1) its squared radius
    spread: FloatArray  # (K, n, 1) 1 + k |rel|^2, the division model's denominator
    undist: FloatArray  # (K, n, 2)
    rx: FloatArray  # (K, n) the ankle's ray
    ry: FloatArray
    denom_raw: FloatArray  # (K, n) N . ray before the clamp
    t: FloatArray  # (K, n) the ray's length to the plane
    zt_raw: FloatArray  # (K, n) the shoulder's depth before the clamp
    zt: FloatArray
    top_u: FloatArray  # (K, n, 2) the shoulder's undistorted image about c
    sq_top: FloatArray  # (K, n, 1)
    disc_raw: FloatArray  # (K, n, 1) 1 - 4 k |top_u|^2 before the clamp
    root: FloatArray  # (K, n, 1) sqrt of the clamped disc
    gain: FloatArray  # (K, n, 1) 2 / (1 + root): distorted over undistorted radius
    cos: FloatArray | None  # (K, n) the lean's rotation, None when upright
    sin: FloatArray | None
    along: FloatArray  # (K, n, 2) the (turned) segment from ankle to shoulder
    length_raw: FloatArray  # (K, n, 1)
    length: FloatArray
    top: FloatArray  # (K, n, 2)


def _forward(cam: CameraBatch, ankles_n: FloatArray, heights_m: FloatArray, lean: FloatArray | None) -> _Pass:
    rel = ankles_n - cam.c
    sq_rel = np.sum(rel * rel, -1, keepdims=True)
    spread = 1.0 + cam.k[..., None] * sq_rel
    undist = rel / spread
    rx, ry = undist[..., 0] / cam.fx, undist[..., 1] / cam.fy
    n = cam.normal
    denom_raw = rx * n[..., 0] + ry * n[..., 1] + n[..., 2]
    t = -cam.rho / np.minimum(denom_raw, -1e-9)  # a ray that misses the ground
    xt = rx * t + heights_m * n[..., 0]
    yt = ry * t + heights_m * n[..., 1]
    zt_raw = t + heights_m * n[..., 2]
    zt = np.maximum(zt_raw, 1e-9)
    top_u = np.stack((cam.fx * xt / zt, cam.fy * yt / zt), -1)
    sq_top = np.sum(top_u * top_u, -1, keepdims=True)
    disc_raw = 1.0 - 4.0 * cam.k[..., None] * sq_top
    root = np.sqrt(np.maximum(disc_raw, 0.0))
    gain = 2.0 / (1.0 + root)
    along = cam.c + top_u * gain - ankles_n
    cos = sin = None
    if lean is not None:
        cos, sin = np.cos(lean), np.sin(lean)
        along = np.stack((cos * along[..., 0] - sin * along[..., 1], sin * along[..., 0] + cos * along[..., 1]), -1)
    length_raw = np.sqrt(np.sum(along * along, -1, keepdims=True))
    length = np.maximum(length_raw, 1e-12)
    top = ankles_n + along + cam.bias[..., None] * along / length
    return _Pass(
        rel, sq_rel, spread, undist, rx, ry, denom_raw, t, zt_raw, zt, top_u, sq_top, disc_raw, root, gain,
        cos, sin, along, length_raw, length, top,
    )  # fmt: skip


def predict(
    cam: CameraBatch, ankles_n: FloatArray, heights_m: FloatArray, lean: FloatArray | None = None
) -> FloatArray:
    """(K, n, 2) predicted (distorted, biased) shoulder centres of people standing on latent ankles (n, 2) or
    (K, n, 2) with heights (n,) or (K, n), their image segments turned about the ankle by `lean` ((K?, n)
    radians, or upright; see the module docstring for why the lean is an angle in the image)."""
    return _forward(cam, ankles_n, heights_m, lean).top


@dataclass(frozen=True)
class Observations:
    """Measured centres (normalised), their noise, and which individual each observation is."""

    tops_n: FloatArray  # (n, 2)
    bottoms_n: FloatArray  # (n, 2)
    ankle_std_n: FloatArray  # (n,)
    top_std_n: FloatArray  # (n,)
    track: np.ndarray  # (n,) int in [0, T)
    tracks: int

    def residuals(self, cam: CameraBatch, ankles_n: FloatArray, person: FloatArray) -> FloatArray:
        """(K, n, 4) whitened residuals (ankle 2, shoulder 2) of people whose individual parameters are
        `person` ((K?, n, q): the height deviation, h = mu (1 + deviation), then the lean, if
        modelled, radians in the image)."""
        lean = person[..., 1] if person.shape[-1] == 2 else None
        top = predict(cam, ankles_n, cam.mu * (1.0 + person[..., 0]), lean)
        ankle_r = np.broadcast_to((ankles_n - self.bottoms_n) / self.ankle_std_n[:, None], top.shape)
        return np.concatenate((ankle_r, (top - self.tops_n) / self.top_std_n[:, None]), -1)


def _chain(cam: CameraBatch, f: _Pass, heights_m: FloatArray) -> dict[str, FloatArray]:
    """d top / d (each of the model's natural quantities) for one camera (K = 1): (2, n) arrays, the shoulder's
    two components over the observations (the component first keeps every operation on contiguous rows).

    Reverse accumulation from the shoulder: top has two components, so carrying d top / d (intermediate) back
    through the pass costs a few array operations per step however many parameters there are. Where a clamp
    holds a quantity its derivative is 0 (a ray that misses the ground, a shoulder behind the camera, a point
    beyond the lens's horizon, a zero-length segment), as a step that stays inside the clamp would see it.
    """
    fx, fy, k, bias = (float(x[0, 0]) for x in (cam.fx, cam.fy, cam.k, cam.bias))
    n0, n1, n2 = (float(x) for x in cam.normal[0, 0])
    e_x, e_y = np.array([[1.0], [0.0]]), np.array([[0.0], [1.0]])
    # top = a + d + bias d / |d|: d top / d d = (1 + s) I - s u u^T, s = bias / |d|, u = d / |d|.
    d_x, d_y = f.along[0, :, 0], f.along[0, :, 1]
    length = f.length[0, :, 0]
    unit = np.stack((d_x, d_y)) / length
    s = bias / length
    turn = np.where(f.length_raw[0, :, 0] > 1e-12, s, 0.0)
    g_dx = -(turn * unit[0]) * unit + (1.0 + s) * e_x
    g_dy = -(turn * unit[1]) * unit + (1.0 + s) * e_y
    out: dict[str, FloatArray] = {"bias": unit}
    # d = R(lean) b, b = c + gain top_u - a: d d / d lean = (-d_y, d_x), d d / d b = R.
    if f.cos is not None and f.sin is not None:
        cos, sin = f.cos[0], f.sin[0]
        out["lean"] = g_dy * d_x - g_dx * d_y
        g_bx, g_by = g_dx * cos + g_dy * sin, g_dy * cos - g_dx * sin
    else:
        g_bx, g_by = g_dx, g_dy
    # gain = 2 / (1 + sqrt(disc)), disc = 1 - 4 k |top_u|^2
    p_x, p_y = f.top_u[0, :, 0], f.top_u[0, :, 1]
    inside = f.disc_raw[0, :, 0] > 0.0
    gain = f.gain[0, :, 0]
    d_gain = np.where(inside, -gain * gain / (4.0 * np.where(inside, f.root[0, :, 0], 1.0)), 0.0)  # d / d disc
    g_b_p = g_bx * p_x + g_by * p_y
    g_k = g_b_p * (d_gain * -4.0 * f.sq_top[0, :, 0])
    lens = g_b_p * (d_gain * -8.0 * k)
    g_px, g_py = gain * g_bx + lens * p_x, gain * g_by + lens * p_y
    # top_u = (fx X / Z, fy Y / Z)
    zt = f.zt[0]
    g_x, g_y = g_px * (fx / zt), g_py * (fy / zt)
    g_z = np.where(f.zt_raw[0] > 1e-9, -(g_px * p_x + g_py * p_y) / zt, 0.0)
    # (X, Y, Z) = t ray + h N
    t, rx, ry = f.t[0], f.rx[0], f.ry[0]
    h = np.broadcast_to(heights_m, f.t.shape)[0]
    g_t = g_x * rx + g_y * ry + g_z
    out["height"] = g_x * n0 + g_y * n1 + g_z * n2
    # t = -rho / (N . ray)
    out["log_rho"] = g_t * t
    denom = np.minimum(f.denom_raw[0], -1e-9)
    g_denom = np.where(f.denom_raw[0] < -1e-9, -g_t * (t / denom), 0.0)
    g_rx, g_ry = g_x * t + g_denom * n0, g_y * t + g_denom * n1
    out["normal"] = np.stack((g_x * h + g_denom * rx, g_y * h + g_denom * ry, g_z * h + g_denom))  # (3, 2, n)
    # ray = (undist_x / fx, undist_y / fy, 1)
    out["log_fx"] = g_px * p_x - g_rx * rx
    out["log_fy"] = g_py * p_y - g_ry * ry
    g_ux, g_uy = g_rx / fx, g_ry / fy
    # undist = rel / (1 + k |rel|^2), rel = a - c
    spread = f.spread[0, :, 0]
    g_u_u = g_ux * f.undist[0, :, 0] + g_uy * f.undist[0, :, 1]
    out["k"] = g_k - g_u_u * (f.sq_rel[0, :, 0] / spread)
    pull = g_u_u * (2.0 * k / spread)
    g_rel_x, g_rel_y = g_ux / spread - pull * f.rel[0, :, 0], g_uy / spread - pull * f.rel[0, :, 1]
    out["ankle_x"], out["ankle_y"] = e_x - g_bx + g_rel_x, e_y - g_by + g_rel_y
    out["cx"], out["cy"] = g_bx - g_rel_x, g_by - g_rel_y
    return out


@dataclass(frozen=True)
class Linearisation:
    """Whitened residuals of one camera and their exact Jacobians, in the block structure the fit exploits: an
    observation's ankle residual depends on its latent ankle alone, with weight 1 / ankle_std on each axis, so
    only the shoulder rows are stored (the full (n, 4, .) Jacobians are these below that diagonal block)."""

    r: FloatArray  # (n, 4) data residuals (ankle 2, shoulder 2)
    ankle_weight: FloatArray  # (n,) d (ankle residual) / d (latent ankle) on each axis
    j_theta: FloatArray  # (n, 2, p) shoulder rows, on the Layout's parameters
    j_ankle: FloatArray  # (n, 2, 2)
    j_person: FloatArray  # (n, 2, q)


def residuals_and_jacobians(
    layout: Layout,
    theta: FloatArray,
    normal0: FloatArray,
    mu0: float,
    obs: Observations,
    ankles_n: FloatArray,
    person: FloatArray,
) -> Linearisation:
    """Whitened residuals of one camera theta (p,) and their exact Jacobians on theta, on the latent ankles
    and on each observation's individual parameters `person` ((n, q), as in `Observations.residuals`).

    One pass and its chain rule instead of 2 (p + 2 + q) + 1 passes of central differences: the fit
    linearises every iteration, and the differences were most of its cost.
    """
    cam = unpack(layout, theta[None], normal0, mu0)
    lean = person[None, :, 1] if person.shape[-1] == 2 else None
    heights = cam.mu * (1.0 + person[None, :, 0])
    f = _forward(cam, ankles_n, heights, lean)
    g = _chain(cam, f, heights)
    # N = m / |m|, m = N0 + t1 e1 + t2 e2: dN/dt_i = (e_i - N (N . e_i)) / |m|.
    e1, e2 = tangent_basis(normal0)
    m = normal0 + layout.value(theta[None], "t1")[0] * e1 + layout.value(theta[None], "t2")[0] * e2
    normal, norm = m / np.linalg.norm(m), float(np.linalg.norm(m))
    split_fy = "log_fy" in layout.index or "log_fy" in layout.fixed
    columns = {
        "log_f": g["log_fx"] if split_fy else g["log_fx"] + g["log_fy"],
        "log_fy": g["log_fy"],
        "aspect": g["log_fy"],
        "cx": g["cx"],
        "cy": g["cy"],
        "t1": np.tensordot((e1 - normal * (normal @ e1)) / norm, g["normal"], 1),
        "t2": np.tensordot((e2 - normal * (normal @ e2)) / norm, g["normal"], 1),
        "log_rho": g["log_rho"],
        "k": g["k"],
        "bias": g["bias"],
        "log_mu": g["height"] * np.broadcast_to(heights, f.t.shape)[0],
    }
    top_w = 1.0 / obs.top_std_n

    def whitened(derivatives: list[FloatArray]) -> FloatArray:
        """(n, 2, m) from m (2, n) derivatives of the shoulder."""
        return np.stack([(d * top_w).T for d in derivatives], -1)

    own = [g["height"] * float(cam.mu[0, 0])] + ([g["lean"]] if lean is not None else [])
    ankle_r = (ankles_n - obs.bottoms_n) / obs.ankle_std_n[:, None]
    r = np.concatenate((ankle_r, (f.top[0] - obs.tops_n) / obs.top_std_n[:, None]), -1)
    return Linearisation(
        r,
        1.0 / obs.ankle_std_n,
        whitened([columns[name] for name in layout.names]),
        whitened([g["ankle_x"], g["ankle_y"]]),
        whitened(own),
    )
