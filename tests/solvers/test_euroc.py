"""Batch smoother on real data: EuRoC MH_01 IMU + pure monocular ORB-SLAM3 (run A), no GT used."""

from __future__ import annotations

import pytest
from fgnav.datasets.load import load_flight
from testutil import PROJECT_ROOT

from fgnav.eval.metrics import evaluate, slam_scale_vs_truth
from fgnav.solvers.batch import BatchOptions, solve_batch

MANIFEST = PROJECT_ROOT / "datasets" / "manifests" / "euroc_mh01_orbslam3.toml"


@pytest.mark.slow
@pytest.mark.realdata
def test_euroc_mh01_metric_trajectory_and_scale(real_data):
    flight = load_flight(MANIFEST)
    # Default options: the EuRoC body is the IMU frame (x up), not FLU, so the builder switches
    # the rotor-drag model off by itself and says why.
    est = solve_batch(flight, BatchOptions(covariance="slow"))
    assert "body +z" in est.info["drag_disabled"]
    m = evaluate(est, flight.ground_truth, alignment="se3")
    # The SLAM run alone, Sim(3)-aligned, has 3.7 cm ATE; the metric estimate reaches 3-4 cm.
    assert m.ate_rmse_m < 0.06, m.ate_rmse_m
    s_true = slam_scale_vs_truth(flight.slam, flight.ground_truth, flight.calib.body_T_cam)[0]
    assert abs(est.slam_scale[0] / s_true - 1) < 0.01
    assert 0 < est.slam_scale_sigma[0] < 0.01 * s_true
