"""Paths and helpers for tests, resolved from this file (never from the working directory)."""

from __future__ import annotations

from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
REAL_DATA = PROJECT_ROOT.parent / "shared" / "data" / "real"


def require_real_data() -> Path:
    """``../shared/data/real``, or skip the calling test with the reason."""
    if not REAL_DATA.is_dir():
        pytest.skip(f"real data folder {REAL_DATA} is absent (CI has ../shared beside the clone)")
    return REAL_DATA
