"""The smoothers on real Crazyflie flow-deck flights (UTIL traj1, traj2; issue 17): IMU + flow +
range, no Vicon used by the estimators. Bounds are the figures measured on 2026-12-02
(``scripts/crazyflie_table.py``) with a margin; the accelerometer check must find the horizontal
channels unusable (drag off, thrust-only prediction) in the batch and the push engine."""

from __future__ import annotations

import pytest
from fgnav.datasets.crazyflie import read_crazyflie

from fgnav.eval.flow_table import flow_figures
from fgnav.methods import METHODS

pytestmark = [pytest.mark.realdata, pytest.mark.slow]

#: (flight, method) -> upper bounds: velocity RMSE of 100 ms averages [m/s], height RMSE [m].
BOUNDS = {
    ("0425-traj1", "batch"): (0.06, 0.010),
    ("0425-traj1", "fixed-lag"): (0.11, 0.013),
    ("0425-traj2", "batch"): (0.075, 0.013),
    ("0425-traj2", "fixed-lag"): (0.14, 0.014),
}


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
