"""The ``range-silent`` detector (fgnav.health): a range stream that, having delivered readings,
delivers none for longer than ``range_gap_s`` while the IMU goes on (the last reading and the
predicted one within the sensor's reach) is named, on the IMU's clock; gaps of real streams, a
stream that ends with the flight, a vehicle above the sensor's reach or on the floor under it
are not. Hand-made events, then the batch and push smoothers on simulated flights (fixed
seeds; the simulator's ``range_blind`` without ``range_no_echo_at_max``: no readings)."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.events import ImuSample, RangeReading, replay_flight
from fgnav.datasets.simulate import SimOptions, simulate
from testutil import CRAZYFLIE_LIKE

from fgnav.health import DEGRADED_QUALITY, Context, FaultDetectors, HealthOptions, health_line
from fgnav.methods import run_batch
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.online import PUSH_STREAMS, OnlineSmoother, replay_online

W, A = np.zeros(3), np.array([0.0, 0.0, 9.81])


def _detector(expected=lambda t: None, options=None, lo=0.1, hi=8.0):
    return FaultDetectors(
        options or HealthOptions(),
        Context(range_expected=expected),
        range_min=lo,
        range_max=hi,
    )


def _fly(det, t1, readings, dt_imu=0.005):
    """IMU samples at 200 Hz from 0 to ``t1`` and the readings ``[(t, r)]`` in time order."""
    readings = list(readings)
    j = 0
    for t in np.arange(0.0, t1 + 1e-9, dt_imu):
        while j < len(readings) and readings[j][0] <= t:
            det.feed(RangeReading(readings[j][0], readings[j][0], readings[j][1]))
            j += 1
        det.feed(ImuSample(float(t), float(t), W, A))


def _stream(t0, t1, r=1.0, dt=0.04):
    return [(float(t), r) for t in np.arange(t0, t1 - 1e-9, dt)]


def test_a_silent_rangefinder_is_named_once_per_gap_on_the_imu_clock():
    """Readings at 1 m to 2 s, none to 5 s, again to 6 s, none after (IMU to 8 s): named at the
    first IMU sample past 1 s after the last reading, before any next one; twice in all."""
    det = _detector()
    _fly(det, 8.0, _stream(0.0, 2.0) + _stream(5.0, 6.0))
    assert det.counts == {"range-silent": 2}
    (a0, b0), (a1, b1) = det.silent_runs
    assert a0 == pytest.approx(1.96) and b0 == pytest.approx(2.965)
    assert a1 == pytest.approx(5.96) and b1 == pytest.approx(6.965)
    assert det.details["range-silent"][0] == (
        "no range reading for 1.00 s since t=1.96 (the last 1.000 m, within the sensor's reach) "
        "while the IMU goes on: a rangefinder that stopped; no height from it"
    )
    assert det.dropped == {}


def test_a_silent_rangefinder_lowers_the_quality_while_it_lasts(silent):
    """Online: the states' quality is at most ``DEGRADED_QUALITY`` from the naming (8.96 s)
    until the next reading (13 s); above it before and after."""
    sm = OnlineSmoother(silent.calib, FixedLagOptions(), silent.name)
    for ev in replay_flight(silent, [n for n in PUSH_STREAMS if getattr(silent, n) is not None]):
        sm.feed(ev)
    q = [(s.t, s.quality) for s in sm.out]
    assert all(v <= DEGRADED_QUALITY for t, v in q if 9.0 <= t < 12.9)
    assert min(v for t, v in q if 6.0 <= t < 8.9) > DEGRADED_QUALITY
    assert min(v for t, v in q if t > 13.5) > DEGRADED_QUALITY


@pytest.mark.parametrize(
    ("kwargs", "readings", "t1", "why"),
    [
        ({}, _stream(0.0, 2.0) + _stream(2.9, 6.0), 6.0, "a gap of 0.94 s: below the bound"),
        ({}, _stream(0.0, 5.5), 6.0, "the stream ends 0.54 s before the IMU's last sample"),
        ({}, _stream(0.0, 2.0, r=7.5), 6.0, "last reading beyond the reach (7.05 m of 8 m)"),
        ({}, _stream(0.0, 2.0, r=0.05), 6.0, "last reading under the floor (0.1 m)"),
        ({"expected": lambda t: 7.5}, _stream(0.0, 2.0), 6.0, "predicted beyond the reach"),
        ({}, [], 6.0, "no range stream"),
        ({"options": HealthOptions(range_gap_s=5.0)}, _stream(0.0, 2.0), 6.0, "bound 5 s"),
    ],
)
def test_gaps_not_named(kwargs, readings, t1, why):
    det = _detector(**kwargs)
    _fly(det, t1, readings)
    assert det.counts == {}, why


def test_named_once_the_prediction_comes_back_within_reach():
    """Predicted beyond the reach at the bound (climbed out) and at the test a gap later, within
    it at the next (the test is repeated every ``range_gap_s``): named then, 3 s after the last
    reading."""
    det = _detector(lambda t: 7.5 if t < 4.0 else 2.0)
    _fly(det, 6.0, _stream(0.0, 2.0))
    assert det.counts == {"range-silent": 1}
    assert det.silent_runs[0][1] == pytest.approx(4.97)


@pytest.fixture(scope="module")
def silent():
    """The fault matrix's flow deck (seed 1, 20 s) whose rangefinder delivers no reading from 8
    to 13 s (0.4-1.3 m over the floor, 8 m reach)."""
    opts = SimOptions(duration=20.0, range_blind=((8.0, 13.0),), **CRAZYFLIE_LIKE)
    return simulate("flowdeck", 1, opts)


@pytest.mark.parametrize("command", ["batch", "online"])
def test_a_silent_rangefinder_is_named(silent, command):
    """Before: batch / online ATE 0.040 / 0.091 m (0.026 / 0.071 nominal) and nothing named;
    now ``range-silent`` names it once, 1 s after the last reading, and the status is
    "degraded" (named, not fixed, as ``range-at-max``); online, the states' quality says so
    from the naming until the next reading (no SLAM or camera anchors this flight)."""
    assert not ((silent.range.t > 8.0) & (silent.range.t < 13.0)).any()
    est = run_batch(silent, {}) if command == "batch" else replay_online(silent)
    h = est.info["health"]
    assert h["detectors"] == {"range-silent": 1} and h["status"] == "degraded"
    assert h["details"]["range-silent"][0].startswith(
        "no range reading for 1.00 s since t=7.96 (the last 0.553 m, within the sensor's reach; "
        "the estimate puts the ground 0.6"
    )
    assert "range-silent 1" in health_line(h)


@pytest.mark.parametrize("command", ["batch", "online"])
def test_a_vehicle_above_the_reach_is_not_named(command):
    """1-3 m up and down under a 2.5 m reach, readings beyond it left out (SLAM): gaps of over
    1 s above the reach, nothing named."""
    f = simulate("vertical", 1, SimOptions(images=False, range_max=2.5))
    assert np.diff(f.range.t).max() > 1.5
    est = run_batch(f, {}) if command == "batch" else replay_online(f)
    assert est.info["health"]["detectors"] == {}
