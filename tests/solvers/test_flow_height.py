"""The range reading behind a flow window's height gate (``FlowFactorOptions.height_max_age_s``):
the batch graph takes the nearest reading that is a distance (``range_refusal``), not the
nearest reading, on the fault matrix's flow-deck base (simulated ``flowdeck``, seed 1, 20 s,
Crazyflie-like sensors; fixed seeds)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.simulate import SimOptions, simulate
from fgnav.datasets.simulate.options import CRAZYFLIE_LIKE

from fgnav.compare import score_estimate
from fgnav.methods import run_batch
from fgnav.solvers.graph import GraphBuilder, GraphOptions
from fgnav.solvers.online import replay_online


def _with_range(f, values):
    return dataclasses.replace(f, range=dataclasses.replace(f.range, range=values))


@pytest.fixture(scope="module")
def flow_deck():
    return simulate("flowdeck", 1, SimOptions(duration=20.0, **CRAZYFLIE_LIKE))


def _heights(f) -> dict[int, float | None]:
    b = GraphBuilder(f, GraphOptions())
    b.build()
    return dict(b.flow.height)


def test_a_refused_nearest_reading_leaves_the_height_to_a_usable_neighbour(flow_deck):
    """Every third reading at the 8 m maximum (a missing echo, 25 Hz): before, a keyframe whose
    nearest reading was one had no height, its window no flow factor (671 readings
    ``flow:no-height``, batch ATE 0.052 m against 0.026 m nominal, health "ok"); now the
    nearest usable reading, 40 ms away at most, gives it (ATE 0.025 m)."""
    f = flow_deck
    hi = float(f.calib.range_max)
    r = f.range.range
    bad = _with_range(f, np.where(np.arange(len(r)) % 3 == 0, hi, r))
    h0, h = _heights(f), _heights(bad)
    assert h.keys() == h0.keys() and None not in h.values()
    assert max(abs(h[k] - h0[k]) for k in h0 if h0[k] is not None) < 0.05
    ate0 = score_estimate(f, run_batch(f, {})).ate_rmse_m
    est = run_batch(bad, {})
    assert "flow:no-height" not in est.info["skipped"]
    assert score_estimate(bad, est).ate_rmse_m < 1.1 * ate0  # measured 0.0250 / 0.0257 m


def test_no_usable_reading_within_the_age_is_no_height(flow_deck):
    """The tolerance is not widened: a keyframe with no usable reading within
    ``height_max_age_s`` (0.25 s) has no height, however near a refused one is."""
    f = flow_deck
    t, r = f.range.t, f.range.range
    gap = (t >= 8.0) & (t < 10.0)
    bad = _with_range(f, np.where(gap, float(f.calib.range_max), r))
    b = GraphBuilder(bad, GraphOptions())
    b.build()
    t_use = t[~gap]
    for k, h in b.flow.height.items():
        age = float(np.min(np.abs(t_use - b.t_kf[k])))
        assert (h is None) == (age > 0.25), (b.t_kf[k], age, h)
    assert sum(h is None for h in b.flow.height.values()) > 25


@pytest.mark.parametrize("factor", [0.5, 1.5])
def test_online_flow_height_tests_the_whole_interval(flow_deck, factor):
    """The push engine's flow height: readings from 8 to 10 s out of the sensor's limits (half
    its 0.1 m floor, a glitching time of flight, or 1.5 x its 8 m maximum, a driver passing raw
    readings on). Before, only the floor and the maximum were tested: each such reading was a
    height (the windows gated on it, ``flow:gated:height``); now ``range_refusal`` refuses it as
    the batch does; a window with no usable reading within ``height_max_age_s`` is counted
    ``range:flow-height:out-of-range`` (33, from 8.25 s until a reading from 10 s has arrived;
    the others take an older usable reading)."""
    f = flow_deck
    t, r = f.range.t, f.range.range
    lo, hi = float(f.calib.range_min), float(f.calib.range_max)
    bad = _with_range(f, np.where((t >= 8.0) & (t < 10.0), factor * (lo if factor < 1 else hi), r))
    est = replay_online(bad)
    d = est.info["dropped"]
    assert "flow:gated:height" not in d
    assert d["range:flow-height:out-of-range"] == 33
    assert "range:flow-height:out-of-range" not in replay_online(f).info["dropped"]


def test_online_flow_height_passes_over_a_refused_newest_reading(flow_deck):
    """Every third reading at the 8 m maximum: before, a window whose newest reading was one had
    no height (646 readings ``flow:no-height``, ATE 0.0893 m against 0.0706 m nominal); now the
    newest usable reading within ``height_max_age_s`` gives it, as in batch (ATE 0.0718 m)."""
    f = flow_deck
    r = f.range.range
    bad = _with_range(f, np.where(np.arange(len(r)) % 3 == 0, float(f.calib.range_max), r))
    est = replay_online(bad)
    d = est.info["dropped"]
    assert "flow:no-height" not in d and not any(k.startswith("range:flow-height") for k in d)
    ate0 = score_estimate(f, replay_online(f)).ate_rmse_m
    assert score_estimate(bad, est).ate_rmse_m < 1.05 * ate0  # measured 0.0718 / 0.0706 m
