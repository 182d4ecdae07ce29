"""Online fixed-lag smoother: the graph builder's output streamed through an iSAM2 fixed-lag
window in the order the measurements arrive (``fgnav.solvers.window.TimeOrderedSmoother`` by
default, ``gtsam.IncrementalFixedLagSmoother`` with ``FixedLagOptions.smoother="gtsam"``).

Per keyframe k (one update, at the keyframe's time, when the IMU up to ``t_k`` is in):

1. Preintegrate the IMU from k-1 with the latest bias estimate and predict ``X(k), V(k)`` from the
   latest state (causal initial values).
2. Take the builder's keyframe chunk (IMU factor, new slow variables of segments starting at k).
3. Attach every measurement factor that arrived up to ``t_k`` (SLAM poses arrive at
   ``t + latency``): to its own keyframe when that keyframe is still inside the window (minus one
   keyframe period of margin), else count it as ``dropped-too-late``. A SLAM session's alignment is
   created at its first pose: from the closed-form fit on the data arrived so far once the motion
   excites the scale (``slam_init_min_excitation_m``), else *provisionally*
   (``slam_provisional``): rotation from the SLAM orientation and the current attitude, scale
   ``slam_provisional_scale`` (or the session's last estimate) under a wide log-scale prior, origin
   placed at the newest pose. In hover the SLAM positions say "not moving" whatever the scale, so
   the velocity is held from the first pose. When the closed-form fit passes its gates, the
   session's alignment chain starts from it and the provisional factors still in the window are
   removed and re-attached to it (left on the provisional alignment, they tied the window to a
   scale the hover had not determined: simulated two-turns causal ATE 4.8 cm against 1.9 cm).
   Slow variables get their own (small) relinearisation threshold; note that iSAM2 fixes the
   linearisation point of every variable a marginal factor involves, so a slow variable is
   relinearised only until its first keyframe leaves the window (the 2 s SLAM segments start
   from the current estimate). Without ``slam_provisional`` (and always for seed 000's per-axis
   model, whose alignment starts when every axis the fit determines has a relative standard error
   below ``slam_init_max_rel_se``) the poses before the closed-form fit are held back and attached
   to the new alignment when their keyframes are still in the window; the others are counted as
   ``slam:before-scale-init``.
4. Update the smoother with timestamps of the new keys and of the slow keys used (refreshed so a
   slow variable stays in the window while it is measured), rounded up to
   ``marginalize_every_s`` blocks so that keyframes leave the window one block at a time.
5. Read the newest state: the causal trajectory.

Causality: the states, slow variables and SLAM alignment use only measurements arrived so far.
Two initial values come from the builder's whole-flight preparation: the gyro bias of the first
keyframe (``GraphOptions.gyro_bias_from_slam``) and, for a flight without an attitude stream, the
attitude track used for gating and for the SLAM scale fit (``attitude_from_slam``). Switch
``gyro_bias_from_slam`` off for a strictly causal run on such flights.

Factorization: iSAM2 eliminates with QR for the first ``startup_qr_s`` seconds, then the window
moves into a Cholesky smoother (the same factors, marginals included, at the same linearisation
point: one full elimination): about 1.2x the updates per second of QR on the benchmark.

Failures: an error from the smoother (``SOLVER_ERRORS``, e.g. "Indeterminate linear system") leaves
it unusable (../shared/GTSAM-NOTES.md). Under Cholesky the failed smoother's factors and values (the
failing update's included) first move into a QR smoother, which survives systems Cholesky does not
(EuRoC MH_01 at 100 s): nothing is lost, counted as ``factorization_fallbacks``. Otherwise the
runner rebuilds a fresh smoother from the last good newest state and slow variables with priors,
re-adds the keyframe without its measurements, counts the failure and goes on; it never crashes on
a solver failure.
"""

from __future__ import annotations

import logging
import math
import time
import tracemalloc
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import gtsam
import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import matrix_to_quat_wxyz
from fgnav.datasets.types import Flight, Trajectory
from fgnav.estimate import Estimate, TimeSeries
from fgnav.keys import B, S, V, X
from fgnav.solvers.graph import GraphBuilder, GraphOptions, MeasurementFactor
from fgnav.solvers.window import TimeOrderedSmoother, move_window

log = logging.getLogger(__name__)

#: What GTSAM raises through its Python wrapper when an update or a read fails (C++
#: ``runtime_error``, ``out_of_range``, ``invalid_argument``; iSAM2 is unusable afterwards).
SOLVER_ERRORS = (RuntimeError, IndexError, ValueError)
#: Implementations of the window (``FixedLagOptions.smoother``).
SMOOTHERS = ("time-ordered", "gtsam")
#: Values of ``FixedLagOptions.engine`` (see :func:`fgnav.solvers.online.resolve_engine`).
ENGINES = ("auto", "push", "prepared")
#: Values of ``FixedLagOptions.vo_worker``.
VO_WORKERS = ("inline", "process")
#: The time-ordered window needs its stamp blocks (one ordering group each) to stay below the keys
#: of one update's new factors (~9 on the benchmark): at most this many blocks per lag, else the
#: runner uses GTSAM's smoother (0.25 s blocks under a 2 s lag: 2x the CPU of 1 s blocks).
MAX_BLOCKS_PER_LAG = 4
#: Seconds between attempts to initialise a SLAM session's alignment (each attempt is a
#: closed-form fit over the session so far; retrying every frame would spike the latency).
SLAM_INIT_RETRY_S = 0.5
#: IMU the push engine's closed-form SLAM fits take either side of their poses [s] (the poses'
#: second differences against the integrated accelerometer): a pose is fitted only where the
#: IMU history reaches this far before it.
SLAM_FIT_IMU_MARGIN_S = 0.6
#: Index offset of the provisional SLAM-alignment keys ``S(PROVISIONAL_KEY_BASE + n)`` (the
#: builder's alignment keys count from 0 per graph).
PROVISIONAL_KEY_BASE = 1_000_000
#: Character codes of the slow-variable symbols (SLAM alignment, drag, ground height).
_SLOW_CHARS = frozenset(map(ord, "sdg"))


def _is_slow(key: int) -> bool:
    """Slow variable (``S``, ``D`` or ``G``)? A GTSAM ``Symbol`` key holds its character in the
    top 8 bits: this avoids building a ``gtsam.Symbol`` per key on the per-update path."""
    return (key >> 56) in _SLOW_CHARS


@dataclass
class FixedLagOptions:
    """Options of the online fixed-lag smoother.

    Attributes:
        graph: graph builder options.
        lag_s: smoother lag [s].
        relinearize_threshold: ISAM2 relinearization threshold of the keyframe states ``X, V, B``
            (largest tangent-space component).
        relinearize_threshold_position: push engine: the same for the translation part of the
            keyframe poses ``X`` [m] (None: ``relinearize_threshold``; the smaller of the two is
            used; the prepared runner always uses ``relinearize_threshold``, and so does the push
            engine with the per-axis SLAM model and during the start's relinearisation without
            an attitude stream: see ``OnlineSmoother._new_smoother``).
            0.5 m let a keyframe position leave the window (marginalised) still linearised at
            its IMU-predicted initial value, a few cm from its estimate: the marginal then holds
            a linearisation error that biases the SLAM scale. Measured 2026-12-02 (push engine,
            EuRoC MH_01, scale walk 3e-4): 0.5 -> 0.003 m, causal ATE 6.27 -> 4.73 cm (lagged
            output 5.95 -> 4.24 cm), final scale error 1.27 -> 0.70 %, NEES 3.5 -> 2.1; V1_02
            ORB-SLAM2 / ORB-SLAM3 keyframes 20.31 / 8.74 -> 20.48 / 7.16 cm; simulated (seed 1,
            camera) two-turns 0.49 -> 0.46, circle 0.43 -> 0.44, rectangle 0.44 -> 0.45,
            figure8 0.52 -> 0.50 cm. Rotation, velocity or bias thresholds of 0.01 alone changed
            nothing (6.2-6.3 cm); 0.01 m gave 4.85 cm; every threshold 0.003 with
            relinearisation at every update 4.74 cm (0.68 %): the linearisation is then spent.
            Opt-in (with ``slam_scale_rw = None``, the default since 2026-12-03, below): MH_01
            causal ATE 4.62 cm, final scale error 0.49 %, NEES 1.90 (lagged output 4.03 cm;
            defaults 6.3 cm, 1.27 %); with the manifest's IMU noise measured in flight
            (2026-12-03) 3.78 cm, 0.05 %, NEES 0.77 (defaults 4.53 cm, 0.48 %). Not the
            default: it costs the 180 s figure8 benchmark without camera ATE
            2.65 -> 2.96 cm and p99 latency 4.6-5.0 -> 12.5-17 ms (every 10th update
            relinearises and re-eliminates the whole window, see below; ``scripts/bench_online.py
            --position-threshold 0.003``, 2026-12-02 20:31, load 0), and it breaks the
            first-estimate rule of iSAM2's marginals (their variables are held, their
            neighbours now relinearised): weakly observed directions get information they
            do not have (circle's per-axis kz 29 % off, hence not with that model; V1_02 NEES
            7.0 / 5.7 -> 10.9 / 6.6, causal ATE 9.36 / 5.34 -> 9.64 / 5.42 cm).
            After an IMU-gap restart it swung the SLAM scale (20 s two-turns without camera,
            8 s gap: -5 % -> +31 % 0.3 s after the restart; 2.56x nominal against the health
            test's 2.5x): the restarted window sees the scale only through its products with the
            velocity and position, whose priors the gap widened, and relinearising the
            positions moved the scale along that near-degenerate direction. The carried
            alignment chain now keeps its first linearisation point during the restart's QR
            start (``OnlineSmoother._carried_chain``): 1.81x; mean ATE over eight restarts
            (seeds 0-1; gaps 6-14, 7-15, 8-11, 10-12 s) 6.68 -> 5.31 cm (old defaults 5.15 cm).
            Without a camera the threshold is neutral to mixed (two-turns seed 1 2.72 -> 3.16
            cm, seed 0 3.38 -> 1.97 cm). Speed: see README (``scripts/bench_online.py``).
            Ruled out as cheaper ways to the same MH_01 gain (2026-12-02 22:00-22:30, MH_01
            push engine, defaults 6.29 cm, +1.27 %,
            NEES 3.69; the keyframe translation's estimate is 18 mm (p50) / 47 mm (p90) from
            its linearisation point when it is marginalised): 3 mm (1 mm) only for the poses of
            the oldest stamp block (the others held for that update) with the graph's scale
            walk 4.94 (4.86) cm, +0.57 % (with 3e-4: 5.01 cm, +0.73 %),
            but the same p99 (17.5 ms, figure8 ATE 2.48 -> 2.73 cm: any relinearised old pose
            re-eliminates the whole time-ordered chain); the two oldest blocks 4.62 cm, +0.60
            %, and for them only in every 3rd / 5th block 5.96 / 6.98 cm; only in the first
            10-40 s 6.25-7.18 cm (the gain accrues over the whole flight, not at take-off);
            only while a pose is among the last 4-20 updates (the root, cheap) 6.9-7.4 cm;
            1 cm 4.95-4.96 cm, +0.67-0.82 %; 2 cm 5.03 cm; rotation at 1 mrad alone 5.38 cm,
            +0.84 %; velocity 3 mm/s or bias 1e-3 alone unchanged; iSAM2's wildfire threshold 0
            unchanged.
            Where the time went (``scripts/profile_online.py``, 2026-12-03, 180 s figure8 benchmark,
            thread CPU time per keyframe update, load 3-5): an update that relinearises at 3 mm
            (every 10th) relinearised 68-77 variables and re-eliminated 117-131 (the window: ~165),
            with 176-188 ``CustomFactor`` callbacks (9-15 ms of its 12-14 ms CPU; a plain update has
            5, a marginalisation 8); covariance and estimate reads 0.2-0.9 ms, unchanged. Those were
            the callbacks of *every* factor of the window: past 65 % of its variables affected,
            iSAM2 re-eliminates in batch and relinearises everything (``fgnav.solvers.window``,
            ballast); re-eliminating from the oldest key with nothing relinearised cost 16.6 ms, 2.5
            ms off the batch path (60 s, load 4). With this option the push engine now pads the
            window with ballast variables (``online.BALLAST_WITH_POSITION_THRESHOLD``):
            relinearising updates 176-182 -> 91-102 callbacks, 12-14 -> 8.7-9.5 ms CPU; CPU p99
            20-21 -> 13-16 ms against 4.8-5.4 ms for the defaults; ``scripts/bench_online.py`` after
            the in-flight IMU noise (06:50, load 3, back to back) defaults 20.0x, p50 1.67 ms, p99
            5.09 ms, ATE 2.65 cm against 3 mm 16.4x, 1.61 ms, 13.1 ms, 2.96 cm: still 2.5-3x the
            defaults' p99, hence still opt-in. The estimates are those without ballast up to the
            elimination order's rounding (MH_01 3 mm 3.784 against 3.775 cm, +0.04 %, NEES 0.77, CPU
            p99 10.2 against 13.4 ms, defaults 4.53 cm, +0.48 %, 4.3 ms; before the in-flight IMU
            noise 4.641 cm either way; V1_02 ORB-SLAM2 / ORB-SLAM3 9.64 / 5.42 cm either way).
            Measured before the in-flight IMU noise on top of the ballast, none a default (MH_01
            push engine, then 6.29 cm, +1.27 %, NEES 3.69 by default, 4.64 cm, +0.49 %, NEES 2.02
            with 3 mm; graph scale walk unless said; bench = 60 s figure8, CPU p99, defaults 4.8-5.5
            ms): the marginal rebuilt at marginalisation from the block's factors linearised at the
            current estimate (``eliminatePartialSequential``, ``LinearContainerFactor`` at the
            estimate) without any relinearisation 5.51 cm, +0.47 %, NEES 3.11 (scale walk 3e-4: 5.66
            cm, +0.73 %; its separator held: 5.42 cm, +0.54 %), but 117 factors linearised (5.5-8.5
            ms), 4-6 ms of elimination and a whole-window re-elimination per block (p99 23-32 ms
            wall), and together with the 3 mm relinearisation worse than without (5.24-5.39 cm,
            +0.59-0.68 %); 3 mm for the oldest one / two blocks only 4.94 / 4.62 cm, +0.57 / +0.60 %
            (bench CPU p99 11.2 / 11.8 ms, 48 / 74 callbacks per relinearisation); one block's poses
            in turn per relinearisation every 3rd update 4.71 cm, +0.57 %, NEES 1.86 (CPU p99 8.9
            ms; every 5th: 4.84 cm, +0.58 %); at most the 12 poses of largest translation delta per
            relinearisation every 3rd update 4.50 cm, +0.64 %, NEES 1.63 (CPU p99 9.0 ms, bench ATE
            3.31 cm against 2.54 cm; 8 every 2nd: 4.53 cm, +0.66 %); relinearizeSkip 1 or 3 at 3 mm:
            p50 5.7-6.0 ms; iSAM2's relinearisation moved off the marginalising updates
            (``force_relinearize``) made no difference above the noise. Whatever the cost, the 3 mm
            threshold loses on the benchmark flight without camera (2.48-2.65 -> 2.96-3.59 cm).
        relinearize_threshold_slow: the same for the slow variables ``S, D, G`` (a provisional
            SLAM scale moves by tens of percent when it becomes observable: its factors must be
            relinearised then).
        relinearize_skip: ISAM2 relinearizes at most every this many updates.
        factorization: ``"CHOLESKY"`` or ``"QR"`` for iSAM2's eliminations. Cholesky is the
            faster (180 s figure8 benchmark: about 1.2x the updates per second of QR, paired),
            QR the more robust on a badly conditioned window (GTSAM-NOTES: Cholesky threw
            "Indeterminate" at the first bias of a 20 Hz CombinedImuFactor chain).
        fallback_factorization: after a solver failure under another factorization, the window
            moves to a smoother with this one (or, if that fails too, the smoother is rebuilt
            with it) for the rest of the flight (None: keep ``factorization``); reported in
            ``Estimate.info["factorization_final"]`` and ``["factorization_fallbacks"]``.
        startup_qr_s: use QR for this many seconds of flight first, then move the window to
            ``factorization`` (lossless: the same factors, marginals included, at the same
            linearisation point in a fresh smoother; one full elimination). The first seconds
            (first bias, hover, SLAM not yet aligned) are where Cholesky failed in the tests.
        startup_relinearize_threshold, startup_relinearize_skip: push engine, a start without
            an attitude stream: the keyframe states' relinearisation during the QR start (None:
            as after it). Such a start's linearisation point is poor (attitude from one
            specific-force mean, velocity and SLAM alignment unknown) and moves by more than
            ``relinearize_threshold`` only rarely:
            relinearising every update until the window moves to ``factorization`` lets the
            alignment converge (causal ATE, EuRoC V1_02 ORB-SLAM3 keyframes 28 -> 9 cm, ORB-SLAM2
            31 -> 20 cm, MH_01 7.0 -> 7.2 cm). With an attitude stream it is not used (simulated
            two-turns without camera: 2.8 -> 5.5 cm with it: the hover's unobservable provisional
            scale moves more).
        slam_init_window_s: seconds of a SLAM session's poses before its closed-form alignment
            is first tried (until then, and until the fit passes its gates, the session uses a
            provisional alignment, or its poses are held back without ``slam_provisional``).
        slam_init_scale_sigma_rel: relative sigma of the prior on the initial SLAM scale.
        slam_init_min_excitation_m: a session's alignment is initialised once the RMS metric
            second difference of its motion (0.5 s half-width) reaches this [m]: below it the
            closed-form scale is dominated by noise (hover; see ``init_slam_alignment``).
        slam_init_max_rel_se: ... and once the fit's relative standard error of the scale is
            below this.
        slam_init_min_pairs: ... and (push engine) once it has this many second-difference pairs
            (the standard error is a lower bound: neighbouring pairs overlap; EuRoC V1_02's
            3 Hz keyframes gave 6 pairs and a scale 22 % off after 4.6 s).
        slam_chain_fuse_provisional: push engine: a session's chain starts from the closed-form
            fit fused (inverse variance in log-scale) with its provisional alignment's estimate
            and marginal, when an earlier session had an alignment (a map reset: the velocity is
            known, so the provisional is well determined; see
            ``OnlineSmoother._fuse_provisional_scale``).
            Measured 2026-12-07, simulated two-turns 25 s with a map reset at 12 s: fit 1.653
            (rel. s.e. 0.29), provisional 1.005, true 0.9965; the new session's final scale 1.045
            -> 1.002, causal ATE 11.8 -> 3.6 cm. A flight's first session is unchanged (its
            provisional marginal is overconfident: two-turns 1.144 +- 9.5 %, true 0.740).
        slam_provisional: before the closed-form fit is possible, attach the SLAM poses to a
            provisional alignment (see module docstring) instead of holding them back.
        slam_provisional_scale: scale of a provisional alignment when the session has no earlier
            estimate and no front-end scale prior [SLAM units per metre].
        slam_provisional_log_scale_sigma: sigma of its log-scale prior. Hover gives the scale no
            information, so a wide prior lets noise move it before the motion starts (simulated
            two-turns, seed 0: sigma 1.0 -> causal ATE 2.2 cm, 0.3 -> 1.9 cm, 0.1 -> 1.9 cm;
            EuRoC MH_01, true scale 5x off the default: 8.5 cm with 0.3 or 1.0). Default 1.0:
            a monocular SLAM's units are arbitrary (EuRoC V1_02: ORB-SLAM2 0.44 per metre,
            ORB-SLAM3 5.0, a log-ratio of -0.8 and +1.6 from the default scale 1), and 0.3 held
            the push engine's provisional scale near 1 until the chain started (V1_02 causal ATE
            with 1.0 vs 0.3: ORB-SLAM2 9.4 vs 19.2 cm, ORB-SLAM3 5.3 vs 8.1 cm, NEES 7.0 / 5.7 vs
            24.5 / 11.4; MH_01 6.29 vs 6.27 cm; two-turns seed 1 0.50 cm both, see README).
        slam_provisional_rot_sigma: sigma of its rotation prior [rad] (initial value from the SLAM
            orientation and the attitude).
        slam_provisional_wait_s, slam_provisional_min_disp_m: push engine, opt-in (0 s: off):
            a session without an earlier scale or a front-end prior holds its first poses back
            for up to ``slam_provisional_wait_s`` until the camera's estimated displacement
            between the session's first and newest pose reaches ``slam_provisional_min_disp_m``;
            the provisional scale is then the SLAM displacement over that displacement (the
            arrived data, IMU-propagated states), else ``slam_provisional_scale`` as before
            (``OnlineSmoother._data_scale``). Measured 2026-12-02 (seed 1, 1.5 s, 0.2 m against
            off): EuRoC V1_02 ORB-SLAM2 keyframes causal ATE 9.36 -> 8.06 cm (provisional scale
            from the data; the default 1 is 2.3x the true 0.44 and pulled the states 0.5 m at
            the second pose, 1.1 s after the first), ORB-SLAM3 keyframes 5.34 -> 7.05 cm (data
            scale 5.61, true 5.01: its start, 4.8-9 s, moves 15-20 cm from the later
            trajectory instead of 10), MH_01 6.29 -> 6.49 cm, two-turns 0.496 -> 0.472 cm. Not
            the default: it loses on two of the four flights.
        slam_provisional_min_poses: push engine, opt-in (1: off): a session without an earlier
            scale or a front-end prior holds its poses back until this many have arrived (3:
            two displacements, the least that makes the scale observable against the start's
            velocity). Two poses give one displacement, which the scale and the velocity since
            the start explain almost equally: on EuRoC V1_02 ORB-SLAM2 keyframes (second pose
            1.1 s after the first) the window's optimum after the second pose, checked with
            Levenberg-Marquardt over the window's factors (marginals at their linearisation
            point), has scale 0.83 against the true 0.44 and the states 0.5-0.9 m off for the
            0.45 s until the third pose, whose optimum is 0.444. Measured 2026-12-05, 3 against
            1, causal ATE own span / lagged [cm]: V1_02 ORB-SLAM2 8.14 / 3.75 -> 6.20 / 3.71,
            ORB-SLAM3 3.46 / 2.45 unchanged (2026-12-07, after the first pose attached at the
            start: 2.95 -> 2.98 cm), MH_01 4.53 / 4.33 -> 4.69 / 4.48 (20 Hz poses:
            held 0.1 s; msf-ekf 4.67, so not the default), the four simulated flights within
            0.01 cm.
        slam_provisional_lone_gap_s: push engine (0: off): while a session's provisional
            alignment has the default scale (no earlier session, front-end prior or data
            scale), a second pose more than this many seconds after the first waits for the
            third, and both attach together (``OnlineSmoother._lone_hold``): over a long single
            displacement the default scale pulls the states by the displacement times the
            scale's error; at 20 Hz nothing waits. Measured 2026-12-07 (with the still
            stretch's accelerometer bias), causal ATE own span: EuRoC V1_02 ORB-SLAM2 (second
            pose 1.1 s after the first) 6.62 -> 5.01 cm; ORB-SLAM3, MH_01 and the simulated
            flights unchanged (nothing waits).
        slam_gap_origin_sigma_m: push engine, Sim(3) chain: a SLAM segment whose predecessor
            has left the window (a SLAM pause longer than the lag) starts from the
            predecessor's last estimate under a prior widened by the walk over the pause; this
            is the prior's origin sigma on top of that walk [m] (its rotation and scale keep
            0.01 rad and 1 %). The predecessor's own origin uncertainty (its marginal: 7-16 cm
            on EuRoC V1_02 ORB-SLAM2) is the world-position gauge that the window's states
            share (their marginal prior keeps it); as an independent prior on the new variable
            it let the first pose after a pause move the SLAM origin instead of correcting the
            drifted state (47.3 s: 19.5 -> 4.6 cm, the velocity left uncorrected, 7.5 cm 0.5 s
            later; UKF 17 -> 2 cm). Measured 2026-12-03 (0.05 m, before -> 0 m, the default),
            EuRoC V1_02 ORB-SLAM2 keyframes causal ATE own span / from 10.3 s / from 20 s 8.43
            / 5.14 / 4.30 -> 8.14 / 4.46 / 3.70 cm (seed 003's UKF 4.69 / 4.69 / 3.45),
            ``fixed-lag@lag`` 4.31 / 3.54 / 3.06 -> 3.75 / 2.80 / 2.26 cm (batch 2.39 / 2.35 /
            2.39); V1_02 ORB-SLAM3 keyframes and MH_01 (no pause longer than the lag)
            unchanged, 3.46 and 4.53 cm. The predecessor's marginal covariance as that prior
            (the correlation with the states dropped) was worse: 9.34 / 6.53 / 4.67 cm; keeping
            the predecessor in the window through the pause 8.97 / 5.33 / 4.06 cm.
        rebuild_rot_sigma [rad], rebuild_pos_sigma [m], rebuild_vel_sigma [m/s],
        rebuild_accel_bias_sigma [m/s^2], rebuild_gyro_bias_sigma [rad/s]: priors of a rebuilt
            smoother on the last good state.
        rebuild_slow_sigma_rel: relative sigma of the priors on slow variables after a rebuild.
        marginalize_every_s: marginalise in blocks: the timestamps given to the smoother are
            rounded up to multiples of this [s], so the window holds between ``lag_s`` and
            ``lag_s + marginalize_every_s`` of keyframes (0: every update). With
            ``smoother="gtsam"`` every marginalisation re-orders the affected part with two
            groups only (marginalised first), which leaves new keys deep in the Bayes tree; with
            the slow variables tied to every keyframe the following updates then re-eliminate
            the whole window and, past iSAM2's batch threshold, relinearise every factor (26 ms
            against 2.6 ms for an incremental update on two-turns): blocks make that rare. The
            time-ordered smoother gives each block its own ordering group. Measurement lateness
            is still checked against ``lag_s``.
        smoother: ``"time-ordered"`` (default): ``fgnav.solvers.window.TimeOrderedSmoother``,
            iSAM2 with constraint groups that keep the Bayes tree in time order (the newest
            keyframe and the slow variables at the root, the oldest block at the leaves:
            marginalisation without re-elimination); ``"gtsam"``:
            ``gtsam.IncrementalFixedLagSmoother`` (the same factors and marginalisation times;
            the causal trajectory agrees within 0.1 mm on two-turns, a test). 180 s figure8
            benchmark (``scripts/bench_online.py``): 22 instead of 30 variables re-eliminated per
            update, none instead of ~100 per
            marginalisation; 1.2-1.5x the updates per second, update p99 2-4 ms instead of
            8-16 ms.
            The time-ordered window needs ``marginalize_every_s >= lag_s / 4`` (one ordering
            group per stamp block; see ``MAX_BLOCKS_PER_LAG``): with smaller blocks (or 0) the
            runner logs a warning and uses ``"gtsam"`` (reported in ``info["smoother"]``).
        fine_levels: time-ordered smoother only: the keys of the last this many updates get one
            ordering group each (newest at the root).
        track_memory: record Python heap peak (tracemalloc; slows the run).
        slow_read_every: read the slow variables (SLAM alignment, drag, ground) from the smoother
            every this many updates (and at the last); the newest state is read at every update.
        engine: how ``fgnav online`` (the ``fixed-lag`` method) runs a flight: ``"push"``, its
            events replayed in arrival order into the push-API smoother
            (:class:`fgnav.solvers.online.OnlineSmoother`: strictly causal, nothing prepared
            from the whole flight); ``"prepared"``, this module's runner over a flight prepared
            as a whole (keyframes on the SLAM and camera times, gyro bias and attitude from the
            whole flight: not strictly causal), kept for comparison; ``"auto"`` (default):
            ``"push"``, which runs every flight and option.
        The push engine's own rules (see :mod:`fgnav.solvers.online`):
        start_wait_s: wait this long after the first IMU sample for a SLAM pose to start at [s].
        init_imu_s: IMU span averaged for the initial attitude [s].
        still_accel_tol [m/s^2], still_gyro_tol [rad/s]: stillness test of the gyro-bias start
            (0 switches it off): a 0.5 s window of the IMU before the start is still when its
            mean specific force is within ``still_accel_tol`` of g and its rate's per-axis
            standard deviation below ``still_gyro_tol`` (EuRoC V1_02 standing with its rotors
            on: 0.002-0.05; its first motion 0.05-0.15).
        clock_jump_s: a stamp older than its stream's newest by more than this is a clock jump
            (IMU: reset), by less an out-of-order sample (rejected) [s].
        max_imu_gap_s: an IMU gap longer than this resets the smoother [s].
        history_s: IMU, attitude, SLAM-pose and keyframe-pose history the push engine keeps for
            its closed-form fits [s]: at least ``slam_fit_max_s`` plus the fits' IMU margin
            (``SLAM_FIT_IMU_MARGIN_S``), the span a SLAM alignment fit may use (checked when
            the options are read). A shorter history cut the fit's span without saying so:
            simulated (seed 1, 24 s, no camera) two-turns / circle causal ATE 0.027 / 0.168 m
            with 30 s, 0.058 / 0.168 with 5 s, 0.065 / 0.818 with 3 s (no fit can span
            ``slam_init_window_s``), 0.061 / 0.695 with 0.
        covariance: read the newest pose and velocity marginals at every keyframe.
        drag_check_s: IMU span of the thrust-axis check of the drag model [s].
        drag_scatter_n: keyframes of the running drag-noise estimate.
        slam_fit_max_s: the closed-form SLAM fit uses the session's last this many seconds [s].
        image_latency_s: with a camera, a keyframe without an image closes only once the IMU is
            this much (plus half a keyframe period) past it, so that an image taken for it
            can still arrive and anchor it [s]: the camera's latency (0 for a replay).
        vo_worker: where the push engine runs the homography VO stage: ``"process"`` in a
            child interpreter (``fgnav.frontends.vo_process``) on another core, so that the
            frames' tracking overlaps the smoother's updates, or ``"inline"`` in the event loop
            (a frame's pair attaches at the keyframe that closes past it). Measured
            (``bench_online.py --camera``, 180 s figure8, back to back): inline 7.1x real time,
            ATE 1.656 cm; process 10.3x, 1.598 cm (delay 1), 12.1x, 1.657 cm (delay 2; on 20 s
            of figure8 0.525 cm inline, 0.529 delay 1, 0.581 delay 2). A
            worker thread is no help: the GIL hand-offs between the VO's Python and the factor
            callbacks cost more than the overlap (8.3x -> 7.4x).
        vo_process_delay_keyframes: with ``vo_worker="process"``, a frame's pair attaches at the
            keyframe update this many keyframes after the one that closes past the frame; that
            update waits for exactly those frames, so the estimate does not depend on the
            child's timing (the newer frames are still being tracked meanwhile).
        lagged_output: also keep each keyframe's state as smoothed just before it leaves the
            window (``OnlineSmoother.lagged_result``: the ``fixed-lag@lag`` row of
            ``fgnav compare``, delayed by the lag).
        slam_trans_rw_m: origin random walk of the push engine's alignment segments
            [m/sqrt(s)] (None: ``graph.slam_trans_rw_m``, which the batch smoother and the
            prepared runner use: 5e-3 since 2026-12-04, 1e-2 before). The push engine keeps
            1e-2: with 5e-3 its causal ATE (2026-12-04) went EuRoC MH_01 4.53 -> 4.19 cm,
            V1_02 ORB-SLAM2 / ORB-SLAM3 own span 8.14 / 3.46 -> 7.97 / 3.33 cm (from 20 s
            3.70 / 2.58 -> 3.47 / 2.44), but MH_01's final scale error 0.48 -> 0.60 % (the
            goal is 0.5 %), ORB-SLAM2's 1.27 -> 1.32 %, circle's per-axis kz off by 7 %, and
            the restart after an 8 s IMU gap cost 2.82x nominal instead of 2.44x (same
            absolute ATE, a better nominal). With ``relinearize_threshold_position = 0.01``
            as well (opt-in, 2026-12-04): MH_01 3.75 cm, final scale error 0.30 %, NEES 0.93;
            V1_02 ORB-SLAM2 / ORB-SLAM3 7.93 / 3.31 cm (from 20 s 3.36 / 2.38); simulated
            (seed 1, camera) two-turns 0.52 -> 0.46, figure8 0.53 -> 0.51 cm; the 180 s
            figure8 benchmark without camera 2.65 -> 2.48 cm, 34.6x -> 32.6x, p99 2.5 -> 3.9
            ms; but a simulated SLAM map reset (two-turns, 25 s, new session at 12 s) 11.8 ->
            17.1 cm (14.6 with the threshold alone, 12.5 with the walk alone), and circle's
            per-axis kz 7 % off: not the default.
        slam_scale_rw: relative SLAM scale random walk of the push engine's alignment
            segments [1/sqrt(s)] (None: ``graph.slam_scale_rw``, which the batch smoother and the
            prepared runner use). Until 2026-12-03 3e-4: the graph's 1e-3 was tuned for the
            simulator's 1e-4/s
            drift; ORB-SLAM3 on MH_01 measures -2.7e-5 +- 2.6e-5 per second. Measured
            2026-12-02, causal ATE EuRoC MH_01 7.17 -> 6.27 cm (NEES 4.8 -> 3.5; final scale
            error 1.24 -> 1.27 %), two-turns 0.966 -> 0.972 cm, figure8 1.134 -> 1.123 cm, V1_02
            ORB-SLAM2 / ORB-SLAM3 keyframes 20.30 / 8.78 -> 20.31 / 8.74 cm. The batch keeps
            1e-3 (3e-4 there: MH_01 3.78 -> 3.82 cm). The bias at take-off that 3e-4 partly
            held back is the 0.5 m position relinearisation threshold's: with
            ``relinearize_threshold_position = 0.003``, 3e-4 -> None (1e-3), measured the same
            evening: MH_01 causal ATE 4.73 -> 4.61 cm, final scale error 0.70 -> 0.49 %
            (mean over time 0.91 -> 0.77 %), NEES 2.07 -> 1.86; V1_02 ORB-SLAM2 / ORB-SLAM3
            keyframes 20.48 / 7.16 -> 20.49 / 7.22 cm; simulated (seed 1, camera) two-turns,
            circle, rectangle, figure8 0.46 / 0.44 / 0.45 / 0.50 -> 0.46 / 0.44 / 0.43 /
            0.50 cm (final scale error rectangle -0.35 -> -0.51 %, figure8 -0.06 -> +0.02 %).
            None (the graph's 1e-3) goes with the 3 mm position threshold (opt-in).
            Default None since 2026-12-03: with the EuRoC manifests' IMU noise measured in flight
            (accelerometer 8x, gyro 6x the densities at rest; ``scripts/euroc_imu_noise.py``)
            3e-4 -> None gives MH_01 causal ATE 4.69 -> 4.53 cm, final scale error 0.70 ->
            0.48 %, NEES 1.11 -> 1.09; V1_02 ORB-SLAM2 / ORB-SLAM3 8.43 / 3.47 -> 8.43 / 3.46
            cm (scale error 1.15 / 0.86 -> 1.19 / 1.12 %); simulated (seed 1, camera)
            two-turns, figure8, rectangle, circle 0.496 / 0.510 / 0.405 / 0.407 -> 0.490 /
            0.514 / 0.410 / 0.396 cm, without camera two-turns 2.820 -> 2.822, figure8 3.384 ->
            3.407 cm. The at-rest densities had made the IMU overconfident, and the tighter walk
            had partly made up for it.
        range_gate_m, range_gate_run: push engine: a range reading whose innovation against
            the keyframe's current estimate and ground height exceeds ``range_gate_m`` (or 10 %
            of the reading, if larger; 0: no gate) is dropped (``range:outlier``); a run of
            ``range_gate_run`` refused readings that agree with each other is a step in the
            terrain (or the height gone wrong): the ground-height variable starts anew from the
            next keyframe (``range:terrain-step``; simulated rectangle over a 0.5 m platform:
            causal ATE 18.2 -> 2.4 cm, the height within 3.2 cm instead of 0.65 m). The robust
            kernel alone let one reading move the window through iSAM2's single Gauss-Newton
            step per update (simulated two-turns seed 1, the first reading 1.81 m against 3.45:
            the third keyframe 30 cm high).
        slam_check_max_s: with ``graph.slam_rotation = "auto"``, give the SLAM-vs-gyro check
            this much SLAM time to decide the rotation convention [s]; until it decides, the
            SLAM orientations are not used as factors.
    """

    graph: GraphOptions = field(default_factory=GraphOptions)
    lag_s: float = 2.0
    relinearize_threshold: float = 0.5
    relinearize_threshold_position: float | None = None
    relinearize_threshold_slow: float = 0.01
    relinearize_skip: int = 10
    factorization: str = "CHOLESKY"
    fallback_factorization: str | None = "QR"
    startup_qr_s: float = 10.0
    startup_relinearize_threshold: float | None = 0.05
    startup_relinearize_skip: int = 1
    slam_init_window_s: float = 3.0
    slam_init_scale_sigma_rel: float = 0.2
    slam_init_min_excitation_m: float = 0.01
    slam_init_max_rel_se: float = 0.3
    slam_init_min_pairs: int = 12
    slam_chain_fuse_provisional: bool = True
    slam_provisional: bool = True
    slam_provisional_scale: float = 1.0
    slam_provisional_log_scale_sigma: float = 1.0
    slam_provisional_rot_sigma: float = 0.3
    slam_provisional_min_disp_m: float = 0.2
    slam_provisional_wait_s: float = 0.0
    slam_provisional_min_poses: int = 1
    slam_provisional_lone_gap_s: float = 0.25
    slam_gap_origin_sigma_m: float = 0.0
    rebuild_rot_sigma: float = 0.01
    rebuild_pos_sigma: float = 0.05
    rebuild_vel_sigma: float = 0.1
    rebuild_accel_bias_sigma: float = 0.05
    rebuild_gyro_bias_sigma: float = 0.005
    rebuild_slow_sigma_rel: float = 0.05
    marginalize_every_s: float = 1.0
    smoother: str = "time-ordered"
    fine_levels: int = 4
    track_memory: bool = False
    slow_read_every: int = 5
    engine: str = "auto"
    start_wait_s: float = 5.0
    init_imu_s: float = 0.2
    still_accel_tol: float = 0.3
    still_gyro_tol: float = 0.025
    clock_jump_s: float = 1.0
    max_imu_gap_s: float = 0.5
    history_s: float = 30.0
    covariance: bool = True
    drag_check_s: float = 0.5
    drag_scatter_n: int = 200
    slam_fit_max_s: float = 20.0
    slam_trans_rw_m: float | None = 1e-2
    slam_scale_rw: float | None = None
    slam_check_max_s: float = 300.0
    image_latency_s: float = 0.0
    range_gate_m: float = 0.2
    range_gate_run: int = 5
    vo_worker: str = "process"
    vo_process_delay_keyframes: int = 1
    lagged_output: bool = True

    def validate(self) -> None:
        """The rules a single value's check does not cover (run when the options are read)."""
        choices = {
            "factorization": ("CHOLESKY", "QR"),
            "fallback_factorization": ("CHOLESKY", "QR", None),
            "smoother": SMOOTHERS,
            "engine": ENGINES,
            "vo_worker": VO_WORKERS,
        }
        for name, valid in choices.items():
            value = getattr(self, name)
            # The factorizations are matched without case, as _isam2_params takes them.
            key = (
                value.upper()
                if name.endswith("factorization") and isinstance(value, str)
                else value
            )
            if key not in valid:
                shown = ", ".join("none" if v is None else str(v) for v in valid)
                raise ValueError(f"FixedLagOptions.{name}={value!r}: expected one of {shown}")
        if self.lag_s < 2.0 / self.graph.keyframe_hz:
            # A window of fewer than 2 keyframe intervals: 0.001 s ran with an ATE 17x worse
            # and health ok.
            raise ValueError(
                f"FixedLagOptions.lag_s={self.lag_s:g}: expected >= 2 / keyframe_hz = "
                f"{2.0 / self.graph.keyframe_hz:g} s (two keyframe intervals)"
            )
        if self.history_s < self.slam_fit_max_s + SLAM_FIT_IMU_MARGIN_S - 1e-9:
            # A history shorter than the closed-form SLAM fit's span cut the fit without saying
            # so (0 ran 2.3x / 4.1x worse on simulated two-turns / circle, health "ok").
            raise ValueError(
                f"FixedLagOptions.history_s={self.history_s:g}: expected >= slam_fit_max_s + "
                f"{SLAM_FIT_IMU_MARGIN_S:g} = {self.slam_fit_max_s + SLAM_FIT_IMU_MARGIN_S:g} s "
                "(the IMU and SLAM poses a closed-form SLAM fit uses, with its IMU margin)"
            )
        if self.range_gate_run < 2:
            raise ValueError(
                f"FixedLagOptions.range_gate_run={self.range_gate_run}: expected >= 2 (readings "
                "that agree with each other: a terrain step)"
            )


def relinearize_thresholds(o: FixedLagOptions, slow_dims: dict[str, int]) -> dict[str, np.ndarray]:
    """iSAM2's relinearisation threshold per variable symbol, one per tangent component:
    ``relinearize_threshold`` for ``X, V, B`` (the pose translation
    ``relinearize_threshold_position``, when set, if smaller), ``relinearize_threshold_slow``
    for the slow variables of ``slow_dims`` (symbol -> tangent dimension)."""
    out: dict[str, np.ndarray] = {}
    for c, dim in {"x": 6, "v": 3, "b": 6}.items():
        thr = np.full(dim, float(o.relinearize_threshold))
        if c == "x" and o.relinearize_threshold_position is not None:
            # Pose3 tangent [rotation, translation]: the position's own threshold.
            thr[3:] = min(o.relinearize_threshold, o.relinearize_threshold_position)
        out[c] = thr
    for c, dim in slow_dims.items():
        out[c] = np.full(dim, float(o.relinearize_threshold_slow))
    return out


def _isam2_params(
    o: FixedLagOptions, slow_dims: dict[str, int], factorization: str | None = None
) -> gtsam.ISAM2Params:
    """ISAM2 parameters; ``slow_dims``: tangent dimension of each slow-variable symbol;
    ``factorization`` overrides ``o.factorization``."""
    p = gtsam.ISAM2Params()
    thresholds = gtsam.ISAM2ThresholdMap()
    for c, thr in relinearize_thresholds(o, slow_dims).items():
        thresholds.insert((c, thr))
    # TimeOrderedSmoother's ballast variables (1-D, never moved: see fgnav.solvers.window).
    thresholds.insert(("z", np.ones(1)))
    p.setRelinearizeThreshold(thresholds)
    p.relinearizeSkip = int(o.relinearize_skip)
    p.setFactorization((factorization or o.factorization).upper())
    p.findUnusedFactorSlots = True
    return p


def rebuild_state_priors(
    k: int, pose: gtsam.Pose3, vel: np.ndarray, bias: Any, o: FixedLagOptions
) -> gtsam.NonlinearFactorGraph:
    """Priors of a rebuilt smoother on the last good keyframe state ``X(k), V(k), B(k)`` (sigmas
    ``o.rebuild_*``)."""
    g = gtsam.NonlinearFactorGraph()
    pose_sig = np.r_[[o.rebuild_rot_sigma] * 3, [o.rebuild_pos_sigma] * 3]
    g.add(gtsam.PriorFactorPose3(X(k), pose, gtsam.noiseModel.Diagonal.Sigmas(pose_sig)))
    g.add(
        gtsam.PriorFactorVector(
            V(k), np.asarray(vel, float), gtsam.noiseModel.Isotropic.Sigma(3, o.rebuild_vel_sigma)
        )
    )
    g.add(
        gtsam.PriorFactorConstantBias(
            B(k),
            bias,
            gtsam.noiseModel.Diagonal.Sigmas(
                np.r_[[o.rebuild_accel_bias_sigma] * 3, [o.rebuild_gyro_bias_sigma] * 3]
            ),
        )
    )
    return g


class FixedLagRunner:
    """Streams one flight through an iSAM2 fixed-lag window (see module docstring).

    Args:
        flight: the flight (ground truth never used).
        options: smoother options.
        priors: optional front-end priors (see :class:`GraphBuilder`).
    """

    def __init__(self, flight: Flight, options: FixedLagOptions | None = None, priors: Any = None):
        self.options = options or FixedLagOptions()
        self.builder = GraphBuilder(flight, self.options.graph, priors)
        self.period = 1.0 / self.options.graph.keyframe_hz
        for name, val in (
            ("factorization", self.options.factorization),
            ("fallback_factorization", self.options.fallback_factorization or "QR"),
        ):
            if str(val).upper() not in ("QR", "CHOLESKY"):
                raise FlightDataError(f"FixedLagOptions.{name}={val!r}: expected QR or CHOLESKY")
        if self.options.smoother not in SMOOTHERS:
            raise FlightDataError(
                f"FixedLagOptions.smoother={self.options.smoother!r}: expected one of "
                f"{', '.join(SMOOTHERS)}"
            )
        if not (isinstance(self.options.fine_levels, int) and self.options.fine_levels >= 0):
            raise FlightDataError(
                f"FixedLagOptions.fine_levels={self.options.fine_levels!r}: expected an integer "
                ">= 0"
            )
        self.window_stats = {"reorders": 0, "unordered_updates": 0}
        self.smoother_kind = self.options.smoother
        blk = self.options.marginalize_every_s
        if self.smoother_kind == "time-ordered" and not (
            blk > 0 and self.options.lag_s / blk <= MAX_BLOCKS_PER_LAG
        ):
            log.warning(
                "fixed-lag: marginalize_every_s=%g with lag_s=%g gives more stamp blocks than the "
                "time-ordered window can order with the keys of one update; using GTSAM's "
                "IncrementalFixedLagSmoother (choose marginalize_every_s >= lag_s / %d)",
                blk,
                self.options.lag_s,
                MAX_BLOCKS_PER_LAG,
            )
            self.smoother_kind = "gtsam"
        self.factorization = self.options.factorization.upper()
        if self.options.startup_qr_s > 0 and self.factorization != "QR":
            self.factorization = "QR"
            self._switch_to: str | None = self.options.factorization.upper()
        else:
            self._switch_to = None
        self.smoother: Any = None
        self._theta_view: gtsam.Values | None = None
        self._install(self._new_smoother(self.factorization))
        self.k_next = 0
        self.t_latest = -math.inf
        self.key_stamp: dict[int, float] = {}
        self.keyframes_in: set[int] = set()
        self.pending: list[MeasurementFactor] = []
        self.queued: list[MeasurementFactor] = []
        self.dropped: dict[str, int] = {}
        self.used: dict[str, int] = {}
        self.n_failures = 0
        self.n_fallbacks = 0
        self._transplanted = False
        self.failure_messages: list[str] = []
        self.slam_scale_init: dict[int, float] = {}
        self._held: dict[int, list[int]] = {}
        self._axis_sigma_rel: dict[int, np.ndarray] = {}
        self.session_ready: dict[int, bool] = {}
        self.session_scale: dict[int, float] = {}
        self.provisional_alignments: list[tuple[int, float]] = []
        self.provisional_key: dict[int, int] = {}
        # Provisional SLAM factors in the smoother: session -> [(factor index, keyframe, row)];
        # re-attached to the session's first closed-form alignment when it is created.
        self.provisional_factors: dict[int, list[tuple[int, int, int]]] = {}
        self._provisional_rows: dict[int, tuple[int, int, int]] = {}
        self._reattach: dict[int, int] = {}
        self.first_pose = gtsam.Pose3()
        self.last_good: dict[int, Any] = {}
        self.newest_k = -1
        # Causal outputs.
        self.out_t: list[float] = []
        self.out_pose: list[gtsam.Pose3] = []
        self.out_vel: list[np.ndarray] = []
        self.out_bias: list[gtsam.imuBias.ConstantBias] = []
        self.latency: list[float] = []
        self.slow_track: dict[str, list[tuple[float, np.ndarray]]] = {}
        self._all_meas = self._measurement_stream()
        self._meas_i = 0
        self._deferred: list[tuple[float, int, str, int]] = []
        self._sess_last_t: dict[int, float] = {}
        self._next_init_try: dict[int, float] = {}
        self.created_slow: set[int] = set()
        self.ever_created: set[int] = set()
        self.newest_good_k = 0
        self.queued_graph = gtsam.NonlinearFactorGraph()
        self.queued_values = gtsam.Values()
        self.queued_stamps: dict[int, float] = {}

    # ------------------------------------------------------------------------------------------
    # Measurement stream
    # ------------------------------------------------------------------------------------------

    def _measurement_stream(self) -> list[tuple[float, int]]:
        """(arrival time, keyframe) of every keyframe's measurement group, sorted by arrival.

        Factors are built lazily per keyframe (see :meth:`_factors_of`) so that SLAM noise uses
        the causal initial scale.
        """
        b = self.builder
        rows: list[tuple[float, int, str, int]] = []
        if b.use_slam:
            slam = b.flight.slam
            for r, (i, k) in enumerate(
                zip(b.slam_assoc.meas_index, b.slam_assoc.keyframe, strict=True)
            ):
                rows.append((float(slam.t[i] + b.slam_latency[i]), int(k), "slam", r))
        if b.use_range:
            for n, k in enumerate(b.range_kf):
                rows.append((float(b.range_arrival[n]), int(k), "range", n))
        for n, k in enumerate(b.contact_kf):
            rows.append((float(b.contact_arrival[n]), int(k), "contact", n))
        if b.use_yaw:
            for n, k in enumerate(b.yaw_kf):
                rows.append((float(b.yaw_arrival[n]), int(k), "yaw", n))
        if b.use_drag:
            for k in np.flatnonzero(b.drag_count > 0):
                rows.append((float(b.drag_arrival[k]), int(k), "drag", int(k)))
        if b.vision is not None:
            # Homography pairs arrive with frame j and tie keyframes i and j (both in the window).
            rows.extend(b.vision.stream_rows())
        if b.flow is not None:
            # A flow window arrives with its newest reading (half a period after its keyframe).
            for k in b.flow.keyframes():
                rows.append((b.flow.arrival(k), int(k), "flow", int(k)))
        rows.sort(key=lambda r: (r[0], r[1]))
        return rows

    def _make_factors(self, kind: str, k: int, row: int) -> list[MeasurementFactor]:
        """The factors of one measurement (empty when it cannot be used yet or any more)."""
        b = self.builder
        if kind == "slam":
            sk = b.slam_key(row)
            key = self._slam_variable(sk, row)
            if key is None:
                return []
            if key != sk:
                return [self._provisional_factor(k, row, key)]
            return b.measurement_factors(
                k, {sk: self.slam_scale_init.get(sk, 1.0)}, kinds=("slam",)
            )
        return b.measurement_factors(k, kinds=(kind,))

    # ------------------------------------------------------------------------------------------
    # Slow variables
    # ------------------------------------------------------------------------------------------

    def _alive(self, key: int) -> bool:
        """Key inside the lag (with one keyframe period of margin) and not marginalised by the
        smoother (block timestamps, see ``marginalize_every_s``)."""
        t = self.key_stamp.get(key)
        if t is None or t < self.t_latest - self.options.lag_s + self.period:
            return False
        blk = self.options.marginalize_every_s
        if not blk > 0:
            return True
        return self._block(t) >= self._block(self.t_latest) - self.options.lag_s

    def _block(self, t: float) -> float:
        """End of the ``marginalize_every_s`` block of time t [s]."""
        blk = self.options.marginalize_every_s
        return math.ceil(t / blk - 1e-9) * blk

    def _current_value(self, key: int) -> Any:
        c = chr(gtsam.Symbol(key).chr())
        if c == "s" and self.builder.slam_model == "sim3":
            return self.smoother.calculateEstimateSimilarity3(key)
        return self.smoother.calculateEstimateVector(key)

    def _slam_variable(self, sk: int, row: int) -> int | None:
        """The alignment variable the SLAM measurement ``row`` attaches to (created if needed):
        the builder's ``sk``, or a provisional variable while the session's scale is not
        initialised; None when the measurement must be skipped."""
        b = self.builder
        o = self.options
        if sk in self.ever_created:
            if self._alive(sk):
                return sk
            self._drop("slam:alignment-marginalized")
            return None
        slam = b.flight.slam
        i = int(b.slam_assoc.meas_index[row])
        session = int(slam.session[i])
        prev = b.slow_chain_previous(sk)
        if prev is not None and self._alive(prev):
            value = self._current_value(prev)
            self.slam_scale_init[sk] = self.slam_scale_init.get(prev, 1.0)
            self._create_slow(sk, value, b.slow_factors(sk, value, chain_start=False))
            return sk
        # Chain start: a new session, or a gap longer than the lag.
        first_t = float(slam.t[slam.session == session][0])
        value = None
        if self.t_latest >= first_t + o.slam_init_window_s and self.t_latest >= (
            self._next_init_try.get(session, -math.inf)
        ):
            self._next_init_try[session] = self.t_latest + SLAM_INIT_RETRY_S
            value, scale = self._init_slam_value(session, sk, i)
        if value is not None:
            sig_rel = self._axis_sigma_rel.pop(session, None) if b.slam_model == "axis" else None
            prior = b.slow_factors(
                sk,
                value,
                chain_start=True,
                scale_sigma_rel=o.slam_init_scale_sigma_rel if sig_rel is None else sig_rel,
            )
            if self.provisional_factors.get(session):
                self._reattach[session] = sk
            self._release_held(session, sk)
        elif not (o.slam_provisional and b.slam_model == "sim3"):
            # Held back: attached to the alignment when it is created if its keyframe is still
            # in the window (counted as dropped until then).
            self._drop("slam:before-scale-init")
            self._held.setdefault(session, []).append(row)
            return None
        elif session in self.session_scale:
            # A gap in an initialised session: restart its chain at the last scale estimate.
            value, scale = self._provisional_slam_value(session)
            prior = b.slow_factors(
                sk, value, chain_start=True, scale_sigma_rel=o.slam_init_scale_sigma_rel
            )
        else:
            return self._provisional_variable(session)
        self.slam_scale_init[sk] = scale
        self.session_scale[session] = scale
        self._create_slow(sk, value, prior)
        return sk

    def _release_held(self, session: int, sk: int) -> None:
        """Attach the session's held-back SLAM poses whose keyframes are still in the window to
        its new alignment ``sk`` (queued like late measurements)."""
        b = self.builder
        for row in self._held.pop(session, []):
            k = int(b.slam_assoc.keyframe[row])
            if b.t_kf[k] < self.t_latest - self.options.lag_s + self.period:
                continue
            self.dropped["slam:before-scale-init"] -= 1
            m = self._provisional_factor(k, row, sk)
            self._provisional_rows.pop(id(m.factor), None)
            self.pending.append(m)
        if self.dropped.get("slam:before-scale-init") == 0:
            del self.dropped["slam:before-scale-init"]

    def _provisional_variable(self, session: int) -> int:
        """The live provisional alignment of ``session`` (a new one when none is alive)."""
        pk = self.provisional_key.get(session)
        if pk is not None and self._alive(pk):
            return pk
        pk = S(PROVISIONAL_KEY_BASE + len(self.provisional_alignments))
        value, scale = self._provisional_slam_value(session)
        self.provisional_key[session] = pk
        self.provisional_alignments.append((session, self.t_latest))
        self.slam_scale_init[pk] = scale
        self._create_slow(pk, value, self._provisional_slam_prior(pk, value))
        return pk

    def _provisional_factor(self, k: int, row: int, pk: int) -> MeasurementFactor:
        """SLAM position factor of association ``row`` (keyframe k) on alignment ``pk`` (a
        provisional one, or the session's first alignment for poses held back before it)."""
        from fgnav.factors.slam_scale import make_slam_axis_offset_factor, make_slam_position_factor

        b = self.builder
        slam = b.flight.slam
        i = int(b.slam_assoc.meas_index[row])
        noise = b._noise(3, b.options.slam_sigma_m * self.slam_scale_init.get(pk, 1.0))
        body_T_cam = np.asarray(b.flight.calib.body_T_cam, float)
        if b.slam_model == "axis":
            fac = make_slam_axis_offset_factor(
                X(k), pk, slam.slam_t_cam[i], noise, body_T_cam[:3, 3]
            )
        else:
            fac = make_slam_position_factor(X(k), pk, slam.slam_t_cam[i], body_T_cam, noise)
        arrival = float(slam.t[i] + b.slam_latency[i])
        self._provisional_rows[id(fac)] = (int(slam.session[i]), k, row)
        return MeasurementFactor(arrival, k, "slam", fac, (X(k), pk))

    def _reattach_provisional(self, graph: gtsam.NonlinearFactorGraph) -> list[int]:
        """Move the provisional SLAM factors still in the window onto the session's new
        closed-form alignment: their poses then shape the window with the fitted scale instead of
        the provisional one. Adds the new factors to ``graph``; returns the indices to remove."""
        remove: list[int] = []
        for session, sk in self._reattach.items():
            for idx, k, row in self.provisional_factors.pop(session, []):
                if not self._alive(X(k)):
                    continue
                remove.append(idx)
                fac = self._provisional_factor(k, row, sk).factor
                self._provisional_rows.pop(id(fac), None)
                graph.add(fac)
        self._reattach = {}
        return remove

    def _create_slow(self, key: int, value: Any, prior: gtsam.NonlinearFactorGraph) -> None:
        """Queue a new slow variable with its prior or random-walk factors."""
        self.queued_graph.push_back(prior)
        self.queued_values.insert(key, value)
        self.queued_stamps[key] = self.t_latest
        self.key_stamp[key] = self.t_latest
        self.created_slow.add(key)
        self.ever_created.add(key)

    def _newest_world_t_cam(self) -> tuple[np.ndarray, np.ndarray]:
        """``world_R_cam`` and ``world_t_cam`` of the newest keyframe's estimate (before the first
        update: the first keyframe's initial value)."""
        b = self.builder
        pose = self.last_good[X(self.newest_k)] if self.newest_k >= 0 else self.first_pose
        body_T_cam = np.asarray(b.flight.calib.body_T_cam, float)
        world_R_body = pose.rotation().matrix()
        world_t_cam = pose.translation() + world_R_body @ body_T_cam[:3, 3]
        return world_R_body @ body_T_cam[:3, :3], world_t_cam

    def _nearest_slam_row(self, session: int) -> int:
        """Row of the session's arrived SLAM pose closest in time to the newest keyframe."""
        b = self.builder
        slam = b.flight.slam
        arrived = slam.t + b.slam_latency <= self.t_latest
        rows = np.flatnonzero((slam.session == session) & arrived)
        t_ref = b.t_kf[max(self.newest_k, 0)]
        return int(rows[np.argmin(np.abs(slam.t[rows] - t_ref))])

    def _provisional_slam_value(self, session: int) -> tuple[Any, float]:
        """Provisional alignment of a session whose scale is not observable yet (causal).

        Rotation ``slam_R_world = slam_R_cam (world_R_cam)^T`` from the SLAM orientation and the
        newest attitude estimate; scale: the session's last estimate, else the front-end prior,
        else ``slam_provisional_scale``; origin such that the SLAM pose nearest the newest keyframe
        maps onto its camera position.
        """
        from fgnav.datasets.geometry import quat_wxyz_to_matrix
        from fgnav.factors.slam_scale import make_slam_T_world

        b = self.builder
        slam = b.flight.slam
        scale = self.session_scale.get(session)
        if scale is None:
            prior = b._prior_scale(session)
            scale = prior if prior is not None else self.options.slam_provisional_scale
        j = self._nearest_slam_row(session)
        world_R_cam, world_t_cam = self._newest_world_t_cam()
        slam_R_world = quat_wxyz_to_matrix(slam.slam_q_cam_wxyz[j]) @ world_R_cam.T
        slam_t_world = slam.slam_t_cam[j] - scale * slam_R_world @ world_t_cam
        log.info(
            "SLAM session %d: provisional alignment at t=%.2f (scale %.4g, log-scale sigma %.2g)",
            session,
            self.t_latest,
            scale,
            self.options.slam_provisional_log_scale_sigma,
        )
        return make_slam_T_world(float(scale), slam_R_world, slam_t_world), float(scale)

    def _provisional_slam_prior(self, key: int, value: Any) -> gtsam.NonlinearFactorGraph:
        """Wide prior on a provisional alignment (tangent ``[omega, u, lambda]``)."""
        o = self.options
        g = gtsam.NonlinearFactorGraph()
        sig = np.r_[
            [o.slam_provisional_rot_sigma] * 3,
            [10.0] * 3,
            [o.slam_provisional_log_scale_sigma],
        ]
        g.add(gtsam.PriorFactorSimilarity3(key, value, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        return g

    def _init_slam_value(self, session: int, sk: int, meas_i: int) -> tuple[Any, float]:
        """Causal closed-form SLAM alignment from the data arrived so far."""
        b = self.builder
        from fgnav.factors.slam_scale import make_slam_T_world

        try:
            if b.slam_model == "axis":
                return self._init_axis_value(session)
            init = b.init_session(session, t_limit=self.t_latest)
        except FlightDataError as e:
            log.debug("SLAM session %d: not initialised at t=%.2f: %s", session, self.t_latest, e)
            return None, 0.0
        if (
            init.excitation < self.options.slam_init_min_excitation_m
            or not init.scale_rel_se <= self.options.slam_init_max_rel_se
        ):
            return None, 0.0
        log.info(
            "SLAM session %d initialised at t=%.2f: scale %.4g (excitation %.3f m)",
            session,
            self.t_latest,
            init.scale,
            init.excitation,
        )
        # Place the SLAM origin so that the newest keyframe's SLAM position matches the smoother.
        slam = b.flight.slam
        _, world_t_cam = self._newest_world_t_cam()
        j = self._nearest_slam_row(session)
        slam_t_world = slam.slam_t_cam[j] - init.scale * init.slam_R_world @ world_t_cam
        return make_slam_T_world(init.scale, init.slam_R_world, slam_t_world), init.scale

    def _init_axis_value(self, session: int) -> tuple[Any, float]:
        """Causal per-axis alignment ``[k, o]`` (seed 000's model): the closed-form per-axis
        scale once every axis it determines has a relative standard error below
        ``slam_init_max_rel_se``; the origin offset ``o`` maps the newest keyframe's camera
        position onto the SLAM pose nearest in time (the world origin stays at the first
        keyframe)."""
        b = self.builder
        k, rel_se = b.init_axis_fit(self.t_latest, session)
        finite = rel_se[np.isfinite(rel_se)]
        if not len(finite) or finite.max() > self.options.slam_init_max_rel_se:
            log.debug(
                "per-axis SLAM scale not initialised at t=%.2f: rel. s.e. %s",
                self.t_latest,
                np.round(rel_se, 3),
            )
            return None, 0.0
        _, world_t_cam = self._newest_world_t_cam()
        j = self._nearest_slam_row(session)
        o = b.flight.slam.slam_t_cam[j] - k * world_t_cam
        # Prior on k from the fit: its relative standard error per axis (at least 2 %; an axis
        # the fit does not determine keeps the initial-prior width).
        self._axis_sigma_rel[session] = np.where(
            np.isfinite(rel_se),
            np.maximum(rel_se, 0.02),
            self.options.slam_init_scale_sigma_rel,
        )
        log.info(
            "per-axis SLAM alignment initialised at t=%.2f: k %s (rel. s.e. %s)",
            self.t_latest,
            np.round(k, 4),
            np.round(rel_se, 3),
        )
        return np.r_[k, o], float(np.max(k))

    # ------------------------------------------------------------------------------------------
    # Updates
    # ------------------------------------------------------------------------------------------

    def _drop(self, reason: str, n: int = 1) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + n

    def _block_stamps(self, stamps: dict[int, float]) -> dict[int, float]:
        """Timestamps given to the smoother: rounded up to ``marginalize_every_s`` blocks."""
        if not self.options.marginalize_every_s > 0:
            return stamps
        return {key: self._block(t) for key, t in stamps.items()}

    def update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, float],
        remove: list[int] | None = None,
    ) -> bool:
        """One smoother update (``remove``: indices of factors to remove).

        On failure under a factorization other than ``fallback_factorization`` (Cholesky), the
        failed smoother's factors (this update's included) and linearisation point are moved into
        a fresh smoother with the fallback (QR): nothing is lost, counted as
        ``factorization_fallbacks``, returns True. Otherwise (or if that fails too) the smoother is
        rebuilt from the last good estimate with priors, counted as a solver failure, returns
        False."""
        self._transplanted = False
        try:
            self.smoother.update(graph, values, self._block_stamps(stamps), list(remove or []))
            return True
        except SOLVER_ERRORS as e:
            msg = " ".join(str(e).split())[:200]
            fb = (self.options.fallback_factorization or "").upper()
            if fb and fb != self.factorization:
                log.warning(
                    "fixed-lag: %s update failed at t=%.3f (%s); moving the window to %s",
                    self.factorization,
                    self.t_latest,
                    msg,
                    fb,
                )
                if self._switch_factorization(fb):
                    self.n_fallbacks += 1
                    self._switch_to = None
                    self._transplanted = True
                    return True
            self.n_failures += 1
            self.failure_messages.append(msg)
            log.warning(
                "fixed-lag: smoother update failed at t=%.3f (%s); rebuilding from the last "
                "good estimate",
                self.t_latest,
                msg,
            )
            self._rebuild()
            return False

    def _new_smoother(self, factorization: str) -> Any:
        # The prepared runner keeps the keyframe threshold for the pose translation too (the
        # 3 mm one was measured on the push engine only).
        o = replace(self.options, relinearize_threshold_position=None)
        params = _isam2_params(o, self.builder.slow_dims(), factorization)
        if self.smoother_kind == "gtsam":
            return gtsam.IncrementalFixedLagSmoother(self.options.lag_s, params)
        return TimeOrderedSmoother(self.options.lag_s, params, self.options.fine_levels)

    def _install(self, smoother: Any) -> None:
        """Make ``smoother`` the current one: the replaced one's window counters go into
        ``window_stats``. For ``IncrementalFixedLagSmoother`` keep a Python view of its
        linearisation point, so the CustomFactor callbacks get that registered object instead of
        a copy of the window (``TimeOrderedSmoother`` keeps its own, see window.py)."""
        for name in self.window_stats:
            self.window_stats[name] += getattr(self.smoother, name, 0)
        self.smoother = smoother
        self._theta_view = (
            smoother.getLinearizationPoint()
            if isinstance(smoother, gtsam.IncrementalFixedLagSmoother)
            else None
        )

    def _switch_factorization(self, factorization: str) -> bool:
        """Move the window into a fresh smoother with another factorization, losslessly: the same
        factors (the marginals of the keys gone included) at the same linearisation point and
        timestamps; the marginals are anchored at their linearisation point and their variables
        held there, as the old iSAM2 held them (only the relinearisation schedule restarts).
        Factor indices change: the provisional SLAM factors are re-indexed. Also used on a
        smoother whose update just failed (its factors and values include that update's; the
        provisional factors that update added are found by identity in ``step``). Returns False
        (smoother unchanged) when the fresh smoother fails too."""
        smoother = self._new_smoother(factorization)
        new_index = try_move_window(
            self.smoother,
            smoother,
            "fixed-lag",
            factorization,
            f"; staying with {self.factorization}",
        )
        if new_index is None:
            return False
        self._install(smoother)
        self.factorization = factorization
        self.provisional_factors = {
            sess: [(new_index[i], k, row) for i, k, row in rows if i in new_index]
            for sess, rows in self.provisional_factors.items()
        }
        log.info("fixed-lag: %s from t=%.2f s", factorization, self.t_latest)
        return True

    def _rebuild(self) -> None:
        """Fresh smoother with priors on the last good newest state and the live slow variables."""
        o = self.options
        fb = (o.fallback_factorization or "").upper()
        self._switch_to = None
        if fb and fb != self.factorization:
            log.warning(
                "fixed-lag: %s failed; the rebuilt smoother uses %s", self.factorization, fb
            )
            self.factorization = fb
        self._install(self._new_smoother(self.factorization))
        self.provisional_factors = {}
        self._reattach = {}
        kg = self.newest_good_k
        g = gtsam.NonlinearFactorGraph()
        v = gtsam.Values()
        stamps: dict[int, float] = {}
        t = float(self.builder.t_kf[kg])
        g.push_back(
            rebuild_state_priors(
                kg, self.last_good[X(kg)], self.last_good[V(kg)], self.last_good[B(kg)], o
            )
        )
        for key in (X(kg), V(kg), B(kg)):
            v.insert(key, self.last_good[key])
            stamps[key] = t
        live_slow = [
            k for k in self.last_good if chr(gtsam.Symbol(k).chr()) in "sdg" and self._alive(k)
        ]
        for key in live_slow:
            val = self.last_good[key]
            g.push_back(self.builder.rebuild_prior(key, val, o.rebuild_slow_sigma_rel))
            v.insert(key, val)
            stamps[key] = self.t_latest
        self.keyframes_in = {kg}
        self.key_stamp = {k: s for k, s in self.key_stamp.items() if k in stamps}
        self.key_stamp.update(stamps)
        self.smoother.update(g, v, self._block_stamps(stamps))

    def step(self) -> bool:
        """Process the next keyframe; False when the flight is over."""
        b = self.builder
        k = self.k_next
        if k >= b.K:
            return False
        wall0 = time.perf_counter()
        t_k = float(b.t_kf[k])
        self.t_latest = t_k
        self.queued_graph = gtsam.NonlinearFactorGraph()
        self.queued_values = gtsam.Values()
        self.queued_stamps = {}
        # 1-2. Predicted state and keyframe chunk.
        if k == 0:
            R0 = b.R_kf[0]
            pose = gtsam.Pose3(gtsam.Rot3(R0), np.zeros(3))
            self.first_pose = pose
            pv = b._prior_velocity(0)
            vel = pv[0] if pv is not None else np.zeros(3)
            bias = b.initial_bias()
            pim = None
            kp = -1
        else:
            kp = self.newest_good_k
            bias = self.last_good[B(kp)]
            pim = b.preintegrate(k, bias, k_from=kp)
            nav = pim.predict(gtsam.NavState(self.last_good[X(kp)], self.last_good[V(kp)]), bias)
            pose, vel = nav.pose(), nav.velocity()
        chunk = b.keyframe_chunk(k, pose, vel, bias, {}, pim if k > 0 and kp == k - 1 else None)
        if k > 0 and kp != k - 1:
            # The previous keyframe was lost in a rebuild: the IMU factor starts at the newest.
            chunk.factors = gtsam.NonlinearFactorGraph()
            chunk.factors.add(gtsam.CombinedImuFactor(X(kp), V(kp), X(k), V(k), B(kp), B(k), pim))
        for key in b.new_slow_keys(k):
            prev = b.slow_chain_previous(key)
            if prev is not None and prev in self.last_good and self._alive(prev):
                value, start = self.last_good[prev], False
            else:
                value, start = self._slow_start_value(key), True
            chunk.values.insert(key, value)
            chunk.timestamps[key] = t_k
            chunk.factors.push_back(b.slow_factors(key, value, chain_start=start))
        self.queued_graph.push_back(chunk.factors)
        self.queued_values.insert(chunk.values)
        self.queued_stamps.update(chunk.timestamps)
        for key, ts in chunk.timestamps.items():
            self.key_stamp[key] = ts
            if _is_slow(key):
                self.created_slow.add(key)
        self.keyframes_in.add(k)
        # 3. Measurements arrived up to t_k.
        self._collect_arrived(t_k)
        measurement_graph = gtsam.NonlinearFactorGraph()
        remove = self._reattach_provisional(measurement_graph)
        still_pending = []
        provisional_at: list[tuple[int, tuple[int, int, int]]] = []
        for m in self.pending:
            if m.keyframe > k:
                still_pending.append(m)
                continue
            if (
                m.keyframe not in self.keyframes_in
                or b.t_kf[m.keyframe] < t_k - self.options.lag_s + self.period
            ):
                self._drop(f"{m.kind}:dropped-too-late")
                continue
            if not all(self._alive(key) or key in self.queued_stamps for key in m.keys):
                self._drop(f"{m.kind}:variable-marginalized")
                continue
            measurement_graph.add(m.factor)
            self.used[m.kind] = self.used.get(m.kind, 0) + 1
            prov = self._provisional_rows.pop(id(m.factor), None)
            if prov is not None:
                provisional_at.append((measurement_graph.size() - 1, prov))
            for key in m.keys:
                if _is_slow(key):
                    self.queued_stamps[key] = t_k
                    self.key_stamp[key] = t_k
        self.pending = still_pending
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(self.queued_graph)
        graph.push_back(measurement_graph)
        # 4. Update (rebuild on failure, then re-add the keyframe without its measurements).
        ok = self.update(graph, self.queued_values, self.queued_stamps, remove)
        if ok and provisional_at:
            if self._transplanted:
                # The failed update's factors moved with the window into a fresh smoother: find
                # the provisional ones there (the wrapper returns the same Python objects).
                moved = [measurement_graph.at(p) for p, _ in provisional_at]
                index_of = self._factor_indices(moved)
                positions = [index_of.get(id(f)) for f in moved]
            else:
                new_idx = list(self.smoother.getISAM2Result().getNewFactorsIndices())
                offset = self.queued_graph.size()
                positions = [int(new_idx[offset + p]) for p, _ in provisional_at]
            for idx, (_, (session, kk, row)) in zip(positions, provisional_at, strict=True):
                if idx is not None:
                    self.provisional_factors.setdefault(session, []).append((idx, kk, row))
        if not ok:
            self._readd_keyframe_after_rebuild(k, pose, vel, bias)
        # 5. Newest state.
        self.newest_k = k
        self._read_newest(k)
        self.k_next = k + 1
        if self._switch_to and t_k - float(b.t_kf[0]) >= self.options.startup_qr_s:
            self._switch_factorization(self._switch_to)
            self._switch_to = None
        self.latency.append(time.perf_counter() - wall0)
        return True

    def _factor_indices(self, wanted: list[Any]) -> dict[int, int]:
        """Index in the smoother of each of the ``wanted`` factor objects (by identity), keyed by
        ``id()``; factors not found are absent."""
        ids = {id(f) for f in wanted}
        factors = self.smoother.getFactors()
        out = {}
        for i in range(factors.size()):
            f = factors.at(i)
            if f is not None and id(f) in ids:
                out[id(f)] = i
        return out

    def _readd_keyframe_after_rebuild(self, k, pose, vel, bias) -> None:
        b = self.builder
        kg = self.newest_good_k
        if kg == k:
            return
        pim = b.preintegrate(k, self.last_good[B(kg)], k_from=kg)
        g = gtsam.NonlinearFactorGraph()
        g.add(gtsam.CombinedImuFactor(X(kg), V(kg), X(k), V(k), B(kg), B(k), pim))
        v = gtsam.Values()
        nav = pim.predict(
            gtsam.NavState(self.last_good[X(kg)], self.last_good[V(kg)]), self.last_good[B(kg)]
        )
        v.insert(X(k), pose3=nav.pose())
        v.insert(V(k), vector=nav.velocity())
        v.insert(B(k), constant_bias=self.last_good[B(kg)])
        t = float(b.t_kf[k])
        stamps = {X(k): t, V(k): t, B(k): t}
        self.key_stamp.update(stamps)
        self.keyframes_in.add(k)
        if not self.update(g, v, stamps):
            log.warning("fixed-lag: keyframe %d could not be re-added after a rebuild", k)

    def _slow_start_value(self, key: int) -> np.ndarray:
        b = self.builder
        c = chr(gtsam.Symbol(key).chr())
        if c == "d":
            return b.drag_start_value()
        if c == "g":
            prev = b.slow_chain_previous(key)
            if prev is not None and prev in self.last_good:
                return self.last_good[prev]
            return np.array(
                [
                    b.ground_start_value(
                        self.last_good.get(X(self.newest_k)) if self.newest_k >= 0 else None,
                        self.t_latest,
                    )
                ]
            )
        raise KeyError(key)

    def _collect_arrived(self, t_now: float) -> None:
        rows = self._all_meas
        while self._meas_i < len(rows) and rows[self._meas_i][0] <= t_now:
            arrival, k, kind, row = rows[self._meas_i]
            self._meas_i += 1
            if k > self.k_next:
                # Its keyframe is not created yet: keep the raw row until then.
                self._deferred.append((arrival, k, kind, row))
                continue
            self.pending.extend(self._make_factors(kind, k, row))
        keep = []
        for arrival, k, kind, row in self._deferred:
            if k <= self.k_next:
                self.pending.extend(self._make_factors(kind, k, row))
            else:
                keep.append((arrival, k, kind, row))
        self._deferred = keep

    def _read_newest(self, k: int) -> None:
        s = self.smoother
        try:
            pose = s.calculateEstimatePose3(X(k))
            vel = s.calculateEstimateVector(V(k))
            bias = s.calculateEstimateConstantBias(B(k))
        except SOLVER_ERRORS as e:
            self.n_failures += 1
            self.failure_messages.append(" ".join(str(e).split())[:200])
            self._rebuild()
            pose = self.last_good[X(self.newest_good_k)]
            vel = self.last_good[V(self.newest_good_k)]
            bias = self.last_good[B(self.newest_good_k)]
            self.out_t.append(float(self.builder.t_kf[k]))
            self.out_pose.append(pose)
            self.out_vel.append(vel)
            self.out_bias.append(bias)
            return
        # Only the newest state is kept (with the slow variables): drop the previous one.
        kp = self.newest_good_k
        for key in (X(kp), V(kp), B(kp)):
            self.last_good.pop(key, None)
        self.last_good[X(k)], self.last_good[V(k)], self.last_good[B(k)] = pose, vel, bias
        self.newest_good_k = k
        t = float(self.builder.t_kf[k])
        if k % self.options.slow_read_every == 0:
            # Forget the stamps of marginalised keys (bounded memory and per-update work).
            horizon = self.t_latest - self.options.lag_s - 2.0 * self.period
            self.key_stamp = {key: ts for key, ts in self.key_stamp.items() if ts >= horizon}
            self.created_slow = {key for key in self.created_slow if key in self.key_stamp}
        read_slow = k % self.options.slow_read_every == 0 or k == self.builder.K - 1
        for key in self.created_slow:
            if self._alive(key) and (read_slow or key not in self.last_good):
                try:
                    self.last_good[key] = self._current_value(key)
                except SOLVER_ERRORS:
                    continue
                self._track(key, t)
        self.out_t.append(t)
        self.out_pose.append(pose)
        self.out_vel.append(vel)
        self.out_bias.append(bias)

    def _track(self, key: int, t: float) -> None:
        sym = gtsam.Symbol(key)
        c = chr(sym.chr())
        val = self.last_good[key]
        name = {"s": "slam", "d": "drag_k", "g": "ground_height"}[c]
        if c == "s" and self.builder.slam_model == "sim3":
            val = np.array([val.scale()])
            sess_seg = self.builder.slam_session_segment(key)
            if sess_seg is not None:
                self.session_scale[sess_seg[0]] = float(val[0])
            elif sym.index() >= PROVISIONAL_KEY_BASE:
                name = "slam_scale_provisional"
        name += f"#{sym.index()}"
        self.slow_track.setdefault(name, []).append((t, np.atleast_1d(np.asarray(val, float))))

    def run(self, progress: bool = False) -> Estimate:
        """Process the whole flight; the causal estimate (newest state after each update)."""
        b = self.builder
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=b.K, desc="fixed-lag", unit="kf")
        if self.options.track_memory:
            tracemalloc.start()
        t0 = time.perf_counter()
        while self.step():
            if bar:
                bar.update(1)
        runtime = time.perf_counter() - t0
        self.finish()
        peak = None
        if self.options.track_memory:
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
        if bar:
            bar.close()
        return self.result(runtime, peak)

    def finish(self) -> None:
        """Count the measurements that arrive after the last keyframe (never processed)."""
        for _, _, kind, _ in self._all_meas[self._meas_i :]:
            self._drop(f"{kind}:arrived-after-last-keyframe")
        self._meas_i = len(self._all_meas)
        for _, _, kind, _ in self._deferred:
            self._drop(f"{kind}:arrived-after-last-keyframe")
        self._deferred = []
        for m in self.pending:
            self._drop(f"{m.kind}:arrived-after-last-keyframe")
        self.pending = []

    def result(self, runtime: float, peak_bytes: int | None = None) -> Estimate:
        """The causal estimate so far (``runtime``: wall time of the run [s])."""
        b = self.builder
        n = len(self.out_t)
        pos = np.array([p.translation() for p in self.out_pose]).reshape(n, 3)
        R = np.array([p.rotation().matrix() for p in self.out_pose]).reshape(n, 3, 3)
        traj = Trajectory(
            np.asarray(self.out_t),
            pos,
            matrix_to_quat_wxyz(R),
            np.asarray(self.out_vel).reshape(n, 3),
            np.array([x.gyroscope() for x in self.out_bias]).reshape(n, 3),
            np.array([x.accelerometer() for x in self.out_bias]).reshape(n, 3),
        )
        series: dict[str, TimeSeries] = {}
        slam_scale: dict[int, float] = {}
        drag_k = ground = None
        # Slow variables: concatenate the chains by kind (causal value after each update).
        # SLAM rows carry their session (scored per session, as the batch's series are).
        by_kind: dict[str, list[tuple[float, np.ndarray, int]]] = {}
        session_of = {j: key[0] for key, j in getattr(b, "slam_var", {}).items()}
        for name, rows in self.slow_track.items():
            kind, _, j = name.partition("#")
            sess = session_of.get(int(j), 0) if kind == "slam" else 0
            by_kind.setdefault(kind, []).extend((r[0], r[1], sess) for r in rows)
        for kind, rows in by_kind.items():
            rows.sort(key=lambda r: r[0])
            t = np.array([r[0] for r in rows])
            val = np.array([r[1] for r in rows])
            if kind == "slam":
                series["slam_scale" if b.slam_model == "sim3" else "slam_axis_scale"] = TimeSeries(
                    t, val[:, 0] if b.slam_model == "sim3" else val[:, :3]
                )
                if b.slam_model == "sim3":
                    series["slam_session"] = TimeSeries(t, np.array([float(r[2]) for r in rows]))
            else:
                series[kind] = TimeSeries(t, val[:, 0] if val.shape[1] == 1 else val)
        if b.use_slam:
            inv = {j: key for key, j in getattr(b, "slam_var", {}).items()}
            for name, rows in self.slow_track.items():
                if not name.startswith("slam#"):
                    continue
                j = int(name.split("#")[1])
                v = rows[-1][1]
                sess = inv[j][0]
                if sess not in slam_scale or rows[-1][0] >= self._last_t_of(sess):
                    axis = b.slam_model == "axis"
                    slam_scale[sess] = float(np.cbrt(np.prod(v[:3])) if axis else v[0])
                    self._sess_last_t[sess] = rows[-1][0]
        if "drag_k" in by_kind:
            drag_k = np.asarray(sorted(by_kind["drag_k"], key=lambda r: r[0])[-1][1])
        if "ground_height" in by_kind:
            ground = float(sorted(by_kind["ground_height"], key=lambda r: r[0])[-1][1][0])
        lat = np.asarray(self.latency)
        info = b.report()
        info.update(
            {
                "lag_s": self.options.lag_s,
                "used": dict(self.used),
                "dropped": dict(self.dropped),
                "slam_provisional_alignments": [
                    {"session": sess, "t": t} for sess, t in self.provisional_alignments
                ],
                "solver_failures": self.n_failures,
                "smoother": self.smoother_kind,
                "window_reorders": self.window_stats["reorders"]
                + getattr(self.smoother, "reorders", 0),
                "window_unordered_updates": self.window_stats["unordered_updates"]
                + getattr(self.smoother, "unordered_updates", 0),
                "factorization_final": self.factorization,
                "factorization_fallbacks": self.n_fallbacks,
                "solver_failure_messages": self.failure_messages[:10],
                "python_heap_peak_bytes": peak_bytes,
                "updates": n,
            }
        )
        return fixed_lag_estimate(
            traj,
            info,
            lat,
            runtime,
            b.t_kf[-1] - b.t_kf[0],
            self.options,
            slam_scale=slam_scale,
            drag_k=drag_k,
            ground_height=ground,
            series=series,
        )

    def _last_t_of(self, sess: int) -> float:
        return self._sess_last_t.get(sess, -math.inf)


def try_move_window(old, new, who: str, factorization: str, note: str = "") -> dict | None:
    """:func:`fgnav.solvers.window.move_window` from smoother ``old`` into ``new`` (a fresh
    ``factorization`` one); its factor index map, or None when GTSAM fails (logged as a warning
    of ``who``, with ``note`` appended)."""
    try:
        return move_window(old, new)
    except SOLVER_ERRORS as e:
        log.warning(
            "%s: moving the window to %s failed (%s)%s",
            who,
            factorization,
            " ".join(str(e).split())[:120],
            note,
        )
        return None


def fixed_lag_estimate(
    traj: Trajectory,
    info: dict[str, Any],
    lat: np.ndarray,
    runtime: float,
    span_s: float,
    options: FixedLagOptions,
    **fields: Any,
) -> Estimate:
    """The fixed-lag smoother's causal estimate (either engine: :class:`FixedLagRunner`, the
    push-API :class:`fgnav.solvers.online.OnlineSmoother`): ``info`` completed with the update
    latency figures (``lat``, wall time of each update [s]), the real-time factor (``span_s``
    of flight time in ``runtime`` seconds of wall time) and the options; ``fields``: the other
    :class:`~fgnav.estimate.Estimate` fields."""
    has = len(lat) > 0
    info = {
        **info,
        "latency_p50_s": float(np.percentile(lat, 50)) if has else None,
        "latency_p99_s": float(np.percentile(lat, 99)) if has else None,
        "latency_max_s": float(lat.max()) if has else None,
        "times_real_time": float(span_s / runtime) if runtime > 0 else None,
        "options": asdict(options),
    }
    return Estimate(
        method="fixed-lag",
        trajectory=traj,
        update_latency=lat,
        runtime_s=runtime,
        causal=True,
        info=info,
        **fields,
    ).check()


def run_fixed_lag(
    flight: Flight,
    options: FixedLagOptions | None = None,
    priors: Any = None,
    progress: bool = False,
) -> Estimate:
    """Run the online fixed-lag smoother over a flight (see module docstring).

    Returns:
        ``Estimate(method="fixed-lag", causal=True)``: the newest state after each update, with
        ``update_latency`` and the counts of used/dropped measurements and solver failures in
        ``info``.
    """
    return FixedLagRunner(flight, options, priors).run(progress)
