"""Closed-form maximum-likelihood scale of a monocular SLAM map (seed 004; Engel, Sturm & Cremers,
"Camera-based navigation of a low-cost quadrocopter", IROS 2012, and "Scale-aware navigation of a
low-cost quadrocopter with a monocular camera", RAS 2014 -- the tum_ardrone method).

Model. Pairs of displacements over the same time interval: ``x_i`` from SLAM [SLAM units] and
``y_i`` from metric sensors [m] (rangefinder height, integrated velocity), both d-vectors in the
same frame. With the unknown true metric displacement ``mu_i``:

    x_i = s mu_i + n_x,  n_x ~ N(0, sigma_x^2 I)      (s: fgnav's scale, SLAM units per metre)
    y_i =   mu_i + n_y,  n_y ~ N(0, sigma_y^2 I)

Minimising the negative log-likelihood over the nuisance ``mu_i`` leaves

    L(s) = sum_i |x_i - s y_i|^2 / (2 (sigma_x^2 + s^2 sigma_y^2))
         = (A - 2 s C + s^2 B) / (2 (sigma_x^2 + s^2 sigma_y^2)),

with ``A = sum x.x``, ``B = sum y.y``, ``C = sum x.y``. ``dL/ds = 0`` gives the quadratic
``C sigma_y^2 s^2 + (B sigma_x^2 - A sigma_y^2) s - C sigma_x^2 = 0`` whose minimising root is

    s* = (A sigma_y^2 - B sigma_x^2 + sign(C) sqrt((A sigma_y^2 - B sigma_x^2)^2
          + 4 C^2 sigma_x^2 sigma_y^2)) / (2 C sigma_y^2).

This is Engel et al.'s ``lambda*`` with ``s_xx = sigma_y^2 A``, ``s_yy = sigma_x^2 B``,
``s_xy = sigma_x sigma_y C`` (their eq. for the scale; seed 004 lost the equation images). Its
limits: ``sigma_y -> 0`` gives ``C / B`` (least squares of x on exact y), ``sigma_x -> 0`` gives
``A / C``. The metric size of a SLAM unit is ``lambda = 1 / s`` [m per SLAM unit]. The
closed form is checked against a numerical minimisation of ``L`` in the tests.

The standard deviation of ``s`` is ``1 / sqrt(L''(s*))`` (Fisher information of the profile
likelihood, computed by a central difference).

Online use: the sums are accumulated; each new pair is gated (metric displacement at least
``min_metric_displacement``; once ``min_pairs_for_gating`` pairs are in, a pair whose normalised
residual ``|x - s y|^2 / (sigma_x^2 + s^2 sigma_y^2)`` exceeds the chi-square quantile
``gate_chi2`` for d degrees of freedom is rejected and counted). One estimator per SLAM session:
a map reset starts a new one (the scale of a monocular SLAM changes at every restart).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import project_to_so3, quat_wxyz_to_matrix
from fgnav.datasets.types import Flight

log = logging.getLogger(__name__)

#: Chi-square 99.7 % quantiles for 1, 2, 3 degrees of freedom (a 3-sigma gate).
CHI2_997 = {1: 8.81, 2: 11.62, 3: 13.93}


@dataclass(frozen=True)
class MLScaleOptions:
    """Options of :class:`MLScaleEstimator`.

    Attributes:
        sigma_slam: noise of each component of a SLAM displacement [SLAM units] (``sigma_x``).
        sigma_metric: noise of each component of a metric displacement [m] (``sigma_y``).
        min_metric_displacement: pairs with ``|y| <`` this are ignored [m] (no scale information,
            the pair is noise).
        min_pairs_for_gating: the outlier gate starts after this many accepted pairs.
        gate_chi2: gate on the normalised residual; None -> ``CHI2_997[d]``.
    """

    sigma_slam: float = 0.02
    sigma_metric: float = 0.03
    min_metric_displacement: float = 0.1
    min_pairs_for_gating: int = 5
    gate_chi2: float | None = None


def ml_scale(A: float, B: float, C: float, sigma_x: float, sigma_y: float) -> float:
    """Closed-form ML scale ``s*`` (SLAM units per metre) from the sums ``A = sum x.x``,
    ``B = sum y.y``, ``C = sum x.y`` and the noises ``sigma_x`` [SLAM units], ``sigma_y`` [m].

    Returns NaN when ``C == 0`` (no information)."""
    if C == 0.0:
        return float("nan")
    sx2, sy2 = sigma_x * sigma_x, sigma_y * sigma_y
    # Quadratic a s^2 + b s + c = 0 (module docstring); the minimising root is
    # (-b + sign(C) sqrt(D)) / (2 a). When -b and sign(C) sqrt(D) have opposite signs that sum
    # cancels (e.g. sigma_y -> 0), so take it from the other root: s1 s2 = c / a.
    a, b, c = C * sy2, B * sx2 - A * sy2, -C * sx2
    root_d = float(np.sqrt(b * b - 4.0 * a * c))
    sgn = float(np.sign(C))
    if -b * sgn >= 0.0:
        return float((-b + sgn * root_d) / (2.0 * a))
    other = (-b - sgn * root_d) / (2.0 * a)
    return float(c / (a * other))


def profile_nll(s: float, A: float, B: float, C: float, sigma_x: float, sigma_y: float) -> float:
    """Negative log-likelihood ``L(s)`` with the true displacements minimised out (see module)."""
    return float((A - 2.0 * s * C + s * s * B) / (2.0 * (sigma_x**2 + s * s * sigma_y**2)))


class MLScaleEstimator:
    """Online closed-form ML scale of one SLAM session.

    ``add_pair(x_slam, y_metric, t)`` -> bool accepted; ``scale`` (s, SLAM units per metre),
    ``metric_per_slam_unit`` (lambda = 1/s), ``sigma`` (std of s), ``history``.
    """

    def __init__(self, options: MLScaleOptions | None = None) -> None:
        self.options = options or MLScaleOptions()
        if not (self.options.sigma_slam > 0 and self.options.sigma_metric > 0):
            raise FlightDataError(
                f"MLScaleOptions: sigma_slam={self.options.sigma_slam} and sigma_metric="
                f"{self.options.sigma_metric} must be positive"
            )
        self.A = 0.0
        self.B = 0.0
        self.C = 0.0
        self.n_pairs = 0
        self.counts = {"accepted": 0, "too_small": 0, "outlier": 0}
        #: (t, s, sigma_s, n_pairs) after each accepted pair.
        self.history: list[tuple[float, float, float, int]] = []

    @property
    def scale(self) -> float:
        """``s*`` [SLAM units per metre] (NaN before the first pair)."""
        o = self.options
        return ml_scale(self.A, self.B, self.C, o.sigma_slam, o.sigma_metric)

    @property
    def metric_per_slam_unit(self) -> float:
        """``lambda = 1 / s`` [m per SLAM unit] (Engel et al.'s and tum_ardrone's scale)."""
        return 1.0 / self.scale

    @property
    def sigma(self) -> float:
        """Standard deviation of ``s`` from the curvature of the profile likelihood."""
        s = self.scale
        if not np.isfinite(s):
            return float("inf")
        o = self.options
        h = 1e-4 * max(abs(s), 1e-6)
        f = lambda v: profile_nll(v, self.A, self.B, self.C, o.sigma_slam, o.sigma_metric)  # noqa: E731
        curv = (f(s + h) - 2.0 * f(s) + f(s - h)) / (h * h)
        return float(1.0 / np.sqrt(curv)) if curv > 0 else float("inf")

    def residual(self, x_slam: np.ndarray, y_metric: np.ndarray, s: float | None = None) -> float:
        """Normalised squared residual ``|x - s y|^2 / (sigma_x^2 + s^2 sigma_y^2)`` (chi-square
        with d degrees of freedom at the true scale)."""
        s = self.scale if s is None else s
        o = self.options
        r = np.asarray(x_slam, float) - s * np.asarray(y_metric, float)
        return float(r @ r / (o.sigma_slam**2 + s * s * o.sigma_metric**2))

    def add_pair(self, x_slam: np.ndarray, y_metric: np.ndarray, t: float = float("nan")) -> bool:
        """Add one pair of displacements over the same interval.

        Args:
            x_slam: (d,) SLAM displacement [SLAM units].
            y_metric: (d,) metric displacement [m], same frame and interval.
            t: time of the pair's end [s] (for ``history``).

        Returns:
            True when accepted; False when too small or gated as an outlier (counted).
        """
        x = np.atleast_1d(np.asarray(x_slam, dtype=float))
        y = np.atleast_1d(np.asarray(y_metric, dtype=float))
        if x.shape != y.shape or x.ndim != 1:
            raise FlightDataError(
                f"ML scale: x_slam and y_metric must be d-vectors of the same length, got "
                f"{x.shape} and {y.shape}"
            )
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            raise FlightDataError(f"ML scale: non-finite pair x={x}, y={y} at t={t}")
        o = self.options
        if np.linalg.norm(y) < o.min_metric_displacement:
            self.counts["too_small"] += 1
            return False
        if self.n_pairs >= o.min_pairs_for_gating:
            gate = o.gate_chi2 if o.gate_chi2 is not None else CHI2_997.get(x.size, 3.0 * x.size)
            if self.residual(x, y) > gate:
                self.counts["outlier"] += 1
                return False
        self.A += float(x @ x)
        self.B += float(y @ y)
        self.C += float(x @ y)
        self.n_pairs += 1
        self.counts["accepted"] += 1
        self.history.append((float(t), self.scale, self.sigma, self.n_pairs))
        return True


# ---------------------------------------------------------------------------------------------
# Pairs from a flight
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PairOptions:
    """How :func:`scale_pairs_from_flight` forms displacement pairs.

    Attributes:
        window: length of each interval [s] (seed 004: "a data sample every second").
        max_gap: an interval whose SLAM samples are further than this from its ends is skipped [s].
        components: ``"vertical"`` (z only: rangefinder height), ``"horizontal"`` (x, y from the
            integrated metric velocity), ``"xyz"`` (both).
    """

    window: float = 1.0
    max_gap: float = 0.15
    components: str = "xyz"


@dataclass(frozen=True, eq=False)
class ScalePairs:
    """Displacement pairs of one flight, in world axes.

    Attributes:
        t0, t1: (M,) interval ends [s].
        x_slam: (M, d) SLAM displacements rotated into world axes [SLAM units].
        y_metric: (M, d) metric displacements [m].
        session: (M,) SLAM session of each pair.
        world_R_slam: rotation of each session's SLAM frame into world axes.
        counts: skipped intervals by reason.
    """

    t0: np.ndarray
    t1: np.ndarray
    x_slam: np.ndarray
    y_metric: np.ndarray
    session: np.ndarray
    world_R_slam: dict[int, np.ndarray]
    counts: dict[str, int] = field(default_factory=dict)


def world_R_slam_from_attitude(
    slam_q_cam_wxyz: np.ndarray, world_q_body_wxyz: np.ndarray, body_R_cam: np.ndarray
) -> np.ndarray:
    """Rotation from the SLAM frame to world axes, the chordal mean over samples of
    ``world_R_body body_R_cam slam_R_cam^T`` (attitude at the SLAM times)."""
    Rs = quat_wxyz_to_matrix(slam_q_cam_wxyz)
    Rw = quat_wxyz_to_matrix(world_q_body_wxyz)
    return project_to_so3(np.einsum("nij,jk,nlk->il", Rw, body_R_cam, Rs))


def scale_pairs_from_flight(
    flight: Flight,
    world_q_body_wxyz_at_slam: np.ndarray,
    height: tuple[np.ndarray, np.ndarray] | None = None,
    world_velocity: tuple[np.ndarray, np.ndarray] | None = None,
    options: PairOptions | None = None,
) -> ScalePairs:
    """Form SLAM/metric displacement pairs over consecutive windows of each SLAM session.

    SLAM displacements are rotated into world axes with :func:`world_R_slam_from_attitude` (per
    session; the SLAM orientation and the attitude give the SLAM frame's rotation, so the
    components can be compared with metric ones). Metric displacements: z from ``height`` (e.g.
    the rangefinder height of ``vertical_velocity_from_range``; flat ground assumed), x and y
    from integrating ``world_velocity`` (e.g. the I&I observer's, or an optical-flow velocity).

    Args:
        flight: needs ``slam`` (tracking-lost samples, session < 0, are skipped and counted).
        world_q_body_wxyz_at_slam: (M, 4) attitude at the SLAM sample times.
        height: ``(t, h)`` height above ground [s, m], needed for vertical components.
        world_velocity: ``(t, v)`` world velocity [s, m/s] (N, 3) or (N, 2), needed for
            horizontal components.
        options: window and components.
    """
    options = options or PairOptions()
    slam = flight.slam
    if slam is None:
        raise FlightDataError(f"{flight.name}: scale pairs need the slam stream")
    q_att = np.asarray(world_q_body_wxyz_at_slam, dtype=float)
    if q_att.shape != (len(slam), 4):
        raise FlightDataError(
            f"{flight.name}: attitude at SLAM times must be ({len(slam)}, 4), got {q_att.shape}"
        )
    comp = options.components
    if comp not in ("vertical", "horizontal", "xyz"):
        raise FlightDataError(
            f"PairOptions.components={comp!r}: expected 'vertical', 'horizontal' or 'xyz'"
        )
    if comp in ("vertical", "xyz") and height is None:
        raise FlightDataError(f"{flight.name}: vertical scale pairs need a height series")
    if comp in ("horizontal", "xyz") and world_velocity is None:
        raise FlightDataError(f"{flight.name}: horizontal scale pairs need a world velocity")
    idx = {"vertical": [2], "horizontal": [0, 1], "xyz": [0, 1, 2]}[comp]
    body_R_cam = np.asarray(flight.calib.body_T_cam, dtype=float)[:3, :3]

    if world_velocity is not None:
        tv, v = np.asarray(world_velocity[0], float), np.asarray(world_velocity[1], float)
        # Position by trapezoidal integration; displacements are differences of it.
        disp = np.concatenate(
            [np.zeros((1, v.shape[1])), np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(tv)[:, None], 0)]
        )

    t0s, t1s, xs, ys, ss = [], [], [], [], []
    counts = {"slam_lost": int((slam.session < 0).sum()), "gap": 0, "no_metric": 0}
    rotations: dict[int, np.ndarray] = {}
    for sid in np.unique(slam.session[slam.session >= 0]):
        rows = np.flatnonzero(slam.session == sid)
        w_R_s = world_R_slam_from_attitude(slam.slam_q_cam_wxyz[rows], q_att[rows], body_R_cam)
        rotations[int(sid)] = w_R_s
        ts = slam.t[rows]
        p_world_axes = slam.slam_t_cam[rows] @ w_R_s.T
        edges = np.arange(ts[0], ts[-1] + 1e-9, options.window)
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            ia = int(np.argmin(np.abs(ts - a)))
            ib = int(np.argmin(np.abs(ts - b)))
            if abs(ts[ia] - a) > options.max_gap or abs(ts[ib] - b) > options.max_gap or ia == ib:
                counts["gap"] += 1
                continue
            ta, tb = ts[ia], ts[ib]
            y = np.zeros(3)
            if 2 in idx:
                th, h = height
                if ta < th[0] or tb > th[-1] or not np.all(np.isfinite(np.interp([ta, tb], th, h))):
                    counts["no_metric"] += 1
                    continue
                ha, hb = np.interp([ta, tb], th, h)
                y[2] = hb - ha
            if 0 in idx:
                if ta < tv[0] or tb > tv[-1]:
                    counts["no_metric"] += 1
                    continue
                for c in range(2):
                    y[c] = np.interp(tb, tv, disp[:, c]) - np.interp(ta, tv, disp[:, c])
            t0s.append(ta)
            t1s.append(tb)
            xs.append((p_world_axes[ib] - p_world_axes[ia])[idx])
            ys.append(y[idx])
            ss.append(int(sid))
    d = len(idx)
    return ScalePairs(
        t0=np.asarray(t0s),
        t1=np.asarray(t1s),
        x_slam=np.asarray(xs).reshape(-1, d),
        y_metric=np.asarray(ys).reshape(-1, d),
        session=np.asarray(ss, dtype=int),
        world_R_slam=rotations,
        counts=counts,
    )


@dataclass(frozen=True, eq=False)
class ScaleResult:
    """ML scale per SLAM session.

    Attributes:
        scale: final ``s`` per session [SLAM units per metre].
        sigma: its standard deviation per session.
        history: per session, (K, 4) rows ``(t, s, sigma_s, n_pairs)`` after each accepted pair.
        counts: per session, accepted / too_small / outlier.
    """

    scale: dict[int, float]
    sigma: dict[int, float]
    history: dict[int, np.ndarray]
    counts: dict[int, dict[str, int]]


def estimate_scale(pairs: ScalePairs, options: MLScaleOptions | None = None) -> ScaleResult:
    """Run one :class:`MLScaleEstimator` per SLAM session over the pairs, in time order."""
    estimators: dict[int, MLScaleEstimator] = {}
    for k in np.argsort(pairs.t1, kind="stable"):
        sid = int(pairs.session[k])
        est = estimators.setdefault(sid, MLScaleEstimator(options))
        est.add_pair(pairs.x_slam[k], pairs.y_metric[k], float(pairs.t1[k]))
    for sid, est in estimators.items():
        log.info("ML scale session %d: s=%.4f +- %.4f %s", sid, est.scale, est.sigma, est.counts)
    return ScaleResult(
        scale={s: e.scale for s, e in estimators.items()},
        sigma={s: e.sigma for s, e in estimators.items()},
        history={
            s: np.asarray(e.history, dtype=float).reshape(-1, 4) for s, e in estimators.items()
        },
        counts={s: dict(e.counts) for s, e in estimators.items()},
    )


def attitude_at(t_query: np.ndarray, t: np.ndarray, world_q_body_wxyz: np.ndarray) -> np.ndarray:
    """Convenience: attitude quaternions at ``t_query`` (normalised linear interpolation)."""
    from fgnav.datasets.geometry import interpolate_quat_wxyz

    return interpolate_quat_wxyz(t, world_q_body_wxyz, np.asarray(t_query, float))


__all__ = [
    "CHI2_997",
    "MLScaleEstimator",
    "MLScaleOptions",
    "PairOptions",
    "ScalePairs",
    "ScaleResult",
    "attitude_at",
    "estimate_scale",
    "ml_scale",
    "profile_nll",
    "scale_pairs_from_flight",
    "world_R_slam_from_attitude",
]
