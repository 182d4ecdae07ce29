"""Benchmark of the online fixed-lag smoother on a 3-minute simulated flight.

Flight: ``figure8`` for 180 s, 200 Hz IMU, 20 Hz SLAM, 50 Hz rangefinder, 10 Hz yaw, 100 Hz
attitude, and with ``--camera`` the 30 Hz downward camera (320x240, rendered; the push engine's
homography VO stage tracks its frames inside the loop's clock, by default in a child process
beside the smoother, ``--vo-worker inline`` in the event loop; ``--engine prepared`` runs the VO
once before the smoother, outside its clock). Keyframes at 20 Hz, lag 2 s. Prints updates/s,
update latency p50/p99/max, times real time (wall, and CPU with the VO process's), memory and the
ATE of the causal trajectory. Wall-clock numbers depend on the machine's load: run it on an idle
machine.

Camera, 2026-12-03 afternoon (180 s, reference workload 71-100 ms): VO in the event loop
7.1-8.6x real time, ATE 1.656 cm (4.7-5.6x before the VO's LK guess moved to original pixels);
VO process 10.3-11.0x, ATE 1.598-1.60 cm.

No camera, 2026-12-07, two rounds at about 06:25 and 06:46 (the per-keyframe Python trimmed, the
estimate bit-identical: one quaternion's rotation matrix and one yaw's wrap on plain floats, the
range factor's sensor parts shared, finite checks on floats, repeated work of the health detectors
skipped) of three runs each, before and after alternating, reference workload 62-71 ms: before
27.7-34.5x real time (wall), p50 0.99-1.16 ms, p99 2.82-5.58 ms, smoother CPU / reference
84.7-96.1; after 32.7-36.6x, p50 0.94-1.02 ms, p99 2.85-4.08 ms, CPU / reference 78.1-83.4 (about
13 % less CPU); ATE 2.75 cm both. Where the time goes now (py-spy, 180 s): iSAM2's update without
the callbacks 17 %, the CustomFactor callbacks 10 %, the newest state's estimate read 7 % (its
back-substitution, 97 us; the lagged output's read after it 1.2 us), its covariance 6 %,
marginalisation 2 %: GTSAM's part about 43 %; the SLAM-vs-gyro check's fits in the first 10 s 5 %;
the rest is Python spread thinly (no line above 2 % of the run). 60x would need that Python cut to
about a quarter, out of reach of such trimming.

No camera, 2026-12-08 (branch speed: more per-keyframe and per-pose Python on plain floats, every
output byte-identical). This VM's CPU speed swung 1.5x between runs that day (reference workload
51-97 ms), so the figures are instruction counts of the replay alone (valgrind): 180 s 26.45 ->
25.61 G (-3.2 %); 60 s -2.8 %, with 7.5 % fewer instruction-cache and 3.2 % fewer data-cache misses
(fewer numpy calls). CPU time: old and new alternating in one process, paired ratios 0.84-1.07
(median 0.99); the script back to back in a quiet spell (reference 51-55 ms): 39.2x -> 42.4x and
37.6x -> 39.4x CPU, smoother CPU / reference 90.1 -> 81.3 and 89.3 -> 83.3. Where the 60 s
replay's instructions go (callgrind): the Python interpreter 30 %, numpy 21 %, malloc/memset 13 %,
GTSAM/Eigen 21 %, OpenBLAS 8 % (numpy's 3x3 products each a dgemm call: 717k of them, mostly the
SLAM-vs-gyro check's stacked products in the first 13 s); by GTSAM call: iSAM2's update 24 % (of
it the CustomFactor callbacks 9 %: a SLAM position factor's linearisation 28 us, 20 us of it its
Jacobians' numpy), the joint marginal 6 %, the newest estimate's back-substitution 6 %. In the
quiet spell ``--speed-limit``'s window (IMU, attitude, SLAM; no range, drag) ran at 47-53x with
the custom factors and 60-77x with built-in ones, the full benchmark at 38-40x: 60x needs about
1.5x less CPU per keyframe, which Python trims at this level do not give (less GTSAM work per
keyframe, e.g. the newest marginal from the root clique, or factors in C++, would).

    .venv/bin/python scripts/bench_online.py [--camera] [--vo-worker process|inline]
        [--duration 180] [--keyframe-hz 20]
        [--lag 2] [--marginalize-every 1] [--factorization CHOLESKY|QR]
        [--smoother time-ordered|gtsam] [--relinearize-position 0.003]

Also prints a machine reference workload (a fixed mix of Python, NumPy and GTSAM work, best of 3,
before and after the run) and the smoother's CPU time in units of it: this VM's CPU speed varies by
about 1.5x over a day. The ratio is only a rough normaliser (it moved from 36 to 56 between two
runs of the same code); compare implementations back to back.

Measured 2026-11-22 (fourth session), one after the other on an idle machine; the same causal
trajectory for both windows (ATE 2.46 cm without the camera, 6.63 cm with it):

    flight       window          real time (wall / CPU)  p50 / p99 / max [ms]    CPU/ref
    no camera    time-ordered    40.9x / 39.1x           1.15 / 2.00 / 11.8      36.2
    no camera    gtsam           27.7x / 26.8x           1.48 / 7.90 / 35.9      68.4
    no camera    time-ordered    28.9x / 27.5x           1.67 / 2.84 / 20.8      54.3
    30 Hz camera time-ordered    23.5x / 21.7x           2.05 / 3.57 / 32.5      55.7
    30 Hz camera gtsam           20.0x / 18.9x           1.94 / 15.9 / 40.3      69.8
    30 Hz camera time-ordered    26.9x / 24.6x           1.81 / 2.90 / 29.1      42.6

After the review fixes (split cliques marginalised first, re-stamp checks): no camera 28.2x
(p99 4.10 ms), 30 Hz camera 25.1x (p99 4.47 ms, max 56.7 ms).

(``gtsam``: ``IncrementalFixedLagSmoother``; both windows with the linearisation-point view that
spares the CustomFactor callbacks a copy of the window.) The homography VO front-end ran at
3.2-3.7x real time. Earlier the same day, without the callback view, the time-ordered window gave
24-27x without and 20.1x with the camera; the third session's code (IncrementalFixedLagSmoother,
callbacks copying the window) 16.2-24.0x without the camera, p99 11-18 ms.

Where the time went (per update, no camera): with ``IncrementalFixedLagSmoother`` each update
re-eliminated about 30 variables (it re-orders the window at every marginalisation and leaves the
newest keyframe at the bottom of a chain of cliques), and every marginalisation about 100; the
time-ordered window (``fgnav.solvers.window``) re-eliminates about 22 (the SLAM pose arrives three
keyframes late, 0.15 s) and marginalises without re-eliminating. Then (perf, 60 s flight) 41 % of
the iSAM2 update was in the CustomFactor callbacks, about half of it copying the window's Values
for each callback: the view removed that copy (15 % less CPU for the whole run, paired). The rest:
reading the newest state (iSAM2's back-substitution) ~0.2 ms, building the measurement factors,
the IMU preintegration and the keyframe chunk ~0.1-0.2 ms each.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate

import fgnav.solvers.vision  # noqa: F401  (OpenCV and SciPy imported before the CPU clock)
from fgnav.eval.metrics import evaluate
from fgnav.solvers.fixed_lag import SMOOTHERS, FixedLagOptions, run_fixed_lag
from fgnav.solvers.graph import GraphOptions


def children_cpu_s() -> float:
    """CPU time of the ended child processes (the push engine's VO process, ``vo_worker``)."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def reference_workload_s(repeats: int = 3) -> float:
    """CPU seconds (best of ``repeats``) of a fixed mix of Python, NumPy and GTSAM work (a chain
    of 400 Pose3 CustomFactor and built-in between factors, linearised and solved 10 times): the
    machine's speed at the time of the run, to compare runs made at different times (this VM's
    CPU speed has been seen to vary by 1.5x over a day)."""
    import gtsam

    def between_error(z):
        def f(this, values, H):
            pa, pb = values.atPose3(this.keys()[0]), values.atPose3(this.keys()[1])
            e = z.localCoordinates(pa.between(pb))
            if H is not None:
                H[0] = -np.eye(6)
                H[1] = np.eye(6)
            return e

        return f

    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    rng = np.random.default_rng(0)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), noise))
    for i in range(400):
        z = gtsam.Pose3.Expmap(rng.normal(0.0, 0.1, 6))
        values.insert(i, gtsam.Pose3.Expmap(rng.normal(0.0, 0.1, 6)))
        if i:
            graph.add(gtsam.CustomFactor(noise, [i - 1, i], between_error(z)))
            graph.add(gtsam.BetweenFactorPose3(i - 1, i, z, noise))
    best = float("inf")
    for _ in range(repeats):
        c0 = time.process_time()
        for _ in range(10):
            graph.linearize(values).optimize()
        best = min(best, time.process_time() - c0)
    return best


def builtin_stand_in(flight, opts):
    """The push smoother's window and IMU factors with GTSAM's built-in factors standing in for
    the custom ones: the SLAM position at the simulator's true scale and alignment as a
    ``GPSFactor`` on the body (no alignment variable), the attitude stream as a
    ``PoseRotationPrior3D`` at every keyframe (for the yaw factor). The speed limit of this
    design: no Python callbacks in the measurement factors."""
    import gtsam
    from fgnav.datasets.events import replay_flight

    from fgnav.keys import X
    from fgnav.solvers.online import OnlineSmoother

    truth = flight.meta["truth"]["slam_sessions"]

    class StandIn(OnlineSmoother):
        def _slam_factor(self, k, payload, g, stamps, remove, prov_new):
            sess, _row, t, p, _q = payload
            tr = truth[str(sess)]
            R = np.asarray(tr["slam_R_world"], float)
            scale = tr["scale"] * (1.0 + tr["scale_drift_per_s"] * (t - tr["t_start"]))
            world_t_cam = R.T @ (np.asarray(p) - np.asarray(tr["slam_t_world"])) / scale
            pose = self.values[X(self.k)]
            world_t_body = world_t_cam - pose.rotation().matrix() @ self.body_T_cam[:3, 3]
            # The estimator's world origin is the first keyframe: positions relative to the
            # first SLAM pose's (the start; same axes, the attitude stream fixes the yaw).
            if not hasattr(self, "origin"):
                self.origin = world_t_body - pose.translation()
            world_t_body = world_t_body - self.origin
            g.add(gtsam.GPSFactor(X(k), world_t_body, self._noise(3, self.go.slam_sigma_m)))
            self._use("slam")

        def _flow_factor(self, j, g, stamps):
            k = j + 1
            R = self._attitude_at(self.t_kf[k])
            if R is not None:
                g.add(
                    gtsam.PoseRotationPrior3D(
                        X(k), gtsam.Rot3(R), gtsam.noiseModel.Isotropic.Sigma(3, 0.03)
                    )
                )

    sm = StandIn(flight.calib, opts, "builtin")
    streams = [n for n in ("imu", "attitude", "slam") if getattr(flight, n) is not None]
    t0 = time.perf_counter()
    for ev in replay_flight(flight, streams):
        sm.feed(ev)
    return sm.result(time.perf_counter() - t0)


def speed_limit(flight, args) -> None:
    """Custom factors (SLAM position with its alignment, yaw) against built-in stand-ins on the
    same window (IMU, attitude, SLAM; no range, drag or camera), back to back."""
    from fgnav.datasets.events import replay_flight

    from fgnav.solvers.online import feed_all

    g = GraphOptions(keyframe_hz=args.keyframe_hz, use_range=False, use_drag=False)
    opts = FixedLagOptions(lag_s=args.lag, graph=g, covariance=False)
    streams = ["imu", "attitude", "yaw", "slam"]
    t0 = time.perf_counter()
    custom = feed_all(replay_flight(flight, streams), flight.calib, opts, "custom").result()
    t_custom = time.perf_counter() - t0
    builtin = builtin_stand_in(flight, opts)
    t_builtin = builtin.runtime_s
    for name, est, t in (("custom", custom, t_custom), ("built-in", builtin, t_builtin)):
        m = evaluate(est, flight.ground_truth, alignment="se3")
        print(
            f"speed limit: {name:8s} {args.duration / t:6.1f}x real time, p99 "
            f"{np.percentile(est.update_latency, 99) * 1e3:.2f} ms, ATE {m.ate_rmse_m:.4f} m"
        )
    print(f"speed limit: custom / built-in time = {t_custom / t_builtin:.2f} (goal <= 2)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="figure8")
    ap.add_argument("--duration", type=float, default=180.0)
    ap.add_argument("--keyframe-hz", type=float, default=20.0)
    ap.add_argument("--lag", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--marginalize-every",
        type=float,
        default=FixedLagOptions.marginalize_every_s,
        help="marginalisation block [s] (FixedLagOptions.marginalize_every_s; 0: every update)",
    )
    ap.add_argument(
        "--factorization",
        default=FixedLagOptions.factorization,
        choices=("CHOLESKY", "QR"),
        help="iSAM2 factorization after the QR start (FixedLagOptions.factorization)",
    )
    ap.add_argument(
        "--smoother",
        default=FixedLagOptions.smoother,
        choices=SMOOTHERS,
        help="fixed-lag window implementation (FixedLagOptions.smoother)",
    )
    ap.add_argument(
        "--camera",
        action="store_true",
        help="render the 30 Hz downward camera and add its homography factors (push engine: the "
        "VO stage runs inside the loop's clock, see --vo-worker; prepared: once before the "
        "smoother, its time printed apart)",
    )
    ap.add_argument(
        "--vo-worker",
        default=FixedLagOptions.vo_worker,
        choices=("process", "inline"),
        help="push engine's VO stage: in a child process beside the smoother or in the event "
        "loop (FixedLagOptions.vo_worker)",
    )
    ap.add_argument("--memory", action="store_true", help="trace the Python heap (slower)")
    ap.add_argument(
        "--position-threshold",
        "--relinearize-position",
        dest="position_threshold",
        type=float,
        default=FixedLagOptions.relinearize_threshold_position,
        help="keyframe position relinearisation threshold [m] "
        "(FixedLagOptions.relinearize_threshold_position; <= 0: none, the keyframe threshold)",
    )
    ap.add_argument(
        "--slam-trans-rw",
        type=float,
        default=FixedLagOptions.slam_trans_rw_m,
        help="push engine's SLAM alignment origin walk [m/sqrt(s)] "
        "(FixedLagOptions.slam_trans_rw_m; < 0: the graph's)",
    )
    ap.add_argument(
        "--speed-limit",
        action="store_true",
        help="also run the same window with GTSAM's built-in factors standing in for the custom "
        "ones (GPSFactor for the SLAM position at the true scale, PoseRotationPrior3D for the "
        "attitude) and print the ratio",
    )
    ap.add_argument(
        "--engine",
        default="push",
        choices=("push", "prepared"),
        help="push: the flight's events replayed in arrival order into the push-API smoother "
        "(fgnav.solvers.online, the default of fgnav online; its clock counts every event); "
        "prepared: the runner over the prepared flight (fgnav.solvers.fixed_lag)",
    )
    args = ap.parse_args()
    ref0 = reference_workload_s()
    sim = SimOptions(
        duration=args.duration,
        images=args.camera,
        image_rate_hz=30.0,
        slam_rate_hz=20.0,
        range_rate_hz=50.0,
    )
    t0 = time.perf_counter()
    flight = simulate(args.scenario, seed=args.seed, options=sim)
    print(f"simulated {args.scenario} {args.duration:.0f} s in {time.perf_counter() - t0:.1f} s")
    opts = FixedLagOptions(
        lag_s=args.lag,
        graph=GraphOptions(keyframe_hz=args.keyframe_hz),
        marginalize_every_s=args.marginalize_every,
        factorization=args.factorization,
        smoother=args.smoother,
        track_memory=args.memory,
        vo_worker=args.vo_worker,
        relinearize_threshold_position=(
            args.position_threshold
            if args.position_threshold and args.position_threshold > 0
            else None
        ),
        slam_trans_rw_m=(
            None if args.slam_trans_rw is None or args.slam_trans_rw < 0 else args.slam_trans_rw
        ),
    )
    print(
        f"lag {args.lag} s, marginalisation every {args.marginalize_every} s, "
        f"window {args.smoother}, position relinearisation threshold "
        f"{opts.relinearize_threshold_position}, SLAM origin walk {opts.slam_trans_rw_m}"
    )
    print(f"engine: {args.engine}")
    if args.camera and args.engine == "prepared":
        # The VO front-end (cached per flight) runs here, outside the smoother's CPU clock.
        from fgnav.solvers.vision import run_homography_frontend

        c0 = time.process_time()
        _, vo_wall = run_homography_frontend(flight)
        print(f"VO front-end: {vo_wall:.1f} s wall, {time.process_time() - c0:.1f} s CPU")
    cpu0 = time.process_time() + children_cpu_s()
    if args.engine == "push":
        from fgnav.solvers.online import replay_online

        est = replay_online(flight, opts, progress=True)
    else:
        est = run_fixed_lag(flight, opts, progress=True)
    cpu = time.process_time() + children_cpu_s() - cpu0  # the VO process's CPU included
    lat = est.update_latency
    info = est.info
    m = evaluate(est, flight.ground_truth, alignment="se3")
    hom = info.get("homography")
    if hom:
        n_hom = info["used"].get("homography", 0)
        print(
            f"camera: VO front-end {hom['vo_time_s']:.1f} s "
            f"({args.duration / hom['vo_time_s']:.1f}x real time, before the smoother); "
            f"{n_hom} homography factors"
        )
    if info.get("vo_time_s"):
        # The push engine's VO stage, inside the loop's clock (in its own process by default,
        # FixedLagOptions.vo_worker, overlapping the smoother).
        vo_s = info["vo_time_s"]
        where = "in its process, beside" if opts.vo_worker == "process" else "inside"
        print(
            f"camera: VO stage {vo_s:.1f} s wall {where} the loop ({100 * vo_s / est.runtime_s:.0f}"
            f" % of its time, {1e3 * vo_s / max(1, info['vo_counts'].get('frames', 0)):.2f} ms "
            "per frame)"
        )
    print(f"updates: {len(lat)} ({len(lat) / est.runtime_s:.1f} updates/s wall)")
    p50, p99 = np.percentile(lat, [50, 99]) * 1e3
    print(f"latency: p50 {p50:.2f} ms, p99 {p99:.2f} ms, max {lat.max() * 1e3:.2f} ms")
    print(f"times real time: {info['times_real_time']:.1f}x wall, {args.duration / cpu:.1f}x CPU")
    print(f"process max RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    if info.get("python_heap_peak_bytes"):
        print(f"python heap peak: {info['python_heap_peak_bytes'] / 2**20:.1f} MiB")
    if "window_reorders" in info:
        print(
            f"window: {info['smoother']} (re-orderings {info['window_reorders']}, unordered "
            f"updates {info['window_unordered_updates']})"
        )
    print(
        f"solver failures: {info['solver_failures']}, factorization "
        f"{info['factorization_final']} (fallbacks {info['factorization_fallbacks']}), "
        f"dropped: {info['dropped']}"
    )
    print(
        f"ATE (causal, SE(3) alignment): {m.ate_rmse_m:.4f} m; velocity RMSE {m.vel_rmse_mps:.4f}"
    )
    if args.speed_limit:
        speed_limit(flight, args)
    ref = 0.5 * (ref0 + reference_workload_s())
    print(
        f"machine reference workload: {1e3 * ref:.0f} ms CPU (before and after the run); "
        f"smoother CPU / reference: {cpu / ref:.1f}"
    )


if __name__ == "__main__":
    main()
