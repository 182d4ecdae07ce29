"""Batch smoother on real data: EuRoC MH_01 IMU + pure monocular ORB-SLAM3 (run A), no GT used."""

from __future__ import annotations

import dataclasses

import numpy as np
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
    # The SLAM run alone, Sim(3)-aligned, has 3.7 cm ATE; the metric estimate reaches 3-4 cm
    # (3.78 cm with the IMU densities at rest, 3.27 cm with the manifest's in-flight ones).
    assert m.ate_rmse_m < 0.038, m.ate_rmse_m
    s_true = slam_scale_vs_truth(flight.slam, flight.ground_truth, flight.calib.body_T_cam)[0]
    assert abs(est.slam_scale[0] / s_true - 1) < 0.01
    assert 0 < est.slam_scale_sigma[0] < 0.01 * s_true


V102 = {
    "orbslam2_kf1": PROJECT_ROOT / "datasets" / "manifests" / "euroc_v102_orbslam2_kf1.toml",
    "orbslam3_kf2": PROJECT_ROOT / "datasets" / "manifests" / "euroc_v102_orbslam3_kf2.toml",
}


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize("run", sorted(V102))
def test_euroc_v102_keyframes_batch_within_4cm(real_data, run):
    # IMU + the ~3 Hz keyframes of a monocular ORB-SLAM run, default options. The ORB-SLAM3 file
    # stores its rotations inverted (data README): the SLAM-vs-gyro check must find that itself.
    flight = load_flight(V102[run])
    est = solve_batch(flight, BatchOptions())
    check = est.info.get("slam_gyro_check") or {}
    assert check.get("inverted") is (run == "orbslam3_kf2")
    m = evaluate(est, flight.ground_truth, alignment="se3")
    # 3.37 / 3.82 cm with the IMU densities at rest, 2.39 / 2.29 cm in flight (the manifests'),
    # 1.88 / 1.78 cm with the origin walk 5e-3.
    assert m.ate_rmse_m <= 0.03, m.ate_rmse_m
    s_true = slam_scale_vs_truth(flight.slam, flight.ground_truth, flight.calib.body_T_cam)[0]
    assert abs(est.slam_scale[0] / s_true - 1) < 0.02


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize("run", sorted(V102))
def test_euroc_v102_batch_origin_walk_default_beats_the_old_one(real_data, run):
    # graph.slam_trans_rw_m 1e-2 -> 5e-3 (2026-12-04, nearer ORB-SLAM3's measured map drift):
    # batch ATE 2.39 / 2.29 -> 1.88 / 1.78 cm (ORB-SLAM2 / ORB-SLAM3 keyframes).
    flight = load_flight(V102[run])
    new = evaluate(solve_batch(flight, BatchOptions()), flight.ground_truth, alignment="se3")
    o = BatchOptions()
    old_opts = dataclasses.replace(o, graph=dataclasses.replace(o.graph, slam_trans_rw_m=1e-2))
    old = evaluate(solve_batch(flight, old_opts), flight.ground_truth, alignment="se3")
    assert new.ate_rmse_m < old.ate_rmse_m - 0.003, (new.ate_rmse_m, old.ate_rmse_m)
    assert new.ate_rmse_m < 0.021, new.ate_rmse_m


@pytest.mark.realdata
@pytest.mark.parametrize(
    "manifest, ate_max, scale_max, convention",
    [
        (MANIFEST, 0.050, 0.005, "as-is"),
        (V102["orbslam2_kf1"], 0.090, 0.013, "as-is"),
        (V102["orbslam3_kf2"], 0.032, 0.013, "inverse"),
    ],
)
def test_euroc_push_engine_causal_accuracy(real_data, manifest, ate_max, scale_max, convention):
    # The push engine's newest state (strictly causal), default options. Measured 2026-12-02
    # with FixedLagOptions.slam_scale_rw 3e-4: MH_01 6.3 cm (7.2 with the graph's 1e-3), V1_02
    # ORB-SLAM2 keyframes 20.3 cm, ORB-SLAM3 keyframes 8.7 cm (8.8) (before the
    # still-stretch gyro-bias start, the early SLAM-vs-gyro decision and the start's
    # relinearisation: 7.5, 45 and 59 cm). After the start from the still stretch (attitude and
    # velocity integrated from rest) and the provisional log-scale sigma 1.0 (was 0.3): MH_01
    # 6.3 cm, V1_02 ORB-SLAM2 9.4 cm, ORB-SLAM3 5.3 cm; NEES 3.7, 7.0, 5.7 (16.2, 14.6 before).
    # With the keyframe positions relinearised at 3 mm and the graph's scale walk (opt-in,
    # FixedLagOptions.relinearize_threshold_position; the test below): MH_01 4.62 cm, final
    # scale error 0.49 % (1.27 % with the defaults), NEES 1.90; V1_02 ORB-SLAM2 9.69 cm,
    # ORB-SLAM3 5.86 cm. 2026-12-03, the manifests' in-flight IMU noise (accel 8x, gyro 6x the
    # file's densities at rest, scripts/euroc_imu_noise.py): MH_01 6.29 -> 4.69 cm, final scale
    # error 1.27 -> 0.70 %, NEES 3.69 -> 1.11; V1_02 ORB-SLAM2 9.36 -> 8.43 cm (1.46 -> 1.16 %),
    # ORB-SLAM3 5.34 -> 3.46 cm (1.19 -> 0.87 %). Then the push engine's scale walk 3e-4 -> the
    # graph's 1e-3 (FixedLagOptions.slam_scale_rw None): MH_01 4.53 cm, 0.48 % (issue 15's goals,
    # 5.0 cm and 0.5 %), NEES 1.09; V1_02 8.43 / 3.46 cm, 1.19 / 1.12 %. 2026-12-07: a SLAM pose
    # that arrived before the start (the first, with no latency) attaches at it instead of being
    # lost: ORB-SLAM3 3.46 -> 2.95 cm, NEES 2.18 -> 1.35; MH_01 and ORB-SLAM2 unchanged.
    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.online import replay_online

    flight = load_flight(manifest)
    est = replay_online(flight, FixedLagOptions())
    assert est.info["slam_rotation_convention"] == convention
    # By default the provisional alignment starts at slam_provisional_scale (1).
    assert [p["from"] for p in est.info["slam_provisional_scales"]] == ["default"]
    assert est.info["slam_gyro_check"]["t"] - flight.slam.t[0] < 7.0
    assert est.info["solver_failures"] == 0 and est.info["reset_counter"] == 0
    m = evaluate(est, flight.ground_truth, alignment="se3")
    assert m.ate_rmse_m < ate_max, m.ate_rmse_m
    s_true = slam_scale_vs_truth(flight.slam, flight.ground_truth, flight.calib.body_T_cam)[0]
    assert abs(est.slam_scale[0] / s_true - 1) < scale_max, est.slam_scale[0] / s_true - 1


@pytest.mark.realdata
def test_euroc_mh01_push_engine_position_relinearisation(real_data):
    # Opt-in (not the default: see FixedLagOptions.relinearize_threshold_position): the keyframe
    # positions relinearised at 3 mm and the graph's scale walk. Measured 2026-12-02 evening:
    # MH_01 causal ATE 4.61-4.62 cm, final scale error 0.49 % (defaults: 6.27 cm, 1.27 %).
    # 2026-12-03 with the manifest's in-flight IMU noise: 3.78 cm, 0.05 %, NEES 0.77 (defaults
    # 4.69 cm, 0.70 %).
    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.online import replay_online

    flight = load_flight(MANIFEST)
    opts = FixedLagOptions(relinearize_threshold_position=0.003, slam_scale_rw=None)
    est = replay_online(flight, opts)
    assert est.info["solver_failures"] == 0 and est.info["reset_counter"] == 0
    m = evaluate(est, flight.ground_truth, alignment="se3")
    assert m.ate_rmse_m < 0.042, m.ate_rmse_m
    s_true = slam_scale_vs_truth(flight.slam, flight.ground_truth, flight.calib.body_T_cam)[0]
    assert abs(est.slam_scale[0] / s_true - 1) < 0.004, est.slam_scale[0] / s_true - 1


@pytest.mark.realdata
@pytest.mark.parametrize(
    "run, scale_tol, ate_max", [("orbslam2_kf1", 0.12, 0.085), ("orbslam3_kf2", 0.15, 0.075)]
)
def test_euroc_v102_push_engine_provisional_scale_from_data(real_data, run, scale_tol, ate_max):
    # Opt-in (FixedLagOptions.slam_provisional_wait_s, not the default: it loses on ORB-SLAM3
    # and MH_01): the provisional SLAM scale from the arrived motion instead of 1. Measured
    # 2026-12-02 (1.5 s, 0.2 m): provisional scale ORB-SLAM2 0.483 against the true 0.443 (the
    # default 1 is 2.3x off), causal ATE 9.36 -> 8.06 cm; ORB-SLAM3 5.61 against 5.01 (its
    # convention not decided yet: the rotation that maps the displacements is taken), causal
    # ATE 5.34 -> 7.05 cm.
    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.online import replay_online

    flight = load_flight(V102[run])
    est = replay_online(flight, FixedLagOptions(slam_provisional_wait_s=1.5))
    (prov,) = est.info["slam_provisional_scales"]
    assert prov["from"] == "data"
    # The held poses attach: the provisional is made within the wait of the first pose.
    assert prov["t"] - flight.slam.t[0] <= 1.5 + 1e-6
    assert est.info["solver_failures"] == 0 and est.info["reset_counter"] == 0
    s_true = slam_scale_vs_truth(flight.slam, flight.ground_truth, flight.calib.body_T_cam)[0]
    assert abs(prov["scale"] / s_true - 1) < scale_tol, prov["scale"] / s_true - 1
    m = evaluate(est, flight.ground_truth, alignment="se3")
    assert m.ate_rmse_m < ate_max, m.ate_rmse_m
    assert abs(est.slam_scale[0] / s_true - 1) < 0.02


@pytest.mark.realdata
def test_euroc_v102_orbslam2_second_pose_waits_for_the_third(real_data):
    """ORB-SLAM2 keyframes: the second pose comes 1.1 s after the first while the provisional
    scale is the default 1 (true 0.44); one displacement cannot tell the scale from the velocity,
    and the default pulled the states 0.3-0.6 m until the third pose. By default
    (``slam_provisional_lone_gap_s`` 0.25 s) the second waits for the third; opt-in
    ``slam_provisional_min_poses = 3`` holds the first two (the provisional starts at the third:
    MH_01 4.53 -> 4.69 cm, so not the default). Measured 2026-12-07, causal ATE own span: off
    6.62, default 5.01, min_poses 3 4.91 cm."""
    import numpy as np

    from fgnav.eval.align import align, associate
    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.online import replay_online

    flight = load_flight(V102["orbslam2_kf1"])
    runs = {
        "off": replay_online(flight, FixedLagOptions(slam_provisional_lone_gap_s=0.0)),
        "default": replay_online(flight, FixedLagOptions()),
        "min3": replay_online(flight, FixedLagOptions(slam_provisional_min_poses=3)),
    }
    ts = np.asarray(flight.slam.t)
    covered = ts[ts >= runs["off"].trajectory.t[0] - 0.05]
    worst, ate = {}, {}
    for name, est in runs.items():
        assert est.info["solver_failures"] == 0 and est.info["reset_counter"] == 0
        (prov,) = est.info["slam_provisional_scales"]
        assert prov["from"] == "default"
        # The provisional starts at the first pose, or with min_poses 3 at the third.
        first = covered[2] if name == "min3" else covered[0]
        assert prov["t"] == pytest.approx(first, abs=1e-6), name
        ate[name] = evaluate(est, flight.ground_truth, alignment="se3").ate_rmse_m
        a = associate(est.trajectory, flight.ground_truth)
        x, g = est.trajectory.world_t_body[a.est_index], a.gt.world_t_body
        err = np.linalg.norm(g - align(x, g, "se3").apply_positions(x), axis=1)
        t = est.trajectory.t[a.est_index]
        between = (t > covered[1]) & (t < covered[2])  # after the second pose, before the third
        worst[name] = float(err[between].max())
    assert worst["off"] > 0.3 and worst["default"] < 0.15 and worst["min3"] < 0.15, worst
    assert ate["default"] < 0.053 and ate["default"] < ate["off"] - 0.012, ate
    assert ate["min3"] < 0.053, ate


@pytest.mark.realdata
def test_euroc_v102_orbslam2_orientations_tie_the_provisional_alignment(real_data):
    """Once the SLAM-vs-gyro check has decided the convention (5.35 s after the first of these
    3 Hz keyframes), every pose gives one rotation factor as it attaches, to the provisional
    alignment too; a pose moved from the provisional onto the chain keeps the one it had (the
    count checks that none is made twice). Until 2026-12-07's seventh session a provisional
    pose got its rotation factor only when moved onto the chain: the provisional's rotation
    (prior 0.3 rad) and the attitude were free while its scale was unknown. Measured: causal
    ATE own span 5.01 -> 4.61 cm (ukf003 4.69), NEES 7.0 -> 4.8."""
    import numpy as np

    from fgnav.solvers.online import replay_online

    flight = load_flight(V102["orbslam2_kf1"])
    est = replay_online(flight)
    used = est.info["used"]
    t_dec = est.info["slam_gyro_check"]["t"]
    before = int(np.sum(np.asarray(flight.slam.t) < t_dec - 1e-9))
    assert used["slam:reattached"] > 0  # poses did move from the provisional to the chain
    assert used["slam-rotation"] == used["slam"] - before, (used, before)
    assert evaluate(est, flight.ground_truth, alignment="se3").ate_rmse_m < 0.047


def _ate_from(est, flight, t_from: float) -> float:
    """SE(3)-aligned position RMSE [m] of ``est`` from ``t_from`` s after the first IMU sample
    (aligned over that span only, as ``scripts/error_windows.py``)."""
    import numpy as np

    from fgnav.eval.align import align, associate

    a = associate(est.trajectory, flight.ground_truth)
    t = est.trajectory.t[a.est_index] - float(flight.imu.t[0])
    keep = t >= t_from
    x, g = est.trajectory.world_t_body[a.est_index][keep], a.gt.world_t_body[keep]
    e = g - align(x, g, "se3").apply_positions(x)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


@pytest.mark.realdata
def test_euroc_v102_orbslam2_push_engine_segment_after_pause(real_data):
    """V1_02 ORB-SLAM2 keyframes (3 Hz, pauses up to 2.35 s, longer than the 2 s lag): a SLAM
    segment that starts after its predecessor left the window has no origin sigma of its own
    (``FixedLagOptions.slam_gap_origin_sigma_m`` 0, the walk over the pause only). Measured
    2026-12-03, causal ATE from 10.3 s (seed 003's UKF's first output) / from 20 s: 5.14 / 4.30
    cm with the former 5 cm, 4.46 / 3.70 cm with 0 (UKF 4.69 / 3.45 cm)."""
    import dataclasses

    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.online import replay_online

    flight = load_flight(V102["orbslam2_kf1"])
    opts = FixedLagOptions()
    assert opts.slam_gap_origin_sigma_m == 0.0
    est = replay_online(flight, opts)
    assert est.info["used"]["slam:segments-after-gap"] == 4
    assert est.info["solver_failures"] == 0 and est.info["reset_counter"] == 0
    common, late = _ate_from(est, flight, 10.3), _ate_from(est, flight, 20.0)
    assert common < 0.046 and late < 0.038, (common, late)
    old = replay_online(flight, dataclasses.replace(opts, slam_gap_origin_sigma_m=0.05))
    assert _ate_from(old, flight, 10.3) > common + 0.005
    assert _ate_from(old, flight, 20.0) > late + 0.005


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize(
    "manifest, own_span_too",
    [(MANIFEST, True), (V102["orbslam2_kf1"], True), (V102["orbslam3_kf2"], True)],
)
def test_fixed_lag_beats_the_causal_filters_on_the_common_span(real_data, manifest, own_span_too):
    # `fgnav compare`'s "ATE common" column: each method scored from the latest first output of
    # the causal methods (the filters emit nothing before their scale fit, 4-5 s after the first
    # SLAM pose on V1_02) to the end. Measured 2026-12-04 [cm], fixed-lag / ukf003 / msf-ekf:
    # MH_01 from 4.2 s 4.45 / 6.96 / 4.67 (own spans 4.53 / 6.96 / 4.67); V1_02 ORB-SLAM2 from
    # 10.3 s 4.46 / 4.69 / 7.71 (own 8.14 / 4.69 / 7.71: the smoother's 5 s before the filters
    # emit hold most of its error), ORB-SLAM3 from 8.8 s 2.70 / 3.25 / 4.58 (own 3.46 / 3.25 /
    # 4.58).
    from fgnav.compare import compare

    res = compare(load_flight(manifest), ["fixed-lag", "ukf003", "msf-ekf"], progress=False)
    ate = {n: r.ate_common_m for n, r in res.runs.items()}
    assert res.common_span_start_s is not None and None not in ate.values(), ate
    assert ate["fixed-lag"] < min(ate["ukf003"], ate["msf-ekf"]), ate
    # Each scored over its own span (the smoother from its start, the filters from their first
    # output). 2026-12-07, after a SLAM pose that arrives before the start attaches at it (it
    # was silently lost): ORB-SLAM3 2.95 / 3.25 / 4.58 cm (was 3.46). ORB-SLAM2 lost until the
    # seventh session (8.14 against ukf003's 4.69: its 5-8 s, IMU alone until the SLAM scale is
    # observable; 5.01 since the still stretch's accelerometer bias and the lone second pose's
    # wait); 4.61 since the SLAM orientations also tie the provisional alignment (ORB-SLAM3
    # 3.01 -> 3.10, MH_01 4.53 unchanged).
    own = {n: r.metrics.ate_rmse_m for n, r in res.runs.items()}
    if own_span_too:
        assert own["fixed-lag"] < min(own["ukf003"], own["msf-ekf"]), own


@pytest.mark.slow
@pytest.mark.realdata
def test_euroc_mh01_identity_body_T_cam_replaced_by_the_fitted_rotation(real_data):
    """A calibration whose camera rotation is the identity (90 deg off on EuRoC): the
    SLAM-vs-gyro check names it and, with ``[graph] slam_extrinsic = "auto"``, both smoothers
    use the rotation the gyro fits (0.55 deg from the true one). Measured 2026-12-07: batch
    2.79 cm (nominal 2.8; before: LM did not converge), push engine 5.1 cm, no reset (nominal
    4.5; before: diverged, 3.9 m after 3 rebuilds); with the early misfit (1.2 s in) and the
    chain's rotation from the motion, 5.2 cm."""
    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.online import replay_online

    flight = load_flight(MANIFEST)
    T = np.array(flight.calib.body_T_cam, float)
    T[:3, :3] = np.eye(3)
    bad = dataclasses.replace(flight, calib=dataclasses.replace(flight.calib, body_T_cam=T))
    est = solve_batch(bad, BatchOptions(covariance="none"))
    assert est.info["slam_gyro_check"]["body_R_cam_replaced"]
    assert evaluate(est, flight.ground_truth, alignment="se3").ate_rmse_m < 0.035
    push = replay_online(bad, FixedLagOptions())
    check = push.info["slam_gyro_check"]
    assert check["body_R_cam_replaced"] and not check["body_R_cam_ok"]
    assert push.info["reset_counter"] == 0
    assert push.info["slam_extrinsic_suspect"]["t"] - flight.slam.t[0] < 2.0
    assert evaluate(push, flight.ground_truth, alignment="se3").ate_rmse_m < 0.065
