"""``fgnav online``: run the fixed-lag smoother over a flight as if it were live.

By default (``[online] engine = "auto"``) the flight's events are replayed in arrival order into
the push-API smoother (:mod:`fgnav.solvers.online`), which sees nothing before it arrives (the
front-end priors of ``--priors`` / ``[priors]`` run inside it as a stage fed the same events);
``[online] engine = "prepared"`` runs the runner over a flight prepared as a whole
(:mod:`fgnav.solvers.fixed_lag`; not strictly causal) instead, and the run says so.

Thin layer over the ``fixed-lag`` method of :mod:`fgnav.methods` (which assembles the options and
calls :func:`fgnav.solvers.fixed_lag.run_fixed_lag`). Options come from the ``[graph]``,
``[online]`` and ``[priors]`` tables of ``--config`` (fields of
:class:`~fgnav.solvers.graph.GraphOptions` and :class:`~fgnav.solvers.fixed_lag.FixedLagOptions`);
``--lag`` overrides. A run whose estimate diverged and did not recover (health "diverged") is
written, then exits 1 with one line saying so. A native flight folder without images that the push
engine runs is read in chunks as it is replayed (:func:`fgnav.datasets.native.open_flight_streams`:
bounded memory on a long flight; the ground truth is read after the run, for scoring). Prints the
update latency (p50/p99) and how many times faster than real time the run was; scores the causal
trajectory when the flight has ground truth.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from fgnav.commands import add_config_argument, add_flight_argument, add_out_argument
from fgnav.commands.batch import add_priors_argument, method_config, score_and_write
from fgnav.config import check_tables
from fgnav.datasets.errors import FgnavError
from fgnav.eval.outputs import summary_extra
from fgnav.methods import fixed_lag_options, require_streams, run_fixed_lag

HELP = "run the online fixed-lag smoother over a flight"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_flight_argument(parser)
    add_out_argument(parser)
    parser.add_argument("--lag", type=float, default=None, help="smoother lag [s] (default 2)")
    add_config_argument(parser, "TOML file with [graph], [online] and [priors] tables")
    parser.add_argument("--keyframe-hz", type=float, default=None, help="keyframe rate [Hz]")
    add_priors_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _streams(path: str, config, opts):
    """The flight opened as streams (:func:`fgnav.datasets.native.open_flight_streams`) when it
    is a native folder without images that the push engine runs (the prepared engine reads the
    whole flight); else None (read whole)."""
    from fgnav.datasets.errors import FlightFormatError
    from fgnav.datasets.native import is_native_folder, open_flight_streams
    from fgnav.solvers.online import resolve_engine

    if not is_native_folder(path):
        return None
    try:
        source = open_flight_streams(path)
    except FlightFormatError:
        return None  # images, or a bad file: the whole read names the problem
    return source if resolve_engine(opts) == "push" else None


def run(args: argparse.Namespace) -> int:
    from fgnav.datasets.load import load_flight

    check_tables(args.config, ["graph", "online", "priors"])
    config = method_config(args, online={"lag_s": args.lag})
    opts = fixed_lag_options(config)  # option values checked before the flight is read
    source = _streams(args.flight, config, opts)
    if source is not None:
        require_streams("fixed-lag", source.outline)
        print("input: native folder read in chunks as it is replayed (bounded memory)")
        est = run_fixed_lag(source.outline, config, not args.no_progress, source=source)
        flight = source.scoring_flight()
    else:
        flight = load_flight(args.flight)
        require_streams("fixed-lag", flight)
        est = run_fixed_lag(flight, config, progress=not args.no_progress)
    lat = est.update_latency
    info = est.info
    print(
        f"online: {len(lat)} updates, latency p50 {np.percentile(lat, 50) * 1e3:.2f} ms, "
        f"p99 {np.percentile(lat, 99) * 1e3:.2f} ms, max {lat.max() * 1e3:.2f} ms, "
        f"{info['times_real_time']:.1f}x real time, {info['solver_failures']} solver failures"
    )
    if info.get("engine") == "push":
        print("engine: push (events replayed in arrival order; strictly causal)")
    elif info.get("engine"):
        print("engine: prepared (whole-flight preparation; not strictly causal)")
    if info.get("reset_counter"):
        print(f"resets: {info['reset_counter']} (state lost and re-initialised; see summary.json)")
    if info.get("factorization_fallbacks"):
        print(
            f"factorization: {info['factorization_fallbacks']} Cholesky failure(s) moved the "
            f"window to {info['factorization_final']} (nothing lost)"
        )
    if info.get("window_reorders"):
        print(
            f"window: {info['window_reorders']} full re-orderings before a marginalisation "
            f"({info['window_unordered_updates']} updates could not keep the time order; "
            "more stamp blocks than keys per update: see FixedLagOptions.marginalize_every_s)"
        )
    score_and_write(flight, est, Path(args.out), summary_extra(flight.name, est, "online"))
    if (info.get("health") or {}).get("status") == "diverged":
        # As batch's not-converged (exit 1), but written: the log of a run that went wrong.
        raise FgnavError(
            f"{flight.name}: the estimate diverged and did not recover (health: diverged; "
            f"written to {args.out} for inspection)"
        )
    return 0
