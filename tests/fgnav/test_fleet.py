"""``fgnav fleet``: flight discovery, hashes, the isolated child (timeout, crash, memory limit),
the whole fleet on a 2-worker LocalCluster and on real ``dask scheduler`` / ``dask worker``
processes, with results equal to single-flight ``fgnav batch`` runs, and resume."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fgnav.datasets.simulate import SimOptions, simulate_to_folder

from fgnav.cli import main
from fgnav.fleet import (
    COLUMN_DOC,
    COLUMNS,
    FleetError,
    content_hash,
    crash_summary,
    discover,
    flight_name,
    hist_bin_edges,
    options_hash,
    run_flight_job,
    write_report,
)
from fgnav.fleet_worker import ABORT_ENV, error_reason

#: The six good flights: (scenario, seed); 6 s each, no images.
GOOD = [
    ("two-turns", 1),
    ("two-turns", 2),
    ("circle", 3),
    ("two-turns", 4),
    ("circle", 5),
    ("two-turns", 6),
]
FLIGHT_S = 6.0
CRASH_NAME = "crashme"


def _simulate(folder: Path, scenario: str, seed: int, duration: float = FLIGHT_S) -> Path:
    return simulate_to_folder(
        scenario, folder, seed=seed, options=SimOptions(duration=duration, images=False)
    )


@pytest.fixture(scope="module")
def tiny_flight(tmp_path_factory) -> Path:
    """One simulated flight (for the child-process tests)."""
    return _simulate(tmp_path_factory.mktemp("tiny") / "tiny", "two-turns", 7)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    """A folder of 8 flights: 6 good ones (nested in sub-folders), a corrupt ULog and a good
    flight named ``crashme`` whose child the test hook aborts."""
    root = tmp_path_factory.mktemp("campaign")
    for i, (scenario, seed) in enumerate(GOOD):
        _simulate(root / f"day{i % 2}" / f"{scenario}-{seed}", scenario, seed)
    (root / "day1" / "broken.ulg").write_bytes(b"ULog\x01\x12" + bytes(range(256)) * 8)
    _simulate(root / CRASH_NAME, "circle", 8)
    return root


@pytest.fixture(scope="module")
def batch_ates(campaign, tmp_path_factory) -> dict[str, float]:
    """ATE of single-flight ``fgnav batch`` on each good flight (from its summary.json)."""
    out = tmp_path_factory.mktemp("batch")
    ates = {}
    for i, (scenario, seed) in enumerate(GOOD):
        name = f"{scenario}-{seed}"
        assert (
            main(
                [
                    "batch",
                    str(campaign / f"day{i % 2}" / name),
                    "--out",
                    str(out / name),
                    "--no-progress",
                ]
            )
            == 0
        )
        summary = json.loads((out / name / "summary.json").read_text())
        ates[name] = summary["metrics"]["ate_rmse_m"]
    return ates


# ----------------------------------------------------------------------------------------------
# Fast: discovery, hashes, the child
# ----------------------------------------------------------------------------------------------


def test_discover_folders_globs_and_errors(tmp_path):
    (tmp_path / "a" / "f1").mkdir(parents=True)
    (tmp_path / "a" / "f1" / "meta.json").write_text("{}")
    (tmp_path / "a" / "f1" / "inner.ulg").write_bytes(b"x")  # inside a flight: not a flight
    (tmp_path / "a" / "b").mkdir()
    (tmp_path / "a" / "b" / "log1.ulg").write_bytes(b"x")
    (tmp_path / "a" / "b" / "notes.txt").write_text("x")
    (tmp_path / "a" / "b" / "fleet.toml").write_text("[graph]\nkeyframe_hz = 10\n")
    (tmp_path / "a" / "b" / "m.toml").write_text('[imu]\nformat = "euroc"\npath = "x.csv"\n')
    found = discover([str(tmp_path / "a")])
    assert [f.name for f in found] == ["f1", "log1", "m"]
    # Globs are expanded by fgnav; a flight given twice is listed once.
    pattern = str(tmp_path / "**" / "*.ulg")
    found = discover([pattern, str(tmp_path / "a" / "b" / "log1.ulg")])
    assert [f.name for f in found] == ["log1", "inner"]
    assert found[1].input == str(tmp_path / "a" / "f1" / "inner.ulg")
    with pytest.raises(FleetError, match="no such file"):
        discover([str(tmp_path / "nope")])
    with pytest.raises(FleetError, match="matches"):
        discover([str(tmp_path / "*.bag")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(FleetError, match="no flights"):
        discover([str(tmp_path / "empty")])
    assert flight_name(tmp_path / "MH_01" / "mav0") == "MH_01"


@pytest.mark.realdata
def test_discover_finds_crazyflie_logs_without_a_suffix(real_data, tmp_path):
    """A folder of Crazyflie SD-card logs (no file suffix) is scanned by content (it was "no
    flights found in this folder"); its README is not a flight. A damaged copy (truncated: CRC
    mismatch) and a manifest that is not TOML are taken, so that their rows say why (review,
    2026-12-07: the scan left them out, "1 flights, 1 ok"); a TOML without ``[imu]`` is not."""
    import shutil

    folder = tmp_path / "cf"
    folder.mkdir()
    src = real_data / "crazyflie_util_flowdeck"
    shutil.copy(src / "0425-traj1", folder / "0425-traj1")
    (folder / "README.md").write_text("# flights\n")
    data = (src / "0425-traj3").read_bytes()
    (folder / "0425-traj3-cut").write_bytes(data[: len(data) // 2])
    (folder / "config.toml").write_text("[graph]\nkeyframe_hz = 10\n")
    (folder / "typo.toml").write_text("[imu\nformat = 'euroc'\n")
    found = discover([str(folder)])
    assert [f.name for f in found] == ["0425-traj1", "0425-traj3-cut", "typo"]


def test_content_hash_follows_content_not_place(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        (d / "sub").mkdir(parents=True)
        (d / "meta.json").write_text('{"x": 1}')
        (d / "sub" / "imu.csv").write_bytes(b"1,2,3\n")
    assert content_hash(a) == content_hash(b)
    (b / "sub" / "imu.csv").write_bytes(b"1,2,4\n")
    assert content_hash(a) != content_hash(b)
    # A manifest's hash covers the files it names.
    data = tmp_path / "data"
    data.mkdir()
    (data / "imu.csv").write_text("1\n")
    m = tmp_path / "m.toml"
    m.write_text('root = "data"\n[imu]\nformat = "euroc"\npath = "imu.csv"\n')
    h0 = content_hash(m)
    (data / "imu.csv").write_text("2\n")
    assert content_hash(m) != h0
    assert options_hash("batch", {}) != options_hash("batch", {"graph": {"keyframe_hz": 5.0}})
    assert options_hash("batch", {}) != options_hash("fixed-lag", {})


def _job(path: Path, **kw) -> dict:
    return {
        "flight": kw.pop("flight", path.name),
        "path": str(path),
        "methods": ["batch"],
        "config": {},
        "out_dir": None,
        "timeout_s": None,
        "memory_limit_mb": None,
        **kw,
    }


def test_child_timeout_and_crash_become_rows(tiny_flight, monkeypatch):
    rows = run_flight_job(_job(tiny_flight, timeout_s=0.2))
    assert [(r["method"], r["status"]) for r in rows] == [("batch", "timeout")]
    assert "0.2 s" in rows[0]["reason"] and rows[0]["task_wall_s"] < 5.0
    monkeypatch.setenv(ABORT_ENV, tiny_flight.name)
    rows = run_flight_job(_job(tiny_flight))
    assert rows[0]["status"] == "crashed"
    assert "SIGABRT" in rows[0]["reason"] and "\n" not in rows[0]["reason"]
    assert "Fatal Python error: Aborted in run_job (fgnav/fleet_worker.py:" in rows[0]["reason"]
    monkeypatch.delenv(ABORT_ENV)
    rows = run_flight_job(_job(tiny_flight, methods=["batch", "ekf-vo002", "nonsense"]))
    assert [r["status"] for r in rows] == ["ok", "error", "error"]
    assert rows[0]["ate_rmse_m"] < 0.1
    assert rows[0]["duration_s"] == pytest.approx(FLIGHT_S, abs=0.02)
    assert "needs" in rows[1]["reason"] and "unknown method" in rows[2]["reason"]


def test_crash_summary_names_the_fatal_error_and_the_crashing_frame():
    dump = """some warning
Fatal Python error: Segmentation fault

Thread 0x00007f0000000001 (most recent call first):
  File "/x/other.py", line 3 in wait

Current thread 0x00007fd89209ab80 (most recent call first):
  File "/x/fgnav/frontends/homography_vo.py", line 447 in estimate_homography
  File "/x/fgnav/solvers/vision.py", line 209 in run_homography_frontend

Extension modules: numpy._core._multiarray_umath, cv2 (total: 2)
"""
    assert crash_summary(dump) == (
        "Fatal Python error: Segmentation fault in estimate_homography "
        "(/x/fgnav/frontends/homography_vo.py:447)"
    )
    assert crash_summary("a\nMemoryError: x\n\nExtension modules: numpy\n") == "MemoryError: x"
    assert crash_summary("") == ""


def test_child_memory_limit_is_an_error_row(tiny_flight):
    rows = run_flight_job(_job(tiny_flight, memory_limit_mb=150))
    assert rows[0]["status"] in ("error", "crashed")
    assert "memory" in rows[0]["reason"] and "150 MB" in rows[0]["reason"]


def test_cli_rejects_bad_arguments_in_one_line(tmp_path, capsys):
    assert main(["fleet", str(tmp_path), "--out", str(tmp_path / "o"), "--workers", "0"]) == 1
    assert main(["fleet", str(tmp_path), "--out", str(tmp_path / "o"), "--methods", "magic"]) == 1
    assert main(["fleet", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3
    assert "--workers" in err[0] and "magic" in err[1] and "missing" in err[2]


def test_histogram_bins_are_shared_and_log_when_wide():
    edges, log = hist_bin_edges([0.006, 0.01, 0.012, 0.04, 0.2, 0.36])
    assert log and edges[0] == pytest.approx(0.006) and edges[-1] == pytest.approx(0.36)
    assert len(edges) == 6  # 5 bins, the minimum
    ratios = edges[1:] / edges[:-1]
    assert ratios == pytest.approx([ratios[0]] * 5)
    edges, log = hist_bin_edges([-12.8, -0.6, 0.2, 0.3] * 10)
    assert not log and len(edges) == 21 and edges[0] == -12.8 and edges[-1] == 0.3
    assert not hist_bin_edges([0.01, 0.02], log=None)[1]


def test_report_counts_ranks_and_explains_columns(tmp_path):
    def row(flight, method, status, ate=None, reason=""):
        r = {c: None for c in COLUMNS}
        r.update(
            flight=flight,
            input=f"in/{flight}",
            method=method,
            status=status,
            reason=reason,
            duration_s=60.0,
            runtime_s=1.0 + (ate or 0.0),
            ate_rmse_m=ate,
            scale_err_pct={"0": 10 * (ate or 0.0)},
            drag_k_per_s=[0.38, 0.4],
        )
        return r

    rows = [row(f"f{i}", "batch", "ok" if i % 2 else "skipped", 0.01 * (i + 1)) for i in range(7)]
    rows += [
        row("nogt", "batch", "ok"),
        row("bad", "batch", "error", reason="bad.ulg: x"),
        row("f0", "fixed-lag", "crashed", reason="child interpreter killed by SIGABRT"),
    ]
    path = write_report(rows, tmp_path, "Run today.")
    text = path.read_text()
    assert "Run today." in text
    assert "9 flights, 10 runs: 4 ok, 4 skipped, 1 error, 1 crashed (`skipped`" in text
    worst = text.split("## Worst flights by ATE: batch")[1].split("##")[0]
    assert "1 finished run(s) without ground truth are not ranked" in worst
    ranked = [
        line.split("|")[1].strip()
        for line in worst.splitlines()
        if line.startswith("| f") and "flight" not in line
    ]
    assert ranked == ["f6", "f5", "f4", "f3", "f2"]
    assert "SIGABRT" in text.split("## Failed runs")[1].split("## All runs")[0]
    for c, doc in COLUMN_DOC.items():
        assert f"- `{c}`: {doc}" in text
    for name in ("ate", "scale_err", "drag_k", "runtime"):
        assert (tmp_path / "figures" / f"{name}.png").stat().st_size > 1000


# ----------------------------------------------------------------------------------------------
# Slow: whole fleets
# ----------------------------------------------------------------------------------------------


def _check_table(out: Path, campaign: Path, batch_ates: dict[str, float], good_status: str):
    rows = json.loads((out / "fleet.json").read_text())
    assert len(rows) == 8 and all(list(r) == list(COLUMNS) for r in rows)
    by = {r["flight"]: r for r in rows}
    assert by["broken"]["status"] == "error"
    assert "broken.ulg" in by["broken"]["reason"] and "ULog" in by["broken"]["reason"]
    assert by[CRASH_NAME]["status"] == "crashed" and "SIGABRT" in by[CRASH_NAME]["reason"]
    for name, ate in batch_ates.items():
        r = by[name]
        assert r["status"] == good_status, r
        assert r["reason"] == ""
        assert abs(r["ate_rmse_m"] - ate) < 1e-9
        assert r["duration_s"] == pytest.approx(FLIGHT_S, abs=0.02)
        assert "slam" in r["streams"] and len(r["drag_k_per_s"]) == 2
        summary = json.loads((out / r["out_dir"] / "summary.json").read_text())
        assert summary["metrics"]["ate_rmse_m"] == r["ate_rmse_m"]
        assert (out / r["out_dir"] / "estimate.tum").is_file()
        assert (out / r["out_dir"]).parent.joinpath("child-stderr.txt").is_file()
    csv_lines = (out / "fleet.csv").read_text().splitlines()
    assert csv_lines[0] == ",".join(COLUMNS) and len(csv_lines) == 9
    report = (out / "fleet.md").read_text()
    assert "Worst flights by ATE: batch" in report and "SIGABRT" in report
    assert (out / "figures" / "ate.png").is_file()
    return rows


@pytest.mark.slow
def test_fleet_on_a_local_cluster_matches_batch_and_resumes(
    campaign, batch_ates, tmp_path, monkeypatch, capsys
):
    monkeypatch.setenv(ABORT_ENV, CRASH_NAME)
    out = tmp_path / "fleet"
    argv = [
        "fleet",
        str(campaign),
        "--out",
        str(out),
        "--workers",
        "2",
        "--timeout",
        "120",
        "--no-progress",
    ]
    assert main(argv) == 0
    summary = capsys.readouterr().out
    assert "8 flights, 8 runs: 6 ok, 0 skipped, 1 error, 0 timeout, 1 crashed" in summary
    assert "on 2 workers" in summary
    first = _check_table(out, campaign, batch_ates, "ok")
    # Rerun: the six good flights are skipped with their figures; the two failures run again.
    assert main(argv) == 0
    assert "6 skipped, 1 error, 0 timeout, 1 crashed" in capsys.readouterr().out
    again = _check_table(out, campaign, batch_ates, "skipped")
    keep = ("ate_rmse_m", "runtime_s", "input_hash", "options_hash", "out_dir")
    for a, b in zip(first, again, strict=True):
        if a["status"] == "ok":
            assert all(a[k] == b[k] for k in keep)
    # --force reruns a flight done before.
    one = str(campaign / "day0" / "two-turns-1")
    argv = ["fleet", one, "--out", str(out), "--workers", "1", "--force", "--no-progress"]
    assert main(argv) == 0
    assert "1 flights, 1 runs: 1 ok, 0 skipped" in capsys.readouterr().out


@pytest.mark.slow
def test_resume_survives_other_runs_and_a_lost_table(campaign, batch_ates, tmp_path, capsys):
    a, b = (str(campaign / "day0" / "two-turns-1"), str(campaign / "day1" / "two-turns-2"))
    out = tmp_path / "fleet"

    def fleet(*inputs: str) -> dict[str, dict]:
        argv = ["fleet", *inputs, "--out", str(out), "--workers", "1", "--no-progress"]
        assert main(argv) == 0
        capsys.readouterr()
        return {r["flight"]: r for r in json.loads((out / "fleet.json").read_text())}

    assert fleet(a)["two-turns-1"]["status"] == "ok"
    assert list(fleet(b)) == ["two-turns-2"]  # fleet.json now holds the second run only
    both = fleet(a, b)  # the first flight's result comes from the journal
    assert [r["status"] for r in both.values()] == ["skipped", "skipped"]
    assert abs(both["two-turns-1"]["ate_rmse_m"] - batch_ates["two-turns-1"]) < 1e-9
    # The client lost its table (killed before writing it) and a flight's files are gone: the
    # journal still resumes the other; the one without files runs again.
    (out / "fleet.json").unlink()
    shutil.rmtree(out / both["two-turns-1"]["out_dir"])
    again = fleet(a, b)
    assert [again[n]["status"] for n in ("two-turns-1", "two-turns-2")] == ["ok", "skipped"]
    assert abs(again["two-turns-1"]["ate_rmse_m"] - batch_ates["two-turns-1"]) < 1e-9
    # A torn last line of the journal (an interrupted write) is skipped with a warning.
    with open(out / "fleet-runs.jsonl", "a") as fh:
        fh.write('{"flight": "torn')
    assert [r["status"] for r in fleet(a, b).values()] == ["skipped", "skipped"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=5)


@pytest.fixture
def dask_cluster(tmp_path):
    """Real ``dask scheduler`` and ``dask worker`` processes (2 single-threaded workers) on
    127.0.0.1; the workers carry the crash hook; stopped (bounded time) at the end."""
    dask_cli = shutil.which("dask", path=str(Path(sys.executable).parent)) or "dask"
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, ABORT_ENV: CRASH_NAME}
    procs = []
    logs = [open(tmp_path / "scheduler.log", "w"), open(tmp_path / "worker.log", "w")]
    try:
        procs.append(
            subprocess.Popen(
                [
                    dask_cli,
                    "scheduler",
                    "--host",
                    "127.0.0.1",
                    "--port",
                    str(port),
                    "--no-dashboard",
                ],
                stdout=logs[0],
                stderr=subprocess.STDOUT,
                env=env,
                start_new_session=True,
            )
        )
        procs.append(
            subprocess.Popen(
                [
                    dask_cli,
                    "worker",
                    address,
                    "--host",
                    "127.0.0.1",
                    "--nthreads",
                    "1",
                    "--nworkers",
                    "2",
                    "--no-dashboard",
                ],
                stdout=logs[1],
                stderr=subprocess.STDOUT,
                env=env,
                start_new_session=True,
            )
        )
        from distributed import Client

        deadline = time.monotonic() + 60
        with Client(address, timeout="30s") as client:
            while len(client.scheduler_info()["workers"]) < 2:
                assert time.monotonic() < deadline, (tmp_path / "worker.log").read_text()
                time.sleep(0.5)
        yield address
    finally:
        for p in reversed(procs):
            _stop(p)
        for f in logs:
            f.close()


@pytest.mark.slow
def test_fleet_on_a_dask_scheduler(campaign, batch_ates, dask_cluster, tmp_path, capsys):
    out = tmp_path / "fleet"
    argv = ["fleet", str(campaign), "--out", str(out), "--scheduler", dask_cluster, "--no-progress"]
    assert main(argv) == 0
    assert "6 ok, 0 skipped, 1 error, 0 timeout, 1 crashed" in capsys.readouterr().out
    rows = _check_table(out, campaign, batch_ates, "ok")
    assert len({r["worker"] for r in rows if r["status"] == "ok"}) == 2


def test_allocation_failure_without_memory_error_is_named_under_a_limit():
    """Under RLIMIT_AS a C extension may fail an allocation without setting MemoryError (seen in
    a clean-clone CI run: ``SystemError: error return without exception set``)."""
    e = SystemError("error return without exception set")
    assert error_reason(e, 150).startswith("out of memory (--memory-limit 150 MB): SystemError")
    assert error_reason(e, None) == "SystemError: error return without exception set"
    assert error_reason(MemoryError(), 150).startswith("out of memory (--memory-limit 150 MB)")
    # The wording of a builtin's failure (seen 2026-12-07: the child died inside compile()).
    e = SystemError("<built-in function compile> returned NULL without setting an exception")
    assert error_reason(e, 150).startswith("out of memory (--memory-limit 150 MB): SystemError")
