"""GTSAM symbols of fgnav's variables (one place; see ../shared/DESIGN.md section 3).

Per keyframe k: ``X(k)`` Pose3 ``world_T_body``, ``V(k)`` velocity ``world_v_body`` (3-vector),
``B(k)`` ``imuBias.ConstantBias``. Slow variables, one per segment j: ``S(j)`` SLAM alignment,
``D(j)`` drag coefficient, ``G(j)`` ground height, ``W(j)`` horizontal wind (optional).
"""

from __future__ import annotations

import gtsam


def X(k: int) -> int:
    """Pose3 ``world_T_body`` at keyframe k."""
    return gtsam.symbol("x", k)


def V(k: int) -> int:
    """Velocity ``world_v_body`` [m/s] at keyframe k."""
    return gtsam.symbol("v", k)


def B(k: int) -> int:
    """IMU bias (``imuBias.ConstantBias``) at keyframe k."""
    return gtsam.symbol("b", k)


def S(j: int) -> int:
    """SLAM alignment j (``Similarity3`` ``slam_T_world`` of a session segment, or for seed 000's
    per-axis model a Vector6 ``[kx, ky, kz, ox, oy, oz]``: per-axis scale and origin offset)."""
    return gtsam.symbol("s", j)


def D(j: int) -> int:
    """Drag coefficient k = mu/m [1/s] of segment j (scalar or per-axis vector)."""
    return gtsam.symbol("d", j)


def G(j: int) -> int:
    """Ground height under the rangefinder [m] of terrain segment j."""
    return gtsam.symbol("g", j)


def W(j: int) -> int:
    """Horizontal wind ``world_v_wind_xy`` [m/s] (Vector2) of segment j (optional, drag factor)."""
    return gtsam.symbol("w", j)


def describe(key: int) -> str:
    """Human-readable ``x12`` form of a key."""
    s = gtsam.Symbol(key)
    return f"{chr(s.chr())}{s.index()}"
