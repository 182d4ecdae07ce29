"""The front-ends that supply priors (seed 000's I&I observer velocity, seed 004's closed-form ML
scale) as one event-fed stage: :class:`FrontendPriorStage` (issue 14, build item 3).

Fed the measurement events of :mod:`fgnav.datasets.events` in arrival order (``feed``), it gives
from what has arrived only:

* ``velocity_at(t)``: the observer's ``world_v_body`` [m/s] at the processed IMU sample nearest
  ``t`` with its set sigma (the observer is deterministic: ``PriorOptions.velocity_sigma``), from
  ``settle_time`` after the first IMU sample on (the observer has not converged before);
* ``scale(session)``: the ML scale ``s`` [SLAM units per metre] of a SLAM session and its Fisher
  sigma, once ``min_pairs`` vertical displacement pairs have been accepted.

Pipeline, per IMU sample (processed once the next IMU sample has arrived, and with the attitude
stream once an attitude sample at or after it has arrived, so that the interpolation brackets it):

1. attitude: the attitude stream interpolated at the IMU time (normalised linear interpolation,
   as :func:`fgnav.datasets.geometry.interpolate_quat_wxyz`), or, when no attitude sample has
   arrived within ``ATTITUDE_WAIT_S`` of the first IMU sample, seed 002's attitude EKF
   (:class:`fgnav.frontends.attitude_ekf.AttitudeEkfStage`) fed the IMU, yaw and range;
2. the vertical filter (:class:`fgnav.frontends.ii_observer.VerticalFilter`): range readings
   taken up to the sample (a reading arriving after its sample was processed is applied at the
   next one), then the prediction to the next sample -> ``world_vz`` and the height;
3. ``observer``: :class:`fgnav.frontends.ii_observer.IIObserverStepper` (by default full
   kinematics, SLAM axes aligned by attitude, as :func:`fgnav.frontends.pipeline.observer_priors`;
   the seed-000 baseline, :class:`fgnav.baselines.seed000.Seed000`, runs this stage with its own
   observer, alignment and vertical filter options and the observer's delay compensation);
4. ``ml-scale``: each SLAM pose whose time the processed IMU has passed joins its session's
   pairs: windows of ``PairOptions.window`` from the session's first pose, the poses nearest each
   window end (within ``max_gap``), the SLAM displacement rotated into world axes by the chordal
   mean of ``world_R_body body_R_cam slam_R_cam^T`` over the session's poses *so far* (the
   whole-flight :func:`fgnav.frontends.scale_ml.scale_pairs_from_flight` uses all of them), its
   vertical component paired with the filtered height's change ->
   :class:`fgnav.frontends.scale_ml.MLScaleEstimator`.

The whole-flight functions of :mod:`fgnav.frontends.pipeline` and
:func:`fgnav.frontends.ii_observer.run_ii_observer` replay a flight into this stage (time order:
the SLAM poses at their capture times) and read its full history (``keep_history``). Not
modelled by default: the SLAM delivery latency inside the observer (a late pose is applied at the
current time, counted ``slam_late``; ``slam_history_s`` > 0 rolls the observer back instead, as
the seed-000 baseline does); the stage is rebuilt, not carried, when the smoother resets.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import AttitudeSample, ImuSample, RangeReading, SlamPose, YawReading
from fgnav.datasets.geometry import nlerp_quat_wxyz, project_to_so3, quat_wxyz_to_matrix
from fgnav.datasets.types import Calibration
from fgnav.frontends.attitude_ekf import AttitudeEkfStage
from fgnav.frontends.ii_observer import (
    IIObserverOptions,
    IIObserverResult,
    IIObserverStepper,
    VerticalFilter,
    VerticalFilterOptions,
    drag_k_problem,
)
from fgnav.frontends.scale_ml import MLScaleEstimator, MLScaleOptions, PairOptions, ScaleResult

PRIOR_SOURCES = ("ml-scale", "observer")
"""Front-ends that can feed the smoother (see :mod:`fgnav.frontends.pipeline`)."""

PRIOR_STREAMS = ("imu", "slam", "range")
"""The streams every front-end prior needs (the observer's SLAM velocity and the ML scale's
pairs both take the vertical filter's rangefinder height)."""

PRIOR_STREAMS_WAIT_S = 5.0
"""A link (``fgnav live``) that has carried this much IMU time [s] without one of
:data:`PRIOR_STREAMS` gets the warning :func:`missing_streams_message` (a flight is checked before
it runs)."""


def missing_streams_message(name: str, sources: Any, missing: Any) -> str:
    """``"NAME: front-end prior 'SOURCE' needs the slam, range stream(s)"`` (the first source):
    the one line ``fgnav batch`` / ``online`` refuse a flight with and ``fgnav live`` warns
    with."""
    return f"{name}: front-end prior '{tuple(sources)[0]}' needs the {', '.join(missing)} stream(s)"


ML_SCALE_SIGMAS = (0.015, 0.02)
"""Displacement noises ``(SLAM units, m)`` of the vertical scale pairs: SLAM position noise of
~1 cm at scale ~1 at both ends; rangefinder height after the vertical filter ~2 cm
(scripts/reproduce_seed004.py uses the same)."""

log = logging.getLogger(__name__)

ATTITUDE_WAIT_S = 0.5
"""Without an attitude sample by this long after the first IMU sample the stage runs the
attitude EKF [s]."""

ATTITUDE_STALL_S = 1.0
"""An attitude stream silent for this long of IMU time (the stage holding IMU samples for it)
is declared stopped: one warning, and the attitude EKF takes over from the held samples on [s]."""

HOLD_MAX_S = 10.0
"""Input held unprocessed (IMU samples waiting for their attitude, range readings and SLAM poses
waiting for the IMU) is dropped, counted, once older than this behind the newest of its stream
[s]: the buffers stay bounded whatever stops."""

HISTORY_S = 10.0
"""Attitude, height and velocity kept for late queries [s]."""


@dataclass(frozen=True)
class PriorOptions:
    """The ``[priors]`` table: which front-ends feed the smoother.

    Attributes:
        sources: names of :data:`PRIOR_SOURCES`.
        drag_k: ``mu/m`` per body axis ``(kx, ky)`` [1/s] (a calibration; the observer needs it).
        velocity_sigma: standard deviation given to each observer velocity component [m/s].
        settle_time: observer outputs earlier than this after the first IMU sample are not
            used [s].
        min_pairs: a session's ML scale is given once this many pairs are accepted.
    """

    sources: tuple[str, ...] = ()
    drag_k: tuple[float, float] | None = None
    velocity_sigma: float = 0.2
    settle_time: float = 5.0
    min_pairs: int = 3

    def check(self, name: str = "[priors]") -> PriorOptions:
        unknown = [s for s in self.sources if s not in PRIOR_SOURCES]
        if unknown:
            raise FlightDataError(
                f"unknown front-end prior(s) {unknown}; valid: {list(PRIOR_SOURCES)}"
            )
        if "observer" in self.sources and self.drag_k is None:
            raise FlightDataError(
                f"{name}: front-end prior 'observer' needs a calibrated drag coefficient "
                "(flight.meta['drag_k'] or [priors] drag_k)"
            )
        return self


def prior_sources(value: Any) -> tuple[str, ...]:
    """``[priors] sources`` as names: a list of names, or one name as a string (``"ml-scale"``
    was read letter by letter); anything else is an error naming the option."""
    if value is None:
        return ()
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise FlightDataError(
            f"[priors]: option sources = {value!r}: expected a list of front-end names "
            f"(from {list(PRIOR_SOURCES)})"
        )
    return tuple(value)


def prior_drag_k(value: Any) -> tuple[float, float] | None:
    """``[priors] drag_k`` as ``(kx, ky)`` [1/s]: one number (both axes) or a list of one or two,
    each finite and > 0; anything else is an error naming the option (a string, an empty list or
    three values were a ValueError, an IndexError or silently cut to two)."""
    if value is None:
        return None
    values = list(value) if isinstance(value, (list, tuple)) else [value]
    ok = 1 <= len(values) <= 2 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
        for v in values
    )
    if not ok:
        raise FlightDataError(
            f"[priors]: option drag_k = {value!r}: expected a number > 0 or a list of two "
            "(kx, ky) [1/s]"
        )
    k = float(values[0]), float(values[-1])
    problem = drag_k_problem(k)  # (1e-300: the observer's velocity priors 1e14 m/s)
    if problem is not None:
        raise FlightDataError(f"[priors]: option drag_k = {value!r}: {problem}")
    return k


def prior_options(table: Any, drag_k: Any = None) -> PriorOptions | None:
    """``PriorOptions`` from a ``[priors]`` table (``sources``, ``drag_k``); ``drag_k``: the
    flight's calibrated value when the table has none. None without sources. The table's values
    are checked (:func:`prior_sources`, :func:`prior_drag_k`) also when there are no sources."""
    table = dict(table or {})
    sources = prior_sources(table.get("sources"))
    k = prior_drag_k(table["drag_k"]) if "drag_k" in table else None
    if not sources:
        return None
    if k is None and drag_k is not None:
        k = tuple(float(v) for v in np.atleast_1d(np.asarray(drag_k, dtype=float))[[0, -1]])
    return PriorOptions(sources=sources, drag_k=k).check()


class _MlSession:
    """Pairing state of one SLAM session (see the module docstring, step 4)."""

    def __init__(self, t0: float, p: np.ndarray, options: MLScaleOptions) -> None:
        self.t0 = t0
        self.n_edge = 0  # index of the window start edge a = t0 + n * window
        self.a = (t0, p)  # the pose chosen for edge a
        self.prev = (t0, p)
        self.M = np.zeros((3, 3))
        self.est = MLScaleEstimator(options)
        self.counts = {"gap": 0, "no_metric": 0}


class FrontendPriorStage:
    """Seed 000's observer and seed 004's ML scale as one event-fed stage (module docstring).

    Args:
        calib: the vehicle's calibration (``body_T_cam``, ``body_T_range``, range limits, IMU
            noise for the attitude EKF).
        options: the ``[priors]`` options.
        keep_history: keep every output (the whole-flight functions read it).
        name: used in messages.
        observer_options: the observer's gains and kinematics (default: full kinematics; its
            ``drag_k`` is ``options.drag_k``). The seed-000 baseline gives its own.
        align_slam_axes: rotate each SLAM session into world axes first (default; False: the
            paper's model, SLAM axes are world axes).
        vertical_options: the vertical filter's options.
        slam_history_s: the observer's delay compensation history
            (:class:`~fgnav.frontends.ii_observer.IIObserverStepper`; 0: a late SLAM pose is
            applied at the current time).
        given_vertical: the world vertical velocity [m/s] and height [m] at an IMU sample's
            time, in place of the vertical filter (an analysis input, e.g. the truth, to test the
            observer alone: :func:`~fgnav.frontends.ii_observer.run_ii_observer`'s ``world_vz``).
    """

    def __init__(
        self,
        calib: Calibration,
        options: PriorOptions,
        keep_history: bool = False,
        name: str = "priors",
        *,
        observer_options: IIObserverOptions | None = None,
        align_slam_axes: bool = True,
        vertical_options: VerticalFilterOptions | None = None,
        slam_history_s: float = 0.0,
        given_vertical: Callable[[float], tuple[float, float]] | None = None,
    ) -> None:
        self.options = options.check()
        self.calib = calib
        self.name = name
        self.keep = keep_history
        self.use_observer = "observer" in options.sources
        self.use_ml = "ml-scale" in options.sources
        self.body_R_cam = np.asarray(calib.body_T_cam, dtype=float)[:3, :3]
        self.vertical = VerticalFilter(
            calib.body_T_range, calib.range_min, calib.range_max, vertical_options
        )
        self.given_vertical = given_vertical
        self.observer_options = dataclasses.replace(
            observer_options or IIObserverOptions(kinematics="full"), drag_k=options.drag_k
        )
        self.stepper = (
            IIObserverStepper(
                self.observer_options,
                options.drag_k,
                self.body_R_cam,
                align_slam_axes,
                history_s=slam_history_s,
            )
            if self.use_observer
            else None
        )
        self.latest_row: tuple | None = None  # (ObserverOutput, q, height) of the newest sample
        sx, sy = ML_SCALE_SIGMAS
        self.ml_options = MLScaleOptions(sigma_slam=sx, sigma_metric=sy)
        self.pair_options = PairOptions(components="vertical")
        self.sessions: dict[int, _MlSession] = {}
        self.counts: dict[str, int] = {}
        self._imu: deque = deque()  # arrived IMU samples not processed yet
        self._att: deque = deque()  # (t, q) of the attitude stream
        self._mode: str | None = None  # "stream" or "ekf" once decided
        self._ekf: AttitudeEkfStage | None = AttitudeEkfStage(calib, name=f"{name}.attitude")
        self._ekf_q: deque = deque()  # (t, q) of the EKF at IMU samples
        self._range: deque = deque()  # (t, r) arrived, not applied yet
        self._slam_ml: deque = deque()  # SLAM poses waiting for the processed IMU
        self._t_first: float | None = None
        self._t_last_imu = -math.inf
        self._t_done = -math.inf  # newest processed IMU sample
        self._hq: deque = deque()  # (t, q) processed attitude
        self._hh: deque = deque()  # (t, h) processed height
        self._vel: deque = deque()  # (t, world_v_body) after the settle time
        self._rows: list = []  # keep_history: (ObserverOutput, q, height)

    # -- public -----------------------------------------------------------------------------

    def feed(self, ev: Any) -> None:
        """One event in arrival order (IMU, attitude, range, yaw, SLAM; others are ignored)."""
        if isinstance(ev, ImuSample):
            t = float(ev.t)
            if not t > self._t_last_imu:
                self._count("imu_out_of_order")
                return
            self._t_last_imu = t
            if self._t_first is None:
                self._t_first = t
            self._imu.append(ev)
            self._feed_ekf(ev)
            self._decide()
            self._check_stall(t)
            self._trim(self._imu, t, "imu_held_too_long", lambda e: e.t)
            self._drain()
        elif isinstance(ev, AttitudeSample):
            q = np.asarray(ev.world_q_body_wxyz, dtype=float)
            if self._att and not ev.t > self._att[-1][0]:
                self._count("attitude_out_of_order")
                return
            if not np.all(np.isfinite(q)):
                return
            if self._mode == "ekf":
                # (after the stream stopped and the EKF took over: not used)
                self._count("attitude_after_fallback")
                return
            self._att.append((float(ev.t), q / np.linalg.norm(q)))
            if len(self._att) > 2 and self._att[1][0] < float(ev.t) - HOLD_MAX_S:
                self._att.popleft()  # (no IMU to interpolate for: the IMU stopped)
            self._decide()
            self._drain()
        elif isinstance(ev, RangeReading):
            if math.isfinite(ev.range):
                self._range.append((float(ev.t), float(ev.range)))
                self._trim(self._range, float(ev.t), "range_held_too_long", lambda r: r[0])
            self._feed_ekf(ev)
        elif isinstance(ev, YawReading):
            self._feed_ekf(ev)
        elif isinstance(ev, SlamPose):
            if self.stepper is not None:
                self.stepper.add_slam(ev.t, ev.slam_t_cam, ev.slam_q_cam_wxyz, ev.session)
            if self.use_ml:
                self._slam_ml.append(ev)
                self._trim(self._slam_ml, float(ev.t), "ml_slam_held_too_long", lambda e: e.t)

    def flush(self) -> None:
        """The end of the input: process the IMU samples still held (the last one without a
        next sample to predict to; attitude clamped to the newest sample)."""
        self._decide(final=True)
        self._drain(final=True)

    def velocity_at(self, t: float, max_dt: float) -> tuple[np.ndarray, float] | None:
        """Observer ``world_v_body`` at the processed sample nearest ``t`` (within ``max_dt``)
        and its sigma, or None (not converged, not processed yet, or no observer)."""
        vel = self._vel
        if not vel:
            return None
        i = len(vel) - 1
        while i > 0 and vel[i][0] > t:
            i -= 1
        cand = [j for j in (i, i + 1) if 0 <= j < len(vel)]
        j = min(cand, key=lambda j: abs(vel[j][0] - t))
        if abs(vel[j][0] - t) > max_dt:
            return None
        return vel[j][1], self.options.velocity_sigma

    def scale(self, session: int) -> tuple[float, float, int] | None:
        """``(s, sigma, n_pairs)`` of a session's ML scale, or None before ``min_pairs``."""
        s = self.sessions.get(session)
        if s is None or s.est.n_pairs < self.options.min_pairs:
            return None
        v, sig = s.est.scale, s.est.sigma
        if not (math.isfinite(v) and v > 0 and math.isfinite(sig) and sig > 0):
            return None
        return float(v), float(sig), s.est.n_pairs

    def scale_result(self) -> ScaleResult:
        """The ML scale of every session so far (as :func:`fgnav.frontends.scale_ml.
        estimate_scale` returns it)."""
        es = {sid: s.est for sid, s in self.sessions.items()}
        return ScaleResult(
            scale={s: e.scale for s, e in es.items()},
            sigma={s: e.sigma for s, e in es.items()},
            history={s: np.asarray(e.history, dtype=float).reshape(-1, 4) for s, e in es.items()},
            counts={s: {**e.counts, **self.sessions[s].counts} for s, e in es.items()},
        )

    def observer_result(self) -> IIObserverResult:
        """The observer's history (``keep_history``) as
        :func:`~fgnav.frontends.ii_observer.run_ii_observer` returns it."""
        if not self.keep or self.stepper is None:
            raise FlightDataError(f"{self.name}: observer history not kept")
        rows = self._rows
        n = len(rows)
        pos = np.full((n, 3), np.nan)
        xi = np.full((n, 2), np.nan)
        sess = np.full(n, -1, dtype=int)
        for i, (o, _, h) in enumerate(rows):
            if o.session >= 0:
                xi[i], sess[i], pos[i, :2] = o.xi, o.session, o.world_xy
            pos[i, 2] = h
        return IIObserverResult(
            t=np.array([o.t for o, _, _ in rows]),
            eta=np.array([o.eta for o, _, _ in rows]).reshape(-1, 2),
            xi=xi,
            world_v_body=np.array([o.world_v_body for o, _, _ in rows]).reshape(-1, 3),
            world_t_body=pos,
            session=sess,
            world_q_body_wxyz=np.array([q for _, q, _ in rows]).reshape(-1, 4),
            counts=self.observer_counts(),
            options=self.observer_options,
            drag_k=self.stepper.observer.k.copy(),
        )

    def observer_counts(self) -> dict[str, int]:
        """The observer's counts as :func:`~fgnav.frontends.ii_observer.run_ii_observer` reports
        them (SLAM poses, capped scale steps, the vertical filter's range readings)."""
        if self.stepper is None:
            return {}
        counts = dict(self.stepper.counts)
        counts["capped_scale_steps"] = self.stepper.observer.capped_steps
        if self.given_vertical is None:
            counts.update({f"range_{k}": v for k, v in self.vertical.counts.items()})
        else:
            counts["height_is_relative"] = 1
        return counts

    @property
    def attitude_mode(self) -> str | None:
        """``"stream"`` (the attitude stream), ``"ekf"`` (the attitude EKF) or None (not
        decided yet)."""
        return self._mode

    @property
    def all_counts(self) -> dict[str, int]:
        """Diagnostics: the stage's, the vertical filter's and the observer's counts."""
        out = dict(self.counts)
        out.update({f"range_{k}": v for k, v in self.vertical.counts.items()})
        if self.stepper is not None:
            out.update({f"observer_{k}": v for k, v in self.stepper.counts.items()})
        for sid, s in self.sessions.items():
            out.update({f"ml_scale[{sid}]_{k}": v for k, v in {**s.est.counts, **s.counts}.items()})
        if self._mode:
            out[f"attitude_{self._mode}"] = 1
        return out

    # -- internals --------------------------------------------------------------------------

    def _count(self, key: str, n: int = 1) -> None:
        self.counts[key] = self.counts.get(key, 0) + n

    def _feed_ekf(self, ev) -> None:
        if self._ekf is None:
            return
        for est in self._ekf.feed(ev):
            self._ekf_q.append((est.t, np.asarray(est.world_q_body_wxyz, dtype=float)))

    def _decide(self, final: bool = False) -> None:
        if self._mode is not None or self._t_first is None:
            return
        if self._att:
            self._mode = "stream"
            self._ekf, self._ekf_q = None, deque()
        elif final or self._t_last_imu >= self._t_first + ATTITUDE_WAIT_S:
            self._mode = "ekf"

    def _trim(self, buf: deque, t: float, key: str, t_of: Callable[[Any], float]) -> None:
        """Drop (counted as ``key``) what ``buf`` has held for more than ``HOLD_MAX_S`` behind
        ``t``."""
        while buf and t_of(buf[0]) < t - HOLD_MAX_S:
            buf.popleft()
            self._count(key)

    def _check_stall(self, t: float) -> None:
        """The attitude stream stopped (no sample for ``ATTITUDE_STALL_S`` of IMU time while IMU
        samples wait for it): one warning, and the attitude EKF takes over, fed the held IMU
        samples (it starts afresh: its start window's samples are dropped, counted as
        ``imu_without_attitude``)."""
        if self._mode != "stream" or not self._att or not self._imu:
            return
        t_att = self._att[-1][0]
        if not (float(self._imu[0].t) > t_att and t - t_att > ATTITUDE_STALL_S):
            return
        log.warning(
            "%s: the attitude stream stopped at t=%.3f s (no sample for %.1f s of IMU time): "
            "the attitude EKF takes over",
            self.name,
            t_att,
            t - t_att,
        )
        self._count("attitude_stream_stopped")
        self._mode = "ekf"
        self._att = deque()
        self._ekf = AttitudeEkfStage(self.calib, name=f"{self.name}.attitude")
        self._ekf_q = deque()
        for ev in self._imu:
            self._feed_ekf(ev)

    def _attitude(self, t: float, final: bool) -> np.ndarray | None:
        """``world_q_body_wxyz`` at IMU time ``t``, or None while it cannot be known yet."""
        if self._mode == "stream":
            att = self._att
            if not att:
                return None
            if att[-1][0] < t:
                if not final:
                    return None
                return att[-1][1]
            while len(att) > 2 and att[1][0] <= t:
                att.popleft()  # keep the sample before t
            if att[0][0] >= t:
                return att[0][1]
            (t0, q0), (t1, q1) = att[0], att[1]
            return nlerp_quat_wxyz(t0, q0, t1, q1, t)
        if self._mode == "ekf":
            eq = self._ekf_q
            while eq and eq[0][0] < t:
                eq.popleft()
            if eq and eq[0][0] == t:
                return eq[0][1]
            return None
        return None

    def _drain(self, final: bool = False) -> None:
        while self._imu and (len(self._imu) >= 2 or final):
            ev = self._imu[0]
            t = float(ev.t)
            q = self._attitude(t, final)
            if q is None:
                if self._mode == "ekf" and (final or (self._ekf_q and self._ekf_q[0][0] > t)):
                    self._imu.popleft()  # the EKF never gave this sample (its start window)
                    self._count("imu_without_attitude")
                    continue
                return
            self._imu.popleft()
            nxt = self._imu[0] if self._imu else None
            self._process(ev, q, None if nxt is None else float(nxt.t))

    def _process(self, ev: ImuSample, q: np.ndarray, t_next: float | None) -> None:
        t = float(ev.t)
        R = quat_wxyz_to_matrix(q)
        acc = np.asarray(ev.body_accel, dtype=float)
        vf = self.vertical
        rng = self._range
        while rng and rng[0][0] <= t:
            tr, r = rng.popleft()
            if tr < self._t_done:
                self._count("range_late")
            vf.update_range(r, R)
        if t_next is not None:
            vf.predict(t_next - t, R, acc)
        vz, h = vf.world_vz, vf.height
        if self.given_vertical is not None:
            vz, h = self.given_vertical(t)
        horizon = t - HISTORY_S
        self._hq.append((t, q))
        self._hh.append((t, h))
        while self._hq and self._hq[0][0] < horizon:
            self._hq.popleft()
            self._hh.popleft()
        if self.stepper is not None:
            o = self.stepper.step(t, acc, np.asarray(ev.body_omega, dtype=float), R, vz)
            if t >= self._t_first + self.options.settle_time:
                self._vel.append((t, o.world_v_body))
                while self._vel and self._vel[0][0] < horizon:
                    self._vel.popleft()
            self.latest_row = (o, q, h)
            if self.keep:
                self._rows.append(self.latest_row)
        self._t_done = t
        while self._slam_ml and self._slam_ml[0].t <= t:
            self._ml_pose(self._slam_ml.popleft())

    def _ml_pose(self, ev: SlamPose) -> None:
        sid = int(ev.session)
        if sid < 0:
            self._count("ml_slam_lost")
            return
        q = self._attitude_history(float(ev.t))
        if q is None:
            self._count("ml_slam_without_attitude")
            return
        t, p = float(ev.t), np.asarray(ev.slam_t_cam, dtype=float)
        s = self.sessions.get(sid)
        new = s is None
        if new:
            s = self.sessions[sid] = _MlSession(t, p, self.ml_options)
        Rs = quat_wxyz_to_matrix(np.asarray(ev.slam_q_cam_wxyz, dtype=float))
        s.M += quat_wxyz_to_matrix(q) @ self.body_R_cam @ Rs.T
        if new:
            return
        po = self.pair_options
        while True:
            b = s.t0 + (s.n_edge + 1) * po.window
            if b > t + 1e-9:
                break
            a = s.t0 + s.n_edge * po.window
            # The pose nearest b: the previous one or this one (the first at or after b).
            tb, pb = s.prev if abs(s.prev[0] - b) <= abs(t - b) else (t, p)
            ta, pa = s.a
            if abs(ta - a) > po.max_gap or abs(tb - b) > po.max_gap or ta == tb:
                s.counts["gap"] += 1
            else:
                hab = self._height_at(ta, tb)
                if hab is None:
                    s.counts["no_metric"] += 1
                else:
                    x = (project_to_so3(s.M) @ (pb - pa))[2:3]
                    s.est.add_pair(x, np.array([hab[1] - hab[0]]), tb)
            s.a = (tb, pb)
            s.n_edge += 1
        s.prev = (t, p)

    def _attitude_history(self, t: float) -> np.ndarray | None:
        hq = self._hq
        if not hq or t > hq[-1][0]:
            return None
        if t <= hq[0][0]:
            return hq[0][1] if t >= hq[0][0] - 0.1 else None
        k = len(hq) - 1
        while k > 0 and hq[k - 1][0] > t:
            k -= 1
        (t0, q0), (t1, q1) = hq[k - 1], hq[k]
        return nlerp_quat_wxyz(t0, q0, t1, q1, t)

    def _height_at(self, ta: float, tb: float) -> tuple[float, float] | None:
        hh = self._hh
        if not hh or ta < hh[0][0] or tb > hh[-1][0]:
            return None
        th = np.array([r[0] for r in hh])
        h = np.array([r[1] for r in hh])
        ha, hb = np.interp([ta, tb], th, h)
        if not (math.isfinite(ha) and math.isfinite(hb)):
            return None
        return float(ha), float(hb)
