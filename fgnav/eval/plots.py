"""Figures comparing estimates with ground truth (matplotlib, Agg; files only, no windows).

Every function takes estimates (a list of :class:`~fgnav.estimate.Estimate`, labelled by their
``method``), optionally the truth, and an output path (the extension picks the format: ``.png``,
``.pdf``, ``.svg``), and returns the path written. Trajectories are aligned to the truth with the
given mode before plotting, and the mode is printed in the title. Figures are built with
``matplotlib.figure.Figure`` (no pyplot global state), so they are safe in threads and tests.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from fgnav.datasets.geometry import wrap_angle, yaw_of
from fgnav.datasets.types import Trajectory
from fgnav.estimate import Estimate, TimeSeries
from fgnav.eval.align import DEFAULT_MAX_GT_GAP_S, Alignment, align, associate
from fgnav.eval.metrics import scale_series

logger = logging.getLogger(__name__)

#: Figure size [inches] and resolution [dpi] of saved figures.
FIGSIZE = (8.0, 6.0)
DPI = 120


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    logger.info("wrote figure %s", path)
    return path


def _finish_over_time(ax, fig: Figure, t0: float, ylabel: str, title: str, path) -> Path:
    """Labels, grid, legend (when anything is labelled) and title of a plot over time; saved."""
    ax.set_xlabel(f"time [s] (t0 = {t0:.3f})")
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize="small")
    ax.set_title(title)
    return _save(fig, path)


def aligned_to_truth(
    estimate: Estimate,
    truth: Trajectory,
    alignment: str = "se3",
    max_gap_s: float = DEFAULT_MAX_GT_GAP_S,
) -> tuple[Trajectory, Trajectory, Alignment]:
    """The estimate's samples matched to truth, aligned into the truth's world.

    Returns:
        ``(aligned estimate, truth interpolated at its times, alignment)``.
    """
    a = associate(estimate.trajectory, truth, max_gap_s=max_gap_s)
    est = estimate.trajectory.select(a.est_index)
    al = align(est.world_t_body, a.gt.world_t_body, alignment)
    return al.apply(est), a.gt, al


def plot_top_view(
    estimates: Sequence[Estimate],
    truth: Trajectory | None,
    path: str | Path,
    alignment: str = "se3",
    view_margin: float | None = None,
) -> Path:
    """Top view (world x-y, metres) of each estimate, aligned to the truth when given.

    ``view_margin``: with truth, limit the view to the truth's x-y extent grown by this fraction
    of its size on each side (at least 1 m), so that one diverging estimate does not shrink the
    others to a dot; estimates leaving the view say so in the legend.
    """
    fig = Figure(figsize=FIGSIZE)
    ax = fig.add_subplot()
    box = None
    if truth is not None:
        ax.plot(truth.world_t_body[:, 0], truth.world_t_body[:, 1], "k-", lw=2, label="truth")
        if view_margin is not None:
            lo, hi = truth.world_t_body[:, :2].min(axis=0), truth.world_t_body[:, :2].max(axis=0)
            pad = max(1.0, view_margin * float(np.max(hi - lo)))
            box = (lo - pad, hi + pad)
    for est in estimates:
        if truth is not None:
            traj, _, al = aligned_to_truth(est, truth, alignment)
            label = f"{est.method} ({al.mode}" + (f", s={al.s:.3g})" if al.mode == "sim3" else ")")
        else:
            traj, label = est.trajectory, est.method
        xy = traj.world_t_body[:, :2]
        if box is not None and (np.any(xy < box[0]) or np.any(xy > box[1])):
            label += ", leaves the view"
        ax.plot(xy[:, 0], xy[:, 1], lw=1, label=label)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if box is not None:
        ax.set_xlim(box[0][0], box[1][0])
        ax.set_ylim(box[0][1], box[1][1])
        ax.set_aspect("equal", adjustable="box")
    else:
        ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    mode = alignment if truth is not None else "no truth"
    ax.set_title(f"Top view (alignment: {mode})")
    return _save(fig, path)


def plot_errors_over_time(
    estimates: Sequence[Estimate],
    truth: Trajectory,
    path: str | Path,
    alignment: str = "se3",
    log_scale: bool = False,
) -> Path:
    """Position error [m], velocity error [m/s] (when both have velocity) and wrapped yaw error
    [deg] over time, after alignment. ``log_scale``: logarithmic position and velocity axes (for
    methods whose errors differ by orders of magnitude)."""
    fig = Figure(figsize=(FIGSIZE[0], 1.4 * FIGSIZE[1]))
    ax_p, ax_v, ax_y = fig.subplots(3, 1, sharex=True)
    t0 = float(truth.t[0])
    for est in estimates:
        traj, gt, _ = aligned_to_truth(est, truth, alignment)
        t = traj.t - t0
        ax_p.plot(t, np.linalg.norm(traj.world_t_body - gt.world_t_body, axis=1), label=est.method)
        if traj.world_v_body is not None and gt.world_v_body is not None:
            ax_v.plot(t, np.linalg.norm(traj.world_v_body - gt.world_v_body, axis=1))
        else:
            ax_v.plot([], [])
        dyaw = wrap_angle(yaw_of(traj.world_R_body()) - yaw_of(gt.world_R_body()))
        ax_y.plot(t, np.rad2deg(dyaw))
    if log_scale:
        ax_p.set_yscale("log")
        ax_v.set_yscale("log")
    ax_p.set_ylabel("position error [m]")
    ax_v.set_ylabel("velocity error [m/s]")
    ax_y.set_ylabel("yaw error [deg]")
    ax_y.set_xlabel(f"time since truth start [s] (t0 = {t0:.3f})")
    for ax in (ax_p, ax_v, ax_y):
        ax.grid(True, alpha=0.3)
    ax_p.legend(fontsize="small")
    ax_p.set_title(f"Errors after {alignment} alignment")
    return _save(fig, path)


def _plot_series(ax, ts: TimeSeries, label: str, t0: float) -> None:
    value = np.asarray(ts.value, dtype=float)
    t = np.asarray(ts.t, dtype=float) - t0
    cols = value[:, None] if value.ndim == 1 else value
    sig = None if ts.sigma is None else np.asarray(ts.sigma, dtype=float).reshape(cols.shape)
    for j in range(cols.shape[1]):
        name = label if cols.shape[1] == 1 else f"{label}[{j}]"
        (line,) = ax.plot(t, cols[:, j], label=name)
        if sig is not None:
            ax.fill_between(
                t, cols[:, j] - sig[:, j], cols[:, j] + sig[:, j], color=line.get_color(), alpha=0.2
            )


def _t0(estimates: Sequence[Estimate]) -> float:
    return min(float(e.trajectory.t[0]) for e in estimates) if estimates else 0.0


def plot_scale(
    estimates: Sequence[Estimate],
    path: str | Path,
    truth_scale: dict[int, float] | None = None,
) -> Path:
    """SLAM scale ``s`` (SLAM units per metre) over time per session, with 1-sigma bands where the
    series has sigmas, and the true scale as dashed lines when given."""
    fig = Figure(figsize=FIGSIZE)
    ax = fig.add_subplot()
    t0 = _t0(estimates)
    for est in estimates:
        for sid, ts in sorted(scale_series(est).items()):
            _plot_series(ax, ts, f"{est.method} session {sid}", t0)
    for sid, s in sorted((truth_scale or {}).items()):
        ax.axhline(s, color="k", ls="--", lw=1, label=f"truth session {sid}")
    return _finish_over_time(
        ax, fig, t0, "SLAM scale s [SLAM units / m]", "SLAM scale estimate", path
    )


def plot_drag(
    estimates: Sequence[Estimate],
    path: str | Path,
    truth_k: Sequence[float] | float | None = None,
) -> Path:
    """Drag coefficient k [1/s] over time (``series["drag_k"]``), true value(s) dashed."""
    fig = Figure(figsize=FIGSIZE)
    ax = fig.add_subplot()
    t0 = _t0(estimates)
    for est in estimates:
        ts = est.series.get("drag_k")
        if ts is not None:
            _plot_series(ax, ts, est.method, t0)
    if truth_k is not None:
        for j, k in enumerate(np.atleast_1d(np.asarray(truth_k, dtype=float))):
            ls = ("--", ":", "-.")[j % 3]
            ax.axhline(k, color="k", ls=ls, lw=1, label=f"truth k[{j}] = {k:g}")
    return _finish_over_time(ax, fig, t0, "drag k [1/s]", "Rotor-drag coefficient estimate", path)


def plot_latency(estimates: Sequence[Estimate], path: str | Path) -> Path:
    """Histogram of update latency [ms] (log-spaced bins) of the estimates that record it."""
    fig = Figure(figsize=FIGSIZE)
    ax = fig.add_subplot()
    lats = {
        e.method: 1e3 * np.asarray(e.update_latency, dtype=float)
        for e in estimates
        if e.update_latency is not None and np.asarray(e.update_latency).size
    }
    positive = [v[v > 0] for v in lats.values() if np.any(v > 0)]
    if positive:
        lo = min(float(v.min()) for v in positive)
        hi = max(float(v.max()) for v in positive)
        bins = np.logspace(math.log10(lo), math.log10(hi * 1.0001), 50)
        for method, v in lats.items():
            p50, p99 = np.percentile(v, [50, 99])
            ax.hist(
                v[v > 0],
                bins=bins,
                histtype="step",
                label=f"{method} (p50 {p50:.2f} ms, p99 {p99:.2f} ms)",
            )
        ax.set_xscale("log")
        ax.legend(fontsize="small")
    else:
        ax.text(0.5, 0.5, "no update latency recorded", ha="center", transform=ax.transAxes)
    ax.set_xlabel("update latency [ms]")
    ax.set_ylabel("updates")
    ax.grid(True, alpha=0.3)
    ax.set_title("Time per update")
    return _save(fig, path)
