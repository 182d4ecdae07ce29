"""``--config`` files: TOML tables that fill an options dataclass, flags override them."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, TypeVar

from fgnav.datasets._files import read_toml
from fgnav.datasets.errors import FgnavError, FlightFormatError

T = TypeVar("T")


def load_config(path: str | Path | None, section: str | None = None) -> dict[str, Any]:
    """Read a TOML config file (or ``{}`` for None); return the table ``section`` if given."""
    if path is None:
        return {}
    p = Path(path)
    data = read_toml(p, "config file")
    if section is None:
        return data
    table = data.get(section, {})
    if not isinstance(table, dict):
        raise FlightFormatError(p, f"[{section}] must be a table")
    return table


def options_from(
    cls: type[T],
    table: dict[str, Any],
    source: str = "config",
    section: str | None = None,
    **overrides,
) -> T:
    """Build options dataclass ``cls`` from a config table plus non-None overrides.

    Unknown keys raise an error naming them and listing the valid ones; values are checked by
    :func:`check_option_values` (the error names the option, the file and table or the flag).
    """
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - names)
    where = f"{source} [{section}]" if section else source
    if unknown:
        raise FlightFormatError(
            where, f"unknown option(s) {unknown} for {cls.__name__}; valid: {sorted(names)}"
        )
    kwargs = dict(table)
    given = {k: v for k, v in overrides.items() if v is not None}
    kwargs.update(given)
    zero_ok = getattr(cls, "ZERO_MEANS_OFF", frozenset())
    for name, value in kwargs.items():
        problem = option_value_problem(name, value, zero_ok=name in zero_ok)
        if problem is not None:
            origin = "command line" if name in given else where
            raise OptionValueError(f"{origin}: option {name} = {value!r}: {problem}")
    return cls(**kwargs)


def check_tables(path: str | Path | None, allowed: list[str]) -> None:
    """Refuse a ``--config`` file with a table the command does not read (a typo such as
    ``[grpah]`` would otherwise be ignored)."""
    unknown = sorted(set(load_config(path)) - set(allowed))
    if unknown:
        raise FlightFormatError(
            path, f"unknown table(s) {unknown} for this command; valid: {sorted(allowed)}"
        )


class OptionValueError(FgnavError, ValueError):
    """An option value that cannot be meant (non-finite, or <= 0 where only > 0 makes sense)."""


#: Option names (exact) whose value must be > 0 besides the name patterns of
#: :func:`option_value_problem`.
POSITIVE_OPTIONS = frozenset(
    {
        "gravity",
        "robust_k",
        "max_iterations",
        "lambda_init",
        "lambda_factor",
        "lambda_max",
        "lambda_min",
        "rel_tol",
        "cov_pose_stride",
        "relinearize_skip",
        "slow_read_every",
        "fine_levels",
        "slam_provisional_scale",
        "slam_provisional_min_poses",
        "slam_init_max_rel_se",
    }
)


def option_value_problem(name: str, value: Any, zero_ok: bool = False) -> str | None:
    """What is wrong with option ``name = value`` (None: nothing found; ``zero_ok``: 0 switches
    the option's stream off, as a class's ``ZERO_MEANS_OFF`` names).

    Every number (also inside tuples and lists) must be finite. Noise sigmas (``*sigma*``), rates
    (``*_hz``), random walks (``*_rw``, ``*_rw_m``), lags and segment lengths (``lag_s``,
    ``*segment_s``) and :data:`POSITIVE_OPTIONS` must be > 0; durations and lengths (``*_s``,
    ``*_m``, offsets excepted) must be >= 0. Booleans, strings and None are not checked here.
    """
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return None
    if isinstance(value, (list, tuple)):
        for v in value:
            p = option_value_problem("", v)
            if p is not None:
                return p
        return None
    if not isinstance(value, (int, float)):
        return None
    if not math.isfinite(value):
        return "expected a finite number"
    positive = (
        "sigma" in name
        or name.endswith(("_hz", "_rw", "_rw_m", "lag_s", "segment_s"))
        or name in POSITIVE_OPTIONS
    )
    if positive and not (value > 0 or (zero_ok and value == 0)):
        return "expected >= 0 (0: off)" if zero_ok else "expected > 0"
    if name.endswith(("_s", "_m")) and "offset" not in name and value < 0:
        return "expected >= 0"
    return None
