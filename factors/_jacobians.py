"""Small numpy helpers shared by the factor modules (no frames of their own).

GTSAM conventions used by every factor of ``fgnav.factors``:

- ``Pose3`` ``world_T_body`` is perturbed on the right, ``world_T_body * Exp([omega, v])``: to first
  order ``world_R_body -> world_R_body (I + [omega]x)`` and ``world_t_body -> world_t_body +
  world_R_body v``. Jacobian columns are ``[omega (3), v (3)]``.
- ``Similarity3`` ``slam_T_world`` = ``(R, t, s)`` maps ``p`` to ``s (R p + t)``; its tangent
  is ``[omega (3), u (3), lambda (1)]`` and the first-order change of the mapped point is
  ``s R ([omega]x^T p + u + lambda p)`` (GTSAM ``Similarity3::transformFrom`` H1).
- Vectors (velocity, drag, ground height as a 1-vector) are perturbed by plain addition.
- ``imuBias.ConstantBias`` tangent is ``[accelerometer (3), gyroscope (3)]``.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

#: Largest deviation of ``R^T R`` from identity accepted for a calibration rotation (about what
#: four printed decimals give); closer rotations are re-orthonormalised.
ROTATION_TOLERANCE = 1e-3
#: Deviation of ``R^T R`` from identity below which a rotation counts as exactly orthonormal
#: (double rounding of a projected rotation is ~1e-16).
ORTHONORMAL_EXACT = 1e-12


#: Opt-in record of the errors that the SLAM and range factors' callbacks computed while
#: linearising (``CustomFactor -> unwhitened error``): a caller that needs those factors' errors
#: at the linearisation point just used (the online smoother's health monitor, after its iSAM2
#: update) sets a dict here around the update and reads them instead of evaluating each callback
#: again. None: not recording (the default; a callback then only checks this).
LINEARIZED: dict | None = None


_EYE3 = np.eye(3)
_EYE3.flags.writeable = False


def skew(v: np.ndarray) -> np.ndarray:
    """3-vector -> 3x3 skew-symmetric matrix ``[v]x`` with ``skew(a) @ b == cross(a, b)``."""
    x, y, z = np.asarray(v, dtype=float).tolist()
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def pose_parts(a_T_b: gtsam.Pose3 | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (3, 3) and translation (3,) of a ``gtsam.Pose3`` or a 4x4 homogeneous matrix."""
    if isinstance(a_T_b, gtsam.Pose3):
        m = a_T_b.matrix()
    else:
        m = np.asarray(a_T_b, dtype=float)
        if m.shape != (4, 4):
            raise ValueError(f"expected a Pose3 or a 4x4 pose matrix, got shape {m.shape}")
    return m[:3, :3], m[:3, 3]


def pose_matrix(a_T_b: gtsam.Pose3 | np.ndarray) -> np.ndarray:
    """4x4 homogeneous matrix of a ``gtsam.Pose3`` or of a 4x4 pose matrix."""
    if isinstance(a_T_b, gtsam.Pose3):
        return a_T_b.matrix()
    m = np.asarray(a_T_b, dtype=float)
    if m.shape != (4, 4):
        raise ValueError(f"expected a Pose3 or a 4x4 pose matrix, got shape {m.shape}")
    return m


def sim3_parts(a_T_b: gtsam.Similarity3) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R (3, 3), t (3,), s)`` of a ``gtsam.Similarity3`` that maps ``p -> s (R p + t)``."""
    return a_T_b.rotation().matrix(), np.asarray(a_T_b.translation(), dtype=float), a_T_b.scale()


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> rotation vector (3,) (GTSAM ``Rot3.Logmap``)."""
    return np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(R)), dtype=float)


def so3_right_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """Inverse right Jacobian of SO(3) at rotation vector ``phi``:
    ``Log(Exp(phi) Exp(delta)) = phi + Jr^-1(phi) delta + O(|delta|^2)``."""
    theta2 = float(phi @ phi)
    K = skew(phi)
    # (_EYE3: a shared read-only identity; np.eye(3) per call was a third of this function)
    if theta2 < 1e-10:
        return _EYE3 + 0.5 * K + K @ K / 12.0
    theta = np.sqrt(theta2)
    coeff = 1.0 / theta2 - (1.0 + np.cos(theta)) / (2.0 * theta * np.sin(theta))
    return _EYE3 + 0.5 * K + coeff * K @ K


def as_vector(value: np.ndarray | float, size: int, name: str) -> np.ndarray:
    """``value`` as a float vector of length ``size``; ``ValueError`` naming ``name`` otherwise."""
    v = np.asarray(value, dtype=float).reshape(-1)
    if v.shape != (size,):
        raise ValueError(f"{name}: expected {size} values, got shape {np.shape(value)}")
    # (on plain floats: a factor is made per measurement, numpy's isfinite().all() on a few
    # values cost 3x the rest of this function)
    if not all(map(math.isfinite, v.tolist())):
        raise ValueError(f"{name}: non-finite value {v}")
    return v


def check_noise_dim(noise_model: gtsam.noiseModel.Base, dim: int) -> None:
    """Raise ``ValueError`` unless ``noise_model`` has dimension ``dim`` (a wrong row count crashes
    GTSAM's solvers instead of raising)."""
    if noise_model.dim() != dim:
        raise ValueError(f"noise model has dimension {noise_model.dim()}, the factor needs {dim}")


#: ``custom_factor`` readers of a variable of GTSAM's own type (``read(values, key)``).
pose_at = gtsam.Values.atPose3
vector_at = gtsam.Values.atVector
similarity3_at = gtsam.Values.atSimilarity3


def pose_matrix_at(values: gtsam.Values, key: int) -> np.ndarray:
    """4x4 matrix of the ``Pose3`` at ``key`` (a ``custom_factor`` reader)."""
    return values.atPose3(key).matrix()


def scalar_at(values: gtsam.Values, key: int) -> float:
    """The ``Vector1`` at ``key`` as a float (a ``custom_factor`` reader)."""
    return float(values.atVector(key)[0])


def custom_factor(
    noise_model: gtsam.noiseModel.Base,
    dim: int,
    variables,
    error,
    constants: tuple = (),
    *,
    lazy: bool = False,
    record: bool = False,
) -> gtsam.CustomFactor:
    """The ``gtsam.CustomFactor`` plumbing every factor of ``fgnav.factors`` shares.

    Args:
        noise_model: noise of the ``dim``-D error (checked with ``check_noise_dim``).
        dim: the error's dimension.
        variables: ``((key, read), ...)`` in the factor's key order; ``read(values, key)`` gives
            the argument ``error`` takes for that variable (``pose_at``, ``pose_matrix_at``,
            ``scalar_at``, ...).
        error: ``error(*states, *constants[, with_jacobians]) -> (e, jacobians)``, one Jacobian
            per variable; with ``lazy`` it takes the last ``with_jacobians`` flag (GTSAM asks for
            Jacobians when it linearises, not when it only evaluates the error).
        constants: the measurement and calibration arguments after the states.
        record: keep the error in ``LINEARIZED`` when it is set and the factor is linearised.
    """
    check_noise_dim(noise_model, dim)
    variables = tuple(variables)

    def error_fn(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        with_jacobians = H is not None
        args = [read(values, key) for key, read in variables]
        if lazy:
            e, jacobians = error(*args, *constants, with_jacobians)
        else:
            e, jacobians = error(*args, *constants)
        if with_jacobians:
            for i, J in enumerate(jacobians):
                H[i] = J
            if record and LINEARIZED is not None:
                LINEARIZED[this] = e
        return e

    return gtsam.CustomFactor(noise_model, [key for key, _ in variables], error_fn)


#: Validated pose matrices by their bytes (calibrations repeat for every factor of a flight).
_POSE_CACHE: dict[bytes, np.ndarray] = {}
_POSE_CACHE_MAX = 64
_I3 = np.eye(3)


def _det3(R: np.ndarray) -> float:
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def as_pose_matrix(a_T_b: gtsam.Pose3 | np.ndarray, name: str) -> np.ndarray:
    """A ``Pose3`` or 4x4 rigid pose as a 4x4 float matrix with an exactly orthonormal rotation.

    Calibration files often print rotations with few digits, so a rotation block within
    ``ROTATION_TOLERANCE`` of orthonormal is projected onto the nearest rotation (SVD); anything
    further raises ``ValueError`` naming ``name``. The result is read-only; results are cached by
    the input's bytes (a flight's factors share a few calibration poses).
    """
    m = a_T_b.matrix() if isinstance(a_T_b, gtsam.Pose3) else np.array(a_T_b, dtype=float)
    if m.shape == (4, 4):
        cached = _POSE_CACHE.get(m.tobytes())
        if cached is not None:
            return cached
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ValueError(f"{name}: expected a Pose3 or a finite 4x4 pose, got shape {m.shape}")
    raw = m.tobytes()
    R = m[:3, :3]
    deviation = float(np.abs(R.T @ R - _I3).max())
    if deviation > ROTATION_TOLERANCE or _det3(R) < 0:
        raise ValueError(f"{name}: rotation block is not a rotation matrix:\n{R}")
    if deviation <= ORTHONORMAL_EXACT:
        # Already orthonormal to rounding (a Pose3, or a matrix projected before): no SVD, which
        # costs more than the rest of a factor's construction.
        m[3] = (0.0, 0.0, 0.0, 1.0)
        out = m
    else:
        U, _, Vt = np.linalg.svd(R)
        out = np.eye(4)
        out[:3, :3] = U @ Vt
        out[:3, 3] = m[:3, 3]
    out.flags.writeable = False
    if len(_POSE_CACHE) >= _POSE_CACHE_MAX:
        _POSE_CACHE.clear()
    _POSE_CACHE[raw] = out
    return out
