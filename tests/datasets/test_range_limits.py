"""A rangefinder's limits (fgnav.datasets.range_limits): the one test of which readings are
distances, at the floor and at the maximum, for one reading and for a stream."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from fgnav.datasets.range_limits import (
    RANGE_AT_MAX_TOL_M,
    RANGE_AT_MIN_TOL_M,
    RangeLimits,
    range_at_max,
    range_refusal,
)
from fgnav.factors.tilted_range import gate_range

DOWN = gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.zeros(3))
LO, HI = 0.1, 8.0


@pytest.mark.parametrize(
    ("r", "clamps", "why"),
    [
        (1.0, True, None),
        (math.nan, True, "non-finite"),
        (math.inf, True, "non-finite"),
        (0.09, True, "out-of-range"),
        (8.01, True, "out-of-range"),
        (LO, True, "at-min"),
        (LO, False, None),  # a sensor that has read below its floor: a distance
        (LO + 2 * RANGE_AT_MIN_TOL_M, True, None),
        (HI, True, "at-max"),
        (HI, False, "at-max"),  # at the maximum whatever the floor does
        (HI - 0.5 * RANGE_AT_MAX_TOL_M, True, "at-max"),
        (HI - 2 * RANGE_AT_MAX_TOL_M, True, None),
    ],
)
def test_range_refusal(r, clamps, why):
    assert range_refusal(r, LO, HI, clamps) == why


def test_gate_range_refuses_a_reading_at_the_maximum():
    ok, why = gate_range(HI, np.eye(3), DOWN, LO, HI, np.deg2rad(30))
    assert not ok and why.startswith("at-max: 8.0000 m at the sensor's maximum 8.0 m")
    ok, why = gate_range(HI - 0.001, np.eye(3), DOWN, LO, HI, np.deg2rad(30))
    assert ok and why == "ok"


def test_an_infinite_maximum_refuses_no_finite_reading():
    """``Calibration.range_max`` defaults to inf (unknown): no reading is at it."""
    assert not range_at_max(1e9, math.inf)
    assert range_refusal(1e9, 0.0, math.inf) is None
    assert RangeLimits(0.0, math.inf).mask(np.array([0.5, 1e9, np.inf])).tolist() == [
        True,
        True,
        False,
    ]


def test_stream_limits_learn_the_floor_and_mask_as_refusal():
    r = np.array([LO, 0.5, HI, HI - 1e-4, 3.0, np.nan, 9.0, LO + 1e-4, 0.05, LO])
    causal = RangeLimits(LO, HI)
    why = []
    for x in r:
        causal.see(x)
        why.append(causal.refusal(float(x)))
    # The floor clamps until 0.05 arrives (the 9th reading): the last 0.1 is a distance.
    assert why == [
        "at-min",
        None,
        "at-max",
        "at-max",
        None,
        "non-finite",
        "out-of-range",
        "at-min",
        "out-of-range",
        None,
    ]
    # The whole stream has read below its floor: no reading at it is refused.
    whole = RangeLimits.of_stream(r, LO, HI)
    assert not whole.clamps
    expected = [whole.refusal(float(x)) is None for x in r]
    assert (
        whole.mask(r).tolist()
        == expected
        == [
            True,
            True,
            False,
            False,
            True,
            False,
            False,
            True,
            False,
            True,
        ]
    )
    clamping = RangeLimits.of_stream(r[r >= LO], LO, HI)
    assert clamping.clamps
    assert clamping.mask(r).tolist() == [clamping.refusal(float(x)) is None for x in r]
