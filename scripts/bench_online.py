"""Benchmark of the online fixed-lag smoother on a 3-minute simulated flight.

Flight: ``figure8`` for 180 s, 200 Hz IMU, 20 Hz SLAM, 50 Hz rangefinder, 10 Hz yaw, 100 Hz
attitude (images off: the camera's 30 Hz frames only feed homography factors, not used here).
Prints updates/s, update latency p50/p99/max, times real time, Python heap peak and the ATE of the
causal trajectory. Wall-clock numbers depend on the machine's load: run it on an idle machine.

    .venv/bin/python scripts/bench_online.py [--duration 180] [--keyframe-hz 20] [--lag 2]
        [--marginalize-every 1]
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate

from fgnav.eval.metrics import evaluate
from fgnav.solvers.fixed_lag import FixedLagOptions, run_fixed_lag
from fgnav.solvers.graph import GraphOptions


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
    ap.add_argument("--memory", action="store_true", help="trace the Python heap (slower)")
    args = ap.parse_args()
    sim = SimOptions(duration=args.duration, images=False, slam_rate_hz=20.0, range_rate_hz=50.0)
    t0 = time.perf_counter()
    flight = simulate(args.scenario, seed=args.seed, options=sim)
    print(f"simulated {args.scenario} {args.duration:.0f} s in {time.perf_counter() - t0:.1f} s")
    opts = FixedLagOptions(
        lag_s=args.lag,
        graph=GraphOptions(keyframe_hz=args.keyframe_hz),
        marginalize_every_s=args.marginalize_every,
        track_memory=args.memory,
    )
    print(f"lag {args.lag} s, marginalisation every {args.marginalize_every} s")
    cpu0 = time.process_time()
    est = run_fixed_lag(flight, opts, progress=True)
    cpu = time.process_time() - cpu0
    lat = est.update_latency
    info = est.info
    m = evaluate(est, flight.ground_truth, alignment="se3")
    print(f"updates: {len(lat)} ({len(lat) / est.runtime_s:.1f} updates/s wall)")
    p50, p99 = np.percentile(lat, [50, 99]) * 1e3
    print(f"latency: p50 {p50:.2f} ms, p99 {p99:.2f} ms, max {lat.max() * 1e3:.2f} ms")
    print(f"times real time: {info['times_real_time']:.1f}x wall, {args.duration / cpu:.1f}x CPU")
    print(f"process max RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    if info.get("python_heap_peak_bytes"):
        print(f"python heap peak: {info['python_heap_peak_bytes'] / 2**20:.1f} MiB")
    print(f"solver failures: {info['solver_failures']}, dropped: {info['dropped']}")
    print(
        f"ATE (causal, SE(3) alignment): {m.ate_rmse_m:.4f} m; velocity RMSE {m.vel_rmse_mps:.4f}"
    )


if __name__ == "__main__":
    main()
