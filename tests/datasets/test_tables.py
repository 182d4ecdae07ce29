"""Shared helpers of the readers (``fgnav.datasets._tables``)."""

from __future__ import annotations

import numpy as np
import pytest


def test_increasing_mask_leaves_out_a_lone_jump_and_what_the_caller_left_out():
    """A lone stamp far ahead (a PX4 ULog with 200 bytes flipped: one IMU stamp at 1.8e13 s)
    hid every later sample under a plain running maximum; samples the caller marks -inf are not
    neighbours (the first of a stream whose next four were masked was left out)."""
    from fgnav.datasets._tables import clock_reset, increasing_mask

    t = np.arange(10.0)
    t[4] = 1.8e13
    assert increasing_mask(t).tolist() == [True] * 4 + [False] + [True] * 5
    m = np.array([0.0, -np.inf, -np.inf, -np.inf, -np.inf, 5.0, 5.0, 7.0])
    assert increasing_mask(m).tolist() == [True, False, False, False, False, True, False, True]
    # A clock reset: 100 samples back by 2 s, then on. One lone bad stamp is no reset.
    r = np.r_[np.arange(0, 10, 0.01), np.arange(8, 12, 0.01)]
    keep = increasing_mask(r)
    i, back = clock_reset(r, keep)
    assert i == 1000 and back == pytest.approx(2.0 - 0.01, abs=1e-9)
    assert clock_reset(t, increasing_mask(t)) is None


@pytest.mark.parametrize("tok", ["1E-999999999", "1.5E+999999999", "2e101"])
def test_time_stamp_with_an_absurd_exponent_is_named(tok):
    """``1E-999999999`` was a decimal.InvalidOperation traceback: one line naming file, line
    and column."""
    from pathlib import Path

    from fgnav.datasets._tables import RawTable, parse_ns
    from fgnav.datasets.errors import FlightFormatError

    raw = RawTable(Path("x.csv"), ["timestamp"], ["timestamp [ns]"], [["1000"], [tok]], [2, 3])
    with pytest.raises(FlightFormatError) as e:
        parse_ns(raw)
    assert str(e.value) == f"x.csv:3: column 1 ('timestamp'): time stamp {tok!r} ns out of range"
    ok = RawTable(Path("x.csv"), None, None, [["1.40363657975856E+018"]], [1])
    assert parse_ns(ok).ns == [1403636579758560000]
