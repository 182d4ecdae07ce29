"""PX4 ULog reader: a ``.ulg`` flight log -> :class:`~fgnav.datasets.types.Flight` in fgnav frames.

What is read (topic -> field of the flight), all converted from PX4's NED world / FRD body into
fgnav's z-up world / FLU body by :mod:`fgnav.datasets.frames`, time from PX4's microseconds since
boot into float seconds on the same clock (``t = timestamp_us * 1e-6``):

* ``sensor_combined`` -> ``flight.imu``. PX4 has already rotated the samples into the vehicle
  body frame (``SENS_BOARD_ROT`` and the thermal/offset calibration are applied on board), so only
  FRD -> FLU remains. The IMU time is the gyro time ``timestamp``; the accelerometer sample time is
  ``timestamp + accelerometer_timestamp_relative``. When the relative offsets are not all zero the
  accelerometer is linearly interpolated onto the gyro times (samples whose offset is PX4's
  "invalid" marker are left out of the interpolation and counted). Non-finite samples and
  implausible ones (beyond :data:`.types.IMU_MAX_RATE` / :data:`.types.IMU_MAX_ACCEL`: corrupted)
  are left out and counted.
* ``vehicle_attitude`` -> ``flight.attitude`` (onboard EKF2 attitude, ``timestamp_sample`` when
  logged).
* ``vehicle_local_position`` -> ``flight.references["px4_ekf2"]``: onboard EKF2 position and
  velocity, with the attitude interpolated (slerp) at its times. Rows outside the attitude's time
  span are left out and counted. Validity flags are summarised in ``meta["px4_ekf2"]``.
* ``distance_sensor`` (downward-facing instances only) -> ``flight.range`` plus
  ``calib.body_T_range`` (from ``EKF2_RNG_POS_X/Y/Z`` and ``EKF2_RNG_PITCH``) and
  ``calib.range_min/max`` (from the message). ``signal_quality`` 0..100 -> quality 0..1, -1 stays
  "unknown". Readings outside ``[min_distance, max_distance]`` are kept (the range factor gates
  them); non-finite and negative ones are left out and counted.
* ``vehicle_visual_odometry``, ``vehicle_mocap_odometry``, ``vehicle_odometry`` ->
  ``flight.references["px4_<topic>"]`` (both the current ``position[3]``/``q[4]``/``velocity[3]``
  layout and the older ``x y z``/``vx vy vz`` one).
* ``vehicle_optical_flow`` (PX4 >= 1.13, body axes), else ``optical_flow`` (PX4 <= 1.12, body
  axes), else ``sensor_optical_flow`` (sensor axes, turned into the body by ``SENS_FLOW_ROT``, a
  yaw of k x 45 deg) -> ``flight.flow`` in radians (``calib.flow_pixels_per_rad = 1``), see
  :func:`flow_from_px4`. PX4's integrated flow is a rotation about the body FRD axes, positive
  for a right-hand rotation of the sensor: ``pixel_flow = dt [w_x - v_y / d, w_y + v_x / d]``
  (EKF2 ``optical_flow.cpp``/``optical_flow_control.cpp``: ``flow_rate = -pixel_flow / dt``,
  compensated by the negated gyro, predicted as ``(v_y, -v_x) / d``), so fgnav's flow
  (``FlowSeries``, sensor x forward, y right, z down) is ``[-pixel_flow[1], pixel_flow[0]]``. The
  time is ``timestamp_sample`` (the end of the integration interval), the interval
  ``integration_timespan_us``, quality 0..255 -> 0..1. Readings with quality 0, no interval, an
  interval of 1 s or more (EKF2 drops them too), non-finite values or a time not after the
  previous one are left out and counted (``meta["flow"]``, one warning line). ``body_T_flow``:
  the sensor axes as the body's FRD, the lever arm ``position_offset`` (``vehicle_optical_flow``)
  or ``EKF2_OF_POS_X/Y/Z`` minus ``EKF2_IMU_POS_X/Y/Z``. The flow module's own gyro
  (``delta_angle``) is not used: the smoothers compensate rotation with the IMU's. A log without
  a downward ``distance_sensor`` takes the flow message's ``distance_m`` (finite, > 0) as its
  range stream at the flow sensor, as EKF2 does. Every flow topic is also summarised in
  ``meta["px4_optical_flow"]``.
* Parameters users need (``EKF2_MCOEF``, ``EKF2_BCOEF_X/Y``, ``EKF2_DRAG_*``, ``EKF2_RNG_*``,
  ``EKF2_IMU_POS_*``, ``EKF2_OF_*``, ``SENS_*``) -> ``meta["px4_params"]``.

Multi-instance topics: the instance is chosen by ``instance_policy`` (``"most_samples"``: the
instance with the most samples, ties to the lowest id; ``"first"``: the lowest id). What was chosen
and what else exists is in ``meta["px4_instances"]``; every topic and instance of the log, with
sample counts, is in ``meta["px4_topics"]``. The accelerometer and gyro that ``sensor_combined``
uses (``sensor_selection``) are named in ``meta["px4_imu_selection"]``.

A damaged log: pyulog's corruption reports become one note and one warning line; a log cut inside
a message (pyulog stops there without a word: :func:`ulog_cut_bytes`) gets a note and a warning
line too, and reads up to its last whole message.
"""

from __future__ import annotations

import contextlib
import io
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ._tables import increasing_mask
from .errors import FlightFormatError
from .frames import frd_to_flu, ned_q_frd_to_world_q_body, ned_to_enu
from .geometry import make_pose, matrix_to_quat_wxyz, quat_wxyz_to_matrix
from .types import (
    AttitudeSeries,
    Calibration,
    Flight,
    FlowSeries,
    ImuSeries,
    RangeSeries,
    Trajectory,
    imu_plausible,
)

log = logging.getLogger(__name__)

InstancePolicy = Literal["most_samples", "first"]

#: PX4 microseconds -> seconds.
US_TO_S = 1e-6
#: ``sensor_combined.accelerometer_timestamp_relative`` value meaning "no accelerometer sample"
#: (``sensor_combined_s::RELATIVE_TIMESTAMP_INVALID`` = INT32_MAX in PX4's msg/SensorCombined.msg).
RELATIVE_TIMESTAMP_INVALID = 2147483647
#: ``distance_sensor.orientation`` of a downward-facing sensor (MAV_SENSOR_ROTATION_PITCH_270).
ROTATION_DOWNWARD_FACING = 25
#: ``distance_sensor.signal_quality`` is 0..100 (percent), -1 unknown.
SIGNAL_QUALITY_PERCENT = 100.0
#: ``vehicle_odometry`` frame enums (PX4 msg/VehicleOdometry.msg since v1.14).
POSE_FRAME_NED, POSE_FRAME_FRD = 1, 2
VELOCITY_FRAME_NED, VELOCITY_FRAME_FRD, VELOCITY_FRAME_BODY_FRD = 1, 2, 3

#: Parameter names (exact, or prefixes ending in ``_``) copied into ``meta["px4_params"]``.
PARAMS_OF_INTEREST = (
    "EKF2_MCOEF",
    "EKF2_BCOEF_",
    "EKF2_DRAG_",
    "EKF2_RNG_",
    "EKF2_IMU_POS_",
    "EKF2_OF_",
    "SENS_",
)
ODOMETRY_TOPICS = ("vehicle_visual_odometry", "vehicle_mocap_odometry", "vehicle_odometry")
#: Flow topics in the order one is chosen (the first present).
FLOW_TOPICS = ("vehicle_optical_flow", "optical_flow", "sensor_optical_flow")
#: ``*optical_flow.quality``: 0 no valid flow, 255 best.
FLOW_QUALITY_MAX = 255.0
#: EKF2 uses a flow reading only when ``integration_timespan_us < 1e6``.
FLOW_MAX_INTERVAL_S = 1.0
#: ``SENS_FLOW_ROT``: PX4 rotations 0..7 are yaws of ``k * 45`` deg (sensor -> body, FRD).
FLOW_ROT_YAW_STEP_DEG = 45.0

Topic = Mapping[str, np.ndarray]


# ----------------------------------------------------------------------------------------------
# Converters: one topic's columns (a dict of arrays, as pyulog gives them) -> fgnav series
# ----------------------------------------------------------------------------------------------


def _vec(d: Topic, names: list[str]) -> np.ndarray:
    return np.column_stack([np.asarray(d[n], dtype=float) for n in names])


def _sample_time(d: Topic) -> np.ndarray:
    """``timestamp_sample`` when logged and non-zero, else ``timestamp`` [s]."""
    ts = d.get("timestamp_sample")
    if ts is not None and np.all(np.asarray(ts) > 0):
        return np.asarray(ts, dtype=float) * US_TO_S
    return np.asarray(d["timestamp"], dtype=float) * US_TO_S


def imu_from_sensor_combined(d: Topic) -> tuple[ImuSeries, dict[str, Any]]:
    """``sensor_combined`` columns -> IMU in FLU at the gyro times.

    Args:
        d: columns ``timestamp`` [us], ``gyro_rad[0..2]`` [rad/s, FRD],
            ``accelerometer_m_s2[0..2]`` [m/s^2, FRD], ``accelerometer_timestamp_relative`` [us].

    Returns:
        The series and notes (how accelerometer time was handled, samples left out).
    """
    t = np.asarray(d["timestamp"], dtype=float) * US_TO_S
    gyro = frd_to_flu(_vec(d, [f"gyro_rad[{i}]" for i in range(3)]))
    accel = frd_to_flu(_vec(d, [f"accelerometer_m_s2[{i}]" for i in range(3)]))
    notes: dict[str, Any] = {"imu_time": "sensor_combined.timestamp (gyro sample time)"}
    rel = np.asarray(d.get("accelerometer_timestamp_relative", np.zeros(t.shape)), dtype=np.int64)
    valid_rel = rel != RELATIVE_TIMESTAMP_INVALID
    if np.any(rel[valid_rel] != 0) or not np.all(valid_rel):
        t_acc = t[valid_rel] + rel[valid_rel] * US_TO_S
        order = np.argsort(t_acc, kind="stable")
        t_acc, acc = t_acc[order], accel[valid_rel][order]
        accel = np.column_stack([np.interp(t, t_acc, acc[:, i]) for i in range(3)])
        notes["accel_time"] = (
            "interpolated onto gyro times from timestamp + accelerometer_timestamp_relative "
            f"(|relative| max {np.abs(rel[valid_rel]).max() * US_TO_S * 1e3:.2f} ms)"
        )
        notes["accel_invalid_relative_timestamp"] = int(np.count_nonzero(~valid_rel))
    else:
        notes["accel_time"] = "same as gyro (accelerometer_timestamp_relative all zero)"
    finite = np.all(np.isfinite(gyro), axis=1) & np.all(np.isfinite(accel), axis=1)
    plausible = imu_plausible(gyro, accel)  # beyond any IMU's full scale: a corrupted sample
    ok = finite & plausible
    keep = ok & increasing_mask(np.where(ok, t, -np.inf))
    notes["imu_samples_skipped_nonfinite"] = int(np.count_nonzero(~finite))
    notes["imu_samples_skipped_implausible"] = int(np.count_nonzero(finite & ~plausible))
    notes["imu_samples_skipped_time_not_increasing"] = int(np.count_nonzero(ok & ~keep))
    return ImuSeries(t=t[keep], body_omega=gyro[keep], body_accel=accel[keep]), notes


def attitude_from_vehicle_attitude(d: Topic) -> tuple[AttitudeSeries, dict[str, Any]]:
    """``vehicle_attitude`` columns (``q[0..3]`` = ``[w, x, y, z]`` of FRD -> NED) -> attitude of
    FLU in the z-up world."""
    t = _sample_time(d)
    q = _vec(d, [f"q[{i}]" for i in range(4)])
    finite = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
    keep = finite & increasing_mask(np.where(finite, t, -np.inf))
    notes = {
        "attitude_samples_skipped_invalid": int(np.count_nonzero(~finite)),
        "attitude_samples_skipped_time_not_increasing": int(np.count_nonzero(finite & ~keep)),
    }
    if "quat_reset_counter" in d:
        # EKF2 heading/attitude resets (jumps kept as logged).
        notes["quat_resets"] = int(np.count_nonzero(np.diff(np.asarray(d["quat_reset_counter"]))))
    return AttitudeSeries(t=t[keep], world_q_body_wxyz=ned_q_frd_to_world_q_body(q[keep])), notes


def interpolate_attitude(att: AttitudeSeries, t: np.ndarray) -> np.ndarray:
    """Slerp ``world_q_body_wxyz`` at times ``t`` (within ``att``'s span) -> (N, 4)."""
    q_xyzw = np.column_stack([att.world_q_body_wxyz[:, 1:], att.world_q_body_wxyz[:, :1]])
    if len(att) == 1:
        return np.repeat(att.world_q_body_wxyz, len(t), axis=0)
    R = Slerp(att.t, Rotation.from_quat(q_xyzw))(t)
    return matrix_to_quat_wxyz(R.as_matrix())


def trajectory_from_local_position(
    d: Topic, att: AttitudeSeries
) -> tuple[Trajectory | None, dict[str, Any]]:
    """``vehicle_local_position`` (NED ``x y z`` [m], ``vx vy vz`` [m/s]) + attitude -> EKF2
    reference trajectory in the z-up world. Rows outside the attitude time span or non-finite are
    left out and counted."""
    t = _sample_time(d)
    p = ned_to_enu(_vec(d, ["x", "y", "z"]))
    v = ned_to_enu(_vec(d, ["vx", "vy", "vz"]))
    finite = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(v), axis=1)
    inside = (t >= att.t[0]) & (t <= att.t[-1])
    keep = finite & inside
    keep &= increasing_mask(np.where(keep, t, -np.inf))
    notes: dict[str, Any] = {
        "samples": int(t.size),
        "kept": int(np.count_nonzero(keep)),
        "skipped_nonfinite": int(np.count_nonzero(~finite)),
        "skipped_outside_attitude_span": int(np.count_nonzero(finite & ~inside)),
        "attitude": "vehicle_attitude, slerp-interpolated at the position times",
    }
    for flag in ("xy_valid", "z_valid", "v_xy_valid", "v_z_valid"):
        if flag in d:
            notes[f"{flag}_fraction"] = float(np.mean(np.asarray(d[flag]) != 0))
    for counter in ("xy_reset_counter", "z_reset_counter", "vxy_reset_counter", "vz_reset_counter"):
        if counter in d:
            # EKF2 state resets: the logged estimate jumps there (kept as logged).
            notes[counter.replace("_counter", "s")] = int(
                np.count_nonzero(np.diff(np.asarray(d[counter])))
            )
    if not np.any(keep):
        return None, notes
    q = interpolate_attitude(att, t[keep])
    return Trajectory(
        t=t[keep], world_t_body=p[keep], world_q_body_wxyz=q, world_v_body=v[keep]
    ), notes


def body_T_range_from_params(params: Mapping[str, float]) -> np.ndarray:
    """``EKF2_RNG_POS_X/Y/Z`` (FRD [m]) and ``EKF2_RNG_PITCH`` [rad] -> 4x4 ``body_T_range`` (FLU).

    The beam (sensor +z) of a downward sensor points along body -z; PX4 tilts it forward by the
    pitch offset: beam = ``(sin p, 0, cos p)`` in FRD (``sensor_range_finder.cpp``,
    ``cos_tilt = R(2,0) sin p + R(2,2) cos p``), i.e. ``(sin p, 0, -cos p)`` in FLU.
    """
    pitch = float(params.get("EKF2_RNG_PITCH", 0.0))
    pos_frd = np.array([float(params.get(f"EKF2_RNG_POS_{a}", 0.0)) for a in "XYZ"])
    c, s = np.cos(pitch), np.sin(pitch)
    Ry_minus_pitch = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    body_R_range = Ry_minus_pitch @ np.diag([1.0, -1.0, -1.0])
    return make_pose(body_R_range, frd_to_flu(pos_frd))


def range_from_distance_sensor(d: Topic) -> tuple[RangeSeries | None, float, float, dict[str, Any]]:
    """``distance_sensor`` columns of one downward-facing instance -> range series.

    Returns:
        ``(series or None, range_min [m], range_max [m], notes)``.
    """
    t = _sample_time(d)
    r = np.asarray(d["current_distance"], dtype=float)
    q_raw = np.asarray(d.get("signal_quality", np.full(t.shape, -1)), dtype=float)
    quality = np.where(q_raw < 0, -1.0, q_raw / SIGNAL_QUALITY_PERCENT)
    finite = np.isfinite(r)
    negative = finite & (r < 0.0)  # no distance is negative: a corrupted sample
    ok = finite & ~negative
    keep = ok & increasing_mask(np.where(ok, t, -np.inf))
    rmin = np.asarray(d.get("min_distance", [0.0]), dtype=float)
    rmax = np.asarray(d.get("max_distance", [np.inf]), dtype=float)
    range_min = float(np.nanmax(rmin)) if rmin.size else 0.0
    range_max = float(np.nanmin(rmax)) if rmax.size else float("inf")
    notes = {
        "samples": int(t.size),
        "skipped_nonfinite": int(np.count_nonzero(~finite)),
        "skipped_negative": int(np.count_nonzero(negative)),
        "skipped_time_not_increasing": int(np.count_nonzero(ok & ~keep)),
        "outside_min_max_kept": int(np.count_nonzero(keep & ((r < range_min) | (r > range_max)))),
    }
    if not np.any(keep):
        return None, range_min, range_max, notes
    return RangeSeries(t=t[keep], range=r[keep], quality=quality[keep]), range_min, range_max, notes


def trajectory_from_odometry(d: Topic) -> tuple[Trajectory | None, dict[str, Any]]:
    """``vehicle_odometry``-like columns -> trajectory in a z-up world (NED or FRD world ->
    z-up via ``ENU_R_NED``; velocity in body FRD is rotated into the world)."""
    t = _sample_time(d)
    if "position[0]" in d:
        p_ned = _vec(d, [f"position[{i}]" for i in range(3)])
        v_raw = _vec(d, [f"velocity[{i}]" for i in range(3)]) if "velocity[0]" in d else None
        vel_frame = int(np.asarray(d.get("velocity_frame", [VELOCITY_FRAME_NED]))[0])
        pose_frame = int(np.asarray(d.get("pose_frame", [POSE_FRAME_NED]))[0])
    elif "x" in d:
        p_ned = _vec(d, ["x", "y", "z"])
        v_raw = _vec(d, ["vx", "vy", "vz"]) if "vx" in d else None
        vel_frame, pose_frame = VELOCITY_FRAME_NED, POSE_FRAME_NED
    else:
        raise ValueError("odometry topic has neither position[0..2] nor x/y/z")
    q = ned_q_frd_to_world_q_body(_vec(d, [f"q[{i}]" for i in range(4)]))
    p = ned_to_enu(p_ned)
    v = None
    if v_raw is not None:
        if vel_frame == VELOCITY_FRAME_BODY_FRD:
            v = np.einsum("nij,nj->ni", quat_wxyz_to_matrix(q), frd_to_flu(v_raw))
        else:
            v = ned_to_enu(v_raw)
    finite = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(q), axis=1)
    if v is not None:
        finite &= np.all(np.isfinite(v), axis=1)
    keep = finite & increasing_mask(np.where(finite, t, -np.inf))
    notes = {
        "samples": int(t.size),
        "skipped_nonfinite": int(np.count_nonzero(~finite)),
        "skipped_time_not_increasing": int(np.count_nonzero(finite & ~keep)),
        "pose_frame": {POSE_FRAME_NED: "NED", POSE_FRAME_FRD: "FRD"}.get(
            pose_frame, str(pose_frame)
        ),
    }
    if not np.any(keep):
        return None, notes
    traj = Trajectory(
        t=t[keep],
        world_t_body=p[keep],
        world_q_body_wxyz=q[keep],
        world_v_body=None if v is None else v[keep],
    )
    return traj, notes


def _flow_columns(d: Topic, topic: str) -> dict[str, np.ndarray]:
    """One flow topic's columns under common names (``optical_flow`` of PX4 <= 1.12 has its own)."""
    if topic == "optical_flow":
        t = np.asarray(d["timestamp"], dtype=float) * US_TO_S
        x, y = d["pixel_flow_x_integral"], d["pixel_flow_y_integral"]
        dt_us, dist = d["integration_timespan"], d.get("ground_distance_m")
    else:
        t = _sample_time(d)
        x, y = d["pixel_flow[0]"], d["pixel_flow[1]"]
        dt_us, dist = d["integration_timespan_us"], d.get("distance_m")
    n = t.size
    return {
        "t": t,
        "flow": np.column_stack([np.asarray(x, float), np.asarray(y, float)]),
        "dt": np.asarray(dt_us, dtype=float) * US_TO_S,
        "quality": np.asarray(d.get("quality", np.full(n, FLOW_QUALITY_MAX)), dtype=float),
        "distance": np.full(n, np.nan) if dist is None else np.asarray(dist, dtype=float),
        "min_distance": np.asarray(d.get("min_ground_distance", [np.nan]), dtype=float),
        "max_distance": np.asarray(d.get("max_ground_distance", [np.nan]), dtype=float),
    }


def body_T_flow_from_px4(
    d: Topic, topic: str, params: Mapping[str, float]
) -> tuple[np.ndarray, str]:
    """The flow sensor's pose in the FLU body (axes: the body's FRD) and where its lever arm came
    from: ``position_offset`` of ``vehicle_optical_flow`` when logged, else ``EKF2_OF_POS_X/Y/Z``,
    minus the IMU's ``EKF2_IMU_POS_X/Y/Z`` (fgnav's body origin is the IMU; EKF2 subtracts it)."""
    if topic == "vehicle_optical_flow" and all(f"position_offset[{i}]" in d for i in range(3)):
        pos = np.array([float(np.asarray(d[f"position_offset[{i}]"])[-1]) for i in range(3)])
        source = "vehicle_optical_flow.position_offset"
    else:
        pos = np.array([float(params.get(f"EKF2_OF_POS_{a}", 0.0)) for a in "XYZ"])
        source = "EKF2_OF_POS_X/Y/Z"
    imu = np.array([float(params.get(f"EKF2_IMU_POS_{a}", 0.0)) for a in "XYZ"])
    if not np.all(np.isfinite(pos)):
        pos, source = np.zeros(3), "none (non-finite offset logged)"
    return make_pose(np.diag([1.0, -1.0, -1.0]), frd_to_flu(pos - imu)), source


def flow_from_px4(
    d: Topic, topic: str, params: Mapping[str, float]
) -> tuple[FlowSeries | None, dict[str, Any], dict[str, np.ndarray]]:
    """One PX4 flow topic's columns -> fgnav flow [rad] (see the module docstring).

    Args:
        d: columns of ``vehicle_optical_flow``, ``sensor_optical_flow`` or ``optical_flow``.
        topic: which of them.
        params: the log's parameters (``SENS_FLOW_ROT`` for ``sensor_optical_flow``).

    Returns:
        ``(series or None, notes with the skip counts, the kept readings' columns)``.

    Raises:
        ValueError: ``SENS_FLOW_ROT`` is not one of PX4's yaw rotations 0..7.
    """
    c = _flow_columns(d, topic)
    t, flow, dt, quality = c["t"], c["flow"], c["dt"], c["quality"]
    notes: dict[str, Any] = {"topic": topic, "samples": int(t.size)}
    if topic == "sensor_optical_flow":
        rot = int(params.get("SENS_FLOW_ROT", 0))
        if not 0 <= rot <= 7:
            raise ValueError(f"SENS_FLOW_ROT = {rot}: expected a yaw rotation 0..7")
        a = np.radians(FLOW_ROT_YAW_STEP_DEG * rot)
        yaw = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        flow = flow @ yaw.T
        notes["sensor_to_body"] = f"SENS_FLOW_ROT {rot} (yaw {FLOW_ROT_YAW_STEP_DEG * rot:g} deg)"
    finite = np.all(np.isfinite(flow), axis=1) & np.isfinite(dt) & np.isfinite(t)
    reasons = {
        "skipped_nonfinite": ~finite,
        "skipped_quality_zero": finite & (quality <= 0),
        "skipped_no_interval": finite & (quality > 0) & (dt <= 0),
        "skipped_interval_over_1s": finite & (quality > 0) & (dt >= FLOW_MAX_INTERVAL_S),
    }
    ok = finite & (quality > 0) & (dt > 0) & (dt < FLOW_MAX_INTERVAL_S)
    keep = ok & increasing_mask(np.where(ok, t, -np.inf))
    reasons["skipped_time_not_increasing"] = ok & ~keep
    notes.update({k: int(np.count_nonzero(v)) for k, v in reasons.items()})
    kept = {k: (v[keep] if v.shape[:1] == t.shape else v) for k, v in c.items()}
    if not np.any(keep):
        return None, notes, kept
    fx, fy = flow[keep, 0], flow[keep, 1]
    series = FlowSeries(
        t=t[keep],
        dt=dt[keep],
        flow=np.column_stack([-fy, fx]),
        quality=quality[keep] / FLOW_QUALITY_MAX,
    )
    return series, notes, kept


def range_from_flow_distance(
    kept: dict[str, np.ndarray],
) -> tuple[RangeSeries | None, float, float, int]:
    """The flow message's ``distance_m`` (finite, > 0) as a range series: ``(series or None,
    range_min, range_max, readings left out)``; quality unknown (-1)."""
    r = kept["distance"]
    good = np.isfinite(r) & (r > 0)
    lo = kept["min_distance"][np.isfinite(kept["min_distance"])]
    hi = kept["max_distance"][np.isfinite(kept["max_distance"])]
    range_min = float(lo.max()) if lo.size else 0.0
    range_max = float(hi.min()) if hi.size else float("inf")
    if not np.any(good):
        return None, range_min, range_max, int(r.size)
    series = RangeSeries(t=kept["t"][good], range=r[good], quality=np.full(int(good.sum()), -1.0))
    return series, range_min, range_max, int(np.count_nonzero(~good))


def params_of_interest(params: Mapping[str, float]) -> dict[str, float]:
    """The parameters named by :data:`PARAMS_OF_INTEREST` (sorted by name)."""
    out = {}
    for name in sorted(params):
        if any(name == p or (p.endswith("_") and name.startswith(p)) for p in PARAMS_OF_INTEREST):
            out[name] = params[name]
    return out


# ----------------------------------------------------------------------------------------------
# The reader
# ----------------------------------------------------------------------------------------------


def _choose(
    instances: dict[int, Any], name: str, policy: InstancePolicy, meta: dict[str, Any]
) -> Any | None:
    if not instances:
        return None
    counts = {i: len(d.data["timestamp"]) for i, d in instances.items()}
    if policy == "first":
        chosen = min(counts)
    elif policy == "most_samples":
        chosen = max(sorted(counts), key=lambda i: counts[i])
    else:
        raise ValueError(f"instance_policy must be 'most_samples' or 'first', got {policy!r}")
    meta["px4_instances"][name] = {"chosen": chosen, "policy": policy, "available": counts}
    if len(counts) > 1:
        log.info("%s: %d instances %s, using %d (%s)", name, len(counts), counts, chosen, policy)
    return instances[chosen]


ULOG_HEADER_BYTES = 16
"""The ULog file header (magic, version, timestamp); messages follow: ``uint16`` payload size,
``uint8`` type, payload."""


def ulog_cut_bytes(path: Path) -> int:
    """Bytes missing from the last message of a ULog (0: the file ends on a message boundary).

    pyulog stops silently at a message cut short (a truncated file reads as a shorter flight):
    this walks the message headers from the file header to the end. Meaningful only for a file
    pyulog reads without corruption (a damaged size field sends the walk astray)."""
    data = path.read_bytes()
    pos, n = ULOG_HEADER_BYTES, len(data)
    while pos + 3 <= n:
        pos += 3 + int.from_bytes(data[pos : pos + 2], "little")
    if pos < n:  # a message header cut inside its 3 bytes
        return 3 - (n - pos)
    return pos - n


def read_ulog(path: str | Path, instance_policy: InstancePolicy = "most_samples") -> Flight:
    """Read a PX4 ULog into a :class:`Flight` in fgnav frames (see the module docstring).

    Args:
        path: ``.ulg`` file.
        instance_policy: how one instance of a multi-instance topic is chosen
            (``"most_samples"`` or ``"first"``).

    Returns:
        The flight, checked: ``imu`` (always), ``attitude``, ``range`` and ``flow`` when
        present, references ``px4_ekf2`` and ``px4_<odometry topic>``, ``meta`` with frames,
        parameters, instance choices, and counts of everything left out.

    Raises:
        FlightFormatError: not a readable ULog, or no ``sensor_combined`` data.
    """
    from pyulog import ULog

    path = Path(path)
    if not path.is_file():
        raise FlightFormatError(path, "no such file (expected a PX4 .ulg log)")
    # pyulog prints what it finds wrong in a file to stdout, a line per bad message (hundreds
    # on a damaged log, mixed into fgnav's own output): taken here and said once.
    printed = io.StringIO()
    try:
        with contextlib.redirect_stdout(printed):
            ulog = ULog(str(path))
    except Exception as exc:  # pyulog raises bare Exceptions on corrupt files
        raise FlightFormatError(path, f"not a readable PX4 ULog ({exc})") from exc
    pyulog_lines = [x.strip() for x in printed.getvalue().splitlines() if x.strip()]

    by_topic: dict[str, dict[int, Any]] = {}
    for d in ulog.data_list:
        by_topic.setdefault(d.name, {})[d.multi_id] = d
    meta: dict[str, Any] = {
        "format": "px4-ulog",
        "frames": "converted from PX4 NED world / FRD body to z-up world (x east, y north) / "
        "FLU body by fgnav.datasets.frames",
        "time": "seconds since PX4 boot (timestamp_us * 1e-6)",
        "px4_version": ulog.get_version_info_str(),
        "px4_hardware": ulog.msg_info_dict.get("ver_hw", ""),
        "px4_topics": {
            n: {i: len(d.data["timestamp"]) for i, d in sorted(inst.items())}
            for n, inst in sorted(by_topic.items())
        },
        "px4_instances": {},
        "px4_dropouts": {
            "count": len(ulog.dropouts),
            "total_ms": sum(x.duration for x in ulog.dropouts),
        },
        "px4_params": params_of_interest(ulog.initial_parameters),
        "px4_changed_params": [
            (t * US_TO_S, n, v)
            for t, n, v in ulog.changed_parameters
            if n in params_of_interest({n: v})
        ],
        "notes": [],
    }
    if ulog.file_corruption or pyulog_lines:
        msg = "pyulog reports file corruption: some messages were unreadable"
        if pyulog_lines:
            msg += f" ({len(pyulog_lines)} message(s) from pyulog, the first: {pyulog_lines[0]!r})"
        meta["notes"].append(msg)
        log.warning("%s: %s", path, msg)
    else:
        cut = ulog_cut_bytes(path)
        if cut:
            msg = (
                f"the file ends inside a message ({cut} byte(s) missing): cut short (a copy "
                "interrupted, a log not closed?); read up to the last whole message"
            )
            meta["notes"].append(msg)
            log.warning("%s: %s", path, msg)

    sc = _choose(by_topic.get("sensor_combined", {}), "sensor_combined", instance_policy, meta)
    if sc is None:
        raise FlightFormatError(path, "no sensor_combined topic: the log has no IMU data to read")
    imu, notes = imu_from_sensor_combined(sc.data)
    meta["imu"] = notes
    if len(imu) == 0:
        raise FlightFormatError(path, "sensor_combined has no finite samples")
    sel = by_topic.get("sensor_selection", {}).get(0)
    if sel is not None:
        selection = {
            "accel_device_id": int(sel.data["accel_device_id"][-1]),
            "gyro_device_id": int(sel.data["gyro_device_id"][-1]),
        }
        for kind in ("accel", "gyro"):
            for i, d in sorted(by_topic.get(f"sensor_{kind}", {}).items()):
                if int(d.data["device_id"][0]) == selection[f"{kind}_device_id"]:
                    selection[f"sensor_{kind}_instance"] = i
        meta["px4_imu_selection"] = selection

    attitude = None
    va = _choose(by_topic.get("vehicle_attitude", {}), "vehicle_attitude", instance_policy, meta)
    if va is not None:
        attitude, meta["attitude"] = attitude_from_vehicle_attitude(va.data)
        if len(attitude) == 0:
            attitude = None

    references: dict[str, Trajectory] = {}
    lp = _choose(
        by_topic.get("vehicle_local_position", {}), "vehicle_local_position", instance_policy, meta
    )
    if lp is not None and attitude is not None:
        traj, meta["px4_ekf2"] = trajectory_from_local_position(lp.data, attitude)
        if traj is not None:
            references["px4_ekf2"] = traj
    elif lp is not None:
        meta["notes"].append("vehicle_local_position present but no attitude: px4_ekf2 not built")

    for topic in ODOMETRY_TOPICS:
        od = _choose(by_topic.get(topic, {}), topic, instance_policy, meta)
        if od is None:
            continue
        try:
            traj, meta[f"px4_{topic}"] = trajectory_from_odometry(od.data)
        except (KeyError, ValueError) as exc:
            meta["notes"].append(f"{topic}: unrecognised layout ({exc}); not read")
            continue
        if traj is not None:
            references[f"px4_{topic}"] = traj

    calib_kwargs: dict[str, Any] = {}
    range_series = None
    ds_all = by_topic.get("distance_sensor", {})
    downward = {
        i: d
        for i, d in ds_all.items()
        if np.any(np.asarray(d.data.get("orientation", [])) == ROTATION_DOWNWARD_FACING)
    }
    if ds_all and len(downward) < len(ds_all):
        meta["notes"].append(
            f"distance_sensor: instances {sorted(set(ds_all) - set(downward))} are not "
            "downward-facing and were not read"
        )
    ds = _choose(downward, "distance_sensor", instance_policy, meta)
    if ds is not None:
        data = ds.data
        if not np.all(np.asarray(data["orientation"]) == ROTATION_DOWNWARD_FACING):
            mask = np.asarray(data["orientation"]) == ROTATION_DOWNWARD_FACING
            meta["notes"].append(
                f"distance_sensor: {int(np.count_nonzero(~mask))} samples with another orientation "
                "left out"
            )
            data = {k: np.asarray(v)[mask] for k, v in data.items()}
        range_series, rmin, rmax, meta["range"] = range_from_distance_sensor(data)
        calib_kwargs.update(
            range_min=rmin,
            range_max=rmax,
            body_T_range=body_T_range_from_params(ulog.initial_parameters),
        )

    flow_series, summary = None, {}
    for topic in FLOW_TOPICS:
        inst = by_topic.get(topic, {})
        if not inst:
            continue
        d = _choose(inst, topic, instance_policy, meta)
        t = _sample_time(d.data)
        summary[topic] = {
            "samples": int(t.size),
            "rate_hz": float(1.0 / np.median(np.diff(t))) if t.size > 1 else 0.0,
            "fields": sorted(d.data),
        }
        if flow_series is not None or "flow" in meta:
            summary[topic]["note"] = f"not converted: {meta['flow']['topic']} was"
            continue
        try:
            flow_series, meta["flow"], kept = flow_from_px4(d.data, topic, ulog.initial_parameters)
        except (KeyError, ValueError) as exc:
            summary[topic]["note"] = f"not converted: {exc}"
            meta["notes"].append(f"{topic}: not converted ({exc})")
            continue
        summary[topic]["note"] = "converted to the flow stream"
        skipped = {k: v for k, v in meta["flow"].items() if k.startswith("skipped") and v}
        if skipped:
            log.warning("%s: %s: readings left out: %s", path, topic, skipped)
        body_T_flow, meta["flow"]["lever_arm"] = body_T_flow_from_px4(
            d.data, topic, ulog.initial_parameters
        )
        calib_kwargs.update(body_T_flow=body_T_flow, flow_pixels_per_rad=1.0)
        if range_series is None and flow_series is not None:
            rs, rmin, rmax, n_bad = range_from_flow_distance(kept)
            if rs is not None:
                range_series = rs
                calib_kwargs.update(range_min=rmin, range_max=rmax, body_T_range=body_T_flow)
                meta["range"] = {
                    "source": f"{topic}.distance_m (no downward distance_sensor)",
                    "samples": int(len(rs)),
                    "skipped_nonfinite_or_zero": n_bad,
                }
    if summary:
        meta["px4_optical_flow"] = summary

    flight = Flight(
        name=path.stem,
        source=str(path),
        imu=imu,
        attitude=attitude,
        range=range_series,
        flow=flow_series,
        references=references,
        calib=Calibration(**calib_kwargs),
        meta=meta,
    )
    return flight.check()
