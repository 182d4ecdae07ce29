"""What has arrived so far: a bounded history of measurement events for event-fed filters.

The filter baselines are fed events in arrival order (``feed(event)``) and never see the flight.
Some of their steps need a stretch of past data: the closed-form SLAM-scale fit that starts
them, the scale guess of a new SLAM map, re-propagating the IMU after a delayed measurement.
:class:`Arrived` keeps those samples (trimmed to a horizon) and hands them back as a
:class:`~fgnav.datasets.types.Flight` of the arrived prefix, so a fit can only use data that has
arrived.
"""

from __future__ import annotations

import bisect

from fgnav.datasets.events import (
    AttitudeSample,
    Event,
    ImuSample,
    RangeReading,
    SlamPose,
    YawReading,
    flight_from_events,
)
from fgnav.datasets.types import Calibration, Flight

TRIM_MIN_SAMPLES = 4096
"""IMU samples are dropped in blocks of at least this many (or half the history)."""


class Arrived:
    """Samples that have arrived, by stream, in measurement-time order.

    IMU samples carry a running index (:meth:`imu_index`) that stays valid when old samples are
    trimmed. Duplicate or older-than-newest IMU, attitude and yaw samples are not kept; SLAM
    poses, which may arrive out of capture order, are inserted in capture order.
    """

    def __init__(self) -> None:
        self.imu: list[ImuSample] = []
        self.imu_t: list[float] = []
        self.base = 0  # running index of imu[0]
        self.att: list[AttitudeSample] = []
        self.yaw: list[YawReading] = []
        self.range: list[RangeReading] = []
        self.slam: list[SlamPose] = []
        self.slam_t: list[float] = []

    def add(self, ev: Event) -> None:
        """Keep one event (other event types are ignored)."""
        if isinstance(ev, ImuSample):
            if not self.imu_t or ev.t > self.imu_t[-1]:
                self.imu.append(ev)
                self.imu_t.append(ev.t)
        elif isinstance(ev, SlamPose):
            k = bisect.bisect_right(self.slam_t, ev.t)
            if not (k and self.slam_t[k - 1] == ev.t):
                self.slam.insert(k, ev)
                self.slam_t.insert(k, ev.t)
        else:
            lst = {AttitudeSample: self.att, YawReading: self.yaw, RangeReading: self.range}.get(
                type(ev)
            )
            if lst is not None and (not lst or ev.t > lst[-1].t):
                lst.append(ev)

    # -- IMU by running index --------------------------------------------------------------------

    def imu_index(self, ev: ImuSample) -> int:
        return self.base + bisect.bisect_left(self.imu_t, ev.t)

    def imu_at(self, index: int) -> ImuSample:
        return self.imu[index - self.base]

    def imu_from(self, t: float) -> list[ImuSample]:
        """IMU samples at or after ``t``."""
        return self.imu[bisect.bisect_left(self.imu_t, t) :]

    def slam_after(self, t: float) -> list[SlamPose]:
        """SLAM poses taken after ``t``."""
        return self.slam[bisect.bisect_right(self.slam_t, t) :]

    def others_from(self, t: float) -> list[Event]:
        """Attitude, yaw and range samples taken at or after ``t``."""
        return [e for lst in (self.att, self.yaw, self.range) for e in lst if e.t >= t]

    def trim(self, t_keep: float) -> None:
        """Forget samples taken before ``t_keep`` (IMU in blocks, to keep the cost amortised)."""
        n = bisect.bisect_left(self.imu_t, t_keep)
        if not (n > TRIM_MIN_SAMPLES or (n and n >= len(self.imu_t) // 2)):
            return
        del self.imu[:n], self.imu_t[:n]
        self.base += n
        for lst in (self.att, self.yaw, self.range):
            lst[:] = [e for e in lst if e.t >= t_keep]
        k = bisect.bisect_left(self.slam_t, t_keep)
        del self.slam[:k], self.slam_t[:k]

    def flight(self, calib: Calibration, name: str) -> Flight:
        """What has arrived, as a flight (IMU, attitude, yaw, range, SLAM; no ground truth)."""
        return flight_from_events(
            calib,
            name,
            {
                "imu": self.imu,
                "attitude": self.att,
                "yaw": self.yaw,
                "range": self.range,
                "slam": self.slam,
            },
        )
