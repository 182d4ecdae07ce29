"""Subcommands of the ``fgnav`` CLI (see fgnav/cli.py)."""

from __future__ import annotations

import argparse


def out_folder(text: str) -> str:
    """``--out``'s type: a folder path, not empty (an unset shell variable, ``--out "$OUT"``,
    would otherwise write the outputs into the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path: name the output folder")
    return text


ESTIMATE_FILES = "output folder (estimate.tum, states.csv, summary.json)"
"""``--out``'s help of the commands that write one estimate (batch, online, live)."""


def add_out_argument(parser: argparse.ArgumentParser, help: str = ESTIMATE_FILES) -> None:
    """The required ``--out`` folder (:func:`out_folder`)."""
    parser.add_argument("--out", type=out_folder, required=True, help=help)
