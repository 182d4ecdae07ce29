"""Tilted downward rangefinder over flat ground: slant range from height, attitude and lever arm.

Measurement model (seed 002 eqs. 20-21, with the lever arm and a ground-height variable as in the
PX4 EKF2 range-finder fusion)::

    d = world_R_body body_R_range e_z                 beam direction in world (sensor +z axis)
    p = world_t_body + world_R_body body_t_range      sensor position in world [m]
    cos_tilt = -d_z                                   1 when the beam points straight down
    range = (p_z - ground) / cos_tilt + n             [m]

The beam is the sensor's +z axis (``fgnav.datasets.types.Calibration.body_T_range``), so a
rangefinder looking down a body FLU frame has ``body_R_range`` with ``body_R_range e_z = -e_z``
(e.g. a rotation of pi about body x).

Keys: ``X`` Pose3 ``world_T_body``; ``G`` ground height: a gtsam Vector of size 1 ``[ground]`` [m]
(world z of the flat ground under the sensor; a Vector1, not a double, so that
``PriorFactorVector`` / ``BetweenFactorVector`` and ``calculateEstimateVector`` serve it).

Residual (1,): unwhitened ``h(x) - z`` [m]; zero when the measured range equals the slant distance
from the sensor to the plane ``z = ground`` along the beam.

Jacobians (right perturbation ``[omega, v]`` of the pose): with ``b = body_R_range e_z``,
``l = body_t_range``, ``r`` the predicted range, ``c = cos_tilt``:
``dr/domega = (-(R [l]x)_z - r (R [b]x)_z) / c``, ``dr/dv = R_z / c``, ``dr/dground = -1 / c``
(``R = world_R_body``, ``_z`` its third row).

Noise: sensor sigma [m] (grows with range for many sensors); use a robust kernel (Huber/Cauchy)
against obstacles under the vehicle. Gate every reading with ``gate_range`` before making a
factor: out of the sensor's interval, at its floor (:func:`range_at_min`) or at its maximum
(:func:`range_at_max`), beam not pointing down, or tilt above a limit -> no factor. The limits are
tested in one place, :func:`fgnav.datasets.range_limits.range_refusal` (``RangeLimits`` for a
stream of readings), which every consumer of range readings calls (the smoothers, the flow and
camera heights, the filter baselines, the health checks).
During optimisation ``cos_tilt`` is floored at ``MIN_COS_TILT`` so that a bad intermediate
attitude cannot divide by zero (the Jacobian of the floored value is zero).

Not modelled: sloped or rough terrain (ground is a flat horizontal plane per ``G`` variable), beam
width, the sensor's time offset, multipath and readings from non-ground obstacles.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from fgnav.datasets.range_limits import (  # (the limits' home; re-exported here)
    RANGE_AT_MAX_TOL_M,
    RANGE_AT_MIN_TOL_M,
    RANGE_LIMIT_TAGS,
    RangeLimits,
    range_at_max,
    range_at_min,
    range_clamps,
    range_refusal,
)
from fgnav.factors._jacobians import (
    as_pose_matrix,
    custom_factor,
    pose_matrix,
    pose_matrix_at,
    pose_parts,
    scalar_at,
    skew,
)

ERROR_DIM = 1

#: Floor on cos(tilt) inside the factor: cos(85 deg). Readings are gated far below this tilt; the
#: floor only protects optimiser iterates from a division by ~0.
MIN_COS_TILT = float(np.cos(np.deg2rad(85.0)))

_E_Z = np.array([0.0, 0.0, 1.0])

__all__ = [
    "ERROR_DIM",
    "MIN_COS_TILT",
    "RANGE_AT_MAX_TOL_M",
    "RANGE_AT_MIN_TOL_M",
    "RANGE_LIMIT_TAGS",
    "RangeLimits",
    "gate_range",
    "make_range_factor",
    "predicted_range",
    "range_at_max",
    "range_at_min",
    "range_clamps",
    "range_refusal",
    "tilted_range_error",
]


def tilted_range_error(
    world_T_body: gtsam.Pose3,
    ground: np.ndarray,
    range_meas: float,
    body_T_range: gtsam.Pose3 | np.ndarray,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Residual and Jacobians of the tilted-rangefinder model.

    Args:
        world_T_body: body pose in the world (z up).
        ground: (1,) world z of the ground plane [m].
        range_meas: measured distance along the beam [m].
        body_T_range: rangefinder pose in the body frame (beam = sensor +z axis).

    Returns:
        ``(e (1,), [e_D_pose (1x6), e_D_ground (1x1)])`` [m].
    """
    body_R_range, body_t_range = pose_parts(body_T_range)
    b = body_R_range @ _E_Z
    return _tilted_range(
        pose_matrix(world_T_body),
        float(np.asarray(ground).ravel()[0]),
        range_meas,
        b,
        skew(b),
        body_t_range,
        skew(body_t_range),
        True,
    )


def predicted_range(
    world_R_body: np.ndarray,
    world_t_body: np.ndarray,
    ground: np.ndarray | float,
    body_T_range: np.ndarray,
) -> np.ndarray:
    """The reading the model predicts, ``h(x)`` of :func:`tilted_range_error` without its floor:
    the distance along the beam from the sensor to the plane ``z = ground`` [m], NaN where the
    beam points 85 deg or more from down (``cos_tilt < MIN_COS_TILT``: no reading predicted).
    Vectorised over leading axes: ``world_R_body`` (..., 3, 3), ``world_t_body`` (..., 3),
    ``ground`` (...) [m]; ``body_T_range`` a 4x4 matrix."""
    T = np.asarray(body_T_range, float)
    R = np.asarray(world_R_body, float)
    z = np.asarray(world_t_body, float)[..., 2] + (R @ T[:3, 3])[..., 2]
    cos = -(R @ T[:3, 2])[..., 2]
    ok = cos >= MIN_COS_TILT
    return np.where(ok, (z - ground) / np.where(ok, cos, 1.0), np.nan)


def _tilted_range(
    m: np.ndarray,
    ground: float,
    range_meas: float,
    b: np.ndarray,
    b_skew: np.ndarray,
    body_t_range: np.ndarray,
    body_t_range_skew: np.ndarray,
    with_jacobians: bool,
) -> tuple[np.ndarray, list[np.ndarray] | None]:
    """``tilted_range_error`` with the beam direction ``b``, the lever arm and their skew
    matrices precomputed (the factor's callback; ``m``: 4x4 ``world_T_body``); no Jacobians
    unless ``with_jacobians``."""
    world_R_body = m[:3, :3]
    Rz = world_R_body[2]
    cos_tilt = -(Rz @ b)
    floored = cos_tilt < MIN_COS_TILT
    if floored:
        cos_tilt = MIN_COS_TILT
    height = m[2, 3] + Rz @ body_t_range - ground
    r = height / cos_tilt
    e = np.array([r - range_meas])
    if not with_jacobians:
        return e, None
    cos_D_omega = np.zeros(3) if floored else Rz @ b_skew
    e_D_pose = np.empty((1, 6))
    e_D_pose[0, :3] = (-(Rz @ body_t_range_skew) - r * cos_D_omega) / cos_tilt
    e_D_pose[0, 3:] = Rz / cos_tilt
    return e, [e_D_pose, np.array([[-1.0 / cos_tilt]])]


#: ``_sensor_parts``' newest ``(body_T_range, parts)`` (a flight has one rangefinder pose).
_PARTS: tuple | None = None


def _sensor_parts(body_T_range: np.ndarray) -> tuple[np.ndarray, ...]:
    """``(beam, beam_skew, body_t_range, body_t_range_skew)`` of a validated sensor pose (the
    read-only matrix of ``as_pose_matrix``, the same object for the same pose), kept for the
    newest pose: every factor of a flight shares them (read-only, as the callbacks use them);
    they were computed again for each of the 50 Hz readings."""
    global _PARTS
    cached = _PARTS
    if cached is not None and cached[0] is body_T_range:
        return cached[1]
    body_R_range, body_t_range = pose_parts(body_T_range)
    beam = body_R_range @ _E_Z
    parts = (beam, skew(beam), np.array(body_t_range), skew(body_t_range))
    for a in parts:
        a.flags.writeable = False
    _PARTS = (body_T_range, parts)
    return parts


def make_range_factor(
    pose_key: int,
    ground_key: int,
    range_meas: float,
    body_T_range: gtsam.Pose3 | np.ndarray,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """Tilted-rangefinder factor on ``(X: Pose3, G: Vector1 ground height)`` (1-D, [m]).

    Args:
        range_meas: measured range [m], already accepted by ``gate_range``.
        body_T_range: rangefinder pose in the body frame (Pose3 or 4x4; beam = sensor +z).
        noise_model: 1-D noise [m] (robust kernels recommended).
    """
    z = float(range_meas)
    if not math.isfinite(z):
        raise ValueError(f"range_meas: non-finite value {range_meas}")
    return custom_factor(
        noise_model,
        ERROR_DIM,
        ((pose_key, pose_matrix_at), (ground_key, scalar_at)),
        _tilted_range,
        (z, *_sensor_parts(as_pose_matrix(body_T_range, "body_T_range"))),
        lazy=True,
        record=True,
    )


def gate_range(
    range_meas: float,
    world_R_body: np.ndarray,
    body_T_range: gtsam.Pose3 | np.ndarray,
    range_min: float,
    range_max: float,
    max_tilt_rad: float,
    clamps: bool = True,
) -> tuple[bool, str]:
    """Decide whether a range reading may become a factor.

    Args:
        range_meas: measured range [m].
        world_R_body: (3, 3) current attitude estimate.
        body_T_range: rangefinder pose in the body frame (beam = sensor +z).
        range_min, range_max: valid interval of the sensor [m] (inclusive).
        max_tilt_rad: largest accepted angle between the beam and the world down axis [rad].
        clamps: the sensor may clamp at its floor (:func:`range_clamps`): a reading at
            ``range_min`` is then no distance (:func:`range_at_min`).

    Returns:
        ``(True, "ok")`` or ``(False, reason)`` with a short reason naming the failed test and the
        values (``"non-finite"``, ``"out of range"``, ``"at-min"``, ``"at-max"``, ``"beam not
        pointing down"``, ``"tilt"``); the limits are :func:`range_refusal`'s.
    """
    why = range_refusal(float(range_meas), range_min, range_max, clamps)
    if why == "non-finite":
        return False, f"non-finite range {range_meas}"
    if why == "out-of-range":
        return False, f"out of range: {range_meas:.3f} m not in [{range_min}, {range_max}] m"
    if why == "at-min":
        return False, f"at-min: {range_meas:.4f} m at the sensor's floor {range_min} m"
    if why == "at-max":
        return False, f"at-max: {range_meas:.4f} m at the sensor's maximum {range_max} m (no echo)"
    body_R_range, _ = pose_parts(body_T_range)
    cos_tilt = -float((np.asarray(world_R_body, dtype=float) @ body_R_range @ _E_Z)[2])
    if cos_tilt <= 0.0:
        return False, f"beam not pointing down (cos tilt {cos_tilt:.3f})"
    tilt = float(np.arccos(min(cos_tilt, 1.0)))
    if tilt > max_tilt_rad:
        return False, f"tilt {np.rad2deg(tilt):.1f} deg above {np.rad2deg(max_tilt_rad):.1f} deg"
    return True, "ok"
