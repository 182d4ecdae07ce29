"""SLAM-vs-gyro consistency: rotation convention, camera extrinsic rotation and SLAM clock offset.

A monocular SLAM's relative camera rotations and the gyro's integrated rotations over the same
intervals describe one rigid motion: ``G_ij = body_R_cam C_ij body_R_cam^T`` with

- ``G_ij = R_gyro(t_i + offset)^T R_gyro(t_j + offset)``: the body rotation from SLAM pose i to j
  integrated from the gyro (bias ``b`` removed), body frame;
- ``C_ij``: the camera rotation between the two poses. A file states ``slam_R_cam`` (fgnav's
  convention, ``"as-is"``: ``C_ij = R_i^T R_j``); some SLAM forks write ``cam_R_slam`` instead
  while their positions stay camera centres (``"inverse"``: ``C_ij = R_i R_j^T``). Both give the
  same rotation *angle* (``trace(A^T B) = trace(A B^T)``); only the axes tell them apart: the
  wrong convention puts world-frame axes where camera-frame axes belong, which no fixed
  ``body_R_cam`` maps onto the gyro's once the attitude varies.
- ``offset``: SLAM clock offset, ``t_imu = t_slam + offset_s`` (the convention of
  :func:`.time_offset.estimate_time_offset` with clock a = IMU, clock b = SLAM).

The estimator (:func:`check_slam_gyro`) works on whatever has arrived:

1. pairs ``(i, j)``: each SLAM pose with the first one at least ``pair_s`` later in the same
   session, at most ``max_pair_s`` apart (gaps are skipped);
2. coarse clock offset: cross-correlation of the gyro's rate magnitude with the SLAM's
   (:func:`.time_offset.estimate_time_offset`; both are invariant to the convention and to
   ``body_R_cam``), when at least ``min_overlap_s`` of data has arrived (else 0);
3. per convention: ``body_R_cam`` fitted to the pairs' rotation vectors (orthogonal Procrustes,
   a hand-eye rotation) alternating with the gyro bias (first order:
   ``Log(G_ij(b)^T X C_ij X^T) ~ r_ij + b dt_ij``); its median residual angle is the score;
4. the convention whose score is at most half the other's wins (else undecided); before
   ``min_rotation_rad`` of rotation has arrived, an early decision needs at most a quarter
   (``SlamGyroOptions.early_*``: a few seconds of flight instead of 15-18 s on EuRoC); the offset is
   refined by the 3-D residual of the winner on a fine grid (parabola through the minimum);
5. ``body_R_cam`` check: the given rotation is named wrong when the fitted one is more than
   :data:`EXTRINSIC_TOL_DEG` from it and fits at least 1.5x better.

:class:`SlamGyroCheck` is the causal, incremental form (``add_imu``, ``add_slam`` or ``add(event)``
with :mod:`.events` events; ``decision()`` is None until enough rotation has arrived, then fixed);
:func:`check_flight` runs the same core on a whole flight and :func:`apply_slam_check` applies the
``slam_rotation`` / ``slam_time_offset`` options to a flight (batch side).

A mirrored (left-handed) SLAM frame is tested by :func:`check_mirror` (see the section above it),
where the check names the inverse convention or a wrong ``body_T_cam`` rotation: on a yaw-only
flight with a downward camera a flip of x or y looks like the inverse convention, a flip of z
like a ``body_T_cam`` rotation 80 deg off.

Not modelled: a time-varying clock offset (drift), another SLAM rotation that is neither as
stated nor inverted, the camera's lever arm (rotations do not see it), gyro scale
errors. The gyro bias is one constant over the data used.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import FgnavError, FlightDataError
from .geometry import (
    make_pose,
    matrix_to_quat_wxyz,
    project_to_so3,
    quat_wxyz_to_matrix,
    slerp_rotations,
    so3_exp,
    so3_log,
)
from .time_offset import estimate_time_offset
from .types import Flight, ImuSeries, SlamSeries

log = logging.getLogger(__name__)

#: The SLAM rate signal's samples (pair mid-times) further apart than this (or 3 median
#: intervals) bound a gap the coarse clock offset leaves out.
SLAM_RATE_MAX_GAP_S = 0.5
#: Values of the ``slam_rotation`` option: decide from the gyro, keep as stated, invert.
SLAM_ROTATION_MODES = ("auto", "as-is", "inverse")
#: String values of the ``slam_time_offset`` option (else a number of seconds to add to SLAM
#: times): estimate and report only, or estimate and apply.
SLAM_TIME_OFFSET_MODES = ("report", "apply")
#: What to do with a ``body_T_cam`` rotation the check names wrong: ``"auto"``, use the fitted
#: one (one warning line says so); ``"as-is"``, keep it (the warning only names it).
SLAM_EXTRINSIC_MODES = ("auto", "as-is")
#: A convention wins when the other's median residual is at least this many times larger.
CONVENTION_RATIO = 2.0
#: A given body_R_cam this far [deg] from the fitted one (and fitting 1.5x worse) is named wrong.
EXTRINSIC_TOL_DEG = 5.0
#: Fitting body_R_cam needs two excited axes: second/first singular value of the correlation.
MIN_AXIS_SPREAD = 0.05
#: The coarse clock offset counts only where the gyro's and the SLAM's rotation rates correlate
#: at least this well there (simulated flights 0.90-0.999, EuRoC 0.83-0.96; a vertical flight
#: 0.09-0.25).
OFFSET_MIN_CORRELATION = 0.5


class SlamConventionError(FgnavError, ValueError):
    """A bad ``slam_rotation`` / ``slam_time_offset`` option."""


@dataclass(frozen=True)
class SlamGyroOptions:
    """Options of the SLAM-vs-gyro check.

    Attributes:
        pair_s: shortest interval of a rotation pair [s].
        max_pair_s: longest interval of a rotation pair [s] (longer: a gap, skipped).
        max_offset_s: search half-width of the SLAM clock offset [s].
        min_overlap_s: data needed for the offset's cross-correlation [s] (shorter: offset 0).
        min_rotation_rad: total rotation (sum of the pairs' angles, non-overlapping) needed before
            a decision.
        min_pairs: pairs needed before a decision.
        early_rotation_rad, early_min_pairs, early_ratio: an earlier decision, before
            ``min_rotation_rad`` / ``min_pairs`` have arrived: with at least this much rotation
            and this many pairs, a convention wins when the other's median residual is at least
            ``early_ratio`` times its own (fitted ``body_R_cam``; no fallback on the given one).
            Measured causally (default thresholds, fitted residual ratio at 0.4-0.8 rad): EuRoC
            MH_01 ORB-SLAM3 as stated 10-21 at 4-6 s, V1_02 ORB-SLAM2 keyframes as stated 12 at
            5 s, V1_02 ORB-SLAM3 keyframes inverted 10-63 at 3-5 s; the simulated flights
            (two-turns, figure8, circle, seeds 0-2, as stated) 1.0-2.1 below 1 rad and 2.4-6.8
            at 1.6-2.2 rad; rectangle 3.3-12 (right) at 0.2-0.7 rad. Data that cannot tell
            the conventions apart (circle, rectangle's yaw-only turns) stays at 1.0-1.5.
            ``early_rotation_rad = inf`` switches it off.
        refine_half_width_s: the fine offset grid covers the coarse offset +- this [s].
        refine_step_s: fine grid step [s].
    """

    pair_s: float = 0.25
    max_pair_s: float = 1.0
    max_offset_s: float = 0.5
    min_overlap_s: float = 5.0
    min_rotation_rad: float = 3.0
    min_pairs: int = 20
    early_rotation_rad: float = 0.4
    early_min_pairs: int = 6
    early_ratio: float = 4.0
    refine_half_width_s: float = 0.03
    refine_step_s: float = 0.003


@dataclass(frozen=True, eq=False)
class SlamGyroDecision:
    """Result of :func:`check_slam_gyro`.

    Attributes:
        convention: ``"as-is"`` or ``"inverse"``: the one that fits (``"as-is"`` when undecided).
        decided: False when neither convention fits clearly better.
        residual_deg: convention -> median residual angle with the fitted ``body_R_cam`` [deg].
        residual_given_deg: the same with the given ``body_R_cam`` [deg].
        body_R_cam_fit: (3, 3) the rotation that fits under ``convention``.
        body_R_cam_error_deg: angle between the given and the fitted rotation [deg].
        body_R_cam_ok: False when the given rotation is wrong (see the module docstring).
        time_offset_s: SLAM clock offset, ``t_imu = t_slam + offset`` [s].
        offset_correlation: correlation of the rate magnitudes at the coarse offset (NaN: not
            estimated, too little data).
        time_offset_ok: the offset is determined: ``offset_correlation`` at least
            :data:`OFFSET_MIN_CORRELATION`. Below it the rates did not vary enough to tell
            (a simulated vertical flight: 0.09-0.25 and offsets of -0.53..+0.20 s on a
            synchronous SLAM, named as a clock offset); the offset is then neither named nor
            applied.
        gyro_bias: (3,) gyro bias [rad/s] fitted with ``convention``.
        n_pairs: rotation pairs used.
        rotation_rad: total rotation seen (non-overlapping pairs) [rad].
        axis_spread: second over first singular value of the gyro/camera rotation-vector
            correlation under ``convention``: below :data:`MIN_AXIS_SPREAD` one axis alone
            turned (a yawing flight); the fit then keeps the given rotation about the
            unexcited directions (its Gauss-Newton starts there, with a ridge), so it is never
            further from the truth there than the given one.
    """

    convention: str
    decided: bool
    residual_deg: dict[str, float]
    residual_given_deg: dict[str, float]
    body_R_cam_fit: np.ndarray
    body_R_cam_error_deg: float
    body_R_cam_ok: bool
    time_offset_s: float
    offset_correlation: float
    gyro_bias: np.ndarray
    n_pairs: int
    rotation_rad: float
    axis_spread: float = float("nan")

    @property
    def time_offset_ok(self) -> bool:
        return bool(self.offset_correlation >= OFFSET_MIN_CORRELATION)

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary."""
        return {
            "convention": self.convention,
            "decided": self.decided,
            "residual_deg": {k: round(v, 3) for k, v in self.residual_deg.items()},
            "residual_given_deg": {k: round(v, 3) for k, v in self.residual_given_deg.items()},
            "body_R_cam_ok": self.body_R_cam_ok,
            "body_R_cam_error_deg": round(self.body_R_cam_error_deg, 2),
            "body_q_cam_fit_wxyz": np.round(matrix_to_quat_wxyz(self.body_R_cam_fit), 5).tolist(),
            "time_offset_s": round(self.time_offset_s, 4),
            "time_offset_ok": self.time_offset_ok,
            "offset_correlation": round(self.offset_correlation, 3),
            "gyro_bias": np.round(self.gyro_bias, 4).tolist(),
            "n_pairs": self.n_pairs,
            "axis_spread": round(self.axis_spread, 4),
        }

    def extrinsic_message(self) -> str | None:
        """One line naming a wrong ``body_T_cam`` rotation and the one that fits (None: fits)."""
        if self.body_R_cam_ok:
            return None
        q = matrix_to_quat_wxyz(self.body_R_cam_fit)
        given, fitted = self.residual_given_deg[self.convention], self.residual_deg[self.convention]
        return (
            f"body_T_cam rotation is wrong: it is {self.body_R_cam_error_deg:.1f} deg from the "
            f"rotation the gyro fits (median residual {given:.2f} vs {fitted:.2f} deg); "
            "body_q_cam_wxyz that fits: "
            f"[{', '.join(f'{x:.4f}' for x in q)}]"
        )


@dataclass(frozen=True, eq=False)
class _Pairs:
    t_i: np.ndarray
    t_j: np.ndarray
    R_i: np.ndarray
    R_j: np.ndarray


def pose_pairs(
    t: np.ndarray, session: np.ndarray | None, pair_s: float, max_pair_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i, j)`` of the pose pairs whose rotations are compared: each pose (times
    ``t`` [s], increasing) with the first one at least ``pair_s`` later, kept when at most
    ``max_pair_s`` later (a gap otherwise) and of the same session (``session`` None: one)."""
    j = np.searchsorted(t, t + pair_s - 1e-9)
    i = np.arange(len(t))
    ok = j < len(t)
    i, j = i[ok], j[ok]
    ok = t[j] - t[i] <= max_pair_s
    if session is not None:
        ok &= session[i] == session[j]
    return i[ok], j[ok]


def _pairs(t: np.ndarray, R: np.ndarray, session: np.ndarray, o: SlamGyroOptions) -> _Pairs:
    i, j = pose_pairs(t, session, o.pair_s, o.max_pair_s)
    return _Pairs(t[i], t[j], R[i], R[j])


def _integrate(t: np.ndarray, omega: np.ndarray, block: int = 64) -> np.ndarray:
    """Gyro orientation track (N, 3, 3) from the identity at ``t[0]`` (zero bias): products
    within blocks of ``block`` steps vectorised over the blocks, then chained block by block."""
    steps = so3_exp(omega[:-1] * np.diff(t)[:, None])
    n = len(steps)
    nb = -(-n // block)
    S = np.concatenate([steps, np.broadcast_to(np.eye(3), (nb * block - n, 3, 3))])
    S = S.reshape(nb, block, 3, 3)
    cum = np.empty_like(S)
    cum[:, 0] = S[:, 0]
    for k in range(1, block):
        cum[:, k] = cum[:, k - 1] @ S[:, k]
    start = np.empty((nb, 3, 3))
    start[0] = np.eye(3)
    for b in range(1, nb):
        start[b] = start[b - 1] @ cum[b - 1, -1]
    full = (start[:, None] @ cum).reshape(-1, 3, 3)[:n]
    return np.concatenate([np.eye(3)[None], full])


def _camera_increments(p: _Pairs, convention: str) -> np.ndarray:
    tr = (0, 2, 1)
    if convention == "as-is":
        return np.transpose(p.R_i, tr) @ p.R_j
    return p.R_i @ np.transpose(p.R_j, tr)


class _Core:
    """Residuals of the pairs for one clock offset (gyro track integrated once)."""

    def __init__(self, imu_t: np.ndarray, R_gyro: np.ndarray, p: _Pairs, offset: float):
        Ri = slerp_rotations(imu_t, R_gyro, p.t_i + offset)
        Rj = slerp_rotations(imu_t, R_gyro, p.t_j + offset)
        self.G = np.transpose(Ri, (0, 2, 1)) @ Rj
        self.dt = p.t_j - p.t_i
        self.p = p

    def residuals(self, C: np.ndarray, X: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """Rotation vectors (P, 3) of ``G(b)^T X C X^T`` (body frame) [rad]."""
        G = self.G @ so3_exp(-bias[None, :] * self.dt[:, None])
        return so3_log(np.transpose(G, (0, 2, 1)) @ X @ C @ X.T)

    def fit(
        self, convention: str, X_given: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, float, float, float]:
        """Fitted ``body_R_cam``, bias, median residual [deg] fitted and with ``X_given``, and
        the axis spread (conditioning of the rotation fit)."""
        C = _camera_increments(self.p, convention)
        c = so3_log(C)
        a = so3_log(self.G)
        M = a.T @ c
        sv = np.linalg.svd(M, compute_uv=False)
        spread = float(sv[1] / sv[0]) if sv[0] > 0 else 0.0
        # From the given rotation, and from the Procrustes one when two axes are excited (a
        # grossly wrong given rotation); the given start wins unless the other fits 10 % better
        # (the ridge keeps unexcited directions at the start value).
        X, bias = self._gauss_newton(C, c, X_given, free_rotation=True)
        fit_med = _median_deg(self.residuals(C, X, bias))
        if spread >= MIN_AXIS_SPREAD:
            X2, bias2 = self._gauss_newton(C, c, project_to_so3(M), free_rotation=True)
            fit2 = _median_deg(self.residuals(C, X2, bias2))
            if fit2 < fit_med / 1.1:
                X, bias, fit_med = X2, bias2, fit2
        _, b_g = self._gauss_newton(C, c, X_given, free_rotation=False)
        given_med = _median_deg(self.residuals(C, X_given, b_g))
        return X, bias, fit_med, given_med, spread

    def _gauss_newton(
        self, C: np.ndarray, c: np.ndarray, X: np.ndarray, free_rotation: bool, iterations: int = 6
    ) -> tuple[np.ndarray, np.ndarray]:
        """Joint fit of ``body_R_cam = Exp(phi) X`` and the bias. First-order model of the
        residual ``r = Log(G(b)^T X C X^T)``: ``r(phi, b + db) ~ r - [X c]x phi + db dt``; a
        ridge on ``phi`` keeps directions the rotations do not excite at the start value. Pairs
        above 3x the median residual get weight 0."""
        bias = np.zeros(3)
        dt = self.dt
        ridge = 1e-3 * float(np.sum(c**2))
        for _ in range(iterations):
            r = self.residuals(C, X, bias)
            ang = np.linalg.norm(r, axis=1)
            w = ang <= max(3.0 * float(np.median(ang)), 1e-4)
            xc = c[w] @ X.T
            J = np.zeros((int(w.sum()), 3, 6))
            J[:, 0, 1], J[:, 0, 2] = xc[:, 2], -xc[:, 1]
            J[:, 1, 0], J[:, 1, 2] = -xc[:, 2], xc[:, 0]
            J[:, 2, 0], J[:, 2, 1] = xc[:, 1], -xc[:, 0]
            J[:, :, 3:] = dt[w, None, None] * np.eye(3)
            if not free_rotation:
                J = J[:, :, 3:]
            H = np.einsum("nki,nkj->ij", J, J)
            g = np.einsum("nki,nk->i", J, r[w])
            if free_rotation:
                H[:3, :3] += ridge * np.eye(3)
            step = -np.linalg.solve(H, g)
            if free_rotation:
                X = so3_exp(step[None, :3])[0] @ X
            bias = bias + step[-3:]
        return X, bias


def _median_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.median(np.linalg.norm(r, axis=1))))


def _rotation_seen(p: _Pairs) -> float:
    """Sum of the angles of non-overlapping pairs [rad]."""
    total, t_last = 0.0, -np.inf
    ang = np.linalg.norm(so3_log(np.transpose(p.R_i, (0, 2, 1)) @ p.R_j), axis=1)
    for k in range(len(ang)):
        if p.t_i[k] >= t_last:
            total += float(ang[k])
            t_last = float(p.t_j[k])
    return total


def _coarse_offset(
    imu_t: np.ndarray, imu_omega: np.ndarray, p: _Pairs, o: SlamGyroOptions
) -> tuple[float, float]:
    """Offset from the rate magnitudes (convention- and extrinsic-free), or (0, NaN)."""
    span = min(imu_t[-1], p.t_j[-1]) - max(imu_t[0], p.t_i[0])
    if span < o.min_overlap_s + o.max_offset_s or len(p.t_i) < 4:
        return 0.0, float("nan")
    dt = p.t_j - p.t_i
    rate = np.linalg.norm(so3_log(np.transpose(p.R_i, (0, 2, 1)) @ p.R_j), axis=1) / dt
    t_mid = 0.5 * (p.t_i + p.t_j)
    t_mid, first = np.unique(t_mid, return_index=True)
    rate = rate[first]
    smooth = float(min(np.median(dt), 0.5))
    try:
        res = estimate_time_offset(
            imu_t,
            np.linalg.norm(imu_omega, axis=1),
            t_mid,
            rate,
            o.max_offset_s,
            smooth_s=smooth,
            min_overlap_s=o.min_overlap_s,
            # A tracking loss (no pair across it) is left out, not bridged.
            max_gap_s=max(SLAM_RATE_MAX_GAP_S, 3.0 * float(np.median(np.diff(t_mid)))),
        )
    except FlightDataError:
        return 0.0, float("nan")
    return res.offset_s, res.correlation


def _angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(so3_log((A.T @ B)[None])[0])))


def check_slam_gyro(
    imu_t: np.ndarray,
    imu_omega: np.ndarray,
    slam_t: np.ndarray,
    slam_q_cam_wxyz: np.ndarray,
    body_R_cam: np.ndarray,
    session: np.ndarray | None = None,
    options: SlamGyroOptions | None = None,
    *,
    force: bool = False,
    refine_undecided: bool = True,
) -> SlamGyroDecision | None:
    """Compare SLAM relative rotations with the gyro's (module docstring: model and steps).

    Args:
        imu_t, imu_omega: (N,) IMU times [s] and (N, 3) body angular rates [rad/s].
        slam_t, slam_q_cam_wxyz: (M,) SLAM image times [s, SLAM clock] and (M, 4) orientations as
            stored in the file.
        body_R_cam: (3, 3) the given camera-to-body rotation.
        session: (M,) SLAM map ids (pairs never span two); None: one map.
        options: thresholds (:class:`SlamGyroOptions`).
        force: decide even with less rotation than ``options.min_rotation_rad`` (whole flights).
        refine_undecided: refine the clock offset and refit when the conventions do not separate
            (False: such a result comes back unrefined; :class:`SlamGyroCheck` drops it anyway
            and tries again later, so the work is skipped).

    Returns:
        The decision, or None when too little rotation (or too few pairs) has arrived.
    """
    o = options or SlamGyroOptions()
    imu_t = np.asarray(imu_t, float)
    imu_omega = np.asarray(imu_omega, float)
    slam_t = np.asarray(slam_t, float)
    sess = np.zeros(len(slam_t), int) if session is None else np.asarray(session)
    if len(imu_t) < 2 or len(slam_t) < 2:
        return None
    R = quat_wxyz_to_matrix(np.asarray(slam_q_cam_wxyz, float))
    inside = (slam_t > imu_t[0] + o.max_offset_s) & (slam_t < imu_t[-1] - o.max_offset_s)
    p = _pairs(slam_t[inside], R[inside], sess[inside], o)
    n_min = 4 if force else min(o.min_pairs, o.early_min_pairs)
    if len(p.t_i) < n_min:
        return None
    seen = _rotation_seen(p)
    early = not force and (seen < o.min_rotation_rad or len(p.t_i) < o.min_pairs)
    if early and (seen < o.early_rotation_rad or len(p.t_i) < o.early_min_pairs):
        return None
    R_gyro = _integrate(imu_t, imu_omega)
    offset, corr = _coarse_offset(imu_t, imu_omega, p, o)
    X_given = np.asarray(body_R_cam, float)
    core = _Core(imu_t, R_gyro, p, offset)
    fits = {c: core.fit(c, X_given) for c in ("as-is", "inverse")}
    fitted = {c: f[2] for c, f in fits.items()}
    given = {c: f[3] for c, f in fits.items()}
    best = min(fitted, key=fitted.__getitem__)
    other = "inverse" if best == "as-is" else "as-is"
    decided = fitted[other] >= (o.early_ratio if early else CONVENTION_RATIO) * fitted[best]
    if not decided and not early:
        best_g = min(given, key=given.__getitem__)
        other_g = "inverse" if best_g == "as-is" else "as-is"
        if given[other_g] >= CONVENTION_RATIO * given[best_g]:
            best, decided = best_g, True
    convention = best if decided else "as-is"
    if np.isfinite(corr) and (decided or refine_undecided):
        # Fine offset: the 3-D residual of the winner (its fitted rotation and bias).
        X, bias = fits[convention][0], fits[convention][1]
        C = _camera_increments(p, convention)
        grid = offset + np.arange(
            -o.refine_half_width_s, o.refine_half_width_s + 0.5 * o.refine_step_s, o.refine_step_s
        )
        cost = np.array(
            [
                float(np.mean(np.sum(_Core(imu_t, R_gyro, p, d).residuals(C, X, bias) ** 2, 1)))
                for d in grid
            ]
        )
        k = int(np.argmin(cost))
        offset = float(grid[k])
        if 0 < k < len(grid) - 1:
            c0, c1, c2 = cost[k - 1], cost[k], cost[k + 1]
            denom = c0 - 2.0 * c1 + c2
            if denom > 0:
                offset += 0.5 * (c0 - c2) / denom * o.refine_step_s
        core = _Core(imu_t, R_gyro, p, offset)
        fits = {c: core.fit(c, X_given) for c in ("as-is", "inverse")}
        fitted = {c: f[2] for c, f in fits.items()}
        given = {c: f[3] for c, f in fits.items()}
    X_fit, bias, fit_med, given_med, spread = fits[convention]
    err_deg = _angle_deg(X_given, X_fit)
    ok = not (err_deg > EXTRINSIC_TOL_DEG and given_med > 1.5 * fit_med)
    return SlamGyroDecision(
        convention=convention,
        decided=decided,
        residual_deg=fitted,
        residual_given_deg=given,
        body_R_cam_fit=X_fit,
        body_R_cam_error_deg=err_deg,
        body_R_cam_ok=ok,
        time_offset_s=float(offset),
        offset_correlation=float(corr),
        gyro_bias=bias,
        n_pairs=len(p.t_i),
        rotation_rad=seen,
        axis_spread=spread,
    )


#: :class:`SlamGyroCheck` with ``window_s``: the data older than the window is dropped once this
#: much [s] of it has gathered.
WINDOW_TRIM_S = 10.0
#: :meth:`SlamGyroCheck.stated_misfit`: pairs rotating at least this much [rad] count, and at
#: least this many of them are needed.
STATED_MIN_PAIR_RAD = 0.05
STATED_MIN_PAIRS = 5


class SlamGyroCheck:
    """Causal SLAM-vs-gyro check, fed measurements as they arrive.

    ``decision()`` is None until enough rotation (``options.min_rotation_rad``) has arrived and
    the two conventions separate; then it is computed once and kept (later data does not change
    it). Attempts are spaced ``retry_s`` of SLAM time apart to bound the work.

    Args:
        body_R_cam: (3, 3) the given camera-to-body rotation.
        options: thresholds (:class:`SlamGyroOptions`).
        retry_s: SLAM time between two decision attempts [s].
        window_s: keep only the newest ``window_s`` of SLAM (and the IMU from 1 s before it;
            dropped in chunks of :data:`WINDOW_TRIM_S`), which bounds the work of an attempt
            (it fits all that is kept: 0.25 s at 40 s of data) and the memory; None: all.
    """

    def __init__(
        self,
        body_R_cam: np.ndarray,
        options: SlamGyroOptions | None = None,
        retry_s: float = 1.0,
        window_s: float | None = None,
    ) -> None:
        self.body_R_cam = np.asarray(body_R_cam, float)
        self.options = options or SlamGyroOptions()
        self.retry_s = retry_s
        self.window_s = window_s
        self._imu_t: list[float] = []
        self._imu_w: list[np.ndarray] = []
        self._slam_t: list[float] = []
        self._slam_q: list[np.ndarray] = []
        self._slam_s: list[int] = []
        # Accelerometer and SLAM positions, when given to every sample (for mirror_verdict).
        self._imu_a: list[np.ndarray] | None = []
        self._slam_p: list[np.ndarray] | None = []
        self._decision: SlamGyroDecision | None = None
        self._last_try = -np.inf

    def add_imu(
        self, t: float, body_omega: np.ndarray, body_accel: np.ndarray | None = None
    ) -> None:
        """One gyro sample (body frame) [rad/s] at time ``t`` [s]; times must increase. The
        specific force ``body_accel`` [m/s^2], given with every sample, lets
        :meth:`mirror_verdict` test the SLAM frame's handedness."""
        if self._imu_t and t <= self._imu_t[-1]:
            return
        self._imu_t.append(float(t))
        self._imu_w.append(np.asarray(body_omega, float))
        if self._imu_a is not None:
            if body_accel is None:
                self._imu_a = None
            else:
                self._imu_a.append(np.asarray(body_accel, float))

    def add_slam(
        self,
        t: float,
        slam_q_cam_wxyz: np.ndarray,
        session: int = 0,
        slam_t_cam: np.ndarray | None = None,
    ) -> None:
        """One SLAM orientation as stored (image time ``t`` [s, SLAM clock]); its position
        ``slam_t_cam``, given with every pose, for :meth:`mirror_verdict`."""
        if self._slam_t and t <= self._slam_t[-1]:
            return
        self._slam_t.append(float(t))
        self._slam_q.append(np.asarray(slam_q_cam_wxyz, float))
        self._slam_s.append(int(session))
        if self._slam_p is not None:
            if slam_t_cam is None:
                self._slam_p = None
            else:
                self._slam_p.append(np.asarray(slam_t_cam, float))
        if self.window_s is not None and t - self._slam_t[0] > self.window_s + WINDOW_TRIM_S:
            self._trim(t - self.window_s)

    def _trim(self, start: float) -> None:
        """Drop the SLAM before ``start`` and the IMU before ``start - 1 s``."""
        import bisect

        k = bisect.bisect_left(self._slam_t, start)
        for buf in (self._slam_t, self._slam_q, self._slam_s, self._slam_p):
            if buf is not None:
                del buf[:k]
        k = bisect.bisect_left(self._imu_t, start - 1.0)
        for buf in (self._imu_t, self._imu_w, self._imu_a):
            if buf is not None:
                del buf[:k]

    def mirror_verdict(self) -> MirrorVerdict | None:
        """:func:`check_mirror` on what has arrived (None: too little data, or accelerometer or
        positions not given with every sample)."""
        if not self._imu_a or not self._slam_p or len(self._slam_t) < 3:
            return None
        imu = ImuSeries(
            np.asarray(self._imu_t),
            np.asarray(self._imu_w).reshape(-1, 3),
            np.asarray(self._imu_a).reshape(-1, 3),
        )
        slam = SlamSeries(
            t=np.asarray(self._slam_t),
            slam_t_cam=np.asarray(self._slam_p).reshape(-1, 3),
            slam_q_cam_wxyz=np.asarray(self._slam_q).reshape(-1, 4),
            session=np.asarray(self._slam_s),
        )
        return check_mirror(imu, slam, self.body_R_cam, self.options)

    def add(self, event: Any) -> None:
        """An :mod:`.events` event: ``ImuSample`` and ``SlamPose`` are used, others ignored."""
        from .events import ImuSample, SlamPose

        if isinstance(event, ImuSample):
            self.add_imu(event.t, event.body_omega, event.body_accel)
        elif isinstance(event, SlamPose):
            self.add_slam(event.t, event.slam_q_cam_wxyz, event.session, event.slam_t_cam)

    def stated_misfit(
        self, min_pair_rad: float = STATED_MIN_PAIR_RAD, min_pairs: int = STATED_MIN_PAIRS
    ) -> float | None:
        """How badly the stated ``body_R_cam`` maps the SLAM's relative rotations onto the
        gyro's, long before :meth:`decision` can fit one: the median over the pairs that
        rotate at least ``min_pair_rad`` of ``|residual| / |rotation|`` with the stated
        rotation (gyro bias fitted, the better convention, no clock offset), or None with
        fewer such pairs than ``min_pairs``. A right rotation gives a few hundredths (the SLAM
        and gyro noise), one ``a`` off about ``2 sin(a / 2)`` for rotations across the error's
        axis (1.4 at 90 deg): a first warning needs one excited axis, not the two a fit does."""
        if len(self._slam_t) < 2 or len(self._imu_t) < 2:
            return None
        t = np.asarray(self._slam_t)
        R = quat_wxyz_to_matrix(np.asarray(self._slam_q).reshape(-1, 4))
        imu_t = np.asarray(self._imu_t)
        inside = (t > imu_t[0]) & (t < imu_t[-1])
        p = _pairs(t[inside], R[inside], np.asarray(self._slam_s)[inside], self.options)
        if len(p.t_i) < min_pairs:
            return None
        ang = np.linalg.norm(so3_log(np.transpose(p.R_i, (0, 2, 1)) @ p.R_j), axis=1)
        big = ang >= min_pair_rad
        if big.sum() < min_pairs:
            return None
        core = _Core(imu_t, _integrate(imu_t, np.asarray(self._imu_w).reshape(-1, 3)), p, 0.0)
        out = []
        for c in ("as-is", "inverse"):
            C = _camera_increments(p, c)
            _, b = core._gauss_newton(C, so3_log(C), self.body_R_cam, free_rotation=False)
            r = np.linalg.norm(core.residuals(C, self.body_R_cam, b), axis=1)
            out.append(float(np.median(r[big] / ang[big])))
        return min(out)

    def decision(self) -> SlamGyroDecision | None:
        """The decision once the data separates the conventions (None before)."""
        if self._decision is not None or len(self._slam_t) < 2:
            return self._decision
        if self._slam_t[-1] - self._last_try < self.retry_s:
            return None
        self._last_try = self._slam_t[-1]
        d = check_slam_gyro(
            np.asarray(self._imu_t),
            np.asarray(self._imu_w).reshape(-1, 3),
            np.asarray(self._slam_t),
            np.asarray(self._slam_q).reshape(-1, 4),
            self.body_R_cam,
            np.asarray(self._slam_s),
            self.options,
            refine_undecided=False,
        )
        if d is not None and d.decided:
            self._decision = d
        return self._decision


def _flight_decision(
    flight: Flight, options: SlamGyroOptions | None = None
) -> SlamGyroDecision | None:
    imu: ImuSeries = flight.imu
    slam: SlamSeries = flight.slam
    return check_slam_gyro(
        imu.t,
        imu.body_omega,
        slam.t,
        slam.slam_q_cam_wxyz,
        np.asarray(flight.calib.body_T_cam, float)[:3, :3],
        slam.session,
        options,
        force=True,
    )


def check_flight(flight: Flight, options: SlamGyroOptions | None = None) -> SlamGyroDecision:
    """The check on a whole flight's IMU and SLAM (decides on whatever rotation there is).

    Raises:
        FlightDataError: the flight has no IMU or SLAM stream, or too few SLAM pairs.
    """
    if flight.imu is None or flight.slam is None:
        raise FlightDataError(f"{flight.name}: the SLAM-vs-gyro check needs imu and slam streams")
    d = _flight_decision(flight, options)
    if d is None:
        raise FlightDataError(f"{flight.name}: too few SLAM pose pairs for the SLAM-vs-gyro check")
    return d


def check_modes(rotation: Any, time_offset: Any, source: str = "options") -> None:
    """Raise a one-line :class:`SlamConventionError` for bad ``slam_rotation`` /
    ``slam_time_offset`` values."""
    if rotation not in SLAM_ROTATION_MODES:
        raise SlamConventionError(
            f"{source}: slam_rotation = {rotation!r}; valid: {', '.join(SLAM_ROTATION_MODES)}"
        )
    number = isinstance(time_offset, int | float) and not isinstance(time_offset, bool)
    if number and not (math.isfinite(time_offset) and abs(time_offset) <= 1e6):
        raise SlamConventionError(
            f"{source}: slam_time_offset = {time_offset!r}; expected a number of seconds in "
            "[-1e6, 1e6] "
            f"or one of {', '.join(SLAM_TIME_OFFSET_MODES)}"
        )
    if not number and time_offset not in SLAM_TIME_OFFSET_MODES:
        raise SlamConventionError(
            f"{source}: slam_time_offset = {time_offset!r}; valid: "
            f"{', '.join(SLAM_TIME_OFFSET_MODES)} or a number of seconds"
        )


def check_extrinsic_mode(extrinsic: Any, source: str = "options") -> None:
    """Raise a one-line :class:`SlamConventionError` for a bad ``slam_extrinsic`` value."""
    if extrinsic not in SLAM_EXTRINSIC_MODES:
        raise SlamConventionError(
            f"{source}: slam_extrinsic = {extrinsic!r}; valid: {', '.join(SLAM_EXTRINSIC_MODES)}"
        )


def check_mirror_mode(mirror: Any, source: str = "options") -> None:
    """Raise a one-line :class:`SlamConventionError` for a bad ``slam_mirror`` value."""
    if mirror not in SLAM_MIRROR_MODES:
        raise SlamConventionError(
            f"{source}: slam_mirror = {mirror!r}; valid: {', '.join(SLAM_MIRROR_MODES)}"
        )


def invert_slam_rotations(slam: SlamSeries) -> SlamSeries:
    """The SLAM series with each orientation inverted (conjugate quaternion), positions kept."""
    q = np.array(slam.slam_q_cam_wxyz, float)
    q[:, 1:] *= -1.0
    return dataclasses.replace(slam, slam_q_cam_wxyz=q)


#: ``flight.meta`` key of the applied check (a flight carrying it is not checked again).
META_KEY = "slam_gyro_check"


def file_modes(flight: Flight, rotation: str, time_offset: str | float) -> tuple[str, str | float]:
    """``(slam_rotation, slam_time_offset)`` for this flight: a manifest's ``[slam]`` options
    (``flight.meta["slam_options"]``) win over the given ones."""
    per_file = (flight.meta.get("slam_options") if isinstance(flight.meta, dict) else None) or {}
    return per_file.get("slam_rotation", rotation), per_file.get("slam_time_offset", time_offset)


def apply_slam_check(
    flight: Flight,
    rotation: str = "auto",
    time_offset: str | float = "report",
    extrinsic: str = "auto",
    mirror: str = "auto",
) -> Flight:
    """Apply the ``slam_rotation`` / ``slam_time_offset`` options to a whole flight (batch).

    A manifest's ``[slam] slam_rotation`` / ``slam_time_offset`` (``flight.meta["slam_options"]``)
    win over the arguments. ``"auto"`` inverts the rotations when the inverse convention fits and
    the stated one does not (one warning line says so); ``"inverse"`` always inverts; a wrong
    ``body_T_cam`` rotation is named in a warning and, with ``extrinsic = "auto"``, replaced by
    the rotation the gyro fits (the calibration's translation kept; EuRoC with an identity
    rotation given: the fitted one is 0.6-1.1 deg from the true one on MH_01 and both V1_02
    files; simulated two turns about body z, 12 deg given: 2.9 deg, the rotation about the
    unexcited axes kept from the given one). ``"apply"`` adds the estimated offset to the
    SLAM times, a number adds that offset, ``"report"`` only logs it. With ``mirror = "auto"``,
    a decision that names the inverse convention or a wrong ``body_T_cam`` rotation is tested
    for a mirrored SLAM frame (:func:`check_mirror`): one whose axis is identified is
    un-mirrored and checked again, one whose axis is not is not used (``slam`` None); one line
    says so and ``record["mirrored"]`` names it. The result is recorded in
    ``flight.meta["slam_gyro_check"]``; a flight that has it is returned unchanged.
    """
    if flight.slam is None or flight.imu is None or {META_KEY, CAUSAL_META_KEY} & set(flight.meta):
        return flight
    rotation, time_offset = file_modes(flight, rotation, time_offset)
    check_modes(rotation, time_offset, "slam options")
    check_extrinsic_mode(extrinsic, "slam options")
    check_mirror_mode(mirror, "slam options")
    d = None
    if rotation == "auto" or isinstance(time_offset, str) or extrinsic == "auto":
        d = _flight_decision(flight)
        if d is None:
            log.info("%s: too few SLAM pose pairs for the SLAM-vs-gyro check", flight.name)
    mirrored: dict[str, Any] | None = None
    if (
        d is not None
        and mirror == "auto"
        and rotation == "auto"
        and (d.convention == "inverse" or not d.body_R_cam_ok)
    ):
        v = check_mirror(flight.imu, flight.slam, np.asarray(flight.calib.body_T_cam)[:3, :3])
        if v is not None and v.mirrored:
            mirrored = {"axis": None if v.axis is None else "xyz"[v.axis], "message": v.message()}
            if v.axis is None:
                log.warning("%s: %s: SLAM not used", flight.name, v.message())
                meta = {**flight.meta, META_KEY: {**d.summary(), "mirrored": mirrored}}
                return dataclasses.replace(flight, slam=None, meta=meta)
            log.warning("%s: %s: un-mirrored (slam_mirror = 'auto')", flight.name, v.message())
            flight = dataclasses.replace(flight, slam=unmirror_slam(flight.slam, v.axis))
            d = _flight_decision(flight)
    slam = flight.slam
    record: dict[str, Any] = {"slam_rotation": rotation, "slam_time_offset": time_offset}
    if mirrored is not None:
        record["mirrored"] = mirrored
    invert = rotation == "inverse"
    if d is not None:
        record.update(d.summary())
        if rotation == "auto" and d.convention == "inverse":
            invert = True
            log.warning(
                "%s: SLAM rotations are the inverse of the stated slam_R_cam (gyro residual "
                "%.2f deg inverted vs %.2f deg as stated): using them inverted",
                flight.name,
                d.residual_deg["inverse"],
                d.residual_deg["as-is"],
            )
        elif rotation == "as-is" and d.convention == "inverse":
            log.warning(
                "%s: slam_rotation = 'as-is' kept, but the inverse fits the gyro (%.2f vs %.2f "
                "deg)",
                flight.name,
                d.residual_deg["inverse"],
                d.residual_deg["as-is"],
            )
        msg = d.extrinsic_message()
        if msg:
            log.warning("%s: %s", flight.name, msg)
    calib = flight.calib
    record["body_R_cam_replaced"] = False
    if d is not None and not d.body_R_cam_ok and extrinsic == "auto":
        t_cam = np.asarray(calib.body_T_cam, float)[:3, 3]
        calib = dataclasses.replace(calib, body_T_cam=make_pose(d.body_R_cam_fit, t_cam))
        record["body_R_cam_replaced"] = True
        log.warning(
            "%s: using the body_T_cam rotation the gyro fits (slam_extrinsic = 'auto')",
            flight.name,
        )
    if invert:
        slam = invert_slam_rotations(slam)
    if isinstance(time_offset, str):
        offset = d.time_offset_s if d is not None and d.time_offset_ok else 0.0
        applied = time_offset == "apply"
        if d is not None and not d.time_offset_ok:
            log.info(
                "%s: SLAM clock offset not determined (rate correlation %.2f < %.2f: too little "
                "rotation to tell)",
                flight.name,
                d.offset_correlation,
                OFFSET_MIN_CORRELATION,
            )
    else:
        offset, applied = float(time_offset), True
    log.info(
        "%s: SLAM clock offset %+.4f s (t_imu = t_slam + offset)%s",
        flight.name,
        offset,
        " applied" if applied and offset else ", reported, not applied",
    )
    if applied and offset:
        slam = dataclasses.replace(slam, t=slam.t + offset)
    record["applied_time_offset_s"] = offset if applied else 0.0
    record["inverted"] = invert
    meta = {**flight.meta, META_KEY: record}
    return dataclasses.replace(flight, slam=slam, meta=meta, calib=calib)


#: ``flight.meta`` key of the causally applied check (:func:`apply_slam_check_causal`).
CAUSAL_META_KEY = "slam_gyro_check_causal"
#: :func:`apply_slam_check_causal`: SLAM time [s] after which undecided attempts are spaced by a
#: tenth of the time so far (1 s before).
RETRY_GROWTH_AFTER_S = 30.0


def apply_slam_check_causal(
    flight: Flight,
    rotation: str = "auto",
    time_offset: str | float = "report",
    extrinsic: str = "auto",
    max_s: float = 300.0,
) -> Flight:
    """The ``slam_rotation`` / ``slam_time_offset`` / ``slam_extrinsic`` options applied as a
    causal filter would apply them: each SLAM pose as decided when it *arrives*.

    The :class:`SlamGyroCheck` is fed the IMU and SLAM in arrival order (capture time plus the
    series' ``latency``). Poses arriving before its decision pass as stated; from the decision
    on (the pose that completes it included): with ``"auto"`` the decided convention, with
    ``extrinsic = "auto"`` and a ``body_T_cam`` rotation named wrong the orientation turned so
    that the *given* ``body_T_cam`` yields the fitted body rotation
    (``slam_R_cam' = slam_R_cam R_fit^T R_given``; the calibration is not changed, a filter
    reads it once at its start), and with ``"apply"`` the clock offset (a pose whose shifted
    time would not follow its predecessor's is left out and counted). ``"as-is"`` /
    ``"inverse"`` and a numeric offset are given before the flight and apply to every pose.
    Undecided after ``max_s`` of SLAM, or at the end: the rest as stated. This is what the
    filter baselines get (the batch smoother gets :func:`apply_slam_check`, the push-API
    smoother runs the same check itself). The record, with ``decided_at_s`` (arrival clock),
    is ``flight.meta[CAUSAL_META_KEY]``; a flight checked either way is returned unchanged.
    """
    if (
        flight.slam is None
        or flight.imu is None
        or META_KEY in flight.meta
        or CAUSAL_META_KEY in flight.meta
    ):
        return flight
    from .events import SlamPose, replay_flight

    rotation, time_offset = file_modes(flight, rotation, time_offset)
    check_modes(rotation, time_offset, "slam options")
    check_extrinsic_mode(extrinsic, "slam options")
    slam = flight.slam
    n = len(slam)
    decided_at = math.inf  # arrival time of the pose that completed the decision
    d: SlamGyroDecision | None = None
    if rotation == "auto" or time_offset == "apply" or extrinsic == "auto":
        sgc = SlamGyroCheck(np.asarray(flight.calib.body_T_cam, float)[:3, :3])
        t_first = None
        for ev in replay_flight(flight, ("imu", "slam")):
            sgc.add(ev)
            if not isinstance(ev, SlamPose):
                continue
            t_first = ev.t if t_first is None else t_first
            d = sgc.decision()
            if d is not None:
                decided_at = float(ev.arrival)
                break
            if ev.t - t_first > max_s:
                break
            # Each attempt fits all that has arrived: past RETRY_GROWTH_AFTER_S of SLAM the
            # attempts are spaced by a tenth of it (a flight that never decides, 120 s: 6.6 s
            # of fits with 1 s spacing); the decisions seen (EuRoC 4-12 s) come before.
            if ev.t - t_first > RETRY_GROWTH_AFTER_S:
                sgc.retry_s = max(1.0, 0.1 * (ev.t - t_first))
    record: dict[str, Any] = {
        "slam_rotation": rotation,
        "slam_time_offset": time_offset,
        "decided_at_s": None,
    }
    q = np.array(slam.slam_q_cam_wxyz, float)
    t = np.array(slam.t, float)
    late = slam.latency
    arrival = t + (np.zeros(n) if late is None else np.asarray(late, float))
    invert = np.zeros(n, bool)
    if rotation == "inverse":
        invert[:] = True
    after = arrival >= decided_at
    offset = 0.0
    if d is not None:
        record.update(d.summary())
        record["decided_at_s"] = decided_at
        log.info(
            "%s: SLAM-vs-gyro check decided at t=%.2f s (%s; the %d poses that arrived before "
            "it taken as stated)",
            flight.name,
            decided_at,
            d.convention,
            int((~after).sum()),
        )
        if rotation == "auto" and d.convention == "inverse":
            invert[after] = True
            log.warning(
                "%s: SLAM rotations are the inverse of the stated slam_R_cam (decided at t=%.2f "
                "s): inverted from there",
                flight.name,
                decided_at,
            )
        if time_offset == "apply" and d.time_offset_ok:
            offset = float(d.time_offset_s)
    shifted = after  # the poses the offset applies to: from the decision, or all if given
    if not isinstance(time_offset, str):
        offset, shifted = float(time_offset), np.ones(n, bool)
    q[invert, 1:] *= -1.0
    record["inverted_from"] = int(np.argmax(invert)) if invert.any() else None
    record["body_R_cam_turned"] = False
    if d is not None and not d.body_R_cam_ok and extrinsic == "auto":
        given = np.asarray(flight.calib.body_T_cam, float)[:3, :3]
        turn = np.asarray(d.body_R_cam_fit, float).T @ given
        R = quat_wxyz_to_matrix(q[after]) @ turn
        q[after] = matrix_to_quat_wxyz(R)
        record["body_R_cam_turned"] = True
        log.warning(
            "%s: body_T_cam rotation %.1f deg from the one the gyro fits: SLAM orientations "
            "turned to the fitted rotation from t=%.2f s (slam_extrinsic = 'auto')",
            flight.name,
            d.body_R_cam_error_deg,
            decided_at,
        )
    keep = np.ones(n, bool)
    if offset:
        t[shifted] += offset
        # arrival unchanged: a pose is not known earlier because its clock is corrected
        newest = -math.inf
        for i in range(n):  # each pose after the newest one kept
            if t[i] > newest:
                newest = t[i]
            else:
                keep[i] = False
        if not keep.all():
            log.warning(
                "%s: %d SLAM poses left out: the applied clock offset %+.4f s put them before "
                "their predecessor",
                flight.name,
                int((~keep).sum()),
                offset,
            )
    record["applied_time_offset_s"] = offset
    record["left_out"] = int((~keep).sum())
    new_late = None if late is None and not offset else np.maximum(arrival - t, 0.0)[keep]
    slam = dataclasses.replace(
        slam,
        t=t[keep],
        slam_t_cam=np.asarray(slam.slam_t_cam, float)[keep],
        slam_q_cam_wxyz=q[keep],
        session=np.asarray(slam.session)[keep],
        latency=new_late,
    )
    meta = {**flight.meta, CAUSAL_META_KEY: record}
    return dataclasses.replace(flight, slam=slam, meta=meta)


# ----------------------------------------------------------------------------------------------
# Mirrored (left-handed) SLAM frame
# ----------------------------------------------------------------------------------------------
#
# A bridge that flips one axis sign writes ``p' = D p`` and ``R' = D R D`` with ``D = diag`` of
# ones and one -1 (axis a). ``D = -R_a(pi)``, so ``R' = R_a(pi) R R_a(pi)`` is a proper rotation:
# a world turn (which the alignment absorbs) and a camera turn of 180 deg about camera axis a (a
# ``body_R_cam`` 180 deg off to the gyro check, or on yaw-only flights about a downward camera's
# optical axis the inverse convention), while ``p' = R_a(pi) (-p)`` needs a negative scale. The
# rotations alone cannot tell a mirror from a camera really mounted 180 deg turned; the positions
# can: :func:`position_scale` fits the SLAM's second differences to the accelerometer rotated
# into the SLAM frame by the SLAM's own orientations and a ``body_R_cam``, whose scale is positive
# for a right-handed frame and negative for a mirrored one.

#: Values of the ``slam_mirror`` option: ``"auto"``, a mirrored frame whose axis is identified is
#: un-mirrored (one warning line says so), one whose axis is not is not used; ``"off"``: not
#: checked.
SLAM_MIRROR_MODES = ("auto", "off")
#: :func:`check_mirror`: a hypothesis's position scale counts when positive with a relative
#: standard error at most this (simulated two-turns, seed 1: right hypotheses 0.04-0.06, wrong
#: ones negative or above 2).
MIRROR_MAX_REL_SE = 0.25
#: :func:`check_mirror`: the winning hypothesis's gyro residual (given ``body_R_cam``) at most this
#: many times the best residual any hypothesis fits (the noise floor), and every other counted
#: hypothesis's at least this many times the winner's.
MIRROR_RESIDUAL_RATIO = 1.5
MIRROR_MARGIN = 2.0
#: :func:`check_mirror`: a hypothesis counts only when its position fit explains the SLAM's
#: second differences (R^2, gravity and bias fitted) within this of the best hypothesis's (the
#: right one 0.84 at 12 s of simulated two-turns, a wrong convention 0.50-0.52 with a positive
#: but noisy scale).
MIRROR_R2_GAP = 0.1


def mirror_rotations(R: np.ndarray, axis: int) -> np.ndarray:
    """``D R D`` for each (N, 3, 3) rotation, ``D`` the identity with ``-1`` at ``axis``."""
    D = np.ones(3)
    D[axis] = -1.0
    return R * D[None, :, None] * D[None, None, :]


def unmirror_slam(slam: SlamSeries, axis: int) -> SlamSeries:
    """The SLAM series with the sign of ``axis`` (0, 1, 2: x, y, z) flipped in the positions and
    the orientations (``p -> D p``, ``R -> D R D``: its own inverse)."""
    D = np.ones(3)
    D[axis] = -1.0
    q = np.array(slam.slam_q_cam_wxyz, float)
    q[:, 1:] *= -D  # the rotation vector of D R D is -D times R's
    return dataclasses.replace(
        slam, slam_t_cam=np.asarray(slam.slam_t_cam, float) * D, slam_q_cam_wxyz=q
    )


def hat_kernel_integrals(
    imu_t: np.ndarray, a: np.ndarray, t_i: np.ndarray, t_j: np.ndarray, t_k: np.ndarray
) -> np.ndarray:
    """``int_i^j a (s - t_i) / h1 ds + int_j^k a (t_k - s) / h2 ds`` (P, 3) of the samples ``a``
    (M, 3) at ``imu_t`` against the hat kernel rising from 0 at ``t_i`` to 1 at ``t_j`` and
    falling to 0 at ``t_k`` (cumulative trapezoid sums of ``a`` and ``t a``, interpolated at the
    three times): times ``w = (h1 + h2) / 2`` it matches a divided second difference of the
    positions (:class:`fgnav.solvers.measurements.SecondDifferences`)."""
    imu_t = np.asarray(imu_t, dtype=float)
    dt = np.diff(imu_t)
    ta = imu_t[:, None] * a
    cum_a = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (a[1:] + a[:-1]) * dt[:, None], 0)])
    cum_ta = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (ta[1:] + ta[:-1]) * dt[:, None], 0)])

    def integral(cum: np.ndarray, t: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t, imu_t, cum[:, c]) for c in range(3)])

    Ia_ij = integral(cum_a, t_j) - integral(cum_a, t_i)
    Ita_ij = integral(cum_ta, t_j) - integral(cum_ta, t_i)
    Ia_jk = integral(cum_a, t_k) - integral(cum_a, t_j)
    Ita_jk = integral(cum_ta, t_k) - integral(cum_ta, t_j)
    rising = (Ita_ij - t_i[:, None] * Ia_ij) / (t_j - t_i)[:, None]
    falling = (t_k[:, None] * Ia_jk - Ita_jk) / (t_k - t_j)[:, None]
    return rising + falling


def position_scale(
    imu_t: np.ndarray,
    body_accel: np.ndarray,
    slam_t: np.ndarray,
    slam_p: np.ndarray,
    slam_R_cam: np.ndarray,
    body_R_cam: np.ndarray,
    session: np.ndarray | None = None,
    h: float = 0.5,
    step: float = 0.1,
) -> tuple[float, float, int, float]:
    """Scale [SLAM units per metre] of the SLAM positions against the accelerometer, rotated into
    the SLAM frame through the SLAM's own orientations: second differences of the positions over
    ``+-h`` (centres ``step`` apart, one session) against the hat-kernel integrals of
    ``slam_R_cam(t) body_R_cam^T f(t)`` (``f`` the specific force), least squares jointly with the
    gravity (a constant in the SLAM frame) and an accelerometer bias (body frame).

    Returns:
        ``(scale, rel_se, n, r2)``: negative for a mirrored frame; ``rel_se`` its relative
        standard error (inf with fewer than 10 second differences); ``r2`` the share of the
        second differences' variance the fit explains.
    """
    t = np.asarray(slam_t, float)
    P = np.asarray(slam_p, float)
    imu_t = np.asarray(imu_t, float)
    sess = np.zeros(len(t), int) if session is None else np.asarray(session)
    lo, hi = max(t[0], imu_t[0]) + h, min(t[-1], imu_t[-1]) - h
    centres, last = [], -np.inf
    for j in range(1, len(t) - 1):
        if lo <= t[j] <= hi and t[j] - last >= step - 1e-9:
            centres.append(j)
            last = t[j]
    if len(centres) < 10:
        return float("nan"), math.inf, len(centres), 0.0
    j = np.asarray(centres)
    i = np.minimum(np.searchsorted(t, t[j] - h), j - 1)
    k = np.maximum(np.minimum(np.searchsorted(t, t[j] + h), len(t) - 1), j + 1)
    ok = (sess[i] == sess[j]) & (sess[k] == sess[j])
    i, j, k = i[ok], j[ok], k[ok]
    if len(j) < 10:
        return float("nan"), math.inf, len(j), 0.0
    h1, h2 = t[j] - t[i], t[k] - t[j]
    w = 0.5 * (h1 + h2)
    sd2 = w[:, None] * ((P[k] - P[j]) / h2[:, None] - (P[j] - P[i]) / h1[:, None])
    Rs = slerp_rotations(t, np.asarray(slam_R_cam, float), imu_t)
    v = Rs @ (np.asarray(body_R_cam, float).T @ np.asarray(body_accel, float)[:, :, None])
    hat = hat_kernel_integrals(imu_t, v[:, :, 0], t[i], t[j], t[k])
    A = np.zeros((len(j), 3, 7))
    A[:, :, 0] = w[:, None] * hat
    A[:, :, 1:4] = (w**2)[:, None, None] * np.eye(3)
    A[:, :, 4:] = (w**2)[:, None, None] * (np.asarray(slam_R_cam, float)[j] @ body_R_cam.T)
    A = A.reshape(-1, 7)
    y = sd2.reshape(-1)
    x, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = y - A @ x
    cov = np.linalg.pinv(A.T @ A) * float(r @ r) / max(len(y) - 7, 1)
    scale = float(x[0])
    rel = float(np.sqrt(max(cov[0, 0], 0.0)) / abs(scale)) if scale else math.inf
    tss = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(r @ r) / tss if tss > 0 else 0.0
    return scale, rel, len(j), r2


@dataclass(frozen=True)
class MirrorVerdict:
    """Result of :func:`check_mirror`.

    Attributes:
        mirrored: the SLAM frame is left-handed.
        axis: the flipped axis (0, 1, 2) when identified, else None.
        hypotheses: ``"<convention>/<none|x|y|z>"`` -> ``(gyro residual with the given
            body_R_cam [deg], position scale, its rel. s.e., the position fit's R^2)``.
        convention: the winning hypothesis's rotation convention.
        conclusive: False when no hypothesis won (too little motion yet, or none fits the gyro
            through the given ``body_R_cam`` near the noise floor): not mirrored, so far.
    """

    mirrored: bool
    axis: int | None
    hypotheses: dict[str, tuple[float, float, float, float]]
    convention: str = "as-is"
    conclusive: bool = True

    def message(self) -> str:
        """One line naming the mirrored frame."""
        if self.axis is None:
            return (
                "slam-mirrored: the SLAM frame is left-handed (an axis sign flipped; which one "
                "the motion does not tell)"
            )
        return f"slam-mirrored: the SLAM frame is left-handed (axis {'xyz'[self.axis]} sign?)"


def check_mirror(
    imu: ImuSeries, slam: SlamSeries, body_R_cam: np.ndarray, options: SlamGyroOptions | None = None
) -> MirrorVerdict | None:
    """Is the SLAM frame mirrored? Eight hypotheses (the stated or inverse rotation convention,
    times no axis or one of x, y, z flipped) are scored with the *given* ``body_R_cam``: the
    gyro residual of the SLAM-vs-gyro check and the sign of :func:`position_scale`. Among those
    with a positive, determined scale (rel. s.e. at most :data:`MIRROR_MAX_REL_SE`, R^2 within
    :data:`MIRROR_R2_GAP` of the best) the one of
    least residual wins when that residual is within :data:`MIRROR_RESIDUAL_RATIO` of the noise
    floor (the best any hypothesis fits, or the SLAM-vs-gyro fit with a free ``body_R_cam``) and
    every other counted one is :data:`MIRROR_MARGIN` times worse. A winning
    flip is the mirror; flips tied within the margin (and no unflipped one among them): mirrored,
    axis unknown. None: too little data to tell.
    """
    o = options or SlamGyroOptions()
    X = np.asarray(body_R_cam, float)
    imu_t = np.asarray(imu.t, float)
    t = np.asarray(slam.t, float)
    R0 = quat_wxyz_to_matrix(np.asarray(slam.slam_q_cam_wxyz, float))
    P0 = np.asarray(slam.slam_t_cam, float)
    sess = np.asarray(slam.session)
    if len(imu_t) < 2 or len(t) < 3:
        return None
    # The gyro residuals with the given rotation (bias fitted; the coarse clock offset, which
    # neither the convention nor a flip changes): one integration, the pairs once.
    inside = (t > imu_t[0] + o.max_offset_s) & (t < imu_t[-1] - o.max_offset_s)
    p0 = _pairs(t[inside], R0[inside], sess[inside], o)
    if len(p0.t_i) < 4:
        return None
    omega = np.asarray(imu.body_omega, float)
    offset, _ = _coarse_offset(imu_t, omega, p0, o)
    core = _Core(imu_t, _integrate(imu_t, omega), p0, offset)
    # The noise floor: what a free body_R_cam fits (the same for every flip: a flip turns the
    # camera increments by a fixed rotation, which a free body_R_cam takes up). A hypothesis
    # must come near it with the given rotation: a given rotation wrong by another angle fits
    # no hypothesis (EuRoC MH_01 with the identity given, 173 deg off: 3.0-5.1 deg against 0.09).
    fitted = min(core.fit(c, X)[2] for c in ("as-is", "inverse"))
    hyp: dict[str, tuple[float, float, float, float]] = {}
    for flip in (None, 0, 1, 2):
        R = R0 if flip is None else mirror_rotations(R0, flip)
        D = np.ones(3)
        if flip is not None:
            D[flip] = -1.0
        core.p = p = _pairs(t[inside], R[inside], sess[inside], o)
        for conv in ("as-is", "inverse"):
            C = _camera_increments(p, conv)
            _, b = core._gauss_newton(C, so3_log(C), X, free_rotation=False)
            resid = _median_deg(core.residuals(C, X, b))
            RR = R if conv == "as-is" else np.transpose(R, (0, 2, 1))
            s, rel, _, r2 = position_scale(imu_t, imu.body_accel, t, P0 * D, RR, X, sess)
            name = f"{conv}/{'none' if flip is None else 'xyz'[flip]}"
            hyp[name] = (resid, s, rel, r2)
    floor = min(fitted, *(v[0] for v in hyp.values()))
    r2_max = max(v[3] for v in hyp.values())
    counted = {
        k: v
        for k, v in hyp.items()
        if v[1] > 0 and v[2] <= MIRROR_MAX_REL_SE and v[3] >= r2_max - MIRROR_R2_GAP
    }
    if not counted:
        return MirrorVerdict(False, None, hyp, conclusive=False)
    best = min(counted, key=lambda k: counted[k][0])
    r_best = counted[best][0]
    if r_best > MIRROR_RESIDUAL_RATIO * max(floor, 1e-9):
        return MirrorVerdict(False, None, hyp, conclusive=False)
    if best.endswith("/none"):
        return MirrorVerdict(False, None, hyp, best.split("/")[0])
    close = [k for k, v in counted.items() if k != best and v[0] < MIRROR_MARGIN * r_best]
    if any(k.endswith("/none") for k in close):
        return MirrorVerdict(False, None, hyp, conclusive=False)
    axes = {best[-1]} | {k[-1] for k in close}
    axis = "xyz".index(best[-1]) if len(axes) == 1 else None
    return MirrorVerdict(True, axis, hyp, best.split("/")[0])
