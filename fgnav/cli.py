"""The ``fgnav`` command line: one entry point, one module per subcommand.

Each subcommand lives in ``fgnav/commands/<name>.py`` and defines ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int``; ``run`` is a thin layer over a library call.
A subcommand whose module does not exist yet is listed and says so when called.
Known errors (:class:`fgnav.datasets.FgnavError`) print one line on stderr and exit with code 1;
Ctrl-C prints one line and exits with code 130.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from fgnav.datasets.errors import FgnavError

# name -> (module, help shown while the module is not available yet)
COMMANDS: dict[str, str] = {
    "info": "streams, rates, durations, gaps and time overlap of a flight",
    "simulate": "simulate a flight with ground truth for every sensor",
    "batch": "smooth a whole flight (batch solver)",
    "online": "run the online fixed-lag smoother over a flight",
    "compare": "run the smoothers and the filter baselines on a flight and compare them",
    "demo": "simulate a flight and run the main job on it",
    "fleet": "run methods over many logged flights on Dask (local or a cluster), one table",
    "live": "run the online estimator on a live MAVLink link (udpin:HOST:PORT)",
    "replay": "send a flight as MAVLink messages to udpout:HOST:PORT (a stand-in autopilot)",
}


def _load(name: str):
    try:
        return importlib.import_module(f"fgnav.commands.{name}")
    except ModuleNotFoundError as e:
        if e.name == f"fgnav.commands.{name}":
            return None
        raise


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, object]]:
    parser = argparse.ArgumentParser(
        prog="fgnav",
        description="Factor-graph smoothing back-end for multirotors flying without GPS.",
    )
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="more log output: -v fgnav's DEBUG lines, -vv every library's (INFO lines are printed "
        "by default)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules: dict[str, object] = {}
    for name, fallback_help in COMMANDS.items():
        mod = _load(name)
        modules[name] = mod
        if mod is None:
            p = sub.add_parser(name, help=f"{fallback_help} (not available yet)")
            p.add_argument("rest", nargs=argparse.REMAINDER)
        else:
            p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
            mod.add_arguments(p)
    return parser, modules


def log_levels(verbose: int) -> tuple[int, int | None]:
    """``(root level, level of the "fgnav" loggers or None)`` with ``verbose`` ``-v`` flags: INFO
    by default (the commands' progress and the readers' notes); ``-v``: fgnav's DEBUG lines too;
    ``-vv``: every library's (matplotlib's font search, Dask's scheduler ...). (``-v`` had been
    the default INFO, and only ``-vv`` added anything.)"""
    if verbose >= 2:
        return logging.DEBUG, None
    return logging.INFO, (logging.DEBUG if verbose == 1 else None)


def main(argv: list[str] | None = None) -> int:
    parser, modules = build_parser()
    args = parser.parse_args(argv)
    root_level, fgnav_level = log_levels(args.verbose)
    logging.basicConfig(level=root_level, format="%(levelname)s %(name)s: %(message)s")
    if fgnav_level is not None:
        logging.getLogger("fgnav").setLevel(fgnav_level)
    if args.command is None:
        parser.print_help()
        return 1
    mod = modules[args.command]
    if mod is None:
        print(f"fgnav: '{args.command}' is not available yet in this version", file=sys.stderr)
        return 1
    try:
        return int(mod.run(args) or 0)
    except FgnavError as e:
        print(f"fgnav {args.command}: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:  # (a file not found, a folder not writable, a full disk ...)
        print(f"fgnav {args.command}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as e:  # Ctrl-C: one line (a command may say what it had done)
        detail = f": {e}" if str(e) else ""
        print(f"fgnav {args.command}: interrupted{detail}", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
