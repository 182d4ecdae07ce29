"""The batch smoother's input from measurement events: :class:`EventCollector`.

DESIGN.md sec. 7: "the batch smoother collects them [the events] and solves once". The collector
is fed the same events as the online smoother (a replay, or a live link: ``fgnav live --batch``)
and turns what it kept into a :class:`~fgnav.datasets.types.Flight` for
:func:`fgnav.methods.run_batch` (through :func:`fgnav.datasets.events.flight_from_events`), which
then decides with the whole flight in hand (keyframes on the SLAM times, the accelerometer check
on every keyframe, ...).

Kept: IMU samples, attitude samples, range and yaw readings, SLAM poses (their arrival minus
their capture time becomes ``SlamSeries.latency``, at least 0) and optical-flow samples. Not
kept, counted: image frames (``images:not-collected``; a live link carries none), SLAM poses of a
negative session (``slam:tracking-lost``), samples with a non-finite value
(``<stream>:non-finite``). Order: each stream is sorted by its capture time, a sample with the
time of one kept before it in that stream is dropped (``<stream>:duplicate-time``). Quaternions
that are not unit (a link's float32) are normalised. Nothing else is judged here: the flight's
checks (``Flight.check``) and the batch smoother's own gates apply as to a file.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import STREAM_OF_EVENT, ImageFrame, SlamPose, flight_from_events
from fgnav.datasets.types import Calibration, Flight


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

    def __init__(self, calib: Calibration, name: str = "events") -> None:
        self.calib = calib
        self.name = name
        self._events: dict[str, list[Any]] = {}
        self.dropped: dict[str, int] = {}

    def _drop(self, key: str) -> None:
        self.dropped[key] = self.dropped.get(key, 0) + 1

    def feed(self, ev: Any) -> None:
        """Keep one event (any order; see the module docstring for what is kept)."""
        if isinstance(ev, ImageFrame):
            self._drop("images:not-collected")
            return
        stream = STREAM_OF_EVENT.get(type(ev))
        if stream is None:
            return
        if isinstance(ev, SlamPose) and ev.session < 0:
            self._drop("slam:tracking-lost")
            return
        # Every field of a kept event is a number or an array of them (quality -1: unknown).
        if not all(np.all(np.isfinite(v)) for v in ev):
            self._drop(f"{stream}:non-finite")
            return
        self._events.setdefault(stream, []).append(ev)

    def counts(self) -> dict[str, Any]:
        """Samples kept per stream and dropped by ``stream:reason``."""
        return {
            "kept": {s: len(e) for s, e in sorted(self._events.items())},
            "dropped": dict(sorted(self.dropped.items())),
        }

    def _in_order(self, stream: str) -> list[Any]:
        """The stream's events by capture time, a repeated time dropped (counted)."""
        evs = sorted(self._events[stream], key=lambda e: e.t)
        kept = [e for i, e in enumerate(evs) if i == 0 or e.t != evs[i - 1].t]
        if len(kept) < len(evs):
            self.dropped[f"{stream}:duplicate-time"] = len(evs) - len(kept)
        return kept

    def flight(self) -> Flight:
        """The flight of every event kept so far (checked); an error naming what is missing
        when no IMU sample was kept."""
        if not self._events.get("imu"):
            raise FlightDataError(f"{self.name}: no IMU sample collected: nothing to solve")
        f = flight_from_events(self.calib, self.name, {s: self._in_order(s) for s in self._events})
        fixed: dict[str, Any] = {}
        if f.attitude is not None:
            q = _unit(f.attitude.world_q_body_wxyz)
            fixed["attitude"] = dataclasses.replace(f.attitude, world_q_body_wxyz=q)
        if f.slam is not None:
            fixed["slam"] = dataclasses.replace(
                f.slam,
                slam_q_cam_wxyz=_unit(f.slam.slam_q_cam_wxyz),
                latency=np.maximum(f.slam.latency, 0.0),
            )
        meta = {"source": "measurement events (fgnav.solvers.collect)", "collected": self.counts()}
        return dataclasses.replace(f, source="events", meta=meta, **fixed).check()
