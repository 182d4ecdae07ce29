"""Accelerometer rotor-drag factor: horizontal specific force of a multirotor from body velocity.

Measurement model (seed 000 eq. 3, after Martin & Salaun 2010; PX4 EKF2 ``EKF2_MCOEF``)::

    f_xy = -K (body_R_world world_v_body)_xy + b_a,xy + n,     body_R_world = world_R_body^T

``f_xy`` [m/s^2] is the mean of the body x and y accelerometer samples over a keyframe interval
(body FLU axes). The thrust acts along body z only, so the horizontal specific force is the rotor
drag, whatever the tilt: gravity does not appear. ``K = k I`` for a scalar drag coefficient or
``diag(kx, ky)`` per axis, ``k = mu / m`` [1/s]. ``b_a,xy`` are the x, y components of the
accelerometer bias (GTSAM's convention: measured = true + bias).

Keys: ``X`` Pose3 ``world_T_body``, ``V`` velocity ``world_v_body`` [m/s] (Vector3), ``B``
``imuBias.ConstantBias``, ``D`` drag coefficient: a Vector of size 1 (``k``) or 2 (``kx, ky``)
[1/s].

Residual (2,): unwhitened ``h(x) - z`` [m/s^2]; zero when the mean accelerometer xy equals
``-K u_xy + b_a,xy`` with ``u = world_R_body^T world_v_body``.

Jacobians (GTSAM local coordinates, see ``fgnav.factors._jacobians``): with ``u`` above,
``e_D_pose = -K [skew(u), 0]_xy`` (2x6), ``e_D_vel = -K (world_R_body^T)_xy`` (2x3),
``e_D_bias = [I2 0 | 0]`` (2x6), ``e_D_drag = -u_xy`` (2x1) or ``-diag(u_xy)`` (2x2).

Optional wind (``wind_key``): with a horizontal wind ``world_v_wind = [wx, wy, 0]`` [m/s] (a gtsam
Vector of size 2, key ``W``), the drag acts on the air-relative velocity:
``u = world_R_body^T (world_v_body - world_v_wind)``; ``e_D_wind = -e_D_vel[:, :2]`` (2x2). Wind
and drag are separable only while the heading or the ground velocity changes (a constant wind at
one heading looks like an accelerometer bias).

Noise: the mean of ``n`` samples of discrete-time standard deviation ``sigma`` has standard
deviation ``sigma / sqrt(n)``; ``mean_accel_noise`` adds a floor for model error in quadrature.

Not modelled: vertical wind, gusts faster than the wind variable's random walk, quadratic drag,
the change of velocity within the averaging interval (the state at the keyframe stands for the
interval mean), vibration aliasing and rotor-speed dependence of ``k``.
"""

from __future__ import annotations

import gtsam
import numpy as np
from fgnav.factors._jacobians import as_vector, check_noise_dim

ERROR_DIM = 2


def accel_drag_error(
    world_T_body: gtsam.Pose3,
    world_v_body: np.ndarray,
    bias: gtsam.imuBias.ConstantBias,
    drag_k: np.ndarray,
    mean_body_accel_xy: np.ndarray,
    world_v_wind_xy: np.ndarray | None = None,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Residual and Jacobians of the rotor-drag model.

    Args:
        world_T_body: pose of the body in the world (Pose3).
        world_v_body: (3,) velocity of the body in world axes [m/s].
        bias: IMU bias; its accelerometer x, y enter the model [m/s^2].
        drag_k: (1,) ``[k]`` or (2,) ``[kx, ky]`` drag coefficient [1/s].
        mean_body_accel_xy: (2,) mean measured specific force along body x, y [m/s^2].
        world_v_wind_xy: optional (2,) horizontal wind velocity in world axes [m/s].

    Returns:
        ``(e, [e_D_pose (2x6), e_D_vel (2x3), e_D_bias (2x6), e_D_drag (2xn_k)])`` with
        ``e = h(x) - z`` [m/s^2]; with wind a fifth Jacobian ``e_D_wind`` (2x2) follows.
    """
    v_air = np.array(world_v_body, dtype=float)
    if world_v_wind_xy is not None:
        v_air[:2] -= world_v_wind_xy
    e, jacobians = _accel_drag(
        world_T_body.rotation().matrix(),
        v_air,
        bias.accelerometer(),
        drag_k,
        mean_body_accel_xy,
        True,
    )
    if world_v_wind_xy is None:
        return e, jacobians
    return e, [*jacobians, -jacobians[1][:, :2]]


def _accel_drag(
    world_R_body: np.ndarray,
    v_air: np.ndarray,
    b: np.ndarray,
    drag_k: np.ndarray,
    z: np.ndarray,
    with_jacobians: bool,
) -> tuple[np.ndarray, list[np.ndarray] | None]:
    """``accel_drag_error`` on the rotation matrix, the air-relative velocity and the
    accelerometer bias (the factor's callback); no Jacobians unless ``with_jacobians``."""
    k = np.atleast_1d(np.asarray(drag_k, dtype=float))
    if k.shape == (1,):
        kx = ky = float(k[0])
    elif k.shape == (2,):
        kx, ky = k.tolist()
    else:
        raise ValueError(f"drag_k: expected 1 or 2 values, got shape {np.shape(drag_k)}")
    u0, u1, u2 = (world_R_body.T @ v_air).tolist()
    e = np.array([-kx * u0 + b[0] - z[0], -ky * u1 + b[1] - z[1]])
    if not with_jacobians:
        return e, None
    # -K [u]x rows x, y (rotation columns); translation columns are zero.
    e_D_pose = np.zeros((2, 6))
    e_D_pose[0, 1] = kx * u2
    e_D_pose[0, 2] = -kx * u1
    e_D_pose[1, 0] = -ky * u2
    e_D_pose[1, 2] = ky * u0
    e_D_vel = world_R_body.T[:2] * np.array([[-kx], [-ky]])
    e_D_bias = np.zeros((2, 6))
    e_D_bias[0, 0] = 1.0
    e_D_bias[1, 1] = 1.0
    e_D_drag = np.array([[-u0], [-u1]]) if k.size == 1 else np.array([[-u0, 0.0], [0.0, -u1]])
    return e, [e_D_pose, e_D_vel, e_D_bias, e_D_drag]


def make_accel_drag_factor(
    pose_key: int,
    vel_key: int,
    bias_key: int,
    drag_key: int,
    mean_body_accel_xy: np.ndarray,
    noise_model: gtsam.noiseModel.Base,
    wind_key: int | None = None,
) -> gtsam.CustomFactor:
    """``CustomFactor`` on ``(X, V, B, D)`` or ``(X, V, B, D, W)`` for one keyframe interval (see
    the module docstring).

    Args:
        pose_key, vel_key, bias_key, drag_key: keys of ``world_T_body`` (Pose3), ``world_v_body``
            (Vector3), the IMU bias (ConstantBias) and the drag coefficient (Vector1 or Vector2).
        mean_body_accel_xy: (2,) mean body-x, body-y accelerometer reading [m/s^2].
        noise_model: 2-D noise model (e.g. ``mean_accel_noise``; may be robust).
        wind_key: optional key of the horizontal wind ``world_v_wind_xy`` (Vector2) [m/s].
    """
    z = as_vector(mean_body_accel_xy, 2, "mean_body_accel_xy")
    check_noise_dim(noise_model, ERROR_DIM)

    def error_fn(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        if wind_key is not None:
            e, jacobians = accel_drag_error(
                values.atPose3(pose_key),
                values.atVector(vel_key),
                values.atConstantBias(bias_key),
                values.atVector(drag_key),
                z,
                values.atVector(wind_key),
            )
        else:
            e, jacobians = _accel_drag(
                values.atPose3(pose_key).rotation().matrix(),
                values.atVector(vel_key),
                values.atConstantBias(bias_key).accelerometer(),
                values.atVector(drag_key),
                z,
                H is not None,
            )
        if H is not None:
            for i, J in enumerate(jacobians):
                H[i] = J
        return e

    keys = [pose_key, vel_key, bias_key, drag_key]
    if wind_key is not None:
        keys.append(wind_key)
    return gtsam.CustomFactor(noise_model, keys, error_fn)


def mean_accel_noise(
    sigma_accel_discrete: float, n_samples: int, model_sigma: float
) -> gtsam.noiseModel.Isotropic:
    """2-D noise of the interval-mean accelerometer xy.

    Args:
        sigma_accel_discrete: standard deviation of one accelerometer sample [m/s^2] (continuous
            noise density [m/s^2/sqrt(Hz)] times sqrt(sample rate [Hz])).
        n_samples: number of samples averaged (>= 1).
        model_sigma: floor for drag-model error (wind, quadratic drag, vibration) [m/s^2], added in
            quadrature.

    Returns:
        ``Isotropic.Sigma(2, sqrt(sigma^2 / n + model_sigma^2))``.
    """
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1, got {n_samples}")
    if sigma_accel_discrete < 0 or model_sigma < 0:
        raise ValueError("sigma_accel_discrete and model_sigma must be >= 0")
    sigma = float(np.sqrt(sigma_accel_discrete**2 / n_samples + model_sigma**2))
    if sigma <= 0:
        raise ValueError("mean_accel_noise: total sigma is zero")
    return gtsam.noiseModel.Isotropic.Sigma(ERROR_DIM, sigma)
