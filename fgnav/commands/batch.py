"""``fgnav batch``: smooth a whole flight with the batch solver and write the estimate.

Thin layer over the ``batch`` method of :mod:`fgnav.methods` (which assembles the options and
calls :func:`fgnav.solvers.batch.solve_batch`). Options come from the ``[graph]``, ``[lm]``,
``[batch]`` and ``[priors]`` tables of ``--config`` with the flags written in (fields of
:class:`~fgnav.solvers.graph.GraphOptions`, :class:`~fgnav.solvers.batch.LMOptions` and
``covariance`` / ``cov_pose_stride`` of :class:`~fgnav.solvers.batch.BatchOptions`). When the
flight has ground truth, the estimate is scored (SE(3) alignment; the mode used is printed: a
straight-line flight falls back to translation only) and the metrics go into
``summary.json``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

import numpy as np

from fgnav.commands import add_config_argument, add_flight_argument, add_out_argument
from fgnav.config import check_tables
from fgnav.datasets.errors import FgnavError
from fgnav.datasets.types import Flight
from fgnav.estimate import Estimate
from fgnav.eval.align import mode_label
from fgnav.eval.outputs import summary_extra
from fgnav.methods import (
    batch_options,
    load_method_config,
    require_streams,
    run_batch,
    with_flags,
)

HELP = "smooth a whole flight (batch solver)"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_flight_argument(parser)
    add_out_argument(parser)
    add_config_argument(parser, "TOML file with [graph], [lm], [batch] and [priors] tables")
    parser.add_argument("--keyframe-hz", type=float, default=None, help="keyframe rate [Hz]")
    parser.add_argument(
        "--covariance",
        choices=("all", "slow", "none"),
        default=None,
        help="marginal covariances to compute (default all)",
    )
    add_priors_argument(parser)
    parser.add_argument(
        "--write-anyway",
        action="store_true",
        help="write the estimate (exit 0) even when the solver did not converge",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


class NotConvergedError(FgnavError, RuntimeError):
    """The batch solve did not converge (``info["health"]["status"] == "not-converged"``)."""


def add_priors_argument(parser: argparse.ArgumentParser) -> None:
    """``--priors``: front-ends whose outputs become priors (``[priors] sources`` in config)."""
    parser.add_argument(
        "--priors",
        default=None,
        help="comma-separated front-end priors: ml-scale (seed 004 closed-form SLAM scale), "
        "observer (seed 000 velocity); default none, or [priors] sources in --config",
    )


def priors_flag(args: argparse.Namespace) -> list[str] | None:
    """``--priors a,b`` as a list (None when not given: ``[priors] sources`` applies)."""
    if args.priors is None:
        return None
    return [s.strip() for s in args.priors.split(",") if s.strip()]


def method_config(args: argparse.Namespace, **tables: dict[str, Any]) -> dict[str, Any]:
    """The ``--config`` tables with the flags written in (:func:`fgnav.methods.with_flags`):
    ``--keyframe-hz`` into ``[graph]``, ``--priors`` into ``[priors]``, plus ``tables``."""
    return with_flags(
        load_method_config(args.config),
        graph={"keyframe_hz": args.keyframe_hz},
        priors={"sources": priors_flag(args)},
        **tables,
    )


def score_and_write(flight: Flight, est: Estimate, out: Path, extra: dict[str, Any]) -> None:
    """Evaluate against the flight's ground truth when present, print a summary, write files."""
    from fgnav.compare import score_estimate
    from fgnav.coverage import coverage, coverage_lines
    from fgnav.eval.outputs import write_estimate
    from fgnav.health import health_line

    metrics = None
    try:
        metrics = score_estimate(flight, est)
    except FgnavError as e:  # the estimate is written all the same
        log.warning("%s: not scored against ground truth: %s", est.method, e)
    if metrics is not None:
        print(
            f"{est.method}: ATE {metrics.ate_rmse_m:.4f} m RMSE "
            f"({mode_label(metrics.alignment)} alignment), "
            f"velocity RMSE {metrics.vel_rmse_mps:.4f} m/s, yaw RMSE "
            f"{metrics.yaw_rmse_deg:.3f} deg, RPE {metrics.rpe_pct:.3f} %"
        )
    for sid, s in sorted(est.slam_scale.items()):
        sig = est.slam_scale_sigma.get(sid)
        sig_txt = f" +/- {sig:.2g}" if sig is not None else ""
        err = ""
        if metrics is not None and sid in metrics.scale_final_err_pct:
            err = f" (error vs truth: final {metrics.scale_final_err_pct[sid]:+.2f} %"
            if sid in metrics.scale_mean_abs_err_pct:
                err += f", mean |error| over time {metrics.scale_mean_abs_err_pct[sid]:.2f} %"
            err += ")"
        axes = (est.info.get("slam_axis_scale_nonpositive") or {}).get(sid)
        if axes is not None:
            sig_txt += f" (per-axis {', '.join(f'{v:.5g}' for v in axes)}: not all positive)"
        print(f"SLAM session {sid}: scale {s:.5g}{sig_txt} SLAM units per metre{err}")
    if est.drag_k is not None:
        ks = np.atleast_1d(est.drag_k)
        sig = None if est.drag_k_sigma is None else np.atleast_1d(est.drag_k_sigma)
        if sig is not None and len(sig) == len(ks):
            # With its sigma: a value that stayed at its prior (an unobserved axis, a vertical
            # flight) reads as such (kx 0.003 +/- 0.2) instead of as a measurement.
            k = ", ".join(f"{v:.4f} +/- {e:.2g}" for v, e in zip(ks, sig, strict=True))
        else:
            k = ", ".join(f"{v:.4f}" for v in ks)
        print(f"drag k: {k} 1/s")
    for line in coverage_lines(flight, est):
        print(line)
    line = health_line(est.info.get("health"))
    if line:
        print(line)
    extra = {**extra, "coverage": coverage(flight, est)}
    paths = write_estimate(est, out, metrics=metrics, extra=extra)
    print(f"wrote {', '.join(str(p) for p in paths.values())}")


def not_converged_message(est: Estimate) -> str | None:
    """One line saying why the batch solve is not trusted (None: it converged)."""
    info = est.info
    health = info.get("health") or {}
    if health.get("status") != "not-converged":
        return None
    errors = info.get("lm_errors") or [float("nan")]
    per = health.get("error_per_factor")
    why = (
        f"LM stopped at the iteration limit ({info.get('lm_iterations')} iterations)"
        if info.get("lm_converged") is False
        else "LM stopped at a poor minimum"
    )
    det = health.get("detectors") or {}
    return (
        f"batch did not converge: {why}, error {errors[0]:.4g} -> {errors[-1]:.4g}"
        + (f" ({per:.1f} per factor)" if per is not None else "")
        + (f"; detectors: {', '.join(f'{k} {v}' for k, v in det.items())}" if det else "")
    )


def run(args: argparse.Namespace) -> int:
    from fgnav.datasets.load import load_flight

    check_tables(args.config, ["graph", "lm", "batch", "priors"])
    config = method_config(args, batch={"covariance": args.covariance})
    batch_options(config)  # option values checked before the flight is read
    flight = load_flight(args.flight)
    require_streams("batch", flight)
    est = run_batch(flight, config, progress=not args.no_progress)
    print(
        f"batch: {len(est.trajectory)} keyframes, {est.info['lm_iterations']} LM iterations, "
        f"{est.runtime_s:.2f} s"
    )
    verdict = not_converged_message(est)
    if verdict and not args.write_anyway:
        raise NotConvergedError(
            f"{flight.name}: {verdict}; nothing written (--write-anyway writes it)"
        )
    if verdict:
        log.warning("%s: %s; written anyway (--write-anyway)", flight.name, verdict)
    score_and_write(flight, est, Path(args.out), summary_extra(flight.name, est, "batch"))
    return 0
