"""Frames per second of the homography visual odometry at 320x240 and 640x480.

Seed 002 (sec. IV-C, Fig. 15) reports about 18 ms per frame, ~50 frames/s, for rectification plus
Shi-Tomasi and Lucas-Kanade in C++/OpenCV on a 3rd-generation Intel i5 at 3.4 GHz.

This script simulates a short ``two-turns`` flight at each resolution, runs
``fgnav.frontends.homography_vo.run`` (true attitude and height as inputs, so only the vision is
timed) with and without rectification, and prints the wall time per frame (all steps: image
access, rectifying warp, corners, LK both ways, RANSAC, decomposition, dead reckoning). OpenCV is
limited to one thread so the numbers are per core.

Usage::

    .venv/bin/python scripts/bench_vo.py [--duration 6] [--repeat 3]

Timings on a shared, loaded machine are noisy: the best of ``--repeat`` runs is reported.
"""

from __future__ import annotations

import argparse
import platform
import time

import cv2
import numpy as np
from fgnav.datasets.simulate import SimOptions, simulate
from fgnav.datasets.types import AttitudeSeries

from fgnav.estimate import TimeSeries
from fgnav.frontends.homography_vo import HomographyVOOptions, run

#: Seed 002's reported rate (frames/s) on an Intel i5 (sec. V).
PAPER_FPS = 50.0
RESOLUTIONS = ((320, 240), (640, 480))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=6.0, help="simulated seconds per run")
    ap.add_argument("--repeat", type=int, default=3, help="runs per configuration (best kept)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(
        f"OpenCV {cv2.__version__}, 1 thread, {platform.processor() or platform.machine()}; "
        "machine shared with other jobs: timings are noisy (best of "
        f"{args.repeat} runs)"
    )
    print(
        f"{'resolution':>10s} {'rectify':>8s} {'decomp':>9s} {'frames':>6s} {'ms/frame':>9s} "
        f"{'frames/s':>9s}"
    )
    for w, h in RESOLUTIONS:
        flight = simulate(
            "two-turns",
            seed=0,
            options=SimOptions(
                duration=args.duration, image_width=w, image_height=h, slam_rate_hz=0.0
            ),
        )
        gt = flight.ground_truth
        attitude = AttitudeSeries(t=gt.t, world_q_body_wxyz=gt.world_q_body_wxyz)
        height = TimeSeries(
            t=gt.t, value=gt.world_t_body[:, 2] - float(flight.meta["truth"]["ground_height"])
        )
        n = len(flight.images)
        for rectify, decomposition in ((False, "opencv"), (True, "opencv"), (True, "attitude")):
            opts = HomographyVOOptions(rectify=rectify, decomposition=decomposition)
            best = np.inf
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                res = run(flight, attitude=attitude, height=height, options=opts)
                best = min(best, time.perf_counter() - t0)
            ms = best / n * 1000.0
            print(
                f"{w:>5d}x{h:<4d} {rectify!s:>8s} {decomposition:>9s} {n:6d} {ms:9.2f} "
                f"{1000.0 / ms:9.1f}   ({res.counts['valid_pairs']} valid pairs)"
            )
    print(f"paper (C++, i5 3.4 GHz): ~{PAPER_FPS:.0f} frames/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
