"""``--config`` files: TOML tables that fill an options dataclass, flags override them."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any, TypeVar

from fgnav.datasets.errors import FlightFormatError

T = TypeVar("T")


def load_config(path: str | Path | None, section: str | None = None) -> dict[str, Any]:
    """Read a TOML config file (or ``{}`` for None); return the table ``section`` if given."""
    if path is None:
        return {}
    p = Path(path)
    if not p.is_file():
        raise FlightFormatError(p, "config file not found")
    try:
        data = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise FlightFormatError(p, f"not valid TOML: {e}") from e
    if section is None:
        return data
    table = data.get(section, {})
    if not isinstance(table, dict):
        raise FlightFormatError(p, f"[{section}] must be a table")
    return table


def options_from(cls: type[T], table: dict[str, Any], source: str = "config", **overrides) -> T:
    """Build options dataclass ``cls`` from a config table plus non-None overrides.

    Unknown keys raise an error naming them and listing the valid ones.
    """
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - names)
    if unknown:
        raise FlightFormatError(
            source, f"unknown option(s) {unknown} for {cls.__name__}; valid: {sorted(names)}"
        )
    kwargs = dict(table)
    kwargs.update({k: v for k, v in overrides.items() if v is not None})
    return cls(**kwargs)
