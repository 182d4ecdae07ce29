"""``fgnav replay``: a stand-in autopilot that sends a flight as MAVLink messages.

The flight's events, in arrival order (:func:`fgnav.datasets.events.replay_flight`, so each
stream's latency, e.g. the SLAM poses', is applied), are sent as the messages ``fgnav live``
listens for (:mod:`fgnav.live.convert`): ``HIGHRES_IMU``, ``ATTITUDE_QUATERNION`` (rates from the
newest IMU sample), ``DISTANCE_SENSOR`` (downward, rounded to 1 cm), ``ODOMETRY`` with
``estimator_type = VISION`` (the SLAM pose, ``reset_counter`` = its session id) and
``OPTICAL_FLOW_RAD``. Yaw and images have no message here and are not sent.

Clock. Stamps are on a boot clock that starts at the flight's first sample of the streams sent:
``t_boot = t_flight - boot_offset_s`` (:attr:`ReplayResult.boot_offset_s`, printed). Each
message leaves when the flight's clock reaches its arrival time, paced on the wall clock at
``speed`` times real time (0: as fast as possible).

The autopilot's side of the link: a ``HEARTBEAT`` at ``heartbeat_hz`` (the sensors come from
system 1, component 1; SLAM poses from component 191, as a companion computer's SLAM bridge
would send them); it waits for the peer's first ``HEARTBEAT`` (``wait_peer_s``) before sending
the flight; it sends ``TIMESYNC`` requests at ``timesync_hz`` (``ts1`` = its boot clock now) and
answers the peer's. Every ``ODOMETRY`` the peer sends back (``estimator_type = VIO``) is
recorded, converted back to fgnav's frames and the flight's clock
(:func:`fgnav.live.convert.pose_from_odometry`): :attr:`ReplayResult.odometry`.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fgnav.datasets.events import (
    STREAM_OF_EVENT,
    AttitudeSample,
    FlowSample,
    ImuSample,
    RangeReading,
    SlamPose,
    replay_flight,
)
from fgnav.datasets.types import Flight, Trajectory
from fgnav.live import convert
from fgnav.live.convert import Rejected
from fgnav.live.inbound import SequenceCounter
from fgnav.live.link import LinkError, Parsers, UdpLink, new_mavlink, pack

log = logging.getLogger(__name__)

SENDABLE_STREAMS = ("imu", "attitude", "range", "slam", "flow")
"""Streams that have a MAVLink message here."""

MAV_TYPE_QUADROTOR = 2
MAV_AUTOPILOT_GENERIC = 0
MAV_STATE_ACTIVE = 4
MAV_COMP_ID_AUTOPILOT1 = 1
MAV_COMP_ID_ONBOARD_COMPUTER = 191

LINGER_MAX_S = 60.0
"""Longest wait for ODOMETRY after the last message [wall s]."""

PEER_STOPPED_S = 2.0
"""ODOMETRY that stopped more than this before the flight's end (and a tenth of it) is noted."""

SLEEP_QUANTUM_S = 0.002
"""Longest single sleep while pacing, so timers and replies are serviced in between."""


@dataclass
class ReplayOptions:
    """Options of the stand-in autopilot.

    Attributes:
        speed: times real time (0: as fast as possible).
        streams: streams to send (of :data:`SENDABLE_STREAMS`; the flight's others are skipped).
        wait_peer_s: wait up to this long [wall s] for the peer's HEARTBEAT before sending (0:
            send at once).
        linger_s: after the last message, keep listening for ODOMETRY until none has come for
            this long [wall s] (at most :data:`LINGER_MAX_S`), so a peer still working through
            its backlog is heard out.
        heartbeat_hz, timesync_hz: rates of HEARTBEAT and TIMESYNC requests [Hz, wall clock];
            0 turns TIMESYNC requests off.
        system_id: MAVLink system id of the autopilot.
    """

    speed: float = 1.0
    streams: tuple[str, ...] = SENDABLE_STREAMS
    wait_peer_s: float = 30.0
    linger_s: float = 2.0
    heartbeat_hz: float = 1.0
    timesync_hz: float = 1.0
    system_id: int = 1


@dataclass
class ReplayResult:
    """What the stand-in autopilot sent and received.

    Attributes:
        boot_offset_s: ``t_flight - t_boot`` [s] (the flight time of boot-clock 0).
        sent: messages sent, by name.
        flight_s: flight time spanned by the messages sent [s]; wall_s: wall time [s].
        odometry: the ODOMETRY received back, in fgnav's frames on the flight's clock (None
            when none came).
        received: messages received, by name; lost: by ``"sysid/compid"`` (sequence numbers).
        odometry_rejected: ODOMETRY received that could not be converted back, by reason.
        timesync: replies received and the median ``tc1 - ts1`` [ms] (how far behind the
            peer's clock was when it answered).
        peer_heartbeat: whether the peer's HEARTBEAT was heard.
        send_errors: packets the peer's host refused (nobody listening yet, or any more).
        flight_start, flight_end: flight times [s] of the first and last message sent.
        peer_quiet_s: wall seconds the peer had been silent (no message at all) when the last
            message was sent (None: never heard).
    """

    boot_offset_s: float
    sent: dict[str, int]
    flight_s: float
    wall_s: float
    odometry: Trajectory | None
    received: dict[str, int]
    lost: dict[str, int]
    odometry_rejected: dict[str, int] = field(default_factory=dict)
    timesync: dict[str, Any] = field(default_factory=dict)
    peer_heartbeat: bool = False
    send_errors: int = 0
    flight_start: float = math.nan
    flight_end: float = math.nan
    peer_quiet_s: float | None = None

    def peer_stopped(self) -> str | None:
        """A one-line note when the peer's ODOMETRY stopped well before the flight's end (the
        peer died or stalled: the record and its score cover only a part), else None. Well
        before: more than :data:`PEER_STOPPED_S` and a tenth of the flight."""
        span = self.flight_end - self.flight_start
        if self.odometry is None or not span > 0:
            return None
        t_last = float(self.odometry.t[-1])
        behind = self.flight_end - t_last
        if not behind > max(PEER_STOPPED_S, 0.1 * span):
            return None
        quiet = ""
        if self.peer_quiet_s is not None and self.peer_quiet_s > 1.0:
            quiet = f"; nothing heard from it in the last {self.peer_quiet_s:.1f} s wall"
        return (
            f"the peer's ODOMETRY stopped {behind:.1f} s of flight before the end (the last at "
            f"{t_last - self.flight_start:.1f} s of {span:.1f} s){quiet}: the record covers "
            f"{self.covered_fraction():.0%} of the flight"
        )

    def covered_fraction(self) -> float:
        """The part of the flight's span up to the last ODOMETRY received (0 without one)."""
        span = self.flight_end - self.flight_start
        if self.odometry is None or not span > 0:
            return 0.0
        return float(min(max((self.odometry.t[-1] - self.flight_start) / span, 0.0), 1.0))

    @property
    def speed(self) -> float:
        """Achieved times real time."""
        return self.flight_s / self.wall_s if self.wall_s > 0 else float("inf")


def boot_offset(flight: Flight, streams: Iterable[str]) -> float:
    """Flight time of the first sample of the streams sent: boot-clock 0."""
    firsts = [
        float(getattr(flight, s).t[0])
        for s in streams
        if getattr(flight, s, None) is not None and len(getattr(flight, s))
    ]
    if not firsts:
        raise LinkError(f"{flight.name}: none of the streams {list(streams)} to send")
    return min(firsts)


class _Recorder:
    """The autopilot side's receive path (drained on the sending thread between messages)."""

    def __init__(self, link: UdpLink, mav: Any, offset: float) -> None:
        self.link, self.mav, self.offset = link, mav, offset
        self.parsers = Parsers()
        self.seq = SequenceCounter()
        self.received: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.rows: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []
        self.timesync_ms: list[float] = []
        self.peer_heartbeat = False
        self.boot_now_s = 0.0
        self.last_odometry = -math.inf  # wall clock (monotonic) of the newest ODOMETRY
        self.last_heard = -math.inf  # wall clock (monotonic) of the peer's newest message

    def drain(self) -> None:
        while True:
            item = self.link.get(timeout=0.0) if not self.link.queue.empty() else None
            if item is None:
                return
            data, peer, _ = item
            for msg in self.parsers.parse(data, peer):
                self._handle(msg, peer)

    def _handle(self, msg: Any, peer) -> None:
        name = msg.get_type()
        self.received[name] += 1
        if name == "BAD_DATA":
            return
        self.last_heard = time.monotonic()
        self.seq.add(msg.get_srcSystem(), msg.get_srcComponent(), msg.get_seq())
        if name == "HEARTBEAT":
            self.peer_heartbeat = True
        elif name == "TIMESYNC":
            if msg.tc1 == 0:  # the peer asks: answer with the autopilot's boot clock
                now_ns = int(round(self.boot_now_s * convert.NS_PER_S))
                self.link.send(pack(self.mav, self.mav.timesync_encode(now_ns, msg.ts1)))
            else:
                self.timesync_ms.append((msg.tc1 - msg.ts1) / 1e6)
        elif name == "ODOMETRY" and int(msg.estimator_type) == convert.MAV_ESTIMATOR_TYPE_VIO:
            try:
                t, p, q, v = convert.pose_from_odometry(msg)
            except Rejected as e:
                self.rejected[e.reason] += 1
                return
            self.rows.append((t + self.offset, p, q, v))
            self.last_odometry = time.monotonic()

    def trajectory(self) -> Trajectory | None:
        if not self.rows:
            return None
        rows = sorted(self.rows, key=lambda r: r[0])
        keep = [rows[0]]
        for r in rows[1:]:
            if r[0] > keep[-1][0]:
                keep.append(r)
            else:
                self.rejected["odometry:repeated_time"] += 1
        return Trajectory(
            t=np.array([r[0] for r in keep]),
            world_t_body=np.array([r[1] for r in keep]),
            world_q_body_wxyz=np.array([r[2] for r in keep]),
            world_v_body=np.array([r[3] for r in keep]),
        )


class StandInAutopilot:
    """Sends a flight over a ``udpout`` link (see the module docstring)."""

    def __init__(self, flight: Flight, link: UdpLink, options: ReplayOptions | None = None):
        self.flight = flight
        self.link = link
        self.options = options or ReplayOptions()
        bad = [s for s in self.options.streams if s not in SENDABLE_STREAMS]
        if bad:
            raise LinkError(f"cannot send stream(s) {bad}; sendable: {list(SENDABLE_STREAMS)}")
        self.streams = tuple(s for s in self.options.streams if getattr(flight, s) is not None)
        if not self.streams:
            has = [s for s in SENDABLE_STREAMS if getattr(flight, s) is not None]
            raise LinkError(
                f"{flight.name}: has none of the streams {list(self.options.streams)} to send "
                f"(it has {has})"
            )
        self.offset = boot_offset(flight, self.streams)
        sysid = self.options.system_id
        self.mav = new_mavlink(sysid, MAV_COMP_ID_AUTOPILOT1)
        self.slam_mav = new_mavlink(sysid, MAV_COMP_ID_ONBOARD_COMPUTER)
        self.sent: Counter[str] = Counter()
        self._rec = _Recorder(link, self.mav, self.offset)
        self._last_omega: np.ndarray | None = None
        self._next_heartbeat = 0.0
        self._next_timesync = 0.0

    def _send(self, msg: Any, mav: Any | None = None) -> None:
        self.link.send(pack(mav or self.mav, msg))
        self.sent[msg.get_type()] += 1

    def _service(self, now: float) -> None:
        """Timers (wall clock) and the receive path."""
        o = self.options
        if o.heartbeat_hz > 0 and now >= self._next_heartbeat:
            self._send(
                self.mav.heartbeat_encode(
                    MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_GENERIC, 0, 0, MAV_STATE_ACTIVE
                )
            )
            self._next_heartbeat = now + 1.0 / o.heartbeat_hz
        if o.timesync_hz > 0 and now >= self._next_timesync and self._rec.peer_heartbeat:
            ts1 = int(round(self._rec.boot_now_s * convert.NS_PER_S))
            if ts1 > 0:
                self._send(self.mav.timesync_encode(0, ts1))
            self._next_timesync = now + 1.0 / o.timesync_hz
        self._rec.drain()

    def _message(self, ev: Any) -> tuple[Any, Any]:
        off, c = self.offset, self.flight.calib
        m = self.mav
        if isinstance(ev, ImuSample):
            self._last_omega = ev.body_omega
            return m.highres_imu_encode(**convert.highres_imu_fields(ev, off)), m
        if isinstance(ev, AttitudeSample):
            f = convert.attitude_quaternion_fields(ev, off, self._last_omega)
            return m.attitude_quaternion_encode(**f), m
        if isinstance(ev, RangeReading):
            f = convert.distance_sensor_fields(ev, off, c.range_min, c.range_max)
            return m.distance_sensor_encode(**f), m
        if isinstance(ev, SlamPose):
            f = convert.vision_odometry_fields(ev, off, reset_counter=ev.session)
            return self.slam_mav.odometry_encode(**f), self.slam_mav
        if isinstance(ev, FlowSample):
            f = convert.optical_flow_rad_fields(ev, off, c.flow_pixels_per_rad)
            return m.optical_flow_rad_encode(**f), m
        raise LinkError(f"no MAVLink message for {STREAM_OF_EVENT[type(ev)]} events")

    def _wait_for_peer(self) -> None:
        o = self.options
        if o.wait_peer_s <= 0:
            return
        t_end = time.monotonic() + o.wait_peer_s
        while not self._rec.peer_heartbeat:
            now = time.monotonic()
            if now >= t_end:
                raise LinkError(
                    f"no HEARTBEAT from {self.link.address} within {o.wait_peer_s:g} s: is "
                    f"`fgnav live --mavlink udpin:{self.link.address.host}:"
                    f"{self.link.address.port}` running?"
                )
            self._service(now)
            time.sleep(0.01)

    def run(self) -> ReplayResult:
        o = self.options
        link = self.link
        link.start()
        a_first = a_last = None
        try:
            self._wait_for_peer()
            t_start = time.perf_counter()
            n = 0
            for ev in replay_flight(self.flight, self.streams):
                if a_first is None:
                    a_first = ev.arrival
                a_last = ev.arrival
                self._rec.boot_now_s = ev.arrival - self.offset
                if o.speed > 0:
                    target = t_start + (ev.arrival - a_first) / o.speed
                    while True:
                        now = time.perf_counter()
                        if now >= target:
                            break
                        self._service(time.monotonic())
                        time.sleep(min(target - now, SLEEP_QUANTUM_S))
                n += 1
                if n % 64 == 0:
                    self._service(time.monotonic())
                self._send(*self._message(ev))
            t_send_end = time.perf_counter()
            t_last = time.monotonic()
            self._rec.drain()
            heard = self._rec.last_heard
            quiet = None if heard == -math.inf else max(t_last - heard, 0.0)
            while (now := time.monotonic()) < min(
                max(t_last, self._rec.last_odometry) + o.linger_s, t_last + LINGER_MAX_S
            ):
                self._service(now)
                time.sleep(0.01)
        finally:
            link.close()
        rec = self._rec
        ts = rec.timesync_ms
        return ReplayResult(
            boot_offset_s=self.offset,
            sent=dict(sorted(self.sent.items())),
            flight_s=0.0 if a_first is None else float(a_last - a_first),
            wall_s=t_send_end - t_start,
            odometry=rec.trajectory(),
            received=dict(sorted(rec.received.items())),
            lost=dict(rec.seq.lost),
            odometry_rejected=dict(rec.rejected),
            timesync={
                "replies": len(ts),
                "median_tc1_minus_ts1_ms": float(np.median(ts)) if ts else None,
            },
            peer_heartbeat=rec.peer_heartbeat,
            send_errors=link.send_errors,
            flight_start=math.nan if a_first is None else float(a_first),
            flight_end=math.nan if a_last is None else float(a_last),
            peer_quiet_s=quiet,
        )
