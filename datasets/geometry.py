"""Small rotation and pose helpers in numpy (no GTSAM here).

Conventions (see ../shared/DESIGN.md section 2): quaternions are Hamilton, unit, stored
``[w, x, y, z]`` (``*_wxyz``); ``a_R_b`` maps vectors from frame b into frame a; a pose ``a_T_b`` is
a 4x4 homogeneous matrix. All functions accept a single item or a stack along the first axis.
"""

from __future__ import annotations

import math

import numpy as np

GRAVITY = 9.81
"""Gravity magnitude [m/s^2] used everywhere in fgnav (world gravity is ``(0, 0, -GRAVITY)``):
GTSAM's ``PreintegrationParams.MakeSharedU()`` default and the simulator's value, so that
simulated specific force, IMU preintegration and every filter agree."""


def quat_wxyz_to_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) ``[w, x, y, z]`` (..., 4) -> rotation matrix(es) (..., 3, 3).

    The quaternion is normalised first; a zero quaternion raises ``ValueError``.
    """
    q = np.asarray(q_wxyz, dtype=float)
    if q.shape == (4,):
        # One quaternion (the online smoother's SLAM poses and attitude samples): the same
        # operations on Python floats (IEEE doubles either way: the same bits), without
        # numpy's per-call overhead on nine 0-d slices (about 5x faster, 2026-12-07). The norm
        # too: numpy's sum of the four squares adds them in order from 0.0 (fewer than eight
        # terms: no pairwise split), as written here.
        w, x, y, z = q.tolist()
        n = math.sqrt(w * w + x * x + y * y + z * z)
        if n == 0.0:
            raise ValueError("zero-norm quaternion")
        w, x, y, z = w / n, x / n, y / n, z / n
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n == 0.0):
        raise ValueError("zero-norm quaternion")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix(es) (..., 3, 3) -> unit quaternion(s) ``[w, x, y, z]`` with w >= 0."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for i, m in enumerate(flat):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        if tr > 0:
            s = 2.0 * np.sqrt(tr + 1.0)
            q = [
                0.25 * s,
                (m[2, 1] - m[1, 2]) / s,
                (m[0, 2] - m[2, 0]) / s,
                (m[1, 0] - m[0, 1]) / s,
            ]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [
                (m[2, 1] - m[1, 2]) / s,
                0.25 * s,
                (m[0, 1] + m[1, 0]) / s,
                (m[0, 2] + m[2, 0]) / s,
            ]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q = [
                (m[0, 2] - m[2, 0]) / s,
                (m[0, 1] + m[1, 0]) / s,
                0.25 * s,
                (m[1, 2] + m[2, 1]) / s,
            ]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q = [
                (m[1, 0] - m[0, 1]) / s,
                (m[0, 2] + m[2, 0]) / s,
                (m[1, 2] + m[2, 1]) / s,
                0.25 * s,
            ]
        q = np.asarray(q)
        q /= np.linalg.norm(q)
        out[i] = q if q[0] >= 0 else -q
    return out.reshape(R.shape[:-2] + (4,))


def quat_xyzw_to_wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    """Reorder ``[x, y, z, w]`` (TUM, ROS, Eigen coeffs) -> ``[w, x, y, z]``."""
    q = np.asarray(q_xyzw, dtype=float)
    return np.concatenate([q[..., 3:4], q[..., 0:3]], axis=-1)


def quat_wxyz_to_xyzw(q_wxyz: np.ndarray) -> np.ndarray:
    """Reorder ``[w, x, y, z]`` -> ``[x, y, z, w]`` (TUM, ROS)."""
    q = np.asarray(q_wxyz, dtype=float)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


def quat_multiply_wxyz(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of ``[w, x, y, z]`` quaternions (broadcasting)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def skew(v: np.ndarray) -> np.ndarray:
    """3-vector -> 3x3 skew-symmetric matrix ``[v]x`` with ``skew(a) @ b == cross(a, b)``."""
    x, y, z = np.asarray(v, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rotation vector(s) (..., 3) -> rotation matrix(es) (..., 3, 3) (Rodrigues).

    Near zero the coefficients use their Taylor series, so small rotations stay exact to
    double precision.
    """
    phi = np.asarray(phi, dtype=float)
    angle = np.linalg.norm(phi, axis=-1)
    small = angle < 1e-4
    safe = np.where(small, 1.0, angle)
    a2 = angle * angle
    c1 = np.where(small, 1.0 - a2 / 6.0, np.sin(safe) / safe)
    c2 = np.where(small, 0.5 - a2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    K = np.zeros(phi.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -z, y, -x
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = z, -y, x
    return np.eye(3) + c1[..., None, None] * K + c2[..., None, None] * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrix(es) (..., 3, 3) -> rotation vector(s) (..., 3), angle in [0, pi]."""
    R = np.asarray(R, dtype=float)
    cos_angle = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos_angle)
    w = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    small = angle < 1e-8
    f = np.where(small, 0.5, angle / (2.0 * np.sin(np.where(small, 1.0, angle))))
    out = f[..., None] * w
    near_pi = np.pi - angle < 1e-6
    if np.any(near_pi):
        # Near pi: axis from the largest diagonal element of (R + I) / 2, sign from w.
        flat_R, flat_out = R.reshape(-1, 3, 3), out.reshape(-1, 3)
        for i in np.flatnonzero(near_pi.reshape(-1)):
            B = (flat_R[i] + np.eye(3)) / 2.0
            j = int(np.argmax(np.diag(B)))
            axis = B[:, j] / np.linalg.norm(B[:, j])
            flat_out[i] = float(np.arccos(np.clip((np.trace(flat_R[i]) - 1) / 2, -1, 1))) * axis
        out = flat_out.reshape(out.shape)
    return out


def ordered_product(R: np.ndarray) -> np.ndarray:
    """``R[0] @ R[1] @ ... @ R[-1]`` of a stack (N, 3, 3) by pairwise batched products (identity
    for N = 0)."""
    if len(R) == 0:
        return np.eye(3)
    while len(R) > 1:
        if len(R) % 2:
            R = np.concatenate([R, np.eye(3)[None]])
        R = R[0::2] @ R[1::2]
    return R[0]


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to a 3x3 matrix: SVD projection onto SO(3) (orthogonal
    Procrustes)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rotation_mean(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (N, 3, 3): SVD projection of their sum onto SO(3)."""
    return project_to_so3(np.sum(np.asarray(Rs, dtype=float), axis=0))


def slerp_rotations(t_src: np.ndarray, world_R_body: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Interpolate rotations (N, 3, 3) given at increasing ``t_src`` to ``t_query`` (geodesic
    between neighbours; held at the ends)."""
    t_query = np.clip(np.asarray(t_query, dtype=float), t_src[0], t_src[-1])
    if len(t_src) == 1:
        return np.broadcast_to(world_R_body[0], (len(t_query), 3, 3)).copy()
    j = np.clip(np.searchsorted(t_src, t_query, side="right") - 1, 0, len(t_src) - 2)
    a = (t_query - t_src[j]) / (t_src[j + 1] - t_src[j])
    Ri = world_R_body[j]
    rel = so3_log(np.transpose(Ri, (0, 2, 1)) @ world_R_body[j + 1])
    return Ri @ so3_exp(a[:, None] * rel)


def slerp_wxyz(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of (N, 4) unit quaternions ``[w, x, y, z]`` at ``u``.

    The shorter arc is taken (``q1`` is sign-flipped when ``q0 . q1 < 0``).
    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    u = np.asarray(u, dtype=float)[:, None]
    dot = np.sum(q0 * q1, axis=1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.clip(np.abs(dot), 0.0, 1.0)
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    small = sin_theta < 1e-9
    safe = np.where(small, 1.0, sin_theta)
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * theta) / safe)
    w1 = np.where(small, u, np.sin(u * theta) / safe)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def interpolate_quat_wxyz(t: np.ndarray, q_wxyz: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Normalised linear interpolation of unit quaternions (sign-aligned), clamped at the ends.

    Args:
        t: (N,) sample times [s], increasing.
        q_wxyz: (N, 4) quaternions ``[w, x, y, z]``.
        t_query: (M,) query times [s].

    Returns:
        (M, 4) unit quaternions.
    """
    q = np.array(q_wxyz, dtype=float)
    flip = np.sum(q[1:] * q[:-1], axis=1) < 0
    sign = np.concatenate([[1.0], np.cumprod(np.where(flip, -1.0, 1.0))])
    q *= sign[:, None]
    out = np.stack([np.interp(t_query, t, q[:, i]) for i in range(4)], axis=1)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def nlerp_quat_wxyz(t0: float, q0: np.ndarray, t1: float, q1: np.ndarray, t: float) -> np.ndarray:
    """Normalised linear interpolation of two unit quaternions ``[w, x, y, z]`` (sign-aligned)
    at ``t`` (one query: :func:`interpolate_quat_wxyz` for arrays)."""
    if q0 @ q1 < 0:
        q1 = -q1
    a = (t - t0) / (t1 - t0) if t1 > t0 else 0.0
    q = q0 + a * (q1 - q0)
    return q / np.linalg.norm(q)


def yaw_of(world_R_body: np.ndarray) -> np.ndarray:
    """Yaw (rad, (-pi, pi]) of rotation matrix(es): heading of the body x axis in the world x-y
    plane (ZYX Euler convention, z up)."""
    R = np.asarray(world_R_body, dtype=float)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angle(s) to (-pi, pi]."""
    if type(a) is float:
        # A Python float (the online smoother's yaw readings): Python's float ``%`` is numpy's
        # ``mod`` (C ``fmod`` with the result moved to the divisor's sign: the same bits) at
        # a tenth of the cost; returned as numpy's 0-d result, as for any other input.
        w = (a + math.pi) % (2.0 * math.pi) - math.pi
        return np.array(math.pi if w == -math.pi else w)
    a = np.asarray(a, dtype=float)
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def rpy_to_matrix(roll, pitch, yaw) -> np.ndarray:
    """ZYX Euler angles (rad; scalars or arrays that broadcast) -> ``Rz(yaw) Ry(pitch) Rx(roll)``
    of shape (..., 3, 3)."""
    roll, pitch, yaw = np.broadcast_arrays(*(np.asarray(v, float) for v in (roll, pitch, yaw)))
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    R = np.empty(roll.shape + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def matrix_to_rpy(world_R_body: np.ndarray) -> np.ndarray:
    """ZYX ``(roll, pitch, yaw)`` [rad] (..., 3) of rotation matrix(es) (..., 3, 3)."""
    R = np.asarray(world_R_body, dtype=float)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = -np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) and translation (3,) -> 4x4 homogeneous pose."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_pose(a_T_b: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid pose: ``b_T_a``."""
    R = a_T_b[:3, :3]
    t = a_T_b[:3, 3]
    return make_pose(R.T, -R.T @ t)


def velocity_from_positions(
    t: np.ndarray, p: np.ndarray, window_s: float = 0.1, rate_hz: float = 300.0
) -> np.ndarray:
    """Smoothed first derivative of positions sampled at (possibly irregular) times ``t``.

    The positions are linearly resampled on a uniform ``rate_hz`` grid, differentiated with a
    centred Savitzky-Golay filter (quadratic, ``window_s`` long: no lag, quantisation noise
    averaged) and interpolated back at ``t``. For motion-capture positions quantised to 1 mm at a
    few hundred Hz, where a plain finite difference is dominated by the quantisation.

    Args:
        t: (N,) increasing times [s].
        p: (N, D) positions.
        window_s: filter window [s].
        rate_hz: resampling rate [Hz].

    Returns:
        (N, D) velocities [units of p per second]; ``np.gradient`` when the series is shorter
        than one window. Pieces between gaps longer than ``VELOCITY_MAX_GAP_S`` are
        differentiated apart (resampled across a log's clock jump of 1e6 s, the grid took
        15 GB); a lone sample's velocity is 0.
    """
    t = np.asarray(t, dtype=float)
    p = np.asarray(p, dtype=float)
    cuts = np.flatnonzero(np.diff(t) > VELOCITY_MAX_GAP_S) + 1 if t.size > 1 else []
    if len(cuts):
        return np.concatenate(
            [
                _velocity_piece(tp, pp, window_s, rate_hz)
                for tp, pp in zip(np.split(t, cuts), np.split(p, cuts), strict=True)
            ]
        )
    return _velocity_piece(t, p, window_s, rate_hz)


#: :func:`velocity_from_positions` differentiates the pieces between longer gaps apart [s].
VELOCITY_MAX_GAP_S = 1.0


def _velocity_piece(t: np.ndarray, p: np.ndarray, window_s: float, rate_hz: float) -> np.ndarray:
    from scipy.signal import savgol_filter

    window = int(round(window_s * rate_hz)) | 1
    tu = np.arange(t[0], t[-1], 1.0 / rate_hz) if t.size > 1 else t
    if tu.size < window:
        return np.gradient(p, t, axis=0) if t.size > 1 else np.zeros_like(p)
    pu = np.column_stack([np.interp(tu, t, p[:, i]) for i in range(p.shape[1])])
    vu = savgol_filter(pu, window, 2, deriv=1, delta=1.0 / rate_hz, axis=0, mode="interp")
    return np.column_stack([np.interp(t, tu, vu[:, i]) for i in range(p.shape[1])])
