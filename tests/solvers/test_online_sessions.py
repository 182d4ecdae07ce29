"""SLAM session ids as the input gives them: the push engine's alignment keys depend on the
sessions' order of arrival only, so ids 9 and 10 (or 10**11) run exactly as 0 and 1."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.eval.metrics import evaluate
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.online import replay_online


@pytest.fixture(scope="module")
def reset_flight():
    opts = SimOptions(images=False, duration=25.0, slam_resets=(12.0,))
    return simulate("two-turns", seed=1, options=opts)


@pytest.fixture(scope="module")
def reference(reset_flight):
    return replay_online(reset_flight, FixedLagOptions())


@pytest.mark.parametrize("offset", [9, 1000, 10**11])
def test_session_ids_do_not_change_the_estimate(reset_flight, reference, offset):
    """Before: session 10's chain keys S(10 * 100000 + segment) were the provisional keys
    S(1000000 + n): the run with ids 9, 10 rebuilt once and scored 16.3 cm against 12.0 cm.
    Ids of 1000 and more were taken for the health check's jump splits (then numbered from
    1000) and the map reset was not named (review, 2026-12-07)."""
    f = reset_flight
    shifted = dataclasses.replace(
        f, slam=dataclasses.replace(f.slam, session=f.slam.session + offset)
    )
    est = replay_online(shifted, FixedLagOptions())
    assert est.info["reset_counter"] == reference.info["reset_counter"] == 0
    assert est.info["health"]["detectors"].get("slam-reset") == 1
    assert sorted(est.slam_scale) == [offset, offset + 1]
    np.testing.assert_allclose(
        est.trajectory.world_t_body, reference.trajectory.world_t_body, rtol=0, atol=1e-9
    )
    m = evaluate(est, f.ground_truth, alignment="se3")
    assert m.ate_rmse_m < 0.05, m.ate_rmse_m  # 3.6 cm across the map reset (11.8 cm before)


def _truth_scale_at_end(f, session: int) -> float:
    s = f.meta["truth"]["slam_sessions"][str(session)]
    return s["scale"] * (1.0 + s["scale_drift_per_s"] * (s["t_end"] - s["t_start"]))


def test_new_session_chain_starts_from_the_provisional_it_has_estimated(reset_flight, reference):
    """After a map reset the provisional alignment is estimated with the velocity known from the
    session before; its scale is fused with the closed-form fit's when the chain starts
    (FixedLagOptions.slam_chain_fuse_provisional). Measured 2026-12-07 (reset at 12 s, chain
    at 16 s): fit 1.653 (rel. s.e. 0.29), provisional 1.005, true 0.9965; final scale of the
    new session 1.045 -> 1.002, causal ATE 11.8 -> 3.6 cm."""
    f = reset_flight
    old = replay_online(f, FixedLagOptions(slam_chain_fuse_provisional=False))
    truth = _truth_scale_at_end(f, 1)
    assert abs(reference.slam_scale[1] / truth - 1.0) < 0.015, reference.slam_scale
    assert abs(old.slam_scale[1] / truth - 1.0) > 0.03, old.slam_scale
    new_ate = evaluate(reference, f.ground_truth, alignment="se3").ate_rmse_m
    old_ate = evaluate(old, f.ground_truth, alignment="se3").ate_rmse_m
    assert new_ate < 0.5 * old_ate, (new_ate, old_ate)
    # The first session has no alignment before it: its chain starts from the fit alone.
    np.testing.assert_allclose(reference.slam_scale[0], old.slam_scale[0], rtol=1e-9)


def _lost(f, t0: float, t1: float, moved_m: float = 0.0, session: int | None = None):
    """``f`` with no SLAM pose in ``[t0, t1)``; the poses after it moved by ``moved_m`` metres
    along SLAM x (in the session's units) and, given ``session``, under that id."""
    s = f.slam
    keep = ~((s.t >= t0) & (s.t < t1))
    p = s.slam_t_cam[keep].copy()
    after = s.t[keep] >= t1
    p[after, 0] += moved_m * f.meta["truth"]["slam_sessions"]["0"]["scale"]
    sess = s.session[keep] if session is None else np.where(after, session, s.session[keep])
    slam = dataclasses.replace(
        s,
        t=s.t[keep],
        slam_t_cam=p,
        slam_q_cam_wxyz=s.slam_q_cam_wxyz[keep],
        session=sess,
        latency=None if s.latency is None else s.latency[keep],
    )
    return dataclasses.replace(f, slam=slam)


@pytest.fixture(scope="module")
def two_turns_25s():
    return simulate("two-turns", seed=1, options=SimOptions(images=False, duration=25.0))


@pytest.mark.parametrize("moved_m", [0.0, 2.0])
def test_a_relocalisation_after_lost_tracking_is_a_jump(two_turns_25s, moved_m):
    """SLAM lost 8-14 s, back in the same session 2 m away (review, 2026-12-07): the jump
    detector compared only poses <= 1 s apart, and the move was fitted as motion (0.87 m, health
    "ok"). The returning pose is now compared with the estimate (within 0.5 m + 4 position
    sigmas): named ``slam-jump``, a new alignment, 0.074 m. Back unchanged: nothing named
    (0.062 m; no false jump on two-turns, figure8, hover, rectangle lost 8-14, 10-12, 8-18 s,
    nor on the EuRoC files)."""
    f = _lost(two_turns_25s, 8.0, 14.0, moved_m)
    est = replay_online(f, FixedLagOptions())
    jumps = est.info["health"]["detectors"].get("slam-jump", 0)
    assert jumps == (1 if moved_m else 0)
    m = evaluate(est, f.ground_truth, alignment="se3")
    assert m.ate_rmse_m < 0.12, m.ate_rmse_m


def _turned(f, t1: float, deg: float, gap_from: float | None = None):
    """``f``'s SLAM map turned by ``deg`` about SLAM z at its pose at ``t1`` (positions and
    orientations from then on), after a loss of tracking from ``gap_from`` when given."""
    s = f.slam
    keep = np.ones(len(s.t), bool) if gap_from is None else ~((s.t >= gap_from) & (s.t < t1))
    t, p, q = s.t[keep], s.slam_t_cam[keep].copy(), s.slam_q_cam_wxyz[keep].copy()
    after = t >= t1
    a = np.radians(deg)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    c = p[np.argmax(after)].copy()
    p[after] = (p[after] - c) @ R.T + c
    q[after] = matrix_to_quat_wxyz(R @ quat_wxyz_to_matrix(q[after]))
    slam = dataclasses.replace(
        s,
        t=t,
        slam_t_cam=p,
        slam_q_cam_wxyz=q,
        session=s.session[keep],
        latency=None if s.latency is None else s.latency[keep],
    )
    return dataclasses.replace(f, slam=slam)


@pytest.mark.parametrize(
    ("scenario", "gap_from", "before_m"), [("figure8", None, 1.98), ("two-turns", 8.0, 0.18)]
)
def test_a_turned_map_is_a_jump(scenario, gap_from, before_m):
    """The SLAM map turned 30 deg about the current pose at 14 s (no displacement there), in
    the same session (review, 2026-12-07): fitted as motion with health "ok" (figure8 1.98 m;
    two-turns after lost tracking 8-14 s 0.18 m). The SLAM orientation's turn against the
    gyro's now names a ``slam-jump`` (measured: 0.087 / 0.074 m, the unturned runs' figures)."""
    f = simulate(scenario, seed=1, options=SimOptions(images=False, duration=25.0))
    est = replay_online(_turned(f, 14.0, 30.0, gap_from), FixedLagOptions())
    assert est.info["health"]["detectors"].get("slam-jump", 0) == 1
    m = evaluate(est, f.ground_truth, alignment="se3")
    assert m.ate_rmse_m < 0.15 < before_m, m.ate_rmse_m


def test_every_slam_pose_is_counted_once_across_a_loss_and_a_new_session(two_turns_25s):
    """SLAM lost 8-18 s, back as session 1 (review, 2026-12-07): a provisional factor made in the
    update that moved the window to QR was counted as used and again as dropped
    (``slam:provisional-not-reattachable``): 302 counted of 301 received. It stays in the graph:
    now an event (``used["slam:provisional-kept"]``), not a drop."""
    f = _lost(two_turns_25s, 8.0, 18.0, session=1)
    est = replay_online(f, FixedLagOptions())
    i = est.info
    out = sum(v for k, v in {**i["dropped"], **i["skipped"]}.items() if k.startswith("slam"))
    assert i["used"]["slam"] + out == i["received"]["slam"] == len(f.slam)
