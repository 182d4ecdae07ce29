"""Reading a whole TOML or YAML file, and its values, with the one-line errors of
:mod:`fgnav.datasets.errors`."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import yaml

from .errors import FlightFormatError


def existing_file(path: str | Path, what: str = "file") -> Path:
    """``path`` as a :class:`Path`; a one-line error when it does not exist or is not a file
    (a folder given for a file was reported as not found)."""
    p = Path(path)
    if not p.exists():
        raise FlightFormatError(p, f"{what} not found")
    if not p.is_file():
        raise FlightFormatError(p, f"is {'a folder' if p.is_dir() else 'not a file'}, not a {what}")
    return p


def read_toml(path: str | Path, what: str = "file") -> dict[str, Any]:
    """The TOML document at ``path``; a missing ``what`` or bad TOML is a one-line
    :class:`FlightFormatError` naming the file (and, from tomllib, the line and column)."""
    p = existing_file(path, what)
    try:
        return tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise FlightFormatError(p, f"not valid TOML: {e}") from e


def read_yaml(path: str | Path, what: str = "file") -> Any:
    """The YAML document at ``path`` (``yaml.safe_load``), with the errors of :func:`read_toml`."""
    p = existing_file(path, what)
    try:
        return yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise FlightFormatError(p, f"not valid YAML: {e}") from e


def file_number(value: Any, key: str, path: Path) -> float:
    """A value read from a file as a float, or an error naming the file and ``key``."""
    try:
        return float(value)
    except (TypeError, ValueError):
        raise FlightFormatError(path, f"{key}: expected a number, found {value!r}") from None
