"""Frames per second and accuracy of the homography visual odometry at 320x240 and 640x480.

Seed 002 (sec. IV-C, Fig. 15) reports about 18 ms per frame, ~50 frames/s, for rectification plus
Shi-Tomasi and Lucas-Kanade in C++/OpenCV on a 3rd-generation Intel i5 at 3.4 GHz.

This script simulates a short ``two-turns`` flight at each resolution, runs the VO
(``fgnav.frontends.homography_vo.run``: every frame through ``HomographyVoStage``; true attitude
and height as inputs, so only the vision is timed) with and without rectification, and prints the
wall and CPU time per frame (all steps: image access, rectifying warp, corners, LK, RANSAC,
decomposition, dead reckoning) and the accuracy against the simulator's true homographies: the
RMS corner transfer error and its mean radial part over the pairs (a positive radial part is an
expansion of the measured homography). OpenCV runs on ``--threads`` threads (default 1: per-core
numbers). The pairs whose Lucas-Kanade started from the previous pair's motion
(``HomographyVOOptions.flow_guess``) and those whose guess was rejected (tracked again through the
pyramid) are counted on each line; ``--set flow_guess=none`` times the tracking without it.
``--attitude ahrs`` feeds the flight's simulated AHRS stream (0.005 rad noise) instead of the
true attitude, as the online loop does: the rectified images then jitter with its noise, and
the accuracy includes that of the attitude.

Usage::

    .venv/bin/python scripts/bench_vo.py [--duration 12] [--repeat 5] [--threads 1,2]
        [--resolutions 320x240] [--attitude ahrs]
        [--set lk_window_px=21 --set forward_backward=True ...]

Timings on a shared, loaded machine are noisy: the best of ``--repeat`` runs is reported (wall
and CPU separately).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import platform
import time

import cv2
import numpy as np
from fgnav.datasets.simulate import SimOptions, simulate
from fgnav.datasets.simulate.render import inter_frame_homography
from fgnav.datasets.simulate.simulator import world_T_cam_at
from fgnav.datasets.types import AttitudeSeries

from fgnav.estimate import TimeSeries
from fgnav.frontends.homography_vo import (
    HomographyVOOptions,
    corner_transfer_components,
    run,
)

#: Seed 002's reported rate (frames/s) on an Intel i5 (sec. V).
PAPER_FPS = 50.0
CONFIGS = ((False, "opencv"), (True, "opencv"), (True, "attitude"))


def _option_overrides(items: list[str]) -> dict:
    names = {f.name for f in dataclasses.fields(HomographyVOOptions)}
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in names:
            raise SystemExit(
                f"--set {item!r}: expected NAME=VALUE with NAME one of {sorted(names)}"
            )
        try:
            out[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            out[key] = value
    return out


def accuracy(flight, res, ground: float) -> tuple[float, float, float]:
    """RMS corner transfer error [px], mean radial part [px] and its standard error over the
    valid pairs, against the simulator's true homographies."""
    cam = flight.images.camera
    err, radial = [], []
    for m in res.measurements:
        if not m.valid:
            continue
        T_i, T_j = world_T_cam_at(flight, [m.t_i, m.t_j])
        H_true = inter_frame_homography(T_i, T_j, cam.K, ground)
        r, t = corner_transfer_components(m.H, H_true, cam.width, cam.height, cam.K[:2, 2])
        err.append(np.hypot(r, t))
        radial.append(r)
    err, radial = np.array(err), np.array(radial)
    return (
        float(np.sqrt(np.mean(err**2))),
        float(radial.mean()),
        float(radial.std() / np.sqrt(radial.size)),
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=12.0, help="simulated seconds per run")
    ap.add_argument("--repeat", type=int, default=5, help="runs per configuration (best kept)")
    ap.add_argument("--threads", default="1", help="OpenCV thread counts to run, e.g. 1,2")
    ap.add_argument(
        "--resolutions", default="320x240,640x480", help="image sizes WxH, comma-separated"
    )
    ap.add_argument(
        "--attitude",
        choices=("truth", "ahrs"),
        default="truth",
        help="attitude input: the true one (only the vision timed) or the simulated AHRS stream",
    )
    ap.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE", help="VO option override"
    )
    args = ap.parse_args()
    overrides = _option_overrides(args.set)
    threads = [int(n) for n in args.threads.split(",")]
    print(
        f"OpenCV {cv2.__version__}, {platform.processor() or platform.machine()}; machine shared "
        f"with other jobs: timings are noisy (best of {args.repeat} runs, wall and CPU apart)"
    )
    if overrides:
        print(f"options: {overrides}")
    print(
        f"{'resolution':>10s} {'thr':>3s} {'rectify':>7s} {'decomp':>8s} {'frames':>6s} "
        f"{'ms/frame':>8s} {'frames/s':>8s} {'CPU f/s':>8s} {'rms px':>7s} {'radial px':>13s}"
    )
    resolutions = [tuple(int(v) for v in r.split("x")) for r in args.resolutions.split(",")]
    for w, h in resolutions:
        flight = simulate(
            "two-turns",
            seed=0,
            options=SimOptions(
                duration=args.duration, image_width=w, image_height=h, slam_rate_hz=0.0
            ),
        )
        gt = flight.ground_truth
        ground = float(flight.meta["truth"]["ground_height"])
        attitude = (
            AttitudeSeries(t=gt.t, world_q_body_wxyz=gt.world_q_body_wxyz)
            if args.attitude == "truth"
            else flight.attitude
        )
        height = TimeSeries(t=gt.t, value=gt.world_t_body[:, 2] - ground)
        n = len(flight.images)
        for n_threads in threads:
            cv2.setNumThreads(n_threads)
            for rectify, decomposition in CONFIGS:
                opts = HomographyVOOptions(
                    **{"rectify": rectify, "decomposition": decomposition, **overrides}
                )
                best, best_cpu = np.inf, np.inf
                for _ in range(args.repeat):
                    t0, c0 = time.perf_counter(), time.process_time()
                    res = run(flight, attitude=attitude, height=height, options=opts)
                    best = min(best, time.perf_counter() - t0)
                    best_cpu = min(best_cpu, time.process_time() - c0)
                rms, radial, sem = accuracy(flight, res, ground)
                ms = best / n * 1000.0
                print(
                    f"{w:>5d}x{h:<4d} {n_threads:3d} {rectify!s:>7s} {decomposition:>8s} {n:6d} "
                    f"{ms:8.2f} {1000.0 / ms:8.1f} {n / best_cpu:8.1f} {rms:7.4f} "
                    f"{radial:+7.4f}+-{sem:.4f}   ({res.counts['valid_pairs']} valid pairs, LK "
                    f"guessed {res.counts.get('flow_guess_previous', 0)}, guess rejected "
                    f"{res.counts.get('flow_guess_rejected', 0)})"
                )
    print(f"paper (C++, i5 3.4 GHz): ~{PAPER_FPS:.0f} frames/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
