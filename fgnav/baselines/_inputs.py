"""What a filter baseline received and did not use: one place shared by every filter baseline.

Each baseline passes the events it is fed through :class:`Inputs` before its model sees them:

* An IMU sample that is no measurement is not used, counted by reason: ``imu:bad-shape``,
  ``imu:non-finite``, ``imu:implausible`` (a rate or specific force beyond
  :data:`~fgnav.datasets.types.IMU_MAX_RATE` / ``IMU_MAX_ACCEL``, the bound of the push-API
  smoother). One such sample integrated by a filter had moved its state so far that its
  innovation gate refused every later SLAM pose.
* An IMU gap longer than :data:`IMU_GAP_S` (the smoothers' ``max_imu_gap_s`` default) is counted
  (:attr:`Inputs.gaps`, ``info["imu_gaps"]``) and said once as a warning; the filters that
  integrate the IMU widen their covariance over it.
* The last sample time of each stream: :meth:`Inputs.warn_ended` says, once and as a warning
  naming the method, which aiding stream ended more than
  :data:`~fgnav.coverage.TRUNCATED_STREAM_S` before the IMU (the filter dead-reckoned since).

The convention of ``Estimate.info["unused"]`` (every filter baseline's result has it):
``{"<stream>:<reason>": count}`` of the measurements the method received and did not use (gated,
out of limits, implausible, arrived too late, before the start ...), zero counts left out.
:func:`fgnav.coverage.unused_counts` reads it for the "not used" line of ``fgnav compare``.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Mapping
from typing import Any

from fgnav.coverage import TRUNCATED_STREAM_S
from fgnav.datasets.events import STREAM_OF_EVENT, Event, ImuSample
from fgnav.datasets.types import IMU_MAX_ACCEL, IMU_MAX_RATE

log = logging.getLogger(__name__)

#: An IMU interval longer than this is a gap [s]: the smoothers' ``max_imu_gap_s`` default
#: (:class:`~fgnav.solvers.fixed_lag.FixedLagOptions`; not imported: it loads GTSAM).
IMU_GAP_S = 0.5

#: Over an IMU gap, the unknown acceleration's standard deviation [m/s^2]: a filter integrating
#: the held sample over the gap ``dt`` widens its velocity and position variances by
#: ``(sigma dt)^2`` and ``(sigma dt^2 / 2)^2``.
GAP_ACCEL_SIGMA = 2.0
#: Over an IMU gap, the unknown body rate's standard deviation [rad/s] (attitude variance).
GAP_RATE_SIGMA = 0.1

_MAX_RATE_SQ, _MAX_ACCEL_SQ = IMU_MAX_RATE**2, IMU_MAX_ACCEL**2


def imu_problem(ev: ImuSample) -> str | None:
    """Why an IMU sample is no measurement (``"bad-shape"``, ``"non-finite"``,
    ``"implausible"``), None when it is one."""
    try:
        w0, w1, w2 = (float(v) for v in ev.body_omega)
        a0, a1, a2 = (float(v) for v in ev.body_accel)
    except (TypeError, ValueError):
        return "bad-shape"
    w_sq, a_sq = w0 * w0 + w1 * w1 + w2 * w2, a0 * a0 + a1 * a1 + a2 * a2
    if not math.isfinite(float(ev.t) + w_sq + a_sq):
        return "non-finite"
    if w_sq > _MAX_RATE_SQ or a_sq > _MAX_ACCEL_SQ:
        return "implausible"
    return None


def unused_table(*tables: Mapping[str, int]) -> dict[str, int]:
    """``info["unused"]`` from ``stream:reason -> count`` tables (summed; zeros left out)."""
    out: Counter[str] = Counter()
    for t in tables:
        for k, v in t.items():
            out[k] += int(v)
    return {k: v for k, v in sorted(out.items()) if v}


class Inputs:
    """The input bookkeeping of one filter baseline run (module docstring).

    Args:
        method: the method's name in messages (``"msf-ekf"``).
        name: the flight's name.
    """

    def __init__(self, method: str, name: str = "flight") -> None:
        self.method = method
        self.name = name
        self.unused: Counter[str] = Counter()
        self.received: Counter[str] = Counter()
        self.last_t: dict[str, float] = {}
        self.gaps = 0
        self.gap_max_s = 0.0
        self._imu_t: float | None = None
        self._ended_said = False

    def skip(self, key: str, n: int = 1) -> None:
        """Count ``n`` measurements not used (``key`` is ``stream:reason``)."""
        self.unused[key] += n

    def take(self, ev: Event) -> bool:
        """Note one event (an IMU sample's gap too, :meth:`imu_gap`); False for an IMU sample
        that is no measurement (counted: the caller drops it)."""
        stream = STREAM_OF_EVENT.get(type(ev))
        if stream is not None:
            self.received[stream] += 1
        if isinstance(ev, ImuSample):
            why = imu_problem(ev)
            if why is not None:
                self.skip(f"imu:{why}")
                return False
            self.imu_gap(ev)
        t = float(ev.t)
        if stream is not None and math.isfinite(t):
            self.last_t[stream] = max(t, self.last_t.get(stream, -math.inf))
        return True

    def imu_gap(self, ev: ImuSample) -> float:
        """The interval from the previous IMU sample when it is a gap (longer than
        :data:`IMU_GAP_S`; counted, the first one said as a warning), else 0."""
        t, prev = float(ev.t), self._imu_t
        if prev is not None and t <= prev:
            return 0.0
        self._imu_t = t
        if prev is None or t - prev <= IMU_GAP_S:
            return 0.0
        gap = t - prev
        if not self.gaps:
            log.warning(
                "%s: %s: IMU gap of %.2f s at %.2f s: the filter held the previous sample and "
                "widened its covariance",
                self.method,
                self.name,
                gap,
                prev,
            )
        self.gaps += 1
        self.gap_max_s = max(self.gap_max_s, gap)
        return gap

    def ended_streams(self, aiding: tuple[str, ...]) -> dict[str, float]:
        """The aiding streams (of those received) whose last sample is more than
        ``TRUNCATED_STREAM_S`` before the last IMU sample: ``stream -> seconds dead-reckoned``."""
        t_end = self.last_t.get("imu")
        if t_end is None:
            return {}
        return {
            s: t_end - self.last_t[s]
            for s in aiding
            if s in self.last_t and t_end - self.last_t[s] > TRUNCATED_STREAM_S
        }

    def warn_ended(self, aiding: tuple[str, ...]) -> dict[str, float]:
        """:meth:`ended_streams`, said once as a warning naming the method and the stream."""
        ended = self.ended_streams(aiding)
        if ended and not self._ended_said:
            self._ended_said = True
            for s, dt in ended.items():
                log.warning(
                    "%s: %s: the %s stream ended %.1f s before the IMU: nothing after it is aided "
                    "by it (counted in info['streams_ended'])",
                    self.method,
                    self.name,
                    s,
                    dt,
                )
        return ended

    def info(self, aiding: tuple[str, ...]) -> dict[str, Any]:
        """The result's entries: ``imu_gaps`` and ``streams_ended`` (``unused`` is the caller's:
        :func:`unused_table` of :attr:`unused` and its own counts)."""
        return {
            "imu_gaps": {"n": self.gaps, "longest_s": self.gap_max_s},
            "streams_ended": self.warn_ended(aiding),
        }
