"""``fgnav fleet`` inputs (review, 2026-12-08): an input that yields no flight (an empty folder, a
pattern that matches nothing, a missing path) is an error row while the other inputs' flights
run; a native flight folder that lost its ``meta.json`` gets a row naming it."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import pytest
from fgnav.datasets.simulate import SimOptions, simulate_to_folder

from fgnav.cli import main
from fgnav.fleet import FleetError, InputProblem, discover, find_flights


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    """One simulated 8 s flight (no images)."""
    return simulate_to_folder(
        "two-turns",
        tmp_path_factory.mktemp("one") / "tt4",
        seed=4,
        options=SimOptions(duration=8.0, images=False),
    )


def test_inputs_without_flights_are_listed_not_raised(flight, tmp_path):
    good = tmp_path / "good"
    shutil.copytree(flight, good / "tt4")
    (tmp_path / "empty").mkdir()
    (tmp_path / "dirs" / "x").mkdir(parents=True)  # a pattern matching folders without flights
    lost = tmp_path / "camp" / "lost"
    shutil.copytree(flight, lost)
    (lost / "meta.json").unlink()
    inputs = [
        str(good),
        str(tmp_path / "empty"),
        str(tmp_path / "nothere" / "*.ulg"),
        str(tmp_path / "missing"),
        str(tmp_path / "dirs" / "*"),
        str(tmp_path / "camp"),
        str(tmp_path / "empty"),  # (an input given twice: one problem)
    ]
    flights, problems = find_flights(inputs)
    assert [(f.name, f.path) for f in flights] == [("tt4", good / "tt4"), ("lost", lost)]
    assert problems == [
        InputProblem(inputs[1], f"{inputs[1]}: no flights found in this folder"),
        InputProblem(inputs[2], f"{inputs[2]}: no file or folder matches this pattern"),
        InputProblem(inputs[3], f"{inputs[3]}: no such file or folder"),
        InputProblem(inputs[4], f"{inputs[4]}: no flights found in this pattern's folders"),
    ]
    assert [q.name for q in problems] == ["empty", inputs[2], "missing", inputs[4]]
    # The folder that lost its meta.json, given itself, is a flight too (its row says why).
    assert [f.path for f in find_flights([str(lost)])[0]] == [lost]
    # discover() stays strict: the first input without flights is the error.
    with pytest.raises(FleetError, match="empty: no flights found in this folder"):
        discover(inputs)


def test_only_inputs_without_flights_is_one_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    out = tmp_path / "o"
    argv = ["fleet", str(tmp_path / "empty"), str(tmp_path / "none*.ulg"), "--out", str(out)]
    assert main([*argv, "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"fgnav fleet: error: no flights in the inputs: {tmp_path / 'empty'}: no flights found"
        f" in this folder; {tmp_path / 'none*.ulg'}: no file or folder matches this pattern"
    ]
    assert not out.exists()


def _cluster():
    """A LocalCluster reached by address (threads, 2 workers, loopback, no dashboard)."""
    from distributed import LocalCluster

    return LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=False,
        protocol="tcp://",
        host="127.0.0.1",
        dashboard_address=None,
        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        silence_logs=logging.WARNING,
    )


@pytest.mark.slow
def test_bad_inputs_are_rows_beside_the_flights_that_ran(flight, tmp_path, capsys):
    """``fgnav fleet GOOD EMPTY --out O`` stopped before any flight ran ("EMPTY: no flights
    found in this folder"), and the scan left a flight folder without meta.json out without a
    word."""
    good = tmp_path / "good"
    shutil.copytree(flight, good / "tt4")
    lost = good / "lost"
    shutil.copytree(flight, lost)
    (lost / "meta.json").unlink()
    (tmp_path / "empty").mkdir()
    empty, pattern = str(tmp_path / "empty"), str(tmp_path / "nothere" / "*.ulg")
    out = tmp_path / "o"
    with _cluster() as cluster:
        addr = cluster.scheduler_address
        argv = ["fleet", str(good), empty, pattern, "--out", str(out), "--no-progress"]
        assert main([*argv, "--scheduler", addr, "--methods", "batch,fixed-lag"]) == 0
    cap = capsys.readouterr()
    rows = json.loads((out / "fleet.json").read_text())
    got = [(r["flight"], r["input"], r["method"], r["status"]) for r in rows]
    assert got == [
        ("lost", str(lost), "batch", "error"),
        ("lost", str(lost), "fixed-lag", "error"),
        ("tt4", str(good / "tt4"), "batch", "ok"),
        ("tt4", str(good / "tt4"), "fixed-lag", "ok"),
        ("empty", empty, "batch", "error"),
        ("empty", empty, "fixed-lag", "error"),
        (pattern, pattern, "batch", "error"),
        (pattern, pattern, "fixed-lag", "error"),
    ]
    assert rows[0]["reason"] == (
        f"{lost}: no meta.json: a native flight folder needs it (this one has calib.yaml, "
        "imu.csv, attitude.csv, range.csv, yaw.csv, slam.csv, ground_truth.csv)"
    )
    assert rows[2]["ate_rmse_m"] < 0.1
    assert rows[4]["reason"] == f"{empty}: no flights found in this folder"
    assert rows[6]["reason"] == f"{pattern}: no file or folder matches this pattern"
    failed = cap.err.strip().splitlines()
    assert f"empty ({empty}) batch: error: {empty}: no flights found in this folder" in failed
    assert f"lost ({lost}) fixed-lag: error: {lost}: no meta.json: " in "\n".join(failed)
    assert len(failed) == 6, failed
    summary = "fleet: 2 flights (and 2 input(s) without a flight), 8 runs: 2 ok, 0 skipped, 6 error"
    assert summary in cap.out
    report = (out / "fleet.md").read_text()
    assert "2 flights and 2 input(s) without a flight (see Failed runs), 8 runs: 2 ok, 6 error" in (
        report
    )
    assert f"| empty | {empty} | batch | error | {empty}: no flights found in this folder |" in (
        report
    )
