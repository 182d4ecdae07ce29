"""The push engine's fixed-capacity row buffer (accelerometer-check rows, drag means) holds what
a ``deque(maxlen=n)`` of the same rows holds, in the same order."""

from __future__ import annotations

from collections import deque

import numpy as np

from fgnav.solvers.online import _Ring


def test_ring_matches_a_bounded_deque():
    rng = np.random.default_rng(5)
    ring, ref = _Ring(7, 3), deque(maxlen=7)
    assert len(ring) == 0 and ring.array().shape == (0, 3)
    for _ in range(30):
        row = rng.normal(size=3)
        ring.append(row)
        ref.append(row.copy())
        row[:] = 0.0  # the ring copied the row
        assert len(ring) == len(ref)
        np.testing.assert_array_equal(ring.array(), np.array(ref))
        assert ring.array().flags["C_CONTIGUOUS"]
