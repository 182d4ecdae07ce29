"""Rotor-drag accelerometer factor: zero error, Jacobians, robust noise, drag recovery."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from fgnav.factors.accel_drag import accel_drag_error, make_accel_drag_factor, mean_accel_noise

from fgnav.keys import B, D, V, W, X

from .numdiff import assert_jacobians_close, random_pose, unit_noise


def _random_state(rng: np.random.Generator, n_k: int):
    pose = random_pose(rng)
    vel = rng.uniform(-3.0, 3.0, 3)
    bias = gtsam.imuBias.ConstantBias(rng.normal(0, 0.2, 3), rng.normal(0, 0.01, 3))
    k = rng.uniform(0.1, 0.6, n_k)
    return pose, vel, bias, k


def _values(pose, vel, bias, k) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(V(0), vel)
    values.insert(B(0), bias)
    values.insert(D(0), k)
    return values


def _model(pose, vel, bias, k) -> np.ndarray:
    u = pose.rotation().matrix().T @ vel
    return -np.broadcast_to(k, (2,)) * u[:2] + bias.accelerometer()[:2]


@pytest.mark.parametrize("n_k", [1, 2])
def test_zero_error_and_shapes(n_k: int) -> None:
    rng = np.random.default_rng(1)
    pose, vel, bias, k = _random_state(rng, n_k)
    e, J = accel_drag_error(pose, vel, bias, k, _model(pose, vel, bias, k))
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    assert [j.shape for j in J] == [(2, 6), (2, 3), (2, 6), (2, n_k)]


def test_error_value_against_hand_computed_case() -> None:
    # Level body yawed +90 deg flying along world +x: body velocity is (0, -2, 0).
    pose = gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), np.zeros(3))
    bias = gtsam.imuBias.ConstantBias(np.array([0.1, -0.2, 0.0]), np.zeros(3))
    e, _ = accel_drag_error(pose, np.array([2.0, 0.0, 0.0]), bias, np.array([0.3]), np.zeros(2))
    np.testing.assert_allclose(e, [0.1, -0.3 * -2.0 - 0.2], atol=1e-12)


@pytest.mark.parametrize("n_k", [1, 2])
@pytest.mark.parametrize("seed", range(5))
def test_jacobians_match_central_differences(seed: int, n_k: int) -> None:
    rng = np.random.default_rng(100 + seed)
    pose, vel, bias, k = _random_state(rng, n_k)
    z = rng.normal(0.0, 1.0, 2)
    factor = make_accel_drag_factor(X(0), V(0), B(0), D(0), z, unit_noise(2))
    assert_jacobians_close(factor, _values(pose, vel, bias, k), [6, 3, 6, n_k])


def test_robust_noise_evaluates_and_linearises() -> None:
    rng = np.random.default_rng(7)
    pose, vel, bias, k = _random_state(rng, 2)
    z = _model(pose, vel, bias, k) + np.array([5.0, 0.0])  # an outlier
    base = gtsam.noiseModel.Isotropic.Sigma(2, 0.1)
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345), base)
    values = _values(pose, vel, bias, k)
    f_gauss = make_accel_drag_factor(X(0), V(0), B(0), D(0), z, base)
    f_robust = make_accel_drag_factor(X(0), V(0), B(0), D(0), z, robust)
    assert f_robust.error(values) < 0.5 * f_gauss.error(values)
    A, b = f_robust.linearize(values).jacobian()
    assert A.shape == (2, 17) and np.all(np.isfinite(A)) and np.all(np.isfinite(b))


def test_bad_measurement_and_noise_are_rejected() -> None:
    with pytest.raises(ValueError, match="mean_body_accel_xy"):
        make_accel_drag_factor(X(0), V(0), B(0), D(0), np.zeros(3), unit_noise(2))
    with pytest.raises(ValueError, match="dimension 3"):
        make_accel_drag_factor(X(0), V(0), B(0), D(0), np.zeros(2), unit_noise(3))


def test_mean_accel_noise_sigma() -> None:
    model = mean_accel_noise(0.2, 100, 0.03)
    np.testing.assert_allclose(model.sigmas(), [np.hypot(0.02, 0.03)] * 2, rtol=1e-12)
    with pytest.raises(ValueError):
        mean_accel_noise(0.2, 0, 0.03)


@pytest.mark.parametrize("k_true", [np.array([0.35]), np.array([0.3, 0.2])])
def test_drag_recovered_from_hover_and_move_segment(k_true: np.ndarray) -> None:
    """Poses, velocities and bias pinned by priors; k starts 60 % off and is recovered."""
    rng = np.random.default_rng(42)
    rate_hz, keyframe_hz, sigma_sample = 200.0, 10.0, 0.05
    n_per_kf = int(rate_hz / keyframe_hz)
    noise = mean_accel_noise(sigma_sample, n_per_kf, 0.0)
    bias = gtsam.imuBias.ConstantBias(np.array([0.05, -0.03, 0.0]), np.zeros(3))
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    tight = gtsam.noiseModel.Isotropic.Sigma
    t = np.arange(60) / keyframe_hz
    for i, ti in enumerate(t):
        # Hover for 2 s, then fly a figure with changing heading and a little tilt.
        moving = ti > 2.0
        vel = np.array([2.0 * np.sin(0.8 * ti), 1.5 * np.cos(0.5 * ti), 0.1]) * moving
        pose = gtsam.Pose3(gtsam.Rot3.Ypr(0.7 * ti, 0.05 * np.sin(ti), -0.04), np.array([ti, 0, 2]))
        samples = _model(pose, vel, bias, k_true) + rng.normal(0.0, sigma_sample, (n_per_kf, 2))
        graph.add(make_accel_drag_factor(X(i), V(i), B(0), D(0), samples.mean(axis=0), noise))
        graph.add(gtsam.PriorFactorPose3(X(i), pose, tight(6, 1e-6)))
        graph.add(gtsam.PriorFactorVector(V(i), vel, tight(3, 1e-6)))
        values.insert(X(i), pose)
        values.insert(V(i), vel)
    graph.add(gtsam.PriorFactorConstantBias(B(0), bias, tight(6, 1e-6)))
    values.insert(B(0), gtsam.imuBias.ConstantBias())
    values.insert(D(0), 0.4 * k_true)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    k_est = result.atVector(D(0))
    # Expected accuracy: sigma_k ~ sigma_mean / (|u| sqrt(N)) ~ 0.011 / (1.5 * 7) ~ 1e-3.
    np.testing.assert_allclose(k_est, k_true, atol=5e-3)
    sigma_k = np.sqrt(np.diag(gtsam.Marginals(graph, result).marginalCovariance(D(0))))
    assert np.all(sigma_k < 5e-3)


@pytest.mark.parametrize("seed", range(5))
def test_wind_jacobians_match_central_differences(seed: int) -> None:
    rng = np.random.default_rng(150 + seed)
    pose, vel, bias, k = _random_state(rng, 2)
    values = _values(pose, vel, bias, k)
    values.insert(W(0), rng.normal(0.0, 3.0, 2))
    factor = make_accel_drag_factor(
        X(0), V(0), B(0), D(0), rng.normal(0, 1, 2), unit_noise(2), W(0)
    )
    assert_jacobians_close(factor, values, [6, 3, 6, 2, 2])


def test_wind_is_subtracted_from_the_ground_velocity() -> None:
    rng = np.random.default_rng(151)
    pose, vel, bias, k = _random_state(rng, 1)
    wind = np.array([1.5, -0.5])
    air = vel - np.array([*wind, 0.0])
    e, J = accel_drag_error(pose, vel, bias, k, _model(pose, air, bias, k), wind)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    assert len(J) == 5 and J[4].shape == (2, 2)


def test_drag_and_wind_recovered_while_turning() -> None:
    """Constant wind, changing heading and speed: k and the wind separate."""
    rng = np.random.default_rng(43)
    k_true, wind_true, sigma = np.array([0.3]), np.array([2.0, -1.0]), 0.01
    bias = gtsam.imuBias.ConstantBias()
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pin = gtsam.noiseModel.Isotropic.Sigma
    for i in range(60):
        t = 0.1 * i
        pose = gtsam.Pose3(gtsam.Rot3.Ypr(0.5 * t, 0.03, -0.02), np.zeros(3))
        vel = np.array([2.0 * np.cos(0.7 * t), 1.5 * np.sin(0.4 * t), 0.0])
        air = vel - np.array([*wind_true, 0.0])
        z = _model(pose, air, bias, k_true) + rng.normal(0.0, sigma, 2)
        graph.add(make_accel_drag_factor(X(i), V(i), B(0), D(0), z, pin(2, sigma), W(0)))
        graph.add(gtsam.PriorFactorPose3(X(i), pose, pin(6, 1e-6)))
        graph.add(gtsam.PriorFactorVector(V(i), vel, pin(3, 1e-6)))
        values.insert(X(i), pose)
        values.insert(V(i), vel)
    graph.add(gtsam.PriorFactorConstantBias(B(0), bias, pin(6, 1e-6)))
    values.insert(B(0), bias)
    values.insert(D(0), np.array([0.5]))
    values.insert(W(0), np.zeros(2))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    assert result.atVector(D(0))[0] == pytest.approx(k_true[0], abs=3e-3)
    np.testing.assert_allclose(result.atVector(W(0)), wind_true, atol=0.03)
