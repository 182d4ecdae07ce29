"""``fgnav demo``: simulate a flight, smooth it (batch and fixed-lag) and compare every method.

A real run, nothing canned: (1) :func:`fgnav.datasets.simulate.simulate_to_folder` writes the
scenario's flight to ``DIR/flight``, read back with :func:`fgnav.datasets.load.load_flight`;
(2) the batch smoother and (3) the fixed-lag smoother run on it and their metrics are printed;
(4) :func:`fgnav.compare.compare` runs every other method the flight allows (reusing the two
smoother estimates) and writes ``DIR/report.md``, ``DIR/compare.json``, the figures and each
method's outputs. The wall time of every stage is printed. ``make demo`` runs it.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from fgnav.commands import add_config_argument, out_folder
from fgnav.commands.compare import parse_methods, print_result
from fgnav.compare import CompareResult, MethodRun, compare
from fgnav.config import check_tables, load_config, options_from
from fgnav.datasets.simulate import SCENARIOS, SimOptions
from fgnav.methods import METHOD_TABLES, check_method_config

HELP = "simulate a flight and run the main job on it"

log = logging.getLogger(__name__)

#: The two smoothers run (and reported) before the comparison.
SMOOTHERS = ("batch", "fixed-lag")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out", type=out_folder, default="out/demo", help="output folder (default out/demo)"
    )
    parser.add_argument("--scenario", default="two-turns", choices=SCENARIOS, help="flight plan")
    parser.add_argument("--seed", type=int, default=1, help="simulator seed (default 1)")
    parser.add_argument("--duration", type=float, default=None, help="flight length [s]")
    parser.add_argument(
        "--no-images", action="store_true", help="no camera images (seed 002's VO is skipped)"
    )
    parser.add_argument(
        "--methods",
        default=None,
        help="comma-separated methods (default: every method the flight allows)",
    )
    add_config_argument(parser, "TOML file: [simulate] and the per-method tables")
    parser.add_argument("--no-figures", action="store_true", help="do not draw the PNG figures")


def _print_smoother(run: MethodRun) -> None:
    name = run.method.name
    if not run.ok:
        print(f"{name}: FAILED: {run.error}")
        return
    est = run.estimate
    print(f"{name}: {len(est.trajectory)} states in {est.runtime_s:.2f} s")
    m = run.metrics
    if m is not None:
        print(
            f"  ATE {m.ate_rmse_m:.4f} m RMSE ({m.alignment} alignment), RPE {m.rpe_pct:.2f} %, "
            f"velocity RMSE {m.vel_rmse_mps:.4f} m/s, yaw RMSE {m.yaw_rmse_deg:.3f} deg"
        )
        for sid, err in sorted(m.scale_final_err_pct.items()):
            print(f"  SLAM session {sid}: scale {est.slam_scale[sid]:.5g}, error {err:+.2f} %")
        if m.latency_p50_s == m.latency_p50_s:
            print(
                f"  update latency p50 {m.latency_p50_ms:.2f} ms, p99 {m.latency_p99_ms:.2f} ms, "
                f"{m.times_real_time:.1f}x real time"
            )
    if est.drag_k is not None:
        print(f"  drag k {[round(float(k), 4) for k in est.drag_k]} 1/s")


def run(args: argparse.Namespace) -> int:
    from fgnav.datasets.load import load_flight
    from fgnav.datasets.simulate import simulate_to_folder

    out = Path(args.out)
    check_tables(args.config, ["simulate", *METHOD_TABLES])
    config = load_config(args.config)
    sim_opts = options_from(
        SimOptions,
        config.get("simulate", {}),
        source=str(args.config or "flags"),
        section="simulate",
        duration=args.duration,
        images=False if args.no_images else None,
    )
    methods = parse_methods(args.methods)
    method_config = {k: v for k, v in config.items() if k != "simulate"}
    check_method_config(method_config)
    stages: dict[str, float] = {}
    t_all = time.perf_counter()

    t0 = time.perf_counter()
    print(f"[1/4] simulating {args.scenario} (seed {args.seed}) -> {out / 'flight'}")
    folder = simulate_to_folder(
        args.scenario,
        out / "flight",
        seed=args.seed,
        options=sim_opts,
        progress=True,
        overwrite=True,
    )
    flight = load_flight(folder)
    stages["simulate"] = time.perf_counter() - t0
    streams = ", ".join(f"{k} {len(v)}" for k, v in flight.streams().items())
    print(f"      {flight.name}: {streams} ({stages['simulate']:.1f} s)")

    reused = {}
    for i, name in enumerate(SMOOTHERS, start=2):
        if methods is not None and name not in methods:
            print(f"[{i}/4] {name}: not requested (--methods)")
            continue
        t0 = time.perf_counter()
        print(f"[{i}/4] {name} smoother")
        res = compare(flight, methods=[name], config=method_config, progress=True)
        stages[name] = time.perf_counter() - t0
        for skipped, reason in res.skipped.items():
            print(f"{skipped}: skipped: {reason}")
        for r in res.runs.values():
            _print_smoother(r)
            if r.ok:
                reused[name] = r.estimate
        print(f"      ({stages[name]:.1f} s)")

    t0 = time.perf_counter()
    print("[4/4] comparing methods")
    result: CompareResult = compare(
        flight, methods=methods, config=method_config, progress=True, estimates=reused
    )
    paths = result.write(out, figures=not args.no_figures)
    stages["compare"] = time.perf_counter() - t0
    print_result(result, out, paths)
    stages["total"] = time.perf_counter() - t_all
    print("wall time: " + ", ".join(f"{k} {v:.1f} s" for k, v in stages.items()))
    return 0
