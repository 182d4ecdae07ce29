"""Seed 002's attitude-and-height EKF with an optical-flow dead reckoning in place of its
homography VO: the paper's system (Paz & Nesmachnow, ../shared/seeds/002_*.txt, sec. III-B) as it
would run on a vehicle with a flow deck (issue 17), fed events in arrival order.

1. The ``[q0 q1 q2 q3 h]`` EKF (:class:`fgnav.frontends.attitude_ekf.AttitudeHeightEkf`, eqs.
   11-21): gyro prediction and accelerometer gravity update on every IMU sample, yaw ``[cos,
   sin]`` update when the flight has a yaw stream, tilted-rangefinder height update (the first
   valid reading sets the height). Its attitude and height make the flow metric (the first
   coupling of the paper, with the flow sensor instead of the camera).
2. Flow dead reckoning, per reading (``FlowSeries`` convention, sensor frame ``body_T_flow``):
   the rotational part is removed with the gyro (mean of the IMU samples over the reading's
   interval, no bias: the paper's EKF has none), the translational image motion times the
   distance along the optical axis ``d = (h + (R t_flow)_z) / cos(tilt)`` gives the sensor's
   velocity across the axis, ``v_s,xy = -(flow / (ppr dt) - rot) d``; the component along the
   axis is chosen so that the world vertical velocity equals the rate of the EKF height (low-passed
   with ``height_rate_tau_s``); the body velocity is ``body_R_flow v_s - omega x t_flow`` and the
   world velocity ``R`` times it. The position integrates it (eqs. 9-10 of the paper, the VO
   translation replaced by flow) from the world origin, over the time since the previous used
   reading (a gap is crossed at the new reading's velocity); z is the EKF height (plus
   ``ground_height``).

Readings are skipped (counted) when their quality is below ``quality_min``, the EKF height is not
known yet, the sensor is lower than ``height_min`` or tilted more than ``max_tilt_deg``.

Output, ``Estimate(method="ekf-flow002", causal=True)`` at every used reading: the dead-reckoned
x, y, the EKF height as z, the EKF attitude, and ``world_v_body`` as the mean velocity over the
trailing ``velocity_window_s`` (the per-reading flow velocity carries the sensor's quantisation
noise: 0.2 px per 10 ms reading at 48 px/rad and 0.8 m is 0.33 m/s); no covariance.

Not modelled (as in the paper): gyro bias, vehicle acceleration in the gravity update (gated),
non-flat ground, time offsets.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from fgnav.baselines._inputs import Inputs, unused_table
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import (
    Event,
    FlowSample,
    ImuSample,
    RangeReading,
    YawReading,
    replay_flight,
)
from fgnav.datasets.geometry import quat_wxyz_to_matrix
from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, RangeLimits
from fgnav.datasets.types import Calibration, Flight, Trajectory
from fgnav.estimate import Estimate, TimeSeries
from fgnav.frontends.attitude_ekf import (
    INIT_ACCEL_WINDOW_S,
    AttitudeEkfOptions,
    AttitudeHeightEkf,
    initial_attitude_from_accel,
)

log = logging.getLogger(__name__)

REQUIRED_STREAMS = ("imu", "flow", "range")

#: The attitude-and-height EKF's counts of measurements it did not use, as ``info["unused"]``
#: keys (:mod:`fgnav.baselines._inputs`).
_EKF_UNUSED_KEYS = {
    "accel_gated": "imu:accel-gated",
    "range_tilt": "range:tilted",
    "range_outlier": "range:outlier",
}


@dataclass
class Seed002FlowOptions:
    """Options of :class:`Seed002Flow`.

    Attributes:
        ekf: options of the ``[q, h]`` EKF (seed 002 sec. III-B).
        quality_min: flow readings of lower quality are skipped (unknown quality, < 0, is not).
        height_min: no dead reckoning below this sensor height [m].
        max_tilt_deg: no dead reckoning with the optical axis tilted more than this [deg].
        height_rate_tau_s: time constant of the low-pass on the EKF height rate [s].
        velocity_window_s: the reported velocity is the mean over this trailing window [s].
        ground_height: world z of the ground [m], added to the EKF height for z.
    """

    ekf: AttitudeEkfOptions = field(default_factory=AttitudeEkfOptions)
    quality_min: float = 0.5
    height_min: float = 0.1
    max_tilt_deg: float = 35.0
    height_rate_tau_s: float = 0.1
    velocity_window_s: float = 0.1
    ground_height: float = 0.0

    def check(self) -> None:
        """Raise ``ValueError`` naming the first invalid option (the sign rules of
        :func:`fgnav.config.option_value_problem` apply before)."""
        for name in ("height_rate_tau_s", "velocity_window_s"):
            if not getattr(self, name) > 0:
                raise ValueError(
                    f"Seed002FlowOptions.{name}={getattr(self, name)!r}: expected > 0 [s]"
                )


class Seed002Flow:
    """The attitude-and-height EKF plus flow dead reckoning (module docstring), event-fed:
    :meth:`start`, :meth:`feed` in arrival order, :meth:`latest`, :meth:`result`."""

    def __init__(self, options: Seed002FlowOptions | None = None) -> None:
        self.opt = options or Seed002FlowOptions()
        self.counts: dict[str, int] = {
            "flow_used": 0,
            "flow_non_finite": 0,
            "flow_bad_interval": 0,
            "flow_implausible_rate": 0,
            "flow_low_quality": 0,
            "flow_no_height": 0,
            "flow_low": 0,
            "flow_tilted": 0,
            "flow_before_start": 0,
            "range_out_of_limits": 0,
        }

    def start(self, calib: Calibration, name: str = "flight") -> None:
        """Prepare to be fed events of a vehicle with calibration ``calib``."""
        self._calib = calib
        self._name = name
        self._ppr = float(calib.flow_pixels_per_rad)
        T = np.asarray(calib.body_T_flow, float)
        self._body_R_flow, self._body_t_flow = T[:3, :3], T[:3, 3]
        self._ekf: AttitudeHeightEkf | None = None
        self._init_acc: list[np.ndarray] = []
        self._t_first: float | None = None
        self._yaw0: float | None = None
        self._last: ImuSample | None = None
        self._imu_hist: deque[tuple[float, np.ndarray]] = deque()
        self._height_ok = False
        self._h_prev: tuple[float, float] | None = None
        self._h_rate = 0.0
        self._xy = np.zeros(2)
        self._t_prev_used: float | None = None
        self._out_t: list[float] = []
        self._out_p: list[np.ndarray] = []
        self._out_q: list[np.ndarray] = []
        self._lat: list[float] = []
        self._t0 = time.perf_counter()
        self._inputs = Inputs("ekf-flow002", name)
        self._range_limits = RangeLimits(calib.range_min, calib.range_max)
        # The flow factors' plausibility bounds (imported here: fgnav.solvers.flow loads GTSAM).
        from fgnav.solvers.flow import FLOW_MAX_DT_S, FlowFactorOptions

        self._flow_max_dt = FLOW_MAX_DT_S
        self._flow_max_rate = FlowFactorOptions.max_rate_rad_s

    def feed(self, ev: Event) -> None:
        """One measurement event, in arrival order (IMU, yaw, range, flow; others ignored; a
        corrupted IMU sample is dropped and counted: :mod:`fgnav.baselines._inputs`)."""
        if not self._inputs.take(ev):
            return
        if isinstance(ev, ImuSample):
            self._imu(ev)
        elif isinstance(ev, YawReading):
            if self._ekf is None:
                self._yaw0 = float(ev.yaw) if self._yaw0 is None else self._yaw0
            else:
                self._predict_to(ev.t)
                self._ekf.update_yaw(float(ev.yaw))
        elif isinstance(ev, RangeReading):
            self._range(ev)
        elif isinstance(ev, FlowSample):
            self._flow(ev)

    def latest(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(world_t_body, world_q_body_wxyz)`` of the newest used reading (None before)."""
        if not self._out_t:
            return None
        return self._out_p[-1].copy(), self._out_q[-1].copy()

    @property
    def ekf_counts(self) -> dict[str, int]:
        """The attitude-and-height EKF's counts (empty before it starts)."""
        return dict(self._ekf.counts) if self._ekf is not None else {}

    @property
    def output_t(self) -> float | None:
        """Time of the newest used reading (None before the first)."""
        return self._out_t[-1] if self._out_t else None

    def latest_output(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
        """``(t, world_t_body, world_q_body_wxyz, world_v_body)`` of the newest used reading as
        :meth:`result` reports it: the velocity is the mean over the trailing
        ``velocity_window_s`` (zero at the first reading, where :meth:`result` repeats the first
        windowed value); None before the first."""
        n = len(self._out_t)
        if n == 0:
            return None
        w = self.opt.velocity_window_s
        k0 = max(bisect.bisect_left(self._out_t, self._out_t[-1] - w) - 1, 0)
        t, p = np.asarray(self._out_t[k0:]), np.array(self._out_p[k0:])
        v, _ = window_velocity(t, p, np.array([n - 1 - k0]), w)
        return self._out_t[-1], self._out_p[-1].copy(), self._out_q[-1].copy(), v[0]

    # -- steps ------------------------------------------------------------------------------------

    def _imu(self, ev: ImuSample) -> None:
        if self._ekf is None:
            if self._t_first is None:
                self._t_first = ev.t
            self._init_acc.append(np.asarray(ev.body_accel, float))
            if ev.t - self._t_first >= INIT_ACCEL_WINDOW_S:
                q0 = initial_attitude_from_accel(np.mean(self._init_acc, axis=0), self._yaw0 or 0.0)
                T = np.asarray(self._calib.body_T_range, float)
                self._ekf = AttitudeHeightEkf(
                    self.opt.ekf,
                    q0,
                    0.0,
                    beam_body=T[:3, 2],
                    body_t_range=T[:3, 3],
                    gyro_noise_density=self.opt.ekf.gyro_noise_density
                    or self._calib.imu_noise.gyro_noise_density,
                )
                self._last = ev
            return
        self._predict_to(ev.t)
        self._last = ev
        self._ekf.update_accel(ev.body_accel)
        self._imu_hist.append((ev.t, np.asarray(ev.body_omega, float)))
        while self._imu_hist and self._imu_hist[0][0] < ev.t - 1.0:
            self._imu_hist.popleft()

    def _predict_to(self, t: float) -> None:
        if self._last is not None and t > self._last.t:
            self._ekf.predict(self._last.body_omega, t - self._last.t)
            self._last = self._last._replace(t=t)

    def _range(self, ev: RangeReading) -> None:
        self._range_limits.see(float(ev.range))  # (every reading: its floor, range_clamps)
        if self._ekf is None:
            return
        why = self._range_limits.refusal(float(ev.range))
        if why in RANGE_LIMIT_TAGS:
            key = f"range_{why.replace('-', '_')}"  # range_at_min, range_at_max: no distance
            self.counts[key] = self.counts.get(key, 0) + 1
            return
        if why is not None:
            self.counts["range_out_of_limits"] += 1
            return
        self._predict_to(ev.t)
        if not self._height_ok:
            self._ekf.reset_height(float(ev.range))
            self._height_ok = True
        else:
            self._ekf.update_range(float(ev.range))
        h = self._ekf.height
        if self._h_prev is not None and ev.t > self._h_prev[0]:
            rate = (h - self._h_prev[1]) / (ev.t - self._h_prev[0])
            a = 1.0 - math.exp(-(ev.t - self._h_prev[0]) / self.opt.height_rate_tau_s)
            self._h_rate += a * (rate - self._h_rate)
        self._h_prev = (ev.t, h)

    def _mean_rate(self, t0: float, t1: float) -> np.ndarray:
        ws = [w for t, w in self._imu_hist if t0 - 1e-9 <= t < t1 - 1e-9]
        if not ws:
            return self._last.body_omega if self._last is not None else np.zeros(3)
        return np.mean(ws, axis=0)

    def _flow(self, ev: FlowSample) -> None:
        o, cnt = self.opt, self.counts
        if self._ekf is None:
            cnt["flow_before_start"] += 1
            return
        f = np.asarray(ev.flow, float)
        dt = float(ev.dt)
        # The flow-factor gate (fgnav.solvers.flow): a reading is image motion over its own
        # interval, which a flow sensor integrates over 10-100 ms.
        if not (f.shape == (2,) and np.all(np.isfinite(f)) and math.isfinite(dt)):
            cnt["flow_non_finite"] += 1
            return
        if not 0.0 < dt <= self._flow_max_dt:
            cnt["flow_bad_interval"] += 1
            return
        if math.hypot(f[0], f[1]) > self._flow_max_rate * self._ppr * dt:
            cnt["flow_implausible_rate"] += 1
            return
        if 0 <= ev.quality < o.quality_min:
            cnt["flow_low_quality"] += 1
            return
        if not self._height_ok:
            cnt["flow_no_height"] += 1
            return
        w0 = time.perf_counter()
        self._predict_to(ev.t)
        ekf = self._ekf
        R = quat_wxyz_to_matrix(ekf.world_q_body_wxyz)
        axis = R @ self._body_R_flow[:, 2]
        cos_tilt = -float(axis[2])
        h = ekf.height + float((R @ self._body_t_flow)[2])
        if h < o.height_min:
            cnt["flow_low"] += 1
            return
        if cos_tilt < math.cos(math.radians(o.max_tilt_deg)):
            cnt["flow_tilted"] += 1
            return
        d = h / cos_tilt
        omega = self._mean_rate(ev.t - dt, ev.t)
        w_s = self._body_R_flow.T @ omega
        rot = np.array([-w_s[1], w_s[0]])
        v_xy = -(f / (self._ppr * dt) - rot) * d
        a = R @ self._body_R_flow
        v_axis = (self._h_rate - a[2, 0] * v_xy[0] - a[2, 1] * v_xy[1]) / a[2, 2]
        body_v = self._body_R_flow @ np.r_[v_xy, v_axis] - np.cross(omega, self._body_t_flow)
        world_v = R @ body_v
        # The velocity (of the reading's own interval dt, gated above: a dt of 1e-6 s made it
        # 1e4 times the noise) is held since the previous used reading, so that readings
        # skipped in between (tilt, height) leave no hole; at most FLOW_MAX_DT_S, the longest
        # interval a reading may cover (after a long stretch without a used reading, over dt).
        span = dt if self._t_prev_used is None else ev.t - self._t_prev_used
        if not 0.0 < span <= self._flow_max_dt:
            span = dt
        self._xy = self._xy + world_v[:2] * span
        self._t_prev_used = ev.t
        self._out_t.append(float(ev.t))
        self._out_p.append(np.r_[self._xy, ekf.height + o.ground_height])
        self._out_q.append(ekf.world_q_body_wxyz)
        cnt["flow_used"] += 1
        self._lat.append(time.perf_counter() - w0)

    def unused(self) -> dict[str, int]:
        """What was not used, ``stream:reason -> count`` (:mod:`fgnav.baselines._inputs`)."""
        c = self.counts
        return unused_table(
            self._inputs.unused,
            {
                f"flow:{k[len('flow_') :].replace('_', '-')}": v
                for k, v in c.items()
                if k.startswith("flow_") and k != "flow_used"
            },
            {
                "range:out-of-limits": c["range_out_of_limits"],
                "range:at-min": c.get("range_at_min", 0),
                "range:at-max": c.get("range_at_max", 0),
            },
            {key: self.ekf_counts.get(k, 0) for k, key in _EKF_UNUSED_KEYS.items()},
        )

    # -- whole flight -----------------------------------------------------------------------------

    def run(self, flight: Flight) -> Estimate:
        """Run over a flight's IMU, yaw, range and flow events in arrival order."""
        check_flight(flight)
        self.start(flight.calib, flight.name)
        for ev in replay_flight(flight, ("imu", "yaw", "range", "flow")):
            self.feed(ev)
        return self.result()

    def result(self) -> Estimate:
        """The causal estimate of everything fed so far."""
        if len(self._out_t) < 2:
            raise FlightDataError(
                f"{self._name}: the seed-002 flow dead reckoning used fewer than 2 flow readings "
                f"({self.counts})"
            )
        t = np.asarray(self._out_t)
        p = np.array(self._out_p)
        v, ok = window_velocity(t, p, np.arange(len(t)), self.opt.velocity_window_s)
        v[~ok] = v[ok][0] if ok.any() else 0.0
        traj = Trajectory(
            t=t, world_t_body=p, world_q_body_wxyz=np.array(self._out_q), world_v_body=v
        )
        return Estimate(
            method="ekf-flow002",
            trajectory=traj,
            series={"ekf_height": TimeSeries(t=t.copy(), value=p[:, 2] - self.opt.ground_height)},
            update_latency=np.asarray(self._lat),
            runtime_s=time.perf_counter() - self._t0,
            causal=True,
            info={
                "options": dataclasses.asdict(self.opt),
                "counts": dict(self.counts),
                "ekf_counts": self.ekf_counts,
                "unused": self.unused(),
                **self._inputs.info(("flow", "range")),
            },
        ).check()


def window_velocity(
    t: np.ndarray, p: np.ndarray, k: np.ndarray, window_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Causal velocity at the samples ``k`` of the positions ``p`` at times ``t``: the position
    difference over the trailing ``window_s`` (at least the previous sample). Returns ``(v,
    ok)``, ``v`` zero where there is no earlier sample (``ok`` False)."""
    j = np.searchsorted(t, t[k] - window_s, side="left")
    j = np.minimum(j, k - 1).clip(0)
    span = t[k] - t[j]
    v = np.zeros((len(k), p.shape[1]))
    ok = span > 0
    v[ok] = (p[k[ok]] - p[j[ok]]) / span[ok, None]
    return v, ok


def check_flight(flight: Flight) -> None:
    """Raise :class:`FlightDataError` naming every missing input of the baseline."""
    flight.require_streams(REQUIRED_STREAMS, "the seed-002 EKF + flow dead reckoning")


def run_seed002_flow(flight: Flight, options: Seed002FlowOptions | None = None) -> Estimate:
    """Run seed 002's EKF with flow dead reckoning over a flight (library entry point)."""
    return Seed002Flow(options).run(flight)
