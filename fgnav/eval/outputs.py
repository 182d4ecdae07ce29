"""Files written for an estimate: TUM trajectory, per-state CSV, JSON summary.

- ``estimate.tum``: TUM RGB-D format ``t tx ty tz qx qy qz qw`` (time [s], ``world_t_body`` [m],
  ``world_R_body`` as a unit quaternion in x y z w order), one pose per line, full double precision
  (:func:`fgnav.datasets.tum.write_tum`), readable by ``evo_ape tum truth.tum estimate.tum``.
- ``states.csv``: one row per state: time, position, quaternion ``[w, x, y, z]``, and whichever of
  velocity, gyro bias, accelerometer bias, position sigmas (world frame) and velocity sigmas the
  estimate has; the header names each column with its frame and unit.
- ``summary.json``: method, options and diagnostics (``Estimate.info``), SLAM scale per session
  with sigma, drag k with sigma, ground height, timings, and metrics when given.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from fgnav.datasets.tum import write_tum
from fgnav.datasets.types import Trajectory
from fgnav.estimate import Estimate
from fgnav.eval.metrics import Metrics, to_jsonable

logger = logging.getLogger(__name__)

#: printf format giving the shortest text that round-trips every float64.
FULL_PRECISION = "%.17g"


def position_sigmas_world(traj: Trajectory, pose_cov: np.ndarray) -> np.ndarray:
    """(N, 3) standard deviations [m] of the position along world x, y, z.

    The Pose3 covariance's translation block is in the body frame (GTSAM's right perturbation);
    it is rotated into world: ``world_R_body P_tt world_R_body^T``.
    """
    R = traj.world_R_body()
    P = np.einsum("nij,njk,nlk->nil", R, pose_cov[:, 3:6, 3:6], R)
    return np.sqrt(np.clip(np.diagonal(P, axis1=1, axis2=2), 0.0, None))


def write_states_csv(estimate: Estimate, path: str | Path) -> Path:
    """Write one CSV row per state of ``estimate`` (see the module docstring).

    Returns:
        The path written.
    """
    path = Path(path)
    traj = estimate.trajectory
    names = ["t_s"]
    cols: list[np.ndarray] = [traj.t[:, None]]
    names += [f"world_t_body_{a}_m" for a in "xyz"]
    cols.append(traj.world_t_body)
    names += [f"world_q_body_{a}" for a in "wxyz"]
    cols.append(traj.world_q_body_wxyz)
    optional = (
        ("world_v_body", "mps", traj.world_v_body),
        ("gyro_bias", "radps", traj.gyro_bias),
        ("accel_bias", "mps2", traj.accel_bias),
    )
    for name, unit, a in optional:
        if a is not None:
            names += [f"{name}_{ax}_{unit}" for ax in "xyz"]
            cols.append(a)
    if estimate.pose_cov is not None:
        names += [f"sigma_world_t_body_{a}_m" for a in "xyz"]
        cols.append(position_sigmas_world(traj, estimate.pose_cov))
    if estimate.vel_cov is not None:
        names += [f"sigma_world_v_body_{a}_mps" for a in "xyz"]
        cols.append(np.sqrt(np.clip(np.diagonal(estimate.vel_cov, axis1=1, axis2=2), 0, None)))
    data = np.column_stack(cols)
    np.savetxt(path, data, fmt=FULL_PRECISION, delimiter=",", header=",".join(names), comments="")
    return path


def _latency_summary(estimate: Estimate) -> dict[str, Any]:
    lat = None if estimate.update_latency is None else np.asarray(estimate.update_latency, float)
    duration = estimate.trajectory.duration
    out: dict[str, Any] = {
        "runtime_s": estimate.runtime_s,
        "duration_s": duration,
        "times_real_time": duration / estimate.runtime_s if estimate.runtime_s > 0 else None,
        "n_updates": 0 if lat is None else int(lat.size),
    }
    if lat is not None and lat.size:
        out.update(
            update_latency_p50_s=float(np.percentile(lat, 50)),
            update_latency_p99_s=float(np.percentile(lat, 99)),
            update_latency_max_s=float(lat.max()),
        )
    return out


def summary_dict(
    estimate: Estimate, metrics: Metrics | None = None, extra: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The content of ``summary.json`` as a JSON-ready dict."""
    traj = estimate.trajectory
    summary: dict[str, Any] = {
        "method": estimate.method,
        "causal": estimate.causal,
        "n_states": len(traj),
        "t_start_s": float(traj.t[0]),
        "t_end_s": float(traj.t[-1]),
        "info": estimate.info,
        "slam_scale": {
            sid: {"s": s, "sigma": estimate.slam_scale_sigma.get(sid)}
            for sid, s in sorted(estimate.slam_scale.items())
        },
        "slam_scale_units": "SLAM units per metre",
        "drag_k_per_s": estimate.drag_k,
        "drag_k_sigma_per_s": estimate.drag_k_sigma,
        "ground_height_m": estimate.ground_height,
        "has_pose_cov": estimate.pose_cov is not None,
        "has_vel_cov": estimate.vel_cov is not None,
        "series": sorted(estimate.series),
        "timing": _latency_summary(estimate),
    }
    if metrics is not None:
        summary["metrics"] = metrics.as_dict()
    if extra:
        summary["extra"] = extra
    return to_jsonable(summary)


def summary_extra(flight_name: str, estimate: Estimate, command: str) -> dict[str, Any]:
    """``summary.json``'s ``extra`` of a command's run: flight name, command, and the front-end
    priors the estimate used (``info["frontend_priors"]``)."""
    extra: dict[str, Any] = {"flight": flight_name, "command": command}
    if "frontend_priors" in estimate.info:
        extra["frontend_priors"] = estimate.info["frontend_priors"]
    return extra


def write_estimate(
    estimate: Estimate,
    out_dir: str | Path,
    metrics: Metrics | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """Write ``estimate.tum``, ``states.csv`` and ``summary.json`` into ``out_dir`` (created).

    Args:
        estimate: the estimate.
        out_dir: output folder.
        metrics: scores to include in the summary, when known.
        extra: free JSON-able content added under ``"extra"`` (flight name, command line ...).

    Returns:
        ``{"tum": path, "states": path, "summary": path}``.
    """
    estimate.check()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "tum": write_tum(out / "estimate.tum", estimate.trajectory),
        "states": write_states_csv(estimate, out / "states.csv"),
        "summary": out / "summary.json",
    }
    text = json.dumps(summary_dict(estimate, metrics, extra), indent=2, allow_nan=False)
    paths["summary"].write_text(text + "\n")
    logger.info("wrote %s estimate to %s", estimate.method, out)
    return paths
