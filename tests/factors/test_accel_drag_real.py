"""The rotor-drag factor on a real flight: EuRoC V1_02 (AscTec Firefly), ground-truth pose,
velocity and accelerometer bias pinned, drag coefficients fitted with the factor.

The EuRoC IMU x axis points roughly up and is tilted from the thrust axis, so a body frame with z
along the mean in-flight specific force (the thrust axis) is built first; the factor's model holds
in that frame.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from fgnav.datasets.geometry import quat_wxyz_to_matrix
from fgnav.factors.accel_drag import accel_drag_error, make_accel_drag_factor, mean_accel_noise

from fgnav.keys import B, D, V, X

pytestmark = pytest.mark.realdata

#: ADIS16448 accelerometer density [m/s^2/sqrt(Hz)] (calib/EuRoC.yaml) and rate [Hz].
ACCEL_DENSITY = 2.0e-3
IMU_RATE_HZ = 200.0
WINDOW = 40  # IMU samples per factor (0.2 s)
#: Height above the start [m] taken as "flying".
AIRBORNE_M = 0.3


def _load(real_data):
    d = real_data / "euroc_V1_02_medium"
    gt = np.loadtxt(d / "groundtruth" / "V102_groundtruth.csv", delimiter=",", comments="#")
    imu = np.loadtxt(d / "imu0" / "V102.txt", delimiter=",", comments="#")
    t_gt, t_imu = gt[:, 0] * 1e-9, imu[:, 0] * 1e-9
    accel = np.column_stack([np.interp(t_gt, t_imu, imu[:, 4 + j]) for j in range(3)])
    return gt, accel


def _body_R_imu(specific_force_imu: np.ndarray) -> np.ndarray:
    thrust = np.mean(specific_force_imu / np.linalg.norm(specific_force_imu, axis=1)[:, None], 0)
    z = thrust / np.linalg.norm(thrust)
    x = np.array([0.0, 0.0, -1.0])  # the IMU's -z is forward on the Firefly
    x -= (x @ z) * z
    x /= np.linalg.norm(x)
    return np.vstack([x, np.cross(z, x), z])


def test_drag_fitted_on_euroc_explains_horizontal_specific_force(real_data) -> None:
    gt, accel = _load(real_data)
    airborne = gt[:, 3] > gt[0, 3] + AIRBORNE_M
    world_R_imu = quat_wxyz_to_matrix(gt[:, 4:8])
    bias_imu = gt[:, 14:17]
    body_R_imu = _body_R_imu((accel - bias_imu)[airborne])
    starts = [i for i in range(0, len(gt) - WINDOW, WINDOW) if airborne[i : i + WINDOW].all()]
    assert len(starts) > 200

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    pin = gtsam.noiseModel.Isotropic.Sigma
    # Model floor: the residual RMS of a linear-drag fit on this flight is ~0.1 m/s^2.
    noise = mean_accel_noise(ACCEL_DENSITY * np.sqrt(IMU_RATE_HZ), WINDOW, 0.1)
    states = []
    for n, i in enumerate(starts):
        mid = i + WINDOW // 2
        world_R_body = world_R_imu[mid] @ body_R_imu.T
        pose = gtsam.Pose3(gtsam.Rot3(world_R_body), gt[mid, 1:4])
        vel = gt[mid, 8:11]
        bias = gtsam.imuBias.ConstantBias(body_R_imu @ bias_imu[mid], np.zeros(3))
        z = (accel[i : i + WINDOW] @ body_R_imu.T).mean(axis=0)[:2]
        graph.add(make_accel_drag_factor(X(n), V(n), B(n), D(0), z, noise))
        graph.add(gtsam.PriorFactorPose3(X(n), pose, pin(6, 1e-6)))
        graph.add(gtsam.PriorFactorVector(V(n), vel, pin(3, 1e-6)))
        graph.add(gtsam.PriorFactorConstantBias(B(n), bias, pin(6, 1e-6)))
        values.insert(X(n), pose)
        values.insert(V(n), vel)
        values.insert(B(n), bias)
        states.append((pose, vel, bias, z))
    values.insert(D(0), np.zeros(2))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    k = result.atVector(D(0))

    def rms(drag: np.ndarray) -> float:
        e = np.array([accel_drag_error(p, v, b, drag, z)[0] for p, v, b, z in states])
        return float(np.sqrt(np.mean(e**2)))

    # Measured: k = (0.163, 0.194) 1/s, residual RMS 0.092 m/s^2 against 0.160 without drag.
    assert np.all((k > 0.12) & (k < 0.26)), k
    assert rms(k) < 0.12
    assert rms(k) < 0.7 * rms(np.zeros(2))
