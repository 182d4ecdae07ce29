from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import ordered_product, quat_wxyz_to_matrix, so3_exp

from fgnav.solvers.measurements import (
    associate,
    gyro_bias_from_slam,
    init_slam_alignment,
    keyframe_times,
    mean_in_windows,
)


def test_keyframe_times_anchor_and_fill():
    anchors = np.array([0.0, 0.1, 0.2, 1.0, 1.05, 1.1])
    t = keyframe_times(0.0, 1.2, 10.0, anchors)
    # Anchors kept, the 0.2 -> 1.0 gap filled every 0.1 s, 1.05 dropped (closer than 0.75 period).
    np.testing.assert_allclose(t[:3], [0.0, 0.1, 0.2])
    assert 1.0 in t and 1.1 in t and 1.05 not in t
    assert np.all(np.diff(t) >= 0.075 - 1e-12) and np.all(np.diff(t) <= 0.15 + 1e-12)
    with pytest.raises(FlightDataError, match="keyframe rate"):
        keyframe_times(0.0, 1.0, 0.0)


def test_associate_nearest_tolerance_and_decimation():
    t_kf = np.array([0.0, 1.0, 2.0])
    a = associate(np.array([0.01, 0.02, 0.6, 1.99, 5.0]), t_kf, tolerance=0.05)
    np.testing.assert_array_equal(a.keyframe, [0, 2])
    np.testing.assert_array_equal(a.meas_index, [0, 3])
    assert a.skipped == {
        "no-keyframe-within-tolerance": 1,
        "after-last-keyframe": 1,
        "decimated": 1,
    }
    b = associate(np.array([-1.0, 0.0]), t_kf, tolerance=0.05)
    assert b.skipped == {"before-first-keyframe": 1}
    np.testing.assert_allclose(a.dt, [0.01, -0.01])


def test_mean_in_windows_counts():
    t = np.arange(0.0, 1.0, 0.01)
    x = np.column_stack([t, 2 * t])
    m, n = mean_in_windows(t, x, np.array([0.5, 5.0]), 0.05)
    assert n[0] == 11 and n[1] == 0
    np.testing.assert_allclose(m[0], [0.5, 1.0], atol=1e-9)
    assert np.all(np.isnan(m[1]))


def test_init_slam_alignment_recovers_similarity(two_turns_20s):
    f = two_turns_20s
    truth = f.meta["truth"]["slam_sessions"]["0"]
    R_imu = np.array([quat_wxyz_to_matrix(q) for q in f.ground_truth.world_q_body_wxyz])
    init = init_slam_alignment(f.slam, f.imu, R_imu, f.calib.body_T_cam, 9.81)
    # Scale drifts 5e-4/s in the simulator: compare with the mean over the flight.
    s_mean = truth["scale"] * (1 + truth["scale_drift_per_s"] * 10.0)
    assert abs(init.scale / s_mean - 1) < 0.05
    R_err = init.slam_R_world @ np.asarray(truth["slam_R_world"]).T
    assert np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1))) < 1.0
    assert init.excitation > 0.05


def test_gyro_bias_from_slam_matches_the_simulated_bias(two_turns_20s):
    f = two_turns_20s
    b = gyro_bias_from_slam(f.imu, f.slam, np.asarray(f.calib.body_T_cam))
    true = f.ground_truth.gyro_bias.mean(axis=0)
    # Median over 20 windows of 1 s with SLAM orientation noise: measured 3.0e-3 rad/s off on x
    # (0.4e-3 on the 180 s figure8), against a bias of 1.2e-2 rad/s.
    assert np.linalg.norm(true) > 0.01
    assert np.linalg.norm(b - true) < 0.3 * np.linalg.norm(true), (b, true)


def test_ordered_product_equals_the_sequential_product():
    rng = np.random.default_rng(3)
    for n in (0, 1, 2, 7, 200):
        R = so3_exp(rng.normal(0.0, 0.3, (n, 3)))
        expected = np.eye(3)
        for Ri in R:
            expected = expected @ Ri
        assert np.allclose(ordered_product(R), expected, atol=1e-12)
