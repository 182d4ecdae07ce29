"""scripts/bench_online.py runs end to end on a short flight (the push engine fed every event) and
prints the figures its users read: updates, latency percentiles, times real time and the causal
ATE; its options reach the smoother (the SLAM origin walk is echoed, a failed run exits non-zero).
Speed itself is not asserted here (benchmarks print figures; tests do not time)."""

from __future__ import annotations

import re

from testutil import run_script


def test_bench_online_prints_its_figures_and_passes_its_options() -> None:
    out = run_script("bench_online.py", "--duration", "20", "--slam-trans-rw", "0.005")
    assert "SLAM origin walk 0.005" in out, out
    m = re.search(r"updates: (\d+) ", out)
    assert m and int(m.group(1)) >= 390, out  # 20 Hz keyframes over 20 s
    assert re.search(r"latency: p50 [\d.]+ ms, p99 [\d.]+ ms, max [\d.]+ ms", out), out
    assert re.search(r"times real time: [\d.]+x wall, [\d.]+x CPU", out), out
    assert "solver failures: 0" in out, out
    m = re.search(r"ATE \(causal, SE\(3\) alignment\): ([\d.]+) m", out)
    # Measured 2026-12-04: 0.036 m (figure8, seed 1, 20 s, no camera).
    assert m and float(m.group(1)) < 0.06, out
