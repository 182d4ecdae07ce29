"""Reading a whole TOML or YAML file, and its values, with the one-line errors of
:mod:`fgnav.datasets.errors`."""

from __future__ import annotations

import math
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


def resolved(path: Path, owner: str | Path, what: str, line: int | None = None) -> Path:
    """``path.resolve()``; a path that cannot be resolved (a symbolic link loop: RuntimeError
    before Python 3.13, OSError after) is a one-line :class:`FlightFormatError` naming the file
    ``owner`` that gave it, ``what`` (its key or field) and the path."""
    try:
        return path.resolve()
    except (RuntimeError, OSError) as e:
        why = "a symbolic link loop" if "loop" in str(e).lower() else str(e)
        raise FlightFormatError(
            owner, f"{what}: cannot resolve {path} ({why})", line=line
        ) from None


def read_text(path: str | Path, what: str = "file") -> str:
    """The text of the file ``path`` (UTF-8); a missing file or one that is not text (a binary
    file given as a config or calibration: a UnicodeDecodeError) is a one-line
    :class:`FlightFormatError` naming it."""
    p = existing_file(path, what)
    try:
        return p.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise FlightFormatError(
            p, f"not a text {what}: byte {e.start} is not UTF-8 ({e.reason})"
        ) from None
    except OSError as e:
        raise FlightFormatError(p, f"cannot read the {what}: {e.strerror or e}") from None


def yaml_error(path: str | Path, e: yaml.YAMLError) -> FlightFormatError:
    """YAML error ``e`` of the file ``path`` as one line: file:line, column and the problem
    (PyYAML's own message is four lines with a copy of the text and a caret)."""
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    problem = getattr(e, "problem", None) or str(e).splitlines()[0]
    context = getattr(e, "context", None)
    where = f", column {mark.column + 1}" if mark is not None else ""
    msg = f"not valid YAML{where}: {problem}" + (f" ({context})" if context else "")
    return FlightFormatError(path, " ".join(msg.split()), line=mark.line + 1 if mark else None)


def read_toml(path: str | Path, what: str = "file") -> dict[str, Any]:
    """The TOML document at ``path``; a missing ``what``, a file that is not text or bad TOML is
    a one-line :class:`FlightFormatError` naming the file (and, from tomllib, the line and
    column)."""
    p = existing_file(path, what)
    text = read_text(p, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise FlightFormatError(p, f"not valid TOML: {e}") from e


def read_yaml(path: str | Path, what: str = "file") -> Any:
    """The YAML document at ``path`` (``yaml.safe_load``), with the errors of :func:`read_toml`
    (a YAML error on one line: :func:`yaml_error`)."""
    p = existing_file(path, what)
    text = read_text(p, what)
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise yaml_error(p, e) from None


def file_number(value: Any, key: str, path: Path) -> float:
    """A value read from a file as a float, or an error naming the file and ``key``."""
    try:
        return float(value)
    except (TypeError, ValueError):
        raise FlightFormatError(path, f"{key}: expected a number, found {value!r}") from None


def file_count(value: Any, key: str, path: Path) -> int:
    """A whole number read from a file (a size or count: ``1``, ``752``, ``752.0``), or an error
    naming the file and ``key`` (a string, list, null, bool, fraction, ``.inf`` or ``.nan``: an
    OverflowError or a silently truncated ``int()`` before)."""
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not ok or not math.isfinite(value) or value != int(value):
        raise FlightFormatError(path, f"{key}: expected a whole number, found {value!r}")
    return int(value)
