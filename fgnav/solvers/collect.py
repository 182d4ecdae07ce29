"""The batch smoother's input from measurement events: :class:`EventCollector`.

DESIGN.md sec. 7: "the batch smoother collects them [the events] and solves once". The collector
is fed the same events as the online smoother (a replay, or a live link: ``fgnav live --batch``)
and turns what it kept into a :class:`~fgnav.datasets.types.Flight` for
:func:`fgnav.methods.run_batch`, which then decides with the whole flight in hand (keyframes on
the SLAM times, the accelerometer check on every keyframe, ...).

Kept: IMU samples, attitude samples, range and yaw readings, SLAM poses (their arrival minus
their capture time becomes ``SlamSeries.latency``) and optical-flow samples. Not kept, counted:
image frames (``images:not-collected``; a live link carries none), SLAM poses of a negative
session (``slam:tracking-lost``), samples with a non-finite value (``<stream>:non-finite``).
Order: each stream is sorted by its capture time, a sample with the time of one kept before it
in that stream is dropped (``<stream>:duplicate-time``). Nothing else is judged here: the batch
smoother's readers-side checks (``Flight.check``) and its own gates apply as to a file.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fgnav.datasets import types as ft
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import STREAM_OF_EVENT, ImageFrame, SlamPose

#: The values each kept stream's event contributes, as one flat tuple of floats per event.
_ROW = {
    "imu": lambda e: (e.t, *e.body_omega, *e.body_accel),
    "attitude": lambda e: (e.t, *e.world_q_body_wxyz),
    "range": lambda e: (e.t, e.range, e.quality),
    "yaw": lambda e: (e.t, e.yaw),
    "slam": lambda e: (e.t, *e.slam_t_cam, *e.slam_q_cam_wxyz, e.session, e.arrival - e.t),
    "flow": lambda e: (e.t, e.dt, *e.flow, e.quality),
}


def _unit(q: np.ndarray) -> np.ndarray:
    """Quaternions normalised where they are not already (a link's float32 ones), others
    kept bit for bit."""
    n = np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(np.abs(n - 1.0) > 1e-12, q / n, q)


class EventCollector:
    """Events in, a :class:`Flight` out (module docstring).

    Args:
        calib: the calibration the flight gets (a live link's ``--calib``).
        name: the flight's name.
    """

    def __init__(self, calib: ft.Calibration, name: str = "events") -> None:
        self.calib = calib
        self.name = name
        self._rows: dict[str, list[tuple[float, ...]]] = {}
        self.dropped: dict[str, int] = {}

    def _drop(self, key: str) -> None:
        self.dropped[key] = self.dropped.get(key, 0) + 1

    def feed(self, ev: Any) -> None:
        """Keep one event (any order; see the module docstring for what is kept)."""
        if isinstance(ev, ImageFrame):
            self._drop("images:not-collected")
            return
        stream = STREAM_OF_EVENT.get(type(ev))
        row_of = _ROW.get(stream)
        if row_of is None:
            return
        if isinstance(ev, SlamPose) and ev.session < 0:
            self._drop("slam:tracking-lost")
            return
        row = tuple(float(x) for x in row_of(ev))
        # Quality -1 (unknown) and the rest must be finite.
        if not all(math.isfinite(x) for x in row):
            self._drop(f"{stream}:non-finite")
            return
        self._rows.setdefault(stream, []).append(row)

    def counts(self) -> dict[str, Any]:
        """Samples kept per stream and dropped by ``stream:reason``."""
        return {
            "kept": {s: len(r) for s, r in sorted(self._rows.items())},
            "dropped": dict(sorted(self.dropped.items())),
        }

    def _table(self, stream: str) -> np.ndarray | None:
        rows = self._rows.get(stream)
        if not rows:
            return None
        a = np.asarray(rows, dtype=float)
        a = a[np.argsort(a[:, 0], kind="stable")]
        dup = np.zeros(len(a), dtype=bool)
        dup[1:] = a[1:, 0] == a[:-1, 0]
        if dup.any():
            self.dropped[f"{stream}:duplicate-time"] = int(dup.sum())
        return a[~dup]

    def flight(self) -> ft.Flight:
        """The flight of every event kept so far (checked); an error naming what is missing
        when no IMU sample was kept."""
        streams: dict[str, Any] = {}
        imu = self._table("imu")
        if imu is None:
            raise FlightDataError(f"{self.name}: no IMU sample collected: nothing to solve")
        streams["imu"] = ft.ImuSeries(t=imu[:, 0], body_omega=imu[:, 1:4], body_accel=imu[:, 4:7])
        if (a := self._table("attitude")) is not None:
            q = _unit(a[:, 1:5])
            streams["attitude"] = ft.AttitudeSeries(t=a[:, 0], world_q_body_wxyz=q)
        if (a := self._table("range")) is not None:
            quality = a[:, 2] if np.any(a[:, 2] >= 0) else None
            streams["range"] = ft.RangeSeries(t=a[:, 0], range=a[:, 1], quality=quality)
        if (a := self._table("yaw")) is not None:
            streams["yaw"] = ft.YawSeries(t=a[:, 0], yaw=a[:, 1])
        if (a := self._table("slam")) is not None:
            q = _unit(a[:, 4:8])
            streams["slam"] = ft.SlamSeries(
                t=a[:, 0],
                slam_t_cam=a[:, 1:4],
                slam_q_cam_wxyz=q,
                session=a[:, 8].astype(int),
                latency=np.maximum(a[:, 9], 0.0),
            )
        if (a := self._table("flow")) is not None:
            quality = a[:, 4] if np.any(a[:, 4] >= 0) else None
            streams["flow"] = ft.FlowSeries(t=a[:, 0], dt=a[:, 1], flow=a[:, 2:4], quality=quality)
        meta = {"source": "measurement events (fgnav.solvers.collect)", "collected": self.counts()}
        return ft.Flight(
            name=self.name, source="events", calib=self.calib, meta=meta, **streams
        ).check()
