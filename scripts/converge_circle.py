"""Convergence of per-axis SLAM scale and velocity on seed 000's circle: I&I observer vs smoothers.

Flight: the simulator's ``circle`` (seed 000, sec. 4: radius 2 m, 1 m/s, initial body velocity
``u = 0.2, v = -0.2`` m/s, SLAM positions with per-axis scale ``kx = 0.3, ky = 0.2``), seeded, in
two variants:

* ``clean``: noise-free sensors and no SLAM scale drift (the paper's simulation);
* ``noisy``: the simulator's default noise, biases and SLAM scale drift (5e-4 per second).

Sensor set (seed 000's): accelerometer + attitude (AHRS) + monocular SLAM positions.

* (a) ``ii-observer``: the I&I observer (``fgnav.frontends.ii_observer``) with the paper's gains
  (7, 8), ``K_hat(0) = 0``, ``V_hat(0) = 0`` and the simulator's drag ``mu/m`` (the paper assumes
  it known); two rows: the ``published`` kinematics (Coriolis term neglected, eq. 8) and the
  ``full`` ones. Its ``y5 = w`` (eq. 5) is, as in the paper, the vertical velocity
  from the rangefinder height (``vertical_velocity_from_range``) -- the only use of the
  rangefinder here.
* (b) ``fixed-lag``: the online fixed-lag smoother (lag 2 s), causal: the newest estimate after
  each keyframe update; scale from ``estimate.series["slam_axis_scale"]`` (read every update).
* (c) ``batch``: the batch smoother on the whole flight (not causal: its scale is one constant
  for the flight; reported as final errors and the smoothed velocity error).
* (d) ``batch[0,T]``: the batch smoother re-solved on the prefix ``[0, T]`` of the flight for a
  grid of ``T``; the scale and the *newest* velocity at ``T`` are what a smoother run at time ``T``
  would output, so this is a fair convergence-vs-data-duration curve (resolution: the grid).

Both smoothers use ``GraphOptions(use_gyro=False, use_range=False, use_yaw=False,
use_homography=False, slam_model="axis")``: the accelerometer through the IMU preintegration (rates
from the attitude stream, no gyro) and the drag factor (drag ``kx, ky`` *estimated*, not given),
the attitude stream, and per-axis SLAM positions.

Errors: per-axis scale relative error ``|k_hat_i - k_i(t)| / k_i(t)`` against the simulator's
(drifting, in ``noisy``) truth, and the horizontal body velocity error ``|V_hat - V|`` with ``V =
[u, v]`` the body-frame horizontal velocity (the observer's ``eta``; the smoothers' ``world_R_body^T
world_v_body`` with their own attitude) [m/s].

Convergence time: the first time after which the error stays below the threshold until the end of
the flight ("never" if the last sample is above it). Thresholds: scale 1 % and 5 % per axis,
velocity 0.05 m/s (clean) and 0.15 m/s (noisy: an accelerometer bias ``b`` biases the observer's
velocity by ``b / (mu/m)``, ~0.1 m/s for the simulator's 0.05 m/s^2 bias spread, so 0.05 m/s is
not reachable by it). In ``noisy`` the errors are first smoothed by a trailing (causal) RMS over
``--window`` seconds (1 s) so that a single noisy sample does not reset the time. Velocity RMSE
"after convergence" is over the samples after the velocity convergence time (whole flight for the
non-causal batch).

Usage: ``python scripts/converge_circle.py [--seed 0] [--duration 40] [--variants clean noisy]
[--out out/converge_circle]``. Prints one table per variant and writes ``converge_circle.png``
and ``results.json`` to the output folder.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from fgnav.datasets.simulate import SimOptions, simulate
from fgnav.datasets.types import Flight, Trajectory

from fgnav.frontends.ii_observer import IIObserverOptions, run_ii_observer
from fgnav.solvers.batch import BatchOptions, solve_batch
from fgnav.solvers.fixed_lag import FixedLagOptions, run_fixed_lag
from fgnav.solvers.graph import GraphOptions

log = logging.getLogger("converge_circle")

#: Per-axis scale relative-error thresholds [-].
SCALE_THRESHOLDS = (0.01, 0.05)
#: Velocity-error thresholds [m/s] per variant (see module docstring for the noisy one).
VELOCITY_THRESHOLD = {"clean": 0.05, "noisy": 0.15}
#: Trailing RMS window applied to the noisy variant's errors [s].
NOISY_WINDOW_S = 1.0
#: Prefix durations of the batch convergence curve [s] (those up to the flight's length are used).
BATCH_PREFIX_T = (
    1.0,
    1.5,
    2.0,
    3.0,
    4.0,
    5.0,
    6.0,
    8.0,
    10.0,
    12.5,
    15.0,
    20.0,
    25.0,
    30.0,
    35.0,
    40.0,
)
AXES = ("kx", "ky")
#: Suffix of the smoother rows with ``--smoother-gyro``.
GYRO_SUFFIX = " +gyro"


@dataclass
class Curve:
    """Error histories of one method.

    Attributes:
        method: row name; causal: whether each value uses only data up to its time.
        t_scale: (M,) [s]; scale_rel: (M, 2) per-axis scale relative error (absolute value).
        t_vel: (N,) [s]; vel_err: (N,) horizontal body velocity error norm [m/s].
        scale_final: (2,) last per-axis scale estimate [SLAM units per metre].
        runtime_s: wall time of the method [s]; note: free text for the table footnotes.
    """

    method: str
    causal: bool
    t_scale: np.ndarray
    scale_rel: np.ndarray
    t_vel: np.ndarray
    vel_err: np.ndarray
    scale_final: np.ndarray
    runtime_s: float = 0.0
    note: str = ""
    info: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# Truth
# ---------------------------------------------------------------------------------------------


def truth_axis_scale(flight: Flight, t: np.ndarray) -> np.ndarray:
    """(N, 2) true ``kx, ky`` at times ``t`` (the simulator's linear drift within the session)."""
    s = flight.meta["truth"]["slam_sessions"]["0"]
    t = np.asarray(t, float)
    return (
        np.asarray(s["axis_scale"][:2], float)
        * (1.0 + s["scale_drift_per_s"] * (t - s["t_start"]))[:, None]
    )


def body_vxy(traj: Trajectory) -> np.ndarray:
    """(N, 2) horizontal body velocity ``[u, v]`` = first two rows of ``world_R_body^T v``."""
    return np.einsum("nji,nj->ni", traj.world_R_body(), traj.world_v_body)[:, :2]


def truth_body_vxy(flight: Flight, t: np.ndarray) -> np.ndarray:
    """(N, 2) true ``[u, v]`` interpolated at ``t`` [m/s]."""
    gt = flight.ground_truth
    v = body_vxy(gt)
    return np.column_stack([np.interp(t, gt.t, v[:, i]) for i in range(2)])


# ---------------------------------------------------------------------------------------------
# Methods
# ---------------------------------------------------------------------------------------------


def seed000_graph_options(use_gyro: bool = False) -> GraphOptions:
    """Seed 000's sensor set for the smoothers: accelerometer (+ drag) + attitude + per-axis SLAM
    (``use_gyro``: also the gyro, outside seed 000's set; a diagnostic)."""
    return GraphOptions(
        use_gyro=use_gyro,
        use_range=False,
        use_yaw=False,
        use_homography=False,
        slam_model="axis",
    )


def run_observer(flight: Flight, kinematics: str) -> Curve:
    drag = tuple(flight.meta["truth"]["drag_k"][:2])
    t0 = time.perf_counter()
    res = run_ii_observer(flight, IIObserverOptions(kinematics=kinematics, drag_k=drag))
    runtime = time.perf_counter() - t0
    ok = np.all(np.isfinite(res.xi), axis=1)
    K = truth_axis_scale(flight, res.t[ok])
    return Curve(
        method=f"ii-observer ({kinematics})",
        causal=True,
        t_scale=res.t[ok],
        scale_rel=np.abs(res.xi[ok] - K) / K,
        t_vel=res.t,
        vel_err=np.linalg.norm(res.eta - truth_body_vxy(flight, res.t), axis=1),
        scale_final=res.xi[ok][-1],
        runtime_s=runtime,
        note="gains 7/8, K_hat(0)=0, drag given, y5 from the rangefinder",
    )


def run_fixed_lag_curve(flight: Flight, graph: GraphOptions) -> Curve:
    t0 = time.perf_counter()
    est = run_fixed_lag(flight, FixedLagOptions(graph=graph, slow_read_every=1))
    runtime = time.perf_counter() - t0
    traj = est.trajectory
    s = est.series.get("slam_axis_scale")
    if s is None or len(s.t) == 0:
        t_s, k = np.zeros(0), np.zeros((0, 2))
    else:
        t_s, k = np.asarray(s.t, float), np.asarray(s.value, float).reshape(len(s.t), -1)[:, :2]
    K = truth_axis_scale(flight, t_s)
    dropped = est.info.get("dropped", {})
    return Curve(
        method="fixed-lag",
        causal=True,
        t_scale=t_s,
        scale_rel=np.abs(k - K) / K if len(t_s) else np.zeros((0, 2)),
        t_vel=traj.t,
        vel_err=np.linalg.norm(body_vxy(traj) - truth_body_vxy(flight, traj.t), axis=1),
        scale_final=k[-1] if len(t_s) else np.full(2, np.nan),
        runtime_s=runtime,
        note="lag 2 s, drag estimated",
        info={
            "solver_failures": est.info.get("solver_failures"),
            "slam_before_scale_init": int(dropped.get("slam:before-scale-init", 0)),
            "drag_k": _rounded(est.drag_k),
        },
    )


def _rounded(x, digits: int = 4) -> list[float] | None:
    return None if x is None else [round(float(v), digits) for v in np.ravel(x)]


def crop(flight: Flight, t1: float) -> Flight:
    """The flight's streams (and ground truth) up to time ``t1`` [s]."""
    changes = {}
    for name in ("imu", "attitude", "range", "yaw", "slam", "images", "ground_truth"):
        s = getattr(flight, name)
        if s is not None:
            changes[name] = s.between(-math.inf, t1)
    return dataclasses.replace(flight, **changes)


def solve_batch_xy(flight: Flight, graph: GraphOptions):
    """Batch smoother: (estimate, per-axis scale (2,), runtime [s])."""
    t0 = time.perf_counter()
    est = solve_batch(flight, BatchOptions(graph=graph, covariance="none"))
    k = np.asarray(est.series["slam_axis_scale"].value, float).reshape(-1)[:2]
    return est, k, time.perf_counter() - t0


def run_batch_full(flight: Flight, graph: GraphOptions) -> Curve:
    est, k, runtime = solve_batch_xy(flight, graph)
    traj = est.trajectory
    t_end = np.array([traj.t[-1]])
    K = truth_axis_scale(flight, t_end)
    return Curve(
        method="batch (whole flight)",
        causal=False,
        t_scale=t_end,
        scale_rel=np.abs(k[None, :] - K) / K,
        t_vel=traj.t,
        vel_err=np.linalg.norm(body_vxy(traj) - truth_body_vxy(flight, traj.t), axis=1),
        scale_final=k,
        runtime_s=runtime,
        note="one constant scale for the flight; smoothed velocity",
        info={"drag_k": _rounded(est.drag_k), "lm_iterations": est.info.get("lm_iterations")},
    )


def run_batch_prefixes(flight: Flight, graph: GraphOptions, t_grid: list[float]) -> Curve:
    """Batch on ``[0, T]`` for each ``T``: scale and newest velocity at ``T``. A failed solve (too
    little motion for the closed-form initial scale) counts as not converged (error inf)."""
    t_out, rel, verr, k_last, runtime, failed = [], [], [], np.full(2, np.nan), 0.0, []
    for T in t_grid:
        sub = crop(flight, flight.imu.t[0] + T)
        try:
            est, k, rt = solve_batch_xy(sub, graph)
        except Exception as e:  # noqa: BLE001 -- any solver failure is a non-converged point
            log.warning("batch on [0, %g] s failed: %s", T, e)
            failed.append(T)
            t_out.append(T)
            rel.append(np.full(2, np.inf))
            verr.append(np.inf)
            continue
        runtime += rt
        traj = est.trajectory
        t_T = np.array([traj.t[-1]])
        K = truth_axis_scale(flight, t_T)[0]
        t_out.append(float(t_T[0]))
        rel.append(np.abs(k - K) / K)
        verr.append(float(np.linalg.norm(body_vxy(traj)[-1] - truth_body_vxy(flight, t_T)[0])))
        k_last = k
    t_arr = np.asarray(t_out, float)
    return Curve(
        method="batch[0,T]",
        causal=True,
        t_scale=t_arr,
        scale_rel=np.asarray(rel, float).reshape(-1, 2),
        t_vel=t_arr.copy(),
        vel_err=np.asarray(verr, float),
        scale_final=k_last,
        runtime_s=runtime,
        note=f"re-solved on prefixes T = {', '.join(f'{x:g}' for x in t_grid)} s; newest state",
        info={
            "failed_prefixes": failed,
            "prefix_scale_rel_pct": {
                f"{T:g}": _rounded(100 * r, 2) for T, r in zip(t_grid, rel, strict=True)
            },
        },
    )


# ---------------------------------------------------------------------------------------------
# Convergence
# ---------------------------------------------------------------------------------------------


def trailing_rms(t: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """RMS of ``x`` over ``(t_i - window_s, t_i]`` for each i (causal)."""
    x = np.asarray(x, float)
    if window_s <= 0 or len(t) == 0:
        return np.abs(x)
    c = np.concatenate([[0.0], np.cumsum(x * x)])
    lo = np.searchsorted(t, t - window_s, side="right")
    n = np.arange(1, len(t) + 1) - lo
    return np.sqrt((c[1:] - c[lo]) / n)


def convergence_time(t: np.ndarray, err: np.ndarray, threshold: float) -> float:
    """First time after which ``err < threshold`` holds to the end (inf: never; NaN counts as
    above)."""
    if len(t) == 0:
        return math.inf
    bad = ~(np.asarray(err) < threshold)
    if bad[-1]:
        return math.inf
    idx = np.flatnonzero(bad)
    return float(t[0] if idx.size == 0 else t[idx[-1] + 1])


def processed(c: Curve, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Scale relative errors (M, 2) and velocity errors (N,) smoothed by a trailing RMS over
    ``window_s`` (0: as they are). The batch[0,T] points are separate solves: never smoothed."""
    w = 0.0 if c.method.startswith("batch[0,T]") else window_s
    rel = np.column_stack([trailing_rms(c.t_scale, c.scale_rel[:, i], w) for i in range(2)])
    return rel.reshape(-1, 2), trailing_rms(c.t_vel, c.vel_err, w)


def summarise(c: Curve, v_thr: float, window_s: float) -> dict:
    """Convergence times and final errors of one curve (errors smoothed by ``window_s``)."""
    rel, verr = processed(c, window_s)
    row: dict = {"method": c.method, "causal": c.causal, "note": c.note, "runtime_s": c.runtime_s}
    row["scale_final"] = [float(x) for x in c.scale_final]
    row["scale_rel_final"] = [float(x) for x in rel[-1]] if len(rel) else [math.nan] * 2
    row["vel_err_final"] = float(verr[-1]) if len(verr) else math.nan
    if c.causal:
        for thr in SCALE_THRESHOLDS:
            for i, ax in enumerate(AXES):
                row[f"t_{ax}_{thr:g}"] = convergence_time(c.t_scale, rel[:, i], thr)
        t_v = convergence_time(c.t_vel, verr, v_thr)
        row["t_vel"] = t_v
        after = c.t_vel >= t_v
        row["vel_rmse_after"] = (
            float(np.sqrt(np.mean(c.vel_err[after] ** 2))) if after.any() else math.nan
        )
    else:
        row["vel_rmse_after"] = float(np.sqrt(np.mean(c.vel_err**2)))
    row.update(c.info)
    return row


def _fmt_t(x) -> str:
    if x is None:
        return "n/a"
    return "never" if not math.isfinite(x) else f"{x:.2f}"


def _fmt_v(x) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.3f}"


def format_table(rows: list[dict], v_thr: float) -> str:
    head = (
        f"| method | causal | t kx<1% | t ky<1% | t kx<5% | t ky<5% | t |V~|<{v_thr:g} | "
        "final kx err | final ky err | final |V~| | V RMSE after conv. | runtime |"
    )
    lines = [head, "|:--|:--|" + "--:|" * 10]
    for r in rows:
        ts = [_fmt_t(r.get(f"t_{ax}_{thr:g}")) for thr in SCALE_THRESHOLDS for ax in AXES]
        lines.append(
            f"| {r['method']} | {'yes' if r['causal'] else 'no'} | "
            + " | ".join(ts)
            + f" | {_fmt_t(r.get('t_vel'))} | {100 * r['scale_rel_final'][0]:.2f} % | "
            f"{100 * r['scale_rel_final'][1]:.2f} % | {_fmt_v(r['vel_err_final'])} | "
            f"{_fmt_v(r['vel_rmse_after'])} | {r['runtime_s']:.1f} s |"
        )
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------------------------


def run_variant(
    variant: str,
    seed: int,
    duration: float | None,
    prefix_grid: list[float],
    window_s: float,
    smoother_gyro: bool = False,
) -> tuple[list[Curve], list[dict], float, float]:
    """Simulate and run every method on one variant: (curves, table rows, v threshold, window)."""
    if variant == "clean":
        opts = SimOptions(noise_free=True, images=False, slam_scale_drift_per_s=0.0)
        w = 0.0
    elif variant == "noisy":
        opts = SimOptions(images=False)
        w = window_s
    else:
        raise ValueError(f"unknown variant {variant!r}: expected clean or noisy")
    if duration is not None:
        opts = dataclasses.replace(opts, duration=duration)
    flight = simulate("circle", seed, opts)
    t_len = float(flight.imu.t[-1] - flight.imu.t[0])
    grid = [T for T in prefix_grid if T <= t_len + 1e-9]
    graph = seed000_graph_options(smoother_gyro)
    curves = [run_observer(flight, kin) for kin in ("published", "full")]
    curves.append(run_fixed_lag_curve(flight, graph))
    full = run_batch_full(flight, graph)
    if grid:
        curves.append(run_batch_prefixes(flight, graph, grid))
    curves.append(full)
    if smoother_gyro:
        for c in curves[2:]:
            c.method += GYRO_SUFFIX
    v_thr = VELOCITY_THRESHOLD[variant]
    rows = [summarise(c, v_thr, w) for c in curves]
    return curves, rows, v_thr, w


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = list(results)
    style = {
        "ii-observer (published)": dict(color="tab:red", lw=1.0),
        "ii-observer (full)": dict(color="tab:orange", lw=1.0),
        "fixed-lag": dict(color="tab:blue", lw=1.0),
        "batch[0,T]": dict(color="k", marker="o", ms=4, lw=1.0),
        "batch (whole flight)": dict(color="tab:green", lw=1.0, ls="--"),
    }
    fig, axes = plt.subplots(
        3, len(variants), figsize=(6.5 * len(variants), 9), sharex=True, squeeze=False
    )
    for j, var in enumerate(variants):
        curves, rows, v_thr, w = results[var]
        for c in curves:
            st = style.get(c.method.removesuffix(GYRO_SUFFIX), {})
            rel, verr = processed(c, w)
            for i in range(2):
                ax = axes[i, j]
                if c.causal:
                    ax.semilogy(c.t_scale, 100 * np.maximum(rel[:, i], 1e-6), **st)
                else:
                    ax.axhline(100 * max(rel[0, i], 1e-6), **st)
            axes[2, j].semilogy(c.t_vel, np.maximum(verr, 1e-6), label=c.method, **st)
        for i, ax_name in enumerate(AXES):
            ax = axes[i, j]
            for thr in SCALE_THRESHOLDS:
                ax.axhline(100 * thr, color="0.5", lw=0.8, ls=":")
            ax.set_ylabel(f"|{ax_name} error| [%]")
            ax.set_ylim(1e-3, 200)
            ax.grid(True, which="major", alpha=0.4)
        ax = axes[2, j]
        ax.axhline(v_thr, color="0.5", lw=0.8, ls=":")
        ax.set_ylabel("|V - V_hat| (body u, v) [m/s]")
        ax.set_ylim(1e-4, 2)
        ax.set_xlabel("t [s]")
        ax.grid(True, which="major", alpha=0.4)
        title = "noise-free, no scale drift" if var == "clean" else "noisy sensors, scale drift"
        smooth = f"\nerrors: trailing {w:g} s RMS" if w > 0 else "\nerrors as they are"
        axes[0, j].set_title(f"circle ({title}){smooth}; dotted: thresholds", fontsize=10)
    axes[2, 0].legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _jsonable(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=None, help="flight length [s] (40)")
    ap.add_argument("--variants", nargs="+", default=["clean", "noisy"], choices=["clean", "noisy"])
    ap.add_argument(
        "--prefixes",
        type=float,
        nargs="*",
        default=list(BATCH_PREFIX_T),
        help="batch prefix lengths T [s] (none: skip the batch[0,T] curve)",
    )
    ap.add_argument("--window", type=float, default=NOISY_WINDOW_S, help="noisy RMS window [s]")
    ap.add_argument(
        "--smoother-gyro",
        action="store_true",
        help="give the smoothers the gyro too (outside seed 000's sensor set; a diagnostic)",
    )
    ap.add_argument("--out", type=Path, default=Path("out/converge_circle"))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)

    results = {}
    for var in args.variants:
        curves, rows, v_thr, w = run_variant(
            var, args.seed, args.duration, list(args.prefixes), args.window, args.smoother_gyro
        )
        results[var] = (curves, rows, v_thr, w)
        smooth = f", errors smoothed by a trailing {w:g} s RMS" if w > 0 else ""
        print(
            f"\ncircle seed {args.seed}, {var}: scale thresholds 1 %/5 % per axis, velocity "
            f"{v_thr:g} m/s{smooth}; times [s] after which the error stays below"
        )
        print(format_table(rows, v_thr))
        for r in rows:
            keys = ("solver_failures", "slam_before_scale_init", "drag_k", "lm_iterations")
            extra = {k: r[k] for k in keys if k in r}
            if r.get("failed_prefixes"):
                extra["failed_prefixes"] = r["failed_prefixes"]
            if "prefix_scale_rel_pct" in r:
                extra["|kx|,|ky| err % per T"] = r["prefix_scale_rel_pct"]
            fin = ", ".join(f"{x:.4f}" for x in r["scale_final"])
            print(
                f"  {r['method']}: final (kx, ky) = ({fin}); {r['note']}"
                + (f"; {extra}" if extra else "")
            )
    png = args.out / "converge_circle.png"
    plot(results, png)
    summary = {
        var: {"velocity_threshold": v_thr, "window_s": w, "rows": rows}
        for var, (_, rows, v_thr, w) in results.items()
    }
    (args.out / "results.json").write_text(json.dumps(_jsonable(summary), indent=1) + "\n")
    print(f"\nfigure: {png.resolve()}\nresults: {(args.out / 'results.json').resolve()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
