"""Plot functions write non-empty image files (no figure is shown)."""

from __future__ import annotations

import numpy as np
from fgnav.datasets.types import Trajectory

from fgnav.estimate import Estimate, TimeSeries
from fgnav.eval.plots import (
    aligned_to_truth,
    plot_drag,
    plot_errors_over_time,
    plot_latency,
    plot_scale,
    plot_top_view,
)

PNG_MAGIC = b"\x89PNG"


def _estimates(truth: Trajectory) -> list[Estimate]:
    rng = np.random.default_rng(5)
    n = len(truth)
    noisy = Trajectory(
        truth.t,
        truth.world_t_body + rng.normal(0, 0.1, (n, 3)) + [5.0, 0.0, 0.0],
        truth.world_q_body_wxyz,
        truth.world_v_body + rng.normal(0, 0.05, (n, 3)),
    )
    scale = TimeSeries(truth.t, 0.2 + 0.05 * np.exp(-(truth.t - truth.t[0])), np.full(n, 0.01))
    drag = TimeSeries(truth.t, np.tile([0.3, 0.2], (n, 1)))
    a = Estimate(
        "smoother",
        noisy,
        slam_scale={0: 0.2},
        series={"slam_scale": scale, "drag_k": drag},
        update_latency=rng.lognormal(np.log(1e-3), 0.5, 2000),
    )
    b = Estimate(
        "dead-reckoning", Trajectory(truth.t, 0.9 * truth.world_t_body, truth.world_q_body_wxyz)
    )
    return [a, b]


def test_plots_write_files(truth, tmp_path):
    ests = _estimates(truth)
    paths = [
        plot_top_view(ests, truth, tmp_path / "top.png"),
        plot_top_view(ests, None, tmp_path / "top_no_truth.png"),
        plot_errors_over_time(ests, truth, tmp_path / "errors.png", alignment="4dof"),
        plot_scale(ests, tmp_path / "sub" / "scale.png", truth_scale={0: 0.2}),
        plot_drag(ests, tmp_path / "drag.png", truth_k=[0.3, 0.2]),
        plot_latency(ests, tmp_path / "latency.png"),
        plot_latency(ests[1:], tmp_path / "no_latency.png"),
    ]
    for p in paths:
        assert p.is_file() and p.read_bytes()[:4] == PNG_MAGIC and p.stat().st_size > 5000


def test_aligned_to_truth_removes_offset(truth):
    est = _estimates(truth)[0]
    traj, gt, al = aligned_to_truth(est, truth, "se3")
    np.testing.assert_allclose(al.t, [-5.0, 0.0, 0.0], atol=0.02)
    assert np.sqrt(np.mean(np.sum((traj.world_t_body - gt.world_t_body) ** 2, axis=1))) < 0.2
