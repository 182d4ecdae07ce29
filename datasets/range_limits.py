"""A rangefinder's limits: which readings are distances.

A reading is a distance when it is finite, within the sensor's interval ``[range_min,
range_max]`` (``Calibration.range_min``, ``range_max``) and at neither end of it: at the floor of a
sensor that clamps there (:func:`range_at_min`, :func:`range_clamps`) it says "at or below the
floor", at the maximum (:func:`range_at_max`) "no echo". :func:`range_refusal` is the one test;
:class:`RangeLimits` applies it to a stream of readings (causally, or over a whole flight). Every
consumer of range readings calls it: the smoothers' range factors and ground guesses, the flow
and camera heights, the filter baselines and the health checks. Knows nothing of GTSAM.
"""

from __future__ import annotations

import math

import numpy as np

#: A reading within this of the sensor's ``range_min`` [m] is at its floor (:func:`range_at_min`):
#: half a millimetre, below the step of a millimetre-quantised sensor and far above the rounding
#: of a written float.
RANGE_AT_MIN_TOL_M = 5e-4


def range_at_min(range_meas: float, range_min: float) -> bool:
    """A reading at the sensor's floor: within :data:`RANGE_AT_MIN_TOL_M` above ``range_min``
    (inclusive). A sensor that clamps to its minimum reports it for anything at or below it, so
    the reading says "at or below the floor", not a distance; no height factor (counted
    ``range:at-min``). Callers apply it while the sensor has reported no reading below
    ``range_min`` (:func:`range_clamps`): one that has does not clamp, and its readings at
    ``range_min`` are distances (a Crazyflie's time of flight reads 12-25 mm on the floor, under
    its 40 mm limit, and 40 mm on the way down; out-of-range readings, which the ground-contact
    test uses)."""
    return range_min <= range_meas <= range_min + RANGE_AT_MIN_TOL_M


def range_clamps(readings: np.ndarray, range_min: float) -> bool:
    """Whether a rangefinder may clamp at its floor: none of ``readings`` (those seen so far,
    causally) is below ``range_min`` (see :func:`range_at_min`)."""
    r = np.asarray(readings, float)
    return not bool((r < range_min).any())


#: A reading within this of the sensor's ``range_max`` [m] is at its maximum
#: (:func:`range_at_max`): the floor's half millimetre (:data:`RANGE_AT_MIN_TOL_M`).
RANGE_AT_MAX_TOL_M = RANGE_AT_MIN_TOL_M


def range_at_max(range_meas: float, range_max: float) -> bool:
    """A reading at the sensor's maximum: within :data:`RANGE_AT_MAX_TOL_M` below ``range_max``
    (inclusive). Many rangefinders, drivers and simulators report their maximum when no echo
    comes back (a clamping driver; Webots' distance sensors; Qt's distance readings for "far"):
    the reading says "nothing within range", not a distance; no height factor (counted
    ``range:at-max``). Others report more than the maximum (MAVLink ``OBSTACLE_DISTANCE``:
    ``max_distance + 1`` cm is "no obstacle"; ArduPilot's Benewake driver: the maximum plus
    1 m), or infinity (ROS REP 117): out of range, refused anyway.

    Unlike the floor (:func:`range_clamps`), always: a sensor that has reported readings above
    its maximum is not thereby known to give distances at it (a driver may pass raw readings
    beyond the datasheet's limit and still put the limit in for a missing echo), and the two
    mistakes do not cost the same: a real distance within half a millimetre of the maximum
    refused is one reading at the edge of the sensor's range, where it is least accurate, while
    a missing echo taken for a distance pulls the height to the maximum (simulated two-turns,
    every third reading at its 8 m maximum: batch ATE 4.2x nominal with health "ok", ekf004
    24 m against 0.035; two 4 s runs of them: batch 2.8x, online 1.7x, named ``range-stuck``).
    The floor's exception came from data (a Crazyflie's time of flight reads under its 40 mm
    limit on the floor, and 40 mm on the way down, where a landing needs heights); no shared
    flight comes near its maximum (Crazyflie: 1.99 m of 4 m)."""
    return range_max - RANGE_AT_MAX_TOL_M <= range_meas <= range_max


def range_refusal(
    range_meas: float, range_min: float, range_max: float, clamps: bool = True
) -> str | None:
    """Why a range reading is no distance, or None when it is one: the one test of the sensor's
    limits (:class:`RangeLimits` applies it to a stream of readings).

    Args:
        range_meas: the reading [m].
        range_min, range_max: the sensor's interval [m] (inclusive).
        clamps: the sensor may clamp at its floor (:func:`range_clamps`).

    Returns:
        None, ``"non-finite"``, ``"out-of-range"`` (outside ``[range_min, range_max]``),
        ``"at-min"`` (at the floor of a sensor that clamps there, :func:`range_at_min`) or
        ``"at-max"`` (:func:`range_at_max`).
    """
    if not math.isfinite(range_meas):
        return "non-finite"
    if not range_min <= range_meas <= range_max:
        return "out-of-range"
    if clamps and range_at_min(range_meas, range_min):
        return "at-min"
    if range_at_max(range_meas, range_max):
        return "at-max"
    return None


#: :func:`range_refusal`'s reasons counted by their own name (``range:at-min``,
#: ``range:at-max``) where the others are counted as gates (``range:gated:...``).
RANGE_LIMIT_TAGS = ("at-min", "at-max")


class RangeLimits:
    """:func:`range_refusal` for one stream of readings, with what the stream has shown of its
    floor: the sensor clamps there until a reading below ``range_min`` has been seen
    (:func:`range_clamps`). A causal consumer calls :meth:`see` with each reading as it arrives,
    before testing it; a whole-flight one builds it with :meth:`of_stream`.

    Args:
        range_min, range_max: the sensor's interval [m] (``Calibration.range_min``,
            ``range_max``).
    """

    __slots__ = ("range_min", "range_max", "clamps")

    def __init__(self, range_min: float, range_max: float) -> None:
        self.range_min = float(range_min)
        self.range_max = float(range_max)
        #: no reading below ``range_min`` seen: the sensor may clamp at its floor
        self.clamps = True

    @classmethod
    def of_stream(cls, readings: np.ndarray, range_min: float, range_max: float) -> RangeLimits:
        """The limits as a whole stream of readings shows them (batch: not causal)."""
        limits = cls(range_min, range_max)
        limits.clamps = range_clamps(readings, limits.range_min)
        return limits

    def see(self, range_meas: float) -> None:
        """A reading arrived: one below ``range_min`` shows that the sensor does not clamp."""
        if range_meas < self.range_min:
            self.clamps = False

    def refusal(self, range_meas: float) -> str | None:
        """:func:`range_refusal` of a reading (None: a distance)."""
        return range_refusal(range_meas, self.range_min, self.range_max, self.clamps)

    def usable(self, range_meas: float) -> bool:
        """The reading is a distance (:meth:`refusal` is None)."""
        return self.refusal(range_meas) is None

    def mask(self, readings: np.ndarray) -> np.ndarray:
        """:meth:`usable` of each of ``readings`` (a boolean array)."""
        r = np.asarray(readings, float)
        lo, hi = self.range_min, self.range_max
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(r) & (r >= lo) & (r < hi - RANGE_AT_MAX_TOL_M)
            if self.clamps:
                ok &= r > lo + RANGE_AT_MIN_TOL_M
        return ok
