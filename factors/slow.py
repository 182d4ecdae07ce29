"""Initial values, priors and random walks of fgnav's slow variables (built-in GTSAM factors only).

Slow variables (``../shared/DESIGN.md`` section 3), one per segment ``j``:

- ``D(j)`` drag coefficient ``k = mu / m`` [1/s]: a gtsam Vector of size 1 ``[k]`` or 2 ``[kx, ky]``
  (``fgnav.factors.accel_drag``).
- ``G(j)`` ground height [m]: a gtsam Vector of size 1 (``fgnav.factors.tilted_range``).
- ``W(j)`` horizontal wind ``world_v_wind_xy`` [m/s]: a gtsam Vector of size 2 (optional,
  ``fgnav.factors.accel_drag``).
- ``S(j)`` SLAM alignment ``slam_T_world``: a ``gtsam.Similarity3`` mapping ``p -> s (R p + t)``
  with ``slam_t_world = s t`` (``fgnav.factors.slam_scale``), a new one at every SLAM map reset.

Random walks are ``BetweenFactor``s with zero mean and sigma ``sigma_per_sqrt_unit * sqrt(elapsed)``
(elapsed time [s] or distance [m]), the discrete form of a Wiener process.

Similarity3 sigmas: GTSAM's local coordinates of ``slam_T_world`` are ``[omega, u, lambda]``; a
change ``u`` moves ``slam_t_world`` by ``s R u`` [SLAM units] and ``lambda`` multiplies the scale by
``exp(lambda)``. The helpers below take sigmas as (rotation [rad], ``slam_t_world`` [SLAM units],
relative scale [-]) and convert them (``u`` sigma = translation sigma / s).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from fgnav.factors.slam_scale import make_slam_T_world


@dataclass(frozen=True)
class SlamAlignmentSigmas:
    """Standard deviations of a SLAM alignment ``slam_T_world`` prior or random-walk step.

    Attributes:
        rotation_rad: of each axis of ``slam_R_world`` [rad].
        translation: of each axis of ``slam_t_world`` [SLAM units].
        log_scale: of ``log(s)`` [-] (0.5 lets the scale move by a factor e^0.5 = 1.65 at 1 sigma).
    """

    rotation_rad: float
    translation: float
    log_scale: float

    def as_tangent_sigmas(self, scale: float) -> np.ndarray:
        """(7,) sigmas in GTSAM ``Similarity3`` local coordinates at scale ``scale``."""
        for name in ("rotation_rad", "translation", "log_scale"):
            if not getattr(self, name) > 0:
                raise ValueError(
                    f"SlamAlignmentSigmas.{name} must be > 0, got {getattr(self, name)}"
                )
        if not scale > 0:
            raise ValueError(f"scale must be > 0, got {scale}")
        return np.array([self.rotation_rad] * 3 + [self.translation / scale] * 3 + [self.log_scale])


def random_walk_sigma(sigma_per_sqrt_unit: float, elapsed: float) -> float:
    """Standard deviation of a Wiener-process step: ``sigma_per_sqrt_unit * sqrt(elapsed)``.

    Args:
        sigma_per_sqrt_unit: density, e.g. [1/s/sqrt(s)] for drag or [m/sqrt(m)] for terrain.
        elapsed: time [s] or distance [m] between the two variables (> 0).
    """
    if not elapsed > 0 or not sigma_per_sqrt_unit > 0:
        raise ValueError(
            f"random walk needs elapsed > 0 and sigma > 0, got {elapsed}, {sigma_per_sqrt_unit}"
        )
    return float(sigma_per_sqrt_unit * np.sqrt(elapsed))


def drag_initial(k0: float | Sequence[float], per_axis: bool = False) -> np.ndarray:
    """Initial value of a drag variable: ``[k0]``, or ``[kx, ky]`` when ``per_axis``.

    Args:
        k0: drag coefficient(s) [1/s]; a scalar is repeated for both axes when ``per_axis``.
        per_axis: make a Vector2 ``[kx, ky]`` instead of a Vector1.
    """
    k = np.atleast_1d(np.asarray(k0, dtype=float))
    n = 2 if per_axis else 1
    if k.size == 1:
        k = np.repeat(k, n)
    if k.shape != (n,) or not np.all(np.isfinite(k)):
        raise ValueError(f"drag k0: expected 1 or {n} finite values, got {k0}")
    return k


def drag_prior(
    key: int, k0: float | Sequence[float], sigma: float, per_axis: bool = False
) -> gtsam.PriorFactorVector:
    """Prior on a drag variable at ``drag_initial(k0, per_axis)`` with sigma [1/s] per axis."""
    mean = drag_initial(k0, per_axis)
    return gtsam.PriorFactorVector(key, mean, _isotropic(mean.size, sigma))


def drag_random_walk(
    key_a: int, key_b: int, sigma_per_sqrt_s: float, dt: float, per_axis: bool = False
) -> gtsam.BetweenFactorVector:
    """Random walk ``k_b - k_a ~ N(0, (sigma_per_sqrt_s^2 dt) I)`` between drag variables.

    Args:
        sigma_per_sqrt_s: drift density [1/s/sqrt(s)].
        dt: time between the two segments' centres [s].
        per_axis: the variables are Vector2 ``[kx, ky]``.
    """
    n = 2 if per_axis else 1
    return gtsam.BetweenFactorVector(
        key_a, key_b, np.zeros(n), _isotropic(n, random_walk_sigma(sigma_per_sqrt_s, dt))
    )


def wind_prior(key: int, wind0_xy: Sequence[float], sigma: float) -> gtsam.PriorFactorVector:
    """Prior on a horizontal wind variable (Vector2 ``world_v_wind_xy``), sigma [m/s] per axis."""
    mean = np.asarray(wind0_xy, dtype=float).ravel()
    if mean.shape != (2,) or not np.all(np.isfinite(mean)):
        raise ValueError(f"wind0_xy: expected 2 finite values, got {wind0_xy}")
    return gtsam.PriorFactorVector(key, mean, _isotropic(2, sigma))


def wind_random_walk(
    key_a: int, key_b: int, sigma_per_sqrt_s: float, dt: float
) -> gtsam.BetweenFactorVector:
    """Random walk ``w_b - w_a ~ N(0, (sigma_per_sqrt_s^2 dt) I2)`` between wind variables.

    Args:
        sigma_per_sqrt_s: wind drift density [m/s/sqrt(s)].
        dt: time between the two segments' centres [s].
    """
    return gtsam.BetweenFactorVector(
        key_a, key_b, np.zeros(2), _isotropic(2, random_walk_sigma(sigma_per_sqrt_s, dt))
    )


def ground_initial(ground0: float) -> np.ndarray:
    """Initial value of a ground-height variable: Vector1 ``[ground0]`` [m]."""
    if not np.isfinite(ground0):
        raise ValueError(f"ground0: non-finite value {ground0}")
    return np.array([float(ground0)])


def ground_prior(key: int, ground0: float, sigma: float) -> gtsam.PriorFactorVector:
    """Prior on a ground-height variable at ``ground0`` [m] with sigma [m]."""
    return gtsam.PriorFactorVector(key, ground_initial(ground0), _isotropic(1, sigma))


def ground_random_walk(key_a: int, key_b: int, sigma_step: float) -> gtsam.BetweenFactorVector:
    """Terrain step ``ground_b - ground_a ~ N(0, sigma_step^2)`` between terrain segments.

    Args:
        sigma_step: standard deviation of the terrain height change [m]; for a terrain density use
            ``random_walk_sigma(sigma_per_sqrt_m, distance_m)``.
    """
    return gtsam.BetweenFactorVector(key_a, key_b, np.zeros(1), _isotropic(1, sigma_step))


def slam_alignment_initial(
    s0: float, slam_R_world0: np.ndarray, slam_t_world0: np.ndarray
) -> gtsam.Similarity3:
    """Initial ``slam_T_world``: ``p_slam = s0 slam_R_world0 p_world + slam_t_world0``."""
    return make_slam_T_world(s0, slam_R_world0, slam_t_world0)


def slam_alignment_prior(
    key: int,
    s0: float,
    slam_R_world0: np.ndarray,
    slam_t_world0: np.ndarray,
    sigmas: SlamAlignmentSigmas,
) -> gtsam.PriorFactorSimilarity3:
    """Prior on a SLAM alignment at ``slam_alignment_initial(s0, ...)``.

    A broad ``sigmas.log_scale`` (an unknown monocular scale) and broad rotation and translation
    sigmas let the data decide; the prior then only regularises the first iterations.
    """
    mean = slam_alignment_initial(s0, slam_R_world0, slam_t_world0)
    noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas.as_tangent_sigmas(s0))
    return gtsam.PriorFactorSimilarity3(key, mean, noise)


def slam_alignment_random_walk(
    key_a: int, key_b: int, scale: float, sigmas: SlamAlignmentSigmas
) -> gtsam.BetweenFactorSimilarity3:
    """Identity-mean between factor ``slam_T_world_a^-1 slam_T_world_b`` for slow drift of one
    SLAM session's alignment (not across map resets: a reset gets a new, unconnected variable).

    Args:
        scale: current scale estimate (converts the translation sigma to GTSAM's coordinates).
        sigmas: step sigmas (rotation [rad], ``slam_t_world`` [SLAM units], log-scale [-]).
    """
    noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas.as_tangent_sigmas(scale))
    return gtsam.BetweenFactorSimilarity3(key_a, key_b, gtsam.Similarity3(), noise)


def _isotropic(dim: int, sigma: float) -> gtsam.noiseModel.Isotropic:
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    return gtsam.noiseModel.Isotropic.Sigma(dim, float(sigma))
