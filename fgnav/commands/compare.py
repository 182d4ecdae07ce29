"""``fgnav compare``: run the smoothers and the filter baselines on a flight and compare them.

Thin layer over :func:`fgnav.compare.compare`. ``--config`` is a TOML file whose tables configure
the methods (``[graph]``, ``[lm]``, ``[batch]``, ``[online]``, ``[msf-ekf]``, ``[ekf004]`` ...,
see :mod:`fgnav.methods`). Prints the comparison table, the methods skipped (with the stream each
misses) or failed (with the error), a ``WARNING`` line per implausible estimate (the row's
``flag``, :func:`fgnav.compare.plausibility_flags`), and where ``report.md`` and ``compare.json``
are. The exit code is 0 when at least one method produced an estimate (others may have failed or
been skipped, estimates may be flagged), 1 when none did (after the table and files, with a
one-line summary on stderr) or on an error.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

from fgnav.commands import add_config_argument, add_flight_argument, add_out_argument
from fgnav.compare import CompareResult, compare
from fgnav.config import check_tables
from fgnav.coverage import compare_lines
from fgnav.methods import (
    METHOD_TABLES,
    METHODS,
    MethodUnavailableError,
    check_method_config,
    load_method_config,
)

HELP = "run the smoothers and the filter baselines on a flight and compare them"


def parse_methods(text: str | None) -> list[str] | None:
    """``"a,b"`` -> ``["a", "b"]`` (None: all methods the flight allows). A name given twice is
    kept once, at its first place (as ``fgnav fleet`` does; :func:`repeated_methods` names them).

    Raises:
        MethodUnavailableError: a name that is neither a method nor ``ref:<reference>``, or no
            name at all (``--methods ""``), before the flight is read (the flight's references
            are checked once it is).
    """
    if text is None:
        return None
    names = [m.strip() for m in text.split(",") if m.strip()]
    if not names:
        raise MethodUnavailableError(
            f"--methods {text!r}: no method named; valid: {', '.join(METHODS)}, "
            "ref:<reference of the flight>"
        )
    for m in names:
        if m not in METHODS and not m.startswith("ref:"):
            raise MethodUnavailableError(
                f"unknown method {m!r}; valid: {', '.join(METHODS)}, ref:<reference of the flight>"
            )
    return list(dict.fromkeys(names))


def repeated_methods(text: str | None) -> dict[str, int]:
    """``{name: count}`` of the names ``--methods`` gives more than once."""
    names = [m.strip() for m in (text or "").split(",") if m.strip()]
    return {m: n for m, n in Counter(names).items() if n > 1}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_flight_argument(parser)
    add_out_argument(parser, "output folder (report.md, compare.json)")
    parser.add_argument(
        "--methods",
        default=None,
        help="comma-separated methods (default: all the flight allows; known: "
        + ", ".join(METHODS)
        + ", ref:NAME for a reference trajectory the flight carries)",
    )
    add_config_argument(parser, "TOML file with per-method tables")
    parser.add_argument("--no-figures", action="store_true", help="do not draw the PNG figures")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def print_result(result: CompareResult, out: Path, paths: dict[str, Path]) -> None:
    """Print the table, skipped and failed methods, implausible estimates, and the files."""
    print(result.table())
    runs = {n: r.estimate for n, r in result.runs.items() if r.estimate is not None}
    for line in compare_lines(result.flight, runs):
        print(line)
    only = [n for n, r in result.runs.items() if r.ok and r.method.positions_only]
    if only and result.flight.ground_truth is not None:
        print(f"{', '.join(only)}: scored on positions only (RPE, yaw RMSE and NEES left out)")
    for name, reason in result.skipped.items():
        print(f"skipped {name}: {reason}")
    for name, error in result.failed.items():
        print(f"FAILED {name}: {error}")
    for name, r in result.runs.items():
        if r.flags:
            reasons = "; ".join(f["reason"] for f in r.flags)
            print(f"WARNING {name}: implausible estimate: {reasons}")
    if result.flight.ground_truth is None:
        print("no ground truth in this flight: accuracy columns are empty")
    print(f"report: {paths['report']}")
    print(f"metrics: {paths['json']}")


def run(args: argparse.Namespace) -> int:
    from fgnav.datasets.load import load_flight

    check_tables(args.config, list(METHOD_TABLES))
    config = load_method_config(args.config)
    check_method_config(config)
    methods = parse_methods(args.methods)
    for name, n in repeated_methods(args.methods).items():
        print(
            f"fgnav compare: note: --methods names {name} {n} times; it runs once", file=sys.stderr
        )
    flight = load_flight(args.flight)
    result = compare(
        flight,
        methods=methods,
        config=config,
        progress=not args.no_progress,
    )
    out = Path(args.out)
    paths = result.write(out, figures=not args.no_figures)
    print_result(result, out, paths)
    if not any(r.ok for r in result.runs.values()):  # (as fgnav fleet when every run failed)
        print(f"fgnav compare: {no_result_summary(result)}", file=sys.stderr)
        return 1
    return 0


def no_result_summary(result: CompareResult) -> str:
    """The one line of a comparison in which no method produced an estimate."""
    failed, skipped = len(result.failed), len(result.skipped)
    return (
        f"no method produced a result ({failed} failed, {skipped} skipped"
        + ("; see the lines above" if failed or skipped else "")
        + ")"
    )
