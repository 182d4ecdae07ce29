"""Yaw factor: values across +-pi, Jacobians (both forms), robust noise, recovery near pi."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from fgnav.factors.yaw import make_yaw_factor, wrap_angle, yaw_error

from fgnav.keys import X

from .numdiff import assert_jacobians_close, unit_noise


def _pose(yaw: float, pitch: float = 0.1, roll: float = -0.2) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Ypr(yaw, pitch, roll), np.array([1.0, 2.0, 3.0]))


@pytest.mark.parametrize("yaw", [-3.1, -1.0, 0.0, 2.0, np.pi])
def test_zero_error_and_shapes(yaw: float) -> None:
    e, J = yaw_error(_pose(yaw), yaw)
    assert e.shape == (1,) and abs(e[0]) < 1e-12 and J[0].shape == (1, 6)
    e, J = yaw_error(_pose(yaw), yaw + 2 * np.pi, cos_sin=True)
    assert e.shape == (2,) and np.max(np.abs(e)) < 1e-12 and J[0].shape == (2, 6)


def test_wrapped_across_pi() -> None:
    e, _ = yaw_error(_pose(np.deg2rad(179.0)), np.deg2rad(-179.0))
    assert e[0] == pytest.approx(np.deg2rad(-2.0), abs=1e-12)
    e, _ = yaw_error(_pose(np.deg2rad(-179.0)), np.deg2rad(179.0))
    assert e[0] == pytest.approx(np.deg2rad(2.0), abs=1e-12)
    e, _ = yaw_error(_pose(np.deg2rad(10.0)), np.deg2rad(10.0) + 4 * np.pi)
    assert e[0] == pytest.approx(0.0, abs=1e-12)
    e, _ = yaw_error(_pose(np.deg2rad(179.0)), np.deg2rad(-179.0), cos_sin=True)
    assert np.linalg.norm(e) == pytest.approx(2 * np.sin(np.deg2rad(1.0)), abs=1e-12)
    assert wrap_angle(-np.pi) == np.pi


def test_jacobian_agrees_with_gtsam_rot3_yaw() -> None:
    R = gtsam.Rot3.Ypr(2.5, 0.3, -0.4)
    H = np.zeros((1, 3), order="F")
    R.yaw(H)
    _, J = yaw_error(gtsam.Pose3(R, np.zeros(3)), 0.0)
    np.testing.assert_allclose(J[0][:, :3], H, atol=1e-12)


@pytest.mark.parametrize("cos_sin", [False, True])
@pytest.mark.parametrize("seed", range(5))
def test_jacobians_match_central_differences(seed: int, cos_sin: bool) -> None:
    rng = np.random.default_rng(400 + seed)
    pose = gtsam.Pose3(
        gtsam.Rot3.Ypr(rng.uniform(-np.pi, np.pi), *rng.uniform(-0.6, 0.6, 2)), rng.normal(0, 3, 3)
    )
    values = gtsam.Values()
    values.insert(X(0), pose)
    factor = make_yaw_factor(
        X(0), rng.uniform(-np.pi, np.pi), unit_noise(2 if cos_sin else 1), cos_sin
    )
    assert_jacobians_close(factor, values, [6])


@pytest.mark.parametrize("cos_sin", [False, True])
def test_robust_noise_evaluates_and_linearises(cos_sin: bool) -> None:
    dim = 2 if cos_sin else 1
    base = gtsam.noiseModel.Isotropic.Sigma(dim, 0.02)
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345), base)
    values = gtsam.Values()
    values.insert(X(0), _pose(0.3))
    f_robust = make_yaw_factor(X(0), 1.3, robust, cos_sin)
    f_gauss = make_yaw_factor(X(0), 1.3, base, cos_sin)
    assert f_robust.error(values) < 0.1 * f_gauss.error(values)
    A, b = f_robust.linearize(values).jacobian()
    assert A.shape == (dim, 6) and np.all(np.isfinite(A)) and np.all(np.isfinite(b))


@pytest.mark.parametrize("cos_sin", [False, True])
def test_yaw_recovered_across_pi(cos_sin: bool) -> None:
    """Truth at +179.5 deg, start at -179.5 deg: the optimiser takes the 1 deg way round."""
    rng = np.random.default_rng(12)
    yaw_true, sigma = np.deg2rad(179.5), np.deg2rad(0.5)
    truth = _pose(yaw_true)
    graph = gtsam.NonlinearFactorGraph()
    # Prior: translation and roll/pitch known, yaw unknown (large sigma about the body z axis
    # is only approximately world z at this small tilt; both factors agree at the truth).
    start = _pose(np.deg2rad(-179.5))
    graph.add(
        gtsam.PriorFactorPose3(
            X(0), truth, gtsam.noiseModel.Diagonal.Sigmas([1e-4, 1e-4, 10, 1e-4, 1e-4, 1e-4])
        )
    )
    dim = 2 if cos_sin else 1
    noise = gtsam.noiseModel.Isotropic.Sigma(dim, sigma)
    measured = yaw_true + rng.normal(0.0, sigma, 20)
    for z in measured:
        graph.add(make_yaw_factor(X(0), wrap_angle(z), noise, cos_sin))
    values = gtsam.Values()
    values.insert(X(0), start)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    yaw_est = result.atPose3(X(0)).rotation().yaw()
    assert abs(wrap_angle(yaw_est - yaw_true)) < np.deg2rad(0.5)
