"""Flow-and-range figures: the end drift with the start pose known, and the goal checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fgnav.datasets.geometry import matrix_to_quat_wxyz, rpy_to_matrix
from fgnav.datasets.types import Trajectory

from fgnav.estimate import Estimate
from fgnav.eval.flow_table import check_goals, flow_figures, markdown_table


def _traj(t, p, yaw):
    R = np.array([rpy_to_matrix(0.0, 0.0, y) for y in yaw])
    v = np.gradient(p, t, axis=0)
    return Trajectory(t=t, world_t_body=p, world_q_body_wxyz=matrix_to_quat_wxyz(R), world_v_body=v)


def test_start_known_drift_is_the_end_error_after_placing_the_first_pose():
    t = np.arange(0.0, 20.0, 0.05)
    truth_p = np.column_stack([np.cos(0.3 * t), np.sin(0.3 * t), np.full_like(t, 1.0)])
    truth = _traj(t, truth_p, 0.3 * t)
    # The estimate: the truth in a frame rotated by 40 deg and shifted, plus a drift of 0.1 m
    # along x by the end: with the start pose known only the drift remains.
    a = math.radians(40.0)
    Rz = rpy_to_matrix(0.0, 0.0, a)
    drift = np.column_stack([0.1 * t / t[-1], np.zeros_like(t), np.zeros_like(t)])
    est_p = (Rz @ (truth_p + drift).T).T + [3.0, -2.0, 0.5]
    est = Estimate(method="x", trajectory=_traj(t, est_p, 0.3 * t + a), causal=False)
    fig = flow_figures(est, truth)
    assert fig["start_drift_m"] == pytest.approx(0.1, abs=1e-6)
    assert fig["start_drift_pct"] == pytest.approx(100 * 0.1 / fig["path_m"], rel=1e-6)
    assert fig["path_m"] == pytest.approx(0.3 * t[-1], rel=0.01)


def test_goals_and_better_than_filters():
    rows = {
        "batch": {
            "hvel100_rmse_mps": 0.05,
            "height_rmse_m": 0.01,
            "ate_m": 0.1,
            "start_drift_pct": 1.5,
        },
        "cf-ekf": {
            "hvel100_rmse_mps": 0.2,
            "height_rmse_m": 0.02,
            "ate_m": 0.05,
            "start_drift_pct": 3.0,
        },
    }
    g = {x["goal"]: x["met"] for x in check_goals(rows)}
    assert g["hvel100_rmse_mps"] and g["height_rmse_m"] and not g["start_drift_pct"]
    assert g["better than cf-ekf: hvel100_rmse_mps"]
    assert not g["better than cf-ekf: ate_m"]
    text = markdown_table(rows)
    assert "| batch | 0.050 | 1.00 | 0.100 | 1.50 |" in text
