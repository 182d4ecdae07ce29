"""Figures of the optical-flow stream on a simulated flow-deck flight (issue 17): the batch
smoother (IMU + flow + range), the fixed-lag smoother, the Crazyflie-style EKF (``cf-ekf``) and
seed 002's EKF with flow dead reckoning (``ekf-flow002``) against the truth.

Flight: ``flowdeck`` (Crazyflie-like, 0.4-1.3 m over the floor, up to 1.4 m/s), IMU + flow
(100 Hz) + range (25 Hz); no SLAM, attitude, yaw or images. ``--crazyflie-range`` (default) sets
the rangefinder as measured on the real flow-deck flights (8 mm noise, no airborne outliers);
``--sim-range`` keeps the simulator's (1 cm, 1 % obstacle spikes).

Figures (``fgnav.eval.metrics.flow_flight_figures``, one 4-DoF alignment per trajectory):
horizontal velocity RMSE (raw and 100 ms averages), height RMSE, ATE, end drift.

    .venv/bin/python scripts/bench_flow.py --duration 40 --seed 0
"""

from __future__ import annotations

import argparse
import json
import time

from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.eval.metrics import flow_flight_figures
from fgnav.methods import METHODS


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sim-range", action="store_true", help="the simulator's rangefinder")
    ap.add_argument("--methods", default="batch,fixed-lag,cf-ekf,ekf-flow002")
    ap.add_argument("--json", default=None, help="write the figures here")
    a = ap.parse_args()
    rng = {} if a.sim_range else {"range_noise_m": 0.008, "range_outlier_prob": 0.0}
    opts = SimOptions(
        images=False,
        slam_rate_hz=0.0,
        attitude_rate_hz=0.0,
        yaw_rate_hz=0.0,
        duration=a.duration,
        **rng,
    )
    flight = simulate("flowdeck", seed=a.seed, options=opts)
    rows = {}
    print(
        f"flowdeck seed {a.seed}, {a.duration:g} s, range "
        f"{'simulator' if a.sim_range else 'Crazyflie-like (8 mm, no outliers)'}"
    )
    print(
        f"{'method':14s} {'hvel':>7s} {'hvel100':>8s} {'height':>7s} {'ATE4':>7s} "
        f"{'drift':>7s} {'drift%':>7s} {'time':>6s}"
    )
    for name in a.methods.split(","):
        t0 = time.perf_counter()
        est = METHODS[name].run(flight, {})
        wall = time.perf_counter() - t0
        fig = flow_flight_figures(est, flight.ground_truth)
        fig100 = flow_flight_figures(est, flight.ground_truth, velocity_average_s=0.1)
        fig["hvel100_rmse_mps"] = fig100["hvel_rmse_mps"]
        fig["wall_s"] = wall
        rows[name] = fig
        print(
            f"{name:14s} {fig['hvel_rmse_mps']:7.3f} {fig['hvel100_rmse_mps']:8.3f} "
            f"{fig['height_rmse_m']:7.3f} {fig['ate_m']:7.3f} {fig['end_drift_m']:7.3f} "
            f"{fig['end_drift_pct']:7.2f} {wall:6.1f}"
        )
    print("units: m/s, m/s (100 ms means), m, m, m, % of the horizontal path, s")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
