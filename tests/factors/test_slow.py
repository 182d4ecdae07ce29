"""Slow-variable helpers: values, sigmas in GTSAM coordinates, random walks in a small graph."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from fgnav.factors.accel_drag import make_accel_drag_factor
from fgnav.factors.slam_scale import make_slam_T_world
from fgnav.factors.slow import (
    SlamAlignmentSigmas,
    drag_initial,
    drag_prior,
    drag_random_walk,
    ground_initial,
    ground_prior,
    ground_random_walk,
    random_walk_sigma,
    slam_alignment_initial,
    slam_alignment_prior,
    slam_alignment_random_walk,
    wind_prior,
    wind_random_walk,
)

from fgnav.keys import B, D, G, S, V, W, X


def _whitened_norm(factor, values) -> float:
    return float(np.sqrt(2.0 * factor.error(values)))


def test_drag_and_ground_values_and_priors() -> None:
    np.testing.assert_array_equal(drag_initial(0.3), [0.3])
    np.testing.assert_array_equal(drag_initial(0.3, per_axis=True), [0.3, 0.3])
    np.testing.assert_array_equal(drag_initial([0.3, 0.2], per_axis=True), [0.3, 0.2])
    with pytest.raises(ValueError, match="drag k0"):
        drag_initial([0.3, 0.2])
    values = gtsam.Values()
    values.insert(D(0), np.array([0.5]))
    values.insert(G(0), ground_initial(-1.0))
    assert _whitened_norm(drag_prior(D(0), 0.3, 0.1), values) == pytest.approx(2.0)
    assert _whitened_norm(ground_prior(G(0), -1.5, 0.25), values) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="sigma"):
        ground_prior(G(0), 0.0, 0.0)


def test_random_walk_sigma_scales_with_sqrt_elapsed() -> None:
    assert random_walk_sigma(0.01, 4.0) == pytest.approx(0.02)
    values = gtsam.Values()
    values.insert(D(0), np.array([0.3, 0.2]))
    values.insert(D(1), np.array([0.32, 0.2]))
    factor = drag_random_walk(D(0), D(1), 0.01, 4.0, per_axis=True)
    assert _whitened_norm(factor, values) == pytest.approx(1.0)
    values.insert(G(0), np.array([0.0]))
    values.insert(G(1), np.array([0.3]))
    assert _whitened_norm(ground_random_walk(G(0), G(1), 0.1), values) == pytest.approx(3.0)
    with pytest.raises(ValueError):
        random_walk_sigma(0.01, 0.0)


def test_wind_prior_and_random_walk() -> None:
    values = gtsam.Values()
    values.insert(W(0), np.array([1.0, 0.0]))
    values.insert(W(1), np.array([1.0, 0.4]))
    assert _whitened_norm(wind_prior(W(0), [0.0, 0.0], 0.5), values) == pytest.approx(2.0)
    assert _whitened_norm(wind_random_walk(W(0), W(1), 0.1, 4.0), values) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="wind0_xy"):
        wind_prior(W(0), [0.0], 0.5)


def test_slam_alignment_prior_sigmas_are_in_slam_units() -> None:
    s0 = 2.5
    R0 = gtsam.Rot3.Ypr(0.7, 0.1, -0.2).matrix()
    t0 = np.array([1.0, -2.0, 0.3])
    sigmas = SlamAlignmentSigmas(rotation_rad=0.1, translation=0.5, log_scale=0.2)
    prior = slam_alignment_prior(S(0), s0, R0, t0, sigmas)
    # Offsets of the translation [SLAM units] and of log(scale), one at a time.
    for value, expected in [
        (make_slam_T_world(s0, R0, t0 + np.array([0.0, 0.05, 0.0])), 0.05 / 0.5),
        (make_slam_T_world(s0 * np.exp(0.02), R0, t0), 0.02 / 0.2),
    ]:
        values = gtsam.Values()
        values.insert(S(0), value)
        assert _whitened_norm(prior, values) == pytest.approx(expected, rel=1e-3)
    values = gtsam.Values()
    values.insert(S(0), slam_alignment_initial(s0, R0, t0))
    assert prior.error(values) == pytest.approx(0.0, abs=1e-18)
    with pytest.raises(ValueError, match="log_scale"):
        SlamAlignmentSigmas(0.1, 0.5, 0.0).as_tangent_sigmas(1.0)


def test_slam_alignment_random_walk_is_zero_for_equal_alignments() -> None:
    sim = make_slam_T_world(0.4, gtsam.Rot3.Yaw(1.0).matrix(), np.array([1.0, 2.0, 3.0]))
    values = gtsam.Values()
    values.insert(S(0), sim)
    values.insert(S(1), sim)
    factor = slam_alignment_random_walk(S(0), S(1), 0.4, SlamAlignmentSigmas(0.01, 0.01, 0.01))
    assert factor.error(values) == pytest.approx(0.0, abs=1e-18)


def test_drag_random_walk_tracks_a_change_of_drag() -> None:
    """Two drag segments linked by a random walk: each recovers its own k (payload change)."""
    rng = np.random.default_rng(13)
    k_true = [0.30, 0.36]
    sigma_mean = 0.01
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pin = gtsam.noiseModel.Isotropic.Sigma
    bias = gtsam.imuBias.ConstantBias()
    graph.add(gtsam.PriorFactorConstantBias(B(0), bias, pin(6, 1e-6)))
    values.insert(B(0), bias)
    for i in range(80):
        seg = i // 40
        pose = gtsam.Pose3(gtsam.Rot3.Yaw(0.1 * i), np.zeros(3))
        vel = np.array([2.0 * np.cos(0.2 * i), 2.0 * np.sin(0.3 * i), 0.0])
        u = pose.rotation().matrix().T @ vel
        z = -k_true[seg] * u[:2] + rng.normal(0.0, sigma_mean, 2)
        graph.add(make_accel_drag_factor(X(i), V(i), B(0), D(seg), z, pin(2, sigma_mean)))
        graph.add(gtsam.PriorFactorPose3(X(i), pose, pin(6, 1e-6)))
        graph.add(gtsam.PriorFactorVector(V(i), vel, pin(3, 1e-6)))
        values.insert(X(i), pose)
        values.insert(V(i), vel)
    graph.add(drag_prior(D(0), 0.5, 1.0))
    graph.add(drag_random_walk(D(0), D(1), 0.01, 4.0))
    values.insert(D(0), drag_initial(0.5))
    values.insert(D(1), drag_initial(0.5))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    assert result.atVector(D(0))[0] == pytest.approx(k_true[0], abs=0.01)
    assert result.atVector(D(1))[0] == pytest.approx(k_true[1], abs=0.01)
