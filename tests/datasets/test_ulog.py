"""PX4 ULog reader: topic converters on synthetic columns, and the two real logs."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fgnav.datasets.errors import FlightFormatError
from fgnav.datasets.geometry import quat_wxyz_to_matrix, wrap_angle, yaw_of
from fgnav.datasets.ulog import (
    RELATIVE_TIMESTAMP_INVALID,
    attitude_from_vehicle_attitude,
    body_T_range_from_params,
    imu_from_sensor_combined,
    params_of_interest,
    range_from_distance_sensor,
    read_ulog,
    trajectory_from_odometry,
)

G = 9.80665


def _sensor_combined(n: int, rel_us: np.ndarray) -> dict[str, np.ndarray]:
    t_us = 1_000_000 + 5000 * np.arange(n, dtype=np.uint64)
    d = {"timestamp": t_us, "accelerometer_timestamp_relative": rel_us.astype(np.int32)}
    for i, v in enumerate([0.1, 0.2, 0.3]):
        d[f"gyro_rad[{i}]"] = np.full(n, v, dtype=np.float32)
    # Accelerometer x ramps linearly in its own time so that interpolation is exact.
    t_acc = (t_us.astype(float) + rel_us) * 1e-6
    d["accelerometer_m_s2[0]"] = (2.0 * t_acc).astype(np.float64)
    d["accelerometer_m_s2[1]"] = np.zeros(n)
    d["accelerometer_m_s2[2]"] = np.full(n, -G)
    return d


def test_sensor_combined_frd_to_flu_and_accel_time():
    n = 50
    imu, notes = imu_from_sensor_combined(_sensor_combined(n, np.zeros(n)))
    np.testing.assert_allclose(imu.t, 1.0 + 0.005 * np.arange(n))
    np.testing.assert_allclose(imu.body_omega[0], [0.1, -0.2, -0.3], rtol=1e-6)
    np.testing.assert_allclose(imu.body_accel[:, 2], G)  # FRD -G on z -> FLU +G
    assert "same as gyro" in notes["accel_time"]

    rel = np.full(n, 2000.0)  # accelerometer sampled 2 ms after the gyro
    rel[10] = RELATIVE_TIMESTAMP_INVALID
    imu, notes = imu_from_sensor_combined(_sensor_combined(n, rel))
    # Interpolated onto gyro time: the ramp value at the gyro time (2 * t), inside the span.
    inside = (imu.t >= imu.t[0] + 0.002) & (imu.t <= imu.t[-1] - 0.002)
    np.testing.assert_allclose(imu.body_accel[inside, 0], 2.0 * imu.t[inside], atol=1e-9)
    assert notes["accel_invalid_relative_timestamp"] == 1
    assert "interpolated" in notes["accel_time"]


def test_vehicle_attitude_px4_yaw_zero_is_fgnav_yaw_half_pi():
    d = {
        "timestamp": np.array([10, 20, 30], dtype=np.uint64),
        "timestamp_sample": np.array([9, 19, 29], dtype=np.uint64),
        "q[0]": np.ones(3),
        "q[1]": np.zeros(3),
        "q[2]": np.zeros(3),
        "q[3]": np.zeros(3),
    }
    att, notes = attitude_from_vehicle_attitude(d)
    np.testing.assert_allclose(att.t, [9e-6, 19e-6, 29e-6])
    np.testing.assert_allclose(yaw_of(quat_wxyz_to_matrix(att.world_q_body_wxyz)), np.pi / 2)
    assert notes["attitude_samples_skipped_invalid"] == 0


def test_distance_sensor_quality_limits_and_mount():
    d = {
        "timestamp": np.array([1, 2, 3, 4], dtype=np.uint64) * 100_000,
        "current_distance": np.array([1.0, np.nan, 0.05, 3.0], dtype=np.float32),
        "min_distance": np.full(4, 0.1, dtype=np.float32),
        "max_distance": np.full(4, 8.0, dtype=np.float32),
        "signal_quality": np.array([100, 50, -1, 0], dtype=np.int8),
        "orientation": np.full(4, 25, dtype=np.uint8),
    }
    rs, rmin, rmax, notes = range_from_distance_sensor(d)
    np.testing.assert_allclose(rs.range, [1.0, 0.05, 3.0])
    np.testing.assert_allclose(rs.quality, [1.0, -1.0, 0.0])
    assert (rmin, rmax) == (pytest.approx(0.1), pytest.approx(8.0))
    assert notes["skipped_nonfinite"] == 1 and notes["outside_min_max_kept"] == 1

    # No pitch: beam straight down the FLU body; FRD offsets become FLU.
    T = body_T_range_from_params(
        {"EKF2_RNG_POS_X": 0.1, "EKF2_RNG_POS_Y": 0.2, "EKF2_RNG_POS_Z": 0.3}
    )
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], [0.1, -0.2, -0.3])
    # Positive pitch tilts the beam forward: (sin p, 0, -cos p) in FLU.
    p = 0.3
    T = body_T_range_from_params({"EKF2_RNG_PITCH": p})
    np.testing.assert_allclose(T[:3, 2], [np.sin(p), 0.0, -np.cos(p)], atol=1e-15)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


def test_odometry_body_velocity_rotated_into_world():
    yaw_ned = np.deg2rad(90.0)  # nose east
    q = [np.cos(yaw_ned / 2), 0.0, 0.0, np.sin(yaw_ned / 2)]
    d = {
        "timestamp": np.array([100, 200], dtype=np.uint64),
        "position[0]": np.array([1.0, 1.0]),
        "position[1]": np.array([2.0, 2.0]),
        "position[2]": np.array([-3.0, -3.0]),
        "velocity[0]": np.array([1.0, 1.0]),  # 1 m/s forward in body FRD
        "velocity[1]": np.zeros(2),
        "velocity[2]": np.zeros(2),
        "pose_frame": np.array([1, 1]),
        "velocity_frame": np.array([3, 3]),
        **{f"q[{i}]": np.full(2, q[i]) for i in range(4)},
    }
    traj, _ = trajectory_from_odometry(d)
    np.testing.assert_allclose(traj.world_t_body[0], [2.0, 1.0, 3.0])
    np.testing.assert_allclose(traj.world_v_body[0], [1.0, 0.0, 0.0], atol=1e-12)  # east


def test_params_of_interest():
    params = {"EKF2_MCOEF": 0.15, "EKF2_BCOEF_X": 25.0, "SENS_BOARD_ROT": 0, "MC_ROLL_P": 6.5}
    assert params_of_interest(params) == {
        "EKF2_BCOEF_X": 25.0,
        "EKF2_MCOEF": 0.15,
        "SENS_BOARD_ROT": 0,
    }


def test_not_a_ulog_is_a_clear_error(tmp_path):
    bad = tmp_path / "flight.ulg"
    bad.write_bytes(b"this is not a ulog file" * 10)
    with pytest.raises(FlightFormatError, match="flight.ulg"):
        read_ulog(bad)
    with pytest.raises(FlightFormatError, match="no such file"):
        read_ulog(tmp_path / "missing.ulg")


def _add_topic(ulog, name: str, multi_id: int, fields: list[tuple[str, int, str]], cols) -> None:
    """Add a topic instance (format + data) to a loaded pyulog ULog before ``write_ulog``."""
    from pyulog import ULog

    # Replace any format of that name the log already defines (PX4 logs carry unused formats).
    fmt = object.__new__(ULog.MessageFormat)
    fmt.name, fmt.fields = name, fields
    ulog._message_formats[name] = fmt
    flat = []
    for type_str, size, field in fields:
        names = [f"{field}[{i}]" for i in range(size)] if size else [field]
        flat += [ULog._FieldData(n, type_str) for n in names]
    d = object.__new__(ULog.Data)
    d.multi_id, d.name, d.field_data, d.timestamp_idx, d.data = multi_id, name, flat, 0, cols
    d.msg_id = 1000 + len(ulog._data_list)
    ulog._data_list.append(d)


DISTANCE_FIELDS = [
    ("uint64_t", 0, "timestamp"),
    ("float", 0, "current_distance"),
    ("float", 0, "min_distance"),
    ("float", 0, "max_distance"),
    ("int8_t", 0, "signal_quality"),
    ("uint8_t", 0, "orientation"),
]
ODOMETRY_FIELDS = [
    ("uint64_t", 0, "timestamp"),
    ("uint64_t", 0, "timestamp_sample"),
    ("uint8_t", 0, "pose_frame"),
    ("float", 3, "position"),
    ("float", 4, "q"),
    ("uint8_t", 0, "velocity_frame"),
    ("float", 3, "velocity"),
]
FLOW_FIELDS = [
    ("uint64_t", 0, "timestamp"),
    ("float", 2, "pixel_flow"),
    ("float", 0, "distance_m"),
    ("uint8_t", 0, "quality"),
]


@pytest.mark.realdata
def test_synthetic_topics_in_a_written_ulog(real_data, tmp_path):
    """Rangefinder, visual odometry and flow topics added to a real log, written with pyulog,
    read back end to end (no public log has them)."""
    from pyulog import ULog

    src = real_data / "px4_cubeorange_quad_flight" / "test.ulg"
    ulog = ULog(str(src), ["sensor_combined", "vehicle_attitude"])
    t0 = int(ulog.data_list[0].data["timestamp"][0])
    n = 50
    ts = (t0 + 20_000 * np.arange(n)).astype(np.uint64)
    rng_m = np.linspace(1.0, 3.0, n).astype(np.float32)
    rng_m[7] = np.nan
    down = {
        "timestamp": ts,
        "current_distance": rng_m,
        "min_distance": np.full(n, 0.1, np.float32),
        "max_distance": np.full(n, 8.0, np.float32),
        "signal_quality": np.full(n, 80, np.int8),
        "orientation": np.full(n, 25, np.uint8),
    }
    forward = {k: v[:10].copy() for k, v in down.items()}
    forward["orientation"][:] = 0
    _add_topic(ulog, "distance_sensor", 0, DISTANCE_FIELDS, forward)
    _add_topic(ulog, "distance_sensor", 1, DISTANCE_FIELDS, down)
    odo = {
        "timestamp": ts,
        "timestamp_sample": ts - np.uint64(1000),
        "pose_frame": np.full(n, 1, np.uint8),
        "velocity_frame": np.full(n, 1, np.uint8),
        **{f"position[{i}]": np.full(n, v, np.float32) for i, v in enumerate([1.0, 2.0, -3.0])},
        **{f"q[{i}]": np.full(n, v, np.float32) for i, v in enumerate([1.0, 0.0, 0.0, 0.0])},
        **{f"velocity[{i}]": np.full(n, v, np.float32) for i, v in enumerate([0.5, 0.0, 0.0])},
    }
    _add_topic(ulog, "vehicle_visual_odometry", 0, ODOMETRY_FIELDS, odo)
    flow = {
        "timestamp": ts,
        "pixel_flow[0]": np.zeros(n, np.float32),
        "pixel_flow[1]": np.zeros(n, np.float32),
        "distance_m": np.ones(n, np.float32),
        "quality": np.full(n, 200, np.uint8),
    }
    _add_topic(ulog, "vehicle_optical_flow", 0, FLOW_FIELDS, flow)
    ulog._initial_parameters.update({"EKF2_RNG_PITCH": 0.2, "EKF2_RNG_POS_Z": 0.05})
    out = tmp_path / "synthetic.ulg"
    ulog.write_ulog(str(out))

    f = read_ulog(out)
    # Only the downward instance is read; the NaN reading is left out and counted.
    assert f.meta["px4_instances"]["distance_sensor"]["chosen"] == 1
    assert any("not downward-facing" in note for note in f.meta["notes"])
    assert len(f.range) == n - 1 and f.meta["range"]["skipped_nonfinite"] == 1
    np.testing.assert_allclose(f.range.t, np.delete(ts, 7) * 1e-6)
    np.testing.assert_allclose(f.range.range, np.delete(rng_m, 7))
    np.testing.assert_allclose(f.range.quality, 0.8)
    assert (f.calib.range_min, f.calib.range_max) == (pytest.approx(0.1), pytest.approx(8.0))
    np.testing.assert_allclose(
        f.calib.body_T_range[:3, 2], [np.sin(0.2), 0.0, -np.cos(0.2)], atol=1e-7
    )
    np.testing.assert_allclose(f.calib.body_T_range[:3, 3], [0.0, 0.0, -0.05], atol=1e-7)
    # Visual odometry: NED -> z-up, time from timestamp_sample.
    vo = f.references["px4_vehicle_visual_odometry"]
    np.testing.assert_allclose(vo.t, (ts - 1000) * 1e-6)
    np.testing.assert_allclose(vo.world_t_body[0], [2.0, 1.0, 3.0])
    np.testing.assert_allclose(vo.world_v_body[0], [0.0, 0.5, 0.0], atol=1e-7)  # north -> +y
    # Flow is summarised, not converted.
    assert f.meta["px4_optical_flow"]["vehicle_optical_flow"]["samples"] == n


def _accel_gravity_angle_deg(flight, window_s: float = 0.25) -> np.ndarray:
    """Angle between the low-passed accelerometer and the attitude's world z axis in body."""
    w = int(window_s * flight.imu.rate_hz)
    kernel = np.ones(w) / w
    acc = np.column_stack(
        [np.convolve(flight.imu.body_accel[:, i], kernel, "valid") for i in range(3)]
    )
    t_acc = flight.imu.t[w // 2 : w // 2 + acc.shape[0]]
    att = flight.attitude.between(t_acc[0], t_acc[-1])
    acc_i = np.column_stack([np.interp(att.t, t_acc, acc[:, i]) for i in range(3)])
    up_in_body = quat_wxyz_to_matrix(att.world_q_body_wxyz)[:, 2, :]
    cos = np.sum(up_in_body * acc_i, axis=1) / np.linalg.norm(acc_i, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@pytest.mark.realdata
def test_cubeorange_flight(real_data):
    from pyulog import ULog

    path = real_data / "px4_cubeorange_quad_flight" / "test.ulg"
    f = read_ulog(path)
    assert f.imu.rate_hz == pytest.approx(187.5, abs=1.0)
    assert f.attitude.rate_hz == pytest.approx(20.8, abs=0.5)
    # At rest on the ground before take-off (the first second): specific force (0, 0, +g) in FLU.
    rest = f.imu.between(f.imu.t[0], f.imu.t[0] + 1.0)
    np.testing.assert_allclose(rest.body_accel.mean(axis=0), [0.0, 0.0, G], atol=0.3)
    # Attitude agrees with the accelerometer's tilt (hover: thrust along body z) within 2.5 deg.
    assert np.median(_accel_gravity_angle_deg(f)) < 1.0
    assert np.percentile(_accel_gravity_angle_deg(f), 99) < 2.5

    ekf = f.references["px4_ekf2"]
    assert ekf.rate_hz == pytest.approx(10.4, abs=0.3)
    # Hover at about 10 m: height is positive up in fgnav's world.
    assert 9.0 < ekf.world_t_body[:, 2].max() < 12.0
    assert abs(ekf.world_t_body[0, 2]) < 1.0
    # ENU from NED, checked against the raw log: x_enu = y_ned, y_enu = x_ned.
    raw = ULog(str(path), ["vehicle_local_position"]).data_list[0].data
    np.testing.assert_allclose(ekf.world_t_body[:, 0], raw["y"], rtol=1e-6)
    np.testing.assert_allclose(ekf.world_t_body[:, 1], raw["x"], rtol=1e-6)
    # EKF2's heading (NED yaw, clockwise from north) is pi/2 - fgnav yaw.
    yaw = yaw_of(quat_wxyz_to_matrix(ekf.world_q_body_wxyz))
    assert np.abs(wrap_angle(yaw - (np.pi / 2 - raw["heading"]))).max() < np.deg2rad(3.0)
    # Velocity is the derivative of position (vertical, during the climb and descent).
    vz_fd = np.gradient(ekf.world_t_body[:, 2], ekf.t)
    assert np.median(np.abs(vz_fd - ekf.world_v_body[:, 2])) < 0.1

    assert f.meta["px4_params"]["EKF2_MCOEF"] == pytest.approx(0.15)
    assert "SENS_BOARD_ROT" in f.meta["px4_params"]
    assert f.meta["px4_imu_selection"]["sensor_accel_instance"] == 2
    assert f.meta["px4_topics"]["sensor_accel"] == {0: 33, 1: 33, 2: 33}
    assert f.range is None
    json.dumps(f.meta)  # metadata stays serialisable (native flight folders store it as JSON)
    with pytest.raises(ValueError, match="instance_policy"):
        read_ulog(path, instance_policy="largest")


@pytest.mark.realdata
def test_handheld_optitrack_log(real_data):
    f = read_ulog(real_data / "px4_fmuv5_quad_handheld_optitrack" / "log008.ulg")
    assert f.imu.rate_hz == pytest.approx(200.0, abs=1.0)
    assert f.attitude.rate_hz == pytest.approx(20.0, abs=0.5)
    rest = f.imu.between(f.imu.t[0], f.imu.t[0] + 3.0)
    np.testing.assert_allclose(rest.body_accel.mean(axis=0), [0.0, 0.0, G], atol=0.6)
    # Carried by hand with tilts up to 48 deg: the attitude follows the accelerometer's tilt.
    tilt = np.degrees(np.arccos(quat_wxyz_to_matrix(f.attitude.world_q_body_wxyz)[:, 2, 2]))
    assert 40.0 < tilt.max() < 55.0
    angle = _accel_gravity_angle_deg(f)
    assert np.median(angle) < 2.0
    ekf = f.references["px4_ekf2"]
    meta = f.meta["px4_ekf2"]
    assert meta["xy_valid_fraction"] == 0.0 and meta["z_valid_fraction"] == 1.0
    assert meta["kept"] + meta["skipped_outside_attitude_span"] == meta["samples"] == 730
    assert ekf.t[0] >= f.attitude.t[0]


@pytest.mark.realdata
def test_attitude_rotates_rest_accel_to_world_up(real_data):
    # At rest the converted attitude maps the mean specific force onto world +z.
    f = read_ulog(real_data / "px4_fmuv5_quad_handheld_optitrack" / "log008.ulg")
    R = quat_wxyz_to_matrix(f.attitude.world_q_body_wxyz[:20])
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    f_world = R @ f.imu.between(f.attitude.t[0], f.attitude.t[19]).body_accel.mean(axis=0)
    up = f_world / np.linalg.norm(f_world, axis=1, keepdims=True)
    np.testing.assert_allclose(up, np.tile([0.0, 0.0, 1.0], (20, 1)), atol=0.02)


# ----------------------------------------------------------------------------------------------
# Optical flow: PX4's integrated-radians convention -> fgnav's flow stream
# ----------------------------------------------------------------------------------------------

VEHICLE_FLOW_FIELDS = [
    ("uint64_t", 0, "timestamp"),
    ("uint64_t", 0, "timestamp_sample"),
    ("float", 2, "pixel_flow"),
    ("float", 3, "delta_angle"),
    ("float", 0, "distance_m"),
    ("uint32_t", 0, "integration_timespan_us"),
    ("uint8_t", 0, "quality"),
    ("float", 0, "max_flow_rate"),
    ("float", 0, "min_ground_distance"),
    ("float", 0, "max_ground_distance"),
    ("float", 3, "position_offset"),
]
SENSOR_COMBINED_FIELDS = [
    ("uint64_t", 0, "timestamp"),
    ("float", 3, "gyro_rad"),
    ("uint32_t", 0, "gyro_integral_dt"),
    ("int32_t", 0, "accelerometer_timestamp_relative"),
    ("float", 3, "accelerometer_m_s2"),
    ("uint32_t", 0, "accelerometer_integral_dt"),
]


def _px4_flow_reading(R, p_world, v_world, omega_flu, ground, lever_flu, dt):
    """PX4 EKF2's flow model written from its sources, solved for the logged ``pixel_flow``:
    ``optical_flow.cpp`` takes ``flow_rate = -pixel_flow / dt`` and the flow gyro rate
    ``-delta_angle / dt``; ``optical_flow_control.cpp`` compensates ``flow_rate - gyro_rate``;
    ``optical_flow_fusion.cpp`` ``predictFlow`` is ``(v_y, -v_x) * R_to_earth(2, 2) / hagl`` with
    the body FRD velocity at the sensor. NED world, FRD body: independent of fgnav's convention.
    """
    frd = np.diag([1.0, -1.0, -1.0])
    ned_from_world = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    R_ned = ned_from_world @ R @ frd  # FRD body -> NED
    w = frd @ omega_flu
    pos = frd @ lever_flu
    v_body = R_ned.T @ (ned_from_world @ v_world + R_ned @ np.cross(w, pos))
    # Height of the sensor above the ground (NED down is -z_world), over R_to_earth(2, 2).
    hagl = (p_world[2] + (R @ lever_flu)[2]) - ground
    scale = R_ned[2, 2] / hagl
    los = np.array([v_body[1] * scale, -v_body[0] * scale])  # predicted compensated rate
    # los = flow_rate - gyro_rate = -pixel_flow / dt + w_xy  ->  pixel_flow = (w_xy - los) dt
    return (w[:2] - los) * dt


def test_px4_flow_reading_matches_fgnav_flow_model_at_random_states():
    """The converted reading of a PX4 flow message built with EKF2's model equals fgnav's
    flow-factor prediction at the same state (tilts up to 25 deg, lever arm, rates)."""
    from fgnav.datasets.frames import frd_to_flu
    from fgnav.datasets.geometry import rpy_to_matrix
    from fgnav.datasets.ulog import body_T_flow_from_px4, flow_from_px4
    from fgnav.factors.optical_flow import FlowSensor, predict_flow

    rng = np.random.default_rng(7)
    n = 40
    pos_offset_frd = np.array([0.04, -0.03, 0.06])
    imu_pos_frd = np.array([0.01, 0.01, -0.02])
    states = []
    flow_frd = np.zeros((n, 2))
    for i in range(n):
        R = rpy_to_matrix(*rng.uniform(-0.45, 0.45, 2), rng.uniform(-np.pi, np.pi))
        p = np.array([*rng.uniform(-3, 3, 2), rng.uniform(0.5, 2.5)])
        v = rng.normal(0.0, 1.0, 3)
        w = rng.normal(0.0, 0.8, 3)
        ground = rng.uniform(-0.2, 0.2)
        lever = frd_to_flu(pos_offset_frd - imu_pos_frd)
        flow_frd[i] = _px4_flow_reading(R, p, v, w, ground, lever, 0.02)
        states.append((R, p, v, w, ground))
    ts = (2_000_000 + 20_000 * np.arange(n)).astype(np.uint64)
    cols = {
        "timestamp": ts + 500,
        "timestamp_sample": ts,
        "pixel_flow[0]": flow_frd[:, 0],
        "pixel_flow[1]": flow_frd[:, 1],
        "integration_timespan_us": np.full(n, 20_000),
        "quality": np.full(n, 255),
        **{f"position_offset[{k}]": np.full(n, pos_offset_frd[k]) for k in range(3)},
    }
    params = {f"EKF2_IMU_POS_{a}": imu_pos_frd[k] for k, a in enumerate("XYZ")}
    series, notes, _ = flow_from_px4(cols, "vehicle_optical_flow", params)
    body_T_flow, source = body_T_flow_from_px4(cols, "vehicle_optical_flow", params)
    assert source == "vehicle_optical_flow.position_offset"
    np.testing.assert_allclose(series.t, ts * 1e-6)
    np.testing.assert_allclose(series.dt, 0.02)
    np.testing.assert_allclose(series.quality, 1.0)
    sensor = FlowSensor(body_T_flow, 1.0)
    for i, (R, p, v, w, ground) in enumerate(states):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = R, p
        pred = predict_flow(pose, v, ground, 0.02, w, sensor)
        np.testing.assert_allclose(series.flow[i], pred, atol=1e-9, rtol=1e-9)
    # The same readings in the sensor's axes, mounted with a yaw of 90 deg (SENS_FLOW_ROT 2:
    # body = Rz(90) sensor): turned back into the body by the reader.
    a = np.pi / 2
    Rz = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    raw = flow_frd @ Rz  # sensor = Rz^T body, row-wise
    cols_s = dict(cols, **{"pixel_flow[0]": raw[:, 0], "pixel_flow[1]": raw[:, 1]})
    series_s, notes_s, _ = flow_from_px4(cols_s, "sensor_optical_flow", {"SENS_FLOW_ROT": 2})
    np.testing.assert_allclose(series_s.flow, series.flow, atol=1e-12)
    assert "yaw 90 deg" in notes_s["sensor_to_body"]
    with pytest.raises(ValueError, match="SENS_FLOW_ROT"):
        flow_from_px4(cols_s, "sensor_optical_flow", {"SENS_FLOW_ROT": 9})


def test_px4_flow_bad_readings_are_left_out_and_counted():
    from fgnav.datasets.ulog import flow_from_px4

    n = 10
    cols = {
        "timestamp": (1_000_000 + 10_000 * np.arange(n)).astype(np.uint64),
        "pixel_flow_x_integral": np.full(n, 0.01),
        "pixel_flow_y_integral": np.full(n, -0.02),
        "integration_timespan": np.full(n, 10_000),
        "quality": np.full(n, 128),
        "ground_distance_m": np.full(n, 1.2),
    }
    cols["quality"][1] = 0
    cols["integration_timespan"][2] = 0
    cols["integration_timespan"][3] = 1_500_000
    cols["pixel_flow_x_integral"][4] = np.nan
    cols["timestamp"][6] = cols["timestamp"][5]
    series, notes, kept = flow_from_px4(cols, "optical_flow", {})
    assert notes["skipped_quality_zero"] == 1
    assert notes["skipped_no_interval"] == 1
    assert notes["skipped_interval_over_1s"] == 1
    assert notes["skipped_nonfinite"] == 1
    assert notes["skipped_time_not_increasing"] == 1
    assert len(series) == n - 5
    # Old topic, body FRD axes: fgnav flow = [-y, x].
    np.testing.assert_allclose(series.flow, np.tile([0.02, 0.01], (n - 5, 1)))
    np.testing.assert_allclose(series.quality, 128 / 255)
    np.testing.assert_allclose(kept["distance"], 1.2)


def _write_flowdeck_ulog(flight, path, with_distance_sensor: bool = True):
    """A simulated flow-deck flight as a PX4 log: ``sensor_combined`` (FRD), a downward
    ``distance_sensor`` with ``EKF2_RNG_POS_*``, and ``vehicle_optical_flow`` in radians about the
    body FRD axes (fgnav flow ``[fx, fy]`` is PX4 ``[fy, -fx]``) with its ``position_offset``."""
    from pyulog import ULog

    ulog = ULog(None)
    t_us = lambda t: np.round((np.asarray(t) + 1.0) * 1e6).astype(np.uint64)  # noqa: E731
    imu = flight.imu
    n = len(imu)
    sc = {"timestamp": t_us(imu.t), "accelerometer_timestamp_relative": np.zeros(n, np.int32)}
    sc |= {"gyro_integral_dt": np.full(n, 5000), "accelerometer_integral_dt": np.full(n, 5000)}
    flip = np.array([1.0, -1.0, -1.0])
    for k in range(3):
        sc[f"gyro_rad[{k}]"] = (imu.body_omega[:, k] * flip[k]).astype(np.float32)
        sc[f"accelerometer_m_s2[{k}]"] = (imu.body_accel[:, k] * flip[k]).astype(np.float32)
    _add_topic(ulog, "sensor_combined", 0, SENSOR_COMBINED_FIELDS, sc)
    rng = flight.range
    m = len(rng)
    if with_distance_sensor:
        ds = {
            "timestamp": t_us(rng.t),
            "current_distance": rng.range.astype(np.float32),
            "min_distance": np.full(m, flight.calib.range_min, np.float32),
            "max_distance": np.full(m, flight.calib.range_max, np.float32),
            "signal_quality": np.full(m, -1, np.int8),
            "orientation": np.full(m, 25, np.uint8),
        }
        _add_topic(ulog, "distance_sensor", 0, DISTANCE_FIELDS, ds)
    fl = flight.flow
    k = len(fl)
    ppr = flight.calib.flow_pixels_per_rad
    offset = flight.calib.body_T_flow[:3, 3] * flip  # FLU -> FRD
    dist = np.interp(fl.t, rng.t, rng.range).astype(np.float32)
    of = {
        "timestamp": t_us(fl.t) + np.uint64(300),
        "timestamp_sample": t_us(fl.t),
        "pixel_flow[0]": (fl.flow[:, 1] / ppr).astype(np.float32),
        "pixel_flow[1]": (-fl.flow[:, 0] / ppr).astype(np.float32),
        **{f"delta_angle[{j}]": np.full(k, np.nan, np.float32) for j in range(3)},
        "distance_m": dist,
        "integration_timespan_us": np.round(fl.dt * 1e6).astype(np.uint32),
        "quality": np.round(fl.quality * 255).astype(np.uint8),
        "max_flow_rate": np.full(k, 8.0, np.float32),
        "min_ground_distance": np.full(k, flight.calib.range_min, np.float32),
        "max_ground_distance": np.full(k, flight.calib.range_max, np.float32),
        **{f"position_offset[{j}]": np.full(k, offset[j], np.float32) for j in range(3)},
    }
    _add_topic(ulog, "vehicle_optical_flow", 0, VEHICLE_FLOW_FIELDS, of)
    rp = flight.calib.body_T_range[:3, 3] * flip
    ulog._initial_parameters.update(
        {f"EKF2_RNG_POS_{a}": float(rp[j]) for j, a in enumerate("XYZ")}
    )
    ulog.write_ulog(str(path))
    return path


@pytest.mark.parametrize("with_distance_sensor", [True, False])
def test_px4_flow_log_feeds_the_batch_smoother(tmp_path, with_distance_sensor):
    """A simulated flow-deck flight written as a PX4 log (IMU, range, flow) and read back: the
    batch smoother with IMU + flow + range gets its horizontal velocity within the bound of the
    simulated flight itself; without a ``distance_sensor`` the flow message's distance is the
    range."""
    from fgnav.datasets.simulate import SimOptions, simulate

    from fgnav.solvers.batch import BatchOptions, solve_batch
    from fgnav.solvers.graph import GraphOptions

    sim = simulate(
        "flowdeck",
        seed=0,
        options=SimOptions(
            duration=20.0, images=False, slam_rate_hz=0.0, attitude_rate_hz=0.0, yaw_rate_hz=0.0
        ),
    )
    path = _write_flowdeck_ulog(sim, tmp_path / "flowdeck.ulg", with_distance_sensor)
    f = read_ulog(path)
    assert f.meta["flow"]["topic"] == "vehicle_optical_flow"
    assert len(f.flow) == len(sim.flow)
    np.testing.assert_allclose(f.flow.flow, sim.flow.flow / 48.0, atol=1e-6)
    assert f.calib.flow_pixels_per_rad == 1.0
    np.testing.assert_allclose(f.calib.body_T_flow, sim.calib.body_T_flow, atol=1e-6)
    if with_distance_sensor:
        np.testing.assert_allclose(f.calib.body_T_range, sim.calib.body_T_range, atol=1e-6)
    else:
        assert "distance_m" in f.meta["range"]["source"]
        np.testing.assert_allclose(f.calib.body_T_range, sim.calib.body_T_flow, atol=1e-6)
    if with_distance_sensor:
        # The same streams through a manifest's tables (`format = "ulog"`).
        from fgnav.datasets.load import load_flight

        man = tmp_path / "flight.toml"
        man.write_text(
            'name = "px4-flow"\n'
            + "".join(
                f'[{t}]\nformat = "ulog"\npath = "flowdeck.ulg"\n'
                for t in ("imu", "range", "flow", "calib")
            )
        )
        fm = load_flight(man)
        np.testing.assert_array_equal(fm.flow.flow, f.flow.flow)
        np.testing.assert_allclose(fm.calib.body_T_flow, f.calib.body_T_flow)
    est = solve_batch(f, BatchOptions(graph=GraphOptions(), covariance="none"))
    assert est.info["factors"]["flow"] > 350
    gt = sim.ground_truth
    t = est.trajectory.t - 1.0  # the log's clock starts 1 s before the simulator's
    v = np.column_stack([np.interp(t, gt.t, gt.world_v_body[:, k]) for k in range(2)])
    # The log's world yaw is the estimator's own (no heading source): compare speeds.
    speed_err = np.linalg.norm(est.trajectory.world_v_body[:, :2], axis=1) - np.linalg.norm(
        v, axis=1
    )
    rmse = float(np.sqrt(np.mean(speed_err[t > 1.0] ** 2)))
    assert rmse < 0.03, rmse


@pytest.mark.realdata
def test_pyulog_prints_are_taken_and_said_once(real_data, tmp_path, capsys):
    """pyulog prints a line per unreadable message to stdout (hundreds on a damaged log, mixed
    into fgnav's output): the reader takes them and says them once, as a warning and a note."""
    data = bytearray((real_data / "px4_cubeorange_quad_flight" / "test.ulg").read_bytes())
    data[408612] ^= 0xFF  # a message id no subscription has (pyulog: "no subscription found")
    bad = tmp_path / "bad.ulg"
    bad.write_bytes(bytes(data))
    f = read_ulog(bad)
    assert capsys.readouterr().out == ""
    notes = [n for n in f.meta["notes"] if "pyulog reports file corruption" in n]
    assert len(notes) == 1 and "no subscription found" in notes[0]
    assert len(f.imu) > 1000


def test_sensor_combined_implausible_samples_left_out_and_counted():
    """A finite but absurd sample (1e30 rad/s, 9.8e30 m/s^2: a corrupted value) is left out and
    counted like a non-finite one."""
    n = 20
    d = _sensor_combined(n, np.zeros(n))
    d["gyro_rad[1]"][5] = 1e30
    d["accelerometer_m_s2[2]"][9] = -9.8e30
    d["gyro_rad[0]"][12] = np.nan
    imu, notes = imu_from_sensor_combined(d)
    assert len(imu) == n - 3
    assert notes["imu_samples_skipped_implausible"] == 2
    assert notes["imu_samples_skipped_nonfinite"] == 1
    assert np.all(np.abs(imu.body_omega) < 1.0) and np.all(np.abs(imu.body_accel) < 20.0)


def test_distance_sensor_negative_reading_left_out_and_counted():
    d = {
        "timestamp": np.array([1, 2, 3], dtype=np.uint64) * 100_000,
        "current_distance": np.array([1.0, -5.0, 2.0], dtype=np.float32),
    }
    rs, _, _, notes = range_from_distance_sensor(d)
    np.testing.assert_allclose(rs.range, [1.0, 2.0])
    assert notes["skipped_negative"] == 1


def test_ulog_cut_bytes_walks_the_message_headers(tmp_path):
    from fgnav.datasets.ulog import ulog_cut_bytes

    msg = (5).to_bytes(2, "little") + b"D" + b"12345"
    p = tmp_path / "x.ulg"
    for body, cut in ((msg * 3, 0), (msg * 3 + msg[:6], 2), (msg * 3 + msg[:1], 2), (b"", 0)):
        p.write_bytes(b"ULog\x01\x12\x35\x00" + bytes(8) + body)
        assert ulog_cut_bytes(p) == cut, (body, cut)


def test_truncated_ulog_is_said(real_data, tmp_path, caplog):
    """A ULog cut inside a message read as a shorter flight with no word: one warning line and a
    note; the whole log has neither."""
    src = real_data / "px4_cubeorange_quad_flight" / "test.ulg"
    whole = read_ulog(src)
    assert not any("ends inside a message" in n for n in whole.meta["notes"])
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(src.read_bytes()[:486757])
    with caplog.at_level("WARNING"):
        f = read_ulog(cut)
    notes = [n for n in f.meta["notes"] if "the file ends inside a message" in n]
    assert len(notes) == 1, f.meta["notes"]
    assert len(f.imu) < len(whole.imu)
    assert sum("ends inside a message" in r.getMessage() for r in caplog.records) == 1
