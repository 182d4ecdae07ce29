"""Subcommands of the ``fgnav`` CLI (see fgnav/cli.py)."""

from __future__ import annotations

import argparse


def nonempty_path(text: str) -> str:
    """The type of the commands' path arguments: not empty (an unset shell variable,
    ``--out "$OUT"``, would write the outputs into the current folder, and ``--calib ""`` was
    read as the folder ``.``)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path")
    return text


def out_folder(text: str) -> str:
    """``--out``'s type: a non-empty path (:func:`nonempty_path`) that is a folder or can become
    one: an existing file, or a file where a parent folder should be, failed only when the
    outputs were written, after the whole solve, with a traceback."""
    from pathlib import Path

    p = Path(nonempty_path(text))
    for q in (p, *p.parents):
        if q.exists():
            if not q.is_dir():
                what = "is" if q == p else f"is inside {q}, which is"
                raise argparse.ArgumentTypeError(f"{text!r} {what} a file, not a folder")
            break
    return text


ESTIMATE_FILES = "output folder (estimate.tum, states.csv, summary.json)"
"""``--out``'s help of the commands that write one estimate (batch, online, live)."""


def add_out_argument(parser: argparse.ArgumentParser, help: str = ESTIMATE_FILES) -> None:
    """The required ``--out`` folder (:func:`out_folder`)."""
    parser.add_argument("--out", type=out_folder, required=True, help=help)


FLIGHT_INPUT = "flight folder, manifest or log (see `fgnav info`)"
"""The positional ``flight``'s help of the commands that read one flight (batch, online, compare,
replay)."""


def add_flight_argument(parser: argparse.ArgumentParser) -> None:
    """The positional ``flight`` input (:func:`nonempty_path`)."""
    parser.add_argument("flight", type=nonempty_path, help=FLIGHT_INPUT)


def add_config_argument(parser: argparse.ArgumentParser, help: str) -> None:
    """The optional ``--config`` TOML file (:func:`nonempty_path`); ``help`` names its tables."""
    parser.add_argument("--config", type=nonempty_path, default=None, help=help)
