"""Typed measurement events and the one replay that merges streams in arrival order.

Every estimator in fgnav is fed these events, one at a time, in the order they arrive (see
../shared/DESIGN.md section 7): the online smoother, the filter baselines, and the batch smoother
(which collects them and solves once). A live source (MAVLink) produces the same events as a
replayed log. Frames and units are those of :mod:`fgnav.datasets.types` (world z up, body FLU,
SI units, float seconds on one clock).

Each event has two times:

- ``t``: when the measurement was taken (image exposure, IMU sample time, ...);
- ``arrival``: when it becomes available to the estimator (``t`` plus the stream's latency). An
  estimator may use an event only from its arrival on; a replay delivers events sorted by arrival.

Events are ``NamedTuple`` classes: immutable, cheap to make at 1 kHz, and dispatched by type.
This module knows nothing of GTSAM.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable, Iterator, Mapping, Sequence
from operator import attrgetter
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .types import (
    AttitudeSeries,
    Calibration,
    CameraIntrinsics,
    Flight,
    FlowSeries,
    ImuSeries,
    RangeSeries,
    SlamSeries,
    YawSeries,
)


class ImuSample(NamedTuple):
    """One IMU sample (body FLU): ``body_omega`` [rad/s], ``body_accel`` specific force [m/s^2]."""

    t: float
    arrival: float
    body_omega: np.ndarray
    body_accel: np.ndarray


class AttitudeSample(NamedTuple):
    """An AHRS attitude: ``world_q_body_wxyz`` unit quaternion of ``world_R_body``."""

    t: float
    arrival: float
    world_q_body_wxyz: np.ndarray


class SlamPose(NamedTuple):
    """A monocular-SLAM camera pose in the SLAM frame at the SLAM's own scale.

    ``t`` is the image capture time, ``arrival`` when the pose reached us. ``session`` is the SLAM
    map id: a new id means a new map (new frame and scale).
    """

    t: float
    arrival: float
    slam_t_cam: np.ndarray
    slam_q_cam_wxyz: np.ndarray
    session: int


class RangeReading(NamedTuple):
    """A rangefinder distance along its beam [m]; ``quality`` in [0, 1], -1 when unknown."""

    t: float
    arrival: float
    range: float
    quality: float = -1.0


class YawReading(NamedTuple):
    """A heading measurement: yaw of ``world_R_body`` [rad] (ZYX), in (-pi, pi]."""

    t: float
    arrival: float
    yaw: float


class ImageFrame(NamedTuple):
    """One camera frame: the pixels in memory (``image``) or a file (``path``) to read on use.

    ``index`` is the frame's index in its stream (for bookkeeping only).
    """

    t: float
    arrival: float
    index: int
    camera: CameraIntrinsics | None
    image: np.ndarray | None = None
    path: Path | None = None

    def load(self, grey: bool = True) -> np.ndarray:
        """The frame as a uint8 array (grey by default); raises FlightDataError if unreadable."""
        import cv2

        from .errors import FlightDataError

        if self.image is not None:
            img = self.image
        else:
            flag = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_UNCHANGED
            img = cv2.imread(str(self.path), flag)
            if img is None:
                raise FlightDataError(f"cannot read image {self.path} (missing or not an image)")
            return img
        if grey and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        return img


class FlowSample(NamedTuple):
    """Integrated optical flow over ``dt`` ending at ``t`` (convention of ``FlowSeries``)."""

    t: float
    arrival: float
    dt: float
    flow: np.ndarray
    quality: float = -1.0


Event = ImuSample | AttitudeSample | SlamPose | RangeReading | YawReading | ImageFrame | FlowSample
"""Any measurement event."""

STREAM_OF_EVENT: dict[type, str] = {
    ImuSample: "imu",
    AttitudeSample: "attitude",
    SlamPose: "slam",
    RangeReading: "range",
    YawReading: "yaw",
    ImageFrame: "images",
    FlowSample: "flow",
}
"""Stream name (as in ``Flight``) of each event type."""

EVENT_STREAMS = ("imu", "attitude", "range", "yaw", "slam", "images", "flow")
"""Sensor streams a flight can replay, in the order events of equal arrival are delivered."""


def _arrival(t: np.ndarray, latency: float | np.ndarray | None) -> np.ndarray:
    if latency is None:
        return t
    return t + np.asarray(latency, dtype=float)


def stream_events(
    flight: Flight, name: str, latency: float | np.ndarray | None = None
) -> Iterator[Event]:
    """The events of one of ``flight``'s streams, in arrival order.

    Args:
        flight: the flight (its ground truth is never read).
        name: a stream name of :data:`EVENT_STREAMS`.
        latency: seconds from measurement to arrival, a scalar or one per sample. ``None`` uses
            the stream's own (the SLAM stream's ``latency`` column), else 0.
    """
    s = getattr(flight, name)
    if s is None:
        return iter(())
    return series_events(s, name, latency)


def series_events(s: Any, name: str, latency: float | np.ndarray | None = None) -> Iterator[Event]:
    """The events of one stream's series (``name`` of :data:`EVENT_STREAMS`; ``latency`` as in
    :func:`stream_events`), in arrival order."""
    t = np.asarray(s.t, dtype=float)
    if latency is None and name == "slam" and s.latency is not None:
        latency = s.latency
    arr = _arrival(t, latency)
    order = np.argsort(arr, kind="stable")
    return _make_events(name, s, t, arr, order)


def chunked_events(chunks: Iterable[Any], name: str) -> Iterator[Event]:
    """The events of a stream read in chunks (consecutive series, e.g.
    :func:`fgnav.datasets.native.iter_stream_csv`), in arrival order across the chunks too.

    Every sample of a later chunk is taken after this chunk's last one and arrives no earlier
    than it is taken, so the events of this chunk (and those held from before) that arrive by
    its last capture time go out now, merged in arrival order; the others (the latency's tail)
    are held for the next chunk.
    """
    held: list[Event] = []
    key = attrgetter("arrival")
    for chunk in chunks:
        bound = float(chunk.t[-1])
        keep: list[Event] = []
        for ev in heapq.merge(held, series_events(chunk, name), key=key):
            if ev.arrival <= bound:
                yield ev
            else:
                keep.append(ev)
        held = keep
    yield from held


def _make_events(name, s, t, arr, order) -> Iterator[Event]:
    tl, al = t.tolist(), arr.tolist()
    if name == "imu":
        w, a = s.body_omega, s.body_accel
        for i in order.tolist():
            yield ImuSample(tl[i], al[i], w[i], a[i])
    elif name == "attitude":
        q = s.world_q_body_wxyz
        for i in order.tolist():
            yield AttitudeSample(tl[i], al[i], q[i])
    elif name == "slam":
        p, q, sess = s.slam_t_cam, s.slam_q_cam_wxyz, s.session.tolist()
        for i in order.tolist():
            yield SlamPose(tl[i], al[i], p[i], q[i], int(sess[i]))
    elif name == "range":
        r = s.range.tolist()
        qual = s.quality.tolist() if s.quality is not None else None
        for i in order.tolist():
            yield RangeReading(tl[i], al[i], r[i], -1.0 if qual is None else qual[i])
    elif name == "yaw":
        y = s.yaw.tolist()
        for i in order.tolist():
            yield YawReading(tl[i], al[i], y[i])
    elif name == "images":
        cam = s.camera
        for i in order.tolist():
            if s.frames is not None:
                yield ImageFrame(tl[i], al[i], i, cam, image=s.frames[i])
            else:
                yield ImageFrame(tl[i], al[i], i, cam, path=Path(s.paths[i]))
    elif name == "flow":
        dt, f = s.dt.tolist(), s.flow
        qual = s.quality.tolist() if s.quality is not None else None
        for i in order.tolist():
            yield FlowSample(tl[i], al[i], dt[i], f[i], -1.0 if qual is None else qual[i])
    else:
        raise ValueError(f"unknown stream {name!r}; expected one of {', '.join(EVENT_STREAMS)}")


def flight_streams(
    flight: Flight,
    streams: Iterable[str] | None = None,
    latency: Mapping[str, float | np.ndarray] | None = None,
) -> dict[str, Iterator[Event]]:
    """Per-stream event iterators of a flight (the streams it has, or those named)."""
    names = EVENT_STREAMS if streams is None else tuple(streams)
    latency = latency or {}
    return {
        n: stream_events(flight, n, latency.get(n))
        for n in names
        if getattr(flight, n, None) is not None
    }


def replay(streams: Mapping[str, Iterable[Event]] | Iterable[Iterable[Event]]) -> Iterator[Event]:
    """Merge per-stream iterators, each in arrival order, into one stream in arrival order.

    Lazy (``heapq.merge``): a reader that yields chunks streams a long log in bounded memory.
    Events of equal arrival come in the order the streams are given (with a mapping, the
    order of :data:`EVENT_STREAMS` for known names), so an IMU sample precedes the measurements
    that arrive with it.
    """
    if isinstance(streams, Mapping):
        rank = {n: i for i, n in enumerate(EVENT_STREAMS)}
        items = sorted(streams.items(), key=lambda kv: rank.get(kv[0], len(rank)))
        iters = [v for _, v in items]
    else:
        iters = list(streams)
    return heapq.merge(*iters, key=attrgetter("arrival"))


def replay_flight(
    flight: Flight,
    streams: Iterable[str] | None = None,
    latency: Mapping[str, float | np.ndarray] | None = None,
    *,
    named_order: bool = False,
) -> Iterator[Event]:
    """``replay(flight_streams(flight, streams, latency))``: the flight as one event stream.

    Events of equal arrival come in the order of :data:`EVENT_STREAMS`; with ``named_order``, in
    the order ``streams`` names them.
    """
    names = None if streams is None else tuple(streams)
    found = flight_streams(flight, names, latency)
    if named_order and names is not None:
        return replay([found[n] for n in names if n in found])
    return replay(found)


def flight_from_events(
    calib: Calibration, name: str, events: Mapping[str, Sequence[Event]]
) -> Flight:
    """The inverse of :func:`replay_flight`: per-stream event lists (each in capture-time
    order) back to a :class:`Flight` (``imu``, ``attitude``, ``yaw``, ``range``, ``slam``,
    ``flow``; a SLAM pose's arrival minus its capture time becomes ``SlamSeries.latency``).
    Not checked: the caller decides what to trust."""

    def col(stream: str, field: str, shape: tuple[int, ...] = ()) -> np.ndarray:
        return np.array([getattr(e, field) for e in events[stream]], dtype=float).reshape(
            -1, *shape
        )

    series: dict[str, Any] = {}
    have = {s for s, evs in events.items() if len(evs)}
    if "imu" in have:
        series["imu"] = ImuSeries(
            col("imu", "t"), col("imu", "body_omega", (3,)), col("imu", "body_accel", (3,))
        )
    if "attitude" in have:
        series["attitude"] = AttitudeSeries(
            col("attitude", "t"), col("attitude", "world_q_body_wxyz", (4,))
        )
    if "yaw" in have:
        series["yaw"] = YawSeries(col("yaw", "t"), col("yaw", "yaw"))
    if "range" in have:
        series["range"] = RangeSeries(
            col("range", "t"), col("range", "range"), col("range", "quality")
        )
    if "slam" in have:
        t = col("slam", "t")
        series["slam"] = SlamSeries(
            t,
            col("slam", "slam_t_cam", (3,)),
            col("slam", "slam_q_cam_wxyz", (4,)),
            np.array([e.session for e in events["slam"]], dtype=int),
            col("slam", "arrival") - t,
        )
    if "flow" in have:
        series["flow"] = FlowSeries(
            col("flow", "t"), col("flow", "dt"), col("flow", "flow", (2,)), col("flow", "quality")
        )
    return Flight(name, calib=calib, **series)
