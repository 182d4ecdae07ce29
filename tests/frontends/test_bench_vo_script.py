"""scripts/bench_vo.py runs end to end on a short flight; with the simulated AHRS attitude (as the
online loop feeds the VO) every pair after the first starts LK from the previous pair's motion and
none is rejected, and the corner transfer error stays at the tracker's level."""

from __future__ import annotations

import re

from testutil import run_script


def test_bench_vo_with_the_ahrs_attitude_guesses_every_pair() -> None:
    args = ["--duration", "4", "--repeat", "1", "--resolutions", "320x240", "--attitude", "ahrs"]
    out = run_script("bench_vo.py", *args)
    rows = [line for line in out.splitlines() if line.lstrip().startswith("320x240")]
    assert len(rows) == 3, out  # unrectified, rectified, rectified with the attitude decomposition
    for row in rows:
        m = re.search(r"\((\d+) valid pairs, LK guessed (\d+), guess rejected (\d+)\)", row)
        assert m, row
        valid, guessed, rejected = (int(g) for g in m.groups())
        assert valid >= 75 and guessed == valid - 1 and rejected == 0, row
        rms_px = float(row.split()[8])
        # Against the true homographies, the AHRS noise in the rectification included.
        assert rms_px < 0.1, row
