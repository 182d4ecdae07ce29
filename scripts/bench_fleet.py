"""Benchmark ``fgnav fleet``: speed-up from 1 to 2 workers and the fleet's per-flight overhead.

Simulates ``--flights`` flights of ``--duration`` s (no images; kept in ``--data`` and reused),
then runs the batch smoother over them with :func:`fgnav.fleet.run_fleet` on a LocalCluster of 1
and of 2 workers (``--force``: every flight runs). Printed:

- ``tasks_s``: first submission to last result (the LocalCluster's start-up is printed apart);
  speed-up = tasks_s(1 worker) / tasks_s(2 workers).
- per-flight overhead of the fleet machinery with 1 worker (flights run one after another):
  ``(tasks_s - sum(work_s)) / n``, where ``work_s`` is the child's own work (loading the flight,
  running, scoring and writing the method, imports of the method's modules included); split
  into the child interpreter (start, fgnav imports, JSON: ``task_wall_s - work_s``) and Dask
  (submission, scheduling, result gathering: the rest).

Usage: ``.venv/bin/python scripts/bench_fleet.py [--flights 8] [--duration 60] [--data DIR]``
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from fgnav.datasets.simulate import SimOptions, simulate_to_folder

from fgnav.fleet import FleetOptions, run_fleet

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ("two-turns", "circle")


def make_flights(data: Path, n: int, duration: float) -> list[Path]:
    """``n`` simulated flights in ``data`` (reused when present)."""
    out = []
    for i in range(n):
        scenario = SCENARIOS[i % len(SCENARIOS)]
        folder = data / f"{scenario}-{duration:g}s-seed{i + 1}"
        if not (folder / "meta.json").is_file():
            opts = SimOptions(duration=duration, images=False)
            simulate_to_folder(scenario, folder, seed=i + 1, options=opts, overwrite=True)
        out.append(folder)
    return out


def run(flights: list[Path], out: Path, workers: int) -> dict[str, float]:
    opts = FleetOptions(workers=workers, force=True, progress=False)
    res = run_fleet([str(f) for f in flights], out / f"workers{workers}", opts)
    bad = [r for r in res.rows if r["status"] != "ok"]
    if bad:
        raise SystemExit(f"failed runs: {[(r['flight'], r['reason']) for r in bad]}")
    n = len(res.rows)
    work = sum(r["work_s"] for r in res.rows)
    child = statistics.mean(r["task_wall_s"] - r["work_s"] for r in res.rows)
    figures = {
        "workers": res.workers,
        "startup_s": res.startup_s,
        "tasks_s": res.tasks_s,
        "sum_work_s": work,
        "sum_runtime_s": sum(r["runtime_s"] for r in res.rows),
        "overhead_per_flight_s": (res.tasks_s * res.workers - work) / n,
        "child_per_flight_s": child,
    }
    print(
        f"{res.workers} worker(s): cluster start {res.startup_s:.2f} s, tasks {res.tasks_s:.2f} s "
        f"for {n} flights (sum of child work {work:.2f} s, of method run time "
        f"{figures['sum_runtime_s']:.2f} s)"
    )
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", type=int, default=8)
    ap.add_argument("--duration", type=float, default=60.0, help="flight length [s]")
    ap.add_argument("--data", type=Path, default=ROOT / "out" / "bench_fleet" / "flights")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench_fleet")
    args = ap.parse_args()
    t0 = time.perf_counter()
    flights = make_flights(args.data, args.flights, args.duration)
    took = time.perf_counter() - t0
    print(f"{len(flights)} simulated flights of {args.duration:g} s ({took:.1f} s)")
    one = run(flights, args.out, 1)
    two = run(flights, args.out, 2)
    print(f"speed-up 1 -> 2 workers: {one['tasks_s'] / two['tasks_s']:.2f}x (goal >= 1.7x)")
    print(
        f"fleet overhead per flight (1 worker): {one['overhead_per_flight_s']:.3f} s "
        f"(goal < 1.5 s): child interpreter {one['child_per_flight_s']:.3f} s, Dask "
        f"{one['overhead_per_flight_s'] - one['child_per_flight_s']:.3f} s"
    )
    print(
        f"with 2 workers: {two['overhead_per_flight_s']:.3f} s per flight "
        f"(worker-seconds not spent in child work / flights)"
    )


if __name__ == "__main__":
    main()
