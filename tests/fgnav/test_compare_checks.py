"""``fgnav compare`` review findings (2026-12-08): exit code when nothing ran, the SLAM scale of a
flight without SLAM, repeated ``--methods``, reference rows scored on positions only, and the
implausible-estimate flags."""

from __future__ import annotations

import dataclasses
import json

import pytest
from fgnav.datasets.simulate import SimOptions, simulate
from testutil import compare_cli

from fgnav.compare import compare, truth_slam_scales
from fgnav.methods import METHODS, reference_estimate


@pytest.fixture(scope="module")
def flight():
    """12 s of two-turns without images, seed 3."""
    return simulate("two-turns", seed=3, options=SimOptions(duration=12.0, images=False))


@pytest.fixture(scope="module")
def imu_only(flight):
    """The same flight with the IMU (and truth) only: no SLAM, attitude, yaw, range, flow."""
    return dataclasses.replace(flight, slam=None, attitude=None, yaw=None, range=None, flow=None)


def test_no_slam_no_true_slam_scale(imu_only, tmp_path):
    """A flight without SLAM has no true SLAM scale, though the simulator's metadata lists the
    sessions it drew (report.md stated "true SLAM scale ... session 0: 0.246991")."""
    assert imu_only.meta["truth"]["slam_sessions"]
    assert truth_slam_scales(imu_only) == (None, "the flight has no SLAM stream")
    res = compare(imu_only, ["msf-ekf"], progress=False)
    paths = res.write(tmp_path, figures=False)
    data = json.loads(paths["json"].read_text())
    assert data["truth"]["slam_scale"] is None
    report = paths["report"].read_text()
    assert "true SLAM scale: not available (the flight has no SLAM stream)" in report
    assert "session 0:" not in report


def _counting(calls: list[str]):
    """A method entry that records its call and replays the truth (fast)."""

    def entry(flight, config, progress=False):
        calls.append("run")
        est = reference_estimate(
            dataclasses.replace(flight, references={"truth": flight.ground_truth}), "truth", "x"
        )
        return dataclasses.replace(est, method="ekf004")

    return entry


def test_repeated_methods_run_once(cli_folder, tmp_path, capsys, monkeypatch):
    """``--methods ekf004,ekf004,ekf004`` ran the method three times and kept one row: now it
    runs once, with a one-line note (``fgnav fleet`` also runs a repeated name once)."""
    calls: list[str] = []
    monkeypatch.setitem(
        METHODS, "ekf004", dataclasses.replace(METHODS["ekf004"], entry=_counting(calls))
    )
    rc = compare_cli(cli_folder, tmp_path / "out", "ekf004,ekf004, ekf004")
    captured = capsys.readouterr()
    assert rc == 0 and calls == ["run"]
    assert captured.err.strip() == (
        "fgnav compare: note: --methods names ekf004 3 times; it runs once"
    )
    data = json.loads((tmp_path / "out" / "compare.json").read_text())
    assert [r["method"] for r in data["table"]] == ["ekf004"]
    # The API does the same.
    res = compare(
        simulate("two-turns", 4, SimOptions(duration=4.0, images=False)),
        ["ekf004"] * 2,
        progress=False,
    )
    assert list(res.runs) == ["ekf004"] and calls == ["run", "run"]


def _raises(flight, config, progress=False):
    raise RuntimeError("deliberate failure")


def test_exit_1_when_no_method_produced_a_row(cli_folder, tmp_path, capsys, monkeypatch):
    """Every method failed or was skipped: the table and files are written, then one line on
    stderr and exit 1 (it was exit 0, as ``fgnav fleet`` is not); one row is enough for 0."""
    monkeypatch.setitem(METHODS, "msf-ekf", dataclasses.replace(METHODS["msf-ekf"], entry=_raises))
    monkeypatch.setitem(METHODS, "ukf003", dataclasses.replace(METHODS["ukf003"], entry=_raises))
    rc = compare_cli(cli_folder, tmp_path / "a", "msf-ekf,ukf003")
    captured = capsys.readouterr()
    assert rc == 1
    assert "FAILED msf-ekf: RuntimeError: deliberate failure" in captured.out
    assert captured.err.strip() == (
        "fgnav compare: no method produced a result (2 failed, 0 skipped; see the lines above)"
    )
    assert (tmp_path / "a" / "report.md").is_file()
    # Skipped only (the flight has no flow): exit 1 too.
    rc = compare_cli(cli_folder, tmp_path / "b", "ekf-flow002,cf-ekf")
    captured = capsys.readouterr()
    assert rc == 1
    assert "skipped cf-ekf: needs flow; the flight has none" in captured.out
    assert captured.err.strip().splitlines() == [
        "fgnav compare: no method produced a result (0 failed, 2 skipped; see the lines above)"
    ]
    # One method with a row: exit 0, the failure still printed.
    calls: list[str] = []
    monkeypatch.setitem(
        METHODS, "ekf004", dataclasses.replace(METHODS["ekf004"], entry=_counting(calls))
    )
    rc = compare_cli(cli_folder, tmp_path / "c", "msf-ekf,ekf004")
    captured = capsys.readouterr()
    assert rc == 0 and calls == ["run"] and "no method produced" not in captured.err
    assert "FAILED msf-ekf: RuntimeError: deliberate failure" in captured.out
