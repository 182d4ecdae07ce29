"""scripts/bench_factors.py runs end to end on a tiny problem and prints one row per factor."""

from __future__ import annotations

from testutil import run_script

FACTOR_ROWS = (
    "BetweenFactorPose3 (C++)",
    "accel_drag",
    "slam_position",
    "slam_relative",
    "slam_rotation",
    "slam_axis_scale",
    "yaw cos_sin",
    "tilted_range",
    "homography (8-D)",
    "homography_decomposed",
)


def test_bench_script_prints_a_row_per_factor() -> None:
    args = ["--n-poses", "6", "--n-linearize", "10", "--repeats", "1"]
    out = run_script("bench_factors.py", *args, timeout=120)
    rows = {line[:26].strip(): line[26:].split() for line in out.splitlines()}
    for name in FACTOR_ROWS:
        assert name in rows, out
        linearize_us = float(rows[name][0])
        assert linearize_us > 0.0
    # One callback per keyframe (5 with a previous pose, 6 without).
    assert rows["yaw"][3] == "6" and rows["homography (8-D)"][3] == "5"
