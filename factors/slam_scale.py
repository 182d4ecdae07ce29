"""Monocular-SLAM position factors with unknown scale (absolute, per-axis, relative, rotation).

Measurement model (seed 000 eq. 4 and the scale ``lambda`` of seed 004 / Engel et al.; ethz-asl MSF
``z = L C (p - p_wv + ...)``). The SLAM system reports the camera pose in its own frame ``slam`` at
an unknown scale ``s`` [SLAM units per metre]::

    slam_t_cam = s * slam_R_world * world_t_cam + slam_t_world + n                      (absolute)
    world_t_cam = world_t_body + world_R_body * body_t_cam                              (lever arm)

Variable ``S`` ``slam_T_world`` is a ``gtsam.Similarity3`` ``(R, t, s)``. GTSAM's ``Similarity3``
maps a point as ``transformFrom(p) = s * (R p + t)``, so ``R = slam_R_world``, ``s`` is the scale
and the translation held by GTSAM is ``t = slam_t_world / s`` (``slam_t_world = s * t``). Use
``make_slam_T_world`` / ``slam_alignment_parts`` to convert. Tangent (GTSAM ``Similarity3``
local coordinates): ``[omega (3), u (3), lambda (1)]``, right perturbation
``slam_T_world * Exp(xi)``; to first order the scale becomes ``s exp(lambda)``.

Factors of this module (residual = unwhitened ``h(x) - z``, SLAM units):

- ``make_slam_position_factor`` (keys ``X, S``; 3-D): the absolute model above; zero when the
  similarity maps the true camera position onto the measured one.
- ``make_slam_axis_scale_factor`` (keys ``X``, per-axis scale Vector3 ``[kx, ky, kz]``; 3-D): seed
  000's ``slam_t = diag(kx, ky, kz) world_t_cam`` (SLAM frame axes and origin equal the world's).
- ``make_slam_axis_offset_factor`` (keys ``X``, Vector6 ``[kx, ky, kz, ox, oy, oz]``; 3-D): the
  per-axis model with an unknown SLAM origin, ``slam_t = diag(k) world_t_cam + o`` (SLAM axes
  equal the world's). The smoothers use it: the world origin is then the first keyframe's position
  (as with ``S``), not the SLAM origin, which is unknown until the scale is (a causal estimator
  would otherwise jump when the per-axis scale is first initialised).
- ``make_slam_relative_factor`` (keys ``X_i, X_j, S``; 3-D): the displacement
  ``slam_t_cam_j - slam_t_cam_i = s slam_R_world (world_t_cam_j - world_t_cam_i)``; independent of
  ``slam_t_world``, so a slow drift of the SLAM origin does not bias it (the translation part of
  ``S`` gets no information from it).
- ``make_slam_position_offset_factor`` (keys ``X, V, S``; 3-D): the absolute model for an image
  taken ``dt`` seconds after (``dt < 0``: before) the keyframe ``X, V``. The body is carried to
  the capture time at constant specific force and angular rate (the IMU reading near the capture
  time, bias-corrected by the caller): ``world_t_body(t) = world_t_body + world_v_body dt +
  (world_R_body f + g) dt^2 / 2``, ``world_R_body(t) = world_R_body Exp(omega dt)``. For an online
  smoother whose keyframes lie on a fixed grid while the images arrive late; with ``|dt|`` up to
  half a 20 Hz keyframe period the neglected jerk and bias terms are below 0.1 mm at 1 m/s^2.
- ``make_slam_axis_position_offset_factor`` (keys ``X, V``, Vector6 ``[k, o]``; 3-D): the
  per-axis model with the unknown origin for an image taken ``dt`` seconds from the keyframe,
  the body carried to the capture time as in the offset factor above: ``diag(k) world_t_cam(t) +
  o``.
- ``make_slam_rotation_factor`` (keys ``X, S``; 3-D): ``Log(slam_R_cam_meas^T slam_R_world
  world_R_body body_R_cam)`` [rad]; it makes the yaw of the SLAM frame (and roll/pitch) observable.

Noise: isotropic in SLAM units (a SLAM position sigma of ``sigma_m`` metres is ``s * sigma_m``
SLAM units); robust kernels recommended against SLAM jumps. Not modelled: time offset between SLAM
and IMU (interpolate the keyframe first), SLAM map resets (start a new ``S`` variable), scale drift
within one session (use a random walk between ``S`` variables), rolling shutter.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from fgnav.factors._jacobians import (
    as_pose_matrix,
    as_vector,
    custom_factor,
    pose_at,
    pose_matrix,
    pose_matrix_at,
    pose_parts,
    sim3_parts,
    similarity3_at,
    skew,
    so3_log,
    so3_right_jacobian_inv,
    vector_at,
)

ERROR_DIM = 3


def make_slam_T_world(
    scale: float, slam_R_world: np.ndarray, slam_t_world: np.ndarray
) -> gtsam.Similarity3:
    """``Similarity3`` for ``p_slam = scale * slam_R_world p_world + slam_t_world``.

    Args:
        scale: SLAM units per metre (> 0).
        slam_R_world: (3, 3) rotation from world to SLAM axes.
        slam_t_world: (3,) world origin in the SLAM frame [SLAM units].
    """
    if not scale > 0:
        raise ValueError(f"scale must be > 0, got {scale}")
    t = as_vector(slam_t_world, 3, "slam_t_world")
    return gtsam.Similarity3(gtsam.Rot3(np.asarray(slam_R_world, dtype=float)), t / scale, scale)


def slam_alignment_parts(slam_T_world: gtsam.Similarity3) -> tuple[float, np.ndarray, np.ndarray]:
    """Inverse of ``make_slam_T_world``: ``(scale, slam_R_world (3, 3), slam_t_world (3,))``."""
    R, t, s = sim3_parts(slam_T_world)
    return s, R, s * t


def _world_t_cam(world_T_body, body_t_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera position in world and its Jacobian (3x6) w.r.t. the pose's local coordinates."""
    world_R_body, world_t_body = pose_parts(world_T_body)
    p = world_t_body + world_R_body @ body_t_cam
    p_D_pose = np.empty((3, 6))
    p_D_pose[:, :3] = -world_R_body @ skew(body_t_cam)
    p_D_pose[:, 3:] = world_R_body
    return p, p_D_pose


def slam_position_error(
    world_T_body: gtsam.Pose3,
    slam_T_world: gtsam.Similarity3,
    slam_t_cam_meas: np.ndarray,
    body_T_cam: gtsam.Pose3 | np.ndarray,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Absolute SLAM position residual.

    Args:
        world_T_body: body pose in the world.
        slam_T_world: alignment (see module docstring for GTSAM's ``Similarity3`` convention).
        slam_t_cam_meas: (3,) measured camera position in the SLAM frame [SLAM units].
        body_T_cam: camera pose in the body frame (only its translation, the lever arm, is used).

    Returns:
        ``(e (3,), [e_D_pose (3x6), e_D_sim (3x7)])``.
    """
    _, body_t_cam = pose_parts(body_T_cam)
    e, jacobians = _slam_position(
        pose_matrix(world_T_body),
        slam_T_world,
        np.asarray(slam_t_cam_meas, dtype=float),
        body_t_cam,
        skew(body_t_cam),
        True,
    )
    return e, jacobians


def _slam_position(
    m: np.ndarray,
    slam_T_world: gtsam.Similarity3,
    z: np.ndarray,
    body_t_cam: np.ndarray,
    body_t_cam_skew: np.ndarray,
    with_jacobians: bool,
) -> tuple[np.ndarray, list[np.ndarray] | None]:
    """``slam_position_error`` with the lever arm's skew matrix precomputed (the factor's
    callback: every linearisation calls it; ``m``: 4x4 ``world_T_body``); no Jacobians unless
    ``with_jacobians``."""
    world_R_body = m[:3, :3]
    p = m[:3, 3] + world_R_body @ body_t_cam
    y, sR = _sim3_point(slam_T_world, p)
    e = y - z
    if not with_jacobians:
        return e, None
    p_D_pose = np.empty((3, 6))
    p_D_pose[:, :3] = -world_R_body @ body_t_cam_skew
    p_D_pose[:, 3:] = world_R_body
    return e, [sR @ p_D_pose, _sim3_point_D_sim(sR, p)]


def _sim3_point(slam_T_world: gtsam.Similarity3, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(y, s R)``: the world point ``p`` in the SLAM frame, ``y = s (R p + t)`` [SLAM units],
    and the scaled rotation (``y_D_p``)."""
    R = slam_T_world.rotation().matrix()
    s = slam_T_world.scale()
    return s * (R @ p + slam_T_world.translation()), s * R


def _sim3_point_D_sim(sR: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Jacobian (3x7) of ``y = s (R p + t)`` w.r.t. the ``Similarity3`` local coordinates
    ``[omega, u, lambda]`` (module docstring), from ``s R`` and the world point ``p``."""
    y_D_sim = np.empty((3, 7))
    y_D_sim[:, :3] = -sR @ skew(p)
    y_D_sim[:, 3:6] = sR
    y_D_sim[:, 6] = sR @ p
    return y_D_sim


def slam_axis_scale_error(
    world_T_body: gtsam.Pose3,
    axis_scale: np.ndarray,
    slam_t_meas: np.ndarray,
    body_t_cam: np.ndarray | None = None,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Seed 000 per-axis scale residual ``diag(k) world_t_cam - slam_t_meas``.

    Args:
        world_T_body: body pose in the world.
        axis_scale: (3,) ``[kx, ky, kz]`` [SLAM units per metre].
        slam_t_meas: (3,) measured SLAM position [SLAM units].
        body_t_cam: (3,) lever arm [m] (default zero: the body origin is measured, as in seed 000).

    Returns:
        ``(e (3,), [e_D_pose (3x6), e_D_scale (3x3)])``.
    """
    lever = np.zeros(3) if body_t_cam is None else np.asarray(body_t_cam, dtype=float)
    p, p_D_pose = _world_t_cam(world_T_body, lever)
    k = np.asarray(axis_scale, dtype=float)
    e = k * p - np.asarray(slam_t_meas, dtype=float)
    return e, [k[:, None] * p_D_pose, np.diag(p)]


def slam_axis_offset_error(
    world_T_body: gtsam.Pose3,
    alignment: np.ndarray,
    slam_t_meas: np.ndarray,
    body_t_cam: np.ndarray | None = None,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Per-axis scale and offset residual ``diag(k) world_t_cam + o - slam_t_meas``.

    Args:
        world_T_body: body pose in the world.
        alignment: (6,) ``[kx, ky, kz]`` [SLAM units per metre] and ``[ox, oy, oz]`` [SLAM units].
        slam_t_meas: (3,) measured SLAM position [SLAM units].
        body_t_cam: (3,) lever arm [m] (default zero).

    Returns:
        ``(e (3,), [e_D_pose (3x6), e_D_alignment (3x6)])``.
    """
    a = np.asarray(alignment, dtype=float)
    e, (e_D_pose, e_D_k) = slam_axis_scale_error(world_T_body, a[:3], slam_t_meas, body_t_cam)
    return e + a[3:], [e_D_pose, np.hstack([e_D_k, np.eye(3)])]


def slam_relative_error(
    world_T_body_i: gtsam.Pose3,
    world_T_body_j: gtsam.Pose3,
    slam_T_world: gtsam.Similarity3,
    slam_t_cam_i: np.ndarray,
    slam_t_cam_j: np.ndarray,
    body_T_cam: gtsam.Pose3 | np.ndarray,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Relative SLAM displacement residual
    ``s slam_R_world (world_t_cam_j - world_t_cam_i) - (slam_t_cam_j - slam_t_cam_i)``.

    Returns:
        ``(e (3,), [e_D_pose_i (3x6), e_D_pose_j (3x6), e_D_sim (3x7)])``; the translation columns
        of ``e_D_sim`` are zero.
    """
    _, body_t_cam = pose_parts(body_T_cam)
    p_i, p_i_D_pose = _world_t_cam(world_T_body_i, body_t_cam)
    p_j, p_j_D_pose = _world_t_cam(world_T_body_j, body_t_cam)
    R, _, s = sim3_parts(slam_T_world)
    sR = s * R
    d = p_j - p_i
    y = sR @ d
    e = y - (np.asarray(slam_t_cam_j, dtype=float) - np.asarray(slam_t_cam_i, dtype=float))
    e_D_sim = np.zeros((3, 7))
    e_D_sim[:, :3] = -sR @ skew(d)
    e_D_sim[:, 6] = y
    return e, [-sR @ p_i_D_pose, sR @ p_j_D_pose, e_D_sim]


def slam_rotation_error(
    world_T_body: gtsam.Pose3,
    slam_T_world: gtsam.Similarity3,
    slam_R_cam_meas: np.ndarray,
    body_T_cam: gtsam.Pose3 | np.ndarray,
    with_jacobians: bool = True,
) -> tuple[np.ndarray, list[np.ndarray] | None]:
    """SLAM orientation residual ``Log(slam_R_cam_meas^T slam_R_world world_R_body body_R_cam)``
    [rad] (right-invariant error in the camera frame).

    Returns:
        ``(e (3,), [e_D_pose (3x6), e_D_sim (3x7)])``; only rotation columns are non-zero.
        Without ``with_jacobians`` (an error-only evaluation): ``(e, None)``.
    """
    world_R_body, _ = pose_parts(world_T_body)
    body_R_cam, _ = pose_parts(body_T_cam)
    slam_R_world, _, _ = sim3_parts(slam_T_world)
    meas_T = np.asarray(slam_R_cam_meas, dtype=float).T
    return _rotation_error(world_R_body, slam_R_world, meas_T, body_R_cam, with_jacobians)


def _slam_rotation(
    m: np.ndarray,
    slam_T_world: gtsam.Similarity3,
    slam_R_cam_meas_T: np.ndarray,
    body_R_cam: np.ndarray,
    with_jacobians: bool,
) -> tuple[np.ndarray, list[np.ndarray] | None]:
    """``slam_rotation_error`` on the 4x4 ``world_T_body`` with the measurement's transpose and
    ``body_R_cam`` taken apart once (the factor's callback: the same arithmetic on the same
    arrays, without the per-call conversions and the similarity's unused translation and
    scale); no Jacobians unless ``with_jacobians``."""
    R_sw = slam_T_world.rotation().matrix()
    return _rotation_error(m[:3, :3], R_sw, slam_R_cam_meas_T, body_R_cam, with_jacobians)


def _rotation_error(
    world_R_body: np.ndarray,
    slam_R_world: np.ndarray,
    slam_R_cam_meas_T: np.ndarray,
    body_R_cam: np.ndarray,
    with_jacobians: bool,
) -> tuple[np.ndarray, list[np.ndarray] | None]:
    """The SLAM orientation residual and its Jacobians from the rotations (shared by
    ``slam_rotation_error`` and the factor's callback)."""
    world_R_cam = world_R_body @ body_R_cam
    e = so3_log(slam_R_cam_meas_T @ (slam_R_world @ world_R_cam))
    if not with_jacobians:
        return e, None
    Jr_inv = so3_right_jacobian_inv(e)
    e_D_pose = np.zeros((3, 6))
    e_D_pose[:, :3] = Jr_inv @ body_R_cam.T
    e_D_sim = np.zeros((3, 7))
    e_D_sim[:, :3] = Jr_inv @ world_R_cam.T
    return e, [e_D_pose, e_D_sim]


def make_slam_position_factor(
    pose_key: int,
    sim_key: int,
    slam_t_cam_meas: np.ndarray,
    body_T_cam: gtsam.Pose3 | np.ndarray,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """Absolute SLAM position factor on ``(X: Pose3, S: Similarity3 slam_T_world)`` (3-D).

    Args:
        slam_t_cam_meas: (3,) camera position reported by SLAM [SLAM units].
        body_T_cam: camera pose in the body frame (Pose3 or 4x4); its translation is the lever arm.
        noise_model: 3-D noise in SLAM units (may be robust).
    """
    z = as_vector(slam_t_cam_meas, 3, "slam_t_cam_meas")
    body_t_cam = np.array(as_pose_matrix(body_T_cam, "body_T_cam")[:3, 3])
    body_t_cam_skew = skew(body_t_cam)
    return custom_factor(
        noise_model,
        ERROR_DIM,
        ((pose_key, pose_matrix_at), (sim_key, similarity3_at)),
        _slam_position,
        (z, body_t_cam, body_t_cam_skew),
        lazy=True,
        record=True,
    )


def slam_position_offset_error(
    world_T_body: gtsam.Pose3,
    world_v_body: np.ndarray,
    slam_T_world: gtsam.Similarity3,
    slam_t_cam_meas: np.ndarray,
    body_t_cam: np.ndarray,
    dt: float,
    body_accel: np.ndarray,
    body_omega: np.ndarray,
    gravity: float,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """SLAM position residual of an image taken ``dt`` [s] after the keyframe (see the module
    docstring): ``s (R p_cam(t) + t) - z`` with ``p_cam(t) = p + v dt + (R_b f + g) dt^2 / 2 + R_b
    Exp(omega dt) c``, ``g = (0, 0, -gravity)``.

    Args:
        world_T_body, world_v_body: keyframe pose and velocity.
        slam_T_world: alignment.
        slam_t_cam_meas: (3,) measured camera position [SLAM units].
        body_t_cam: (3,) lever arm [m].
        dt: capture time minus keyframe time [s].
        body_accel: (3,) specific force over ``dt`` [m/s^2] (bias-corrected).
        body_omega: (3,) angular rate over ``dt`` [rad/s] (bias-corrected).
        gravity: g [m/s^2].

    Returns:
        ``(e (3,), [e_D_pose (3x6), e_D_vel (3x3), e_D_sim (3x7)])``.
    """
    return _slam_offset(
        pose_matrix(world_T_body),
        np.asarray(world_v_body, float),
        slam_T_world,
        np.asarray(slam_t_cam_meas, float),
        *_offset_terms(body_t_cam, dt, body_accel, body_omega, gravity),
        True,
    )


def _offset_terms(body_t_cam, dt, body_accel, body_omega, gravity):
    """Constant parts of the offset model: ``(dt, E c, f dt^2 / 2, g dt^2 / 2)``."""
    c = as_vector(body_t_cam, 3, "body_t_cam")
    E = gtsam.Rot3.Expmap(as_vector(body_omega, 3, "body_omega") * float(dt)).matrix()
    half = 0.5 * float(dt) ** 2
    f_half = as_vector(body_accel, 3, "body_accel") * half
    g_half = np.array([0.0, 0.0, -float(gravity) * half])
    return float(dt), E @ c, f_half, g_half


def _carried_camera(m, v, dt, Ec, f_half, g_half):
    """``(R_b, lever, p_cam(t))`` of the offset model: the camera carried ``dt`` from the
    keyframe pose matrix ``m`` and velocity ``v``."""
    R_b = m[:3, :3]
    lever = f_half + Ec
    return R_b, lever, m[:3, 3] + v * dt + g_half + R_b @ lever


def _slam_offset(m, v, slam_T_world, z, dt, Ec, f_half, g_half, with_jacobians):
    R_b, lever, p = _carried_camera(m, v, dt, Ec, f_half, g_half)
    y, sR = _sim3_point(slam_T_world, p)
    e = y - z
    if not with_jacobians:
        return e, None
    e_D_pose = np.empty((3, 6))
    e_D_pose[:, :3] = -sR @ R_b @ skew(lever)
    e_D_pose[:, 3:] = sR @ R_b
    return e, [e_D_pose, sR * dt, _sim3_point_D_sim(sR, p)]


def make_slam_position_offset_factor(
    pose_key: int,
    vel_key: int,
    sim_key: int,
    slam_t_cam_meas: np.ndarray,
    body_T_cam: gtsam.Pose3 | np.ndarray,
    dt: float,
    body_accel: np.ndarray,
    body_omega: np.ndarray,
    gravity: float,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """SLAM position of an image taken ``dt`` seconds from the keyframe, on ``(X: Pose3,
    V: Vector3, S: Similarity3)`` (3-D, SLAM units); see :func:`slam_position_offset_error`.

    Args:
        slam_t_cam_meas: (3,) camera position reported by SLAM [SLAM units].
        body_T_cam: camera pose in the body frame; its translation is the lever arm [m].
        dt: capture time minus keyframe time [s] (keep ``|dt|`` within a keyframe period).
        body_accel, body_omega: bias-corrected IMU reading near the capture time (held constant
            over ``dt``) [m/s^2], [rad/s].
        gravity: g [m/s^2] (world z up).
        noise_model: 3-D noise in SLAM units (may be robust).
    """
    z = as_vector(slam_t_cam_meas, 3, "slam_t_cam_meas")
    terms = _offset_terms(
        as_pose_matrix(body_T_cam, "body_T_cam")[:3, 3], dt, body_accel, body_omega, gravity
    )
    return _offset_factor(
        _slam_offset,
        similarity3_at,
        (pose_key, vel_key, sim_key),
        z,
        terms,
        noise_model,
    )


def _offset_factor(offset, at_alignment, keys, z, terms, noise_model) -> gtsam.CustomFactor:
    """CustomFactor on ``(X: Pose3, V: Vector3, alignment)`` from an offset model
    ``offset(pose matrix, v, alignment, z, *terms, with_jacobians)``; ``at_alignment`` reads
    the alignment from the values (``Values.atSimilarity3`` or ``Values.atVector``)."""
    pose_key, vel_key, align_key = keys
    variables = ((pose_key, pose_matrix_at), (vel_key, vector_at), (align_key, at_alignment))
    return custom_factor(
        noise_model, ERROR_DIM, variables, offset, (z, *terms), lazy=True, record=True
    )


def make_slam_axis_scale_factor(
    pose_key: int,
    scale_key: int,
    slam_t_meas: np.ndarray,
    noise_model: gtsam.noiseModel.Base,
    body_t_cam: np.ndarray | None = None,
) -> gtsam.CustomFactor:
    """Seed 000 per-axis scale factor on ``(X: Pose3, scale: Vector3 [kx, ky, kz])`` (3-D).

    Args:
        slam_t_meas: (3,) SLAM position [SLAM units], SLAM axes and origin equal to the world's.
        noise_model: 3-D noise in SLAM units.
        body_t_cam: optional (3,) lever arm [m].
    """
    return _axis_factor(
        slam_axis_scale_error, pose_key, scale_key, slam_t_meas, noise_model, body_t_cam
    )


def make_slam_axis_offset_factor(
    pose_key: int,
    alignment_key: int,
    slam_t_meas: np.ndarray,
    noise_model: gtsam.noiseModel.Base,
    body_t_cam: np.ndarray | None = None,
) -> gtsam.CustomFactor:
    """Per-axis scale + SLAM-origin offset factor on ``(X: Pose3, alignment: Vector6
    [kx, ky, kz, ox, oy, oz])`` (3-D): ``diag(k) world_t_cam + o - slam_t_meas``.

    Args:
        slam_t_meas: (3,) SLAM position [SLAM units]; SLAM axes equal the world's (seed 000),
            the origin is free.
        noise_model: 3-D noise in SLAM units.
        body_t_cam: optional (3,) lever arm [m].

    Not modelled: a rotation between the SLAM and world axes (use the Sim(3) factor), scale drift
    within one alignment variable (chain them with a random walk).
    """
    return _axis_factor(
        slam_axis_offset_error, pose_key, alignment_key, slam_t_meas, noise_model, body_t_cam
    )


def _axis_factor(error, pose_key, vector_key, slam_t_meas, noise_model, body_t_cam):
    """CustomFactor on ``(X: Pose3, Vector)`` from a per-axis ``error(pose, vector, z, lever)``."""
    z = as_vector(slam_t_meas, 3, "slam_t_meas")
    lever = None if body_t_cam is None else as_vector(body_t_cam, 3, "body_t_cam")
    variables = ((pose_key, pose_at), (vector_key, vector_at))
    return custom_factor(noise_model, ERROR_DIM, variables, error, (z, lever))


def slam_axis_position_offset_error(
    world_T_body: gtsam.Pose3,
    world_v_body: np.ndarray,
    alignment: np.ndarray,
    slam_t_meas: np.ndarray,
    body_t_cam: np.ndarray,
    dt: float,
    body_accel: np.ndarray,
    body_omega: np.ndarray,
    gravity: float,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Per-axis scale and offset residual of an image taken ``dt`` [s] from the keyframe:
    ``diag(k) p_cam(t) + o - z`` with ``p_cam(t) = p + v dt + (R_b f + g) dt^2 / 2 + R_b
    Exp(omega dt) c`` (see :func:`slam_position_offset_error`).

    Args:
        world_T_body, world_v_body: keyframe pose and velocity.
        alignment: (6,) ``[kx, ky, kz]`` [SLAM units per metre], ``[ox, oy, oz]`` [SLAM units].
        slam_t_meas: (3,) measured camera position [SLAM units] (SLAM axes = world axes).
        body_t_cam: (3,) lever arm [m].
        dt: capture time minus keyframe time [s].
        body_accel, body_omega: bias-corrected IMU reading near the capture time.
        gravity: g [m/s^2].

    Returns:
        ``(e (3,), [e_D_pose (3x6), e_D_vel (3x3), e_D_alignment (3x6)])``.
    """
    return _axis_offset(
        pose_matrix(world_T_body),
        np.asarray(world_v_body, float),
        np.asarray(alignment, float),
        np.asarray(slam_t_meas, float),
        *_offset_terms(body_t_cam, dt, body_accel, body_omega, gravity),
        True,
    )


def _axis_offset(m, v, a, z, dt, Ec, f_half, g_half, with_jacobians):
    R_b, lever, p = _carried_camera(m, v, dt, Ec, f_half, g_half)
    k = a[:3]
    e = k * p + a[3:] - z
    if not with_jacobians:
        return e, None
    e_D_pose = np.empty((3, 6))
    e_D_pose[:, :3] = -k[:, None] * (R_b @ skew(lever))
    e_D_pose[:, 3:] = k[:, None] * R_b
    return e, [e_D_pose, np.diag(k * dt), np.hstack([np.diag(p), np.eye(3)])]


def make_slam_axis_position_offset_factor(
    pose_key: int,
    vel_key: int,
    alignment_key: int,
    slam_t_meas: np.ndarray,
    body_t_cam: np.ndarray,
    dt: float,
    body_accel: np.ndarray,
    body_omega: np.ndarray,
    gravity: float,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """Per-axis SLAM position of an image taken ``dt`` seconds from the keyframe, on ``(X:
    Pose3, V: Vector3, alignment: Vector6 [kx, ky, kz, ox, oy, oz])`` (3-D, SLAM units); see
    :func:`slam_axis_position_offset_error`. The push-API smoother's per-axis factor (its
    keyframes lie on a grid, the SLAM poses between them).

    Args:
        slam_t_meas: (3,) SLAM position [SLAM units]; SLAM axes equal the world's (seed 000).
        body_t_cam: (3,) lever arm [m].
        dt: capture time minus keyframe time [s] (keep ``|dt|`` within a keyframe period).
        body_accel, body_omega: bias-corrected IMU reading near the capture time (held constant
            over ``dt``) [m/s^2], [rad/s].
        gravity: g [m/s^2] (world z up).
        noise_model: 3-D noise in SLAM units (may be robust).

    Not modelled: a rotation between the SLAM and world axes, jerk and bias change over ``dt``.
    """
    z = as_vector(slam_t_meas, 3, "slam_t_meas")
    terms = _offset_terms(
        as_vector(body_t_cam, 3, "body_t_cam"), dt, body_accel, body_omega, gravity
    )
    return _offset_factor(
        _axis_offset,
        vector_at,
        (pose_key, vel_key, alignment_key),
        z,
        terms,
        noise_model,
    )


def make_slam_relative_factor(
    pose_i_key: int,
    pose_j_key: int,
    sim_key: int,
    slam_t_cam_i: np.ndarray,
    slam_t_cam_j: np.ndarray,
    body_T_cam: gtsam.Pose3 | np.ndarray,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """Relative SLAM displacement factor on ``(X_i, X_j, S)`` (3-D; see module docstring).

    The noise is that of a difference of two SLAM positions (``sqrt(2)`` times one position's sigma
    for independent errors; less when SLAM errors are correlated over short intervals).
    """
    z_i = as_vector(slam_t_cam_i, 3, "slam_t_cam_i")
    z_j = as_vector(slam_t_cam_j, 3, "slam_t_cam_j")
    body_T_cam = as_pose_matrix(body_T_cam, "body_T_cam")
    variables = ((pose_i_key, pose_at), (pose_j_key, pose_at), (sim_key, similarity3_at))
    constants = (z_i, z_j, body_T_cam)
    return custom_factor(noise_model, ERROR_DIM, variables, slam_relative_error, constants)


def make_slam_rotation_factor(
    pose_key: int,
    sim_key: int,
    slam_R_cam_meas: np.ndarray,
    body_T_cam: gtsam.Pose3 | np.ndarray,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """SLAM orientation factor on ``(X, S)`` (3-D, [rad]; see module docstring).

    Args:
        slam_R_cam_meas: (3, 3) camera orientation reported by SLAM.
        body_T_cam: camera pose in the body frame; its rotation is used.
        noise_model: 3-D noise [rad] on the rotation error expressed in the camera frame.
    """
    z = np.asarray(slam_R_cam_meas, dtype=float)
    if z.shape != (3, 3) or not all(map(math.isfinite, z.ravel().tolist())):
        raise ValueError(f"slam_R_cam_meas: expected a finite 3x3 rotation, got shape {z.shape}")
    z = gtsam.Rot3(z).matrix()
    body_R_cam = as_pose_matrix(body_T_cam, "body_T_cam")[:3, :3]
    variables = ((pose_key, pose_matrix_at), (sim_key, similarity3_at))
    return custom_factor(
        noise_model,
        ERROR_DIM,
        variables,
        _slam_rotation,
        (z.T, body_R_cam),
        lazy=True,
        record=True,
    )
