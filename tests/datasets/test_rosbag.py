"""ROS 1 / ROS 2 bag reader: bags written here with rosbags' writers, read back exactly."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from fgnav.datasets.errors import FlightFormatError
from fgnav.datasets.geometry import matrix_to_quat_wxyz
from fgnav.datasets.rosbag import list_bag_topics, read_bag
from fgnav.datasets.types import Calibration
from rosbags.typesys import Stores, get_typestore

T0_NS = 1_700_000_000_123_000_000
N_IMU, N_RANGE, N_POSE, N_IMG = 40, 10, 8, 4
IMU_DT_NS, RANGE_DT_NS, POSE_DT_NS, IMG_DT_NS = 5_000_000, 20_000_000, 25_000_000, 50_000_000
RECEIVE_LAG_NS = 3_000_000  # messages arrive after their stamps: the reader must use stamps


def _data(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(N_POSE, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q_imu = rng.normal(size=(N_IMU, 4))
    q_imu /= np.linalg.norm(q_imu, axis=1, keepdims=True)
    return {
        "gyro": rng.normal(size=(N_IMU, 3)),
        "accel": rng.normal(size=(N_IMU, 3)) + [0, 0, 9.81],
        "q_imu_wxyz": q_imu,
        # sensor_msgs/Range is float32: exact round trip of float32-representable values.
        "range": rng.uniform(0.5, 5.0, size=N_RANGE).astype(np.float32).astype(float),
        "pos": rng.normal(size=(N_POSE, 3)),
        "q_wxyz": q,
        "vel_body": rng.normal(size=(N_POSE, 3)),
        "images": rng.integers(0, 256, size=(N_IMG, 6, 8), dtype=np.uint8),
    }


def _stamp(ts, ns: int):
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(ts, ns: int, frame: str, ros1: bool):
    H = ts.types["std_msgs/msg/Header"]
    if ros1:
        return H(seq=0, stamp=_stamp(ts, ns), frame_id=frame)
    return H(stamp=_stamp(ts, ns), frame_id=frame)


def _messages(ts, d, ros1: bool, compressed: bool):
    """(topic, msgtype, stamp_ns, message) in receive order."""
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    Q = ts.types["geometry_msgs/msg/Quaternion"]
    P = ts.types["geometry_msgs/msg/Point"]
    Pose = ts.types["geometry_msgs/msg/Pose"]
    cov9, cov36 = np.zeros(9), np.zeros(36)
    out = []

    def quat(q):
        return Q(x=q[1], y=q[2], z=q[3], w=q[0])

    for i in range(N_IMU):
        ns = T0_NS + i * IMU_DT_NS
        msg = ts.types["sensor_msgs/msg/Imu"](
            header=_header(ts, ns, "imu_link", ros1),
            orientation=quat(d["q_imu_wxyz"][i]),
            orientation_covariance=cov9,
            angular_velocity=V3(*d["gyro"][i]),
            angular_velocity_covariance=cov9,
            linear_acceleration=V3(*d["accel"][i]),
            linear_acceleration_covariance=cov9,
        )
        out.append(("/imu/data", "sensor_msgs/msg/Imu", ns, msg))
    R = ts.types["sensor_msgs/msg/Range"]
    for i in range(N_RANGE):
        ns = T0_NS + i * RANGE_DT_NS
        msg = R(
            header=_header(ts, ns, "range", ros1),
            radiation_type=1,
            field_of_view=0.05,
            min_range=0.2,
            max_range=8.0,
            range=d["range"][i],
        )
        out.append(("/rangefinder", "sensor_msgs/msg/Range", ns, msg))
    for i in range(N_POSE):
        ns = T0_NS + i * POSE_DT_NS
        pose = Pose(position=P(*d["pos"][i]), orientation=quat(d["q_wxyz"][i]))
        ps = ts.types["geometry_msgs/msg/PoseStamped"](
            header=_header(ts, ns, "map", ros1), pose=pose
        )
        out.append(("/orb_slam/pose", "geometry_msgs/msg/PoseStamped", ns, ps))
        od = ts.types["nav_msgs/msg/Odometry"](
            header=_header(ts, ns, "world", ros1),
            child_frame_id="base_link",
            pose=ts.types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov36),
            twist=ts.types["geometry_msgs/msg/TwistWithCovariance"](
                twist=ts.types["geometry_msgs/msg/Twist"](
                    linear=V3(*d["vel_body"][i]), angular=V3(0.0, 0.0, 0.0)
                ),
                covariance=cov36,
            ),
        )
        out.append(("/vicon/odom", "nav_msgs/msg/Odometry", ns, od))
    for i in range(N_IMG):
        ns = T0_NS + i * IMG_DT_NS
        img = d["images"][i]
        if compressed:
            ok, png = cv2.imencode(".png", img)
            assert ok
            msg = ts.types["sensor_msgs/msg/CompressedImage"](
                header=_header(ts, ns, "cam", ros1), format="png", data=png.ravel()
            )
            out.append(("/cam/image_raw/compressed", "sensor_msgs/msg/CompressedImage", ns, msg))
        else:
            msg = ts.types["sensor_msgs/msg/Image"](
                header=_header(ts, ns, "cam", ros1),
                height=img.shape[0],
                width=img.shape[1],
                encoding="mono8",
                is_bigendian=0,
                step=img.shape[1],
                data=img.ravel(),
            )
            out.append(("/cam/image_raw", "sensor_msgs/msg/Image", ns, msg))
        info_kwargs = dict(
            header=_header(ts, ns, "cam", ros1),
            height=6,
            width=8,
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=ts.types["sensor_msgs/msg/RegionOfInterest"](
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
            ),
        )
        K = np.array([100.0, 0, 4.0, 0, 101.0, 3.0, 0, 0, 1])
        D = np.array([0.1, -0.01, 0.0, 0.0, 0.0])
        R9, P12 = np.eye(3).ravel(), np.zeros(12)
        if ros1:
            info_kwargs.update(D=D, K=K, R=R9, P=P12)
        else:
            info_kwargs.update(d=D, k=K, r=R9, p=P12)
        info = ts.types["sensor_msgs/msg/CameraInfo"](**info_kwargs)
        out.append(("/cam/camera_info", "sensor_msgs/msg/CameraInfo", ns, info))
    out.sort(key=lambda x: x[2])
    return out


def _write_messages(w, ts, msgs, serialize) -> None:
    """One connection per topic, then every message received RECEIVE_LAG_NS after its stamp."""
    conns = {}
    for topic, mt, _, _ in msgs:
        if topic not in conns:
            conns[topic] = w.add_connection(topic, mt, typestore=ts)
    for topic, mt, ns, msg in msgs:
        w.write(conns[topic], ns + RECEIVE_LAG_NS, serialize(msg, mt))


def write_ros1(path: Path, d, compressed: bool = False) -> Path:
    from rosbags.rosbag1 import Writer

    ts = get_typestore(Stores.ROS1_NOETIC)
    msgs = _messages(ts, d, ros1=True, compressed=compressed)
    with Writer(path) as w:
        _write_messages(w, ts, msgs, ts.serialize_ros1)
    return path


def write_ros2(path: Path, d, storage: str, compressed: bool = True) -> Path:
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs = _messages(ts, d, ros1=False, compressed=compressed)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        _write_messages(w, ts, msgs, ts.serialize_cdr)
    return path


def _times(n: int, dt_ns: int) -> np.ndarray:
    ns = T0_NS + dt_ns * np.arange(n)
    return (ns // 10**9) + (ns % 10**9) * 1e-9


def _check_streams(flight, d):
    np.testing.assert_array_equal(flight.imu.t, _times(N_IMU, IMU_DT_NS))
    np.testing.assert_array_equal(flight.imu.body_omega, d["gyro"])
    np.testing.assert_array_equal(flight.imu.body_accel, d["accel"])
    np.testing.assert_array_equal(flight.range.t, _times(N_RANGE, RANGE_DT_NS))
    np.testing.assert_array_equal(flight.range.range, d["range"])
    assert flight.calib.range_min == pytest.approx(0.2) and flight.calib.range_max == 8.0
    np.testing.assert_array_equal(flight.images.t, _times(N_IMG, IMG_DT_NS))
    np.testing.assert_array_equal(flight.images.frames, d["images"])
    cam = flight.images.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (100, 101, 4, 3, 8, 6)
    assert cam.distortion[:2] == (0.1, -0.01)


@pytest.mark.parametrize("kind", ["ros1", "ros2-sqlite3", "ros2-mcap"])
def test_bag_round_trip_with_mapping(tmp_path, kind):
    d = _data(1)
    if kind == "ros1":
        path = write_ros1(tmp_path / "flight.bag", d)
        img_topic = "/cam/image_raw"
    else:
        path = write_ros2(tmp_path / "flight_bag", d, storage=kind.split("-")[1])
        img_topic = "/cam/image_raw/compressed"
    topics = {
        "imu": "/imu/data",
        "range": "/rangefinder",
        "images": img_topic,
        "camera_info": "/cam/camera_info",
        "slam": "/orb_slam/pose",
        "ground_truth": "/vicon/odom",
    }
    f = read_bag(path, topics)
    _check_streams(f, d)
    assert f.attitude is None  # not asked for
    np.testing.assert_array_equal(f.slam.t, _times(N_POSE, POSE_DT_NS))
    np.testing.assert_array_equal(f.slam.slam_t_cam, d["pos"])
    np.testing.assert_allclose(f.slam.slam_q_cam_wxyz, d["q_wxyz"], atol=1e-15)
    assert set(f.slam.session) == {0}
    gt = f.ground_truth
    np.testing.assert_array_equal(gt.world_t_body, d["pos"])
    # Odometry twist is in the child (body) frame: rotated into the world.
    from fgnav.datasets.geometry import quat_wxyz_to_matrix

    expected_v = np.einsum("nij,nj->ni", quat_wxyz_to_matrix(d["q_wxyz"]), d["vel_body"])
    np.testing.assert_allclose(gt.world_v_body, expected_v, atol=1e-12)
    assert f.meta["bag_mapping"]["mode"] == "given"
    assert f.meta["bag_streams"]["imu"]["messages"] == N_IMU


def test_auto_mapping_by_type(tmp_path):
    d = _data(2)
    path = write_ros1(tmp_path / "auto.bag", d)
    f = read_bag(path)
    _check_streams(f, d)
    mapping = f.meta["bag_mapping"]
    assert mapping["mode"].startswith("auto")
    assert mapping["map"]["imu"] == "/imu/data" and mapping["map"]["attitude"] == "/imu/data"
    # Pose topics cannot be told apart by type: references, with the reason.
    assert set(f.references) == {"orb_slam/pose", "vicon/odom"}
    assert "slam" in mapping["reasons"]["ref:vicon/odom"]
    assert f.slam is None and f.ground_truth is None
    np.testing.assert_allclose(f.attitude.world_q_body_wxyz, d["q_imu_wxyz"], atol=1e-15)
    json.dumps(f.meta)  # metadata stays serialisable


def test_list_bag_topics(tmp_path):
    path = write_ros2(tmp_path / "b", _data(3), storage="sqlite3")
    topics = list_bag_topics(path)
    assert ("/imu/data", "sensor_msgs/msg/Imu", N_IMU) in topics
    assert ("/cam/image_raw/compressed", "sensor_msgs/msg/CompressedImage", N_IMG) in topics
    assert [t for t, _, _ in topics] == sorted(t for t, _, _ in topics)


def test_mapping_errors_list_available_topics(tmp_path):
    path = write_ros1(tmp_path / "e.bag", _data(4))
    with pytest.raises(FlightFormatError, match=r"'/imu/missing' is not in the bag.*/imu/data"):
        read_bag(path, {"imu": "/imu/missing"})
    with pytest.raises(FlightFormatError, match="has type sensor_msgs/msg/Range"):
        read_bag(path, {"imu": "/rangefinder"})
    with pytest.raises(FlightFormatError, match="unknown stream 'lidar'"):
        read_bag(path, {"lidar": "/rangefinder"})
    with pytest.raises(FlightFormatError, match="not a readable ROS bag|no such bag"):
        read_bag(tmp_path / "nothing.bag")
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag at all")
    with pytest.raises(FlightFormatError, match="junk.bag"):
        read_bag(junk)


def test_images_without_camera_info(tmp_path):
    from rosbags.rosbag1 import Writer

    ts = get_typestore(Stores.ROS1_NOETIC)
    d = _data(5)
    msgs = [m for m in _messages(ts, d, ros1=True, compressed=False) if "camera_info" not in m[0]]
    path = tmp_path / "nocam.bag"
    with Writer(path) as w:
        conns = {}
        for topic, mt, ns, msg in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, mt, typestore=ts)
            w.write(conns[topic], ns, ts.serialize_ros1(msg, mt))
    f = read_bag(path)  # auto: images left out, and said so
    assert f.images is None
    assert any("images" in n and "left out" in n for n in f.meta["notes"])
    with pytest.raises(FlightFormatError, match="no CameraInfo"):
        read_bag(path, {"images": "/cam/image_raw"})


def test_decode_raw_image_encodings(tmp_path):
    from types import SimpleNamespace

    from fgnav.datasets.rosbag import IMAGE, _decode_image

    rng = np.random.default_rng(6)
    rgb = rng.integers(0, 256, size=(4, 5, 3), dtype=np.uint8)
    step = 5 * 3 + 2  # rows padded by 2 bytes
    buf = np.zeros((4, step), np.uint8)
    buf[:, :15] = rgb.reshape(4, 15)
    msg = SimpleNamespace(height=4, width=5, encoding="rgb8", step=step, data=buf.ravel())
    bgr = _decode_image(msg, IMAGE, "/cam", 0, tmp_path)
    np.testing.assert_array_equal(bgr, rgb[:, :, ::-1])
    msg16 = SimpleNamespace(
        height=4, width=5, encoding="mono16", step=10, data=np.zeros(40, np.uint8)
    )
    with pytest.raises(FlightFormatError, match="encoding 'mono16'"):
        _decode_image(msg16, IMAGE, "/cam", 3, tmp_path)
    short = SimpleNamespace(
        height=4, width=5, encoding="mono8", step=5, data=np.zeros(12, np.uint8)
    )
    with pytest.raises(FlightFormatError, match="message 2: 12 bytes"):
        _decode_image(short, IMAGE, "/cam", 2, tmp_path)


def test_header_stamps_sorted_repeats_and_zero_counted(tmp_path):
    from rosbags.rosbag1 import Writer

    ts = get_typestore(Stores.ROS1_NOETIC)
    d = _data(7)
    imu_msgs = [m for m in _messages(ts, d, ros1=True, compressed=False) if m[0] == "/imu/data"][:5]
    # Stamps out of order, one repeated, one unset (0): receive order 0..4.
    stamps = [T0_NS + 30_000_000, T0_NS + 10_000_000, T0_NS + 20_000_000, T0_NS + 20_000_000, 0]
    receive = [T0_NS + 40_000_000 + i * 1_000_000 for i in range(5)]
    path = tmp_path / "order.bag"
    with Writer(path) as w:
        conn = w.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=ts)
        for (_, mt, _, msg), st, rc in zip(imu_msgs, stamps, receive, strict=True):
            msg.header.stamp = _stamp(ts, st)
            w.write(conn, rc, ts.serialize_ros1(msg, mt))
    f = read_bag(path, {"imu": "/imu/data"})
    counts = f.meta["bag_streams"]["imu"]
    assert counts["messages"] == 5 and counts["repeated_stamp_skipped"] == 1
    assert counts["zero_stamp_receive_time_used"] == 1 and counts["out_of_order"] >= 1
    expected_ns = [T0_NS + 10_000_000, T0_NS + 20_000_000, T0_NS + 30_000_000, receive[4]]
    np.testing.assert_allclose(f.imu.t, [(n // 10**9) + (n % 10**9) * 1e-9 for n in expected_ns])
    np.testing.assert_array_equal(f.imu.body_omega[0], d["gyro"][1])  # sorted with its message


def test_extrinsics_from_tf_static(tmp_path):
    from fgnav.datasets.geometry import make_pose, rpy_to_matrix
    from fgnav.datasets.rosbag import lookup_static_transform
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = get_typestore(Stores.ROS2_HUMBLE)
    d = _data(8)
    msgs = _messages(ts, d, ros1=False, compressed=True)
    for _, _, _, msg in msgs:  # the camera frame is an optical frame
        if msg.header.frame_id == "cam":
            msg.header.frame_id = "cam_optical"
    base_T_imu = make_pose(rpy_to_matrix(0.0, 0.0, np.pi / 2), [0.1, 0.0, 0.0])
    base_T_cam = make_pose(rpy_to_matrix(-np.pi / 2, 0.0, -np.pi / 2), [0.2, 0.0, -0.05])
    imu_T_range = make_pose(rpy_to_matrix(0.0, np.pi / 2, 0.0), [0.0, 0.0, -0.03])  # x down

    def tf(parent, child, T):
        q = matrix_to_quat_wxyz(T[:3, :3])
        return ts.types["geometry_msgs/msg/TransformStamped"](
            header=_header(ts, T0_NS, parent, False),
            child_frame_id=child,
            transform=ts.types["geometry_msgs/msg/Transform"](
                translation=ts.types["geometry_msgs/msg/Vector3"](*T[:3, 3]),
                rotation=ts.types["geometry_msgs/msg/Quaternion"](x=q[1], y=q[2], z=q[3], w=q[0]),
            ),
        )

    tf_msg = ts.types["tf2_msgs/msg/TFMessage"](
        transforms=[
            tf("base_link", "imu_link", base_T_imu),
            tf("base_link", "cam_optical", base_T_cam),
            tf("imu_link", "range", imu_T_range),
        ]
    )
    path = tmp_path / "tf_bag"
    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        conns = {}
        tf_conn = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        w.write(tf_conn, T0_NS, ts.serialize_cdr(tf_msg, "tf2_msgs/msg/TFMessage"))
        for topic, mt, ns, msg in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, mt, typestore=ts)
            w.write(conns[topic], ns, ts.serialize_cdr(msg, mt))

    f = read_bag(path)
    expected_cam = np.linalg.inv(base_T_imu) @ base_T_cam
    np.testing.assert_allclose(f.calib.body_T_cam, expected_cam, atol=1e-12)
    # fgnav's range beam (+z) is the ROS range frame's +x: body -z here (pointing down).
    np.testing.assert_allclose(f.calib.body_T_range[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(f.calib.body_T_range[:3, 3], [0.0, 0.0, -0.03], atol=1e-12)
    assert np.linalg.det(f.calib.body_T_range[:3, :3]) == pytest.approx(1.0)
    assert f.meta["extrinsics"]["body_T_cam"] == "/tf_static imu_link -> cam_optical"
    assert not any("Calibration default" in n for n in f.meta["notes"])
    transforms = {("a", "b"): base_T_imu}
    assert lookup_static_transform(transforms, "a", "c") is None
    np.testing.assert_allclose(
        lookup_static_transform(transforms, "b", "a"), np.linalg.inv(base_T_imu)
    )

    # Without /tf_static the extrinsics keep the Calibration defaults, and the notes say so.
    g = read_bag(write_ros2(tmp_path / "no_tf", d, storage="sqlite3"))
    assert np.array_equal(g.calib.body_T_cam, Calibration().body_T_cam)
    assert np.array_equal(g.calib.body_T_range, Calibration().body_T_range)
    assert any(
        "body_T_range left at the Calibration default (the bag has no /tf_static)" in n
        for n in g.meta["notes"]
    )


def test_bad_values_left_out_counted_and_printed(tmp_path):
    """NaN and absurd (1e30 rad/s) IMU samples, a NaN pose and a negative range are left out
    and counted in ``meta["bag_streams"]``, and ``fgnav info`` prints those nested counts (and
    the ranges kept outside the message's limits)."""
    from fgnav.info import flight_info

    d = _data(3)
    d["gyro"][3, 0] = np.nan
    d["gyro"][5, 1] = 1e30
    d["accel"][7, 2] = -9.8e30
    d["range"][2] = -5.0
    d["range"][4] = 9.0  # beyond max_range 8: kept, counted
    d["pos"][1, 0] = np.nan
    path = write_ros1(tmp_path / "bad.bag", d)
    topics = {"imu": "/imu/data", "range": "/rangefinder", "slam": "/orb_slam/pose"}
    topics["ground_truth"] = "/vicon/odom"
    f = read_bag(path, topics)
    counts = f.meta["bag_streams"]
    assert len(f.imu) == N_IMU - 3 and np.all(np.isfinite(f.imu.body_omega))
    assert counts["imu"]["nonfinite_skipped"] == 1 and counts["imu"]["implausible_skipped"] == 2
    assert len(f.range) == N_RANGE - 1 and counts["range"]["negative_skipped"] == 1
    assert counts["range"]["outside_min_max_kept"] == 1
    assert len(f.slam) == N_POSE - 1 and counts["slam"]["nonfinite_skipped"] == 1
    assert len(f.ground_truth) == N_POSE - 1 and counts["ground_truth"]["nonfinite_skipped"] == 1
    notes = flight_info(f).notes
    for line in (
        "bag_streams.imu.nonfinite_skipped = 1",
        "bag_streams.imu.implausible_skipped = 2",
        "bag_streams.range.negative_skipped = 1",
        "bag_streams.slam.nonfinite_skipped = 1",
        "bag_streams.range.outside_min_max_kept = 1",
    ):
        assert line in notes, notes


def test_damaged_message_is_a_one_line_error_naming_the_topic(tmp_path, monkeypatch):
    """rosbags raises assorted errors (AssertionError, KeyError ...) on a damaged bag: one
    FlightFormatError line naming the bag, the topic and the message's place."""
    from rosbags.highlevel import AnyReader

    path = write_ros1(tmp_path / "damaged.bag", _data(4))
    real = AnyReader.deserialize
    calls = {"n": 0}

    def deserialize(self, raw, typename):
        calls["n"] += 1
        if calls["n"] == 6:
            raise AssertionError
        return real(self, raw, typename)

    monkeypatch.setattr(AnyReader, "deserialize", deserialize)
    with pytest.raises(FlightFormatError) as e:
        read_bag(path, {"imu": "/imu/data"})
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(path)), msg
    assert "damaged bag: cannot decode message 5" in msg and "/imu/data" in msg, msg
