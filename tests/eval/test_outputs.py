"""Files written for an estimate read back to the same numbers."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest
from fgnav.datasets.tum import read_tum

from fgnav.estimate import Estimate, TimeSeries
from fgnav.eval.metrics import evaluate
from fgnav.eval.outputs import position_sigmas_world, write_estimate


@dataclass
class _Options:
    gain: float = 7.0
    window_s: float = 2.0


def _estimate(truth, rng) -> Estimate:
    n = len(truth)
    P = np.zeros((n, 6, 6))
    P[:, :3, :3] = np.eye(3) * 1e-4
    P[:, 3:, 3:] = np.diag([0.01, 0.04, 0.09])  # body-frame sigmas 0.1, 0.2, 0.3 m
    return Estimate(
        method="unit",
        trajectory=truth,
        pose_cov=P,
        vel_cov=np.tile(np.eye(3) * 0.0025, (n, 1, 1)),
        slam_scale={0: np.float64(0.2), 3: 0.5},
        slam_scale_sigma={0: 0.01},
        drag_k=np.array([0.3, 0.2]),
        drag_k_sigma=np.array([0.01, 0.02]),
        ground_height=np.float32(-0.5),
        series={"slam_scale": TimeSeries(truth.t, np.full(n, 0.2))},
        update_latency=rng.uniform(0.001, 0.003, 500),
        runtime_s=12.0,
        causal=True,
        info={"options": _Options(), "n_rejected": np.int64(3), "nan": float("nan")},
    )


def test_write_estimate_round_trip(truth, tmp_path):
    rng = np.random.default_rng(3)
    est = _estimate(truth, rng)
    metrics = evaluate(est, truth, alignment="none")
    paths = write_estimate(est, tmp_path / "out", metrics=metrics, extra={"flight": "synthetic"})
    assert set(paths) == {"tum", "states", "summary"}
    assert all(p.is_file() for p in paths.values())

    back = read_tum(paths["tum"])
    np.testing.assert_array_equal(back.t, truth.t)
    np.testing.assert_array_equal(back.world_t_body, truth.world_t_body)

    header = paths["states"].read_text().splitlines()[0].split(",")
    assert header[:4] == ["t_s", "world_t_body_x_m", "world_t_body_y_m", "world_t_body_z_m"]
    assert "world_v_body_x_mps" in header and "sigma_world_t_body_z_m" in header
    assert "gyro_bias_x_radps" not in header  # the truth has no biases
    data = np.loadtxt(paths["states"], delimiter=",", skiprows=1)
    assert data.shape == (len(truth), len(header))
    np.testing.assert_array_equal(data[:, 0], truth.t)
    col = {name: i for i, name in enumerate(header)}
    np.testing.assert_array_equal(data[:, col["world_q_body_w"]], truth.world_q_body_wxyz[:, 0])
    sig = data[:, [col[f"sigma_world_t_body_{a}_m"] for a in "xyz"]]
    np.testing.assert_allclose(sig, position_sigmas_world(truth, est.pose_cov), rtol=1e-15)
    # Body z is close to world z (small tilts): the vertical sigma stays close to 0.3 m.
    assert np.all(np.abs(sig[:, 2] - 0.3) < 0.03)
    np.testing.assert_allclose(data[:, col["sigma_world_v_body_x_mps"]], 0.05)

    summary = json.loads(paths["summary"].read_text())
    assert summary["method"] == "unit" and summary["causal"] is True
    assert summary["slam_scale"]["0"] == {"s": 0.2, "sigma": 0.01}
    assert summary["slam_scale"]["3"] == {"s": 0.5, "sigma": None}
    assert summary["drag_k_per_s"] == [0.3, 0.2]
    assert summary["ground_height_m"] == pytest.approx(-0.5)
    assert summary["info"]["options"] == {"gain": 7.0, "window_s": 2.0}
    assert summary["info"]["n_rejected"] == 3 and summary["info"]["nan"] is None
    timing = summary["timing"]
    assert timing["n_updates"] == 500
    assert 0.001 < timing["update_latency_p50_s"] < timing["update_latency_p99_s"] < 0.003
    assert timing["times_real_time"] == pytest.approx(truth.duration / 12.0)
    assert summary["metrics"]["alignment"] == "none"
    assert summary["metrics"]["ate_rmse_m"] == 0.0
    assert summary["extra"] == {"flight": "synthetic"}
