"""Shared fixtures; paths come from tests/testutil.py."""

from __future__ import annotations

from pathlib import Path

import pytest
from testutil import require_real_data, two_turns_folder


@pytest.fixture(scope="session")
def real_data() -> Path:
    """``../shared/data/real``; skips with the reason where it is absent."""
    return require_real_data()


@pytest.fixture(scope="session")
def cli_folder(tmp_path_factory) -> Path:
    """The simulated 8 s two-turns flight folder (seed 4, no images) the CLI tests run on (read
    only: commands write to their own ``--out``)."""
    return two_turns_folder(tmp_path_factory, seed=4)
