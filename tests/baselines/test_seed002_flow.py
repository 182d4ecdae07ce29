"""Seed 002's attitude-and-height EKF with flow dead reckoning on a simulated flow-deck flight:
figures against the truth, causality, skipped readings counted."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.events import replay_flight
from fgnav.datasets.simulate import SimOptions, simulate
from testutil import CRAZYFLIE_LIKE, assert_same_prefix, feed_until

from fgnav.baselines.seed002_flow import Seed002Flow, run_seed002_flow
from fgnav.eval.metrics import flow_flight_figures
from fgnav.methods import METHODS


@pytest.fixture(scope="module")
def flight():
    return simulate("flowdeck", seed=0, options=SimOptions(duration=20.0, **CRAZYFLIE_LIKE))


#: Measured 2026-12-02 on flowdeck seed 0, 20 s, Crazyflie-like rangefinder, 4-DoF alignment:
#: horizontal velocity RMSE 0.143 m/s (100 ms trailing means of the dead-reckoned position:
#: the per-reading flow noise and a 50 ms lag), height RMSE 7.1 mm, ATE 6.8 cm; noise-free:
#: 0.039 m/s (the lag), ATE 0.9 cm.
FLOW002_HVEL_BOUND, FLOW002_HEIGHT_BOUND, FLOW002_ATE_BOUND = 0.19, 0.011, 0.10


def test_figures_on_the_simulated_flow_deck_flight(flight):
    est = METHODS["ekf-flow002"].run(flight, {})
    fig = flow_flight_figures(est, flight.ground_truth)
    assert fig["hvel_rmse_mps"] < FLOW002_HVEL_BOUND
    assert fig["height_rmse_m"] < FLOW002_HEIGHT_BOUND
    assert fig["ate_m"] < FLOW002_ATE_BOUND
    c = est.info["counts"]
    n_low = flight.meta["notes"]["flow_low_quality"]
    assert c["flow_low_quality"] == n_low > 0
    assert c["flow_used"] + n_low + c["flow_before_start"] + c["flow_no_height"] == len(flight.flow)
    clean = simulate(
        "flowdeck", seed=0, options=SimOptions(duration=20.0, noise_free=True, **CRAZYFLIE_LIKE)
    )
    fig0 = flow_flight_figures(run_seed002_flow(clean), clean.ground_truth)
    assert fig0["ate_m"] < 0.02 and fig0["hvel_rmse_mps"] < 0.05


def test_causal_a_run_cut_at_t_gives_the_same_states_before_t(flight):
    full = run_seed002_flow(flight)
    f = Seed002Flow()
    f.start(flight.calib, flight.name)
    part = feed_until(f, replay_flight(flight, ("imu", "yaw", "range", "flow")), 8.0)
    assert_same_prefix(part, full, min_states=700, t_cut=8.0, atol=0.0)
    np.testing.assert_array_equal(f.latest()[0], part.trajectory.world_t_body[-1])
