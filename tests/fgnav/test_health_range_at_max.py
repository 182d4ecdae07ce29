"""The ``range-at-max`` detector (fgnav.health): readings at the rangefinder's maximum (no echo)
for ``range_stuck_s`` while the estimate puts the ground well within the sensor's reach (a
blinded sensor) are named; readings at the maximum while the vehicle is above the sensor's
reach are not. Hand-made readings, then the batch and push smoothers on simulated flights
(fixed seeds; the simulator's ``range_blind`` and ``range_no_echo_at_max``)."""

from __future__ import annotations

import dataclasses

import pytest
from fgnav.datasets.events import RangeReading
from fgnav.datasets.simulate import SimOptions, simulate
from testutil import CRAZYFLIE_LIKE

from fgnav.health import Context, FaultDetectors, HealthOptions, health_line
from fgnav.methods import run_batch
from fgnav.solvers.online import replay_online

HI = 8.0


def _detector(expected):
    """A detector whose predicted reading is ``expected(t)`` (range 0.1-8 m)."""
    return FaultDetectors(context=Context(range_expected=expected), range_min=0.1, range_max=HI)


def _feed(det, values, t0=0.0, dt=0.04):
    for i, r in enumerate(values):
        t = t0 + i * dt
        det.feed(RangeReading(t, t, r, -1.0))


def test_readings_at_the_maximum_with_the_ground_within_reach_are_named_once():
    """2 s at 8 m while the estimate predicts 1.0 m: named once, 1 s after the first
    prediction (``range_stuck_s``); a second run after a distance is named again."""
    det = _detector(lambda t: 1.0)
    _feed(det, [HI] * 50)
    assert det.counts == {"range-at-max": 1}
    assert det.at_max_runs == [(0.0, pytest.approx(1.0))]
    assert det.details["range-at-max"][0].startswith(
        "rangefinder at its maximum 8.000 m (no echo) since t=0.00 while the estimate put the "
        "ground at most 1.00 m away along its beam, well within its reach (below 7.05 m)"
    )
    _feed(det, [1.0] + [HI] * 30, t0=2.0)
    assert det.counts == {"range-at-max": 2}
    # A run of readings at the maximum is no stuck rangefinder, and nothing is dropped by it.
    assert "range-stuck" not in det.counts and det.dropped == {}


@pytest.mark.parametrize(
    ("expected", "why"),
    [
        (lambda t: 7.5, "above the bound: range_max (8) - 0.15 m - 10 % = 7.05 m"),
        (lambda t: 1.0 if t < 0.5 else 8.5, "above the reach once in the run: climbed out"),
        (lambda t: None, "no prediction: the ground was never measured"),
    ],
)
def test_readings_at_the_maximum_not_named(expected, why):
    det = _detector(expected)
    _feed(det, [HI] * 100)
    assert det.counts == {}, why


def test_short_runs_and_unknown_limits_are_not_named():
    # Runs of 0.8 s between distances (a poor surface, intermittent echoes).
    det = _detector(lambda t: 1.0)
    for k in range(5):
        _feed(det, [1.0] + [HI] * 20, t0=k * 0.84)
    assert det.counts == {}
    # The prediction must hold range_stuck_s from its first value: known from 1.5 s of a 2 s run.
    det = _detector(lambda t: None if t < 1.5 else 1.0)
    _feed(det, [HI] * 50)
    assert det.counts == {}
    # No range_max: no reading is at the maximum.
    det = FaultDetectors(context=Context(range_expected=lambda t: 1.0), range_min=0.1)
    _feed(det, [HI] * 50)
    assert det.counts == {}
    # The margin is an option.
    det = FaultDetectors(
        HealthOptions(range_at_max_margin_rel=0.01),
        Context(range_expected=lambda t: 7.5),
        range_min=0.1,
        range_max=HI,
    )
    _feed(det, [HI] * 50)
    assert det.counts == {"range-at-max": 1}


@pytest.fixture(scope="module")
def blinded():
    """The fault matrix's flow deck (seed 1, 20 s) whose rangefinder gets no echo from 8 to 13 s
    (0.4-1.3 m over the floor, 8 m reach) and reports its maximum for it."""
    opts = SimOptions(duration=20.0, range_no_echo_at_max=True, **CRAZYFLIE_LIKE)
    return simulate("flowdeck", 1, dataclasses.replace(opts, range_blind=((8.0, 13.0),)))


@pytest.mark.parametrize("command", ["batch", "online"])
def test_a_blinded_rangefinder_is_named(blinded, command):
    """Before: readings at the maximum were refused and nothing named (batch / online ATE 0.040
    / 0.099 m against 0.026 / 0.071 nominal, health "ok"); now ``range-at-max`` names it once,
    the status is "degraded" as for ``range-at-min`` (the ATE is unchanged: named, not fixed)."""
    est = run_batch(blinded, {}) if command == "batch" else replay_online(blinded)
    h = est.info["health"]
    assert h["detectors"] == {"range-at-max": 1} and h["status"] == "degraded"
    detail = h["details"]["range-at-max"][0]
    assert detail.startswith("rangefinder at its maximum 8.000 m (no echo) since t=8.0")
    assert "range-at-max 1" in health_line(h)


@pytest.mark.parametrize(
    ("scenario", "options"),
    [
        # 1-3 m up and down under a 2.5 m reach (SLAM): four runs of 1-2.6 s at the maximum.
        ("vertical", SimOptions(images=False, range_max=2.5)),
        # A flow deck at 0.4-1.3 m under a 0.8 m reach (no other height source): one 9.4 s run.
        ("flowdeck", SimOptions(duration=20.0, range_max=0.8, **CRAZYFLIE_LIKE)),
    ],
)
@pytest.mark.parametrize("command", ["batch", "online"])
def test_a_vehicle_above_the_reach_is_not_named(scenario, options, command):
    f = simulate(scenario, 1, dataclasses.replace(options, range_no_echo_at_max=True))
    at_max = f.range.range == f.calib.range_max
    assert at_max.sum() > 190
    est = run_batch(f, {}) if command == "batch" else replay_online(f)
    assert est.info["health"]["detectors"] == {}
