"""scripts/profile_online.py: the per-update profile of the push engine (issue 15)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from testutil import PROJECT_ROOT


def _profile(*extra: str) -> dict:
    res = subprocess.run(
        [
            sys.executable,
            str(PROJECT_ROOT / "scripts" / "profile_online.py"),
            "figure8",
            "--duration",
            "22",
            "--position-threshold",
            "0.003",
            "--probe",
            "--json",
            *extra,
        ],
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    )
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_profile_shows_the_batch_relinearisation_that_ballast_avoids():
    ballast, bare = _profile(), _profile("--no-ballast")
    # The same estimates: ballast changes which factors iSAM2 relinearises, not the result.
    assert ballast["summary"]["ate_cm"] == pytest.approx(bare["summary"]["ate_cm"], abs=1e-6)
    assert ballast["summary"]["solver_failures"] == bare["summary"]["solver_failures"] == 0
    t_b, t_n = ballast["table"], bare["table"]
    for t in (t_b, t_n):
        assert {"all", "plain", "relinearising", "marginalising"} <= set(t)
        assert t["all"]["n"] > 150 and t["all"]["cpu_p99"] >= t["all"]["cpu_p50"] > 0
        # A plain update: a few callbacks (the new factors), the top of the tree.
        assert t["plain"]["cb_n"] < 10 and t["plain"]["reelim"] < 40
    # Relinearising at 3 mm re-eliminates most of the window either way, but without ballast
    # iSAM2's batch path relinearises every factor: many more Python callbacks.
    assert t_n["relinearising"]["reelim"] > 100 and t_b["relinearising"]["reelim"] > 100
    assert t_n["relinearising"]["cb_n"] > 1.2 * t_b["relinearising"]["cb_n"]
    # The probe: from the oldest key the whole chain, from the newest the root only.
    for p in (ballast["probes"], bare["probes"]):
        old = [n for from_oldest, _, _, n in p if from_oldest]
        new = [n for from_oldest, _, _, n in p if not from_oldest]
        assert old and sorted(old)[len(old) // 2] > 100 and max(new) < 40
