"""``fgnav fleet INPUTS... --out DIR``: run methods over many logged flights on Dask, one table.

Thin layer over :func:`fgnav.fleet.run_fleet`: each INPUT is a flight (anything ``fgnav info``
reads), a folder scanned recursively for flights, or a glob pattern (``'logs/**/*.ulg'``, quoted:
fgnav expands it). Without ``--scheduler`` a LocalCluster runs on this machine (loopback, one
single-threaded worker per core); with it, the same tasks run on an existing Dask cluster (``DIR``
must then be a path shared by every worker and this client). Writes ``DIR/fleet.csv``,
``fleet.json``, ``fleet.parquet`` (with pyarrow), ``fleet.md`` and, per flight and method,
``DIR/flights/<flight>-<hash>/<method>/``, and the journal ``DIR/fleet-runs.jsonl``. A rerun skips
the runs already done with the same input content and options, found in ``fleet.json`` or the
journal (``--force`` reruns them). Failed flights are rows of the table (status
``error``, ``timeout``, ``crashed``), each also printed on stderr after the run, one line
``flight (input) method: status: reason``. An input that yields no flight (a path that does
not exist, a folder without flights, a pattern that matches nothing) is an ``error`` row per
method too, and the other inputs' flights run; only when no input yields a flight is it a
one-line error (exit 1). A finished run whose estimate ``fgnav compare``
would flag implausible (:func:`fgnav.compare.plausibility_flags`) has the codes in the table's
``flag`` column and the reasons in ``flags``, one ``WARNING`` line each after the run, and the
summary line counts them. ``--scheduler`` is checked before anything runs (not empty,
``[tcp://]HOST:PORT`` or another Dask protocol this installation can use: tls, ws, wss; ucx only
with Dask's UCX support) and contacted only when a flight is to run (a rerun that reuses every
row does not): a refused connection, an unknown host or a server that is not a Dask scheduler is
then a one-line error. The exit code is 0 once the table is written, unless
every run failed: then 1 (after the table and the summary line).
"""

from __future__ import annotations

import argparse
import sys

from fgnav.commands import add_config_argument, add_out_argument
from fgnav.config import check_tables
from fgnav.methods import METHOD_TABLES, check_method_config, load_method_config

HELP = "run methods over many logged flights on Dask (local or a cluster), one table"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "inputs",
        nargs="+",
        metavar="INPUT",
        help="flight (log, manifest, flight folder), folder to scan, or quoted glob pattern",
    )
    add_out_argument(parser, "output folder (the table, per-flight runs)")
    parser.add_argument(
        "--methods",
        default="batch",
        help="comma-separated methods of `fgnav compare` (default batch)",
    )
    add_config_argument(parser, "TOML file with the per-method tables")
    parser.add_argument(
        "--scheduler", default=None, help="address of a running Dask scheduler (tcp://HOST:PORT)"
    )
    parser.add_argument(
        "--workers", type=int, default=None, help="local workers (default: one per core)"
    )
    parser.add_argument(
        "--timeout", type=float, default=None, help="wall-time limit per flight [s]"
    )
    parser.add_argument(
        "--memory-limit",
        type=float,
        default=None,
        help="address-space limit of each flight's child process [MB]",
    )
    parser.add_argument("--force", action="store_true", help="rerun flights already done")
    parser.add_argument(
        "--no-flight-files", action="store_true", help="write the table only, no per-flight files"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from fgnav.datasets.errors import FgnavError
    from fgnav.fleet import FleetOptions, check_limits, run_fleet

    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    if args.workers is not None and args.workers <= 0:
        raise FgnavError(f"--workers must be positive, got {args.workers}")
    check_limits(args.timeout, args.memory_limit)
    # The tables and their options checked here, before any worker starts (one line, exit 1).
    check_tables(args.config, list(METHOD_TABLES))
    config = load_method_config(args.config)
    check_method_config(config)
    opts = FleetOptions(
        methods=methods or ("batch",),
        config=config,
        scheduler=args.scheduler,
        workers=args.workers,
        timeout_s=args.timeout,
        memory_limit_mb=args.memory_limit,
        force=args.force,
        flight_files=not args.no_flight_files,
        progress=not args.no_progress,
    )
    res = run_fleet(args.inputs, args.out, opts)
    for line in res.failure_lines():
        print(line, file=sys.stderr)
    for line in res.flagged_lines():  # as fgnav compare warns (the numbers and exit code stay)
        print(f"WARNING {line}")
    print(res.summary_line())
    return 1 if res.all_failed() else 0
