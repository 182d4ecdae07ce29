"""Errors raised by fgnav.datasets, and the readers' notes. Every message names the file/stream,
the line or field, and what was expected, so that a user can fix the input without reading code."""

from __future__ import annotations

import logging


class FgnavError(Exception):
    """Base of fgnav's known errors; the CLI prints them as one line and exits with code 1."""


class FlightDataError(FgnavError, ValueError):
    """A time series or flight violates the data model (shape, finiteness, time order)."""


class FlightFormatError(FgnavError, ValueError):
    """A file could not be read as the format it claims to be.

    Args:
        path: the file.
        message: what is wrong and what was expected.
        line: 1-based line number in the file, when known.
    """

    def __init__(self, path: object, message: str, line: int | None = None) -> None:
        self.path = str(path)
        self.line = line
        self.reason = message
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {message}")


def note(
    log: logging.Logger, notes: list[str] | None, msg: str, level: int = logging.WARNING
) -> None:
    """A reader's note (skipped lines, a detected time unit, a projected rotation): ``msg`` is
    logged on ``log`` at ``level`` and appended to ``notes`` when given (the reader's list,
    which ends in ``flight.meta["notes"]``)."""
    log.log(level, msg)
    if notes is not None:
        notes.append(msg)
