"""``fgnav live``: the estimator fed from a MAVLink link, answering with ``ODOMETRY``.

One loop on the caller's thread takes datagrams from the link's reader thread
(:class:`~fgnav.live.link.UdpLink`), parses them, turns sensor messages into events
(:class:`~fgnav.live.inbound.Inbound`), feeds the estimator and, at each new keyframe state,
sends ``ODOMETRY`` (:func:`fgnav.live.convert.odometry_fields`) to every peer heard from. It also
sends a ``HEARTBEAT`` at ``heartbeat_hz`` and answers ``TIMESYNC`` requests (``tc1 = 0``) with
``tc1`` = the boot clock's now as fgnav knows it (the newest stamp received) [ns] and ``ts1``
mirrored.

One clock: the estimator runs on the messages' boot-clock stamps only. The wall clock is used
for the link's own timers (heartbeat, idle timeout, ``--duration``) and for nothing the
estimator sees, so a flight replayed at 4x real time gives the same estimate as at 1x.

It stops on :meth:`LiveSession.stop` (the command calls it on SIGINT/SIGTERM), after
``duration_s`` of wall time, or after ``idle_timeout_s`` of wall time without a datagram once
the first one has come. :meth:`LiveSession.run` returns a :class:`LiveResult`: the estimator's
causal estimate and the counts (see :meth:`LiveResult.counts` for the keys).
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fgnav.datasets.errors import FgnavError
from fgnav.datasets.events import ImuSample
from fgnav.datasets.types import Calibration
from fgnav.estimate import Estimate
from fgnav.live import convert
from fgnav.live.estimators import LiveEstimator
from fgnav.live.inbound import Inbound
from fgnav.live.link import Parsers, UdpLink, new_mavlink, pack

log = logging.getLogger(__name__)

MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY = 197
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4

IMU_HISTORY = 512
"""IMU samples kept to find the angular rate at a state's time (2.5 s at 200 Hz)."""


class LiveError(FgnavError, RuntimeError):
    """The live session could not produce an estimate."""


@dataclass
class LiveOptions:
    """Options of the link (``[live]`` table of ``--config``).

    Attributes:
        idle_timeout_s: stop after this many wall seconds without a datagram (once one came);
            0 never.
        duration_s: stop after this many wall seconds; 0 never.
        heartbeat_hz: rate of fgnav's HEARTBEAT [Hz] (wall clock).
        system_id, component_id: fgnav's MAVLink ids (default: system 1, component 197,
            ``MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY``).
        imu_id: the ``HIGHRES_IMU.id`` used.
        source_system: the vehicle's MAVLink system id (0: the first system to send
            ``HIGHRES_IMU``; other systems' messages are dropped as ``<stream>:other_system``).
        poll_s: the loop's longest wait for a datagram [s] (timers are checked between).
    """

    idle_timeout_s: float = 5.0
    duration_s: float = 0.0
    heartbeat_hz: float = 1.0
    system_id: int = 1
    component_id: int = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
    imu_id: int = 0
    source_system: int = 0
    poll_s: float = 0.05

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """The MAVLink id ranges (a system id of 300 or a component id of -1 failed in the
        first message's ``struct.pack``)."""
        for name, lo in (
            ("system_id", 1),
            ("component_id", 0),
            ("imu_id", 0),
            ("source_system", 0),
        ):
            value = getattr(self, name)
            if isinstance(value, int) and not isinstance(value, bool) and not lo <= value <= 255:
                raise LiveError(f"LiveOptions.{name}={value}: expected an integer in [{lo}, 255]")


@dataclass
class LiveResult:
    """What a live session did.

    Attributes:
        estimate: the estimator's causal estimate (None when it never started).
        inbound: :meth:`fgnav.live.inbound.Inbound.counts` (messages, received, dropped, lost).
        estimator: the estimator's ``counts()`` (received, used, late, dropped).
        sent: messages sent by name.
        exit_reason: ``"stopped"``, ``"duration"``, ``"idle"`` or ``"error"`` (an unexpected
            exception, named in ``failure``: the session ended there, its estimate kept).
        wall_s: wall time of the session [s].
        link: datagrams and bytes read, the largest queue depth, send errors, receive buffer.
        error: why there is no estimate, when there is none.
        failure: the unexpected exception that ended the session (``"Type: message"``), if one
            did.
    """

    estimate: Estimate | None
    inbound: dict[str, Any]
    estimator: dict[str, Any]
    sent: dict[str, int]
    exit_reason: str
    wall_s: float
    link: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    failure: str | None = None

    def counts(self) -> dict[str, Any]:
        """The counts written under ``summary.json``'s ``extra.live``:

        - ``messages``: MAVLink messages parsed, by name;
        - ``received``: per stream, sensor messages received (before any check);
        - ``used``, ``late``: per stream, as the estimator counts them;
        - ``dropped``: ``"stream:reason"`` -> n, at the edge (``fgnav.live.inbound``) and in
          the estimator, together; ``dropped_at_link``: those of the edge alone;
        - ``lost``: ``"sysid/compid"`` -> messages missing by sequence number; ``duplicate``,
          ``reordered``: messages repeated (the same sequence number again), or late;
        - ``slam_sessions``: SLAM sessions started (``reset_counter`` changes, sources);
        - ``source``: the ``"sysid/compid"`` followed (see :mod:`fgnav.live.inbound`);
          ``clock_restarts``, ``clock_outliers``: the IMU clock's confirmed backward jumps and
          the stamps it ignored;
        - ``left``: ``"stream:reason"`` -> measurements the estimator still held when the
          stream ended (after its last keyframe, or waiting for a SLAM alignment): its
          estimate's ``info["skipped"]``;
        - ``sent``: messages fgnav sent, by name.
        """
        dropped = dict(self.inbound["dropped"])
        for k, v in self.estimator.get("dropped", {}).items():
            dropped[k] = dropped.get(k, 0) + v
        return {
            "messages": self.inbound["messages"],
            "received": self.inbound["received"],
            "used": self.estimator.get("used", {}),
            "late": self.estimator.get("late", {}),
            "dropped": dict(sorted(dropped.items())),
            "dropped_at_link": self.inbound["dropped"],
            "lost": self.inbound["lost"],
            "duplicate": self.inbound.get("duplicate", {}),
            "reordered": self.inbound.get("reordered", {}),
            "slam_sessions": self.inbound.get("slam_sessions", 0),
            "source": self.inbound.get("source"),
            "clock_restarts": self.inbound.get("clock_restarts", 0),
            "clock_outliers": self.inbound.get("clock_outliers", 0),
            "left": dict((self.estimate.info.get("skipped") or {}) if self.estimate else {}),
            "sent": self.sent,
        }


class LiveSession:
    """The live loop (see the module docstring).

    Args:
        link: an unstarted ``udpin`` :class:`UdpLink`.
        estimator: the estimator to feed (push API).
        calib: the calibration (IMU noise for the rate variances, flow units).
        options: :class:`LiveOptions`.
        record: also fed every event the link turns a message into, before the estimator
            (``fgnav live --batch``: a :class:`fgnav.solvers.collect.EventCollector`).
    """

    def __init__(
        self,
        link: UdpLink,
        estimator: LiveEstimator,
        calib: Calibration,
        options: LiveOptions | None = None,
        record: Any = None,
    ) -> None:
        self.link = link
        self.estimator = estimator
        self.record = record
        self.calib = calib
        self.options = options or LiveOptions()
        o = self.options
        self.inbound = Inbound(
            calib.flow_pixels_per_rad, imu_id=o.imu_id, source_system=o.source_system
        )
        self.mav = new_mavlink(o.system_id, o.component_id)
        self.sent: dict[str, int] = {}
        self._parsers = Parsers()
        self._stop = threading.Event()
        self._imu: deque[ImuSample] = deque(maxlen=IMU_HISTORY)
        self._imu_t: deque[float] = deque(maxlen=IMU_HISTORY)
        self._estimator_errors: dict[str, int] = {}
        self._restarts_seen = 0
        self.failure: str | None = None

    def stop(self) -> None:
        """Ask the loop to finish (safe from a signal handler or another thread)."""
        self._stop.set()

    # ------------------------------------------------------------------------------------------

    def _send(self, msg: Any, to: tuple[str, int] | None = None) -> None:
        self.link.send(pack(self.mav, msg), to)
        name = msg.get_type()
        self.sent[name] = self.sent.get(name, 0) + 1

    def _heartbeat(self) -> None:
        self._send(
            self.mav.heartbeat_encode(
                MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE
            )
        )

    def _rate_at(self, t: float) -> tuple[np.ndarray | None, np.ndarray | None]:
        """IMU angular rate nearest ``t`` and its variance (white noise at the IMU rate)."""
        if not self._imu:
            return None, None
        ts = self._imu_t
        i = bisect.bisect_left(ts, t)
        if i >= len(ts) or (i > 0 and t - ts[i - 1] < ts[i] - t):
            i -= 1
        dt = float(np.median(np.diff(np.asarray(ts)))) if len(ts) > 1 else math.nan
        nd = self.calib.imu_noise.gyro_noise_density
        var = np.full(3, nd**2 / dt) if dt > 0 else None
        return self._imu[i].body_omega, var

    def _odometry(self, state: Any) -> None:
        omega, var = self._rate_at(float(state.t))
        fields = convert.odometry_fields(state, omega, var)
        self._send(self.mav.odometry_encode(**fields))

    def _handle(self, msg: Any, peer: tuple[str, int]) -> None:
        name = self.inbound.count(msg)
        if name == "TIMESYNC":
            if msg.tc1 == 0 and self.inbound.from_vehicle(msg, "timesync"):  # a request
                now = self.inbound.clock_ns()  # None: no clock yet, or none TIMESYNC carries
                if now is not None:
                    self._send(self.mav.timesync_encode(now, msg.ts1), to=peer)
            return
        ev = self.inbound.event(msg)
        if ev is None:
            return
        if self.record is not None:
            self.record.feed(ev)
        if isinstance(ev, ImuSample):
            if self.inbound.clock_restarts != self._restarts_seen:
                # The IMU clock restarted: the rates of the old clock say nothing of the new.
                self._restarts_seen = self.inbound.clock_restarts
                self._imu.clear()
                self._imu_t.clear()
            if self.inbound.imu_on_clock and (not self._imu_t or ev.t > self._imu_t[-1]):
                self._imu.append(ev)
                self._imu_t.append(ev.t)
        try:
            state = self.estimator.feed(ev)
        except FgnavError as e:  # a known failure on one event: counted, the link goes on
            key = f"{type(ev).__name__}:{type(e).__name__}"
            self._estimator_errors[key] = self._estimator_errors.get(key, 0) + 1
            log.warning("estimator: %s", e)
            return
        if state is not None:
            self._odometry(state)

    def run(self) -> LiveResult:
        """Run until stopped (see the module docstring); returns the :class:`LiveResult`."""
        o = self.options
        link = self.link
        link.start()
        wall0 = time.monotonic()
        last_datagram: float | None = None
        next_heartbeat = wall0
        reason = "stopped"
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if o.heartbeat_hz > 0 and now >= next_heartbeat and link.peers:
                    self._heartbeat()
                    next_heartbeat = now + 1.0 / o.heartbeat_hz
                if o.duration_s > 0 and now - wall0 >= o.duration_s:
                    reason = "duration"
                    break
                if (
                    o.idle_timeout_s > 0
                    and last_datagram is not None
                    and now - last_datagram >= o.idle_timeout_s
                ):
                    reason = "idle"
                    break
                item = link.get(timeout=o.poll_s)
                if item is None:
                    continue
                data, peer, _ = item
                last_datagram = time.monotonic()
                try:
                    for msg in self._parsers.parse(data, peer):
                        self._handle(msg, peer)
                except Exception as e:  # noqa: BLE001 - the session ends, its outputs kept
                    self._fail("on a message", e)
                    reason = "error"
                    break
        finally:
            link.close()
        wall = time.monotonic() - wall0
        close = getattr(self.estimator, "close", None)
        if callable(close) and self.failure is None:
            # End of the stream: the smoother's held input (an IMU sample after a clock
            # discontinuity, the VO's last frames) is taken or counted.
            try:
                close()
            except Exception as e:  # noqa: BLE001
                self._fail("closing the estimator", e)
        try:
            counts = self.estimator.counts()
        except Exception as e:  # noqa: BLE001
            self._fail("counting", e)
            counts = {}
        if self._estimator_errors:
            counts = dict(counts)
            dropped = dict(counts.get("dropped", {}))
            for k, v in self._estimator_errors.items():
                dropped[f"estimator_error:{k}"] = v
            counts["dropped"] = dropped
        est, error = None, None
        try:
            est = self.estimator.result()
        except FgnavError as e:
            error = str(e)
        except Exception as e:  # noqa: BLE001
            self._fail("on the estimate", e)
            error = self.failure
        return LiveResult(
            estimate=est,
            inbound=self.inbound.counts(),
            estimator=counts,
            sent=dict(sorted(self.sent.items())),
            exit_reason=reason,
            wall_s=wall,
            link={
                "datagrams": link.datagrams,
                "bytes": link.bytes,
                "queue_max": link.queue_max,
                "send_errors": link.send_errors,
                "read_errors": link.read_errors,
                "truncated_datagrams": self._parsers.truncated,
                "rcvbuf_bytes": link.rcvbuf_bytes,
                "peers": [f"{h}:{p}" for h, p in link.peers],
            },
            error=error,
            failure=self.failure,
        )

    def _fail(self, where: str, e: Exception) -> None:
        """An unexpected exception: the first is kept (one line; the traceback with -v)."""
        log.debug("unexpected %s %s", type(e).__name__, where, exc_info=True)
        if self.failure is None:
            self.failure = f"{type(e).__name__} {where}: {e}"
