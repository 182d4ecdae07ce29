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

import gtsam
import numpy as np
from fgnav.factors._jacobians import check_noise_dim, pose_parts

#: Floor on ``R[0,0]^2 + R[1,0]^2`` = cos(pitch)^2; 1e-4 = cos(89.43 deg)^2, beyond any flight.
MIN_HORIZONTAL_NORM2 = 1e-4

# [e_x]x rows 0 and 1 enter the derivative of the body x axis: R (I + [w]x) e_x = r0 - R [e_x]x w.
_SKEW_EX = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


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
    world_R_body, _ = pose_parts(world_T_body)
    c, s = world_R_body[0, 0], world_R_body[1, 0]
    psi = float(np.arctan2(s, c))
    dx = -(world_R_body @ _SKEW_EX)
    norm2 = max(c * c + s * s, MIN_HORIZONTAL_NORM2)
    psi_D_omega = (c * dx[1] - s * dx[0]) / norm2
    if cos_sin:
        e = np.array([np.cos(psi) - np.cos(yaw_meas), np.sin(psi) - np.sin(yaw_meas)])
        J = np.zeros((2, 6))
        J[:, :3] = np.outer([-np.sin(psi), np.cos(psi)], psi_D_omega)
        return e, [J]
    J = np.zeros((1, 6))
    J[0, :3] = psi_D_omega
    return np.array([wrap_angle(psi - yaw_meas)]), [J]


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
    check_noise_dim(noise_model, 2 if cos_sin else 1)

    def error_fn(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        e, jacobians = yaw_error(values.atPose3(pose_key), z, cos_sin)
        if H is not None:
            H[0] = jacobians[0]
        return e

    return gtsam.CustomFactor(noise_model, [pose_key], error_fn)
