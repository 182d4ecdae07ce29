"""The smoothers on real Crazyflie flow-deck flights (UTIL traj1, traj2; issue 17): IMU + flow +
range, no Vicon used by the estimators. Bounds are the figures measured on 2026-12-03
(``scripts/crazyflie_table.py``) with a margin; the accelerometer check must find the
horizontal channels unusable (drag off, thrust-only prediction with drag dynamics) in the batch
and the push engine, and the push engine's tilt must stay within a few degrees of Vicon."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.crazyflie import read_crazyflie
from fgnav.datasets.geometry import quat_wxyz_to_matrix

from fgnav.eval.align import interpolate_trajectory
from fgnav.eval.flow_table import flow_figures
from fgnav.methods import METHODS

pytestmark = [pytest.mark.realdata, pytest.mark.slow]

#: (flight, method) -> upper bounds: velocity RMSE of 100 ms averages [m/s], height RMSE [m].
BOUNDS = {
    # measured 0.037, 0.61 cm (ground walk 0.002 m/sqrt(s), 2026-12-02; 0.82 cm at 0.01)
    ("0425-traj1", "batch"): (0.045, 0.0075),
    ("0425-traj1", "fixed-lag"): (0.073, 0.0105),  # 0.067, 0.90 cm (1.05 cm at 0.01)
    ("0425-traj2", "batch"): (0.055, 0.008),  # 0.047, 0.66 cm (0.95 cm)
    ("0425-traj2", "fixed-lag"): (0.069, 0.011),  # 0.062, 0.97 cm (1.20 cm)
}
#: (flight, method) -> upper bound of the end drift with the start pose known [% of the path]
#: (measured 0.99, 1.31, 1.84, 1.40 with the thrust-only bias walk at 0.5 s (cf17c); 1.00, 1.33,
#: 1.86, 1.44 at 3 s; 1.48, 1.68, 2.11, 1.80 before the yaw-rate bias hold and the flow gain).
DRIFT_BOUNDS = {
    ("0425-traj1", "batch"): 1.1,
    ("0425-traj1", "fixed-lag"): 1.45,
    ("0425-traj2", "batch"): 2.0,
    ("0425-traj2", "fixed-lag"): 1.55,
}
#: traj3 (the fastest flight, steady 1.25 m/s circles): push-engine velocity RMSE (100 ms) and
#: end drift bounds [m/s], [%]: measured 0.068 m/s, 0.19 % with the thrust-only bias walk at
#: 0.5 s; 0.095 m/s at 3 s (the push engine overshot the speed by 8 % along the track).
TRAJ3_FIXED_LAG_BOUNDS = (0.075, 0.5)
#: Largest and RMS tilt error of the push engine's newest state against Vicon [deg] (measured
#: 2.7 / 1.2 on traj1, 3.8 / 1.0 on traj2; 14 deg on traj6 before the provisional thrust-only
#: start: the spinning-up accelerometer on the ground tilted it).
TILT_BOUNDS = (5.0, 1.5)


@pytest.fixture(scope="module")
def flights():
    from testutil import require_real_data

    root = require_real_data() / "crazyflie_util_flowdeck"
    if not root.is_dir():
        pytest.skip(f"{root} is absent")
    return {n: read_crazyflie(root / n) for n in ("0425-traj1", "0425-traj2")}


@pytest.fixture(scope="module")
def runs(flights):
    out = {}
    for name, f in flights.items():
        for m in ("batch", "fixed-lag", "cf-ekf", "ekf-flow002"):
            est = METHODS[m].run(f, {})
            out[name, m] = (est, flow_figures(est, f.ground_truth))
    return out


@pytest.mark.parametrize("key", sorted(BOUNDS))
def test_bounds(runs, key):
    _, fig = runs[key]
    vel, height = BOUNDS[key]
    assert fig["hvel100_rmse_mps"] <= vel, fig
    assert fig["height_rmse_m"] <= height, fig


@pytest.mark.parametrize("key", sorted(DRIFT_BOUNDS))
def test_end_drift_bounds(runs, key):
    assert runs[key][1]["start_drift_pct"] <= DRIFT_BOUNDS[key], runs[key][1]


@pytest.mark.parametrize("method", ["batch", "fixed-lag"])
def test_yaw_rate_bias_held_at_its_prior(runs, method):
    """Thrust-only, no yaw source: the gyro's z bias stays at its prior mean (it moved to
    +0.8 / +0.6 mrad/s on traj1 when estimated, against Vicon's -0.9 in flight)."""
    for flight in ("0425-traj1", "0425-traj2"):
        gb = runs[flight, method][0].trajectory.gyro_bias
        assert gb is not None
        assert np.abs(gb[:, 2] - gb[0, 2]).max() < 3e-4, (flight, method)
        if method == "batch":
            assert abs(gb[0, 2]) < 3e-4, flight


@pytest.mark.parametrize("flight", ["0425-traj1", "0425-traj2"])
def test_smoothers_beat_both_filters_on_velocity_and_height(runs, flight):
    for m in ("batch", "fixed-lag"):
        fig = runs[flight, m][1]
        for f in ("cf-ekf", "ekf-flow002"):
            other = runs[flight, f][1]
            assert fig["hvel100_rmse_mps"] < other["hvel100_rmse_mps"], (m, f)
            assert fig["height_rmse_m"] < other["height_rmse_m"], (m, f)


@pytest.mark.parametrize("flight", ["0425-traj1", "0425-traj2"])
def test_drag_decision_unusable_accelerometer(runs, flight):
    batch = runs[flight, "batch"][0].info
    assert batch["accel_check"]["decision"] == "unusable"
    assert batch["accel_check"]["ratio"] > 2.0
    assert batch["drag_disabled"].startswith("accelerometer check: drag off")
    assert batch["accel_horizontal"] == "thrust-only"
    assert "drag" not in batch["factors"]
    online = runs[flight, "fixed-lag"][0].info
    assert online["engine"] == "push"
    assert online["accel_check"]["decision"] == "unusable"
    assert online["accel_horizontal"] == "thrust-only"
    assert online["drag"].startswith("off at t=")
    assert online["used"].get("contact", 0) > 20  # on the floor before take-off and after landing
    # The thrust-only prediction's drag dynamics in both smoothers.
    assert batch["factors"].get("drag-dynamics", 0) > 500
    assert online["used"].get("drag-dynamics", 0) > 500


@pytest.mark.parametrize("flight", ["0425-traj1", "0425-traj2"])
def test_push_engine_tilt_stays_within_a_few_degrees(runs, flights, flight):
    est = runs[flight, "fixed-lag"][0]
    tr, gt = est.trajectory, flights[flight].ground_truth
    ok = (tr.t > gt.t[0]) & (tr.t < gt.t[-1])
    g = interpolate_trajectory(gt, tr.t[ok])
    up = quat_wxyz_to_matrix(tr.world_q_body_wxyz[ok])[:, 2, :]  # world z in body axes
    up_true = quat_wxyz_to_matrix(g.world_q_body_wxyz)[:, 2, :]
    ang = np.degrees(np.arccos(np.clip((up * up_true).sum(axis=1), -1.0, 1.0)))
    assert ang.max() <= TILT_BOUNDS[0] and np.sqrt(np.mean(ang**2)) <= TILT_BOUNDS[1], (
        ang.max(),
        np.sqrt(np.mean(ang**2)),
    )


def test_traj3_push_engine_velocity_with_the_flow_gain():
    """traj3's fixed-lag velocity regressed to 0.095 m/s with ``flow_rate_gain`` (0.065 with the
    linear scale, whose 8 % under-read at traj3's rates hid it): a thrust-only bias walk of 3 s
    was too slow for the drag misfit that turns with the body velocity, and the filter overshot
    the speed in steady fast flight. Also the batch stays below the goals there."""
    from testutil import require_real_data

    path = require_real_data() / "crazyflie_util_flowdeck" / "0425-traj3"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    f = read_crazyflie(path)
    fig = flow_figures(METHODS["fixed-lag"].run(f, {}), f.ground_truth)
    assert fig["hvel100_rmse_mps"] <= TRAJ3_FIXED_LAG_BOUNDS[0], fig
    assert fig["start_drift_pct"] <= TRAJ3_FIXED_LAG_BOUNDS[1], fig
    assert fig["height_rmse_m"] <= 0.0105, fig  # 0.90 cm (1.09 cm with a ground walk of 0.01)
    b = flow_figures(METHODS["batch"].run(f, {}), f.ground_truth)
    assert b["hvel100_rmse_mps"] <= 0.045 and b["start_drift_pct"] <= 0.6, b  # 0.037, 0.34 %


def test_traj6_height_beats_the_crazyflie_ekf():
    """traj6 (the highest flight, 2 m): with a terrain walk of 0.01 m/sqrt(s) the ground height
    wandered by up to 4 cm (batch -2 cm in the climb, +4 cm on the floor after landing) and both
    smoothers lost to cf-ekf's flat-floor height (batch 1.27, fixed-lag 1.03 against 0.98 cm);
    at the default 0.002: 0.66 and 0.82 cm."""
    from testutil import require_real_data

    path = require_real_data() / "crazyflie_util_flowdeck" / "0425-traj6"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    f = read_crazyflie(path)
    ekf = flow_figures(METHODS["cf-ekf"].run(f, {}), f.ground_truth)["height_rmse_m"]
    for m, bound in (("batch", 0.0075), ("fixed-lag", 0.0095)):
        h = flow_figures(METHODS[m].run(f, {}), f.ground_truth)["height_rmse_m"]
        assert h <= bound and h < ekf, (m, h, ekf)


def _drift_parts():
    """``scripts/crazyflie_drift_parts.py`` as a module (its ``parts``: the end drift of the
    estimate's velocity integrated over the truth's times, start pose known)."""
    import importlib.util
    import sys

    from testutil import PROJECT_ROOT

    path = PROJECT_ROOT / "scripts" / "crazyflie_drift_parts.py"
    spec = importlib.util.spec_from_file_location("crazyflie_drift_parts", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    try:
        spec.loader.exec_module(mod)
    finally:
        del sys.modules[spec.name]
    return mod


#: traj2 / traj13 (the two flights with a still stretch before the push engine's start):
#: causal end drift of the integrated velocity [%] (``crazyflie_drift_parts``) with the first
#: gyro bias at zero (the firmware removed the rest bias): measured 0.93 / 0.85; 1.59 / 1.49
#: when it was the stretch's mean rate (1-1.5 mrad/s off on x, y; body z held 0.7 / 0.2 mrad/s
#: off). Position end drift (``start_drift_pct``) 1.40 / 0.64 -> 1.33 / 0.60 %.
STILL_START_DRIFT_BOUND = 1.1


@pytest.mark.parametrize("name", ["0425-traj2", "0425-traj13"])
def test_push_engine_keeps_the_rest_bias_removed_by_the_firmware(flights, name):
    from testutil import require_real_data

    f = flights.get(name)
    if f is None:
        path = require_real_data() / "crazyflie_util_flowdeck" / name
        if not path.exists():
            pytest.skip(f"{path} is absent")
        f = read_crazyflie(path)
    assert f.calib.imu_noise.rest_bias_removed
    est = METHODS["fixed-lag"].run(f, {})
    gb = est.trajectory.gyro_bias
    assert np.abs(gb[0]).max() < 1e-4, gb[0]  # the still stretch's mean is not taken
    assert np.abs(gb[:, 2]).max() < 3e-4  # body z held at the prior's zero
    r = _drift_parts().parts(est, f)
    assert r["drift"] <= STILL_START_DRIFT_BOUND, r


def test_push_engine_counts_every_flow_reading(flights):
    """Every flow reading is used or dropped by reason. Fed straight to the push API (without
    the replay's `use_slam = false`), the smoother waits ``start_wait_s`` for a SLAM pose and
    starts in flight: the readings before that are ``flow:before-start`` (they were counted as
    ``flow:late``)."""
    from fgnav.datasets.events import replay_flight

    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.online import PUSH_STREAMS, feed_all

    f = flights["0425-traj1"]
    streams = [n for n in PUSH_STREAMS if getattr(f, n, None) is not None]
    est = feed_all(replay_flight(f, streams), f.calib, FixedLagOptions(), f.name).result()
    i = est.info
    flow_out = {k: v for k, v in {**i["dropped"], **i["skipped"]}.items() if k[:5] == "flow:"}
    assert i["used"]["flow"] + sum(flow_out.values()) == i["received"]["flow"] == len(f.flow)
    # The first keyframe's window reaches half a keyframe interval before the start.
    t0 = est.trajectory.t[0]
    lo, hi = (int(np.count_nonzero(f.flow.t <= t)) for t in (t0 - 0.05, t0))
    assert 0 < lo <= flow_out["flow:before-start"] <= hi and "flow:late" not in flow_out


def test_replay_of_a_log_without_slam_starts_at_once(flights):
    """``replay_online`` itself (not only ``fgnav online``) tells the smoother the log has no
    SLAM stream: called directly it waited ``start_wait_s`` (5 s), started in flight with
    the accelerometer unusable and diverged (traj1: 1.26 m after a rebuild, against 0.106 m)."""
    from fgnav.eval.metrics import evaluate
    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.online import replay_online

    f = flights["0425-traj1"]
    est = replay_online(f, FixedLagOptions())
    assert est.trajectory.t[0] - f.imu.t[0] < 1.0
    assert est.info["reset_counter"] == 0
    assert evaluate(est, f.ground_truth, alignment="4dof").ate_rmse_m < 0.15
