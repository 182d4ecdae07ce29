"""Run the smoothers and the filter baselines on one flight and score them against ground truth.

:func:`compare` runs every method of :mod:`fgnav.methods` the flight allows (or the ones asked
for), one after the other. A method that raises is recorded with its error and the others still
run; a method the flight cannot feed is listed with the stream it misses. When the flight has
ground truth, each estimate is scored with :func:`fgnav.eval.metrics.evaluate` after the
alignment its method states (SE(3) for metric estimates). The true SLAM scale per session comes
from the simulator's metadata (``meta["truth"]["slam_sessions"]``: the scale drifts linearly,
``scale * (1 + scale_drift_per_s * (t - t_start))``, and its value at the session's end time is
used, the time of an estimate's final scale) or, for real flights, from a Sim(3) fit of the SLAM
camera positions to the truth (:func:`fgnav.eval.metrics.slam_scale_vs_truth`).

:meth:`CompareResult.write` writes ``compare.json`` (all metrics, skipped methods with reasons,
failures with errors, flight info, timings), ``<method>/`` with ``estimate.tum``, ``states.csv``
and ``summary.json`` per method, the figures (PNG) and ``report.md`` made from the same dict as
``compare.json`` (:mod:`fgnav.report`).
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fgnav.coverage import flight_t0
from fgnav.datasets.errors import FgnavError
from fgnav.datasets.types import Flight
from fgnav.estimate import Estimate, TimeSeries
from fgnav.eval.metrics import (
    DEFAULT_RPE_DELTA_M,
    Metrics,
    common_span_ate,
    evaluate,
    to_jsonable,
)
from fgnav.methods import (
    METHODS,
    Method,
    MethodUnavailableError,
    available_methods,
    get_method,
    slam_checked,
)

log = logging.getLogger(__name__)

CAUSAL_SLAM_CHECK = ("fixed-lag", "fixed-lag@lag")
"""Methods that check the SLAM rotation convention and clock themselves, causally (the push-API
smoother's SLAM-vs-gyro check; the prepared runner applies the whole-flight check itself)."""

#: Metric keys copied from :meth:`Metrics.as_dict` into each table row of ``compare.json``.
ROW_METRICS = (
    "ate_rmse_m",
    "ate_4dof_m",
    "rpe_pct",
    "scale_final_abs_err_pct",
    "vel_rmse_mps",
    "yaw_rmse_deg",
    "nees_pos",
    "times_real_time",
)


#: Plausibility flags (:func:`plausibility_flags`), after scoring; information only (the numbers
#: and the exit code stay): the largest speed of a multirotor [m/s] (racing quadrotors reach
#: 30-40 m/s; the flights here fly below 5 m/s) ...
FLAG_MAX_SPEED_MPS = 50.0
#: ... measured over spans of at least this long [s] (consecutive samples when they are further
#: apart): a filter's position correction between two outputs 5 ms apart is no speed ...
FLAG_SPEED_SPAN_S = 1.0
#: ... and, with ground truth, an ATE above the larger of this [m] ...
FLAG_ATE_MIN_M = 1.0
#: ... and this fraction of the true path length over the scored span.
FLAG_ATE_PATH_FRACTION = 0.1


#: Top view: the truth's extent grown by this fraction on each side (a diverging estimate
#: leaves the view instead of shrinking the others to a dot; the legend says so).
TOP_VIEW_MARGIN = 0.25


@dataclass
class MethodRun:
    """The outcome of one method.

    Attributes:
        method: the registry entry.
        estimate: its estimate (None when it failed).
        metrics: scores against truth (None without truth, or when scoring failed).
        error: ``"<ExceptionType>: message"`` (on one line) when the method failed.
        traceback: the formatted traceback of a failure.
        evaluation_error: why a finished estimate could not be scored.
        wall_s: wall time of the run and its scoring [s].
        reused: True when the estimate was given to :func:`compare` instead of computed there.
        ate_common_m: ATE over the span every causal method covers [m].
        flags: why the estimate is implausible (:func:`plausibility_flags`; empty when it is not).
    """

    method: Method
    estimate: Estimate | None = None
    metrics: Metrics | None = None
    error: str | None = None
    traceback: str | None = None
    evaluation_error: str | None = None
    wall_s: float = 0.0
    reused: bool = False
    ate_common_m: float | None = None
    #: ``[{"code", "reason"}]`` of :func:`plausibility_flags` (empty: nothing implausible)
    flags: list[dict[str, str]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.estimate is not None

    def row(self) -> dict[str, Any]:
        """The table row (JSON-ready; values at full precision)."""
        m = self.method
        row: dict[str, Any] = {
            "method": m.name,
            "status": "ok" if self.ok else "failed",
            "causal": self.estimate.causal if self.ok else m.causal,
            "alignment": self.metrics.alignment if self.metrics else None,
            # RPE, yaw RMSE and NEES left out (blank): see Method.positions_only
            "positions_only": m.positions_only,
        }
        d = self.metrics.as_dict() if self.metrics else {}
        for key in ROW_METRICS:
            row[key] = d.get(key)
        row["ate_common_m"] = self.ate_common_m
        lat = None if not self.ok else self.estimate.update_latency
        lat = None if lat is None else np.asarray(lat, dtype=float)
        has_lat = lat is not None and lat.size > 0
        row["latency_p50_ms"] = float(1e3 * np.percentile(lat, 50)) if has_lat else None
        if self.ok and row["times_real_time"] is None and self.estimate.runtime_s > 0:
            row["times_real_time"] = self.estimate.trajectory.duration / self.estimate.runtime_s
        row["flag"] = ",".join(f["code"] for f in self.flags) or None
        return to_jsonable(row)


@dataclass
class CompareResult:
    """Everything :func:`compare` found (see :meth:`to_dict` for the JSON layout).

    Attributes:
        flight: the flight compared.
        runs: outcome per method that was attempted, in table order.
        skipped: ``{method: reason}`` for the methods the flight (or this installation) cannot run.
        truth_scale: true SLAM scale per session (SLAM units per metre) used for scale errors.
        truth_scale_source: where it came from, or why it is unknown.
        timings: wall time per stage [s] (``"<method>"`` and ``"total"``).
        config: the config tables used.
    """

    flight: Flight
    runs: dict[str, MethodRun] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    truth_scale: dict[int, float] | None = None
    truth_scale_source: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    rpe_delta_m: float = DEFAULT_RPE_DELTA_M
    flow_figures: dict[str, dict[str, float]] = field(default_factory=dict)
    #: start [s, flight clock] of the span every causal method covers (``ate_common_m``)
    common_span_start_s: float | None = None

    @property
    def estimates(self) -> list[Estimate]:
        """The estimates of the methods that ran, in table order."""
        return [r.estimate for r in self.runs.values() if r.estimate is not None]

    @property
    def failed(self) -> dict[str, str]:
        """``{method: error}`` of the methods that raised."""
        return {n: r.error or "" for n, r in self.runs.items() if not r.ok}

    def rows(self) -> list[dict[str, Any]]:
        """The table rows (one per attempted method)."""
        return [r.row() for r in self.runs.values()]

    def table(self) -> str:
        """The fixed-width text table (see :data:`fgnav.report.COLUMNS`)."""
        from fgnav.report import format_table

        return format_table(self.rows())

    def truth_drag_k(self) -> list[float] | None:
        truth = self.flight.meta.get("truth") if isinstance(self.flight.meta, dict) else None
        k = truth.get("drag_k") if isinstance(truth, dict) else None
        return [float(x) for x in k] if k is not None else None

    def to_dict(
        self, outputs: Mapping[str, str] | None = None, figures: Mapping[str, str] | None = None
    ) -> dict[str, Any]:
        """The content of ``compare.json``.

        Args:
            outputs: output folder of each method (relative to the report), when written.
            figures: figure files by key (relative paths), when drawn.
        """
        from fgnav.eval.outputs import summary_dict

        methods: dict[str, Any] = {}
        for name, r in self.runs.items():
            entry: dict[str, Any] = {
                "status": "ok" if r.ok else "failed",
                "description": r.method.description,
                "requires": list(r.method.requires),
                "optional_used": [s for s in r.method.optional if s in self.flight.streams()],
                "wall_s": r.wall_s,
                "reused": r.reused,
                "output": (outputs or {}).get(name),
            }
            if r.ok:
                entry["flags"] = list(r.flags)
                entry["estimate"] = summary_dict(r.estimate)
                entry["estimate"]["runtime_s"] = r.estimate.runtime_s
                entry["metrics"] = r.metrics.as_dict() if r.metrics else None
                entry["evaluation_error"] = r.evaluation_error
            else:
                entry["error"] = r.error
                entry["traceback"] = r.traceback
            methods[name] = entry
        data = {
            "flight": flight_info(self.flight),
            "truth": {
                "ground_truth": self.flight.ground_truth is not None,
                "slam_scale": self.truth_scale,
                "slam_scale_source": self.truth_scale_source,
                "slam_scale_units": "SLAM units per metre",
                "drag_k": self.truth_drag_k(),
            },
            "rpe_delta_m": self.rpe_delta_m,
            "common_span_start_s": self.common_span_start_s,
            "common_span_start_rel_s": (
                None
                if self.common_span_start_s is None
                else self.common_span_start_s - flight_t0(self.flight)
            ),
            "table": self.rows(),
            "flags": {n: [f["reason"] for f in r.flags] for n, r in self.runs.items() if r.flags},
            "flag_bounds": {
                "max_speed_mps": FLAG_MAX_SPEED_MPS,
                "speed_span_s": FLAG_SPEED_SPAN_S,
                "ate_min_m": FLAG_ATE_MIN_M,
                "ate_path_fraction": FLAG_ATE_PATH_FRACTION,
            },
            "flow_table": self.flow_table(),
            "methods": methods,
            "skipped": dict(self.skipped),
            "timings": dict(self.timings),
            "config": self.config,
            "figures": dict(figures or {}),
        }
        return to_jsonable(data)

    def flow_table(self) -> dict[str, Any] | None:
        """The flow-and-range figures per method, their markdown table and the goal checks
        (``fgnav.eval.flow_table``); None for a flight without optical flow or truth."""
        if not self.flow_figures:
            return None
        from fgnav.eval.flow_table import check_goals, goals_markdown, markdown_table

        goals = check_goals(self.flow_figures)
        return {
            "figures": self.flow_figures,
            "markdown": markdown_table(self.flow_figures),
            "goals": goals,
            "goals_markdown": goals_markdown(goals),
        }

    def write(self, out_dir: str | Path, figures: bool = True) -> dict[str, Path]:
        """Write ``compare.json``, ``report.md``, the figures and ``<method>/`` outputs.

        Args:
            out_dir: output folder (created).
            figures: draw the PNG figures.

        Returns:
            Paths by name: ``"json"``, ``"report"``, ``"<method>"`` (folders), ``"fig:<key>"``.
        """
        from fgnav.eval.outputs import write_estimate
        from fgnav.report import write_report

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths: dict[str, Path] = {}
        outputs: dict[str, str] = {}
        for name, r in self.runs.items():
            if not r.ok:
                continue
            sub = out / method_dirname(name)
            write_estimate(
                r.estimate,
                sub,
                metrics=r.metrics,
                extra={"flight": self.flight.name, "command": "compare"},
            )
            paths[name] = sub
            outputs[name] = sub.name + "/"
        figs, fig_errors = ({}, {}) if not figures else self._draw_figures(out)
        for key, p in figs.items():
            paths[f"fig:{key}"] = p
        data = self.to_dict(outputs, {k: p.name for k, p in figs.items()})
        data["figure_errors"] = fig_errors
        paths["json"] = out / "compare.json"
        paths["json"].write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
        paths["report"] = write_report(data, out / "report.md")
        log.info("wrote %s and %s", paths["json"], paths["report"])
        return paths

    def _draw_figures(self, out: Path) -> tuple[dict[str, Path], dict[str, str]]:
        from fgnav.eval import plots

        ests = self.estimates
        truth = self.flight.ground_truth
        figs: dict[str, Path] = {}
        errors: dict[str, str] = {}
        if not ests:
            return figs, {"all": "no method produced an estimate"}
        # Trajectories that cannot be matched to truth are drawn unaligned by nobody: leave them
        # out of the truth-based figures and say so.
        scored = [e for e in ests if truth is None or self.runs[e.method].metrics is not None]
        dropped = [e.method for e in ests if e not in scored]
        jobs = {
            "top_view": lambda p: plots.plot_top_view(
                scored, truth, p, view_margin=TOP_VIEW_MARGIN
            ),
            "errors": lambda p: plots.plot_errors_over_time(scored, truth, p, log_scale=True),
            "scale": lambda p: plots.plot_scale(ests, p, self.truth_scale),
            "drag": lambda p: plots.plot_drag(
                [held_to_end(e, "drag_k") for e in ests], p, self.truth_drag_k()
            ),
            "latency": lambda p: plots.plot_latency(ests, p),
        }
        if truth is None:
            jobs.pop("errors")
            errors["errors"] = "the flight has no ground truth"
        if not any(e.update_latency is not None and len(e.update_latency) for e in ests):
            jobs.pop("latency")
            errors["latency"] = "no method records its update latency"
        if not any(scale_series_present(e) for e in ests):
            jobs.pop("scale")
            errors["scale"] = "no method estimates a SLAM scale over time"
        if not any("drag_k" in e.series for e in ests):
            jobs.pop("drag")
            errors["drag"] = "no method estimates the drag coefficient over time"
        for key, job in jobs.items():
            try:
                figs[key] = job(out / f"{key}.png")
            except Exception as e:  # a figure must not stop the report
                log.warning("figure %s failed: %s", key, e)
                errors[key] = f"{type(e).__name__}: {e}"
        if dropped:
            errors["not_in_truth_figures"] = (
                f"{', '.join(dropped)}: could not be matched to the truth (see per-method notes)"
            )
        return figs, errors


def _fmt_big(x: float) -> str:
    return f"{x:.3g}" if math.isfinite(x) else str(x)


def max_speed(traj: Any, span_s: float = FLAG_SPEED_SPAN_S) -> tuple[float, float]:
    """Largest speed [m/s] of the positions over spans of at least ``span_s`` (from each sample
    to the first one ``span_s`` or more later; the first to the last sample on a shorter
    trajectory) and the time [s] the span starts; ``(0, nan)`` with fewer than 2 samples.
    Non-finite positions give ``inf`` (or NaN)."""
    t = np.asarray(traj.t, dtype=float)
    p = np.asarray(traj.world_t_body, dtype=float)
    if t.size < 2 or not t[-1] > t[0]:
        return 0.0, math.nan
    j = np.searchsorted(t, t + span_s, side="left")
    i = np.flatnonzero(j < t.size)
    if i.size == 0:
        i, j = np.array([0]), np.array([t.size - 1])
    else:
        j = j[i]
    with np.errstate(over="ignore", invalid="ignore"):
        v = np.linalg.norm(p[j] - p[i], axis=1) / (t[j] - t[i])
    bad = ~np.isfinite(v)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        return (math.inf if not np.isnan(v[k]) else math.nan), float(t[i[k]])
    k = int(np.argmax(v))
    return float(v[k]), float(t[i[k]])


def plausibility_flags(
    est: Estimate, metrics: Metrics | None, t0: float = 0.0
) -> list[dict[str, str]]:
    """Why an estimate is implausible, as ``[{"code", "reason"}]`` (empty: nothing found).

    Codes: ``non-finite`` (positions, velocities or the ATE not finite), ``speed`` (faster than
    :data:`FLAG_MAX_SPEED_MPS` over spans of :data:`FLAG_SPEED_SPAN_S`, see :func:`max_speed`;
    no ground truth needed), ``ate`` (with ground truth: ATE above the larger of
    :data:`FLAG_ATE_MIN_M` and :data:`FLAG_ATE_PATH_FRACTION` of the true path). A diverged
    filter's row used to print as any other (ATE 4920 m, 1.95e28 m, exit 0, no warning). ``t0``:
    the flight's first time (times in the reasons are relative to it).
    """
    traj = est.trajectory
    out: list[dict[str, str]] = []
    bad = [
        f"{name} ({int((~np.isfinite(a)).any(axis=1).sum())} of {len(a)} samples)"
        for name, a in (("positions", traj.world_t_body), ("velocities", traj.world_v_body))
        if a is not None and not np.isfinite(np.asarray(a, dtype=float)).all()
    ]
    if metrics is not None and not math.isfinite(metrics.ate_rmse_m):
        bad.append(f"ATE ({metrics.ate_rmse_m})")
    if bad:
        out.append({"code": "non-finite", "reason": "non-finite " + ", ".join(bad)})
    v, t_v = max_speed(traj)
    if not v <= FLAG_MAX_SPEED_MPS:  # (NaN and inf included)
        out.append(
            {
                "code": "speed",
                "reason": f"speed {_fmt_big(v)} m/s over {FLAG_SPEED_SPAN_S:g} s from "
                f"{t_v - t0:.1f} s (a multirotor flies below {FLAG_MAX_SPEED_MPS:g} m/s)",
            }
        )
    if metrics is not None and math.isfinite(metrics.ate_rmse_m):
        path = metrics.path_length_m if math.isfinite(metrics.path_length_m) else 0.0
        bound = max(FLAG_ATE_MIN_M, FLAG_ATE_PATH_FRACTION * path)
        if metrics.ate_rmse_m > bound:
            out.append(
                {
                    "code": "ate",
                    "reason": f"ATE {_fmt_big(metrics.ate_rmse_m)} m > {bound:.3g} m (the "
                    f"larger of {FLAG_ATE_MIN_M:g} m and {100 * FLAG_ATE_PATH_FRACTION:g} % of "
                    f"the {path:.3g} m true path)",
                }
            )
    return out


def held_to_end(est: Estimate, key: str) -> Estimate:
    """The estimate with ``series[key]`` extended by its last value at the trajectory's end.

    Smoothers report a piecewise-constant variable (drag k per segment) once, at the start of its
    segment; a single segment would plot as one point. The value holds until the next sample, so
    repeating the last one at the end time draws the steps it stands for.
    """
    import dataclasses

    ts = est.series.get(key)
    t_end = float(est.trajectory.t[-1])
    if ts is None or not len(ts.t) or float(ts.t[-1]) >= t_end:
        return est
    value = np.asarray(ts.value)
    sigma = None if ts.sigma is None else np.asarray(ts.sigma)
    ext = TimeSeries(
        np.append(np.asarray(ts.t, dtype=float), t_end),
        np.concatenate([value, value[-1:]]),
        None if sigma is None else np.concatenate([sigma, sigma[-1:]]),
    )
    return dataclasses.replace(est, series={**est.series, key: ext})


def has_scale(est: Estimate) -> bool:
    """True when the estimate reports a SLAM scale (final value or series)."""
    return bool(est.slam_scale) or scale_series_present(est)


def scale_series_present(est: Estimate) -> bool:
    """True when the estimate has a SLAM-scale time series for :func:`plots.plot_scale`."""
    return any(k == "slam_scale" or k.startswith("slam_scale/") for k in est.series)


def one_line(text: str) -> str:
    """``text`` with every run of whitespace (newlines included) made one space."""
    return " ".join(text.split())


def method_dirname(name: str) -> str:
    """Folder name of a method's outputs (``ref:x`` -> ``ref_x``)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def flight_info(flight: Flight) -> dict[str, Any]:
    """Name, source, duration, streams (samples, rate) and simulator identity of a flight."""
    streams = {
        name: {"n": len(s), "rate_hz": s.rate_hz, "t0": float(s.t[0]), "t1": float(s.t[-1])}
        for name, s in flight.streams().items()
    }
    try:
        t0, t1 = flight.time_window()
        duration = t1 - t0
    except FgnavError:
        duration = math.nan
    meta = flight.meta if isinstance(flight.meta, dict) else {}
    return to_jsonable(
        {
            "name": flight.name,
            "source": flight.source,
            "duration_s": duration,
            "streams": streams,
            "synthetic": bool(meta.get("synthetic", False)),
            "scenario": meta.get("scenario"),
            "seed": meta.get("seed"),
        }
    )


def truth_slam_scales(flight: Flight) -> tuple[dict[int, float] | None, str]:
    """True SLAM scale per session and where it comes from.

    Flights without a SLAM stream: None (a simulated flight's metadata lists the sessions the
    simulator drew even when the SLAM stream was left out). Simulated flights: ``scale * (1 +
    scale_drift_per_s * (t_end - t_start))`` of each session in ``meta["truth"]["slam_sessions"]``
    (the scale at the session's last pose). Real flights with SLAM and ground truth:
    :func:`slam_scale_vs_truth`. Otherwise None and the reason.
    """
    if flight.slam is None:  # (a simulated flight's metadata still lists the sessions it drew)
        return None, "the flight has no SLAM stream"
    truth = flight.meta.get("truth") if isinstance(flight.meta, dict) else None
    sessions = truth.get("slam_sessions") if isinstance(truth, dict) else None
    if sessions:
        at = truth_slam_scale_at(flight) or {}
        out = {}
        for sid, v in sessions.items():
            t_end = float(v.get("t_end", v.get("t_start", 0.0)))
            out[int(sid)] = float(at[int(sid)](t_end))
        return out, "simulator truth, value at the session's end time (linear scale drift)"
    if flight.ground_truth is None:
        return None, "the flight has no ground truth"
    from fgnav.eval.metrics import slam_scale_vs_truth

    try:
        out = slam_scale_vs_truth(flight.slam, flight.ground_truth, flight.calib.body_T_cam)
    except FgnavError as e:
        return None, f"Sim(3) fit of SLAM to ground truth failed: {e}"
    if not out:
        return None, "no SLAM session overlaps the ground truth enough for a Sim(3) fit"
    return out, "Sim(3) fit of the SLAM camera positions to the ground truth (whole session)"


def truth_slam_scale_at(flight: Flight) -> dict[int, Callable[[np.ndarray], np.ndarray]] | None:
    """True SLAM scale of each session as a function of time, for simulated flights (the
    simulator's linear drift ``scale (1 + scale_drift_per_s (t - t_start))``); None otherwise.
    For the per-axis model the scale is the geometric mean of the axes (as the estimates')."""
    truth = flight.meta.get("truth") if isinstance(flight.meta, dict) else None
    sessions = truth.get("slam_sessions") if isinstance(truth, dict) else None
    if not sessions:
        return None
    out: dict[int, Callable[[np.ndarray], np.ndarray]] = {}
    for sid, v in sessions.items():
        scale, drift = float(v["scale"]), float(v.get("scale_drift_per_s", 0.0))
        t_start = float(v.get("t_start", 0.0))
        out[int(sid)] = lambda t, s0=scale, d=drift, t0=t_start: (
            s0 * (1.0 + d * (np.asarray(t, float) - t0))
        )
    return out


def score_estimate(
    flight: Flight,
    est: Estimate,
    alignment: str = "se3",
    delta_m: float = DEFAULT_RPE_DELTA_M,
    positions_only: bool = False,
) -> Metrics | None:
    """Score ``est`` against the flight's ground truth (None when it has none): ``alignment``
    (DESIGN.md section 9), the true SLAM scale when the estimate has one, the positions only
    when asked (:attr:`fgnav.methods.Method.positions_only`, the ``ref:<name>`` rows). One
    scoring for ``fgnav batch``/``online``, ``compare`` and ``fleet``.

    Raises:
        FgnavError: the estimate cannot be matched to the truth (see :func:`evaluate`).
    """
    if flight.ground_truth is None:
        return None
    return evaluate(
        est,
        flight.ground_truth,
        alignment=alignment,
        truth_scale=truth_slam_scales(flight)[0] if has_scale(est) else None,
        delta_m=delta_m,
        truth_scale_at=truth_slam_scale_at(flight),
        positions_only=positions_only,
    )


def compare(
    flight: Flight,
    methods: list[str] | None = None,
    config: Mapping[str, Any] | None = None,
    progress: bool = True,
    estimates: Mapping[str, Estimate] | None = None,
    registry: Mapping[str, Method] | None = None,
) -> CompareResult:
    """Run methods on a flight and score them.

    Args:
        flight: the flight (checked).
        methods: method names (None: every method the flight allows, see
            :func:`fgnav.methods.available_methods`). Names the flight cannot feed are skipped
            with the reason; unknown names raise; a name given twice runs once.
        config: config tables by name (``[graph]``, ``[msf-ekf]`` ..., see :mod:`fgnav.methods`).
        progress: progress bars of the methods that have them.
        estimates: estimates already computed for some methods (scored, not re-run).
        registry: the methods to choose from (default :data:`fgnav.methods.METHODS`).

    Returns:
        The :class:`CompareResult`.

    Raises:
        FgnavError: an unknown method name.
    """
    flight.check()
    cfg = dict(config or {})
    # SLAM rotation convention and clock (the [graph] options) decided once for every method
    # but the online smoother, which decides them causally from what has arrived.
    raw = flight
    flight = slam_checked(flight, cfg)
    # The causal filters get each SLAM pose as decided when it arrived (as stated before).
    causal_flight = None
    reg = METHODS if registry is None else registry
    if methods is not None:  # a name given twice runs once (as in fgnav fleet)
        methods = list(dict.fromkeys(methods))
    t_all = time.perf_counter()
    runnable, skipped = available_methods(flight, methods, reg)
    for name, reason in skipped.items():
        log.info("%s: skipped: %s", name, reason)
    res = CompareResult(flight=flight, skipped=skipped, config=cfg)
    res.truth_scale, res.truth_scale_source = truth_slam_scales(flight)
    given = dict(estimates or {})
    for name in runnable:
        method = get_method(name, flight, reg)
        run = MethodRun(method=method)
        t0 = time.perf_counter()
        if name in given:
            run.estimate, run.reused = given[name].check(), True
        else:
            log.info("%s: running (%s)", name, method.description)
            try:
                if name in CAUSAL_SLAM_CHECK:
                    given_flight = raw
                elif method.causal and "slam" in method.requires + method.optional:
                    if causal_flight is None:
                        causal_flight = slam_checked(raw, cfg, causal=True)
                    given_flight = causal_flight
                else:
                    given_flight = flight
                run.estimate = method.run(given_flight, cfg, progress)
            except MethodUnavailableError as e:  # known only once it looks at its options
                res.skipped[name] = one_line(str(e))
                log.info("%s: skipped: %s", name, res.skipped[name])
                continue
            except Exception as e:  # one method's failure must not stop the comparison
                run.error = f"{type(e).__name__}: {one_line(str(e))}"
                run.traceback = traceback.format_exc()
                log.warning("%s failed: %s", name, run.error)
        if run.ok and flight.ground_truth is not None:
            try:
                run.metrics = score_estimate(
                    flight,
                    run.estimate,
                    method.alignment,
                    delta_m=res.rpe_delta_m,
                    positions_only=method.positions_only,
                )
            except Exception as e:  # scoring problems are reported per method
                run.evaluation_error = f"{type(e).__name__}: {one_line(str(e))}"
                log.warning("%s: not scored: %s", name, run.evaluation_error)
        if run.ok and flight.ground_truth is not None and flight.flow is not None:
            from fgnav.eval.flow_table import flow_figures

            try:
                res.flow_figures[name] = flow_figures(run.estimate, flight.ground_truth)
            except Exception as e:  # scoring problems are reported per method
                log.warning("%s: no flow figures: %s", name, one_line(str(e)))
        run.wall_s = time.perf_counter() - t0
        res.timings[name] = run.wall_s
        res.runs[name] = run
        if run.ok:
            log.info(
                "%s: done in %.2f s%s",
                name,
                run.wall_s,
                f", ATE {run.metrics.ate_rmse_m:.4f} m" if run.metrics else "",
            )
    if flight.ground_truth is not None:
        scored = {n: r for n, r in res.runs.items() if r.ok and r.metrics is not None}
        res.common_span_start_s, ates = common_span_ate(
            {n: r.estimate.trajectory for n, r in scored.items()},
            {n: r.estimate.causal for n, r in scored.items()},
            flight.ground_truth,
            # The mode each method asks for: its metrics' mode is the one used, which a
            # degenerate geometry turns into a translation (and align() does not take back).
            {n: r.method.alignment for n, r in scored.items()},
        )
        for n, ate in ates.items():
            res.runs[n].ate_common_m = ate
    t_first = flight_t0(flight)
    for n, r in res.runs.items():
        if r.ok:
            r.flags = plausibility_flags(r.estimate, r.metrics, t_first)
            for f in r.flags:
                log.info("%s: implausible: %s", n, f["reason"])
    res.timings["total"] = time.perf_counter() - t_all
    return res
