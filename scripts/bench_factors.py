"""Cost of fgnav's custom factors next to GTSAM's built-in BetweenFactorPose3.

Two measurements per factor type:

1. ``linearize``: microseconds per factor of ``graph.linearize(values)`` called from Python on a
   graph of ``--n-linearize`` copies of the factor (best of ``--repeats``).
2. ``ISAM2``: a chain of ``--n-poses`` poses fed one keyframe per ``ISAM2.update`` (odometry
   ``BetweenFactorPose3`` + velocity priors + slow variables), with and without one factor of the
   type per keyframe. The extra time divided by the number of Python callbacks made (counted by
   wrapping the factor module's error function) is the cost of one callback inside ISAM2, which
   grows with the number of variables (../shared/GTSAM-NOTES.md).

Usage: ``.venv/bin/python scripts/bench_factors.py [--n-poses 200] [--n-linearize 500]``.
Timings are wall-clock on whatever else the machine is running: say so when quoting them.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from fgnav.factors import accel_drag, homography_motion, slam_scale, tilted_range, yaw
from fgnav.factors.slam_scale import make_slam_T_world

from fgnav.keys import B, D, G, S, V, X

WIDTH, HEIGHT = 320, 240
K = np.array([[256.0, 0.0, 159.5], [0.0, 256.0, 119.5], [0.0, 0.0, 1.0]])
BODY_T_CAM = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.05, 0.0, -0.03]))
BODY_T_RANGE = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.0, 0.05, -0.02]))
GROUND = 0.0
SLAM_T_WORLD = make_slam_T_world(0.4, gtsam.Rot3.Yaw(0.7).matrix(), np.array([1.0, -2.0, 0.5]))
AXIS_SCALE = np.array([0.3, 0.2, 0.5])
DRAG_K = np.array([0.3])
BIAS = gtsam.imuBias.ConstantBias(np.array([0.02, -0.01, 0.03]), np.zeros(3))


@dataclass
class Truth:
    poses: list[gtsam.Pose3]
    velocities: list[np.ndarray]


def make_truth(n: int) -> Truth:
    """A 10 Hz figure at 2-3 m over flat ground with small tilts."""
    t = np.arange(n) * 0.1
    poses, vels = [], []
    for ti in t:
        p = np.array([3 * np.sin(0.3 * ti), 2 * np.sin(0.6 * ti), 2.5 + 0.3 * np.sin(0.5 * ti)])
        v = np.array([0.9 * np.cos(0.3 * ti), 1.2 * np.cos(0.6 * ti), 0.15 * np.cos(0.5 * ti)])
        poses.append(gtsam.Pose3(gtsam.Rot3.Ypr(0.2 * ti, 0.05 * np.sin(ti), -0.04), p))
        vels.append(v)
    return Truth(poses, vels)


def _unit(dim: int) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Isotropic.Sigma(dim, 0.1)


def _slam_t(pose: gtsam.Pose3) -> np.ndarray:
    return SLAM_T_WORLD.transformFrom(pose.compose(BODY_T_CAM).translation())


def _homography(truth: Truth, k: int) -> np.ndarray:
    return homography_motion.predicted_homography(
        truth.poses[k - 1], truth.poses[k], GROUND, K, BODY_T_CAM
    )


def _decomposed(truth: Truth, k: int) -> tuple[np.ndarray, np.ndarray]:
    cam_i = truth.poses[k - 1].compose(BODY_T_CAM)
    cam_j_T_cam_i = truth.poses[k].compose(BODY_T_CAM).between(cam_i)
    d = cam_i.translation()[2] - GROUND
    return cam_j_T_cam_i.rotation().matrix(), cam_j_T_cam_i.translation() / d


# name -> (module, name of the error function its callback calls (counted), factor maker (truth, k)
# or None when the factor needs a previous pose and k == 0)
FactorMaker = Callable[[Truth, int], gtsam.NonlinearFactor | None]


def _between(truth: Truth, k: int):
    if k == 0:
        return None
    odo = truth.poses[k - 1].between(truth.poses[k])
    return gtsam.BetweenFactorPose3(X(k - 1), X(k), odo, _unit(6))


def _drag(truth: Truth, k: int):
    pose, vel = truth.poses[k], truth.velocities[k]
    z = -DRAG_K[0] * (pose.rotation().matrix().T @ vel)[:2] + BIAS.accelerometer()[:2]
    return accel_drag.make_accel_drag_factor(X(k), V(k), B(0), D(0), z, _unit(2))


def _slam_pos(truth: Truth, k: int):
    z = _slam_t(truth.poses[k])
    return slam_scale.make_slam_position_factor(X(k), S(0), z, BODY_T_CAM, _unit(3))


def _slam_rel(truth: Truth, k: int):
    if k == 0:
        return None
    zi, zj = _slam_t(truth.poses[k - 1]), _slam_t(truth.poses[k])
    return slam_scale.make_slam_relative_factor(X(k - 1), X(k), S(0), zi, zj, BODY_T_CAM, _unit(3))


def _slam_rot(truth: Truth, k: int):
    R = SLAM_T_WORLD.rotation().matrix() @ truth.poses[k].compose(BODY_T_CAM).rotation().matrix()
    return slam_scale.make_slam_rotation_factor(X(k), S(0), R, BODY_T_CAM, _unit(3))


def _slam_axis(truth: Truth, k: int):
    z = AXIS_SCALE * truth.poses[k].translation()
    return slam_scale.make_slam_axis_scale_factor(X(k), S(1), z, _unit(3))


def _yaw(truth: Truth, k: int):
    return yaw.make_yaw_factor(X(k), truth.poses[k].rotation().yaw(), _unit(1))


def _yaw_cs(truth: Truth, k: int):
    return yaw.make_yaw_factor(X(k), truth.poses[k].rotation().yaw(), _unit(2), cos_sin=True)


def _range(truth: Truth, k: int):
    r, _ = tilted_range.tilted_range_error(truth.poses[k], np.array([GROUND]), 0.0, BODY_T_RANGE)
    return tilted_range.make_range_factor(X(k), G(0), r[0], BODY_T_RANGE, _unit(1))


def _homog(truth: Truth, k: int):
    if k == 0:
        return None
    return homography_motion.make_homography_factor(
        X(k - 1), X(k), G(0), _homography(truth, k), K, BODY_T_CAM, (WIDTH, HEIGHT), _unit(8)
    )


def _homog_dec(truth: Truth, k: int):
    if k == 0:
        return None
    R, u = _decomposed(truth, k)
    return homography_motion.make_homography_decomposed_factor(
        X(k - 1), X(k), G(0), R, u, BODY_T_CAM, _unit(6)
    )


CASES: list[tuple[str, object, str, FactorMaker]] = [
    ("BetweenFactorPose3 (C++)", None, "", _between),
    ("accel_drag", accel_drag, "_accel_drag", _drag),
    ("slam_position", slam_scale, "_slam_position", _slam_pos),
    ("slam_relative", slam_scale, "slam_relative_error", _slam_rel),
    ("slam_rotation", slam_scale, "slam_rotation_error", _slam_rot),
    ("slam_axis_scale", slam_scale, "slam_axis_scale_error", _slam_axis),
    ("yaw", yaw, "_yaw", _yaw),
    ("yaw cos_sin", yaw, "_yaw", _yaw_cs),
    ("tilted_range", tilted_range, "_tilted_range", _range),
    ("homography (8-D)", homography_motion, "homography_error", _homog),
    ("homography_decomposed", homography_motion, "homography_decomposed_error", _homog_dec),
]


def base_values(truth: Truth, n: int) -> gtsam.Values:
    values = gtsam.Values()
    for k in range(n):
        values.insert(X(k), truth.poses[k])
        values.insert(V(k), truth.velocities[k])
    values.insert(B(0), BIAS)
    values.insert(D(0), DRAG_K)
    values.insert(S(0), SLAM_T_WORLD)
    values.insert(S(1), AXIS_SCALE)
    values.insert(G(0), np.array([GROUND]))
    return values


def bench_linearize(truth: Truth, maker: FactorMaker, n_factors: int, repeats: int) -> float:
    """Microseconds per factor of ``graph.linearize`` from Python."""
    graph = gtsam.NonlinearFactorGraph()
    k = 1
    while graph.size() < n_factors:
        graph.add(maker(truth, k))
        k = k % (len(truth.poses) - 1) + 1
    values = base_values(truth, len(truth.poses))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        graph.linearize(values)
        best = min(best, time.perf_counter() - t0)
    return best / n_factors * 1e6


def _slow_priors(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
    tight = gtsam.noiseModel.Isotropic.Sigma
    graph.add(gtsam.PriorFactorConstantBias(B(0), BIAS, tight(6, 0.01)))
    graph.add(gtsam.PriorFactorVector(D(0), DRAG_K, tight(1, 0.1)))
    graph.add(gtsam.PriorFactorSimilarity3(S(0), SLAM_T_WORLD, tight(7, 0.1)))
    graph.add(gtsam.PriorFactorVector(S(1), AXIS_SCALE, tight(3, 0.1)))
    graph.add(gtsam.PriorFactorVector(G(0), np.array([GROUND]), tight(1, 0.1)))
    values.insert(B(0), BIAS)
    values.insert(D(0), DRAG_K)
    values.insert(S(0), SLAM_T_WORLD)
    values.insert(S(1), AXIS_SCALE)
    values.insert(G(0), np.array([GROUND]))


def bench_isam2(truth: Truth, maker: FactorMaker | None) -> float:
    """Total seconds of ``ISAM2.update`` over the chain, with one ``maker`` factor per keyframe."""
    params = gtsam.ISAM2Params()
    isam = gtsam.ISAM2(params)
    total = 0.0
    for k in range(len(truth.poses)):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(gtsam.PriorFactorPose3(X(0), truth.poses[0], _unit(6)))
            _slow_priors(graph, values)
        else:
            graph.add(_between(truth, k))
        graph.add(gtsam.PriorFactorVector(V(k), truth.velocities[k], _unit(3)))
        values.insert(X(k), truth.poses[k])
        values.insert(V(k), truth.velocities[k])
        if maker is not None:
            factor = maker(truth, k)
            if factor is not None:
                graph.add(factor)
        t0 = time.perf_counter()
        isam.update(graph, values)
        total += time.perf_counter() - t0
    return total


def count_callbacks(module: object, name: str, run: Callable[[], float]) -> tuple[float, int]:
    """Run ``run`` with ``module.name`` wrapped by a counter; ``(result, calls)``."""
    original = getattr(module, name)
    calls = 0

    def counted(*args, **kwargs):
        nonlocal calls
        calls += 1
        return original(*args, **kwargs)

    setattr(module, name, counted)
    try:
        result = run()
    finally:
        setattr(module, name, original)
    return result, calls


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-poses", type=int, default=200, help="ISAM2 chain length")
    parser.add_argument("--n-linearize", type=int, default=500, help="factors per linearize graph")
    parser.add_argument("--repeats", type=int, default=3, help="best of N runs")
    args = parser.parse_args()

    truth = make_truth(max(args.n_poses, 2))
    n = args.n_poses
    print(f"ISAM2 chain of {n} keyframes (odometry + velocity priors + 5 slow variables);")
    print(f"every time is the best of {args.repeats} runs, each case run beside its own baseline")
    header = (
        f"{'factor':<26} {'linearize us/factor':>20} {'ISAM2 ms/update':>16} "
        f"{'baseline ms':>12} {'callbacks':>10} {'extra us/callback':>18}"
    )
    print(header)
    print("-" * len(header))
    for name, module, fn_name, maker in CASES:
        lin_us = bench_linearize(truth, maker, args.n_linearize, args.repeats)
        totals, baselines, calls = [], [], 0
        for _ in range(args.repeats):
            baselines.append(bench_isam2(truth, None))
            if module is None:
                totals.append(bench_isam2(truth, maker))
            else:
                total, calls = count_callbacks(
                    module, fn_name, lambda m=maker: bench_isam2(truth, m)
                )
                totals.append(total)
        total, baseline = min(totals), min(baselines)
        per_cb = f"{(total - baseline) / calls * 1e6:18.1f}" if calls else f"{'(C++)':>18}"
        calls_s = f"{calls:10d}" if calls else f"{'-':>10}"
        print(
            f"{name:<26} {lin_us:20.1f} {total / n * 1e3:16.3f} {baseline / n * 1e3:12.3f} "
            f"{calls_s} {per_cb}"
        )
    print(
        "extra us/callback = (ISAM2 time - baseline) / callbacks: it includes the extra elimination"
        " work of factors that tie every keyframe to a slow variable (B, D, S, G)."
    )
    print("Wall-clock on a shared, loaded machine: compare rows, not absolute numbers.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
