"""MAVLink <-> fgnav conversions: the only place on the live link where frames and units change.

fgnav's frames (../shared/DESIGN.md section 2) are world z up and body FLU, SI units, float
seconds. MAVLink's are z down: NED or ``LOCAL_FRD`` worlds and FRD bodies, with centimetres,
milliseconds and microseconds in some fields. Both directions are here, so every conversion has
its inverse beside it and a round-trip test (``tests/live/test_convert.py``).

Frames. ``F = diag(1, -1, -1)`` (``FLU_R_FRD``, a half turn about x, its own inverse) maps

* body FRD -> body FLU (angular rate, specific force, body velocity): ``v_flu = F v_frd``;
* a z-down world (NED, or ``MAV_FRAME_LOCAL_FRD``) -> fgnav's z-up world:
  ``world_FLU = F world_FRD``, i.e. x kept, y and z negated (x north, y west, z up for NED);
* orientations: ``world_R_body = F ned_R_frd F``; for quaternions ``[w, x, y, z]`` this is
  ``[w, x, -y, -z]`` (conjugation by the half turn about x rotates the vector part by ``F``).

fgnav's world yaw is arbitrary (gauge), so one fixed rotation serves every z-down world; it is
the same in and out, so the ``LOCAL_FRD`` frame fgnav sends is the NED frame of the attitude it
receives. (The PX4 ULog reader, :mod:`fgnav.datasets.frames`, maps NED to ENU instead: another
valid choice of the same gauge, 90 degrees of yaw apart.)

Clock. Every stamp is the autopilot's boot clock: ``time_usec`` [us] and ``time_boot_ms`` [ms]
become float seconds ``t``; fgnav's time 0 is the boot. SLAM ``ODOMETRY.time_usec`` is the
image capture time. An event's ``arrival`` is given by the caller (see
:class:`fgnav.live.inbound.Inbound`).

Messages in (-> :mod:`fgnav.datasets.events`):

* ``HIGHRES_IMU`` (body FRD, m/s^2, rad/s) -> :class:`ImuSample` (body FLU);
* ``ATTITUDE_QUATERNION`` (FRD body to NED, ``time_boot_ms``) -> :class:`AttitudeSample`;
* ``DISTANCE_SENSOR`` with orientation ``MAV_SENSOR_ROTATION_PITCH_270`` (25, downward), cm ->
  :class:`RangeReading` [m]; 0 cm (no reading) dropped; ``signal_quality`` 0 (unknown) -> -1,
  1 (invalid signal) dropped, 2..100 -> 0..1;
* ``ODOMETRY`` with ``estimator_type = MAV_ESTIMATOR_TYPE_VISION`` -> :class:`SlamPose`:
  ``x, y, z, q`` are the SLAM camera pose ``slam_T_cam`` in the SLAM's own frame and scale,
  taken as they are whatever ``frame_id`` says (the SLAM alignment absorbs the frame);
  ``quality`` -1 (the SLAM failed) dropped;
* ``OPTICAL_FLOW_RAD`` -> :class:`FlowSample`. MAVLink: ``integrated_x`` is positive for a
  right-hand sensor rotation about x and negative for motion along +y; ``integrated_y`` positive
  for rotation about y and for motion along +x. fgnav's ``FlowSeries`` convention is
  ``flow = [-v_x / d - w_y, -v_y / d + w_x] * dt`` (per radian), so
  ``flow = pixels_per_rad * [-integrated_y, integrated_x]``; ``quality`` 0..255 -> 0..1.

Messages out: ``ODOMETRY`` of a state (``frame_id = MAV_FRAME_LOCAL_FRD``, ``child_frame_id =
MAV_FRAME_BODY_FRD``, ``estimator_type = MAV_ESTIMATOR_TYPE_VIO``; see :func:`odometry_fields`).
The stand-in autopilot (:mod:`fgnav.live.replay`) uses the inverses (``*_fields`` of events,
:func:`pose_from_odometry`).

Covariances are MAVLink's 21-element row-major upper triangles (:func:`upper_triangle`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from fgnav.datasets.events import (
    AttitudeSample,
    FlowSample,
    ImuSample,
    RangeReading,
    SlamPose,
)
from fgnav.datasets.frames import FLU_R_FRD
from fgnav.datasets.geometry import matrix_to_quat_wxyz, matrix_to_rpy, quat_wxyz_to_matrix, skew

F = FLU_R_FRD
"""``diag(1, -1, -1)``: FRD -> FLU body vectors and z-down -> z-up world vectors (self-inverse)."""

# MAVLink enum values (common.xml); asserted against pymavlink in the tests.
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_LOCAL_FRD = 20
MAV_ESTIMATOR_TYPE_VISION = 2
MAV_ESTIMATOR_TYPE_VIO = 3
MAV_SENSOR_ROTATION_PITCH_270 = 25
MAV_DISTANCE_SENSOR_LASER = 0

HIGHRES_IMU_ACCEL_GYRO = 0b111111
"""``HIGHRES_IMU.fields_updated`` bits of x/y/z acceleration and x/y/z gyro
(``HIGHRES_IMU_UPDATED_XACC`` .. ``ZGYRO``): both must be set for a new IMU sample."""

US_PER_S = 1_000_000
MS_PER_S = 1_000
NS_PER_S = 1_000_000_000
CM_PER_M = 100.0
UINT16_MAX = 65535
FLOW_QUALITY_MAX = 255
"""``OPTICAL_FLOW_RAD.quality``: 0 no valid flow, 255 best."""

QUAT_NORM_TOL = 1e-3
"""A received quaternion whose norm is further than this from 1 is rejected (float32 fields)."""


class Rejected(ValueError):
    """A message that cannot become an event; ``reason`` is the counter's name."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


# ----------------------------------------------------------------------------------------------
# Clock
# ----------------------------------------------------------------------------------------------


def us_to_s(time_usec: int) -> float:
    """Boot-clock microseconds -> seconds."""
    return time_usec / US_PER_S


def ms_to_s(time_boot_ms: int) -> float:
    """Boot-clock milliseconds -> seconds."""
    return time_boot_ms / MS_PER_S


def s_to_us(t: float) -> int:
    """Seconds on the boot clock -> microseconds (rounded); a time before boot raises."""
    us = round(t * US_PER_S)
    if us < 0:
        raise ValueError(f"time {t!r} s is before the boot clock's start")
    return int(us)


def s_to_ms(t: float) -> int:
    """Seconds on the boot clock -> milliseconds (rounded); a time before boot raises."""
    ms = round(t * MS_PER_S)
    if ms < 0:
        raise ValueError(f"time {t!r} s is before the boot clock's start")
    return int(ms)


# ----------------------------------------------------------------------------------------------
# Frames
# ----------------------------------------------------------------------------------------------


def frd_quat_to_flu(q_wxyz: Sequence[float]) -> np.ndarray:
    """``a_FRD_q_b_FRD`` -> ``a_FLU_q_b_FLU`` (both frames through ``F``): ``[w, x, -y, -z]``.

    Its own inverse. Used for NED/LOCAL_FRD-world, FRD-body attitudes.
    """
    w, x, y, z = (float(v) for v in q_wxyz)
    return np.array([w, x, -y, -z])


def _unit_quat(q: Sequence[float], stream: str) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    n = float(np.linalg.norm(q))
    if not np.all(np.isfinite(q)) or abs(n - 1.0) > QUAT_NORM_TOL:
        raise Rejected(f"{stream}:invalid_quaternion", f"norm {n:.4g}")
    return q / n


def _finite(values: Sequence[float], stream: str) -> np.ndarray:
    a = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(a)):
        raise Rejected(f"{stream}:non_finite")
    return a


# Field names: ODOMETRY's position and velocity; its (and ATTITUDE_QUATERNION's) body rates.
_XYZ = ("x", "y", "z")
_VXYZ = ("vx", "vy", "vz")
_RATES = ("rollspeed", "pitchspeed", "yawspeed")
_NAN3 = (math.nan,) * 3


def _named(names: Sequence[str], values: Sequence[float]) -> dict[str, float]:
    """Message fields from a vector, one float a name: ``_named(("x", "y"), v)`` is
    ``{"x": float(v[0]), "y": float(v[1])}``."""
    return {name: float(v) for name, v in zip(names, values, strict=True)}


# ----------------------------------------------------------------------------------------------
# In: messages -> events
# ----------------------------------------------------------------------------------------------


def imu_from_highres(msg: Any, arrival: float | None = None) -> ImuSample:
    """``HIGHRES_IMU`` (body FRD) -> :class:`ImuSample` (body FLU). ``arrival`` defaults to t."""
    if (int(msg.fields_updated) & HIGHRES_IMU_ACCEL_GYRO) != HIGHRES_IMU_ACCEL_GYRO:
        raise Rejected("imu:not_updated", f"fields_updated {int(msg.fields_updated):#x}")
    t = us_to_s(msg.time_usec)
    frd_accel = _finite((msg.xacc, msg.yacc, msg.zacc), "imu")
    frd_omega = _finite((msg.xgyro, msg.ygyro, msg.zgyro), "imu")
    return ImuSample(t, t if arrival is None else arrival, F @ frd_omega, F @ frd_accel)


def highres_imu_fields(ev: ImuSample, boot_offset: float) -> dict[str, Any]:
    """Fields of ``HIGHRES_IMU`` for an IMU sample; ``t_boot = ev.t - boot_offset``."""
    a = F @ np.asarray(ev.body_accel, float)
    w = F @ np.asarray(ev.body_omega, float)
    return dict(
        time_usec=s_to_us(ev.t - boot_offset),
        **_named(("xacc", "yacc", "zacc"), a),
        **_named(("xgyro", "ygyro", "zgyro"), w),
        **_named(("xmag", "ymag", "zmag"), _NAN3),
        abs_pressure=math.nan,
        diff_pressure=math.nan,
        pressure_alt=math.nan,
        temperature=math.nan,
        fields_updated=HIGHRES_IMU_ACCEL_GYRO,
        id=0,
    )


def attitude_from_quaternion(msg: Any, arrival: float | None = None) -> AttitudeSample:
    """``ATTITUDE_QUATERNION`` (FRD body to NED) -> :class:`AttitudeSample` (FLU to z-up world).

    ``repr_offset_q`` is for display only and ignored.
    """
    t = ms_to_s(msg.time_boot_ms)
    q = _unit_quat((msg.q1, msg.q2, msg.q3, msg.q4), "attitude")
    return AttitudeSample(t, t if arrival is None else arrival, frd_quat_to_flu(q))


def attitude_quaternion_fields(
    ev: AttitudeSample, boot_offset: float, body_omega: np.ndarray | None = None
) -> dict[str, Any]:
    """Fields of ``ATTITUDE_QUATERNION``; rates from ``body_omega`` (FLU, rad/s) when given."""
    q = frd_quat_to_flu(ev.world_q_body_wxyz)
    w = np.full(3, math.nan) if body_omega is None else F @ np.asarray(body_omega, float)
    return dict(
        time_boot_ms=s_to_ms(ev.t - boot_offset),
        **_named(("q1", "q2", "q3", "q4"), q),
        **_named(_RATES, w),
        repr_offset_q=[1.0, 0.0, 0.0, 0.0],
    )


def range_from_distance_sensor(msg: Any, arrival: float | None = None) -> RangeReading:
    """``DISTANCE_SENSOR`` facing down (orientation 25) -> :class:`RangeReading` [m].

    Other orientations, 0 cm (many sensors' "no reading", whatever ``min_distance`` says; the
    file readers leave zero ranges out too), readings outside the message's own
    ``[min_distance, max_distance]`` (a sensor's out-of-range code), a reading at
    ``max_distance`` (a missing echo reported as the maximum: ``range:at_max``, as the
    estimators refuse one at the calibration's ``range_max``, ``range_at_max``, which they
    cannot where the calibration has no maximum) and ``signal_quality`` 1 (invalid signal) are
    rejected.
    """
    if int(msg.orientation) != MAV_SENSOR_ROTATION_PITCH_270:
        raise Rejected("range:orientation", f"orientation {int(msg.orientation)}, not 25 (down)")
    d = int(msg.current_distance)
    if d == 0:
        raise Rejected("range:zero", "0 cm: no reading")
    if not int(msg.min_distance) <= d <= int(msg.max_distance):
        raise Rejected(
            "range:out_of_sensor_limits",
            f"{d} cm outside [{int(msg.min_distance)}, {int(msg.max_distance)}] cm",
        )
    if d == int(msg.max_distance):
        raise Rejected("range:at_max", f"{d} cm at max_distance: no echo")
    t = ms_to_s(msg.time_boot_ms)
    sq = int(getattr(msg, "signal_quality", 0))
    if sq == 1:  # MAVLink: 1 = invalid signal (0 = unknown, 100 = best)
        raise Rejected("range:invalid_signal", "signal_quality 1")
    quality = -1.0 if sq == 0 else (min(sq, 100) - 2) / 98.0
    return RangeReading(t, t if arrival is None else arrival, d / CM_PER_M, quality)


def _cm(x: float) -> int:
    if not math.isfinite(x):
        return UINT16_MAX
    return int(min(max(round(x * CM_PER_M), 0), UINT16_MAX))


def distance_sensor_fields(
    ev: RangeReading, boot_offset: float, range_min: float = 0.0, range_max: float = math.inf
) -> dict[str, Any]:
    """Fields of ``DISTANCE_SENSOR`` (downward) for a range reading, rounded to 1 cm."""
    sq = 0 if ev.quality < 0 else int(round(2 + 98 * min(max(ev.quality, 0.0), 1.0)))
    return dict(
        time_boot_ms=s_to_ms(ev.t - boot_offset),
        min_distance=_cm(range_min),
        max_distance=_cm(range_max),
        current_distance=_cm(ev.range),
        type=MAV_DISTANCE_SENSOR_LASER,
        id=0,
        orientation=MAV_SENSOR_ROTATION_PITCH_270,
        covariance=255,  # UINT8_MAX: unknown
        horizontal_fov=0.0,
        vertical_fov=0.0,
        quaternion=[0.0, 0.0, 0.0, 0.0],
        signal_quality=sq,
    )


def slam_from_odometry(msg: Any, session: int, arrival: float | None = None) -> SlamPose:
    """``ODOMETRY`` of a vision (SLAM) source -> :class:`SlamPose` in the SLAM's own frame.

    ``session`` is the SLAM map id the caller derives from ``reset_counter``. ``quality`` -1
    (MAVLink: "odometry has failed"; 0 unknown, 1-100 worst to best) is rejected.
    """
    if int(msg.estimator_type) != MAV_ESTIMATOR_TYPE_VISION:
        raise Rejected("slam:estimator_type", f"estimator_type {int(msg.estimator_type)}")
    if int(getattr(msg, "quality", 0)) < 0:
        raise Rejected("slam:failed", f"quality {int(msg.quality)}: odometry has failed")
    t = us_to_s(msg.time_usec)
    p = _finite((msg.x, msg.y, msg.z), "slam")
    q = _unit_quat(msg.q, "slam")
    return SlamPose(t, t if arrival is None else arrival, p, q, int(session))


def vision_odometry_fields(ev: SlamPose, boot_offset: float, reset_counter: int) -> dict[str, Any]:
    """Fields of ``ODOMETRY`` sent by a SLAM bridge: the camera pose as it is, unknown twist."""
    nan21 = [math.nan] + [0.0] * 20
    return dict(
        time_usec=s_to_us(ev.t - boot_offset),
        frame_id=MAV_FRAME_LOCAL_FRD,
        child_frame_id=MAV_FRAME_BODY_FRD,
        **_named(_XYZ, ev.slam_t_cam),
        q=[float(v) for v in ev.slam_q_cam_wxyz],
        **_named(_VXYZ, _NAN3),
        **_named(_RATES, _NAN3),
        pose_covariance=nan21,
        velocity_covariance=list(nan21),
        reset_counter=int(reset_counter) % 256,
        estimator_type=MAV_ESTIMATOR_TYPE_VISION,
        quality=0,
    )


def flow_from_rad(
    msg: Any, pixels_per_rad: float = 1.0, arrival: float | None = None
) -> FlowSample:
    """``OPTICAL_FLOW_RAD`` -> :class:`FlowSample` (fgnav's flow convention, see the module).

    ``t`` is ``time_usec`` (the end of the integration interval), ``dt`` the integration time.
    """
    if int(msg.quality) == 0:
        raise Rejected("flow:no_valid_flow")
    dt = int(msg.integration_time_us) / US_PER_S
    if dt <= 0:
        raise Rejected("flow:no_interval")
    ix, iy = _finite((msg.integrated_x, msg.integrated_y), "flow")
    t = us_to_s(msg.time_usec)
    flow = pixels_per_rad * np.array([-iy, ix])
    return FlowSample(
        t, t if arrival is None else arrival, dt, flow, int(msg.quality) / FLOW_QUALITY_MAX
    )


def optical_flow_rad_fields(
    ev: FlowSample, boot_offset: float, pixels_per_rad: float = 1.0
) -> dict[str, Any]:
    """Fields of ``OPTICAL_FLOW_RAD`` for a flow sample (gyro integrals unknown: NaN)."""
    fx, fy = (np.asarray(ev.flow, float) / pixels_per_rad).tolist()
    q = FLOW_QUALITY_MAX if ev.quality < 0 else int(round(FLOW_QUALITY_MAX * ev.quality))
    return dict(
        time_usec=s_to_us(ev.t - boot_offset),
        sensor_id=0,
        integration_time_us=int(round(ev.dt * US_PER_S)),
        integrated_x=float(fy),
        integrated_y=float(-fx),
        integrated_xgyro=math.nan,
        integrated_ygyro=math.nan,
        integrated_zgyro=math.nan,
        temperature=0,
        quality=max(1, min(q, FLOW_QUALITY_MAX)),
        time_delta_distance_us=0,
        distance=-1.0,
    )


# ----------------------------------------------------------------------------------------------
# Covariances
# ----------------------------------------------------------------------------------------------

_IU = np.triu_indices(6)


def upper_triangle(M: np.ndarray) -> list[float]:
    """A symmetric 6x6 -> MAVLink's 21 floats: the upper triangle row by row."""
    M = np.asarray(M, dtype=float)
    return [float(v) for v in M[_IU]]


def from_upper_triangle(v: Sequence[float]) -> np.ndarray | None:
    """MAVLink's 21 floats -> the symmetric 6x6 (None when the first is NaN: unknown)."""
    v = np.asarray(v, dtype=float)
    if v.shape != (21,):
        raise ValueError(f"expected 21 covariance entries, got {v.shape}")
    if math.isnan(v[0]):
        return None
    M = np.zeros((6, 6))
    M[_IU] = v
    return M + np.triu(M, 1).T


def rpy_from_body_rotation(rpy: np.ndarray) -> np.ndarray:
    """``d(roll, pitch, yaw) / d(theta)`` for a right (body) perturbation ``R Exp(theta)`` of
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``: the inverse of ``omega_body = E(roll, pitch) rpy_dot``,
    ``E = [[1, 0, -sp], [0, cr, sr cp], [0, -sr, cr cp]]`` (singular at pitch +-90 deg)."""
    r, p = float(rpy[0]), float(rpy[1])
    cr, sr, cp, sp = math.cos(r), math.sin(r), math.cos(p), math.sin(p)
    E = np.array([[1.0, 0.0, -sp], [0.0, cr, sr * cp], [0.0, -sr, cr * cp]])
    return np.linalg.inv(E)


def odometry_pose_cov(world_R_body: np.ndarray, pose_cov: np.ndarray) -> np.ndarray:
    """fgnav's pose covariance -> ``ODOMETRY.pose_covariance`` as a 6x6 (x, y, z, roll, pitch,
    yaw) in ``LOCAL_FRD`` world / FRD body.

    ``pose_cov`` is GTSAM's Pose3 tangent ``[theta, rho]`` (body frame, right perturbation
    ``world_T_body Exp(xi)``: ``R -> R Exp(theta)``, ``p -> p + R rho``). Out:
    ``p_o = F p`` so ``dp_o = F R rho``; ``R_o = F R F`` so ``R_o Exp(F theta)`` and
    ``d rpy_o = E^-1(rpy_o) F theta``. The result is ``J P J^T``, cross terms included.
    """
    R = np.asarray(world_R_body, float)
    R_o = F @ R @ F
    J = np.zeros((6, 6))
    J[0:3, 3:6] = F @ R
    J[3:6, 0:3] = rpy_from_body_rotation(matrix_to_rpy(R_o)) @ F
    C = J @ np.asarray(pose_cov, float) @ J.T
    return 0.5 * (C + C.T)


def odometry_velocity_cov(
    world_R_body: np.ndarray,
    world_v_body: np.ndarray,
    vel_cov: np.ndarray,
    rot_cov: np.ndarray | None,
    rate_var: np.ndarray | None,
) -> np.ndarray:
    """fgnav's velocity covariance -> ``ODOMETRY.velocity_covariance`` as a 6x6 (vx, vy, vz,
    rollspeed, pitchspeed, yawspeed), velocity in body FRD.

    ``v_o = F R^T v``: ``dv_o = F R^T dv + F [v_b]x theta`` (``v_b = R^T v``, rotation
    perturbation ``theta`` of covariance ``rot_cov``, taken as uncorrelated with the velocity:
    fgnav's state output has no velocity-pose cross-covariance). The rate block is
    ``diag(rate_var)`` (zero when None); velocity and rates are uncorrelated.
    """
    R = np.asarray(world_R_body, float)
    v_b = R.T @ np.asarray(world_v_body, float)
    A = F @ R.T
    C = np.zeros((6, 6))
    C[0:3, 0:3] = A @ np.asarray(vel_cov, float) @ A.T
    if rot_cov is not None:
        B = F @ skew(v_b)
        C[0:3, 0:3] += B @ np.asarray(rot_cov, float) @ B.T
    if rate_var is not None:
        C[3:6, 3:6] = np.diag(np.asarray(rate_var, float))
    return 0.5 * (C + C.T)


# ----------------------------------------------------------------------------------------------
# Out: a state -> ODOMETRY; and back (the stand-in autopilot's record)
# ----------------------------------------------------------------------------------------------


def mavlink_quality(quality: int) -> int:
    """fgnav's 0-100 health -> ``ODOMETRY.quality`` (1 worst .. 100 best; 0 means "unknown" in
    MAVLink, so fgnav's 0 is sent as 1)."""
    return int(min(max(int(quality), 1), 100))


def odometry_fields(
    state: Any,
    body_omega: np.ndarray | None = None,
    rate_var: np.ndarray | None = None,
) -> dict[str, Any]:
    """Fields of the ``ODOMETRY`` fgnav sends for one state.

    Args:
        state: an ``OnlineState`` (``t`` on the boot clock, ``world_T_body``, ``world_v_body``,
            ``gyro_bias``, ``pose_cov``, ``vel_cov``, ``reset_counter``, ``quality``).
        body_omega: IMU angular rate at the state (FLU, rad/s; the gyro bias is removed here),
            or None (rates sent as NaN).
        rate_var: variance of each rate [rad^2/s^2], or None.

    Returns:
        ``time_usec`` = the state's time; position and quaternion as ``world_FRD = F world_FLU``
        and body FRD (``frame_id = LOCAL_FRD``, ``child_frame_id = BODY_FRD``); velocity in body
        FRD; covariances (:func:`odometry_pose_cov`, :func:`odometry_velocity_cov`, NaN-first
        when unknown); ``estimator_type = VIO``; ``reset_counter`` mod 256; ``quality``.
    """
    T = np.asarray(state.world_T_body, float)
    R, p = T[:3, :3], T[:3, 3]
    v = np.asarray(state.world_v_body, float)
    q_o = frd_quat_to_flu(matrix_to_quat_wxyz(R))
    p_o = F @ p
    v_o = F @ R.T @ v
    if body_omega is None:
        w_o = np.full(3, math.nan)
        rate_var = None
    else:
        w_o = F @ (np.asarray(body_omega, float) - np.asarray(state.gyro_bias, float))
    unknown = [math.nan] + [0.0] * 20
    pose_cov = getattr(state, "pose_cov", None)
    vel_cov = getattr(state, "vel_cov", None)
    pc = unknown if pose_cov is None else upper_triangle(odometry_pose_cov(R, pose_cov))
    vc = unknown
    if vel_cov is not None:
        rot = None if pose_cov is None else np.asarray(pose_cov, float)[0:3, 0:3]
        vc = upper_triangle(odometry_velocity_cov(R, v, vel_cov, rot, rate_var))
    return dict(
        time_usec=s_to_us(state.t),
        frame_id=MAV_FRAME_LOCAL_FRD,
        child_frame_id=MAV_FRAME_BODY_FRD,
        **_named(_XYZ, p_o),
        q=[float(c) for c in q_o],
        **_named(_VXYZ, v_o),
        **_named(_RATES, w_o),
        pose_covariance=pc,
        velocity_covariance=vc,
        reset_counter=int(state.reset_counter) % 256,
        estimator_type=MAV_ESTIMATOR_TYPE_VIO,
        quality=mavlink_quality(state.quality),
    )


def pose_from_odometry(msg: Any) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """fgnav's ``ODOMETRY`` (LOCAL_FRD / BODY_FRD) back into fgnav's frames.

    Returns:
        ``(t, world_t_body, world_q_body_wxyz, world_v_body)``: boot-clock seconds, z-up world
        position [m], FLU-to-world quaternion, world velocity [m/s] (NaN when not sent).
    """
    if int(msg.frame_id) != MAV_FRAME_LOCAL_FRD or int(msg.child_frame_id) != MAV_FRAME_BODY_FRD:
        raise Rejected(
            "odometry:frame", f"frame_id {int(msg.frame_id)}, child {int(msg.child_frame_id)}"
        )
    q = frd_quat_to_flu(_unit_quat(msg.q, "odometry"))
    p = F @ _finite((msg.x, msg.y, msg.z), "odometry")
    v_o = np.asarray((msg.vx, msg.vy, msg.vz), float)
    v = quat_wxyz_to_matrix(q) @ (F @ v_o)
    return us_to_s(msg.time_usec), p, q, v
