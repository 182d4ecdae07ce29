"""The accelerometer check of the drag model (fgnav.solvers.accel_check)."""

from __future__ import annotations

import numpy as np
import pytest

from fgnav.solvers.accel_check import check_horizontal_accel


def _speeds(n: int, rng: np.random.Generator) -> np.ndarray:
    t = np.arange(n) * 0.05
    return np.column_stack([np.sin(0.7 * t), 0.8 * np.cos(0.4 * t)]) + 0.05 * rng.normal(
        size=(n, 2)
    )


def test_a_drag_signal_with_white_noise_is_usable():
    rng = np.random.default_rng(0)
    u = _speeds(600, rng)
    f = -np.array([0.38, 0.42]) * u + [0.05, -0.03] + 0.01 * rng.normal(size=u.shape)
    c = check_horizontal_accel(f, u, white_sigma=0.01)
    assert c.decision == "usable"
    assert c.k == pytest.approx((0.38, 0.42), abs=0.01)
    assert c.bias == pytest.approx((0.05, -0.03), abs=0.01)
    assert c.ratio < 0.05
    assert c.drag_on and "drag on" in c.line()


def test_wandering_offsets_far_above_drag_are_unusable():
    # Crazyflie-like: offsets of 1-5 m/s^2 wandering over seconds, drag 0.2 m/s^2.
    rng = np.random.default_rng(1)
    u = _speeds(800, rng)
    offset = np.cumsum(0.15 * rng.normal(size=u.shape), axis=0) - 3.0
    f = -0.3 * u + offset + 0.5 * rng.normal(size=u.shape)
    c = check_horizontal_accel(f, u, white_sigma=0.01)
    assert c.decision == "unusable"
    assert c.ratio > 1.0
    assert not c.drag_on and "drag off" in c.line()


def test_moderate_misfit_raises_the_noise_floor():
    rng = np.random.default_rng(2)
    u = _speeds(800, rng)
    f = -0.4 * u + 0.2 * rng.normal(size=u.shape)
    c = check_horizontal_accel(f, u, white_sigma=0.0)
    assert c.decision == "noisy"
    assert c.residual == pytest.approx(0.2 * np.sqrt(2), rel=0.1)
    assert "noise floor raised" in c.line()


def test_white_noise_of_the_means_is_not_counted_against_the_accelerometer():
    rng = np.random.default_rng(3)
    u = _speeds(2000, rng)
    f = -0.4 * u + 0.2 * rng.normal(size=u.shape)
    c = check_horizontal_accel(f, u, white_sigma=0.2)
    assert c.residual < 0.05
    assert c.decision == "usable"


def test_too_few_keyframes_is_undecided():
    c = check_horizontal_accel(np.zeros((5, 2)), np.zeros((5, 2)))
    assert c.decision == "undecided" and c.drag_on
