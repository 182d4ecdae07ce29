"""Downward-sensor faults the health report names (fgnav.health): a rangefinder pinned at its
floor (``range-at-min``), a wholly rejected optical-flow stream (``flow-rejected``) and a flow
stream with no height source (``flow-no-height``); the detectors on hand-made readings, the
push-API smoother and the batch on simulated flights (fixed seeds)."""

from __future__ import annotations

import dataclasses
import logging

import gtsam
import numpy as np
import pytest
from fgnav.datasets.events import RangeReading, replay_flight
from fgnav.datasets.simulate import SimOptions, simulate
from fgnav.factors.tilted_range import RANGE_AT_MIN_TOL_M, gate_range, range_clamps
from testutil import CRAZYFLIE_LIKE, require_real_data

from fgnav.compare import score_estimate
from fgnav.health import DEGRADED_QUALITY, Context, FaultDetectors
from fgnav.methods import run_batch
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.online import PUSH_STREAMS, OnlineSmoother

DOWN = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.zeros(3))


def _online(flight):
    sm = OnlineSmoother(flight.calib, FixedLagOptions(), flight.name)
    for ev in replay_flight(flight, [n for n in PUSH_STREAMS if getattr(flight, n) is not None]):
        sm.feed(ev)
    est = sm.result()
    return sm, est, score_estimate(flight, est).ate_rmse_m


@pytest.mark.parametrize(
    ("range_meas", "clamps", "ok", "reason"),
    [
        (0.1, True, False, "at-min"),
        (0.1 + 0.5 * RANGE_AT_MIN_TOL_M, True, False, "at-min"),
        (0.1 + 2.0 * RANGE_AT_MIN_TOL_M, True, True, "ok"),
        (0.1, False, True, "ok"),  # a sensor that read below its floor: a distance
        (0.09, True, False, "out of range"),
    ],
)
def test_gate_range_at_the_floor(range_meas, clamps, ok, reason):
    accepted, why = gate_range(range_meas, np.eye(3), DOWN, 0.1, 8.0, np.deg2rad(30), clamps)
    assert accepted is ok and why.startswith(reason)


def test_range_at_min_named_while_the_height_changes_not_at_take_off():
    height = {"z": 0.0}
    det = FaultDetectors(context=Context(height=lambda t: height["z"]), range_min=0.1)
    for i in range(100):
        t = i * 0.04
        height["z"] = 0.2 * t  # climbing at 0.2 m/s, the sensor pinned at its 0.1 m floor
        assert det.feed(RangeReading(t, t, 0.1, -1.0)) is not None  # (the gates drop it)
    # Named once the height moved by more than 0.15 m + range_min (0.25 m): at t = 1.28 s.
    assert det.counts == {"range-at-min": 1}  # not range-stuck: identical values, no distance
    assert det.at_min_runs == [(0.0, pytest.approx(1.28))]
    assert "rangefinder at its minimum 0.100 m since t=0.00" in det.details["range-at-min"][0]
    # A take-off: at the floor while the height goes 0 -> 0.2 m (under it, as it reads), then
    # distances: nothing named.
    det = FaultDetectors(context=Context(height=lambda t: height["z"]), range_min=0.1)
    for i in range(100):
        t = i * 0.04
        height["z"] = min(0.2 * t, 0.2)
        det.feed(RangeReading(t, t, 0.1 if t < 1.0 else 0.2 + 0.01 * np.sin(t), -1.0))
    assert det.counts == {}
    # A sensor that has read below its floor does not clamp there: 0.1 is a distance (and a
    # constant one while the height changes is range-stuck, as before).
    det = FaultDetectors(context=Context(height=lambda t: height["z"]), range_min=0.1)
    det.feed(RangeReading(0.0, 0.0, 0.05, -1.0))
    for i in range(1, 100):
        t = i * 0.04
        height["z"] = 0.2 * t
        det.feed(RangeReading(t, t, 0.1, -1.0))
    assert "range-at-min" not in det.counts and det.counts["range-stuck"] == 1


@pytest.fixture(scope="module")
def two_turns():
    """The fault matrix's flight (seed 1, 24 s, no images) and a copy with every range reading
    at the calibration's ``range_min``."""
    f = simulate("two-turns", 1, SimOptions(duration=24.0, images=False))
    r = np.full(len(f.range), float(f.calib.range_min))
    return f, dataclasses.replace(f, range=dataclasses.replace(f.range, range=r))


def test_online_range_pinned_at_min_is_named_and_no_height(two_turns):
    """Before: the readings at the floor were heights (ATE 0.152 m against 0.027 m nominal,
    health "ok"); now none is a factor, the fault is named, the ATE near nominal."""
    f, bad = two_turns
    _, _, ate0 = _online(f)
    sm, est, ate = _online(bad)
    h = est.info["health"]
    assert h["detectors"] == {"range-at-min": 1} and h["status"] == "degraded"
    assert est.info["dropped"]["range:at-min"] == h["dropped"]["range:at-min"] > 400
    assert "range" not in est.info["used"]
    assert ate < 1.3 * ate0, (ate, ate0)  # measured 0.032 / 0.027 m


def test_batch_range_pinned_at_min_is_named_and_no_height(two_turns):
    """Before: 0.137 m against 0.007 m nominal, health "ok" (and the stuck-range test solve,
    every reading removed, failed on an empty range stream)."""
    f, bad = two_turns
    ate0 = score_estimate(f, run_batch(f, {})).ate_rmse_m
    est = run_batch(bad, {})
    h = est.info["health"]
    assert h["detectors"] == {"range-at-min": 1} and h["status"] == "degraded"
    assert h["dropped"] == {"range:at-min": len(bad.range)}
    assert est.info["factors"].get("range", 0) == 0
    assert score_estimate(bad, est).ate_rmse_m < 1.3 * ate0  # measured 0.0071 / 0.0070 m


def test_batch_range_stuck_from_the_first_reading_is_dropped(two_turns):
    """A rangefinder stuck at 2.0 m for the whole flight: the stuck-range test solve (every
    reading removed) raised on an empty range stream and the readings were kept; now the run is
    named and dropped."""
    f, _ = two_turns
    r = np.full(len(f.range), 2.0)
    bad = dataclasses.replace(f, range=dataclasses.replace(f.range, range=r))
    ate0 = score_estimate(f, run_batch(f, {})).ate_rmse_m
    est = run_batch(bad, {})
    h = est.info["health"]
    assert h["detectors"]["range-stuck"] == 1 and h["dropped"]["range:stuck"] == len(r)
    assert score_estimate(bad, est).ate_rmse_m < 1.3 * ate0


def test_online_range_stuck_from_the_first_reading_is_named(two_turns):
    """Stuck at 2.0 m from the first reading: the run began before any height was known and
    was never tested (ATE 0.152 m, health "ok"); now compared from the first height known in
    it, named at 11 s, its readings dropped from there."""
    f, _ = two_turns
    r = np.full(len(f.range), 2.0)
    bad = dataclasses.replace(f, range=dataclasses.replace(f.range, range=r))
    _, _, ate0 = _online(f)
    _, est, ate = _online(bad)
    h = est.info["health"]
    assert h["detectors"] == {"range-stuck": 1} and h["dropped"]["range:stuck"] > 250
    assert ate < 2.0 * ate0, (ate, ate0)  # measured 0.047 / 0.027 m


@pytest.fixture(scope="module")
def flow_deck():
    """A Crazyflie-like flow-deck flight (seed 0, 12 s: IMU, flow, range)."""
    return simulate("flowdeck", 0, SimOptions(duration=12.0, **CRAZYFLIE_LIKE))


def test_flow_wholly_rejected_is_a_degrading_fault(flow_deck):
    f = flow_deck
    bad = dataclasses.replace(f, flow=dataclasses.replace(f.flow, quality=np.zeros(len(f.flow))))
    sm, est, _ = _online(f)
    assert est.info["health"]["status"] == "ok" and est.info["health"]["detectors"] == {}
    assert {s.quality for s in sm.out} == {30}  # dead-reckoned position, no yaw source
    sm, est, ate = _online(bad)
    h = est.info["health"]
    assert h["status"] == "degraded" and h["detectors"]["flow-rejected"] == 1
    rej = est.info["flow_all_rejected"]
    assert set(rej["reasons"]) == {"gated:quality"} and rej["since_s"] == pytest.approx(4.98)
    # The quality drops once 5 s of rejected readings are seen (the smoother starts at 5 s).
    q = {round(s.t, 2): s.quality for s in sm.out}
    assert set(q.values()) == {30, DEGRADED_QUALITY}
    assert min(t for t, v in q.items() if v == DEGRADED_QUALITY) == pytest.approx(10.05)
    b = run_batch(bad, {})
    assert b.info["health"]["status"] == "degraded"
    assert b.info["health"]["detectors"] == {"flow-rejected": 1}


def test_flow_without_a_height_source_is_named_at_the_start(flow_deck, caplog):
    f = flow_deck
    bad = dataclasses.replace(f, range=None)
    with caplog.at_level(logging.WARNING):
        sm, est, ate = _online(bad)
    h = est.info["health"]
    assert h["detectors"]["flow-no-height"] == 1
    assert "no rangefinder reading has arrived" in h["details"]["flow-no-height"][0]
    # Named at the first flow window (the start, 5 s: flow has arrived since 0 s): every state
    # from then on says so in its quality (30 -> 20; 10 once it diverges).
    q = [s.quality for s in sm.out]
    assert q[0] == 30 and max(q[1:]) == DEGRADED_QUALITY and min(q) == 10
    # Without a height or flow, the thrust-only prediction of this flight (no attitude stream)
    # reaches 30 m/s at 9.8 s: named and recovered from, never silent (it was "ok" before).
    assert h["detectors"] == {"flow-no-height": 1, "divergence": 1}
    assert h["status"] == "diverged" and ate > 1.0
    assert sum("flow-no-height" in r.message for r in caplog.records) == 1
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        b = run_batch(bad, {})
    assert b.info["health"]["status"] == "degraded"
    assert b.info["health"]["detectors"] == {"flow-no-height": 1}
    line = [r.message for r in caplog.records if "no height source" in r.message]
    assert len(line) == 1 and "(no rangefinder stream)" in line[0]
    # Flow switched off by the configuration: nothing to name.
    b = run_batch(bad, {"graph": {"use_flow": False}})
    assert b.info["health"]["status"] == "ok" and b.info["health"]["detectors"] == {}


def test_crazyflie_range_reads_below_its_floor_so_40mm_is_a_distance():
    """traj2 reads 40 mm (its range_min) once on the way down, after 12-25 mm on the floor:
    the sensor does not clamp there, the reading stays a height (the README's figures)."""
    from fgnav.datasets.load import load_flight

    f = load_flight(require_real_data() / "crazyflie_util_flowdeck" / "0425-traj2")
    r, lo = f.range.range, float(f.calib.range_min)
    assert int((r == lo).sum()) == 1 and not range_clamps(r, lo)
    det = FaultDetectors(context=Context(height=lambda t: 0.0), range_min=lo)
    for t, x in zip(f.range.t, r, strict=True):
        det.feed(RangeReading(float(t), float(t), float(x), -1.0))
    assert "range-at-min" not in det.counts
