"""Benchmark of the batch smoother: wall and CPU time per flight minute on a simulated flight.

Flight: ``figure8`` (default 180 s), 200 Hz IMU, 20 Hz SLAM, 50 Hz rangefinder, 10 Hz yaw, 100 Hz
attitude. Prints graph-building, LM and covariance times, per flight minute, and the ATE. Wall-clock
numbers depend on the machine's load.

    .venv/bin/python scripts/bench_batch.py [--duration 180] [--keyframe-hz 20]
"""

from __future__ import annotations

import argparse
import time

from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate

from fgnav.eval.metrics import evaluate
from fgnav.solvers.batch import BatchOptions, solve_batch
from fgnav.solvers.graph import GraphOptions


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="figure8")
    ap.add_argument("--duration", type=float, default=180.0)
    ap.add_argument("--keyframe-hz", type=float, default=20.0)
    ap.add_argument("--covariance", default="slow", choices=("all", "slow", "none"))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    sim = SimOptions(duration=args.duration, images=False, slam_rate_hz=20.0, range_rate_hz=50.0)
    flight = simulate(args.scenario, seed=args.seed, options=sim)
    opts = BatchOptions(
        graph=GraphOptions(keyframe_hz=args.keyframe_hz), covariance=args.covariance
    )
    cpu0 = time.process_time()
    est = solve_batch(flight, opts)
    cpu = time.process_time() - cpu0
    info = est.info
    minutes = args.duration / 60.0
    m = evaluate(est, flight.ground_truth, alignment="se3")
    print(
        f"{info['n_variables']} variables, {info['n_factors']} factors, "
        f"{info['lm_iterations']} LM iterations"
    )
    print(
        f"build {info['time_build_s']:.2f} s, LM {info['time_solve_s']:.2f} s, covariance "
        f"({args.covariance}) {info['time_covariance_s']:.2f} s"
    )
    print(
        f"total {est.runtime_s:.2f} s wall ({est.runtime_s / minutes:.2f} s per flight minute), "
        f"{cpu:.2f} s CPU ({cpu / minutes:.2f} s per flight minute)"
    )
    print(
        f"ATE (SE(3) alignment) {m.ate_rmse_m:.4f} m, SLAM scale {est.slam_scale}, "
        f"drag k {est.drag_k}"
    )


if __name__ == "__main__":
    main()
