"""The batch smoother's input from events (fgnav.solvers.collect.EventCollector)."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import ImageFrame, ImuSample, SlamPose, replay_flight

from fgnav.eval.metrics import evaluate
from fgnav.methods import run_batch
from fgnav.solvers.collect import EventCollector

STREAMS = ("imu", "attitude", "range", "yaw", "slam")


def test_replayed_events_give_the_flight_back_and_the_same_batch(two_turns_12s):
    """Events in arrival order (SLAM 0.1 s late) -> the same arrays (SLAM latency from arrival
    minus capture) -> the same batch solution as from the flight itself."""
    flight = two_turns_12s
    c = EventCollector(flight.calib, "collected")
    for ev in replay_flight(flight, STREAMS):
        c.feed(ev)
    g = c.flight()
    assert set(g.streams()) == set(STREAMS)
    for s in STREAMS:
        for name in ("t", "body_omega", "body_accel", "world_q_body_wxyz", "range", "yaw"):
            if hasattr(getattr(flight, s), name):
                np.testing.assert_array_equal(
                    getattr(g, s).__dict__[name], getattr(flight, s).__dict__[name]
                )
    np.testing.assert_array_equal(g.slam.slam_t_cam, flight.slam.slam_t_cam)
    np.testing.assert_array_equal(g.slam.session, flight.slam.session)
    np.testing.assert_allclose(g.slam.latency, flight.slam.latency, atol=1e-9)
    assert c.counts() == {
        "kept": {s: len(getattr(flight, s)) for s in sorted(STREAMS)},
        "dropped": {},
    }
    ate = evaluate(run_batch(g, {}), flight.ground_truth).ate_rmse_m
    direct = evaluate(run_batch(flight, {}), flight.ground_truth).ate_rmse_m
    assert ate == pytest.approx(direct, abs=1e-9) and ate < 0.02


def test_order_duplicates_and_what_is_left_out(two_turns_12s):
    """Any order is sorted per stream; a repeated stamp, a non-finite value, a tracking-lost
    pose and an image are left out, each counted by reason; no IMU is an error."""
    flight = two_turns_12s
    c = EventCollector(flight.calib)
    with pytest.raises(FlightDataError, match="no IMU sample collected"):
        c.flight()
    evs = list(replay_flight(flight, ("imu", "slam")))
    rng = np.random.default_rng(3)
    for i in rng.permutation(len(evs)):
        c.feed(evs[i])
    imu = [e for e in evs if isinstance(e, ImuSample)]
    c.feed(imu[5])  # the same stamp again
    c.feed(imu[6]._replace(body_accel=np.array([np.nan, 0.0, 9.8])))
    pose = next(e for e in evs if isinstance(e, SlamPose))
    c.feed(pose._replace(t=pose.t + 0.01, session=-1))
    c.feed(ImageFrame(t=1.0, arrival=1.0, index=0, camera=None))
    g = c.flight()
    np.testing.assert_array_equal(g.imu.t, flight.imu.t)
    np.testing.assert_array_equal(g.slam.t, flight.slam.t)
    assert c.counts()["dropped"] == {
        "images:not-collected": 1,
        "imu:duplicate-time": 1,
        "imu:non-finite": 1,
        "slam:tracking-lost": 1,
    }
