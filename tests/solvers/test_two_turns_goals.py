"""Issue 6's figures on the whole simulated two-turns flight with every sensor (camera included).

Measured (seeds 0/1/2, 320x240 images): batch ATE 0.58/0.63/0.45 cm, fixed-lag 0.73/1.07/0.83 cm;
final SLAM scale error batch -0.12/-0.39/-0.29 %, fixed-lag -0.14/-0.34/-0.22 %; drag kx within
1.9 % of truth.
"""

from __future__ import annotations

import pytest
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate
from testutil import truth_scale_at

from fgnav.eval.metrics import evaluate
from fgnav.solvers.batch import BatchOptions, solve_batch
from fgnav.solvers.fixed_lag import FixedLagOptions, run_fixed_lag


@pytest.mark.slow
def test_two_turns_all_sensors_batch_and_fixed_lag_goals():
    f = simulate("two-turns", seed=1, options=SimOptions())
    assert f.images is not None and f.meta["truth"]["slam_sessions"]["0"]["scale_drift_per_s"] > 0
    s_end = truth_scale_at(f, float(f.slam.t[-1]))
    kx_true = f.meta["truth"]["drag_k"][0]
    batch = solve_batch(f, BatchOptions(covariance="slow"))
    online = run_fixed_lag(f, FixedLagOptions(lag_s=2.0))
    assert batch.info["factors"].get("homography", 0) > 0
    for est, ate_max in ((batch, 0.01), (online, 0.02)):
        m = evaluate(est, f.ground_truth, alignment="se3")
        assert m.ate_rmse_m <= ate_max, (est.method, m.ate_rmse_m)
        assert m.vel_rmse_mps < 0.015, (est.method, m.vel_rmse_mps)
        assert abs(est.slam_scale[0] / s_end - 1.0) <= 0.005, (est.method, est.slam_scale[0])
        assert abs(est.drag_k[0] / kx_true - 1.0) <= 0.05, (est.method, est.drag_k)


@pytest.mark.slow
def test_two_turns_stress_drift_final_scale_within_its_sigma():
    """At five times the default drift (1.4 % over the flight) the flight's end scale is at the
    information limit of these sensors (the IMU bias walk absorbs most of a drift this slow): the
    batch estimate lags, but its reported sigma covers the error (measured -0.45 %, sigma
    0.50 %)."""
    f = simulate("two-turns", seed=1, options=SimOptions(images=False, slam_scale_drift_per_s=5e-4))
    est = solve_batch(f, BatchOptions(covariance="slow"))
    err = est.slam_scale[0] - truth_scale_at(f, float(f.slam.t[-1]))
    sigma = est.slam_scale_sigma[0]
    assert 0 < sigma < 0.01 * est.slam_scale[0]
    assert abs(err) < 2.0 * sigma, (err, sigma)
