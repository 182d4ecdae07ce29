"""Received MAVLink messages -> fgnav events, on the autopilot's boot clock, every one counted.

:class:`Inbound` is the state the edge conversion needs across messages: the newest IMU time
(which is the "now" of the boot clock, for arrival times), the SLAM session derived from
``ODOMETRY.reset_counter`` (per sending system and component, and only from vision ODOMETRY:
the autopilot's own ODOMETRY, with its own counter, had started a new session at every pose),
and the counters of what was received, dropped and lost. The
conversions themselves are :mod:`fgnav.live.convert`.

Arrival time. An event's ``arrival`` is when it reached fgnav, expressed on the boot clock: the
newest IMU time seen when it was received, or its own stamp if later (an estimator uses an event
only from its arrival on: ``fgnav.datasets.events``). So a SLAM pose stamped at its image time ``t``
that arrives 100 ms later has ``arrival`` 100 ms after ``t``, measured by the IMU stream, never by
fgnav's wall clock.

Counter keys (``counts()``; written to ``summary.json`` by :mod:`fgnav.live.session`):

* ``messages``: per MAVLink message name, every message parsed (``BAD_DATA`` included);
* ``received``: per stream (``imu``, ``attitude``, ``range``, ``slam``, ``flow``), the messages
  of that stream, before any check;
* ``dropped``: ``"stream:reason"`` -> n, messages of a stream that did not become events
  (reasons: ``not_updated``, ``other_instance``, ``non_finite``, ``invalid_quaternion``,
  ``orientation``, ``out_of_sensor_limits``, ``invalid_signal``, ``estimator_type``,
  ``vio_echo``, ``no_valid_flow``, ``no_interval``, ``off_clock``: a stamp more than
  ``OFF_CLOCK_S`` from the newest IMU stamp, e.g. a bridge that stamps on the UNIX epoch, as
  MAVROS does; such a stamp once kept fgnav's "now" at 1.7e9 s and lost every pose);
* ``lost``: ``"sysid/compid"`` -> messages missing from the MAVLink sequence numbers.
"""

from __future__ import annotations

import time
from collections import Counter
from typing import Any

from fgnav.datasets.events import Event, ImuSample
from fgnav.live import convert
from fgnav.live.convert import Rejected

STREAM_OF_MESSAGE = {
    "HIGHRES_IMU": "imu",
    "ATTITUDE_QUATERNION": "attitude",
    "DISTANCE_SENSOR": "range",
    "ODOMETRY": "slam",
    "OPTICAL_FLOW_RAD": "flow",
}
"""The sensor stream each input message feeds."""

OFF_CLOCK_S = 5.0
"""A non-IMU stamp further than this from the newest IMU stamp is on another clock [s]."""


class SequenceCounter:
    """Messages lost per source, from MAVLink's 8-bit sequence numbers (as pymavlink's
    ``mavutil`` counts them: a gap of ``(seq - expected) mod 256``)."""

    def __init__(self) -> None:
        self._last: dict[tuple[int, int], int] = {}
        self.lost: Counter[str] = Counter()
        self.seen: Counter[str] = Counter()

    def add(self, sysid: int, compid: int, seq: int) -> int:
        """Record one message; returns how many were lost before it."""
        key = (int(sysid), int(compid))
        name = f"{key[0]}/{key[1]}"
        self.seen[name] += 1
        last = self._last.get(key)
        self._last[key] = int(seq)
        if last is None:
            return 0
        gap = (int(seq) - (last + 1)) % 256
        if gap:
            self.lost[name] += gap
        return gap


class Inbound:
    """Turns parsed messages into events (see the module docstring).

    Args:
        flow_pixels_per_rad: ``Calibration.flow_pixels_per_rad`` (flow events are in its units).
        imu_id: the ``HIGHRES_IMU.id`` used (others are dropped as ``imu:other_instance``).
    """

    def __init__(self, flow_pixels_per_rad: float = 1.0, imu_id: int = 0) -> None:
        self.flow_pixels_per_rad = float(flow_pixels_per_rad)
        self.imu_id = int(imu_id)
        self.newest_imu_t: float | None = None
        self.newest_stamp: float | None = None
        self.session = 0
        # (sysid, compid) -> (its last reset_counter, its session)
        self._slam_sources: dict[tuple[int, int], tuple[int, int]] = {}
        self._imu_wall: float | None = None  # monotonic wall time of the newest IMU stamp
        self.messages: Counter[str] = Counter()
        self.received: Counter[str] = Counter()
        self.dropped: Counter[str] = Counter()
        self.sequence = SequenceCounter()

    def _arrival(self, t: float) -> float:
        if self.newest_imu_t is None or t > self.newest_imu_t:
            return t
        return self.newest_imu_t

    def count(self, msg: Any) -> str:
        """Count a parsed message (type and sequence number); returns its type name."""
        name = msg.get_type()
        self.messages[name] += 1
        if name != "BAD_DATA":
            self.sequence.add(msg.get_srcSystem(), msg.get_srcComponent(), msg.get_seq())
        return name

    def event(self, msg: Any) -> Event | None:
        """The event of a sensor message (None for other messages and for dropped ones, which
        are counted). Call :meth:`count` first."""
        name = msg.get_type()
        stream = STREAM_OF_MESSAGE.get(name)
        if stream is None:
            return None
        if name == "ODOMETRY" and int(msg.estimator_type) == convert.MAV_ESTIMATOR_TYPE_VIO:
            self.dropped["slam:vio_echo"] += 1  # fgnav's own output, echoed back
            return None
        self.received[stream] += 1
        try:
            ev = self._convert(name, msg)
        except Rejected as e:
            self.dropped[e.reason] += 1
            return None
        if isinstance(ev, ImuSample):
            if self.newest_imu_t is None or ev.t > self.newest_imu_t:
                self.newest_imu_t = ev.t
                self._imu_wall = time.monotonic()
        elif self.newest_imu_t is not None and abs(ev.t - self.newest_imu_t) > OFF_CLOCK_S:
            self.dropped[f"{stream}:off_clock"] += 1
            return None
        if self.newest_stamp is None or ev.t > self.newest_stamp:
            self.newest_stamp = ev.t
        return ev

    def _convert(self, name: str, msg: Any) -> Event:
        if name == "HIGHRES_IMU":
            if int(getattr(msg, "id", 0)) != self.imu_id:
                raise Rejected("imu:other_instance")
            ev = convert.imu_from_highres(msg)
        elif name == "ATTITUDE_QUATERNION":
            ev = convert.attitude_from_quaternion(msg)
        elif name == "DISTANCE_SENSOR":
            ev = convert.range_from_distance_sensor(msg)
        elif name == "ODOMETRY":
            ev = convert.slam_from_odometry(msg, 0)  # checked before its session counts
            ev = ev._replace(session=self._slam_session(_source(msg), int(msg.reset_counter)))
        else:
            ev = convert.flow_from_rad(msg, self.flow_pixels_per_rad)
        return ev._replace(arrival=self._arrival(ev.t))

    def _slam_session(self, source: tuple[int, int], reset_counter: int) -> int:
        """The session of a SLAM source's pose: a new source, or a changed ``reset_counter``
        of one (a rise, or its wrap past 255), starts a new one."""
        last = self._slam_sources.get(source)
        if last is not None and last[0] == reset_counter:
            return last[1]
        if self._slam_sources:
            self.session += 1
        self._slam_sources[source] = (reset_counter, self.session)
        return self.session

    def clock_ns(self) -> int | None:
        """The boot clock's "now" as fgnav knows it [ns], or None: the newest IMU stamp plus
        the wall time since it arrived (else the newest stamp received). Answered with the
        stamp alone, PX4's offset took the sample's age (up to 20 ms at 50 Hz)."""
        if self.newest_imu_t is not None and self._imu_wall is not None:
            now = self.newest_imu_t + (time.monotonic() - self._imu_wall)
        elif self.newest_stamp is not None:
            now = self.newest_stamp
        else:
            return None
        return int(round(now * convert.NS_PER_S))

    def counts(self) -> dict[str, Any]:
        """The counters (see the module docstring), as plain dicts."""
        return {
            "messages": dict(sorted(self.messages.items())),
            "received": dict(sorted(self.received.items())),
            "dropped": dict(sorted(self.dropped.items())),
            "lost": dict(sorted(self.sequence.lost.items())),
            "slam_sessions": self.session + 1 if self._slam_sources else 0,
        }


def _source(msg: Any) -> tuple[int, int]:
    """(sysid, compid) of a parsed message ((0, 0) for one built by hand, never sent)."""
    try:
        return int(msg.get_srcSystem()), int(msg.get_srcComponent())
    except (AttributeError, TypeError):
        return 0, 0
