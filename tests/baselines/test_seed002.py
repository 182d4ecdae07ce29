"""Seed 002 baseline (attitude/height EKF + rectified homography VO) on a short simulated
two-turns flight with rendered images, against truth.

Bounds are about 2x the values measured with this code (quoted in each test)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import ImageFrame, ImuSample, RangeReading, replay_flight
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.baselines.seed002 import Seed002Vo, run_seed002
from fgnav.eval.metrics import evaluate

DURATION_S = 10.0
"""Seconds of two-turns flown (hover, then the start of the first turn): rendering and VO take
about 4 s."""


@pytest.fixture(scope="module")
def flight():
    return simulate("two-turns", 1, SimOptions(duration=DURATION_S))


def test_two_turns_dead_reckoning_against_truth(flight):
    """Measured (seed 1, 10 s, 201 frames): ATE 1.4 cm after SE(3) alignment, 4.6 cm with no
    alignment (start at the origin with the EKF yaw), yaw 0.67 deg, velocity (backward
    difference of 20 Hz positions) 0.22 m/s; all 200 pairs valid."""
    est = run_seed002(flight)
    assert est.method == "ekf-vo002" and est.causal
    assert len(est.trajectory) == len(flight.images)
    assert est.info["vo_counts"]["valid_pairs"] == len(flight.images) - 1
    m = evaluate(est, flight.ground_truth, "se3")
    assert m.ate_rmse_m < 0.03
    assert m.yaw_rmse_deg < 1.5
    assert m.vel_rmse_mps < 0.4
    # Without alignment: the VO starts at the world origin, the truth does not.
    gt = flight.ground_truth
    k = np.searchsorted(gt.t, est.trajectory.t)
    start = gt.world_t_body[k[0]] * [1.0, 1.0, 0.0]
    err = est.trajectory.world_t_body - (gt.world_t_body[k] - start)
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) < 0.1


def test_missing_streams_are_named(flight):
    with pytest.raises(FlightDataError, match="missing: images"):
        run_seed002(dataclasses.replace(flight, images=None))
    with pytest.raises(FlightDataError, match="missing: range, images"):
        run_seed002(dataclasses.replace(flight, images=None, range=None))


def test_event_fed_run_is_the_whole_flight_run_and_causal(flight):
    """Fed the flight's events one at a time it gives what run_seed002 gives; stopped at T, its
    newest output is the full run's row at that time (nothing depends on later events)."""
    full = run_seed002(flight)
    vo = Seed002Vo()
    vo.start(flight.calib, flight.name)
    T = 6.02
    seen = None
    for ev in replay_flight(flight, ("imu", "yaw", "range", "images"), named_order=True):
        if ev.arrival > T and seen is None:
            seen = vo.latest_output()
        vo.feed(ev)
    vo.close()
    est = vo.result()
    for k in ("t", "world_t_body", "world_q_body_wxyz", "world_v_body"):
        np.testing.assert_array_equal(getattr(est.trajectory, k), getattr(full.trajectory, k))
    assert est.info["vo_counts"] == full.info["vo_counts"]
    t, p, q, v = seen
    assert vo.latest()[0] == vo.output_t == est.trajectory.t[-1]
    i = int(np.flatnonzero(full.trajectory.t == t)[0])
    assert T - 0.1 < t <= T and i > 0
    np.testing.assert_array_equal(p, full.trajectory.world_t_body[i])
    np.testing.assert_array_equal(q, full.trajectory.world_q_body_wxyz[i])
    np.testing.assert_array_equal(v, full.trajectory.world_v_body[i])


def test_out_of_order_and_late_events_are_counted_not_fatal(flight):
    """An IMU sample and an image older than their stream's newest, a range reading arriving
    after its time: counted, and the dead reckoning goes on."""
    events = list(replay_flight(flight, ("imu", "yaw", "range", "images"), named_order=True))
    k = next(i for i, e in enumerate(events) if e.arrival > 5.0)
    old_imu = next(e for e in events if isinstance(e, ImuSample) and e.t > 4.0)
    old_img = next(e for e in events if isinstance(e, ImageFrame) and e.t > 4.0)
    old_rng = next(e for e in events if isinstance(e, RangeReading) and e.t > 4.9)
    events = [*events[:k], old_imu, old_img, old_rng._replace(arrival=5.0), *events[k:]]
    vo = Seed002Vo()
    vo.start(flight.calib, flight.name)
    for ev in events:
        vo.feed(ev)
    vo.close()
    est = vo.result()
    assert vo.ekf_counts["imu_late"] == 1 and vo.ekf_counts["late"] >= 1
    assert vo.vo_counts["image_out_of_order"] == 1
    assert len(est.trajectory) == len(flight.images)
    m = evaluate(est, flight.ground_truth, "se3")
    assert m.ate_rmse_m < 0.03
