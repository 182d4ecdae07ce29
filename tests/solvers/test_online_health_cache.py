"""The push engine's health monitor reads the SLAM and range factors' errors that the callbacks
computed while iSAM2 linearised them (``fgnav.factors._jacobians.LINEARIZED``), not a second
callback per factor: the innovations it sees are the same numbers as evaluating each factor's
whitened error at the window's linearisation point."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate
from fgnav.factors import _jacobians

from fgnav.health import HealthMonitor
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.online import OnlineSmoother, replay_online


@pytest.fixture(scope="module")
def flight():
    return simulate(
        "figure8", seed=3, options=SimOptions(duration=15.0, images=False, range_rate_hz=50.0)
    )


def _run(flight, monkeypatch, cached: bool):
    seen: list[tuple[str, float, float, int]] = []
    hits: list[int] = []  # recorded errors the monitor used, per keyframe
    innovations = HealthMonitor.innovations
    health_keyframe = OnlineSmoother._health_keyframe

    def record(self, sensor, t, chi2, dof):
        seen.append((sensor, t, chi2, dof))
        return innovations(self, sensor, t, chi2, dof)

    def keyframe(self, k, g):
        if not cached:
            self._lin_errors = None  # every factor evaluated again at the linearisation point
        n = self._lin_hits
        health_keyframe(self, k, g)
        hits.append(self._lin_hits - n)

    monkeypatch.setattr(HealthMonitor, "innovations", record)
    monkeypatch.setattr(OnlineSmoother, "_health_keyframe", keyframe)
    est = replay_online(flight, FixedLagOptions())
    monkeypatch.undo()
    return est, seen, hits


def test_recorded_errors_are_the_errors_at_the_linearisation_point(flight, monkeypatch):
    est_a, seen_a, hits_a = _run(flight, monkeypatch, cached=True)
    est_b, seen_b, hits_b = _run(flight, monkeypatch, cached=False)
    assert _jacobians.LINEARIZED is None  # not left recording
    sensors = {s for s, *_ in seen_a}
    # Nearly every monitored factor's error was the recorded one (the others: evaluated).
    assert sum(hits_a) >= 0.95 * len(seen_a) and sum(hits_b) == 0
    assert sensors == {"slam", "range"}
    # The same factors, the same numbers (bit for bit), the same estimate.
    assert len(seen_a) == len(seen_b) > 400
    assert seen_a == seen_b
    np.testing.assert_array_equal(est_a.trajectory.world_t_body, est_b.trajectory.world_t_body)
