from __future__ import annotations

import gtsam
import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate
from testutil import circle_axis_run, truth_axis_scale_at, truth_scale_at

from fgnav.eval.metrics import evaluate
from fgnav.keys import X
from fgnav.solvers.fixed_lag import FixedLagOptions, FixedLagRunner, run_fixed_lag
from fgnav.solvers.graph import GraphOptions


def _indeterminate_update(r: FixedLagRunner) -> bool:
    """Update with two new variables tied only to each other: an indeterminate linear system."""
    g = gtsam.NonlinearFactorGraph()
    a, b = gtsam.symbol("z", 0), gtsam.symbol("z", 1)
    g.add(gtsam.BetweenFactorVector(a, b, np.ones(1), gtsam.noiseModel.Isotropic.Sigma(1, 1.0)))
    v = gtsam.Values()
    v.insert(a, np.zeros(1))
    v.insert(b, np.zeros(1))
    t = float(r.builder.t_kf[r.newest_k])
    return r.update(g, v, {a: t, b: t})


@pytest.fixture(scope="module")
def online_two_turns(two_turns_12s):
    return run_fixed_lag(two_turns_12s, FixedLagOptions(lag_s=2.0))


def test_fixed_lag_two_turns(two_turns_12s, online_two_turns):
    f, est = two_turns_12s, online_two_turns
    assert est.method == "fixed-lag" and est.causal
    n = len(est.trajectory)
    assert est.update_latency.shape == (n,) and est.info["updates"] == n
    assert est.info["solver_failures"] == 0
    # The newest state after each update. SLAM from the first pose on a provisional alignment
    # (hover: "not moving" whatever the scale), moved onto the closed-form alignment once the
    # motion excites the scale; the flight ends while the causal scale is still converging
    # (measured 5.3 cm ATE, 5.6 cm/s; before the provisional alignment the hover was dead
    # reckoning).
    m = evaluate(est, f.ground_truth, alignment="se3")
    assert m.ate_rmse_m < 0.1, m.ate_rmse_m
    assert m.vel_rmse_mps < 0.1
    assert est.info["slam_provisional_alignments"][0]["session"] == 0
    assert "slam:before-scale-init" not in est.info["dropped"]
    s_true = truth_scale_at(f, float(est.trajectory.t[-1]))
    assert abs(est.slam_scale[0] / s_true - 1) < 0.03
    # SLAM poses before the scale could be initialised are counted, never silently lost.
    n_slam = len(f.slam)
    used = est.info["used"].get("slam", 0)
    dropped = sum(v for k, v in est.info["dropped"].items() if k.startswith("slam"))
    skipped = sum(v for k, v in est.info["skipped"].items() if k.startswith("slam"))
    assert used > 0 and used + dropped + skipped == n_slam


@pytest.mark.slow
def test_fixed_lag_two_turns_28s_causal_accuracy():
    """The full two-turns flight (seed 0): measured causal ATE 1.9 cm, velocity 3.2 cm/s."""
    f = simulate("two-turns", seed=0, options=SimOptions(images=False))
    est = run_fixed_lag(f, FixedLagOptions(lag_s=2.0))
    m = evaluate(est, f.ground_truth, alignment="se3")
    assert m.ate_rmse_m < 0.035, m.ate_rmse_m
    assert m.vel_rmse_mps < 0.055
    assert abs(est.slam_scale[0] / truth_scale_at(f, float(est.trajectory.t[-1])) - 1) < 0.02


def test_late_measurements_beyond_lag_are_counted():
    f = simulate(
        "two-turns",
        seed=2,
        options=SimOptions(
            duration=10.0, images=False, slam_latency_s=2.5, slam_latency_jitter_s=0.0
        ),
    )
    opts = FixedLagOptions(lag_s=2.0, graph=GraphOptions(use_range=False, use_yaw=False))
    est = run_fixed_lag(f, opts)
    assert est.info["used"].get("slam", 0) == 0
    assert est.info["dropped"].get("slam:dropped-too-late", 0) > 0
    # With a lag longer than the latency, the same late poses are attached to their keyframes.
    est_long = run_fixed_lag(f, FixedLagOptions(lag_s=3.5, graph=opts.graph))
    assert est_long.info["used"].get("slam", 0) > 0
    assert est_long.info["dropped"].get("slam:dropped-too-late", 0) == 0


def test_solver_failure_rebuilds_and_continues(two_turns_12s, online_two_turns):
    f = two_turns_12s
    r = FixedLagRunner(f, FixedLagOptions(lag_s=2.0))
    for _ in range(60):
        assert r.step()
    assert _indeterminate_update(r) is False
    assert r.n_failures == 1 and "Indeterminate" in r.failure_messages[0]
    while r.step():
        pass
    r.finish()
    est = r.result(1.0)
    assert est.info["solver_failures"] == 1
    assert len(est.trajectory) == r.builder.K
    m = evaluate(est, f.ground_truth, alignment="se3")
    ref = evaluate(online_two_turns, f.ground_truth, alignment="se3")
    assert m.ate_rmse_m < ref.ate_rmse_m + 0.05


@pytest.mark.slow
def test_fixed_lag_circle_per_axis_slam_with_camera():
    """Seed 000's circle (per-axis SLAM scale 0.3/0.2/0.25, drifting) with every sensor and the
    rendered downward camera: the per-axis alignment (scale + SLAM-origin offset) starts once the
    closed-form fit is determined, the world origin stays at the first keyframe (no jump), and the
    homography factors keep the start metric. Measured (20 s, seeds 0/1/2): ATE 0.89/0.92/1.05 cm,
    final kx, ky within 0.8 % of the drifting truth."""
    f, est, m = circle_axis_run(run_fixed_lag)
    assert est.info["slam_model"] == "axis"
    assert m.ate_rmse_m < 0.02, m.ate_rmse_m
    assert m.vel_rmse_mps < 0.05, m.vel_rmse_mps
    k_true = truth_axis_scale_at(f, est.trajectory.t[-1])
    k = est.series["slam_axis_scale"].value[-1]
    np.testing.assert_allclose(k[:2], k_true[:2], rtol=0.02)
    # SLAM poses before the per-axis fit is determined are counted, not silently lost.
    assert 0 < est.info["dropped"]["slam:before-scale-init"] < 200


def test_factorization_switch_is_lossless(two_turns_12s):
    """QR for the first seconds, then the window moves to a Cholesky smoother: the causal
    trajectory equals the QR-only run (measured 5.6e-10 m apart on 20 s of two-turns). At 1 s the
    SLAM poses still sit on the provisional alignment: their factor indices are remapped for the
    later re-attachment (same trajectory, 8.6e-10 m)."""
    f = two_turns_12s
    qr = run_fixed_lag(f, FixedLagOptions(factorization="QR"))
    assert qr.info["factorization_final"] == "QR"
    assert qr.info["slam_provisional_alignments"]
    for t_switch in (1.0, 4.0):
        opts = FixedLagOptions(factorization="CHOLESKY", startup_qr_s=t_switch)
        switched = run_fixed_lag(f, opts)
        assert switched.info["factorization_final"] == "CHOLESKY"
        assert switched.info["solver_failures"] == 0
        assert switched.info["used"]["slam"] == qr.info["used"]["slam"]
        diff = np.abs(qr.trajectory.world_t_body - switched.trajectory.world_t_body).max()
        assert diff < 1e-6, (t_switch, diff)
    with pytest.raises(FlightDataError, match="factorization"):
        FixedLagRunner(f, FixedLagOptions(factorization="LU"))


def test_cholesky_failure_falls_back_to_qr(two_turns_12s):
    f = two_turns_12s
    r = FixedLagRunner(f, FixedLagOptions(startup_qr_s=0.0))
    assert r.factorization == "CHOLESKY"
    for _ in range(30):
        assert r.step()
    assert _indeterminate_update(r) is False
    assert r.factorization == "QR"
    while r.step():
        pass
    r.finish()
    est = r.result(1.0)
    assert est.info["solver_failures"] == 1 and est.info["factorization_final"] == "QR"
    assert evaluate(est, f.ground_truth, alignment="se3").ate_rmse_m < 0.05


def test_cholesky_failure_moves_the_window_to_qr():
    """No SLAM in the window (2.5 s latency), no range or yaw: Cholesky fails at 1.8 s (measured)
    where QR does not. The failed smoother's factors and values move into a QR smoother: no
    solver failure, no rebuild, the same causal trajectory as a QR-only run up to relinearisation
    timing (measured 5e-10 m at 2 s, 3 cm at 10 s; ATE 0.250 vs 0.248 m on this weak set)."""
    f = simulate(
        "two-turns",
        seed=2,
        options=SimOptions(
            duration=10.0, images=False, slam_latency_s=2.5, slam_latency_jitter_s=0.0
        ),
    )
    g = GraphOptions(use_range=False, use_yaw=False)
    qr = run_fixed_lag(f, FixedLagOptions(lag_s=3.5, graph=g, factorization="QR"))
    ch = run_fixed_lag(f, FixedLagOptions(lag_s=3.5, graph=g, startup_qr_s=0.0))
    assert ch.info["factorization_fallbacks"] == 1 and ch.info["solver_failures"] == 0
    assert ch.info["factorization_final"] == "QR"
    early = qr.trajectory.t < 2.0
    diff = np.abs(qr.trajectory.world_t_body - ch.trajectory.world_t_body).max(axis=1)
    assert diff[early].max() < 1e-6
    ate = [evaluate(e, f.ground_truth, alignment="se3").ate_rmse_m for e in (qr, ch)]
    assert abs(ate[0] - ate[1]) < 0.01, ate


def test_failed_update_with_provisional_slam_factors_keeps_them_registered(two_turns_12s):
    """An update that adds provisional SLAM factors fails (simulated after iSAM2 took them): the
    window, that update included, moves to the fallback smoother, where the provisional factors
    are found again (by identity), so the later re-attachment to the closed-form alignment still
    moves them."""
    opts = FixedLagOptions(factorization="QR", fallback_factorization="CHOLESKY", startup_qr_s=0)
    r = FixedLagRunner(two_turns_12s, opts)
    real_update = r.smoother.update
    fail = {"armed": False}

    def failing_update(graph, values, stamps, remove=None):
        result = real_update(graph, values, stamps, remove)
        if fail["armed"]:
            raise RuntimeError("simulated failure after the update")
        return result

    r.smoother.update = failing_update

    def registered() -> int:
        return sum(len(rows) for rows in r.provisional_factors.values())

    for _ in range(19):
        r.step()
    before = registered()
    assert before > 0  # the provisional phase (hover)
    fail["armed"] = True
    r.step()
    assert r.n_fallbacks == 1 and r.n_failures == 0 and r.factorization == "CHOLESKY"
    assert registered() > before
    factors = r.smoother.getFactors()
    for rows in r.provisional_factors.values():
        for idx, k, _ in rows:
            assert X(k) in factors.at(idx).keys()
    est = r.run()
    assert est.info["factorization_fallbacks"] == 1 and est.info["solver_failures"] == 0
    assert not r.provisional_factors  # all re-attached once the closed-form alignment came


def test_pose_translation_has_its_own_relinearisation_threshold():
    # The keyframe positions relinearise at 3 mm when set (0.5 m left them marginalised at
    # their IMU-predicted value: MH_01's causal scale 1.27 % off against 0.70 %); the rest as set.
    from fgnav.solvers.fixed_lag import relinearize_thresholds

    thr = relinearize_thresholds(FixedLagOptions(relinearize_threshold_position=0.003), {"s": 7})
    np.testing.assert_array_equal(thr["x"], [0.5, 0.5, 0.5, 0.003, 0.003, 0.003])
    np.testing.assert_array_equal(thr["v"], np.full(3, 0.5))
    np.testing.assert_array_equal(thr["b"], np.full(6, 0.5))
    np.testing.assert_array_equal(thr["s"], np.full(7, 0.01))
    old = relinearize_thresholds(FixedLagOptions(), {})
    np.testing.assert_array_equal(old["x"], np.full(6, 0.5))
    # The start's tighter threshold wins over a looser position threshold.
    start = FixedLagOptions(relinearize_threshold=0.001, relinearize_threshold_position=0.003)
    np.testing.assert_array_equal(relinearize_thresholds(start, {})["x"], np.full(6, 0.001))
