"""Numerical Jacobians of GTSAM factors by central differences through ``Values.retract``.

Each key's dimension comes from ``dims``; a perturbation ``delta`` of one key is applied with
``values.retract(VectorValues)``, i.e. in GTSAM's local coordinates (right perturbation for Pose3
and Similarity3, addition for vectors), exactly the coordinates of the analytic Jacobians.
"""

from __future__ import annotations

import gtsam
import numpy as np

EPS = 1e-6


def numerical_jacobians(
    factor: gtsam.NonlinearFactor, values: gtsam.Values, dims: list[int], eps: float = EPS
) -> list[np.ndarray]:
    """Central-difference Jacobians of ``factor.unwhitenedError`` w.r.t. each of its keys."""
    keys = list(factor.keys())
    jacobians = []
    for key, dim in zip(keys, dims, strict=True):
        cols = []
        for i in range(dim):
            step = np.zeros(dim)
            step[i] = eps
            e_plus = factor.unwhitenedError(values.retract(_delta(values, keys, dims, key, step)))
            e_minus = factor.unwhitenedError(values.retract(_delta(values, keys, dims, key, -step)))
            cols.append((np.asarray(e_plus) - np.asarray(e_minus)) / (2.0 * eps))
        jacobians.append(np.stack(cols, axis=1))
    return jacobians


def analytic_jacobians(
    factor: gtsam.NonlinearFactor, values: gtsam.Values, dims: list[int]
) -> list[np.ndarray]:
    """The factor's own Jacobian blocks, from ``linearize`` (the factor must have unit sigmas, so
    that whitened and unwhitened Jacobians agree)."""
    A, _ = factor.linearize(values).jacobian()
    if A.shape[1] != sum(dims):
        raise AssertionError(f"Jacobian has {A.shape[1]} columns, expected {sum(dims)}")
    blocks = np.split(A, np.cumsum(dims)[:-1], axis=1)
    return list(blocks)


def assert_jacobians_close(
    factor: gtsam.NonlinearFactor, values: gtsam.Values, dims: list[int], rtol: float = 1e-6
) -> None:
    """Analytic Jacobians equal central differences to ``rtol`` relative to the largest entry."""
    analytic = analytic_jacobians(factor, values, dims)
    numeric = numerical_jacobians(factor, values, dims)
    for i, (Ja, Jn) in enumerate(zip(analytic, numeric, strict=True)):
        scale = max(1.0, float(np.max(np.abs(Jn))))
        err = float(np.max(np.abs(Ja - Jn)))
        assert err <= rtol * scale, f"key #{i}: max |analytic - numeric| = {err:.3e}\n{Ja}\n{Jn}"


def _delta(
    values: gtsam.Values, keys: list[int], dims: list[int], key: int, step: np.ndarray
) -> gtsam.VectorValues:
    delta = gtsam.VectorValues()
    for k, d in zip(keys, dims, strict=True):
        delta.insert(k, step if k == key else np.zeros(d))
    return delta


def unit_noise(dim: int) -> gtsam.noiseModel.Base:
    """Unit isotropic noise: whitened == unwhitened."""
    return gtsam.noiseModel.Unit.Create(dim)


def random_pose(rng: np.random.Generator, trans_scale: float = 3.0) -> gtsam.Pose3:
    """A seeded non-identity pose (rotation angle up to ~1.5 rad)."""
    return gtsam.Pose3(
        gtsam.Rot3.Expmap(rng.uniform(-0.9, 0.9, 3)), rng.uniform(-trans_scale, trans_scale, 3)
    )
