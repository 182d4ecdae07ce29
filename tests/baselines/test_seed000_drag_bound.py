"""Seed 000's I&I observer refuses a drag coefficient it cannot run on (review 2026-12-07: ``drag_k
= [1e-300, 1e-300]`` ran to hundreds of metres): its options' ``check()`` from the Python API,
and the observer itself for a flight's ``meta["drag_k"]``."""

from __future__ import annotations

import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.types import Calibration

from fgnav.baselines.seed000 import Seed000, Seed000Options
from fgnav.frontends.ii_observer import IIObserver, IIObserverOptions, drag_k_problem


@pytest.mark.parametrize("k", [(1e-300, 1e-300), (0.4, 0.009), (0.4, 101.0), (0.4, float("nan"))])
def test_out_of_range_drag_k_is_refused(k):
    assert drag_k_problem(k) is not None
    with pytest.raises(FlightDataError, match=r"Seed000Options\.drag_k=.*expected \(kx, ky\) in"):
        Seed000(Seed000Options(drag_k=k)).start(Calibration())
    with pytest.raises(FlightDataError, match="observer.drag_k="):
        Seed000Options(observer=IIObserverOptions(drag_k=k)).check()
    with pytest.raises(FlightDataError, match="I&I observer: drag_k="):
        IIObserver(IIObserverOptions(), drag_k=k)


def test_the_bounds_themselves_are_taken():
    for k in [(0.01, 0.01), (0.38, 0.42), (100.0, 100.0)]:
        assert drag_k_problem(k) is None
        assert Seed000Options(drag_k=k).check().drag_k == k
        IIObserver(IIObserverOptions(), drag_k=k)
