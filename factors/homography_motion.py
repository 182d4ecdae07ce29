"""Downward-camera homography motion factors: two views of the ground plane ``z = ground``.

Measurement model (seed 002 sec. II-B3 and Algorithm 2; Hartley & Zisserman, "Multiple View
Geometry", ch. 13, plane-induced homography). Cameras ``world_T_cam_i`` and ``world_T_cam_j`` with
``world_T_cam = world_T_body body_T_cam`` (camera x right, y down, z forward). With
``(R, t) = cam_j_T_cam_i`` (points map as ``X_j = R X_i + t``), the unit plane normal
``n = -cam_i_R_world e_z`` in cam i (world down: it points from the camera towards the ground)
and the height of camera i above the plane ``d = world_t_cam_i,z - ground`` [m], every ground
point satisfies ``n^T X_i = d`` and::

    X_j = (R + t n^T / d) X_i
        = world_R_cam_j^T (I - (world_t_cam_i - world_t_cam_j) e_z^T / d) world_R_cam_i X_i
    H_ji = K (R + t n^T / d) K^-1          pixels of image i -> pixels of image j (up to scale)

``make_homography_factor`` (keys ``X_i, X_j, G``; 8-D, [px]): residual = transfer error of the four
image corners (pixel centres ``(0, 0), (W-1, 0), (W-1, H-1), (0, H-1)`` of image i)::

    e = pi(H_pred c_k) - pi(H_meas c_k),   k = 1..4,   pi([x, y, w]) = [x / w, y / w]

which is independent of the scale of ``H_meas`` and has none of the four-fold ambiguity of a
decomposition. Zero when the measured homography maps the corners where the predicted one does.

``make_homography_decomposed_factor`` (keys ``X_i, X_j, G``; 6-D): seed 002 Algorithm 2's
decomposed measurement ``(cam_j_R_cam_i, t / d)`` (e.g. ``cv2.decomposeHomographyMat`` with the
solution whose normal is closest to the predicted ``n``), residual
``[Log(R_meas^T R_pred) [rad], t_pred / d_pred - (t / d)_meas [-]]``.

The metric translation comes from ``d``, i.e. from the ground height ``G`` and the pose heights that
the rangefinder constrains: the papers' "double coupling" as one graph.

Jacobians: analytic, by forward-mode differentiation of ``H`` along each of the 13 local coordinates
(``[omega_i, v_i, omega_j, v_j, ground]``, right perturbation of the body poses), then through the
projection of the corners (``e_D_pose_i`` 8x6, ``e_D_pose_j`` 8x6, ``e_D_ground`` 8x1).

Noise: corner transfer sigma [px] from the homography fit (a few tenths of a pixel for hundreds of
tracked corners; grows with extrapolation to the corners). Robust kernels are recommended: a wrong
RANSAC model moves all four corners at once.

Not modelled: lens distortion (undistort the tracks first), non-planar or sloped ground, rolling
shutter, the time offset between camera and IMU. ``d`` is floored at ``MIN_CAMERA_HEIGHT`` during
optimisation (an iterate below the ground would divide by ~0); a predicted corner behind camera j
(``w <= 0``) makes the residual meaningless, which only happens for motions far beyond one frame.
"""

from __future__ import annotations

import gtsam
import numpy as np
from fgnav.factors._jacobians import (
    as_pose_matrix,
    custom_factor,
    pose_at,
    pose_parts,
    skew,
    so3_log,
    so3_right_jacobian_inv,
    vector_at,
)

ERROR_DIM = 8
DECOMPOSED_ERROR_DIM = 6

#: Floor on the height of camera i above the ground inside the factors [m]: far below any flight
#: altitude at which a downward camera resolves the ground, well above zero.
MIN_CAMERA_HEIGHT = 0.01

_E_Z = np.array([0.0, 0.0, 1.0])
_GENERATORS = np.stack([skew(e) for e in np.eye(3)])  # [e_k]x, k = 0..2


def image_corners(image_size: tuple[int, int]) -> np.ndarray:
    """(4, 3) homogeneous pixel centres of the corners of a ``(width, height)`` image."""
    w, h = image_size
    if w < 2 or h < 2:
        raise ValueError(f"image_size: expected (width, height) >= 2 px, got {image_size}")
    return np.array(
        [[0.0, 0.0, 1.0], [w - 1.0, 0.0, 1.0], [w - 1.0, h - 1.0, 1.0], [0.0, h - 1.0, 1.0]]
    )


class _TwoViewGeometry:
    """``H_e = R + t n^T / d`` of two body poses over the ground, with its derivatives (13, ...)
    along ``[omega_i, v_i, omega_j, v_j, ground]``."""

    def __init__(
        self,
        world_T_body_i: gtsam.Pose3,
        world_T_body_j: gtsam.Pose3,
        ground: float,
        body_T_cam: np.ndarray,
    ) -> None:
        Ri, ti = pose_parts(world_T_body_i)
        Rj, tj = pose_parts(world_T_body_j)
        Rc, lc = pose_parts(body_T_cam)
        self.Ra, self.ta = Ri @ Rc, ti + Ri @ lc
        self.Rb, self.tb = Rj @ Rc, tj + Rj @ lc
        self.d_raw = self.ta[2] - ground
        self.d = max(self.d_raw, MIN_CAMERA_HEIGHT)
        self.D = self.ta - self.tb

        dRa = np.zeros((13, 3, 3))
        dRb = np.zeros((13, 3, 3))
        dta = np.zeros((13, 3))
        dtb = np.zeros((13, 3))
        dRa[0:3] = Ri @ _GENERATORS @ Rc
        dta[0:3] = (-Ri @ skew(lc)).T
        dta[3:6] = Ri.T
        dRb[6:9] = Rj @ _GENERATORS @ Rc
        dtb[6:9] = (-Rj @ skew(lc)).T
        dtb[9:12] = Rj.T
        dground = np.zeros(13)
        dground[12] = 1.0
        self.dRa, self.dRb = dRa, dRb
        self.dD = dta - dtb
        self.dd = dta[:, 2] - dground
        if self.d_raw < MIN_CAMERA_HEIGHT:
            self.dd = np.zeros(13)

    def euclidean_homography(self) -> tuple[np.ndarray, np.ndarray]:
        """``H_e`` (3, 3) and ``dH_e`` (13, 3, 3)."""
        M = np.eye(3) - np.outer(self.D, _E_Z) / self.d
        dM = -self.dD[:, :, None] * _E_Z[None, None, :] / self.d
        dM += np.outer(self.D, _E_Z)[None] * (self.dd / self.d**2)[:, None, None]
        RbT = self.Rb.T
        H = RbT @ M @ self.Ra
        dH = (
            np.transpose(self.dRb, (0, 2, 1)) @ (M @ self.Ra)
            + RbT @ dM @ self.Ra
            + (RbT @ M) @ self.dRa
        )
        return H, dH

    def rotation_and_scaled_translation(
        self,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``R = cam_j_R_cam_i``, ``dR`` (13, 3, 3), ``u = t / d`` (3,), ``du`` (13, 3)."""
        RbT = self.Rb.T
        R = RbT @ self.Ra
        dR = np.transpose(self.dRb, (0, 2, 1)) @ self.Ra + RbT @ self.dRa
        t = RbT @ self.D
        dt = np.einsum("mji,j->mi", self.dRb, self.D) + self.dD @ self.Rb
        u = t / self.d
        du = dt / self.d - np.outer(self.dd, t) / self.d**2
        return R, dR, u, du


def predicted_homography(
    world_T_body_i: gtsam.Pose3,
    world_T_body_j: gtsam.Pose3,
    ground: float,
    K: np.ndarray,
    body_T_cam: gtsam.Pose3 | np.ndarray,
) -> np.ndarray:
    """Pixel homography image i -> image j (``H[2, 2] = 1``) predicted from the state.

    Args:
        world_T_body_i, world_T_body_j: body poses at the two frames.
        ground: world z of the ground plane [m].
        K: (3, 3) camera matrix [px].
        body_T_cam: camera pose in the body frame.
    """
    geo = _TwoViewGeometry(
        world_T_body_i, world_T_body_j, ground, as_pose_matrix(body_T_cam, "body_T_cam")
    )
    H_e, _ = geo.euclidean_homography()
    H = K @ H_e @ np.linalg.inv(K)
    return H / H[2, 2]


def homography_error(
    world_T_body_i: gtsam.Pose3,
    world_T_body_j: gtsam.Pose3,
    ground: np.ndarray,
    measured_corners_j: np.ndarray,
    K: np.ndarray,
    body_T_cam: np.ndarray,
    corners_i: np.ndarray,
    K_inv: np.ndarray | None = None,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Corner-transfer residual of the homography model.

    Args:
        world_T_body_i, world_T_body_j: body poses at frames i and j.
        ground: (1,) world z of the ground plane [m].
        measured_corners_j: (4, 2) ``pi(H_meas c_k)`` [px] (see ``transfer_corners``).
        K: (3, 3) camera matrix [px].
        body_T_cam: 4x4 camera pose in the body frame.
        corners_i: (4, 3) homogeneous corner pixels of image i (``image_corners``).
        K_inv: inverse of ``K`` if already computed (saves an inversion per call).

    Returns:
        ``(e (8,) [px], [e_D_pose_i (8x6), e_D_pose_j (8x6), e_D_ground (8x1)])``, ``e`` ordered
        ``[x1, y1, x2, y2, x3, y3, x4, y4]``.
    """
    geo = _TwoViewGeometry(world_T_body_i, world_T_body_j, float(np.ravel(ground)[0]), body_T_cam)
    H_e, dH_e = geo.euclidean_homography()
    rays = corners_i @ (np.linalg.inv(K) if K_inv is None else K_inv).T  # (4, 3) K^-1 c_k
    q = (rays @ H_e.T) @ K.T  # (4, 3) K H_e K^-1 c_k
    dq = np.einsum("mab,kb->mka", dH_e, rays) @ K.T  # (13, 4, 3)
    w = q[:, 2]
    x = q[:, :2] / w[:, None]
    dx = (dq[..., :2] - x[None] * dq[..., 2:3]) / w[None, :, None]  # (13, 4, 2)
    e = (x - measured_corners_j).ravel()
    J = dx.reshape(13, ERROR_DIM).T
    return e, [J[:, 0:6], J[:, 6:12], J[:, 12:13]]


def transfer_corners(H: np.ndarray, corners_i: np.ndarray) -> np.ndarray:
    """(4, 2) pixels ``pi(H c_k)`` of the homogeneous corners ``corners_i`` (4, 3)."""
    q = corners_i @ np.asarray(H, dtype=float).T
    if np.any(np.abs(q[:, 2]) < 1e-12 * np.max(np.abs(q))):
        raise ValueError("homography maps an image corner to infinity")
    return q[:, :2] / q[:, 2:3]


def make_homography_factor(
    pose_i_key: int,
    pose_j_key: int,
    ground_key: int,
    H_meas: np.ndarray,
    K: np.ndarray,
    body_T_cam: gtsam.Pose3 | np.ndarray,
    image_size: tuple[int, int],
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """Corner-transfer homography factor on ``(X_i, X_j, G: Vector1)`` (8-D, [px]).

    Args:
        H_meas: (3, 3) measured homography mapping pixels of image i to image j (any scale).
        K: (3, 3) camera matrix [px] of the (undistorted) images.
        body_T_cam: camera pose in the body frame (Pose3 or 4x4).
        image_size: ``(width, height)`` [px].
        noise_model: 8-D noise [px] (may be robust).
    """
    H_meas = np.asarray(H_meas, dtype=float)
    if H_meas.shape != (3, 3) or not np.all(np.isfinite(H_meas)):
        raise ValueError(f"H_meas: expected a finite 3x3 matrix, got shape {H_meas.shape}")
    K = _check_K(K)
    body_T_cam = as_pose_matrix(body_T_cam, "body_T_cam")
    K_inv = np.linalg.inv(K)
    corners_i = image_corners(image_size)
    measured = transfer_corners(H_meas, corners_i)
    variables = ((pose_i_key, pose_at), (pose_j_key, pose_at), (ground_key, vector_at))
    constants = (measured, K, body_T_cam, corners_i, K_inv)
    return custom_factor(noise_model, ERROR_DIM, variables, homography_error, constants)


def homography_decomposed_error(
    world_T_body_i: gtsam.Pose3,
    world_T_body_j: gtsam.Pose3,
    ground: np.ndarray,
    cam_j_R_cam_i_meas: np.ndarray,
    t_over_d_meas: np.ndarray,
    body_T_cam: np.ndarray,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Residual of the decomposed homography ``(R, t / d)`` (seed 002 Algorithm 2).

    Args:
        cam_j_R_cam_i_meas: (3, 3) measured rotation ``R`` of ``X_j = R X_i + t``.
        t_over_d_meas: (3,) measured ``t / d`` (cam j axes, in units of the height of camera i).

    Returns:
        ``(e (6,), [e_D_pose_i (6x6), e_D_pose_j (6x6), e_D_ground (6x1)])``, ``e = [rotation
        error (3) [rad], t / d error (3) [-]]``.
    """
    geo = _TwoViewGeometry(world_T_body_i, world_T_body_j, float(np.ravel(ground)[0]), body_T_cam)
    R, dR, u, du = geo.rotation_and_scaled_translation()
    e_rot = so3_log(cam_j_R_cam_i_meas.T @ R)
    # d(Log(R_meas^T R)) = Jr^-1 vee(R^T dR) to first order.
    omega = R.T @ dR  # (13, 3, 3), skew-symmetric to first order
    vee = np.stack([omega[:, 2, 1], omega[:, 0, 2], omega[:, 1, 0]], axis=1)
    J = np.empty((DECOMPOSED_ERROR_DIM, 13))
    J[:3] = so3_right_jacobian_inv(e_rot) @ vee.T
    J[3:] = du.T
    e = np.concatenate([e_rot, u - t_over_d_meas])
    return e, [J[:, 0:6], J[:, 6:12], J[:, 12:13]]


def make_homography_decomposed_factor(
    pose_i_key: int,
    pose_j_key: int,
    ground_key: int,
    cam_j_R_cam_i_meas: np.ndarray,
    t_over_d_meas: np.ndarray,
    body_T_cam: gtsam.Pose3 | np.ndarray,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """Decomposed-homography factor on ``(X_i, X_j, G: Vector1)`` (6-D; see module docstring).

    Args:
        cam_j_R_cam_i_meas: (3, 3) measured inter-frame rotation.
        t_over_d_meas: (3,) measured translation divided by the height of camera i (OpenCV's
            ``decomposeHomographyMat`` translation for ``H = K (R + t n^T) K^-1``).
        body_T_cam: camera pose in the body frame.
        noise_model: 6-D noise: rotation [rad] then ``t / d`` [-].
    """
    R_meas = np.asarray(cam_j_R_cam_i_meas, dtype=float)
    if R_meas.shape != (3, 3) or not np.all(np.isfinite(R_meas)):
        raise ValueError(f"cam_j_R_cam_i_meas: expected a finite 3x3 rotation, got {R_meas.shape}")
    R_meas = gtsam.Rot3(R_meas).matrix()
    u_meas = np.asarray(t_over_d_meas, dtype=float).ravel()
    if u_meas.shape != (3,) or not np.all(np.isfinite(u_meas)):
        raise ValueError(f"t_over_d_meas: expected 3 finite values, got {np.shape(t_over_d_meas)}")
    body_T_cam = as_pose_matrix(body_T_cam, "body_T_cam")
    variables = ((pose_i_key, pose_at), (pose_j_key, pose_at), (ground_key, vector_at))
    return custom_factor(
        noise_model,
        DECOMPOSED_ERROR_DIM,
        variables,
        homography_decomposed_error,
        (R_meas, u_meas, body_T_cam),
    )


def _check_K(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K: expected a 3x3 camera matrix with positive focal lengths, got {K}")
    return K
