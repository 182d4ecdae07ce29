"""SLAM scale factors: Similarity3 convention, zero error, Jacobians, robust noise, recovery."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from fgnav.factors.slam_scale import (
    make_slam_axis_offset_factor,
    make_slam_axis_scale_factor,
    make_slam_position_factor,
    make_slam_relative_factor,
    make_slam_rotation_factor,
    make_slam_T_world,
    slam_alignment_parts,
    slam_axis_offset_error,
    slam_axis_scale_error,
    slam_position_error,
    slam_relative_error,
    slam_rotation_error,
)

from fgnav.keys import S, V, X

from .numdiff import assert_jacobians_close, random_pose, unit_noise


def _random_sim(rng: np.random.Generator) -> gtsam.Similarity3:
    R = gtsam.Rot3.Expmap(rng.uniform(-1.0, 1.0, 3)).matrix()
    return make_slam_T_world(rng.uniform(0.2, 3.0), R, rng.uniform(-2.0, 2.0, 3))


def _cam_truth(pose: gtsam.Pose3, sim: gtsam.Similarity3, body_T_cam: gtsam.Pose3):
    world_T_cam = pose.compose(body_T_cam)
    slam_t_cam = sim.transformFrom(world_T_cam.translation())
    slam_R_cam = sim.rotation().matrix() @ world_T_cam.rotation().matrix()
    return slam_t_cam, slam_R_cam


def test_similarity3_convention_round_trip() -> None:
    R = gtsam.Rot3.Ypr(0.4, -0.1, 0.2).matrix()
    sim = make_slam_T_world(2.5, R, np.array([1.0, -2.0, 0.5]))
    p = np.array([0.3, 0.7, -1.1])
    np.testing.assert_allclose(sim.transformFrom(p), 2.5 * R @ p + [1.0, -2.0, 0.5], atol=1e-12)
    s, R2, t2 = slam_alignment_parts(sim)
    assert s == pytest.approx(2.5)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, [1.0, -2.0, 0.5], atol=1e-12)
    with pytest.raises(ValueError, match="scale"):
        make_slam_T_world(0.0, R, np.zeros(3))


def test_zero_error_and_shapes_at_consistent_state() -> None:
    rng = np.random.default_rng(3)
    pose_i, pose_j, sim = random_pose(rng), random_pose(rng), _random_sim(rng)
    body_T_cam = random_pose(rng, 0.2)
    z_i, R_i = _cam_truth(pose_i, sim, body_T_cam)
    z_j, _ = _cam_truth(pose_j, sim, body_T_cam)
    e, J = slam_position_error(pose_i, sim, z_i, body_T_cam)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    assert [j.shape for j in J] == [(3, 6), (3, 7)]
    e, J = slam_relative_error(pose_i, pose_j, sim, z_i, z_j, body_T_cam)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    assert [j.shape for j in J] == [(3, 6), (3, 6), (3, 7)]
    e, J = slam_rotation_error(pose_i, sim, R_i, body_T_cam)
    np.testing.assert_allclose(e, 0.0, atol=1e-9)
    assert [j.shape for j in J] == [(3, 6), (3, 7)]
    k = np.array([0.3, 0.2, 1.5])
    lever = body_T_cam.translation()
    e, J = slam_axis_scale_error(pose_i, k, k * (pose_i.transformFrom(lever)), lever)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    assert [j.shape for j in J] == [(3, 6), (3, 3)]
    a = np.r_[k, 0.4, -1.2, 2.0]
    e, J = slam_axis_offset_error(pose_i, a, k * (pose_i.transformFrom(lever)) + a[3:], lever)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    assert [j.shape for j in J] == [(3, 6), (3, 6)]


@pytest.mark.parametrize("seed", range(5))
def test_jacobians_match_central_differences(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    pose_i, pose_j, sim = random_pose(rng), random_pose(rng), _random_sim(rng)
    body_T_cam = random_pose(rng, 0.3)
    z_i, z_j = rng.normal(0, 2, 3), rng.normal(0, 2, 3)
    values = gtsam.Values()
    values.insert(X(0), pose_i)
    values.insert(X(1), pose_j)
    values.insert(S(0), sim)
    values.insert(S(1), rng.uniform(0.2, 2.0, 3))
    values.insert(S(2), np.r_[rng.uniform(0.2, 2.0, 3), rng.normal(0.0, 2.0, 3)])
    unit = unit_noise(3)
    assert_jacobians_close(
        make_slam_position_factor(X(0), S(0), z_i, body_T_cam, unit), values, [6, 7]
    )
    assert_jacobians_close(
        make_slam_relative_factor(X(0), X(1), S(0), z_i, z_j, body_T_cam, unit), values, [6, 6, 7]
    )
    R_meas = gtsam.Rot3.Expmap(rng.uniform(-1, 1, 3)).matrix()
    rot = make_slam_rotation_factor(X(0), S(0), R_meas, body_T_cam, unit)
    assert_jacobians_close(rot, values, [6, 7])
    # The error-only evaluation (no Jacobians computed) gives the same error.
    e, J = slam_rotation_error(pose_i, sim, R_meas, body_T_cam, with_jacobians=False)
    assert J is None
    np.testing.assert_array_equal(e, slam_rotation_error(pose_i, sim, R_meas, body_T_cam)[0])
    np.testing.assert_array_equal(rot.unwhitenedError(values), e)
    assert_jacobians_close(
        make_slam_axis_scale_factor(X(1), S(1), z_j, unit, body_t_cam=body_T_cam.translation()),
        values,
        [6, 3],
    )
    assert_jacobians_close(
        make_slam_axis_offset_factor(X(1), S(2), z_j, unit, body_t_cam=body_T_cam.translation()),
        values,
        [6, 6],
    )


def test_robust_noise_evaluates_and_linearises() -> None:
    rng = np.random.default_rng(11)
    pose, sim = random_pose(rng), _random_sim(rng)
    z, _ = _cam_truth(pose, sim, gtsam.Pose3())
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(S(0), sim)
    base = gtsam.noiseModel.Isotropic.Sigma(3, 0.05)
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(0.1), base)
    outlier = z + np.array([3.0, 0.0, 0.0])
    f_robust = make_slam_position_factor(X(0), S(0), outlier, np.eye(4), robust)
    f_gauss = make_slam_position_factor(X(0), S(0), outlier, np.eye(4), base)
    assert f_robust.error(values) < 0.01 * f_gauss.error(values)
    A, b = f_robust.linearize(values).jacobian()
    assert A.shape == (3, 13) and np.all(np.isfinite(A)) and np.all(np.isfinite(b))


def test_bad_inputs_are_rejected() -> None:
    with pytest.raises(ValueError, match="slam_t_cam_meas"):
        make_slam_position_factor(X(0), S(0), np.zeros(2), np.eye(4), unit_noise(3))
    with pytest.raises(ValueError, match="body_T_cam"):
        make_slam_position_factor(X(0), S(0), np.zeros(3), 2.0 * np.eye(4), unit_noise(3))
    with pytest.raises(ValueError, match="dimension"):
        make_slam_relative_factor(
            X(0), X(1), S(0), np.zeros(3), np.ones(3), np.eye(4), unit_noise(2)
        )


def _trajectory(n: int) -> list[gtsam.Pose3]:
    t = np.linspace(0.0, 12.0, n)
    return [
        gtsam.Pose3(
            gtsam.Rot3.Ypr(0.5 * ti, 0.05, -0.03),
            np.array([3.0 * np.cos(0.5 * ti), 2.0 * np.sin(0.5 * ti), 1.5 + 0.3 * np.sin(ti)]),
        )
        for ti in t
    ]


def _pin_poses(graph, values, poses) -> None:
    for i, pose in enumerate(poses):
        graph.add(gtsam.PriorFactorPose3(X(i), pose, gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        values.insert(X(i), pose)


def test_alignment_recovered_from_absolute_positions() -> None:
    rng = np.random.default_rng(5)
    poses = _trajectory(40)
    body_T_cam = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.1, 0.0, -0.05]))
    truth = make_slam_T_world(
        0.37, gtsam.Rot3.Ypr(1.2, 0.02, -0.01).matrix(), np.array([2, -1, 0.5])
    )
    sigma = 0.01
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    _pin_poses(graph, values, poses)
    noise = gtsam.noiseModel.Isotropic.Sigma(3, sigma)
    for i, pose in enumerate(poses):
        z, _ = _cam_truth(pose, truth, body_T_cam)
        graph.add(
            make_slam_position_factor(X(i), S(0), z + rng.normal(0, sigma, 3), body_T_cam, noise)
        )
    values.insert(S(0), make_slam_T_world(1.0, gtsam.Rot3.Yaw(0.6).matrix(), np.zeros(3)))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    s, R, t = slam_alignment_parts(result.atSimilarity3(S(0)))
    s_true, R_true, t_true = slam_alignment_parts(truth)
    assert abs(s / s_true - 1.0) < 0.01
    assert np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(R_true.T @ R))) < 0.01
    np.testing.assert_allclose(t, t_true, atol=0.02)


def test_scale_recovered_from_relative_displacements_despite_origin_drift() -> None:
    rng = np.random.default_rng(6)
    poses = _trajectory(40)
    truth = make_slam_T_world(2.2, gtsam.Rot3.Ypr(-0.8, 0.0, 0.03).matrix(), np.zeros(3))
    drift_per_frame = np.array([0.05, -0.03, 0.02])  # SLAM origin drift [SLAM units per frame]
    sigma = 0.01
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    _pin_poses(graph, values, poses)
    z = [
        truth.transformFrom(p.translation()) + i * drift_per_frame + rng.normal(0, sigma, 3)
        for i, p in enumerate(poses)
    ]
    noise = gtsam.noiseModel.Isotropic.Sigma(3, sigma * np.sqrt(2))
    for i in range(len(poses) - 1):
        graph.add(make_slam_relative_factor(X(i), X(i + 1), S(0), z[i], z[i + 1], np.eye(4), noise))
    # The relative factor says nothing about the SLAM origin: a weak prior fixes it.
    graph.add(
        gtsam.PriorFactorSimilarity3(
            S(0),
            gtsam.Similarity3(),
            gtsam.noiseModel.Diagonal.Sigmas([1e3] * 3 + [10] * 3 + [1e3]),
        )
    )
    values.insert(S(0), gtsam.Similarity3())
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    s, R, _ = slam_alignment_parts(result.atSimilarity3(S(0)))
    # Drift adds a constant displacement bias of |drift| / |mean displacement| ~ 0.06 / 1.0 of
    # the scale at worst; the absolute factor would see the accumulated drift of 2 units instead.
    assert abs(s / 2.2 - 1.0) < 0.08
    assert np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(truth.rotation().matrix().T @ R))) < 0.1


def test_per_axis_scale_recovered() -> None:
    rng = np.random.default_rng(8)
    poses = _trajectory(30)
    k_true = np.array([0.3, 0.2, 0.5])
    sigma = 0.005
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    _pin_poses(graph, values, poses)
    noise = gtsam.noiseModel.Isotropic.Sigma(3, sigma)
    for i, pose in enumerate(poses):
        z = k_true * pose.translation() + rng.normal(0, sigma, 3)
        graph.add(make_slam_axis_scale_factor(X(i), S(0), z, noise))
    values.insert(S(0), np.ones(3))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    np.testing.assert_allclose(result.atVector(S(0)), k_true, atol=2e-3)


def test_rounded_calibration_rotation_is_accepted_and_orthonormalised() -> None:
    from fgnav.factors._jacobians import as_pose_matrix

    m = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, 0.2, 0.1), np.array([0.1, 0.0, 0.0])).matrix().round(4)
    fixed = as_pose_matrix(m, "body_T_cam")
    np.testing.assert_allclose(fixed[:3, :3].T @ fixed[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(fixed, m, atol=1e-4)


def _offset_truth(rng: np.random.Generator):
    """A body moving at constant specific force and angular rate: the exact pose at ``dt``."""
    pose, sim = random_pose(rng), _random_sim(rng)
    v, f, w = rng.normal(0, 1.5, 3), rng.normal(0, 2.0, 3), rng.normal(0, 1.0, 3)
    return pose, v, sim, f, w


@pytest.mark.parametrize("dt", [-0.024, 0.0, 0.031])
def test_offset_factor_zero_at_consistent_state_and_matches_plain_at_dt0(dt: float) -> None:
    from fgnav.factors.slam_scale import make_slam_position_offset_factor

    rng = np.random.default_rng(7)
    pose, v, sim, f, w = _offset_truth(rng)
    g = 9.81
    body_T_cam = random_pose(rng, 0.3)
    # The model's own prediction of the camera at t_k + dt (constant f and omega).
    R = pose.rotation().matrix()
    E = gtsam.Rot3.Expmap(w * dt).matrix()
    p = (
        pose.translation()
        + v * dt
        + 0.5 * (R @ f + np.array([0, 0, -g])) * dt**2
        + R @ E @ body_T_cam.translation()
    )
    z = sim.transformFrom(p)
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(V(0), v)
    values.insert(S(0), sim)
    fac = make_slam_position_offset_factor(
        X(0), V(0), S(0), z, body_T_cam, dt, f, w, g, unit_noise(3)
    )
    np.testing.assert_allclose(fac.unwhitenedError(values), 0.0, atol=1e-10)
    if dt == 0.0:
        plain = make_slam_position_factor(X(0), S(0), z + 0.1, body_T_cam, unit_noise(3))
        off = make_slam_position_offset_factor(
            X(0), V(0), S(0), z + 0.1, body_T_cam, 0.0, f, w, g, unit_noise(3)
        )
        np.testing.assert_allclose(off.unwhitenedError(values), plain.unwhitenedError(values))


@pytest.mark.parametrize("seed", range(4))
def test_offset_factor_jacobians_match_central_differences(seed: int) -> None:
    from fgnav.factors.slam_scale import make_slam_position_offset_factor

    rng = np.random.default_rng(300 + seed)
    pose, v, sim, f, w = _offset_truth(rng)
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(V(0), v)
    values.insert(S(0), sim)
    fac = make_slam_position_offset_factor(
        X(0),
        V(0),
        S(0),
        rng.normal(0, 2, 3),
        random_pose(rng, 0.3),
        rng.uniform(-0.05, 0.05),
        f,
        w,
        9.81,
        unit_noise(3),
    )
    assert_jacobians_close(fac, values, [6, 3, 7])


def _axis_offset_case(rng: np.random.Generator, dt: float):
    """Per-axis alignment ``[k, o]``, a moving body and the camera position the model predicts
    at ``t_k + dt`` (constant specific force and angular rate)."""
    pose, v, _, f, w = _offset_truth(rng)
    a = np.r_[rng.uniform(0.2, 3.0, 3), rng.normal(0, 2.0, 3)]
    c = rng.normal(0, 0.2, 3)
    R = pose.rotation().matrix()
    E = gtsam.Rot3.Expmap(w * dt).matrix()
    p = pose.translation() + v * dt + 0.5 * (R @ f + np.array([0, 0, -9.81])) * dt**2 + R @ E @ c
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(V(0), v)
    values.insert(S(0), a)
    return values, a[:3] * p + a[3:], c, f, w


@pytest.mark.parametrize("dt", [-0.024, 0.0, 0.031])
def test_axis_offset_factor_zero_at_consistent_state_and_matches_plain_at_dt0(dt: float) -> None:
    from fgnav.factors.slam_scale import make_slam_axis_position_offset_factor

    values, z, c, f, w = _axis_offset_case(np.random.default_rng(11), dt)
    fac = make_slam_axis_position_offset_factor(
        X(0), V(0), S(0), z, c, dt, f, w, 9.81, unit_noise(3)
    )
    np.testing.assert_allclose(fac.unwhitenedError(values), 0.0, atol=1e-10)
    if dt == 0.0:
        plain = make_slam_axis_offset_factor(X(0), S(0), z + 0.1, unit_noise(3), c)
        off = make_slam_axis_position_offset_factor(
            X(0), V(0), S(0), z + 0.1, c, 0.0, f, w, 9.81, unit_noise(3)
        )
        np.testing.assert_allclose(off.unwhitenedError(values), plain.unwhitenedError(values))


@pytest.mark.parametrize("seed", range(4))
def test_axis_offset_factor_jacobians_match_central_differences(seed: int) -> None:
    from fgnav.factors.slam_scale import make_slam_axis_position_offset_factor

    rng = np.random.default_rng(400 + seed)
    dt = rng.uniform(-0.05, 0.05)
    values, _, c, f, w = _axis_offset_case(rng, dt)
    fac = make_slam_axis_position_offset_factor(
        X(0), V(0), S(0), rng.normal(0, 2, 3), c, dt, f, w, 9.81, unit_noise(3)
    )
    assert_jacobians_close(fac, values, [6, 3, 6])
