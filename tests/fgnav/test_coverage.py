"""Nothing lost quietly (issue 18 Build 3): skipped/dropped counts by reason, short streams and the
scored part of the flight printed at the end of ``batch``, ``online``, ``compare`` and ``info``."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest
from fgnav.datasets.native import write_flight
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate
from testutil import PROJECT_ROOT

from fgnav.cli import main
from fgnav.coverage import compare_lines, samples_after, stream_span_notes, unused_counts

MH01 = PROJECT_ROOT / "datasets" / "manifests" / "euroc_mh01_orbslam3.toml"


@pytest.fixture(scope="module")
def imu_cut_folder(tmp_path_factory):
    """10 s simulated flight whose IMU file stops at 5 s (a truncated log)."""
    f = simulate("two-turns", seed=6, options=SimOptions(duration=10.0, images=False))
    cut = dataclasses.replace(f, imu=f.imu.select(f.imu.t <= 5.0))
    return write_flight(cut, tmp_path_factory.mktemp("cut") / "flight"), f


def test_stream_span_notes(imu_cut_folder):
    _, f = imu_cut_folder
    assert stream_span_notes(f) == []
    cut = dataclasses.replace(f, imu=f.imu.select(f.imu.t <= 5.0))
    notes = stream_span_notes(cut)
    assert len(notes) == 1
    assert re.fullmatch(r"imu ends at 5\.0 s, 5\.0 s before \w+ \(ends 10\.0 s\)", notes[0])
    late = dataclasses.replace(f, range=f.range.select(f.range.t >= 3.0))
    assert any(n.startswith("range starts at 3.0 s, 3.0 s after") for n in stream_span_notes(late))


@pytest.mark.parametrize("command", ["batch", "online"])
def test_truncated_imu_is_reported(imu_cut_folder, tmp_path, capsys, command):
    folder, f = imu_cut_folder
    out = tmp_path / command
    assert main([command, str(folder), "--out", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    t_last, tol = 5.0, 0.005
    if command == "online":
        # The push engine closes a keyframe once an IMU sample after it has arrived: the last
        # one is the last before the IMU's end; the poses after it wait for a keyframe.
        t_last, tol = float(np.loadtxt(out / "estimate.tum", ndmin=2)[-1, 0]), 1e-6
    n_after = int(np.count_nonzero(f.slam.t > t_last + tol))
    m = re.search(r"skipped \(not used\): \d+ \(.*slam:after-last-keyframe (\d+)", text)
    assert m is not None, text
    assert abs(int(m.group(1)) - n_after) <= 1, (m.group(1), n_after)
    assert "stream: imu ends at 5.0 s, 5.0 s before" in text
    # (online: up to the last keyframe that closed, one keyframe period before the IMU's end)
    assert re.search(r"scored: 0\.\d-(5\.0|4\.9) s of the flight's 0\.0-10\.0 s", text), text
    assert ("dropped (online): " in text) == (command == "online")
    cov = json.loads((out / "summary.json").read_text())["extra"]["coverage"]
    assert cov["scored_s"][1] == pytest.approx(5.0, abs=0.01 if command == "batch" else 0.051)
    assert cov["stream_notes"] and cov["stream_notes"][0].startswith("imu ends at 5.0 s")


def test_info_prints_short_streams(imu_cut_folder, capsys):
    folder, _ = imu_cut_folder
    assert main(["info", str(folder)]) == 0
    assert "short stream: imu ends at 5.0 s, 5.0 s before" in capsys.readouterr().out


def test_unused_counts_of_filters_and_compare_lines(imu_cut_folder):
    from fgnav.estimate import Estimate

    _, f = imu_cut_folder
    info = {"counts": {"slam_updates": 90, "slam_rejected_gate": 3, "too_old": 0}}
    assert unused_counts(info) == {"slam_rejected_gate": 3}
    info = {"counts": {"used": {"range": 9}, "skipped": {"range": 2}, "gated": {"slam": 1}}}
    assert unused_counts(info) == {"skipped:range": 2, "gated:slam": 1}
    assert unused_counts({"skipped": {"a": 1}, "dropped": {"b": 2}}) == {"a": 1, "dropped:b": 2}
    gt = f.ground_truth.select(f.ground_truth.t <= 5.0)
    est = Estimate(method="msf-ekf", trajectory=gt, info={"counts": {"too_old": 2}})
    after = samples_after(f, est)
    assert after["slam"] == int(np.count_nonzero(f.slam.t > gt.t[-1] + 0.05))
    (line,) = compare_lines(f, {"msf-ekf": est})
    assert line.startswith("msf-ekf: not used 2 (too_old 2), after its estimate ends ")
    assert line.endswith("; scored 0.0-5.0 s")


@pytest.mark.slow
@pytest.mark.realdata
def test_euroc_imu_cut_at_half(real_data, tmp_path, capsys):
    """EuRoC MH_01's IMU file cut at half: before, half the SLAM poses were skipped and said only
    inside summary.json while the printed ATE (3.35 cm) looked better than the full flight's."""
    root = real_data / "euroc_MH_01_easy"
    lines = (root / "imu0" / "data.cleaned.csv").read_text().splitlines()
    imu = tmp_path / "imu_half.csv"
    imu.write_text("\n".join(lines[: len(lines) // 2]) + "\n")
    text = MH01.read_text()
    text = re.sub(r'(?m)^root = ".*"$', f'root = "{root}"', text)
    text = text.replace('path = "imu0/data.cleaned.csv"', f'path = "{imu}"')
    manifest = tmp_path / "mh01_imu_half.toml"
    manifest.write_text(text)
    out = tmp_path / "batch"
    argv = ["batch", str(manifest), "--out", str(out), "--covariance", "none", "--no-progress"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    # Measured: 1831 of 3669 SLAM poses after the IMU's end at 92.0 s (SLAM ends at 184.0 s).
    assert "skipped (not used): 1831 (slam:after-last-keyframe 1831)" in printed
    assert "stream: imu ends at 92.0 s, 92.0 s before slam (ends 184.0 s)" in printed
    assert "scored: 1.1-92.0 s of the flight's 0.0-184.0 s" in printed


@pytest.mark.parametrize("command", ["batch", "online"])
def test_reader_skip_counts_are_printed(imu_cut_folder, tmp_path, capsys, command):
    """The readers' skip counts (``meta[stream]["skipped_..."]``, e.g. the Crazyflie reader's
    gyro stamps that went back) were written to the notes and said only by ``fgnav info``
    (review 2026-12-07: a log with 9528 IMU samples left out gave "health: ok")."""
    _, f = imu_cut_folder
    meta = {**f.meta, "imu": {"skipped_time_not_increasing": 7, "skipped_nonfinite": 0}}
    folder = write_flight(dataclasses.replace(f, meta=meta), tmp_path / "flight")
    assert main([command, str(folder), "--out", str(tmp_path / "o"), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "reader skipped: imu.skipped_time_not_increasing 7\n" in text, text
