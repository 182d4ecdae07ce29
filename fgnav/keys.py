"""GTSAM symbols of fgnav's variables (one place; see ../shared/DESIGN.md section 3).

The key functions are GTSAM's own :mod:`gtsam.symbol_shorthand` (``X(k) == gtsam.symbol("x",
k)``); the letters fgnav gives them:

Per keyframe k:

- ``X(k)``: Pose3 ``world_T_body``.
- ``V(k)``: velocity ``world_v_body`` [m/s] (3-vector).
- ``B(k)``: IMU bias (``imuBias.ConstantBias``).

Slow variables, one per segment j:

- ``S(j)``: SLAM alignment (``Similarity3`` ``slam_T_world`` of a session segment, or for seed
  000's per-axis model a Vector6 ``[kx, ky, kz, ox, oy, oz]``: per-axis scale and origin offset).
- ``D(j)``: drag coefficient k = mu/m [1/s] (scalar or per-axis vector).
- ``G(j)``: ground height under the rangefinder [m] of a terrain segment.
- ``W(j)``: horizontal wind ``world_v_wind_xy`` [m/s] (Vector2; optional, drag factor).
"""

from __future__ import annotations

import gtsam
from gtsam.symbol_shorthand import B, D, G, S, V, W, X

__all__ = ["B", "D", "G", "S", "V", "W", "X", "describe"]


def describe(key: int) -> str:
    """Human-readable ``x12`` form of a key."""
    s = gtsam.Symbol(key)
    return f"{chr(s.chr())}{s.index()}"
