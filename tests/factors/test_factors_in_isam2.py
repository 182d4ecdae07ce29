"""Every custom factor inside ISAM2 (where a wrong Jacobian row count would crash the process) and
with robust noise: a short chain started off the truth converges back to it."""

from __future__ import annotations

import gtsam
import numpy as np
from fgnav.factors.accel_drag import make_accel_drag_factor
from fgnav.factors.homography_motion import (
    make_homography_decomposed_factor,
    make_homography_factor,
    predicted_homography,
)
from fgnav.factors.slam_scale import (
    make_slam_axis_scale_factor,
    make_slam_position_factor,
    make_slam_relative_factor,
    make_slam_rotation_factor,
    make_slam_T_world,
)
from fgnav.factors.slow import drag_prior, ground_prior
from fgnav.factors.tilted_range import make_range_factor, tilted_range_error
from fgnav.factors.yaw import make_yaw_factor

from fgnav.keys import B, D, G, S, V, X

K = np.array([[256.0, 0.0, 159.5], [0.0, 256.0, 119.5], [0.0, 0.0, 1.0]])
SIZE = (320, 240)
BODY_T_CAM = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.05, 0.0, -0.03]))
BODY_T_RANGE = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.0, 0.05, -0.02]))
SIM = make_slam_T_world(0.4, gtsam.Rot3.Yaw(0.7).matrix(), np.array([1.0, -2.0, 0.5]))
AXIS = np.array([0.3, 0.2, 0.5])
DRAG = np.array([0.3])
BIAS = gtsam.imuBias.ConstantBias(np.array([0.02, -0.01, 0.03]), np.zeros(3))


def _robust(dim: int, sigma: float) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.345),
        gtsam.noiseModel.Isotropic.Sigma(dim, sigma),
    )


def _measurement_factors(poses, vels, k):
    pose, vel = poses[k], vels[k]
    cam = pose.compose(BODY_T_CAM)
    z_slam = SIM.transformFrom(cam.translation())
    u = pose.rotation().matrix().T @ vel
    r, _ = tilted_range_error(pose, np.zeros(1), 0.0, BODY_T_RANGE)
    out = [
        make_accel_drag_factor(
            X(k), V(k), B(0), D(0), -DRAG[0] * u[:2] + BIAS.accelerometer()[:2], _robust(2, 0.02)
        ),
        make_slam_position_factor(X(k), S(0), z_slam, BODY_T_CAM, _robust(3, 0.004)),
        make_slam_rotation_factor(
            X(k),
            S(0),
            SIM.rotation().matrix() @ cam.rotation().matrix(),
            BODY_T_CAM,
            _robust(3, 0.01),
        ),
        make_slam_axis_scale_factor(X(k), S(1), AXIS * pose.translation(), _robust(3, 0.004)),
        make_yaw_factor(X(k), pose.rotation().yaw(), _robust(1, 0.02)),
        make_yaw_factor(X(k), pose.rotation().yaw(), _robust(2, 0.02), cos_sin=True),
        make_range_factor(X(k), G(0), r[0], BODY_T_RANGE, _robust(1, 0.01)),
    ]
    if k > 0:
        prev = poses[k - 1]
        H = predicted_homography(prev, pose, 0.0, K, BODY_T_CAM)
        cam_i = prev.compose(BODY_T_CAM)
        rel = cam.between(cam_i)
        out += [
            make_homography_factor(X(k - 1), X(k), G(0), H, K, BODY_T_CAM, SIZE, _robust(8, 0.5)),
            make_homography_decomposed_factor(
                X(k - 1),
                X(k),
                G(0),
                rel.rotation().matrix(),
                rel.translation() / cam_i.z(),
                BODY_T_CAM,
                _robust(6, 0.005),
            ),
            make_slam_relative_factor(
                X(k - 1),
                X(k),
                S(0),
                SIM.transformFrom(cam_i.translation()),
                z_slam,
                BODY_T_CAM,
                _robust(3, 0.006),
            ),
        ]
    return out


def test_all_factors_in_isam2_converge_to_truth() -> None:
    rng = np.random.default_rng(40)
    n = 8
    poses = [
        gtsam.Pose3(gtsam.Rot3.Ypr(0.3 * k, 0.05, -0.04), np.array([0.2 * k, 0.1 * k, 2.5]))
        for k in range(n)
    ]
    vels = [
        np.array([2.0, 1.0, 0.0]) + 0.3 * np.array([np.sin(k), np.cos(k), 0.0]) for k in range(n)
    ]
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(1e-4)  # converge fully: relinearise whatever moved
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    for k in range(n):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(
                gtsam.PriorFactorPose3(X(0), poses[0], gtsam.noiseModel.Isotropic.Sigma(6, 0.01))
            )
            graph.add(
                gtsam.PriorFactorConstantBias(B(0), BIAS, gtsam.noiseModel.Isotropic.Sigma(6, 1e-3))
            )
            graph.add(drag_prior(D(0), 0.5, 1.0))
            graph.add(ground_prior(G(0), 0.0, 0.01))
            graph.add(
                gtsam.PriorFactorSimilarity3(S(0), SIM, gtsam.noiseModel.Isotropic.Sigma(7, 1.0))
            )
            graph.add(gtsam.PriorFactorVector(S(1), AXIS, gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
            values.insert(B(0), BIAS)
            values.insert(D(0), np.array([0.5]))
            values.insert(G(0), np.array([0.05]))
            values.insert(S(0), SIM.retract(rng.normal(0, 0.02, 7)))
            values.insert(S(1), AXIS * 1.1)
        graph.add(gtsam.PriorFactorVector(V(k), vels[k], gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
        for f in _measurement_factors(poses, vels, k):
            graph.add(f)
        values.insert(X(k), poses[k].retract(rng.normal(0, 0.03, 6)))
        values.insert(V(k), vels[k])
        isam.update(graph, values)
    for _ in range(5):
        isam.update()
    est = isam.calculateEstimate()
    for k in range(n):
        assert np.linalg.norm(poses[k].localCoordinates(est.atPose3(X(k)))) < 1e-3
    assert abs(est.atVector(D(0))[0] - DRAG[0]) < 1e-3
    np.testing.assert_allclose(est.atVector(S(1)), AXIS, atol=1e-3)
    assert abs(est.atSimilarity3(S(0)).scale() - SIM.scale()) < 1e-3
