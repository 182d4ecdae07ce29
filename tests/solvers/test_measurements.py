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
    slam_second_differences,
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


def test_second_differences_on_keyframes_match_the_imu_exactly():
    # Irregular 3 Hz keyframes with gaps of a sinusoidal motion: the divided differences on the
    # samples equal the hat-kernel integral of the acceleration (no interpolation bias).
    rng = np.random.default_rng(4)
    t_kf = np.cumsum(rng.uniform(0.2, 0.45, 120))
    t_kf = t_kf[(t_kf < 12.0) | (t_kf > 14.5)]  # a 2.5 s gap
    omega = 2.0 * np.pi * 0.8
    amp = np.array([1.0, -0.5, 0.3])

    def pos(t):
        return np.sin(omega * t)[:, None] * amp

    imu_t = np.arange(0.0, t_kf[-1] + 1.0, 0.005)
    world_a = -(omega**2) * pos(imu_t)
    scale = 2.7
    d = slam_second_differences(t_kf, scale * pos(t_kf), imu_t, world_a, h=0.5, step=0.1)
    assert len(d.centers) > 60
    assert np.all((d.width >= 0.25) & (d.width <= 1.0))
    assert not np.any((d.centers > 12.0) & (d.centers < 14.5))  # no triple spans the gap
    rel = np.linalg.norm(d.slam_d2 / scale - d.world_d2, axis=1) / np.linalg.norm(
        d.world_d2, axis=1
    )
    assert np.median(rel) < 1e-3
    # Positions interpolated between keyframes at +-h (the former method) are biased low.
    c = d.centers
    p_interp = np.stack(
        [
            np.column_stack([np.interp(c + s, t_kf, pos(t_kf)[:, a]) for a in range(3)])
            for s in (-0.5, 0.0, 0.5)
        ]
    )
    interp_d2 = p_interp[0] - 2 * p_interp[1] + p_interp[2]
    exact_d2 = pos(c + 0.5) - 2 * pos(c) + pos(c - 0.5)
    ratio = np.sum(interp_d2 * exact_d2) / np.sum(exact_d2**2)
    assert ratio < 0.9


def test_closed_form_scale_unbiased_on_3hz_keyframes():
    # Simulated 3 Hz SLAM keyframes (seed 000's two-turns): the closed-form fit within 2 % of the
    # truth (mean over the flight: the simulator drifts the scale 1e-4/s).
    from fgnav.datasets.simulate import SimOptions, simulate

    f = simulate(
        "two-turns", seed=1, options=SimOptions(duration=30.0, images=False, slam_rate_hz=3.0)
    )
    truth = f.meta["truth"]["slam_sessions"]["0"]
    R_imu = np.array([quat_wxyz_to_matrix(q) for q in f.ground_truth.world_q_body_wxyz])
    init = init_slam_alignment(f.slam, f.imu, R_imu, f.calib.body_T_cam, 9.81)
    s_mean = truth["scale"] * (1 + truth["scale_drift_per_s"] * 15.0)
    assert abs(init.scale / s_mean - 1) < 0.02
    # On the arrived prefix (what the online smoother calls): within 5 %.
    first = f.slam.select(f.slam.t <= 15.0)
    init15 = init_slam_alignment(first, f.imu, R_imu, f.calib.body_T_cam, 9.81)
    assert abs(init15.scale / truth["scale"] - 1) < 0.05


def test_init_slam_alignment_rotation_from_motion():
    """``rotation="motion"``: the SLAM rotation from the second differences and the rotation
    increments (no ``body_R_cam``) is within a degree of the truth on figure8's first 8 s
    (0.55 deg measured; spread 0.83), with an identity ``body_R_cam`` given (180 deg off) through
    which the orientations give no fit; a flight that only climbs (``vertical``: one
    direction, no turns) has a spread near 0 (0.001 measured: the rotation about the vertical
    is undetermined)."""
    from fgnav.datasets.simulate import SimOptions, simulate
    from fgnav.datasets.types import SlamSeries

    def head(f, seconds):
        n = f.slam.t < f.slam.t[0] + seconds
        return SlamSeries(f.slam.t[n], f.slam.slam_t_cam[n], f.slam.slam_q_cam_wxyz[n], None)

    def attitude(f):
        return np.array([quat_wxyz_to_matrix(q) for q in f.ground_truth.world_q_body_wxyz])

    f = simulate("figure8", seed=1, options=SimOptions(duration=20.0, images=False))
    truth = f.meta["truth"]["slam_sessions"]["0"]
    wrong = np.eye(4)  # the identity for a downward camera: 180 deg off
    wrong[:3, 3] = np.asarray(f.calib.body_T_cam)[:3, 3]
    init = init_slam_alignment(head(f, 8.0), f.imu, attitude(f), wrong, 9.81, rotation="motion")
    R_err = init.slam_R_world @ np.asarray(truth["slam_R_world"]).T
    assert np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1))) < 1.0
    assert init.rotation_spread > 0.5 and init.scale_rel_se < 0.05
    s_mean = truth["scale"] * (1 + truth["scale_drift_per_s"] * 4.0)
    assert abs(init.scale / s_mean - 1) < 0.05
    with pytest.raises(FlightDataError, match="does not match the IMU"):
        init_slam_alignment(head(f, 3.0), f.imu, attitude(f), wrong, 9.81)
    with pytest.raises(ValueError, match="rotation='gyro'"):
        init_slam_alignment(f.slam, f.imu, attitude(f), wrong, 9.81, rotation="gyro")
    v = simulate("vertical", seed=1, options=SimOptions(duration=20.0, images=False))
    up = init_slam_alignment(head(v, 8.0), v.imu, attitude(v), wrong, 9.81, rotation="motion")
    assert up.rotation_spread < 0.05
    # An estimated attitude wanders: its small increments must not pass for turns (a random walk
    # of 1e-5 rad per sample gave spreads of 0.33-0.81 and rotations 48-151 deg off when every
    # increment counted, whatever its size).
    rng = np.random.default_rng(0)
    walk = so3_exp(np.cumsum(rng.normal(0.0, 1e-5, (len(v.imu.t), 3)), axis=0))
    noisy = attitude(v) @ walk
    up = init_slam_alignment(head(v, 8.0), v.imu, noisy, wrong, 9.81, rotation="motion")
    assert up.rotation_spread < 0.05
