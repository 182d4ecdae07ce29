"""Shared simulated flights for the solver tests (simulated once per session; short and seeded)."""

from __future__ import annotations

import pytest
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate


@pytest.fixture(scope="session")
def two_turns_20s():
    """20 s of the seed-002 two-turns flight, all sensors except images, seed 0."""
    return simulate("two-turns", seed=0, options=SimOptions(duration=20.0, images=False))


@pytest.fixture(scope="session")
def two_turns_12s():
    """12 s of the two-turns flight (hover, then the first turn), seed 1."""
    return simulate("two-turns", seed=1, options=SimOptions(duration=12.0, images=False))


@pytest.fixture(scope="session")
def two_turns():
    """The whole two-turns flight (the scenario's duration), all sensors except images, seed 1."""
    return simulate("two-turns", seed=1, options=SimOptions(images=False))
