"""IMU saturation (issue 18): samples pinned at a rail flagged sample by sample, the IMU factors of
their keyframe intervals down-weighted on the pinned axes, in batch as online."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
from fgnav.datasets.events import ImuSample

from fgnav.compare import score_estimate
from fgnav.health import (
    SAT_ACCEL_BITS,
    SAT_GYRO_BITS,
    FaultDetectors,
    HealthOptions,
    imu_saturation_flags,
)
from fgnav.solvers.batch import BatchOptions, solve_batch
from fgnav.solvers.graph import GraphBuilder, saturated_pim_params

RNG_SEED = 0


def _series(rail: float = 0.5, n: int = 800, rate_hz: float = 200.0):
    """Gyro z a sine of amplitude 1 rad/s clipped at ``rail``, x and y noise, accelerometer at
    hover with noise."""
    rng = np.random.default_rng(RNG_SEED)
    t = np.arange(n) / rate_hz
    w = rng.normal(0.0, 0.01, (n, 3))
    w[:, 2] = np.clip(np.sin(2 * np.pi * 0.5 * t), -rail, rail)
    a = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, 0.05, (n, 3))
    return t, w, a


def test_flags_are_the_detectors_samples():
    t, w, a = _series()
    flags = imu_saturation_flags(t, w, a)
    det = FaultDetectors()
    for i in range(len(t)):
        det.feed(ImuSample(t[i], t[i], w[i], a[i]))
    assert det.imu_flags == flags[-1]
    pinned = np.abs(w[:, 2]) == 0.5
    # every flagged sample is pinned on gyro z, and nothing else is flagged
    assert np.all(((flags & SAT_GYRO_BITS[2]) != 0) == (flags != 0))
    assert np.all(pinned[flags != 0])
    assert np.all(flags[~pinned] == 0)
    assert not np.any(flags & (SAT_GYRO_BITS[0] | SAT_GYRO_BITS[1] | sum(SAT_ACCEL_BITS)))
    # causal: all pinned samples but the first saturation_run - 1 of the rail
    run = HealthOptions().saturation_run
    assert (flags != 0).sum() == pinned.sum() - (run - 1)
    # the detector counts every pinned sample (the first run at once when it is complete)
    assert det.counts["imu-saturation"] == pinned.sum()
    # a noisy gyro below any rail: nothing
    assert not imu_saturation_flags(t, w * 0.01, a).any()


def test_saturated_params_inflate_the_pinned_axis_only():
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(9.81)
    p.setGyroscopeCovariance(np.eye(3) * 1.7e-4**2)
    p.setAccelerometerCovariance(np.eye(3) * 2e-3**2)
    p.setIntegrationCovariance(np.eye(3) * 1e-8)
    n, dt = 10, 0.005
    w = np.tile([0.01, 0.02, 0.5], (n, 1))
    a = np.tile([0.0, 0.0, 9.81], (n, 1))
    flags = np.zeros(n, dtype=np.uint8)
    assert saturated_pim_params(p, w, a, flags, np.full(n, dt), 1.0) is p
    flags[4:] = SAT_GYRO_BITS[2]  # the last 6 samples pinned on z
    q = saturated_pim_params(p, w, a, flags, np.full(n, dt), 1.0)
    e = 1.0 * 0.5 * 6 * dt  # rotation error sigma of the pinned part [rad]
    gyro = np.diag(q.getGyroscopeCovariance())
    np.testing.assert_allclose(gyro[:2], 1.7e-4**2)
    np.testing.assert_allclose(gyro[2], 1.7e-4**2 + e**2 / (n * dt))
    np.testing.assert_allclose(q.getAccelerometerCovariance(), p.getAccelerometerCovariance())
    np.testing.assert_allclose(q.getBiasAccCovariance(), p.getBiasAccCovariance())
    np.testing.assert_allclose(q.n_gravity, p.n_gravity)
    np.testing.assert_allclose(np.diag(p.getGyroscopeCovariance()), 1.7e-4**2)  # unchanged
    # The preintegrated rotation of z then has the variance e^2 more (GTSAM integrates Q T).
    cov = {}
    for name, params in (("base", p), ("sat", q)):
        pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
        for i in range(n):
            pim.integrateMeasurement(a[i], w[i], dt)
        cov[name] = pim.preintMeasCov()
    np.testing.assert_allclose(cov["sat"][2, 2] - cov["base"][2, 2], e**2, rtol=0.02)
    np.testing.assert_allclose(cov["sat"][0, 0], cov["base"][0, 0], rtol=0.02)


def test_batch_gyro_saturation_recovers(two_turns_20s):
    """Batch over two-turns with the gyro clipped at 0.5 rad/s (the yaw rate reaches 1 rad/s):
    the down-weighted intervals are counted and the ATE stays near the unclipped solve's
    (before: 12x nominal on the 24 s matrix flight, LM not converged)."""
    f = two_turns_20s
    clipped = dataclasses.replace(
        f, imu=dataclasses.replace(f.imu, body_omega=np.clip(f.imu.body_omega, -0.5, 0.5))
    )
    b = GraphBuilder(clipped)
    n_sat = b.counts["imu-saturated-intervals"]
    assert 100 < n_sat < b.K - 1
    assert "imu-saturated-intervals" not in GraphBuilder(f).counts
    opts = BatchOptions(covariance="none")
    ate0 = score_estimate(f, solve_batch(f, opts)).ate_rmse_m
    est = solve_batch(clipped, opts)
    assert est.info["factors"]["imu-saturated-intervals"] == n_sat
    ate = score_estimate(clipped, est).ate_rmse_m
    assert ate < 1.5 * ate0 + 0.005, (ate, ate0)
