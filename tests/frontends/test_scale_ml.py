"""Closed-form ML scale (seed 004 / Engel et al.): formula vs numerical maximisation, statistical
recovery of a known scale, gating, sessions and pairs from a synthetic flight."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import matrix_to_quat_wxyz, rpy_to_matrix
from fgnav.datasets.types import Flight, SlamSeries
from scipy.optimize import minimize_scalar

from fgnav.frontends.scale_ml import (
    MLScaleEstimator,
    MLScaleOptions,
    PairOptions,
    estimate_scale,
    ml_scale,
    profile_nll,
    scale_pairs_from_flight,
)


def _pairs(rng, n, s_true, sigma_x, sigma_y, d=3, spread=0.5):
    mu = rng.normal(0.0, spread, (n, d))
    x = s_true * mu + rng.normal(0.0, sigma_x, (n, d))
    y = mu + rng.normal(0.0, sigma_y, (n, d))
    return x, y


def test_closed_form_equals_numerical_maximum_likelihood():
    rng = np.random.default_rng(0)
    for s_true, sx, sy in [(0.3, 0.01, 0.05), (2.5, 0.2, 0.02), (1.0, 0.05, 0.05)]:
        x, y = _pairs(rng, 40, s_true, sx, sy)
        A, B, C = np.sum(x * x), np.sum(y * y), np.sum(x * y)
        s_cf = ml_scale(A, B, C, sx, sy)

        # Full likelihood over s and the nuisance mu_i, minimised numerically over s (mu_i in
        # closed form for a given s, which is exact: the NLL is quadratic in mu).
        def full_nll(s, x=x, y=y, sx=sx, sy=sy):
            mu = (s * x / sx**2 + y / sy**2) / (s * s / sx**2 + 1 / sy**2)
            return 0.5 * np.sum((x - s * mu) ** 2) / sx**2 + 0.5 * np.sum((y - mu) ** 2) / sy**2

        s_num = minimize_scalar(
            full_nll, bounds=(1e-3, 10.0), method="bounded", options={"xatol": 1e-10}
        ).x
        assert s_cf == pytest.approx(s_num, rel=1e-6)
        assert profile_nll(s_cf, A, B, C, sx, sy) == pytest.approx(full_nll(s_cf), rel=1e-9)
    # Limits: exact metric -> least squares of x on y; exact SLAM -> A / C.
    x, y = _pairs(rng, 30, 0.7, 0.02, 0.02)
    A, B, C = np.sum(x * x), np.sum(y * y), np.sum(x * y)
    assert ml_scale(A, B, C, 0.02, 1e-9) == pytest.approx(C / B, rel=1e-6)
    assert ml_scale(A, B, C, 1e-9, 0.02) == pytest.approx(A / C, rel=1e-6)


def test_recovers_known_scale_within_statistical_bounds():
    """Over 200 Monte-Carlo runs the estimate is unbiased within 3 standard errors and its spread
    matches the reported sigma (Fisher information) within 20 %; the naive ratio sum|x|/sum|y|
    is biased when the metric side is noisy."""
    rng = np.random.default_rng(1)
    s_true, sx, sy = 0.45, 0.02, 0.04
    est, sig, naive = [], [], []
    for _ in range(200):
        x, y = _pairs(rng, 30, s_true, sx, sy, spread=0.3)
        e = MLScaleEstimator(
            MLScaleOptions(
                sigma_slam=sx, sigma_metric=sy, min_metric_displacement=0.0, gate_chi2=1e9
            )
        )
        for xi, yi in zip(x, y, strict=True):
            e.add_pair(xi, yi)
        est.append(e.scale)
        sig.append(e.sigma)
        naive.append(np.sum(x * y) / np.sum(y * y))
    est = np.asarray(est)
    assert abs(est.mean() - s_true) < 3 * est.std() / np.sqrt(len(est))
    assert est.std() == pytest.approx(np.mean(sig), rel=0.2)
    # Least squares of x on noisy y shrinks the scale by B_true / (B_true + n d sigma_y^2).
    assert np.mean(naive) < s_true - 3 * np.std(naive) / np.sqrt(len(naive))


def test_gating_and_small_displacements_are_counted():
    rng = np.random.default_rng(2)
    x, y = _pairs(rng, 40, 1.3, 0.01, 0.02, spread=0.5)
    e = MLScaleEstimator(MLScaleOptions(sigma_slam=0.01, sigma_metric=0.02))
    big = np.linalg.norm(y, axis=1) >= 0.1
    for k, (xi, yi) in enumerate(zip(x, y, strict=True)):
        if k == 20:
            e.add_pair(xi * 3.0, yi)  # a SLAM jump (relocalisation): must be gated
        e.add_pair(xi, yi, t=float(k))
    assert e.counts["outlier"] == 1
    assert e.counts["too_small"] == int((~big).sum())
    assert e.counts["accepted"] == int(big.sum())
    assert e.scale == pytest.approx(1.3, rel=0.02)
    assert e.metric_per_slam_unit == pytest.approx(1 / e.scale)
    hist = np.asarray(e.history)
    assert hist.shape == (int(big.sum()), 4) and np.all(np.diff(hist[:, 3]) == 1)
    with pytest.raises(FlightDataError, match="same length"):
        e.add_pair([1.0, 2.0], [1.0])


def _vertical_flight(seed, s_by_session=(0.8, 2.0), reset_t=20.0):
    """Up/down at 0.5 m/s; SLAM frame rotated (camera down), per-session scale and offset."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, 40.0, 0.05)  # 20 Hz SLAM
    z = 2.0 + np.sin(2 * np.pi * t / 8.0)
    pos = np.stack([0.2 * np.sin(0.3 * t), 0.1 * t, z], axis=1)
    world_R_body = np.stack([rpy_to_matrix(0.02, -0.01, 0.5 + 0.01 * k) for k in range(len(t))])
    body_R_cam = rpy_to_matrix(np.pi, 0.0, -np.pi / 2)  # camera looking down
    session = (t >= reset_t).astype(int)
    slam_R_world = [rpy_to_matrix(0.3, 0.1, -1.0), rpy_to_matrix(-0.2, 0.4, 2.0)]
    slam_t = np.empty_like(pos)
    slam_q = np.empty((len(t), 4))
    for k in range(len(t)):
        sid = session[k]
        s = s_by_session[sid]
        slam_t[k] = s * slam_R_world[sid] @ pos[k] + [1.0, -2.0, 0.5] + rng.normal(0, 0.005, 3)
        slam_q[k] = matrix_to_quat_wxyz(slam_R_world[sid] @ world_R_body[k] @ body_R_cam)
    from fgnav.datasets.geometry import make_pose
    from fgnav.datasets.types import Calibration

    flight = Flight(
        name="vertical-scale",
        slam=SlamSeries(t=t, slam_t_cam=slam_t, slam_q_cam_wxyz=slam_q, session=session),
        calib=Calibration(body_T_cam=make_pose(body_R_cam, np.zeros(3))),
    ).check()
    q_att = matrix_to_quat_wxyz(world_R_body)
    height = (t, z + rng.normal(0, 0.01, len(t)))
    vel = (t, np.gradient(pos, t, axis=0))
    return flight, q_att, height, vel


def test_pairs_from_flight_per_session_vertical_and_xyz():
    flight, q_att, height, vel = _vertical_flight(seed=3)
    for comp in ("vertical", "xyz"):
        pairs = scale_pairs_from_flight(
            flight, q_att, height=height, world_velocity=vel, options=PairOptions(components=comp)
        )
        assert set(pairs.world_R_slam) == {0, 1}
        res = estimate_scale(pairs, MLScaleOptions(sigma_slam=0.01, sigma_metric=0.02))
        assert res.scale[0] == pytest.approx(0.8, rel=0.02)
        assert res.scale[1] == pytest.approx(2.0, rel=0.02)
        assert res.sigma[0] < 0.02
        # Each session's history starts from its own first pair.
        assert res.history[1][0, 0] >= 20.0
    with pytest.raises(FlightDataError, match="height"):
        scale_pairs_from_flight(flight, q_att, options=PairOptions(components="vertical"))


def test_simulated_vertical_flight_scale():
    """Seed 004's vertical experiment on the simulator: rangefinder height pairs every second.
    Measured (seed 0): 8 % after 2 s, 1.3 % after 5 s, 0.2-0.9 % from 6 s on."""
    from fgnav.datasets.geometry import interpolate_quat_wxyz
    from fgnav.datasets.simulate import SimOptions, simulate

    from fgnav.frontends.ii_observer import vertical_velocity_from_range

    flight = simulate("vertical", 0, SimOptions(images=False, duration=20.0))
    att = flight.attitude
    q_imu = interpolate_quat_wxyz(att.t, att.world_q_body_wxyz, flight.imu.t)
    q_slam = interpolate_quat_wxyz(att.t, att.world_q_body_wxyz, flight.slam.t)
    vv = vertical_velocity_from_range(flight, q_imu)
    pairs = scale_pairs_from_flight(
        flight, q_slam, height=(vv.t, vv.height), options=PairOptions(components="vertical")
    )
    res = estimate_scale(pairs, MLScaleOptions(sigma_slam=0.015, sigma_metric=0.02))
    truth = flight.meta["truth"]["slam_sessions"]["0"]
    hist = res.history[0]
    s_t = truth["scale"] * (1 + truth["scale_drift_per_s"] * (hist[:, 0] - truth["t_start"]))
    rel = np.abs(hist[:, 1] / s_t - 1)
    assert rel[hist[:, 0] >= 5.0].max() < 0.03
    assert rel[-1] < 0.015
    # The reported sigma covers the final error.
    assert rel[-1] * s_t[-1] < 3 * res.sigma[0]
