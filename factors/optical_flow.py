"""Downward optical-flow sensor over flat ground: integrated image motion from velocity and height.

Measurement model (fgnav's flow convention, ``fgnav.datasets.types.FlowSeries``; DESIGN.md 4.6)::

    l = body_t_flow, A = body_R_flow^T                 lever arm [m], body -> sensor rotation
    u = world_R_body^T world_v_body + omega x l        velocity of the sensor in body axes [m/s]
    v = A u,  w = A omega                              sensor-frame velocity [m/s], rate [rad/s]
    h = world_t_body_z + (world_R_body l)_z - ground   height of the sensor above ground [m]
    c = -(world_R_body body_R_flow e_z)_z              cos(tilt) of the optical axis (sensor +z)
    d = h / c                                          distance to the ground along the axis [m]
    flow = ppr * dt * [-v_x / d - w_y,  -v_y / d + w_x] + n          [px]

``ppr`` is the sensor's pixels per radian of image motion (``Calibration.flow_pixels_per_rad``;
1 for a sensor that reports integrated radians, as PX4's ``sensor_optical_flow``), ``dt`` the
integration interval [s]. ``flow`` is the image motion of the ground point on the optical axis:
motion along the axis moves that point nowhere, so the translational part is exactly
``v_xy * cos(tilt) / h`` for a flat horizontal ground.

Angular rate: ``omega`` [rad/s] (body FLU) is a **measured input**, the mean gyro over the
sample's interval minus the gyro bias known when the factor is made (the builder's initial bias);
it is not a key. A remaining gyro-bias error ``db`` [rad/s] shows as a velocity error of
``d * db`` (0.5 m * 0.005 rad/s = 2.5 mm/s).

Keys: ``X`` Pose3 ``world_T_body``, ``V`` ``world_v_body`` [m/s] (Vector3), ``G`` ground height
(Vector1) [m], shared with the tilted rangefinder (``tilted_range.py``), which fixes it.

Residual (2,): unwhitened ``h(x) - z`` [px]; zero when the measured flow equals the prediction
above at the state (consistent state: flow simulated from the same pose, velocity and ground).

Jacobians (right perturbation ``[delta, dt]`` of the pose, see ``_jacobians``), with ``q = c/h``
the inverse distance and ``T = -ppr dt [v_x, v_y] q`` the translational part:
``du/ddelta = [u_R]x`` (``u_R = world_R_body^T world_v_body``), ``du/dV = world_R_body^T``,
``dh/ddelta = -(world_R_body [l]x)_z``, ``dh/ddt = world_R_body_z``, ``dh/dG = -1``,
``dc/ddelta = (world_R_body [a]x)_z`` with ``a = body_R_flow e_z``, ``dq = dc/h - c dh/h^2``;
``dT = -ppr dt (A_xy du q + v_xy dq)``.

Noise: sensor sigma [px] per sample (PMW3901 on a Crazyflie: about 0.2 px per 10 ms sample at
48 px/rad, README of ``crazyflie_util_flowdeck``); consecutive samples are negatively correlated
(lag-1 about -0.3), which the graph handles by summing the samples of a keyframe interval into
one measurement (``measurement.dt`` and ``flow`` are then sums; see ``flow_sum_sigma``).
During optimisation ``h`` is floored at ``MIN_HEIGHT`` and ``c`` at ``MIN_COS_TILT`` (zero
Jacobian of a floored value); readings are gated far above both (``gate_flow``).

Not modelled: sloped or rough ground, the field of view (points off the axis see another depth
when tilted; the sensor averages over about 42 deg), lens distortion, the change of velocity,
attitude and rate within the interval (the state at one time stands for the interval), the
sensor's time offset, scale error of ``ppr`` and texture-dependent dropouts (gated by quality).

References and differences:

- Crazyflie firmware, ``kalman_core/mm_flow.c``: ``predictedNX = (dt Npix / thetapix)
  (v_body_x R[2][2] / z - omega_y)``, ``predictedNY = (dt Npix / thetapix)(v_body_y R[2][2] / z +
  omega_x)`` with ``Npix = 35``, ``thetapix = 4.2 deg``, two scalar updates, raw gyro. Same
  small-angle model; its count axes are the flow deck's rotated and negated axes (the reader maps
  them to ours). Differences: the firmware's state velocity is in body axes, ``z`` is the
  position (flat floor at z = 0 assumed, floored at 0.1 m), no lever arm, no ground variable, no
  sensor-frame rotation, a fixed per-count noise, no robust kernel. Here the height is relative to
  an estimated ground ``G``, the lever arm and ``body_T_flow`` enter, and the sensor noise respects
  the correlation of consecutive samples.
- PX4 EKF2 flow fusion (``optflow_fusion``/``EKF2_OF_*``): integrated radians compensated for body
  rotation with the gyro (or the sensor's own gyro) before fusion, predicted as rotation rates
  about the sensor axes from the body-frame velocity at the sensor (``EKF2_OF_POS_X/Y/Z`` lever
  arm) over the range ``(h - terrain) / R_z,z``; terrain is an EKF state (here ``G``). PX4 expresses
  flow as rates about x and y (a 90 deg rotation of our image-motion axes), scales noise between
  ``EKF2_OF_N_MIN`` and ``EKF2_OF_N_MAX`` by quality, gates on ``EKF2_OF_QMIN``, the range-aid
  height and an innovation test. Here rotation is compensated inside the model (same equations)
  and outliers are down-weighted by a Huber kernel instead of rejected.
"""

from __future__ import annotations

from typing import NamedTuple

import gtsam
import numpy as np
from fgnav.factors._jacobians import (
    as_pose_matrix,
    as_vector,
    custom_factor,
    pose_matrix,
    pose_matrix_at,
    pose_parts,
    scalar_at,
    skew,
    vector_at,
)

# Floor on cos(tilt) of the optical axis inside the factor: the rangefinder's, cos(85 deg).
from fgnav.factors.tilted_range import MIN_COS_TILT

ERROR_DIM = 2

#: Floor on the sensor height inside the factor [m]: readings are gated far above it (a flow
#: sensor focuses from about 8 cm); it only protects optimiser iterates from a division by ~0.
MIN_HEIGHT = 0.02

_E_Z = np.array([0.0, 0.0, 1.0])


class FlowMeasurement(NamedTuple):
    """One (possibly summed) flow reading.

    Attributes:
        flow: (2,) integrated image motion in the sensor's x, y [px] (``FlowSeries`` convention).
        dt: integration interval [s] (sum of the intervals of summed samples).
    """

    flow: np.ndarray
    dt: float


class FlowSensor(NamedTuple):
    """Calibration of the flow sensor.

    Attributes:
        body_T_flow: 4x4 pose of the sensor in the body (optical axis = sensor +z).
        pixels_per_rad: flow units per radian of image motion (1.0 for radians).
    """

    body_T_flow: np.ndarray
    pixels_per_rad: float


def optical_flow_error(
    world_T_body: gtsam.Pose3,
    world_v_body: np.ndarray,
    ground: np.ndarray,
    body_omega: np.ndarray,
    measurement: FlowMeasurement,
    calib: FlowSensor,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Residual and Jacobians of the optical-flow model.

    Args:
        world_T_body: body pose in the world (z up).
        world_v_body: (3,) body velocity in world axes [m/s].
        ground: (1,) world z of the ground plane [m].
        body_omega: (3,) mean bias-corrected body rate over the interval [rad/s] (measured input).
        measurement: flow [px] and interval [s].
        calib: ``body_T_flow`` and pixels per radian.

    Returns:
        ``(e (2,), [e_D_pose (2x6), e_D_vel (2x3), e_D_ground (2x1)])`` [px].
    """
    m = as_pose_matrix(calib.body_T_flow, "body_T_flow")
    body_R_flow, body_t_flow = pose_parts(m)
    e, jac = _optical_flow(
        pose_matrix(world_T_body),
        np.asarray(world_v_body, float),
        float(np.asarray(ground).ravel()[0]),
        np.asarray(measurement.flow, float),
        float(measurement.dt),
        np.asarray(body_omega, float),
        body_R_flow,
        np.array(body_t_flow),
        float(calib.pixels_per_rad),
        True,
    )
    return e, jac


def _optical_flow(
    m: np.ndarray,
    world_v_body: np.ndarray,
    ground: float,
    flow: np.ndarray,
    dt: float,
    body_omega: np.ndarray,
    body_R_flow: np.ndarray,
    body_t_flow: np.ndarray,
    pixels_per_rad: float,
    with_jacobians: bool,
) -> tuple[np.ndarray, list[np.ndarray] | None]:
    """``optical_flow_error`` on a 4x4 ``world_T_body`` ``m`` (the factor's callback)."""
    world_R_body = m[:3, :3]
    Rz = world_R_body[2]
    A = body_R_flow.T
    u_rot = world_R_body.T @ world_v_body
    u = u_rot + np.cross(body_omega, body_t_flow)
    v = A @ u
    w = A @ body_omega
    axis = body_R_flow @ _E_Z
    c = -(Rz @ axis)
    c_floored = c < MIN_COS_TILT
    if c_floored:
        c = MIN_COS_TILT
    h = m[2, 3] + Rz @ body_t_flow - ground
    h_floored = h < MIN_HEIGHT
    if h_floored:
        h = MIN_HEIGHT
    q = c / h
    s = pixels_per_rad * dt
    pred = s * np.array([-v[0] * q - w[1], -v[1] * q + w[0]])
    e = pred - flow
    if not with_jacobians:
        return e, None
    # Derivatives of u (3), h and c with respect to the pose [delta, dt], velocity and ground.
    u_D_delta = skew(u_rot)
    h_D_pose = np.zeros(6)
    if not h_floored:
        h_D_pose[:3] = -(Rz @ skew(body_t_flow))
        h_D_pose[3:] = Rz
    c_D_pose = np.zeros(6)
    if not c_floored:
        c_D_pose[:3] = Rz @ skew(axis)
    q_D_pose = c_D_pose / h - c * h_D_pose / h**2
    q_D_ground = 0.0 if h_floored else c / h**2
    Axy = A[:2]
    e_D_pose = np.zeros((2, 6))
    e_D_pose[:, :3] = -s * q * (Axy @ u_D_delta)
    e_D_pose -= s * np.outer(v[:2], q_D_pose)
    e_D_vel = -s * q * (Axy @ world_R_body.T)
    e_D_ground = (-s * v[:2] * q_D_ground).reshape(2, 1)
    return e, [e_D_pose, e_D_vel, e_D_ground]


def predict_flow(
    world_T_body: gtsam.Pose3 | np.ndarray,
    world_v_body: np.ndarray,
    ground: float,
    dt: float,
    body_omega: np.ndarray,
    calib: FlowSensor,
) -> np.ndarray:
    """Ideal flow reading (2,) [px] of the model at a state (simulation, tests, baselines)."""
    m = as_pose_matrix(calib.body_T_flow, "body_T_flow")
    body_R_flow, body_t_flow = pose_parts(m)
    e, _ = _optical_flow(
        pose_matrix(world_T_body),
        np.asarray(world_v_body, float),
        float(ground),
        np.zeros(2),
        float(dt),
        np.asarray(body_omega, float),
        body_R_flow,
        np.array(body_t_flow),
        float(calib.pixels_per_rad),
        False,
    )
    return e


def make_optical_flow_factor(
    pose_key: int,
    velocity_key: int,
    ground_key: int,
    measurement: FlowMeasurement,
    body_omega: np.ndarray,
    calib: FlowSensor,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """Optical-flow factor on ``(X: Pose3, V: Vector3, G: Vector1)`` (2-D, [px]).

    Args:
        measurement: flow [px] (already gated by ``gate_flow``) and interval [s].
        body_omega: (3,) mean bias-corrected body rate over the interval [rad/s] (input).
        calib: sensor pose in the body and pixels per radian.
        noise_model: 2-D noise [px] (robust kernel recommended).
    """
    flow = as_vector(measurement.flow, 2, "flow")
    omega = as_vector(body_omega, 3, "body_omega")
    dt = float(measurement.dt)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"flow dt: expected a positive interval, got {measurement.dt}")
    ppr = float(calib.pixels_per_rad)
    if not (np.isfinite(ppr) and ppr > 0):
        raise ValueError(f"flow pixels_per_rad: expected > 0, got {calib.pixels_per_rad}")
    body_R_flow, body_t_flow = pose_parts(as_pose_matrix(calib.body_T_flow, "body_T_flow"))
    body_R_flow, body_t_flow = np.array(body_R_flow), np.array(body_t_flow)
    variables = ((pose_key, pose_matrix_at), (velocity_key, vector_at), (ground_key, scalar_at))
    constants = (flow, dt, omega, body_R_flow, body_t_flow, ppr)
    return custom_factor(noise_model, ERROR_DIM, variables, _optical_flow, constants, lazy=True)


def flow_sum_sigma(sigma: float, n: int, lag1_corr: float) -> float:
    """Standard deviation [px] of the sum of ``n`` consecutive flow samples, each of standard
    deviation ``sigma`` with lag-1 correlation ``lag1_corr`` and none beyond (an MA(1) process):
    ``var = sigma^2 (n + 2 (n - 1) rho)``. With rho = -0.3 the sum of 5 samples has 0.52 of the
    independent-sample variance; neighbouring sums stay correlated only through their edge
    samples (correlation ``rho / (n + 2 (n - 1) rho)``, -0.12 for n = 5), which is neglected.
    """
    if n < 1:
        raise ValueError(f"flow_sum_sigma: n = {n}, expected >= 1")
    var = sigma**2 * (n + 2.0 * (n - 1) * lag1_corr)
    return float(np.sqrt(max(var, sigma**2 * 0.05)))


def gate_flow(
    height: float,
    cos_tilt: float,
    quality: float,
    height_min: float,
    height_max: float,
    max_tilt_rad: float,
    quality_min: float,
) -> tuple[bool, str]:
    """Decide whether a flow reading may become a factor.

    Args:
        height: height of the sensor above the ground estimate [m] (e.g. the latest range).
        cos_tilt: cosine of the optical axis' angle to the world down axis.
        quality: sensor quality in [0, 1], negative when unknown (then not tested).
        height_min, height_max: usable height interval [m] (focus, texture resolution).
        max_tilt_rad: largest accepted tilt [rad].
        quality_min: smallest accepted quality.

    Returns:
        ``(True, "ok")`` or ``(False, reason)`` (``"non-finite"``, ``"height"``, ``"tilt"``,
        ``"quality"``).
    """
    if not (np.isfinite(height) and np.isfinite(cos_tilt)):
        return False, f"non-finite height {height} or cos tilt {cos_tilt}"
    if not height_min <= height <= height_max:
        return False, f"height {height:.3f} m not in [{height_min}, {height_max}] m"
    if cos_tilt < np.cos(max_tilt_rad):
        tilt = float(np.degrees(np.arccos(np.clip(cos_tilt, -1.0, 1.0))))
        return False, f"tilt {tilt:.1f} deg above {np.degrees(max_tilt_rad):.1f} deg"
    if quality >= 0 and quality < quality_min:
        return False, f"quality {quality:.2f} below {quality_min}"
    return True, "ok"
