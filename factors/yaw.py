"""Yaw (heading) factor on a Pose3, wrapped or as the ``[cos, sin]`` pair.

Measurement model (seed 002 eqs. 17-19)::

    psi(world_R_body) = atan2(R[1, 0], R[0, 0])     ZYX yaw of the body x axis (GTSAM Rot3.yaw())
    e = wrap(psi - psi_meas)                        in (-pi, pi]           (default, 1-D) [rad]
    e = [cos psi - cos psi_meas, sin psi - sin psi_meas]                   (``cos_sin=True``, 2-D)

The wrapped form never produces a 2 pi jump at +-pi (seed 002's reason for eq. 18); the
``[cos, sin]`` form is seed 002's eq. 19, smooth everywhere, with an error norm of
``2 sin(|dpsi| / 2)`` (about ``|dpsi|`` for small errors, so the same sigma [rad] applies).

Keys: ``X`` Pose3 ``world_T_body`` (world z up, body FLU). Zero error: the body x axis projected
on the world x-y plane has heading ``psi_meas`` (from world +x towards +y).

Jacobian (right perturbation ``[omega, v]``): with ``c = R[0, 0]``, ``s = R[1, 0]``,
``dpsi/domega = (c (-(R [e_x]x)[1]) - s (-(R [e_x]x)[0])) / (c^2 + s^2)``, zero w.r.t. ``v``;
the ``[cos, sin]`` form multiplies it by ``[-sin psi, cos psi]^T``.

Noise: sigma [rad] of the heading source (magnetometer, SLAM, visual odometry). Not modelled:
magnetic disturbances (use a robust kernel), the yaw singularity at pitch +-90 deg (there the
horizontal projection of the body x axis vanishes; its squared norm is floored at
``MIN_HORIZONTAL_NORM2``, which bounds the Jacobian).
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from fgnav.factors._jacobians import custom_factor, pose_matrix, pose_matrix_at

#: Floor on ``R[0,0]^2 + R[1,0]^2`` = cos(pitch)^2; 1e-4 = cos(89.43 deg)^2, beyond any flight.
MIN_HORIZONTAL_NORM2 = 1e-4


def wrap_angle(a: float) -> float:
    """Wrap an angle [rad] to (-pi, pi]."""
    w = float(np.mod(a + np.pi, 2.0 * np.pi) - np.pi)
    return np.pi if w == -np.pi else w


def yaw_error(
    world_T_body: gtsam.Pose3, yaw_meas: float, cos_sin: bool = False
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Yaw residual and its Jacobian.

    Args:
        world_T_body: body pose in the world (z up, body FLU).
        yaw_meas: measured yaw [rad], any range.
        cos_sin: residual as the 2-D ``[cos, sin]`` difference instead of the wrapped angle.

    Returns:
        ``(e, [e_D_pose])``: ``e`` (1,) [rad] and ``e_D_pose`` (1x6); or ``e`` (2,) and (2x6).
    """
    return _yaw(pose_matrix(world_T_body), yaw_meas, cos_sin, True)


def _yaw(
    m: np.ndarray, yaw_meas: float, cos_sin: bool, with_jacobians: bool
) -> tuple[np.ndarray, list[np.ndarray] | None]:
    """``yaw_error`` on the 4x4 ``world_T_body`` in plain float arithmetic (the factor's
    callback); no Jacobian unless ``with_jacobians``. With ``S = [e_x]x``,
    ``(R S)[i] = [0, R[i, 2], -R[i, 1]]``, so
    ``dpsi/domega = [0, s R[0, 2] - c R[1, 2], c R[1, 1] - s R[0, 1]] / (c^2 + s^2)``.
    """
    (c, r01, r02, _), (s, r11, r12, _) = m[:2].tolist()
    psi = math.atan2(s, c)
    if cos_sin:
        e = np.array([math.cos(psi) - math.cos(yaw_meas), math.sin(psi) - math.sin(yaw_meas)])
    else:
        e = np.array([wrap_angle(psi - yaw_meas)])
    if not with_jacobians:
        return e, None
    norm2 = max(c * c + s * s, MIN_HORIZONTAL_NORM2)
    d_omega = [0.0, (s * r02 - c * r12) / norm2, (c * r11 - s * r01) / norm2]
    if cos_sin:
        J = np.zeros((2, 6))
        J[:, :3] = np.outer([-math.sin(psi), math.cos(psi)], d_omega)
        return e, [J]
    J = np.zeros((1, 6))
    J[0, :3] = d_omega
    return e, [J]


def make_yaw_factor(
    pose_key: int, yaw_meas: float, noise_model: gtsam.noiseModel.Base, cos_sin: bool = False
) -> gtsam.CustomFactor:
    """Yaw factor on ``X`` (1-D wrapped [rad], or 2-D ``[cos, sin]`` with ``cos_sin=True``).

    Args:
        yaw_meas: measured yaw [rad].
        noise_model: 1-D (or 2-D for ``cos_sin``) noise [rad]; may be robust.
    """
    z = float(yaw_meas)
    if not np.isfinite(z):
        raise ValueError(f"yaw_meas: non-finite value {yaw_meas}")
    dim = 2 if cos_sin else 1
    variables = ((pose_key, pose_matrix_at),)
    return custom_factor(noise_model, dim, variables, _yaw, (z, cos_sin), lazy=True)
