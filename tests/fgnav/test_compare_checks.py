"""``fgnav compare`` review findings (2026-12-08): exit code when nothing ran, the SLAM scale of a
flight without SLAM, repeated ``--methods``, reference rows scored on positions only, and the
implausible-estimate flags."""

from __future__ import annotations

import dataclasses
import json

import pytest
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.compare import compare, truth_slam_scales


@pytest.fixture(scope="module")
def flight():
    """12 s of two-turns without images, seed 3."""
    return simulate("two-turns", seed=3, options=SimOptions(duration=12.0, images=False))


@pytest.fixture(scope="module")
def imu_only(flight):
    """The same flight with the IMU (and truth) only: no SLAM, attitude, yaw, range, flow."""
    return dataclasses.replace(flight, slam=None, attitude=None, yaw=None, range=None, flow=None)


def test_no_slam_no_true_slam_scale(imu_only, tmp_path):
    """A flight without SLAM has no true SLAM scale, though the simulator's metadata lists the
    sessions it drew (report.md stated "true SLAM scale ... session 0: 0.246991")."""
    assert imu_only.meta["truth"]["slam_sessions"]
    assert truth_slam_scales(imu_only) == (None, "the flight has no SLAM stream")
    res = compare(imu_only, ["msf-ekf"], progress=False)
    paths = res.write(tmp_path, figures=False)
    data = json.loads(paths["json"].read_text())
    assert data["truth"]["slam_scale"] is None
    report = paths["report"].read_text()
    assert "true SLAM scale: not available (the flight has no SLAM stream)" in report
    assert "session 0:" not in report
