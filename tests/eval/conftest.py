"""Synthetic trajectories for the evaluation tests (seeded, analytic velocity)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from fgnav.datasets.geometry import matrix_to_quat_wxyz, rpy_to_matrix
from fgnav.datasets.types import Trajectory


def synthetic_truth(duration_s: float = 60.0, rate_hz: float = 20.0) -> Trajectory:
    """A 3-D Lissajous-like flight (about 2 m/s) with yaw along the path and roll/pitch wobble."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz) + 1000.0
    u = t - t[0]
    w1, w2, w3 = 2 * np.pi / 30.0, 2 * np.pi / 20.0, 2 * np.pi / 15.0
    p = np.stack([10 * np.sin(w1 * u), 6 * np.sin(w2 * u), 1.5 + 0.5 * np.sin(w3 * u)], axis=1)
    v = np.stack(
        [10 * w1 * np.cos(w1 * u), 6 * w2 * np.cos(w2 * u), 0.5 * w3 * np.cos(w3 * u)], axis=1
    )
    yaw = np.arctan2(v[:, 1], v[:, 0])
    R = np.stack(
        [
            rpy_to_matrix(0.1 * np.sin(0.7 * x), 0.08 * np.cos(0.5 * x), y)
            for x, y in zip(u, yaw, strict=True)
        ]
    )
    return Trajectory(t=t, world_t_body=p, world_q_body_wxyz=matrix_to_quat_wxyz(R), world_v_body=v)


@pytest.fixture
def truth() -> Trajectory:
    return synthetic_truth()


@pytest.fixture
def make_truth() -> Callable[..., Trajectory]:
    return synthetic_truth
