"""MSF-style error-state EKF with the visual scale and the SLAM-frame drift in the state.

The strongest filter anchor fgnav is compared against (Weiss & Siegwart 2011, "Real-time metric
state estimation for modular vision-inertial systems"; ethzasl_msf's pose sensor). It fuses:

* IMU propagation (strapdown, gravity ``(0, 0, -g)`` in world z up, body FLU);
* monocular-SLAM camera poses of unknown scale, with the model of DESIGN.md section 4.2::

      slam_t_cam = s * slam_R_world * (world_t_body + world_R_body * body_t_cam) + slam_t_world
      slam_R_cam = slam_R_world * world_R_body * body_R_cam          (optional, on by default)

  where ``s`` (SLAM units per metre), ``slam_R_world`` and ``slam_t_world`` are filter states (the
  MSF ``lambda``, ``q_wv``, ``p_wv``); a SLAM map reset (new session id) re-initialises them;
* optionally a downward rangefinder ``r = (z_sensor - ground) / cos(tilt)`` (ground height fixed
  at the first valid reading, so terrain steps bias it; the smoother estimates ground instead).

Error state (22): ``[dp(3) world, dv(3) world, dtheta(3) body (right perturbation),
dbg(3), dba(3), ds(1), dphi_sw(3) (right perturbation of slam_R_world), dslam_t_world(3)]``.

Measurements are Mahalanobis-gated (chi-square). Corrupted IMU samples are dropped and counted
(:mod:`fgnav.baselines._inputs`); over an IMU gap the covariance is widened
(``GAP_ACCEL_SIGMA``, ``GAP_RATE_SIGMA``); when every SLAM pose has been gated for
``slam_reset_s`` the filter has diverged, and the vehicle's position, velocity and attitude are
re-initialised from the SLAM (``gating_resets``, a warning) through the alignment as it was
``slam_reset_s`` before the gating began (the poses fused between the fault and the gate's
closing had moved it).

Delayed measurements (SLAM poses arriving ``latency`` seconds after their image time) are handled
MSF-style with a state buffer: the filter restores the buffered state at the image time, applies
the update and re-propagates the IMU to the present. The reported trajectory is causal: each
output sample is what the filter knew at that time, before any later correction.

Not modelled: rotor drag (MSF has none), IMU-camera time offset and extrinsic calibration states,
SLAM scale drift beyond a random walk.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from fgnav.baselines._arrived import Arrived
from fgnav.baselines._counts import SlamRangeCounts
from fgnav.baselines._inputs import (
    GAP_ACCEL_SIGMA,
    GAP_RATE_SIGMA,
    IMU_GAP_S,
    Inputs,
    unused_table,
)
from fgnav.baselines._options import SlamRangeOptions
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import (
    AttitudeSample,
    Event,
    ImuSample,
    RangeReading,
    SlamPose,
    replay_flight,
)
from fgnav.datasets.geometry import (
    GRAVITY,
    matrix_to_quat_wxyz,
    quat_wxyz_to_matrix,
    skew,
    so3_exp,
    so3_log,
)
from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, RangeLimits
from fgnav.datasets.types import (
    Calibration,
    Flight,
    Trajectory,
)
from fgnav.estimate import Estimate, TimeSeries
from fgnav.solvers.measurements import gyro_bias_from_slam, level_rotation_from_accel

log = logging.getLogger(__name__)


# Error-state layout.
IP, IV, ITH, IBG, IBA, IS, IPHI, ITSW = 0, 3, 6, 9, 12, 15, 16, 19
N_ERR = 22

MIN_SCALE_REL_SIGMA = 0.05
"""Floor of the initial relative scale uncertainty (the closed-form fit neglects biases)."""

RESET_SCALE_REL_SIGMA = 0.5
"""Relative scale uncertainty after a SLAM map reset when no closed-form fit was possible."""

REINIT_GIVE_UP_S = 20.0
"""After a map reset, how long to wait for the closed-form scale before keeping the old one."""

FIT_RETRY_S = 0.5
"""Before the start, how often the closed-form scale fit is tried on the data that has arrived."""

HISTORY_BEFORE_START_S = 40.0
"""Before the start, how much of the arrived data is kept for the fit (longest window 32 s)."""

SLAM_VELOCITY_SPAN_S = 0.3
"""A re-initialisation from the SLAM takes the velocity over at least this span of poses [s]."""

ALIGN_HISTORY_S = 5.0
"""The alignment after each fused SLAM pose is kept this long [s] (a gating reset goes back
``slam_reset_s`` before the gating began: :meth:`MsfEkf._restore_alignment`)."""

# Chi-square quantiles (probability 0.999) for the gates, by measurement dimension.
CHI2_999 = {1: 10.83, 3: 16.27, 6: 22.46}


@dataclass
class MsfOptions(SlamRangeOptions):
    """Options of :class:`MsfEkf`: the shared SLAM and range options
    (:class:`~fgnav.baselines._options.SlamRangeOptions`; the SLAM orientation is the MSF pose
    sensor's, ``initial_scale`` None is :func:`initial_scale_guess`, and
    ``initial_scale_rel_sigma`` None three times its standard error) and:

    Attributes:
        alignment_walk_rot, alignment_walk_pos: random walk of the SLAM alignment
            [rad/sqrt(s)], [SLAM units/sqrt(s)].
        output_rate_hz: rate of the reported causal trajectory.
        buffer_s: how far back delayed measurements may reach [s]; older ones are counted and
            skipped.
    """

    alignment_walk_rot: float = 1e-4
    alignment_walk_pos: float = 1e-3
    output_rate_hz: float = 20.0
    buffer_s: float = 1.0


@dataclass
class _State:
    p: np.ndarray
    v: np.ndarray
    R: np.ndarray
    bg: np.ndarray
    ba: np.ndarray
    s: float
    slam_R_world: np.ndarray
    slam_t_world: np.ndarray
    P: np.ndarray

    def copy(self) -> _State:
        return _State(
            self.p.copy(),
            self.v.copy(),
            self.R.copy(),
            self.bg.copy(),
            self.ba.copy(),
            float(self.s),
            self.slam_R_world.copy(),
            self.slam_t_world.copy(),
            self.P.copy(),
        )


@dataclass
class MsfCounts(SlamRangeCounts):
    """What the filter did with its measurements (reported, never silent): the shared counts
    and measurements too old for the history / replayed after a delayed one."""

    too_old: int = 0
    replayed: int = 0


def pose_covariance(x: _State) -> np.ndarray:
    """(6, 6) covariance of the pose in GTSAM's Pose3 tangent order ``[rot, trans]`` (body
    frame, right perturbation) from the filter's ``[dtheta(body), dp(world)]`` blocks."""
    J = np.zeros((6, N_ERR))
    J[0:3, ITH : ITH + 3] = np.eye(3)
    J[3:6, IP : IP + 3] = x.R.T
    return J @ x.P @ J.T


SCALE_INIT_WINDOWS_S = (4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0)
"""Windows tried, in order, by :func:`initial_scale_guess` until the scale is determined."""


def initial_scale_guess(flight: Flight, max_rel_std: float = 0.05) -> float:
    """Closed-form initial ``s`` (SLAM units per metre); see :func:`initial_state_guess`."""
    return initial_state_guess(flight, max_rel_std)[0]


@dataclass(frozen=True)
class InitFit:
    """Result of the closed-form initialisation over one window ``[t_start, t_end]``.

    Attributes:
        scale: ``s`` (SLAM units per metre).
        rel_std: relative standard error of ``scale``.
        t_start, t_end: the window [s]; the filter starts at ``t_end`` (causal).
        world_v_body_start, world_v_body_end: velocity at the window's ends [m/s].
        world_R_body_end: attitude at ``t_end``.
        gyro_bias: gyro bias [rad/s] used (from SLAM rotation increments without an attitude
            stream, else zero).
    """

    scale: float
    rel_std: float
    t_start: float
    t_end: float
    world_v_body_start: np.ndarray
    world_v_body_end: np.ndarray
    world_R_body_end: np.ndarray
    gyro_bias: np.ndarray


def initial_state_guess(
    flight: Flight, max_rel_std: float = 0.05
) -> tuple[float, np.ndarray, float]:
    """Closed-form initial ``s`` (SLAM units per metre) from the start of the flight.

    With ``slam_R_world`` fixed by the first SLAM orientation and the initial attitude, and the
    IMU double-integrated with zero initial velocity (``D(t)``; attitude from the attitude
    stream or integrated gyro), the SLAM positions follow the linear model::

        slam_t_cam(t) = s * slam_R_world * (D(t) + world_R_body(t) * body_t_cam)
                        + u * t + c + w * t^2 / 2

    with unknowns ``s``, ``u = s slam_R_world v0``, ``c`` and ``w`` (the accelerometer bias seen
    through a nearly constant attitude). Solved by least squares over growing windows
    (``SCALE_INIT_WINDOWS_S``) until the standard error of ``s`` is below ``max_rel_std`` of
    ``s``. Returns ``(s, world_v_body0, rel_std)``: the initial velocity follows from ``u``,
    ``rel_std`` is the relative standard error of ``s``. Raises
    :class:`FlightDataError` when no window determines it.
    """
    slam, imu = flight.slam, flight.imu
    if slam is None or imu is None:
        raise FlightDataError(f"{flight.name}: MSF needs IMU and SLAM streams")
    fit, last = _fit_from(flight, max(slam.t[0], imu.t[0]), max_rel_std)
    if fit is None:
        raise FlightDataError(
            f"{flight.name}: the start of the flight does not determine the SLAM scale "
            f"(last try: {last}); pass MsfOptions.initial_scale"
        )
    return fit.scale, fit.world_v_body_start, fit.rel_std


def new_map_scale_guess(
    flight: Flight, t_first: float, t_meas: float, t_now: float, min_rel_sigma: float
) -> tuple[float, float] | None:
    """Closed-form scale of a new SLAM map (after a reset) from the data received since its
    first pose ``t_first``, causally: SLAM up to ``t_meas``, IMU and attitude up to ``t_now``.

    Returns ``(s, rel_sigma)`` with ``rel_sigma = max(2 * standard error, min_rel_sigma)``, or
    None while the map is younger than the first fit window or the data do not fix the scale.
    """
    if t_meas - t_first < SCALE_INIT_WINDOWS_S[0]:
        return None
    sub = dataclasses.replace(
        flight,
        imu=flight.imu.between(t_first, t_now),
        slam=flight.slam.between(t_first, t_meas),
        attitude=flight.attitude.between(t_first, t_now) if flight.attitude else None,
    )
    try:
        s, _, rel = initial_state_guess(sub)
    except FlightDataError:
        return None
    return s, max(2.0 * rel, min_rel_sigma)


def initial_fit(flight: Flight, max_rel_std: float = 0.05, step_s: float = 2.0) -> InitFit:
    """The first window of the flight that determines the SLAM scale (see
    :func:`initial_state_guess` for the model): windows start at the first SLAM pose and slide by
    ``step_s`` while the vehicle has not moved enough (a static start, as in EuRoC). Without an
    attitude stream the gyro bias is first estimated from the window's SLAM rotation increments
    (metric-free), so the integrated attitude does not drift. Raises :class:`FlightDataError`
    when no window of the flight determines the scale."""
    slam, imu = flight.slam, flight.imu
    if slam is None or imu is None:
        raise FlightDataError(f"{flight.name}: MSF needs IMU and SLAM streams")
    t_from = max(slam.t[0], imu.t[0])
    last = None
    while t_from + SCALE_INIT_WINDOWS_S[0] <= min(slam.t[-1], imu.t[-1]):
        fit, last = _fit_from(flight, t_from, max_rel_std)
        if fit is not None:
            return fit
        t_from += step_s
    raise FlightDataError(
        f"{flight.name}: no window of the flight determines the SLAM scale "
        f"(last try: {last}); pass MsfOptions.initial_scale"
    )


def arrived_initial_fit(
    arrived: Arrived, prefix: Flight, t_now: float, counts: SlamRangeCounts
) -> InitFit | None:
    """:func:`initial_fit` on the arrived ``prefix`` for a filter's start: None while the
    arrived data do not fix the scale (the history is then trimmed to
    ``HISTORY_BEFORE_START_S`` before ``t_now``); else the fit, its window counted as
    ``init_window_s`` (seconds from the first SLAM pose)."""
    try:
        fit = initial_fit(prefix)
    except FlightDataError:
        arrived.trim(t_now - HISTORY_BEFORE_START_S)
        return None
    t0 = prefix.slam.t[0]
    counts.extra["init_window_s"] = (fit.t_start - t0, fit.t_end - t0)
    return fit


def _fit_from(flight: Flight, t0: float, max_rel_std: float) -> tuple[InitFit | None, tuple | None]:
    """Growing windows from ``t0``; the first that determines ``s``, and the last try."""
    slam, imu = flight.slam, flight.imu
    last = None
    for window_s in SCALE_INIT_WINDOWS_S:
        j = np.flatnonzero((slam.t >= t0) & (slam.t <= t0 + window_s))
        if len(j) == 0:
            break
        j = j[slam.session[j] == slam.session[j[0]]]
        k = np.flatnonzero((imu.t >= t0) & (imu.t <= slam.t[j[-1]]))
        if len(j) < 10 or len(k) < 20:
            continue
        fit = _scale_lsq(flight, j, k, t0)
        last = (window_s, fit.scale, fit.rel_std)
        if np.isfinite(fit.scale) and fit.scale > 0 and fit.rel_std < max_rel_std:
            log.info(
                "initial SLAM scale %.4f (+-%.1f %%) from %.0f s of data at t=%.1f s",
                fit.scale,
                100 * fit.rel_std,
                window_s,
                t0 - slam.t[0],
            )
            return fit, last
        if slam.t[j[-1]] < t0 + window_s - 1.0:
            break
    return None, last


def _scale_lsq(flight: Flight, j: np.ndarray, k: np.ndarray, t0: float) -> InitFit:
    slam, imu = flight.slam, flight.imu
    gyro_bias = np.zeros(3)
    if flight.attitude is not None:
        att = flight.attitude
        idx = np.clip(np.searchsorted(att.t, imu.t[k]), 0, len(att) - 1)
        Rs = quat_wxyz_to_matrix(att.world_q_body_wxyz[idx])
    else:
        t1 = slam.t[j[-1]]
        sub_slam = slam.select(j)
        gyro_bias = gyro_bias_from_slam(imu.between(t0, t1), sub_slam, flight.calib.body_T_cam)
        R = level_rotation_from_accel(imu.body_accel[k[:20]].mean(axis=0))
        Rs = np.empty((len(k), 3, 3))
        for m, i in enumerate(k):
            Rs[m] = R
            if i + 1 < len(imu):
                R = R @ so3_exp((imu.body_omega[i] - gyro_bias) * (imu.t[i + 1] - imu.t[i]))
    a_w = np.einsum("nij,nj->ni", Rs, imu.body_accel[k]) - np.array([0.0, 0.0, GRAVITY])
    dt = np.diff(imu.t[k], append=imu.t[k][-1])[:, None]
    v = np.cumsum(a_w * dt, axis=0) - a_w * dt  # velocity at the start of each step
    step = v * dt + 0.5 * a_w * dt**2
    D = np.cumsum(step, axis=0) - step  # displacement at the start of each step
    slam_R = quat_wxyz_to_matrix(slam.slam_q_cam_wxyz[j])
    body_R_cam = flight.calib.body_T_cam[:3, :3]
    body_t_cam = flight.calib.body_T_cam[:3, 3]
    slam_R_world = slam_R[0] @ (Rs[0] @ body_R_cam).T
    ts = slam.t[j] - t0
    m = np.clip(np.searchsorted(imu.t[k], slam.t[j]), 0, len(k) - 1)
    pc = D[m] + np.einsum("nij,j->ni", Rs[m], body_t_cam)
    A = np.zeros((3 * len(j), 10))
    A[:, 0] = (pc @ slam_R_world.T).ravel()
    for ax in range(3):
        A[ax::3, 1 + ax] = ts
        A[ax::3, 4 + ax] = 1.0
        A[ax::3, 7 + ax] = 0.5 * ts**2
    b = slam.slam_t_cam[j].ravel()
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    res = b - A @ sol
    dof = max(len(b) - A.shape[1], 1)
    cov = (res @ res / dof) * np.linalg.pinv(A.T @ A)
    s = float(sol[0])
    ok = s != 0 and np.isfinite(s)
    v0 = slam_R_world.T @ sol[1:4] / s if ok else np.zeros(3)
    # w = -s slam_R_world b: the accelerometer bias b (world) integrated over the window.
    bias_world = -slam_R_world.T @ sol[7:10] / s if ok else np.zeros(3)
    return InitFit(
        scale=s,
        rel_std=float(np.sqrt(max(cov[0, 0], 0.0)) / abs(s)) if ok else np.inf,
        t_start=float(t0),
        t_end=float(slam.t[j[-1]]),
        world_v_body_start=v0,
        world_v_body_end=v0 + v[m[-1]] - bias_world * ts[-1],
        world_R_body_end=Rs[m[-1]],
        gyro_bias=gyro_bias,
    )


class MsfEkf:
    """Error-state EKF, MSF style. See the module docstring for the model.

    Fed events in arrival order (:meth:`start`, then :meth:`feed` per event, :meth:`latest`,
    :meth:`result`), as every fgnav estimator is; :meth:`run` replays a flight into it. The
    filter starts once the data that has arrived fixes the SLAM scale. The primitives
    (:meth:`initialize`, :meth:`propagate`, ``update_*``) can also be driven directly.
    """

    def __init__(self, options: MsfOptions | None = None) -> None:
        self.opt = options or MsfOptions()
        self.opt.check()  # (the config path checks it before; here the Python API)
        self.x: _State | None = None
        self.counts = MsfCounts()
        self._body_T_cam = np.eye(4)
        self._body_T_range = np.eye(4)
        self._ground = None
        self._noise = None
        self._scale_rel_sigma = 0.3

    # ------------------------------------------------------------------------------------------
    # Set-up
    # ------------------------------------------------------------------------------------------

    def initialize(
        self,
        world_R_body: np.ndarray,
        slam_t_cam: np.ndarray,
        slam_R_cam: np.ndarray,
        scale: float,
        body_T_cam: np.ndarray,
        imu_noise,
        world_v_body: np.ndarray | None = None,
    ) -> None:
        """Start at world origin with attitude ``world_R_body``; the SLAM alignment follows from
        the first SLAM pose and ``scale``."""
        o = self.opt
        self._body_T_cam = np.asarray(body_T_cam, float)
        self._noise = imu_noise
        body_R_cam = self._body_T_cam[:3, :3]
        body_t_cam = self._body_T_cam[:3, 3]
        p = np.zeros(3)
        slam_R_world = slam_R_cam @ (world_R_body @ body_R_cam).T
        slam_t_world = slam_t_cam - scale * slam_R_world @ (p + world_R_body @ body_t_cam)
        P = np.zeros((N_ERR, N_ERR))
        P[IP : IP + 3, IP : IP + 3] = np.eye(3) * 1e-6
        P[IV : IV + 3, IV : IV + 3] = np.eye(3) * o.initial_velocity_sigma**2
        P[ITH : ITH + 3, ITH : ITH + 3] = np.diag([0.02**2, 0.02**2, 1e-6])
        P[IBG : IBG + 3, IBG : IBG + 3] = np.eye(3) * o.initial_bias_sigma_gyro**2
        P[IBA : IBA + 3, IBA : IBA + 3] = np.eye(3) * o.initial_bias_sigma_accel**2
        self._reset_alignment_cov(P, scale)
        v = np.zeros(3) if world_v_body is None else np.asarray(world_v_body, float)
        self.x = _State(
            p,
            v,
            world_R_body.copy(),
            np.zeros(3),
            np.zeros(3),
            float(scale),
            slam_R_world,
            slam_t_world,
            P,
        )

    def _reset_alignment_cov(self, P: np.ndarray, scale: float) -> None:
        P[IS:, :] = 0.0
        P[:, IS:] = 0.0
        P[IS, IS] = (self._scale_rel_sigma * scale) ** 2
        P[IPHI : IPHI + 3, IPHI : IPHI + 3] = np.eye(3) * 0.05**2
        P[ITSW : ITSW + 3, ITSW : ITSW + 3] = np.eye(3) * (0.1 * scale) ** 2

    def reset_session(
        self,
        slam_t_cam: np.ndarray,
        slam_R_cam: np.ndarray,
        scale: float | None = None,
        scale_rel_sigma: float = RESET_SCALE_REL_SIGMA,
    ) -> None:
        """A SLAM map reset: new frame and scale. Keep the vehicle state and re-anchor the
        alignment on this pose, with ``scale`` (or the old ``s`` when None) as the new map's
        initial scale."""
        x = self.x
        body_R_cam = self._body_T_cam[:3, :3]
        body_t_cam = self._body_T_cam[:3, 3]
        if scale is not None:
            x.s = float(scale)
        x.slam_R_world = slam_R_cam @ (x.R @ body_R_cam).T
        x.slam_t_world = slam_t_cam - x.s * x.slam_R_world @ (x.p + x.R @ body_t_cam)
        self._scale_rel_sigma = scale_rel_sigma
        self._reset_alignment_cov(x.P, x.s)
        self.counts.session_resets += 1

    # ------------------------------------------------------------------------------------------
    # Propagation
    # ------------------------------------------------------------------------------------------

    def propagate(self, omega: np.ndarray, f: np.ndarray, dt: float) -> None:
        """Strapdown step with body rate ``omega`` [rad/s] and specific force ``f`` [m/s^2]."""
        if dt <= 0:
            return
        x = self.x
        o = self.opt
        n = self._noise
        w = omega - x.bg
        a_b = f - x.ba
        a_w = x.R @ a_b + np.array([0.0, 0.0, -GRAVITY])
        x.p = x.p + x.v * dt + 0.5 * a_w * dt * dt
        x.v = x.v + a_w * dt
        dR = so3_exp(w * dt)
        Phi = np.eye(N_ERR)
        Phi[IP : IP + 3, IV : IV + 3] = np.eye(3) * dt
        Phi[IV : IV + 3, ITH : ITH + 3] = -x.R @ skew(a_b) * dt
        Phi[IV : IV + 3, IBA : IBA + 3] = -x.R * dt
        Phi[ITH : ITH + 3, ITH : ITH + 3] = dR.T
        Phi[ITH : ITH + 3, IBG : IBG + 3] = -np.eye(3) * dt
        x.R = x.R @ dR
        q = np.zeros(N_ERR)
        q[IV : IV + 3] = n.accel_noise_density**2 * dt
        q[ITH : ITH + 3] = n.gyro_noise_density**2 * dt
        q[IBG : IBG + 3] = n.gyro_random_walk**2 * dt
        q[IBA : IBA + 3] = n.accel_random_walk**2 * dt
        q[IS] = (o.scale_walk * x.s) ** 2 * dt
        q[IPHI : IPHI + 3] = o.alignment_walk_rot**2 * dt
        q[ITSW : ITSW + 3] = o.alignment_walk_pos**2 * dt
        if dt > IMU_GAP_S:
            # An IMU gap: the held sample says little about the motion over it.
            q[IP : IP + 3] += (0.5 * GAP_ACCEL_SIGMA * dt * dt) ** 2
            q[IV : IV + 3] += (GAP_ACCEL_SIGMA * dt) ** 2
            q[ITH : ITH + 3] += (GAP_RATE_SIGMA * dt) ** 2
        P = Phi @ x.P @ Phi.T
        P[np.diag_indices(N_ERR)] += q
        x.P = 0.5 * (P + P.T)

    # ------------------------------------------------------------------------------------------
    # Updates
    # ------------------------------------------------------------------------------------------

    def _correct(self, H: np.ndarray, r: np.ndarray, Rm: np.ndarray, dim: int) -> bool:
        """EKF correction with residual ``r = z - h(x)``; False when gated out."""
        x = self.x
        S = H @ x.P @ H.T + Rm
        if self.opt.gate:
            d2 = float(r @ np.linalg.solve(S, r))
            if d2 > CHI2_999[dim]:
                return False
        K = np.linalg.solve(S, H @ x.P).T
        dx = K @ r
        IKH = np.eye(N_ERR) - K @ H
        x.P = IKH @ x.P @ IKH.T + K @ Rm @ K.T
        x.p = x.p + dx[IP : IP + 3]
        x.v = x.v + dx[IV : IV + 3]
        x.R = x.R @ so3_exp(dx[ITH : ITH + 3])
        x.bg = x.bg + dx[IBG : IBG + 3]
        x.ba = x.ba + dx[IBA : IBA + 3]
        x.s = float(x.s + dx[IS])
        x.slam_R_world = x.slam_R_world @ so3_exp(dx[IPHI : IPHI + 3])
        x.slam_t_world = x.slam_t_world + dx[ITSW : ITSW + 3]
        return True

    def update_slam(self, slam_t_cam: np.ndarray, slam_R_cam: np.ndarray | None) -> bool:
        """Fuse one SLAM camera pose (position, and orientation if enabled and given)."""
        x = self.x
        o = self.opt
        body_R_cam = self._body_T_cam[:3, :3]
        body_t_cam = self._body_T_cam[:3, 3]
        world_t_cam = x.p + x.R @ body_t_cam
        h = x.s * x.slam_R_world @ world_t_cam + x.slam_t_world
        Hp = np.zeros((3, N_ERR))
        Hp[:, IP : IP + 3] = x.s * x.slam_R_world
        Hp[:, ITH : ITH + 3] = -x.s * x.slam_R_world @ x.R @ skew(body_t_cam)
        Hp[:, IS] = x.slam_R_world @ world_t_cam
        Hp[:, IPHI : IPHI + 3] = -x.s * x.slam_R_world @ skew(world_t_cam)
        Hp[:, ITSW : ITSW + 3] = np.eye(3)
        rp = slam_t_cam - h
        if o.use_slam_rotation and slam_R_cam is not None:
            h_R = x.slam_R_world @ x.R @ body_R_cam
            rr = so3_log(h_R.T @ slam_R_cam)
            Hr = np.zeros((3, N_ERR))
            Hr[:, ITH : ITH + 3] = body_R_cam.T
            Hr[:, IPHI : IPHI + 3] = body_R_cam.T @ x.R.T
            H = np.vstack([Hp, Hr])
            r = np.concatenate([rp, rr])
            Rm = np.diag(
                [(x.s * o.slam_position_sigma_m) ** 2] * 3 + [o.slam_rotation_sigma**2] * 3
            )
            ok = self._correct(H, r, Rm, 6)
        else:
            ok = self._correct(Hp, rp, np.eye(3) * (x.s * o.slam_position_sigma_m) ** 2, 3)
        return self.counts.gated("slam", ok)

    def update_range(self, r_meas: float) -> bool:
        """Fuse one tilted-rangefinder reading against the fixed ground height."""
        x = self.x
        o = self.opt
        body_R_range = self._body_T_range[:3, :3]
        body_t_range = self._body_T_range[:3, 3]
        d_body = body_R_range[:, 2]
        c = -(x.R @ d_body)[2]
        if c < np.cos(o.range_max_tilt_rad):
            self.counts.range_rejected_tilt += 1
            return False
        num = x.p[2] + (x.R @ body_t_range)[2] - self._ground
        h = num / c
        dnum = np.zeros(N_ERR)
        dnum[IP + 2] = 1.0
        dnum[ITH : ITH + 3] = (-x.R @ skew(body_t_range))[2]
        dc = np.zeros(N_ERR)
        dc[ITH : ITH + 3] = (x.R @ skew(d_body))[2]
        H = ((dnum * c - num * dc) / c**2)[None, :]
        ok = self._correct(H, np.array([r_meas - h]), np.array([[o.range_sigma**2]]), 1)
        return self.counts.gated("range", ok)

    # ------------------------------------------------------------------------------------------
    # Event stream (the estimator never sees the flight; see fgnav.datasets.events)
    # ------------------------------------------------------------------------------------------

    def start(self, calib: Calibration, name: str = "flight") -> None:
        """Prepare to be fed events of a vehicle with calibration ``calib``."""
        self._calib = calib
        self._name = name
        self._body_T_range = np.asarray(calib.body_T_range, float)
        self._hist = Arrived()
        self._queue: list[Event] = []  # measurements that arrived after the newest IMU sample
        self._imu_prev: ImuSample | None = None
        self._snaps: list[tuple[int, _State]] = []  # (IMU sample index, state at that sample)
        self._snap_times: list[float] = []
        self._applied: list[tuple[float, object]] = []  # (time, update) fused within the buffer
        self._session: int | None = None
        self._pending: tuple[int, float] | None = None  # (new session, its first image time)
        self._next_fit_try = -np.inf
        self._next_out = np.inf
        self._out_t: list[float] = []
        self._out_x: list[_State] = []
        self._lat: list[float] = []
        self._scale_hist: tuple[list, list, list, list] = ([], [], [], [])
        self._final_scales: dict[int, tuple[float, float]] = {}
        self._t0 = time.perf_counter()
        self._n_slam = 0
        self._n_range_out = 0
        self._n_range_at: dict[str, int] = {}  # "at-min", "at-max": no distance (range_refusal)
        self._range_limits = RangeLimits(calib.range_min, calib.range_max)
        self._inputs = Inputs("msf-ekf", name)
        self._slam_gated_since: float | None = None
        # The alignment after each fused SLAM pose (its time -> s, slam_R_world, slam_t_world,
        # their covariance): what a gating reset goes back to (_reset_from_slam).
        self._align_hist: dict[float, tuple] = {}

    def feed(self, ev: Event) -> None:
        """One measurement event, in arrival order (IMU, attitude, SLAM pose, range)."""
        if not self._inputs.take(ev):
            return
        if isinstance(ev, ImuSample):
            self._hist.add(ev)
            if self.x is None:
                self._try_start(ev.arrival)
                return
            self._propagate_to(ev)
            return
        if isinstance(ev, AttitudeSample):
            self._hist.add(ev)
            return
        if isinstance(ev, SlamPose):
            self._n_slam += 1
            self._hist.add(ev)
        elif isinstance(ev, RangeReading):
            if not self.opt.use_range:
                return
            self._range_limits.see(float(ev.range))
            why = self._range_limits.refusal(float(ev.range))
            if why in RANGE_LIMIT_TAGS:
                self._n_range_at[why] = self._n_range_at.get(why, 0) + 1
                return
            if why is not None:
                self._n_range_out += 1
                return
            if self.x is None:
                self._hist.add(ev)
        else:
            return
        if self.x is None:
            return
        if self._imu_prev is not None and ev.arrival <= self._imu_prev.t:
            self._deliver(ev)
        else:
            self._queue.append(ev)

    def latest(self) -> _State | None:
        """The filter's current state (None before the scale is known)."""
        return self.x

    def _try_start(self, t_now: float) -> None:
        """Start once the data that has arrived fixes the scale (closed-form fit over the
        arrived prefix, :func:`initial_fit`), or at the first SLAM pose with a given scale."""
        o, h = self.opt, self._hist
        if not h.slam_t or t_now < self._next_fit_try:
            return
        self._next_fit_try = t_now + FIT_RETRY_S
        prefix = h.flight(self._calib, self._name)
        bg0 = np.zeros(3)
        R0 = None
        if o.initial_scale is not None:
            t_start = max(prefix.imu.t[0], prefix.slam.t[0])
            scale0, v0, rel0 = o.initial_scale, np.zeros(3), 0.15
        else:
            fit = arrived_initial_fit(h, prefix, t_now, self.counts)
            if fit is None:
                return
            scale0, v0, rel0 = fit.scale, fit.world_v_body_end, fit.rel_std
            R0, bg0 = fit.world_R_body_end, fit.gyro_bias
            # Causal: the state at the window's last image time t_end is carried to now by
            # the IMU samples buffered since.
            t_start = fit.t_end
        if prefix.attitude is not None:
            att = prefix.attitude
            i0 = min(int(np.searchsorted(att.t, t_start)), len(att) - 1)
            R0 = quat_wxyz_to_matrix(att.world_q_body_wxyz[i0])
        elif R0 is None:
            imu = prefix.imu
            k = (imu.t >= t_start) & (imu.t <= t_start + 0.5)
            R0 = level_rotation_from_accel(imu.body_accel[k].mean(axis=0))
        self._scale_rel_sigma = (
            o.initial_scale_rel_sigma
            if o.initial_scale_rel_sigma is not None
            else max(3.0 * rel0, MIN_SCALE_REL_SIGMA)
        )
        slam = prefix.slam
        j0 = min(int(np.searchsorted(slam.t, t_start)), len(slam) - 1)
        slam_R0 = quat_wxyz_to_matrix(slam.slam_q_cam_wxyz[j0])
        self.initialize(
            R0,
            slam.slam_t_cam[j0],
            slam_R0,
            scale0,
            self._calib.body_T_cam,
            self._calib.imu_noise,
            world_v_body=v0,
        )
        self.x.bg = np.asarray(bg0, float).copy()
        self._session = int(slam.session[j0])
        self.counts.extra["initial_scale"] = scale0
        # Causal output: nothing before the anchoring SLAM pose has arrived.
        self._next_out = max(float(slam.t[j0]), float(slam.t[j0] + slam.latency[j0]))
        # Re-deliver what arrived since t_start: the IMU from t_start, the later poses.
        later = h.slam_after(slam.t[j0]) + [e for e in h.range if e.t >= t_start]
        replay_ev = sorted(later + h.imu_from(t_start), key=lambda e: (e.arrival, _RANK[type(e)]))
        h.trim(t_start - self.opt.buffer_s)
        for e in replay_ev:
            if isinstance(e, ImuSample):
                self._propagate_to(e)
            elif self._imu_prev is not None and e.arrival <= self._imu_prev.t:
                self._deliver(e)
            else:
                self._queue.append(e)

    def _propagate_to(self, ev: ImuSample) -> None:
        """Measurements that arrived before this IMU sample, then the strapdown step to it."""
        prev = self._imu_prev
        if prev is not None:
            for q in self._queue:
                self._deliver(q)
            self._queue.clear()
            self.propagate(prev.body_omega, prev.body_accel, ev.t - prev.t)
        self._imu_prev = ev
        o = self.opt
        if prev is None:
            self._snaps.append((self._hist.imu_index(ev), self.x.copy()))
            self._snap_times.append(ev.t)
            return
        self._snaps.append((self._hist.imu_index(ev), self.x.copy()))
        self._snap_times.append(ev.t)
        while self._snap_times and self._snap_times[0] < ev.t - o.buffer_s:
            self._snaps.pop(0)
            self._snap_times.pop(0)
        while self._applied and self._applied[0][0] < ev.t - o.buffer_s:
            self._applied.pop(0)
        t_keep = ev.t - max(o.buffer_s, REINIT_GIVE_UP_S) - 1.0
        self._hist.trim(t_keep if self._pending is None else min(t_keep, self._pending[1]))
        if ev.t >= self._next_out:
            self._out_t.append(ev.t)
            self._out_x.append(self.x.copy())
            self._next_out += 1.0 / o.output_rate_hz

    def _deliver(self, ev: Event) -> None:
        """Apply one measurement at its measurement time (through the state buffer)."""
        cur_t = self._imu_prev.t
        w0 = time.perf_counter()
        if isinstance(ev, SlamPose) and ev.session != self._session:
            # New map: wait until the data since the reset fixes its scale.
            if self._pending is None or self._pending[0] != ev.session:
                self._pending = (ev.session, ev.t)
            guess = self._reinit_guess(self._pending[1], ev.t, cur_t)
            if guess is None:
                self.counts.slam_waiting_reinit += 1
                return
            self._final_scales[self._session] = (self.x.s, float(np.sqrt(self.x.P[IS, IS])))
            self._session = self._pending[0]
            self._pending = None
            self.reset_session(ev.slam_t_cam, quat_wxyz_to_matrix(ev.slam_q_cam_wxyz), *guess)
            self._align_hist.clear()
            # No replay across a reset: buffered states belong to the old map.
            self._snaps.clear()
            self._snap_times.clear()
            self._applied.clear()
            return
        n_old = self.counts.too_old
        self._apply_at(ev.t, cur_t, lambda e=ev: self._measure(e))
        if self.counts.too_old > n_old:
            self._inputs.skip("slam:too-old" if isinstance(ev, SlamPose) else "range:too-old")
        self._lat.append(time.perf_counter() - w0)
        if isinstance(ev, SlamPose):
            for lst, v in zip(
                self._scale_hist,
                (cur_t, self.x.s, np.sqrt(self.x.P[IS, IS]), self._session),
                strict=True,
            ):
                lst.append(v)

    def run(self, flight: Flight) -> Estimate:
        """Run over a flight's events in arrival order and return the causal estimate."""
        imu, slam = flight.imu, flight.slam
        if imu is None or slam is None:
            missing = [n for n, s in (("imu", imu), ("slam", slam)) if s is None]
            raise FlightDataError(f"{flight.name}: MSF-EKF needs IMU and SLAM; missing {missing}")
        self.start(flight.calib, flight.name)
        for ev in replay_flight(flight, ("imu", "attitude", "slam", "range")):
            self.feed(ev)
        return self.result()

    def result(self) -> Estimate:
        """The causal estimate of everything fed so far."""
        if self.x is None:
            raise FlightDataError(
                f"{self._name}: no window of the flight determines the SLAM scale; pass "
                "MsfOptions.initial_scale"
            )
        self.counts.extra["events_after_imu_end"] = len(self._queue)
        self.counts.extra["range_out_of_limits"] = self._n_range_out
        for why, n in self._n_range_at.items():
            self.counts.extra[f"range_{why.replace('-', '_')}"] = n
        after = {}
        for e in self._queue:
            k = "slam:after-imu-end" if isinstance(e, SlamPose) else "range:after-imu-end"
            after[k] = after.get(k, 0) + 1
        self._unused = unused_table(
            self.counts.unused(),
            self._inputs.unused,
            after,
            {"range:out-of-limits": self._n_range_out},
            {f"range:{why}": n for why, n in self._n_range_at.items()},
        )
        self._inputs_info = self._inputs.info(("slam", "range"))
        final = dict(self._final_scales)
        final[self._session] = (self.x.s, float(np.sqrt(self.x.P[IS, IS])))
        return self._estimate(
            self._out_t,
            self._out_x,
            self._lat,
            self._scale_hist,
            final,
            time.perf_counter() - self._t0,
        )

    def _reinit_guess(
        self, t_first: float, t_meas: float, t_now: float
    ) -> tuple[float, float] | None:
        """Scale of a new SLAM map (:func:`new_map_scale_guess`) from the data that has
        arrived; None while undetermined. After ``REINIT_GIVE_UP_S`` the old scale is kept with
        a large uncertainty."""
        if t_meas - t_first > REINIT_GIVE_UP_S:
            self.counts.extra["reinit_gave_up"] = self.counts.extra.get("reinit_gave_up", 0) + 1
            return self.x.s, RESET_SCALE_REL_SIGMA
        if t_meas - t_first < SCALE_INIT_WINDOWS_S[0]:
            return None
        prefix = self._hist.flight(self._calib, self._name)
        return new_map_scale_guess(prefix, t_first, t_meas, t_now, MIN_SCALE_REL_SIGMA)

    def _measure(self, ev: Event) -> None:
        if isinstance(ev, SlamPose):
            R = quat_wxyz_to_matrix(ev.slam_q_cam_wxyz)
            if self.update_slam(ev.slam_t_cam, R):
                self._slam_gated_since = None
                self._keep_alignment(float(ev.t))
            elif self._slam_gated_since is None or ev.t < self._slam_gated_since:
                self._slam_gated_since = float(ev.t)
            elif ev.t - self._slam_gated_since >= self.opt.slam_reset_s:
                self._reset_from_slam(ev, R)
        else:
            if self._ground is None:
                self._init_ground(float(ev.range))
            self.update_range(float(ev.range))

    def _keep_alignment(self, t: float) -> None:
        """Keep the alignment after the pose of time ``t`` fused (replays overwrite theirs), the
        last ``ALIGN_HISTORY_S`` of them."""
        x = self.x
        hist = self._align_hist
        hist[t] = (x.s, x.slam_R_world.copy(), x.slam_t_world.copy(), x.P[IS:, IS:].copy())
        if len(hist) > 1 and min(hist) < t - ALIGN_HISTORY_S:
            for k in [k for k in hist if k < t - ALIGN_HISTORY_S]:
                del hist[k]

    def _restore_alignment(self) -> bool:
        """A gating reset: the alignment as it was ``slam_reset_s`` before the poses began to
        be gated (the poses fused between the fault and the gate's closing had moved it: after
        one 150 m/s^2 accelerometer sample the scale went from 0.80 +- 0.08 to 0.44 +- 0.01 in
        0.5 s, and the restart kept it). False when there is none (the history is of this
        SLAM map only)."""
        if self._slam_gated_since is None:
            return False
        t_back = self._slam_gated_since - self.opt.slam_reset_s
        older = [t for t in self._align_hist if t <= t_back]
        if not older:
            return False
        s, R_sw, t_sw, P_a = self._align_hist[max(older)]
        x = self.x
        x.s, x.slam_R_world, x.slam_t_world = s, R_sw.copy(), t_sw.copy()
        x.P[IS:, :] = 0.0
        x.P[:, IS:] = 0.0
        x.P[IS:, IS:] = P_a
        return True

    def _reset_from_slam(self, ev: SlamPose, slam_R_cam: np.ndarray) -> None:
        """Every SLAM pose gated for ``slam_reset_s``: the filter has diverged. Re-initialise
        position, velocity (from the SLAM poses of the last ``SLAM_VELOCITY_SPAN_S``) and
        attitude from the SLAM through the alignment and scale as they were ``slam_reset_s``
        before the gating began (:meth:`_restore_alignment`; the current ones without such a
        pose), correlated with them; the biases keep their values with their initial
        uncertainty. The buffered states (diverged) are dropped."""
        x, o = self.x, self.opt
        if self._restore_alignment():
            self.counts.extra["gating_alignment_restored"] = (
                self.counts.extra.get("gating_alignment_restored", 0) + 1
            )
        body_R_cam = self._body_T_cam[:3, :3]
        body_t_cam = self._body_T_cam[:3, 3]
        if o.use_slam_rotation:
            x.R = x.slam_R_world.T @ slam_R_cam @ body_R_cam.T
        world_t_cam = x.slam_R_world.T @ (np.asarray(ev.slam_t_cam, float) - x.slam_t_world) / x.s
        x.p = world_t_cam - x.R @ body_t_cam
        earlier = [
            e
            for e in self._hist.slam
            if e.session == ev.session and e.t <= ev.t - SLAM_VELOCITY_SPAN_S
        ]
        x.v = np.zeros(3)
        if earlier:
            e = earlier[-1]
            d = np.asarray(ev.slam_t_cam, float) - np.asarray(e.slam_t_cam, float)
            x.v = x.slam_R_world.T @ d / (x.s * (ev.t - e.t))
        P = x.P
        P[:IS, :] = 0.0
        P[:, :IS] = 0.0
        P[IP : IP + 3, IP : IP + 3] = np.eye(3) * o.slam_position_sigma_m**2
        P[IV : IV + 3, IV : IV + 3] = np.eye(3) * o.initial_velocity_sigma**2
        P[ITH : ITH + 3, ITH : ITH + 3] = np.eye(3) * 0.05**2
        P[IBG : IBG + 3, IBG : IBG + 3] = np.eye(3) * o.initial_bias_sigma_gyro**2
        P[IBA : IBA + 3, IBA : IBA + 3] = np.eye(3) * o.initial_bias_sigma_accel**2
        # The position, velocity and attitude just taken from the SLAM are functions of the
        # alignment (s, slam_R_world, slam_t_world) they went through: their errors carry its
        # errors. Left uncorrelated, the next poses read as exact measures of the alignment
        # (after one 150 m/s^2 accelerometer sample, the scale's sigma fell from 0.023 to 0.005
        # within 1 s at 13 % off, and the estimate settled 0.6 m off).
        J = np.zeros((9, N_ERR - IS))  # d(p, v, theta) / d(s, phi, t_sw)
        w = world_t_cam
        J[0:3, 0] = -w / x.s
        J[0:3, 1:4] = skew(w)
        J[0:3, 4:7] = -x.slam_R_world.T / x.s
        J[3:6, 0] = -x.v / x.s
        J[3:6, 1:4] = skew(x.v)
        if o.use_slam_rotation:
            J[6:9, 1:4] = -x.R.T
            J[0:3, 1:4] -= x.R @ skew(body_t_cam) @ x.R.T
        JP = J @ P[IS:, IS:]
        P[:9, :9] += JP @ J.T
        P[:9, IS:] = JP
        P[IS:, :9] = JP.T
        self._slam_gated_since = None
        self.counts.gating_resets += 1
        self._snaps.clear()
        self._snap_times.clear()
        self._applied.clear()
        if self.counts.gating_resets == 1:
            log.warning(
                "msf-ekf: %s: every SLAM pose gated for %.1f s (the filter diverged) at %.2f s: "
                "position, velocity and attitude re-initialised from the SLAM",
                self._name,
                o.slam_reset_s,
                ev.t,
            )

    def _init_ground(self, r: float) -> None:
        x = self.x
        body_R_range = self._body_T_range[:3, :3]
        c = -(x.R @ body_R_range[:, 2])[2]
        self._ground = x.p[2] + (x.R @ self._body_T_range[:3, 3])[2] - r * c

    def _apply_at(self, t_meas: float, cur_t: float, apply) -> None:
        """Apply a measurement taken at ``t_meas``. If it is in the past, restore the buffered
        state there, apply it, then re-propagate the buffered IMU samples to ``cur_t``,
        re-applying in time order the measurements already fused after ``t_meas``."""
        snaps, snap_times, applied = self._snaps, self._snap_times, self._applied
        if t_meas >= cur_t - 1e-9 or not snaps:
            apply()
            applied.append((t_meas, apply))
            return
        k = bisect.bisect_right(snap_times, t_meas) - 1
        if k < 0:
            self.counts.too_old += 1
            return
        self.counts.replayed += 1
        idx, st = snaps[k]
        self.x = st.copy()
        h = self._hist
        i = h.imu_index(self._imu_prev)
        # Measurements after t_meas, already fused, to re-apply on the way back to cur_t.
        later = sorted((a for a in applied if a[0] > t_meas), key=lambda a: a[0])
        applied[:] = [a for a in applied if a[0] <= t_meas]
        queue = [(t_meas, apply, True)] + [(tq, fn, False) for tq, fn in later]
        snaps[k + 1 :] = []
        snap_times[k + 1 :] = []
        t_now = h.imu_at(idx).t
        for m in range(idx, i):
            cur, nxt = h.imu_at(m), h.imu_at(m + 1)
            t_next = nxt.t
            while queue and queue[0][0] < t_next:
                tq, fn, first = queue.pop(0)
                self.propagate(cur.body_omega, cur.body_accel, tq - t_now)
                t_now = max(t_now, tq)
                self._apply_counted(fn, first)
                applied.append((tq, fn))
            self.propagate(cur.body_omega, cur.body_accel, t_next - t_now)
            t_now = t_next
            snaps.append((m + 1, self.x.copy()))
            snap_times.append(t_next)
        for tq, fn, first in queue:  # measured at or after cur_t: apply now
            self._apply_counted(fn, first)
            applied.append((tq, fn))

    def _apply_counted(self, fn, first: bool) -> None:
        """Run an update; a re-application during replay does not count it again."""
        saved = dataclasses.replace(self.counts, extra=self.counts.extra)
        fn()
        if not first:
            extra = self.counts.extra
            self.counts = saved
            self.counts.extra = extra

    def _estimate(self, out_t, out_x, lat, history, final_scales, wall) -> Estimate:
        sh_t, sh, ss, sid = (np.asarray(h) for h in history)
        n = len(out_t)
        R = np.array([x.R for x in out_x])
        pose_cov = np.empty((n, 6, 6))
        for k, x in enumerate(out_x):
            pose_cov[k] = pose_covariance(x)
        traj = Trajectory(
            t=np.asarray(out_t),
            world_t_body=np.array([x.p for x in out_x]),
            world_q_body_wxyz=matrix_to_quat_wxyz(R),
            world_v_body=np.array([x.v for x in out_x]),
            gyro_bias=np.array([x.bg for x in out_x]),
            accel_bias=np.array([x.ba for x in out_x]),
        )
        return Estimate(
            method="msf-ekf",
            trajectory=traj,
            pose_cov=pose_cov,
            vel_cov=np.array([x.P[IV : IV + 3, IV : IV + 3] for x in out_x]),
            slam_scale={k: v[0] for k, v in final_scales.items()},
            slam_scale_sigma={k: v[1] for k, v in final_scales.items()},
            series={
                "slam_scale": TimeSeries(sh_t, sh, ss),
                "slam_session": TimeSeries(sh_t, sid.astype(int)),
            },
            update_latency=np.asarray(lat),
            runtime_s=wall,
            causal=True,
            info={
                "options": self.opt.__dict__.copy(),
                "counts": self.counts.__dict__.copy(),
                "unused": self._unused,
                **self._inputs_info,
            },
        )


_RANK = {ImuSample: 0, AttitudeSample: 1, RangeReading: 2, SlamPose: 3}


def run_msf(flight: Flight, options: MsfOptions | None = None) -> Estimate:
    """Run the MSF-style EKF over a flight (library entry point)."""
    return MsfEkf(options).run(flight)
