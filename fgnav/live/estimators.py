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
* ``msf-ekf``, ``ekf004``, ``ukf003``, ``cf-ekf``, ``ekf-flow002``: the event-fed filter
  baselines (``[msf-ekf]``, ``[ekf004]``, ``[ukf003]``, ``[cf-ekf]``, ``[ekf-flow002]``: the
  options classes ``fgnav.methods`` fills for them) behind :class:`FilterLive` adapters
  (:class:`MsfLive`, :class:`Ekf004Live`, :class:`Ukf003Live`, :class:`CfEkfLive`,
  :class:`Flow002Live`), which give them the same shape: their newest state as an
  ``OnlineState`` at an output rate on the IMU's clock.

Not here: ``ii-observer`` (no covariance, a calibrated drag coefficient; its
:class:`~fgnav.baselines.seed000.Seed000` is event-fed) and ``ekf-vo002`` (images: not on the
link).
"""

from __future__ import annotations

import importlib
import math
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np

from fgnav.baselines._inputs import IMU_GAP_S
from fgnav.datasets.errors import FgnavError
from fgnav.datasets.events import STREAM_OF_EVENT, Event, ImuSample, RangeReading, SlamPose
from fgnav.datasets.geometry import make_pose, quat_wxyz_to_matrix
from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, RangeLimits
from fgnav.datasets.types import Calibration
from fgnav.estimate import Estimate, OnlineState

#: An IMU stamp back by more than this [s], or ahead by more than the filters' ``IMU_GAP_S``,
#: waits for the next sample to decide it (the push engine's ``clock_jump_s`` and
#: ``max_imu_gap_s`` defaults).
CLOCK_JUMP_S = 1.0
OUTPUT_RESTART_S = 1.0
"""A filter's output schedule starts again at a stamp this far (or one output interval, if
longer) before the next output [s]."""


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


DEFAULT_ESTIMATOR = "online"

CONFIG_TABLES = {
    "online": ["graph", "online", "priors"],
    "msf-ekf": ["msf-ekf"],
    "ekf004": ["ekf004"],
    "ukf003": ["ukf003"],
    "cf-ekf": ["cf-ekf"],
    "ekf-flow002": ["ekf-flow002"],
}
"""``--config`` tables each estimator reads."""


def make_estimator(name: str, calib: Calibration, config: Mapping[str, Any]) -> LiveEstimator:
    """Build the estimator ``name`` of :data:`ESTIMATORS`."""
    if name not in ESTIMATORS:
        raise LiveEstimatorError(f"unknown estimator {name!r}; expected one of {list(ESTIMATORS)}")
    return ESTIMATORS[name](calib, config)


# ----------------------------------------------------------------------------------------------
# The filter baselines behind the push API
# ----------------------------------------------------------------------------------------------

QUALITY_SIGMA_M = 0.1
"""A filter's quality is ``100 / (1 + sigma / QUALITY_SIGMA_M)`` with ``sigma`` the RMS position
standard deviation [m]: 91 at 1 cm, 50 at 10 cm, 9 at 1 m; 0 (unknown) without a covariance."""


def quality_from_pose_cov(pose_cov: np.ndarray | None) -> int:
    """0-100 quality from the translation block of a pose covariance (:data:`QUALITY_SIGMA_M`)."""
    if pose_cov is None:
        return 0
    sigma = math.sqrt(max(float(np.trace(pose_cov[3:6, 3:6])) / 3.0, 0.0))
    return int(round(100.0 / (1.0 + sigma / QUALITY_SIGMA_M)))


class FilterLive:
    """An event-fed filter baseline (``start(calib, name)``, ``feed(ev)``, ``result()``) with the
    push API of the online smoother.

    The common part: events of streams the filter does not use are counted as
    ``"<stream>:not_used"``; ``feed`` returns an :class:`~fgnav.estimate.OnlineState` at most
    every ``1 / output_rate_hz`` seconds of the filter's state time (the IMU clock), else None;
    ``latest()``; ``counts()``; ``result()`` is the filter's causal estimate with
    ``info["live_counts"]``. A filter keeps its vehicle state across SLAM map resets, so
    ``reset_counter`` stays 0.

    A subclass names ``USED_STREAMS`` and its ``FILTER`` (built from ``options``, default the
    filter's options class, and started with ``calib``; the output rate ``rate_hz``, default
    ``RATE_HZ`` or else the options' ``output_rate_hz``) and supplies :meth:`_feed` (feed the
    filter, return the time of its newest state or None), :meth:`_state` (that state as an
    ``OnlineState``) and :meth:`_filter_counts` (``used``, ``late`` and ``dropped`` counts from
    the filter's own). A filter's newest output time is its ``output_t`` (cheap: :meth:`_feed`
    runs per event), the output itself ``latest_output()`` (read at the output rate only).
    """

    USED_STREAMS: tuple[str, ...] = ()
    FILTER: tuple[str, str, str] = ("", "", "")
    """The filter: its module, class and options class."""
    RATE_HZ: float | None = None
    """Default output rate [Hz]; None: the options' ``output_rate_hz``."""
    TABLE: str = ""
    """The ``--config`` table of its options (the estimator's name)."""

    @classmethod
    def from_config(cls, calib: Calibration, config: Mapping[str, Any]) -> FilterLive:
        """The adapter with its options from the ``[TABLE]`` table of ``config`` (the
        :data:`ESTIMATORS` factory; a live link has no flight metadata: ``drag_k`` and the like
        come from the table or the defaults)."""
        from fgnav.methods import _options

        module, _, options_name = cls.FILTER
        options_cls = getattr(importlib.import_module(module), options_name)
        return cls(calib, _options(options_cls, config, cls.TABLE))

    def __init__(
        self,
        calib: Calibration,
        options: Any = None,
        name: str = "live",
        rate_hz: float | None = None,
    ) -> None:
        module_name, filter_name, options_name = self.FILTER
        module = importlib.import_module(module_name)
        self.options = options or getattr(module, options_name)()
        self._calib = calib
        self._filter = getattr(module, filter_name)(options=self.options)
        self._filter.start(calib, name)
        rate = rate_hz or self.RATE_HZ or self.options.output_rate_hz
        self._dt_out = 1.0 / rate
        self._next_out: float | None = None
        self._received: Counter[str] = Counter()
        self._dropped: Counter[str] = Counter()
        self._latest: OnlineState | None = None
        self._imu_last: float | None = None  # newest IMU stamp taken
        self._suspect: list[Event] | None = None  # an IMU sample off the clock, events behind

    def feed(self, ev: Event) -> OnlineState | None:
        """One event; an IMU sample off the clock (back by more than :data:`CLOCK_JUMP_S` or
        ahead by more than :data:`IMU_GAP_S`) waits with the events behind it for the next
        IMU sample, which decides it as the push engine does: kept when that one continues
        from it, else dropped as ``imu:time-outlier`` (one stamp an hour ahead overflowed a
        filter's state; review)."""
        held = self._suspect
        if held is None:
            if isinstance(ev, ImuSample) and self._imu_last is not None:
                dt = float(ev.t) - self._imu_last
                if -dt > CLOCK_JUMP_S or dt > IMU_GAP_S:
                    self._suspect = [ev]
                    return None
            return self._take(ev)
        if not isinstance(ev, ImuSample):
            held.append(ev)
            return None
        self._suspect = None
        suspect, last, t = held[0], self._imu_last, float(ev.t)
        out = None
        if not (0.0 < t - last <= IMU_GAP_S) or 0.0 < t - float(suspect.t) <= t - last:
            out = self._take(suspect)  # confirmed: a real gap or clock restart
        else:
            self._received["imu"] += 1
            self._dropped["imu:time-outlier"] += 1
        for e in (*held[1:], ev):
            out = self._take(e) or out
        return out

    def _take(self, ev: Event) -> OnlineState | None:
        stream = STREAM_OF_EVENT[type(ev)]
        if stream == "imu":
            self._imu_last = float(ev.t)
        self._received[stream] += 1
        if stream not in self.USED_STREAMS:
            self._dropped[f"{stream}:not_used"] += 1
            return None
        t = self._feed(ev)
        if t is None:
            return None
        if self._next_out is None or t < self._next_out - max(OUTPUT_RESTART_S, self._dt_out):
            # The first state, or the clock went back (a restart): the schedule starts again.
            self._next_out = t
        if t < self._next_out:
            return None
        # The next output time after t (a loop of += dt never ended on a stamp of 1.8e13 s).
        self._next_out += (math.floor((t - self._next_out) / self._dt_out) + 1) * self._dt_out
        if self._next_out <= t:
            self._next_out = t + self._dt_out
        self._latest = self._state(t)
        return self._latest

    def latest(self) -> OnlineState | None:
        return self._latest

    def counts(self) -> dict[str, dict[str, int]]:
        used, late, dropped = self._filter_counts()
        dropped = Counter(dropped)
        dropped.update(self._dropped)
        return {
            "received": dict(sorted(self._received.items())),
            "used": {k: v for k, v in used.items() if v},
            "late": {k: v for k, v in late.items() if v},
            "dropped": {k: v for k, v in sorted(dropped.items()) if v},
        }

    def close(self) -> None:
        """The link stopped: a suspect IMU sample's events go on without it (:meth:`result`
        calls it too)."""
        held, self._suspect = self._suspect, None
        if held:
            self._received["imu"] += 1
            self._dropped["imu:time-outlier"] += 1
            for e in held[1:]:
                self._take(e)

    def result(self) -> Estimate:
        self.close()
        est = self._filter.result()
        est.info["live_counts"] = self.counts()
        return est

    @staticmethod
    def _online_state(
        t: float,
        world_T_body: np.ndarray,
        world_v_body: np.ndarray,
        pose_cov: np.ndarray | None = None,
        vel_cov: np.ndarray | None = None,
        accel_bias: np.ndarray | None = None,
        gyro_bias: np.ndarray | None = None,
        **extra: Any,
    ) -> OnlineState:
        """An ``OnlineState`` with the quality from ``pose_cov`` (zero biases when the filter has
        none)."""
        return OnlineState(
            t=float(t),
            world_T_body=world_T_body,
            world_v_body=np.array(world_v_body, float),
            accel_bias=np.zeros(3) if accel_bias is None else np.array(accel_bias, float),
            gyro_bias=np.zeros(3) if gyro_bias is None else np.array(gyro_bias, float),
            pose_cov=pose_cov,
            vel_cov=vel_cov,
            reset_counter=0,
            quality=quality_from_pose_cov(pose_cov),
            **extra,
        )

    # -- per filter ----------------------------------------------------------------------------

    def _feed(self, ev: Event) -> float | None:
        raise NotImplementedError

    def _state(self, t: float) -> OnlineState:
        raise NotImplementedError

    def _filter_counts(self) -> tuple[dict[str, int], dict[str, int], dict[str, int]]:
        raise NotImplementedError


def _slam_range_dropped(c: Any) -> dict[str, int]:
    """The link's dropped counts from a :class:`~fgnav.baselines._counts.SlamRangeCounts` (the
    counts the SLAM-and-range filters share)."""
    return {
        "slam:gate": c.slam_rejected_gate,
        "slam:waiting_new_map_scale": c.slam_waiting_reinit,
        "range:gate": c.range_rejected_gate,
        "range:tilt": c.range_rejected_tilt,
    }


class MsfLive(FilterLive):
    """:class:`~fgnav.baselines.msf_ekf.MsfEkf` with the push API (:class:`FilterLive`): its state
    at each IMU sample, at ``output_rate_hz`` (default 20 Hz), once the filter has started."""

    USED_STREAMS = ("imu", "attitude", "slam", "range")
    FILTER = ("fgnav.baselines.msf_ekf", "MsfEkf", "MsfOptions")
    TABLE = "msf-ekf"

    def __init__(self, calib: Calibration, options=None, name: str = "live") -> None:
        super().__init__(calib, options, name)
        self._imu_used = 0
        self._session = 0  # newest SLAM session fed (the scale reported is the filter's one)
        self._range_limits = RangeLimits(calib.range_min, calib.range_max)

    def _feed(self, ev: Event) -> float | None:
        if isinstance(ev, RangeReading):
            # (the filter's own test, range_refusal)
            self._range_limits.see(float(ev.range))
            why = self._range_limits.refusal(float(ev.range))
            if why in RANGE_LIMIT_TAGS:
                self._dropped[f"range:{why.replace('-', '_')}"] += 1
            elif why is not None:
                self._dropped["range:out_of_limits"] += 1
        if isinstance(ev, SlamPose):
            self._session = int(ev.session)
        self._filter.feed(ev)
        if not isinstance(ev, ImuSample) or self._filter.latest() is None:
            return None
        self._imu_used += 1
        return ev.t

    def _state(self, t: float) -> OnlineState:
        from fgnav.baselines.msf_ekf import IV, pose_covariance

        x = self._filter.latest()
        return self._online_state(
            t,
            make_pose(x.R, x.p),
            x.v,
            pose_covariance(x),
            x.P[IV : IV + 3, IV : IV + 3].copy(),
            x.ba,
            x.bg,
            slam_scale={self._session: float(x.s)},
        )

    def _filter_counts(self) -> tuple[dict[str, int], dict[str, int], dict[str, int]]:
        c = self._filter.counts
        used = {"imu": self._imu_used, "slam": c.slam_updates, "range": c.range_updates}
        dropped = {**_slam_range_dropped(c), "slam_or_range:older_than_buffer": c.too_old}
        return used, {"slam_or_range": c.replayed}, dropped


EKF004_RATE_HZ = 100.0
""":class:`Ekf004Live`'s output rate [Hz] (a state per attitude sample of a 100 Hz AHRS)."""

#: The link's stream of each measurement kind of :class:`~fgnav.baselines.ekf004.Ekf004Counts`
#: (longest prefix first), and the link's names of two skip reasons.
_EKF004_STREAMS = (
    ("vertical_speed", "range"),
    ("yaw_rate", "imu"),
    ("attitude", "attitude"),
    ("gyro", "imu"),
    ("imu", "imu"),
    ("yaw", "yaw"),
    ("range", "range"),
    ("slam", "slam"),
    ("scale", "slam"),
)
_EKF004_SKIPS = {"range": "range:unusable", "vertical_speed": "range:vertical_speed_gap"}


def _ekf004_key(kind: str, table: str) -> str:
    """``"stream:reason"`` of a gated or skipped ``Ekf004Counts`` key."""
    if table == "skipped" and kind in _EKF004_SKIPS:
        return _EKF004_SKIPS[kind]
    prefix, stream = next(((p, s) for p, s in _EKF004_STREAMS if kind.startswith(p)), (kind, kind))
    if table == "gated":
        return f"{stream}:gate" if kind == stream else f"{stream}:{kind}_gate"
    rest = kind[len(prefix) :].lstrip("_") if prefix == stream else kind
    return f"{stream}:{rest or kind}"


class Ekf004Live(FilterLive):
    """:class:`~fgnav.baselines.ekf004.Ekf004Runner` (seed 004's EKF with delay compensation)
    with the push API (:class:`FilterLive`).

    The runner holds the first ``fgnav.baselines.ekf004.SOURCES_WINDOW_S`` of events and decides
    from them its ``"auto"`` attitude source (``ATTITUDE_QUATERNION`` among them: the stream,
    else the attitude estimated from the IMU) and scale source (``ml`` with the stream, else
    ``imu_fit``), and which of yaw and range its start waits for; ``[ekf004]
    attitude_source`` / ``scale_source`` set them. Its states are the causal trajectory (the state
    at each attitude sample, before later corrections; from the first scale fit on with
    ``imu_fit``), at ``rate_hz``; the pose covariance maps the Euler-angle errors to the body
    rotation (:meth:`~fgnav.baselines.ekf004.Ekf004.pose_cov`); no IMU biases (zero); the drag
    coefficient is the fixed ``drag_k``; the SLAM scale that of the newest pose's session. It
    runs in the link's FLU body (no internal thrust body as :func:`run_ekf004` for an x-up IMU).
    A SLAM pose older than the filter counts as late (it is rolled back and replayed);
    attitude samples are ``attitude:not_used`` when the attitude comes from the IMU.
    """

    USED_STREAMS = ("imu", "attitude", "yaw", "range", "slam")
    FILTER = ("fgnav.baselines.ekf004", "Ekf004Runner", "Ekf004Options")
    TABLE = "ekf004"
    RATE_HZ = EKF004_RATE_HZ

    def __init__(
        self, calib: Calibration, options=None, name: str = "live", rate_hz: float | None = None
    ) -> None:
        super().__init__(calib, options, name, rate_hz)
        self._late: Counter[str] = Counter()
        self._session: int | None = None

    def _feed(self, ev: Event) -> float | None:
        f = self._filter
        if isinstance(ev, SlamPose):
            self._session = int(ev.session)
            if f.latest() is not None and ev.t < f.ekf.t:
                self._late["slam"] += 1
        f.feed(ev)
        return f.output_t

    def _state(self, t: float) -> OnlineState:
        from fgnav.baselines.ekf004 import IP, IR, IV, IY, state_covariances
        from fgnav.datasets.geometry import rpy_to_matrix

        _, x, P = self._filter.latest_output()
        pose_cov, vel_cov = state_covariances(x, P)
        sess = self._filter.sessions.get(self._session)
        scale = {} if sess is None or sess.scale is None else {self._session: float(sess.scale)}
        return self._online_state(
            t,
            make_pose(rpy_to_matrix(*x[IR : IY + 1]), x[IP : IP + 3]),
            x[IV : IV + 3],
            pose_cov,
            vel_cov,
            slam_scale=scale,
            drag_k=np.array(self.options.drag_k, float),
        )

    def _filter_counts(self) -> tuple[dict[str, int], dict[str, int], dict[str, int]]:
        f = self._filter
        c = f.counts
        used = {
            "imu": f.imu_used,
            "attitude": c.used.get("attitude", 0) if f.attitude_source == "stream" else 0,
            "yaw": c.used.get("yaw", 0),
            "range": c.used.get("vertical_speed", 0),
            "slam": c.used.get("slam", 0) + c.used.get("slam_reset", 0),
        }
        dropped: Counter[str] = Counter()
        for table in ("gated", "skipped"):
            for kind, n in getattr(c, table).items():
                dropped[_ekf004_key(kind, table)] += n
        if f.attitude_source == "imu":
            dropped["attitude:not_used"] += self._received["attitude"]
        return used, dict(self._late), dict(dropped)


UKF003_LAG_S = 0.2
""":class:`Ukf003Live` holds events back this long [s] (at least the SLAM latency: the simulated
flights' 0.1 s plus jitter) so that each SLAM pose's camera trigger reaches the filter before the
IMU samples after its capture time."""


class Ukf003Live(FilterLive):
    """:class:`~fgnav.baselines.ukf003.Ukf003` with the push API (:class:`FilterLive`).

    The UKF clones its state when an image is taken (a camera trigger at the capture time ``t``)
    and fuses the SLAM pose of that image when it arrives (``t + latency``). A live link has no
    trigger message, so the adapter holds every event back for ``lag_s`` of arrival time and, when
    a SLAM pose arrives, inserts its trigger at ``t`` among the held events (after the IMU samples
    of equal time, as :meth:`Ukf003.run` orders them): the filter then sees what
    :meth:`Ukf003.run` feeds it, and its states come ``lag_s`` late (their ``t`` says so). A pose
    later than ``lag_s`` finds no clone and is counted as ``"slam:no_clone"``; tracking-lost poses
    (negative session) as ``"slam:tracking_lost"``. :meth:`close` feeds what is held.

    The states are the filter's causal trajectory (``output_rate_hz``, default 100 Hz, on the IMU
    clock) at ``output_rate_hz`` of this adapter's own (``rate_hz``, default the filter's); the
    pose and velocity covariances come from the Euler-angle and body-velocity state to first
    order (:func:`fgnav.baselines.ukf003.state_covariances`); ``ground_height`` is the altimeter
    bias ``z_b``; the SLAM scale is that of the filter's session. The filter runs in the link's
    FLU body (it does not switch to an internal thrust body as :meth:`Ukf003.run` does for an
    x-up IMU). Attitude samples are passed on even when the filter does not fuse them
    (``use_attitude``): its start takes the initial attitude from them.
    """

    USED_STREAMS = ("imu", "attitude", "slam", "range", "yaw")
    FILTER = ("fgnav.baselines.ukf003", "Ukf003", "Ukf003Options")
    TABLE = "ukf003"

    def __init__(
        self,
        calib: Calibration,
        options=None,
        name: str = "live",
        lag_s: float = UKF003_LAG_S,
        rate_hz: float | None = None,
    ) -> None:
        self.lag_s = float(lag_s)
        super().__init__(calib, options, name, rate_hz)
        self._imu_used = 0
        self._held: list[Any] = []
        self._released = -math.inf  # arrival time of the newest event fed to the filter

    def _feed(self, ev: Event) -> float | None:
        from fgnav.baselines.ukf003 import CameraTrigger

        if isinstance(ev, SlamPose):
            if ev.session < 0:
                self._dropped["slam:tracking_lost"] += 1
                return None
            if ev.t > self._released:
                k = len(self._held)
                while k and (
                    self._held[k - 1].arrival > ev.t
                    or (
                        self._held[k - 1].arrival == ev.t
                        and not isinstance(self._held[k - 1], ImuSample)
                    )
                ):
                    k -= 1
                self._held.insert(k, CameraTrigger(float(ev.t), float(ev.t)))
        self._held.append(ev)
        self._release(ev.arrival - self.lag_s)
        return self._filter.output_t

    def _release(self, until: float) -> None:
        k = 0
        while k < len(self._held) and self._held[k].arrival <= until:
            ev = self._held[k]
            self._filter.feed(ev)
            self._released = ev.arrival
            if isinstance(ev, ImuSample) and self._filter.latest() is not None:
                self._imu_used += 1
            k += 1
        del self._held[:k]

    def close(self) -> None:
        """Feed the filter every event still held (the link stopped)."""
        super().close()
        self._release(math.inf)

    def _state(self, t: float) -> OnlineState:
        from fgnav.baselines.ukf003 import (
            IBA,
            IBG,
            IP,
            IPHI,
            IS,
            IV,
            IZB,
            euler_to_matrix,
            state_covariances,
        )

        _, x, P = self._filter.latest_output()
        world_R_body = euler_to_matrix(x[None, IPHI : IPHI + 3])[0]
        pose_cov, vel_cov = state_covariances(x, P)
        session = self._filter.session
        return self._online_state(
            t,
            make_pose(world_R_body, x[IP : IP + 3]),
            world_R_body @ x[IV : IV + 3],
            pose_cov,
            vel_cov,
            x[IBA : IBA + 3],
            x[IBG : IBG + 3],
            slam_scale={} if session is None else {int(session): float(x[IS])},
            ground_height=float(x[IZB]),
        )

    def _filter_counts(self) -> tuple[dict[str, int], dict[str, int], dict[str, int]]:
        c = self._filter.counts
        used = {
            "imu": self._imu_used,
            "slam": c.slam_updates,
            "range": c.range_updates,
            "yaw": c.yaw_updates,
            "attitude": c.attitude_updates,
        }
        dropped = {
            **_slam_range_dropped(c),
            "slam:no_clone": c.slam_no_clone,
            "slam:out_of_order": c.slam_out_of_order,
            "range:out_of_limits": c.range_out_of_limits,
            "range:at_min": c.extra.get("range_at_min", 0),
            "range:at_max": c.extra.get("range_at_max", 0),
            "yaw:gate": c.yaw_rejected_gate,
            "attitude:gate": c.attitude_rejected_gate,
        }
        return used, {}, dropped


class CfEkfLive(FilterLive):
    """:class:`~fgnav.baselines.cf_ekf.CfEkf` (the Crazyflie's ``kalman_core`` with flow and
    time-of-flight) with the push API (:class:`FilterLive`).

    The states are the filter's causal trajectory (after each prediction step, at
    ``output_rate_hz``, default 100 Hz, on the IMU clock); the pose covariance takes the
    body-frame attitude error as it is and the world velocity's includes the attitude's share
    (:func:`fgnav.baselines.cf_ekf.state_covariances`). The filter has no IMU biases (reported as
    zero) and no SLAM. Flow measures velocity, so the horizontal position is unobservable: its
    variance sits at the firmware's bound (``MAX_COVARIANCE``, 100 m^2) and the quality at 1
    (flowdeck seed 0).
    """

    USED_STREAMS = ("imu", "flow", "range")
    FILTER = ("fgnav.baselines.cf_ekf", "CfEkf", "CfEkfOptions")
    TABLE = "cf-ekf"

    def __init__(self, calib: Calibration, options=None, name: str = "live") -> None:
        super().__init__(calib, options, name)
        self._imu_used = 0

    def _feed(self, ev: Event) -> float | None:
        self._filter.feed(ev)
        t = self._filter.output_t
        if t is not None:
            self._imu_used += isinstance(ev, ImuSample)
        return t

    def _state(self, t: float) -> OnlineState:
        from fgnav.baselines.cf_ekf import IP, IU, state_covariances

        _, S, q, P = self._filter.latest_output()
        world_R_body = quat_wxyz_to_matrix(q)
        pose_cov, vel_cov = state_covariances(world_R_body, S, P)
        v = world_R_body @ S[IU : IU + 3]
        return self._online_state(t, make_pose(world_R_body, S[IP : IP + 3]), v, pose_cov, vel_cov)

    def _filter_counts(self) -> tuple[dict[str, int], dict[str, int], dict[str, int]]:
        c = self._filter.counts
        used = {"imu": self._imu_used, "flow": c.flow_updates, "range": c.tof_updates}
        dropped = {
            "flow:outlier": c.flow_outliers,
            "flow:low_quality": c.flow_low_quality,
            "flow:before_start": c.flow_before_start,
            "range:outlier": c.tof_outliers,
            "range:tilt": c.tof_tilted,
        }
        return used, {}, dropped


EKF_FLOW002_RATE_HZ = 100.0
""":class:`Flow002Live`'s output rate [Hz] (a state per flow reading of a 100 Hz flow deck)."""


class Flow002Live(FilterLive):
    """:class:`~fgnav.baselines.seed002_flow.Seed002Flow` (seed 002's attitude-and-height EKF
    with optical-flow dead reckoning) with the push API (:class:`FilterLive`).

    Its state is that of the newest used flow reading (``t`` the reading's time), at most
    ``rate_hz``: the dead-reckoned position, the EKF attitude and the trailing-window velocity
    as :meth:`~fgnav.baselines.seed002_flow.Seed002Flow.result` reports them. The dead reckoning
    has no covariance (its x, y drift is unbounded), so ``pose_cov`` and ``vel_cov`` are None and
    ``quality`` is 0 (unknown; the link sends ``ODOMETRY.quality`` 1); no IMU biases (zero).
    """

    USED_STREAMS = ("imu", "yaw", "range", "flow")
    FILTER = ("fgnav.baselines.seed002_flow", "Seed002Flow", "Seed002FlowOptions")
    TABLE = "ekf-flow002"
    RATE_HZ = EKF_FLOW002_RATE_HZ

    def _feed(self, ev: Event) -> float | None:
        self._filter.feed(ev)
        return self._filter.output_t

    def _state(self, t: float) -> OnlineState:
        _, p, q, v = self._filter.latest_output()
        return self._online_state(t, make_pose(quat_wxyz_to_matrix(q), p), v)

    def _filter_counts(self) -> tuple[dict[str, int], dict[str, int], dict[str, int]]:
        c, e = self._filter.counts, self._filter.ekf_counts
        used = {
            "imu": e.get("accel", 0) + e.get("accel_gated", 0),
            "flow": c["flow_used"],
            "range": e.get("range", 0),
            "yaw": e.get("yaw", 0),
        }
        dropped = {
            "flow:low_quality": c["flow_low_quality"],
            "flow:no_height": c["flow_no_height"],
            "flow:too_low": c["flow_low"],
            "flow:tilted": c["flow_tilted"],
            "flow:before_start": c["flow_before_start"],
            "range:out_of_limits": c["range_out_of_limits"],
            "range:at_min": c.get("range_at_min", 0),
            "range:at_max": c.get("range_at_max", 0),
            "range:tilt": e.get("range_tilt", 0),
            "range:outlier": e.get("range_outlier", 0),
        }
        return used, {}, dropped


ESTIMATORS: dict[str, EstimatorFactory] = {
    "online": online_smoother,
    **{a.TABLE: a.from_config for a in (MsfLive, Ekf004Live, Ukf003Live, CfEkfLive, Flow002Live)},
}
"""Estimators by name (``fgnav live --estimator``): the push-API smoother and the filter
baselines behind :class:`FilterLive` adapters, each with its ``--config`` table."""
