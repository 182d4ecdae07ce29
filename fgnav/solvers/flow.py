"""Downward optical flow in the smoother graph (../shared/DESIGN.md sec. 4.6): readings summed over
a keyframe window into one factor on ``X(k), V(k), G(g_k)``.

A flow sensor (PMW3901, PX4Flow, ARK Flow) reports the image motion integrated over short
intervals (10-12 ms on a Crazyflie, ``FlowSeries``); the keyframes are 10-20 Hz. This module turns
the readings of one keyframe window into one
:func:`fgnav.factors.optical_flow.make_optical_flow_factor`:

1. **Clean** each reading: non-finite flow or interval (``flow:non-finite``), an interval not in
   ``(0, FLOW_MAX_DT_S]`` (``flow:bad-interval``), quality below
   ``quality_min`` (``flow:gated:quality``; quality unknown, ``< 0``, is not tested), an image
   motion faster than ``max_rate_rad_s`` (``flow:implausible-rate``: a sensor's counter at its
   rail, e.g. a PMW3901 delta of 32767 counts, 6900 rad/s on a Crazyflie; 200 such readings
   took a real flight from 0.08 to 2.2 m ATE with health "ok").
2. **Gate** the window (:func:`fgnav.factors.optical_flow.gate_flow`): the flow sensor's height
   above the ground (from the rangefinder, see below) outside ``[height_min, height_max]``
   (``flow:gated:height``; no range reading to tell it: ``flow:no-height``), or the optical axis
   tilted more than ``max_tilt_deg`` (``flow:gated:tilt``). Counts are of readings.
3. **Sum**: ``flow`` and ``dt`` are the sums of the accepted readings, so the factor sees the
   image motion over the window (the sensor's rate-dependent gain ``calib.flow_rate_gain``
   undone on the window's mean rate, :func:`linearise_flow`); the angular rate input is the mean
   bias-corrected gyro over the
   union of the readings' intervals (zero-order hold on each IMU sample), so the rotational part
   cancels exactly as the sensor integrated it.
4. **Noise**: per reading ``sigma_rad * flow_pixels_per_rad`` [flow units] with lag-1 correlation
   ``lag1_corr`` between consecutive readings and none beyond (real PMW3901 on a Crazyflie: 0.2 px
   per reading at 48 px/rad, lag-1 about -0.3; ``crazyflie_util_flowdeck`` README). The sum of a
   run of ``n`` consecutive readings has the standard deviation
   :func:`~fgnav.factors.optical_flow.flow_sum_sigma` ``(sigma, n, rho)``; runs separated by a
   missing reading are independent, so their variances add. The correlation of the edge readings
   of neighbouring windows (``rho / (n + 2 (n - 1) rho)``, -0.12 for 5 readings) is neglected.
   The graph's robust kernel (Huber by default) on top.

**Windows** (batch, :meth:`FlowFactors.associate`): keyframe k owns the readings whose interval
midpoint ``t - dt/2`` lies in ``(m_{k-1}, m_k]``, ``m_k`` the midpoint between keyframes k and
k+1 (half a period before the first and after the last keyframe): the window is centred on
``t_k``, so the state at ``t_k`` stands for the window with no lag. Readings outside every window
are ``flow:outside-keyframes``.

**Height for the gate**: the nearest range reading within ``height_max_age_s`` of the keyframe
that is a distance (:func:`fgnav.datasets.range_limits.range_refusal`: a refused reading, out of
the sensor's limits, at its floor or at its maximum, is passed over for a usable neighbour within
that age: every third reading at the maximum on the simulated flow deck took the batch from 0.026
to 0.052 m ATE when only the nearest reading was looked at, 0.025 m now), through the attitude at
the keyframe: ``h_flow = r cos(tilt_range) - (R t_range)_z + (R t_flow)_z`` (sensor lever arms
``body_T_range``, ``body_T_flow``).

**Ground**: the factor's ground is the ground-height variable ``G`` of the keyframe's segment,
the one the rangefinder measures: flow gives ``v / h``, the rangefinder ``h``; together the
horizontal velocity is observable (the position is dead-reckoned from it and drifts). Without a
rangefinder in the graph, flow is refused (``ObservabilityError``).

Online use: :func:`flow_keyframe_factor` is the whole recipe for one group of readings; the batch
builder calls it for every window, and an online smoother can call it with the readings it
groups for a keyframe (e.g. those that ended in ``(t_{k-1}, t_k]``, known when keyframe k is
closed; the state at ``t_k`` then stands for a window centred half a period earlier, which
biases the velocity by ``a P / 2`` under an acceleration ``a``: 2.5 cm/s at 1 m/s^2 and 20 Hz).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import gtsam
import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import FlowSample
from fgnav.datasets.range_limits import RangeLimits
from fgnav.datasets.types import Calibration, Flight
from fgnav.factors.optical_flow import (
    FlowMeasurement,
    FlowSensor,
    flow_sum_sigma,
    gate_flow,
    make_optical_flow_factor,
)

log = logging.getLogger(__name__)

#: A reading continues the previous one (a run of correlated readings) when its interval starts
#: within this fraction of its length of the previous reading's end.
CONTIGUOUS_FRAC = 0.25
#: A reading integrated over a longer interval [s] is no flow sensor's (``flow:bad-interval``;
#: 1 s intervals on a fifth of the readings made a simulated flow deck diverge).
FLOW_MAX_DT_S = 0.5


@dataclass
class FlowFactorOptions:
    """Options of the optical-flow factors (``GraphOptions.flow``; None there: defaults).

    Attributes:
        sigma_rad: noise of one reading [rad of image motion] (times ``flow_pixels_per_rad`` in
            flow units): 0.2 px at 48 px/rad, the real Crazyflie's per-reading residual.
        lag1_corr: correlation of the noise of consecutive readings (real PMW3901: about -0.3).
        height_min, height_max: usable height of the flow sensor above the ground [m] (the
            PMW3901 focuses from about 8 cm; its resolution of ground texture limits the top).
        max_tilt_deg: largest tilt of the optical axis [deg].
        quality_min: readings of lower quality (in [0, 1]) are skipped; unknown quality (< 0)
            is not tested.
        min_readings: fewer accepted readings in a window: no factor (``flow:few-readings``).
        height_max_age_s: largest time between a keyframe and the range reading used for its
            height gate [s] (the nearest reading within the sensor's limits, ``range_refusal``).
        max_rate_rad_s: a reading whose image motion over its interval is faster than this
            [rad/s] is no measurement (``flow:implausible-rate``; a PMW3901 tracks up to about
            7 rad/s).
    """

    sigma_rad: float = 0.2 / 48.0
    lag1_corr: float = -0.3
    height_min: float = 0.1
    height_max: float = 4.0
    max_tilt_deg: float = 35.0
    quality_min: float = 0.5
    min_readings: int = 2
    height_max_age_s: float = 0.25
    max_rate_rad_s: float = 20.0

    def check(self) -> FlowFactorOptions:
        if not self.sigma_rad > 0:
            raise FlightDataError(f"flow.sigma_rad={self.sigma_rad}: expected > 0")
        if not -0.5 <= self.lag1_corr <= 0.5:
            raise FlightDataError(f"flow.lag1_corr={self.lag1_corr}: expected in [-0.5, 0.5]")
        if not 0 <= self.height_min < self.height_max:
            raise FlightDataError(
                f"flow.height_min={self.height_min}, height_max={self.height_max}: expected "
                "0 <= height_min < height_max"
            )
        if not 0 < self.max_tilt_deg < 90:
            raise FlightDataError(f"flow.max_tilt_deg={self.max_tilt_deg}: expected in (0, 90)")
        if int(self.min_readings) != self.min_readings or self.min_readings < 1:
            raise FlightDataError(f"flow.min_readings={self.min_readings}: expected >= 1")
        if not self.max_rate_rad_s > 0:
            raise FlightDataError(f"flow.max_rate_rad_s={self.max_rate_rad_s}: expected > 0")
        return self


def flow_options(value: Any) -> FlowFactorOptions:
    """``GraphOptions.flow`` as options: None -> defaults; a dict (TOML table) by name."""
    if value is None:
        return FlowFactorOptions().check()
    if isinstance(value, FlowFactorOptions):
        return value.check()
    if isinstance(value, dict):
        from fgnav.config import options_from

        # Unknown keys and values of the wrong type are one error naming them (a string sigma
        # was a TypeError deep in the graph).
        return options_from(FlowFactorOptions, value, "flow").check()
    raise FlightDataError(f"GraphOptions.flow: expected a table of flow options, got {value!r}")


def resolve_use_flow(flight: Flight, use_flow: bool | None, use_range: bool) -> bool:
    """``GraphOptions.use_flow``: None ("auto") is on when the flight has a flow stream and a
    rangefinder the graph uses; True without a flow stream is off (logged)."""
    has_flow = flight.flow is not None and len(flight.flow) > 0
    if use_flow is None:
        return has_flow and use_range and flight.range is not None
    if use_flow and not has_flow:
        log.warning("%s: use_flow is on but the flight has no flow stream", flight.name)
        return False
    return bool(use_flow)


class FlowFactorResult(NamedTuple):
    """What :func:`flow_keyframe_factor` made of a group of readings.

    Attributes:
        factor: the factor on ``(X, V, G)``, or None.
        reason: ``"ok"``, or why there is no factor (``"empty"``, ``"gated:height"``,
            ``"gated:tilt"``, ``"no-height"``, ``"few-readings"``, ``"no-imu"``).
        skipped: readings not used, by reason (``"non-finite"``, ``"bad-interval"``,
            ``"gated:quality"``, ``"implausible-rate"``, and the
            window's reason for all of its readings when it is gated).
        n_used: readings summed into the factor.
        arrival: arrival time of the newest reading used (or of the group) [s].
        sigma: standard deviation of the summed flow [flow units] (NaN without a factor).
    """

    factor: gtsam.NonlinearFactor | None
    reason: str
    skipped: dict[str, int]
    n_used: int
    arrival: float
    sigma: float


def mean_rate_over(
    imu_t: np.ndarray, imu_omega: np.ndarray, t0: np.ndarray, t1: np.ndarray
) -> np.ndarray:
    """Integral [rad] of the gyro (N, 3) over each interval ``[t0_i, t1_i]``, with each sample held
    until the next (zero-order hold, as the preintegration); (M, 3). Times outside the IMU span
    hold the first/last sample."""
    t = np.asarray(imu_t, float)
    w = np.asarray(imu_omega, float)
    steps = np.diff(t)[:, None] * w[:-1]
    cum = np.vstack([np.zeros((1, 3)), np.cumsum(steps, axis=0)])

    def integral(x: np.ndarray) -> np.ndarray:
        i = np.clip(np.searchsorted(t, x, side="right") - 1, 0, len(t) - 1)
        return cum[i] + (x - t[i])[:, None] * w[i]

    return integral(np.asarray(t1, float)) - integral(np.asarray(t0, float))


def linearise_flow(
    flow: np.ndarray, dt: float, pixels_per_rad: float, gain: Sequence[float]
) -> np.ndarray:
    """The (summed) flow ``flow`` [flow units] over ``dt`` [s] with the sensor's rate-dependent
    gain undone (``Calibration.flow_rate_gain`` ``(a, b)``: an image rate ``r`` reads as
    ``(a + b |r|) r``): ``m = flow / (ppr dt)``, ``|r|`` the root of ``a |r| + b |r|^2 = |m|``
    (with ``b < 0`` clamped at the top of the curve, ``|r| = a / (2 |b|)``), returned as
    ``flow |r| / |m|``. Unchanged for ``(1, 0)``. Applied to a keyframe window's sum (noise of
    its mean rate about 0.1 rad/s on a Crazyflie, against 0.4 rad/s per reading), not per reading:
    ``|m|`` of a noisy reading overstates ``|r|``."""
    a, b = (float(x) for x in gain)
    f = np.asarray(flow, float)
    if a == 1.0 and b == 0.0:
        return f
    m = float(np.linalg.norm(f)) / (pixels_per_rad * dt)
    if not m > 0:
        return f
    if b == 0.0:
        r = m / a
    elif b < 0 and a * a + 4.0 * b * m <= 0:
        r = a / (-2.0 * b)
    else:
        r = (-a + math.sqrt(a * a + 4.0 * b * m)) / (2.0 * b)
    return f * (r / m)


def _run_sigma(
    ends: np.ndarray, starts: np.ndarray, dts: np.ndarray, sigma: float, rho: float
) -> float:
    """Standard deviation of the sum of readings (in time order) made of runs of consecutive
    readings (MA(1) within a run, independent runs)."""
    var = 0.0
    n = 1
    for i in range(1, len(ends)):
        if abs(starts[i] - ends[i - 1]) <= CONTIGUOUS_FRAC * dts[i]:
            n += 1
        else:
            var += flow_sum_sigma(sigma, n, rho) ** 2
            n = 1
    var += flow_sum_sigma(sigma, n, rho) ** 2
    return math.sqrt(var)


def flow_keyframe_factor(
    samples: Sequence[FlowSample],
    imu_t: np.ndarray,
    imu_omega: np.ndarray,
    calib: Calibration,
    pose_key: int,
    velocity_key: int,
    ground_key: int,
    options: FlowFactorOptions | None = None,
    *,
    gyro_bias: np.ndarray | None = None,
    height: float | None = None,
    world_R_body: np.ndarray | None = None,
    robust: Callable[[gtsam.noiseModel.Base], gtsam.noiseModel.Base] | None = None,
) -> FlowFactorResult:
    """One optical-flow factor from the readings of one keyframe window (module docstring).

    Args:
        samples: the readings (``FlowSample``: ``t`` end of interval, ``dt``, ``flow``,
            ``quality``, ``arrival``), in any order.
        imu_t, imu_omega: gyro samples (N,), (N, 3) [rad/s] covering the readings' intervals.
        calib: ``body_T_flow``, ``flow_pixels_per_rad`` and ``flow_rate_gain`` (nothing else).
        pose_key, velocity_key, ground_key: ``X(k)``, ``V(k)``, ``G(j)`` of the keyframe.
        options: gates and noise (defaults when None).
        gyro_bias: (3,) gyro bias subtracted from the rate input [rad/s] (the estimate known when
            the factor is made; zero when None).
        height: height of the flow sensor above the ground estimate at the keyframe [m], for the
            height gate; None: no range reading to tell it (reason ``"no-height"``, no factor).
        world_R_body: attitude at the keyframe for the tilt gate (None: not tested).
        robust: wraps the Gaussian noise model (e.g. the graph's Huber); None: Gaussian.

    Returns:
        :class:`FlowFactorResult` (factor or None, reason, per-reading skip counts, ...).
    """
    o = options or FlowFactorOptions()
    skipped: Counter[str] = Counter()
    arrival = max((float(s.arrival) for s in samples), default=float("nan"))
    nan = float("nan")
    if not samples:
        return FlowFactorResult(None, "empty", {}, 0, arrival, nan)
    # 1. Clean the readings.
    kept: list[FlowSample] = []
    max_flow_per_s = o.max_rate_rad_s * float(calib.flow_pixels_per_rad)
    for s in sorted(samples, key=lambda s: s.t):
        f = np.asarray(s.flow, float)
        if not (f.shape == (2,) and np.all(np.isfinite(f)) and np.isfinite(s.dt)):
            skipped["non-finite"] += 1
        elif not 0.0 < s.dt <= FLOW_MAX_DT_S:
            skipped["bad-interval"] += 1  # (a flow sensor integrates over 10-100 ms)
        elif s.quality >= 0 and s.quality < o.quality_min:
            skipped["gated:quality"] += 1
        elif math.hypot(f[0], f[1]) > max_flow_per_s * s.dt:
            skipped["implausible-rate"] += 1
        else:
            kept.append(s)
    # 2. Gate the window on height and tilt.
    body_T_flow = np.asarray(calib.body_T_flow, float)
    if kept:
        reason = None
        if height is None:
            reason = "no-height"
        else:
            cos_tilt = 1.0
            if world_R_body is not None:
                cos_tilt = -float((np.asarray(world_R_body) @ body_T_flow[:3, 2])[2])
            ok, why = gate_flow(
                float(height),
                cos_tilt,
                -1.0,
                o.height_min,
                o.height_max,
                math.radians(o.max_tilt_deg),
                o.quality_min,
            )
            if not ok:
                reason = "gated:" + (
                    "height" if why.startswith(("height", "non-finite")) else "tilt"
                )
        if reason is not None:
            skipped[reason] += len(kept)
            return FlowFactorResult(None, reason, dict(skipped), 0, arrival, nan)
    if len(kept) < max(1, int(o.min_readings)):
        if kept:
            skipped["few-readings"] += len(kept)
        return FlowFactorResult(None, "few-readings", dict(skipped), 0, arrival, nan)
    if len(imu_t) < 2:
        # No IMU over the window (a dropout shorter than the smoother's gap limit): the
        # rotational part cannot be removed (it raised from the gyro integral).
        skipped["no-imu"] += len(kept)
        return FlowFactorResult(None, "no-imu", dict(skipped), 0, arrival, nan)
    # 3. Sum the readings; mean rate over their intervals.
    ends = np.array([s.t for s in kept], float)
    dts = np.array([s.dt for s in kept], float)
    starts = ends - dts
    flow = np.sum([np.asarray(s.flow, float) for s in kept], axis=0)
    dt = float(dts.sum())
    rot = mean_rate_over(imu_t, imu_omega, starts, ends).sum(axis=0)
    omega = rot / dt - (np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, float))
    ppr = float(calib.flow_pixels_per_rad)
    flow = linearise_flow(flow, dt, ppr, calib.flow_rate_gain)
    # 4. Noise of the sum (correlated runs), in flow units.
    sigma = _run_sigma(ends, starts, dts, o.sigma_rad * ppr, o.lag1_corr)
    noise: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(2, sigma)
    if robust is not None:
        noise = robust(noise)
    factor = make_optical_flow_factor(
        pose_key,
        velocity_key,
        ground_key,
        FlowMeasurement(flow, dt),
        omega,
        FlowSensor(body_T_flow, ppr),
        noise,
    )
    arrival = max(float(s.arrival) for s in kept)
    return FlowFactorResult(factor, "ok", dict(skipped), len(kept), arrival, sigma)


def flow_body_velocity(
    flow: np.ndarray,
    dt: float,
    body_omega: np.ndarray,
    height: float,
    world_R_body: np.ndarray,
    body_T_flow: np.ndarray,
    pixels_per_rad: float,
) -> np.ndarray:
    """Horizontal body velocity [m/s] (3,) that explains a (summed) flow reading: the flow model
    of ``factors/optical_flow.py`` solved for the sensor's x, y velocity with no velocity along the
    optical axis, moved to the body origin (lever arm) and expressed in body axes (z = 0 for a
    level sensor). A dead-reckoning velocity for initial values and checks; NaN when the sensor's
    distance to the ground is not positive."""
    A = np.asarray(body_T_flow, float)[:3, :3].T
    lever = np.asarray(body_T_flow, float)[:3, 3]
    R = np.asarray(world_R_body, float)
    c = -float((R @ np.asarray(body_T_flow, float)[:3, 2])[2])
    if not (height > 0 and c > 0 and dt > 0):
        return np.full(3, np.nan)
    q = c / height
    w = A @ np.asarray(body_omega, float)
    rate = np.asarray(flow, float) / (pixels_per_rad * dt)
    v_sensor = np.array([-(rate[0] + w[1]) / q, -(rate[1] - w[0]) / q, 0.0])
    return A.T @ v_sensor - np.cross(body_omega, lever)


def flow_sensor_height(
    range_m: float, world_R_body: np.ndarray, body_T_range: np.ndarray, body_T_flow: np.ndarray
) -> float:
    """Height [m] of the flow sensor above the ground seen by a range reading ``range_m`` along
    the rangefinder's beam (its +z axis), both sensors at their lever arms, flat ground."""
    R = np.asarray(world_R_body, float)
    cos_range = -float((R @ body_T_range[:3, 2])[2])
    return float(range_m * cos_range - (R @ body_T_range[:3, 3])[2] + (R @ body_T_flow[:3, 3])[2])


#: Reasons a reading itself is rejected (not its window's height or tilt gate).
READING_REJECT_REASONS = ("non-finite", "bad-interval", "gated:quality", "implausible-rate")
#: Sensor time [s] over which every flow reading rejected makes a warning.
FLOW_ALL_REJECTED_S = 5.0


class FlowRejectWatch:
    """Tells when a flow stream is rejected entirely: once every reading over
    :data:`FLOW_ALL_REJECTED_S` of sensor time has been rejected by its own gates (quality,
    interval, rate, non-finite; not the window's height or tilt gate), one warning naming the
    counts by reason. Fed the readings of each window in time order (:meth:`add`; a window not
    newer than the last is ignored, so a rebuild does not count twice).

    :meth:`report` (``info["flow_all_rejected"]`` online, ``info["flow"]["all_rejected"]`` in
    batch): None while a usable reading came within every span, else the first run of rejected
    readings: ``since_s``, ``until_s`` (sensor time), ``readings``, ``reasons`` (counts), and
    ``runs`` (how many such runs).
    """

    def __init__(self, name: str = "flow", span_s: float = FLOW_ALL_REJECTED_S) -> None:
        self.name = name
        self.span_s = float(span_s)
        self._last = -math.inf
        self._start: float | None = None
        self._n = 0
        self._reasons: Counter[str] = Counter()
        self._first: dict[str, Any] | None = None
        self._runs = 0
        self._counted = False  # the current run has been counted in _runs

    def add(self, t_first: float, t_last: float, n: int, skipped: dict[str, int]) -> None:
        """A window of ``n`` readings from ``t_first`` to ``t_last`` [s] and its skip counts."""
        if n <= 0 or not t_last > self._last:
            return
        self._last = float(t_last)
        rejected = {r: int(skipped.get(r, 0)) for r in READING_REJECT_REASONS if skipped.get(r)}
        if sum(rejected.values()) < n:
            self._start, self._n, self._reasons, self._counted = None, 0, Counter(), False
            return
        if self._start is None:
            self._start = float(t_first)
        self._n += n
        self._reasons.update(rejected)
        if self._last - self._start < self.span_s:
            return
        if not self._counted:
            self._counted = True
            self._runs += 1
        if self._first is None:
            log.warning(
                "%s: every flow reading rejected for %.1f s (%.2f-%.2f s, %d readings: %s); the "
                "flow stream is not used",
                self.name,
                self._last - self._start,
                self._start,
                self._last,
                self._n,
                ", ".join(f"{r} {c}" for r, c in sorted(self._reasons.items())),
            )
        if self._first is None or self._first["since_s"] == self._start:
            self._first = {
                "since_s": self._start,
                "until_s": self._last,
                "readings": self._n,
                "reasons": dict(self._reasons),
            }

    def restart(self) -> None:
        """A new run of the stream (the smoother reset, its clock may restart): the current run
        ends; the report of the first one is kept."""
        self._last = -math.inf
        self._start, self._n, self._reasons, self._counted = None, 0, Counter(), False

    @property
    def rejecting(self) -> bool:
        """A run of rejected readings longer than the span lasts now."""
        return self._counted

    def current(self) -> dict[str, Any]:
        """The current run: ``since_s``, ``until_s``, ``readings``, ``reasons``."""
        return {
            "since_s": self._start,
            "until_s": self._last,
            "readings": self._n,
            "reasons": dict(self._reasons),
        }

    def report(self) -> dict[str, Any] | None:
        return None if self._first is None else {**self._first, "runs": self._runs}


class FlowFactors:
    """The flow windows of one flight, for :class:`fgnav.solvers.graph.GraphBuilder`.

    Args:
        flight: the flight (needs ``flow``, ``imu``; ``range`` for the height gate).
        options: flow options.
        skip: the builder's counter of skipped measurements, ``skip(reason, n)``.
    """

    def __init__(
        self, flight: Flight, options: FlowFactorOptions, skip: Callable[[str, int], None]
    ):
        self.flight = flight
        self.options = options
        self._skip = skip
        self.flow = flight.flow
        self.window: np.ndarray = np.array([], dtype=int)
        self.by_keyframe: dict[int, np.ndarray] = {}
        self.height: dict[int, float | None] = {}
        self.counts: Counter[str] = Counter()
        self.watch = FlowRejectWatch(flight.name)

    def associate(self, t_kf: np.ndarray, R_kf: np.ndarray) -> None:
        """Keyframe window of every reading and the flow-sensor height at each keyframe."""
        fl = self.flow
        K = len(t_kf)
        if K > 1:
            mids = 0.5 * (t_kf[1:] + t_kf[:-1])
            edges = np.r_[
                t_kf[0] - 0.5 * (t_kf[1] - t_kf[0]), mids, t_kf[-1] + 0.5 * (t_kf[-1] - t_kf[-2])
            ]
        else:
            edges = np.array([t_kf[0] - 0.05, t_kf[0] + 0.05])
        centre = fl.t - 0.5 * fl.dt
        k = np.searchsorted(edges, centre, side="left") - 1
        outside = (k < 0) | (k >= K)
        self._skip("flow:outside-keyframes", int(outside.sum()))
        k = np.where(outside, -1, k)
        self.window = k
        order = np.argsort(k, kind="stable")
        ks = k[order]
        starts = np.searchsorted(ks, np.arange(K), side="left")
        ends = np.searchsorted(ks, np.arange(K), side="right")
        self.by_keyframe = {
            int(j): order[a:b] for j, (a, b) in enumerate(zip(starts, ends, strict=True)) if b > a
        }
        self.counts["flow-samples"] = len(fl)
        rng = self.flight.range
        T_range = np.asarray(self.flight.calib.body_T_range, float)
        T_flow = np.asarray(self.flight.calib.body_T_flow, float)
        calib = self.flight.calib
        limits = (
            None
            if rng is None
            else RangeLimits.of_stream(rng.range, calib.range_min, calib.range_max)
        )
        # The readings that are distances (range_refusal: not out of the limits, at the floor
        # or at the maximum); the nearest of them within height_max_age_s gives the height.
        usable = np.array([], dtype=int) if rng is None else np.flatnonzero(limits.mask(rng.range))
        t_use = np.asarray(rng.t, float)[usable] if len(usable) else np.array([])
        for j in self.by_keyframe:
            self.height[j] = None
            if len(usable) == 0:
                continue
            i = int(np.searchsorted(t_use, t_kf[j]))
            cand = [c for c in (i - 1, i) if 0 <= c < len(usable)]
            c = min(cand, key=lambda c: abs(t_use[c] - t_kf[j]))
            if abs(t_use[c] - t_kf[j]) > self.options.height_max_age_s:
                continue
            r = float(rng.range[usable[c]])
            self.height[j] = flow_sensor_height(r, R_kf[j], T_range, T_flow)

    def keyframes(self) -> list[int]:
        """Keyframes that own at least one reading."""
        return sorted(self.by_keyframe)

    def samples_at(self, k: int) -> list[FlowSample]:
        """The readings of keyframe k's window as events (arrival = measurement time)."""
        fl = self.flow
        q = fl.quality
        return [
            FlowSample(
                float(fl.t[i]),
                float(fl.t[i]),
                float(fl.dt[i]),
                fl.flow[i],
                float(q[i]) if q is not None else -1.0,
            )
            for i in self.by_keyframe.get(k, ())
        ]

    def arrival(self, k: int) -> float:
        """Arrival of keyframe k's window: its newest reading [s]."""
        idx = self.by_keyframe.get(k)
        return float(self.flow.t[idx].max()) if idx is not None and len(idx) else float("nan")

    def factor_at(
        self,
        k: int,
        keys: tuple[int, int, int],
        imu_t: np.ndarray,
        imu_omega: np.ndarray,
        gyro_bias: np.ndarray,
        R_k: np.ndarray,
        robust: Callable[[gtsam.noiseModel.Base], gtsam.noiseModel.Base] | None,
    ) -> FlowFactorResult:
        """The factor of keyframe k's window (skips counted on the builder)."""
        res = flow_keyframe_factor(
            self.samples_at(k),
            imu_t,
            imu_omega,
            self.flight.calib,
            *keys,
            self.options,
            gyro_bias=gyro_bias,
            height=self.height.get(k),
            world_R_body=R_k,
            robust=robust,
        )
        for reason, n in res.skipped.items():
            self._skip(f"flow:{reason}", n)
        idx = self.by_keyframe.get(k)
        if idx is not None and len(idx):
            t = self.flow.t[idx]
            self.watch.add(float(t.min()), float(t.max()), len(idx), res.skipped)
        if res.factor is not None:
            self.counts["flow-readings-used"] += res.n_used
        return res

    def velocity_hint(
        self, R_kf: np.ndarray, imu_t: np.ndarray, imu_omega: np.ndarray, gyro_bias: np.ndarray
    ) -> np.ndarray:
        """(K, 3) body velocity at each keyframe from its window's readings alone
        (:func:`flow_body_velocity`; quality-gated readings out); NaN where the window has no
        reading or no height. Initial values and the accelerometer check use it."""
        K = len(R_kf)
        out = np.full((K, 3), np.nan)
        fl = self.flow
        q = fl.quality
        T_flow = np.asarray(self.flight.calib.body_T_flow, float)
        ppr = float(self.flight.calib.flow_pixels_per_rad)
        for k, idx in self.by_keyframe.items():
            h = self.height.get(k)
            if h is None or not self.options.height_min <= h <= self.options.height_max:
                continue
            if q is not None:
                idx = idx[~(q[idx] < self.options.quality_min) | (q[idx] < 0)]
            if len(idx) == 0:
                continue
            ends, dts = fl.t[idx], fl.dt[idx]
            dt = float(dts.sum())
            rot = mean_rate_over(imu_t, imu_omega, ends - dts, ends).sum(axis=0)
            omega = rot / dt - np.asarray(gyro_bias, float)
            flow = linearise_flow(
                fl.flow[idx].sum(axis=0), dt, ppr, self.flight.calib.flow_rate_gain
            )
            out[k] = flow_body_velocity(flow, dt, omega, float(h), R_kf[k], T_flow, ppr)
        return out

    def report(self) -> dict[str, Any]:
        return {
            "options": dataclasses.asdict(self.options),
            **dict(self.counts),
            "all_rejected": self.watch.report(),
        }
