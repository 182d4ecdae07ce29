"""Rotor-drag factor gating and noise floor in the graph builder."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate

from fgnav.solvers.graph import GraphBuilder, GraphOptions


@pytest.fixture(scope="module")
def flight():
    return simulate("two-turns", seed=0, options=SimOptions(duration=6.0, images=False))


def _with_accel(flight, accel):
    return dataclasses.replace(flight, imu=dataclasses.replace(flight.imu, body_accel=accel))


def test_keyframes_not_thrust_borne_are_skipped_and_counted(flight):
    # The first 2 s "standing tilted": specific force 10 deg off body z (as EuRoC MH_01 on its
    # floor, 5.5 deg), which the linear drag model cannot explain with v = 0.
    a = flight.imu.body_accel.copy()
    m = flight.imu.t < flight.imu.t[0] + 2.0
    c, s = math.cos(math.radians(10.0)), math.sin(math.radians(10.0))
    a[m] = a[m] @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]).T
    tilted = _with_accel(flight, a)
    b = GraphBuilder(tilted, GraphOptions(drag_max_tilt_deg=5.0))
    n_kf = int((b.t_kf < flight.imu.t[0] + 2.0).sum())
    skipped = b.skipped["drag:not-thrust-borne"]
    assert abs(skipped - n_kf) <= 2, (skipped, n_kf)
    assert np.all(b.drag_count[b.t_kf < flight.imu.t[0] + 1.9] == 0)
    assert "drag:not-thrust-borne" not in GraphBuilder(flight, GraphOptions()).skipped
    off = GraphBuilder(tilted, GraphOptions(drag_max_tilt_deg=180.0))
    assert "drag:not-thrust-borne" not in off.skipped


def test_drag_noise_floor_from_measured_vibration(flight):
    clean = GraphBuilder(flight, GraphOptions())
    assert clean.drag_sigma == pytest.approx(GraphOptions().drag_model_sigma)
    rng = np.random.default_rng(4)
    a = flight.imu.body_accel.copy()
    a[:, :2] += rng.normal(0.0, 0.3, (len(a), 2))  # rotor vibration, white at 200 Hz
    b = GraphBuilder(_with_accel(flight, a), GraphOptions())
    n = float(np.median(b.drag_count[b.drag_count > 0]))
    expected = 0.3 / math.sqrt(n)  # scatter of a keyframe's mean of n samples
    assert b.drag_sigma == pytest.approx(expected, rel=0.25), (b.drag_sigma, expected)
    fixed = GraphBuilder(_with_accel(flight, a), GraphOptions(drag_sigma_from_data=False))
    assert fixed.drag_sigma == GraphOptions().drag_model_sigma


def test_marginal_query_failure_falls_back_to_regularised_covariances():
    """GTSAM can report an indeterminate system only when a marginal is queried (seen on EuRoC
    MH_01 with the FLU body and an ungated drag factor): the batch then uses the regularised
    marginals instead of crashing."""
    import gtsam

    from fgnav.solvers.batch import _marginal_covariances

    x0 = gtsam.symbol("x", 0)
    g = gtsam.NonlinearFactorGraph()
    g.add(gtsam.PriorFactorVector(x0, np.zeros(2), gtsam.noiseModel.Isotropic.Sigma(2, 0.5)))
    values = gtsam.Values()
    values.insert(x0, np.zeros(2))

    class Failing:
        def marginalCovariance(self, key):
            raise RuntimeError("Indeterminant linear system detected while working near variable")

    info: dict = {}
    covs = _marginal_covariances(Failing(), g.linearize(values), values, [x0], info)
    np.testing.assert_allclose(covs[x0], 0.25 * np.eye(2), rtol=1e-3)
    assert info["covariance_regularised"] is True


def test_drag_windows_are_the_keyframe_accel_windows(flight):
    """The drag factor's keyframe means and arrival times come from the same windows as the
    other keyframe specific-force means: half the shorter neighbouring interval each side."""
    b = GraphBuilder(flight, GraphOptions())
    t = b.t_kf
    gaps = np.diff(t)
    half = 0.5 * np.concatenate([[gaps[0]], np.minimum(gaps[1:], gaps[:-1]), [gaps[-1]]])
    np.testing.assert_array_equal(b._kf_half_windows(), half)
    np.testing.assert_array_equal(b.drag_arrival, t + half)
    # A direct mean of the IMU samples in [t - half, t + half] (no thrust-borne gate trips on
    # this flight, so every keyframe with a sample keeps it).
    imu_t, acc = flight.imu.t, flight.imu.body_accel
    for k in (0, 1, len(t) // 2, len(t) - 1):
        inside = (imu_t >= t[k] - half[k]) & (imu_t <= t[k] + half[k])
        assert b.drag_count[k] == inside.sum() > 0
        np.testing.assert_allclose(b.drag_mean[k], acc[inside, :2].mean(axis=0), atol=1e-12)
    means, counts = b._kf_accel_means()
    np.testing.assert_array_equal(means[:, :2], b.drag_mean)
    np.testing.assert_array_equal(counts, b.drag_count)
