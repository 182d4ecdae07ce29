"""Rendering speed of the simulator's downward camera (frames per second).

Renders the poses of a simulated two-turns flight at 320x240 and 640x480 (one warpPerspective
per frame, plus noise and uint8 conversion as in ``simulate()``) and prints frames/s. Timings
depend on the machine's load; run it on an idle machine for figures worth quoting.

Usage: ``.venv/bin/python scripts/bench_render.py [--frames N] [--seed S]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from fgnav.datasets.geometry import make_pose
from fgnav.datasets.simulate import SimOptions, simulate
from fgnav.datasets.simulate.render import Carpet, ground_footprints, pinhole_from_fov, to_uint8

SIZES = ((320, 240), (640, 480))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200, help="frames rendered per size")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    flight = simulate("two-turns", seed=args.seed, options=SimOptions(images=False))
    gt = flight.ground_truth
    step = max(1, len(gt) // args.frames)
    R = gt.world_R_body()
    poses = np.stack(
        [
            make_pose(R[i], gt.world_t_body[i]) @ flight.calib.body_T_cam
            for i in range(0, len(gt), step)
        ][: args.frames]
    )
    rng = np.random.default_rng(args.seed)
    print(f"{len(poses)} poses of two-turns (3.5-4 m high); machine load affects the timings")
    for width, height in SIZES:
        fx, fy, cx, cy = pinhole_from_fov(width, height, 64.0)
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        corners = ground_footprints(poses, K, width, height, 0.0).reshape(-1, 2)
        t0 = time.perf_counter()
        carpet = Carpet.make(corners.min(axis=0), corners.max(axis=0), 0.0, 0.01, rng)
        t_carpet = time.perf_counter() - t0
        carpet.render(poses[0], K, width, height)  # warm-up
        t0 = time.perf_counter()
        for P in poses:
            img = carpet.render(P, K, width, height)
            to_uint8(img + 2.0 * rng.standard_normal(img.shape, dtype=np.float32))
        dt = time.perf_counter() - t0
        t0 = time.perf_counter()
        for P in poses:
            to_uint8(carpet.render(P, K, width, height))
        dt_clean = time.perf_counter() - t0
        print(
            f"{width}x{height}: {len(poses) / dt:7.1f} frames/s with pixel noise, "
            f"{len(poses) / dt_clean:7.1f} frames/s warp only "
            f"(carpet {carpet.levels[0].shape[1]}x{carpet.levels[0].shape[0]} texels "
            f"built in {t_carpet:.2f} s)"
        )


if __name__ == "__main__":
    main()
