"""ROS 1 (``.bag``) and ROS 2 (bag folder, sqlite3 or mcap) reader -> :class:`Flight`.

Uses ``rosbags`` (pure Python; no ROS installation). Each fgnav stream comes from one topic:

* ``imu``: ``sensor_msgs/Imu`` -> ``flight.imu``.
* ``attitude``: ``sensor_msgs/Imu`` (its orientation), ``PoseStamped``,
  ``PoseWithCovarianceStamped``, ``nav_msgs/Odometry``, ``QuaternionStamped`` -> ``attitude``.
* ``range``: ``sensor_msgs/Range`` -> ``range`` (and ``calib.range_min/max``).
* ``images``: ``sensor_msgs/Image`` or ``CompressedImage`` -> ``images``.
* ``camera_info``: ``sensor_msgs/CameraInfo`` -> intrinsics of ``images`` (``calib.camera``).
* ``slam``: ``PoseStamped``, ``PoseWithCovarianceStamped``, ``Odometry``, ``TransformStamped``
  -> ``slam`` (one session, id 0).
* ``ground_truth``: the same types -> ``ground_truth``.
* ``ref:<name>``: the same types -> ``references[name]``.

``topics`` maps stream -> topic. When it is None, topics are mapped by message type: the ``Imu``,
``Range``, image and ``CameraInfo`` topic with the most messages; the IMU's orientation becomes
``attitude`` when the IMU fills it (``orientation_covariance[0] != -1``, REP-145); pose and
odometry topics cannot be told apart (SLAM output or ground truth?), so each becomes a reference
``ref:<topic>`` and the user maps it with ``topics={"slam": ...}``. The mapping used and the
reason are in ``meta["bag_mapping"]``.

Frames: ROS follows REP-103: world ENU (z up), body FLU, SI units, quaternions ``x y z w``. These
are fgnav's conventions, so values are copied as they are (quaternions reordered to ``[w, x, y,
z]``). Assumed and recorded in ``meta``: the IMU's ``frame_id`` is the body frame; a pose or
odometry topic gives the pose of its ``child_frame_id`` (or of the camera for ``slam``) in its
``header.frame_id``; odometry twist is in the child (body) frame (nav_msgs/Odometry definition) and
is rotated into the world. Extrinsics come from ``/tf_static`` (``tf2_msgs/TFMessage``) when the
bag has it: the body frame is the IMU's ``frame_id``; ``body_T_cam`` is the transform to the
images' ``frame_id`` (taken as an optical frame, x right, y down, z forward, REP-103's
``*_optical`` convention = fgnav's camera frame); ``body_T_range`` is the transform to the Range
``frame_id`` turned so that its +z is the beam (ROS ranges measure along the sensor's +x). Chains
of static transforms are followed in both directions. Dynamic ``/tf`` is not read. What could not
be resolved keeps :class:`Calibration`'s default (camera at the body origin with identity
rotation, rangefinder pointing down) and ``meta["notes"]`` says so.

Time: the message's ``header.stamp`` (sensor time), never the bag's receive time, as float
seconds. Messages whose stamp is zero (header not filled) use the receive time; they are counted
in ``meta["bag_streams"][stream]``. Messages are sorted by stamp; repeated stamps are left out and
counted, and so are (same place) non-finite values (IMU, attitude, poses), IMU samples beyond
:data:`.types.IMU_MAX_RATE` / :data:`.types.IMU_MAX_ACCEL` (corrupted) and negative ranges; ranges
outside the message's ``min_range .. max_range`` are kept and counted. A message the bag cannot
give or decode (a damaged bag) is an error naming the topic and the message's place in the file.

Images are decoded with OpenCV into memory (``ImageSeries.frames``, grey ``(N, H, W)`` or BGR
``(N, H, W, 3)`` uint8); ``image_stride`` keeps every n-th frame of long bags.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import FlightFormatError
from .geometry import invert_pose, make_pose, quat_wxyz_to_matrix
from .types import (
    AttitudeSeries,
    Calibration,
    CameraIntrinsics,
    Flight,
    ImageSeries,
    ImuSeries,
    RangeSeries,
    SlamSeries,
    Trajectory,
    imu_plausible,
)

log = logging.getLogger(__name__)

IMU = "sensor_msgs/msg/Imu"
RANGE = "sensor_msgs/msg/Range"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_COV_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
QUATERNION_STAMPED = "geometry_msgs/msg/QuaternionStamped"
ODOMETRY = "nav_msgs/msg/Odometry"

POSE_TYPES = (POSE_STAMPED, POSE_COV_STAMPED, ODOMETRY, TRANSFORM_STAMPED)
#: Message types accepted per stream (``ref:<name>`` streams accept ``POSE_TYPES``).
STREAM_TYPES: dict[str, tuple[str, ...]] = {
    "imu": (IMU,),
    "attitude": (IMU, POSE_STAMPED, POSE_COV_STAMPED, ODOMETRY, QUATERNION_STAMPED),
    "range": (RANGE,),
    "images": (IMAGE, COMPRESSED_IMAGE),
    "camera_info": (CAMERA_INFO,),
    "slam": POSE_TYPES,
    "ground_truth": POSE_TYPES,
}
#: ``sensor_msgs/Imu``: ``orientation_covariance[0] == -1`` means "no orientation" (REP-145).
NO_ORIENTATION = -1.0
#: ``sensor_msgs/Image`` encodings read (8-bit only) -> channels.
IMAGE_ENCODINGS = {"mono8": 1, "8UC1": 1, "bgr8": 3, "rgb8": 3, "8UC3": 3, "bgra8": 4, "rgba8": 4}
NS_TO_S = 1e-9
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC = "/tf_static"
#: Rotation from fgnav's range frame (beam along +z) into a ROS range frame (beam along +x):
#: its columns are fgnav's x, y, z axes in the ROS frame (z -> x, x -> y, y -> z; a proper
#: rotation).
ROSRANGE_R_RANGE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _open_reader(path: Path):
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    bag = path
    if (
        path.is_file()
        and path.suffix in (".db3", ".mcap")
        and (path.parent / "metadata.yaml").exists()
    ):
        bag = path.parent
    if not bag.exists():
        raise FlightFormatError(
            path, "no such bag (expected a ROS 1 .bag file or a ROS 2 bag folder)"
        )
    store = Stores.ROS1_NOETIC if bag.is_file() else Stores.ROS2_HUMBLE
    try:
        reader = AnyReader([bag], default_typestore=get_typestore(store))
        reader.open()
    except (AnyReaderError, OSError, ValueError) as exc:
        raise FlightFormatError(path, f"not a readable ROS bag ({exc})") from exc
    return reader


def list_bag_topics(path: str | Path) -> list[tuple[str, str, int]]:
    """Topics of a bag as ``(topic, message type, message count)``, sorted by topic.

    Raises:
        FlightFormatError: not a readable bag.
    """
    reader = _open_reader(Path(path))
    try:
        return sorted(
            (name, info.msgtype or "?", int(info.msgcount)) for name, info in reader.topics.items()
        )
    finally:
        reader.close()


def _format_topics(topics: Iterable[tuple[str, str, int]]) -> str:
    return ", ".join(f"{t} [{m}, {n}]" for t, m, n in topics)


def _auto_map(topics: list[tuple[str, str, int]]) -> tuple[dict[str, str], dict[str, str]]:
    """Stream -> topic by message type, and the reason of each choice."""
    mapping: dict[str, str] = {}
    reasons: dict[str, str] = {}

    def most(types: tuple[str, ...]) -> list[tuple[str, str, int]]:
        return sorted((x for x in topics if x[1] in types), key=lambda x: (-x[2], x[0]))

    for stream, types in (
        ("imu", (IMU,)),
        ("range", (RANGE,)),
        ("images", (IMAGE, COMPRESSED_IMAGE)),
    ):
        cands = most(types)
        if cands:
            mapping[stream] = cands[0][0]
            reasons[stream] = (
                f"only {types[0]} topic"
                if len(cands) == 1
                else (f"most messages of {len(cands)} candidates {[c[0] for c in cands]}")
            )
    infos = most((CAMERA_INFO,))
    if infos and "images" in mapping:
        ns = mapping["images"].rsplit("/", 1)[0]
        same_ns = [c for c in infos if c[0].rsplit("/", 1)[0] == ns]
        mapping["camera_info"] = (same_ns or infos)[0][0]
        reasons["camera_info"] = "same namespace as the images" if same_ns else "most messages"
    for name, msgtype, _ in most(POSE_TYPES):
        mapping[f"ref:{name.lstrip('/')}"] = name
        reasons[f"ref:{name.lstrip('/')}"] = (
            f"{msgtype}: SLAM output or ground truth cannot be told by type; map it with "
            "topics={'slam': ...} or {'ground_truth': ...}"
        )
    return mapping, reasons


@dataclass
class _Acc:
    """Messages of one topic: stamps and deserialised messages, in bag order."""

    t: list[float]
    msgs: list[Any]
    zero_stamps: int = 0


def _stamp(msg: Any, receive_ns: int, acc: _Acc) -> float:
    st = msg.header.stamp
    if st.sec == 0 and st.nanosec == 0:
        acc.zero_stamps += 1
        return receive_ns * NS_TO_S
    return st.sec + st.nanosec * NS_TO_S


def _ordered(acc: _Acc, stream: str, notes: dict[str, Any]) -> tuple[np.ndarray, list[Any]]:
    """Sort by stamp, leave out repeated stamps; record counts."""
    t = np.asarray(acc.t, dtype=float)
    order = np.argsort(t, kind="stable")
    t = t[order]
    keep = np.ones(t.size, dtype=bool)
    keep[1:] = np.diff(t) > 0
    notes[stream] = {
        "messages": int(t.size),
        "out_of_order": int(np.count_nonzero(np.diff(order) < 0)) if t.size > 1 else 0,
        "repeated_stamp_skipped": int(np.count_nonzero(~keep)),
        "zero_stamp_receive_time_used": acc.zero_stamps,
    }
    idx = order[keep]
    return t[keep], [acc.msgs[i] for i in idx]


def _xyz(v: Any) -> list[float]:
    return [v.x, v.y, v.z]


def _wxyz(q: Any) -> list[float]:
    return [q.w, q.x, q.y, q.z]


def _pose_of(msg: Any, msgtype: str) -> tuple[list[float], list[float]]:
    if msgtype == POSE_STAMPED:
        p = msg.pose
    elif msgtype in (POSE_COV_STAMPED, ODOMETRY):
        p = msg.pose.pose
    elif msgtype == TRANSFORM_STAMPED:
        return _xyz(msg.transform.translation), _wxyz(msg.transform.rotation)
    else:
        raise ValueError(msgtype)
    return _xyz(p.position), _wxyz(p.orientation)


def _normalised(q: np.ndarray, where: str, path: Path) -> np.ndarray:
    n = np.linalg.norm(q, axis=1, keepdims=True)
    if np.any(n < 0.5):
        i = int(np.flatnonzero(n[:, 0] < 0.5)[0])
        raise FlightFormatError(path, f"{where}: message {i} has a zero/invalid quaternion {q[i]}")
    return q / n


def _decode_image(msg: Any, msgtype: str, topic: str, i: int, path: Path) -> np.ndarray:
    import cv2

    if msgtype == COMPRESSED_IMAGE:
        img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise FlightFormatError(
                path, f"{topic}: message {i} ({msg.format!r}) could not be decoded"
            )
        return img
    ch = IMAGE_ENCODINGS.get(msg.encoding)
    if ch is None:
        raise FlightFormatError(
            path,
            f"{topic}: message {i} has encoding {msg.encoding!r}; "
            f"expected one of {sorted(IMAGE_ENCODINGS)}",
        )
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if data.size < msg.step * msg.height or msg.step < msg.width * ch:
        raise FlightFormatError(
            path,
            f"{topic}: message {i}: {data.size} bytes for {msg.height} rows of step {msg.step}",
        )
    img = data[: msg.step * msg.height].reshape(msg.height, msg.step)[:, : msg.width * ch]
    img = img.reshape(msg.height, msg.width, ch) if ch > 1 else img.reshape(msg.height, msg.width)
    if msg.encoding == "rgb8":
        img = img[:, :, ::-1]
    elif ch == 4:
        img = img[:, :, :3] if msg.encoding == "bgra8" else img[:, :, 2::-1]
    return np.ascontiguousarray(img)


def _extrinsic(static, body_frame, sensor_frame, stream: str, meta) -> np.ndarray | None:
    """``body_T_sensor`` from static transforms, or None with a note saying why."""
    what = "body_T_range" if stream == "range" else "body_T_cam"
    if not body_frame or not sensor_frame:
        reason = "no IMU frame_id (body frame)" if not body_frame else "no sensor frame_id"
    elif not static:
        reason = "the bag has no /tf_static"
    else:
        T = lookup_static_transform(static, body_frame, sensor_frame)
        if T is not None:
            meta.setdefault("extrinsics", {})[what] = f"/tf_static {body_frame} -> {sensor_frame}"
            return T
        reason = f"no /tf_static chain from {body_frame!r} to {sensor_frame!r}"
    meta["notes"].append(
        f"{stream}: {what} left at the Calibration default ({reason}); set it in a calibration"
    )
    return None


def _camera_from_info(msg: Any) -> CameraIntrinsics:
    # ROS 2 names the fields k and d, ROS 1 K and D.
    K = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=float)
    D = np.asarray(msg.d if hasattr(msg, "d") else msg.D, dtype=float)
    return CameraIntrinsics(
        fx=float(K[0]),
        fy=float(K[4]),
        cx=float(K[2]),
        cy=float(K[5]),
        width=int(msg.width),
        height=int(msg.height),
        distortion=tuple(float(x) for x in D),
    )


def _static_transforms(msgs: list[Any]) -> dict[tuple[str, str], np.ndarray]:
    """``(parent, child) -> parent_T_child`` (4x4) from ``TFMessage``s (last one wins)."""
    out = {}
    for m in msgs:
        for tr in m.transforms:
            R = quat_wxyz_to_matrix(_wxyz(tr.transform.rotation))
            out[(tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))] = make_pose(
                R, _xyz(tr.transform.translation)
            )
    return out


def lookup_static_transform(
    transforms: Mapping[tuple[str, str], np.ndarray], target: str, source: str
) -> np.ndarray | None:
    """``target_T_source`` (4x4) through a chain of static transforms, or None.

    Args:
        transforms: ``(parent, child) -> parent_T_child``.
        target, source: frame ids (leading ``/`` ignored).
    """
    target, source = target.lstrip("/"), source.lstrip("/")
    edges: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (parent, child), T in transforms.items():
        edges.setdefault(parent, []).append((child, T))
        edges.setdefault(child, []).append((parent, invert_pose(T)))
    # Breadth-first from the target: found[f] = target_T_f.
    found = {target: np.eye(4)}
    queue = [target]
    while queue:
        frame = queue.pop(0)
        for nxt, T in edges.get(frame, []):
            if nxt not in found:
                found[nxt] = found[frame] @ T
                queue.append(nxt)
    return found.get(source)


def read_bag(
    path: str | Path,
    topics: Mapping[str, str] | None = None,
    *,
    camera: CameraIntrinsics | None = None,
    image_stride: int = 1,
) -> Flight:
    """Read a ROS 1 or ROS 2 bag into a :class:`Flight` (see the module docstring).

    Args:
        path: ``.bag`` file, ROS 2 bag folder, or the ``.db3``/``.mcap`` file inside one.
        topics: stream -> topic (streams: ``imu``, ``attitude``, ``range``, ``images``,
            ``camera_info``, ``slam``, ``ground_truth``, ``ref:<name>``); None maps by type.
        camera: intrinsics of the images when the bag has no ``CameraInfo``.
        image_stride: keep every n-th image.

    Returns:
        The checked flight; ``meta`` has the mapping, per-stream counts and notes.

    Raises:
        FlightFormatError: unreadable bag, unknown stream, a topic not in the bag (the message
            lists the bag's topics), a topic of the wrong type, or an undecodable message.
    """
    path = Path(path)
    reader = _open_reader(path)
    try:
        return _read(reader, path, topics, camera, image_stride)
    finally:
        reader.close()


def _read(reader, path, topics, camera, image_stride) -> Flight:
    available = sorted((n, i.msgtype or "?", int(i.msgcount)) for n, i in reader.topics.items())
    types = {n: m for n, m, _ in available}
    meta: dict[str, Any] = {
        "format": "ros-bag",
        "frames": "REP-103 (ENU world, FLU body) = fgnav's; values copied, quaternions reordered",
        "time": "header.stamp in seconds",
        "bag_topics": available,
        "notes": [],
    }
    if topics is None:
        mapping, reasons = _auto_map(available)
        meta["bag_mapping"] = {"mode": "auto (by message type)", "map": mapping, "reasons": reasons}
        log.info("%s: topics mapped by type: %s", path.name, mapping)
    else:
        mapping = dict(topics)
        meta["bag_mapping"] = {"mode": "given", "map": mapping}
        for stream, topic in mapping.items():
            if stream not in STREAM_TYPES and not stream.startswith("ref:"):
                raise FlightFormatError(
                    path,
                    f"unknown stream {stream!r}; "
                    f"expected one of {sorted(STREAM_TYPES)} or 'ref:<name>'",
                )
            if topic not in types:
                raise FlightFormatError(
                    path,
                    f"stream {stream!r}: topic {topic!r} is not in the bag; "
                    f"topics: {_format_topics(available)}",
                )
            allowed = POSE_TYPES if stream.startswith("ref:") else STREAM_TYPES[stream]
            if types[topic] not in allowed:
                raise FlightFormatError(
                    path,
                    f"stream {stream!r}: topic {topic!r} has type {types[topic]}; "
                    f"expected one of {list(allowed)}",
                )
    if image_stride < 1:
        raise ValueError(f"image_stride must be >= 1, got {image_stride}")

    wanted = set(mapping.values())
    tf_topic = TF_STATIC_TOPIC if types.get(TF_STATIC_TOPIC) == TF_MESSAGE else None
    if tf_topic:
        wanted.add(tf_topic)
    accs = {topic: _Acc([], []) for topic in wanted}
    conns = [c for c in reader.connections if c.topic in wanted]
    topic, n_read = None, 0
    try:
        for conn, receive_ns, raw in reader.messages(connections=conns):
            topic = conn.topic
            msg = reader.deserialize(raw, conn.msgtype)
            topic = None
            acc = accs[conn.topic]
            n_read += 1
            if conn.topic == tf_topic:  # TFMessage has no header of its own
                acc.msgs.append(msg)
                continue
            acc.t.append(_stamp(msg, receive_ns, acc))
            acc.msgs.append(msg)
    except FlightFormatError:
        raise
    except Exception as e:  # rosbags raises assorted errors on a damaged bag: say where
        what = (
            f"cannot decode message {n_read} (from 0, in file order) on {topic}"
            if topic is not None
            else f"unreadable after {n_read} message(s) of the topics read"
        )
        why = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
        raise FlightFormatError(path, f"damaged bag: {what} ({why})") from e

    counts: dict[str, Any] = {}
    static: dict[tuple[str, str], np.ndarray] = {}
    if tf_topic:
        static = _static_transforms(accs[tf_topic].msgs)
        meta["tf_static"] = sorted(f"{p} -> {c}" for p, c in static)
    body_frame = None
    streams: dict[str, Any] = {}
    references: dict[str, Trajectory] = {}
    calib_kwargs: dict[str, Any] = {}

    if "imu" in mapping:
        t, msgs = _ordered(accs[mapping["imu"]], "imu", counts)
        w = np.array([_xyz(m.angular_velocity) for m in msgs], dtype=float).reshape(-1, 3)
        a = np.array([_xyz(m.linear_acceleration) for m in msgs], dtype=float).reshape(-1, 3)
        finite = np.all(np.isfinite(w), axis=1) & np.all(np.isfinite(a), axis=1)
        plausible = imu_plausible(w, a)
        counts["imu"]["nonfinite_skipped"] = int(np.count_nonzero(~finite))
        counts["imu"]["implausible_skipped"] = int(np.count_nonzero(finite & ~plausible))
        ok = finite & plausible
        streams["imu"] = ImuSeries(t=t[ok], body_omega=w[ok], body_accel=a[ok])
        counts["imu"]["frame_id"] = msgs[0].header.frame_id if msgs else ""
        body_frame = counts["imu"]["frame_id"] or None
        has_orientation = bool(msgs) and all(
            m.orientation_covariance[0] != NO_ORIENTATION for m in msgs
        )
        if topics is None and has_orientation:
            mapping["attitude"] = mapping["imu"]
            meta["bag_mapping"]["reasons"]["attitude"] = "the IMU fills its orientation (REP-145)"

    if "attitude" in mapping:
        topic = mapping["attitude"]
        t, msgs = _ordered(accs[topic], "attitude", counts)
        mt = types[topic]
        if mt == IMU:
            q = np.array([_wxyz(m.orientation) for m in msgs], dtype=float)
        elif mt == QUATERNION_STAMPED:
            q = np.array([_wxyz(m.quaternion) for m in msgs], dtype=float)
        else:
            q = np.array([_pose_of(m, mt)[1] for m in msgs], dtype=float)
        q = q.reshape(-1, 4)
        finite = np.all(np.isfinite(q), axis=1)
        counts["attitude"]["nonfinite_skipped"] = int(np.count_nonzero(~finite))
        streams["attitude"] = AttitudeSeries(
            t=t[finite], world_q_body_wxyz=_normalised(q[finite], topic, path)
        )

    if "range" in mapping:
        topic = mapping["range"]
        t, msgs = _ordered(accs[topic], "range", counts)
        r = np.array([m.range for m in msgs], dtype=float)
        finite = np.isfinite(r)
        negative = finite & (r < 0.0)  # no range is negative: a corrupted message
        ok = finite & ~negative
        counts["range"]["nonfinite_skipped"] = int(np.count_nonzero(~finite))
        counts["range"]["negative_skipped"] = int(np.count_nonzero(negative))
        if msgs:
            calib_kwargs["range_min"] = float(msgs[0].min_range)
            calib_kwargs["range_max"] = float(msgs[0].max_range)
            counts["range"]["field_of_view_rad"] = float(msgs[0].field_of_view)
            counts["range"]["frame_id"] = msgs[0].header.frame_id
            lo, hi = calib_kwargs["range_min"], calib_kwargs["range_max"]
            counts["range"]["outside_min_max_kept"] = int(
                np.count_nonzero(ok & ((r < lo) | (r > hi)))
            )
        if np.any(ok):
            streams["range"] = RangeSeries(
                t=t[ok], range=r[ok], quality=np.full(int(ok.sum()), -1.0)
            )
        T = _extrinsic(static, body_frame, counts["range"].get("frame_id"), "range", meta)
        if T is not None:
            calib_kwargs["body_T_range"] = T @ make_pose(ROSRANGE_R_RANGE, np.zeros(3))

    if "camera_info" in mapping and camera is None:
        _, msgs = _ordered(accs[mapping["camera_info"]], "camera_info", counts)
        if msgs:
            camera = _camera_from_info(msgs[0])
    if "images" in mapping:
        topic = mapping["images"]
        t, msgs = _ordered(accs[topic], "images", counts)
        t, msgs = t[::image_stride], msgs[::image_stride]
        counts["images"]["stride"] = image_stride
        if camera is None and topics is None:
            meta["notes"].append(
                f"images: {len(msgs)} images on {topic} left out: no CameraInfo topic and no "
                "camera intrinsics given (pass camera=...)"
            )
        elif camera is None:
            raise FlightFormatError(
                path, f"images on {topic}: no CameraInfo topic; pass camera intrinsics"
            )
        else:
            frames = [_decode_image(m, types[topic], topic, i, path) for i, m in enumerate(msgs)]
            shapes = {f.shape for f in frames}
            if len(shapes) > 1:
                raise FlightFormatError(
                    path, f"images on {topic}: frames of different shapes {sorted(shapes)}"
                )
            streams["images"] = ImageSeries(t=t, frames=np.stack(frames), camera=camera)
            calib_kwargs["camera"] = camera
            cam_frame = msgs[0].header.frame_id if msgs else ""
            counts["images"]["frame_id"] = cam_frame
            T = _extrinsic(static, body_frame, cam_frame, "images", meta)
            if T is not None:
                calib_kwargs["body_T_cam"] = T
                if "optical" not in cam_frame:
                    meta["notes"].append(
                        f"images: frame {cam_frame!r} is taken as an optical frame (x right, "
                        "y down, z forward); check body_T_cam if it is a FLU camera link"
                    )

    for stream in [s for s in mapping if s in ("slam", "ground_truth") or s.startswith("ref:")]:
        topic = mapping[stream]
        mt = types[topic]
        t, msgs = _ordered(accs[topic], stream, counts)
        poses = [_pose_of(m, mt) for m in msgs]
        pos = np.array([p for p, _ in poses], dtype=float).reshape(-1, 3)
        q = np.array([q for _, q in poses], dtype=float).reshape(-1, 4)
        finite = np.all(np.isfinite(pos), axis=1) & np.all(np.isfinite(q), axis=1)
        if mt == ODOMETRY:
            v_body = np.array([_xyz(m.twist.twist.linear) for m in msgs], dtype=float).reshape(
                -1, 3
            )
            finite &= np.all(np.isfinite(v_body), axis=1)
        counts[stream]["nonfinite_skipped"] = int(np.count_nonzero(~finite))
        counts[stream]["frame_id"] = msgs[0].header.frame_id if msgs else ""
        t, pos, q = t[finite], pos[finite], _normalised(q[finite], topic, path)
        if stream == "slam":
            streams["slam"] = SlamSeries(
                t=t, slam_t_cam=pos, slam_q_cam_wxyz=q, session=np.zeros(t.size, dtype=np.int64)
            )
            continue
        vel = None
        if mt == ODOMETRY:
            vel = np.einsum("nij,nj->ni", quat_wxyz_to_matrix(q), v_body[finite])
        traj = Trajectory(t=t, world_t_body=pos, world_q_body_wxyz=q, world_v_body=vel)
        if stream == "ground_truth":
            streams["ground_truth"] = traj
        else:
            references[stream[4:]] = traj

    meta["bag_streams"] = counts
    flight = Flight(
        name=path.stem if path.is_file() else path.name,
        source=str(path),
        references=references,
        calib=Calibration(**calib_kwargs),
        meta=meta,
        **streams,
    )
    return flight.check()
