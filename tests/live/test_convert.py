"""MAVLink <-> fgnav conversions: round trips over the wire (pymavlink's encoder and parser,
float32 fields) and hand-computed values for each frame and unit change."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from fgnav.datasets.events import (  # noqa: E402
    AttitudeSample,
    FlowSample,
    ImuSample,
    RangeReading,
    SlamPose,
)
from fgnav.datasets.geometry import (  # noqa: E402
    GRAVITY,
    make_pose,
    matrix_to_quat_wxyz,
    matrix_to_rpy,
    quat_wxyz_to_matrix,
    rpy_to_matrix,
    so3_exp,
)

from fgnav.estimate import OnlineState  # noqa: E402
from fgnav.live import convert  # noqa: E402
from fgnav.live.convert import Rejected  # noqa: E402
from fgnav.live.link import mavlink_dialect, new_mavlink, pack  # noqa: E402

F32 = 2e-6  # relative precision of float32 fields


@pytest.fixture(scope="module")
def wire():
    """Encode with pymavlink, pack, parse back: what the other end of the link sees."""
    tx = new_mavlink(1, 1)
    rx = new_mavlink(0, 0)

    def through(name: str, fields: dict):
        msg = getattr(tx, f"{name}_encode")(**fields)
        out = rx.parse_buffer(pack(tx, msg))
        assert out is not None and len(out) == 1 and out[0].get_type() != "BAD_DATA"
        return out[0]

    return through


def test_enum_values_are_pymavlink_s():
    m = mavlink_dialect()
    assert convert.MAV_FRAME_BODY_FRD == m.MAV_FRAME_BODY_FRD == 12
    assert convert.MAV_FRAME_LOCAL_FRD == m.MAV_FRAME_LOCAL_FRD == 20
    assert convert.MAV_ESTIMATOR_TYPE_VISION == m.MAV_ESTIMATOR_TYPE_VISION
    assert convert.MAV_ESTIMATOR_TYPE_VIO == m.MAV_ESTIMATOR_TYPE_VIO
    assert convert.MAV_SENSOR_ROTATION_PITCH_270 == m.MAV_SENSOR_ROTATION_PITCH_270 == 25
    bits = sum(
        getattr(m, f"HIGHRES_IMU_UPDATED_{a}")
        for a in ("XACC", "YACC", "ZACC", "XGYRO", "YGYRO", "ZGYRO")
    )
    assert convert.HIGHRES_IMU_ACCEL_GYRO == bits


def test_imu_hand_values_and_round_trip(wire):
    # At rest, level: specific force +g along FLU z is -g along FRD z; a roll rate keeps its
    # sign, pitch and yaw rates flip.
    ev = ImuSample(1.25, 1.25, np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.0, GRAVITY]))
    f = convert.highres_imu_fields(ev, boot_offset=0.25)
    assert f["time_usec"] == 1_000_000
    assert (f["xgyro"], f["ygyro"], f["zgyro"]) == (0.1, -0.2, -0.3)
    assert (f["xacc"], f["yacc"], f["zacc"]) == (0.0, -0.0, -GRAVITY)
    msg = wire("highres_imu", f)
    back = convert.imu_from_highres(msg)
    assert back.t == 1.0 and back.arrival == 1.0
    np.testing.assert_allclose(back.body_omega, ev.body_omega, rtol=F32)
    np.testing.assert_allclose(back.body_accel, ev.body_accel, rtol=F32)


def test_imu_without_updated_fields_is_rejected(wire):
    ev = ImuSample(0.0, 0.0, np.zeros(3), np.zeros(3))
    f = convert.highres_imu_fields(ev, 0.0) | {"fields_updated": 0b000111}  # accel only
    with pytest.raises(Rejected) as e:
        convert.imu_from_highres(wire("highres_imu", f))
    assert e.value.reason == "imu:not_updated"


def test_attitude_hand_values():
    # fgnav yaw +30 deg (nose towards world +y, left of x) is NED yaw -30 deg: world y flips.
    q_flu = matrix_to_quat_wxyz(rpy_to_matrix(0.0, 0.0, math.radians(30)))
    f = convert.attitude_quaternion_fields(AttitudeSample(0.5, 0.5, q_flu), 0.0)
    q_ned = np.array([f["q1"], f["q2"], f["q3"], f["q4"]])
    np.testing.assert_allclose(
        q_ned, [math.cos(math.radians(-15)), 0, 0, math.sin(math.radians(-15))], atol=1e-12
    )
    assert f["time_boot_ms"] == 500
    # fgnav pitch +10 deg (about y-left: nose down) is NED pitch -10 deg (nose up positive).
    q_flu = matrix_to_quat_wxyz(rpy_to_matrix(0.0, math.radians(10), 0.0))
    q = convert.frd_quat_to_flu(q_flu)
    rpy_ned = matrix_to_rpy(quat_wxyz_to_matrix(q))
    np.testing.assert_allclose(rpy_ned, [0.0, math.radians(-10), 0.0], atol=1e-12)


def _attitude_quaternion(wire, time_boot_ms: int, q_ned, repr_offset_q):
    """An ATTITUDE_QUATERNION at rest written by hand (``q_ned``: q1..q4, NED from FRD), as
    received."""
    fields = dict(time_boot_ms=time_boot_ms, q1=q_ned[0], q2=q_ned[1], q3=q_ned[2], q4=q_ned[3])
    rates = dict(rollspeed=0.0, pitchspeed=0.0, yawspeed=0.0)
    return wire("attitude_quaternion", fields | rates | {"repr_offset_q": repr_offset_q})


def test_attitude_agrees_with_the_accelerometer_and_round_trips(wire):
    """A tilted vehicle at rest: the FRD accelerometer reads ``ned_R_frd^T (0, 0, -g)``. Both
    converted to fgnav, the specific force is ``world_R_body^T (0, 0, +g)``."""
    rng = np.random.default_rng(0)
    zero_imu = convert.highres_imu_fields(ImuSample(0.0, 0.0, np.zeros(3), np.zeros(3)), 0.0)
    for _ in range(5):
        ned_R_frd = so3_exp(rng.normal(size=3) * 0.8)
        q_ned = matrix_to_quat_wxyz(ned_R_frd)
        frd_accel = ned_R_frd.T @ np.array([0.0, 0.0, -GRAVITY])
        msg = _attitude_quaternion(wire, 1234, q_ned, [1.0, 0, 0, 0])
        att = convert.attitude_from_quaternion(msg, arrival=2.0)
        assert att.t == 1.234 and att.arrival == 2.0
        # the message of a zero IMU sample with the FRD accelerometer written in by hand
        accel = dict(xacc=frd_accel[0], yacc=frd_accel[1], zacc=frd_accel[2])
        imu = wire("highres_imu", zero_imu | {"time_usec": 1234000} | accel)
        world_R_body = quat_wxyz_to_matrix(att.world_q_body_wxyz)
        np.testing.assert_allclose(
            convert.imu_from_highres(imu).body_accel,
            world_R_body.T @ [0.0, 0.0, GRAVITY],
            atol=2e-5,
        )
        # and back out: the same NED quaternion (float32)
        f = convert.attitude_quaternion_fields(att, 0.0)
        np.testing.assert_allclose([f["q1"], f["q2"], f["q3"], f["q4"]], q_ned, atol=1e-6)


def test_attitude_non_unit_quaternion_is_rejected(wire):
    msg = _attitude_quaternion(wire, 0, [0.5, 0.0, 0.0, 0.0], [0.0] * 4)
    with pytest.raises(Rejected) as e:
        convert.attitude_from_quaternion(msg)
    assert e.value.reason == "attitude:invalid_quaternion"


def test_range_centimetres_orientation_and_quality(wire):
    ev = RangeReading(2.0, 2.0, 1.2345, 0.5)
    f = convert.distance_sensor_fields(ev, 0.0, range_min=0.1, range_max=8.0)
    assert (f["current_distance"], f["min_distance"], f["max_distance"]) == (123, 10, 800)
    assert f["orientation"] == 25 and f["signal_quality"] == 51  # 2 + 98 * 0.5 (1: invalid)
    back = convert.range_from_distance_sensor(wire("distance_sensor", f))
    assert back.t == 2.0 and back.range == 1.23
    assert back.quality == pytest.approx(0.5, abs=0.01)
    unknown = convert.distance_sensor_fields(ev._replace(quality=-1.0), 0.0)
    assert unknown["signal_quality"] == 0 and unknown["max_distance"] == 65535
    assert convert.range_from_distance_sensor(wire("distance_sensor", unknown)).quality == -1.0
    with pytest.raises(Rejected) as e:
        convert.range_from_distance_sensor(wire("distance_sensor", f | {"orientation": 0}))
    assert e.value.reason == "range:orientation"
    with pytest.raises(Rejected) as e:
        convert.range_from_distance_sensor(wire("distance_sensor", f | {"current_distance": 801}))
    assert e.value.reason == "range:out_of_sensor_limits"
    with pytest.raises(Rejected) as e:  # a missing echo reported as the maximum
        convert.range_from_distance_sensor(wire("distance_sensor", f | {"current_distance": 800}))
    assert e.value.reason == "range:at_max"
    assert convert.range_from_distance_sensor(
        wire("distance_sensor", f | {"current_distance": 799})
    )
    with pytest.raises(Rejected) as e:  # MAVLink's "invalid signal"
        convert.range_from_distance_sensor(wire("distance_sensor", f | {"signal_quality": 1}))
    assert e.value.reason == "range:invalid_signal"
    worst = convert.distance_sensor_fields(ev._replace(quality=0.0), 0.0)
    assert worst["signal_quality"] == 2  # the worst valid reading is not sent as invalid


def test_slam_pose_is_taken_as_is(wire):
    q = matrix_to_quat_wxyz(so3_exp(np.array([0.3, -0.2, 1.0])))
    ev = SlamPose(3.0, 3.1, np.array([1.5, -2.0, 0.25]), q, 4)
    f = convert.vision_odometry_fields(ev, boot_offset=1.0, reset_counter=4)
    assert f["time_usec"] == 2_000_000 and f["reset_counter"] == 4
    assert f["estimator_type"] == convert.MAV_ESTIMATOR_TYPE_VISION
    back = convert.slam_from_odometry(wire("odometry", f), session=7, arrival=2.5)
    assert (back.t, back.arrival, back.session) == (2.0, 2.5, 7)
    np.testing.assert_allclose(back.slam_t_cam, ev.slam_t_cam, rtol=F32)
    np.testing.assert_allclose(back.slam_q_cam_wxyz, q, atol=1e-6)
    with pytest.raises(Rejected):
        convert.slam_from_odometry(wire("odometry", f | {"estimator_type": 3}), session=0)


def test_failed_slam_odometry_is_rejected(wire):
    """ODOMETRY.quality: -1 = odometry has failed, 0 = unknown, 1..100 (common.xml); a failed
    pose carrying garbage was fused as a good one."""
    ev = SlamPose(3.0, 3.0, np.array([1.5, -2.0, 0.25]), np.array([1.0, 0.0, 0.0, 0.0]), 0)
    f = convert.vision_odometry_fields(ev, boot_offset=0.0, reset_counter=0)
    with pytest.raises(Rejected) as e:
        convert.slam_from_odometry(wire("odometry", f | {"quality": -1}), session=0)
    assert e.value.reason == "slam:failed"
    for quality in (0, 1, 100):
        convert.slam_from_odometry(wire("odometry", f | {"quality": quality}), session=0)


def test_a_zero_range_is_no_reading(wire):
    """DISTANCE_SENSOR at 0 cm is many sensors' "no reading", also with min_distance 0 (it was
    taken as ground contact); the file readers leave zero ranges out too."""
    f = convert.distance_sensor_fields(RangeReading(2.0, 2.0, 1.0), 0.0, 0.0, 8.0)
    assert f["min_distance"] == 0
    with pytest.raises(Rejected) as e:
        convert.range_from_distance_sensor(wire("distance_sensor", f | {"current_distance": 0}))
    assert e.value.reason == "range:zero"
    assert convert.range_from_distance_sensor(wire("distance_sensor", f)).range == 1.0


def test_flow_signs_follow_mavlink_text(wire):
    # Forward motion (sensor +x) over the ground: fgnav flow x = -v_x/d dt < 0; MAVLink's
    # integrated_y is positive for motion along +x (PX4: "forwards: +Y").
    d, v, dt = 2.0, 1.0, 0.05
    ev = FlowSample(1.0, 1.0, dt, np.array([-v / d * dt, 0.0]), 1.0)
    f = convert.optical_flow_rad_fields(ev, 0.0)
    assert f["integrated_y"] == pytest.approx(v / d * dt) and f["integrated_x"] == 0.0
    # Sideways motion along +y: integrated_x negative; fgnav flow y = -v_y/d dt.
    ev2 = FlowSample(1.0, 1.0, dt, np.array([0.0, -v / d * dt]), 0.5)
    f2 = convert.optical_flow_rad_fields(ev2, 0.0)
    assert f2["integrated_x"] == pytest.approx(-v / d * dt)
    for e, fields in ((ev, f), (ev2, f2)):
        back = convert.flow_from_rad(wire("optical_flow_rad", fields), pixels_per_rad=1.0)
        assert back.dt == pytest.approx(dt) and back.t == 1.0
        np.testing.assert_allclose(back.flow, e.flow, atol=1e-8)
        assert back.quality == pytest.approx(e.quality, abs=1 / 255)
    # Flow in sensor pixels: pixels_per_rad scales both ways.
    back = convert.flow_from_rad(
        wire("optical_flow_rad", convert.optical_flow_rad_fields(ev, 0.0, 400.0)), 400.0
    )
    np.testing.assert_allclose(back.flow, ev.flow, atol=1e-8)
    with pytest.raises(Rejected):
        convert.flow_from_rad(wire("optical_flow_rad", f | {"quality": 0}))


def _state(R, p, v, pose_cov=None, vel_cov=None, t=4.5, quality=80, reset=3):
    return OnlineState(
        t=t,
        world_T_body=make_pose(R, p),
        world_v_body=np.asarray(v, float),
        accel_bias=np.zeros(3),
        gyro_bias=np.array([0.01, 0.0, 0.0]),
        pose_cov=pose_cov,
        vel_cov=vel_cov,
        reset_counter=reset,
        quality=quality,
    )


def test_odometry_out_hand_values_and_round_trip(wire):
    R = rpy_to_matrix(0.0, 0.0, math.radians(90))  # nose along world +y
    st = _state(
        R, [1.0, 2.0, 3.0], [1.0, 0.0, 0.0], pose_cov=np.eye(6) * 1e-4, vel_cov=np.eye(3) * 1e-2
    )
    f = convert.odometry_fields(
        st, body_omega=np.array([0.11, 0.2, 0.3]), rate_var=np.full(3, 1e-6)
    )
    assert (f["frame_id"], f["child_frame_id"]) == (20, 12)
    assert f["estimator_type"] == convert.MAV_ESTIMATOR_TYPE_VIO
    assert (f["time_usec"], f["reset_counter"], f["quality"]) == (4_500_000, 3, 80)
    assert (f["x"], f["y"], f["z"]) == (1.0, -2.0, -3.0)
    # world +x velocity, nose along +y: the body moves to its right (FLU -y, FRD +y).
    np.testing.assert_allclose([f["vx"], f["vy"], f["vz"]], [0.0, 1.0, 0.0], atol=1e-12)
    # gyro bias removed, then FRD
    np.testing.assert_allclose(
        [f["rollspeed"], f["pitchspeed"], f["yawspeed"]], [0.1, -0.2, -0.3], atol=1e-12
    )
    # LOCAL_FRD yaw of a FLU yaw of +90 deg is -90 deg
    rpy = matrix_to_rpy(quat_wxyz_to_matrix(f["q"]))
    np.testing.assert_allclose(rpy, [0.0, 0.0, math.radians(-90)], atol=1e-12)
    msg = wire("odometry", f)
    t, p, q, v = convert.pose_from_odometry(msg)
    assert t == 4.5
    np.testing.assert_allclose(p, [1.0, 2.0, 3.0], rtol=F32)
    np.testing.assert_allclose(quat_wxyz_to_matrix(q), R, atol=1e-6)
    np.testing.assert_allclose(v, [1.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(
        convert.from_upper_triangle(msg.pose_covariance),
        convert.odometry_pose_cov(R, st.pose_cov),
        rtol=F32,
        atol=1e-12,
    )
    # unknown covariances: NaN first
    f_unknown = convert.odometry_fields(_state(R, [0, 0, 0], [0, 0, 0]))
    assert math.isnan(f_unknown["pose_covariance"][0])
    assert math.isnan(f_unknown["velocity_covariance"][0])
    assert convert.from_upper_triangle(wire("odometry", f_unknown).pose_covariance) is None


def test_fields_are_every_field_of_their_message_in_order_as_plain_values():
    """Each ``*_fields`` dict names exactly its message's fields, in the message's order, and
    the components taken from vectors are Python floats (not numpy scalars)."""
    m = mavlink_dialect()
    q = matrix_to_quat_wxyz(so3_exp(np.array([0.3, -0.2, 1.0])))
    R = quat_wxyz_to_matrix(q)
    cases = {
        "highres_imu": convert.highres_imu_fields(
            ImuSample(1.0, 1.0, np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.5, GRAVITY])), 0.0
        ),
        "attitude_quaternion": convert.attitude_quaternion_fields(
            AttitudeSample(1.0, 1.0, q), 0.0, np.array([0.1, 0.2, 0.3])
        ),
        "distance_sensor": convert.distance_sensor_fields(RangeReading(1.0, 1.0, 1.2), 0.0),
        "odometry": convert.vision_odometry_fields(
            SlamPose(1.0, 1.0, np.array([1.5, -2.0, 0.25]), q, 0), 0.0, 0
        ),
        "optical_flow_rad": convert.optical_flow_rad_fields(
            FlowSample(1.0, 1.0, 0.02, np.array([0.1, -0.2]), 0.5), 0.0
        ),
    }
    out = convert.odometry_fields(
        _state(R, [1.0, 2.0, 3.0], [0.5, 0.0, 0.0]), body_omega=np.array([0.1, 0.2, 0.3])
    )
    for name, f in [*cases.items(), ("odometry", out)]:
        msg_type = getattr(m, f"MAVLink_{name}_message")
        assert list(f) == msg_type.fieldnames, name
    for f, keys in (
        (cases["highres_imu"], ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro", "xmag")),
        (cases["attitude_quaternion"], ("q1", "q2", "q3", "q4", "rollspeed", "yawspeed")),
        (cases["odometry"], ("x", "y", "z", "vx", "vz", "rollspeed", "yawspeed")),
        (out, ("x", "y", "z", "vx", "vy", "vz", "rollspeed", "pitchspeed", "yawspeed")),
    ):
        assert all(type(f[k]) is float for k in keys), keys


def test_upper_triangle_round_trip_and_order():
    A = np.arange(36, dtype=float).reshape(6, 6)
    S = A + A.T
    v = convert.upper_triangle(S)
    assert len(v) == 21
    assert v[:6] == S[0].tolist() and v[6:11] == S[1, 1:].tolist() and v[-1] == S[5, 5]
    np.testing.assert_array_equal(convert.from_upper_triangle(v), S)


def test_pose_covariance_hand_values():
    P = np.diag([1e-4, 2e-4, 3e-4, 0.01, 0.04, 0.09])  # [rot, trans] in body
    C = convert.odometry_pose_cov(np.eye(3), P)
    np.testing.assert_allclose(np.diag(C), [0.01, 0.04, 0.09, 1e-4, 2e-4, 3e-4], atol=1e-15)
    # Yawed 90 deg: body x along world y, so world x carries the body-y variance; roll and
    # pitch (at zero) are rotations about the body axes, so they keep theirs.
    C = convert.odometry_pose_cov(rpy_to_matrix(0.0, 0.0, math.pi / 2), P)
    np.testing.assert_allclose(np.diag(C)[:3], [0.04, 0.01, 0.09], atol=1e-15)
    np.testing.assert_allclose(np.diag(C)[3:], [1e-4, 2e-4, 3e-4], atol=1e-15)
    # Rolled 90 deg: the body z axis is level, so a body-z rotation changes the pitch and a
    # body-y rotation the yaw (E^-1 at roll 90 deg, pitch 0).
    C = convert.odometry_pose_cov(rpy_to_matrix(math.pi / 2, 0.0, 0.0), P)
    np.testing.assert_allclose(np.diag(C)[3:], [1e-4, 3e-4, 2e-4], atol=1e-15)


def _rpy_o(R):
    return matrix_to_rpy(convert.F @ R @ convert.F)


def test_pose_and_velocity_covariances_match_sampling():
    """``J P J^T`` against the covariance of the MAVLink values of perturbed states."""
    rng = np.random.default_rng(3)
    R = rpy_to_matrix(0.3, -0.4, 2.0)
    p = np.array([1.0, -2.0, 0.5])
    v = np.array([1.5, -0.5, 0.3])
    L = rng.normal(size=(6, 6)) * 0.01
    P = L @ L.T + np.eye(6) * 1e-5
    Lv = rng.normal(size=(3, 3)) * 0.05
    Pv = Lv @ Lv.T
    n = 20000
    xi = rng.multivariate_normal(np.zeros(6), P, size=n)
    dv = rng.multivariate_normal(np.zeros(3), Pv, size=n)
    F = convert.F
    y = np.empty((n, 6))
    vel = np.empty((n, 3))
    rpy0 = _rpy_o(R)
    for k in range(n):
        Rk = R @ so3_exp(xi[k, :3])
        pk = p + R @ xi[k, 3:]  # first order in rho, as GTSAM's retract
        y[k, :3] = F @ pk
        d = _rpy_o(Rk) - rpy0
        y[k, 3:] = (d + np.pi) % (2 * np.pi) - np.pi
        vel[k] = F @ Rk.T @ (v + dv[k])
    C = convert.odometry_pose_cov(R, P)
    Cs = np.cov(y.T)
    np.testing.assert_allclose(Cs, C, atol=0.05 * np.abs(C).max())
    Cv = convert.odometry_velocity_cov(R, v, Pv, P[:3, :3], rate_var=np.full(3, 1e-6))
    np.testing.assert_allclose(np.cov(vel.T), Cv[:3, :3], atol=0.05 * np.abs(Cv[:3, :3]).max())
    np.testing.assert_allclose(np.diag(Cv)[3:], 1e-6)
    assert np.all(Cv[:3, 3:] == 0)


def test_boot_clock_units():
    assert convert.s_to_us(1.25) == 1_250_000 and convert.s_to_us(3.0000004) == 3_000_000
    assert convert.s_to_ms(0.0124) == 12 and convert.s_to_ms(0.0126) == 13
    assert convert.us_to_s(2_500_000) == 2.5 and convert.ms_to_s(2500) == 2.5
    with pytest.raises(ValueError):
        convert.s_to_us(-0.1)
