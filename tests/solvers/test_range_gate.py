"""The push engine's range innovation gate (``FixedLagOptions.range_gate_m``) and the median start
of a ground-height variable.

Before the gate a single wrong reading at the start keyframe (simulated two-turns seed 1 has one:
1.81 m against 3.45 m) went through the robust kernel's one Gauss-Newton step per update and put
the third keyframe 30 cm high at 3 m/s; that flight's causal velocity RMSE was 0.136 m/s
(0.027 m/s with the gate).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate

from fgnav.eval.align import associate
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.online import replay_online


@pytest.fixture(scope="module")
def clean():
    return simulate("two-turns", 0, SimOptions(duration=8, images=False, range_outlier_prob=0.0))


def _with_range(flight, r):
    return dataclasses.replace(flight, range=dataclasses.replace(flight.range, range=r))


def _max_height_error(est, flight, t_end: float) -> float:
    """Largest |z error| [m] of the causal states before ``t_end`` (start-anchored, the world's
    origin is the first state's position)."""
    tr = est.trajectory
    a = associate(tr, flight.ground_truth)
    x, g, t = tr.world_t_body[a.est_index], a.gt.world_t_body, tr.t[a.est_index]
    e = x[:, 2] - (g[:, 2] - g[0, 2])
    return float(np.abs(e[t < t_end]).max())


def test_an_outlier_at_the_start_keyframe_is_gated(clean):
    r = clean.range.range.copy()
    i = int(np.argmin(np.abs(clean.range.t - 0.2)))  # the start keyframe's reading
    r[i] *= 0.5
    f = _with_range(clean, r)
    est = replay_online(f)
    assert est.info["dropped"].get("range:outlier") == 1
    assert _max_height_error(est, f, 3.0) < 0.06
    # Without the gate the same reading moves the window (measured 0.30 m).
    off = replay_online(f, FixedLagOptions(range_gate_m=0.0))
    assert "range:outlier" not in off.info["dropped"]
    assert _max_height_error(off, f, 3.0) > 0.15


def test_clean_readings_pass_the_gate(clean):
    est = replay_online(clean)
    assert "range:outlier" not in est.info["dropped"]
    assert est.info["used"]["range"] > 140
    assert _max_height_error(est, clean, 8.0) < 0.06


def test_a_persistent_offset_is_taken_after_a_run(clean):
    """Readings 0.5 m longer from 4 s on (a step down in the terrain, or a height estimate
    gone wrong) agree with each other: every ``range_gate_run``-th is taken, the range is not
    lost for good."""
    r = clean.range.range.copy()
    r[clean.range.t >= 4.0] += 0.5
    est = replay_online(_with_range(clean, r))
    used, dropped = est.info["used"], est.info["dropped"]
    assert used.get("range:gate-run", 0) >= 5
    assert dropped.get("range:outlier", 0) >= 4 * used["range:gate-run"] - 4
