"""Push-API online fixed-lag smoother: measurement events in, the newest state out.

``OnlineSmoother(calib, options)`` is fed the typed events of :mod:`fgnav.datasets.events` one at a
time, in arrival order (a replayed log or a live link: the smoother cannot tell them apart), and
keeps an iSAM2 fixed-lag window (:class:`fgnav.solvers.window.TimeOrderedSmoother`). It never sees
a flight: every decision uses only what has arrived.

Keyframes follow a grid step of ``1 / keyframe_hz`` after the newest one (or the next camera
image, see *Camera*); keyframe k *closes* when an IMU sample after ``t_k`` arrives: the arrived
IMU preintegrated since k-1 (zero-order hold, the bias estimate of k-1) gives a
``CombinedImuFactor`` and the predicted initial values, and one iSAM2 update adds it with every
measurement that has arrived for a keyframe still in the window. The newest state is the causal
output (``latest()``, ``result()``); each keyframe's state as smoothed when the next update
marginalises it is the ``fixed-lag@lag`` output (``lagged_result()``).

- **Start**: at the first SLAM pose's capture time when a SLAM pose arrives within ``start_wait_s``
  of the first IMU sample (``FixedLagOptions.graph.use_slam``), else at the IMU. Attitude from the
  attitude stream when one has arrived, else level from the mean specific force of the last
  ``init_imu_s``; yaw from the yaw stream or ``graph.initial_yaw``. Gyro bias: the mean rate of the
  newest still stretch of the arrived IMU before the start (specific force within
  ``still_accel_tol`` of g, rate scatter below ``still_gyro_tol``; a vehicle standing before it
  takes off), else zero (its prior sigma covers it) until the SLAM-vs-gyro check gives one; the same
  stretch gives the accelerometer bias along its specific force, ``|f| - g`` (``still_accel_bias``;
  across it a bias is one with the tilt). When that still stretch ended before the start (a take-off
  before it, no attitude stream), attitude and velocity are the stretch's level attitude and rest
  integrated with the arrived IMU up to the start (``_from_still``), not a level on the moving
  vehicle's specific force.
- **SLAM** (``graph.slam_model`` ``sim3``; the per-axis model below): a pose taken at ``t``
  attaches to the keyframe nearest ``t`` through
  :func:`fgnav.factors.slam_scale.make_slam_position_offset_factor` (the body carried over
  ``t - t_k`` by the IMU reading at ``t``). Each session has a chain of
  ``Similarity3`` alignment variables, one per ``graph.slam_segment_s`` of the session's time, with
  a random walk between them; a segment whose predecessor has left the window (a SLAM pause longer
  than the lag) starts from the predecessor's last estimate under a prior widened by the walk over
  the gap, never from a fresh fit. A session's chain starts from the closed-form fit
  (:func:`fgnav.solvers.measurements.init_slam_alignment`) over its poses so far once they span
  ``slam_init_window_s`` and the fit passes the excitation, standard-error and pair-count gates
  (both rotation conventions tried until the SLAM-vs-gyro check decides); before that
  its poses attach to a *provisional* alignment (rotation from the SLAM orientation and the current
  attitude, scale from the previous session or ``slam_provisional_scale``, origin at the newest
  pose, wide log-scale prior; while its scale is the default, a second pose long after the first
  waits for the third: ``slam_provisional_lone_gap_s``). When the chain starts, the provisional
  factors still in the window are removed and re-attached to it (counted as ``slam:reattached``). A
  new session id (a map reset) starts a new chain; its starting scale fuses the fit with the
  provisional alignment's estimate, which the velocity known from the session before determines
  (``slam_chain_fuse_provisional``). A pose that arrives before the start (the first, with no
  latency) attaches at the start once it is made. The causal
  SLAM-vs-gyro check (:class:`fgnav.datasets.slam_gyro.SlamGyroCheck`) decides the file's rotation
  convention (an inverted file is named and used inverted), names a wrong ``body_T_cam`` rotation
  and estimates the clock offset; once decided, the SLAM orientations become factors, on the
  provisional alignment too (a pose moved from it onto the chain keeps its rotation factor). The
  orientation check (``OnlineSmoother._orientation_check``, once a second) compares the
  alignment rotation the SLAM orientations give through ``body_R_cam`` with the one the SLAM
  positions and the IMU's motion give: relative rotations about one axis (a hover, yaw-only
  turns) cannot show a wrong ``body_R_cam``, the positions can. A contradiction is named
  (health detector ``body_T_cam-rotation``); the orientations are then not used and an
  alignment seeded through them is re-seeded from the motion.
- **Range** and **yaw**: interpolated to the keyframe time once the sample after it has arrived
  (bracketing gap at most ``graph.interp_max_gap_s``); range gated on limits and tilt, and on
  its innovation against the keyframe's current estimate (``FixedLagOptions.range_gate_m``; a
  run of refused readings that agree is a terrain step: the ground height starts anew,
  ``_range_gate``). A new ground-height variable starts from the median of the newest
  three readings.
- **Drag**: mean accelerometer over the keyframe's window once the next keyframe has closed; off
  when the mean specific force of the first ``drag_check_s`` is more than
  ``graph.drag_thrust_max_angle_deg`` from body +z, or when the accelerometer check
  (:mod:`fgnav.solvers.accel_check`) finds the horizontal channels unusable (then, with
  ``graph.accel_horizontal = "auto"`` and no SLAM in use, the IMU prediction is thrust-only);
  said once; its noise floor follows the running scatter of the keyframe means. With ``"auto"``
  and no SLAM in use the prediction is thrust-only from the start (when the start's specific
  force is along body +z) until the check finds the accelerometer usable in the air (no ground
  contact among its keyframes) or noisy over a full window: a vibrating accelerometer integrated
  while the check decides tilted the Crazyflie's attitude by up to 14 deg on the ground. Without
  SLAM a thrust-only prediction carries the drag dynamics (``graph.thrust_only_drag_sigma``: the
  x, y bias tied to ``k u_xy``); with SLAM (only with ``accel_horizontal = "thrust-only"``
  given) the bias walks freely.
- **Time rules**: a sample older than its stream's newest by less than ``clock_jump_s`` is
  rejected and counted (``<stream>:out-of-order``; equal stamps ``<stream>:duplicate``); an IMU
  stamp that goes back by more than that is a clock jump and resets the smoother
  (``reset_counter`` += 1). An IMU gap longer than ``max_imu_gap_s`` also resets it (the chain is
  not integrated blindly): it restarts from the newest state and SLAM alignment before the gap
  (``_carry_state``, ``_carried_chain``) and keeps a decided SLAM rotation convention and clock
  offset. A measurement whose keyframe has left the window is counted as
  ``<stream>:late``.
- **Factorization**: QR for the first ``startup_qr_s``, then Cholesky; a failed Cholesky update
  moves the window, that update's factors included, into a QR smoother (nothing lost); a failure
  under QR rebuilds it from the last good newest state and slow variables with priors
  (``solver_failures``, ``reset_counter`` += 1): the smoother never crashes on a solver failure.
- **Health** (:mod:`fgnav.health`): fault detectors on the events and a monitor of the whitened
  errors and the state; a diverging estimate lowers ``quality`` and is rebuilt from the last
  healthy state.
- **Camera** (downward, with the rangefinder): every image anchors the keyframe at its time
  (keyframes at least ``MIN_ANCHOR_GAP_PERIODS`` apart; a keyframe without an image waits half a
  period plus ``image_latency_s`` for one) and goes through the homography VO stage
  (:class:`fgnav.frontends.homography_vo.HomographyVoStage`, inside this loop: its time counts)
  with the attitude and height known when it arrives; each gated pair becomes a homography factor
  between the keyframes of its frames (pairs across frames without a keyframe composed).
- **Optical flow**: the readings ending in each keyframe's window summed into one factor
  (:func:`fgnav.solvers.flow.flow_keyframe_factor`) once the next keyframe has closed.

- **Front-end priors** (``priors``: the ``[priors]`` table): seed 000's I&I observer and seed
  004's ML scale run as :class:`fgnav.frontends.prior_stages.FrontendPriorStage`, fed every
  event this smoother accepts. When keyframe k closes, the observer's velocity at the processed
  IMU sample nearest ``t_k`` (within half a period; after its 5 s settle time) is a prior on
  ``V(k)`` (sigma 0.2 m/s, as the prepared engine's); a session's ML scale, once the stage has
  accepted 3 pairs, is the initial value and prior (its Fisher sigma) of the session's chain
  when the chain starts after that, else one scale-only prior on the chain's newest alignment
  variable (once per session); a provisional alignment starts from it. Used counts:
  ``prior:observer-velocity``, ``prior:ml-scale``.

- **Per-axis SLAM** (seed 000, ``graph.slam_model = "axis"``, or ``"auto"`` on a flight whose
  SLAM input declares it, ``meta["slam_model"]``): each session (a map reset the input
  declares, or a jump the health check splits off, has a new scale and origin) feeds its own
  chain of Vector6 ``[kx, ky, kz, ox, oy, oz]`` variables (per-axis scale, SLAM origin; SLAM
  axes = world axes),
  one per ``graph.slam_segment_s``, with the batch's relative random walk between them. It starts
  from the per-axis least-squares fit (:func:`fgnav.solvers.measurements.fit_axis_scale`) over
  the arrived poses once they span ``slam_init_window_s`` and the fit has
  ``slam_init_min_pairs`` pairs and one axis within ``slam_init_max_rel_se``; the poses wait
  for it (no provisional alignment) and attach through
  :func:`fgnav.factors.slam_scale.make_slam_axis_position_offset_factor`.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import math
import operator
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import (
    STREAM_OF_EVENT,
    AttitudeSample,
    FlowSample,
    ImageFrame,
    ImuSample,
    RangeReading,
    SlamPose,
    YawReading,
)
from fgnav.datasets.geometry import (
    make_pose,
    matrix_to_quat_wxyz,
    quat_wxyz_to_matrix,
    slerp_rotations,
    so3_exp,
    so3_log,
    wrap_angle,
)
from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, RangeLimits, range_at_max
from fgnav.datasets.types import (
    IMU_MAX_ACCEL,
    IMU_MAX_RATE,
    Calibration,
    ImuSeries,
    SlamSeries,
    Trajectory,
)
from fgnav.estimate import Estimate, OnlineState, TimeSeries
from fgnav.factors import _jacobians
from fgnav.factors.accel_drag import make_accel_drag_factor, mean_accel_noise
from fgnav.factors.slam_scale import (
    make_slam_axis_position_offset_factor,
    make_slam_position_factor,
    make_slam_position_offset_factor,
    make_slam_rotation_factor,
    make_slam_T_world,
    slam_alignment_parts,
)
from fgnav.factors.tilted_range import (
    MIN_COS_TILT,
    gate_range,
    make_range_factor,
    predicted_range,
)
from fgnav.factors.yaw import make_yaw_factor
from fgnav.frontends.vo_process import VoProcess
from fgnav.health import (
    Context,
    HealthMonitor,
    HealthOptions,
    ScaleDriftWatch,
    Snapshot,
    sensor_of,
)
from fgnav.keys import B, S, V, X
from fgnav.solvers.accel_check import AccelLimits, RunningAccelCheck
from fgnav.solvers.fixed_lag import (
    ENGINES,
    SLAM_FIT_IMU_MARGIN_S,
    SOLVER_ERRORS,
    VO_WORKERS,
    FixedLagOptions,
    _isam2_params,
    fixed_lag_estimate,
    rebuild_state_priors,
    try_move_window,
)
from fgnav.solvers.flow import FlowRejectWatch, flow_sensor_height
from fgnav.solvers.graph import (
    ACCEL_CHECK_MAX_TILT_DEG,
    GROUND_EPOCH_STRIDE,
    WEAK_SCALE_PRIOR_REL,
    choose_slam_model,
    gyro_bias_prior_sigmas,
    pim_params,
    robust_noise,
    saturated_pim_params,
    thrust_only_noise,
)
from fgnav.solvers.measurements import (
    MIN_ANCHOR_GAP_PERIODS,
    fit_axis_scale,
    init_slam_alignment,
    level_rotation_from_accel,
    slam_second_differences,
    world_specific_accel,
)
from fgnav.solvers.window import TimeOrderedSmoother

log = logging.getLogger(__name__)

_EYE4 = np.eye(4)
#: Quaternion conjugation (w, -x, -y, -z): the inverse rotation.
_CONJ = np.array([1.0, -1.0, -1.0, -1.0])
#: Accelerometer-bias walk on body x, y over the keyframe interval where the prediction turns
#: thrust-only [m/s^3/sqrt(Hz)]: the bias may jump by the measured offsets (1-5 m/s^2 on the
#: Crazyflie) within one 50 ms interval.
BIAS_RELEASE_WALK = 30.0
#: Ballast variables per window variable with ``relinearize_threshold_position`` set
#: (``TimeOrderedSmoother(ballast=...)``; above 1 / 0.65 - 1 = 0.54, iSAM2's batch share).
#: Measured 2026-12-03 (60 s figure8 benchmark without camera, 3 mm, load 2-5): the updates
#: that relinearise 188 -> 96 CustomFactor callbacks on average, 16.3 -> 7.4 ms; estimates
#: the same up to the elimination order's rounding (MH_01 3.784 against 3.775 cm).
BALLAST_WITH_POSITION_THRESHOLD = 0.6
#: Keyframes of the first accelerometer check (0.5 s at 20 Hz; then every 5 keyframes over the
#: last ``drag_scatter_n``): the IMU prediction uses the measured horizontal specific force until
#: it has decided, so it decides early (the Crazyflie: ratio 7-40 already on the first 0.5 s).
ONLINE_ACCEL_CHECK_MIN_KEYFRAMES = 10
#: Restart after an IMU gap longer than ``max_imu_gap_s`` (issue 18): the chain is broken, not
#: integrated blindly, and the smoother starts again from the newest state before the gap. The
#: mean acceleration over the gap is unknown, with this sigma [m/s^2]: the carried velocity's
#: prior sigma grows by it times the gap, the position's by half of it times the gap squared
#: (the carried SLAM alignment then places the vehicle at the first pose after the gap).
GAP_ACCEL_SIGMA = 1.0
#: Sigma of the unknown mean yaw rate over an IMU gap [rad/s] (the carried yaw's prior).
GAP_YAW_RATE_SIGMA = 0.5
#: A slow variable carried over a restart keeps its marginal covariance, sigmas times this.
CARRY_SIGMA_FACTOR = 2.0
#: Oldest SLAM pose that places the vehicle at a restart after an IMU gap [s before the start].
GAP_PLACE_MAX_S = 0.5
#: Window of the stillness test of the gyro-bias start [s] (see ``_still_gyro_bias``).
STILL_WINDOW_S = 0.5
#: Longest still stretch averaged for the gyro-bias start [s].
STILL_MAX_S = 2.0
#: A mean rate above this [rad/s] on any axis is motion, not a gyro bias (MEMS gyro biases are
#: below 0.1 rad/s: EuRoC's ADIS16448 about 0.08 on one axis).
STILL_MAX_GYRO_BIAS = 0.2
#: Largest IMU sample taken [rad/s, m/s^2]: ``fgnav.datasets.types.IMU_MAX_RATE`` and
#: ``IMU_MAX_ACCEL`` (the readers skip the same samples); a larger one is dropped as
#: ``imu:implausible``.
_IMU_MAX_RATE_SQ, _IMU_MAX_ACCEL_SQ = IMU_MAX_RATE**2, IMU_MAX_ACCEL**2
#: Largest SLAM position coordinate taken [SLAM units]: a map's units are arbitrary but its
#: positions stay within some thousand units of its origin (metres-like in the monocular
#: systems fgnav reads: EuRoC's ORB-SLAM runs within 20); a larger finite value is a corrupted
#: pose (a SLAM bridge's -1e30 made the jump detector open a session per pose and the estimate
#: non-finite), dropped as ``slam:implausible-position``.
SLAM_MAX_COORD = 1e6
#: Late measurements of one stream before ``OnlineSmoother._warn_late`` says so (once).
LATE_WARN_N = 20
#: A window in which the attitude stream turns by more than this [rad] is motion, not still:
#: a steady roll or pitch rate in flight passes the rate tests (simulated figure8 with its
#: first 12 s of SLAM removed: 0.12 rad/s taken for the gyro bias, the start diverged).
STILL_MAX_ATTITUDE_TURN = 0.02
#: A new ground-height variable starts from the median of the newest three range readings of
#: the last this many seconds (one could be an outlier: simulated two-turns seed 1's first is).
GROUND_GUESS_S = 0.3
#: The range innovation gate is at least this fraction of the reading (see
#: ``FixedLagOptions.range_gate_m``).
RANGE_GATE_REL = 0.1
#: A SLAM pose within this time [s] of the previous one is dropped (``slam:too-close``).
MIN_SLAM_DT_S = 1e-3
#: A non-IMU stamp this far ahead of the newest IMU stamp [s] is dropped (``<stream>:future-
#: time``): no reading of the flight.
FUTURE_STAMP_S = 600.0
#: The push engine's count of a range bracket refused by ``range_refusal`` (as
#: ``_range_factor`` counts a value ``gate_range`` refuses: its "out of range" is ``gated:out``).
_RANGE_DROP = {"out-of-range": "range:gated:out", "non-finite": "range:non-finite"}
#: Range readings are gated only while the stream has been taken within this many seconds [s].
RANGE_GATE_FRESH_S = 1.0
#: Index offset of provisional SLAM-alignment keys ``S(PROVISIONAL_BASE + n)``, above every
#: chain key (2^40: 11 million sessions of 100 000 segments).
PROVISIONAL_BASE = 1 << 40
#: Index stride of a session's alignment chain: ``S(index * SESSION_STRIDE + segment)``, with
#: ``index`` the session's order of arrival (0, 1, ...), whatever id the SLAM gives it.
SESSION_STRIDE = 100_000
#: Rotation sigma [rad] of the prior on a SLAM segment that starts after its predecessor left
#: the window (on top of the walk over the pause; the scale's is 1 %).
GAP_SEGMENT_ROT_SIGMA = 0.01
#: Floor of that prior's sigmas (a zero walk and a zero origin sigma would pin the origin).
MIN_GAP_SEGMENT_SIGMA = 1e-6
#: Velocity prior at a start integrated from rest (``OnlineSmoother._from_still``): sigma
#: ``STILL_VEL_SIGMA + STILL_VEL_SIGMA_RATE * age`` [m/s] with ``age`` the time since the
#: still stretch ended (an accelerometer bias and a tilt of the still attitude of 0.1 m/s^2
#: each, integrated, plus a floor). Only EuRoC V1_02 starts this way among the shared flights
#: (MH_01, the Crazyflie flights and the simulated ones do not). Tried 2026-12-05, rate 0.1
#: (the still attitude absorbs a bias as tilt in the still orientation, so only the bias
#: term): V1_02 causal ATE own span / common span / ``fixed-lag@lag`` common, ORB-SLAM2
#: 8.14 / 4.46 / 2.81 -> 7.71 / 4.36 / 2.67 cm, ORB-SLAM3 3.46 / 2.70 / 2.15 -> 3.30 / 2.80 /
#: 2.30 cm (rate 0.02, floor 0.02: ORB-SLAM2 7.24, ORB-SLAM3 3.54): mixed, not adopted. The
#: ORB-SLAM2 excess is the second SLAM pose (1.2 s after the first) pulling the states 0.5-0.7
#: m while the provisional scale is still 1 (true 0.44); see FixedLagOptions.
STILL_VEL_SIGMA = 0.05
STILL_VEL_SIGMA_RATE = 0.2
#: Angle [deg] between the closed-form fit's SLAM rotation through ``body_R_cam`` and the one
#: the motion fits above which the motion's is preferred while ``body_R_cam`` is unverified.
SLAM_FIT_ROTATION_MAX_DEG = 10.0
#: Least ``rotation_spread`` of a motion-only alignment fit (two directions among the
#: accelerations and turns): from accelerations alone the chain's first fits on EuRoC MH_01
#: and the simulated flights had 0.002-0.07 (one axis); with the turns, simulated rectangle
#: and figure8 0.86-0.99, a climb without turns (``vertical``) 0.001-0.004.
SLAM_FIT_MOTION_MIN_SPREAD = 0.2
#: Largest scale relative standard error of a motion-only fit to be used (its rotation is
#: fitted to the same pairs: simulated two-turns with an identity ``body_R_cam`` had 0.165 at
#: 7.4 s and a rotation that diverged; rectangle and figure8 0.007-0.05 when adopted).
SLAM_FIT_MOTION_MAX_REL_SE = 0.05
#: While ``body_R_cam`` is unverified the motion's fit replaces the one through it when it fits
#: the scale this many times better (and is ``SLAM_FIT_ROTATION_MAX_DEG`` away).
SLAM_FIT_MOTION_BETTER = 1.5
#: The SLAM orientations through ``body_R_cam`` (and the rotation convention) contradict the
#: SLAM positions and the IMU (:meth:`OnlineSmoother._orientation_check`) when the motion-only
#: fit passes the chain's gates with two directions, has a scale rel. s.e. of at most
#: ``SLAM_MOTION_DOMINANT_MAX_REL_SE``, is ``SLAM_MOTION_DOMINANT_DEG`` or more from the fit
#: through the orientations and fits the scale ``SLAM_MOTION_DOMINANT_BETTER`` times better (or
#: the orientations give no positive scale). Measured on simulated hover (60 s, seed 1), every
#: second from 8 s: right ``body_T_cam`` 0.8-6.8 deg apart, orientation s.e. / motion s.e.
#: 0.99-1.01; an identity for the true rotation 173-180 deg apart, ratio 5-2800 (the motion's
#: s.e. 0.05-0.08: the hover's small motion).
SLAM_MOTION_DOMINANT_DEG = 30.0
SLAM_MOTION_DOMINANT_BETTER = 3.0
SLAM_MOTION_DOMINANT_MAX_REL_SE = 0.1
#: Keyframes between two prunings of the held-back SLAM poses (``OnlineSmoother._prune_held``).
HELD_PRUNE_EVERY = 20
#: Seconds between two orientation checks (two closed-form fits over the arrived poses).
SLAM_ORIENTATION_CHECK_S = 1.0
#: With the convention undecided, the motion's fit takes the inverse convention only when its
#: scale rel. s.e. is under this fraction of the stated one's (turns about one axis fit both
#: conventions' increments: the inverse's rotation came out 179 deg off on simulated rectangle).
SLAM_MOTION_INVERSE_RATIO = 0.5
#: Seconds between two tries of the early misfit (``SlamGyroCheck.stated_misfit``, which
#: integrates the arrived gyro again: 3.5 ms at 1 s of data, 14 ms at 40 s) and of the
#: provisional re-seed (a motion fit).
SLAM_MISFIT_RETRY_S = 1.0
SLAM_RESEED_RETRY_S = 0.5
#: The causal SLAM-vs-gyro check (OnlineSmoother._slam_check) keeps the newest
#: SLAM_CHECK_WINDOW_S of data (its attempts fit all of it: 0.25 s at 40 s of a hover, 0.07 s
#: more for the early misfit; before, the cost grew with the flight, 2 s per attempt at 300 s);
#: past SLAM_CHECK_GROWTH_AFTER_S of SLAM undecided its attempts are spaced by a tenth of the time
#: so far (1 s before). The decisions seen come before either (EuRoC 4-12 s, the simulated
#: flights 2-30 s, hover 48 s).
SLAM_CHECK_WINDOW_S = 60.0
SLAM_CHECK_GROWTH_AFTER_S = 60.0
#: Added to the session id of the poses of a mirrored SLAM frame un-mirrored (a new alignment).
MIRROR_SESSION_BASE = 1 << 40
#: A mirror test inconclusive at the SLAM-vs-gyro decision is repeated every MIRROR_RETEST_S of
#: SLAM for MIRROR_RETEST_FOR_S (each a few ms per second of data: the gyro residuals of eight
#: hypotheses and their position fits).
MIRROR_RETEST_S = 2.0
MIRROR_RETEST_FOR_S = 30.0
#: ``SlamGyroCheck.stated_misfit`` above which the stated ``body_R_cam`` is suspected before the
#: check decides (named, see OnlineSmoother._suspect_extrinsic). Measured causally over the first
#: 25 s: right rotations 0.01-0.05 on EuRoC MH_01 / V1_02 (both files), 0.03-0.14 on the
#: simulated flights; an identity given for EuRoC's (90 deg off) 0.54-1.4, the simulated
#: flights' 0.3-2.1 (rectangle, figure8, circle; two-turns' yaw-only turns cannot tell it from
#: the inverse convention: 0.07-0.12).
SLAM_EXTRINSIC_SUSPECT_MISFIT = 0.5
# The SLAM units check (OnlineSmoother._units_check): second differences over the newest
# UNITS_POSES poses of the provisional alignment (from UNITS_MIN_POSES on); the median of a 3-D
# normal's norm in its per-axis sigmas; the scale they give re-seeds the provisional above
# UNITS_MIN_RATIO times its own where the IMU's difference is UNITS_MOTION_DOMINANT times the
# noise's typical size or more, above UNITS_NOISE_MIN_RATIO where the noise dominates (a SLAM
# that many times noisier than slam_sigma_m in metres is no metric SLAM).
UNITS_POSES = 10
UNITS_MIN_POSES = 4
UNITS_MAXWELL_MEDIAN = 1.5382
UNITS_MIN_RATIO = 2.5
UNITS_NOISE_MIN_RATIO = 8.0
UNITS_MOTION_DOMINANT = 2.0
#: _gyro_turn: below this sum of |rotation vector| components the turn is their sum's norm.
GYRO_TURN_SMALL_RAD = 0.15


#: ``cos`` of the accelerometer check's largest tilt (a keyframe tilted more is left out).
_COS_ACCEL_CHECK_MAX_TILT = math.cos(math.radians(ACCEL_CHECK_MAX_TILT_DEG))

_first = operator.itemgetter(0)
_second = operator.itemgetter(1)


#: ``ndarray.sum``'s reduction without its Python wrapper (the same arithmetic).
_add_reduce = np.add.reduce


def still_accel_bias(f_still: np.ndarray, gravity: float) -> np.ndarray:
    """The accelerometer bias a still stretch of mean specific force ``f_still`` shows: along
    ``f_still``, ``|f| - g``; zero across it, where a bias cannot be told from a tilt of the level
    attitude taken from ``f_still``. Measured 2026-12-07 on EuRoC V1_02 (the shared flight that
    starts after a still stretch; |f| 9.79-9.82 against g 9.81): with a zero bias the
    integration from the stretch's end drifted 30 cm vertically before the second SLAM pose;
    causal ATE own span ORB-SLAM2 8.14 -> 6.62 cm, ORB-SLAM3 2.95 -> 3.01 cm."""
    n = float(np.linalg.norm(f_still))
    return f_still / n * (n - gravity) if n > 0 else np.zeros(3)


def _norm(v) -> float:
    """``np.linalg.norm`` of a vector (its arithmetic: the square root of ``v.dot(v)``)
    without its per-call overhead."""
    v = np.asarray(v, float).ravel()
    return math.sqrt(v.dot(v))


def _chr(key: int) -> str:
    """Symbol character of a GTSAM key (top 8 bits; no ``gtsam.Symbol`` per call)."""
    return chr(key >> 56)


#: Layout of a packed output state (:class:`_States`).
_ROW = {
    "t": 0,
    "T": slice(1, 17),
    "v": slice(17, 20),
    "ba": slice(20, 23),
    "bg": slice(23, 26),
    "P": slice(26, 62),
    "Pv": slice(62, 71),
    "reset": 71,
    "quality": 72,
    "drag": slice(73, 75),
    "ground": 75,
}
_ROW_LEN = 76
_NAN_ROW = np.full(_ROW_LEN, np.nan)
_NAN_ROW.flags.writeable = False
#: Layout of a packed fixed-lag@lag row: epoch, then the trajectory columns.
_LAG_ROW = {"t": 1, "T": slice(2, 18), "v": slice(18, 21), "bg": slice(21, 24), "ba": slice(24, 27)}


def _trajectory(rows: np.ndarray, layout: dict) -> Trajectory:
    """The trajectory of packed state rows (``_ROW`` or ``_LAG_ROW`` layout)."""
    T = rows[:, layout["T"]].reshape(-1, 4, 4)
    return Trajectory(
        rows[:, layout["t"]].copy(),
        T[:, :3, 3].copy(),
        matrix_to_quat_wxyz(T[:, :3, :3]),
        rows[:, layout["v"]].copy(),
        rows[:, layout["bg"]].copy(),
        rows[:, layout["ba"]].copy(),
    )


class _States:
    """The output states, packed one float row each (a list of ``OnlineState`` objects costs
    about 1.6 kB a state: 115 MB for a 1-hour flight at 20 Hz; a row 0.6 kB); the newest is kept
    whole (its SLAM scales included). Indexable like a list; ``[-1]`` may be replaced."""

    def __init__(self) -> None:
        self._rows: list[np.ndarray] = []
        self._last: OnlineState | None = None

    @staticmethod
    def _pack(st: OnlineState) -> np.ndarray:
        r = _NAN_ROW.copy()  # (np.full costs 10x a copy)
        r[0] = st.t
        r[_ROW["T"]] = np.asarray(st.world_T_body, float).ravel()
        r[_ROW["v"]], r[_ROW["ba"]], r[_ROW["bg"]] = st.world_v_body, st.accel_bias, st.gyro_bias
        if st.pose_cov is not None:
            r[_ROW["P"]] = np.asarray(st.pose_cov, float).ravel()
        if st.vel_cov is not None:
            r[_ROW["Pv"]] = np.asarray(st.vel_cov, float).ravel()
        r[71], r[72] = st.reset_counter, st.quality
        if st.drag_k is not None:
            d = np.atleast_1d(np.asarray(st.drag_k, float))[:2]
            r[73 : 73 + len(d)] = d
        if st.ground_height is not None:
            r[75] = st.ground_height
        return r

    @staticmethod
    def _unpack(r: np.ndarray) -> OnlineState:
        P, Pv = r[_ROW["P"]].reshape(6, 6), r[_ROW["Pv"]].reshape(3, 3)
        drag = r[_ROW["drag"]]
        drag = drag[np.isfinite(drag)]
        return OnlineState(
            t=float(r[0]),
            world_T_body=r[_ROW["T"]].reshape(4, 4).copy(),
            world_v_body=r[_ROW["v"]].copy(),
            accel_bias=r[_ROW["ba"]].copy(),
            gyro_bias=r[_ROW["bg"]].copy(),
            pose_cov=None if np.isnan(P).all() else P.copy(),
            vel_cov=None if np.isnan(Pv).all() else Pv.copy(),
            slam_scale={},
            drag_k=drag.copy() if len(drag) else None,
            ground_height=None if np.isnan(r[75]) else float(r[75]),
            reset_counter=int(r[71]),
            quality=int(r[72]),
        )

    def append(self, st: OnlineState) -> None:
        self._rows.append(self._pack(st))
        self._last = st

    def __len__(self) -> int:
        return len(self._rows)

    def __bool__(self) -> bool:
        return bool(self._rows)

    def __getitem__(self, i: int) -> OnlineState:
        n = len(self._rows)
        if i == -1 or i == n - 1:
            return self._last
        return self._unpack(self._rows[i])

    def __setitem__(self, i: int, st: OnlineState) -> None:
        if not (i == -1 or i == len(self._rows) - 1):
            raise IndexError("only the newest state may be replaced")
        self._rows[-1] = self._pack(st)
        self._last = st

    def array(self) -> np.ndarray:
        """(N, 76) packed rows."""
        return np.array(self._rows) if self._rows else np.empty((0, _ROW_LEN))


class _Ring:
    """The newest ``capacity`` rows of ``width`` floats in a preallocated array (a deque with
    ``maxlen`` of small vectors without re-stacking them at every read)."""

    __slots__ = ("_buf", "_n", "_i")

    def __init__(self, capacity: int, width: int) -> None:
        self._buf = np.empty((max(int(capacity), 1), width))
        self._n = 0  # rows held
        self._i = 0  # next row to write

    def append(self, row) -> None:
        self._buf[self._i] = row
        self._i = (self._i + 1) % len(self._buf)
        self._n = min(self._n + 1, len(self._buf))

    def __len__(self) -> int:
        return self._n

    def array(self) -> np.ndarray:
        """The rows held, oldest first (a copy)."""
        if self._n < len(self._buf):
            return self._buf[: self._n].copy()
        return np.concatenate((self._buf[self._i :], self._buf[: self._i]))


class _Imu:
    """Arrived IMU samples (lists, trimmed to the history)."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.w: list[np.ndarray] = []
        self.a: list[np.ndarray] = []
        self.sat: list[int] = []  # saturation flags (fgnav.health.SAT_GYRO_BITS, ...)

    def add(self, t: float, w: np.ndarray, a: np.ndarray, sat: int = 0) -> None:
        self.t.append(t)
        self.w.append(w)
        self.a.append(a)
        self.sat.append(sat)

    def trim(self, t_keep: float) -> None:
        t = self.t
        if len(t) > 1000 and t[1000] < t_keep:  # else bisect_left(t, t_keep) <= 1000
            i = bisect.bisect_left(t, t_keep)
            del t[:i], self.w[:i], self.a[:i], self.sat[:i]

    def span(self, ta: float, tb: float) -> slice:
        return slice(bisect.bisect_left(self.t, ta), bisect.bisect_right(self.t, tb))

    def series(self, ta: float, tb: float) -> ImuSeries | None:
        s = self.span(ta, tb)
        if s.stop - s.start < 2:
            return None
        return ImuSeries(np.asarray(self.t[s]), np.asarray(self.w[s]), np.asarray(self.a[s]))

    def nearest(self, t: float) -> int:
        i = bisect.bisect_left(self.t, t)
        if i >= len(self.t):
            return len(self.t) - 1
        if i > 0 and t - self.t[i - 1] < self.t[i] - t:
            return i - 1
        return i


@dataclass
class _Session:
    """One SLAM session (map): arrived poses, alignment chain, provisional factors."""

    t: list[float]
    p: list[np.ndarray]
    q: list[np.ndarray]
    t_first: float
    chain: dict[int, int]  # segment -> key
    last_key: int | None = None
    last_seg: int = -1
    provisional: int | None = None  # key of the provisional alignment
    # [(factor index, (k, t, p, q, has a rotation factor, made with this one))] still in the
    # smoother, and [(factor index, k)] of the rotation factors made on the provisional
    prov_factors: list = None
    prov_rot: list = field(default_factory=list)
    next_fit: float = -math.inf
    index: int = 0  # order of arrival: the chain's keys are S(index * SESSION_STRIDE + segment)
    carried: bool = False  # its chain starts from an alignment carried over an IMU gap
    # The provisional alignment re-seeded from the motion (_reseed_provisional): done, next
    # try, and the (slam_R_world, scale) seed for _start_provisional.
    reseeded: bool = False
    reseed_now: bool = False  # body_T_cam's rotation replaced: re-seed at the next pose
    next_reseed: float = -math.inf
    seed: tuple | None = None
    # (slam_R_world, scale) of the motion's fit after the orientations were contradicted
    # (_orient_contradicted): the provisional alignment is re-seeded with it at the next pose.
    motion_seed: tuple | None = None
    # The provisional alignment's scale is the default (nothing known): a second pose long after
    # the first waits for the third (FixedLagOptions.slam_provisional_lone_gap_s).
    lone_hold: bool = False
    lone_waiting: bool = False
    # The provisional alignment's scale is the default and _units_check still looks (with the
    # poses up to index units_seen looked at); where the next seed's scale comes from
    # (``_prov_scales``' "from").
    units_pending: bool = False
    units_seen: int = 0
    seed_source: str = "re-seed"


class OnlineSmoother:
    """Causal fixed-lag smoother fed one event at a time (see the module docstring).

    Args:
        calib: the vehicle's calibration (IMU noise, ``body_T_cam``, ``body_T_range``, limits).
        options: smoother options (graph noise, lag, iSAM2 settings, SLAM start gates, the
            push API's start, time and drag rules).
        name: name used in messages.
        priors: the ``[priors]`` options (:class:`fgnav.frontends.prior_stages.PriorOptions`):
            the front-ends that supply priors run as a stage fed the same events (see *Front-end
            priors* in the module docstring); None: none.
    """

    def __init__(
        self,
        calib: Calibration,
        options: FixedLagOptions | None = None,
        name: str = "online",
        health: HealthOptions | None = None,
        priors: Any = None,
    ):
        self.calib = calib.check()
        self.prior_options = priors.check() if priors is not None and priors.sources else None
        self.options = options or FixedLagOptions()
        self.go = self.options.graph.check()
        # The alignment segments' walks: the push engine's own where set, else the graph's.
        o, go = self.options, self.go
        self._trans_rw = go.slam_trans_rw_m if o.slam_trans_rw_m is None else o.slam_trans_rw_m
        self._scale_rw = go.slam_scale_rw if o.slam_scale_rw is None else o.slam_scale_rw
        self.name = name
        self._flow_watch = FlowRejectWatch(name)  # a flow stream rejected entirely (kept on reset)
        self._flow_first_t: float | None = None  # the first flow reading's time (kept on reset)
        # The rangefinder's limits (range_refusal): its floor clamps until a reading below
        # range_min arrives (then its readings at range_min are distances; see range_at_min).
        # Kept on reset.
        self._range_limits = RangeLimits(self.calib.range_min, self.calib.range_max)
        if self.go.slam_model not in ("auto", "sim3", "axis"):
            raise FlightDataError(
                f"{name}: graph.slam_model={self.go.slam_model!r}: expected auto, sim3 or axis"
            )
        if self.options.vo_worker not in VO_WORKERS:
            raise FlightDataError(
                f"{name}: online.vo_worker={self.options.vo_worker!r}: expected inline or process"
            )
        for skip in ("relinearize_skip", "startup_relinearize_skip"):
            v = getattr(self.options, skip)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                # (ISAM2's relinearizeSkip: 0 killed the process with SIGFPE)
                raise FlightDataError(f"{name}: online.{skip}={v!r}: expected an integer >= 1")
        if self.options.vo_process_delay_keyframes < 1:
            raise FlightDataError(
                f"{name}: online.vo_process_delay_keyframes="
                f"{self.options.vo_process_delay_keyframes!r}: expected an integer >= 1"
            )
        # Seed 000's per-axis model (SLAM axes = world axes, one scale per axis shared by every
        # session): a configuration of the SLAM input; "auto" is the Sim(3) model here (a
        # replay resolves it from the flight's declaration before it builds the smoother).
        self._axis = self.go.slam_model == "axis"
        if not self.options.lag_s > 0:
            raise FlightDataError(f"{name}: lag_s={self.options.lag_s}: expected > 0")
        self.period = 1.0 / self.go.keyframe_hz
        self.body_T_cam = np.asarray(calib.body_T_cam, float)
        self.body_T_range = np.asarray(calib.body_T_range, float)
        self.pim_params = pim_params(self.calib.imu_noise, self.go.gravity)
        self.reset_counter = 0
        self.received: dict[str, int] = {}
        self.used: dict[str, int] = {}
        self._late_warned: set[str] = set()  # streams whose late drops were said (_warn_late)
        # [priors] sources fed by a link without a stream they need (a flight is checked before
        # it runs: fgnav.methods.online_prior_options): said once (_watch_prior_streams).
        self._prior_watch_t0: float | None = None
        self._prior_watch_done = False
        self.dropped: dict[str, int] = {}
        self._slam_unused_said = False
        self.n_failures = 0
        self.n_fallbacks = 0
        self.failure_messages: list[str] = []
        self.latency: list[float] = []
        # Outputs (every state).
        self.out = _States()
        # fixed-lag@lag rows: epoch, t, world_T_body (16), velocity, gyro bias, accel bias
        self.out_lag: list[np.ndarray] = []
        self._out_epoch: list[int] = []  # clock epoch of each state (a backward jump: +1)
        self._epoch = 0
        self._jumped_at = -math.inf
        self.track: dict[str, list[tuple[float, float, int]]] = {}
        self._session_scale: dict[int, float] = {}
        self._drag_decision: str | None = None
        self._noise_cache: dict[tuple, Any] = {}
        self._lin_errors: dict | None = None  # errors recorded at the update's linearisation
        self._lin_factors: list | None = None  # the update's factors, alive through it
        self._lin_hits = 0  # monitored factors whose recorded error health used
        self._health_init(health)
        # The early SLAM-rotation misfit's suspicion (_suspect_extrinsic) outlives a reset, as
        # the check's decision does: the calibration is the same.
        self._extrinsic_suspect: dict[str, float] | None = None
        # The SLAM orientations against the motion (_orientation_check): None while checked,
        # "consistent" once confirmed, "contradicted" (the orientations unused: what was found
        # in _orient_found), "verified" once the SLAM-vs-gyro check has decided with two axes
        # turned (_slam_check). A property of the calibration: it outlives resets too.
        self._orient_verdict: str | None = None
        self._orient_found: dict[str, Any] | None = None
        # A mirrored SLAM frame (_slam_check, slam_mirror = "auto"): the flipped axis whose sign
        # every pose from the decision on gets back (in a session of its own), or "off" (axis
        # not identified: the SLAM poses from then on dropped). Outlives resets.
        self._mirror: int | str | None = None
        self._mirror_named: dict[str, Any] | None = None
        # The check kept after its decision while a mirror is still possible (_mirror_retest).
        self._mirror_sgc = None
        self._mirror_next = self._mirror_until = -math.inf
        # An IMU sample after a clock jump or gap, held until the next one says whether the
        # discontinuity is real or the stamp corrupted: (event, t, omega, accel).
        self._imu_suspect: tuple | None = None
        self._suspect_events: list = []  # the other events that arrived after it
        self._clear()

    # ------------------------------------------------------------------------------------------
    # Public interface
    # ------------------------------------------------------------------------------------------

    def feed(self, ev: Any) -> OnlineState | None:
        """Take one event (arrival order); the newest state when keyframes closed, else None."""
        if type(ev) is ImuSample:
            # Most events: straight to the IMU path (the fault detectors, fed there, never drop
            # a sample; they only flag saturation).
            return self._feed_imu(ev)
        if self._imu_suspect is not None:
            # After an IMU sample held at a clock discontinuity, in arrival order after it.
            self._suspect_events.append(ev)
            return None
        if isinstance(ev, SlamPose) and not self._slam_plausible(ev):
            return None
        ev = self._health_feed(ev)
        if ev is None:
            return None
        if isinstance(ev, ImuSample):
            return self._feed_imu(ev, health=False)  # (a subclass: the detectors had it)
        stream = _STREAM.get(type(ev))
        if stream is None:
            raise TypeError(f"{self.name}: not a measurement event: {type(ev).__name__}")
        self.received[stream] = self.received.get(stream, 0) + 1
        if not self._check_time(stream, ev.t):
            return None
        if self._pstage is not None:
            self._pstage.feed(ev)
        if isinstance(ev, SlamPose):
            if self.go.use_slam:
                self._on_slam(ev)
            else:
                self._drop("slam:off")
        elif isinstance(ev, RangeReading):
            if self.go.use_range:
                self._on_scalar("range", ev.t, ev.range)
            else:
                self._drop("range:off")
        elif isinstance(ev, YawReading):
            if self.go.use_yaw:
                self._on_scalar("yaw", ev.t, ev.yaw)
            else:
                self._drop("yaw:off")
        elif isinstance(ev, AttitudeSample):
            q = np.asarray(ev.world_q_body_wxyz, float)
            n2 = float(q @ q) if q.shape == (4,) else math.nan
            if q.shape != (4,):
                self._drop("attitude:bad-shape")
            elif abs(n2 - 1.0) < 0.2:  # (False for NaN)
                self._att.append((ev.t, q / math.sqrt(n2)))
                self._trim(self._att)
                self._use("attitude")
            else:
                self._drop("attitude:non-finite")
        elif isinstance(ev, ImageFrame):
            self._on_image(ev)
        elif isinstance(ev, FlowSample):
            if self._flow_first_t is None:
                self._flow_first_t = float(ev.t)
            if self.go.use_flow is not False and self.go.use_range:
                self._flow.append(ev)
                while len(self._flow) > 2 and self._flow[0].t < self._t_imu_last - 5.0:
                    self._flow.popleft()
            else:
                self._drop("flow:off")
                if self.go.use_flow is not False:
                    self._flow_no_height("use_range is off")
        else:
            self._drop(f"{stream}:not-used-online")
        return None

    def _slam_plausible(self, ev: SlamPose) -> bool:
        """A SLAM pose's values before anything sees them (the jump detector included): finite,
        a position within ``SLAM_MAX_COORD`` units of the map's origin and a unit quaternion;
        else counted as received and dropped by reason."""
        p = np.asarray(ev.slam_t_cam, float)
        q = np.asarray(ev.slam_q_cam_wxyz, float)
        why = None
        if p.shape != (3,) or q.shape != (4,):
            why = "slam:bad-shape"
        # (the finiteness and the largest coordinate on plain floats: the same tests as
        # numpy's isfinite().all() and abs().max(), without their per-call overhead)
        elif not all(map(math.isfinite, (*p.tolist(), *q.tolist()))):
            why = "slam:non-finite"
        elif max(map(abs, p.tolist())) > SLAM_MAX_COORD:
            why = "slam:implausible-position"
        elif abs(float(q @ q) - 1.0) > 0.2:
            why = "slam:non-unit-quaternion"
        if why is None:
            return True
        self.received["slam"] = self.received.get("slam", 0) + 1
        self._drop(why)
        return False

    def latest(self) -> OnlineState | None:
        """The newest state (None before initialisation)."""
        return (
            self.out[-1] if self.out and self.out[-1].reset_counter == self.reset_counter else None
        )

    def close(self) -> None:
        """End of the stream: take the VO process's last measurements (counted, not made into
        factors: no keyframe closes after them) and stop it. :meth:`result` stays available."""
        if self._imu_suspect is not None:
            self._imu_suspect = None
            self._drop("imu:time-unconfirmed")  # the last sample, after a discontinuity
            self._release_suspect_events()
        self._vo_collect(math.inf)
        if isinstance(self._vo, VoProcess):
            self._vo.close()

    def reset(self, reason: str = "requested") -> None:
        """Drop the window and every buffer; the next events initialise again."""
        self.reset_counter += 1
        self._drop(f"reset:{reason}")
        log.warning("%s: reset (%s) at t=%.3f", self.name, reason, self._t_imu_last)
        self._health.restart()
        self._clear()

    def counts(self) -> dict[str, dict[str, int]]:
        """Received, used, late and dropped counts by stream (late: keyframe left the window)."""
        late = {k.split(":")[0]: v for k, v in self.dropped.items() if k.endswith(":late")}
        return {
            "received": dict(self.received),
            "used": dict(self.used),
            "late": late,
            "dropped": dict(self.dropped),
        }

    def result(self, runtime: float | None = None, epoch: int = -1) -> Estimate:
        """The causal estimate: every state output so far on one clock. A backward clock jump
        starts a new epoch (its states' times restart); ``epoch`` picks one (default the last),
        ``info["clock_epochs"]`` counts the states of each."""
        self._vo_collect(math.inf)  # the VO process's last frames (their counts)
        ep = np.asarray(self._out_epoch, dtype=int)
        epochs = sorted(set(ep.tolist()))
        which = epochs[epoch] if epochs else 0
        rows = self.out.array()[ep == which] if len(ep) else np.empty((0, _ROW_LEN))
        n = len(rows)
        if n == 0:
            raise FlightDataError(
                f"{self.name}: the online smoother produced no state (no IMU, or no keyframe "
                "closed)"
            )
        self._say_slam_unused()
        traj = _trajectory(rows, _ROW)
        pose_cov = vel_cov = None
        if np.isfinite(rows[:, _ROW["P"]]).any():
            pose_cov = rows[:, _ROW["P"]].reshape(n, 6, 6).copy()
            vel_cov = rows[:, _ROW["Pv"]].reshape(n, 3, 3).copy()
        last = self.out._unpack(rows[-1])
        series: dict[str, TimeSeries] = {}
        for name, track in self.track.items():
            rows = [r for r in track if r[3] == which]
            if rows:
                series[name] = TimeSeries(
                    np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
                )
                if name == "slam_scale":
                    series["slam_session"] = TimeSeries(
                        series[name].t, np.array([float(r[2]) for r in rows])
                    )
        lat = np.asarray(self.latency)
        t_all = self.out.array()[:, 0]
        span = sum(float(np.ptp(t_all[ep == x])) for x in epochs if (ep == x).any())
        if runtime is None:
            runtime = getattr(self, "runtime_s", None)
        runtime = float(lat.sum()) if runtime is None else runtime
        info = {
            "engine": "push-api",
            "lag_s": self.options.lag_s,
            **self.counts(),
            "skipped": self._leftovers(),
            "solver_failures": self.n_failures,
            "factorization_fallbacks": self.n_fallbacks,
            "factorization_final": self.factorization,
            "solver_failure_messages": self.failure_messages[:10],
            "reset_counter": self.reset_counter,
            "clock_epochs": [int((ep == x).sum()) for x in epochs],
            "drag": self._drag_decision,
            "accel_check": self._accel_check.as_dict() if self._accel_check is not None else None,
            "accel_horizontal": "thrust-only" if self._thrust_only else "measured",
            "slam_gyro_check": getattr(self, "slam_check", None),
            "slam_extrinsic_suspect": self._extrinsic_suspect,
            "slam_orientation_check": {
                "verdict": self._orient_verdict,
                "contradiction": self._orient_found,
            },
            "vo_time_s": getattr(self, "vo_busy_s", None),
            "vo_counts": dict(self._vo.counts) if self._vo is not None else None,
            "flow_all_rejected": self._flow_watch.report(),
            "slam_unused": self._slam_unused_said,
            "slam_rotation_convention": self._slam_conv,
            "slam_provisional_scales": list(self._prov_scales),
            "frontend_prior_stage": self._prior_report(),
            "health": self._health_report(),
            "updates": len(lat),
        }
        return fixed_lag_estimate(
            traj,
            info,
            lat,
            runtime,
            span,
            self.options,
            pose_cov=pose_cov,
            vel_cov=vel_cov,
            slam_scale=dict(self._session_scale),
            drag_k=last.drag_k if self._drag_in_model() else None,
            ground_height=last.ground_height,
            series=series,
        )

    def _leftovers(self) -> dict[str, int]:
        """Measurements that arrived but wait for a keyframe that never closed (the IMU ended
        first) or for a SLAM alignment: ``<stream>:after-last-keyframe``,
        ``slam:before-alignment``."""
        out: dict[str, int] = {}
        for k, kind, _ in self._pending:
            key = f"{kind}:after-last-keyframe" if k > self.k else f"{kind}:pending"
            out[key] = out.get(key, 0) + 1
        t_new = self.t_kf.get(self.k, -math.inf)
        for t, _ in self._slam_wait:
            key = "slam:after-last-keyframe" if t > t_new + 1e-9 else "slam:after-last-update"
            out[key] = out.get(key, 0) + 1
        if self._held:
            out["slam:before-alignment"] = len(self._held)
        return out

    # ------------------------------------------------------------------------------------------
    # State
    # ------------------------------------------------------------------------------------------

    def _clear(self) -> None:
        o = self.options
        self.smoother: TimeOrderedSmoother | None = None
        self.factorization = "QR" if o.startup_qr_s > 0 else o.factorization.upper()
        self.t0: float | None = None
        self.k = -1  # newest closed keyframe
        self.t_kf: dict[int, float] = {}
        self.imu = _Imu()
        self._t_imu_last = getattr(self, "_t_imu_last", -math.inf)
        self._t_last: dict[str, float] = {}
        self._first_imu_t: float | None = None
        self._first_slam_t: float | None = None
        self._att: deque = deque()
        self._scalar: dict[str, deque] = {"range": deque(), "yaw": deque()}
        self._scalar_wait: dict[str, deque] = {"range": deque(), "yaw": deque()}
        # Ground heights of the consecutive range readings the innovation gate refused.
        self._range_run: deque = deque(maxlen=max(self.options.range_gate_run, 1))
        # Ground epochs after terrain steps: (first keyframe, epoch), in order.
        self._g_epochs: list[tuple[int, int]] = []
        # Newest keyframe a range reading within the limits reached the gate at (inf: the gate
        # holds from the start; -inf: the ground was seeded without a reading, the next one
        # seeds it anew).
        self._range_seen_t = math.inf
        # A range factor is on the current ground chain (the health's range_expected).
        self._ground_measured = False
        self._pim: gtsam.PreintegratedCombinedMeasurements | None = None
        self._kf_index: deque = deque()  # (time, keyframe) of the kept keyframes, in order
        self._anchors: deque = deque()  # arrived image times not yet passed
        self._anchors_on = False
        self._slam_wait: list = []  # SLAM poses taken after the newest keyframe
        self._slam_prestart: list = []  # SLAM poses that arrived before the start
        self._flow: deque = deque()  # arrived optical-flow readings (last 5 s)
        if isinstance(getattr(self, "_vo", None), VoProcess):
            self._vo.close()
        self._vo = None  # the homography VO stage (made at the first image)
        self._vo_off: str | None = None
        self._vo_links: deque = deque()  # (t_i, t_j, H or None, inliers, rms) of the VO pairs
        self._hchain: list | None = None  # [keyframe, t end, H, inliers, sum rms^2, links]
        self._flow_done_t = -math.inf  # end of the last flow window made into a factor
        self._flow_watch.restart()
        self._pending: list[tuple[int, str, Any]] = []  # (keyframe, kind, payload)
        self.sessions: dict[int, _Session] = {}
        self.values: dict[int, Any] = {}  # last good estimate of live keys
        self.stamp: dict[int, float] = {}
        self._n_prov = 0
        self._prov_scales: list[dict[str, Any]] = []  # each provisional alignment's start
        self._drag_means = _Ring(self.options.drag_scatter_n, 2)
        self._drag_sigma = float(self.go.drag_model_sigma)
        self._drag_on = self.go.use_drag
        self._drag_checked = False
        self._thrust_axis_ok = True
        # Accelerometer check (fgnav.solvers.accel_check): keyframe-mean horizontal specific
        # force and the smoother's body velocity; thrust-only prediction once it is unusable.
        # f_xy, u_xy, white sigma of the last keyframes, with the check's running sums
        self._accel_rows = RunningAccelCheck(self.options.drag_scatter_n)
        self._accel_check = None
        self._thrust_only = self.go.accel_horizontal == "thrust-only"
        self._thrust_provisional = False  # thrust-only until the accelerometer check decides
        self._bias_release = False
        self._last_contact_t = -math.inf  # newest ground-contact keyframe
        self._queued_values = gtsam.Values()
        self._cur_stamps: dict[int, float] = {}
        self._held: list = []
        self._state_kf: set[int] = set()  # keyframes whose X, V, B estimates are kept
        self._lag_done = -1  # newest keyframe read for the lagged output
        # SLAM clock offset: given (seconds) or, with "apply", the check's once it has decided.
        off = self.go.slam_time_offset
        self._slam_offset = float(off) if not isinstance(off, str) else 0.0
        # SLAM rotation convention: fixed by the options, or decided causally from the gyro.
        self._slam_conv: str | None = {"as-is": "as-is", "inverse": "inverse"}.get(
            self.go.slam_rotation
        )
        self._sgc = None
        self._sgc_first: float | None = None  # the check's first SLAM time
        # The slam-scale-drift detector on the alignments' scales (_track_slow).
        ho = self._health.options if self._health is not None else HealthOptions()
        self._scale_watch = ScaleDriftWatch(
            ho.slam_scale_drift_per_s, ho.slam_scale_drift_window_s, ho.slam_scale_drift_settle_s
        )
        self._fit_motion_used = False
        self._misfit_try = -math.inf
        self._orient_next = -math.inf
        if self.go.use_slam and (self._slam_conv is None or off == "apply"):
            from fgnav.datasets.slam_gyro import SlamGyroCheck

            self._sgc = SlamGyroCheck(self.body_T_cam[:3, :3], window_s=SLAM_CHECK_WINDOW_S)
        self._pose_hist: dict[int, tuple[float, gtsam.Pose3]] = {}
        self._height_parts: tuple | None = None  # (alignment, its parts): _sim3_parts
        self._height_last: tuple | None = None  # (session, position, height): _slam_height
        self._bad_since = -math.inf
        # The state carried over a restart after an IMU gap (see _carry_state).
        self._carry: dict[str, Any] | None = None
        self._carried_align: dict[int, tuple[gtsam.Similarity3, np.ndarray | None]] = {}
        # Front-end priors (seed 000's observer velocity, seed 004's ML scale): a stage fed the
        # same events; rebuilt, not carried, on a reset.
        self._pstage = None
        if self.prior_options is not None:
            from fgnav.frontends.prior_stages import FrontendPriorStage

            self._pstage = FrontendPriorStage(self.calib, self.prior_options, name=self.name)
        self._scale_prior_done: set[int] = set()  # sessions whose ML-scale prior is in

    def _use(self, kind: str, n: int = 1) -> None:
        self.used[kind] = self.used.get(kind, 0) + n

    def _drop(self, reason: str, n: int = 1) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + n

    def _warn_late(self, kind: str, delay: float) -> None:
        """Say once per stream when its measurements arrive too late for the window as a rule
        (``LATE_WARN_N`` dropped late, no fewer than it has used): a latency longer than the lag
        leaves the smoother on the IMU alone (simulated rectangle, SLAM 3 s late with a 2 s
        lag: 755 of 821 poses dropped, 1.3 m, said nowhere but in the counts)."""
        n = self.dropped.get(f"{kind}:late", 0)
        if kind in self._late_warned or n < LATE_WARN_N or n < self.used.get(kind, 0):
            return
        self._late_warned.add(kind)
        log.warning(
            "%s: %d %s measurements arrived too late for the window (the newest %.2f s after "
            "its time, lag %.1f s) and were dropped (%s:late); a lag longer than the stream's "
            "latency takes them",
            self.name,
            n,
            kind,
            delay,
            self.options.lag_s,
            kind,
        )

    def _trim(self, buf: deque) -> None:
        horizon = self._t_imu_last - self.options.history_s
        while len(buf) > 2 and buf[0][0] < horizon:
            buf.popleft()

    def _check_time(self, stream: str, t: float) -> bool:
        if not math.isfinite(t):
            self._drop(f"{stream}:non-finite-time")
            return False
        last = self._t_last.get(stream, -math.inf)
        jump = self.options.clock_jump_s
        if stream != "imu" and t > self._t_imu_last + jump:
            if self._t_imu_last - self._jumped_at < 2.0 * jump + 1.0:
                # Soon after an IMU clock jump, stamped far ahead of the new clock: taken
                # before the jump (old clock).
                self._drop(f"{stream}:stamped-before-clock-jump")
                return False
            if self._t_imu_last > -math.inf and t > self._t_imu_last + FUTURE_STAMP_S:
                # No reading of this flight (one flow reading stamped 1e6 s ahead was kept,
                # held every buffer behind it and was counted late again at every keyframe:
                # 13.9 million drops in 120 s). Readings after an IMU that ended are not this:
                # they are counted after the last keyframe.
                self._drop(f"{stream}:future-time")
                return False
        if t < last:
            if last - t <= jump:
                self._drop(f"{stream}:out-of-order")
                return False
            if stream != "imu":
                # This stream's clock went back too (the IMU's jump resets the smoother).
                self._t_last[stream] = t
                return True
            return True  # IMU clock jump: handled by the caller
        if t == last:
            self._drop(f"{stream}:duplicate")
            return False
        if stream == "slam" and t - last < MIN_SLAM_DT_S:
            # A burst (30 000 poses 1e-10 s apart made one IMU feed take 2.6 s): no SLAM runs
            # at a kilohertz.
            self._drop("slam:too-close")
            return False
        self._t_last[stream] = t
        return True

    def _noise(self, dim: int, sigma: float, robust: bool = True) -> Any:
        key = (dim, float(sigma), robust)
        m = self._noise_cache.get(key)
        if m is None:
            m = gtsam.noiseModel.Isotropic.Sigma(dim, float(sigma))
            if robust:
                m = self._robust(m)
            self._noise_cache[key] = m
        return m

    def _robust(self, base: Any) -> Any:
        return robust_noise(base, self.go)

    # ------------------------------------------------------------------------------------------
    # IMU: keyframes close here
    # ------------------------------------------------------------------------------------------

    def _feed_imu(self, ev: ImuSample, health: bool = True) -> OnlineState | None:
        self.received["imu"] = self.received.get("imu", 0) + 1
        t = float(ev.t)
        w = np.asarray(ev.body_omega, float)
        a = np.asarray(ev.body_accel, float)
        # Plain floats, shared with the fault detectors (every sample: numpy's per-call
        # overhead dominated this path). The detectors see only the samples that pass the value
        # and time checks (a 1e30 value is not a saturation, a corrupted stamp not a gap).
        wl, al = w.tolist(), a.tolist()
        if len(wl) != 3 or len(al) != 3 or w.ndim != 1 or a.ndim != 1:
            self._drop("imu:bad-shape")
            return None
        w0, w1, w2 = wl
        a0, a1, a2 = al
        w_sq, a_sq = w0 * w0 + w1 * w1 + w2 * w2, a0 * a0 + a1 * a1 + a2 * a2
        if not math.isfinite(t + w_sq + a_sq):
            self._drop("imu:non-finite")
            return None
        if w_sq > _IMU_MAX_RATE_SQ or a_sq > _IMU_MAX_ACCEL_SQ:
            self._drop("imu:implausible")
            return None
        last = self._t_last.get("imu", -math.inf)
        suspect = self._imu_suspect
        if suspect is not None:
            # The sample after a clock discontinuity decides it: real when this one continues
            # from it, a corrupted stamp when this one continues the old clock.
            self._imu_suspect = None
            ts = float(suspect[0].t)
            if not (0.0 < t - last <= self.options.max_imu_gap_s) or 0.0 < t - ts <= t - last:
                self._imu_accept(*suspect, last=last)  # confirmed
            else:
                self._drop("imu:time-outlier")
            self._release_suspect_events()
            last = self._t_last.get("imu", -math.inf)
        elif last - t > self.options.clock_jump_s or (
            last > -math.inf and t - last > self.options.max_imu_gap_s
        ):
            self._imu_suspect = (ev, t, w, a, (wl, al) if health else None)
            return None
        return self._imu_accept(ev, t, w, a, (wl, al) if health else None, last)

    def _say_slam_unused(self) -> None:
        """SLAM poses arrived and none was used (two poses, both before the start: the run
        read as a SLAM-aided one, 0.29 m against 0.027 m, with health "ok"): said once, with the
        reasons (``info["slam_unused"]``)."""
        n = self.received.get("slam", 0)
        if not n or any(k.startswith("slam") for k in self.used) or self._slam_unused_said:
            return
        self._slam_unused_said = True
        why = ", ".join(f"{k} {v}" for k, v in sorted(self.dropped.items()) if k.startswith("slam"))
        log.warning(
            "%s: %d SLAM pose(s) arrived and none was used (%s): the estimate has no SLAM aiding",
            self.name,
            n,
            why or "none reached a keyframe",
        )

    def _when(self, t: float) -> str:
        """``"at 8.75 s after the start"`` (a log's absolute stamps, e.g. EuRoC's 1.4e9 s, read
        as nothing in a message), or ``"before the start"``."""
        if self.t0 is None or t < self.t0:
            return "before the start"
        return f"at {t - self.t0:.2f} s after the start"

    def _release_suspect_events(self) -> None:
        """The events held behind a suspect IMU sample, once it is decided, in their order."""
        held, self._suspect_events = self._suspect_events, []
        for e in held:
            self.feed(e)

    def _imu_accept(
        self,
        ev: ImuSample,
        t: float,
        w: np.ndarray,
        a: np.ndarray,
        values: tuple[list, list] | None,
        last: float,
    ) -> OnlineState | None:
        """An IMU sample past the value checks: time rules (a clock jump or a gap the next
        sample confirmed resets), then the keyframes it closes. ``values``: its rates and
        specific forces as float lists for the fault detectors (None: they had it)."""
        if t > last:  # most samples (t is finite here): _check_time's accepting branch
            self._t_last["imu"] = t
        elif not self._check_time("imu", t):
            return None
        if t < last:
            self.reset("imu-clock-jump")
            self._epoch += 1
            self._jumped_at = t
            self._t_last = {}
            self._t_last["imu"] = t
        elif self.t0 is not None and t - last > self.options.max_imu_gap_s:
            carry = self._carry_state()
            # The SLAM did not change over the gap: a decided rotation convention and clock
            # offset are kept (a fresh SLAM-vs-gyro check would leave the SLAM orientations
            # unused until it decides again; an undecided one starts again after the gap).
            decided = self._sgc is None, self._slam_conv, self._slam_offset
            self.reset("imu-gap")
            self._carry = carry
            if decided[0]:
                self._sgc, self._slam_conv, self._slam_offset = None, decided[1], decided[2]
            self._t_last = {"imu": t}
        if values is not None and self._health_on:
            self._health.detectors.feed_imu_values(t, *values)
        used = self.used
        used["imu"] = used.get("imu", 0) + 1
        if self._pstage is not None:
            self._pstage.feed(ev)
            if not self._prior_watch_done:
                self._watch_prior_streams(t)
        if self._sgc is not None:
            self._sgc.add_imu(t, w, a)
        if self._mirror_sgc is not None:
            self._mirror_sgc.add_imu(t, w, a)
        if self._first_imu_t is None:
            self._first_imu_t = t
        self.imu.add(t, w, a, self._health.detectors.imu_flags if self._health_on else 0)
        self._t_imu_last = t
        if self.t0 is None:
            self._try_start(t)
            return self.latest() if self.t0 is not None and self.k >= 0 else None
        closed = self._advance(t)
        self.imu.trim(t - self.options.history_s)
        return self.latest() if closed else None

    def _advance(self, t_imu: float) -> bool:
        """Close every keyframe the IMU has passed; True when one closed."""
        if not self._anchors_on and t_imu <= self.t_kf[self.k] + self.period + 1e-9:
            return False  # most samples: no keyframe to close (_next_time's grid rule)
        closed = False
        while True:
            t_next, ready = self._next_time(t_imu)
            if not ready:
                return closed
            self._close_keyframe(t_next)
            closed = True

    def _next_time(self, t_imu: float) -> tuple[float, bool]:
        """The next keyframe's time and whether it can close. Without images: the fixed grid
        step after the newest keyframe, closed once an IMU sample after it has arrived. With
        images: the first image (an anchor: its homography needs its keyframe) taken at least
        ``MIN_ANCHOR_GAP_PERIODS`` after the newest keyframe and at most half a period after the
        grid step, closed once the IMU has passed it; without such an image the grid step,
        closed once the IMU is half a period plus ``image_latency_s`` past it (an image could
        still arrive for it until then)."""
        t_k = self.t_kf[self.k]
        grid = t_k + self.period
        if not self._anchors_on:
            return grid, t_imu > grid + 1e-9
        anchors = self._anchors
        while anchors and anchors[0] <= t_k + 1e-9:
            anchors.popleft()
        for a in anchors:
            if a > grid + 0.5 * self.period + 1e-9:
                break
            if a - t_k >= MIN_ANCHOR_GAP_PERIODS * self.period - 1e-9:
                return a, t_imu > a + 1e-9
        return grid, t_imu > grid + 0.5 * self.period + self.options.image_latency_s

    def _preintegrate(
        self, ta: float, tb: float, bias: gtsam.imuBias.ConstantBias, count: bool = True
    ) -> gtsam.PreintegratedCombinedMeasurements:
        """The arrived IMU from ``ta`` to ``tb`` (zero-order hold: a sample holds until the
        next); an interval holding samples pinned at a rail (the health detectors' flags) has
        its noise inflated on those axes (:func:`fgnav.solvers.graph.saturated_pim_params`)."""
        params = self._accel_params()
        t, a, w = self.imu.t, self.imu.a, self.imu.w
        n = len(t)
        i0 = max(bisect.bisect_right(t, ta) - 1, 0)
        i1 = bisect.bisect_left(t, tb)
        if any(self.imu.sat[i0:i1]):
            dts = [
                max(min(t[i + 1], tb) if i + 1 < n else tb, ta) - max(t[i], ta)
                for i in range(i0, i1)
            ]
            params = saturated_pim_params(
                params,
                np.asarray(w[i0:i1]),
                np.asarray(a[i0:i1]),
                np.asarray(self.imu.sat[i0:i1]),
                np.maximum(dts, 0.0),
                self._health.options.saturation_sigma_rel,
            )
            if count:
                self._use("imu:saturated-intervals")
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
        thrust_only = self._thrust_only
        for i in range(i0, i1):
            s0 = t[i] if t[i] > ta else ta
            s1 = t[i + 1] if i + 1 < n and t[i + 1] < tb else tb
            if s1 > s0:
                ai = np.array([0.0, 0.0, a[i][2]]) if thrust_only else a[i]
                pim.integrateMeasurement(ai, w[i], s1 - s0)
        return pim

    def _mean_accel(self, ta: float, tb: float) -> tuple[np.ndarray | None, int, float]:
        """Time-weighted mean accelerometer over ``[ta, tb]`` (zero-order hold), the number of
        samples and the covered time [s]."""
        t = self.imu.t
        i0 = max(bisect.bisect_right(t, ta) - 1, 0)
        i1 = bisect.bisect_left(t, tb)
        if i1 <= i0 or i0 >= len(t):
            return None, 0, 0.0
        ts = np.asarray(t[i0 : i1 + 1] if i1 < len(t) else [*t[i0:i1], tb])
        s0 = np.maximum(ts[:-1], ta)
        s1 = np.minimum(ts[1:], tb)
        d = np.maximum(s1 - s0, 0.0)
        # (np.add.reduce: ndarray.sum's own reduction, without its Python wrapper)
        dur = float(_add_reduce(d))
        if dur <= 0:
            return None, 0, 0.0
        acc = np.asarray(self.imu.a[i0:i1])
        return _add_reduce(d[:, None] * acc, 0) / dur, int(np.count_nonzero(d > 0)), dur

    def _try_start(self, t: float) -> None:
        """Initialise at the first SLAM pose (or at the IMU after ``start_wait_s``)."""
        if self.go.use_slam and self._first_slam_t is None:
            if t - self._first_imu_t < self.options.start_wait_s:
                return
            t_start = t
        elif self._first_slam_t is not None:
            t_start = max(self._first_slam_t, self.imu.t[0] + self.options.init_imu_s)
            if t < t_start:
                return
        else:
            t_start = t
        if t_start - self.imu.t[0] < self.options.init_imu_s - 1e-6:
            return
        self._start(t_start)

    def _start(self, t_start: float) -> None:
        _o, go = self.options, self.go
        s = self.imu.span(t_start - self.options.init_imu_s, t_start)
        a = np.asarray(self.imu.a[s]) if s.stop > s.start else np.asarray(self.imu.a[-1:])
        yaw0 = go.initial_yaw
        yaws = self._scalar["yaw"]
        if go.use_yaw and yaws:
            yaw0 = float(yaws[-1][1])
        R0 = R_att = self._attitude_at(t_start)
        if R0 is None:
            R0 = level_rotation_from_accel(a.mean(axis=0), yaw0)
        gyro_b, still_age = self._still_gyro_bias(t_start)
        still = gyro_b is not None
        # A still stretch's mean rate is the gyro bias unless the autopilot already removed the
        # bias it measured at rest (``imu_noise.rest_bias_removed``): then that mean is the
        # vehicle's rocking on its legs and the first bias stays at the prior's zero mean.
        # Crazyflie traj2 / traj13 (the two flights with such a stretch): it put the bias
        # 1-1.5 mrad/s off on x, y and held body z 0.7 / 0.2 mrad/s off; causal end drift 1.59
        # / 1.49 -> 0.93 / 0.85 % (scripts/crazyflie_causal_speed.py).
        bias_from_still = still and not self.calib.imu_noise.rest_bias_removed
        if not bias_from_still:
            gyro_b = np.zeros(3)
        vel = np.zeros(3)
        f_still = self._still_force(t_start - still_age) if still else None
        acc_b = still_accel_bias(f_still, go.gravity) if bias_from_still else np.zeros(3)
        if still and R_att is None and self._carry is None and still_age > 0.0:
            R0, vel = self._from_still(t_start, still_age, f_still, gyro_b, yaw0, acc_b)
        self._provisional_thrust_only(a)
        self.t0 = t_start
        self.k = 0
        self.t_kf = {0: t_start}
        bias = gtsam.imuBias.ConstantBias(acc_b, gyro_b)
        pose = gtsam.Pose3(gtsam.Rot3(R0), np.zeros(3))
        yaw_sigma = (
            go.prior_yaw_sigma if not (go.use_yaw and yaws) else max(go.prior_yaw_sigma, 1.0)
        )
        pos_sigma, vel_sigma = go.prior_position_sigma, go.prior_velocity_sigma
        if still and R_att is None and self._carry is None and still_age > 0.0:
            # Integrated from rest (``_from_still``): its error grows with the time since.
            vel_sigma = min(vel_sigma, STILL_VEL_SIGMA + STILL_VEL_SIGMA_RATE * still_age)
        carry, self._carry = self._carry, None
        self._health.pos_sigma_allowed = 0.0
        if carry is not None:
            # Restart after an IMU gap: the newest state before it, its priors widened by the gap.
            gap = max(t_start - carry["t"], 0.0)
            self._bad_since = t_start  # quality halved for the first 2 s
            if self._attitude_at(t_start) is None and not (go.use_yaw and yaws):
                yaw_c = float(np.arctan2(carry["R"][1, 0], carry["R"][0, 0]))
                R0 = level_rotation_from_accel(a.mean(axis=0), yaw_c)
                yaw_sigma = max(yaw_sigma, min(math.pi, GAP_YAW_RATE_SIGMA * gap))
            vel = carry["v"]
            self._carried_align = dict(carry["align"])
            placed = self._slam_place(t_start, R0)
            if placed is None:
                pose = gtsam.Pose3(gtsam.Rot3(R0), carry["p"] + vel * gap)
            else:
                pose = gtsam.Pose3(gtsam.Rot3(R0), placed[0])
                vel = vel if placed[1] is None else placed[1]
            pos_sigma += 0.5 * GAP_ACCEL_SIGMA * gap**2 + go.prior_velocity_sigma * gap
            vel_sigma += GAP_ACCEL_SIGMA * gap
            # (the monitor's position-sigma bound: not a divergence, the gap's own ignorance)
            self._health.pos_sigma_allowed = 2.0 * math.sqrt(3.0) * pos_sigma
            bias = (
                carry["bias"]
                if not bias_from_still
                else gtsam.imuBias.ConstantBias(carry["bias"].accelerometer(), gyro_b)
            )
        # Without an attitude stream the start's attitude is one specific-force mean (tilted
        # by any acceleration, EuRoC V1_02: 2-3 deg): the QR start relinearises more often.
        self.smoother = self._new_smoother(
            self.factorization, startup=self.factorization == "QR" and R_att is None
        )
        g = gtsam.NonlinearFactorGraph()
        # Gauge: yaw about *world* z and the position; roll and pitch only as well as the initial
        # attitude knows them. The Pose3 tangent is in body axes, so the world-frame rotation
        # covariance is rotated into the body (a body whose z is not up, EuRoC's x-up IMU, would
        # otherwise pin a tilt instead of the yaw).
        cov = np.zeros((6, 6))
        cov_w = np.diag([go.prior_rollpitch_sigma**2] * 2 + [yaw_sigma**2])
        cov[:3, :3] = R0.T @ cov_w @ R0
        cov[3:, 3:] = np.eye(3) * pos_sigma**2
        g.add(gtsam.PriorFactorPose3(X(0), pose, gtsam.noiseModel.Gaussian.Covariance(cov)))
        g.add(gtsam.PriorFactorVector(V(0), vel, self._noise(3, vel_sigma, False)))
        g.add(
            gtsam.PriorFactorConstantBias(
                B(0),
                bias,
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.r_[
                        [go.prior_accel_bias_sigma] * 3,
                        gyro_bias_prior_sigmas(
                            go,
                            self.calib,
                            self._thrust_only and not go.use_slam and not (go.use_yaw and yaws),
                        ),
                    ]
                ),
            )
        )
        vals = gtsam.Values()
        vals.insert(X(0), pose3=pose)
        vals.insert(V(0), vector=vel)
        vals.insert(B(0), constant_bias=bias)
        stamps = {X(0): t_start, V(0): t_start, B(0): t_start}
        self.values = {X(0): pose, V(0): vel, B(0): bias}
        self._new_slow(0, g, vals, stamps)
        wall = time.perf_counter()
        self._update(g, vals, stamps, [])
        self._read(0, wall)
        self._kf_index.append((t_start, 0))
        self._waiting_scalar(0)
        # The SLAM poses that arrived before the start attach when taken at or after it (a pose
        # that came with no latency, before the IMU passed its time), else are counted.
        prestart, self._slam_prestart = self._slam_prestart, []
        for t, payload in prestart:
            self._take_slam(t, payload)
        # The IMU that arrived after the start time (the start may lie in the past: the first
        # SLAM pose's capture time) closes its keyframes now.
        self._advance(self._t_imu_last)
        log.info(
            "%s: started at t=%.3f s (gyro bias %s, %s)",
            self.name,
            t_start,
            np.round(gyro_b, 4).tolist(),
            f"from the IMU still {still_age:.2f} s before"
            if bias_from_still
            else "rest bias removed by the autopilot: zero"
            if still
            else "moving: zero",
        )

    def _still_force(self, t_end: float) -> np.ndarray:
        """Mean specific force of the still stretch's last ``STILL_WINDOW_S`` before ``t_end``."""
        return np.asarray(self.imu.a[self.imu.span(t_end - STILL_WINDOW_S, t_end)]).mean(axis=0)

    def _from_still(
        self,
        t_start: float,
        still_age: float,
        f_still: np.ndarray,
        gyro_b: np.ndarray,
        yaw0: float,
        acc_b: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Attitude and velocity at ``t_start`` when the vehicle stood still until ``still_age``
        before it: level (yaw ``yaw0``) from the mean specific force ``f_still`` of the still
        stretch's last ``STILL_WINDOW_S`` (gravity only), then the arrived IMU integrated from the
        stretch's end to ``t_start`` with the still gyro bias and the accelerometer bias ``acc_b``
        (:func:`still_accel_bias`), from rest. A start while moving (EuRoC V1_02: take-off 1.5 s
        before the start) would otherwise level on a specific force tilted by the acceleration (2-3
        deg, 0.4 m/s^2 of gravity read as acceleration) and start from zero velocity. Uses only IMU
        samples before ``t_start``."""
        t_end = t_start - still_age
        R_end = level_rotation_from_accel(f_still, yaw0)
        bias = gtsam.imuBias.ConstantBias(acc_b, gyro_b)
        pim = self._preintegrate(t_end, t_start, bias, count=False)
        nav = pim.predict(gtsam.NavState(gtsam.Rot3(R_end), np.zeros(3), np.zeros(3)), bias)
        return nav.attitude().matrix(), np.asarray(nav.velocity(), float)

    def _still_gyro_bias(self, t_start: float) -> tuple[np.ndarray | None, float]:
        """The mean gyro rate over the newest still stretch of the arrived IMU before
        ``t_start`` and how long before ``t_start`` it ended [s]; ``(None, nan)`` without one.

        Windows of ``STILL_WINDOW_S`` are tested backwards from ``t_start`` over the IMU
        history: still when the mean specific force is within ``still_accel_tol`` of g, the
        rate's scatter (per-axis standard deviation) below ``still_gyro_tol`` and its mean below
        ``STILL_MAX_GYRO_BIAS``, and, where the attitude stream covers the window, its turn over
        the window below ``STILL_MAX_ATTITUDE_TURN``. The rate itself is not tested against a
        bound: a MEMS gyro's
        bias (0.08 rad/s on EuRoC's) is larger than any stillness tolerance. The newest run of
        still windows (at most ``STILL_MAX_S``) is averaged: a vehicle standing with its rotors
        on before a take-off (EuRoC V1_02: 4 s before the first SLAM pose) gives its bias
        before it moves."""
        o, go = self.options, self.go
        if not (o.still_accel_tol > 0 and o.still_gyro_tol > 0) or len(self.imu.t) < 10:
            return None, math.nan
        t = np.asarray(self.imu.t)
        w = np.asarray(self.imu.w)
        a = np.asarray(self.imu.a)
        # A start soon after the first IMU sample tests what there is (at least init_imu_s).
        win = max(o.init_imu_s, min(STILL_WINDOW_S, t_start - t[0]))
        end = t_start
        sums: list[np.ndarray] = []
        newest = math.nan
        while end - win >= t[0] - 1e-9 and t_start - end < o.history_s:
            i0, i1 = np.searchsorted(t, end - win), np.searchsorted(t, end, side="right")
            ok = False
            if i1 - i0 >= 10:
                ww, aa = w[i0:i1], a[i0:i1]
                mean_w = ww.mean(axis=0)
                ok = bool(
                    abs(float(np.linalg.norm(aa.mean(axis=0))) - go.gravity) < o.still_accel_tol
                    and float(ww.std(axis=0).max()) < o.still_gyro_tol
                    and float(np.abs(mean_w).max()) < STILL_MAX_GYRO_BIAS
                )
                if ok:
                    turn = self._attitude_turn(end - win, end)
                    ok = turn is None or turn <= STILL_MAX_ATTITUDE_TURN
            if ok:
                if not sums:
                    newest = t_start - end
                sums.append(mean_w)
                if len(sums) * win >= STILL_MAX_S - 1e-9:
                    break
            elif sums:
                break  # the newest still stretch ended
            end -= win
        if not sums:
            return None, math.nan
        return np.mean(sums, axis=0), newest

    def _attitude_turn(self, ta: float, tb: float) -> float | None:
        """Angle [rad] the attitude stream turns between ``ta`` and ``tb``, or None when it
        does not cover both (samples within 0.2 s)."""
        Ra, Rb = self._attitude_at(ta), self._attitude_at(tb)
        if Ra is None or Rb is None:
            return None
        return _norm(so3_log(Ra.T @ Rb))

    def _attitude_at(self, t: float) -> np.ndarray | None:
        """The attitude sample nearest ``t`` (within 0.2 s), or None."""
        att = self._att
        if not att:
            return None
        i = len(att)
        while i > 0 and att[i - 1][0] > t:  # newest first: ``t`` is usually recent
            i -= 1
        cand = [j for j in (i - 1, i) if 0 <= j < len(att)]
        j = min(cand, key=lambda j: abs(att[j][0] - t))
        if abs(att[j][0] - t) > 0.2:
            return None
        return quat_wxyz_to_matrix(att[j][1])

    # ------------------------------------------------------------------------------------------
    # Keyframes
    # ------------------------------------------------------------------------------------------

    def _close_keyframe(self, t_k: float) -> None:
        wall = time.perf_counter()
        kp = self.k
        k = kp + 1
        self.t_kf[k] = t_k
        self._kf_index.append((t_k, k))
        bias = self.values[B(kp)]
        pim = self._preintegrate(self.t_kf[kp], t_k, bias)
        self._pim = pim
        nav = pim.predict(gtsam.NavState(self.values[X(kp)], self.values[V(kp)]), bias)
        g = gtsam.NonlinearFactorGraph()
        g.add(gtsam.CombinedImuFactor(X(kp), V(kp), X(k), V(k), B(kp), B(k), pim))
        vals = gtsam.Values()
        vals.insert(X(k), pose3=nav.pose())
        vals.insert(V(k), vector=nav.velocity())
        vals.insert(B(k), constant_bias=bias)
        stamps = {X(k): t_k, V(k): t_k, B(k): t_k}
        self._cur_stamps = stamps
        self.values[X(k)], self.values[V(k)], self.values[B(k)] = nav.pose(), nav.velocity(), bias
        self.k = k
        self._new_slow(k, g, vals, stamps)
        self._frontend_priors(k, g)
        self._drag_factor(k - 1, g, stamps)
        self._flow_factor(k - 1, g, stamps)
        self._waiting_scalar(k)
        remove: list[int] = []
        prov_new: list[tuple[int, int, Any]] = []
        self._attach_pending(g, stamps, remove, prov_new)
        n_moves = self.n_fallbacks
        # The monitored factors' errors as iSAM2 linearises them (the health monitor's input:
        # the update leaves the window at that linearisation point; no second callback).
        self._lin_errors = _jacobians.LINEARIZED = {} if self._health_on else None
        # The update's factors as Python objects kept alive through it: a callback's ``this``
        # is then that object (else pybind11 hands it a copy), the key health looks up.
        self._lin_factors = [g.at(i) for i in range(g.size())] if self._health_on else None
        try:
            ok = self._update(g, vals, stamps, remove)
        finally:
            _jacobians.LINEARIZED = None
        self._cur_stamps = {}
        # After a move of the window the new factors' indices are not this update's: such
        # provisional factors stay on the provisional alignment (an event, counted with the
        # used kinds: the poses themselves were counted as used when they attached; as a drop
        # they were counted twice).
        if prov_new and self.n_fallbacks != n_moves:
            self._use("slam:provisional-kept", len(prov_new))
        elif ok and prov_new:
            idx = list(self.smoother.getISAM2Result().getNewFactorsIndices())
            for pos, sess, row in prov_new:
                s = self.sessions.get(sess)
                if s is not None and s.provisional is not None:
                    s.prov_factors.append((int(idx[pos]), row))
                    if row[5]:  # its rotation factor, added right after it
                        s.prov_rot.append((int(idx[pos + 1]), row[0]))
        self._read(k, wall)
        self._health_keyframe(k, g)
        self._orientation_check(t_k)
        if self._held and k % HELD_PRUNE_EVERY == 0:
            self._prune_held()
        if self.factorization == "QR" and self.options.factorization.upper() != "QR":
            if (
                t_k - self.t0 >= self.options.startup_qr_s
                and self.n_failures == 0
                and self.n_fallbacks == 0
            ):
                self._switch_factorization()

    def _frontend_priors(self, k: int, g) -> None:
        """Front-end priors at keyframe k as it closes: the observer's velocity at the processed
        IMU sample nearest ``t_k`` (within half a period) as a prior on ``V(k)``; a session's ML
        scale, the first time the stage has one for a session whose alignment started before,
        as a prior on the scale of its newest alignment variable (once per session; a chain that
        starts after the stage has one takes it as its initial value and prior instead)."""
        ps = self._pstage
        if ps is None:
            return
        pv = ps.velocity_at(self.t_kf[k], 0.5 * self.period)
        if pv is not None:
            g.add(gtsam.PriorFactorVector(V(k), pv[0], self._noise(3, pv[1], False)))
            self._use("prior:observer-velocity")
        for sess, s in self.sessions.items():
            if sess in self._scale_prior_done or self._axis:
                continue
            key = s.last_key if s.chain else None  # a provisional one takes it as value
            if key is None or not self._alive(key) or self._queued_values.exists(key):
                continue
            sc = ps.scale(sess)
            if sc is None:
                continue
            g.add(self._scale_prior(key, self.values[key], sc))
            self._scale_prior_done.add(sess)
            self._use("prior:ml-scale")

    def _scale_prior(self, key: int, value: gtsam.Similarity3, sc) -> Any:
        """A prior on the scale of alignment ``key`` only: ``(s, sigma)`` on the log-scale,
        rotation and translation free (sigmas 1e3)."""
        s, sig = sc[0], sc[1]
        mean = gtsam.Similarity3(value.rotation(), value.translation(), float(s))
        sigmas = np.r_[[1e3] * 6, [sig / s]]
        return gtsam.PriorFactorSimilarity3(key, mean, gtsam.noiseModel.Diagonal.Sigmas(sigmas))

    def _prior_streams_missing(self) -> list[str]:
        """The streams of ``PRIOR_STREAMS`` the front-end priors need that have not arrived."""
        from fgnav.frontends.prior_stages import PRIOR_STREAMS

        return [s for s in PRIOR_STREAMS if s != "imu" and not self.received.get(s)]

    def _watch_prior_streams(self, t: float) -> None:
        """Once ``PRIOR_STREAMS_WAIT_S`` of IMU time has passed: the one line a flight without a
        stream the ``[priors]`` sources need is refused with (``fgnav.methods``), as a warning
        (a link cannot be checked before it runs: ``fgnav live`` with ``ml-scale`` and no
        rangefinder gave no prior and said nothing)."""
        from fgnav.frontends.prior_stages import PRIOR_STREAMS_WAIT_S, missing_streams_message

        if self._prior_watch_t0 is None:
            self._prior_watch_t0 = t
        if t - self._prior_watch_t0 < PRIOR_STREAMS_WAIT_S:
            return
        self._prior_watch_done = True
        missing = self._prior_streams_missing()
        if missing:
            log.warning(
                "%s (none in the first %g s of IMU): no prior from it until they come",
                missing_streams_message(self.name, self.prior_options.sources, missing),
                PRIOR_STREAMS_WAIT_S,
            )

    def _prior_report(self) -> dict[str, Any] | None:
        """The front-end prior stage: sources, the ML scale per session it has, its counts."""
        ps = self._pstage
        if ps is None:
            return None
        scales = {}
        for sess in ps.sessions:
            sc = ps.scale(sess)
            if sc is not None:
                scales[str(sess)] = {"scale": sc[0], "sigma": sc[1], "pairs": sc[2]}
        out = {
            "sources": list(self.prior_options.sources),
            "ml_scale": scales,
            "counts": ps.all_counts,
        }
        missing = self._prior_streams_missing()
        if missing:  # never arrived (see _watch_prior_streams)
            out["missing_streams"] = missing
        return out

    def _ml_scale(self, sess: int):
        """The ML-scale stage's ``(s, sigma, n_pairs)`` for a session, or None."""
        return self._pstage.scale(sess) if self._pstage is not None else None

    def _new_slow(self, k: int, g, vals, stamps) -> None:
        """Drag and ground segments starting at keyframe k."""
        go = self.go
        t_k = self.t_kf[k]
        for c, seg_s, on in (
            ("d", go.drag_segment_s, self._drag_on or self._drag_dynamics()),
            ("g", go.ground_segment_s, go.use_range),
        ):
            if not on:
                continue
            j = int((t_k - self.t0) / seg_s + 1e-9) if seg_s else 0
            key = self._slow_key_at(c, seg_s, k)
            if key in self.values:
                if self._alive(key) or key in stamps:
                    stamps[key] = t_k  # the current segment stays in the window
                continue
            # (the first segment of a ground epoch has no predecessor in it: a prior)
            prev = key - 1 if j > 0 else None
            alive = prev is not None and self._alive(prev)
            if c == "d":
                dim = 2 if go.drag_per_axis else 1
                value = (
                    self.values[prev]
                    if alive
                    else np.full(dim, go.drag_k_init if go.drag_k_init is not None else 0.3)
                )
                if alive:
                    sig = go.drag_rw * math.sqrt(seg_s or 1.0)
                    g.add(
                        gtsam.BetweenFactorVector(
                            prev, key, np.zeros(dim), self._noise(dim, sig, False)
                        )
                    )
                else:
                    g.add(
                        gtsam.PriorFactorVector(
                            key, value, self._noise(dim, go.drag_prior_sigma, False)
                        )
                    )
            else:
                if alive:
                    value = self.values[prev]
                    sig = go.ground_rw * math.sqrt(seg_s)
                    g.add(
                        gtsam.BetweenFactorVector(
                            prev, key, np.zeros(1), self._noise(1, sig, False)
                        )
                    )
                else:
                    guess, within = self._ground_guess(k)
                    self._ground_measured = False  # (until a range factor is on it)
                    if not within:
                        self._range_seen_t = -math.inf  # the next reading confirms it
                    value = np.array([guess])
                    g.add(
                        gtsam.PriorFactorVector(
                            key, value, self._noise(1, go.ground_prior_sigma, False)
                        )
                    )
            vals.insert(key, np.asarray(value, float))
            stamps[key] = t_k
            self.values[key] = np.asarray(value, float)

    def _ground_guess(self, k: int) -> tuple[float, bool]:
        """World z of the ground under keyframe ``k`` from the arrived range readings (the
        median of the newest three of the last ``GROUND_GUESS_S``, else the newest; 0 without
        one), and whether they were all distances (:meth:`RangeLimits.refusal`). A reading below
        the minimum is kept for the guess (a Crazyflie on the floor reads 12-25 mm under its 40
        mm limit, and that ground is right); one at the sensor's maximum is not (no echo: it
        says nothing of the ground, :func:`range_at_max`). The first reading within the limits
        confirms the guess or the ground starts anew (:meth:`_range_gate`)."""
        rng = self._scalar["range"]
        pose = self.values.get(X(k))
        hi = self.calib.range_max
        seen = [(tr, r) for tr, r in rng if not range_at_max(r, hi)]
        if not seen or pose is None:
            return 0.0, False
        t_k = self.t_kf[k]
        recent = [r for tr, r in seen if t_k - GROUND_GUESS_S <= tr <= t_k + 1e-9][-3:] or [
            seen[-1][1]
        ]
        r = float(np.median(recent))
        usable = self._range_limits.usable
        return self._reading_ground(r, pose), all(map(usable, recent))

    def _range_expected(self, t: float) -> float | None:
        """The reading the newest state predicts (the health's ``range-at-max``): the distance
        along the beam from the rangefinder to the ground height, None while no range factor is
        on the current ground chain (its value is a guess) or the beam points 85 deg or more
        from down."""
        if not self._ground_measured or not self.out:
            return None
        s = self.out[-1]
        if s.ground_height is None:
            return None
        T = np.asarray(s.world_T_body, float)
        e = float(predicted_range(T[:3, :3], T[:3, 3], float(s.ground_height), self.body_T_range))
        return e if math.isfinite(e) else None

    def _reading_ground(self, range_m: float, pose: gtsam.Pose3) -> float:
        """World z of the flat ground a range reading sees from ``pose``."""
        return float(pose.translation()[2]) - self._body_height(range_m, pose.rotation().matrix())

    def _body_height(self, range_m: float, world_R_body: np.ndarray) -> float:
        """Height of the body origin above the ground a range reading sees (tilted beam, lever
        arm, flat ground)."""
        return flow_sensor_height(range_m, world_R_body, self.body_T_range, _EYE4)

    def _alive(self, key: int) -> bool:
        """In the window (or added by the update being built), and measured within the lag (a
        measurement on it may attach)."""
        if key in self._cur_stamps:
            return True
        return (
            key in self.smoother
            and key in self.stamp
            and self.stamp[key] >= self.t_kf[self.k] - self.options.lag_s
        )

    def _kf_alive(self, k: int) -> bool:
        return 0 <= k <= self.k and k in self.t_kf and self._alive(X(k))

    # ------------------------------------------------------------------------------------------
    # Drag
    # ------------------------------------------------------------------------------------------

    def _thrust_check(self, t: float) -> None:
        """Decide once, from the IMU of the first ``drag_check_s``, whether the thrust is along
        body +z (the mean specific force near it): else neither the drag model nor the
        accelerometer check applies."""
        s = self.imu.span(self.t0, t)
        acc = np.asarray(self.imu.a[s])
        if len(acc) == 0:
            return
        n = np.linalg.norm(acc, axis=1)
        ok = n > 0.5 * self.go.gravity
        self._drag_checked = True
        self._thrust_axis_ok = True
        if not ok.any():
            if self._drag_on:
                self._drag_decision = "on (no thrust-borne sample to check)"
            return
        d = (acc[ok] / n[ok, None]).mean(axis=0)
        d /= max(float(np.linalg.norm(d)), 1e-12)
        ang = math.degrees(math.acos(float(np.clip(d[2], -1.0, 1.0))))
        if self.go.drag_thrust_check and ang > self.go.drag_thrust_max_angle_deg:
            self._thrust_axis_ok = False
            if self._thrust_provisional:
                self._end_provisional_thrust_only(f"mean thrust {ang:.0f} deg from body +z")
            if self._drag_on:
                self._drag_on = False
                self._drag_decision = (
                    f"off: the mean specific force of the first {self.options.drag_check_s:g} s "
                    f"is {ang:.0f} deg from body +z (the drag model needs the thrust along body "
                    "z)"
                )
                log.warning("%s: drag factor %s", self.name, self._drag_decision)
        elif self._drag_on:
            self._drag_decision = f"on (mean thrust {ang:.0f} deg from body +z)"

    def _drag_factor(self, j: int, g, stamps) -> None:
        """The drag factor of keyframe j over ``[t_j - h0, t_j + h1]`` (half the neighbouring
        keyframe intervals), once keyframe j + 1 has closed; the keyframe's mean horizontal
        specific force also feeds the accelerometer check (:meth:`_accel_decide`)."""
        check = self.go.accel_horizontal == "auto" or (self._drag_on and self.go.drag_accel_check)
        on = self._drag_on or check or self._drag_dynamics()
        if not on or j < 0 or j not in self.t_kf or j + 1 not in self.t_kf:
            return
        t_j = self.t_kf[j]
        if not self._drag_checked:
            if t_j - self.t0 < self.options.drag_check_s:
                return
            self._thrust_check(t_j)
        if not getattr(self, "_thrust_axis_ok", True):
            return  # thrust not along body z: no drag model, no accelerometer check
        h1 = 0.5 * (self.t_kf[j + 1] - t_j)
        h0 = 0.5 * (t_j - self.t_kf[j - 1]) if j - 1 in self.t_kf else h1
        mean, n, dur = self._mean_accel(t_j - h0, t_j + h1)
        if mean is None or n == 0:
            self._drop("drag:no-imu-in-interval")
            return
        norm_mean = _norm(mean)
        f_x, f_y, f_z = mean.tolist()  # (plain floats for the scalar tests and the check's row)
        cos_tilt = f_z / max(norm_mean, 1e-12)
        sigma_a = self.calib.imu_noise.accel_noise_density * math.sqrt(max(n / dur, 1.0))
        if (
            check
            and self._accel_check_open()
            and (
                norm_mean > 0.5 * self.go.gravity
                and cos_tilt >= _COS_ACCEL_CHECK_MAX_TILT
                and X(j) in self.values
                and V(j) in self.values
            )
        ):
            R = self.values[X(j)].rotation().matrix()
            u_x, u_y, _ = (R.T @ np.asarray(self.values[V(j)], float)).tolist()
            self._accel_rows.append((f_x, f_y, u_x, u_y, sigma_a / math.sqrt(n)))
            first = self._accel_check is None or self._accel_check.decision == "undecided"
            if len(self._accel_rows) >= ONLINE_ACCEL_CHECK_MIN_KEYFRAMES and (first or j % 5 == 0):
                self._accel_decide(t_j)
        undecided = self._accel_check is None or self._accel_check.decision == "undecided"
        # While the prediction is (provisionally) thrust-only the x, y bias stands for the
        # negated drag, not for the sensor's bias the measured-force factor needs.
        if self._drag_dynamics() and (not self._drag_on or undecided or self._thrust_only):
            self._drag_dynamics_factor(j, g, stamps)
            return
        if not self._drag_on:
            return
        if self.go.drag_accel_check and undecided:
            self._drop("drag:accelerometer-not-checked-yet")  # drag stays out until checked
            return
        if not self._kf_alive(j):
            self._drop("drag:late")
            return
        if cos_tilt < math.cos(math.radians(self.go.drag_max_tilt_deg)):
            self._drop("drag:not-thrust-borne")
            return
        f_xy = mean[:2]
        self._drag_means.append(f_xy)
        if self.go.drag_sigma_from_data and len(self._drag_means) >= 20 and j % 20 == 0:
            self._drag_sigma = max(self.go.drag_model_sigma, self._drag_scatter())
            chk = self._accel_check
            if chk is not None and chk.decision == "noisy":
                self._drag_sigma = max(self._drag_sigma, chk.residual)
        key = ("drag", n, round(self._drag_sigma, 4))
        noise = self._noise_cache.get(key)
        if noise is None:
            noise = mean_accel_noise(sigma_a, n, self._drag_sigma)
            if self.go.drag_robust:
                noise = self._robust(noise)
            self._noise_cache[key] = noise
        dk = self._slow_key_at("d", self.go.drag_segment_s, j)
        if dk not in self.values or not self._alive(dk):
            self._drop("drag:late")
            return
        g.add(make_accel_drag_factor(X(j), V(j), B(j), dk, f_xy, noise))
        stamps[dk] = self.t_kf[self.k]
        self._use("drag")

    def _drag_dynamics(self) -> bool:
        """The thrust-only prediction models the neglected body x, y specific force as rotor
        drag (``graph.thrust_only_drag_sigma``); not with SLAM in use (module docstring)."""
        return (
            self._thrust_only
            and not self.go.use_slam
            and self.go.thrust_only_drag_sigma is not None
            and getattr(self, "_thrust_axis_ok", True)
        )

    def _drag_dynamics_factor(self, j: int, g, stamps) -> None:
        """Thrust-only prediction: the body x, y accelerometer bias (the negated specific force
        the prediction integrates) is the rotor drag ``k u_xy`` at keyframe j: the drag factor
        with a zero measurement."""
        if not self._kf_alive(j):
            return
        dk = self._slow_key_at("d", self.go.drag_segment_s, j)
        if dk not in self.values or not self._alive(dk):
            return
        noise = self._noise(2, self.go.thrust_only_drag_sigma, False)
        g.add(make_accel_drag_factor(X(j), V(j), B(j), dk, np.zeros(2), noise))
        stamps[dk] = self.t_kf[self.k]
        self._use("drag-dynamics")

    def _accel_check_open(self) -> bool:
        """The accelerometer check still collects keyframes (it stops once it has found the
        horizontal channels unusable: the decision is kept)."""
        return self._accel_check is None or self._accel_check.decision != "unusable"

    def _accel_decide(self, t: float) -> None:
        """Run the accelerometer check on the last ``drag_scatter_n`` keyframes (means of the
        horizontal specific force against the smoother's body velocities at them): unusable ->
        drag off and (``accel_horizontal = "auto"``) thrust-only IMU prediction from the next
        keyframe on, said in one line; noisy -> the drag noise floor is raised to the misfit."""
        # (check_horizontal_accel on the window's rows, from running sums)
        rows = self._accel_rows
        chk = rows.check(AccelLimits(min_keyframes=ONLINE_ACCEL_CHECK_MIN_KEYFRAMES))
        self._accel_check = chk
        if chk.decision != "unusable":
            # The first verdicts (the Crazyflie on the ground, motors spinning up) may still
            # turn "unusable": the provisional thrust-only prediction ends on "usable" in the
            # air, or on "noisy" over a full check window.
            # The ground says little about the accelerometer in flight: "usable" counts once
            # the check's keyframes are all off the ground (no ground contact among them).
            airborne = t - self._last_contact_t > len(rows) * self.period
            if self._thrust_provisional and (
                (chk.decision == "usable" and airborne)
                or (chk.decision == "noisy" and len(rows) >= self.options.drag_scatter_n)
            ):
                self._end_provisional_thrust_only(f"the accelerometer check: {chk.decision}")
            return
        was_thrust_only = self._thrust_only
        self._thrust_provisional = False
        if self.go.drag_accel_check and self._drag_on:
            self._drag_on = False
        if self.go.accel_horizontal == "auto" and not was_thrust_only and not self.go.use_slam:
            # (with SLAM the measured prediction stays: module docstring of accel_check)
            self._thrust_only = True
            if getattr(self, "_health", None) is not None:
                self._health.horizontal_accel_free = True
            # The accelerometer bias has absorbed the measured x, y offsets: it may jump to the
            # thrust-only model's over the next interval.
            self._bias_release = True
        self._drag_decision = (
            f"off at t={t - self.t0:.2f} s after the start: "
            + chk.line()
            + (
                "; IMU prediction thrust-only (body x, y specific force 0)"
                if self._thrust_only
                else ""
            )
        )
        log.warning("%s: %s", self.name, self._drag_decision)

    def _provisional_thrust_only(self, accel: np.ndarray) -> None:
        """``accel_horizontal = "auto"``: predict thrust-only from the start until the
        accelerometer check decides, when the specific force of the start window lies within
        ``drag_thrust_max_angle_deg`` of body +z. A vibrating horizontal accelerometer (the
        Crazyflie's offsets of 1-4 m/s^2 once the motors spin, on the ground) integrated for the
        0.5-1.5 s the check needs tilts the attitude by up to 14 deg against the ground-contact
        zero velocity, and nothing in a thrust-only prediction observes that tilt afterwards.
        Not with SLAM in use (``graph.use_slam``): its positions observe a tilt error through the
        measured accelerometer, and the health monitor's accelerometer-bias judgement (which
        names a wrong ``body_T_cam`` in the fault matrix) needs the measured prediction."""
        if (
            self.go.accel_horizontal != "auto"
            or self.go.use_slam
            or self._thrust_only
            or len(accel) == 0
        ):
            return
        d = np.asarray(accel, float).mean(axis=0)
        n = float(np.linalg.norm(d))
        if not n > 0.5 * self.go.gravity:
            return
        ang = math.degrees(math.acos(float(np.clip(d[2] / n, -1.0, 1.0))))
        if ang > self.go.drag_thrust_max_angle_deg:
            return
        self._thrust_only = True
        self._thrust_provisional = True
        if getattr(self, "_health", None) is not None:
            self._health.horizontal_accel_free = True

    def _end_provisional_thrust_only(self, why: str) -> None:
        """Back to the measured horizontal specific force (the check found it usable, or the
        thrust is not along body z): the x, y accelerometer bias, which stood for the negated
        neglected force, may jump to the sensor's over the next interval."""
        self._thrust_only = False
        self._thrust_provisional = False
        self._bias_release = True
        if getattr(self, "_health", None) is not None:
            self._health.horizontal_accel_free = False
        log.info(
            "%s: IMU prediction with the measured horizontal specific force (%s)", self.name, why
        )

    def _accel_params(self) -> gtsam.PreintegrationCombinedParams:
        """Preintegration parameters of the current accelerometer model: the calibration's, or
        with the body x, y noise and bias walk of the thrust-only prediction
        (:func:`fgnav.solvers.graph.thrust_only_noise`)."""
        if not (self._thrust_only or self._bias_release):
            return self.pim_params
        if not self._bias_release and getattr(self, "_pim_thrust", None) is not None:
            return self._pim_thrust
        n = self.calib.imu_noise
        p = pim_params(n, self.go.gravity)
        walk = BIAS_RELEASE_WALK  # x, y bias walk of a release (one interval)
        if self._thrust_only:
            nd, rw = thrust_only_noise(
                self.go.thrust_only_sigma,
                self.go.thrust_only_tau_s,
                self.go.keyframe_hz,
                n.accel_noise_density,
                n.accel_random_walk,
            )
            p.setAccelerometerCovariance(np.diag([nd**2, nd**2, n.accel_noise_density**2]))
            if not self._bias_release:
                walk = rw
        p.setBiasAccCovariance(np.diag([walk**2, walk**2, n.accel_random_walk**2]))
        if self._bias_release:
            self._bias_release = False
        else:
            self._pim_thrust = p
        return p

    def _flow_factor(self, j: int, g, stamps) -> None:
        """The optical-flow factor of keyframe j: the readings ending in its window
        ``(t_j - h0, t_j + h1]`` (half the neighbouring keyframe intervals) summed
        (:func:`fgnav.solvers.flow.flow_keyframe_factor`), once keyframe j + 1 has closed; a
        reading arriving after its window was made is counted as ``flow:late``."""
        if j < 0 or j not in self.t_kf or j + 1 not in self.t_kf:
            return
        self._contact_factor(j, g, stamps)
        if not self._flow:
            return
        from fgnav.solvers.flow import flow_keyframe_factor, flow_options

        t_j = self.t_kf[j]
        h1 = 0.5 * (self.t_kf[j + 1] - t_j)
        h0 = 0.5 * (t_j - self.t_kf[j - 1]) if j - 1 in self.t_kf else h1
        lo, hi = max(t_j - h0, self._flow_done_t), t_j + h1
        samples = [r for r in self._flow if lo < r.t <= hi]
        # Readings older than the window just made arrived too late for theirs (or were taken
        # before the start, the first window's lower edge).
        n_early = sum(1 for r in self._flow if r.t <= min(lo, self.t0))
        n_late = sum(1 for r in self._flow if r.t <= lo) - n_early
        if n_early:
            self._drop("flow:before-start", n_early)
        if n_late:
            self._drop("flow:late", n_late)
        while self._flow and self._flow[0].t <= hi:
            self._flow.popleft()
        self._flow_done_t = hi
        if not samples:
            return
        if not self._kf_alive(j):
            self._drop("flow:late", len(samples))
            return
        gk = self._slow_key_at("g", self.go.ground_segment_s, j)
        pose = self._pose_at(t_j)
        R = pose.rotation().matrix()
        height = None
        # The newest range reading within height_max_age_s of t_j that is a distance: the whole
        # test of the sensor's limits, as the batch graph's (range_refusal with the stream's
        # clamp state; only the floor and the maximum were tested, so a reading under the floor
        # or beyond the maximum was a height). A refused reading is passed over for an older
        # usable one within the age, as the batch takes the nearest usable; none: no height,
        # counted range:flow-height:<reason of the newest refused>.
        age = flow_options(self.go.flow).height_max_age_s
        why = None
        for t_r, r in reversed(self._scalar["range"]):
            if t_r - t_j > age:
                continue
            if t_j - t_r > age:
                break
            refused = self._range_limits.refusal(r)
            if refused is None:
                height = flow_sensor_height(
                    r, R, self.body_T_range, np.asarray(self.calib.body_T_flow, float)
                )
                break
            why = why or refused
        if height is None and why is not None:
            self._drop(f"range:flow-height:{why}")
        s = self.imu.span(lo - 0.05, hi + 0.05)
        res = flow_keyframe_factor(
            samples,
            np.asarray(self.imu.t[s]),
            np.asarray(self.imu.w[s]),
            self.calib,
            X(j),
            V(j),
            gk,
            flow_options(self.go.flow),
            gyro_bias=np.asarray(self.values[B(self.k)].gyroscope()),
            height=height,
            world_R_body=R,
            robust=self._robust,
        )
        for reason, n in res.skipped.items():
            self._drop(f"flow:{reason}", n)
        ts = [r.t for r in samples]
        self._flow_watch.add(min(ts), max(ts), len(samples), res.skipped)
        self._flow_health(res.reason, max(ts))
        if res.factor is None or gk not in self.values or not self._alive(gk):
            if res.factor is not None:
                self._drop("flow:late", res.n_used)
            return
        g.add(res.factor)
        stamps[gk] = self.t_kf[self.k]
        self._use("flow", res.n_used)

    def _flow_health(self, reason: str, t: float) -> None:
        """The flow's degrading faults after a window (:data:`fgnav.health.DEGRADING`):
        ``flow-rejected`` while the reject watch's run lasts; ``flow-no-height`` once flow has
        arrived for ``flow_no_height_s`` with no range reading (a window without a height)."""
        hm = self._health
        if not hm.options.enabled:
            return
        if self._flow_watch.rejecting:
            rep = self._flow_watch.current()
            # (the watch said it in its own warning: counted, not said again)
            hm.degrade(
                "flow-rejected",
                f"every flow reading rejected from t={rep['since_s']:.2f} s "
                f"({', '.join(f'{r} {c}' for r, c in sorted(rep['reasons'].items()))}): the "
                "flow gives no velocity",
                say=False,
            )
        else:
            hm.restore("flow-rejected")
        if self.received.get("range"):
            hm.restore("flow-no-height")
        elif (
            reason == "no-height"
            and self._flow_first_t is not None
            and t - self._flow_first_t >= hm.options.flow_no_height_s
        ):
            self._flow_no_height("no rangefinder reading has arrived")

    def _flow_no_height(self, why: str) -> None:
        """Name ``flow-no-height`` (said once): optical flow with no height source."""
        if not self._health.options.enabled or "flow-no-height" in self._health.degraded:
            return
        self._health.degrade(
            "flow-no-height",
            f"optical flow arrives but {why}: no height source, and the flow measures velocity "
            "over height, so it gives no metric velocity; it is not used and the horizontal "
            "velocity and the height are dead-reckoned from the IMU (they drift)",
        )

    def _contact_factor(self, j: int, g, stamps) -> None:
        """Ground contact at keyframe j (``graph.contact_height_m``, as the batch graph): the two
        range readings around ``t_j`` (or the two newest, within ``interp_max_gap_s``) put the
        range sensor within ``contact_height_m`` of the ground -> zero velocity and (with
        ``contact_range_sigma``) a range of 0 m at keyframe j."""
        go = self.go
        rng = self._scalar["range"]
        if go.contact_height_m is None or not go.use_range or len(rng) < 2:
            return
        t_j = self.t_kf[j]
        n = len(rng)
        i = bisect.bisect_right(rng, t_j, key=_first)  # no copy of the readings' times
        pair = (i - 1, i) if 1 <= i < n else (n - 2, n - 1)
        if pair[0] < 0 or any(abs(rng[p][0] - t_j) > go.interp_max_gap_s for p in pair):
            return
        if not self._kf_alive(j) or X(j) not in self.values:
            return
        R = self.values[X(j)].rotation().matrix()
        cos_beam = -float((R @ self.body_T_range[:3, 2])[2])
        if any(rng[p][1] * cos_beam > go.contact_height_m for p in pair):
            return
        g.add(gtsam.PriorFactorVector(V(j), np.zeros(3), self._noise(3, go.contact_velocity_sigma)))
        self._use("contact")
        self._last_contact_t = max(self._last_contact_t, t_j)
        gk = self._slow_key_at("g", go.ground_segment_s, j)
        if go.contact_range_sigma is not None and gk in self.values and self._alive(gk):
            g.add(
                make_range_factor(
                    X(j), gk, 0.0, self.body_T_range, self._noise(1, go.contact_range_sigma)
                )
            )
            stamps[gk] = self.t_kf[self.k]

    def _drag_scatter(self) -> float:
        x = self._drag_means.array()
        half = max(1, int(round(0.25 * self.go.keyframe_hz)))
        pad = np.pad(x, ((half, half), (0, 0)), mode="edge")
        win = np.lib.stride_tricks.sliding_window_view(pad, 2 * half + 1, axis=0)
        dev = x - np.median(win, axis=-1)
        mad = float(np.median(np.abs(dev - np.median(dev, axis=0))))
        white = self.calib.imu_noise.accel_noise_density * math.sqrt(self.go.keyframe_hz)
        return math.sqrt(max((1.4826 * mad) ** 2 - white**2, 0.0))

    def _slow_key_at(self, c: str, seg_s: float | None, k: int) -> int:
        """The drag (``c`` "d") or ground ("g") segment variable of keyframe k: one per
        ``seg_s`` of flight; the ground's counted anew in each ground epoch (a terrain step,
        :meth:`_range_gate`), whose index is ``epoch * GROUND_EPOCH_STRIDE``."""
        j = int((self.t_kf[k] - self.t0) / seg_s + 1e-9) if seg_s else 0
        if c == "g":
            for k0, epoch in reversed(self._g_epochs):
                if k >= k0:
                    j += epoch * GROUND_EPOCH_STRIDE
                    break
        return gtsam.symbol(c, j)

    # ------------------------------------------------------------------------------------------
    # Range and yaw
    # ------------------------------------------------------------------------------------------

    def _on_scalar(self, kind: str, t: float, value: float) -> None:
        if not math.isfinite(value):
            self._drop(f"{kind}:non-finite")
            return
        buf = self._scalar[kind]
        if kind == "range":
            self._range_limits.see(value)
        if kind == "yaw" and buf:
            value = buf[-1][1] + wrap_angle(value - buf[-1][1])  # unwrapped
        buf.append((t, float(value)))
        while len(buf) > 2 and buf[0][0] < self._t_imu_last - 5.0:
            buf.popleft()  # interpolation and heights need the newest seconds only
        wait = self._scalar_wait[kind]
        while wait and self.t_kf.get(wait[0], math.inf) <= t:
            self._scalar_at(kind, wait.popleft())

    def _waiting_scalar(self, k: int) -> None:
        """Range and yaw at keyframe k: now when a later sample has arrived, else when it does."""
        for kind in ("range", "yaw"):
            if not self.received.get(kind):
                continue  # no such stream (yet): nothing to wait for
            buf = self._scalar[kind]
            if buf and buf[-1][0] >= self.t_kf[k]:
                self._scalar_at(kind, k)
            else:
                wait = self._scalar_wait[kind]
                wait.append(k)
                while len(wait) > 4 * self.options.lag_s * self.go.keyframe_hz:
                    wait.popleft()
                    self._drop(f"{kind}:keyframes-without-bracketing-samples")

    def _scalar_at(self, kind: str, k: int) -> None:
        """Interpolate a range or yaw stream at keyframe k from its two bracketing samples."""
        buf = self._scalar[kind]
        tk = self.t_kf.get(k)
        if tk is None:
            return
        # The bracket is near the newest samples: search from the end.
        i = len(buf)
        while i > 0 and buf[i - 1][0] >= tk:
            i -= 1
        if i < len(buf) and abs(buf[i][0] - tk) < 1e-9:
            self._pending.append((k, kind, buf[i][1]))
            return
        if i == 0 or i >= len(buf) or buf[i][0] - buf[i - 1][0] > self.go.interp_max_gap_s:
            self._drop(f"{kind}:keyframes-without-bracketing-samples")
            return
        (t0, v0), (t1, v1) = buf[i - 1], buf[i]
        if kind == "range":
            # Both brackets must be distances (range_refusal), as the batch graph gates both: one
            # out of the limits, at the floor or at the maximum, interpolated with a reading
            # beside it, made one up that the value's own gate passed (0.02 m on the ground
            # under a 0.04 m floor beside 0.30 m: 0.16 m). Counted as _range_factor counts a
            # value: range:gated:out, range:at-min, range:at-max.
            for v in (v0, v1):
                why = self._range_limits.refusal(v)
                if why is not None:
                    self._drop(_RANGE_DROP.get(why, f"range:{why}"))
                    return
        w = (tk - t0) / (t1 - t0)
        self._pending.append((k, kind, (1 - w) * v0 + w * v1))

    # ------------------------------------------------------------------------------------------
    # SLAM
    # ------------------------------------------------------------------------------------------

    def _on_slam(self, ev: SlamPose) -> None:
        if self._slam_offset:
            ev = ev._replace(t=ev.t + self._slam_offset)
        # (values checked in feed(): _slam_plausible)
        p = np.asarray(ev.slam_t_cam, float)
        q = np.asarray(ev.slam_q_cam_wxyz, float)
        if self._sgc is not None:
            self._slam_check(float(ev.t), q, int(ev.session), p)
        elif self._mirror_sgc is not None:
            self._mirror_retest(float(ev.t), q, int(ev.session), p)
        if self._mirror is not None:
            if self._mirror == "off":
                self._drop("slam:mirrored")
                return
            # Un-mirrored: D p, D R D; a session of its own (the poses before the decision made
            # their alignment mirrored).
            D = np.ones(3)
            D[self._mirror] = -1.0
            p, q = p * D, np.concatenate([q[:1], -D * q[1:]])
            ev = ev._replace(session=int(ev.session) + MIRROR_SESSION_BASE)
        # The payload keeps the orientation as stored: a convention decided while it waits
        # (the early SLAM-vs-gyro decision) applies when its factor is made (``_slam_factor``).
        q_stored = q
        if self._slam_conv == "inverse":
            q = q * _CONJ
        if self._first_slam_t is None:
            self._first_slam_t = float(ev.t)
        sess = int(ev.session)
        s = self.sessions.get(sess)
        if s is None:
            s = self.sessions[sess] = _Session(
                [], [], [], float(ev.t), {}, prov_factors=[], index=len(self.sessions)
            )
        s.t.append(float(ev.t))
        s.p.append(p)
        s.q.append(q)
        horizon = self._t_imu_last - self.options.history_s
        while len(s.t) > 2 and s.t[0] < horizon:
            del s.t[0], s.p[0], s.q[0]
        payload = (sess, len(s.t) - 1, float(ev.t), p, q_stored)
        if self.t0 is None:
            # Kept in the session for the alignment fit; attached or counted at the start.
            self._slam_prestart.append((float(ev.t), payload))
            return
        self._take_slam(float(ev.t), payload)

    def _take_slam(self, t: float, payload: tuple) -> None:
        """A SLAM pose waits for its keyframe, or is counted when taken before the start."""
        if t < self.t0 - 0.5 * self.period:
            self._drop("slam:before-start")
            return
        self._slam_wait.append((t, payload))

    def _slam_check(self, t: float, q: np.ndarray, session: int, p: np.ndarray) -> None:
        """Feed the causal SLAM-vs-gyro check; act on its decision once (rotation convention,
        ``body_T_cam`` rotation, clock offset: said in one line each and in ``info``). A
        decision naming the inverse convention or a wrong ``body_T_cam`` rotation is first
        tested for a mirrored SLAM frame (``graph.slam_mirror = "auto"``, :meth:`_mirror_test`)."""
        sgc = self._sgc
        sgc.add_slam(t, q, session, p)
        if self._sgc_first is None:
            self._sgc_first = t
        elapsed = t - self._sgc_first
        if elapsed > SLAM_CHECK_GROWTH_AFTER_S:
            # An undecided check's attempts (and the early misfit's) spaced by a tenth of the
            # SLAM time so far: each fits the newest SLAM_CHECK_WINDOW_S.
            sgc.retry_s = max(1.0, 0.1 * elapsed)
        d = sgc.decision()
        if (
            d is not None
            and self._slam_conv is None
            and self.go.slam_mirror == "auto"
            and (d.convention == "inverse" or not d.body_R_cam_ok)
        ):
            d = self._mirror_test(sgc, d, t, at_decision=True)
        if d is None:
            self._suspect_extrinsic(t)
            if elapsed > self.options.slam_check_max_s:
                log.warning(
                    "%s: SLAM-vs-gyro check undecided after %.0f s of SLAM (too little "
                    "rotation): SLAM rotations taken as stated, not used as factors",
                    self.name,
                    self.options.slam_check_max_s,
                )
                self._sgc = None
                self._slam_conv = "undecided"
            return
        self._sgc = None
        adopt = self._slam_conv is None
        if adopt:
            self._slam_conv = d.convention
        if self.go.slam_time_offset == "apply" and d.time_offset_ok:
            self._slam_offset = float(d.time_offset_s)
            log.info(
                "%s: SLAM clock offset %+.4f s applied from t=%.2f s", self.name, d.time_offset_s, t
            )
        self.slam_check = {
            **({"mirrored": self._mirror_named} if self._mirror is not None else {}),
            "t": t,
            "convention": d.convention,
            "residual_deg": d.residual_deg,
            "body_R_cam_ok": bool(d.body_R_cam_ok),
            "body_R_cam_error_deg": float(d.body_R_cam_error_deg),
            "time_offset_s": float(d.time_offset_s),
            "time_offset_ok": d.time_offset_ok,
            "gyro_bias": np.asarray(d.gyro_bias).tolist(),
            "axis_spread": float(d.axis_spread),
        }
        if adopt and d.convention == "inverse":
            log.warning(
                "%s: SLAM rotations are the inverse of the stated slam_R_cam (gyro residual "
                "%.2f deg inverted vs %.2f deg as stated, decided %s): using them "
                "inverted",
                self.name,
                d.residual_deg.get("inverse", float("nan")),
                d.residual_deg.get("as-is", float("nan")),
                self._when(t),
            )
            for s in self.sessions.values():
                s.q = [qq * _CONJ for qq in s.q]
        else:
            log.info(
                "%s: SLAM rotation convention as stated (decided %s)", self.name, self._when(t)
            )
        if not d.body_R_cam_ok:
            replace = self.go.slam_extrinsic == "auto"
            log.warning(
                "%s: body_T_cam rotation is %.1f deg from the one the gyro fits: check the "
                "calibration%s",
                self.name,
                d.body_R_cam_error_deg,
                "; using the fitted rotation from here (slam_extrinsic = 'auto')"
                if replace
                else "",
            )
            self.slam_check["body_R_cam_replaced"] = replace
            if replace:
                # Used by every SLAM factor and alignment fit made from now on (the position
                # factors made before see only the translation, which is kept).
                self.body_T_cam = make_pose(d.body_R_cam_fit, self.body_T_cam[:3, 3])
                # A provisional alignment seeded through the old rotation is seeded anew.
                for s in self.sessions.values():
                    s.reseed_now = s.provisional is not None and not s.reseeded
        from fgnav.datasets.slam_gyro import MIN_AXIS_SPREAD

        if d.axis_spread >= MIN_AXIS_SPREAD and (
            d.body_R_cam_ok or self.slam_check.get("body_R_cam_replaced")
        ):
            # Two axes turned: the rotations themselves have verified body_R_cam (or replaced
            # it) and the convention; the orientation check, which leans on the positions and a
            # motion fit that a SLAM clock offset also bends, has nothing left to find.
            self._orient_verdict = "verified"
        elif self._orient_verdict == "contradicted" and self.slam_check.get("body_R_cam_replaced"):
            # The orientations through the fitted rotation are checked anew.
            self._orient_verdict, self._orient_next = None, -math.inf

    def _mirror_test(self, sgc, d, t: float, at_decision: bool = False):
        """:meth:`SlamGyroCheck.mirror_verdict` on what has arrived: a mirrored frame whose axis
        is identified is un-mirrored from this pose on (and the decision made again on the
        un-mirrored rotations); one whose axis is not leaves the SLAM unused from here. One
        warning line says which. Inconclusive at the decision (too little motion for the
        positions to tell: simulated two-turns' x flip at 10 s): the check is kept and the test
        repeated every ``MIRROR_RETEST_S`` of SLAM for ``MIRROR_RETEST_FOR_S``
        (:meth:`_mirror_retest`). Returns the decision to act on."""
        v = sgc.mirror_verdict()
        if v is None or not v.conclusive:
            if at_decision:
                self._mirror_sgc = sgc
                self._mirror_next, self._mirror_until = t + MIRROR_RETEST_S, t + MIRROR_RETEST_FOR_S
            return d
        self._mirror_sgc = None
        if not v.mirrored:
            return d
        from fgnav.datasets.slam_gyro import check_slam_gyro, mirror_rotations

        axis = None if v.axis is None else "xyz"[v.axis]
        self._mirror_named = {"axis": axis, "message": v.message(), "t": t}
        if v.axis is None:
            log.warning("%s: %s at t=%.2f s: SLAM not used from here", self.name, v.message(), t)
            self._mirror = "off"
            return d
        log.warning(
            "%s: %s at t=%.2f s: un-mirrored from here (slam_mirror = 'auto')",
            self.name,
            v.message(),
            t,
        )
        self._mirror = v.axis
        R = mirror_rotations(quat_wxyz_to_matrix(np.asarray(sgc._slam_q).reshape(-1, 4)), v.axis)
        d2 = check_slam_gyro(
            np.asarray(sgc._imu_t),
            np.asarray(sgc._imu_w).reshape(-1, 3),
            np.asarray(sgc._slam_t),
            matrix_to_quat_wxyz(R),
            sgc.body_R_cam,
            np.asarray(sgc._slam_s),
            sgc.options,
            force=True,
        )
        return d2 if d2 is not None and d2.decided else d

    def _mirror_retest(self, t: float, q: np.ndarray, session: int, p: np.ndarray) -> None:
        """After a decision that named the inverse convention or a wrong ``body_T_cam`` rotation
        with the mirror test inconclusive: the test again, rate-limited; a mirror found now is
        un-mirrored from this pose on with the rotation convention and ``body_T_cam`` rotation
        the un-mirrored rotations fit (the given one when it fits), and named."""
        sgc = self._mirror_sgc
        sgc.add_slam(t, q, session, p)
        if t < self._mirror_next:
            return
        if t > self._mirror_until:
            self._mirror_sgc = None
            return
        self._mirror_next = t + MIRROR_RETEST_S
        d = self._mirror_test(sgc, None, t)
        if self._mirror is None:
            return
        self._orient_verdict, self._orient_next = None, -math.inf
        if d is not None:
            self._slam_conv = d.convention
            X = (
                d.body_R_cam_fit
                if not d.body_R_cam_ok and self.go.slam_extrinsic == "auto"
                else None
            )
            given = np.asarray(self.calib.body_T_cam, float)
            self.body_T_cam = make_pose(given[:3, :3] if X is None else X, given[:3, 3])
            self.slam_check.update(
                convention=d.convention,
                residual_deg=d.residual_deg,
                body_R_cam_ok=bool(d.body_R_cam_ok),
                body_R_cam_error_deg=float(d.body_R_cam_error_deg),
            )
        self.slam_check["mirrored"] = self._mirror_named
        if self._health_on and self._health_checked:  # (else said from slam_check)
            m = self._mirror_named
            self._health.detectors.named(
                "slam-mirrored",
                m["message"].removeprefix("slam-mirrored: ")
                + (f": un-mirrored from t={t:.2f} s" if m["axis"] else ": SLAM not used"),
            )

    def _camera_ready(self, ev: ImageFrame) -> bool:
        """Set up the homography VO stage at the first image (False: images not used, counted).
        On when ``graph.use_homography`` is not False, the rangefinder is used (the metric
        height), and intrinsics are known (calibration or the frame)."""
        if self._vo is not None:
            return True
        if self._vo_off:
            return False
        go = self.go
        cam = self.calib.camera if self.calib.camera is not None else ev.camera
        why = None
        if go.use_homography is False:
            why = "images:off"
        elif not go.use_range:
            why = "images:no-range-for-height"
        elif cam is None:
            why = "images:no-intrinsics"
        if why:
            self._vo_off = why
            return False
        from fgnav.frontends.homography_vo import HomographyVoStage
        from fgnav.solvers.vision import homography_options

        self._hopts = homography_options(go.homography)
        stage = VoProcess if self.options.vo_worker == "process" else HomographyVoStage
        self._vo = stage(
            self.calib, cam, self._hopts.vo, uses_attitude=True, name=self.name, keep_history=False
        )
        self._cam_K = np.asarray(cam.K, float)
        self._image_size = (int(cam.width), int(cam.height))
        self._anchors_on = True
        return True

    def _on_image(self, ev: ImageFrame) -> None:
        """A camera frame: an anchor for the keyframe at its time, and a frame for the
        homography VO stage (run here, inside the online loop), whose gated pairs become
        homography factors between the keyframes at their frames' times (chains across frames
        without a keyframe composed)."""
        if not self._camera_ready(ev):
            self._drop(self._vo_off)
            return
        img, cam = ev.image, ev.camera if ev.camera is not None else self.calib.camera
        if img is not None and (
            np.ndim(img) not in (2, 3)
            or (cam is not None and tuple(np.shape(img)[:2]) != (cam.height, cam.width))
        ):
            # Not a frame of this camera (empty, or another size): the VO stage raised on it,
            # in the event loop or its process.
            self._drop("images:bad-frame")
            return
        self._anchors.append(float(ev.t))
        if self.t0 is None:
            self._drop("images:before-start")
            return
        R, h = self._frame_inputs(float(ev.t))
        if isinstance(self._vo, VoProcess):
            if len(self._vo) >= VO_MAX_IN_FLIGHT:
                # Frames without keyframe updates (an IMU that stopped before the camera): take
                # the oldest now, or the pipes would fill both ways and block both processes.
                self._vo_take(self._vo.take())
            self._vo.submit(ev, R, h)  # taken at the update after this frame's keyframe
            return
        self._vo_take(self._vo.process(ev, R, h))

    def _vo_collect(self, t_max: float) -> None:
        """Take the VO process's measurements of the frames up to ``t_max``, in order (waits for
        them: which frames are taken depends on ``t_max`` only, not on the child's timing)."""
        vo = self._vo
        if not isinstance(vo, VoProcess):
            return
        while (t := vo.oldest_time()) is not None and t <= t_max:
            self._vo_take(vo.take())

    def _vo_take(self, m) -> None:
        """A VO measurement: gated into a link of :meth:`_homography_factors`."""
        self.vo_busy_s = self._vo.busy_s
        if m is None:
            return
        from fgnav.solvers.vision import gate_measurement

        reason = gate_measurement(m, self._image_size, self._hopts)
        if reason:
            self._drop(f"homography:{reason}")
            self._vo_links.append((m.t_i, m.t_j, None, 0, 0.0))
            return
        self._vo_links.append(
            (m.t_i, m.t_j, np.asarray(m.H, float), int(m.num_inliers), float(m.inlier_rms_px))
        )

    def _frame_inputs(self, t: float) -> tuple[np.ndarray, float | None]:
        """Attitude and body height above the ground at ``t`` for the VO's rectification and
        metric scale, from what has arrived: the attitude stream, else the newest keyframe
        estimate carried by the gyro; the newest range reading (tilted, with the lever arm),
        else the newest estimate's height over the ground estimate."""
        R = self._attitude_at(t)
        if R is None:
            pose = self.values[X(self.k)]
            dt = t - self.t_kf[self.k]
            i = self.imu.nearest(t)
            w = self.values[B(self.k)].correctGyroscope(self.imu.w[i])
            R = pose.rotation().matrix() @ gtsam.Rot3.Expmap(w * dt).matrix()
        h = None
        rng = self._scalar["range"]
        if rng and abs(rng[-1][0] - t) <= 0.2:
            h = self._body_height(rng[-1][1], R)
        else:
            gkeys = [k for k in self.values if _chr(k) == "g"]
            if gkeys:
                z = float(self.values[X(self.k)].translation()[2])
                h = z - float(np.asarray(self.values[max(gkeys)])[0])
        return R, h

    def _kf_at(self, t: float) -> int | None:
        """The kept keyframe at ``t`` (within the homography options' frame tolerance)."""
        if not self._kf_index:
            return None
        k = self._kf_near(t)
        return k if abs(self.t_kf[k] - t) <= self._hopts.frame_tolerance_s else None

    def _homography_factors(self, g, stamps) -> None:
        """Turn the VO links whose frames have keyframes into factors (see :meth:`_on_image`)."""
        from fgnav.factors.homography_motion import make_homography_factor

        t_new = self.t_kf[self.k]
        tol = self._hopts.frame_tolerance_s
        o = self._hopts
        # VO process: the frames up to ``vo_process_delay_keyframes`` keyframes back (the newer
        # ones are still tracked while this update runs; they attach at a later one).
        self._vo_collect(
            self.t_kf.get(self.k - self.options.vo_process_delay_keyframes, -math.inf) + tol
        )
        while self._vo_links and self._vo_links[0][1] <= t_new + tol:
            t_i, t_j, H, n_in, rms = self._vo_links.popleft()
            ch = self._hchain
            if H is None:
                self._hchain = None
                continue
            if ch is None or abs(ch[1] - t_i) > tol:
                ki = self._kf_at(t_i)
                if ki is None:
                    self._drop("homography:no-keyframe")
                    self._hchain = None
                    continue
                ch = [ki, t_i, np.eye(3), 10**9, 0.0, 0]
            ch[1], ch[2] = t_j, H @ ch[2]
            ch[3], ch[4], ch[5] = min(ch[3], n_in), ch[4] + rms**2, ch[5] + 1
            self._hchain = ch
            kj = self._kf_at(t_j)
            if kj is None or kj == ch[0]:
                continue
            ki = ch[0]
            self._hchain = [kj, t_j, np.eye(3), 10**9, 0.0, 0]
            if not (self._kf_alive(ki) and self._kf_alive(kj)):
                self._drop("homography:late")
                continue
            gk = self._slow_key_at("g", self.go.ground_segment_s, ki)
            if gk not in self.values or not self._alive(gk):
                self._drop("homography:late")
                continue
            sigma = (
                float(o.corner_sigma_px)
                if o.corner_sigma_px is not None
                else max(o.corner_sigma_floor_px, o.corner_sigma_per_rms * math.sqrt(ch[4]))
            )
            Hc = ch[2] / ch[2][2, 2]
            g.add(
                make_homography_factor(
                    X(ki),
                    X(kj),
                    gk,
                    Hc,
                    self._cam_K,
                    self.body_T_cam,
                    self._image_size,
                    self._robust(gtsam.noiseModel.Isotropic.Sigma(8, sigma)),
                )
            )
            stamps[gk] = t_new
            self._use("homography")

    def _kf_near(self, t: float) -> int:
        """The kept keyframe nearest ``t``."""
        idx = self._kf_index
        i = bisect.bisect_left(idx, t, key=_first)  # (no list of the kept times)
        if i >= len(idx):
            return idx[-1][1]
        if i > 0 and t - idx[i - 1][0] <= idx[i][0] - t:
            return idx[i - 1][1]
        return idx[i][1]

    def _attach_pending(self, g, stamps, remove, prov_new) -> None:
        t_new = self.t_kf[self.k]
        still = []
        for t, payload in self._slam_wait:
            if t > t_new + 1e-9:
                still.append((t, payload))
            else:
                self._pending.append((self._kf_near(t), "slam", payload))
        self._slam_wait = still
        if self._vo is not None:
            self._homography_factors(g, stamps)
        keep = []
        for item in self._pending:
            k, kind, payload = item
            if k > self.k:
                keep.append(item)
                continue
            if not self._kf_alive(k):
                self._drop(f"{kind}:late")
                if kind == "slam":
                    self._warn_late(kind, self.t_kf[self.k] - payload[2])
                continue
            if kind == "slam":
                self._slam_factor(k, payload, g, stamps, remove, prov_new)
            elif kind == "range":
                self._range_factor(k, payload, g, stamps)
            elif kind == "yaw":
                g.add(
                    make_yaw_factor(
                        X(k), float(wrap_angle(payload)), self._noise(1, self.go.yaw_sigma)
                    )
                )
                self._use("yaw")
        self._pending = keep

    def _range_factor(self, k: int, r: float, g, stamps) -> None:
        pose = self.values.get(X(k))
        if pose is None and k in self._pose_hist:
            pose = self._pose_hist[k][1]  # a reading for an older keyframe: its newest estimate
        R = pose.rotation().matrix() if pose is not None else np.eye(3)
        ok, reason = gate_range(
            float(r),
            R,
            self.body_T_range,
            self.calib.range_min,
            self.calib.range_max,
            math.radians(self.go.range_max_tilt_deg),
            self._range_limits.clamps,
        )
        if not ok:
            tag = reason.split(":")[0].split()[0]
            self._drop(f"range:{tag}" if tag in RANGE_LIMIT_TAGS else f"range:gated:{tag}")
            return
        gk = self._slow_key_at("g", self.go.ground_segment_s, k)
        if gk not in self.values or not self._alive(gk):
            self._drop("range:late")
            return
        why = None if pose is None else self._range_gate(float(r), pose, float(self.values[gk][0]))
        if why is not None:
            self._drop(why)
            return
        g.add(
            make_range_factor(
                X(k), gk, float(r), self.body_T_range, self._noise(1, self.go.range_sigma)
            )
        )
        stamps[gk] = self.t_kf[self.k]
        self._use("range")
        self._ground_measured = True

    def _range_gate(self, r: float, pose: gtsam.Pose3, ground: float) -> str | None:
        """The innovation gate of a range reading (None: taken, else why it is dropped): within
        ``range_gate_m`` (or ``RANGE_GATE_REL`` of the reading, if larger) of the range the
        keyframe's current estimate and ground height predict. A run of ``range_gate_run``
        gated readings that agree with each other (their ground heights within the gate) is a
        step in the terrain (or the height gone wrong), not outliers: a new ground epoch starts
        at the next keyframe (``range:terrain-step``), its ground variable from the newest
        readings. A ground seeded without a reading within the limits (a range that starts
        late, or 0 readings below its minimum) that the first one contradicts starts anew the
        same way, unnamed (``range:ground-seeded``): gated against the seed, that reading's
        run was named a terrain step.

        A single wrong reading, through the robust kernel's one Gauss-Newton step per update,
        moved the window: simulated two-turns (seed 1; the first range reading, at the start,
        1.81 m against 3.45) put the third keyframe 30 cm high at 3 m/s."""
        o = self.options
        if o.range_gate_m <= 0:
            return None
        t_k = self.t_kf[self.k]
        # The innovation along the beam: the reading's ground against the estimate's, over the
        # beam's cosine (floored as the factor does).
        seen = self._reading_ground(r, pose)
        beam_z = float((pose.rotation().matrix() @ self.body_T_range[:3, 2])[2])
        e = (seen - ground) / max(-beam_z, MIN_COS_TILT)
        gate = max(o.range_gate_m, RANGE_GATE_REL * r)
        # After a pause of the range (above its limits or without readings; refused readings
        # are no pause) the height may have drifted: the reading is taken, the robust kernel
        # weighs it. A pause counted from the last *taken* reading cut every run of refused
        # readings longer than RANGE_GATE_FRESH_S: at 5 Hz keyframes no step was ever found.
        seeded = self._range_seen_t > -math.inf
        fresh = t_k - self._range_seen_t > RANGE_GATE_FRESH_S
        self._range_seen_t = t_k
        if abs(e) <= gate or (fresh and seeded):
            self._range_run.clear()
            return None
        if not seeded:
            self._g_epochs.append((self.k + 1, len(self._g_epochs) + 1))
            return "range:ground-seeded"
        run = self._range_run
        run.append(seen)
        if len(run) < o.range_gate_run:
            return "range:outlier"
        grounds = list(run)[-o.range_gate_run :]
        if max(grounds) - min(grounds) > gate:
            return "range:outlier"
        run.clear()
        # The readings agree with each other, not with the ground: a step in the terrain (or
        # the height gone wrong). The ground variable starts anew from the next keyframe, from
        # the newest readings (the old one's walk would take minutes to follow).
        self._g_epochs.append((self.k + 1, len(self._g_epochs) + 1))
        self._use("range:terrain-step")
        detail = (
            f"the ground under the rangefinder steps by {float(np.median(grounds)) - ground:+.2f} "
            f"m ({o.range_gate_run} readings agree): the ground height starts anew at "
            f"t={self.t_kf[self.k]:.2f} s"
        )
        if getattr(self, "_health", None) is not None and self._health.options.enabled:
            self._health.detectors.named("terrain-step", detail)  # said there, once
        else:
            log.info("%s: %s", self.name, detail)
        return "range:outlier"

    def _suspect_extrinsic(self, t: float) -> None:
        """Before the check decides: a stated ``body_R_cam`` that maps the SLAM's rotations far
        from the gyro's (:meth:`SlamGyroCheck.stated_misfit` above
        ``SLAM_EXTRINSIC_SUSPECT_MISFIT``) is named, once, in a warning and in
        ``info["slam_extrinsic_suspect"]``: with one excited axis, 1-3 s into a flight, where
        the check needs two (simulated rectangle's yaw-only turns: never). The provisional
        alignment seeded through it is then re-seeded from the motion
        (:meth:`_reseed_provisional`); withdrawing it instead left EuRoC MH_01 with an identity
        rotation IMU-only for 3 s (5.1 -> 55 cm). A right rotation with a SLAM clock 0.3 s off
        reads about 0.5 (simulated rectangle and circle): named, but the re-seed keeps a
        provisional whose rotation the motion confirms."""
        if self._extrinsic_suspect is not None or t - self._misfit_try < max(
            SLAM_MISFIT_RETRY_S, self._sgc.retry_s
        ):
            return
        self._misfit_try = t
        m = self._sgc.stated_misfit()
        if m is None or not m > SLAM_EXTRINSIC_SUSPECT_MISFIT:
            return
        self._extrinsic_suspect = {"t": t, "misfit": m}
        log.warning(
            "%s: SLAM rotations do not fit the gyro through the given body_T_cam rotation "
            "(misfit %.2f of the rotation, right ones give < 0.15) at t=%.2f s: a wrong "
            "rotation, or a SLAM clock offset of some 0.3 s or more (the SLAM-vs-gyro check "
            "tells them apart once two axes have turned)",
            self.name,
            m,
            t,
        )

    def _slam_factor(self, k, payload, g, stamps, remove, prov_new) -> None:
        sess, row, t, p, q = payload
        s = self.sessions[sess]
        if self._axis:
            self._axis_factor(k, payload, s, g, stamps)
            return
        key = self._session_key(sess, s, t, g, stamps, remove, prov_new)
        if key is None:
            self._held.append((k, "slam", payload))
            return
        if s.lone_hold and key == s.provisional and self._lone_hold(sess, s, k, payload, prov_new):
            return
        scale = self._scale_guess(key)
        noise = self._noise(3, self.go.slam_sigma_m * scale)
        dt = t - self.t_kf[k]
        if abs(dt) < 1e-6:
            fac = make_slam_position_factor(X(k), key, p, self.body_T_cam, noise)
        else:
            i = self.imu.nearest(t)
            b = self.values[B(self.k)]
            fac = make_slam_position_offset_factor(
                X(k),
                V(k),
                key,
                p,
                self.body_T_cam,
                dt,
                b.correctAccelerometer(self.imu.a[i]),
                b.correctGyroscope(self.imu.w[i]),
                self.go.gravity,
                noise,
            )
        # A pose re-attached from a provisional alignment (row -2) keeps the rotation factor it
        # was given there: the provisional's rotation then ties the poses' orientations together.
        conv = self._slam_conv
        rot = (
            row != -2
            and self.go.use_slam_rotation is not False
            and conv in ("as-is", "inverse")
            and self._orient_verdict != "contradicted"
        )
        if s.provisional is not None and key == s.provisional:
            # (a row -2 pose re-attached to a new provisional has its rotation factor already)
            prov_new.append((g.size(), sess, (k, t, p, q, rot or row == -2, rot)))
        g.add(fac)
        stamps[key] = self.t_kf[self.k]
        # A provisional pose moved onto the new chain (row < 0) was counted when it first attached.
        self._use("slam" if row >= 0 else "slam:reattached")
        if rot:
            # The camera orientation carried back to the keyframe with the gyro:
            # slam_R_cam(t_k) = slam_R_cam(t) body_R_cam^T Exp(-omega dt) body_R_cam.
            R_meas = quat_wxyz_to_matrix(q * _CONJ if conv == "inverse" else q)
            if abs(dt) >= 1e-6:
                i = self.imu.nearest(t)
                w = self.values[B(self.k)].correctGyroscope(self.imu.w[i])
                bRc = self.body_T_cam[:3, :3]
                R_meas = R_meas @ bRc.T @ gtsam.Rot3.Expmap(-w * dt).matrix() @ bRc
            g.add(
                make_slam_rotation_factor(
                    X(k), key, R_meas, self.body_T_cam, self._noise(3, self.go.slam_rot_sigma)
                )
            )
            self._use("slam-rotation")

    def _lone_hold(self, sess, s: _Session, k: int, payload, prov_new) -> bool:
        """True: the pose is held (the provisional alignment's second, more than
        ``slam_provisional_lone_gap_s`` after its first, while the scale is the default). The
        third pose releases it; both then attach together.

        One displacement cannot tell the scale from the velocity (and the tilt) since the
        start: the window's optimum moves both. Over a long displacement a default scale far
        from the truth pulls the states by the displacement times the scale's error (EuRoC
        V1_02 ORB-SLAM2 keyframes: second pose 1.1 s after the first, true scale 0.44 against
        the default 1: 0.3-0.6 m for the 0.45 s until the third pose); at 20 Hz (MH_01) the
        pull is millimetres and nothing waits."""
        t = payload[2]
        if s.lone_waiting:
            # The third: the held second attaches with it (appended to the pending list being
            # attached).
            s.lone_hold = s.lone_waiting = False
            self._release_held(sess)
            return False
        first = [row[1] for _, row in s.prov_factors] + [
            r[1] for _, ss, r in prov_new if ss == sess
        ]
        if len(first) == 1 and t - first[0] > self.options.slam_provisional_lone_gap_s:
            s.lone_waiting = True
            self._held.append((k, "slam", payload))
            log.info(
                "%s: SLAM session %d: the second pose, %.2f s after the first, waits for the "
                "third (the scale is still the default)",
                self.name,
                sess,
                t - first[0],
            )
            return True
        if len(first) >= 1:
            s.lone_hold = False  # the second came soon after the first
        return False

    def _scale_guess(self, key: int) -> float:
        v = self.values.get(key)
        if v is None:
            return 1.0
        return float(np.max(v[:3])) if isinstance(v, np.ndarray) else float(v.scale())

    # ------------------------------------------------------------------------------------------
    # Seed 000's per-axis SLAM model: one chain of Vector6 [kx, ky, kz, ox, oy, oz] segments
    # ------------------------------------------------------------------------------------------

    def _axis_factor(self, k: int, payload, s: _Session, g, stamps) -> None:
        """A SLAM position under the per-axis model (held until the per-axis fit exists)."""
        _sess, _row, t, p, _q = payload
        key = self._axis_key(_sess, s, t, g, stamps)
        if key is None:
            self._held.append((k, "slam", payload))
            return
        noise = self._noise(3, self.go.slam_sigma_m * self._scale_guess(key))
        dt = t - self.t_kf[k]
        i = self.imu.nearest(t)
        b = self.values[B(self.k)]
        g.add(
            make_slam_axis_position_offset_factor(
                X(k),
                V(k),
                key,
                p,
                self.body_T_cam[:3, 3],
                dt,
                b.correctAccelerometer(self.imu.a[i]) if abs(dt) >= 1e-6 else np.zeros(3),
                b.correctGyroscope(self.imu.w[i]) if abs(dt) >= 1e-6 else np.zeros(3),
                self.go.gravity,
                noise,
            )
        )
        stamps[key] = self.t_kf[self.k]
        self._use("slam")

    def _axis_key(self, sess: int, s: _Session, t: float, g, stamps) -> int | None:
        """The per-axis alignment variable of a pose at ``t`` (None until the fit exists)."""
        o, go = self.options, self.go
        if not s.chain and sess in self._carried_align:
            return self._carried_chain(sess, s, t, g, stamps)
        if not s.chain:
            t_now = self.t_kf[self.k]
            if not (t_now >= s.next_fit and s.t[-1] - s.t[0] >= o.slam_init_window_s):
                return None
            s.next_fit = t_now + 0.5
            fit = self._fit_axis(s)
            if fit is None:
                return None
            self._start_axis_chain(s, t, *fit, g, stamps)
            return s.last_key
        seg, key, known = self._segment(s, t)
        if known is not None:
            return known
        prev = s.last_key
        a = np.asarray(self.values[prev], float)
        walk = math.sqrt(go.slam_segment_s * (seg - s.last_seg))
        k_max = float(np.max(a[:3]))
        # Relative random walk of every axis and an origin walk of _trans_rw metres (the
        # batch's per-axis chain, GraphBuilder.slow_factors).
        rw = np.r_[self._scale_rw * walk * np.abs(a[:3]), [self._trans_rw * walk * k_max] * 3]
        if self._alive(prev):
            g.add(
                gtsam.BetweenFactorVector(
                    prev, key, np.zeros(6), gtsam.noiseModel.Diagonal.Sigmas(rw)
                )
            )
        else:
            # The predecessor left the window: its last estimate, widened by the walk.
            base = np.r_[0.01 * np.abs(a[:3]), [0.05 * k_max] * 3]
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.hypot(base, rw))
            g.add(gtsam.PriorFactorVector(key, a, noise))
            self.used["slam:segments-after-gap"] = self.used.get("slam:segments-after-gap", 0) + 1
        self._add_to_chain(s, seg, key, a, g, stamps)
        return key

    def _fit_axis(self, s: _Session) -> tuple[np.ndarray, np.ndarray, int] | None:
        """Per-axis scale ``(k, rel_se, n_pairs)`` from the arrived SLAM positions and IMU
        (:func:`fgnav.solvers.measurements.fit_axis_scale`), or None (gates not passed: pairs,
        and the best-determined axis's relative standard error)."""
        o = self.options
        if not self.imu.t:
            return None
        t_all = np.asarray(s.t)
        keep = (t_all >= self.imu.t[0] + SLAM_FIT_IMU_MARGIN_S) & (t_all <= self.imu.t[-1])
        keep &= t_all >= t_all[-1] - o.slam_fit_max_s
        if keep.sum() < 8:
            return None
        t = t_all[keep]
        margin = SLAM_FIT_IMU_MARGIN_S
        imu = self.imu.series(t[0] - margin, t[-1] + margin)
        R = self._attitude_track(imu.t) if imu is not None else None
        if R is None:
            return None
        try:
            k, rel_se, n = fit_axis_scale(
                t, np.asarray(s.p)[keep], imu.t, world_specific_accel(imu, R, self.go.gravity)
            )
        except FlightDataError:
            return None
        if n < o.slam_init_min_pairs or not np.min(rel_se) <= o.slam_init_max_rel_se:
            return None
        return k, rel_se, n

    def _start_axis_chain(self, s: _Session, t: float, k, rel_se, n: int, g, stamps) -> None:
        """The chain's first variable: the fitted scales and the origin that maps the newest
        SLAM position onto the current estimate of its keyframe, under a prior (each axis's
        relative sigma the fit's, at least ``slam_init_scale_sigma_rel``, at most 50 % for an
        axis the fit does not determine; the origin free)."""
        o = self.options
        seg, key = self._segment_key(s, t)
        a = np.r_[k, s.p[-1] - k * self._cam_at(s.t[-1])]
        rel = np.minimum(np.maximum(o.slam_init_scale_sigma_rel, rel_se), WEAK_SCALE_PRIOR_REL)
        sig = np.r_[rel * k, [10.0 * float(np.max(k))] * 3]
        g.add(gtsam.PriorFactorVector(key, a, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        self._add_to_chain(s, seg, key, a, g, stamps)
        log.info(
            "%s: per-axis SLAM scale at t=%.2f s: %s (rel. s.e. %s, %d pairs)",
            self.name,
            t,
            np.round(k, 4).tolist(),
            np.round(rel_se, 3).tolist(),
            n,
        )
        self._release_held()

    def _session_key(self, sess, s: _Session, t, g, stamps, remove, prov_new) -> int:
        """The alignment variable of a pose at time ``t`` of session ``sess`` (created here)."""
        o, go = self.options, self.go
        t_now = self.t_kf[self.k]
        if not s.chain and sess in self._carried_align:
            return self._carried_chain(sess, s, t, g, stamps)
        if not s.chain:
            if t_now >= s.next_fit and s.t[-1] - s.t[0] >= o.slam_init_window_s:
                s.next_fit = t_now + 0.5
                fit = self._fit(s)
                if fit is not None:
                    self._start_chain(sess, s, t, fit, g, stamps, remove, prov_new)
            if not s.chain:
                if not o.slam_provisional:
                    return None  # held back until the fit
                self._renew_provisional(sess, s)
                self._units_check(sess, s, remove)
                self._reseed_provisional(sess, s, t_now, remove)
                if s.provisional is None and not self._start_provisional(sess, s, g, stamps):
                    return None  # held back until the data gives the provisional scale
                return s.provisional
        seg, key, known = self._segment(s, t)
        if known is not None:
            return known
        prev = s.last_key
        value = self.values[prev]
        n_seg = seg - s.last_seg
        walk = math.sqrt(go.slam_segment_s * n_seg)
        rw = np.array([go.slam_rot_rw] * 3 + [self._trans_rw] * 3 + [self._scale_rw]) * walk
        if self._alive(prev):
            g.add(
                gtsam.BetweenFactorSimilarity3(
                    prev, key, gtsam.Similarity3(), gtsam.noiseModel.Diagonal.Sigmas(rw)
                )
            )
        else:
            # The predecessor left the window (a pause longer than the lag): its last estimate,
            # widened by the walk over the gap. Its origin's own uncertainty is the position
            # gauge the window's states share (``FixedLagOptions.slam_gap_origin_sigma_m``).
            base = np.r_[[GAP_SEGMENT_ROT_SIGMA] * 3, [o.slam_gap_origin_sigma_m] * 3, [0.01]]
            sig = np.maximum(np.hypot(base, rw), MIN_GAP_SEGMENT_SIGMA)
            g.add(gtsam.PriorFactorSimilarity3(key, value, gtsam.noiseModel.Diagonal.Sigmas(sig)))
            self.used["slam:segments-after-gap"] = self.used.get("slam:segments-after-gap", 0) + 1
        self._add_to_chain(s, seg, key, value, g, stamps)
        if s.carried and t_now - self.t0 < o.startup_qr_s:
            self.smoother.hold_linearization([key])  # see _carried_chain
        return key

    def _segment(self, s: _Session, t: float) -> tuple[int, int, int | None]:
        """The alignment segment of a pose at ``t``, its key (:meth:`_segment_key`) and its
        existing variable (None: a new segment after the newest). An older segment than the
        newest (a late pose) has no variable of its own: the newest one takes it."""
        seg, key = self._segment_key(s, t)
        if seg in s.chain:
            return seg, key, s.chain[seg]
        if seg < s.last_seg:
            return seg, key, s.chain[s.last_seg]
        return seg, key, None

    def _segment_key(self, s: _Session, t: float) -> tuple[int, int]:
        """The alignment segment of session ``s`` at ``t`` (``slam_segment_s`` steps from the
        session's first pose) and its variable's key."""
        seg = int((t - s.t_first) / self.go.slam_segment_s + 1e-9)
        return seg, S(s.index * SESSION_STRIDE + seg)

    def _add_to_chain(self, s: _Session, seg: int, key: int, value: Any, g, stamps) -> None:
        """Insert the new alignment variable ``key`` of segment ``seg``, the session's newest."""
        self._insert(key, value, g, stamps)
        s.chain[seg] = key
        s.last_key, s.last_seg = key, seg

    def _insert(self, key: int, value: Any, g, stamps) -> None:
        self._queued_values.insert(key, value)
        stamps[key] = self.t_kf[self.k]
        self.values[key] = value

    def _fit(self, s: _Session):
        """Closed-form alignment over the session's arrived poses, or None (gates not passed)."""
        inputs = self._fit_inputs(s)
        if inputs is None:
            return None
        t, p, q, imu, R = inputs
        # The fit's SLAM-frame rotation comes from the SLAM orientations: while the convention
        # check has not decided, try both conventions and keep the better fit (the wrong one
        # rotates the accelerations away from the SLAM motion: a poor fit).
        orient_bad = self._orient_verdict == "contradicted"
        fit = None if orient_bad else self._best_fit(t, p, q, imu, R, "orientations")
        if fit is not None:
            log.debug(
                "%s: SLAM fit over %.1f s: scale %.4f, excitation %.3f m, rel. s.e. %.3f",
                self.name,
                t[-1] - t[0],
                fit.scale,
                fit.excitation,
                fit.scale_rel_se,
            )
        alt = None
        if orient_bad or self._orient_verdict is None or self._sgc is not None:
            alt = self._best_fit(*inputs, "motion")
        if not orient_bad and self._orient_verdict is None:
            angle = self._motion_dominates(alt, fit)
            if angle is not None:
                self._orient_contradicted(s, alt, fit, angle, t[-1])
                orient_bad = True
        if orient_bad:
            ok = self._motion_fit_usable(alt)
            if ok:
                self._use("slam:fit-rotation-from-motion")
            return alt if ok else None
        if self._sgc is not None:
            fit = self._fit_unverified_extrinsic(fit, alt)
        return fit if self._fit_passes(fit) else None

    def _best_fit(self, t, p, q, imu, R, rotation: str):
        """:func:`init_slam_alignment` with the decided convention, or while undecided the
        better of the two (scale rel. s.e.; for ``rotation="motion"`` the stated one unless the
        inverse's is under half of it: turns about one axis fit both conventions' rotation
        increments, and the wrong one's rotation came out 179 deg off on simulated rectangle);
        None when neither gives a positive scale."""
        convs = [q] if self._slam_conv in ("as-is", "inverse") else [q, q * _CONJ]
        margin = SLAM_MOTION_INVERSE_RATIO if rotation == "motion" else 1.0
        fit = None
        for qq in convs:
            slam = SlamSeries(t, p, qq, np.zeros(len(t), dtype=int))
            try:
                f = init_slam_alignment(
                    slam, imu, R, self.body_T_cam, self.go.gravity, rotation=rotation
                )
            except FlightDataError:
                continue
            if fit is None or f.scale_rel_se < margin * fit.scale_rel_se:
                fit = f
        return fit

    def _fit_inputs(self, s: _Session):
        """``(t, p, q, imu, world_R_body at the IMU times)`` of the session's arrived poses the
        IMU history covers with the second differences' margin, or None."""
        t_all = np.asarray(s.t)
        if not self.imu.t:
            return None
        # Poses the IMU history covers with the second differences' margin.
        t_min = self.imu.t[0]
        if len(self._att) < 2 and self._pose_hist:
            t_min = max(t_min, self._pose_hist[min(self._pose_hist)][0])
        keep = (t_all >= t_min + SLAM_FIT_IMU_MARGIN_S) & (t_all <= self.imu.t[-1])
        keep &= t_all >= t_all[-1] - self.options.slam_fit_max_s
        if keep.sum() < 8:
            return None
        t = t_all[keep]
        margin = SLAM_FIT_IMU_MARGIN_S
        imu = self.imu.series(t[0] - margin, t[-1] + margin)
        if imu is None:
            return None
        R = self._attitude_track(imu.t)
        if R is None:
            return None
        idx = np.flatnonzero(keep)
        return t, np.asarray(s.p)[idx], np.asarray(s.q)[idx], imu, R

    def _fit_passes(self, fit) -> bool:
        """The closed-form fit passes the gates that start a session's alignment chain."""
        o = self.options
        return (
            fit is not None
            and fit.excitation >= o.slam_init_min_excitation_m
            and fit.scale_rel_se <= o.slam_init_max_rel_se
            and fit.n_pairs >= o.slam_init_min_pairs
        )

    def _motion_fit_usable(self, alt) -> bool:
        """A motion-only fit (``rotation="motion"``) passes the chain's gates and saw two
        directions (``SLAM_FIT_MOTION_MIN_SPREAD``)."""
        return self._fit_passes(alt) and alt.rotation_spread >= SLAM_FIT_MOTION_MIN_SPREAD

    def _motion_fit_ok(self, alt) -> bool:
        """A motion-only fit determines the SLAM rotation: :meth:`_motion_fit_usable` and a
        well-fitted scale (``SLAM_FIT_MOTION_MAX_REL_SE``)."""
        return self._motion_fit_usable(alt) and alt.scale_rel_se <= SLAM_FIT_MOTION_MAX_REL_SE

    def _fit_unverified_extrinsic(self, fit, alt):
        """While the SLAM-vs-gyro check has not verified ``body_R_cam``, the closed-form fit's
        rotation (from the SLAM orientations through ``body_R_cam``) is checked against the one
        the motion alone gives (:func:`init_slam_alignment` ``rotation="motion"``). The motion's
        is used when it passes the chain's gates with acceleration along two axes at least
        (``rotation_spread`` >= ``SLAM_FIT_MOTION_MIN_SPREAD``) and no fit through
        ``body_R_cam`` has a positive scale, or the two differ by more than
        ``SLAM_FIT_ROTATION_MAX_DEG`` and the motion's fits the scale
        ``SLAM_FIT_MOTION_BETTER`` times better (a
        ``body_R_cam`` 90 deg off made the chain start 90 deg off and diverge, or held it back,
        before the check decided). ``alt``: the motion-only fit over the same poses."""
        if not self._motion_fit_ok(alt):
            return fit
        if fit is None:
            why = "gives no positive scale"
        else:
            angle = math.degrees(_norm(so3_log(alt.slam_R_world @ fit.slam_R_world.T)))
            if angle <= SLAM_FIT_ROTATION_MAX_DEG or not (
                SLAM_FIT_MOTION_BETTER * alt.scale_rel_se < fit.scale_rel_se
            ):
                return fit
            why = f"is {angle:.0f} deg off (scale rel. s.e. {fit.scale_rel_se:.3f})"
        if not self._fit_motion_used:
            self._fit_motion_used = True
            log.warning(
                "%s: SLAM alignment: the rotation through body_T_cam %s against the one the "
                "motion fits (scale rel. s.e. %.3f): using the motion's until the SLAM-vs-gyro "
                "check decides",
                self.name,
                why,
                alt.scale_rel_se,
            )
        self._use("slam:fit-rotation-from-motion")
        return alt

    def _motion_dominates(self, alt, fit) -> float | None:
        """The angle [deg] between the motion-only fit ``alt`` and the fit through the SLAM
        orientations ``fit`` when the motion's contradicts it (``SLAM_MOTION_DOMINANT_*``:
        the chain's gates, two directions, a well-fitted scale, far apart and a much better
        fit, or no positive scale through the orientations; ``inf`` then), else None."""
        if not self._motion_fit_usable(alt) or alt.scale_rel_se > SLAM_MOTION_DOMINANT_MAX_REL_SE:
            return None
        if fit is None:
            return math.inf
        angle = math.degrees(_norm(so3_log(alt.slam_R_world @ fit.slam_R_world.T)))
        if angle < SLAM_MOTION_DOMINANT_DEG or not (
            fit.scale_rel_se > SLAM_MOTION_DOMINANT_BETTER * alt.scale_rel_se
        ):
            return None
        return angle

    def _orientation_check(self, t: float) -> None:
        """Do the SLAM orientations, through ``body_R_cam`` and the rotation convention, give
        the alignment rotation the SLAM positions and the IMU's motion give? Once a second, on
        every session's arrived poses (two closed-form fits, :func:`init_slam_alignment` with
        ``rotation="orientations"`` and ``"motion"``), until the motion confirms them (within
        ``SLAM_FIT_ROTATION_MAX_DEG``, its scale rel. s.e. under
        ``SLAM_FIT_MOTION_MAX_REL_SE``) or contradicts them (:meth:`_motion_dominates`, then
        :meth:`_orient_contradicted`). The SLAM-vs-gyro check compares relative rotations
        only: with turns about one axis (a hover's wobble, yaw-only turns) a wrong
        ``body_R_cam`` passes it, or passes as the inverse convention (simulated two-turns with
        an identity ``body_T_cam``), and the alignment seeded through it cannot turn back
        (hover: scale -63 %, nothing named)."""
        if self._orient_verdict is not None or t < self._orient_next or self._axis:
            return
        self._orient_next = t + SLAM_ORIENTATION_CHECK_S
        for s in reversed(list(self.sessions.values())):
            if not s.t or s.t[-1] < t - self.options.lag_s:
                continue  # an ended session (a map reset's predecessor): nothing of it to act on
            inputs = self._fit_inputs(s)
            if inputs is None:
                continue
            alt = self._best_fit(*inputs, "motion")
            if not self._motion_fit_usable(alt):
                continue
            fit = self._best_fit(*inputs, "orientations")
            angle = self._motion_dominates(alt, fit)
            if angle is not None:
                self._orient_contradicted(s, alt, fit, angle, t)
                return
            if fit is not None and self._motion_fit_ok(alt):
                a = math.degrees(_norm(so3_log(alt.slam_R_world @ fit.slam_R_world.T)))
                if a <= SLAM_FIT_ROTATION_MAX_DEG:
                    self._orient_verdict = "consistent"
                    return

    def _orient_contradicted(self, s: _Session, alt, fit, angle: float, t: float) -> None:
        """The SLAM orientations contradict the motion (:meth:`_orientation_check`): named in a
        warning, in ``info["slam_orientation_check"]`` and as the health detector
        ``body_T_cam-rotation``; the orientations are no longer used (no SLAM rotation factors;
        alignment fits from the motion); an alignment already seeded through them far from the
        motion's rotation is re-seeded with the motion's: the provisional one at the next pose
        (:meth:`_reseed_provisional`), a started chain through a rebuild of the window
        (:meth:`_rebuild`, the reset counter rises) with the chain start's wide prior."""
        orient_se = None if fit is None else float(fit.scale_rel_se)
        self._orient_verdict = "contradicted"
        self._orient_found = {
            "t": float(t),
            "angle_deg": None if math.isinf(angle) else round(angle, 1),
            "motion_rel_se": round(float(alt.scale_rel_se), 4),
            "orientation_rel_se": None if orient_se is None else round(orient_se, 4),
            "realigned": False,
        }
        detail = (
            "SLAM orientations through body_T_cam's rotation give an alignment "
            + ("with no positive scale" if fit is None else f"{angle:.0f} deg")
            + " from the one the SLAM positions and the IMU fit (scale rel. s.e. "
            + ("-" if orient_se is None else f"{orient_se:.3f}")
            + f" against {alt.scale_rel_se:.3f}) at t={t:.2f} s: body_T_cam's rotation is wrong "
            "(or the SLAM rotation convention, or a SLAM clock offset of 0.3 s or more); SLAM "
            "orientations no longer used"
        )
        if getattr(self, "_health", None) is not None and self._health.options.enabled:
            self._health.detectors.named("body_T_cam-rotation", detail)  # said there, once
        else:
            log.warning("%s: %s", self.name, detail)
        key = s.last_key
        if key is None:
            if s.provisional is not None:
                s.motion_seed = (alt.slam_R_world, float(alt.scale))
            return
        cur = self.values.get(key)
        if cur is None or not self._alive(key):
            return
        off = math.degrees(_norm(so3_log(alt.slam_R_world @ cur.rotation().matrix().T)))
        if off < SLAM_MOTION_DOMINANT_DEG:
            return
        value = self._align_origin(s, make_slam_T_world(alt.scale, alt.slam_R_world, np.zeros(3)))
        self.values[key] = value
        s.chain = {s.last_seg: key}
        rel = max(self.options.slam_init_scale_sigma_rel, float(alt.scale_rel_se))
        self._orient_found["realigned"] = True
        self._use("slam:realigned-from-motion")
        log.warning(
            "%s: SLAM alignment re-seeded from the motion (%.0f deg turned, scale %.4f -> "
            "%.4f): window rebuilt",
            self.name,
            off,
            float(cur.scale()),
            float(alt.scale),
        )
        # The window's velocity and accelerometer bias were estimated through the wrong
        # alignment: their priors are the start's, not a healthy rebuild's.
        go = self.go
        wide = dataclasses.replace(
            self.options,
            rebuild_vel_sigma=max(self.options.rebuild_vel_sigma, go.prior_velocity_sigma),
            rebuild_accel_bias_sigma=max(
                self.options.rebuild_accel_bias_sigma, go.prior_accel_bias_sigma
            ),
        )
        self._rebuild({}, {key: np.array([0.3, 0.3, 0.3, 10.0, 10.0, 10.0, rel])}, wide)
        if getattr(self, "_health", None) is not None:
            # The kept healthy states hold the old alignment: a recovery must not restore it.
            self._health.discard_snapshots()

    def _attitude_track(self, t: np.ndarray) -> np.ndarray | None:
        """World_R_body at times ``t``: the attitude stream, else the smoother's keyframes."""
        if (
            len(self._att) >= 2
            and self._att[0][0] <= t[0] + 0.1
            and self._att[-1][0] >= t[-1] - 0.1
        ):
            ta = np.array([r[0] for r in self._att])
            qa = np.array([r[1] for r in self._att])
            return slerp_rotations(ta, quat_wxyz_to_matrix(qa), t)
        ks = sorted(self._pose_hist)
        if len(ks) < 2:
            return None
        tk = np.array([self._pose_hist[k][0] for k in ks])
        Rk = np.array([self._pose_hist[k][1].rotation().matrix() for k in ks])
        if tk[0] > t[0] + 0.1:
            return None
        return slerp_rotations(tk, Rk, np.clip(t, tk[0], tk[-1]))

    def _start_chain(self, sess, s: _Session, t, fit, g, stamps, remove, prov_new) -> None:
        o = self.options
        seg, key = self._segment_key(s, t)
        scale, rel = fit.scale, fit.scale_rel_se
        ml = self._ml_scale(sess)
        if ml is not None and sess not in self._scale_prior_done:
            # The ML-scale stage's scale: the initial value, its sigma the prior's.
            scale, rel = ml[0], ml[1] / ml[0]
            self._scale_prior_done.add(sess)
            self._use("prior:ml-scale")
        else:
            scale, rel = self._fuse_provisional_scale(s, scale, rel)
            rel = max(o.slam_init_scale_sigma_rel, rel)
        value = make_slam_T_world(scale, fit.slam_R_world, fit.slam_t_world)
        # The fit's origin is the first camera position of the session: move it to the current
        # world frame through the newest keyframe estimate at the session's first pose.
        value = self._align_origin(s, value)
        sig = np.array([0.3, 0.3, 0.3, 10.0, 10.0, 10.0, rel])
        g.add(gtsam.PriorFactorSimilarity3(key, value, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        self._add_to_chain(s, seg, key, value, g, stamps)
        log.info(
            "%s: SLAM session %d aligned at t=%.2f s: scale %.4f (rel. s.e. %.3f, %d pairs)%s",
            self.name,
            sess,
            t,
            fit.scale,
            fit.scale_rel_se,
            fit.n_pairs,
            "" if ml is None else f"; ML-scale stage {ml[0]:.4f} +- {ml[1]:.4f} used",
        )
        # Re-attach the provisional factors still in the window to the new alignment.
        self._release_held(sess)
        if s.provisional is not None:
            # (row -1: a re-attachment, counted as ``slam:reattached``, not as used)
            self._retire_provisional(sess, s, None, remove, self._pending)

    def _fuse_provisional_scale(self, s: _Session, scale: float, rel: float) -> tuple[float, float]:
        """The chain's starting scale: the closed-form fit's ``scale`` (relative standard error
        ``rel``) fused, by inverse variance in log-scale, with the provisional alignment's
        current estimate and marginal, when the provisional is still in the window
        (``slam_chain_fuse_provisional``). The fit's standard error is a lower bound and the
        fit sees only the poses of its window; the provisional has been estimated from the same
        poses with the states' velocity and attitude: after a map reset, where the velocity is
        known from the session before, it is much the better (simulated two-turns, reset at
        12 s: fit 1.653, provisional 1.005, true 0.9965). Only then: in a flight's first
        session the velocity is unknown too and the provisional's marginal is overconfident
        (two-turns: fit 0.706, provisional 1.144 +- 9.5 %, true 0.740). Returns the scale and
        its relative sigma."""
        key = s.provisional
        if not self.options.slam_chain_fuse_provisional or key is None or not self._alive(key):
            return scale, rel
        if not any(other.chain for other in self.sessions.values() if other is not s):
            # No alignment before this session's: the provisional scale shares the ambiguity of
            # the unknown velocity and its marginal is overconfident (two-turns: 1.144 +- 9.5 %
            # against the true 0.740): the fit alone.
            return scale, rel
        pv = self.values.get(key)
        try:
            var_p = float(np.asarray(self.smoother.marginalCovariance(key))[6, 6])
        except SOLVER_ERRORS:
            return scale, rel
        if pv is None or not (var_p > 0 and math.isfinite(var_p)) or not rel > 0:
            return scale, rel
        p_scale = float(pv.scale())
        var_f = rel**2
        w = var_p / (var_p + var_f)  # the fit's weight
        fused = math.exp(w * math.log(scale) + (1.0 - w) * math.log(p_scale))
        log.info(
            "%s: SLAM chain start: closed-form scale %.4f (rel. s.e. %.3f) and provisional "
            "%.4f (sigma %.3f) -> %.4f",
            self.name,
            scale,
            rel,
            p_scale,
            math.sqrt(var_p),
            fused,
        )
        return fused, math.sqrt(var_p * var_f / (var_p + var_f))

    def _align_origin(self, s: _Session, value: gtsam.Similarity3) -> gtsam.Similarity3:
        """Translation of an alignment so that the newest SLAM pose maps onto the current
        estimate of its keyframe (the fit placed the world origin at the first camera)."""
        scale, R = value.scale(), value.rotation().matrix()
        return make_slam_T_world(scale, R, s.p[-1] - scale * R @ self._cam_at(s.t[-1]))

    def _pose_at(self, t: float) -> gtsam.Pose3:
        """The newest estimate of the keyframe nearest ``t`` (the newest one for later times)."""
        k = self._kf_near(t) if self._kf_index else self.k
        while k > 0 and k not in self._pose_hist:
            k -= 1
        return self._pose_hist[k][1] if k in self._pose_hist else self.values[X(self.k)]

    def _cam_at(self, t: float) -> np.ndarray:
        """``world_t_cam`` of :meth:`_pose_at` ``(t)`` (the camera centre in world [m])."""
        pose = self._pose_at(t)
        return pose.translation() + pose.rotation().matrix() @ self.body_T_cam[:3, 3]

    def _renew_provisional(self, sess, s: _Session) -> None:
        """A provisional alignment that has left the window (a SLAM pause longer than the lag
        before the chain started) gives way to a new one, seeded with its last estimate's
        rotation and scale. Before, every later pose was attached to the departed variable: each
        update failed and rebuilt (simulated rectangle, SLAM paused 1-9 s: 29 rebuilds)."""
        if s.provisional is None or self._alive(s.provisional):
            return
        old = self.values.get(s.provisional)
        self._use("slam:provisional-renewed")
        seed = s.seed
        if old is not None and seed is None:
            seed = (old.rotation().matrix(), float(old.scale()))
        self._retire_provisional(sess, s, seed, [])

    def _units_check(self, sess, s: _Session, remove) -> None:
        """A provisional alignment at the default scale (1 SLAM unit per metre) whose poses
        change their velocity far more than the IMU and ``graph.slam_sigma_m`` can explain at
        its current scale is a SLAM in other units (or a provisional scale gone astray): it is
        re-seeded, once, with the scale they give, named in a warning and counted
        (``slam:provisional-units``).

        The SLAM noise is modelled as ``slam_sigma_m`` times the scale: at the default scale a
        SLAM in centimetres had its noise 100x too tight, and the window diverged within a
        second (simulated two-turns and figure8, 20 s: 364 m/s at 0.75 s), before the camera
        had moved the ``slam_provisional_min_disp_m`` the data's scale (:meth:`_data_scale`)
        needs. The test uses the poses' second differences
        (:func:`fgnav.solvers.measurements.slam_second_differences`), which the velocity does
        not enter: each gives the scale ``|d2_slam| / sqrt(|d2_imu|^2 + (m sigma c)^2)``, the
        IMU's metric second difference and the noise's typical size (``c`` the difference's
        noise gain, ``m`` the Maxwell median ``UNITS_MAXWELL_MEDIAN``). Where the IMU's term
        dominates (``UNITS_MOTION_DOMINANT``), the scale is the motion's and their median must
        exceed ``UNITS_MIN_RATIO`` times the current scale; looked at with each pose, over the
        newest ``UNITS_POSES``, while the provisional lasts (simulated two-turns, 3 Hz
        keyframes, seed 3: the provisional's scale had gone to 0.50 in the hover against the
        true 1.54; re-seeded once the vehicle moved). Where the noise dominates (a hover, a
        camera rate), the scale is the scatter's, as good as ``slam_sigma_m``: only the first
        ``UNITS_POSES`` poses (from the ``UNITS_MIN_POSES``-th, a wider margin while few) are
        looked at, against the higher ``UNITS_NOISE_MIN_RATIO`` (a metric SLAM 2-4x noisier
        than ``slam_sigma_m`` read 2.4-7.2 units per metre). It only seeds the linearisation
        point and the noise under the provisional's wide log-scale prior. A SLAM in units much
        smaller than metres is not tested in a hover: its scatter cannot be told from a SLAM
        quieter than ``slam_sigma_m``."""
        if not s.units_pending or s.provisional is None:
            return
        ts = np.asarray(s.t)
        i0 = int(np.searchsorted(ts, self._prov_t_first(s)))
        # Poses whose keyframe exists (the IMU covers them).
        i1 = int(np.searchsorted(ts, self.t_kf[self.k] + 1e-9))
        if i1 - i0 < UNITS_MIN_POSES or i1 <= s.units_seen:
            return
        s.units_seen = i1
        # The first UNITS_POSES poses, then (motion only) the newest UNITS_POSES, while the
        # provisional lasts: a hover at the start shows only the noise.
        first = i1 - i0 <= UNITS_POSES
        n = min(i1 - i0, UNITS_POSES)
        t, p = ts[i1 - n : i1], np.asarray(s.p[i1 - n : i1])
        imu = self.imu.series(t[0] - 0.05, t[-1] + 0.05)
        R = self._attitude_track(imu.t) if imu is not None else None
        if R is None:
            return
        acc = world_specific_accel(imu, R, self.go.gravity)
        acc -= np.einsum("nij,j->ni", R, self.values[B(self.k)].accelerometer())
        d2 = slam_second_differences(t, p, imu.t, acc, float(np.median(np.diff(t))), 0.0)
        if not len(d2.width):
            return
        # A difference's noise gain: sqrt(6) for equal intervals (2.8 for intervals 1:2).
        typical = UNITS_MAXWELL_MEDIAN * self.go.slam_sigma_m * math.sqrt(6.0)
        each = np.linalg.norm(d2.slam_d2, axis=1) / np.hypot(
            np.linalg.norm(d2.world_d2, axis=1), typical
        )
        # Where the IMU's second difference dominates the noise's typical size, the scale is
        # the motion's (slam_sigma_m does not enter): the lower bar. Else it is the scatter's,
        # as good as slam_sigma_m: a metric SLAM 2-4x noisier than it read 2.4-7.2 units per
        # metre (review; figure8 re-seeded, 0.089 -> 0.33 m), hence the higher bar.
        motion = np.linalg.norm(d2.world_d2, axis=1) >= UNITS_MOTION_DOMINANT * typical
        if int(motion.sum()) >= 2:
            each, bar = each[motion], UNITS_MIN_RATIO
        elif first:
            bar = UNITS_NOISE_MIN_RATIO
        else:
            return
        ratio = float(np.median(each))
        current = self._scale_guess(s.provisional)
        # While the differences are few, a wider margin (2.7x for 2, none from 7 on).
        margin = max(1.0, UNITS_POSES / 1.25 / (len(each) + 1))
        if not ratio > bar * current * margin:
            return
        s.units_pending = False
        log.warning(
            "%s: SLAM session %d: %d of its poses change velocity %.3g times as much as the "
            "IMU and graph.slam_sigma_m = %g m explain at the provisional scale %.4g units per "
            "metre (a SLAM not in metres, or a provisional scale gone astray): re-seeded at "
            "%.4g",
            self.name,
            sess,
            n,
            ratio / current,
            self.go.slam_sigma_m,
            current,
            ratio,
        )
        self._use("slam:provisional-units")
        s.seed_source = "units"
        self._retire_provisional(sess, s, (None, ratio), remove)

    def _reseed_provisional(self, sess, s: _Session, t_now: float, remove) -> None:
        """Once the stated ``body_R_cam`` is suspected (:meth:`_suspect_extrinsic`), the
        provisional alignment seeded through it is replaced, once, by one seeded with the
        rotation the motion fits (:func:`init_slam_alignment` ``rotation="motion"``: the turns
        and accelerations, no ``body_R_cam``) as soon as that passes :meth:`_motion_fit_ok`
        (tried every ``SLAM_RESEED_RETRY_S``) and differs from the provisional's rotation by more
        than ``SLAM_FIT_ROTATION_MAX_DEG`` (else the provisional stays); once the check has
        replaced the rotation (``reseed_now``), by one seeded through the replacement (the
        closed-form fit's chordal mean over the arrived poses when there are enough, else the
        newest pose). The old one's factors in the window move to the new one. A seed 180 deg
        off cannot be undone by the solver (simulated rectangle, 30 s: 123 m)."""
        old = self.values.get(s.provisional)
        if s.motion_seed is not None and old is not None:
            # The SLAM orientations contradicted the motion (_orient_contradicted).
            (seed, scale), s.motion_seed = s.motion_seed, None
            how = "with the rotation the motion fits (the SLAM orientations contradicted)"
        elif old is None or s.reseeded:
            return  # none, or its estimate dropped (out of the window for lag + 5 s)
        elif s.reseed_now:
            inputs = self._fit_inputs(s)
            fit = None if inputs is None else self._best_fit(*inputs, "orientations")
            seed = None if fit is None else fit.slam_R_world
            scale = float(old.scale())
            how = "through the replaced body_T_cam rotation"
        else:
            if self._extrinsic_suspect is None or self._sgc is None or t_now < s.next_reseed:
                return
            s.next_reseed = t_now + SLAM_RESEED_RETRY_S
            inputs = self._fit_inputs(s)
            alt = None if inputs is None else self._best_fit(*inputs, "motion")
            if not self._motion_fit_ok(alt):
                return
            seed, scale = alt.slam_R_world, alt.scale
            angle = math.degrees(_norm(so3_log(seed @ old.rotation().matrix().T)))
            if angle <= SLAM_FIT_ROTATION_MAX_DEG:
                s.reseeded = True  # the motion confirms the provisional's rotation
                return
            how = f"with the rotation the motion fits ({angle:.0f} deg from the provisional's)"
        s.reseeded = True
        log.warning(
            "%s: SLAM session %d: provisional alignment re-seeded %s, scale %.4f",
            self.name,
            sess,
            how,
            scale,
        )
        self._use("slam:provisional-reseeded")
        self._retire_provisional(sess, s, (seed, scale), remove)

    def _retire_provisional(
        self, sess, s: _Session, seed: tuple | None, remove: list, queue: list | None = None
    ) -> None:
        """The session's provisional alignment gives way: its factors still in the window come
        off (``remove``) and their poses wait, as re-attachments (row -1), for the next
        alignment (``queue``: ``_held`` by default; the chain's start, which exists, passes
        ``_pending``); ``seed`` (``(slam_R_world or None, scale)``) seeds that one
        (:meth:`_start_provisional`)."""
        queue = self._held if queue is None else queue
        # Orientations found wrong (_orient_contradicted): the rotation factors made through
        # them come off too; else they stay (a pose moved on keeps its own, row -2).
        bad = self._orient_verdict == "contradicted"
        alive = self._alive(s.provisional)
        for idx, (k, tp, p, q, rot, _made) in s.prov_factors:
            if self._kf_alive(k) and alive:
                remove.append(idx)
                queue.append((k, "slam", (sess, -2 if rot and not bad else -1, tp, p, q)))
        if bad:
            remove.extend(idx for idx, k in s.prov_rot if self._kf_alive(k) and alive)
        s.prov_factors, s.prov_rot = [], []
        s.provisional = None
        s.seed = seed

    def _start_provisional(self, sess, s: _Session, g, stamps) -> bool:
        """The session's provisional alignment (False: not yet, its poses are held back).

        Its scale: the session's predecessor's, else the ML-scale stage's, else the data's
        (:meth:`_data_scale`: a session whose first poses already move waits up to
        ``slam_provisional_wait_s`` for it), else ``slam_provisional_scale``."""
        o = self.options
        if self._orient_verdict == "contradicted" and s.seed is None:
            # The orientations were found wrong (_orient_contradicted): no rotation is seeded
            # through them; the poses wait for the chain the motion's fit starts (_fit).
            return False
        pose = self._pose_at(s.t[-1])
        slam_R_cam = quat_wxyz_to_matrix(s.q[-1])
        world_R_cam = pose.rotation().matrix() @ self.body_T_cam[:3, :3]
        R = slam_R_cam @ world_R_cam.T
        scale = self._session_scale.get(sess - 1, None) or next(
            iter(reversed(list(self._session_scale.values()))), None
        )
        ml = self._ml_scale(sess)
        if ml is not None:
            scale = ml[0]  # the ML-scale stage's (its prior is added with the keyframe)
        source = "session" if scale is not None else "default"
        if ml is not None:
            source = "ml-scale"
        if s.seed is not None:
            # _reseed_provisional: the motion's rotation, or the one through the replaced
            # body_T_cam (None: the newest pose's, above), and the scale.
            R = R if s.seed[0] is None else s.seed[0]
            scale, source = s.seed[1], s.seed_source
            s.seed, s.seed_source = None, "re-seed"
        if scale is None and self._prov_n_covered(s) < o.slam_provisional_min_poses:
            return False  # held back: fewer poses than make the scale observable
        if scale is None:
            data = self._data_scale(s) if o.slam_provisional_wait_s > 0 else None
            if data is None and s.t[-1] - self._prov_t_first(s) < o.slam_provisional_wait_s:
                return False
            if data is None:
                scale = o.slam_provisional_scale
            else:
                scale, d_slam, d_world = data
                source = "data"
                self._use("slam:provisional-data-scale")
                if self._slam_conv not in ("as-is", "inverse"):
                    # Convention not decided yet: the rotation (of either convention) that maps
                    # the camera's world displacement onto the SLAM's.
                    R_inv = quat_wxyz_to_matrix(s.q[-1] * _CONJ) @ world_R_cam.T
                    if float(d_slam @ R_inv @ d_world) > float(d_slam @ R @ d_world):
                        R = R_inv
                log.info(
                    "%s: SLAM session %d: provisional scale %.4f from the arrived motion",
                    self.name,
                    sess,
                    scale,
                )
        origin = s.p[-1] - scale * R @ self._cam_at(s.t[-1])
        if not (math.isfinite(scale) and np.isfinite(R).all() and np.isfinite(origin).all()):
            self._drop("slam:provisional-non-finite")  # a diverged state: wait for a sane one
            return False
        value = make_slam_T_world(scale, R, origin)
        key = S(PROVISIONAL_BASE + self._n_prov)
        self._n_prov += 1
        sig = np.r_[
            [o.slam_provisional_rot_sigma] * 3, [10.0] * 3, [o.slam_provisional_log_scale_sigma]
        ]
        g.add(gtsam.PriorFactorSimilarity3(key, value, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        self._insert(key, value, g, stamps)
        s.provisional = key
        s.prov_factors, s.prov_rot = [], []
        s.lone_hold = source == "default" and o.slam_provisional_lone_gap_s > 0
        s.units_pending, s.units_seen = source == "default", 0
        self._prov_scales.append(
            {"session": int(sess), "t": float(s.t[-1]), "scale": float(scale), "from": source}
        )
        # The poses held back while waiting for the data's scale attach to it now.
        self._release_held(sess)
        return True

    def _release_held(self, sess: int | None = None) -> None:
        """The SLAM poses held back for session ``sess`` (every session's when None) go to
        the pending factors, those whose keyframe has left the window are dropped
        (``slam:before-alignment``); other sessions' stay held."""
        held, self._held = self._held, []
        for item in held:
            if sess is not None and item[2][0] != sess:
                self._held.append(item)
            elif self._kf_alive(item[0]):
                self._pending.append(item)
            else:
                self._drop("slam:before-alignment")

    def _prune_held(self) -> None:
        """Held-back SLAM poses whose keyframe has left the window can no longer attach: they
        are dropped and counted (``slam:before-alignment``) now, not when their session's
        alignment starts, which may be never (a session whose motion never passes the fit's
        gates kept every pose in memory, uncounted until the end)."""
        keep = [item for item in self._held if self._kf_alive(item[0])]
        if len(keep) != len(self._held):
            self._drop("slam:before-alignment", len(self._held) - len(keep))
            self._held = keep

    def _prov_covered(self, s: _Session) -> np.ndarray:
        """Times of the session's arrived poses the smoother covers."""
        t = np.asarray(s.t)
        return t[t >= self.t0 - 0.5 * self.period]

    def _prov_n_covered(self, s: _Session) -> int:
        """How many of the session's arrived poses the smoother covers."""
        return len(self._prov_covered(s))

    def _prov_t_first(self, s: _Session) -> float:
        """Time of the session's first arrived pose the smoother covers."""
        inside = self._prov_covered(s)
        return float(inside[0]) if inside.size else float(s.t[-1])

    def _data_scale(self, s: _Session) -> tuple[float, np.ndarray, np.ndarray] | None:
        """A provisional SLAM scale from what has arrived: the SLAM displacement between the
        session's first pose the smoother covers and its newest, over the current estimate of
        the camera's displacement between their keyframes (IMU-propagated before any
        alignment: a few cm of drift over a displacement of at least
        ``slam_provisional_min_disp_m``), or None (the camera has not moved that far).

        Only a linearisation point under the provisional prior: a provisional scale 2.3x off
        (EuRoC V1_02 ORB-SLAM2, 0.44 units per metre against the default 1) pulled the states
        by 0.5 m for the second before the prior gave way."""
        ts = np.asarray(s.t)
        i0 = int(np.searchsorted(ts, self._prov_t_first(s)))
        # The newest pose whose keyframe exists (a later one would be compared with an older
        # keyframe's position).
        i1 = int(np.searchsorted(ts, self.t_kf[self.k] + 1e-9)) - 1
        if i1 <= i0:
            return None
        v_world = self._cam_at(float(ts[i1])) - self._cam_at(float(ts[i0]))
        v_slam = np.asarray(s.p[i1]) - np.asarray(s.p[i0])
        d_world, d_slam = float(np.linalg.norm(v_world)), float(np.linalg.norm(v_slam))
        if d_world < self.options.slam_provisional_min_disp_m or not d_slam > 0.0:
            return None
        return d_slam / d_world, v_slam, v_world

    # ------------------------------------------------------------------------------------------
    # Health (fgnav.health): sensor fault detectors on the events, the monitor after keyframes
    # ------------------------------------------------------------------------------------------

    def _health_init(self, options: HealthOptions | None) -> None:
        self._health = HealthMonitor(options, f"{self.name}: health")
        self._health.detectors.context = Context(
            speed=lambda t: _norm(self.out[-1].world_v_body) if self.latest() else None,
            height=lambda t: float(self.out[-1].world_T_body[2, 3]) if self.latest() else None,
            scale=lambda s: self._session_scale.get(s),
            slam_height=self._slam_height,
            slam_position=self._slam_world,
            camera=self._camera_now,
            gyro_turn=self._gyro_turn,
            range_expected=self._range_expected,
        )
        self._health.detectors.range_min = float(self.calib.range_min)
        self._health.detectors.range_max = float(self.calib.range_max)
        self._health_checked = False
        self._health_on = self._health.options.enabled

    def _alignment_of(self, session: int) -> Any:
        """The newest alignment value of a session's chain (None without one)."""
        s = self.sessions.get(session)
        return self.values.get(s.last_key) if s is not None and s.last_key is not None else None

    def _sim3_parts(self, S: gtsam.Similarity3) -> tuple[float, np.ndarray, np.ndarray]:
        """``(scale, slam_R_world, slam_t_world)`` of ``S``, kept with the object they came
        from: the alignment changes at the slow-variable reads only, the range readings (50 Hz)
        ask for every one (the newest height is then stale: ``_height_last`` cleared)."""
        cached = self._height_parts
        if cached is None or cached[0] is not S:
            cached = self._height_parts = (S, *slam_alignment_parts(S))
            self._height_last = None
        return cached[1:]

    def _slam_world(self, session: int, slam_t_cam: np.ndarray) -> np.ndarray | None:
        """``world_t_cam`` [m] of a SLAM camera position through its session's newest
        alignment (None without one)."""
        S = self._alignment_of(session)
        p = np.asarray(slam_t_cam, float)
        if isinstance(S, np.ndarray):  # per-axis: slam_t = diag(k) world_t + o
            return (p - S[3:6]) / S[:3]
        if not isinstance(S, gtsam.Similarity3):
            return None
        scale, slam_R_world, slam_t_world = self._sim3_parts(S)
        return slam_R_world.T @ (p - slam_t_world) / scale

    def _gyro_turn(self, ta: float, tb: float) -> float | None:
        """Angle [rad] of the body's rotation from ``ta`` to ``tb`` through the arrived gyro,
        the newest bias estimate removed (None: the IMU does not cover both ends)."""
        imu = self.imu
        ts = imu.t
        if not ts or ts[0] > ta or ts[-1] < tb or tb <= ta:
            return None
        # (the interval lengths on plain floats, the rates in one array: the same numbers as
        # np.diff over np.r_[ta, samples, tb] without numpy's per-call overhead, per SLAM pose)
        i0, i1 = bisect.bisect_left(ts, ta), bisect.bisect_right(ts, tb)
        t = [ta, *ts[i0:i1], tb]
        dt = [t1 - t0 for t0, t1 in zip(t[:-1], t[1:], strict=True)]
        if max(dt) > 0.2:
            return None  # an IMU gap (with or without samples between the two times)
        # Zero-order hold: each interval turns at the sample at its start (the first, at the
        # sample before ta; ta on the first sample: that one).
        rows = imu.w[max(i0 - 1, 0) : i1]
        if i0 == 0:
            rows = rows[:1] + rows
        if len(rows) < len(dt):
            return None
        w = np.array(rows[: len(dt)], float)
        b = self.values.get(B(self.k)) if self.k >= 0 else None  # (-1: before a restart)
        if b is not None:
            w = w - b.gyroscope()
        phi = w * np.array(dt)[:, None]
        if float(np.abs(phi).sum()) < GYRO_TURN_SMALL_RAD:
            # Small turns (consecutive poses): the summed rotation vector, off by at most half
            # the square of the turn (0.6 deg at 0.15 rad) against the product of exponentials.
            return _norm(phi.sum(axis=0))
        R = np.eye(3)
        for Ri in so3_exp(phi):
            R = R @ Ri
        return float(np.linalg.norm(so3_log(R)))

    def _camera_now(self) -> tuple[np.ndarray, float, float] | None:
        """The newest estimate's camera position [m], its position sigma (the root of the
        covariance's trace) [m] and its time [s]; None when no covariance is known. Without
        ``FixedLagOptions.covariance`` the newest marginal is computed here (asked only for a
        SLAM pose back after a pause: the relocalisation test was off without it)."""
        st = self.latest()
        if st is None:
            return None
        cov = st.pose_cov
        if cov is None and self.k >= 0 and st.t == self.t_kf.get(self.k):
            try:
                cov = self.smoother.marginalCovariances([X(self.k)])[0]
            except SOLVER_ERRORS:
                return None
        if cov is None:
            return None
        T = np.asarray(st.world_T_body)
        sigma = math.sqrt(max(float(np.trace(np.asarray(cov)[3:, 3:])), 0.0))
        return T[:3, 3] + T[:3, :3] @ self.body_T_cam[:3, 3], sigma, float(st.t)

    def _slam_height(self, session: int, slam_t_cam: np.ndarray) -> float | None:
        """World z [m] of a SLAM camera position through its session's newest alignment."""
        S = self._alignment_of(session)
        if isinstance(S, np.ndarray):  # per-axis: slam_t = diag(k) world_t + o
            return float((slam_t_cam[2] - S[5]) / S[2])
        if not isinstance(S, gtsam.Similarity3):
            return None
        # The newest height kept with the position it came from (the health detectors ask again
        # for the same SLAM pose at each new range value: 8782 calls for 3601 poses on the 180 s
        # benchmark); _sim3_parts clears it when the alignment changes.
        scale, slam_R_world, slam_t_world = self._sim3_parts(S)
        last = self._height_last
        if last is not None and last[0] == session and last[1] is slam_t_cam:
            return last[2]
        h = float((slam_R_world.T @ (np.asarray(slam_t_cam) - slam_t_world) / scale)[2])
        self._height_last = (session, slam_t_cam, h)
        return h

    def _health_feed(self, ev: Any) -> Any:
        """The event through the fault detectors: None when dropped (counted as received and
        dropped by reason), else the event to use (a SLAM pose after a jump in a new session)."""
        if not self._health.options.enabled:
            return ev
        out = self._health.detectors.feed(ev)
        if out is None:
            stream = _STREAM.get(type(ev), "imu")
            self.received[stream] = self.received.get(stream, 0) + 1
            reason = {"range": "range:stuck", "images": "images:frozen"}.get(stream, stream)
            self._drop(reason)
        return out

    def _health_keyframe(self, k: int, g: gtsam.NonlinearFactorGraph) -> None:
        """Whitened errors of the update's SLAM and range factors at the newest linearisation
        point into the monitor, then its verdict on the newest state: quality lowered while it
        diverges, a rebuild from the last healthy state when it says so."""
        hm = self._health
        known, self._lin_errors = self._lin_errors or {}, None
        factors, self._lin_factors = self._lin_factors, None
        if not hm.options.enabled or not self.out or self.out[-1].t != self.t_kf.get(k):
            return
        if not self._health_checked and getattr(self, "slam_check", None):
            self._health_checked = True
            hm.detectors.slam_check(self.slam_check)
        t = self.t_kf[k]
        # iSAM2's live linearisation point (a view: getLinearizationPoint() copies the window)
        lin = getattr(self.smoother, "_theta_view", None) or self.smoother.getLinearizationPoint()
        if factors is None or len(factors) != g.size():
            factors = [g.at(i) for i in range(g.size())]
        for f in factors:
            keys = f.keys() if f is not None else None
            sensor = sensor_of(keys) if keys is not None else None
            if sensor is None:
                continue
            # Its error at the last linearisation (iSAM2's, at ``lin``) when recorded, else
            # evaluated there (the same numbers: tests/solvers/test_online_health_cache.py).
            e = known.get(f)
            try:
                if e is not None and all(lin.exists(key) for key in keys):
                    e = np.asarray(f.noiseModel().whiten(e), float)
                    self._lin_hits += 1
                else:
                    e = np.asarray(f.whitenedError(lin), float)
            except (RuntimeError, IndexError, ValueError):
                continue  # a key not in the window (the update failed and was rebuilt)
            hm.innovations(sensor, t, float(e @ e), int(e.size))
        snap = hm.after_keyframe(self.out[-1], lambda: self._health_snapshot(k))
        q = hm.quality(self.out[-1].quality, any(s.chain for s in self.sessions.values()))
        if q != self.out[-1].quality:
            self.out[-1] = dataclasses.replace(self.out[-1], quality=q)
        if snap is not None:
            self._health_recover(snap)

    def _health_snapshot(self, k: int) -> Snapshot:
        keys = [X(k), V(k), B(k)] + [
            key for key in self.values if _chr(key) in "sdg" and self._alive(key)
        ]
        vals = {key: self.values[key] for key in keys if key in self.values}
        return Snapshot(k, self.t_kf[k], vals)

    def _health_recover(self, snap: Snapshot) -> None:
        """Rebuild the window from a healthy snapshot: its state carried by the arrived IMU to
        the keyframe before the newest, its slow variables, then :meth:`_rebuild` (priors there
        and the newest IMU factor)."""
        kp = self.k - 1
        if kp < 0 or kp not in self.t_kf or X(kp) not in self.values:
            return
        bias = snap.values[B(snap.k)]
        pim = self._preintegrate(snap.t, self.t_kf[kp], bias, count=False)
        nav = pim.predict(gtsam.NavState(snap.values[X(snap.k)], snap.values[V(snap.k)]), bias)
        self.values[X(kp)], self.values[V(kp)], self.values[B(kp)] = (
            nav.pose(),
            nav.velocity(),
            bias,
        )
        for key, val in snap.values.items():
            if _chr(key) in "sdg" and key in self.values:
                self.values[key] = val
        self._drop("health:recovered")
        self._rebuild({})

    def _carry_state(self) -> dict[str, Any] | None:
        """The newest state and SLAM alignments, to restart from after an IMU gap (None before
        the first keyframe). While the monitor says the estimate diverges, its last healthy
        snapshot instead."""
        if self.k < 0 or X(self.k) not in self.values:
            return None
        snap = self._health.healthy_snapshot() if self._health.status == "diverged" else None
        vals = snap.values if snap is not None else self.values
        k = snap.k if snap is not None else self.k
        t = snap.t if snap is not None else self.t_kf[self.k]
        align = {}
        for sess, sn in self.sessions.items():
            if sn.last_key is not None and sn.last_key in vals:
                cov = None
                if self.smoother is not None and self._alive(sn.last_key):
                    try:
                        cov = np.asarray(self.smoother.marginalCovariance(sn.last_key))
                    except SOLVER_ERRORS:
                        cov = None
                align[sess] = (vals[sn.last_key], cov)
        pose = vals[X(k)]
        return {
            "t": t,
            "R": pose.rotation().matrix(),
            "p": np.asarray(pose.translation(), float),
            "v": np.asarray(vals[V(k)], float),
            "bias": vals[B(k)],
            "align": align,
        }

    def _slam_place(
        self, t: float, world_R_body: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray | None] | None:
        """``world_t_body`` at ``t`` and ``world_v_body`` from the SLAM poses arrived since the
        restart and their session's carried alignment (the newest pose within
        ``GAP_PLACE_MAX_S`` of ``t``, carried to ``t`` with the mean velocity of the poses of
        the ``GAP_PLACE_MAX_S`` before it), or None."""
        for sess, (value, _) in self._carried_align.items():
            sn = self.sessions.get(sess)
            if sn is None or not sn.t or abs(sn.t[-1] - t) > GAP_PLACE_MAX_S:
                continue
            # slam_t_cam = s slam_R_world world_t_cam + slam_t_world (per-axis: diag(k) ... + o)
            if isinstance(value, np.ndarray):
                R, scale, origin = np.diag(1.0 / value[:3]), 1.0, value[3:]
            else:
                R, scale = value.rotation().matrix(), value.scale()
                origin = value.translation()
            world_t_cam = R.T @ (sn.p[-1] - origin) / scale
            vel = None
            j = bisect.bisect_left(sn.t, sn.t[-1] - GAP_PLACE_MAX_S)
            if sn.t[-1] - sn.t[j] > 0:
                vel = R.T @ (sn.p[-1] - sn.p[j]) / scale / (sn.t[-1] - sn.t[j])
            p = world_t_cam - world_R_body @ self.body_T_cam[:3, 3]
            return p + (vel if vel is not None else 0.0) * (t - sn.t[-1]), vel
        return None

    def _carried_chain(self, sess, s: _Session, t, g, stamps) -> int:
        """The alignment chain of a session that was aligned before an IMU gap: its first
        segment after the restart starts from the carried alignment (the SLAM map did not
        change) under the rebuild's priors on slow variables.

        Its linearisation point is held at the carried value, and that of the segments after
        it at their first value, while the restart's QR start lasts (``startup_qr_s``; the
        move to Cholesky frees the ones still in the window): the carried prior is the
        window's marginal from before the gap, whose variables iSAM2 would hold too. The
        restarted window sees the scale only through its products with the velocity and
        position, whose priors the gap widened: relinearising the alignment with the
        keyframe positions (``relinearize_threshold_position``) swung the scale along that
        near-degenerate direction (20 s two-turns without camera, 8 s gap: -5 % -> +31 %
        0.3 s after the restart; ATE 2.56x nominal, held 1.81x)."""
        value, cov = self._carried_align.pop(sess)
        seg, key = self._segment_key(s, t)
        if cov is not None and np.all(np.isfinite(cov)):
            noise = gtsam.noiseModel.Gaussian.Covariance(cov * CARRY_SIGMA_FACTOR**2)
        else:
            noise = gtsam.noiseModel.Diagonal.Sigmas(self._slam_rebuild_sigmas(value))
        g.add(self._slam_prior(key, value, noise))
        self._add_to_chain(s, seg, key, value, g, stamps)
        self.smoother.hold_linearization([key])
        s.carried = True
        self._use("slam:alignment-carried")
        return key

    def _slam_rebuild_sigmas(self, value: Any) -> np.ndarray:
        """Sigmas of the prior that carries a SLAM alignment into a rebuilt window: 0.05 rad,
        0.5 m and ``rebuild_slow_sigma_rel`` of the scale (per-axis: of each axis, the origin
        0.5 m in SLAM units)."""
        rel = self.options.rebuild_slow_sigma_rel
        if isinstance(value, np.ndarray):
            return np.r_[rel * np.abs(value[:3]), [0.5 * float(np.max(value[:3]))] * 3]
        return np.array([0.05, 0.05, 0.05, 0.5, 0.5, 0.5, rel])

    @staticmethod
    def _slam_prior(key: int, value: Any, noise: Any) -> Any:
        """A prior on a SLAM alignment: Sim(3), or the per-axis model's Vector6."""
        if isinstance(value, np.ndarray):
            return gtsam.PriorFactorVector(key, value, noise)
        return gtsam.PriorFactorSimilarity3(key, value, noise)

    def _health_report(self) -> dict[str, Any]:
        rep = self._health.report()
        rep["dropped"] = {
            r: n
            for r, n in self.dropped.items()
            if r in ("range:stuck", "range:at-min", "range:at-max", "images:frozen")
        }
        n_sat = self.used.get("imu:saturated-intervals", 0)
        rep["downweighted"] = {"imu-saturated-intervals": n_sat} if n_sat else {}
        return rep

    # ------------------------------------------------------------------------------------------
    # Smoother
    # ------------------------------------------------------------------------------------------

    def _new_smoother(self, factorization: str, startup: bool = False) -> TimeOrderedSmoother:
        """A fresh window; ``startup``: with the start's relinearisation
        (``FixedLagOptions.startup_relinearize_*``) for the QR start."""
        o = self.options
        dims = {"s": 6 if self._axis else 7, "d": 2 if self.go.drag_per_axis else 1, "g": 1}
        if self._axis and o.relinearize_threshold_position is not None:
            # The per-axis SLAM model keeps the keyframe threshold for the positions: its kz is
            # unobservable at constant altitude, and relinearising the positions gave it the
            # information of a mixed linearisation (circle, seed 1, 20 s with the camera: final
            # kz 29 % off with 3 mm, 0.3 % with 0.5 m; the keys of iSAM2's marginals are held).
            o = dataclasses.replace(o, relinearize_threshold_position=None)
        if startup and o.startup_relinearize_threshold is not None:
            # The start without an attitude stream relinearises every keyframe state, positions
            # included, at its own threshold (3 mm positions on top: EuRoC V1_02 causal ATE
            # ORB-SLAM2 / ORB-SLAM3 keyframes 9.64 / 5.42 cm against 9.70 / 5.85, NEES 10.9 / 6.6
            # against 12.1 / 9.5; MH_01 4.64 against 4.62 cm).
            o = dataclasses.replace(
                o,
                relinearize_threshold=o.startup_relinearize_threshold,
                relinearize_skip=o.startup_relinearize_skip,
                relinearize_threshold_position=None,
            )
        # With the position threshold old keyframe poses relinearise, each re-eliminating the
        # whole window: ballast keeps that off iSAM2's batch path (window.py).
        ballast = BALLAST_WITH_POSITION_THRESHOLD if o.relinearize_threshold_position else 0.0
        return TimeOrderedSmoother(
            o.lag_s, _isam2_params(o, dims, factorization), o.fine_levels, ballast=ballast
        )

    def _block(self, t: float) -> float:
        blk = self.options.marginalize_every_s
        return math.ceil((t - self.t0) / blk - 1e-9) * blk + self.t0 if blk > 0 else t

    def _update(self, g, vals, stamps, remove) -> bool:
        vals.insert(self._queued_values)
        self._queued_values = gtsam.Values()
        self.stamp.update(stamps)
        try:
            self.smoother.update(
                g, vals, {key: self._block(t) for key, t in stamps.items()}, remove
            )
            return True
        except SOLVER_ERRORS as e:
            msg = " ".join(str(e).split())[:200]
            fb = (self.options.fallback_factorization or "").upper()
            if fb and fb != self.factorization and self._move_window(fb):
                # The failed update's factors moved with the window: nothing lost.
                self.n_fallbacks += 1
                log.warning(
                    "%s: %s update failed at t=%.3f (%s); the window moved to %s (nothing lost)",
                    self.name,
                    self.options.factorization.upper(),
                    self.t_kf[self.k],
                    msg,
                    fb,
                )
                return True
            self.n_failures += 1
            self.failure_messages.append(msg)
            log.warning(
                "%s: smoother update failed at t=%.3f (%s); rebuilding",
                self.name,
                self.t_kf[self.k],
                msg,
            )
            self._rebuild(stamps)
            return False

    def _move_window(self, factorization: str) -> bool:
        """Move the window into a fresh smoother with ``factorization``, losslessly: the same
        factors (marginals anchored at their linearisation point, their variables held) at the
        same linearisation point and stamps. Also used on a smoother whose update just failed
        (its factors include that update's). False (smoother unchanged) when that fails too."""
        new = self._new_smoother(factorization)
        index = try_move_window(self.smoother, new, self.name, factorization)
        if index is None:
            return False
        self.smoother = new
        self.factorization = factorization
        for s in self.sessions.values():
            s.prov_factors = [(index[i], row) for i, row in s.prov_factors if i in index]
            s.prov_rot = [(index[i], k) for i, k in s.prov_rot if i in index]
        return True

    def _switch_factorization(self) -> None:
        """After the QR start: the window into a Cholesky smoother (lossless), or, when that
        fails, into a QR one (the start's relinearisation ends either way)."""
        if not self._move_window(self.options.factorization.upper()):
            self._move_window("QR")
            self.factorization = "QR-stay"

    def _rebuild(
        self,
        failed_stamps: dict[int, float] | None = None,
        slam_sigmas: dict[int, np.ndarray] | None = None,
        priors: FixedLagOptions | None = None,
    ) -> None:
        """Fresh QR smoother with priors on the newest good state and the live slow variables
        (those of the window and those the failed update created); the failed update's
        measurements are lost (counted as ``solver-failure:measurements-lost``).
        ``slam_sigmas``: the prior sigmas of these SLAM alignments (default
        :meth:`_slam_rebuild_sigmas`); ``priors``: options whose ``rebuild_*`` sigmas the state
        priors take (default the smoother's)."""
        o = self.options
        live = [
            key
            for key in self.values
            if _chr(key) in "sdg" and (self._alive(key) or key in (failed_stamps or {}))
        ]
        self.reset_counter += 1
        self._bad_since = self.t_kf.get(self.k, 0.0)
        self.factorization = "QR"
        self.smoother = self._new_smoother("QR")
        kg = max(k for k in self.t_kf if X(k) in self.values and k < self.k) if self.k > 0 else 0
        g = gtsam.NonlinearFactorGraph()
        v = gtsam.Values()
        stamps: dict[int, float] = {}
        t = self.t_kf[kg]
        g.push_back(
            rebuild_state_priors(
                kg, self.values[X(kg)], self.values[V(kg)], self.values[B(kg)], priors or o
            )
        )
        for key in (X(kg), V(kg), B(kg)):
            v.insert(key, self.values[key])
            stamps[key] = t
        for key in live:
            val = self.values[key]
            c = _chr(key)
            if c == "s":
                sig = (slam_sigmas or {}).get(key)
                if sig is None:
                    sig = self._slam_rebuild_sigmas(val)
                noise = gtsam.noiseModel.Diagonal.Sigmas(sig)
                g.add(self._slam_prior(key, val, noise))
            else:
                vv = np.asarray(val, float)
                sig = (
                    np.maximum(np.abs(vv) * o.rebuild_slow_sigma_rel, 1e-3)
                    if c == "d"
                    else np.full(1, self.go.range_sigma * 5)
                )
                g.add(gtsam.PriorFactorVector(key, vv, gtsam.noiseModel.Diagonal.Sigmas(sig)))
            v.insert(key, val)
            stamps[key] = self.t_kf[self.k]
        for s in self.sessions.values():
            s.prov_factors, s.prov_rot = [], []
        # The newest keyframe (its IMU factor was in the failed update) is re-added from kg.
        self.stamp = dict(stamps)
        self.smoother.update(g, v, {key: self._block(ts) for key, ts in stamps.items()})
        if kg != self.k:
            k = self.k
            g2 = gtsam.NonlinearFactorGraph()
            v2 = gtsam.Values()
            pim = self._pim
            nav = pim.predict(
                gtsam.NavState(self.values[X(kg)], self.values[V(kg)]), self.values[B(kg)]
            )
            g2.add(gtsam.CombinedImuFactor(X(kg), V(kg), X(k), V(k), B(kg), B(k), pim))
            v2.insert(X(k), pose3=nav.pose())
            v2.insert(V(k), vector=nav.velocity())
            v2.insert(B(k), constant_bias=self.values[B(kg)])
            st2 = {X(k): self.t_kf[k], V(k): self.t_kf[k], B(k): self.t_kf[k]}
            self.stamp.update(st2)
            self.smoother.update(g2, v2, {key: self._block(ts) for key, ts in st2.items()})

    def _read(self, k: int, wall0: float) -> None:
        sm = self.smoother
        failure = None
        pose_cov = vel_cov = None
        try:
            pose = sm.calculateEstimatePose3(X(k))
            vel = np.asarray(sm.calculateEstimateVector(V(k)), float)
            bias = sm.calculateEstimateConstantBias(B(k))
            if not _finite_state(pose, vel, bias):
                # Never an output (SLAM positions in units 1e4 per metre made NaN states,
                # then raised in the next fit): rebuilt from the last good state, as a failure.
                failure = f"non-finite estimate at t={self.t_kf[k]:.3f}"
            elif self.options.covariance:
                try:
                    pose_cov, vel_cov = sm.marginalCovariances([X(k), V(k)])
                except SOLVER_ERRORS:
                    # The estimate stands; only its marginal is not computable (GTSAM's
                    # "Indeterminate" on a near-singular window): reported as missing.
                    self._drop("covariance:indeterminate")
        except SOLVER_ERRORS as e:
            failure = " ".join(str(e).split())[:200]
        if failure is not None:
            self.n_failures += 1
            self.failure_messages.append(failure)
            self._rebuild({})
            pose, vel, bias = self.values[X(k)], self.values[V(k)], self.values[B(k)]
            if not _finite_state(pose, vel, bias):
                self._drop("output:non-finite")
                return
        # Keep only the newest keyframe state (and the slow variables).
        horizon = self.t_kf[k] - self.options.lag_s - 4 * self.period
        for kk in [kk for kk in self._state_kf if kk < k - 1]:
            for key in (X(kk), V(kk), B(kk)):
                self.values.pop(key, None)
            self._state_kf.discard(kk)
        self._state_kf.add(k)
        while len(self._kf_index) > 2 and self._kf_index[0][0] < horizon:
            _, kk = self._kf_index.popleft()
            self.t_kf.pop(kk, None)
        self.values[X(k)], self.values[V(k)], self.values[B(k)] = pose, vel, bias
        self._pose_hist[k] = (self.t_kf[k], pose)
        while len(self._pose_hist) > self.options.history_s * self.go.keyframe_hz:
            # The oldest is the first inserted: keyframes are read once each, in increasing k
            # (``_clear`` starts a new dict), so no min() over the ~600 keys.
            del self._pose_hist[next(iter(self._pose_hist))]
        t = self.t_kf[k]
        # Slow variables.
        every = max(1, self.options.slow_read_every)
        if k % every == 0:
            # A session's newest alignment variables are kept whatever their age: a SLAM pause
            # longer than the lag continues from their last estimate (_session_key).
            needed = {x for ss in self.sessions.values() for x in (ss.last_key, ss.provisional)}
            for key in [key for key in self.values if _chr(key) in "sdg"]:
                if not self._alive(key):
                    if key in needed:
                        continue
                    if self.stamp.get(key, t) < t - self.options.lag_s - 5.0:
                        self.values.pop(key)
                        self.stamp.pop(key, None)
                    continue
                try:
                    c = _chr(key)
                    if c == "s" and not self._axis:
                        self.values[key] = sm.calculateEstimateSimilarity3(key)
                    else:
                        self.values[key] = np.asarray(sm.calculateEstimateVector(key), float)
                except SOLVER_ERRORS:
                    continue
            self._track_slow(t)
        self.latency.append(time.perf_counter() - wall0)
        self.out.append(self._state(k, pose, vel, bias, pose_cov, vel_cov))
        if self.options.lagged_output:
            self._read_lagged(k)
        self._out_epoch.append(self._epoch)

    def _read_lagged(self, k: int) -> None:
        """The smoothed states the next update will marginalise, once each: the
        ``fixed-lag@lag`` output (delayed by the lag and up to one marginalisation block, with
        every measurement of the window)."""
        # Keys leave in marginalisation blocks: read those the next update will marginalise.
        cut = self._block(self.t_kf[k] + self.period) - self.options.lag_s
        sm = self.smoother
        idx = self._kf_index
        # (the keyframes read already come first: keyframes are kept in time order, so the
        # scan starts after them)
        first = bisect.bisect_right(idx, self._lag_done, key=_second)
        for i in range(first, len(idx)):
            t_j, j = idx[i]
            if self._block(t_j) > cut + 1e-6:
                break
            self._lag_done = j
            if X(j) not in sm:
                continue
            try:
                pose = sm.calculateEstimatePose3(X(j))
                vel = np.asarray(sm.calculateEstimateVector(V(j)), float)
                bias = sm.calculateEstimateConstantBias(B(j))
            except SOLVER_ERRORS:
                continue
            self.out_lag.append(
                np.concatenate(
                    (
                        (self._epoch, t_j),
                        pose.matrix().ravel(),
                        vel,
                        bias.gyroscope(),
                        bias.accelerometer(),
                    ),
                    dtype=float,
                )
            )

    def lagged_result(self, epoch: int = -1) -> Estimate:
        """The ``fixed-lag@lag`` output: each keyframe's state as smoothed just before it leaves
        the window (``FixedLagOptions.lagged_output``), delayed by the lag."""
        lag = np.array(self.out_lag)
        eps = sorted(set(lag[:, 0].astype(int).tolist())) if len(lag) else []
        if not eps:
            raise FlightDataError(f"{self.name}: no lagged state (run shorter than the lag?)")
        traj = _trajectory(lag[lag[:, 0] == eps[epoch]], _LAG_ROW)
        est = self.result(epoch=epoch)
        # The causal estimate's slow variables, series, latency and counts; the lagged states
        # (their covariances are not kept).
        return dataclasses.replace(
            est,
            method="fixed-lag@lag",
            trajectory=traj,
            pose_cov=None,
            vel_cov=None,
            causal=False,
            info=dict(est.info, delay_s=self.options.lag_s),
        ).check()

    def _track_slow(self, t: float) -> None:
        for sess, s in self.sessions.items():
            if s.last_key is not None and s.last_key in self.values and self._alive(s.last_key):
                v = self.values[s.last_key]
                if self._axis:
                    # The flight's scale: the geometric mean of the axes (as the batch's).
                    k = np.asarray(v[:3], float)
                    sc = float(np.cbrt(np.prod(k)))
                    self.track.setdefault("slam_axis_scale", []).append((t, k, 0, self._epoch))
                else:
                    sc = float(v.scale())
                self._session_scale[sess] = sc
                self.track.setdefault("slam_scale", []).append((t, sc, sess, self._epoch))
                msg = None if self._axis else self._scale_watch.feed(t, sess, sc)
                if msg:
                    if self._health_on:
                        if not self._health.detectors.scale_change_explained():
                            self._health.detectors.named("slam-scale-drift", msg)
                    else:
                        log.warning("%s: slam-scale-drift: %s", self.name, msg)
        # The drag coefficient only once a drag factor has measured it (a drag variable made
        # before the thrust check turned drag off holds its initial value: not an estimate),
        # and only while drag is in the model (after a check turned it off the variable keeps
        # what its first factors said: a hover's 0.25 / 0.35 1/s was reported as the estimate).
        drag_used = self._drag_in_model() and bool(
            self.used.get("drag") or self.used.get("drag-dynamics")
        )
        for c, name in (("d", "drag_k"), ("g", "ground_height")):
            if c == "d" and not drag_used:
                continue
            keys = [k for k in self.values if _chr(k) == c and self._alive(k)]
            if keys:
                v = np.asarray(self.values[max(keys)], float)
                self.track.setdefault(name, []).append(
                    (t, v if len(v) > 1 else float(v[0]), 0, self._epoch)
                )

    def _drag_in_model(self) -> bool:
        """Drag is in the model now: the measured-force drag factor is on, or the thrust-only
        prediction's drag dynamics are."""
        return bool(self._drag_on or self._drag_dynamics())

    def _state(self, k, pose, vel, bias, pose_cov, vel_cov) -> OnlineState:
        t = self.t_kf[k]
        drag = ground = None
        d = self.track.get("drag_k")
        if d and self._drag_in_model():
            drag = np.atleast_1d(np.asarray(d[-1][1], float))
        gh = self.track.get("ground_height")
        if gh:
            ground = float(gh[-1][1])
        aligned = any(s.chain for s in self.sessions.values())
        provisional = any(s.provisional is not None for s in self.sessions.values())
        q = (
            100
            if aligned or (self.go.use_range and ground is not None and self._scalar["yaw"])
            else 60
            if provisional
            else 30
        )
        if t - self._bad_since < 2.0:
            q //= 2
        return OnlineState(
            t=t,
            world_T_body=pose.matrix(),
            world_v_body=vel,
            accel_bias=np.asarray(bias.accelerometer(), float),
            gyro_bias=np.asarray(bias.gyroscope(), float),
            pose_cov=pose_cov,
            vel_cov=vel_cov,
            slam_scale=dict(self._session_scale),
            drag_k=drag,
            ground_height=ground,
            reset_counter=self.reset_counter,
            quality=int(q),
        )


#: Stream name of each non-IMU event type.
_STREAM = {cls: name for cls, name in STREAM_OF_EVENT.items() if cls is not ImuSample}


def feed_all(
    events,
    calib: Calibration,
    options: FixedLagOptions | None = None,
    name: str = "online",
    progress: bool = False,
    total: int | None = None,
    priors: Any = None,
) -> OnlineSmoother:
    """The :class:`OnlineSmoother` after feeding it ``events`` (e.g.
    :func:`fgnav.datasets.events.replay_flight`; its ``runtime_s`` set: the wall time of the
    loop; ``priors``: :class:`fgnav.frontends.prior_stages.PriorOptions`); its ``result()`` is
    the causal estimate."""
    sm = OnlineSmoother(calib, options, name, priors=priors)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, desc="online", unit="ev", mininterval=0.5)
    t_wall = time.perf_counter()
    for i, ev in enumerate(events):
        sm.feed(ev)
        if bar is not None and i % 1000 == 999:
            bar.update(1000)
    sm.close()
    sm.runtime_s = time.perf_counter() - t_wall
    if bar is not None:
        bar.close()
    return sm


VO_MAX_IN_FLIGHT = 8
"""Frames the VO process may hold before the next is sent (``vo_worker="process"``): 8 frames of
320x240 fit the widened pipe to it, 8 replies (about 1 kB each) the 64 kB one back; normally
1-3 are in flight."""


def _finite_state(pose: gtsam.Pose3, vel: Any, bias: Any) -> bool:
    """Every number of a keyframe state is finite (``np.isfinite(...).all()`` of each, on plain
    floats: numpy's per-call overhead on 25 numbers was most of its time, per keyframe)."""
    isfinite = math.isfinite
    return (
        all(map(isfinite, pose.matrix().ravel().tolist()))
        and all(map(isfinite, np.asarray(vel, float).ravel().tolist()))
        and all(map(isfinite, bias.vector().tolist()))
    )


#: Streams the push engine replays from a flight (images and flow are counted as not used).
PUSH_STREAMS = ("imu", "attitude", "range", "yaw", "slam", "images", "flow")


def resolve_engine(options: FixedLagOptions) -> str:
    """The engine ``options`` select: ``"auto"`` is the push engine, which runs every flight and
    option (the Sim(3) and the per-axis SLAM models, front-end priors as a stage); the
    ``"prepared"`` runner only when configured."""
    if options.engine not in ENGINES:
        raise FlightDataError(
            f"FixedLagOptions.engine={options.engine!r}: expected one of {', '.join(ENGINES)}"
        )
    return "push" if options.engine == "auto" else options.engine


def replay_online(
    flight,
    options: FixedLagOptions | None = None,
    progress: bool = False,
    lagged: bool = False,
    source: Any = None,
    priors: Any = None,
) -> Estimate:
    """A flight's events, in arrival order, through an :class:`OnlineSmoother` (the smoother
    gets the calibration and the events only; ground truth and metadata are never read); the
    causal estimate, or with ``lagged`` the ``fixed-lag@lag`` one. ``priors``: the ``[priors]``
    options (:class:`fgnav.frontends.prior_stages.PriorOptions`), run as a stage inside.

    ``source``: a :class:`fgnav.datasets.native.FlightStreams` whose events are read from its
    files in chunks (bounded memory); ``flight`` is then its outline (checks only).
    """
    sm = replay_smoother(flight, options, progress, source, priors)
    return sm.lagged_result() if lagged else sm.result()


def replay_smoother(
    flight,
    options: FixedLagOptions | None = None,
    progress: bool = False,
    source: Any = None,
    priors: Any = None,
) -> OnlineSmoother:
    """:func:`replay_online`'s smoother after the replay: ``result()`` and, with
    ``FixedLagOptions.lagged_output`` (the default), ``lagged_result()`` of one run."""
    from fgnav.datasets.events import replay_flight

    flight.check()
    options = options or FixedLagOptions()
    if flight.imu is None:
        raise FlightDataError(f"{flight.name}: no IMU stream; the online smoother needs one")
    if options.graph.use_slam and flight.slam is not None:
        # A check of the file, not an input to the estimator: SLAM stamped on another clock
        # would only wait for keyframes that never come.
        flight.require_overlap("imu", "slam")
    if options.graph.use_slam and flight.slam is None:
        # The replay knows the log has no SLAM stream (a live link knows its configured
        # streams): the smoother must not wait ``start_wait_s`` for a first pose. Called
        # directly, without this, a Crazyflie log started 5 s late, in flight, and diverged
        # (traj1: 1.26 m after a rebuild, against 0.106 m).
        options = dataclasses.replace(
            options, graph=dataclasses.replace(options.graph, use_slam=False)
        )
    # A manifest's [slam] options for this file win over the config (configuration only).
    from fgnav.datasets.slam_gyro import file_modes

    rotation, offset = file_modes(
        flight, options.graph.slam_rotation, options.graph.slam_time_offset
    )
    # The SLAM model the input declares (configuration, never its content or ground truth).
    model = choose_slam_model(flight, options.graph.slam_model)
    g = dataclasses.replace(
        options.graph, slam_rotation=rotation, slam_time_offset=offset, slam_model=model
    )
    options = dataclasses.replace(options, graph=g)
    streams = [n for n in PUSH_STREAMS if getattr(flight, n, None) is not None]
    if source is not None:
        events = source.events(streams)
        total = sum(source.counts.get(n, 0) for n in streams)
    else:
        events = replay_flight(flight, streams)
        total = sum(len(getattr(flight, n)) for n in streams)
    return feed_all(events, flight.calib, options, flight.name, progress, total, priors)
