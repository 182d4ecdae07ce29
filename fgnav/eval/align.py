"""Alignment of an estimated trajectory to ground truth, and time association of the two.

Alignment (Umeyama 1991, "Least-squares estimation of transformation parameters between two point
patterns", IEEE PAMI 13(4); the same closed form as evo's ``umeyama_alignment``) finds the
transform ``gt_xyz ~ s * R @ est_xyz + t`` that minimises the summed squared position error:

- ``"se3"``: rotation + translation (metric estimates);
- ``"sim3"``: rotation + translation + scale (raw monocular SLAM);
- ``"4dof"``: yaw about world z + translation (visual-inertial estimates, whose roll and pitch are
  observable from gravity and must not be corrected by the alignment);
- ``"none"``: identity.

The transform maps the estimate's world frame into the ground truth's world frame (both z up).
Applied to a trajectory it maps positions ``s R p + t``, orientations ``R world_R_body`` and
velocities ``s R v``.

Association interpolates ground truth at the estimate's times (linear in position and velocity,
slerp in orientation) and reports every estimate sample it could not match.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import matrix_to_quat_wxyz, slerp_wxyz
from fgnav.datasets.types import Trajectory

logger = logging.getLogger(__name__)

AlignMode = Literal["se3", "sim3", "4dof", "none"]
ALIGN_MODES: tuple[str, ...] = ("se3", "sim3", "4dof", "none")
#: Mode reported when SE(3)/Sim(3) is undetermined (points on a line): centroids aligned only.
DEGENERATE_MODE = "translation (degenerate geometry)"

#: How each mode is written for a user (any other mode, e.g. the degenerate fall-back, as is).
MODE_LABELS = {"se3": "SE(3)", "sim3": "Sim(3)", "4dof": "4-DoF", "none": "no"}


def mode_label(mode: str) -> str:
    """``"SE(3)"``, ``"Sim(3)"``, ``"4-DoF"``, ``"no"`` or the mode itself (the degenerate
    geometry's translation-only fall-back)."""
    return MODE_LABELS.get(mode, mode)


#: Default largest time gap [s] of ground truth across which it is interpolated. Motion-capture
#: ground truth runs at 100-200 Hz (EuRoC 200 Hz); a gap above 0.1 s means missing data.
DEFAULT_MAX_GT_GAP_S = 0.1


@dataclass(frozen=True)
class Alignment:
    """A similarity ``x_gt = s * R @ x_est + t`` from the estimate's world into the truth's world.

    Attributes:
        R: (3, 3) rotation ``gtworld_R_estworld``.
        t: (3,) translation [m, truth's world frame].
        s: scale (metres of truth per unit of the estimate); 1 unless ``mode == "sim3"``.
        mode: ``"se3"``, ``"sim3"``, ``"4dof"`` or ``"none"``.
    """

    R: np.ndarray
    t: np.ndarray
    s: float
    mode: str

    @staticmethod
    def identity() -> Alignment:
        return Alignment(np.eye(3), np.zeros(3), 1.0, "none")

    @property
    def matrix(self) -> np.ndarray:
        """4x4 similarity matrix ``[[s R, t], [0, 1]]``."""
        T = np.eye(4)
        T[:3, :3] = self.s * self.R
        T[:3, 3] = self.t
        return T

    def apply_positions(self, xyz: np.ndarray) -> np.ndarray:
        """Map (N, 3) positions of the estimate's world into the truth's world."""
        return self.s * np.asarray(xyz, dtype=float) @ self.R.T + self.t

    def apply_rotations(self, world_R_body: np.ndarray) -> np.ndarray:
        """Map (N, 3, 3) orientations: ``R @ world_R_body`` (scale does not act on rotations)."""
        return np.einsum("ij,njk->nik", self.R, np.asarray(world_R_body, dtype=float))

    def apply_velocities(self, world_v_body: np.ndarray) -> np.ndarray:
        """Map (N, 3) velocities: ``s R v``."""
        return self.s * np.asarray(world_v_body, dtype=float) @ self.R.T

    def apply(self, traj: Trajectory) -> Trajectory:
        """The trajectory in the truth's world (positions, orientations, velocities; biases are
        body-frame quantities and stay unchanged)."""
        q = matrix_to_quat_wxyz(self.apply_rotations(traj.world_R_body()))
        v = None if traj.world_v_body is None else self.apply_velocities(traj.world_v_body)
        return Trajectory(
            t=traj.t,
            world_t_body=self.apply_positions(traj.world_t_body),
            world_q_body_wxyz=q,
            world_v_body=v,
            gyro_bias=traj.gyro_bias,
            accel_bias=traj.accel_bias,
        )


def _check_pair(est_xyz: np.ndarray, gt_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(est_xyz, dtype=float)
    y = np.asarray(gt_xyz, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape != y.shape:
        raise FlightDataError(
            f"align: expected two (N, 3) position arrays of equal shape, got {x.shape} and "
            f"{y.shape}"
        )
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise FlightDataError("align: positions contain non-finite values")
    return x, y


def umeyama(
    est_xyz: np.ndarray, gt_xyz: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Umeyama's closed form: ``(R, t, s)`` minimising ``sum |gt - (s R est + t)|^2``.

    Args:
        est_xyz: (N, 3) estimated positions (estimate's world frame).
        gt_xyz: (N, 3) matching true positions (truth's world frame) [m].
        with_scale: also estimate the scale ``s`` (Sim(3)); otherwise ``s = 1`` (SE(3)).

    Returns:
        ``R`` (3, 3), ``t`` (3,), ``s``.

    Raises:
        FlightDataError: fewer than 3 points, or the points are (nearly) collinear.
    """
    x, y = _check_pair(est_xyz, gt_xyz)
    n = x.shape[0]
    if n < 3:
        raise FlightDataError(f"align: Umeyama needs at least 3 position pairs, got {n}")
    mean_x = x.mean(axis=0)
    mean_y = y.mean(axis=0)
    xc = x - mean_x
    yc = y - mean_y
    sigma_x = float(np.sum(xc * xc)) / n
    cov_xy = yc.T @ xc / n
    u, d, vt = np.linalg.svd(cov_xy)
    if np.count_nonzero(d > np.finfo(float).eps * max(1.0, d[0])) < 2:
        raise FlightDataError(
            "align: degenerate point set (all positions on a line or a point); the rotation "
            "is not determined"
        )
    S = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        S[2, 2] = -1.0
    R = u @ S @ vt
    s = float(np.trace(np.diag(d) @ S) / sigma_x) if with_scale else 1.0
    t = mean_y - s * R @ mean_x
    return R, t, s


def align_4dof(est_xyz: np.ndarray, gt_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Yaw about world z and translation minimising ``sum |gt - (Rz(yaw) est + t)|^2``.

    Closed form: with centred points, ``yaw = atan2(sum (x_i cross y_i)_z, sum x_i.y_i)`` over the
    horizontal components (the vertical components only fix ``t_z``).

    Returns:
        ``R`` (3, 3) rotation about z, ``t`` (3,).
    """
    x, y = _check_pair(est_xyz, gt_xyz)
    if x.shape[0] < 2:
        raise FlightDataError(
            f"align: 4-DoF alignment needs at least 2 positions, got {x.shape[0]}"
        )
    mean_x = x.mean(axis=0)
    mean_y = y.mean(axis=0)
    xc = x - mean_x
    yc = y - mean_y
    cross = float(np.sum(xc[:, 0] * yc[:, 1] - xc[:, 1] * yc[:, 0]))
    dot = float(np.sum(xc[:, 0] * yc[:, 0] + xc[:, 1] * yc[:, 1]))
    if abs(cross) + abs(dot) <= np.finfo(float).eps:
        raise FlightDataError("align: 4-DoF yaw undetermined (no horizontal motion)")
    yaw = np.arctan2(cross, dot)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = mean_y - R @ mean_x
    return R, t


def align_rotations(est_R: np.ndarray, gt_R: np.ndarray, mode: str = "se3") -> np.ndarray:
    """The constant rotation ``R`` of the estimate's world that best maps its orientations onto
    the true ones, ``gt_R_i ~ R est_R_i`` (chordal L2: the rotation nearest ``sum gt_R_i
    est_R_i^T``): about world z only for ``"4dof"``, the identity for ``"none"``.

    For the orientation metrics (yaw RMSE, pose NEES): the rotation fitted to the positions is
    set by their noise where the trajectory is small (simulated hover, fixed-lag: the position
    fit turned the yaw by 12.8 deg, reported as the yaw RMSE of an estimate whose yaw was within
    0.3 deg)."""
    A = np.asarray(gt_R, float)
    B = np.asarray(est_R, float)
    if A.shape != B.shape or A.ndim != 3 or A.shape[1:] != (3, 3) or A.shape[0] < 1:
        raise FlightDataError(
            f"align_rotations: expected two (N, 3, 3) stacks of one shape, got {A.shape} and "
            f"{B.shape}"
        )
    if mode == "none":
        return np.eye(3)
    M = np.einsum("nij,nkj->ik", A, B)
    if mode == "4dof":
        yaw = math.atan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1])
        c, s = math.cos(yaw), math.sin(yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    u, _, vt = np.linalg.svd(M)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def align(est_xyz: np.ndarray, gt_xyz: np.ndarray, mode: str = "se3") -> Alignment:
    """Align estimated positions to true positions.

    Args:
        est_xyz: (N, 3) estimated positions, estimate's world frame.
        gt_xyz: (N, 3) true positions at the same times, truth's world frame [m].
        mode: ``"se3"``, ``"sim3"``, ``"4dof"`` (yaw + translation) or ``"none"``.

    Returns:
        The :class:`Alignment` ``gt ~ s R est + t``.
    """
    if mode not in ALIGN_MODES:
        raise FlightDataError(f"align: unknown mode {mode!r}, expected one of {ALIGN_MODES}")
    if mode == "none":
        _check_pair(est_xyz, gt_xyz)
        return Alignment.identity()
    if mode == "4dof":
        R, t = align_4dof(est_xyz, gt_xyz)
        return Alignment(R, t, 1.0, mode)
    try:
        R, t, s = umeyama(est_xyz, gt_xyz, with_scale=(mode == "sim3"))
    except FlightDataError as e:
        if "degenerate" not in str(e):
            raise
        # A straight-line trajectory (e.g. a purely vertical flight) leaves the rotation about the
        # line undetermined: align the centroids only, and say so in the mode.
        est, gt = _check_pair(est_xyz, gt_xyz)
        logger.warning("align: %s; %s falls back to translation only", e, mode)
        return Alignment(np.eye(3), gt.mean(axis=0) - est.mean(axis=0), 1.0, DEGENERATE_MODE)
    return Alignment(R, t, s, mode)


# ----------------------------------------------------------------------------------------------
# Time association
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Association:
    """Estimate samples matched to ground truth interpolated at their times.

    Attributes:
        est_index: (M,) indices of the matched estimate samples (increasing).
        gt: ground truth interpolated at ``est.t[est_index]`` (M samples; velocity and biases
            interpolated too when the truth has them).
        n_before: estimate samples before the truth's first time.
        n_after: estimate samples after the truth's last time.
        n_gap: estimate samples inside the truth's span but in a gap of the truth longer than
            ``max_gap_s``.
    """

    est_index: np.ndarray
    gt: Trajectory
    n_before: int
    n_after: int
    n_gap: int

    @property
    def n_matched(self) -> int:
        return int(self.est_index.size)

    @property
    def n_unmatched(self) -> int:
        return self.n_before + self.n_after + self.n_gap


def interpolate_trajectory(traj: Trajectory, t: np.ndarray) -> Trajectory:
    """``traj`` at times ``t`` (all inside its span): linear in position, velocity and biases,
    slerp in orientation."""
    t = np.asarray(t, dtype=float)
    if t.size and (t[0] < traj.t[0] or t[-1] > traj.t[-1]):
        raise FlightDataError(
            f"interpolate_trajectory: times [{t[0]}, {t[-1]}] leave the span "
            f"[{traj.t[0]}, {traj.t[-1]}]"
        )
    j = np.clip(np.searchsorted(traj.t, t, side="right") - 1, 0, max(len(traj) - 2, 0))
    if len(traj) == 1:
        u = np.zeros_like(t)
        j1 = j
    else:
        j1 = j + 1
        u = (t - traj.t[j]) / (traj.t[j1] - traj.t[j])

    def lin(a: np.ndarray | None) -> np.ndarray | None:
        if a is None:
            return None
        return a[j] + (a[j1] - a[j]) * u[:, None]

    return Trajectory(
        t=t,
        world_t_body=lin(traj.world_t_body),
        world_q_body_wxyz=slerp_wxyz(traj.world_q_body_wxyz[j], traj.world_q_body_wxyz[j1], u),
        world_v_body=lin(traj.world_v_body),
        gyro_bias=lin(traj.gyro_bias),
        accel_bias=lin(traj.accel_bias),
    )


def associate(
    est: Trajectory, gt: Trajectory, max_gap_s: float = DEFAULT_MAX_GT_GAP_S, log: bool = True
) -> Association:
    """Match each estimate sample to ground truth interpolated at its time.

    An estimate sample at time ``t`` is matched when ``gt.t[0] <= t <= gt.t[-1]`` and the two
    truth samples around ``t`` are at most ``max_gap_s`` apart (a sample exactly at a truth time
    always matches). Unmatched samples are counted by reason and logged, never silently dropped.

    Args:
        est: estimated trajectory.
        gt: ground truth (same clock) [s].
        max_gap_s: largest truth gap [s] to interpolate across.
        log: warn about unmatched samples (off where the same pair was associated and logged
            before).

    Returns:
        The :class:`Association`.
    """
    est.check("associate.est")
    gt.check("associate.gt")
    t = est.t
    before = t < gt.t[0]
    after = t > gt.t[-1]
    inside = ~before & ~after
    ti = t[inside]
    j = np.searchsorted(gt.t, ti, side="left")
    exact = (j < len(gt)) & (gt.t[np.minimum(j, len(gt) - 1)] == ti)
    jl = np.clip(j - 1, 0, len(gt) - 1)
    jr = np.clip(j, 0, len(gt) - 1)
    gap = (gt.t[jr] - gt.t[jl]) > max_gap_s
    ok_inside = exact | ~gap
    idx_inside = np.flatnonzero(inside)
    est_index = idx_inside[ok_inside]
    n_before, n_after = int(before.sum()), int(after.sum())
    n_gap = int((~ok_inside).sum())
    if log and (n_before or n_after or n_gap):
        # Samples before or after the truth's span are common (a mocap started late, stopped
        # early; the commands' "scored:" line states the span): a warning for truth gaps only.
        logger.log(
            logging.WARNING if n_gap else logging.INFO,
            "associate: %d of %d estimate samples unmatched (%d before the truth, %d after, "
            "%d in truth gaps > %.3f s)",
            n_before + n_after + n_gap,
            len(est),
            n_before,
            n_after,
            n_gap,
            max_gap_s,
        )
    if est_index.size == 0:
        raise FlightDataError(
            f"associate: no estimate sample lies inside the ground truth's span "
            f"[{gt.t[0]:.3f}, {gt.t[-1]:.3f}] s (estimate spans [{t[0]:.3f}, {t[-1]:.3f}] s): "
            f"are the two on the same clock?"
        )
    return Association(
        est_index=est_index,
        gt=interpolate_trajectory(gt, t[est_index]),
        n_before=n_before,
        n_after=n_after,
        n_gap=n_gap,
    )
