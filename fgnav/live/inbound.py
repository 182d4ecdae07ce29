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

One vehicle. fgnav follows one MAVLink system: the first whose ``HIGHRES_IMU`` (of ``imu_id``)
it takes, or the ``source_system`` given (``[live] source_system``). Its components all count
(the SLAM bridge is a component of the vehicle, e.g. 191); sensor messages of any other system
(a second vehicle on the same link) are dropped as ``<stream>:other_system`` (a warning once
per system), its ``TIMESYNC`` requests are not answered, and ``HIGHRES_IMU`` of another
component of the system is ``imu:other_component``.

The clock. The boot clock's "now" is the newest IMU stamp the clock took: the IMU stamps as the
smoother's time rules take them (``fgnav.solvers.online``): the next sample within
``MAX_IMU_GAP_S``; a stamp that jumps either way (or after a gap) is a candidate, taken when the
next sample continues from it (a reboot: ``clock_restarts``; the link's clock goes back with
it) and else ignored (``clock_outliers``: one sample stamped an hour ahead had held "now" there,
every other stream off the clock). Everything is passed on to the estimator, whose own rules
count the outlier.

Counter keys (``counts()``; written to ``summary.json`` by :mod:`fgnav.live.session`):

* ``messages``: per MAVLink message name, every message parsed (``BAD_DATA`` included);
* ``received``: per stream (``imu``, ``attitude``, ``range``, ``slam``, ``flow``), the messages
  of that stream, before any check (fgnav's own ODOMETRY echoed back included);
* ``dropped``: ``"stream:reason"`` -> n, messages of a stream that did not become events
  (reasons: ``not_updated``, ``other_instance``, ``other_component``, ``other_system``,
  ``duplicate`` (the number and bytes of a recent message: a datagram repeated), ``non_finite``,
  ``invalid_quaternion``, ``orientation``, ``out_of_sensor_limits``, ``zero`` (a 0 cm range:
  no reading), ``invalid_signal``, ``estimator_type``, ``failed`` (``ODOMETRY.quality`` -1:
  the SLAM says it failed), ``stale_session`` (a late pose of the SLAM's previous
  ``reset_counter``), ``vio_echo``, ``no_valid_flow``, ``no_interval``, ``off_clock``: a stamp
  more than ``OFF_CLOCK_S`` from the newest IMU stamp, e.g. a bridge that stamps on the UNIX
  epoch, as MAVROS does; such a stamp once kept fgnav's "now" at 1.7e9 s and lost every pose);
* ``lost``: ``"sysid/compid"`` -> messages missing from the MAVLink sequence numbers (of every
  message with a header, those of other dialects, ``UNKNOWN_<id>``, by their raw header);
  ``duplicate`` and ``reordered``: the same, messages repeated or late
  (:class:`SequenceCounter`);
* ``slam_sessions``: SLAM sessions started; ``source``: ``"sysid/compid"`` followed;
  ``clock_restarts``, ``clock_outliers``: see "The clock".
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, deque
from typing import Any

from fgnav.datasets.events import Event, ImuSample
from fgnav.live import convert
from fgnav.live.convert import Rejected

log = logging.getLogger(__name__)

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

CLOCK_JUMP_S = 1.0
"""An IMU stamp further back than this is a clock jump (the smoother's ``clock_jump_s``) [s]."""

MAX_IMU_GAP_S = 0.5
"""An IMU stamp further ahead than this is a gap (the smoother's ``max_imu_gap_s``) [s]."""

STALE_RESET_BACK = 16
"""A SLAM ``reset_counter`` at most this far behind its source's (mod 256) soon after the change
is a late pose of the old map, not a new session."""

STALE_RESET_S = 2.0
"""How long after a ``reset_counter`` change a pose of the old counter is late (boot clock) [s]."""

INT64_MAX_NS = 2**63 - 1


REORDER_WINDOW = 16
"""A sequence number at most this far behind the newest of its source, missing from a gap
counted there, is a late (reordered) message: UDP may reorder datagrams."""

RECENT_MESSAGES = 64
"""Messages remembered per source (sequence number and bytes) to tell a repeated one: fewer than
256, so that a number come round again is not taken for a repeat."""


class _Source:
    """What :class:`SequenceCounter` remembers of one source."""

    __slots__ = ("newest", "recent", "order", "missing")

    def __init__(self, seq: int, data: bytes | None) -> None:
        self.newest = seq
        self.recent: set[tuple[int, bytes | None]] = {(seq, data)}
        self.order: deque[tuple[int, bytes | None]] = deque([(seq, data)])
        self.missing: set[int] = set()  # numbers of counted gaps, within the window

    def remember(self, seq: int, data: bytes | None) -> None:
        self.recent.add((seq, data))
        self.order.append((seq, data))
        if len(self.order) > RECENT_MESSAGES:
            self.recent.discard(self.order.popleft())


class SequenceCounter:
    """Messages lost per source, from MAVLink's 8-bit sequence numbers (as pymavlink's
    ``mavutil`` counts them: a gap of ``(seq - expected) mod 256``), with two exceptions:

    * ``duplicate``: a message whose number and bytes match one of the source's last
      :data:`RECENT_MESSAGES` (a repeated datagram: PX4 packs several messages in one, so all
      of them come again, not only the newest; it had counted 255 lost). Identical bytes are
      required: a sender that does not advance its number but sends other messages (pymavlink's
      ``pack`` alone) loses nothing.
    * ``reordered``: a number at most :data:`REORDER_WINDOW` behind the newest that a counted
      gap left missing (a late datagram): delivered, and its own loss taken back.

    Any other number (behind the newest, not missing, other bytes) opens a new gap of
    ``(seq - newest - 1) mod 256``, as ``mavutil`` counts it: an outage of 240-255 messages, or
    the sender's restart."""

    def __init__(self) -> None:
        self._sources: dict[tuple[int, int], _Source] = {}
        self.lost: Counter[str] = Counter()
        self.seen: Counter[str] = Counter()
        self.duplicate: Counter[str] = Counter()
        self.reordered: Counter[str] = Counter()

    def add(self, sysid: int, compid: int, seq: int, data: bytes | None = None) -> int:
        """Record one message (``data``: its bytes, to tell a duplicate); returns how many were
        lost before it (-1: a duplicate, to drop; -2: a reordered message)."""
        key = (int(sysid), int(compid))
        seq = int(seq) % 256
        name = f"{key[0]}/{key[1]}"
        self.seen[name] += 1
        src = self._sources.get(key)
        if src is None:
            self._sources[key] = _Source(seq, data)
            return 0
        if (seq, data) in src.recent:
            self.duplicate[name] += 1
            return -1
        src.remember(seq, data)
        if seq == src.newest:
            return 0  # another message with the same number
        if seq in src.missing:
            src.missing.discard(seq)
            self.reordered[name] += 1
            self.lost[name] -= 1  # counted lost when the gap opened: it came late
            if self.lost[name] <= 0:
                del self.lost[name]
            return -2
        gap = (seq - src.newest - 1) % 256
        src.newest = seq
        src.missing = {s for s in src.missing if (seq - s) % 256 <= REORDER_WINDOW}
        src.missing.update((seq - k) % 256 for k in range(1, min(gap, REORDER_WINDOW) + 1))
        if gap:
            self.lost[name] += gap
        return gap


def header_ids(msg: Any) -> tuple[int, int, int] | None:
    """(sysid, compid, seq) of a parsed message, from its raw header for a message of another
    dialect (pymavlink's ``UNKNOWN_<id>`` reports source 0/0 and sequence 0), None for
    ``BAD_DATA``."""
    name = msg.get_type()
    if name == "BAD_DATA":
        return None
    if name.startswith("UNKNOWN_"):
        buf = bytes(getattr(msg, "data", b"") or b"")
        if len(buf) >= 7 and buf[0] == 0xFD:  # MAVLink 2: FD len incompat compat seq sys comp
            return buf[5], buf[6], buf[4]
        if len(buf) >= 5 and buf[0] == 0xFE:  # MAVLink 1: FE len seq sys comp
            return buf[3], buf[4], buf[2]
        return None
    return int(msg.get_srcSystem()), int(msg.get_srcComponent()), int(msg.get_seq())


class Inbound:
    """Turns parsed messages into events (see the module docstring).

    Args:
        flow_pixels_per_rad: ``Calibration.flow_pixels_per_rad`` (flow events are in its units).
        imu_id: the ``HIGHRES_IMU.id`` used (others are dropped as ``imu:other_instance``).
        source_system: the vehicle's MAVLink system id; 0: the first system to send
            ``HIGHRES_IMU`` (see the module docstring, "One vehicle").
    """

    def __init__(
        self, flow_pixels_per_rad: float = 1.0, imu_id: int = 0, source_system: int = 0
    ) -> None:
        self.flow_pixels_per_rad = float(flow_pixels_per_rad)
        self.imu_id = int(imu_id)
        self.source_system = int(source_system)
        self.source: tuple[int, int] | None = None  # (sysid, compid) of the vehicle's IMU
        self._warned_systems: set[int] = set()
        self.newest_imu_t: float | None = None
        self.newest_stamp: float | None = None
        self.session = 0
        # (sysid, compid) -> (its last reset_counter, its session, boot time it began)
        self._slam_sources: dict[tuple[int, int], tuple[int, int, float]] = {}
        self._imu_wall: float | None = None  # monotonic wall time of the newest IMU stamp
        self._imu_candidate: float | None = None  # an IMU stamp off the clock, not yet confirmed
        self.clock_restarts = 0
        """Confirmed backward jumps of the IMU clock (an autopilot reboot)."""
        self.clock_outliers = 0
        """IMU stamps off the clock that the next sample did not confirm."""
        self.imu_on_clock = False
        """Whether the last IMU event became the clock's newest sample."""
        self._duplicate = False
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
        ids = header_ids(msg)
        self._duplicate = ids is not None and self.sequence.add(*ids, _bytes(msg)) == -1
        return name

    def from_vehicle(self, msg: Any, what: str) -> bool:
        """Whether ``msg`` comes from the vehicle fgnav follows; else it is counted as
        ``<what>:other_system`` (and warned about once per system)."""
        sysid = _source(msg)[0]
        locked = self.source[0] if self.source is not None else self.source_system
        if not locked or sysid == locked:
            return True
        self.dropped[f"{what}:other_system"] += 1
        if sysid not in self._warned_systems:
            self._warned_systems.add(sysid)
            log.warning(
                "MAVLink system %d ignored: fgnav follows system %d (%s; [live] source_system "
                "chooses); its messages are counted as <stream>:other_system",
                sysid,
                locked,
                "the first to send HIGHRES_IMU" if not self.source_system else "source_system",
            )
        return False

    def event(self, msg: Any) -> Event | None:
        """The event of a sensor message (None for other messages and for dropped ones, which
        are counted). Call :meth:`count` first."""
        name = msg.get_type()
        stream = STREAM_OF_MESSAGE.get(name)
        if stream is None:
            return None
        self.received[stream] += 1
        if name == "ODOMETRY" and int(msg.estimator_type) == convert.MAV_ESTIMATOR_TYPE_VIO:
            self.dropped["slam:vio_echo"] += 1  # fgnav's own output, echoed back
            return None
        if not self.from_vehicle(msg, stream):
            return None
        if self._duplicate:  # the same message again (a repeated datagram)
            self.dropped[f"{stream}:duplicate"] += 1
            return None
        try:
            ev = self._convert(name, msg)
        except Rejected as e:
            self.dropped[e.reason] += 1
            return None
        if isinstance(ev, ImuSample):
            if self.source is None:
                self.source = _source(msg)
                log.info("MAVLink: following system %d (IMU of component %d)", *self.source)
            self._imu_clock(ev.t)
        elif self.newest_imu_t is not None and self._off_clock(ev.t):
            self.dropped[f"{stream}:off_clock"] += 1
            return None
        if self.newest_stamp is None or ev.t > self.newest_stamp:
            self.newest_stamp = ev.t
        return ev._replace(arrival=self._arrival(ev.t))

    def _off_clock(self, t: float) -> bool:
        far = abs(t - self.newest_imu_t) > OFF_CLOCK_S
        if far and self._imu_candidate is not None:  # the clock may be restarting
            return abs(t - self._imu_candidate) > OFF_CLOCK_S
        return far

    def _imu_clock(self, t: float) -> None:
        """The link's clock follows the IMU stamps as the smoother's time rules take them
        (``fgnav.solvers.online``): the next sample within ``MAX_IMU_GAP_S``, a sample out of
        order by less than ``CLOCK_JUMP_S`` leaves it, and any other stamp (a jump either way,
        a gap) is a candidate that the next sample confirms (it continues from it: a reboot,
        or the IMU back after a gap) or not (it continues the clock: the stamp was an outlier,
        e.g. one sample stamped an hour ahead)."""
        self.imu_on_clock = False
        last = self.newest_imu_t
        if last is None or 0.0 < t - last <= MAX_IMU_GAP_S:
            if self._imu_candidate is not None:
                self.clock_outliers += 1
            self._take_imu(t)
            return
        if t <= last and last - t <= CLOCK_JUMP_S:
            return  # out of order or repeated: the estimator counts it
        cand = self._imu_candidate
        if cand is not None and 0.0 < t - cand <= MAX_IMU_GAP_S:
            if t < last:
                self.clock_restarts += 1
                log.warning(
                    "MAVLink: the IMU clock went back %.3f s (%.3f -> %.3f s): a restart",
                    last - t,
                    last,
                    t,
                )
            self._take_imu(t)
            return
        if cand is not None:
            self.clock_outliers += 1
        self._imu_candidate = t

    def _take_imu(self, t: float) -> None:
        self.newest_imu_t = t
        self._imu_wall = time.monotonic()
        self._imu_candidate = None
        self.imu_on_clock = True

    def _convert(self, name: str, msg: Any) -> Event:
        if name == "HIGHRES_IMU":
            if int(getattr(msg, "id", 0)) != self.imu_id:
                raise Rejected("imu:other_instance")
            if self.source is not None and _source(msg)[1] != self.source[1]:
                raise Rejected("imu:other_component")
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
        return ev

    def _slam_session(self, source: tuple[int, int], reset_counter: int) -> int:
        """The session of a SLAM source's pose: a new source, or a changed ``reset_counter``
        of one (a rise, or its wrap past 255), starts a new one; a counter at most
        ``STALE_RESET_BACK`` behind the source's (mod 256) within ``STALE_RESET_S`` of its
        change is a pose of the old map that came late: dropped (``slam:stale_session``). After
        a clock restart (``now`` before the change) a lower counter is a new map."""
        now = self.newest_imu_t if self.newest_imu_t is not None else -math.inf
        last = self._slam_sources.get(source)
        if last is not None:
            if last[0] == reset_counter:
                return last[1]
            back = (last[0] - reset_counter) % 256
            if 1 <= back <= STALE_RESET_BACK and 0.0 <= now - last[2] <= STALE_RESET_S:
                raise Rejected(
                    "slam:stale_session", f"reset_counter {reset_counter} after {last[0]}"
                )
        if self._slam_sources:
            self.session += 1
        self._slam_sources[source] = (reset_counter, self.session, now)
        return self.session

    def clock_ns(self) -> int | None:
        """The boot clock's "now" as fgnav knows it [ns], or None: the newest IMU stamp plus
        the wall time since it arrived (else the newest stamp received). Answered with the
        stamp alone, PX4's offset took the sample's age (up to 20 ms at 50 Hz). None too when
        it does not fit TIMESYNC's int64 nanoseconds."""
        if self.newest_imu_t is not None and self._imu_wall is not None:
            now = self.newest_imu_t + (time.monotonic() - self._imu_wall)
        elif self.newest_stamp is not None:
            now = self.newest_stamp
        else:
            return None
        if not (math.isfinite(now) and 0.0 < now < INT64_MAX_NS / convert.NS_PER_S):
            return None
        ns = int(round(now * convert.NS_PER_S))
        return ns if 0 < ns <= INT64_MAX_NS else None

    def counts(self) -> dict[str, Any]:
        """The counters (see the module docstring), as plain dicts."""
        return {
            "messages": dict(sorted(self.messages.items())),
            "received": dict(sorted(self.received.items())),
            "dropped": dict(sorted(self.dropped.items())),
            "lost": dict(sorted(self.sequence.lost.items())),
            "duplicate": dict(sorted(self.sequence.duplicate.items())),
            "reordered": dict(sorted(self.sequence.reordered.items())),
            "slam_sessions": self.session + 1 if self._slam_sources else 0,
            "source": None if self.source is None else f"{self.source[0]}/{self.source[1]}",
            "clock_restarts": self.clock_restarts,
            "clock_outliers": self.clock_outliers,
        }


def _bytes(msg: Any) -> bytes | None:
    """The bytes a parsed message came in (None for one built by hand)."""
    try:
        buf = msg.get_msgbuf()
    except (AttributeError, TypeError):
        return None
    return bytes(buf) if buf else None


def _source(msg: Any) -> tuple[int, int]:
    """(sysid, compid) of a parsed message ((0, 0) for one built by hand, never sent)."""
    try:
        return int(msg.get_srcSystem()), int(msg.get_srcComponent())
    except (AttributeError, TypeError):
        return 0, 0
