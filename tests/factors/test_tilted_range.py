"""Tilted rangefinder factor: hand-computed ranges, Jacobians, gating, robust noise, recovery."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from fgnav.factors.tilted_range import (
    MIN_COS_TILT,
    gate_range,
    make_range_factor,
    predicted_range,
    tilted_range_error,
)

from fgnav.keys import G, X

from .numdiff import assert_jacobians_close, unit_noise

DOWN = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.zeros(3))  # beam (sensor +z) along body -z


def test_range_of_a_rolled_body_is_height_over_cos() -> None:
    roll = np.deg2rad(30.0)
    pose = gtsam.Pose3(gtsam.Rot3.Roll(roll), np.array([1.0, 2.0, 2.0]))
    e, J = tilted_range_error(pose, np.array([0.5]), 0.0, DOWN)
    assert e[0] == pytest.approx(1.5 / np.cos(roll), abs=1e-12)
    assert [j.shape for j in J] == [(1, 6), (1, 1)]


def test_lever_arm_counts() -> None:
    # Sensor 0.2 m forward of the body origin; pitch nose-down (positive pitch about FLU y) by 10
    # deg lowers it by 0.2 sin(10 deg).
    pitch = np.deg2rad(10.0)
    body_T_range = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.2, 0.0, 0.0]))
    pose = gtsam.Pose3(gtsam.Rot3.Pitch(pitch), np.array([0.0, 0.0, 3.0]))
    e, _ = tilted_range_error(pose, np.array([0.0]), 0.0, body_T_range)
    expected = (3.0 - 0.2 * np.sin(pitch)) / np.cos(pitch)
    assert e[0] == pytest.approx(expected, abs=1e-12)


def test_predicted_range_is_the_factors_prediction_and_nan_beyond_85_deg() -> None:
    """``predicted_range`` (the health checks' expected reading) is ``h(x)`` of the factor at
    random tilted states with a lever arm, one at a time and stacked; NaN once the beam points
    85 deg or more from down (the factor floors its cosine there instead)."""
    rng = np.random.default_rng(7)
    body_T_range = gtsam.Pose3(
        DOWN.rotation().compose(gtsam.Rot3.Expmap([0.1, -0.05, 0.0])), np.array([0.1, 0.0, -0.02])
    )
    T = body_T_range.matrix()
    poses = [
        gtsam.Pose3(gtsam.Rot3.Expmap(rng.uniform(-0.5, 0.5, 3)), rng.uniform(-3, 3, 3))
        for _ in range(6)
    ]
    ground = rng.uniform(-5, -1, 6)
    h = [
        tilted_range_error(p, np.array([g]), 0.0, body_T_range)[0][0]
        for p, g in zip(poses, ground, strict=True)
    ]
    R = np.stack([p.rotation().matrix() for p in poses])
    t = np.stack([p.translation() for p in poses])
    np.testing.assert_allclose(predicted_range(R, t, ground, T), h, rtol=1e-12)
    assert predicted_range(R[0], t[0], ground[0], T) == pytest.approx(h[0], rel=1e-12)
    on_side = gtsam.Rot3.Roll(np.pi / 2)  # beam horizontal (a body rolled 90 deg)
    assert np.isnan(predicted_range(on_side.matrix(), np.zeros(3), -1.0, DOWN.matrix()))


@pytest.mark.parametrize("seed", range(5))
def test_jacobians_match_central_differences(seed: int) -> None:
    rng = np.random.default_rng(300 + seed)
    pose = gtsam.Pose3(gtsam.Rot3.Expmap(rng.uniform(-0.5, 0.5, 3)), rng.uniform(-3, 3, 3))
    body_T_range = gtsam.Pose3(
        DOWN.rotation().compose(gtsam.Rot3.Expmap(rng.uniform(-0.2, 0.2, 3))),
        rng.uniform(-0.2, 0.2, 3),
    )
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(G(0), np.array([rng.uniform(-5, -1)]))
    factor = make_range_factor(X(0), G(0), rng.uniform(1, 5), body_T_range, unit_noise(1))
    assert_jacobians_close(factor, values, [6, 1])


@pytest.mark.parametrize("seed", range(5))
def test_zero_error_at_a_consistent_state(seed: int) -> None:
    """A range made by intersecting the beam with the ground plane (geometry written out here,
    not the factor's) gives zero error at random tilted states with a lever arm."""
    rng = np.random.default_rng(400 + seed)
    pose = gtsam.Pose3(gtsam.Rot3.Expmap(rng.uniform(-0.4, 0.4, 3)), rng.uniform(-3, 3, 3))
    body_T_range = gtsam.Pose3(
        DOWN.rotation().compose(gtsam.Rot3.Expmap(rng.uniform(-0.2, 0.2, 3))),
        rng.uniform(-0.2, 0.2, 3),
    )
    ground = pose.translation()[2] - rng.uniform(1.0, 4.0)
    world_T_range = pose.compose(body_T_range)
    origin = world_T_range.translation()
    beam = world_T_range.rotation().matrix()[:, 2]  # sensor +z in the world
    assert beam[2] < 0.0  # pointing down
    hit = origin + (ground - origin[2]) / beam[2] * beam
    range_true = float(np.linalg.norm(hit - origin))
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(G(0), np.array([ground]))
    factor = make_range_factor(X(0), G(0), range_true, body_T_range, unit_noise(1))
    assert factor.unwhitenedError(values) == pytest.approx([0.0], abs=1e-12)
    assert factor.error(values) == pytest.approx(0.0, abs=1e-20)
    off = make_range_factor(X(0), G(0), range_true + 0.05, body_T_range, unit_noise(1))
    assert off.unwhitenedError(values) == pytest.approx([-0.05], abs=1e-12)  # h(x) - z


def test_cos_tilt_is_floored() -> None:
    pose = gtsam.Pose3(gtsam.Rot3.Roll(np.deg2rad(89.9)), np.array([0.0, 0.0, 2.0]))
    e, J = tilted_range_error(pose, np.array([0.0]), 0.0, DOWN)
    assert e[0] == pytest.approx(2.0 / MIN_COS_TILT)
    assert np.all(np.isfinite(J[0]))


@pytest.mark.parametrize(
    ("range_meas", "roll_deg", "body_T_range", "ok", "reason"),
    [
        (2.0, 5.0, DOWN, True, "ok"),
        (0.05, 0.0, DOWN, False, "out of range"),
        (12.0, 0.0, DOWN, False, "out of range"),
        (float("nan"), 0.0, DOWN, False, "non-finite"),
        (2.0, 35.0, DOWN, False, "tilt"),
        (2.0, 0.0, gtsam.Pose3(), False, "beam not pointing down"),
        (2.0, 120.0, DOWN, False, "beam not pointing down"),
    ],
)
def test_gate_range(range_meas, roll_deg, body_T_range, ok, reason) -> None:
    world_R_body = gtsam.Rot3.Roll(np.deg2rad(roll_deg)).matrix()
    accepted, why = gate_range(range_meas, world_R_body, body_T_range, 0.1, 10.0, np.deg2rad(30))
    assert accepted is ok
    assert why.startswith(reason)


def test_robust_noise_evaluates_and_linearises() -> None:
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(gtsam.Rot3.Roll(0.1), np.array([0.0, 0.0, 2.0])))
    values.insert(G(0), np.array([0.0]))
    base = gtsam.noiseModel.Isotropic.Sigma(1, 0.02)
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345), base)
    obstacle = 0.8  # a box under the vehicle
    f_robust = make_range_factor(X(0), G(0), obstacle, DOWN, robust)
    f_gauss = make_range_factor(X(0), G(0), obstacle, DOWN, base)
    assert f_robust.error(values) < 0.05 * f_gauss.error(values)
    A, b = f_robust.linearize(values).jacobian()
    assert A.shape == (1, 7) and np.all(np.isfinite(A)) and np.all(np.isfinite(b))


def _tilted_poses(rng: np.random.Generator, n: int) -> list[gtsam.Pose3]:
    return [
        gtsam.Pose3(
            gtsam.Rot3.Ypr(rng.uniform(-np.pi, np.pi), *rng.uniform(-0.3, 0.3, 2)),
            np.array([*rng.uniform(-5, 5, 2), rng.uniform(1.0, 4.0)]),
        )
        for _ in range(n)
    ]


def test_ground_height_recovered_from_ranges() -> None:
    rng = np.random.default_rng(9)
    ground_true, sigma = -0.7, 0.02
    body_T_range = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.1, 0.05, -0.03]))
    poses = _tilted_poses(rng, 25)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Isotropic.Sigma(1, sigma)
    for i, pose in enumerate(poses):
        r, _ = tilted_range_error(pose, np.array([ground_true]), 0.0, body_T_range)
        graph.add(make_range_factor(X(i), G(0), r[0] + rng.normal(0, sigma), body_T_range, noise))
        graph.add(gtsam.PriorFactorPose3(X(i), pose, gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        values.insert(X(i), pose)
    graph.add(gtsam.PriorFactorVector(G(0), np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 10)))
    values.insert(G(0), np.zeros(1))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    # sigma / sqrt(25) * cos(tilt) ~ 0.004 m; bound at ~4 sigma.
    assert result.atVector(G(0))[0] == pytest.approx(ground_true, abs=0.016)


def test_heights_recovered_from_ranges_over_known_ground() -> None:
    rng = np.random.default_rng(10)
    sigma = 0.01
    poses = _tilted_poses(rng, 10)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Isotropic.Sigma(1, sigma)
    # Rotation pinned, translation nearly free (10 m) around a prior 0.5 m too high.
    pose_prior = gtsam.noiseModel.Diagonal.Sigmas([1e-6] * 3 + [10.0] * 3)
    for i, pose in enumerate(poses):
        r, _ = tilted_range_error(pose, np.zeros(1), 0.0, DOWN)
        wrong = gtsam.Pose3(pose.rotation(), pose.translation() + np.array([0.0, 0.0, 0.5]))
        graph.add(make_range_factor(X(i), G(0), r[0] + rng.normal(0, sigma), DOWN, noise))
        graph.add(gtsam.PriorFactorPose3(X(i), wrong, pose_prior))
        values.insert(X(i), wrong)
    graph.add(gtsam.PriorFactorVector(G(0), np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, 1e-6)))
    values.insert(G(0), np.zeros(1))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    heights = np.array([result.atPose3(X(i)).z() for i in range(len(poses))])
    truth = np.array([p.z() for p in poses])
    np.testing.assert_allclose(heights, truth, atol=4 * sigma)
