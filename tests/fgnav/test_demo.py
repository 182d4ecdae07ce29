"""``fgnav demo`` end to end (subprocess): a short simulated flight, both smoothers, the report."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


@pytest.mark.slow
def test_demo_short_flight(tmp_path):
    out = tmp_path / "demo"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "fgnav.cli",
            "demo",
            "--out",
            str(out),
            "--duration",
            "8",
            "--no-images",
            "--methods",
            "batch,fixed-lag,ekf004,ekf-vo002",
            "--seed",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    lines = r.stdout.splitlines()
    for stage in (
        "[1/4] simulating two-turns (seed 1)",
        "[2/4] batch",
        "[3/4] fixed-lag",
        "[4/4] comparing methods",
    ):
        assert any(line.startswith(stage) for line in lines), stage
    assert "skipped ekf-vo002: needs images; the flight has none" in r.stdout
    wall = next(line for line in lines if line.startswith("wall time:"))
    for stage in ("simulate", "batch", "fixed-lag", "compare", "total"):
        assert f"{stage} " in wall
    assert (out / "flight" / "meta.json").is_file()
    assert (out / "report.md").is_file() and (out / "top_view.png").is_file()
    data = json.loads((out / "compare.json").read_text())
    rows = {row["method"]: row for row in data["table"]}
    assert list(rows) == ["batch", "fixed-lag", "ekf004"]
    assert all(row["status"] == "ok" for row in rows.values())
    # The smoother estimates of stages 2-3 are reused by the comparison, not recomputed.
    assert data["methods"]["batch"]["reused"] and data["methods"]["fixed-lag"]["reused"]
    assert not data["methods"]["ekf004"]["reused"]
    # 8 s of hover and the start of the first turn: the batch smoother is within centimetres.
    assert rows["batch"]["ate_rmse_m"] < 0.05
    assert rows["fixed-lag"]["latency_p50_ms"] > 0
