"""``fgnav fleet`` inputs and ``--scheduler`` (review, 2026-12-08): an input that yields no flight
(an empty folder, a pattern that matches nothing, a missing path) is an error row while the other
inputs' flights run; a native flight folder that lost its ``meta.json`` gets a row naming it;
an empty, refused, UCX or (on a rerun with nothing to run) malformed ``--scheduler`` is a
one-line error."""

from __future__ import annotations

import json
import re
import shutil
import socket
import time
from pathlib import Path

import pytest
from fgnav.datasets.simulate import SimOptions, simulate_to_folder
from testutil import local_test_cluster

from fgnav.cli import main
from fgnav.fleet import (
    FleetError,
    InputProblem,
    check_scheduler_address,
    discover,
    find_flights,
)


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    """One simulated 8 s flight (no images)."""
    return simulate_to_folder(
        "two-turns",
        tmp_path_factory.mktemp("one") / "tt4",
        seed=4,
        options=SimOptions(duration=8.0, images=False),
    )


def _ucx_usable() -> bool:
    from distributed.comm.registry import backends

    try:
        backends["ucx"].get_connector()
    except Exception:
        return False
    return True


def _closed_port() -> int:
    """A loopback port nothing listens on (bound, then closed)."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


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


@pytest.mark.parametrize(
    ("address", "why"),
    [
        ("", "--scheduler '': an empty address; expected tcp://HOST:PORT"),
        ("  ", "--scheduler '  ': an empty address"),
        ("ucx://127.0.0.1:8786", "the ucx:// protocol is not usable with this Dask installation"),
    ],
)
def test_scheduler_address_checks_without_contact(address, why, flight, tmp_path, capsys):
    """``""`` ran the fleet on a LocalCluster; ``ucx://`` (its package not installed) failed at
    the connection with ``TypeError: Can't instantiate abstract class UCXConnector``."""
    if address.startswith("ucx") and _ucx_usable():
        pytest.skip("Dask's UCX support is installed here")
    with pytest.raises(FleetError, match=re.escape(why)):
        check_scheduler_address(address)
    t0 = time.monotonic()
    argv = ["fleet", str(flight), "--out", str(tmp_path / "o"), "--scheduler", address]
    assert main([*argv, "--no-progress"]) == 1
    assert time.monotonic() - t0 < 10
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and why in err[0], err
    assert not (tmp_path / "o").exists()  # (nothing started, nothing written)


@pytest.mark.parametrize("scheme", ["tcp://", "", "ws://"])
def test_refused_scheduler_is_named_at_once(scheme, flight, tmp_path, capsys):
    """Nothing listening: 20 s, then "not a Dask scheduler (its reply does not read as one:
    OSError: Timed out trying to connect ...)" although nothing replied (ws://: 20 s, then
    "cannot connect (OSError: Timed out ...)")."""
    port = _closed_port()
    address = f"{scheme}127.0.0.1:{port}"
    t0 = time.monotonic()
    argv = ["fleet", str(flight), "--out", str(tmp_path / "o"), "--scheduler", address]
    assert main([*argv, "--no-progress"]) == 1
    assert time.monotonic() - t0 < 10
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"fgnav fleet: error: --scheduler {address}: no Dask scheduler answers at 127.0.0.1 "
        f"port {port} (connection refused: nothing listens there)"
    ]


@pytest.mark.slow
def test_bad_inputs_are_rows_and_the_rerun_checks_the_address(flight, tmp_path, capsys):
    """``fgnav fleet GOOD EMPTY --out O`` stopped before any flight ran ("EMPTY: no flights
    found in this folder"), and the scan left a flight folder without meta.json out without a
    word; a rerun that reuses every row never looked at ``--scheduler`` (exit 0 with ``""``)."""
    good = tmp_path / "good"
    shutil.copytree(flight, good / "tt4")
    lost = good / "lost"
    shutil.copytree(flight, lost)
    (lost / "meta.json").unlink()
    (tmp_path / "empty").mkdir()
    empty, pattern = str(tmp_path / "empty"), str(tmp_path / "nothere" / "*.ulg")
    out = tmp_path / "o"
    with local_test_cluster(2) as cluster:
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
    # A rerun of the good flight and the inputs without one: tt4's runs are reused, nothing to
    # run. The address is checked all the same ...
    argv = ["fleet", str(good / "tt4"), empty, pattern, "--out", str(out), "--no-progress"]
    for bad in ("", "ucx://127.0.0.1:8786", "tcp://127.0.0.1"):
        assert main([*argv, "--methods", "batch,fixed-lag", "--scheduler", bad]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"fgnav fleet: error: --scheduler {bad}"), err
    # ... by its form only: a well-formed address nobody answers is not contacted then.
    idle = f"tcp://127.0.0.1:{_closed_port()}"
    assert main([*argv, "--methods", "batch,fixed-lag", "--scheduler", idle]) == 0
    assert "6 runs: 0 ok, 2 skipped, 4 error" in capsys.readouterr().out
    rows = json.loads((out / "fleet.json").read_text())
    assert [r["status"] for r in rows] == ["skipped", "skipped", *["error"] * 4]
