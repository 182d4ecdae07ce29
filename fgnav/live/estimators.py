"""Estimators the live link can drive: anything with ``feed``, ``latest``, ``counts``, ``result``.

The link is written against the push API of ``fgnav.solvers.online.OnlineSmoother`` (its module
docstring; DESIGN.md's event-stream data flow): ``feed(event)`` in arrival order returns the newest
state when the event closed a keyframe (else None); ``latest()``; ``counts()`` as ``{"received":
{stream: n}, "used": ..., "late": ..., "dropped": {"stream:reason": n}}``; ``result()`` the causal
:class:`~fgnav.estimate.Estimate`. A state is an :class:`~fgnav.estimate.OnlineState` (the link
sends its ``t``, ``world_T_body``, ``world_v_body``, ``gyro_bias``, ``pose_cov``, ``vel_cov``,
``reset_counter`` and ``quality``).

A factory ``make(calib, config) -> estimator`` builds one from the calibration and the
``--config`` tables. :data:`ESTIMATORS` names them:

* ``online``: the push-API fixed-lag smoother (``[graph]``, ``[online]`` and ``[priors]``
  tables: the front-ends that supply priors run inside it on the link's events), imported
  when called;
* ``msf-ekf``: the MSF-style EKF baseline (``[msf-ekf]``) behind :class:`MsfLive`, which gives
  it the same shape (its states at ``output_rate_hz`` on the IMU's clock).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np

from fgnav.datasets.errors import FgnavError
from fgnav.datasets.events import STREAM_OF_EVENT, Event, ImuSample, RangeReading, SlamPose
from fgnav.datasets.geometry import make_pose
from fgnav.datasets.types import Calibration
from fgnav.estimate import Estimate, OnlineState


class LiveEstimatorError(FgnavError, RuntimeError):
    """The requested estimator cannot be built."""


class LiveEstimator(Protocol):
    """What the live link needs of an estimator (the push API)."""

    def feed(self, event: Event) -> Any | None: ...

    def latest(self) -> Any | None: ...

    def counts(self) -> dict[str, dict[str, int]]: ...

    def result(self) -> Estimate: ...

    # Optional: ``close()``, called once when the link stops, before ``counts()`` and
    # ``result()`` (the online smoother takes or counts the input it holds).


EstimatorFactory = Callable[[Calibration, Mapping[str, Any]], LiveEstimator]


def online_smoother(calib: Calibration, config: Mapping[str, Any]) -> LiveEstimator:
    """The push-API fixed-lag smoother ``fgnav.solvers.online.OnlineSmoother``."""
    try:
        from fgnav.solvers.online import OnlineSmoother
    except ModuleNotFoundError as e:
        if e.name != "fgnav.solvers.online":
            raise
        raise LiveEstimatorError(
            "the push-API online smoother (fgnav.solvers.online) is not in this version of "
            "fgnav; use --estimator msf-ekf"
        ) from None
    from fgnav.methods import fixed_lag_options, online_prior_options

    # [priors]: the front-end prior stage inside the smoother, fed the link's events (drag_k
    # from the table: a live link has no flight metadata).
    priors = online_prior_options(None, config)
    return OnlineSmoother(calib, fixed_lag_options(config), name="live", priors=priors)


def msf_ekf(calib: Calibration, config: Mapping[str, Any]) -> LiveEstimator:
    """The MSF-style EKF baseline with the push API (:class:`MsfLive`), ``[msf-ekf]`` table."""
    from fgnav.baselines.msf_ekf import MsfOptions
    from fgnav.methods import _options

    return MsfLive(calib, _options(MsfOptions, config, "msf-ekf"))


ESTIMATORS: dict[str, EstimatorFactory] = {"online": online_smoother, "msf-ekf": msf_ekf}
"""Estimators by name (``fgnav live --estimator``)."""

DEFAULT_ESTIMATOR = "online"

CONFIG_TABLES = {"online": ["graph", "online", "priors"], "msf-ekf": ["msf-ekf"]}
"""``--config`` tables each estimator reads."""


def make_estimator(name: str, calib: Calibration, config: Mapping[str, Any]) -> LiveEstimator:
    """Build the estimator ``name`` of :data:`ESTIMATORS`."""
    if name not in ESTIMATORS:
        raise LiveEstimatorError(f"unknown estimator {name!r}; expected one of {list(ESTIMATORS)}")
    return ESTIMATORS[name](calib, config)


# ----------------------------------------------------------------------------------------------
# The MSF-style EKF behind the push API
# ----------------------------------------------------------------------------------------------

QUALITY_SIGMA_M = 0.1
""":class:`MsfLive`'s quality is ``100 / (1 + sigma / QUALITY_SIGMA_M)`` with ``sigma`` the
RMS position standard deviation [m]: 91 at 1 cm, 50 at 10 cm, 9 at 1 m."""


class MsfLive:
    """:class:`~fgnav.baselines.msf_ekf.MsfEkf` with the push API of the online smoother.

    ``feed`` returns a state every ``1 / output_rate_hz`` seconds of IMU time once the filter
    has started. The filter keeps its vehicle state across SLAM map resets, so
    ``reset_counter`` stays 0. Events it does not use (yaw, images, flow) are counted as
    ``"<stream>:not_used"``.
    """

    USED_STREAMS = ("imu", "attitude", "slam", "range")

    def __init__(self, calib: Calibration, options=None, name: str = "live") -> None:
        from fgnav.baselines.msf_ekf import MsfEkf, MsfOptions

        self.options = options or MsfOptions()
        self._calib = calib
        self._ekf = MsfEkf(self.options)
        self._ekf.start(calib, name)
        self._dt_out = 1.0 / self.options.output_rate_hz
        self._next_out: float | None = None
        self._received: Counter[str] = Counter()
        self._dropped: Counter[str] = Counter()
        self._imu_used = 0
        self._latest: OnlineState | None = None
        self._session = 0  # newest SLAM session fed (the scale reported is the filter's one)

    def feed(self, ev: Event) -> OnlineState | None:
        stream = STREAM_OF_EVENT[type(ev)]
        self._received[stream] += 1
        if stream not in self.USED_STREAMS:
            self._dropped[f"{stream}:not_used"] += 1
            return None
        if isinstance(ev, RangeReading) and not (
            self._calib.range_min <= ev.range <= self._calib.range_max
        ):
            self._dropped["range:out_of_limits"] += 1
        if isinstance(ev, SlamPose):
            self._session = int(ev.session)
        self._ekf.feed(ev)
        if not isinstance(ev, ImuSample) or self._ekf.latest() is None:
            return None
        self._imu_used += 1
        if self._next_out is None:
            self._next_out = ev.t
        if ev.t < self._next_out:
            return None
        while self._next_out <= ev.t:
            self._next_out += self._dt_out
        self._latest = self._state(ev.t)
        return self._latest

    def latest(self) -> OnlineState | None:
        return self._latest

    def _state(self, t: float) -> OnlineState:
        from fgnav.baselines.msf_ekf import IV, pose_covariance

        x = self._ekf.latest()
        pose_cov = pose_covariance(x)
        sigma = math.sqrt(max(float(np.trace(pose_cov[3:6, 3:6])) / 3.0, 0.0))
        return OnlineState(
            t=float(t),
            world_T_body=make_pose(x.R, x.p),
            world_v_body=x.v.copy(),
            accel_bias=x.ba.copy(),
            gyro_bias=x.bg.copy(),
            pose_cov=pose_cov,
            vel_cov=x.P[IV : IV + 3, IV : IV + 3].copy(),
            slam_scale={self._session: float(x.s)},
            reset_counter=0,
            quality=int(round(100.0 / (1.0 + sigma / QUALITY_SIGMA_M))),
        )

    def counts(self) -> dict[str, dict[str, int]]:
        c = self._ekf.counts
        used = {"imu": self._imu_used, "slam": c.slam_updates, "range": c.range_updates}
        dropped = Counter(self._dropped)
        dropped.update(
            {
                "slam:gate": c.slam_rejected_gate,
                "slam:waiting_new_map_scale": c.slam_waiting_reinit,
                "range:gate": c.range_rejected_gate,
                "range:tilt": c.range_rejected_tilt,
                "slam_or_range:older_than_buffer": c.too_old,
            }
        )
        return {
            "received": dict(sorted(self._received.items())),
            "used": {k: v for k, v in used.items() if v},
            "late": {"slam_or_range": c.replayed} if c.replayed else {},
            "dropped": {k: v for k, v in sorted(dropped.items()) if v},
        }

    def result(self) -> Estimate:
        est = self._ekf.result()
        est.info["live_counts"] = self.counts()
        return est
