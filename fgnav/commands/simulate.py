"""``fgnav simulate``: write a simulated flight (sensors + ground truth) as a native folder.

Thin layer over :func:`fgnav.datasets.simulate.simulate_to_folder`. Options come from the
``[simulate]`` table of ``--config`` (fields of :class:`~fgnav.datasets.simulate.SimOptions`);
flags override them.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from fgnav.commands import add_config_argument, add_out_argument
from fgnav.config import load_config, options_from
from fgnav.datasets.errors import FlightFormatError
from fgnav.datasets.simulate import SCENARIOS, SimOptions, simulate_to_folder

HELP = "simulate a flight with ground truth for every sensor"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, choices=SCENARIOS, help="flight plan")
    add_out_argument(parser, "flight folder to write")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random draw")
    parser.add_argument("--duration", type=float, default=None, help="flight length [s]")
    parser.add_argument(
        "--no-images", action="store_true", help="do not render downward-camera images"
    )
    add_config_argument(parser, "TOML file with a [simulate] table of SimOptions fields")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an existing flight folder"
    )


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not args.overwrite:
        raise FlightFormatError(out, "output exists and is not an empty folder (pass --overwrite)")
    table = load_config(args.config, "simulate")
    opts = options_from(
        SimOptions,
        table,
        source=str(args.config or "flags"),
        section="simulate",
        duration=args.duration,
        images=False if args.no_images else None,
    )
    folder = simulate_to_folder(
        args.scenario,
        args.out,
        seed=args.seed,
        options=opts,
        progress=True,
        overwrite=args.overwrite,
    )
    log.info("simulated %s (seed %d) -> %s", args.scenario, args.seed, folder)
    return 0
