"""Frame conversions from logging conventions into fgnav's frames, in one tested place.

fgnav's frames (../shared/DESIGN.md section 2): world z up, x/y level (ENU-like, gravity
``(0, 0, -g)``); body x forward, y left, z up (FLU). Quaternions are Hamilton ``[w, x, y, z]``.

Conventions converted here:

* **PX4 / aerospace** (NED world, FRD body). Positions and velocities: ``x_enu = y_ned``,
  ``y_enu = x_ned``, ``z_enu = -z_ned`` (the matrix ``ENU_R_NED``, a half turn about
  ``(1, 1, 0)/sqrt(2)``, its own inverse). Body vectors (gyro, accelerometer, body velocity):
  ``FLU = (x, -y, -z)`` of FRD (``FLU_R_FRD``, a half turn about x). Orientation::

      world_R_body(ENU <- FLU) = ENU_R_NED @ ned_R_frd @ FRD_R_FLU

  so PX4 yaw 0 (nose north) becomes fgnav yaw +pi/2 (the body x axis points along world +y =
  north), and PX4 yaw +90 deg (east, clockwise seen from above) becomes fgnav yaw 0.
  The same matrices convert any z-down world (e.g. PX4's ``FRD`` world frame of
  ``vehicle_odometry``, whose x is an arbitrary heading): the result is a z-up right-handed
  world whose yaw origin is rotated the same way.
* **Y-up motion capture** (OptiTrack Motive's default: X, Y up, Z, right-handed). Both the mocap
  world and the rigid body's local axes are Y-up; ``ZUP_R_YUP`` (a quarter turn about x) maps
  ``(X, Y, Z) -> (X, -Z, Y)``. Orientation: ``world_R_rb(z-up) = ZUP_R_YUP @ R_yup @ ZUP_R_YUP^T``
  (both frames converted). The rigid body's axes are whatever Motive was given at creation; the
  fixed rotation to the vehicle's FLU body is a calibration (see :func:`align_rotation_sequences`).
  Lengths in mm are converted with :data:`MM_TO_M`.
* **A different body frame, same origin** (e.g. EuRoC's IMU frame to a FLU multirotor body):
  :func:`rotate_body_frame` rotates every body-frame quantity of a flight consistently.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .errors import FlightDataError
from .geometry import GRAVITY, matrix_to_quat_wxyz, project_to_so3, quat_wxyz_to_matrix, so3_exp
from .types import DOWNWARD_RANGE, Flight, Trajectory

#: Rotation taking NED vectors to ENU (symmetric: also ``NED_R_ENU``).
ENU_R_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: Rotation taking FRD body vectors to FLU (symmetric: also ``FRD_R_FLU``).
FLU_R_FRD = np.diag([1.0, -1.0, -1.0])
FRD_R_FLU = FLU_R_FRD
#: Rotation taking Y-up mocap vectors ``(X, Y, Z)`` to z-up ``(X, -Z, Y)``.
ZUP_R_YUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
#: Millimetres to metres.
MM_TO_M = 1e-3


def ned_to_enu(ned_v: np.ndarray) -> np.ndarray:
    """World vectors (positions [m], velocities [m/s]) NED (..., 3) -> ENU-like z-up (..., 3)."""
    v = np.asarray(ned_v, dtype=float)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


def frd_to_flu(frd_v: np.ndarray) -> np.ndarray:
    """Body vectors (angular rate, specific force, body velocity) FRD (..., 3) -> FLU (..., 3)."""
    v = np.asarray(frd_v, dtype=float)
    return np.stack([v[..., 0], -v[..., 1], -v[..., 2]], axis=-1)


def ned_R_frd_to_world_R_body(ned_R_frd: np.ndarray) -> np.ndarray:
    """Orientation matrices ``ned_R_frd`` (..., 3, 3) -> fgnav ``world_R_body`` (ENU <- FLU)."""
    R = np.asarray(ned_R_frd, dtype=float)
    return ENU_R_NED @ R @ FRD_R_FLU


def ned_q_frd_to_world_q_body(ned_q_frd_wxyz: np.ndarray) -> np.ndarray:
    """PX4 attitude quaternions ``[w, x, y, z]`` (..., 4) rotating FRD into NED -> fgnav
    ``world_q_body_wxyz`` (FLU into ENU), with ``w >= 0``."""
    R = quat_wxyz_to_matrix(ned_q_frd_wxyz)
    return matrix_to_quat_wxyz(ned_R_frd_to_world_R_body(R))


def yup_to_zup(yup_v: np.ndarray) -> np.ndarray:
    """World vectors of a Y-up mocap frame (..., 3) -> z-up ``(X, -Z, Y)`` (same unit)."""
    v = np.asarray(yup_v, dtype=float)
    return np.stack([v[..., 0], -v[..., 2], v[..., 1]], axis=-1)


def yup_q_to_zup_q(yup_q_rb_wxyz: np.ndarray) -> np.ndarray:
    """Mocap rigid-body quaternions ``[w, x, y, z]`` (..., 4) with Y-up world and Y-up body axes ->
    z-up world and z-up body axes (``ZUP_R_YUP @ R @ ZUP_R_YUP^T``), with ``w >= 0``."""
    R = quat_wxyz_to_matrix(yup_q_rb_wxyz)
    return matrix_to_quat_wxyz(ZUP_R_YUP @ R @ ZUP_R_YUP.T)


def tilt_angle(world_R_body: np.ndarray) -> np.ndarray:
    """Angle [rad] between the body z axis and the world z axis (..., 3, 3) -> (...,)."""
    R = np.asarray(world_R_body, dtype=float)
    return np.arccos(np.clip(R[..., 2, 2], -1.0, 1.0))


def _small_rotation_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of a stack of rotations with angles well below pi (residuals)."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    w = 0.5 * np.stack(
        [R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1
    )
    sin = np.sin(angle)
    scale = np.where(sin > 1e-9, angle / np.where(sin > 1e-9, sin, 1.0), 1.0)
    return w * scale[:, None]


def _project_to_yaw(M: np.ndarray) -> np.ndarray:
    """Rotation about z maximising ``trace(Rz^T M)``."""
    yaw = np.arctan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1])
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def align_rotation_sequences(
    a_R_x: np.ndarray,
    b_R_y: np.ndarray,
    iterations: int = 100,
    tol: float = 1e-12,
    world_yaw_only: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fixed frame rotations that best align two attitude sources of one rigid motion.

    Two systems observe the same body: source A gives ``a_R_x(t)`` (world a, body frame x),
    source B gives ``b_R_y(t)`` (world b, body frame y). With fixed ``a_R_b`` and ``y_R_x``::

        a_R_x(t) ~= a_R_b @ b_R_y(t) @ y_R_x

    Both are found by alternating orthogonal Procrustes steps minimising the Frobenius residual
    (equivalently the chordal distance) summed over samples, then polished by Gauss-Newton on
    the geodesic residuals. Needs rotation about at least two
    axes to be unique; when the motion keeps one heading (a straight flight), a world tilt and a
    body tilt trade off, and ``world_yaw_only=True`` (both worlds z up, so ``a_R_b`` is a rotation
    about z) removes that ambiguity.

    Args:
        a_R_x: (N, 3, 3) attitude from source A.
        b_R_y: (N, 3, 3) attitude from source B at the same times.
        iterations: maximum alternations.
        tol: stop when the cost changes less than this.
        world_yaw_only: restrict ``a_R_b`` to a rotation about z.

    Returns:
        ``(a_R_b, y_R_x, residual_angle)``: the two fixed rotations and the (N,) residual angle
        [rad] of each sample after alignment.
    """
    A = np.asarray(a_R_x, dtype=float)
    B = np.asarray(b_R_y, dtype=float)
    a_R_b = np.eye(3)
    y_R_x = np.eye(3)
    last = np.inf
    for _ in range(iterations):
        # a_R_b = argmax tr(a_R_b^T sum A (B y_R_x)^T)
        M = np.einsum("nij,nkj->ik", A, B @ y_R_x)
        a_R_b = _project_to_yaw(M) if world_yaw_only else project_to_so3(M)
        # y_R_x = argmax tr(y_R_x^T sum (a_R_b B)^T A)
        y_R_x = project_to_so3(np.einsum("nji,njk->ik", a_R_b @ B, A))
        cost = float(np.sum((A - a_R_b @ B @ y_R_x) ** 2))
        if abs(last - cost) < tol:
            break
        last = cost
    # Gauss-Newton polish: alternation crawls along weakly determined directions (e.g. world yaw
    # vs body yaw on a single-heading motion). Residual r_n = log(A_n^T a_R_b B_n y_R_x); right
    # perturbations give dr/d(theta_y) = I and dr/d(theta_a) = (B_n y_R_x)^T (first order).
    a_cols = np.array([[0.0], [0.0], [1.0]]) if world_yaw_only else np.eye(3)
    for _ in range(iterations):
        E = np.swapaxes(A, -1, -2) @ a_R_b @ B @ y_R_x
        r = _small_rotation_log(E)
        J_a = np.swapaxes(B @ y_R_x, -1, -2) @ a_cols
        J = np.concatenate([J_a, np.broadcast_to(np.eye(3), (len(E), 3, 3))], axis=2)
        step = np.linalg.lstsq(J.reshape(-1, J.shape[2]), -r.reshape(-1), rcond=None)[0]
        a_R_b = a_R_b @ so3_exp(a_cols @ step[: a_cols.shape[1]])
        y_R_x = y_R_x @ so3_exp(step[a_cols.shape[1] :])
        if np.linalg.norm(step) < 1e-12:
            break
    E = np.swapaxes(A, -1, -2) @ (a_R_b @ B @ y_R_x)
    cos = np.clip((np.trace(E, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return a_R_b, y_R_x, np.arccos(cos)


def rotate_body_frame(flight: Flight, new_R_old: np.ndarray) -> Flight:
    """Re-express a flight in a new body frame with the same origin, ``v_new = new_R_old @ v_old``.

    Rotated: IMU angular rate and specific force, ``attitude`` (``world_R_new = world_R_old @
    new_R_old^T``), ground truth and ``references`` (orientation as attitude; ``gyro_bias`` and
    ``accel_bias`` as body vectors; positions and ``world_v_body`` are world vectors of the same
    point and stay), ``calib.body_T_cam`` (``new_T_cam = [new_R_old, 0] @ old_T_cam``) and
    ``calib.body_T_range`` when the flight has a range stream or a ``body_T_range`` other than the
    ``DOWNWARD_RANGE`` default (which only says "looking down the body z axis" and so stays).
    Untouched: SLAM camera poses, images, range values, metadata. References are taken to be
    body trajectories like the ground truth.

    Raises:
        FlightDataError: ``new_R_old`` is not a proper rotation, or the flight has a ``yaw`` stream
            (a yaw angle of the old body x axis cannot be converted without roll and pitch).
    """
    R = np.asarray(new_R_old, dtype=float)
    if (
        R.shape != (3, 3)
        or not np.all(np.isfinite(R))
        or np.abs(R @ R.T - np.eye(3)).max() > 1e-9
        or np.linalg.det(R) < 0
    ):
        raise FlightDataError(f"body rotation: expected a proper 3x3 rotation, got {R.tolist()}")
    if flight.yaw is not None:
        raise FlightDataError(
            f"{flight.name}: cannot rotate the body frame of a flight with a yaw stream (the yaw "
            "of the old body x axis needs roll and pitch to convert)"
        )

    def vec(v: np.ndarray | None) -> np.ndarray | None:
        return None if v is None else np.asarray(v, dtype=float) @ R.T

    def quat(q: np.ndarray) -> np.ndarray:
        return matrix_to_quat_wxyz(quat_wxyz_to_matrix(q) @ R.T)

    def traj(tr: Trajectory | None) -> Trajectory | None:
        if tr is None:
            return None
        return replace(
            tr,
            world_q_body_wxyz=quat(tr.world_q_body_wxyz),
            gyro_bias=vec(tr.gyro_bias),
            accel_bias=vec(tr.accel_bias),
        )

    T = np.eye(4)
    T[:3, :3] = R
    calib = replace(flight.calib, body_T_cam=T @ np.asarray(flight.calib.body_T_cam, dtype=float))
    if flight.range is not None or not np.array_equal(calib.body_T_range, DOWNWARD_RANGE):
        calib = replace(calib, body_T_range=T @ np.asarray(calib.body_T_range, dtype=float))
    imu = flight.imu
    if imu is not None:
        imu = replace(imu, body_omega=vec(imu.body_omega), body_accel=vec(imu.body_accel))
    att = flight.attitude
    if att is not None:
        att = replace(att, world_q_body_wxyz=quat(att.world_q_body_wxyz))
    return replace(
        flight,
        imu=imu,
        attitude=att,
        ground_truth=traj(flight.ground_truth),
        references={k: traj(v) for k, v in flight.references.items()},
        calib=calib,
    )


#: Largest angle [deg] between body z and the thrust axis for a flight's body to count as a
#: multirotor (FLU-like) body.
MAX_THRUST_TILT_DEG = 30.0


def thrust_axis(flight: Flight) -> np.ndarray:
    """Unit rotor-thrust axis in the flight's body frame: ``meta["thrust_axis_body"]`` when the
    reader knows it (EuRoC: the mean specific force in flight, see ``fgnav.datasets.euroc``),
    else the mean direction of the specific force over the IMU samples within 20 % of g
    (hover-like: the thrust balances gravity)."""
    axis = flight.meta.get("thrust_axis_body") if isinstance(flight.meta, dict) else None
    if axis is not None:
        a = np.asarray(axis, dtype=float).reshape(3)
    else:
        if flight.imu is None or len(flight.imu) == 0:
            raise FlightDataError(f"{flight.name}: no IMU to find the thrust axis from")
        f = np.asarray(flight.imu.body_accel, float)
        n = np.linalg.norm(f, axis=1)
        ok = np.abs(n - GRAVITY) < 0.2 * GRAVITY
        if not ok.any():
            raise FlightDataError(
                f"{flight.name}: no IMU sample with a specific force near g: no thrust axis"
            )
        a = (f[ok] / n[ok, None]).mean(axis=0)
    return a / np.linalg.norm(a)


def thrust_body_rotation(
    flight: Flight, max_tilt_deg: float = MAX_THRUST_TILT_DEG
) -> np.ndarray | None:
    """``thrust_R_body`` of a body with z along :func:`thrust_axis` and x along the camera's
    optical axis projected orthogonal to it (else the body axis farthest from z), or None when the
    flight's body z is already within ``max_tilt_deg`` of the thrust axis or the flight has neither
    an IMU nor a recorded thrust axis (its users then name the missing stream). For filters whose
    models need a multirotor body (Euler angles near level, thrust along z): run them on
    ``rotate_body_frame(flight, R)`` and map the estimate back."""
    meta = flight.meta if isinstance(flight.meta, dict) else {}
    if "thrust_axis_body" not in meta and (flight.imu is None or len(flight.imu) == 0):
        return None
    z = thrust_axis(flight)
    if math.degrees(math.acos(float(np.clip(z[2], -1.0, 1.0)))) <= max_tilt_deg:
        return None
    x = np.asarray(flight.calib.body_T_cam, float)[:3, 2]
    if abs(float(x @ z)) > 0.9:
        x = np.eye(3)[int(np.argmin(np.abs(z)))]
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    return np.vstack([x, np.cross(z, x), z])
