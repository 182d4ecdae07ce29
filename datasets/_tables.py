"""Numeric text tables (csv or whitespace separated) with errors that name file, line and column.

Shared by the readers of this package (native csv, EuRoC/ASL csv, TUM). Not a public API: the
readers decide the policy (which columns, time unit, what may be skipped) and this module parses.

Time stamps in integer nanoseconds (EuRoC, ORB-SLAM3) do not fit a float64 exactly (1.4e18 needs
61 bits), so time columns in ns are parsed from the text into Python integers and converted to
seconds as ``seconds + remainder * 1e-9``, which keeps the full float64 resolution of the result.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from .errors import FlightFormatError, note

log = logging.getLogger(__name__)

NS_PER_S = 10**9

_PLAIN_INT = re.compile(r"^[+-]?\d+(\.0*)?$")
_SCIENTIFIC = re.compile(r"^([+-]?)(\d+)\.?(\d*)[eE]([+-]?\d+)$")
_UNIT = re.compile(r"\s*\[[^\]]*\]\s*$")


@dataclass
class RawTable:
    """Lines of a text table split into tokens, before numeric conversion.

    Attributes:
        path: the file.
        header: the header's column names with units stripped, or None.
        header_raw: the header's column names as written (with units), or None.
        rows: token lists, one per data line.
        lines: 1-based line number of each row in the file.
    """

    path: Path
    header: list[str] | None
    header_raw: list[str] | None
    rows: list[list[str]]
    lines: list[int]


def strip_unit(name: str) -> str:
    """``"omega_x [rad/s]"`` -> ``"omega_x"``."""
    return _UNIT.sub("", name).strip()


def unit_of(name: str) -> str | None:
    """``"omega_x [rad/s]"`` -> ``"rad/s"`` (None without a unit)."""
    m = _UNIT.search(name)
    return None if m is None else m.group(0).strip()[1:-1].strip()


def split_line(line: str, sep: str | None) -> list[str]:
    """Tokens of one line: split on ``sep`` (whitespace when None), each token stripped."""
    if sep is None:
        return line.split()
    return [tok.strip() for tok in line.rstrip("\r\n").split(sep)]


def read_raw(
    path: str | Path,
    *,
    sep: str | None,
    header: str,
    comment: str = "#",
) -> RawTable:
    """Split a text table into tokens.

    Args:
        path: file to read.
        sep: column separator (``","``) or None for runs of whitespace.
        header: ``"comment"``: an optional first line starting with ``comment`` is the header
            (EuRoC ``#timestamp [ns],...``), later comment lines are skipped; ``"first"``: the first
            non-blank line is the header (fgnav's native csv); ``"none"``: no header, every comment
            line is skipped (TUM).
        comment: comment prefix.

    Raises:
        FlightFormatError: the file is missing, not text, or has no data line.
    """
    p = Path(path)
    if not p.is_file():
        raise FlightFormatError(p, "file not found" if not p.exists() else "not a file")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise FlightFormatError(p, f"not a text file ({e.reason} at byte {e.start})") from e
    hdr_raw: list[str] | None = None
    rows: list[list[str]] = []
    lines: list[int] = []
    for i, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if hdr_raw is None and not rows:
            if header == "first" or (header == "comment" and s.startswith(comment)):
                body = s[len(comment) :] if s.startswith(comment) else s
                hdr_raw = split_line(body, sep)
                continue
        if s.startswith(comment):
            continue
        rows.append(split_line(s, sep))
        lines.append(i)
    if not rows:
        raise FlightFormatError(p, "no data lines (the file is empty or only has comments)")
    hdr = [strip_unit(h) for h in hdr_raw] if hdr_raw is not None else None
    return RawTable(p, hdr, hdr_raw, rows, lines)


def column_name(header: list[str] | None, j: int) -> str:
    """Name of column j for messages: the header name, else ``column <j+1>``."""
    if header is not None and j < len(header) and header[j]:
        return f"column {j + 1} ({header[j]!r})"
    return f"column {j + 1}"


def cell_error(raw: RawTable, k: int, j: int, what: str) -> FlightFormatError:
    """The error for row k, column j: ``FILE:LINE: column N ('name'): <what>``."""
    return FlightFormatError(raw.path, f"{column_name(raw.header, j)}: {what}", line=raw.lines[k])


def parse_float(raw: RawTable, k: int, j: int) -> float:
    """Value of row k, column j as a finite float, or an error naming file, line and column."""
    tok = raw.rows[k][j]
    try:
        v = float(tok)
    except ValueError:
        raise cell_error(raw, k, j, f"expected a number, found {tok!r}") from None
    if not math.isfinite(v):
        raise cell_error(raw, k, j, f"non-finite value {tok!r} (NaN/inf are not allowed)")
    return v


def check_widths(raw: RawTable, widths: tuple[int, ...], what: str) -> None:
    """Every row has one of ``widths`` columns, else an error naming the line."""
    for k, row in enumerate(raw.rows):
        if len(row) not in widths:
            expected = " or ".join(str(w) for w in widths)
            raise FlightFormatError(
                raw.path,
                f"expected {expected} columns ({what}), found {len(row)}: {' '.join(row)[:80]!r}",
                line=raw.lines[k],
            )


def to_values(raw: RawTable, columns: range | list[int]) -> np.ndarray:
    """(N, len(columns)) float array of the given columns, with errors naming line and column."""
    cols = list(columns)
    try:
        out = np.array([[float(row[j]) for j in cols] for row in raw.rows], dtype=float)
    except ValueError:
        out = None
    if out is not None:
        bad = np.flatnonzero(~np.all(np.isfinite(out), axis=1))
        if not bad.size:
            return out.reshape(len(raw.rows), len(cols))
    for k in range(len(raw.rows)):
        for j in cols:
            parse_float(raw, k, j)
    raise AssertionError("unreachable: a bad value was not found")


@dataclass
class NsTimes:
    """Integer-nanosecond time stamps parsed from text.

    Attributes:
        ns: Python integers, one per row.
        resolution_ns: coarsest resolution found (1 for plain integers; 10_000 for a stamp
            written by a spreadsheet as ``1.40363657975856E+018``).
        example: a token at that coarsest resolution and its line, for messages.
    """

    ns: list[int]
    resolution_ns: int
    example: tuple[int, str] | None


NS_INT64_MAX = 2**63 - 1
"""Largest time stamp [ns] the readers take (numpy's int64)."""
NS_EXPONENT_MAX = 100
"""Largest exponent (either sign) of a time stamp in scientific notation: int64 ns need 18."""


def parse_ns(raw: RawTable, j: int = 0) -> NsTimes:
    """Column j as integer nanoseconds: exact for plain integers (``1403636579763555584`` or
    ``1403636579763555584.000``); decimal and scientific notation are read exactly with
    :class:`decimal.Decimal` and rounded to the nearest ns, and their resolution is reported."""
    ns: list[int] = []
    worst = 1
    example: tuple[int, str] | None = None
    for k, row in enumerate(raw.rows):
        tok = row[j]
        if _PLAIN_INT.match(tok):
            ns.append(int(tok.split(".")[0]))
            continue
        m = _SCIENTIFIC.match(tok)
        if m:
            sign, whole, frac, exp = m.groups()
            digits = int(whole + frac) * (-1 if sign == "-" else 1)
            exponent = int(exp) - len(frac)
            if not -NS_EXPONENT_MAX <= int(exp) <= NS_EXPONENT_MAX:
                # 1E-999999999 was a decimal.InvalidOperation traceback (and 1E+999999999 a
                # power of ten of a billion digits).
                raise cell_error(raw, k, j, f"time stamp {tok!r} ns out of range")
            d = Decimal(digits).scaleb(exponent)
            resolution = 10 ** (exponent + len(frac) - len(frac.rstrip("0")))
        else:
            try:
                d = Decimal(tok)
            except InvalidOperation:
                raise cell_error(raw, k, j, f"expected a time stamp in ns, found {tok!r}") from None
            if not d.is_finite():
                raise cell_error(raw, k, j, f"non-finite time stamp {tok!r}")
            exponent = int(d.normalize().as_tuple().exponent) if d != 0 else 0
            resolution = 10**exponent
        if resolution > worst:
            worst, example = resolution, (raw.lines[k], tok)
        ns.append(int(d.to_integral_value()))
    # The first stamp beyond the signed 64-bit range (about 292 years in ns) is named.
    for k, v in enumerate(ns):
        if not -NS_INT64_MAX <= v <= NS_INT64_MAX:
            raise cell_error(raw, k, j, f"time stamp {raw.rows[k][j]!r} ns out of range")
    return NsTimes(ns, worst, example)


def ns_to_seconds(ns: list[int] | np.ndarray) -> np.ndarray:
    """Integer nanoseconds -> float seconds, rounding once (exact seconds + remainder * 1e-9)."""
    a = np.asarray(ns, dtype=np.int64)
    return (a // NS_PER_S).astype(float) + (a % NS_PER_S).astype(float) * 1e-9


def check_increasing(raw: RawTable, t: np.ndarray, lines: list[int] | None = None) -> None:
    """Strictly increasing time, else an error naming both lines."""
    lines = raw.lines if lines is None else lines
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0])
        raise FlightFormatError(
            raw.path,
            f"time must be strictly increasing: t={float(t[i + 1])!r} s does not follow "
            f"t={float(t[i])!r} s "
            f"(line {lines[i]}); {bad.size} such line(s)",
            line=lines[i + 1],
        )


def drop_repeated_rows(
    raw: RawTable, t: np.ndarray, values: np.ndarray, notes: list[str] | None, what: str
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Drop rows that repeat the previous row exactly (same time, same values), reporting them.

    A repeated time with different values is not dropped (the time check then names it).

    Returns:
        t, values, line numbers of the rows kept.
    """
    same = np.zeros(len(t), dtype=bool)
    if len(t) > 1:
        same[1:] = (t[1:] == t[:-1]) & np.all(values[1:] == values[:-1], axis=1)
    if not same.any():
        return t, values, list(raw.lines)
    dropped = [raw.lines[k] for k in np.flatnonzero(same)]
    shown = ", ".join(str(x) for x in dropped[:10]) + (" ..." if len(dropped) > 10 else "")
    msg = (
        f"{raw.path}: skipped {len(dropped)} {what} line(s) repeating the previous line exactly "
        f"(same time stamp and values): lines {shown}"
    )
    note(log, notes, msg)
    keep = ~same
    return t[keep], values[keep], [ln for ln, k in zip(raw.lines, keep, strict=True) if k]


def increasing_mask(t: np.ndarray) -> np.ndarray:
    """Mask of samples strictly later than every earlier kept sample (``-inf``: a sample the
    caller already leaves out). A lone stamp that jumps ahead of both neighbours while they are
    in order (a flipped bit in a damaged log) is left out first: kept, it would hide every later
    sample (a salvaged Crazyflie traj1 with one flipped bit lost 23 s of IMU to it; a PX4 ULog
    with 200 bytes flipped, one IMU stamp at 1.8e13 s, lost every later sample and its batch
    ran out of memory)."""
    t = np.asarray(t, dtype=float)
    keep = np.zeros(t.shape, dtype=bool)
    idx = np.flatnonzero(t > -np.inf)
    u = t[idx]
    k = np.ones(u.shape, dtype=bool)
    if u.size >= 3:
        k[1:-1] = ~((u[1:-1] > u[2:]) & (u[:-2] < u[2:]))
    if u.size >= 2:
        k[0] = u[0] <= u[1] or (u.size >= 3 and u[0] < u[2])
    if u.size:
        uk = np.where(k, u, -np.inf)
        k[1:] &= u[1:] > np.maximum.accumulate(uk)[:-1]
    keep[idx] = k
    return keep


def clock_reset(
    t: np.ndarray, keep: np.ndarray, min_run: int = 50, min_back_s: float = 1.0
) -> tuple[int, float] | None:
    """A clock reset in stamps ``t`` that :func:`increasing_mask` kept as ``keep``: the first
    run of at least ``min_run`` consecutive samples left out after a step back of more than
    ``min_back_s`` (a lone bad stamp leaves out one). Returns ``(index of its first sample, the
    step back [s])`` or None. Left out quietly, such a run lost the time until the clock passed
    its old value again, and the rest of the log was read on a shifted clock."""
    dropped = np.flatnonzero(~keep)
    if dropped.size < min_run:
        return None
    starts = dropped[np.r_[True, np.diff(dropped) > 1]]
    ends = dropped[np.r_[np.diff(dropped) > 1, True]]
    for a, b in zip(starts, ends, strict=True):
        if b - a + 1 >= min_run and a > 0:
            back = float(np.max(t[:a]) - t[a])
            if back > min_back_s:
                return int(a), back
    return None
