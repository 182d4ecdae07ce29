"""Homography motion factors in the smoother graph against seed 002's EKF + VO dead reckoning.

Simulates a flight with rendered downward images and runs, on the same flight:

* the batch smoother and the fixed-lag smoother with seed 002's sensor set as one graph (IMU,
  rangefinder, homography, yaw; SLAM and drag off), and with drag added;
* both smoothers with every sensor, with and without the homography factors;
* seed 002's baseline (attitude-height EKF + rectified homography VO, dead reckoning).

Prints, per run: wall time (the first graph run includes the homography VO, shared by the later
runs of the same flight), ATE after SE(3) alignment, RPE over ``--rpe-m`` metres, the unaligned
error of the end point relative to the start, velocity and yaw RMSE, the homography factor counts
(VO pairs, gated, factors) and the fixed-lag median update time.

Usage::

    .venv/bin/python scripts/bench_vision.py [--scenario two-turns] [--duration 60] [--seed 1]
        [--blur-s 0.0] [--patches 0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.baselines.seed002 import run_seed002
from fgnav.eval.metrics import evaluate
from fgnav.solvers.batch import BatchOptions, solve_batch
from fgnav.solvers.fixed_lag import FixedLagOptions, run_fixed_lag
from fgnav.solvers.graph import GraphOptions


def _end_error_m(est, truth) -> tuple[float, float]:
    tr = est.trajectory
    k = np.searchsorted(truth.t, tr.t)
    p = truth.world_t_body[k]
    e = (tr.world_t_body[-1] - tr.world_t_body[0]) - (p[-1] - p[0])
    return float(np.linalg.norm(e)), float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="two-turns")
    ap.add_argument("--duration", type=float, default=60.0, help="simulated seconds")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--blur-s", type=float, default=0.0, help="exposure time (motion blur) [s]")
    ap.add_argument("--patches", type=int, default=0, help="featureless patches on the ground")
    ap.add_argument("--rpe-m", type=float, default=5.0, help="RPE segment length [m]")
    args = ap.parse_args()
    flight = simulate(
        args.scenario,
        seed=args.seed,
        options=SimOptions(
            duration=args.duration, motion_blur_s=args.blur_s, featureless_patches=args.patches
        ),
    )
    truth = flight.ground_truth
    seed002_set = GraphOptions(use_slam=False, use_drag=False)
    runs = [
        (
            "batch seed-002 sensors",
            lambda: solve_batch(flight, BatchOptions(graph=seed002_set, covariance="none")),
        ),
        (
            "batch seed-002 + drag",
            lambda: solve_batch(
                flight, BatchOptions(graph=GraphOptions(use_slam=False), covariance="none")
            ),
        ),
        (
            "fixed-lag seed-002 sensors",
            lambda: run_fixed_lag(flight, FixedLagOptions(graph=seed002_set)),
        ),
        ("batch all", lambda: solve_batch(flight, BatchOptions(covariance="none"))),
        (
            "batch all, no homography",
            lambda: solve_batch(
                flight, BatchOptions(graph=GraphOptions(use_homography=False), covariance="none")
            ),
        ),
        ("fixed-lag all", lambda: run_fixed_lag(flight, FixedLagOptions())),
        (
            "fixed-lag all, no homography",
            lambda: run_fixed_lag(
                flight, FixedLagOptions(graph=GraphOptions(use_homography=False))
            ),
        ),
        ("seed 002 EKF + VO", lambda: run_seed002(flight)),
    ]
    print(
        f"{args.scenario}, {args.duration:g} s, seed {args.seed}, blur {args.blur_s:g} s, "
        f"{args.patches} featureless patches; {len(flight.images)} images"
    )
    print(
        f"{'run':30s} {'wall [s]':>8s} {'ATE [cm]':>8s} {'RPE [%]':>7s} {'end [cm]':>8s} "
        f"{'vel [m/s]':>9s} {'yaw [deg]':>9s} {'p50 [ms]':>8s}  homography"
    )
    for name, run in runs:
        t0 = time.perf_counter()
        est = run()
        wall = time.perf_counter() - t0
        m = evaluate(est, truth, "se3", delta_m=args.rpe_m)
        end, path = _end_error_m(est, truth)
        hom = (est.info.get("homography") or {}).get("counts")
        p50 = est.info.get("latency_p50_s")
        p50_ms = f"{1e3 * p50:8.1f}" if p50 is not None else f"{'-':>8s}"
        print(
            f"{name:30s} {wall:8.1f} {100 * m.ate_rmse_m:8.2f} {m.rpe_pct:7.2f} "
            f"{100 * end:8.2f} {m.vel_rmse_mps:9.4f} {m.yaw_rmse_deg:9.3f} {p50_ms}  "
            f"{hom if hom else '-'}",
            flush=True,
        )
    print(f"true path length {path:.2f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
