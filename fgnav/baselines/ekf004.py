"""Seed 004's EKF baseline (Logachev & Minin; the method of Engel, Sturm & Cremers' tum_ardrone).

State (10, world z up, SI units; the seed keeps degrees, we keep radians)::

    x = [x, y, z, vx, vy, vz, roll, pitch, yaw, yaw_rate]

``world_R_body = Rz(yaw) Ry(pitch) Rx(roll)`` (ZYX), body FLU.

Prediction (seed eqs. 6-8; Engel, Sturm & Cremers, IROS 2012): the horizontal acceleration is the
horizontal projection of the thrust minus a linear drag. Without the control inputs of the seed
(eqs. 9-12), the thrust is taken to balance gravity (``T/m = g / (R e3)_z``), so::

    d(v_xy)/dt = g (R e3)_xy / (R e3)_z - Rz(yaw) diag(kx, ky) Rz(yaw)^T v_xy
    d(v_z)/dt = 0,  d(roll)/dt = d(pitch)/dt = 0,  d(yaw)/dt = yaw_rate,  d(yaw_rate)/dt = 0

each with white process noise (the seed predicts roll, pitch, yaw rate and vertical speed from the
control commands; here they are random walks corrected at the sensors' rates). ``kx, ky`` [1/s] are
calibrated constants (the seed's c1..c8 are found by test flights).

Observations (seed eqs. 2-5), each Mahalanobis-gated:

- roll, pitch from the attitude stream (the AR.Drone's accelerometer-based angles);
- yaw rate from the gyroscope, ``(q sin(roll) + r cos(roll)) / cos(pitch)`` (the seed
  differentiates yaw), and absolute yaw from the yaw stream (magnetometer-like) when present;
- vertical speed from differentiated height: consecutive tilt-corrected rangefinder heights
  ``(h_k - h_{k-1}) / dt`` (seed eq. 3);
- SLAM camera pose, scaled: ``h_P(x) = (x + R t_bc, roll, pitch, yaw)`` (seed eqs. 4-5, with the
  camera lever arm ``t_bc``), where the SLAM position is mapped into the world by
  ``world_t_cam = a_world + (1/s) world_R_slam (slam_t_cam - a_slam)``.

SLAM scale (seed: "maximum-likelihood scale"; Engel et al. 2012): pairs of SLAM
displacements ``x_i`` (rotated into world, SLAM units) and metric displacements ``y_i`` [m] over
``scale_pair_interval_s`` are collected; ``y_i`` integrates the drag-model velocity driven by the
measured attitude only (open loop, independent of SLAM: the seed's "velocity from the onboard IMU")
horizontally and differences rangefinder heights vertically. ``s`` comes from the closed-form
estimator of :mod:`fgnav.frontends.scale_ml`. The map's origin ``(a_slam, a_world)`` is the first
SLAM pose of the session and the filter's camera position then; as in tum_ardrone, a change of
scale re-pivots the map at the current SLAM pose so that the position measurement does not jump
(option ``scale_repivot``).
``world_R_slam`` is the chordal mean of ``world_R_cam slam_R_cam^T`` over the first
``align_poses`` poses of a session (filter attitude; the seed rotates the PTAM map by the
accelerometer's gravity direction); SLAM angles are fused only after that.

Delay compensation (seed fig. 2): every processed measurement is kept for ``history_s`` with the
filter state before it; a late SLAM pose (image time ``t``, arriving ``t + latency``) rolls the
filter back to ``t``, is applied there, and the later measurements are replayed. Outputs are
causal: the state the filter had at each attitude sample, before later corrections.

Fed events (:class:`Ekf004Runner`, built from the calibration and the options; a flight's replay
or a live link), the filter decides what the ``"auto"`` choices below need from what has arrived
within ``SOURCES_WINDOW_S`` of the first event (held meanwhile, then processed in order): the
attitude source (an attitude sample among them: the stream), and which of the yaw and range
streams its start waits for.

Without an attitude stream (``attitude_source``: ``"auto"`` picks ``"imu"`` when none has arrived
in that window; EuRoC): the paper's vehicle logged its onboard attitude, so roll and pitch are
*estimated*, causally, from the IMU by seed 002's attitude EKF run as a stage on the arriving IMU,
yaw and range events (:class:`~fgnav.frontends.attitude_ekf.AttitudeEkfStage`, reported in
``Estimate.info["attitude_source"]``) and fused with ``imu_attitude_sigma``. On a multirotor that
gravity-referenced tilt is the rotor-drag tilt ``k v / g`` at low frequencies (the accelerometer
reads thrust and drag, not gravity), which turns the drag-model odometry of the scale pairs into a
``1/k`` low-pass of the velocity: on the simulated two-turns and rectangle flights (seeds 0, 1) the
ML scale was then off by +60 to +400 %. So the scale comes instead (``scale_source``: ``"auto"``
picks ``"imu_fit"``) from closed-form IMU-SLAM fits over consecutive windows of the session
(:func:`fgnav.baselines.msf_ekf.initial_fit`, which integrates the gyro itself with a bias from the
SLAM rotations), combined by inverse variance. As in the MSF and UKF baselines, whose causal
closed-form start this shares, states are reported from the first fit on, when position and
velocity are released (:meth:`Ekf004.release_position`) for the scaled SLAM poses to set them: the
drag-model dead reckoning before it is not trusted (on EuRoC MH_01 the vehicle is carried by hand,
then sits on the ground tilted by 5 deg, which the drag model reads as 0.8 m/s^2). Measured, SE(3)
ATE without / with the attitude stream: two-turns 0.10 / 0.020 m (seed 0), 0.11 / 0.044 m (seed 1);
rectangle 0.039 / 0.029 m, 0.068 / 0.042 m; scale errors -1.6 to +1.4 %; position NEES 0.5-4.2. The
gap is the drag-tilt bias of the estimated roll and pitch in the prediction.

The model needs a FLU multirotor body (z along the rotor thrust): when the flight's body z is more
than ``fgnav.datasets.frames.MAX_THRUST_TILT_DEG`` from the thrust axis (EuRoC's IMU frame, x up),
:func:`run_ekf004` runs the filter in a body with z along it
(:func:`fgnav.datasets.frames.thrust_body_rotation`; EuRoC's manifest records the Firefly's thrust
axis) and maps the estimate back. On EuRoC MH_01 (FLU body, no attitude stream, default drag
0.4 1/s): ATE 0.068 m fed events (2026-12-02); before, from its own merger, 0.070 m, scale
-0.26 %, NEES 4.2 (msf-ekf 0.081 m).

A filter whose every SLAM pose has been gated for ``slam_reset_s`` has diverged (its prediction
left the SLAM track, e.g. the drag model on the ground): the next pose restarts position and
velocity (counted ``slam_reset``).

Not modelled: control inputs, quadratic drag, IMU biases, SLAM scale drift within a session
beyond re-estimation, and wind: the drag model gives the velocity relative to the air, so with wind
both the prediction and the horizontal scale pairs are biased (measured on the simulated rectangle
with 0.7 m/s wind: 47 % scale error; ``scale_components="vertical"`` avoids it when the flight has
vertical motion: 1 % on the simulated vertical scenario with the same wind).
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import chi2

from fgnav.baselines._arrived import Arrived
from fgnav.baselines._inputs import Inputs, unused_table
from fgnav.baselines.msf_ekf import SCALE_INIT_WINDOWS_S, initial_fit
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import (
    AttitudeSample,
    Event,
    ImuSample,
    RangeReading,
    SlamPose,
    YawReading,
    replay_flight,
)
from fgnav.datasets.geometry import (
    GRAVITY,
    matrix_to_quat_wxyz,
    matrix_to_rpy,
    quat_wxyz_to_matrix,
    rotation_mean,
    rpy_to_matrix,
    wrap_angle,
)
from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, RangeLimits
from fgnav.datasets.types import Calibration, Flight, Trajectory
from fgnav.estimate import Estimate, TimeSeries
from fgnav.frontends.attitude_ekf import AttitudeEkfOptions, AttitudeEkfStage
from fgnav.frontends.scale_ml import MLScaleEstimator, MLScaleOptions

log = logging.getLogger(__name__)


# State layout.
IP, IV, IR, IPI, IY, IYR = 0, 3, 6, 7, 8, 9
N_STATE = 10

#: What ``Estimate.info["attitude_source"]`` says for each source of roll and pitch.
ATTITUDE_SOURCES = {
    "stream": "logged attitude stream",
    "imu": "estimated from the IMU (seed-002 attitude EKF), not logged",
}

DEFAULT_DRAG_K = (0.4, 0.4)
"""Rotor-drag coefficients ``k = mu/m`` [1/s] when not calibrated: the order reported for small
multirotors (seed 000's simulation uses 0.3 and 0.2; fgnav's simulator 0.38 and 0.42)."""


@dataclass
class Ekf004Options:
    """Options of :class:`Ekf004`.

    Attributes:
        drag_k: linear drag ``(kx, ky)`` [1/s] along body x, y.
        gravity: [m/s^2].
        accel_noise_xy: process noise of the horizontal acceleration model [m/s^2/sqrt(Hz)].
        accel_noise_z: process noise of the vertical acceleration [m/s^2/sqrt(Hz)].
        angle_walk: random walk of roll and pitch [rad/s/sqrt(Hz)] (no control input).
        yaw_accel_noise: random walk of the yaw rate [rad/s^2/sqrt(Hz)].
        position_noise: position process noise [m/sqrt(s)].
        attitude_sigma: roll/pitch measurement noise [rad].
        yaw_sigma: yaw measurement noise [rad].
        yaw_rate_sigma: gyro-derived yaw-rate noise [rad/s] after decimation.
        gyro_decimation: gyro samples averaged per yaw-rate measurement.
        range_sigma: rangefinder noise [m] (vertical speed noise is ``sqrt(2) range_sigma / dt``).
        range_max_dt_s: longest interval between two range readings that are differentiated [s].
        range_max_tilt_rad: readings at larger tilt are not used.
        range_outlier_m: a height more than this from the median of the last readings is an
            obstacle or a spike and is skipped (counted).
        slam_position_sigma: SLAM camera position noise after scaling [m].
        slam_angle_sigma: SLAM roll/pitch/yaw noise [rad].
        use_slam_angles: also fuse the SLAM orientation (seed eq. 4 observes all six).
        use_yaw: fuse the yaw stream when present.
        scale_pair_interval_s: length of each scale sample (the seed takes one per second).
        scale_components: displacement components of the scale pairs: ``"xyz"``,
            ``"vertical"`` (rangefinder only: unaffected by wind, needs vertical motion; the seed's
            first test) or ``"horizontal"`` (drag-model velocity only).
        scale_min_pairs: accepted pairs needed before SLAM positions are fused.
        scale_repivot: on a scale change, re-pivot the map at the current SLAM pose so that the
            position measurement does not jump (tum_ardrone); when False the map keeps its origin
            at the session's first pose and every position uses the latest scale.
        scale: options of the ML scale estimator (displacement noises, minimum motion, gate).
        align_poses: SLAM poses averaged to estimate ``world_R_slam`` at a session start.
        delay_compensation: roll back and replay for late SLAM poses (seed fig. 2); when False,
            a SLAM pose is applied when it arrives as if it were taken then (the naive filter).
        history_s: measurement history kept for delay compensation [s] (seed: delays to 0.5 s).
        gate_probability: chi-square gate probability of every update.
        max_predict_dt_s: longest single prediction step [s].
        initial_position_sigma: [m]; initial_velocity_sigma: [m/s]; initial_angle_sigma [rad];
        initial_yaw_rate_sigma [rad/s].
        attitude_source: ``"stream"`` (the flight's attitude), ``"imu"`` (estimated from the IMU,
            the attitude EKF stage) or ``"auto"`` (the stream when present).
        imu_attitude_rate_hz: rate of the estimated attitude samples (the EKF's output rate).
        imu_attitude_sigma: roll/pitch noise of the estimated attitude [rad].
        imu_attitude_accel_sigma: ``accel_sigma`` of the attitude EKF [m/s^2].
        imu_attitude_gyro_bias: estimate the gyro bias in the attitude EKF.
        scale_source: ``"ml"`` (the seed's ML scale from metric displacement pairs),
            ``"imu_fit"`` (closed-form IMU-SLAM fits, module docstring) or ``"auto"`` (``"ml"``
            with an attitude stream, else ``"imu_fit"``).
        imu_fit_interval_s: how often a new closed-form fit is tried [s].
        slam_reset_s: when every SLAM pose has been gated for this long [s], the next one
            restarts position and velocity (the prediction diverged; counted ``slam_reset``).
    """

    drag_k: tuple[float, float] = DEFAULT_DRAG_K
    gravity: float = GRAVITY
    accel_noise_xy: float = 0.5
    accel_noise_z: float = 1.0
    angle_walk: float = 0.5
    yaw_accel_noise: float = 1.0
    position_noise: float = 0.01
    attitude_sigma: float = 0.01
    yaw_sigma: float = 0.05
    yaw_rate_sigma: float = 0.02
    gyro_decimation: int = 4
    range_sigma: float = 0.02
    range_max_dt_s: float = 0.2
    range_max_tilt_rad: float = 0.5
    range_outlier_m: float = 0.2
    slam_position_sigma: float = 0.05
    slam_angle_sigma: float = 0.02
    use_slam_angles: bool = True
    use_yaw: bool = True
    scale_pair_interval_s: float = 1.0
    scale_components: str = "xyz"
    scale_min_pairs: int = 5
    scale_repivot: bool = True
    scale: MLScaleOptions = field(default_factory=MLScaleOptions)
    align_poses: int = 10
    delay_compensation: bool = True
    history_s: float = 1.0
    gate_probability: float = 0.999
    max_predict_dt_s: float = 0.01
    initial_position_sigma: float = 0.01
    initial_velocity_sigma: float = 0.5
    initial_angle_sigma: float = 0.05
    initial_yaw_rate_sigma: float = 0.2
    attitude_source: str = "auto"
    imu_attitude_rate_hz: float = 100.0
    imu_attitude_sigma: float = 0.03
    imu_attitude_accel_sigma: float = 0.5
    imu_attitude_gyro_bias: bool = False
    scale_source: str = "auto"
    imu_fit_interval_s: float = 2.0
    slam_reset_s: float = 1.0

    def validate(self) -> None:
        """Raise :class:`FlightDataError` naming the first invalid option."""
        positive = (
            "gravity accel_noise_xy accel_noise_z angle_walk yaw_accel_noise position_noise "
            "attitude_sigma yaw_sigma yaw_rate_sigma range_sigma range_max_dt_s "
            "slam_position_sigma slam_angle_sigma scale_pair_interval_s max_predict_dt_s "
            "initial_position_sigma initial_velocity_sigma initial_angle_sigma "
            "initial_yaw_rate_sigma imu_attitude_rate_hz imu_attitude_sigma "
            "imu_attitude_accel_sigma"
        ).split()
        for name in positive:
            if not getattr(self, name) > 0:
                raise FlightDataError(f"Ekf004Options.{name}={getattr(self, name)!r}: must be > 0")
        if len(self.drag_k) != 2 or min(self.drag_k) < 0:
            raise FlightDataError(f"Ekf004Options.drag_k={self.drag_k!r}: expected (kx, ky) >= 0")
        if self.scale_components not in ("xyz", "vertical", "horizontal"):
            raise FlightDataError(
                f"Ekf004Options.scale_components={self.scale_components!r}: expected 'xyz', "
                "'vertical' or 'horizontal'"
            )
        if self.attitude_source not in ("auto", "stream", "imu"):
            raise FlightDataError(
                f"Ekf004Options.attitude_source={self.attitude_source!r}: expected 'auto', "
                "'stream' or 'imu'"
            )
        if self.scale_source not in ("auto", "ml", "imu_fit"):
            raise FlightDataError(
                f"Ekf004Options.scale_source={self.scale_source!r}: expected 'auto', 'ml' or "
                "'imu_fit'"
            )
        if not 0 < self.gate_probability < 1:
            raise FlightDataError("Ekf004Options.gate_probability: expected a value in (0, 1)")
        for name in ("gyro_decimation", "scale_min_pairs", "align_poses"):
            if int(getattr(self, name)) < 1:
                raise FlightDataError(f"Ekf004Options.{name}: expected an integer >= 1")


# ----------------------------------------------------------------------------------------------
# Model functions
# ----------------------------------------------------------------------------------------------


def euler_rate_matrix(roll: float, pitch: float) -> np.ndarray:
    """``W`` with ``body_omega = W d(roll, pitch, yaw)/dt`` (ZYX); also maps a small Euler-angle
    error to the body rotation vector of GTSAM's right perturbation."""
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    return np.array([[1.0, 0.0, -sp], [0.0, cr, sr * cp], [0.0, -sr, cr * cp]])


def horizontal_accel(
    x: np.ndarray, drag_k: tuple[float, float], g: float
) -> tuple[np.ndarray, np.ndarray]:
    """Seed 004's horizontal acceleration ``a_xy(x)`` [m/s^2] and its (2, 10) Jacobian.

    ``a_xy = g (R e3)_xy / (R e3)_z - Rz(yaw) diag(kx, ky) Rz(yaw)^T v_xy``; with ``A = tan(pitch)``
    and ``B = tan(roll) / cos(pitch)``, ``g (R e3)_xy / (R e3)_z = g [cy A + sy B, sy A - cy B]``.
    """
    roll, pitch, yaw = float(x[IR]), float(x[IPI]), float(x[IY])
    vx, vy = float(x[IV]), float(x[IV + 1])
    kx, ky = drag_k
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr = math.cos(roll)
    tr = math.tan(roll)
    cy, sy = math.cos(yaw), math.sin(yaw)
    A = sp / cp
    B = tr / cp
    # K = Rz diag(kx, ky) Rz^T and its derivative in yaw.
    k11 = kx * cy * cy + ky * sy * sy
    k22 = kx * sy * sy + ky * cy * cy
    k12 = (kx - ky) * cy * sy
    dk11 = 2.0 * (ky - kx) * cy * sy
    dk12 = (kx - ky) * (cy * cy - sy * sy)
    a = np.array(
        [
            g * (cy * A + sy * B) - (k11 * vx + k12 * vy),
            g * (sy * A - cy * B) - (k12 * vx + k22 * vy),
        ]
    )
    J = np.zeros((2, N_STATE))
    J[0, IV], J[0, IV + 1], J[1, IV], J[1, IV + 1] = -k11, -k12, -k12, -k22
    dA_dp = 1.0 / cp**2
    dB_dr = 1.0 / (cr**2 * cp)
    dB_dp = tr * sp / cp**2
    J[0, IR], J[1, IR] = g * sy * dB_dr, -g * cy * dB_dr
    J[0, IPI] = g * (cy * dA_dp + sy * dB_dp)
    J[1, IPI] = g * (sy * dA_dp - cy * dB_dp)
    J[0, IY] = g * (-sy * A + cy * B) - (dk11 * vx + dk12 * vy)
    J[1, IY] = g * (cy * A + sy * B) - (dk12 * vx - dk11 * vy)
    return a, J


def drag_model_velocity(
    t: np.ndarray, world_R_body: np.ndarray, drag_k: tuple[float, float], g: float
) -> np.ndarray:
    """(N, 2) horizontal velocity [m/s] of the drag model driven by measured attitude only.

    Integrates ``dv/dt = a_xy(attitude, v)`` from rest (semi-implicit Euler: the drag term is
    implicit, stable at any step). The drag makes the initial value forgotten with time constant
    ``1/k``, so this metric velocity needs neither SLAM nor an initial velocity.
    """
    rpy = matrix_to_rpy(world_R_body)
    out = np.zeros((t.size, 2))
    v = (0.0, 0.0)
    for i in range(1, t.size):
        v = drag_model_step(v, rpy[i - 1], float(t[i] - t[i - 1]), drag_k, g)
        out[i] = v
    return out


def drag_model_step(
    v_xy: tuple[float, float], rpy: np.ndarray, dt: float, drag_k: tuple[float, float], g: float
) -> tuple[float, float]:
    """One semi-implicit Euler step [s] of :func:`drag_model_velocity` from ``v_xy`` [m/s] with
    the attitude ``rpy`` [rad] at the start of the step."""
    x = np.zeros(N_STATE)
    x[IR : IY + 1] = rpy
    thrust, _ = horizontal_accel(x, drag_k, g)
    kx, ky = drag_k
    vx, vy = v_xy
    cy, sy = math.cos(rpy[2]), math.sin(rpy[2])
    # Drag along body-yaw axes is diagonal: solve (I + dt K) v = v + dt a in those axes.
    bx = cy * (vx + dt * thrust[0]) + sy * (vy + dt * thrust[1])
    by = -sy * (vx + dt * thrust[0]) + cy * (vy + dt * thrust[1])
    bx /= 1.0 + dt * kx
    by /= 1.0 + dt * ky
    return cy * bx - sy * by, sy * bx + cy * by


def check_flight(flight: Flight, opt: Ekf004Options) -> None:
    """Raise :class:`FlightDataError` when the flight lacks what ``opt.attitude_source`` needs
    (an attitude stream, or an IMU to estimate it)."""
    src = opt.attitude_source
    if src == "stream" and flight.attitude is None:
        raise FlightDataError(f"{flight.name}: ekf004 attitude_source='stream' needs an attitude")
    if flight.imu is None and (src == "imu" or flight.attitude is None):
        raise FlightDataError(
            f"{flight.name}: ekf004 needs an attitude stream (roll, pitch) or an IMU to estimate it"
        )


# ----------------------------------------------------------------------------------------------
# Filter
# ----------------------------------------------------------------------------------------------


#: The stream of each measurement kind of :class:`Ekf004Counts` (derived kinds: their source).
_STREAM_OF_KIND = {
    "imu": "imu",
    "attitude": "attitude",
    "yaw": "yaw",
    "range": "range",
    "slam": "slam",
    "vertical_speed": "range",
    "gyro": "imu",
    "yaw_rate": "imu",
}


@dataclass
class Ekf004Counts:
    """What the filter did with each measurement kind (reported in ``Estimate.info``)."""

    used: dict[str, int] = field(default_factory=dict)
    gated: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    replayed: int = 0
    late_beyond_history: int = 0
    active: bool = True
    """False while replaying (a replayed measurement is counted once, when it first arrives)."""

    def unused(self) -> dict[str, int]:
        """The measurements not used, ``stream:reason -> count`` (:mod:`fgnav.baselines._inputs`):
        ``gated`` by kind; ``skipped`` keys ``<stream>_<reason>`` (or ``<stream>``: its height
        was rejected); the vertical speeds from range heights and the SLAM scale pairs are
        counted under their stream (``range:vertical-speed``, ``slam:scale-pair`` ...)."""
        out: dict[str, int] = {}

        def put(key: str, n: int) -> None:
            out[key] = out.get(key, 0) + int(n)

        for kind, n in self.gated.items():
            stream = _STREAM_OF_KIND.get(kind, kind)
            put(
                f"{stream}:gated" if stream == kind else f"{stream}:{kind}-gated".replace("_", "-"),
                n,
            )
        kinds = sorted(_STREAM_OF_KIND, key=len, reverse=True)
        for key, n in self.skipped.items():
            kind = next((k for k in kinds if key == k or key.startswith(f"{k}_")), None)
            if kind is None:  # scale_pair*, scale_estimate: SLAM poses not used for the scale
                put(f"slam:{key.replace('_', '-')}", n)
                continue
            stream = _STREAM_OF_KIND[kind]
            reason = key[len(kind) + 1 :] if key != kind else ("rejected" if kind == stream else "")
            if kind != stream:
                reason = f"{kind}-{reason}" if reason else kind
            put(f"{stream}:{reason.replace('_', '-')}", n)
        return out

    def add(self, table: str, kind: str, n: int = 1) -> None:
        if not self.active:
            return
        d = getattr(self, table)
        d[kind] = d.get(kind, 0) + n


class Ekf004:
    """The EKF core: ``predict`` to a time, then ``update_*`` with one measurement.

    Args:
        options: filter options.
        body_t_cam: camera lever arm in body [m].
    """

    def __init__(self, options: Ekf004Options | None = None, body_t_cam=(0.0, 0.0, 0.0)) -> None:
        self.opt = options or Ekf004Options()
        self.opt.validate()
        self.body_t_cam = np.asarray(body_t_cam, dtype=float)
        self.t = 0.0
        self.x = np.zeros(N_STATE)
        self.P = np.eye(N_STATE)
        self.counts = Ekf004Counts()
        self._gates: dict[int, float] = {}
        self.slam_gated_since: float | None = None
        o = self.opt
        self._F = np.eye(N_STATE)
        self._diag = np.arange(N_STATE)
        q = np.zeros(N_STATE)
        q[IP : IP + 3] = o.position_noise**2
        q[IV : IV + 2] = o.accel_noise_xy**2
        q[IV + 2] = o.accel_noise_z**2
        q[IR] = q[IPI] = o.angle_walk**2
        q[IYR] = o.yaw_accel_noise**2
        self._q = q

    # -- state -----------------------------------------------------------------------------------

    def initialize(self, t: float, x0: np.ndarray, P0: np.ndarray) -> None:
        """Set time [s], state and covariance."""
        self.t = float(t)
        self.x = np.asarray(x0, dtype=float).copy()
        self.P = np.asarray(P0, dtype=float).copy()

    def snapshot(self) -> tuple[float, np.ndarray, np.ndarray, float | None]:
        return self.t, self.x.copy(), self.P.copy(), self.slam_gated_since

    def restore(self, snap: tuple[float, np.ndarray, np.ndarray, float | None]) -> None:
        self.t, x, P, self.slam_gated_since = snap
        self.x, self.P = x.copy(), P.copy()

    def world_R_body(self) -> np.ndarray:
        return rpy_to_matrix(self.x[IR], self.x[IPI], self.x[IY])

    # -- prediction ------------------------------------------------------------------------------

    def _predict_step(self, dt: float) -> None:
        o = self.opt
        x = self.x
        a_xy, Ja = horizontal_accel(x, o.drag_k, o.gravity)
        F = self._F
        F[IV : IV + 2, :] = dt * Ja
        F[IV, IV] += 1.0
        F[IV + 1, IV + 1] += 1.0
        for k in range(3):
            F[IP + k, IV + k] = dt
        F[IY, IYR] = dt
        xn = x.copy()
        xn[IP : IP + 3] += dt * x[IV : IV + 3]
        xn[IV : IV + 2] += dt * a_xy
        xn[IY] = wrap_angle(x[IY] + dt * x[IYR])
        self.x = xn
        self.P = F @ self.P @ F.T
        self.P[self._diag, self._diag] += self._q * dt

    def predict(self, t: float) -> None:
        """Propagate the state to time ``t`` [s] (no-op if ``t`` is not later)."""
        dt_total = t - self.t
        if dt_total <= 0.0:
            return
        n = max(1, int(math.ceil(dt_total / self.opt.max_predict_dt_s)))
        for _ in range(n):
            self._predict_step(dt_total / n)
        self.t = float(t)

    # -- update ----------------------------------------------------------------------------------

    def _gate(self, dim: int) -> float:
        if dim not in self._gates:
            self._gates[dim] = float(chi2.ppf(self.opt.gate_probability, dim))
        return self._gates[dim]

    def update(self, kind: str, r: np.ndarray, H: np.ndarray, Rm: np.ndarray) -> bool:
        """Gated EKF update with residual ``r = z - h(x)``, Jacobian ``H`` and noise ``Rm``.

        Returns:
            True when applied, False when rejected by the chi-square gate (counted).
        """
        PHt = self.P @ H.T
        return self._gated_correction(kind, r, PHt, H @ PHt + Rm)

    def _gated_correction(self, kind: str, r: np.ndarray, PHt: np.ndarray, S: np.ndarray) -> bool:
        """Chi-square gate on ``r`` with innovation covariance ``S``, then the correction with
        gain ``PHt S^-1`` (counted as used or gated)."""
        S_inv = np.linalg.inv(S)
        if float(r @ S_inv @ r) > self._gate(r.size):
            self.counts.add("gated", kind)
            return False
        self._correct(kind, r, PHt, S_inv)
        return True

    def _correct(self, kind: str, r: np.ndarray, PHt: np.ndarray, S_inv: np.ndarray) -> None:
        """The EKF correction with gain ``PHt S^-1`` (yaw wrapped, ``P`` kept symmetric), counted
        as used; no gate (:meth:`_gated_correction` gates first)."""
        K = PHt @ S_inv
        self.x = self.x + K @ r
        self.x[IY] = wrap_angle(self.x[IY])
        P = self.P - K @ PHt.T
        self.P = 0.5 * (P + P.T)
        self.counts.add("used", kind)

    def update_state_components(
        self, kind: str, idx: list[int], r: np.ndarray, var: np.ndarray
    ) -> bool:
        """:meth:`update` for a measurement of state components ``x[idx]`` (selection ``H``) with
        independent noise variances ``var``; the same result with fewer operations."""
        if len(idx) == 1:
            j = idx[0]
            s = float(self.P[j, j] + var[0])
            rj = float(r[0])
            if rj * rj / s > self._gate(1):
                self.counts.add("gated", kind)
                return False
            col = self.P[:, j].copy()
            self.x = self.x + col * (rj / s)
            self.x[IY] = wrap_angle(self.x[IY])
            self.P = self.P - np.outer(col, col) / s
            self.counts.add("used", kind)
            return True
        PHt = self.P[:, idx]
        return self._gated_correction(kind, r, PHt, PHt[idx, :] + np.diag(var))

    def update_attitude(self, roll: float, pitch: float, sigma: float | None = None) -> bool:
        """Roll and pitch [rad] from the attitude stream (noise ``sigma`` [rad], default
        ``attitude_sigma``)."""
        r = np.array([wrap_angle(roll - self.x[IR]), wrap_angle(pitch - self.x[IPI])])
        var = np.full(2, (self.opt.attitude_sigma if sigma is None else sigma) ** 2)
        return self.update_state_components("attitude", [IR, IPI], r, var)

    def update_yaw(self, yaw: float) -> bool:
        """Absolute yaw [rad] (wrapped residual)."""
        r = np.array([wrap_angle(yaw - self.x[IY])])
        return self.update_state_components("yaw", [IY], r, np.array([self.opt.yaw_sigma**2]))

    def update_body_rates(self, body_omega: np.ndarray) -> bool:
        """Yaw rate ``(q sin(roll) + r cos(roll)) / cos(pitch)`` from a gyro reading [rad/s]."""
        roll, pitch = self.x[IR], self.x[IPI]
        rate = (body_omega[1] * math.sin(roll) + body_omega[2] * math.cos(roll)) / math.cos(pitch)
        r = np.array([rate - self.x[IYR]])
        var = np.array([self.opt.yaw_rate_sigma**2])
        return self.update_state_components("yaw_rate", [IYR], r, var)

    def update_vertical_speed(self, vz: float, sigma: float) -> bool:
        """Vertical speed [m/s] from differentiated height (seed eq. 3)."""
        r = np.array([vz - self.x[IV + 2]])
        return self.update_state_components("vertical_speed", [IV + 2], r, np.array([sigma**2]))

    def release_position(self, offset: np.ndarray) -> None:
        """Forget position and velocity: zero velocity, their cross-covariances removed, position
        variance ``offset^2 + initial_position_sigma^2`` per axis [m], velocity variance
        ``initial_velocity_sigma^2``; the next position measurement sets them."""
        o = self.opt
        ip = np.r_[IP : IP + 3, IV : IV + 3]
        self.P[ip, :] = 0.0
        self.P[:, ip] = 0.0
        var = np.asarray(offset, dtype=float) ** 2 + o.initial_position_sigma**2
        self.P[IP : IP + 3, IP : IP + 3] = np.diag(var)
        self.P[IV : IV + 3, IV : IV + 3] = np.eye(3) * o.initial_velocity_sigma**2
        self.x[IV : IV + 3] = 0.0

    def camera_position(self, x: np.ndarray | None = None) -> np.ndarray:
        """``world_t_cam = p + world_R_body body_t_cam`` [m]."""
        x = self.x if x is None else x
        return x[IP : IP + 3] + rpy_to_matrix(x[IR], x[IPI], x[IY]) @ self.body_t_cam

    def update_slam_pose(self, world_t_cam: np.ndarray, rpy: np.ndarray | None) -> bool:
        """Scaled SLAM camera position in world [m] and, optionally, body roll/pitch/yaw [rad]
        (seed eq. 4)."""
        n = 3 if rpy is None else 6
        H = np.zeros((n, N_STATE))
        H[:3, IP : IP + 3] = np.eye(3)
        eps = 1e-6
        base = self.camera_position()
        for j in (IR, IPI, IY):
            xp = self.x.copy()
            xp[j] += eps
            H[:3, j] = (self.camera_position(xp) - base) / eps
        r = np.empty(n)
        r[:3] = world_t_cam - base
        sig = np.full(n, self.opt.slam_position_sigma)
        if rpy is not None:
            H[3, IR] = H[4, IPI] = H[5, IY] = 1.0
            r[3:] = wrap_angle(np.asarray(rpy) - self.x[IR : IY + 1])
            sig[3:] = self.opt.slam_angle_sigma
        Rm = np.diag(sig**2)
        if self.update("slam", r, H, Rm):
            self.slam_gated_since = None
            return True
        if self.slam_gated_since is None:
            self.slam_gated_since = self.t
            return False
        if self.t - self.slam_gated_since < self.opt.slam_reset_s:
            return False
        # Every SLAM pose gated for slam_reset_s: the prediction has diverged (e.g. the drag model
        # on the ground or carried by hand); restart position and velocity from this pose.
        self.release_position(r[:3])
        PHt = self.P @ H.T
        self._correct("slam_reset", r, PHt, np.linalg.inv(H @ PHt + Rm))
        self.slam_gated_since = None
        return True

    # -- outputs ---------------------------------------------------------------------------------

    def pose_cov(self) -> np.ndarray:
        """6x6 covariance in GTSAM's Pose3 tangent ``[rot (body), trans (body)]``."""
        return state_covariances(self.x, self.P)[0]


def state_covariances(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(pose_cov, vel_cov)`` of a state ``x`` with covariance ``P`` (module docstring layout):
    the 6x6 pose covariance in GTSAM's Pose3 tangent ``[rot (body), trans (body)]`` (the
    Euler-angle errors mapped to the body rotation by :func:`euler_rate_matrix`) and the 3x3
    covariance of the world velocity."""
    J = np.zeros((6, N_STATE))
    J[:3, IR : IY + 1] = euler_rate_matrix(x[IR], x[IPI])
    J[3:, IP : IP + 3] = rpy_to_matrix(*x[IR : IY + 1]).T
    C = J @ P @ J.T
    return 0.5 * (C + C.T), P[IV : IV + 3, IV : IV + 3].copy()


# ----------------------------------------------------------------------------------------------
# SLAM session bookkeeping (scale pairs, alignment, anchor)
# ----------------------------------------------------------------------------------------------


@dataclass
class _Session:
    sid: int
    rotations: list[np.ndarray] = field(default_factory=list)
    world_R_slam: np.ndarray | None = None
    estimator: MLScaleEstimator | None = None
    pair_start: tuple[float, np.ndarray] | None = None
    scale: float | None = None
    scale_sigma: float | None = None
    anchor_slam: np.ndarray | None = None
    anchor_world: np.ndarray | None = None
    fit_from: float | None = None
    last_fit_try: float | None = None
    fits: list[tuple[float, float]] = field(default_factory=list)


ODOMETRY_HISTORY_S = 30.0
"""Seconds of attitude-driven odometry and range heights kept for the scale pairs."""

START_WAIT_S = 1.0
"""Longest wait [s] from the first attitude sample for the first yaw reading and range height."""

_IN_ORDER = {ImuSample: "imu", AttitudeSample: "attitude", RangeReading: "range"}
"""Streams whose samples :class:`Ekf004Runner` takes in time order only."""

SOURCES_WINDOW_S = 0.5
"""The streams that have sent an event within this long [s] of the first event's arrival decide
the ``"auto"`` attitude and scale sources and which streams the start waits for."""

IMU_FIT_HISTORY_S = 120.0
"""Seconds of arrived IMU and SLAM data kept for the closed-form scale fits."""


class _MetricOdometry:
    """Metric camera displacements between two past times, independent of SLAM: horizontal from
    the drag-model velocity driven by the attitude samples as they arrive
    (:func:`drag_model_velocity`, one step per sample), vertical from the rangefinder heights
    (:meth:`add_range`). Keeps the last ``ODOMETRY_HISTORY_S``."""

    def __init__(self, opt: Ekf004Options, body_t_cam: np.ndarray, calib, counts) -> None:
        self.opt = opt
        self.body_t_cam = body_t_cam
        self.counts = counts
        body_T_range = np.asarray(calib.body_T_range, dtype=float)
        self._beam = body_T_range[:3, :3] @ np.array([0.0, 0.0, 1.0])
        self._lever = body_T_range[:3, 3]
        self._range_limits = RangeLimits(calib.range_min, calib.range_max)
        self._att: deque[tuple[float, float, float, np.ndarray]] = deque()  # t, x, y, R
        self._v = (0.0, 0.0)
        self._rpy_prev: np.ndarray | None = None
        self._h: deque[tuple[float, float]] = deque()
        self._h_window: list[float] = []
        self.range_total = self.range_skipped = 0

    @property
    def R_latest(self) -> np.ndarray | None:
        return self._att[-1][3] if self._att else None

    def add_attitude(self, t: float, R: np.ndarray, rpy: np.ndarray) -> None:
        """One attitude sample: a semi-implicit Euler step of the drag-model velocity from the
        previous sample (attitude of the previous sample; the drag term implicit)."""
        if not self._att:
            self._att.append((t, 0.0, 0.0, R))
            self._rpy_prev = rpy
            return
        t_prev, px, py, _ = self._att[-1]
        dt = t - t_prev
        if dt <= 0.0:
            return
        vx0, vy0 = self._v
        vx, vy = drag_model_step(self._v, self._rpy_prev, dt, self.opt.drag_k, self.opt.gravity)
        self._att.append((t, px + 0.5 * (vx + vx0) * dt, py + 0.5 * (vy + vy0) * dt, R))
        self._v = (vx, vy)
        self._rpy_prev = rpy
        while self._att and self._att[0][0] < t - ODOMETRY_HISTORY_S:
            self._att.popleft()

    def add_range(self, t: float, r: float) -> float | None:
        """Tilt-corrected body height [m] above the ground of one reading (the latest attitude
        that has arrived), or None when skipped: tilt, limits, or a spike (more than
        ``range_outlier_m`` from the median of the last kept readings); counted ``range``
        (``range_at_min``, ``range_at_max``: at the sensor's floor or maximum, no distance).

        The beam is the sensor's +z axis: ``h_sensor = -range (world_R_body body_R_range e3)_z``;
        the body height subtracts the lever arm ``(world_R_body body_t_range)_z``.
        """
        o = self.opt
        self.range_total += 1
        self._range_limits.see(r)
        why = self._range_limits.refusal(r)
        if why in RANGE_LIMIT_TAGS:
            self.range_skipped += 1
            self.counts.add("skipped", f"range_{why.replace('-', '_')}")
            return None
        R = self.R_latest
        h = None
        if R is not None and why is None:
            cos_tilt = -float(R[2] @ self._beam)
            if cos_tilt > math.cos(o.range_max_tilt_rad):
                h = r * cos_tilt - float(R[2] @ self._lever)
        w = self._h_window
        if h is not None and len(w) >= 3 and abs(h - float(np.median(w))) > o.range_outlier_m:
            h = None
        if h is None:
            self.range_skipped += 1
            self.counts.add("skipped", "range")
            return None
        self._h_window = (w + [h])[-5:]
        self._h.append((t, h))
        while self._h and self._h[0][0] < t - ODOMETRY_HISTORY_S:
            self._h.popleft()
        return h

    def camera_displacement(self, t0: float, t1: float) -> np.ndarray | None:
        """World displacement [m] of the camera from ``t0`` to ``t1`` (z NaN without heights)."""
        if len(self._att) < 2 or t0 < self._att[0][0] or t1 > self._att[-1][0]:
            return None
        t = np.array([a[0] for a in self._att])
        xy = np.array([(a[1], a[2]) for a in self._att])
        dxy = [np.interp(t1, t, xy[:, k]) - np.interp(t0, t, xy[:, k]) for k in range(2)]
        dz = math.nan
        if len(self._h) >= 2 and self._h[0][0] <= t0 and t1 <= self._h[-1][0]:
            ht = np.array([h[0] for h in self._h])
            hv = np.array([h[1] for h in self._h])
            dz = float(np.interp(t1, ht, hv) - np.interp(t0, ht, hv))
        i0 = min(int(np.searchsorted(t, t0)), t.size - 1)
        i1 = min(int(np.searchsorted(t, t1)), t.size - 1)
        lever = (self._att[i1][3] - self._att[i0][3]) @ self.body_t_cam
        return np.array([dxy[0], dxy[1], dz]) + lever


@dataclass
class _Entry:
    """One processed measurement in the history: the state before it, and its data."""

    t: float
    seq: int
    kind: str
    data: Any
    snap: tuple[float, np.ndarray, np.ndarray, float | None] | None = None
    payload: Any = None


class Ekf004Runner:
    """Seed 004's EKF fed events in arrival order (``feed``), with delay compensation.

    Built from the calibration and the options (``Ekf004Runner(calib, options)``, or
    ``Ekf004Runner(options=...)`` then :meth:`start`), it never sees a flight: :meth:`run`
    replays one (:func:`fgnav.datasets.events.replay_flight`) into :meth:`feed`, a live link feeds
    it the same way (:class:`fgnav.live.estimators.Ekf004Live`). :meth:`latest_output` is the
    newest output, :meth:`result` the :class:`Estimate`. Afterwards ``ekf`` holds the filter
    after the last measurement (all late ones applied), ``sessions`` the SLAM sessions.

    The first ``SOURCES_WINDOW_S`` of events are held: the streams among them resolve the
    ``"auto"`` attitude source (the stream when an attitude sample came, else the IMU) and scale
    source, and which of yaw and range the start waits for; then they are processed in order.
    An explicit ``attitude_source="stream"`` never estimates the attitude (no output without
    attitude samples); ``"imu"`` ignores attitude samples.

    What the events become: attitude samples (the stream, or seed 002's attitude EKF run as a
    stage on the IMU, yaw and range events, sampled at ``imu_attitude_rate_hz``) give roll and
    pitch and drive the drag-model odometry; every ``gyro_decimation`` IMU samples give one
    yaw-rate measurement, stamped at the last of them (a delay of half the averaging window);
    consecutive tilt-corrected range heights give the vertical speed; SLAM poses are applied at
    their capture time (rolled back and replayed when late). The filter starts at the first
    attitude sample by which the first yaw reading and range height (of the streams the window
    saw) have arrived, or ``START_WAIT_S`` after the first attitude sample without them.
    """

    def __init__(
        self,
        calib: Calibration | None = None,
        options: Ekf004Options | None = None,
        name: str = "flight",
    ) -> None:
        self.opt = options or Ekf004Options()
        self.opt.validate()
        if calib is not None:
            self.start(calib, name)

    def start(self, calib: Calibration, name: str = "flight") -> None:
        """Prepare to be fed events of a vehicle with calibration ``calib``."""
        opt = self.opt
        self.name = name
        self.calib = calib
        body_T_cam = np.asarray(calib.body_T_cam, dtype=float)
        self.body_R_cam = body_T_cam[:3, :3]
        self.ekf = Ekf004(opt, body_T_cam[:3, 3])
        self.counts = self.ekf.counts
        self.odo = _MetricOdometry(opt, body_T_cam[:3, 3], calib, self.counts)
        # Decided at the end of the sources window (_decide).
        self.attitude_source: str | None = None
        self.scale_source: str | None = None
        self.attitude_sigma = math.nan
        self.expect_yaw = self.expect_range = False
        self.att_stage: AttitudeEkfStage | None = None
        self._arrived: Arrived | None = None
        self._held: list[Event] = []
        self._window_end: float | None = None
        self._t_newest: dict[str, float] = {}
        self._att_next_t = -math.inf
        self._gyro_buf: list[np.ndarray] = []
        self._h_prev: tuple[float, float] | None = None
        self._yaw_first: float | None = None
        self._pending_attitude: tuple[float, np.ndarray] | None = None
        self._t_first_attitude = math.nan
        self._started = False
        self._seq = 0
        self.sessions: dict[int, _Session] = {}
        self.history: list[_Entry] = []
        self.out_t: list[float] = []
        self.out_x: list[np.ndarray] = []
        self.out_P: list[np.ndarray] = []
        self.scale_t: list[float] = []
        self.scale_v: list[float] = []
        self.scale_sid: list[int] = []
        self.latencies: list[float] = []
        self._inputs = Inputs("ekf004", name)
        self.imu_used = 0  # IMU samples taken after the start (yaw rate, attitude EKF)
        self.t_first_output: float | None = None
        self._wall0 = time.perf_counter()

    def _decide(self) -> None:
        """The sources, from the streams of the held events (class docstring); then the held
        events are processed."""
        opt, held = self.opt, self._held
        seen = {type(e) for e in held}
        src = opt.attitude_source
        if src == "auto":
            src = "stream" if AttitudeSample in seen else "imu"
        self.attitude_source = src
        self.scale_source = opt.scale_source
        if self.scale_source == "auto":
            self.scale_source = "ml" if src == "stream" else "imu_fit"
        self.attitude_sigma = opt.attitude_sigma if src == "stream" else opt.imu_attitude_sigma
        self.expect_yaw = YawReading in seen and opt.use_yaw
        self.expect_range = RangeReading in seen
        if src == "imu":
            log.info("ekf004: %s: no attitude stream; attitude estimated from the IMU", self.name)
            ao = AttitudeEkfOptions(
                accel_sigma=opt.imu_attitude_accel_sigma,
                estimate_gyro_bias=opt.imu_attitude_gyro_bias,
            )
            self.att_stage = AttitudeEkfStage(
                self.calib, ao, use_range=self.expect_range, name=self.name
            )
        # The closed-form fits integrate the gyro themselves (bias from SLAM rotations): they get
        # the arrived IMU and SLAM (and a logged attitude), never the IMU-estimated attitude.
        self._arrived = Arrived() if self.scale_source == "imu_fit" else None
        # imu_fit scale: outputs from the first scale on (as the MSF and UKF baselines whose
        # closed-form start it shares); the seed's ML path reports from the first sample.
        self.t_first_output = None if self.scale_source == "ml" else np.inf
        self._held = []
        for ev in held:
            self._feed(ev)

    # -- events ----------------------------------------------------------------------------------

    def feed(self, ev: Event) -> None:
        """One measurement event, in arrival order (IMU, attitude, yaw, range, SLAM pose; a
        corrupted IMU sample is dropped and counted: :mod:`fgnav.baselines._inputs`)."""
        if not self._inputs.take(ev):
            return
        if self.attitude_source is not None:
            self._feed(ev)
            return
        self._held.append(ev)
        if self._window_end is None:
            self._window_end = float(ev.arrival) + SOURCES_WINDOW_S
        if ev.arrival >= self._window_end:
            self._decide()

    def close(self) -> None:
        """The end of the input: the sources are decided now if the window has not ended."""
        if self.attitude_source is None:
            self._decide()

    def _feed(self, ev: Event) -> None:
        w0 = time.perf_counter()
        stream = _IN_ORDER.get(type(ev))
        if stream is not None:
            # The attitude-driven odometry, the range heights and the gyro average take these
            # in time order: an older sample than the newest is skipped (counted).
            if not ev.t > self._t_newest.get(stream, -math.inf):
                self.counts.add("skipped", f"{stream}_out_of_order")
                return
            self._t_newest[stream] = float(ev.t)
        if isinstance(ev, ImuSample):
            self._on_imu(ev)
        elif isinstance(ev, AttitudeSample):
            if self.attitude_source == "stream":
                if self._arrived is not None:
                    self._arrived.add(ev)
                self._on_attitude(ev.t, ev.world_q_body_wxyz)
        elif isinstance(ev, YawReading):
            if self.att_stage is not None:
                self._on_stage(self.att_stage.feed(ev))
            if self.opt.use_yaw:
                if self._yaw_first is None:
                    self._yaw_first = float(ev.yaw)
                    self._try_start()
                self._entry(ev.t, "yaw", float(ev.yaw))
        elif isinstance(ev, RangeReading):
            if self.att_stage is not None:
                self._on_stage(self.att_stage.feed(ev))
            self._on_range(ev)
        elif isinstance(ev, SlamPose):
            if self._arrived is not None:
                self._arrived.add(ev)
            t_meas = ev.t if self.opt.delay_compensation else max(ev.t, ev.arrival)
            self._entry(t_meas, "slam", ev)
        else:
            return
        self.latencies.append(time.perf_counter() - w0)

    @property
    def output_t(self) -> float | None:
        """Time of the newest output (None before the first)."""
        return self.out_t[-1] if self.out_t else None

    def latest(self) -> np.ndarray | None:
        """The filter's state now (module docstring layout; all late measurements applied),
        None before the start."""
        return self.ekf.x.copy() if self._started else None

    def latest_output(self) -> tuple[float, np.ndarray, np.ndarray] | None:
        """The newest output ``(t, x, P)``: the state at an attitude sample and its covariance
        (module docstring layout), as :meth:`result` reports it (pose and velocity covariances
        by :func:`state_covariances`); None before the first."""
        if not self.out_t:
            return None
        return self.out_t[-1], self.out_x[-1].copy(), self.out_P[-1].copy()

    def _on_imu(self, ev: ImuSample) -> None:
        self.imu_used += self._started
        if self._arrived is not None:
            self._arrived.add(ev)
            self._arrived.trim(ev.t - IMU_FIT_HISTORY_S)
        if self.att_stage is not None:
            self._on_stage(self.att_stage.feed(ev))
        self._gyro_buf.append(ev.body_omega)
        if len(self._gyro_buf) == self.opt.gyro_decimation:
            omega = np.mean(self._gyro_buf, axis=0)
            self._gyro_buf = []
            self._entry(ev.t, "gyro", omega)

    def _on_stage(self, estimates) -> None:
        """The attitude EKF's estimates, sampled at ``imu_attitude_rate_hz``."""
        period = 1.0 / self.opt.imu_attitude_rate_hz
        for a in estimates:
            # A quarter period of tolerance for the IMU's time-stamp jitter.
            if a.t >= self._att_next_t - 0.25 * period:
                self._att_next_t = a.t + period
                self._on_attitude(a.t, a.world_q_body_wxyz)

    def _on_attitude(self, t: float, q_wxyz: np.ndarray) -> None:
        R = quat_wxyz_to_matrix(np.asarray(q_wxyz, dtype=float))
        rpy = matrix_to_rpy(R)
        self.odo.add_attitude(t, R, rpy)
        if not self._started:
            if self._pending_attitude is not None:
                self.counts.add("skipped", "attitude_before_start")
            else:
                self._t_first_attitude = t
            self._pending_attitude = (t, rpy)
            self._try_start()
            return
        self._entry(t, "attitude", rpy)

    def _try_start(self) -> None:
        """Start at the newest attitude sample once the first yaw reading and range height have
        arrived (those the flight's streams promise; after ``START_WAIT_S`` without them, start
        anyway)."""
        if self._started or self._pending_attitude is None:
            return
        t, rpy = self._pending_attitude
        waiting = (self.expect_yaw and self._yaw_first is None) or (
            self.expect_range and self._h_prev is None
        )
        if waiting and t - self._t_first_attitude < START_WAIT_S:
            return
        self._initialize(t, rpy)
        self._entry(t, "attitude", rpy)

    def _on_range(self, ev: RangeReading) -> None:
        h = self.odo.add_range(ev.t, float(ev.range))
        if h is None:
            return
        prev, self._h_prev = self._h_prev, (float(ev.t), h)
        if not self._started:
            self._try_start()
            return
        if prev is None:
            return
        dt = float(ev.t) - prev[0]
        if not 0.0 < dt <= self.opt.range_max_dt_s:
            self.counts.add("skipped", "vertical_speed")
            return
        sigma = math.sqrt(2.0) * self.opt.range_sigma / dt
        self._entry(ev.t, "vertical_speed", ((h - prev[1]) / dt, sigma))

    def _entry(self, t: float, kind: str, data: Any) -> None:
        if not self._started:
            self.counts.add("skipped", f"{kind}_before_start")
            return
        self._arrive(_Entry(float(t), self._seq, kind, data))
        self._seq += 1

    # -- initialisation --------------------------------------------------------------------------

    def _initialize(self, t: float, rpy: np.ndarray) -> None:
        o = self.opt
        x0 = np.zeros(N_STATE)
        x0[IR : IY + 1] = rpy
        if self._yaw_first is not None:
            x0[IY] = self._yaw_first
        if self._h_prev is not None:
            x0[IP + 2] = self._h_prev[1]
        sig = np.array(
            [o.initial_position_sigma] * 3
            + [o.initial_velocity_sigma] * 3
            + [o.initial_angle_sigma] * 3
            + [o.initial_yaw_rate_sigma]
        )
        self.ekf.initialize(float(t), x0, np.diag(sig**2))
        self._started = True

    # -- processing ------------------------------------------------------------------------------

    def _apply(self, e: _Entry, first_pass: bool) -> None:
        ekf = self.ekf
        self.counts.active = first_pass
        ekf.predict(e.t)
        if e.kind == "attitude":
            ekf.update_attitude(e.data[0], e.data[1], self.attitude_sigma)
            if first_pass and (self.t_first_output is None or e.t >= self.t_first_output):
                self.out_t.append(e.t)
                self.out_x.append(ekf.x.copy())
                self.out_P.append(ekf.P.copy())
        elif e.kind == "gyro":
            ekf.update_body_rates(e.data)
        elif e.kind == "yaw":
            ekf.update_yaw(e.data)
        elif e.kind == "vertical_speed":
            ekf.update_vertical_speed(*e.data)
        elif e.kind == "slam":
            if first_pass:
                e.payload = self._slam_measurement(e.data)
            if e.payload is not None:
                ekf.update_slam_pose(*e.payload)

    def _slam_measurement(self, ev: SlamPose) -> tuple[np.ndarray, np.ndarray | None] | None:
        """First pass of a SLAM pose: session bookkeeping, then the world measurement."""
        o, ekf = self.opt, self.ekf
        t = float(ev.t)
        sid = int(ev.session)
        if sid < 0:
            self.counts.add("skipped", "slam_tracking_lost")
            return None
        sess = self.sessions.get(sid)
        if sess is None:
            sess = self.sessions[sid] = _Session(sid, estimator=MLScaleEstimator(o.scale))
            log.info("ekf004: SLAM session %d starts at t=%.3f s", sid, t)
        p_sc = np.asarray(ev.slam_t_cam, dtype=float)
        if sess.anchor_slam is None:
            # The map's origin: the filter's camera position at the session's first pose.
            sess.anchor_slam = p_sc.copy()
            sess.anchor_world = ekf.camera_position()
        slam_R_cam = quat_wxyz_to_matrix(np.asarray(ev.slam_q_cam_wxyz, dtype=float))
        if len(sess.rotations) < o.align_poses:
            world_R_cam = ekf.world_R_body() @ self.body_R_cam
            sess.rotations.append(world_R_cam @ slam_R_cam.T)
            sess.world_R_slam = rotation_mean(np.asarray(sess.rotations))
        world_R_slam = sess.world_R_slam
        if self.scale_source == "ml":
            self._scale_pair(sess, t, p_sc)
        else:
            self._scale_imu_fit(sess, t, p_sc)
        if sess.scale is None:
            self.counts.add("skipped", "slam_before_scale")
            return None
        world_t_cam = sess.anchor_world + world_R_slam @ (p_sc - sess.anchor_slam) / sess.scale
        rpy = None
        if o.use_slam_angles and len(sess.rotations) >= o.align_poses:
            rpy = matrix_to_rpy(world_R_slam @ slam_R_cam @ self.body_R_cam.T)
        return world_t_cam, rpy

    def _scale_imu_fit(self, sess: _Session, t: float, p_sc: np.ndarray) -> None:
        """Scale from closed-form IMU-SLAM fits (:func:`fgnav.baselines.msf_ekf.initial_fit`) over
        consecutive windows of the session, on what has arrived up to ``t``: each accepted fit
        starts the next window at its end; the session's scale is their inverse-variance weighted
        mean."""
        o = self.opt
        if sess.fit_from is None:
            sess.fit_from = sess.last_fit_try = t
        if (
            t - sess.fit_from < SCALE_INIT_WINDOWS_S[0]
            or t - sess.last_fit_try < o.imu_fit_interval_s
        ):
            return
        sess.last_fit_try = t
        f = self._arrived.flight(self.calib, self.name)
        slam = f.slam.between(sess.fit_from, t)
        slam = slam.select(np.flatnonzero(slam.session == sess.sid))
        sub = dataclasses.replace(f, imu=f.imu.between(sess.fit_from, t), slam=slam)
        try:
            fit = initial_fit(sub)
        except FlightDataError:
            return
        sess.fit_from = fit.t_end
        if not sess.fits:
            # The drag-model dead reckoning since the session's start (maybe on the ground or
            # carried by hand) is not trusted: the scaled SLAM poses set position and velocity.
            self.ekf.release_position(self.ekf.camera_position() - sess.anchor_world)
            self.t_first_output = min(self.t_first_output, t)
        sess.fits.append((fit.scale, fit.rel_std * fit.scale))
        w = np.array([1.0 / sd**2 for _, sd in sess.fits])
        s_new = float(np.sum(w * [s for s, _ in sess.fits]) / w.sum())
        self._set_scale(sess, t, p_sc, s_new, float(1.0 / np.sqrt(w.sum())))

    def _set_scale(
        self, sess: _Session, t: float, p_sc: np.ndarray, s_new: float, s_sigma: float
    ) -> None:
        if sess.scale is not None and self.opt.scale_repivot:
            sess.anchor_world = (
                sess.anchor_world + sess.world_R_slam @ (p_sc - sess.anchor_slam) / sess.scale
            )
            sess.anchor_slam = p_sc.copy()
        sess.scale, sess.scale_sigma = s_new, s_sigma
        self.scale_t.append(t)
        self.scale_v.append(s_new)
        self.scale_sid.append(sess.sid)

    def _scale_pair(self, sess: _Session, t: float, p_sc: np.ndarray) -> None:
        o = self.opt
        if sess.pair_start is None:
            sess.pair_start = (t, p_sc)
            return
        t0, p0 = sess.pair_start
        if t - t0 < o.scale_pair_interval_s:
            return
        sess.pair_start = (t, p_sc)
        y = self.odo.camera_displacement(t0, t)
        if y is None:
            self.counts.add("skipped", "scale_pair")
            return
        x = sess.world_R_slam @ (p_sc - p0)
        comp = o.scale_components
        if comp == "vertical" or (comp == "xyz" and np.isfinite(y[2])):
            keep = [2] if comp == "vertical" else [0, 1, 2]
        else:
            keep = [0, 1]
        x, y = x[keep], y[keep]
        if not np.all(np.isfinite(y)):
            self.counts.add("skipped", "scale_pair_no_height")
            return
        if not sess.estimator.add_pair(x, y, t):
            self.counts.add("skipped", "scale_pair")
            return
        if sess.estimator.n_pairs < o.scale_min_pairs:
            return
        s_new, s_sigma = sess.estimator.scale, sess.estimator.sigma
        if not (math.isfinite(s_new) and s_new > 0):
            self.counts.add("skipped", "scale_estimate")
            return
        self._set_scale(sess, t, p_sc, s_new, s_sigma)

    def run(self, flight: Flight) -> Estimate:
        """:meth:`start` with the flight's calibration, its events replayed into :meth:`feed`,
        :meth:`close`; the estimate."""
        check_flight(flight, self.opt)
        self.start(flight.calib, flight.name)
        # Ties in arrival: a yaw reading before the attitude sample taken with it (the filter
        # starts at the first attitude sample by which a yaw reading has arrived).
        names = ("imu", "yaw", "attitude", "range", "slam")
        for ev in replay_flight(flight, names, named_order=True):
            self.feed(ev)
        self.close()
        return self.result()

    def _arrive(self, e: _Entry) -> None:
        hist = self.history
        if e.t >= self.ekf.t:
            e.snap = self.ekf.snapshot()
            self._apply(e, first_pass=True)
            hist.append(e)
        else:
            k = bisect.bisect_right([h.t for h in hist], e.t)
            if k == 0:
                self.counts.late_beyond_history += 1
                self.counts.add("skipped", f"{e.kind}_too_late")
                return
            if k < len(hist):
                self.ekf.restore(hist[k].snap)
            e.snap = self.ekf.snapshot()
            self._apply(e, first_pass=True)
            hist.insert(k, e)
            for h in hist[k + 1 :]:
                h.snap = self.ekf.snapshot()
                self._apply(h, first_pass=False)
            self.counts.active = True
            self.counts.replayed += len(hist) - k - 1
        cutoff = self.ekf.t - self.opt.history_s
        n_old = 0
        while n_old < len(hist) - 1 and hist[n_old].t < cutoff:
            n_old += 1
        if n_old:
            del hist[:n_old]

    # -- result ----------------------------------------------------------------------------------

    def result(self) -> Estimate:
        """The causal estimate of everything processed so far."""
        if not self.out_x:
            raise FlightDataError(
                f"{self.name}: ekf004 produced no state: its output starts at the first "
                f"SLAM scale fit ({self.scale_source}), which the flight never allowed (too short "
                "or too little motion)"
            )
        latencies = np.asarray(self.latencies)
        runtime_s = time.perf_counter() - self._wall0
        X = np.asarray(self.out_x)
        covs = [state_covariances(x, P) for x, P in zip(self.out_x, self.out_P, strict=True)]
        R = np.stack([rpy_to_matrix(*x[IR : IY + 1]) for x in X])
        traj = Trajectory(
            t=np.asarray(self.out_t),
            world_t_body=X[:, IP : IP + 3],
            world_q_body_wxyz=matrix_to_quat_wxyz(R),
            world_v_body=X[:, IV : IV + 3],
        )
        series: dict[str, TimeSeries] = {
            "yaw_rate": TimeSeries(traj.t, X[:, IYR]),
        }
        if self.scale_t:
            series["slam_scale"] = TimeSeries(np.asarray(self.scale_t), np.asarray(self.scale_v))
            series["slam_session"] = TimeSeries(
                np.asarray(self.scale_t), np.asarray(self.scale_sid, dtype=int)
            )
        scale = {sid: s.scale for sid, s in self.sessions.items() if s.scale is not None}
        scale_sigma = {
            sid: s.scale_sigma
            for sid, s in self.sessions.items()
            if s.scale is not None and s.scale_sigma is not None
        }
        for sid, s in self.sessions.items():
            if s.scale is None:
                log.warning("ekf004: SLAM session %d never got a scale (too little motion)", sid)
        info = {
            "options": self.opt,
            "counts": self.counts,
            "unused": unused_table(self._inputs.unused, self.counts.unused()),
            **self._inputs.info(("slam", "range", "yaw", "attitude")),
            "drag_k_fixed_per_s": list(self.opt.drag_k),
            "attitude_source": ATTITUDE_SOURCES[self.attitude_source],
            "scale_source": self.scale_source,
            "scale_pairs": {sid: s.estimator.counts for sid, s in self.sessions.items()},
        }
        log.info(
            "ekf004: %d outputs, used %s, gated %s, skipped %s, %d replays",
            len(traj),
            self.counts.used,
            self.counts.gated,
            self.counts.skipped,
            self.counts.replayed,
        )
        return Estimate(
            method="ekf004",
            trajectory=traj,
            pose_cov=np.array([c[0] for c in covs]),
            vel_cov=np.array([c[1] for c in covs]),
            slam_scale=scale,
            slam_scale_sigma=scale_sigma,
            series=series,
            update_latency=latencies,
            runtime_s=runtime_s,
            causal=True,
            info=info,
        ).check()


def run_ekf004(flight: Flight, options: Ekf004Options | None = None) -> Estimate:
    """Run seed 004's EKF over a flight (attitude required; IMU gyro, yaw, range, SLAM optional).

    Args:
        flight: the flight (its ground truth is not used).
        options: filter options.

    Returns:
        ``Estimate(method="ekf004", causal=True)`` with pose and velocity covariances, the SLAM
        scale per session and its history (``series["slam_scale"]``, ``series["slam_session"]``).
    """
    from fgnav.estimate import run_in_thrust_body

    opt = options or Ekf004Options()
    # The drag-model prediction and the tilt-to-acceleration model need a multirotor body (z
    # along the rotor thrust; EuRoC's IMU frame has x up): run in one and map the estimate back.
    return run_in_thrust_body(flight, lambda f: Ekf004Runner(options=opt).run(f))
