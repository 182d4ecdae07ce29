"""The push engine's SLAM-vs-gyro check on a flight that does not decide (too little
rotation): its attempts are spaced out after SLAM_CHECK_GROWTH_AFTER_S and each fits at most the
newest SLAM_CHECK_WINDOW_S (+ the trim chunk), so its cost no longer grows with the flight."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets import slam_gyro
from fgnav.datasets.simulate import SimOptions, simulate

import fgnav.solvers.online as online
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.online import replay_online


def test_undecided_check_is_rate_limited_and_windowed(monkeypatch):
    """Simulated vertical flight, 150 s, seed 0: the check never decides. Before: 150 attempts,
    the last over all 150 s of data (300 s: 161 s of check in a 227 s run, one attempt 1.6 s).
    Now: 60 attempts in the first 60 s, then spaced by a tenth of the time so far: 8 more;
    none over more than 70 s of SLAM."""
    f = simulate("vertical", seed=0, options=SimOptions(duration=150.0, images=False))
    spans, misfits = [], []
    real_check = slam_gyro.check_slam_gyro
    real_misfit = slam_gyro.SlamGyroCheck.stated_misfit

    def check(imu_t, imu_omega, slam_t, *a, **k):
        spans.append((float(slam_t[-1]), float(slam_t[-1] - slam_t[0])))
        return real_check(imu_t, imu_omega, slam_t, *a, **k)

    def misfit(self, *a, **k):
        misfits.append(float(self._slam_t[-1] - self._slam_t[0]))
        return real_misfit(self, *a, **k)

    monkeypatch.setattr(slam_gyro, "check_slam_gyro", check)
    monkeypatch.setattr(slam_gyro.SlamGyroCheck, "stated_misfit", misfit)
    est = replay_online(f, FixedLagOptions())
    assert est.info["slam_gyro_check"] is None  # undecided, as before
    t = np.array([s[0] for s in spans]) - f.slam.t[0]
    width = np.array([s[1] for s in spans])
    limit = online.SLAM_CHECK_WINDOW_S + slam_gyro.WINDOW_TRIM_S
    assert width.max() <= limit + 0.1
    assert (t <= online.SLAM_CHECK_GROWTH_AFTER_S + 1).sum() == pytest.approx(60, abs=1)
    assert (t > online.SLAM_CHECK_GROWTH_AFTER_S + 1).sum() == 8  # 65.8, 73.2, ... 137.9 s
    assert max(misfits) <= limit + 0.1 and len(misfits) == 69  # (its own 1 s clock)
