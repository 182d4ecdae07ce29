"""A range reading at the sensor's maximum is no distance (a missing echo): the simulator's
``range_no_echo_at_max``, the batch and push smoothers and a filter baseline on simulated
two-turns flights (seed 1, 24 s) with readings at ``range_max`` (fixed seeds)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.events import replay_flight
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.compare import score_estimate
from fgnav.methods import METHODS, run_batch
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.online import PUSH_STREAMS, OnlineSmoother


def _online(flight):
    sm = OnlineSmoother(flight.calib, FixedLagOptions(), flight.name)
    for ev in replay_flight(flight, [n for n in PUSH_STREAMS if getattr(flight, n) is not None]):
        sm.feed(ev)
    return sm.result()


def _with_range(f, values):
    return dataclasses.replace(f, range=dataclasses.replace(f.range, range=values))


@pytest.fixture(scope="module")
def two_turns():
    """The fault matrix's flight, its ATEs (batch, online), and copies with every third reading
    at ``range_max`` (intermittent missing echoes) and with every reading at it."""
    f = simulate("two-turns", 1, SimOptions(duration=24.0, images=False))
    hi = float(f.calib.range_max)
    r = f.range.range
    third = _with_range(f, np.where(np.arange(len(r)) % 3 == 0, hi, r))
    every = _with_range(f, np.full(len(r), hi))
    ate = (score_estimate(f, run_batch(f, {})).ate_rmse_m, score_estimate(f, _online(f)).ate_rmse_m)
    return f, ate, third, every


def test_simulated_missing_echoes_are_reported_at_the_maximum():
    """``range_no_echo_at_max``: the dropouts are delivered as ``range_max``; every other
    reading is the default flight's (the same random draws)."""
    opts = SimOptions(duration=8.0, images=False, range_dropout_prob=0.2)
    f = simulate("two-turns", 1, opts)
    g = simulate("two-turns", 1, dataclasses.replace(opts, range_no_echo_at_max=True))
    at_max = g.range.range == g.calib.range_max
    assert int(at_max.sum()) == g.meta["notes"]["range_no_echo_at_max"] == 47
    assert len(g.range) == len(f.range) + 47
    np.testing.assert_array_equal(g.range.t[~at_max], f.range.t)
    np.testing.assert_array_equal(g.range.range[~at_max], f.range.range)


def test_batch_takes_no_height_from_readings_at_the_maximum(two_turns):
    """Every third reading at 8 m: before, each keyframe next to one interpolated it into a
    height (ATE 0.0294 m against 0.0070 m nominal, 4.2x, health "ok"); now both brackets of a
    keyframe are tested, no such keyframe has a range factor, the ATE is nominal."""
    f, (ate0, _), bad, _ = two_turns
    est = run_batch(bad, {})
    h = est.info["health"]
    n_max = int((bad.range.range == bad.calib.range_max).sum())
    assert h["status"] == "ok" and h["detectors"] == {}
    assert h["dropped"] == {"range:at-max": n_max}
    assert est.info["skipped"]["range:at-max"] > 250  # keyframes with a bracket at 8 m
    assert score_estimate(bad, est).ate_rmse_m < 1.3 * ate0  # measured 0.0070 / 0.0070 m


def test_a_rangefinder_at_its_maximum_all_flight_is_no_height_and_not_stuck(two_turns):
    """Every reading at 8 m (no echo all flight): before, a constant reading while the height
    changed, named range-stuck (a fault), and online the readings before the detector could
    tell were heights (0.0552 m against 0.0271 nominal); now none is a height, nothing named."""
    f, (ate0_batch, ate0_online), _, bad = two_turns
    est = _online(bad)
    h = est.info["health"]
    assert h["detectors"] == {} and h["status"] == "ok"
    assert est.info["dropped"]["range:at-max"] == h["dropped"]["range:at-max"] > 400
    assert "range" not in est.info["used"]
    assert score_estimate(bad, est).ate_rmse_m < 1.3 * ate0_online  # measured 0.0321 / 0.0271
    b = run_batch(bad, {})
    assert b.info["health"]["detectors"] == {}
    assert b.info["health"]["dropped"] == {"range:at-max": len(bad.range)}
    assert score_estimate(bad, b).ate_rmse_m < 1.3 * ate0_batch


def test_online_counts_readings_at_the_maximum(two_turns):
    """The push engine refuses a reading at the maximum and a keyframe bracketed by one
    (counted ``range:at-max``, none a factor); the ATE stays nominal (0.0262 / 0.0271 m)."""
    f, (_, ate0), bad, _ = two_turns
    est = _online(bad)
    assert est.info["dropped"]["range:at-max"] > 250
    assert est.info["health"]["detectors"] == {}
    assert score_estimate(bad, est).ate_rmse_m < 1.1 * ate0


def test_a_filter_baseline_counts_readings_at_the_maximum(two_turns):
    """msf-ekf: each reading at 8 m is refused and counted in ``info["unused"]``."""
    _, _, bad, _ = two_turns
    est = METHODS["msf-ekf"].run(bad, {})
    n_max = int((bad.range.range == bad.calib.range_max).sum())
    assert est.info["unused"]["range:at-max"] == n_max
