"""The push-API online smoother (fgnav.solvers.online): accuracy, causality, time rules, faults.

Measured on simulated two-turns, seed 1, no images (IMU, attitude, range, yaw, SLAM; 2026-12-02):
ATE 2.8-2.9 cm, final SLAM scale +0.1 %, no solver failures (the prepared runner: 3.2 cm).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from fgnav.datasets.events import (
    ImuSample,
    RangeReading,
    SlamPose,
    replay_flight,
)
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate

from fgnav.eval.metrics import evaluate
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.online import OnlineSmoother, feed_all, replay_online

STREAMS = ("imu", "attitude", "range", "yaw", "slam")


@pytest.fixture(scope="module")
def push_run(two_turns):
    return replay_online(two_turns, FixedLagOptions())


def _final_truth_scale(f) -> float:
    s = f.meta["truth"]["slam_sessions"]["0"]
    return s["scale"] * (1.0 + s["scale_drift_per_s"] * (float(f.slam.t[-1]) - s["t_start"]))


def test_push_two_turns_accuracy(two_turns, push_run):
    f, est = two_turns, push_run
    assert est.causal and est.method == "fixed-lag" and est.info["engine"] == "push-api"
    m = evaluate(est, f.ground_truth, alignment="se3")
    assert m.ate_rmse_m < 0.035, m.ate_rmse_m
    assert m.vel_rmse_mps < 0.04, m.vel_rmse_mps
    assert abs(est.slam_scale[0] / _final_truth_scale(f) - 1.0) < 0.005, est.slam_scale
    assert est.info["solver_failures"] == 0 and est.info["reset_counter"] == 0
    # Every SLAM pose is used or counted.
    used, dropped = est.info["used"], est.info["dropped"]
    left = {**dropped, **est.info["skipped"]}  # skipped: arrived after the last keyframe
    n_slam = used.get("slam", 0) + sum(v for k, v in left.items() if k.startswith("slam:"))
    assert n_slam == len(f.slam), (used, left)
    # A provisional pose moved onto the chain when it starts is counted apart, not used twice.
    assert used.get("slam:reattached", 0) > 0
    assert est.info["received"]["slam"] == len(f.slam)
    # The newest state's covariance is reported and covers the error (position NEES finite).
    assert est.pose_cov is not None and np.isfinite(est.pose_cov[-1]).all()
    assert np.all(np.linalg.eigvalsh(est.pose_cov[-1]) > 0)


def test_push_position_nees_is_consistent(two_turns, push_run):
    """Issue 15: the newest state's position covariance against its causal error (SE(3)
    alignment, as ``fgnav compare``): NEES between 1 and 6 (3 if consistent). Measured
    2026-12-02: 2.96 (the camera flights of the results table: 0.3-0.6, see
    ``scripts/nees_breakdown.py``)."""
    m = evaluate(push_run, two_turns.ground_truth, alignment="se3")
    assert m.n_nees > 0.9 * len(push_run.trajectory)
    assert 1.0 <= m.nees_pos <= 6.0, m.nees_pos


def test_push_is_causal(two_turns, push_run):
    """A run fed the events arrived up to T gives exactly the states of the full run up to T:
    nothing later changed them."""
    t_cut = 14.0
    events = [e for e in replay_flight(two_turns, STREAMS) if e.arrival <= t_cut]
    cut = feed_all(iter(events), two_turns.calib, FixedLagOptions()).result()
    full = push_run.trajectory
    n = len(cut.trajectory)
    assert n > 200 and cut.trajectory.t[-1] <= t_cut
    np.testing.assert_array_equal(cut.trajectory.t, full.t[:n])
    np.testing.assert_array_equal(cut.trajectory.world_t_body, full.world_t_body[:n])
    np.testing.assert_array_equal(cut.trajectory.world_v_body, full.world_v_body[:n])


def test_push_never_reads_the_flight(two_turns):
    """The smoother gets the calibration and events only: a flight stripped of its truth and
    metadata replays to the same states."""
    stripped = dataclasses.replace(two_turns, ground_truth=None, meta={})
    a = replay_online(stripped, FixedLagOptions())
    events = list(replay_flight(two_turns, STREAMS))
    b = feed_all(iter(events), two_turns.calib, FixedLagOptions()).result()
    np.testing.assert_array_equal(a.trajectory.world_t_body, b.trajectory.world_t_body)


def test_time_rules_and_bad_samples_are_counted(two_turns):
    calib = two_turns.calib
    sm = OnlineSmoother(calib, FixedLagOptions())
    evs = [e for e in replay_flight(two_turns, STREAMS) if e.arrival <= 3.0]
    imu = [e for e in evs if isinstance(e, ImuSample)]
    for e in evs:
        sm.feed(e)
    last = imu[-1]
    # A duplicate, an out-of-order sample, a NaN sample, an out-of-order range.
    sm.feed(last)
    sm.feed(imu[-5])
    sm.feed(ImuSample(last.t + 0.005, last.t + 0.005, np.full(3, np.nan), last.body_accel))
    t_rng = max(e.t for e in evs if isinstance(e, RangeReading))
    sm.feed(RangeReading(t_rng - 0.3, 3.0, 1.0))
    c = sm.counts()
    assert c["dropped"]["imu:duplicate"] == 1
    assert c["dropped"]["imu:out-of-order"] == 1
    assert c["dropped"]["imu:non-finite"] == 1
    assert c["dropped"]["range:out-of-order"] == 1
    assert sm.latest() is not None and sm.reset_counter == 0
    sm.reset()
    assert sm.latest() is None and sm.reset_counter == 1
    assert sm.counts()["dropped"]["reset:requested"] == 1
    with pytest.raises(TypeError):
        sm.feed(object())


def test_slam_pose_arriving_before_the_start_attaches_at_it(two_turns):
    """The start is at the first SLAM pose's capture time, once the IMU has passed it; a pose
    that came with no latency arrived before that (at equal arrival the IMU sample goes first)
    and was kept for the alignment fit but never attached nor counted. It attaches now (EuRoC
    V1_02 ORB-SLAM3 keyframes: causal ATE 3.46 -> 2.95 cm)."""
    f = two_turns
    evs = [
        e
        for e in replay_flight(f, STREAMS, latency={"slam": 0.0})
        if not (isinstance(e, SlamPose) and e.t < 1.0)
    ]
    n_slam = sum(isinstance(e, SlamPose) for e in evs if e.arrival <= 4.0)
    sm = feed_all(iter(e for e in evs if e.arrival <= 4.0), f.calib, FixedLagOptions())
    est = sm.result()
    assert est.trajectory.t[0] == pytest.approx(1.0)
    left = {**est.info["dropped"], **est.info["skipped"]}
    assert "slam:before-start" not in left
    n_left = sum(v for k, v in left.items() if k.startswith("slam:"))
    assert est.info["used"]["slam"] + n_left == n_slam, (est.info["used"], left)


@pytest.mark.slow
def test_jittered_replay_survives_and_counts(two_turns, push_run):
    f = two_turns
    rng = np.random.default_rng(5)
    jump_at, jump_s = 18.0, 5.0
    events = []
    pre, post = [], []
    for e in replay_flight(f, STREAMS):
        if isinstance(e, SlamPose):
            if rng.random() < 0.10:
                continue
            e = e._replace(arrival=e.t + rng.uniform(0.05, 0.5))
        elif isinstance(e, ImuSample):
            if rng.random() < 0.01:
                e = e._replace(arrival=e.t + rng.uniform(0.011, 0.026))
        else:
            e = e._replace(arrival=e.t + rng.uniform(0.0, 0.05))
        (pre if e.t < jump_at else post).append(e)
    pre.sort(key=lambda e: e.arrival)
    post.sort(key=lambda e: e.arrival)
    # After the jump every stamp is jump_s behind (the autopilot rebooted its clock).
    events = pre + [e._replace(t=e.t - jump_s, arrival=e.arrival - jump_s) for e in post]
    sm = OnlineSmoother(f.calib, FixedLagOptions())
    for e in events:
        sm.feed(e)
    c = sm.counts()
    assert sm.reset_counter == 1 and c["dropped"]["reset:imu-clock-jump"] == 1
    assert c["dropped"].get("imu:out-of-order", 0) > 10
    assert c["received"]["slam"] == sum(isinstance(e, SlamPose) for e in events)
    pre_est, post_est = sm.result(epoch=0), sm.result(epoch=-1)
    assert sm.result().info["clock_epochs"] == [len(pre_est.trajectory), len(post_est.trajectory)]
    # Before the jump: within 1.5x of the zero-jitter run on the same span.
    t_end = float(pre_est.trajectory.t[-1])
    assert t_end < jump_at and len(pre_est.trajectory) > 200
    ref = push_run
    keep = np.flatnonzero(ref.trajectory.t <= t_end)
    ref_est = dataclasses.replace(
        ref, trajectory=ref.trajectory.select(keep), pose_cov=None, vel_cov=None
    )
    m = evaluate(pre_est, f.ground_truth, alignment="se3")
    m_ref = evaluate(ref_est, f.ground_truth, alignment="se3")
    assert m.ate_rmse_m <= 1.5 * m_ref.ate_rmse_m, (m.ate_rmse_m, m_ref.ate_rmse_m)
    # After the jump the smoother re-initialised and produced states on the new clock.
    t = post_est.trajectory.t
    assert len(t) > 50 and t[0] < jump_at - jump_s + 1.0
    assert np.isfinite(post_est.trajectory.world_t_body).all()


def test_lagged_output_is_smoothed_and_delayed(two_turns, push_run):
    """``fixed-lag@lag``: the states as smoothed when they leave the window beat the newest
    states (measured 1.9 cm against 3.1 cm on this flight), each keyframe once, in time order."""
    lagged = replay_online(two_turns, FixedLagOptions(), lagged=True)
    assert lagged.method == "fixed-lag@lag" and not lagged.causal
    t = lagged.trajectory.t
    assert np.all(np.diff(t) > 0) and len(t) > 0.9 * len(push_run.trajectory)
    assert t[-1] <= push_run.trajectory.t[-1] - 1.0 + 1e-9  # lag 2 s, 1 s blocks
    m_lag = evaluate(lagged, two_turns.ground_truth, alignment="se3")
    m_new = evaluate(push_run, two_turns.ground_truth, alignment="se3")
    assert m_lag.ate_rmse_m < 0.8 * m_new.ate_rmse_m, (m_lag.ate_rmse_m, m_new.ate_rmse_m)


@pytest.mark.slow
def test_jittered_camera_replay():
    """With the camera: SLAM latency 50-500 ms, arrival jitter up to 20 ms (images) and 50 ms
    (attitude, range, yaw), 10 % of the frames dropped, 1 % of the IMU samples out of order: no
    crash, the rejections counted, ATE within 1.5x of the zero-jitter run (issue 14).
    Measured 2026-12-02 on this 30 s flight, jitter draws rng 11-16: 0.65-0.86 cm against 0.605
    cm without jitter, 0.93-1.42x (mean 1.19x; rng 11: 0.737 cm, 1.22x). On a 12 s flight of the
    same scenario and seed the ratio is 1.3-2.5x (0.38-0.71 against 0.287 cm, rng 11-16, mean
    1.9x): there the start-up before the SLAM alignment's fit (at 6 s, a provisional scale until
    then) is half the flight, and the newest state waits up to 0.5 s for its SLAM pose while the
    scale is unknown (1.1 against 0.44 cm in second 1-2; the SLAM latency alone gives 1.66x);
    after the fit the two runs differ by at most 3 mm per second. Every measurement is used as
    without jitter (the homography factors and keyframes are identical with the image jitter
    alone)."""
    from fgnav.datasets.events import ImageFrame

    f = simulate("two-turns", seed=2, options=SimOptions(duration=30.0))
    streams = ("imu", "attitude", "range", "yaw", "slam", "images")
    ref = replay_online(f, FixedLagOptions())
    assert ref.info["used"].get("homography", 0) > 100
    rng = np.random.default_rng(11)
    events = []
    for e in replay_flight(f, streams):
        if isinstance(e, ImageFrame) and rng.random() < 0.10:
            continue
        if isinstance(e, ImuSample):
            if rng.random() < 0.01:
                e = e._replace(arrival=e.t + rng.uniform(0.011, 0.026))
        elif isinstance(e, SlamPose):
            e = e._replace(arrival=e.t + rng.uniform(0.05, 0.5))
        elif isinstance(e, ImageFrame):
            e = e._replace(arrival=e.t + rng.uniform(0.0, 0.02))
        else:
            e = e._replace(arrival=e.t + rng.uniform(0.0, 0.05))
        events.append(e)
    events.sort(key=lambda e: e.arrival)
    opts = FixedLagOptions(image_latency_s=0.02)
    est = feed_all(iter(events), f.calib, opts).result()
    c = est.info
    assert c["dropped"].get("imu:out-of-order", 0) > 5
    assert c["received"]["images"] == sum(isinstance(e, ImageFrame) for e in events)
    m = evaluate(est, f.ground_truth, alignment="se3")
    m_ref = evaluate(ref, f.ground_truth, alignment="se3")
    assert m.ate_rmse_m <= 0.009 and m.ate_rmse_m <= 1.5 * m_ref.ate_rmse_m, (
        m.ate_rmse_m,
        m_ref.ate_rmse_m,
    )


def _still_then_accelerating(seed, gyro_bias, gyro_sigma, accel_bias, accel_sigma):
    """An :class:`OnlineSmoother` fed 5.2 s of 200 Hz IMU without SLAM: still and level (rotors
    on: white noise) until 3 s, then 1 m/s^2 along world x and z; it starts at the IMU at 5 s."""
    from fgnav.datasets.types import Calibration

    rng = np.random.default_rng(seed)
    sm = OnlineSmoother(Calibration(), FixedLagOptions())
    g = sm.go.gravity
    for i in range(int(5.2 * 200)):
        t = i / 200.0
        w = gyro_bias + rng.normal(0.0, gyro_sigma, 3)
        a = np.array([1.0, 0.0, g + 1.0]) if t >= 3.0 else np.array([0.0, 0.0, g])
        sm.feed(ImuSample(t, t, w, a + accel_bias + rng.normal(0.0, accel_sigma, 3)))
    return sm


def test_start_after_a_still_stretch_integrates_attitude_and_velocity_from_rest():
    """Still (level, rotors on) until 3 s, then a constant acceleration of 1 m/s^2 along world x
    and z until the start at the IMU (5 s): the start levels on the still stretch and integrates
    the IMU since, from rest (EuRoC V1_02 takes off 1.5 s before its start). Leveling on the
    specific force at the start instead tilts the attitude by atan(1 / (g + 1)) = 5.3 deg and
    starts at zero velocity."""
    sm = _still_then_accelerating(1, np.array([0.01, -0.02, 0.08]), 0.01, np.zeros(3), 0.3)
    assert sm.t0 == pytest.approx(5.0, abs=0.01)
    first = sm.out[0]
    z_body_in_world = first.world_T_body[:3, :3] @ np.array([0.0, 0.0, 1.0])
    tilt = math.degrees(math.acos(min(1.0, z_body_in_world[2])))
    assert tilt < 0.5, tilt
    # 2 s at 1 m/s^2 from rest along the body's x and z (level: the world's, up to the yaw).
    v_body = first.world_T_body[:3, :3].T @ first.world_v_body
    # (0.14 m/s off in x here: a 0.4 deg pitch of the 0.5 s still mean with this noise)
    np.testing.assert_allclose(v_body, [2.0, 0.0, 2.0], atol=0.2)
    assert math.sqrt(first.vel_cov[0, 0]) < 0.6


def test_accel_bias_along_gravity_from_the_still_stretch():
    """A still stretch measures |f| = g + the accelerometer bias along the specific force (across
    it a bias is one with the tilt of the level attitude, which absorbs it): the start's bias
    takes that part, and the velocity integrated from rest to the start no longer drifts with it.
    With a zero bias (before 2026-12-07) 0.06 m/s^2 over the 2 s to the start is 0.12 m/s; EuRoC
    V1_02's start drifted 30 cm in height before its second SLAM pose. Simulated two-turns and
    rectangle (still on the ground at the start): the bias's vertical part to 5 mm/s^2."""
    sm = _still_then_accelerating(3, np.zeros(3), 0.002, np.array([0.03, -0.02, 0.06]), 0.05)
    assert sm.t0 == pytest.approx(5.0, abs=0.01)
    first = sm.out[0]
    np.testing.assert_allclose(first.accel_bias, [0.0, 0.0, 0.06], atol=0.01)
    v_body = first.world_T_body[:3, :3].T @ first.world_v_body
    np.testing.assert_allclose(v_body[2], 2.0, atol=0.03)  # zero bias: 2.12

    from fgnav.datasets.events import replay_flight
    from fgnav.datasets.simulate import SimOptions, simulate

    from fgnav.keys import B
    from fgnav.solvers.online import PUSH_STREAMS

    for scenario in ("two-turns", "rectangle"):
        f = simulate(scenario, seed=1, options=SimOptions(images=False, duration=5.0))
        sm = OnlineSmoother(f.calib, FixedLagOptions())
        for ev in replay_flight(f, [n for n in PUSH_STREAMS if getattr(f, n, None) is not None]):
            sm.feed(ev)
            if sm.t0 is not None:
                break
        true_bias = f.ground_truth.accel_bias[np.searchsorted(f.ground_truth.t, sm.t0)]
        b0 = sm.values[B(0)].accelerometer()
        assert abs(b0[2] - true_bias[2]) < 0.005 and abs(true_bias[2]) > 0.015, (b0, true_bias)


def test_gyro_bias_start_from_the_newest_still_stretch():
    """A vehicle that stands (rotors on: vibration) and then moves before the start: the gyro
    bias starts from the still stretch's mean rate, whose size (0.08 rad/s, EuRoC's) is above any
    stillness tolerance on the rate itself."""
    from fgnav.datasets.types import Calibration

    rng = np.random.default_rng(0)
    bias = np.array([0.01, -0.02, 0.08])
    sm = OnlineSmoother(Calibration(), FixedLagOptions())
    g = sm.go.gravity
    st = None
    for i in range(int(6.0 * 200)):
        t = i / 200.0
        w = bias + rng.normal(0.0, 0.01, 3)  # vibration: rate scatter 0.01 rad/s
        a = np.array([0.0, 0.0, g]) + rng.normal(0.0, 0.5, 3)
        if t >= 3.0:  # then it moves (rates of 0.3-0.5 rad/s) until the start at 5 s
            w = w + np.array([0.5 * math.sin(3 * t), 0.3 * math.cos(2 * t), 0.2])
            a = a + np.array([math.sin(2 * t), 0.0, 0.0])
        st = sm.feed(ImuSample(t, t, w, a)) or st
    assert sm.t0 == pytest.approx(5.0, abs=0.01)  # no SLAM: started at the IMU, moving
    first = sm.out[0]
    np.testing.assert_allclose(first.gyro_bias, bias, atol=0.003)
    # Moving all along: no still stretch, the bias starts at zero.
    sm2 = OnlineSmoother(Calibration(), FixedLagOptions())
    for i in range(int(5.5 * 200)):
        t = i / 200.0
        w = bias + np.array([0.5 * math.sin(3 * t), 0.3 * math.cos(2 * t), 0.2])
        sm2.feed(ImuSample(t, t, w, np.array([math.sin(2 * t), 0.0, g])))
    np.testing.assert_array_equal(sm2.out[0].gyro_bias, np.zeros(3))


def test_still_stretch_bias_not_taken_when_the_autopilot_removed_the_rest_bias():
    """``imu_noise.rest_bias_removed`` (the Crazyflie firmware subtracts the bias it measured at
    rest): a still stretch's mean rate before the start is then the vehicle rocking on its legs,
    not the bias, and the first gyro bias stays at the prior's zero mean; the still stretch still
    levels the start. The same stream without the flag starts from the stretch's mean."""
    from fgnav.datasets.types import Calibration, ImuNoise

    rng = np.random.default_rng(2)
    rocking = np.array([0.004, -0.003, 0.002])  # net rate of the rocking over the stretch
    cal = Calibration(imu_noise=ImuNoise(gyro_bias_sigma=3e-3, rest_bias_removed=True))
    firsts = {}
    for flag, calib in ((True, cal), (False, Calibration())):
        sm = OnlineSmoother(calib, FixedLagOptions())
        g = sm.go.gravity
        for i in range(int(5.2 * 200)):
            t = i / 200.0
            w = rocking + rng.normal(0.0, 0.01, 3)
            a = np.array([0.0, 0.0, g]) + rng.normal(0.0, 0.3, 3)
            if t >= 3.0:
                w = w + np.array([0.5 * math.sin(3 * t), 0.3 * math.cos(2 * t), 0.2])
            sm.feed(ImuSample(t, t, w, a))
        assert sm.t0 == pytest.approx(5.0, abs=0.01)
        firsts[flag] = sm.out[0]
    np.testing.assert_array_equal(firsts[True].gyro_bias, np.zeros(3))
    np.testing.assert_allclose(firsts[False].gyro_bias, rocking, atol=0.002)
    assert np.abs(firsts[False].gyro_bias).max() > 0.002


def test_corrupted_stamps_and_values_are_dropped_not_reset():
    """One IMU sample stamped 1000 s ahead, one 50 s behind (a bridge's corrupted stamps), an
    IMU sample of 1e30 m/s^2 and a SLAM position of -1e30 (finite, but no sensor gives them):
    each is dropped by reason and the estimate goes on. Before 2026-12-07 each stamp reset the
    smoother twice (the stamp, then the next sample back on the old clock), the 1e30 sample
    overflowed the accelerometer check (OverflowError) and the -1e30 position opened a SLAM
    session per pose until the estimate was NaN. A real jump (the next samples continue the new
    clock) still resets: ``test_jittered_replay_survives_and_counts``."""
    f = simulate("two-turns", seed=1, options=SimOptions(images=False, duration=15.0))
    streams = ("imu", "attitude", "range", "slam")
    ref = replay_online(f, FixedLagOptions())
    imu_n = slam_n = 0
    events = []
    for e in replay_flight(f, streams):
        if isinstance(e, ImuSample):
            imu_n += 1
            if imu_n == 1000:
                e = e._replace(t=e.t + 1000.0, arrival=e.arrival + 1000.0)
            elif imu_n == 1600:
                e = e._replace(t=e.t - 50.0, arrival=e.arrival - 50.0)
            elif imu_n == 2000:
                e = e._replace(body_accel=np.array([1e30, 0.0, 9.8]))
        elif isinstance(e, SlamPose):
            slam_n += 1
            if slam_n == 150:
                e = e._replace(slam_t_cam=np.array([-1e30, 0.0, 0.0]))
        events.append(e)
    sm = feed_all(iter(events), f.calib, FixedLagOptions())
    est = sm.result()
    d = est.info["dropped"]
    assert sm.reset_counter == 0 and est.info["solver_failures"] == 0
    assert d.get("imu:time-outlier") == 2 and d.get("imu:implausible") == 1, d
    assert d.get("slam:implausible-position") == 1, d
    # The fault detectors see only the samples that pass: no saturation, no IMU gap named.
    detectors = est.info["health"]["detectors"]
    assert not {"imu-saturation", "imu-gap"} & set(detectors), detectors
    m = evaluate(est, f.ground_truth, alignment="se3").ate_rmse_m
    m_ref = evaluate(ref, f.ground_truth, alignment="se3").ate_rmse_m
    assert m <= 1.1 * m_ref + 0.002, (m, m_ref)


def test_a_held_last_imu_sample_is_counted_at_close():
    """The stream's last IMU sample, stamped past a gap, has no next sample to confirm it:
    ``close()`` (``fgnav live`` calls it when the link stops) counts it
    (``imu:time-unconfirmed``) and takes the events held behind it, so that every received IMU
    sample is used or dropped by reason."""
    f = simulate("two-turns", seed=1, options=SimOptions(images=False, duration=6.0))
    events = list(replay_flight(f, ("imu", "range", "slam")))
    last_imu = next(e for e in reversed(events) if isinstance(e, ImuSample))
    late = last_imu._replace(t=last_imu.t + 5.0, arrival=last_imu.arrival + 5.0)
    tail = RangeReading(last_imu.t + 5.001, last_imu.arrival + 5.001, 1.0)
    sm = feed_all(iter([*events, late, tail]), f.calib, FixedLagOptions())
    c = sm.counts()
    imu_dropped = sum(v for k, v in c["dropped"].items() if k.startswith("imu:"))
    assert c["dropped"].get("imu:time-unconfirmed") == 1
    assert c["received"]["imu"] == c["used"]["imu"] + imu_dropped
    assert c["received"]["range"] == sum(isinstance(e, RangeReading) for e in events) + 1


def test_drag_k_reported_only_when_a_drag_factor_measured_it(push_run):
    """An IMU body with x up (EuRoC-like): the thrust check turns drag off 0.5 s in. The drag
    variable made before holds its initial value; it is not reported as an estimate (it was
    printed as 0.3 1/s). With the FLU body the drag estimate is reported."""
    cut = simulate("two-turns", seed=1, options=SimOptions(images=False, duration=8.0))
    imu = dataclasses.replace(
        cut.imu, body_accel=cut.imu.body_accel[:, [2, 1, 0]] * np.array([1.0, 1.0, -1.0])
    )
    tilted = replay_online(dataclasses.replace(cut, imu=imu), FixedLagOptions())
    assert tilted.info["drag"].startswith("off")
    assert tilted.drag_k is None and "drag_k" not in tilted.series
    assert push_run.info["drag"].startswith("on")
    k = np.atleast_1d(push_run.drag_k)
    # Simulated 0.38, 0.42; ky is weakly observable on two-turns (mostly forward flight).
    assert abs(k[0] - 0.38) < 0.03 and 0.0 < k[-1] < 0.6, k


def test_drag_k_not_reported_after_the_accelerometer_check_turned_drag_off():
    """A simulated hover (seed 3, 20 s): drag goes on, and the accelerometer check turns it off
    1.5 s in (too little speed for drag to explain the horizontal force). The drag variable then
    keeps what its first factors said (0.25 / 0.35 1/s was reported as the estimate): no drag k
    in the result, and none in the states after the decision."""
    hover = simulate("hover", seed=3, options=SimOptions(images=False, duration=20.0))
    est = replay_online(hover, FixedLagOptions())
    assert est.info["drag"].startswith("off at t=")
    assert est.drag_k is None
    t_off = float(est.info["drag"].split("t=")[1].split(" s")[0])
    d = est.series.get("drag_k")
    if d is not None:
        assert (np.asarray(d.t) <= est.trajectory.t[0] + t_off + 0.2).all()


def test_slam_poses_that_all_miss_the_start_are_said(two_turns, push_run, caplog):
    """Two SLAM poses, both before the start: nothing used them, and the run read as a
    SLAM-aided one with health "ok" (0.29 m against 0.027 m); now one warning says so, with the
    reason, and ``info["slam_unused"]``. The nominal run says nothing."""
    import logging

    slam = two_turns.slam
    first = slam.select(np.arange(2))
    cut = dataclasses.replace(two_turns, slam=first)
    with caplog.at_level(logging.WARNING, logger="fgnav.solvers.online"):
        est = replay_online(cut, FixedLagOptions())
    said = [r.getMessage() for r in caplog.records if "none was used" in r.getMessage()]
    assert len(said) == 1 and "2 SLAM pose(s)" in said[0] and "slam:" in said[0], said
    assert est.info["slam_unused"] is True
    assert push_run.info["slam_unused"] is False


def _gyro_turn_reference(sm: OnlineSmoother, ta: float, tb: float) -> float | None:
    """The gyro turn written with numpy throughout (the form before its plain-float rewrite)."""
    from fgnav.datasets.geometry import so3_exp, so3_log

    from fgnav.keys import B
    from fgnav.solvers.online import GYRO_TURN_SMALL_RAD

    imu = sm.imu
    if not imu.t or imu.t[0] > ta or imu.t[-1] < tb or tb <= ta:
        return None
    sl = imu.span(ta, tb)
    t = np.r_[ta, imu.t[sl], tb]
    if np.max(np.diff(t)) > 0.2:
        return None
    w = np.asarray(imu.w[max(sl.start - 1, 0) : sl.stop], float)
    if sl.start == 0:
        w = np.vstack([w[:1], w])
    if len(w) < len(t) - 1:
        return None
    b = sm.values.get(B(sm.k)) if sm.k >= 0 else None
    if b is not None:
        w = w - b.gyroscope()
    phi = w[: len(t) - 1] * np.diff(t)[:, None]
    if float(np.abs(phi).sum()) < GYRO_TURN_SMALL_RAD:
        v = phi.sum(axis=0)
        return math.sqrt(v.dot(v))
    R = np.eye(3)
    for Ri in so3_exp(phi):
        R = R @ Ri
    return float(np.linalg.norm(so3_log(R)))


def test_gyro_turn_is_the_numpy_formula_bit_for_bit(two_turns_12s):
    """The SLAM jump detector's gyro turn (interval lengths on plain floats) gives the same
    bits as the numpy formula, on spans within, across and outside the kept IMU, short
    (consecutive SLAM poses) and long (the product of exponentials)."""
    sm = feed_all(replay_flight(two_turns_12s, STREAMS), two_turns_12s.calib, FixedLagOptions())
    t = np.asarray(sm.imu.t)
    rng = np.random.default_rng(0)
    n_long = 0
    for _ in range(3000):
        ta = float(rng.uniform(t[0] - 0.1, t[-1]))
        if rng.random() < 0.3:
            ta = float(t[rng.integers(len(t))])  # on a sample
        tb = ta + float(rng.choice([0.05, 0.1, 0.3, 1.0, rng.uniform(0.0, 0.5)]))
        got, want = sm._gyro_turn(ta, tb), _gyro_turn_reference(sm, ta, tb)
        assert got == want or (got is None and want is None), (ta, tb, got, want)
        n_long += want is not None and want > 0.3
    assert n_long > 50  # the product-of-exponentials branch was exercised
