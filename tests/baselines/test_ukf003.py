"""Seed 003 UKF with state augmentation, against simulator truth.

Bounds are about 1.5-2x the values measured with this code (quoted in each test), so that a
regression shows and seed-to-seed noise does not."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import quat_wxyz_to_matrix, rpy_to_matrix, so3_exp, so3_log
from fgnav.datasets.simulate import SimOptions, simulate
from testutil import assert_same_prefix, feed_until, truth_scale

from fgnav.baselines.ukf003 import (
    N_MAIN,
    Ukf003Options,
    body_rotation_jacobian,
    euler_rate_matrix,
    euler_to_matrix,
    matrix_to_euler,
    run_ukf003,
)
from fgnav.eval.metrics import evaluate


def test_euler_helpers_round_trip_and_rates():
    rng = np.random.default_rng(0)
    phi = np.column_stack(
        [rng.uniform(-np.pi, np.pi, 20), rng.uniform(-1.2, 1.2, 20), rng.uniform(-3, 3, 20)]
    )
    R = euler_to_matrix(phi)
    for k in range(3):
        yaw, pitch, roll = phi[k]
        np.testing.assert_allclose(R[k], rpy_to_matrix(roll, pitch, yaw), atol=1e-12)
    np.testing.assert_allclose(euler_to_matrix(matrix_to_euler(R)), R, atol=1e-12)
    # E maps body rates to Euler rates; J is its inverse (R(phi + dphi) = R Exp(J dphi)).
    h = 1e-6
    for k in range(5):
        E, J = euler_rate_matrix(phi[k]), body_rotation_jacobian(phi[k])
        np.testing.assert_allclose(E @ J, np.eye(3), atol=1e-9)
        w = rng.normal(size=3)
        R1 = euler_to_matrix((phi[k] + h * E @ w)[None])[0]
        np.testing.assert_allclose(so3_log(R[k].T @ R1) / h, w, atol=1e-5)
        np.testing.assert_allclose(R[k] @ so3_exp(h * w), R1, atol=1e-10)


def test_noise_free_flight_with_true_scale_is_exact():
    """Noise-free rectangle, true initial scale: the relative-measurement model, the clones at
    image times and the delayed fusion (0.1 s latency) are consistent. Measured: ATE 4.8 mm,
    velocity 5.4 mm/s (IMU integration at 200 Hz and the unmodelled 0.05 %/s scale drift)."""
    flight = simulate("rectangle", 1, SimOptions(images=False, duration=10.0, noise_free=True))
    s_true = truth_scale(flight)[0]
    est = run_ukf003(flight, Ukf003Options(initial_scale=s_true, initial_scale_rel_sigma=0.01))
    m = evaluate(est, flight.ground_truth, "se3")
    assert m.ate_rmse_m < 0.01
    assert m.vel_rmse_mps < 0.01
    assert est.info["counts"]["slam_rejected_gate"] == 0


def test_rectangle_against_truth():
    """Rectangle, 20 s, seed 1, default noise (SLAM 1 cm, 0.1 s latency). Measured: ATE (SE3)
    1.3 cm, velocity 3.0 cm/s, yaw 0.21 deg, final scale +0.6 % (seed 2: 1.1 cm, 2.1 cm/s,
    +0.5 %); 1.7 s for 20 s of flight. (Before the SLAM noise of each image was cloned with its
    pose: 4.2 cm, 4.2 cm/s, -0.1 %.)"""
    flight = simulate("rectangle", 1, SimOptions(images=False, duration=20.0))
    est = run_ukf003(flight)
    assert est.method == "ukf003" and est.causal
    m = evaluate(est, flight.ground_truth, "se3", truth_scale=truth_scale(flight))
    assert m.ate_rmse_m < 0.08
    assert m.vel_rmse_mps < 0.08
    assert m.yaw_rmse_deg < 1.0
    assert abs(m.scale_final_err_pct[0]) < 3.0
    c = est.info["counts"]
    # The filter starts (causally) at the end of the closed-form initialisation window; every
    # later SLAM pose is fused but the first (the first keyframe) and those arriving after the last
    # IMU sample (0.1 s latency); none gated, lost or out of order here.
    t_init = flight.slam.t[0] + c["extra"]["init_window_s"][1]
    assert est.trajectory.t[0] >= t_init
    assert c["slam_updates"] > 0.97 * np.count_nonzero(flight.slam.t > t_init)
    assert c["slam_rejected_gate"] == 0 and c["slam_out_of_order"] == 0
    assert c["cholesky_jitter"] == 0
    assert c["range_updates"] > 0.9 * np.count_nonzero(flight.range.t >= t_init)
    assert est.pose_cov.shape == (len(est.trajectory), 6, 6)
    assert np.all(np.linalg.eigvalsh(est.pose_cov) > 0)
    # 100 Hz output (Shen's fused rate).
    assert abs(est.trajectory.rate_hz - 100.0) < 1.0


def test_event_fed_filter_is_causal():
    """Fed events in arrival order, the output up to T does not depend on what arrives later."""
    from fgnav.datasets.events import flight_streams, replay

    from fgnav.baselines.ukf003 import CameraTrigger, Ukf003

    flight = simulate("rectangle", 1, SimOptions(images=False, duration=20.0))
    full = run_ukf003(flight)
    t_cut = 12.0
    filt = Ukf003()
    filt.start(flight.calib, flight.name)
    streams = flight_streams(flight, ("imu", "slam", "range", "yaw", "attitude"))
    trig = (CameraTrigger(float(t), float(t)) for t in flight.slam.t)
    events = replay([streams.pop("imu"), trig, *streams.values()])
    assert_same_prefix(feed_until(filt, events, t_cut), full, t_cut=t_cut)
    assert filt.latest().shape == (N_MAIN,)


def test_map_reset_restarts_the_scale():
    """A SLAM map reset at 12 s (new frame and scale): the filter waits for the closed-form fit
    on the new map, then continues. Measured: 1 reset, 80 poses waiting, new-map scale +0.8 %,
    ATE 6.6 cm."""
    flight = simulate("rectangle", 1, SimOptions(images=False, duration=30.0, slam_resets=(12.0,)))
    est = run_ukf003(flight)
    c = est.info["counts"]
    assert c["session_resets"] == 1
    assert c["slam_waiting_reinit"] > 0
    truth = truth_scale(flight)
    assert set(est.slam_scale) == {0, 1}
    assert abs(est.slam_scale[1] / truth[1] - 1) < 0.05
    m = evaluate(est, flight.ground_truth, "se3")
    assert m.ate_rmse_m < 0.2


def test_missing_streams_are_named():
    flight = simulate("hover", 0, SimOptions(images=False, duration=2.0))
    with pytest.raises(FlightDataError, match="missing slam"):
        run_ukf003(dataclasses.replace(flight, slam=None))
    with pytest.raises(FlightDataError, match="missing imu, slam"):
        run_ukf003(dataclasses.replace(flight, slam=None, imu=None))


@pytest.mark.slow
@pytest.mark.parametrize(
    ("scenario", "seed", "ate", "nees"),
    [("two-turns", 0, 0.049, 2.7), ("figure8", 1, 0.027, 1.8)],
)
def test_position_nees_is_consistent(scenario, seed, ate, nees):
    """Full-length flights, default noise: the position NEES (3 for a consistent filter) with the
    SLAM noise of every image in its clone. Measured (quoted in the parameters): two-turns seed 0
    ATE 4.9 cm, NEES 2.7; figure8 seed 1 2.7 cm, 1.8 (before: NEES 13.9 and 6.8, ATE 8.6 and
    7.7 cm, each relative SLAM measurement taken as independent of the others of its
    keyframe). The filter starts after the closed-form initialisation window (causal).

    At the simulator's scale drift of 5e-4 per second (its default until 2026-11), which the
    filter's scale and map-drift walks cover; at the present default, 1e-4 per second, the filter
    is underconfident on figure8 (NEES 0.55, ATE 2.0 cm; two-turns 1.9, 4.4 cm)."""
    flight = simulate(scenario, seed, SimOptions(images=False, slam_scale_drift_per_s=5e-4))
    est = run_ukf003(flight)
    m = evaluate(est, flight.ground_truth, "se3", truth_scale=truth_scale(flight))
    assert m.ate_rmse_m < 1.6 * ate
    assert 0.8 < m.nees_pos < 1.6 * nees
    assert abs(m.scale_final_err_pct[0]) < 3.0
    assert est.info["counts"]["extra"]["init_window_s"][1] <= 8.0


def _x_up(flight):
    """The flight re-expressed in a body with x along the old body z (EuRoC's IMU frame has x
    up); the yaw stream is dropped (a yaw of the old body x axis does not convert)."""
    from fgnav.datasets.frames import rotate_body_frame

    new_R_old = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    return rotate_body_frame(dataclasses.replace(flight, yaw=None), new_R_old)


def test_body_with_x_up_runs_in_an_internal_body():
    """Body x up (pitch -90 deg for the ZYX Euler angles): the filter runs in a body with z along
    the initial specific force and rotates its estimate back. Measured (rectangle, 20 s, seed 1,
    no yaw stream): ATE 1.3 cm in both bodies, final orientation error 0.4 deg."""
    flight = dataclasses.replace(
        simulate("rectangle", 1, SimOptions(images=False, duration=20.0)), yaw=None
    )
    plain = run_ukf003(flight)
    tilted = _x_up(flight)
    est = run_ukf003(tilted)
    assert "internal_body_R_body" in est.info and "internal_body_R_body" not in plain.info
    m = evaluate(est, tilted.ground_truth, "se3")
    m0 = evaluate(plain, flight.ground_truth, "se3")
    assert m.ate_rmse_m < 0.03
    assert abs(m.ate_rmse_m - m0.ate_rmse_m) < 0.01
    # The orientation is the tilted body's: against its truth, as small as in the plain run.
    R_est = quat_wxyz_to_matrix(est.trajectory.world_q_body_wxyz[-1])
    k = np.searchsorted(tilted.ground_truth.t, est.trajectory.t[-1])
    R_gt = quat_wxyz_to_matrix(tilted.ground_truth.world_q_body_wxyz[k])
    assert np.degrees(np.linalg.norm(so3_log(R_gt.T @ R_est))) < 2.0
    assert np.all(np.linalg.eigvalsh(est.pose_cov) > 0)


@pytest.mark.slow
@pytest.mark.realdata
def test_euroc_mh01_in_the_imu_body(real_data):
    """EuRoC MH_01 with ORB-SLAM3 mono, body = the IMU frame (x up): the filter runs in its
    internal body. Measured: ATE 0.147 m (msf-ekf 0.081-0.091 m), final scale +1.5 %, position
    NEES 57 (overconfident: ORB-SLAM drifts more than ``slam_drift_walk_*``; 163 without the
    drift walk, 11 with 2.5 times larger walks, which make the simulated flights underconfident,
    NEES 0.5)."""
    from fgnav.datasets.load import load_flight
    from testutil import PROJECT_ROOT

    from fgnav.eval.metrics import slam_scale_vs_truth

    flight = load_flight(PROJECT_ROOT / "datasets" / "manifests" / "euroc_mh01_orbslam3.toml")
    est = run_ukf003(flight)
    assert "internal_body_R_body" in est.info
    s_true = slam_scale_vs_truth(flight.slam, flight.ground_truth, flight.calib.body_T_cam)
    m = evaluate(est, flight.ground_truth, "se3", truth_scale=s_true)
    assert m.ate_rmse_m < 0.25
    assert abs(m.scale_final_err_pct[0]) < 4.0
