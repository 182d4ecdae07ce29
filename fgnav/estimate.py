"""The result type shared by the smoothers and every filter baseline.

An :class:`Estimate` is what ``fgnav batch``, ``fgnav online`` and each baseline return, and what
``fgnav.eval`` scores. Covariances follow GTSAM's Pose3 tangent order ``[rotation, translation]``
in the body frame (right perturbation ``world_T_body * Exp(xi)``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fgnav.datasets import Trajectory
from fgnav.datasets.errors import FlightDataError

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class TimeSeries:
    """A scalar or vector quantity over time (SLAM scale, drag k, ground height ...).

    Attributes:
        t: (N,) time [s].
        value: (N,) or (N, D) values.
        sigma: optional standard deviations, same shape as ``value``.
    """

    t: np.ndarray
    value: np.ndarray
    sigma: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Estimate:
    """Output of an estimator over one flight.

    Attributes:
        method: name of the method (``"batch"``, ``"fixed-lag"``, ``"msf-ekf"`` ...).
        trajectory: body states at the estimator's output times (pose, optional velocity and
            biases) in fgnav's world frame (z up).
        pose_cov: optional (N, 6, 6) marginal covariance of each pose, Pose3 tangent order
            ``[rot, trans]`` in body frame.
        vel_cov: optional (N, 3, 3) covariance of ``world_v_body``.
        slam_scale: SLAM scale ``s`` (SLAM units per metre) per SLAM session id, final value.
        slam_scale_sigma: its standard deviation per session, when known.
        drag_k: final drag coefficient(s) [1/s] (1 or 2 values), or None.
        drag_k_sigma: standard deviation of ``drag_k``, or None.
        ground_height: final ground height [m] under the rangefinder, or None.
        series: quantities over time for plots, e.g. ``{"slam_scale": TimeSeries, "drag_k": ...}``.
        update_latency: optional (M,) wall time of each update [s] (online methods).
        runtime_s: total wall time of the run [s].
        causal: True when each state only used measurements up to its time (filters, the
            fixed-lag smoother's newest state); False for smoothers' full-window estimates.
        info: free diagnostics: options used, counts (solver failures, rejected measurements).
    """

    method: str
    trajectory: Trajectory
    pose_cov: np.ndarray | None = None
    vel_cov: np.ndarray | None = None
    slam_scale: dict[int, float] = field(default_factory=dict)
    slam_scale_sigma: dict[int, float] = field(default_factory=dict)
    drag_k: np.ndarray | None = None
    drag_k_sigma: np.ndarray | None = None
    ground_height: float | None = None
    series: dict[str, TimeSeries] = field(default_factory=dict)
    update_latency: np.ndarray | None = None
    runtime_s: float = 0.0
    causal: bool = False
    info: dict[str, Any] = field(default_factory=dict)

    def check(self) -> Estimate:
        self.trajectory.check(f"estimate[{self.method}].trajectory")
        n = len(self.trajectory)
        if self.pose_cov is not None and self.pose_cov.shape != (n, 6, 6):
            raise FlightDataError(
                f"estimate[{self.method}].pose_cov: expected ({n}, 6, 6), got {self.pose_cov.shape}"
            )
        if self.vel_cov is not None and self.vel_cov.shape != (n, 3, 3):
            raise FlightDataError(
                f"estimate[{self.method}].vel_cov: expected ({n}, 3, 3), got {self.vel_cov.shape}"
            )
        return self


@dataclass(frozen=True, eq=False)
class OnlineState:
    """The newest state of an online estimator (see ``/README.md``'s online section for the frames).

    What ``feed`` / ``latest`` of the push-API smoother (``fgnav.solvers.online``) and of the
    live filters (``fgnav.live.estimators``) return, and what the live link sends.

    Attributes:
        t: state time [s] on the input clock (a keyframe time for the smoother).
        world_T_body: (4, 4) pose, world z up, body FLU.
        world_v_body: (3,) velocity in world [m/s].
        accel_bias, gyro_bias: (3,) IMU biases [m/s^2], [rad/s].
        pose_cov: (6, 6) marginal covariance, GTSAM Pose3 tangent ``[rot, trans]`` in body frame
            (right perturbation), or None when not computed.
        vel_cov: (3, 3) covariance of ``world_v_body``, or None.
        slam_scale: SLAM units per metre per session (sessions with an alignment).
        drag_k: drag coefficient(s) [1/s], or None.
        ground_height: ground height under the rangefinder [m], or None.
        reset_counter: resets and rebuilds that lost state so far.
        quality: 0-100. The smoother: 0 before initialisation, 30 with the IMU alone, 60 on a
            provisional SLAM alignment, 100 with an aligned session or range and yaw; halved
            for 2 s after a solver failure or reset. A filter: from its position covariance
            (``fgnav.live.estimators.QUALITY_SIGMA_M``).
    """

    t: float
    world_T_body: np.ndarray
    world_v_body: np.ndarray
    accel_bias: np.ndarray
    gyro_bias: np.ndarray
    pose_cov: np.ndarray | None
    vel_cov: np.ndarray | None
    slam_scale: dict[int, float] = field(default_factory=dict)
    drag_k: np.ndarray | None = None
    ground_height: float | None = None
    reset_counter: int = 0
    quality: int = 0


def estimate_in_body(est: Estimate, int_R_body: np.ndarray) -> Estimate:
    """An estimate made in an internal body frame (``v_int = int_R_body @ v_body``, same origin;
    e.g. :func:`fgnav.datasets.frames.thrust_body_rotation`) re-expressed in the flight's body:
    orientation ``world_R_body = world_R_int @ int_R_body``, biases and pose covariance rotated.
    Positions and world velocities are unchanged. ``info["internal_body_R_body"]`` records it."""
    import dataclasses

    from fgnav.datasets.geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix

    tr = est.trajectory
    R = quat_wxyz_to_matrix(tr.world_q_body_wxyz) @ int_R_body
    back = np.asarray(int_R_body, float).T  # body_R_int
    traj = dataclasses.replace(
        tr,
        world_q_body_wxyz=matrix_to_quat_wxyz(R),
        gyro_bias=None if tr.gyro_bias is None else tr.gyro_bias @ back.T,
        accel_bias=None if tr.accel_bias is None else tr.accel_bias @ back.T,
    )
    D = np.zeros((6, 6))
    D[:3, :3] = D[3:, 3:] = back
    pose_cov = None if est.pose_cov is None else D @ est.pose_cov @ D.T
    info = {**est.info, "internal_body_R_body": np.asarray(int_R_body, float).tolist()}
    return dataclasses.replace(est, trajectory=traj, pose_cov=pose_cov, info=info).check()


def run_in_thrust_body(
    flight: Any, run: Callable[[Any], Estimate], max_tilt_deg: float | None = None
) -> Estimate:
    """``run(flight)`` for a filter whose model needs a multirotor body (z along the rotor thrust,
    Euler angles near level): when the flight's body is not one
    (:func:`fgnav.datasets.frames.thrust_body_rotation`), run it on the flight re-expressed in
    such a body (references dropped) and map the estimate back with :func:`estimate_in_body`."""
    import dataclasses

    from fgnav.datasets.frames import MAX_THRUST_TILT_DEG, rotate_body_frame, thrust_body_rotation

    tilt = MAX_THRUST_TILT_DEG if max_tilt_deg is None else max_tilt_deg
    thrust_R_body = thrust_body_rotation(flight, tilt)
    if thrust_R_body is None:
        return run(flight)
    logger.info("%s: run in a body with z along the rotor thrust axis", flight.name)
    inner = rotate_body_frame(dataclasses.replace(flight, references={}), thrust_R_body)
    return estimate_in_body(run(inner), thrust_R_body)
