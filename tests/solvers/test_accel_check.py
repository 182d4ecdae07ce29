"""The accelerometer check of the drag model (fgnav.solvers.accel_check)."""

from __future__ import annotations

import numpy as np
import pytest

from fgnav.solvers.accel_check import AccelLimits, RunningAccelCheck, check_horizontal_accel


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


@pytest.mark.parametrize("case", ["usable", "noisy", "unusable", "still"])
def test_running_check_equals_the_batch_check_on_its_window(case):
    """The sliding-window check from running sums gives the batch check's decision and figures
    on the window's rows, after every row, over several window turns (the sums re-seeded), with
    a non-finite row in the stream."""
    rng = np.random.default_rng(1)
    n, cap = 700, 200
    u = _speeds(n, rng) + (3.0 if case == "still" else 0.0)
    if case == "still":  # a hover: constant speed, the drag fit degenerate
        u = np.full((n, 2), 0.2) + 1e-9 * rng.normal(size=(n, 2))
    wander = {"usable": 0.0, "noisy": 0.15, "unusable": 2.0, "still": 0.0}[case]
    f = -0.4 * u + 5.0 + 0.01 * rng.normal(size=u.shape)
    f += wander * np.sin(0.05 * np.arange(n))[:, None] * [1.0, -1.0]
    white = 0.01 + 0.001 * rng.random(n)
    f[333, 0] = np.nan
    run = RunningAccelCheck(cap)
    decisions = set()
    for i in range(n):
        run.append((f[i, 0], f[i, 1], u[i, 0], u[i, 1], white[i]))
        lo = max(0, i + 1 - cap)
        assert np.array_equal(run.rows()[:, 0], f[lo : i + 1, 0], equal_nan=True)
        if i % 7 and i != n - 1:
            continue
        rows = run.rows()
        ok = np.isfinite(rows).all(axis=1)
        w = float(np.sqrt(np.mean(rows[ok, 4] ** 2)))
        limits = AccelLimits(min_keyframes=10)
        ref = check_horizontal_accel(rows[:, :2], rows[:, 2:4], w, limits)
        got = run.check(limits)
        assert got.decision == ref.decision and got.n == ref.n
        for name in ("ratio", "residual", "signal", "rms_f", "rms_u"):
            want = pytest.approx(getattr(ref, name), rel=1e-9, abs=1e-12, nan_ok=True)
            assert getattr(got, name) == want
        assert got.k == pytest.approx(ref.k, rel=1e-9, abs=1e-9, nan_ok=True)
        assert got.bias == pytest.approx(ref.bias, rel=1e-9, abs=1e-9, nan_ok=True)
        decisions.add(got.decision)
    assert case in decisions or case == "still"


def test_the_line_states_the_limit_the_check_used():
    """The printed line names the ``k_max`` of the limits given, not the module default."""
    rng = np.random.default_rng(3)
    u = _speeds(600, rng)
    f = -np.array([0.38, 0.42]) * u + 0.01 * rng.normal(size=u.shape)
    c = check_horizontal_accel(f, u, white_sigma=0.01, limits=AccelLimits(k_max=1.5))
    assert c.k_max == 1.5 and "k <= 1.5 1/s" in c.line()
    assert "k <= 0.6 1/s" in check_horizontal_accel(f, u, white_sigma=0.01).line()
