"""Crazyflie onboard EKF baseline: the model of bitcraze crazyflie-firmware's ``kalman_core``
(Mueller, Hamer, D'Andrea, ICRA 2015; Mueller, Hehn, D'Andrea, JGCD 2016) with its flow-deck
updates ``mm_flow`` (PMW3901 optical flow) and ``mm_tof`` (VL53L1x time of flight), written in
fgnav's own form and fed events in arrival order.

State (9): ``[p (3) world, u (3) body velocity, d (3) attitude error]`` plus the attitude
quaternion ``world_q_body_wxyz`` held outside the filter state (``d`` is moved into it after every
step, "finalize", with the second-order covariance rotation of the JGCD paper). World z up, body
FLU (the Crazyflie's own frames); ``p_z`` is the height above a flat floor at ``z = 0``.

1. **Prediction** (``kalman_core.c predictDt``), at ``predict_rate_hz`` with the IMU samples
   averaged since the last one (the firmware: 100 Hz): ``p += R (u dt + [0, 0, a_z dt^2 / 2])
   - [0, 0, g dt^2 / 2]``, ``u += dt (f - omega x u - g R^T e3)`` where in flight (``flying``)
   only the body-z specific force is used, ``f = [0, 0, a_z]`` (thrust along body z, drag
   neglected; the firmware's ``quadIsFlying`` branch), else the full accelerometer;
   ``q = q (x) exp(omega dt)``; linearised ``A`` as the firmware (position from body velocity and
   attitude error, body velocity from gyro cross terms and gravity, attitude error rotated by the
   second-order ``exp(-d)`` approximation); process noise added per step
   (``addProcessNoiseDt``): ``(acc_xy dt^2)^2`` on x, y, ``(acc_z dt^2)^2`` on z,
   ``(acc dt)^2`` on the velocities, ``(gyro_rp dt)^2``, ``(gyro_yaw dt)^2`` on the attitude error.
2. **Flow** (``mm_flow.c``), two scalar updates per reading, in fgnav's flow convention
   (``FlowSeries``: sensor x forward, y right for the default ``DOWNWARD_FLOW``)::

       flow_x = ppr dt (-u_x R22 / z - w_y),   flow_y = ppr dt (u_y R22 / z + w_x)

   i.e. the firmware's ``predictedNX = (dt Npix / thetapix)(u_x R22 / z - omega_y)`` on its x count
   (``-flow_x``) and ``predictedNY`` on ``flow_y``; ``z`` floored at 0.1 m; Jacobians on ``p_z``
   and ``u_x, u_y`` only (as the firmware); the raw gyro (no bias state, as the firmware);
   ``ppr`` is ``calib.flow_pixels_per_rad`` (the firmware: 35 px / 0.71674 rad = 48.8, counts /
   10). Noise ``sigma_rad * ppr`` per count axis (firmware ``flowStdFixed`` 2 raw counts = 0.2
   px). Readings whose flow exceeds ``outlier_rad`` (firmware ``OULIER_LIMIT``: 100 raw counts =
   10 px) are dropped.
3. **Time of flight** (``mm_tof.c``), when ``R22 > 0.1``: ``r = p_z / cos(a)`` with ``a = max(
   acos(R22) - cone / 2, 0)`` (a 15 deg cone: the closest point in it), ``H_z = 1 / cos(a)``;
   noise from the zranger2 driver's model ``0.0025 (1 + exp(k (r - 2.5)))`` m,
   ``k = ln(0.2 / 0.0025) / 1.5`` (or ``tof_sigma_m``); readings of ``tof_outlier_m`` or more are
   dropped.

Start: at the first range reading of the IMU-fed filter: ``p = [0, 0, r cos(tilt)]``, attitude
level from the mean specific force of the last ``init_accel_window_s`` (the firmware starts flat
on the ground with yaw 0) and yaw 0, ``u = 0``; initial standard deviations as the firmware
(position x, y 100 m, z 1 m, velocity 0.01 m/s, attitude 0.01 rad).

Outputs: a causal trajectory (state after each prediction step, decimated to
``output_rate_hz``), world velocity ``R u``, pose and velocity covariances
(:func:`state_covariances`; the velocity's includes the attitude error's share, ``-R [u]x d``).

Differences from the firmware, deliberate: measurements are applied at the filter's current time
(the firmware does the same, from its queue), floating point is double, there is no
``attitudeReversion`` (that acts only on the ground), no barometer, no take-off detection (always
``flying``), and the filter starts in the air from the first range reading. Not modelled (as in the
firmware): sensor lever arms, gyro bias, rotor drag, terrain under the vehicle (the floor is flat).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from fgnav.baselines._inputs import Inputs, unused_table
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import Event, FlowSample, ImuSample, RangeReading, replay_flight
from fgnav.datasets.geometry import (
    GRAVITY,
    matrix_to_quat_wxyz,
    quat_multiply_wxyz,
    quat_wxyz_to_matrix,
    skew,
)
from fgnav.datasets.types import Calibration, Flight, Trajectory
from fgnav.estimate import Estimate
from fgnav.solvers.measurements import level_rotation_from_accel

log = logging.getLogger(__name__)

# State layout.
IP, IU, ID = 0, 3, 6
N_STATE = 9
#: Covariance bounds of the firmware (``MAX_COVARIANCE``, ``MIN_COVARIANCE``).
MAX_COVARIANCE = 100.0
MIN_COVARIANCE = 1e-6
#: Floor on the height in the flow model [m] (firmware).
MIN_FLOW_HEIGHT = 0.1
#: zranger2 noise model: std ``EXP_STD_A (1 + exp(k (r - EXP_POINT_A)))`` [m].
EXP_POINT_A, EXP_STD_A, EXP_POINT_B, EXP_STD_B = 2.5, 0.0025, 4.0, 0.2
EXP_COEFF = math.log(EXP_STD_B / EXP_STD_A) / (EXP_POINT_B - EXP_POINT_A)

REQUIRED_STREAMS = ("imu", "flow", "range")


@dataclass
class CfEkfOptions:
    """Options of :class:`CfEkf` (defaults: the firmware's ``kalmanCoreDefaultParams`` and deck
    drivers).

    Attributes:
        predict_rate_hz: prediction rate with averaged IMU samples [Hz] (firmware 100).
        flying: in-flight prediction (body-z specific force only); False uses all three axes.
        proc_noise_acc_xy, proc_noise_acc_z: process noise [m/s^2] (firmware 0.5, 1.0).
        proc_noise_gyro_rollpitch, proc_noise_gyro_yaw: attitude process noise [rad/s] (0.1).
        init_pos_xy_sigma, init_pos_z_sigma [m], init_vel_sigma [m/s], init_att_sigma [rad]:
            initial standard deviations (firmware 100, 1, 0.01, 0.01).
        init_accel_window_s: IMU seconds averaged for the initial roll and pitch.
        sigma_rad: flow noise per count axis [rad of image motion] (firmware 0.2 px at 48.8).
        outlier_rad: flow readings larger than this on an axis are dropped [rad] (10 px).
        quality_min: flow readings of lower quality are dropped (the firmware has no quality
            gate beyond its "valid motion" bit: 0 keeps every delivered reading).
        tof_sigma_m: fixed time-of-flight noise [m]; None: the zranger2 model.
        tof_cone_deg: the time-of-flight field of view [deg] (15).
        tof_outlier_m: time-of-flight readings at or above this are dropped [m] (5).
        output_rate_hz: rate of the reported trajectory [Hz].
    """

    predict_rate_hz: float = 100.0
    flying: bool = True
    proc_noise_acc_xy: float = 0.5
    proc_noise_acc_z: float = 1.0
    proc_noise_gyro_rollpitch: float = 0.1
    proc_noise_gyro_yaw: float = 0.1
    init_pos_xy_sigma: float = 100.0
    init_pos_z_sigma: float = 1.0
    init_vel_sigma: float = 0.01
    init_att_sigma: float = 0.01
    init_accel_window_s: float = 0.2
    sigma_rad: float = 0.2 / (35.0 / 0.71674)
    outlier_rad: float = 10.0 / (35.0 / 0.71674)
    quality_min: float = 0.0
    tof_sigma_m: float | None = None
    tof_cone_deg: float = 15.0
    tof_outlier_m: float = 5.0
    output_rate_hz: float = 100.0


@dataclass
class CfEkfCounts:
    """What the filter did with its measurements (reported, never silent)."""

    predictions: int = 0
    flow_updates: int = 0
    flow_outliers: int = 0
    flow_low_quality: int = 0
    flow_before_start: int = 0
    tof_updates: int = 0
    tof_outliers: int = 0
    tof_tilted: int = 0
    extra: dict = field(default_factory=dict)


def _quat_exp(v: np.ndarray) -> np.ndarray:
    """Unit quaternion of the rotation vector ``v`` [rad] (firmware: angle + 1e-6)."""
    angle = float(np.linalg.norm(v)) + 1e-6
    return np.r_[math.cos(angle / 2.0), math.sin(angle / 2.0) * np.asarray(v) / angle]


def _att_rotation(d: np.ndarray) -> np.ndarray:
    """Second-order ``exp(-[d]x)`` of the firmware for half-angles ``d`` (3x3)."""
    d0, d1, d2 = d
    return np.array(
        [
            [1 - d1 * d1 / 2 - d2 * d2 / 2, d2 + d0 * d1 / 2, -d1 + d0 * d2 / 2],
            [-d2 + d0 * d1 / 2, 1 - d0 * d0 / 2 - d2 * d2 / 2, d0 + d1 * d2 / 2],
            [d1 + d0 * d2 / 2, -d0 + d1 * d2 / 2, 1 - d0 * d0 / 2 - d1 * d1 / 2],
        ]
    )


def state_covariances(
    world_R_body: np.ndarray, S: np.ndarray, P: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pose and world-velocity covariances of the state ``S`` (attitude error ``d`` moved into
    the quaternion, ``finalize``) with covariance ``P``.

    The attitude error is a body-frame right perturbation (``R = R_hat (I + [d]x)``, as the
    filter's ``A`` and ``finalize``), so the (6, 6) pose covariance in GTSAM's Pose3 tangent
    ``[rot, trans]`` (body frame) takes ``d`` as it is and ``world_R_body^T dp`` for the
    translation; the (3, 3) covariance of ``world_v_body = R u`` has ``dv = R du - R [u]x d``.
    """
    R = np.asarray(world_R_body, float)
    J = np.zeros((6, N_STATE))
    J[0:3, ID : ID + 3] = np.eye(3)
    J[3:6, IP : IP + 3] = R.T
    Jv = np.zeros((3, N_STATE))
    Jv[:, IU : IU + 3] = R
    Jv[:, ID : ID + 3] = -R @ skew(S[IU : IU + 3])
    return J @ P @ J.T, Jv @ P @ Jv.T


def tof_sigma(distance_m: float) -> float:
    """Noise [m] of a VL53L1x reading in the Crazyflie's zranger2 driver."""
    return EXP_STD_A * (1.0 + math.exp(EXP_COEFF * (distance_m - EXP_POINT_A)))


class CfEkf:
    """The Crazyflie's ``kalman_core`` with flow and time-of-flight updates (module docstring).

    Event-fed: :meth:`start`, then :meth:`feed` each event in arrival order (IMU samples, flow
    readings, range readings; others are ignored), :meth:`latest` for the newest state and
    :meth:`result` for the causal estimate. The primitives :meth:`predict`,
    :meth:`update_flow`, :meth:`update_tof` act on the current state.
    """

    def __init__(self, options: CfEkfOptions | None = None) -> None:
        self.opt = options or CfEkfOptions()
        self.counts = CfEkfCounts()
        self.S: np.ndarray | None = None
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.R = np.eye(3)
        self.P = np.zeros((N_STATE, N_STATE))

    # -- filter primitives ------------------------------------------------------------------------

    def initialize(self, world_R_body: np.ndarray, height: float) -> None:
        o = self.opt
        self.S = np.zeros(N_STATE)
        self.S[IP + 2] = height
        self.q = matrix_to_quat_wxyz(np.asarray(world_R_body, float)[None])[0]
        self.R = quat_wxyz_to_matrix(self.q)
        self.P = np.diag(
            [o.init_pos_xy_sigma**2] * 2
            + [o.init_pos_z_sigma**2]
            + [o.init_vel_sigma**2] * 3
            + [o.init_att_sigma**2] * 3
        )

    def predict(self, omega: np.ndarray, accel: np.ndarray, dt: float) -> None:
        """One prediction step with body rate ``omega`` [rad/s] and specific force ``accel``
        [m/s^2] held over ``dt`` [s] (``predictDt`` then ``addProcessNoiseDt``)."""
        if dt <= 0:
            return
        o, S, R = self.opt, self.S, self.R
        g = GRAVITY
        u = S[IU : IU + 3].copy()
        w = np.asarray(omega, float)
        A = np.eye(N_STATE)
        A[IP : IP + 3, IU : IU + 3] = R * dt
        # Position from attitude error: d(R (I + [d]x) u)/dd = -R [u]x.
        ux, uy, uz = u
        A[IP : IP + 3, ID] = (uy * R[:, 2] - uz * R[:, 1]) * dt
        A[IP : IP + 3, ID + 1] = (-ux * R[:, 2] + uz * R[:, 0]) * dt
        A[IP : IP + 3, ID + 2] = (ux * R[:, 1] - uy * R[:, 0]) * dt
        # Body velocity from body velocity (gyro cross terms) and attitude error (gravity).
        wx, wy, wz = w
        A[IU : IU + 3, IU : IU + 3] = np.array(
            [[1.0, wz * dt, -wy * dt], [-wz * dt, 1.0, wx * dt], [wy * dt, -wx * dt, 1.0]]
        )
        A[IU, ID + 1] = g * R[2, 2] * dt
        A[IU, ID + 2] = -g * R[2, 1] * dt
        A[IU + 1, ID] = -g * R[2, 2] * dt
        A[IU + 1, ID + 2] = g * R[2, 0] * dt
        A[IU + 2, ID] = g * R[2, 1] * dt
        A[IU + 2, ID + 1] = -g * R[2, 0] * dt
        A[ID : ID + 3, ID : ID + 3] = _att_rotation(w * dt / 2.0)
        self.P = A @ self.P @ A.T
        # State.
        f = np.asarray(accel, float) if not o.flying else np.array([0.0, 0.0, accel[2]])
        dp_body = u * dt + f * dt * dt / 2.0
        S[IP : IP + 3] += R @ dp_body - np.array([0.0, 0.0, g * dt * dt / 2.0])
        S[IU : IU + 3] = u + dt * (f - np.cross(w, u) - g * R[2])
        q = quat_multiply_wxyz(self.q, _quat_exp(w * dt))
        self.q = q / np.linalg.norm(q)
        self.R = quat_wxyz_to_matrix(self.q)
        # Process noise.
        P = self.P
        for i, a in ((0, o.proc_noise_acc_xy), (1, o.proc_noise_acc_xy), (2, o.proc_noise_acc_z)):
            P[IP + i, IP + i] += (a * dt * dt) ** 2
            P[IU + i, IU + i] += (a * dt) ** 2
        for i, s in (
            (0, o.proc_noise_gyro_rollpitch),
            (1, o.proc_noise_gyro_rollpitch),
            (2, o.proc_noise_gyro_yaw),
        ):
            P[ID + i, ID + i] += (s * dt) ** 2
        self._bound()
        self.counts.predictions += 1

    def _bound(self) -> None:
        P = 0.5 * (self.P + self.P.T)
        P = np.where(np.isnan(P) | (P > MAX_COVARIANCE), MAX_COVARIANCE, P)
        d = np.diag(P).copy()
        np.fill_diagonal(P, np.maximum(d, MIN_COVARIANCE))
        self.P = P

    def _scalar_update(self, H: np.ndarray, error: float, std: float) -> None:
        """``kalmanCoreScalarUpdate``: gain, state, Joseph covariance with bounds."""
        PH = self.P @ H
        r = std * std
        s = float(H @ PH) + r
        K = PH / s
        self.S = self.S + K * error
        IKH = np.eye(N_STATE) - np.outer(K, H)
        self.P = IKH @ self.P @ IKH.T + r * np.outer(K, K)
        self._bound()

    def finalize(self) -> None:
        """Move the attitude error into the quaternion and rotate the covariance
        (``kalmanCoreFinalize``)."""
        v = self.S[ID : ID + 3]
        if np.any(np.abs(v) > 0.1e-3) and np.all(np.abs(v) < 10):
            q = quat_multiply_wxyz(self.q, _quat_exp(v))
            self.q = q / np.linalg.norm(q)
            A = np.eye(N_STATE)
            A[ID : ID + 3, ID : ID + 3] = _att_rotation(v / 2.0)
            self.P = A @ self.P @ A.T
        self.R = quat_wxyz_to_matrix(self.q)
        self.S[ID : ID + 3] = 0.0
        self._bound()

    def update_flow(
        self, flow: np.ndarray, dt: float, omega: np.ndarray, ppr: float, body_R_flow: np.ndarray
    ) -> None:
        """Two scalar flow updates (``mm_flow``), the rate ``omega`` [rad/s] in body."""
        o, S, R = self.opt, self.S, self.R
        z = max(float(S[IP + 2]), MIN_FLOW_HEIGHT)
        c = float(R[2, 2])
        u = body_R_flow.T @ S[IU : IU + 3]  # sensor-frame velocity (firmware: body, rotated)
        w = body_R_flow.T @ np.asarray(omega, float)
        k = ppr * dt
        sigma = o.sigma_rad * ppr
        A = body_R_flow.T
        for axis, (sgn, w_term) in enumerate(((-1.0, -w[1]), (-1.0, w[0]))):
            pred = k * (sgn * u[axis] * c / z + w_term)
            H = np.zeros(N_STATE)
            H[IU : IU + 3] = k * sgn * c / z * A[axis]
            H[IP + 2] = -k * sgn * u[axis] * c / (z * z)
            self._scalar_update(H, float(flow[axis]) - pred, sigma)
        self.counts.flow_updates += 1

    def update_tof(self, distance: float) -> bool:
        """Time-of-flight update (``mm_tof``); False when the vehicle is too tilted."""
        R22 = float(self.R[2, 2])
        if not (abs(R22) > 0.1 and R22 > 0):
            self.counts.tof_tilted += 1
            return False
        angle = max(abs(math.acos(min(R22, 1.0))) - math.radians(self.opt.tof_cone_deg / 2.0), 0.0)
        H = np.zeros(N_STATE)
        H[IP + 2] = 1.0 / math.cos(angle)
        pred = float(self.S[IP + 2]) / math.cos(angle)
        std = self.opt.tof_sigma_m if self.opt.tof_sigma_m is not None else tof_sigma(distance)
        self._scalar_update(H, distance - pred, std)
        self.counts.tof_updates += 1
        return True

    # -- event stream -----------------------------------------------------------------------------

    def start(self, calib: Calibration, name: str = "flight") -> None:
        """Prepare to be fed events of a vehicle with calibration ``calib``."""
        self._calib = calib
        self._name = name
        self._ppr = float(calib.flow_pixels_per_rad)
        self._body_R_flow = np.asarray(calib.body_T_flow, float)[:3, :3]
        self._acc_sum = np.zeros(3)
        self._gyro_sum = np.zeros(3)
        self._n_acc = 0
        self._t_pred: float | None = None
        self._last_imu: ImuSample | None = None
        self._recent_acc: list[tuple[float, np.ndarray]] = []
        self._out_t: list[float] = []
        self._out: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._next_out = -np.inf
        self._lat: list[float] = []
        self._t0 = time.perf_counter()
        self._inputs = Inputs("cf-ekf", name)

    def feed(self, ev: Event) -> None:
        """One measurement event, in arrival order (a corrupted IMU sample is dropped and
        counted: :mod:`fgnav.baselines._inputs`)."""
        if not self._inputs.take(ev):
            return
        if isinstance(ev, ImuSample):
            self._imu(ev)
        elif isinstance(ev, FlowSample):
            self._flow(ev)
        elif isinstance(ev, RangeReading):
            self._range(ev)

    def latest(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(world_t_body, world_q_body_wxyz, world_v_body)`` now (None before the start)."""
        if self.S is None:
            return None
        return self.S[IP : IP + 3].copy(), self.q.copy(), self.R @ self.S[IU : IU + 3]

    @property
    def output_t(self) -> float | None:
        """Time of the newest state of the causal trajectory (None before the first)."""
        return self._out_t[-1] if self._out_t else None

    def latest_output(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
        """The newest state of the causal trajectory, ``(t, S, world_q_body_wxyz, P)`` as
        :meth:`result` reports it (after a prediction step); None before the first."""
        if not self._out:
            return None
        S, q, P = self._out[-1]
        return self._out_t[-1], S.copy(), q.copy(), P.copy()

    def _imu(self, ev: ImuSample) -> None:
        self._last_imu = ev
        if self.S is None:
            self._recent_acc.append((ev.t, np.asarray(ev.body_accel, float)))
            w0 = ev.t - self.opt.init_accel_window_s
            while self._recent_acc and self._recent_acc[0][0] < w0:
                self._recent_acc.pop(0)
            return
        if self._t_pred is None:
            self._t_pred = ev.t
        self._acc_sum += ev.body_accel
        self._gyro_sum += ev.body_omega
        self._n_acc += 1
        dt = ev.t - self._t_pred
        if dt >= 1.0 / self.opt.predict_rate_hz - 1e-9:
            w0 = time.perf_counter()
            self.predict(self._gyro_sum / self._n_acc, self._acc_sum / self._n_acc, dt)
            self.finalize()
            self._lat.append(time.perf_counter() - w0)
            self._t_pred = ev.t
            self._acc_sum[:] = 0.0
            self._gyro_sum[:] = 0.0
            self._n_acc = 0
            if ev.t >= self._next_out - 1e-9:
                self._out_t.append(ev.t)
                self._out.append((self.S.copy(), self.q.copy(), self.P.copy()))
                self._next_out = ev.t + 1.0 / self.opt.output_rate_hz

    def _flow(self, ev: FlowSample) -> None:
        o = self.opt
        if self.S is None:
            self.counts.flow_before_start += 1
            return
        f = np.asarray(ev.flow, float)
        if np.any(np.abs(f) >= o.outlier_rad * self._ppr) or not np.all(np.isfinite(f)):
            self.counts.flow_outliers += 1
            return
        if 0 <= ev.quality < o.quality_min:
            self.counts.flow_low_quality += 1
            return
        omega = self._last_imu.body_omega if self._last_imu is not None else np.zeros(3)
        w0 = time.perf_counter()
        self.update_flow(f, float(ev.dt), omega, self._ppr, self._body_R_flow)
        self.finalize()
        self._lat.append(time.perf_counter() - w0)

    def _range(self, ev: RangeReading) -> None:
        r = float(ev.range)
        if not (np.isfinite(r) and 0.0 < r < self.opt.tof_outlier_m):
            self.counts.tof_outliers += 1
            return
        if self.S is None:
            if not self._recent_acc:
                return
            f = np.mean([a for _, a in self._recent_acc], axis=0)
            R0 = level_rotation_from_accel(f)
            beam = R0 @ np.asarray(self._calib.body_T_range, float)[:3, 2]
            self.initialize(R0, r * max(-float(beam[2]), 0.1))
            self.counts.extra["t_start"] = float(ev.t)
            return
        w0 = time.perf_counter()
        self.update_tof(r)
        self.finalize()
        self._lat.append(time.perf_counter() - w0)

    def unused(self) -> dict[str, int]:
        """What was not used, ``stream:reason -> count`` (:mod:`fgnav.baselines._inputs`)."""
        c = self.counts
        return unused_table(
            self._inputs.unused,
            {
                "flow:outlier": c.flow_outliers,
                "flow:low-quality": c.flow_low_quality,
                "flow:before-start": c.flow_before_start,
                "range:outlier": c.tof_outliers,
                "range:tilted": c.tof_tilted,
            },
        )

    def run(self, flight: Flight) -> Estimate:
        """Run over a flight's IMU, flow and range events in arrival order."""
        check_flight(flight)
        self.start(flight.calib, flight.name)
        for ev in replay_flight(flight, ("imu", "range", "flow")):
            self.feed(ev)
        return self.result()

    def result(self) -> Estimate:
        """The causal estimate of everything fed so far."""
        if not self._out:
            raise FlightDataError(
                f"{self._name}: the Crazyflie EKF never started (no range reading in (0, "
                f"{self.opt.tof_outlier_m}) m after an IMU sample)"
            )
        S = np.array([s for s, _, _ in self._out])
        q = np.array([q for _, q, _ in self._out])
        Rs = quat_wxyz_to_matrix(q)
        v = np.einsum("nij,nj->ni", Rs, S[:, IU : IU + 3])
        pose_cov = np.empty((len(S), 6, 6))
        vel_cov = np.empty((len(S), 3, 3))
        for k, (s, _, P) in enumerate(self._out):
            pose_cov[k], vel_cov[k] = state_covariances(Rs[k], s, P)
        traj = Trajectory(
            t=np.asarray(self._out_t),
            world_t_body=S[:, IP : IP + 3].copy(),
            world_q_body_wxyz=q,
            world_v_body=v,
        )
        return Estimate(
            method="cf-ekf",
            trajectory=traj,
            pose_cov=pose_cov,
            vel_cov=vel_cov,
            update_latency=np.asarray(self._lat),
            runtime_s=time.perf_counter() - self._t0,
            causal=True,
            info={
                "options": dataclasses.asdict(self.opt),
                "counts": dataclasses.asdict(self.counts),
                "unused": self.unused(),
                **self._inputs.info(("flow", "range")),
            },
        ).check()


def check_flight(flight: Flight) -> None:
    """Raise :class:`FlightDataError` naming every missing input of the Crazyflie EKF."""
    flight.require_streams(REQUIRED_STREAMS, "the Crazyflie EKF")


def run_cf_ekf(flight: Flight, options: CfEkfOptions | None = None) -> Estimate:
    """Run the Crazyflie EKF over a flight (library entry point)."""
    return CfEkf(options).run(flight)
