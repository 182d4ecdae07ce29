"""Sensor fault detectors and a health monitor for the smoothers (issue 18 Build 1-2).

Two parts, both fed in arrival order and knowing nothing of a flight:

:class:`FaultDetectors` sees every measurement event (``feed(event)``) and names sensor faults,
each counted by name in :meth:`FaultDetectors.report`:

- ``imu-saturation``: a sample whose value on one axis equals (to 1e-9 relative) the largest
  ``|value|`` that axis has shown so far, once that value has come ``saturation_run`` times (a
  quantised sensor's extreme recurs a few times by chance: EuRoC MH_01's accelerometer 3 times
  in a row while carried), above
  ``saturation_min_gyro`` [rad/s] / ``saturation_min_accel`` [m/s^2], on an axis whose readings
  have spanned at least ``saturation_spread_gyro`` / ``saturation_spread_accel`` (max - min): a
  sensor pinned at its rail after moving up to it (a noisy sensor never repeats its extreme
  value; a quantised one at rest repeats it but has not spanned the range). Counted per axis
  (``gyro x`` ...). Each sample gets saturation flags (:data:`SAT_GYRO_BITS`,
  :data:`SAT_ACCEL_BITS`; :func:`imu_saturation_flags` for a whole series) and the smoothers
  down-weight the IMU factor of every keyframe interval holding flagged samples
  (:func:`fgnav.solvers.graph.saturated_pim_params`: the true value lies beyond the rail by an
  unknown amount, taken as ``saturation_sigma_rel`` x the rail, the same over the interval).
- ``imu-dead``: an accelerometer reading exactly ``(0, 0, 0)`` for ``saturation_run`` samples
  or more (a dead or zeroed sensor; a flying vehicle never reads an exact zero specific
  force). Its samples from then on get :data:`DEAD_ACCEL_BIT` and the smoothers take the IMU
  factors over them as missing about ``g`` on every axis (``saturated_pim_params``).
- ``imu-gap``: an IMU interval longer than ``imu_gap_factor`` times the median interval and
  ``imu_gap_min_s``; those past the online smoother's ``max_imu_gap_s`` reset it (the chain is not
  integrated blindly; counted there as ``reset:imu-gap``).
- ``slam-jump``: a SLAM displacement between two poses of one session (``dt <=
  slam_jump_max_dt_s``) that, converted to metres with the newest scale estimate of the session,
  exceeds the motion the IMU-propagated estimate allows, ``|v| dt + slam_jump_min_m + a_max
  dt^2 / 2``: a relocalisation. The poses after a jump continue as a new SLAM session (a new
  alignment, its scale started from the previous one's), so the jump is not fitted as motion.
  After a pause longer than ``slam_jump_max_dt_s`` (lost tracking) the returning pose is
  compared with the estimate instead (online, where the context gives both): its camera
  position through the session's alignment against the newest estimate's, allowed
  ``slam_jump_min_m`` plus ``slam_jump_gap_sigmas`` times the estimate's position sigma plus
  the speed times the time between them: a relocalisation into a moved map (SLAM lost 8-14 s,
  back 2 m away: simulated two-turns 0.87 m with health "ok" before). A turn of the map (the
  SLAM's orientation between two poses of a session, across a pause too, turning more or less
  than the gyro over the same time by over ``slam_turn_jump_deg`` plus
  ``slam_turn_drift_deg_per_s`` per second between them; online, where the context integrates
  the gyro) is a jump too: the angle of a relative rotation does not depend on the file's
  rotation convention, ``body_R_cam`` or a mirrored frame (a map turned 30 deg about the
  current pose: simulated figure8 1.98 m with health "ok" before).
- ``slam-reset``: a SLAM pose of a session the input had not used before, after poses of
  another: a map reset (or a new map after lost tracking) that the input declares. Named, not
  fixed: every session has its own scale and alignment in the smoothers, so the scale is
  estimated again from the motion after it (a map reset at 12 s of the simulated two-turns doubles
  the batch's ATE: two 11-12 s scale fits instead of one of 24 s).
- ``range-stuck``: ``range_stuck_s`` of readings with identical values while the estimate says
  the sensor's height changed by more than ``range_stuck_motion_m``; further identical readings
  are dropped (``range:stuck``) until the value changes. Batch: the whole run is dropped; a
  constant run the detector could not call stuck from the solve that contains it (that solve
  follows a stuck reading the more, the stiffer the ground-height walk) is tested on one more
  solve without its readings (:func:`stuck_range_candidates`, :func:`confirm_stuck_range`).
- ``range-at-min``: a run of readings at the rangefinder's floor (within
  :data:`fgnav.datasets.range_limits.RANGE_AT_MIN_TOL_M` of the calibration's ``range_min``: "at
  or below the floor", not a distance; no such reading is a height factor, each is counted
  ``range:at-min``) over ``range_stuck_s`` or more while the estimated height changed by more
  than ``range_stuck_motion_m`` plus ``range_min`` (below its floor the sensor reads it whatever
  the height up to ``range_min``: a take-off is not the fault). A rangefinder pinned at its
  minimum for a whole flight was a height: simulated two-turns 0.137 / 0.152 m (batch /
  online, nominal 0.007 / 0.027 m) with health "ok" before. Readings below ``range_min`` stay
  out of range, not this, and once one has come the sensor does not clamp at its floor: its
  readings at ``range_min`` are distances (a Crazyflie's time of flight reads 12-25 mm on the
  floor, under its 40 mm limit, and 40 mm once on the way down in traj2).
  Readings at the rangefinder's maximum (:func:`fgnav.datasets.range_limits.range_at_max`: a
  missing echo) are no heights either, counted ``range:at-max`` (in ``dropped``), and not tested
  by ``range-stuck``: a vehicle above the sensor's reach reads its maximum, which is no fault
  (every reading at 8 m on simulated two-turns was named range-stuck).
- ``range-at-max``: a run of readings at the rangefinder's maximum (no echo) over
  ``range_stuck_s`` or more while the estimate puts the ground well within the sensor's reach:
  the reading the estimate predicts (:attr:`Context.range_expected`: the distance along the beam
  to the estimated ground) stayed below ``range_max`` minus ``range_stuck_motion_m`` minus
  ``range_at_max_margin_rel`` of ``range_max`` (8 m: below 7.05 m; 4 m: below 3.45 m) over that
  time, from the first such prediction in the run: a blinded, covered or failed sensor. A vehicle
  above the sensor's reach (the prediction near or above the maximum) is not named, nor a run
  whose prediction is unknown (no range reading has measured the estimate's ground: a sensor
  blind from the start). The readings are no heights anyway (``range:at-max``); named, not
  fixed (a flow deck's flow has no height gate through it: simulated flow deck blinded 8-13 s,
  batch / online ATE 1.6x / 1.4x nominal with health "ok" before).
- ``range-silent``: the range stream, having delivered readings, delivers none for longer than
  ``range_gap_s`` while the IMU goes on (measured on the IMU's clock: said when the gap passes
  the bound, not at the next reading), the sensor's last reading within its reach (from
  ``range_min`` to the ``range-at-max`` bound below ``range_max``) and the predicted reading,
  where the estimate has one, still within it: a rangefinder that stopped (a failed driver or
  link, a sensor off), not one that leaves out readings beyond its reach (a vehicle climbing
  out of it, or on the floor under it). Counted once per gap; named, not fixed (the flow has no
  height through it: simulated flow deck silent 8-13 s, batch / online ATE 0.040 / 0.091 m
  against 0.026 / 0.071 nominal with health "ok" before). The longest gaps of real streams are
  far below the 1 s bound: Crazyflie time of flight (about 23 Hz) 0.13 s in flight and 0.43 s
  on the floor, the simulator's 25 Hz 0.12 s.
- ``flow-rejected``: every optical-flow reading rejected by its own gates for
  :data:`fgnav.solvers.flow.FLOW_ALL_REJECTED_S` or more
  (:class:`fgnav.solvers.flow.FlowRejectWatch`, which says it; counted once per run): the
  stream gives no velocity. Before, only that warning and ``info["flow_all_rejected"]`` said
  it, the health "ok" (a Crazyflie-like flow deck, every reading below the quality gate:
  online 8.3 m, batch 0.053 m against 0.22 / 0.023 m).
- ``flow-no-height``: an optical-flow stream with no height source (no rangefinder stream, or
  ``use_range`` off): the flow measures velocity over height and gives no metric velocity
  without one; the horizontal velocity is dead-reckoned (online: named once flow has arrived
  for ``flow_no_height_s`` with no range reading; batch: from the flight's streams).
- ``camera-frozen``: an image identical (byte for byte) to the previous one; dropped
  (``images:frozen``).
- ``slam-mirrored``: the SLAM frame is left-handed (one axis sign flipped by a bridge:
  positions ``D p``, rotations ``D R D``), found where the SLAM-vs-gyro check names the inverse
  convention or a wrong ``body_T_cam`` rotation (:func:`fgnav.datasets.slam_gyro.check_mirror`);
  named instead of those, with the axis when the motion tells it (the SLAM then un-mirrored,
  ``[graph] slam_mirror``).
- ``slam-scale-drift``: the SLAM scale estimate of one session changes faster than
  ``slam_scale_drift_per_s`` (relative, per second: the least-squares slope of its log over
  ``slam_scale_drift_window_s``, the window at least 80 % covered; :class:`ScaleDriftWatch`): a
  SLAM whose scale runs away (real monocular SLAM drifts about 1e-4 per second: the README's
  *The simulator's SLAM scale drift*). Named, not fixed, and not where a fault that moves the
  scale estimate itself has been named (:data:`SCALE_DRIFT_EXPLAINED_BY`: a jump, a reset, a
  clock offset, a wrong body_T_cam rotation, a mirror, an IMU gap). Push engine: causal, on its
  alignment's scale at every keyframe, the first ``slam_scale_drift_settle_s`` of a session left
  out (the scale converges there), 1e-2 per second; measured largest rates (10 s windows, 4 s
  left out): EuRoC MH_01 4.6e-3, V1_02 ORB-SLAM2 / ORB-SLAM3 1.0e-3 / 1.4e-3, simulated
  two-turns / rectangle / figure8 (seed 1) 1.7e-3 / 0.6e-3 / 0.4e-3; two-turns with its SLAM
  positions times (1 + 0.05 t) 2.2e-2 (the scale walk follows the drift at half its rate). Not
  on the per-axis SLAM model (its scale is three). Batch: on the per-segment scales, 1e-3 per
  second (the scale walk holds them stiff: the 5 %/s drift shows as 2.3e-3; EuRoC MH_01 up to
  5.1e-4, V1_02 1.0e-4 / 1.3e-4, simulated 4e-5).
- ``slam-clock-offset``: the SLAM-vs-gyro check (:mod:`fgnav.datasets.slam_gyro`) found a clock
  offset above ``slam_offset_tol_s`` (reported; ``[graph] slam_time_offset = "apply"`` applies it
  in batch); not where the rates correlate too little to tell (``time_offset_ok``).
- ``body_T_cam-rotation``: the same check found the calibration's camera rotation wrong.
- ``terrain-step`` (batch): the ground the range readings see (through the solved trajectory)
  steps by more than ``terrain_step_m`` and stays there (:func:`terrain_steps`): the ground
  height's walk is cut there and the flight solved again (the push engine cuts it causally, on a
  run of readings its range gate refused that agree with each other).

The detectors need a little of the estimate (speed, height, SLAM scale): a :class:`Context` the
caller fills (the online smoother with its newest state, causally; the batch check with the
solved trajectory).

:class:`HealthMonitor` watches the online smoother after each keyframe: the whitened errors of the
new SLAM and range factors at the newest linearisation point (innovations: the new states are at
their IMU prediction there) give a normalised chi-squared per sensor over a sliding window of
``window_s``; state sanity checks speed (``max_speed_mps``), position sigma (``max_pos_sigma_m``)
and bias bounds. A sanity violation, or a chi-squared above ``chi2_alarm`` for
``diverge_after_s``, is a divergence: reported (a warning line, ``status`` and counts in
``info["health"]``, ``quality`` lowered to at most ``DIVERGED_QUALITY`` until healthy again) and
recovered from the last healthy snapshot (at least ``diverge_after_s`` before the alarm began)
by the smoother's rebuild, at most ``max_recoveries`` times and ``recovery_gap_s`` apart.

A stream the estimate cannot use (``flow-rejected``, ``flow-no-height``, and a rangefinder at its
floor, at its maximum or silent while airborne: ``range-at-min``, ``range-at-max``,
``range-silent``; :data:`DEGRADING`) makes the status ``degraded`` (unless it diverged) and,
while it lasts and no SLAM alignment or camera anchors the estimate, lowers ``quality`` to at
most ``DEGRADED_QUALITY`` (a rangefinder fault lasts until a usable reading, or for
``range-silent`` any reading, arrives).

Batch: :func:`check_batch` replays the flight through the detectors with the solved trajectory as
context and judges the solve itself (LM stopped at ``max_iterations`` while its last iteration
still lowered the error by more than ``batch_stall_rel``, or ``2 error / factors`` above
``batch_error_per_factor_max``: 0.9 on the nominal two-turns and MH_01, 25-210 on runs that
did not converge); :func:`fixed_flight` drops / re-sessions what
the detectors flagged so that :func:`fgnav.methods.run_batch` can solve once more.

Not modelled: a rail that moves (auto-ranging), stuck values that wander by one quantum, SLAM
jumps smaller than ``slam_jump_min_m``, a camera that repeats a frame with new noise.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import statistics
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: Session ids given to SLAM poses after a detected jump: ``session + JUMP_SESSION_BASE * n``
#: (2**40: an input's own ids stay below it; with 1000, an input id of 1000 or more was taken
#: for a jump's split and never counted as a map reset).
JUMP_SESSION_BASE = 1 << 40
#: Quality (0-100) of the online states while the monitor says the estimate diverges.
DIVERGED_QUALITY = 10
#: Quality (0-100) of the online states while a degrading fault (:data:`DEGRADING`) lasts and
#: nothing else anchors the position: below a dead-reckoned state's 30, above a diverged one's.
DEGRADED_QUALITY = 20
#: Faults that leave a stream unusable for the whole of their span: the status is ``degraded``
#: (the rangefinder's: while airborne, no height from it; see :attr:`FaultDetectors.lasting`).
DEGRADING = (
    "flow-rejected",
    "flow-no-height",
    "range-at-min",
    "range-at-max",
    "range-silent",
)
#: Saturation flag bits of an IMU sample: gyro axis i is ``1 << i``, accelerometer axis i is
#: ``1 << (3 + i)``.
SAT_GYRO_BITS = (1, 2, 4)
SAT_ACCEL_BITS = (8, 16, 32)
#: Flag of an IMU sample whose accelerometer reads exactly (0, 0, 0) in a run (``imu-dead``).
DEAD_ACCEL_BIT = 64
#: Detector names, in report order.
DETECTORS = (
    "imu-saturation",
    "imu-dead",
    "imu-gap",
    "slam-jump",
    "slam-reset",
    "range-stuck",
    "range-at-min",
    "range-at-max",
    "range-silent",
    "flow-rejected",
    "flow-no-height",
    "camera-frozen",
    "slam-clock-offset",
    "body_T_cam-rotation",
    "terrain-step",
    "divergence",
    "slam-scale-nonpositive",
    "slam-mirrored",
    "slam-scale-drift",
    "covariance-unavailable",
)


#: a whitened squared error above this leaving the health window makes the running chi2 sum be
#: summed afresh (the subtraction would leave a cancellation error of ~1e-16 of it behind)
_RESUM_CHI2 = 1e4

#: event type -> detector method (filled on first use: the event types import datasets)
_FEED_HANDLERS: dict[type, Callable[[Any, Any], Any]] = {}


def _pass_through(_detectors: Any, ev: Any) -> Any:
    """The feed handler of an event type no detector looks at."""
    return ev


def _init_feed_handlers() -> None:
    from fgnav.datasets.events import ImageFrame, ImuSample, RangeReading, SlamPose

    _FEED_HANDLERS.update(
        {
            ImuSample: lambda d, ev: d._imu(ev),
            SlamPose: lambda d, ev: d._slam(ev),
            RangeReading: lambda d, ev: d._range(ev),
            ImageFrame: lambda d, ev: d._image(ev),
        }
    )


@dataclass
class HealthOptions:
    """Thresholds of the detectors and the monitor (see the module docstring; every number > 0).

    Attributes:
        enabled: run the detectors and the monitor at all.
        saturation_run: equal extreme values in a row that make an IMU axis pinned; also the
            run of exact-zero accelerometer samples that makes ``imu-dead``.
        saturation_min_gyro, saturation_min_accel: the rail must be above this [rad/s, m/s^2].
        saturation_spread_gyro, saturation_spread_accel: the axis must have spanned this
            (max - min) before its extreme counts as a rail [rad/s, m/s^2].
        saturation_sigma_rel: sigma of a pinned sample's unknown excess over its rail, relative
            to the rail value.
        imu_gap_factor, imu_gap_min_s: an IMU interval above this many median intervals and
            above this many seconds is an ``imu-gap``.
        slam_jump_min_m: slack of the SLAM jump test [m] (``|v| dt + this + a dt^2 / 2``);
            also the constant part of the test of a pose back after a pause.
        slam_jump_max_dt_s: longest step between two poses tested as a step [s]; a longer
            pause is tested against the estimate instead.
        slam_jump_accel_max: the acceleration ``a`` of the jump test [m/s^2].
        slam_jump_gap_sigmas: position sigmas of the estimate allowed to a pose back after a
            pause.
        slam_turn_jump_deg, slam_turn_drift_deg_per_s: a SLAM orientation change that differs
            from the gyro's by more than this plus this per second is a turned map [deg].
        terrain_step_m: a step of the ground the range readings see above this is a
            ``terrain-step`` (batch) [m].
        terrain_step_n: readings on each side whose medians are compared (batch).
        range_stuck_s, range_stuck_motion_m: identical range readings for this long while the
            estimated height moved more than this are ``range-stuck`` [s, m]; the same times
            for ``range-at-min`` (the motion bound plus ``range_min``) and ``range-at-max``
            (readings at ``range_max`` for this long while the predicted reading stayed below
            ``range_max`` minus the motion bound minus ``range_at_max_margin_rel``).
        range_at_max_margin_rel: the part of ``range_max`` the predicted reading must stay below
            it by, beside ``range_stuck_motion_m``, for ``range-at-max`` (the estimate's height
            and ground errors, the beam's tilt).
        range_gap_s: no range reading for longer than this while the IMU goes on, the last
            reading and the predicted one within the sensor's reach, is ``range-silent`` [s]
            (real streams' longest gaps: 0.43 s, a Crazyflie on the floor).
        flow_no_height_s: flow without a range reading for this long is ``flow-no-height`` [s].
        slam_offset_tol_s: a SLAM clock offset above this is named [s].
        slam_scale_drift_per_s, slam_scale_drift_batch_per_s: a session's log-scale slope above
            this is ``slam-scale-drift``, push engine and batch [1/s].
        slam_scale_drift_window_s: the window of that slope [s].
        slam_scale_drift_settle_s: time after a session's start left out of it [s].
        window_s: window of the monitor's normalised chi-squared per sensor [s].
        window_min_factors: factors the window needs before its chi-squared counts.
        chi2_alarm: normalised chi-squared above which the window alarms.
        max_speed_mps, max_pos_sigma_m, max_accel_bias, max_gyro_bias: state sanity bounds [m/s,
            m, m/s^2, rad/s]; beyond one is a divergence.
        diverge_after_s: an alarm that lasts this long is a divergence; the rebuild starts at
            least this long before it began [s].
        max_recoveries, recovery_gap_s: rebuilds at most, and at least this far apart [s].
        batch_error_per_factor_max: a batch solution with ``2 error / factors`` above this is
            not converged.
        batch_stall_rel: LM stopped at its iteration limit while its error still fell by more
            than this per iteration is not converged.
    """

    enabled: bool = True
    saturation_run: int = 10
    saturation_min_gyro: float = 0.2
    saturation_min_accel: float = 5.0
    saturation_spread_gyro: float = 0.2
    saturation_spread_accel: float = 2.0
    #: sigma of a pinned sample's unknown excess over its rail, relative to the rail value
    saturation_sigma_rel: float = 1.0
    imu_gap_factor: float = 5.0
    imu_gap_min_s: float = 0.02
    slam_jump_min_m: float = 0.5
    slam_jump_max_dt_s: float = 1.0
    slam_jump_accel_max: float = 5.0
    slam_jump_gap_sigmas: float = 4.0
    slam_turn_jump_deg: float = 8.0
    slam_turn_drift_deg_per_s: float = 1.0
    terrain_step_m: float = 0.2
    terrain_step_n: int = 8
    range_stuck_s: float = 1.0
    range_stuck_motion_m: float = 0.15
    range_at_max_margin_rel: float = 0.1
    range_gap_s: float = 1.0
    flow_no_height_s: float = 1.0
    slam_offset_tol_s: float = 0.1
    slam_scale_drift_per_s: float = 1e-2
    slam_scale_drift_batch_per_s: float = 1e-3
    slam_scale_drift_window_s: float = 10.0
    slam_scale_drift_settle_s: float = 4.0
    window_s: float = 2.0
    window_min_factors: int = 10
    chi2_alarm: float = 100.0
    max_speed_mps: float = 30.0
    max_pos_sigma_m: float = 100.0
    max_accel_bias: float = 2.0
    max_gyro_bias: float = 0.5
    diverge_after_s: float = 1.0
    max_recoveries: int = 3
    recovery_gap_s: float = 5.0
    batch_error_per_factor_max: float = 50.0
    batch_stall_rel: float = 1e-3

    def check(self) -> HealthOptions:
        from fgnav.datasets.errors import FlightDataError

        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool):
                continue
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise FlightDataError(f"HealthOptions.{f.name} = {v}: expected a number > 0")
        return self


@dataclass
class Context:
    """What the detectors know of the estimate: callables of time (None: not known yet).

    Attributes:
        speed: ``speed(t) -> |world_v_body|`` [m/s].
        height: ``height(t) -> z of the body`` [m].
        scale: ``scale(session) -> SLAM units per metre`` or None.
        slam_height: ``slam_height(session, slam_t_cam) -> world z of the camera`` [m] through
            the session's current alignment (None without one): a height that no range
            reading went into, for the stuck-rangefinder test.
        slam_position: ``slam_position(session, slam_t_cam) -> world_t_cam`` (3,) [m] through
            the session's current alignment (None without one).
        camera: ``camera() -> (world_t_cam [m], its position sigma [m], time [s])`` of the
            newest estimate (None without a covariance).
        gyro_turn: ``gyro_turn(t_a, t_b) -> angle`` [rad] of the body's rotation from ``t_a`` to
            ``t_b`` integrated from the arrived gyro (bias removed; None: not covered).
        range_expected: ``range_expected(t) -> the reading the estimate predicts`` [m]: the
            distance along the rangefinder's beam from the sensor to the estimated ground (None:
            not known, e.g. no range reading has measured the ground yet).
    """

    speed: Callable[[float], float | None] = lambda t: None
    height: Callable[[float], float | None] = lambda t: None
    scale: Callable[[int], float | None] = lambda s: None
    slam_height: Callable[[int, np.ndarray], float | None] = lambda s, p: None
    slam_position: Callable[[int, np.ndarray], np.ndarray | None] = lambda s, p: None
    camera: Callable[[], tuple[np.ndarray, float, float] | None] = lambda: None
    gyro_turn: Callable[[float, float], float | None] = lambda ta, tb: None
    range_expected: Callable[[float], float | None] = lambda t: None


@dataclass
class _Episode:
    t: float
    detail: str


@dataclass
class FaultDetectors:
    """The sensor fault detectors of the module docstring, fed events in arrival order."""

    options: HealthOptions = field(default_factory=HealthOptions)
    context: Context = field(default_factory=Context)
    name: str = "health"
    #: the rangefinder's ``range_min`` [m] (None: unknown, no ``range-at-min`` test)
    range_min: float | None = None
    #: the rangefinder's ``range_max`` [m] (None: unknown; readings at it are no echo, not
    #: tested for ``range-stuck``)
    range_max: float | None = None

    def __post_init__(self) -> None:
        self.counts: dict[str, int] = {}
        self.details: dict[str, list[str]] = {}
        self.dropped: dict[str, int] = {}
        self._imu_last: float | None = None
        self._imu_dts: deque = deque(maxlen=200)
        self._slam_last: tuple[int, np.ndarray] | None = None
        self._rail = {"gyro": [0.0] * 3, "accel": [0.0] * 3}
        self._lo = {"gyro": [math.inf] * 3, "accel": [math.inf] * 3}
        self._hi = {"gyro": [-math.inf] * 3, "accel": [-math.inf] * 3}
        self._run = {"gyro": [0] * 3, "accel": [0] * 3}
        self._imu_med: float | None = None
        self._n_imu = 0
        self._acc_zero_run = 0  # consecutive samples whose accelerometer reads (0, 0, 0)
        self._imu_kinds: tuple | None = None  # (kind, lo, hi, rail, run, bits) per sensor
        # Per axis (gyro x, y, z, accel x, y, z) the open interval of values that change no
        # detector state (inside the seen range, below the rail by a margin): most samples.
        self._imu_calm: tuple[float, ...] | None = None
        self._slam_prev: dict[int, tuple[float, np.ndarray]] = {}
        self._slam_prev_q: dict[int, np.ndarray] = {}  # the newest orientation per session
        self._slam_jumps: dict[int, int] = {}
        self._range_val: float | None = None
        self._range_t0: float | None = None
        self._range_slam0: tuple[int, np.ndarray] | None = None
        self._range_stuck = False
        #: (start time, value) of each stuck range run declared
        self.stuck_runs: list[tuple[float, float]] = []
        # The current run of readings at the rangefinder's floor: start time, the first height
        # known in it (time, height, SLAM pose), whether it was named.
        self._atmin_t0: float | None = None
        self._atmin_h0: tuple[float, float, tuple[int, np.ndarray] | None] | None = None
        self._atmin_named = False
        self._range_below = False  # a reading below range_min seen
        #: (start time, time named) of each run at the floor named ``range-at-min``
        self.at_min_runs: list[tuple[float, float]] = []
        # The current run of readings at the rangefinder's maximum: start time, the time of the
        # first predicted reading known in it, the largest prediction, whether it was named.
        self._atmax_t0: float | None = None
        self._atmax_tk: float | None = None
        self._atmax_hi = -math.inf
        self._atmax_named = False
        #: (start time, time named) of each run at the maximum named ``range-at-max``
        self.at_max_runs: list[tuple[float, float]] = []
        # The newest range reading (time, value) and the IMU time past which the stream is
        # tested for silence (inf: no reading yet, or the gap was judged).
        self._range_last: tuple[float, float] | None = None
        self._silent_due = math.inf
        #: the rangefinder's degrading faults (:data:`DEGRADING`) that last now: named, and no
        #: usable reading (or, for ``range-silent``, none at all) since
        self.lasting: set[str] = set()
        #: (time of the last reading, time named) of each gap named ``range-silent``
        self.silent_runs: list[tuple[float, float]] = []
        self._image_hash: bytes | None = None
        self._frozen = False
        self._said: set[str] = set()
        #: saturation flags of the last IMU sample fed (:data:`SAT_GYRO_BITS`, ...)
        self.imu_flags = 0

    # -- bookkeeping ---------------------------------------------------------------------------

    def _count(self, det: str, detail: str | None = None, n: int = 1) -> None:
        self.counts[det] = self.counts.get(det, 0) + n
        if detail is not None:
            d = self.details.setdefault(det, [])
            if len(d) < 10:
                d.append(detail)
            if det not in self._said:
                self._said.add(det)
                log.warning("%s: %s: %s", self.name, det, detail)

    def _drop(self, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1

    def report(self) -> dict[str, Any]:
        """``{"detectors": {name: count}, "details": {name: [first lines]}}``."""
        return {
            "detectors": {k: self.counts[k] for k in DETECTORS if self.counts.get(k)},
            "details": {k: v for k, v in self.details.items() if v},
        }

    # -- events --------------------------------------------------------------------------------

    def feed(self, ev: Any) -> Any:
        """Look at one event; returns the event to use (maybe with a new SLAM session) or None
        when the event is dropped (counted in ``dropped`` by reason)."""
        handler = _FEED_HANDLERS.get(type(ev))
        if handler is None:
            if not _FEED_HANDLERS:
                _init_feed_handlers()
                return self.feed(ev)
            for cls, h in _FEED_HANDLERS.items():  # a subclass of an event type
                if isinstance(ev, cls):
                    return h(self, ev)
            # No detector for this type (attitude, yaw, flow: 20k events on the 180 s
            # benchmark): remembered, so its next events skip this search.
            _FEED_HANDLERS[type(ev)] = _pass_through
            return ev
        return handler(self, ev)

    def _imu(self, ev) -> Any:
        self.feed_imu(ev)
        return ev

    def feed_imu(self, ev) -> int:
        """One IMU sample (never dropped: :meth:`feed` without the dispatch); returns its
        saturation flags (also kept in ``imu_flags``)."""
        w, a = ev.body_omega, ev.body_accel
        return self.feed_imu_values(
            float(ev.t),
            w.tolist() if hasattr(w, "tolist") else w,
            a.tolist() if hasattr(a, "tolist") else a,
        )

    def feed_imu_values(self, t: float, w: list[float], a: list[float]) -> int:
        """:meth:`feed_imu` on the sample's time and its rates and specific forces as lists of
        floats (a caller that has them already)."""
        self.imu_flags = self._imu_values(t, w, a)
        return self.imu_flags

    def _imu_values(self, t: float, w: list[float], a: list[float]) -> int:
        """One IMU sample (plain Python floats: this runs for every sample, up to 1 kHz);
        returns its saturation flags."""
        flags = 0
        if t > self._silent_due:
            self._range_silent(t)
        last = self._imu_last
        if last is not None and t > last:
            dt = t - last
            if len(self._imu_dts) >= 20:
                if self._imu_med is None or self._n_imu % 50 == 0:
                    # (statistics.median: numpy's median of these floats, the same value,
                    # without converting the deque to an array; a third of the time)
                    self._imu_med = float(statistics.median(self._imu_dts))
                if dt > max(
                    self.options.imu_gap_factor * self._imu_med, self.options.imu_gap_min_s
                ):
                    self._count(
                        "imu-gap", f"no IMU sample for {dt:.3f} s after t={self._imu_last:.3f}"
                    )
                    self._imu_last = t
                    return flags
            self._imu_dts.append(dt)
        self._n_imu += 1
        if last is None or t > last:
            self._imu_last = t
        if a[0] == 0.0 and a[1] == 0.0 and a[2] == 0.0:
            # A dead accelerometer (a flying vehicle never reads an exact zero specific force).
            self._acc_zero_run += 1
            n = self.options.saturation_run
            if self._acc_zero_run >= n:
                if self._acc_zero_run == n:
                    self._count("imu-dead", f"accelerometer reads exactly 0 from t={t:.3f}", n)
                else:
                    self._count("imu-dead")
                flags |= DEAD_ACCEL_BIT
        else:
            self._acc_zero_run = 0
        calm = self._imu_calm
        if calm is not None:
            w0, w1, w2 = w
            a0, a1, a2 = a
            if (
                calm[0] < w0 < calm[1]
                and calm[2] < w1 < calm[3]
                and calm[4] < w2 < calm[5]
                and calm[6] < a0 < calm[7]
                and calm[8] < a1 < calm[9]
                and calm[10] < a2 < calm[11]
            ):
                return flags  # strictly inside every axis's calm interval: nothing to update
        flags |= self._imu_axes(t, w, a)
        self._imu_calm = self._calm_intervals()
        return flags

    def _calm_intervals(self) -> tuple[float, ...]:
        """Per axis ``(low, high)``: a value strictly between them is inside the axis's seen
        range ``[lo, hi]`` and below its rail ``r`` by more than the ``1e-9 r`` the rail test of
        :meth:`_imu_axes` allows (margin ``4e-9 r``), so it changes no state and sets no flag."""
        out: list[float] = []
        for kind in ("gyro", "accel"):
            lo, hi, rail = self._lo[kind], self._hi[kind], self._rail[kind]
            for i in range(3):
                b = rail[i] * (1.0 - 4e-9)
                out += (max(lo[i], -b), min(hi[i], b))
        return tuple(out)

    def _imu_axes(self, t: float, w: list[float], a: list[float]) -> int:
        """The per-axis range, rail and run bookkeeping of one sample; its saturation flags."""
        flags = 0
        o = self.options
        kinds = self._imu_kinds
        if kinds is None:
            kinds = self._imu_kinds = tuple(
                (kind, self._lo[kind], self._hi[kind], self._rail[kind], self._run[kind], bits)
                for kind, bits in (("gyro", SAT_GYRO_BITS), ("accel", SAT_ACCEL_BITS))
            )
        isfinite = math.isfinite
        for (kind, lo, hi, rail, run, bits), v in zip(kinds, (w, a), strict=True):
            for i, x in enumerate(v):
                if not isfinite(x):
                    continue
                if x < lo[i]:
                    lo[i] = x
                if x > hi[i]:
                    hi[i] = x
                ax = abs(x)
                r = rail[i]
                if ax > r * (1 + 1e-9):
                    run[i] = 1  # a new largest |value|: the run of samples at it restarts
                    rail[i] = ax
                    continue
                if abs(ax - r) > 1e-9 * r:
                    continue
                run[i] += 1  # samples at exactly the current largest |value|
                if kind == "gyro":
                    floor, spread = o.saturation_min_gyro, o.saturation_spread_gyro
                else:
                    floor, spread = o.saturation_min_accel, o.saturation_spread_accel
                if ax >= floor and hi[i] - lo[i] >= spread:
                    if run[i] == o.saturation_run:
                        self._count(
                            "imu-saturation",
                            f"{kind} {'xyz'[i]} pinned at |{ax:.4g}| from t={t:.3f}",
                            o.saturation_run,
                        )
                    elif run[i] > o.saturation_run:
                        self._count("imu-saturation")
                    if run[i] >= o.saturation_run:
                        flags |= bits[i]
        return flags

    def _slam(self, ev) -> Any:
        o = self.options
        p = np.asarray(ev.slam_t_cam, float)
        if not all(map(math.isfinite, p.tolist())):
            return ev
        sess = int(ev.session)
        n = self._slam_jumps.get(sess, 0)
        virtual = sess + JUMP_SESSION_BASE * n
        prev = self._slam_prev.get(sess)
        t = float(ev.t)
        if prev is None and self._slam_prev and sess < JUMP_SESSION_BASE:
            # (ids from JUMP_SESSION_BASE up: this check's own split at a jump, fed again)
            last_sess, (t_last, _) = max(self._slam_prev.items(), key=lambda kv: kv[1][0])
            self._count(
                "slam-reset",
                f"SLAM session {sess} starts at t={t:.2f}, {t - t_last:.2f} s after the last pose "
                f"of session {last_sess}: a map reset declared by the input (a new scale and "
                "alignment from here)",
            )
        jump = None  # what names a jump at this pose (the first test that finds one)
        if prev is not None and 0 < t - prev[0] <= o.slam_jump_max_dt_s:
            dt = t - prev[0]
            scale = self.context.scale(virtual)
            if scale is None and n:
                scale = self.context.scale(
                    sess + JUMP_SESSION_BASE * (n - 1)
                ) or self.context.scale(sess)
            speed = self.context.speed(t)
            if scale and speed is not None and scale > 0:
                dp = p - prev[1]
                d = math.sqrt(float(dp.dot(dp))) / scale  # (np.linalg.norm's arithmetic)
                allowed = speed * dt + o.slam_jump_min_m + 0.5 * o.slam_jump_accel_max * dt**2
                if d > allowed:
                    jump = (
                        f"moved {d:.2f} m in {dt * 1e3:.0f} ms at t={t:.2f} (the estimate "
                        f"allows {allowed:.2f} m)"
                    )
        elif prev is not None and t - prev[0] > o.slam_jump_max_dt_s:
            moved = self._relocalised(virtual, p, t)
            if moved is not None:
                jump = (
                    f"is back after {t - prev[0]:.1f} s without a pose, {moved[0]:.2f} m from "
                    f"the estimate at t={t:.2f} (it allows {moved[1]:.2f} m): relocalised in a "
                    "moved map"
                )
        q = np.asarray(ev.slam_q_cam_wxyz, float)
        # Its squared norm, once: NaN unless every component is finite (then never > 0).
        qq = float(q @ q) if np.isfinite(q).all() else math.nan
        q_prev = self._slam_prev_q.get(sess)
        if jump is None and prev is not None and q_prev is not None:
            turned = self._turned(prev[0], q_prev, t, q, qq)
            if turned is not None:
                jump = (
                    f"turned {turned[0]:.1f} deg in {t - prev[0]:.2f} s at t={t:.2f} while the "
                    f"gyro turned {turned[1]:.1f} deg: the map turned"
                )
        if jump is not None:
            n += 1
            self._slam_jumps[sess] = n
            virtual = sess + JUMP_SESSION_BASE * n
            self._count("slam-jump", f"SLAM session {sess} {jump}: a new alignment from here")
        if qq > 0:
            self._slam_prev_q[sess] = q / math.sqrt(qq)
        self._slam_prev[sess] = (t, p)
        self._slam_last = (virtual, p)
        return ev if virtual == sess else ev._replace(session=virtual)

    def _turned(
        self, t_prev: float, q_prev: np.ndarray, t: float, q: np.ndarray, qq: float
    ) -> tuple[float, float] | None:
        """(SLAM turn, gyro turn) [deg] when the SLAM orientation's change from the previous
        pose differs from the gyro's by more than the module docstring allows, else None
        (``qq``: ``q @ q``, NaN when a component of ``q`` is not finite)."""
        o = self.options
        if not qq > 0:
            return None
        gyro = self.context.gyro_turn(t_prev, t)
        if gyro is None:
            return None
        c = abs(float(q_prev @ q)) / math.sqrt(qq)
        slam = 2.0 * math.degrees(math.acos(min(c, 1.0)))
        gyro = math.degrees(gyro)
        allowed = o.slam_turn_jump_deg + o.slam_turn_drift_deg_per_s * (t - t_prev)
        return (slam, gyro) if abs(slam - gyro) > allowed else None

    def _relocalised(self, session: int, p: np.ndarray, t: float) -> tuple[float, float] | None:
        """(distance, allowed) [m] when a pose returning after a pause lies further from the
        newest estimate than it allows (see ``slam-jump`` in the module docstring), else None."""
        o = self.options
        world = self.context.slam_position(session, p)
        cam = self.context.camera()
        if world is None or cam is None or not np.isfinite(world).all():
            return None
        pos, sigma, t_est = cam
        speed = self.context.speed(t) or 0.0
        d = float(np.linalg.norm(world - pos))
        allowed = o.slam_jump_min_m + o.slam_jump_gap_sigmas * sigma + speed * abs(t - t_est)
        return (d, allowed) if d > allowed else None

    def _height(self, t: float) -> float | None:
        """The height the stuck-rangefinder test compares: from the newest SLAM pose through its
        alignment when there is one (no range reading in it), else the estimate's."""
        if self._slam_last is not None:
            h = self.context.slam_height(*self._slam_last)
            if h is not None:
                return h
        return self.context.height(t)

    def _range(self, ev) -> Any:
        o = self.options
        r = float(ev.range)
        t = float(ev.t)
        if self._range_last is None or t >= self._range_last[0]:
            self._range_last = (t, r)
            self._silent_due = t + o.range_gap_s
        self.lasting.discard("range-silent")
        if not math.isfinite(r):
            return ev
        if self.range_min is not None:
            from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, range_refusal

            # (a sensor that has read below its floor does not clamp there: range_at_min)
            self._range_below = self._range_below or r < self.range_min
            hi = math.inf if self.range_max is None else self.range_max
            why = range_refusal(r, self.range_min, hi, not self._range_below)
            if why in RANGE_LIMIT_TAGS:
                # No distance: the gates keep it out of the graph (range:at-min, range:at-max);
                # a stuck run starts afresh after it. A run at the maximum (no echo: a vehicle
                # above the sensor's reach, or a blinded sensor) is not tested as stuck.
                self._range_val = None
                if why == "at-min":
                    self._atmax_t0 = None
                    self.lasting.discard("range-at-max")
                    self._at_min(r, t)
                else:
                    self._atmin_t0 = None
                    self.lasting.discard("range-at-min")
                    self._at_max(r, t)
                return ev
            self._atmin_t0 = self._atmax_t0 = None
            self.lasting.difference_update(("range-at-min", "range-at-max"))
        if self._range_val is None or r != self._range_val:
            self._range_val, self._range_t0 = r, t
            self._range_h0 = self._height(t)
            self._range_slam0 = self._slam_last
            self._range_stuck = False
            return ev
        if self._range_stuck:
            self._drop("range:stuck")
            return None
        if self._range_slam0 is None:
            # A run from before any SLAM pose or height was known (a rangefinder stuck from the
            # start): compared from the first ones known in it (never tested before: simulated
            # two-turns stuck at 2.0 m throughout, online 0.152 m with health "ok").
            self._range_slam0 = self._slam_last
        if self._range_h0 is None:
            self._range_h0 = self._height(t)
        if t - self._range_t0 >= o.range_stuck_s:
            h0, h1 = self._range_h0, self._height(t)
            s0, s1 = self._range_slam0, self._slam_last
            if s0 is not None and s1 is not None and s0[0] == s1[0]:
                # Both SLAM positions through the newest alignment: its origin, which walks
                # (and absorbs a stuck reading the more, the stiffer the ground walk), cancels.
                a, b = self.context.slam_height(*s0), self.context.slam_height(*s1)
                if a is not None and b is not None:
                    h0, h1 = a, b
            if h0 is not None and h1 is not None and abs(h1 - h0) > o.range_stuck_motion_m:
                self._range_stuck = True
                self.stuck_runs.append((self._range_t0, r))
                self._count(
                    "range-stuck",
                    f"rangefinder constant at {r:.3f} m since t={self._range_t0:.2f} while the "
                    f"estimated height changed by {h1 - h0:+.2f} m: readings dropped",
                )
                self._drop("range:stuck")
                return None
        return ev

    def _at_min(self, r: float, t: float) -> None:
        """A reading at the rangefinder's floor: the ``range-at-min`` test of its run."""
        o = self.options
        if self._atmin_t0 is None:
            self._atmin_t0, self._atmin_h0, self._atmin_named = t, None, False
        if self._atmin_named:
            return
        h = self._height(t)
        if h is None:
            return
        if self._atmin_h0 is None:
            # The first height known in the run (a run from the start has none at its start).
            self._atmin_h0 = (t, h, self._slam_last)
            return
        if t - self._atmin_t0 < o.range_stuck_s:
            return
        h0, s0, s1 = self._atmin_h0[1], self._atmin_h0[2], self._slam_last
        if s0 is not None and s1 is not None and s0[0] == s1[0]:
            # Both through the newest alignment (as the stuck test): its origin cancels.
            a, b = self.context.slam_height(*s0), self.context.slam_height(*s1)
            if a is not None and b is not None:
                h0, h = a, b
        if abs(h - h0) > o.range_stuck_motion_m + float(self.range_min or 0.0):
            self._atmin_named = True
            self._name_range_fault(
                "range-at-min",
                self.at_min_runs,
                (self._atmin_t0, t),
                f"rangefinder at its minimum {r:.3f} m since t={self._atmin_t0:.2f} while the "
                f"estimated height changed by {h - h0:+.2f} m: readings at the sensor's floor, "
                "not heights (range:at-min)",
            )

    def _at_max(self, r: float, t: float) -> None:
        """A reading at the rangefinder's maximum: the ``range-at-max`` test of its run."""
        o = self.options
        if self._atmax_t0 is None:
            self._atmax_t0, self._atmax_tk, self._atmax_named = t, None, False
            self._atmax_hi = -math.inf
        if self._atmax_named or self.range_max is None:
            return
        e = self.context.range_expected(t)
        if e is None or not math.isfinite(e):
            return
        if self._atmax_tk is None:
            self._atmax_tk = t  # the first prediction known in the run
        self._atmax_hi = max(self._atmax_hi, e)
        bound = self._reach()[1]
        # (a prediction near or above the maximum once in the run: the vehicle may be above the
        # sensor's reach, which is no fault)
        if self._atmax_hi >= bound or t - self._atmax_tk < o.range_stuck_s:
            return
        self._atmax_named = True
        self._name_range_fault(
            "range-at-max",
            self.at_max_runs,
            (self._atmax_t0, t),
            f"rangefinder at its maximum {r:.3f} m (no echo) since t={self._atmax_t0:.2f} while "
            f"the estimate put the ground at most {self._atmax_hi:.2f} m away along its beam, "
            f"well within its reach (below {bound:.2f} m): a blinded or failed sensor; its "
            "readings are no heights (range:at-max)",
        )

    def _name_range_fault(self, det: str, runs: list, run: tuple, detail: str) -> None:
        """Name the rangefinder fault ``det`` (a degrading one: in :attr:`lasting` until a
        usable reading comes) and keep its ``run`` in ``runs``."""
        runs.append(run)
        self.lasting.add(det)
        self._count(det, detail)

    def _reach(self) -> tuple[float, float]:
        """The readings within the sensor's reach (``range-silent``, ``range-at-max``): from
        ``range_min`` to the ``range-at-max`` bound below ``range_max`` (unknown limits:
        unbounded)."""
        o = self.options
        lo = -math.inf if self.range_min is None else self.range_min
        hi = (
            math.inf
            if self.range_max is None
            else self.range_max * (1.0 - o.range_at_max_margin_rel) - o.range_stuck_motion_m
        )
        return lo, hi

    def _range_silent(self, t: float) -> None:
        """An IMU sample past ``range_gap_s`` after the newest range reading: the
        ``range-silent`` test of the gap (once, or again a gap later while the prediction is
        beyond the reach)."""
        self._silent_due = math.inf
        if self._range_last is None:
            return
        t_r, r = self._range_last
        lo, hi = self._reach()
        if not lo <= r < hi:
            return  # (beyond the reach or on the floor: a sensor that leaves those out)
        e = self.context.range_expected(t)
        if e is not None and math.isfinite(e) and not lo <= e < hi:
            self._silent_due = t + self.options.range_gap_s
            return
        where = (
            f"; the estimate puts the ground {e:.2f} m away along its beam"
            if e is not None and math.isfinite(e)
            else ""
        )
        self._name_range_fault(
            "range-silent",
            self.silent_runs,
            (t_r, t),
            f"no range reading for {t - t_r:.2f} s since t={t_r:.2f} (the last {r:.3f} m, "
            f"within the sensor's reach{where}) while the IMU goes on: a rangefinder that "
            "stopped; no height from it",
        )

    def _image(self, ev) -> Any:
        h = _image_digest(ev)
        if h is None:
            return ev
        if h == self._image_hash:
            if not self._frozen:
                self._frozen = True
                self._count("camera-frozen", f"image at t={ev.t:.3f} identical to the previous one")
            else:
                self._count("camera-frozen")
            self._drop("images:frozen")
            return None
        self._frozen = False
        self._image_hash = h
        return ev

    def scale_change_explained(self) -> bool:
        """A fault of :data:`SCALE_DRIFT_EXPLAINED_BY` has been named."""
        return any(self.counts.get(k) for k in SCALE_DRIFT_EXPLAINED_BY)

    def named(self, det: str, detail: str) -> None:
        """A fault an estimator found itself (e.g. the push engine's SLAM-orientation check),
        counted under detector ``det`` and said once."""
        self._count(det, detail)

    def slam_check(self, decision: dict[str, Any] | None) -> None:
        """The SLAM-vs-gyro check's decision (``time_offset_s``, ``body_R_cam_ok``)."""
        if not decision or "slam-check" in self._said:
            return
        self._said.add("slam-check")
        off = decision.get("time_offset_s")
        applied = decision.get("applied_time_offset_s") or 0.0
        ok = decision.get("time_offset_ok", True)  # (False: too little rotation to tell)
        if ok and off is not None and abs(off) > self.options.slam_offset_tol_s:
            self._count(
                "slam-clock-offset",
                f"SLAM clock offset {off:+.3f} s (t_imu = t_slam + offset) from the "
                "SLAM-vs-gyro check"
                + (", applied" if applied else '; [graph] slam_time_offset = "apply" applies it'),
            )
        mirrored = decision.get("mirrored")
        if mirrored:
            self._count(
                "slam-mirrored",
                str(mirrored.get("message", "the SLAM frame is left-handed")).removeprefix(
                    "slam-mirrored: "
                )
                + (": un-mirrored" if mirrored.get("axis") else ": SLAM not used"),
            )
            return  # (the body_T_cam rotation it was named as is the mirror's)
        if decision.get("body_R_cam_ok") is False:
            self._count(
                "body_T_cam-rotation",
                f"body_T_cam rotation {decision.get('body_R_cam_error_deg', float('nan')):.1f} deg "
                "from the one the gyro fits",
            )


#: Faults that change the SLAM scale estimate themselves: ``slam-scale-drift`` is not named once
#: one of them has been (simulated two-turns, batch per-segment scales over 10 s: a 1 m jump
#: -0.23 %/s, a 2 s IMU gap -0.15 %/s, a 0.3 s clock offset +0.17 %/s, against the 5 %/s drift's
#: +0.26 %/s: the segments cannot tell them apart).
SCALE_DRIFT_EXPLAINED_BY = (
    "slam-jump",
    "slam-reset",
    "slam-clock-offset",
    "body_T_cam-rotation",
    "slam-mirrored",
    "imu-gap",
)


class ScaleDriftWatch:
    """The ``slam-scale-drift`` detector's arithmetic: fed each session's scale estimates in time
    order (causal), says once per session when the slope of ``log(scale)`` over the newest
    ``window_s`` exceeds ``bound_per_s`` in size; the estimates of the first ``settle_s`` after
    the session's first are left out (the window at least 80 % covered, 3 estimates or more).

    Args:
        bound_per_s: the largest relative scale rate not named [1/s].
        window_s: the slope's window [s].
        settle_s: estimates before this long after a session's first are left out [s].
    """

    def __init__(self, bound_per_s: float, window_s: float = 10.0, settle_s: float = 10.0):
        self.bound = float(bound_per_s)
        self.window_s = float(window_s)
        self.settle_s = float(settle_s)
        self._hist: dict[int, deque] = {}
        self._first: dict[int, float] = {}
        self.named: dict[int, tuple[float, float]] = {}  # session -> (t, rate)

    def feed(self, t: float, session: int, scale: float) -> str | None:
        """One estimate; the one-line message when this one names a drift (else None)."""
        if session in self.named or not (scale > 0 and math.isfinite(scale)):
            return None
        first = self._first.setdefault(session, t)
        if t - first < self.settle_s:
            return None
        h = self._hist.setdefault(session, deque())
        h.append((t, math.log(scale)))
        while h and h[0][0] < t - self.window_s:
            h.popleft()
        if len(h) < 3 or t - h[0][0] < 0.8 * self.window_s:
            return None
        a = np.asarray(h)
        tc = a[:, 0] - a[:, 0].mean()
        rate = float(tc @ (a[:, 1] - a[:, 1].mean()) / (tc @ tc))
        if not abs(rate) > self.bound:
            return None
        self.named[session] = (t, rate)
        return (
            f"SLAM session {session}: scale {'grows' if rate > 0 else 'shrinks'} "
            f"{100 * abs(rate):.2f} %/s over {self.window_s:.0f} s to t={t:.2f} s (bound "
            f"{100 * self.bound:.2f} %/s; real monocular SLAM drifts about 0.01 %/s)"
        )


def imu_saturation_flags(
    t: np.ndarray,
    body_omega: np.ndarray,
    body_accel: np.ndarray,
    options: HealthOptions | None = None,
) -> np.ndarray:
    """Saturation flags (:data:`SAT_GYRO_BITS`, :data:`SAT_ACCEL_BITS`) of each sample of an
    IMU series, as the ``imu-saturation`` detector gives them sample by sample in time order
    (causal: the first ``saturation_run - 1`` samples at a rail are not flagged)."""
    det = FaultDetectors(options or HealthOptions())
    out = np.zeros(len(t), dtype=np.uint8)
    feed = det._imu_values
    ts, ws, accs = np.asarray(t, float).tolist(), body_omega.tolist(), body_accel.tolist()
    for i, (ti, w, a) in enumerate(zip(ts, ws, accs, strict=True)):
        out[i] = feed(ti, w, a)
    return out


def _image_digest(ev: Any) -> bytes | None:
    """Digest of a frame's pixels (or file) for the frozen-camera check. SHA-1 of the buffer, not
    a copy of it: 63 us for 320x240 against 145 us for BLAKE2b of ``tobytes()`` (no security
    need, only equality with the previous frame)."""
    img = getattr(ev, "image", None)
    if img is not None:
        return hashlib.sha1(np.ascontiguousarray(img), usedforsecurity=False).digest()
    path = getattr(ev, "path", None)
    if path is None:
        return None
    try:
        return hashlib.sha1(path.read_bytes(), usedforsecurity=False).digest()
    except OSError:
        return None  # unreadable: the VO stage counts it


# ----------------------------------------------------------------------------------------------
# Online health monitor
# ----------------------------------------------------------------------------------------------


@dataclass
class Snapshot:
    """A healthy state of the online smoother (values of the live keys at keyframe ``k``)."""

    k: int
    t: float
    values: dict[int, Any]


class HealthMonitor:
    """Normalised innovations per sensor and state sanity after each keyframe (see the module
    docstring); decides when the estimate diverges and when to recover."""

    def __init__(self, options: HealthOptions | None = None, name: str = "health"):
        self.options = (options or HealthOptions()).check()
        self.name = name
        self.detectors = FaultDetectors(self.options, Context(), name)
        #: set by the smoother when its horizontal prediction is thrust-only (see ``sanity``)
        self.horizontal_accel_free = False
        #: The position sigma a restart's prior allows [m] (its norm; the online smoother sets it
        #: after an IMU gap, whose prior grows with the gap): above ``max_pos_sigma_m`` it is
        #: the bound. A 60 s gap gave 1875 m at the restart, a "divergence" before the SLAM poses
        #: re-anchored it, and the recovery dropped the carried SLAM alignment (ATE 1.8 m).
        self.pos_sigma_allowed = 0.0
        self._win: dict[str, deque] = {}
        self._sums: dict[str, list] = {}  # sensor -> [sum of chi2, sum of dof] over its window
        self.status = "ok"
        self.n_diverged = 0
        self.n_recovered = 0
        self.n_keyframes = 0
        self.n_alarm_keyframes = 0
        self.chi2_max: dict[str, float] = {}
        self._alarm_since: float | None = None
        self._last_recovery = -math.inf
        self._snapshots: deque = deque(maxlen=16)
        self._last_snapshot_t = -math.inf
        self.events: list[dict[str, Any]] = []
        #: the degrading faults (:data:`DEGRADING`) that last now
        self.degraded: set[str] = set()

    def innovations(self, sensor: str, t: float, chi2: float, dof: int) -> None:
        """Whitened squared error ``chi2`` of a factor with ``dof`` rows at time ``t``."""
        w = self._win.get(sensor)
        if w is None:
            w = self._win[sensor] = deque()
            self._sums[sensor] = [0.0, 0]
        sums = self._sums[sensor]
        w.append((t, chi2, dof))
        sums[0] += chi2
        sums[1] += dof
        big = False
        while w and w[0][0] < t - self.options.window_s:
            _, c, d = w.popleft()
            sums[0] -= c
            sums[1] -= d
            big = big or not c <= _RESUM_CHI2
        if big:
            # A large (or non-finite) value left the window: the running sum is taken afresh
            # (no cancellation error left behind).
            sums[0] = sum(x[1] for x in w)

    def chi2(self) -> dict[str, float]:
        """Normalised chi-squared (sum of whitened squares / dof) per sensor over the window
        (running sums kept by :meth:`innovations`, not a pass over the window)."""
        out = {}
        n_min = self.options.window_min_factors
        for s, w in self._win.items():
            if len(w) >= n_min:
                c, d = self._sums[s]
                out[s] = c / max(d, 1)
        return out

    def sanity(self, state: Any) -> list[str]:
        """Reasons the state is not sane (empty: sane)."""
        o = self.options
        bad = []
        # Plain floats: this runs at every keyframe (numpy's per-call overhead dominated it).
        v = np.asarray(state.world_v_body, float).tolist()
        p = np.asarray(state.world_T_body, float)[:3, 3].tolist()
        isfinite = math.isfinite
        if not all(map(isfinite, (*v, *p))):
            return ["non-finite state"]
        sp = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        if sp > o.max_speed_mps:
            bad.append(f"speed {sp:.1f} m/s > {o.max_speed_mps:g}")
        c = None if state.pose_cov is None else np.asarray(state.pose_cov, float).ravel().tolist()
        if c is not None and all(map(isfinite, c)):
            # (the 6x6 covariance's position diagonal, row-major: entries 21, 28 and 35)
            sig = math.sqrt(max(c[21] + c[28] + c[35], 0.0))
            limit = max(o.max_pos_sigma_m, self.pos_sigma_allowed)
            if sig > limit:
                bad.append(f"position sigma {sig:.1f} m > {limit:g}")
        ab = [abs(x) for x in np.asarray(state.accel_bias, float).tolist()]
        # With a thrust-only horizontal prediction (the smoother's accelerometer check found the
        # horizontal channels unusable) the x, y "bias" absorbs their offsets (1-5 m/s^2 on the
        # Crazyflie): judged against 3x the bound there.
        b0 = float(o.max_accel_bias)
        bound = [3.0 * b0, 3.0 * b0, b0] if self.horizontal_accel_free else [b0, b0, b0]
        if all(isfinite(x) for x in ab):
            ratio = [a / b for a, b in zip(ab, bound, strict=True)]
            worst = ratio.index(max(ratio))  # the first largest, as numpy's argmax
        else:
            worst = int(np.argmax(np.asarray(ab) / np.asarray(bound)))
        ba, ba_bound = ab[worst], bound[worst]
        gb = [abs(x) for x in np.asarray(state.gyro_bias, float).ravel().tolist()]
        bg = max(gb) if all(isfinite(x) for x in gb) else float(np.max(gb))  # NaN as numpy's
        if ba > ba_bound:
            bad.append(f"accelerometer bias {ba:.2f} m/s^2 > {ba_bound:g}")
        if bg > o.max_gyro_bias:
            bad.append(f"gyro bias {bg:.3f} rad/s > {o.max_gyro_bias:g}")
        return bad

    def after_keyframe(self, state: Any, snapshot: Callable[[], Snapshot]) -> Snapshot | None:
        """Judge the newest state; returns the healthy snapshot to recover from when the
        estimate diverges and a recovery is allowed (else None)."""
        o = self.options
        t = float(state.t)
        self.n_keyframes += 1
        chi = self.chi2()
        for s, c in chi.items():
            self.chi2_max[s] = max(self.chi2_max.get(s, 0.0), c)
        reasons = self.sanity(state)
        high = {s: c for s, c in chi.items() if c > o.chi2_alarm}
        alarm = bool(reasons or high)
        if not alarm:
            self._alarm_since = None
            if self.status != "ok" and self.status != "ok-after-recovery":
                self.status = "ok-after-recovery" if self.n_recovered else "ok"
            if t - self._last_snapshot_t >= 0.25:
                self._snapshots.append(snapshot())
                self._last_snapshot_t = t
            return None
        self.n_alarm_keyframes += 1
        if self._alarm_since is None:
            self._alarm_since = t
        diverged = bool(reasons) or t - self._alarm_since >= o.diverge_after_s
        if not diverged:
            return None
        why = reasons + [f"{s} chi2/dof {c:.0f} > {o.chi2_alarm:g}" for s, c in high.items()]
        first = self.status != "diverged"
        self.status = "diverged"
        if first:
            self.n_diverged += 1
            self.detectors._count(
                "divergence", f"estimate diverging at t={t:.2f}: {', '.join(why)}"
            )
        can = self.n_recovered < o.max_recoveries and t - self._last_recovery >= o.recovery_gap_s
        snap = None
        for s in reversed(self._snapshots):
            if s.t <= self._alarm_since - o.diverge_after_s:
                snap = s
                break
        if snap is None and self._snapshots:
            snap = self._snapshots[0]
        if not can or snap is None:
            if first:
                self.events.append({"t": t, "reasons": why, "recovered_from": None})
                log.warning(
                    "%s: not recovering (%s)",
                    self.name,
                    "no healthy state kept" if snap is None else "recovery limit reached",
                )
            return None
        self.n_recovered += 1
        self._last_recovery = t
        self._alarm_since = None
        self._win.clear()
        self._sums.clear()
        self._snapshots.clear()
        self.events.append({"t": t, "reasons": why, "recovered_from": snap.t})
        log.warning(
            "%s: recovering from the healthy state at t=%.2f s (rebuild)", self.name, snap.t
        )
        return snap

    def discard_snapshots(self) -> None:
        """Forget the healthy states kept so far: their slow variables are known wrong (a SLAM
        alignment re-seeded after its orientations were contradicted), and a recovery must not
        bring them back."""
        self._snapshots.clear()
        self._last_snapshot_t = -math.inf

    def healthy_snapshot(self) -> Snapshot | None:
        """The newest healthy snapshot from before the current alarm (None: none kept)."""
        lim = (self._alarm_since if self._alarm_since is not None else math.inf) - (
            self.options.diverge_after_s
        )
        for s in reversed(self._snapshots):
            if s.t <= lim:
                return s
        return None

    def restart(self) -> None:
        """The smoother restarted from nothing (its keyframe numbers start again): the
        snapshots, windows and alarm of the old chain are dropped; counts and status stay."""
        self._snapshots.clear()
        self._win.clear()
        self._sums.clear()
        self._alarm_since = None
        self._last_snapshot_t = -math.inf

    def degrade(self, det: str, detail: str, say: bool = True) -> None:
        """A degrading fault (:data:`DEGRADING`) begins: counted under ``det`` with ``detail``
        (a warning the first time unless ``say`` is False: said elsewhere) and in force until
        :meth:`restore`; nothing while it is in force."""
        if det in self.degraded:
            return
        self.degraded.add(det)
        if not say:
            self.detectors._said.add(det)
        self.detectors._count(det, detail)

    def restore(self, det: str) -> None:
        """The degrading fault ``det`` ended (the stream is usable again)."""
        self.degraded.discard(det)

    def quality(self, q: int, anchored: bool = False) -> int:
        """``q`` lowered while the estimate diverges (``DIVERGED_QUALITY``), or while a degrading
        fault lasts and nothing else anchors the position (``anchored``: a SLAM alignment or the
        camera; ``DEGRADED_QUALITY``)."""
        if self.status == "diverged":
            return min(q, DIVERGED_QUALITY)
        if (self.degraded or self.detectors.lasting) and not anchored:
            return min(q, DEGRADED_QUALITY)
        return q

    def report_status(self) -> str:
        """``status``, or ``degraded`` when a degrading fault was named and it did not diverge."""
        if self.status != "diverged" and any(self.detectors.counts.get(d) for d in DEGRADING):
            return "degraded"
        return self.status

    def report(self) -> dict[str, Any]:
        rep = self.detectors.report()
        return {
            "status": self.report_status(),
            **rep,
            "dropped": dict(self.detectors.dropped),
            "diverged": self.n_diverged,
            "recovered": self.n_recovered,
            "alarm_keyframes": self.n_alarm_keyframes,
            "keyframes": self.n_keyframes,
            "chi2_max": {k: round(v, 2) for k, v in self.chi2_max.items()},
            "episodes": self.events[:10],
            "options": dataclasses.asdict(self.options),
        }


def sensor_of(keys: Iterable[int]) -> str | None:
    """The sensor of a factor from its keys' symbol characters (None: not monitored): ``slam``
    (``X`` and ``S`` keys), ``range`` (``X`` and ``G`` only)."""
    chars = {chr(k >> 56) for k in keys}
    if "s" in chars and "x" in chars:
        return "slam"
    if chars == {"x", "g"}:
        return "range"
    return None


def health_line(health: dict[str, Any] | None) -> str | None:
    """The ``health:`` line the commands print (None without a report)."""
    if not health:
        return None
    det = health.get("detectors") or {}
    parts = [f"health: {health.get('status', 'ok')}"]
    if health.get("diverged"):
        parts.append(f"diverged {health['diverged']}x, recovered {health.get('recovered', 0)}x")
    if det:
        parts.append("detectors: " + ", ".join(f"{k} {v}" for k, v in det.items()))
    dropped = health.get("dropped") or {}
    if dropped:
        parts.append("dropped: " + ", ".join(f"{k} {v}" for k, v in sorted(dropped.items())))
    weighted = health.get("downweighted") or {}
    if weighted:
        parts.append("down-weighted: " + ", ".join(f"{k} {v}" for k, v in weighted.items()))
    return "; ".join(parts)


# ----------------------------------------------------------------------------------------------
# Batch
# ----------------------------------------------------------------------------------------------


def _interp(t_ref: np.ndarray, y: np.ndarray) -> Callable[[float], float | None]:
    def f(t: float) -> float | None:
        if t < t_ref[0] - 0.5 or t > t_ref[-1] + 0.5:
            return None
        return float(np.interp(t, t_ref, y))

    return f


def check_batch(flight: Any, est: Any, options: HealthOptions | None = None) -> dict[str, Any]:
    """Health of a batch solve: the detectors replayed over the flight with the solved trajectory
    as context, and the solve's own verdict. Returns the ``info["health"]`` dict plus the private
    ``_fixes`` (what :func:`fixed_flight` would change)."""
    from fgnav.datasets.events import replay_flight

    o = (options or HealthOptions()).check()
    tr = est.trajectory
    speed = np.linalg.norm(tr.world_v_body, axis=1) if tr.world_v_body is not None else None
    scales = {int(k): float(v) for k, v in (est.slam_scale or {}).items()}

    def scale(s: int) -> float | None:
        return scales.get(s) or scales.get(s % JUMP_SESSION_BASE)

    ctx = Context(
        speed=_interp(tr.t, speed) if speed is not None else (lambda t: None),
        height=_interp(tr.t, tr.world_t_body[:, 2]),
        scale=scale,
        range_expected=_range_expected(flight, est),
    )
    det = FaultDetectors(o, ctx, f"{est.method}: health")
    if flight.range is not None:
        det.range_min = float(flight.calib.range_min)
        det.range_max = float(flight.calib.range_max)
    jumps: list[tuple[float, int, int]] = []
    stuck: list[float] = []
    frozen: list[float] = []
    streams = [s for s in ("imu", "slam", "range", "images") if getattr(flight, s) is not None]
    for ev in replay_flight(flight, streams):
        out = det.feed(ev)
        name = type(ev).__name__
        if name == "SlamPose" and out is not None and out.session != ev.session:
            jumps.append((float(ev.t), int(ev.session), int(out.session)))
        elif name == "RangeReading" and out is None:
            stuck.append(float(ev.t))
        elif name == "ImageFrame" and out is None:
            frozen.append(float(ev.t))
    # Batch sees the whole flight: a stuck run is dropped from its first reading (the readings
    # before the detector could tell pull the height too: 10x nominal ATE on two-turns).
    if det.stuck_runs and flight.range is not None:
        rt, rv = np.asarray(flight.range.t, float), np.asarray(flight.range.range, float)
        for t0, value in det.stuck_runs:
            i = int(np.searchsorted(rt, t0 - 1e-9))
            j = i
            while j < len(rt) and rv[j] == value:
                j += 1
            stuck.extend(rt[i:j].tolist())
        stuck = sorted(set(stuck))
        det.dropped["range:stuck"] = len(stuck)
    info = est.info or {}
    if det.range_min is not None:
        from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, RangeLimits

        rv = np.asarray(flight.range.range, float)
        limits = RangeLimits.of_stream(rv, det.range_min, det.range_max)
        why = [limits.refusal(float(x)) for x in rv]
        for tag in RANGE_LIMIT_TAGS:
            if why.count(tag):
                det.dropped[f"range:{tag}"] = why.count(tag)
    _flow_faults(det, info)
    det.slam_check(info.get("slam_gyro_check"))
    # (only where the solve used range factors: else a second solve would change nothing)
    used_range = bool((info.get("factors") or {}).get("range"))
    steps = terrain_steps(flight, est, o, stuck) if used_range else []
    for t_step, jump in steps:
        det.named(
            "terrain-step",
            f"the ground under the rangefinder steps by {jump:+.2f} m at t={t_step:.2f} s: "
            "the ground height starts anew there",
        )
    series = getattr(est, "series", None) or {}
    if "slam_scale" in series and "slam_session" in series:
        watch = ScaleDriftWatch(
            o.slam_scale_drift_batch_per_s, o.slam_scale_drift_window_s, settle_s=0.0
        )
        sc, ss = series["slam_scale"], series["slam_session"]
        for t_s, v, sess in sorted(
            zip(
                np.asarray(sc.t, float),
                np.asarray(sc.value, float),
                np.asarray(ss.value),
                strict=True,
            )
        ):
            msg = watch.feed(float(t_s), int(sess), float(v))
            if msg and not det.scale_change_explained():
                det.named("slam-scale-drift", msg + " (batch, per-segment scales)")
    for sess, k in sorted((info.get("slam_axis_scale_nonpositive") or {}).items()):
        det.named(
            "slam-scale-nonpositive",
            f"SLAM session {sess}: per-axis scale {', '.join(f'{v:.4g}' for v in k)} SLAM units "
            "per metre, not positive on every axis",
        )
    no_cov = info.get("covariance", "none") != "none" and bool(info.get("covariance_unavailable"))
    if no_cov:
        det.named(
            "covariance-unavailable",
            "no marginal covariance (Cholesky, damped Cholesky and QR all failed: "
            f"{info['covariance_unavailable']}); the estimate has no sigma",
        )
    rep = det.report()
    n_sat = (info.get("factors") or {}).get("imu-saturated-intervals", 0)
    # A degraded estimate says so first; one without covariances next (both are detectors).
    status = (
        "degraded"
        if any(det.counts.get(d) for d in DEGRADING)
        else "no-covariance"
        if no_cov
        else "ok"
    )
    errors = info.get("lm_errors") or []
    n_f = info.get("n_factors") or 0
    per_factor = 2.0 * errors[-1] / n_f if errors and n_f else None
    last_rel = (errors[-2] - errors[-1]) / max(errors[-2], 1e-300) if len(errors) > 1 else 1.0
    if info.get("lm_converged") is False and last_rel > o.batch_stall_rel:
        status = "not-converged"
    elif per_factor is not None and per_factor > o.batch_error_per_factor_max:
        status = "not-converged"
    return {
        "status": status,
        **rep,
        "dropped": dict(det.dropped),
        "downweighted": {"imu-saturated-intervals": n_sat} if n_sat else {},
        "error_per_factor": per_factor,
        "_fixes": {
            "jumps": jumps,
            "stuck_range_t": stuck,
            "frozen_image_t": frozen,
            "ground_steps_t": [t for t, _ in steps],
        },
    }


def _range_expected(flight: Any, est: Any) -> Callable[[float], float | None]:
    """The batch's :attr:`Context.range_expected`: the reading the solve predicts at time t (the
    distance along the beam from the sensor to the ground height of t's segment, the trajectory
    interpolated); None everywhere when the solve used no range factor (its ground is no
    measurement) or has no ground height, and where the beam points 85 deg or more from down."""
    none: Callable[[float], float | None] = lambda t: None  # noqa: E731
    info = est.info or {}
    ground = (getattr(est, "series", None) or {}).get("ground_height")
    tr = est.trajectory
    if flight.range is None or ground is None or not (info.get("factors") or {}).get("range"):
        return none
    tg = np.asarray(ground.t, float)
    vg = np.asarray(ground.value, float).reshape(len(tg), -1)[:, 0]
    if len(tg) == 0 or tr is None or len(tr.t) < 2:
        return none
    from fgnav.factors.tilted_range import predicted_range

    g = vg[np.clip(np.searchsorted(tg, tr.t, side="right") - 1, 0, len(tg) - 1)]
    expected = predicted_range(
        tr.world_R_body(), tr.world_t_body, g, np.asarray(flight.calib.body_T_range, float)
    )
    f = _interp(tr.t, expected)

    def range_expected(t: float) -> float | None:
        v = f(t)
        return None if v is None or not math.isfinite(v) else v

    return range_expected


def _flow_faults(det: FaultDetectors, info: dict[str, Any]) -> None:
    """The batch's degrading flow faults: ``flow-rejected`` from the solve's reject watch
    (``info["flow"]["all_rejected"]``, said there), ``flow-no-height`` where the graph builder
    found a flow stream with no height source (``info["flow_no_height"]``, said there: no
    rangefinder stream, or ``use_range`` off; not when ``use_flow`` is off)."""
    rej = (info.get("flow") or {}).get("all_rejected")
    if rej:
        det._said.add("flow-rejected")
        det._count(
            "flow-rejected",
            f"every flow reading rejected from t={rej['since_s']:.2f} to {rej['until_s']:.2f} s "
            f"({', '.join(f'{r} {c}' for r, c in sorted(rej['reasons'].items()))}): the flow "
            "gives no velocity",
            int(rej.get("runs") or 1),
        )
    why = info.get("flow_no_height")
    if why:
        det._said.add("flow-no-height")
        det._count(
            "flow-no-height",
            f"optical flow with no height source ({why}): the flow gives no metric velocity; "
            "not used, the horizontal velocity and the height are dead-reckoned",
        )


def terrain_steps(
    flight: Any, est: Any, o: HealthOptions, skip_t: Iterable[float] = ()
) -> list[tuple[float, float]]:
    """Steps of the ground the range readings see through the solved trajectory: ``(time of the
    first reading on the new level [s], step [m])``. Each reading's ground is the sensor's
    height minus the reading times the beam's cosine; a step is where the median of the
    ``terrain_step_n`` readings after differs by more than ``terrain_step_m`` from the median of
    those before, each side's median deviation within a quarter of that (a lone spike moves
    neither median). Every split within a few readings of an edge shows the whole jump: of each
    run of such splits the step is the one that leaves each side the tightest (least mean
    deviation); a run ends where the jump changes sign (a short raised stretch has two edges).
    ``skip_t``: readings already dropped."""
    r = flight.range
    tr = est.trajectory
    n = o.terrain_step_n
    if r is None or len(r.t) < 2 * n or tr is None or len(tr.t) < 2:
        return []
    calib = flight.calib
    from fgnav.datasets.range_limits import RangeLimits

    # (a reading at the sensor's floor or maximum sees no ground: range_refusal)
    keep = RangeLimits.of_stream(r.range, calib.range_min, calib.range_max).mask(r.range)
    keep &= (r.t >= tr.t[0]) & (r.t <= tr.t[-1]) & ~np.isin(r.t, np.asarray(list(skip_t)))
    t, rng = np.asarray(r.t, float)[keep], np.asarray(r.range, float)[keep]
    if len(t) < 2 * n:
        return []
    idx = np.clip(np.searchsorted(tr.t, t), 0, len(tr.t) - 1)
    R = tr.world_R_body()[idx]
    T = np.asarray(calib.body_T_range, float)
    z = np.interp(t, tr.t, tr.world_t_body[:, 2]) + (R @ T[:3, 3])[:, 2]
    cos = np.maximum(-(R @ T[:3, 2])[:, 2], 1e-3)
    ground = z - rng * cos
    # Window j holds readings j .. j+n-1: the split before reading i has window i-n before it
    # and window i after it, i = n .. len - n.
    win = np.lib.stride_tricks.sliding_window_view(ground, n)
    med = np.median(win, axis=1)
    dev = np.abs(win - med[:, None])
    mad, mean_dev = np.median(dev, axis=1), dev.mean(axis=1)
    jump = med[n:] - med[:-n]
    ok = (np.abs(jump) > o.terrain_step_m) & (
        np.maximum(mad[:-n], mad[n:]) < 0.25 * o.terrain_step_m
    )
    spread = mean_dev[:-n] + mean_dev[n:]
    out: list[tuple[float, float]] = []
    cand = np.flatnonzero(ok)
    if cand.size:
        # Runs of splits no more than n readings apart, of one sign (the two edges of a
        # raised stretch 8-14 readings long were one run: one step named, with one edge's sign).
        brk = (np.diff(cand) > n) | (np.diff(np.sign(jump[cand])) != 0)
        for run in np.split(cand, np.flatnonzero(brk) + 1):
            c = run[np.argmin(spread[run])]
            out.append((float(t[c + n]), float(jump[c])))
    return out


def constant_range_runs(flight: Any, min_s: float) -> list[tuple[int, int]]:
    """Index runs ``[i, j)`` of identical range readings spanning at least ``min_s`` [s]."""
    if flight.range is None or len(flight.range.t) < 2:
        return []
    t, r = np.asarray(flight.range.t, float), np.asarray(flight.range.range, float)
    starts = np.flatnonzero(np.r_[True, r[1:] != r[:-1]])
    ends = np.r_[starts[1:], len(r)]
    from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, RangeLimits

    # (a run at the sensor's floor or maximum is no height factor: range-at-min or no echo,
    # not stuck)
    calib = getattr(flight, "calib", None)
    lo = getattr(calib, "range_min", None)
    limits = None
    if lo is not None:
        limits = RangeLimits.of_stream(r, lo, getattr(calib, "range_max", math.inf))
    return [
        (int(i), int(j))
        for i, j in zip(starts, ends, strict=True)
        if np.isfinite(r[i])
        and t[j - 1] - t[i] >= min_s
        and not (limits is not None and limits.refusal(float(r[i])) in RANGE_LIMIT_TAGS)
    ]


def stuck_range_candidates(
    flight: Any, declared_t: Any, options: HealthOptions | None = None
) -> list[tuple[int, int]]:
    """The constant range runs (index runs) the batch's detector did not declare stuck
    (``declared_t``: the times of the readings it dropped). Its context, the solve with those
    readings in it, can follow a stuck reading (the more, the stiffer the ground-height walk);
    :func:`confirm_stuck_range` tests them on a solve without them."""
    o = (options or HealthOptions()).check()
    if flight.range is None:
        return []
    declared = {float(x) for x in declared_t}
    t = np.asarray(flight.range.t, float)
    runs = constant_range_runs(flight, o.range_stuck_s)
    return [(i, j) for i, j in runs if float(t[i]) not in declared]


def confirm_stuck_range(
    flight: Any, runs: list[tuple[int, int]], est: Any, options: HealthOptions | None = None
) -> list[tuple[int, int]]:
    """The runs over which ``est`` (solved without their readings) says the rangefinder's height
    changed by more than ``range_stuck_motion_m`` while it read one value: stuck."""
    o = (options or HealthOptions()).check()
    tr = est.trajectory
    t = np.asarray(flight.range.t, float)
    out = []
    for i, j in runs:
        ts = t[i:j]
        ts = ts[(ts >= tr.t[0] - 0.5) & (ts <= tr.t[-1] + 0.5)]  # as _interp's span
        zs = np.interp(ts, tr.t, tr.world_t_body[:, 2])
        if len(zs) and float(zs.max() - zs.min()) > o.range_stuck_motion_m:
            out.append((i, j))
    return out


def fixed_flight(flight: Any, fixes: dict[str, Any]) -> Any | None:
    """The flight with the detectors' fixes applied (SLAM poses after a jump in a new session,
    stuck range readings and frozen images removed), or None when there is nothing to fix."""
    jumps, stuck, frozen = fixes["jumps"], fixes["stuck_range_t"], fixes["frozen_image_t"]
    steps = fixes.get("ground_steps_t") or []
    if not (jumps or stuck or frozen or steps):
        return None
    changes: dict[str, Any] = {}
    if steps:
        from fgnav.solvers.graph import GROUND_STEPS_META_KEY

        known = [float(x) for x in flight.meta.get(GROUND_STEPS_META_KEY, ())]
        changes["meta"] = {
            **flight.meta,
            GROUND_STEPS_META_KEY: sorted(set(known) | {float(x) for x in steps}),
        }
    if jumps and flight.slam is not None:
        s = flight.slam
        sess = s.session.copy()
        for t, orig, virtual in jumps:
            m = (s.t >= t - 1e-9) & (s.session == orig)
            sess[m] = np.maximum(sess[m], virtual)
        changes["slam"] = dataclasses.replace(s, session=sess)
    if stuck and flight.range is not None:
        keep = ~np.isin(flight.range.t, np.asarray(stuck))
        # (every reading stuck: no range stream; an empty one was refused as a bad flight)
        changes["range"] = flight.range.select(keep) if keep.any() else None
    if frozen and flight.images is not None:
        changes["images"] = flight.images.select(~np.isin(flight.images.t, np.asarray(frozen)))
    return dataclasses.replace(flight, **changes)
