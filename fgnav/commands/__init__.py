"""Subcommands of the ``fgnav`` CLI (see fgnav/cli.py)."""

from __future__ import annotations

import argparse


def out_folder(text: str) -> str:
    """``--out``'s type: a folder path, not empty (an unset shell variable, ``--out "$OUT"``,
    would otherwise write the outputs into the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path: name the output folder")
    return text
