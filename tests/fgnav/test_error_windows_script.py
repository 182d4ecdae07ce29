"""``scripts/error_windows.py``: each method's ATE on its own and on the common span."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest
from fgnav.datasets.simulate import SimOptions, simulate
from testutil import PROJECT_ROOT, compare_cli


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    from fgnav.datasets.native import write_flight

    d = tmp_path_factory.mktemp("ew")
    f = simulate("two-turns", seed=1, options=SimOptions(duration=20.0, images=False))
    folder = write_flight(f, d / "flight")
    out = d / "out"
    rc = compare_cli(folder, out, "fixed-lag,ekf004")
    assert rc == 0
    return folder, out


def test_error_windows_matches_compare_and_scores_one_span(compared):
    folder, out = compared
    table = {r["method"]: r for r in json.loads((out / "compare.json").read_text())["table"]}
    res = subprocess.run(
        [
            sys.executable,
            str(PROJECT_ROOT / "scripts" / "error_windows.py"),
            str(folder),
            str(out),
            "--methods",
            "fixed-lag,ekf004,nope",
            "--late",
            "10",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    lines = res.stdout.splitlines()
    assert any(line.startswith("nope: no ") for line in lines)
    rows = {}
    for line in lines:
        m = re.match(
            r"(\S+)\s+own span\s+([\d.]+)-\s*([\d.]+) s: ATE\s+([\d.]+) cm \(n=(\d+)\) \| "
            r"common span\s+([\d.]+) cm \(n=(\d+)\) \| late\s+([\d.]+) cm",
            line,
        )
        if m:
            rows[m.group(1)] = [float(x) for x in m.groups()[1:]]
    assert set(rows) == {"fixed-lag", "ekf004"}
    for name, (_, _, ate, n_own, _, n_c, late) in rows.items():
        # The own span is scored as fgnav compare scores it.
        assert ate == pytest.approx(table[name]["ate_rmse_m"] * 100, abs=0.006), name
        assert n_c <= n_own and late > 0
    # The common span starts at the later first output (the smoother's, after its start):
    # the filter that emits from t = 0 loses its first samples there.
    t_first = {k: v[0] for k, v in rows.items()}
    late_name = max(t_first, key=t_first.get)
    early_name = min(t_first, key=t_first.get)
    assert rows[late_name][5] == rows[late_name][3]  # n on the common span == own n
    assert rows[late_name][4] == rows[late_name][2]  # and the same ATE
    if t_first[late_name] > t_first[early_name]:
        assert rows[early_name][5] < rows[early_name][3]
    # One RMSE row per 5 s window.
    assert sum(bool(re.match(r"\s*\d+-\d+\s+[\d.]+", line)) for line in lines) >= 4
