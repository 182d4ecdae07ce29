"""Homography motion factors: geometry against projected ground points, Jacobians, robust noise,
and relative-pose recovery from a rendered image pair (simulator carpet + OpenCV tracking)."""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
import pytest
from fgnav.factors.homography_motion import (
    homography_decomposed_error,
    homography_error,
    image_corners,
    make_homography_decomposed_factor,
    make_homography_factor,
    predicted_homography,
    transfer_corners,
)

from fgnav.keys import G, X

from .numdiff import assert_jacobians_close, unit_noise

WIDTH, HEIGHT = 320, 240
FOCAL = 0.5 * WIDTH / np.tan(np.deg2rad(64.0) / 2.0)
K = np.array([[FOCAL, 0.0, (WIDTH - 1) / 2.0], [0.0, FOCAL, (HEIGHT - 1) / 2.0], [0.0, 0.0, 1.0]])
# Downward camera: cam z = body -z, cam x = body x, small lever arm.
BODY_T_CAM = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.05, -0.02, -0.04]))


def _pair(rng: np.random.Generator, ground: float):
    """Two body poses over the ground: tilts < 0.2 rad, heights 1.5-4 m above, < 0.5 m apart."""
    pose_i = gtsam.Pose3(
        gtsam.Rot3.Ypr(rng.uniform(-np.pi, np.pi), *rng.uniform(-0.2, 0.2, 2)),
        np.array([*rng.uniform(-3, 3, 2), ground + rng.uniform(1.5, 4.0)]),
    )
    step = gtsam.Pose3(gtsam.Rot3.Expmap(rng.uniform(-0.08, 0.08, 3)), rng.uniform(-0.3, 0.3, 3))
    return pose_i, pose_i.compose(step)


def _project(world_T_cam: gtsam.Pose3, P: np.ndarray) -> np.ndarray:
    X_cam = (P - world_T_cam.translation()) @ world_T_cam.rotation().matrix()
    q = X_cam @ K.T
    return q[:, :2] / q[:, 2:3]


@pytest.mark.parametrize("seed", range(3))
def test_predicted_homography_maps_projected_ground_points(seed: int) -> None:
    rng = np.random.default_rng(500 + seed)
    ground = rng.uniform(-1, 1)
    pose_i, pose_j = _pair(rng, ground)
    cam_i, cam_j = pose_i.compose(BODY_T_CAM), pose_j.compose(BODY_T_CAM)
    # Ground points under camera i.
    P = np.column_stack(
        [cam_i.translation()[:2] + rng.uniform(-1.0, 1.0, (20, 2)), np.full(20, ground)]
    )
    p_i, p_j = _project(cam_i, P), _project(cam_j, P)
    H = predicted_homography(pose_i, pose_j, ground, K, BODY_T_CAM)
    q = np.column_stack([p_i, np.ones(20)]) @ H.T
    np.testing.assert_allclose(q[:, :2] / q[:, 2:3], p_j, atol=1e-8)


def _measurement(pose_i, pose_j, ground):
    H = predicted_homography(pose_i, pose_j, ground, K, BODY_T_CAM)
    cam_i, cam_j = pose_i.compose(BODY_T_CAM), pose_j.compose(BODY_T_CAM)
    cam_j_T_cam_i = cam_j.between(cam_i)
    d = cam_i.translation()[2] - ground
    return H, cam_j_T_cam_i.rotation().matrix(), cam_j_T_cam_i.translation() / d


def test_zero_error_and_shapes() -> None:
    rng = np.random.default_rng(20)
    ground = 0.4
    pose_i, pose_j = _pair(rng, ground)
    H, R, u = _measurement(pose_i, pose_j, ground)
    corners = image_corners((WIDTH, HEIGHT))
    body_T_cam = BODY_T_CAM.matrix()
    e, J = homography_error(
        pose_i,
        pose_j,
        np.array([ground]),
        transfer_corners(7.0 * H, corners),
        K,
        body_T_cam,
        corners,
    )
    np.testing.assert_allclose(e, 0.0, atol=1e-9)
    assert [j.shape for j in J] == [(8, 6), (8, 6), (8, 1)]
    e, J = homography_decomposed_error(pose_i, pose_j, np.array([ground]), R, u, body_T_cam)
    np.testing.assert_allclose(e, 0.0, atol=1e-9)
    assert [j.shape for j in J] == [(6, 6), (6, 6), (6, 1)]


def _values(pose_i, pose_j, ground) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(X(0), pose_i)
    values.insert(X(1), pose_j)
    values.insert(G(0), np.array([ground]))
    return values


@pytest.mark.parametrize("seed", range(5))
def test_jacobians_match_central_differences(seed: int) -> None:
    rng = np.random.default_rng(600 + seed)
    ground = rng.uniform(-1, 1)
    pose_i, pose_j = _pair(rng, ground)
    # Measurement from a different state, so that the residual is not zero.
    other_i, other_j = _pair(rng, ground)
    H, R, u = _measurement(pose_i, pose_i.compose(other_i.between(other_j)), ground)
    values = _values(pose_i, pose_j, ground + rng.uniform(-0.3, 0.3))
    f8 = make_homography_factor(X(0), X(1), G(0), H, K, BODY_T_CAM, (WIDTH, HEIGHT), unit_noise(8))
    assert_jacobians_close(f8, values, [6, 6, 1])
    f6 = make_homography_decomposed_factor(X(0), X(1), G(0), R, u, BODY_T_CAM, unit_noise(6))
    assert_jacobians_close(f6, values, [6, 6, 1])


def test_robust_noise_evaluates_and_linearises() -> None:
    rng = np.random.default_rng(21)
    pose_i, pose_j = _pair(rng, 0.0)
    H, _, _ = _measurement(pose_i, pose_j, 0.0)
    H_wrong = H @ np.array([[1.0, 0.0, 30.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # 30 px off
    base = gtsam.noiseModel.Isotropic.Sigma(8, 0.5)
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(1.0), base)
    values = _values(pose_i, pose_j, 0.0)
    args = (X(0), X(1), G(0), H_wrong, K, BODY_T_CAM, (WIDTH, HEIGHT))
    f_robust = make_homography_factor(*args, robust)
    assert f_robust.error(values) < 0.01 * make_homography_factor(*args, base).error(values)
    A, b = f_robust.linearize(values).jacobian()
    assert A.shape == (8, 13) and np.all(np.isfinite(A)) and np.all(np.isfinite(b))


def test_bad_inputs_are_rejected() -> None:
    with pytest.raises(ValueError, match="H_meas"):
        make_homography_factor(
            X(0), X(1), G(0), np.eye(2), K, BODY_T_CAM, (320, 240), unit_noise(8)
        )
    with pytest.raises(ValueError, match="K"):
        make_homography_factor(
            X(0), X(1), G(0), np.eye(3), -K, BODY_T_CAM, (320, 240), unit_noise(8)
        )
    with pytest.raises(ValueError, match="dimension"):
        make_homography_factor(
            X(0), X(1), G(0), np.eye(3), K, BODY_T_CAM, (320, 240), unit_noise(6)
        )


def _measured_homography_from_rendered_pair(rng, pose_i, pose_j, ground) -> np.ndarray:
    render = pytest.importorskip("fgnav.datasets.simulate.render")
    cam_i, cam_j = pose_i.compose(BODY_T_CAM).matrix(), pose_j.compose(BODY_T_CAM).matrix()
    xy = np.array([cam_i[:2, 3], cam_j[:2, 3]])
    carpet = render.Carpet.make(xy.min(axis=0) - 3.0, xy.max(axis=0) + 3.0, ground, 0.005, rng)
    img_i = render.to_uint8(carpet.render(cam_i, K, WIDTH, HEIGHT))
    img_j = render.to_uint8(carpet.render(cam_j, K, WIDTH, HEIGHT))
    pts_i = cv2.goodFeaturesToTrack(img_i, 300, 0.01, 8)
    pts_j, status, _ = cv2.calcOpticalFlowPyrLK(img_i, img_j, pts_i, None, winSize=(21, 21))
    ok = status.ravel() == 1
    assert ok.sum() > 100
    H, _ = cv2.findHomography(pts_i[ok], pts_j[ok], cv2.RANSAC, 1.0)
    return H


@pytest.fixture(scope="module")
def rendered_pair():
    rng = np.random.default_rng(31)
    ground = -0.2
    pose_i = gtsam.Pose3(gtsam.Rot3.Ypr(0.6, 0.05, -0.04), np.array([1.0, 2.0, ground + 2.5]))
    step = gtsam.Pose3(gtsam.Rot3.Ypr(0.05, -0.03, 0.02), np.array([0.25, -0.1, 0.05]))
    pose_j = pose_i.compose(step)
    H = _measured_homography_from_rendered_pair(rng, pose_i, pose_j, ground)
    return pose_i, pose_j, ground, H


def _solve_pose_j(factor, pose_i, pose_j_start, ground) -> gtsam.Pose3:
    graph = gtsam.NonlinearFactorGraph()
    graph.add(factor)
    graph.add(gtsam.PriorFactorPose3(X(0), pose_i, gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    graph.add(
        gtsam.PriorFactorVector(G(0), np.array([ground]), gtsam.noiseModel.Isotropic.Sigma(1, 1e-6))
    )
    values = _values(pose_i, pose_j_start, ground)
    return gtsam.LevenbergMarquardtOptimizer(graph, values).optimize().atPose3(X(1))


def _perturbed(pose: gtsam.Pose3) -> gtsam.Pose3:
    return pose.retract(np.array([0.03, -0.02, 0.04, 0.15, -0.1, 0.08]))


def test_relative_pose_recovered_from_rendered_image_pair(rendered_pair) -> None:
    pose_i, pose_j, ground, H = rendered_pair
    noise = gtsam.noiseModel.Isotropic.Sigma(8, 0.5)
    factor = make_homography_factor(X(0), X(1), G(0), H, K, BODY_T_CAM, (WIDTH, HEIGHT), noise)
    est = _solve_pose_j(factor, pose_i, _perturbed(pose_j), ground)
    err = pose_j.localCoordinates(est)
    # Measured: ~0.1 px corner error -> ~2 mm and ~0.8 mrad at 2.5 m (f ~ 256 px); 3x margin.
    assert np.linalg.norm(err[3:]) < 0.006, err
    assert np.linalg.norm(err[:3]) < 0.0025, err


def test_relative_pose_recovered_from_decomposed_rendered_pair(rendered_pair) -> None:
    pose_i, pose_j, ground, H = rendered_pair
    _, Rs, ts, normals = cv2.decomposeHomographyMat(H, K)
    # Pick the solution whose normal is closest to world-down seen from camera i.
    n_pred = -(pose_i.compose(BODY_T_CAM).rotation().matrix().T @ np.array([0.0, 0.0, 1.0]))
    best = int(np.argmax([float(n.ravel() @ n_pred) for n in normals]))
    noise = gtsam.noiseModel.Diagonal.Sigmas([0.002] * 3 + [0.002] * 3)
    factor = make_homography_decomposed_factor(
        X(0), X(1), G(0), Rs[best], ts[best].ravel(), BODY_T_CAM, noise
    )
    est = _solve_pose_j(factor, pose_i, _perturbed(pose_j), ground)
    err = pose_j.localCoordinates(est)
    assert np.linalg.norm(err[3:]) < 0.02, err
    assert np.linalg.norm(err[:3]) < np.deg2rad(0.5), err
