"""Shared fixtures; paths come from tests/testutil.py."""

from __future__ import annotations

from pathlib import Path

import pytest
from testutil import require_real_data


@pytest.fixture(scope="session")
def real_data() -> Path:
    """``../shared/data/real``; skips with the reason where it is absent."""
    return require_real_data()
