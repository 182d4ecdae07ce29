"""``fgnav fleet`` robustness: fleets sharing a scheduler, a scheduler without workers or that
loses them, bad ``--scheduler`` / limit values, damaged flights in a scanned folder, printed
failures, Ctrl-C, duplicate methods and flights, ``--out`` inside a flight, ``--workers``."""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

import pytest
from fgnav.datasets.simulate import SimOptions, simulate_to_folder
from testutil import local_test_cluster

from fgnav.fleet import FleetOptions, content_hash, run_fleet


def _simulate(folder: Path, seed: int, scenario: str = "two-turns") -> Path:
    return simulate_to_folder(
        scenario, folder, seed=seed, options=SimOptions(duration=4.0, images=False)
    )


@pytest.fixture(scope="module")
def twins(tmp_path_factory) -> tuple[Path, Path]:
    """Two flights both named ``tt1`` with different content (a/tt1, b/tt1)."""
    root = tmp_path_factory.mktemp("twins")
    return _simulate(root / "a" / "tt1", 11), _simulate(root / "b" / "tt1", 12)


@pytest.fixture
def scheduler():
    """A LocalCluster reached by address (threads, 2 workers, loopback, no dashboard)."""
    with local_test_cluster(2) as cluster:
        yield cluster


def _opts(**kw) -> FleetOptions:
    return FleetOptions(progress=False, **kw)


def test_concurrent_fleets_on_one_scheduler_get_their_own_results(twins, scheduler, tmp_path):
    """Two fleets on one scheduler, each with a flight named tt1 (different content) submitted
    at once: each gets its own flight's result (the Dask keys were ``fleet-0-tt1`` in both, and
    the second fleet got the first's estimate and no flight files)."""
    outs = [tmp_path / "A", tmp_path / "B"]
    res: dict[int, object] = {}

    def go(k: int) -> None:
        res[k] = run_fleet([str(twins[k])], outs[k], _opts(scheduler=scheduler.scheduler_address))

    threads = [threading.Thread(target=go, args=(k,)) for k in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    rows = [res[k].rows[0] for k in (0, 1)]
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert rows[0]["ate_rmse_m"] != rows[1]["ate_rmse_m"]
    for k, r in enumerate(rows):
        assert r["input_hash"] == content_hash(twins[k])
        summary = json.loads((outs[k] / r["out_dir"] / "summary.json").read_text())
        assert summary["metrics"]["ate_rmse_m"] == r["ate_rmse_m"]


def test_local_cluster_leaves_port_8787_alone():
    """The LocalCluster's scheduler bound its HTTP server to 8787 despite
    ``dashboard_address=None`` (and warned when another Dask or Jupyter had it)."""
    import warnings

    from fgnav.fleet import _dask_client

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        client, cluster = _dask_client(_opts(workers=1), 1)
        try:
            assert cluster.scheduler.http_server.port != 8787
        finally:
            client.close()
            cluster.close()
    assert not [w for w in caught if "8787" in str(w.message)]


@pytest.fixture
def fake_servers():
    """Two loopback TCP servers that are not Dask schedulers: one answers every connection with
    HTTP bytes, one accepts and says nothing (as a web server waiting for a request)."""
    import socket

    socks, conns = [], []

    def serve(s: socket.socket, reply: bytes) -> None:
        while True:
            try:
                c, _ = s.accept()
            except OSError:
                return
            conns.append(c)
            if reply:
                try:
                    c.sendall(reply)
                except OSError:
                    pass

    ports = []
    for reply in (b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n" * 4, b""):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        s.listen()
        socks.append(s)
        ports.append(s.getsockname()[1])
        threading.Thread(target=serve, args=(s, reply), daemon=True).start()
    yield ports
    for c in socks + conns:
        c.close()


def test_bad_scheduler_values_are_one_line_errors(
    twins, fake_servers, tmp_path, monkeypatch, capsys
):
    """``foo`` and ``http://...`` printed a ValueError traceback, a server answering garbage a
    numpy allocation traceback, and a silent server (an HTTP port) held the client >200 s."""
    import time

    import fgnav.fleet
    from fgnav.cli import main

    monkeypatch.setattr(fgnav.fleet, "CONNECT_DEADLINE_S", 2.0)
    garbage, silent = fake_servers
    cases = {
        "foo": "no HOST:PORT",
        "http://127.0.0.1:8786": "http:// is not a Dask protocol",
        f"tcp://127.0.0.1:{garbage}": "not a Dask scheduler",
        f"tcp://127.0.0.1:{silent}": "no Dask scheduler answered within 2 s",
    }
    for address, why in cases.items():
        t0 = time.monotonic()
        argv = ["fleet", str(twins[0]), "--out", str(tmp_path / "o"), "--scheduler", address]
        assert main([*argv, "--no-progress"]) == 1
        assert time.monotonic() - t0 < 10
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"--scheduler {address}: " in err[0] and why in err[0], err


def test_a_scheduler_without_workers_is_a_one_line_error(twins, tmp_path):
    """It waited forever, without a word."""
    from fgnav.fleet import FleetError

    with local_test_cluster(0) as cluster:
        opts = _opts(scheduler=cluster.scheduler_address, worker_wait_s=1.0)
        with pytest.raises(FleetError, match=r"no Dask worker joined within 1 s") as e:
            run_fleet([str(twins[0])], tmp_path / "o", opts)
        assert "\n" not in str(e.value)


def test_flights_left_when_every_worker_is_gone_are_crashed_rows(twins, tmp_path):
    """All workers stopped mid-run: the fleet waited forever (the tasks wait for a worker); now
    the unfinished flights are named ``crashed`` rows after ``no_worker_s``."""
    import time

    with local_test_cluster(1) as cluster:
        opts = _opts(scheduler=cluster.scheduler_address, no_worker_s=1.0)
        res = {}
        t = threading.Thread(
            target=lambda: res.update(r=run_fleet([str(p) for p in twins], tmp_path / "o", opts))
        )
        t.start()
        deadline = time.monotonic() + 30
        while not any(ts.state == "processing" for ts in list(cluster.scheduler.tasks.values())):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        cluster.scale(0)
        t.join(60)
        assert not t.is_alive()
    rows = res["r"].rows
    assert len(rows) == 2 and all(r["flight"] == "tt1" for r in rows)
    lost = [r for r in rows if r["status"] == "crashed"]
    assert lost and all("no Dask worker left for 1 s" in r["reason"] for r in lost)
    assert {r["input"] for r in rows} == {str(p) for p in twins}


@pytest.mark.parametrize(
    "flag, value",
    [
        ("--timeout", "nan"),
        ("--timeout", "inf"),
        ("--timeout", "1e300"),
        ("--timeout", "-1"),
        ("--memory-limit", "nan"),
        ("--memory-limit", "inf"),
        ("--memory-limit", "1e30"),
        ("--memory-limit", "0"),
    ],
)
def test_limits_must_be_finite_positive_and_fit(flag, value, twins, tmp_path, capsys):
    """nan, inf and 1e300 passed the check; Dask printed a traceback and every run crashed."""
    from fgnav.cli import main

    argv = ["fleet", str(twins[0]), "--out", str(tmp_path / "o"), flag, value, "--no-progress"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{flag} must be a finite number > 0" in err[0], err
    assert not (tmp_path / "o").exists()


def test_failures_are_printed_and_all_failed_exits_1(twins, scheduler, tmp_path, capsys):
    """Failed rows were only counted and written; a fleet where every run failed exited 0."""
    from fgnav.cli import main

    bad = tmp_path / "bad.ulg"
    bad.write_bytes(b"not a ulog")
    out = str(tmp_path / "o")
    addr = scheduler.scheduler_address
    argv = ["fleet", str(bad), "--out", out, "--scheduler", addr, "--no-progress"]
    assert main(argv) == 1
    cap = capsys.readouterr()
    err = [line for line in cap.err.splitlines() if line.startswith("bad (")]
    assert len(err) == 1 and err[0].startswith(f"bad ({bad}) batch: error: ") and "ULog" in err[0]
    assert "1 flights, 1 runs: 0 ok, 0 skipped, 1 error" in cap.out
    assert (tmp_path / "o" / "fleet.csv").is_file()
    # One good flight with the bad one: printed again, exit 0.
    argv = ["fleet", str(bad), str(twins[0]), "--out", out, "--scheduler", addr, "--no-progress"]
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert [line for line in cap.err.splitlines() if line.startswith("bad (")] == err
    assert "1 ok, 0 skipped, 1 error" in cap.out


def test_out_inside_the_flight_folder_is_not_its_content(twins, scheduler, tmp_path):
    """``--out`` inside the flight: the fleet's own outputs joined the flight's content hash, so
    a rerun never skipped (and left one flights/ folder per run)."""
    import shutil

    flight = tmp_path / "tt1"
    shutil.copytree(twins[0], flight)
    h = content_hash(flight)
    opts = _opts(scheduler=scheduler.scheduler_address)
    first = run_fleet([str(flight)], flight / "fleet", opts).rows[0]
    assert first["status"] == "ok" and first["input_hash"] == h
    again = run_fleet([str(flight)], flight / "fleet", opts).rows[0]
    assert again["status"] == "skipped" and again["input_hash"] == h
    assert len(list((flight / "fleet" / "flights").iterdir())) == 1
    assert content_hash(flight) != h  # (without the exclusion the outputs count)


def test_a_method_or_a_flight_named_twice_runs_once(twins, scheduler, tmp_path):
    """``--methods batch,batch`` ran batch twice per flight; two copies of one flight (a/tt1 and
    c/tt1, same content) ran at once into one flights/tt1-<hash>/ folder."""
    import shutil

    copy = tmp_path / "c" / "tt1"
    shutil.copytree(twins[0], copy)
    opts = _opts(scheduler=scheduler.scheduler_address, methods=("batch", "batch"))
    res = run_fleet([str(twins[0]), str(copy), str(twins[1])], tmp_path / "o", opts)
    assert [(r["input"], r["method"], r["status"]) for r in res.rows] == [
        (str(twins[0]), "batch", "ok"),
        (str(copy), "batch", "ok"),
        (str(twins[1]), "batch", "ok"),
    ]
    a, c, b = res.rows
    assert c["ate_rmse_m"] == a["ate_rmse_m"] and c["out_dir"] == a["out_dir"]
    assert a["out_dir"] != b["out_dir"]  # (same name, other content: its own folder)
    journal = (tmp_path / "o" / "fleet-runs.jsonl").read_text().splitlines()
    assert len(journal) == 2  # two flights run, not three runs (nor six)


def test_local_workers_are_capped_by_the_flights_and_warned_above_the_cores(caplog):
    """``--workers 1000`` started 1000 worker processes for a handful of flights."""
    from fgnav.fleet import default_workers, local_workers

    cores = default_workers()
    with caplog.at_level(logging.WARNING, logger="fgnav.fleet"):
        assert local_workers(1000, 3) == 3
    assert [r.getMessage() for r in caplog.records] == [
        f"--workers 1000: more than this machine's {cores} core(s)"
    ]
    caplog.clear()
    assert local_workers(None, 1000) == cores
    assert local_workers(None, 1) == 1
    assert local_workers(1, 5) == 1
    assert not caplog.records


def test_ctrl_c_is_one_line_and_leaves_no_child(tmp_path):
    """SIGINT to the fleet's process group, as a terminal's Ctrl-C (review, 2026-12-07): five
    tracebacks (the client's and every worker's), and each flight's child interpreter, in its own
    session, ran on. Now one line, exit 130, the workers ignore the SIGINT, the children die
    with them, and the done flights are in the journal for the rerun."""
    import os
    import signal
    import subprocess
    import sys
    import time

    flights = [_simulate(tmp_path / "in" / f"f{i}", 20 + i, "figure8") for i in range(6)]
    assert len(flights) == 6
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "fgnav.cli", "fleet", str(tmp_path / "in"), "--out", str(out)]
    proc = subprocess.Popen(
        [*cmd, "--workers", "1", "--no-progress"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    journal = out / "fleet-runs.jsonl"
    t_end = time.monotonic() + 120
    while time.monotonic() < t_end and not (journal.exists() and journal.read_text().strip()):
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("fgnav fleet: interrupted: ") and "of 6 flight(s) done" in last
    time.sleep(1.0)
    ps = subprocess.run(["ps", "-eo", "pid,pgid,cmd"], capture_output=True, text=True).stdout
    assert not [ln for ln in ps.splitlines() if "fgnav.fleet_worker" in ln and str(out) in ln]
    alive = [ln for ln in ps.splitlines() if "<defunct>" not in ln]  # (exited, not yet reaped)
    assert not [ln for ln in alive if ln.split()[1:2] == [str(proc.pid)]]
