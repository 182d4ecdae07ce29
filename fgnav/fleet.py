"""Fleets of logged flights: every flight's methods in a Dask task, one table.

:func:`run_fleet` finds the flights of its inputs (:func:`discover`), hashes each one's content
(:func:`content_hash`), skips the (flight, method) runs a previous run in the same output folder
already did with the same input and options (resume), and maps :func:`run_flight_job` over the
rest on a Dask cluster: a ``LocalCluster`` on this machine (loopback only, one single-threaded
worker per core) or an existing scheduler (``tcp://host:port``). The client writes the table
(:func:`write_table`) and the report (:func:`write_report`) from the returned dicts.

Isolation: a Dask task takes paths and returns plain dicts (GTSAM's CustomFactors do not pickle).
It runs the flight in a fresh child interpreter, ``python -m fgnav.fleet_worker`` (a
``subprocess``, so Dask's daemonic worker processes need no ``distributed.worker.daemon``
change), which calls the registry's methods (:mod:`fgnav.methods`, the same library calls as
``fgnav batch`` / ``online``). A native crash, a ``--timeout`` or the ``--memory-limit`` (the
child's ``RLIMIT_AS``) ends the child only: the task returns an error row (``crashed``,
``timeout``, ``error``) and the worker goes on with the next flight.

Outputs under ``out``: ``flights/<flight>-<8 hex of the content hash>/<method>/``
(``estimate.tum``, ``states.csv``, ``summary.json``, written by the child: on a cluster ``out``
must be a path every worker and the client share; the child's log beside them,
``child-stderr.txt``), ``fleet.csv``, ``fleet.json`` (typed rows, read back to resume),
``fleet.parquet`` (when pyarrow is importable), ``fleet.md`` and ``figures/``, and the journal
``fleet-runs.jsonl`` (each ``ok`` row appended as it arrives; resume reads it with ``fleet.json``,
so an interrupted client or a run over other flights into the same folder loses nothing).
"""

from __future__ import annotations

import csv
import glob
import hashlib
import json
import logging
import math
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
import uuid
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from fgnav.datasets.errors import FgnavError
from fgnav.fleet_worker import CRASHED, ERROR, OK, SKIPPED, TIMEOUT

log = logging.getLogger(__name__)

#: Columns of ``fleet.csv`` in order, each with its meaning (units in the names: ``_s`` seconds,
#: ``_m`` metres, ``_pct`` percent, ``_per_s`` 1/s; multi-valued cells as compact JSON).
COLUMN_DOC: dict[str, str] = {
    "flight": "flight name (the input's folder or file name)",
    "input": "the path as given (or as found under a given folder or glob)",
    "method": "registry name (`fgnav.methods`)",
    "status": "ok, error, timeout, crashed, or skipped (ok in an earlier run: figures kept)",
    "reason": "one-line error; empty when ok or skipped",
    "flag": "implausible estimate, as `fgnav compare` flags it (comma-separated codes: non-finite "
    "values, speed above 50 m/s over 1 s, ATE above max(1 m, 10 % of the path)); empty: none",
    "flags": "JSON list of the flags' reasons",
    "duration_s": "overlap of the flight's sensor streams [s]",
    "streams": "JSON list of the flight's streams",
    "ate_rmse_m": "ATE RMSE after the method's alignment [m] (ground truth only)",
    "scale_err_pct": "JSON {SLAM session: final scale error [%]} (ground truth only)",
    "slam_scale": "JSON {SLAM session: estimated scale [SLAM units per metre]}",
    "drag_k_per_s": "JSON [kx, ky] rotor-drag coefficient [1/s]; empty when the drag model is off",
    "solver_failures": "solver failures the method recovered from (fixed-lag)",
    "dropped": "JSON {reason: count} of measurements not used",
    "runtime_s": "the method's own run time [s]",
    "work_s": "child time loading the flight, running, scoring and writing [s]",
    "task_wall_s": "the Dask task's wall time, child start to result [s] (per flight)",
    "n_states": "states in the estimate",
    "input_hash": "sha256 of the input's content (with the files a manifest names)",
    "options_hash": "sha256 of the method, its config and fgnav's version",
    "out_dir": "outputs of the run, relative to the fleet folder (empty with --no-flight-files)",
    "worker": "Dask worker address",
}

#: Columns of ``fleet.csv`` in order.
COLUMNS = tuple(COLUMN_DOC)

#: Cells holding several values, written as compact JSON.
JSON_COLUMNS = ("flags", "streams", "scale_err_pct", "slam_scale", "drag_k_per_s", "dropped")

#: Failed statuses (counted by the progress bar and the summary line).
FAILED = (ERROR, TIMEOUT, CRASHED)

#: Statuses of runs a rerun does not repeat.
DONE = (OK, SKIPPED)

#: File suffixes of flights found when scanning a folder (folders: see :func:`is_flight`).
FLIGHT_SUFFIXES = (".ulg", ".bag", ".db3", ".mcap")

#: The child is single-threaded: one Dask worker per core, no BLAS or OpenMP threads on top.
SINGLE_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENCV_NUM_THREADS": "1",
}


class FleetError(FgnavError):
    """A fleet cannot start: no flights found, an unknown method, an unreachable scheduler."""


# ----------------------------------------------------------------------------------------------
# Finding flights
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FlightInput:
    """One flight of the fleet: its ``name`` in the table, the ``input`` as given, ``path``."""

    name: str
    input: str
    path: Path


def _is_euroc(p: Path) -> bool:
    return (p / "imu0" / "data.csv").is_file() or (p / "mav0" / "imu0" / "data.csv").is_file()


def _is_manifest(p: Path) -> bool:
    """A ``*.toml`` file that reads as a flight manifest (has an ``[imu]`` table)."""
    try:
        return isinstance(tomllib.loads(p.read_text()).get("imu"), dict)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False


def is_flight(p: Path) -> bool:
    """True when ``p`` is a flight ``fgnav info`` reads: a native flight folder (``meta.json``),
    a ROS 2 bag folder (``metadata.yaml``), an EuRoC folder, a log file (``*.ulg``, ``*.bag``,
    ``*.db3``, ``*.mcap``), a manifest (``*.toml`` with an ``[imu]`` table) or a Crazyflie
    SD-card log (any name: recognised by its header and CRC; a file without the log's magic
    first byte is not read further)."""
    if p.is_dir():
        return (p / "meta.json").is_file() or (p / "metadata.yaml").is_file() or _is_euroc(p)
    if p.suffix.lower() == ".toml":
        return _is_manifest(p)
    if not p.is_file():
        return False
    if p.suffix.lower() in FLIGHT_SUFFIXES:
        return True
    from fgnav.datasets.crazyflie import is_crazyflie_log

    return is_crazyflie_log(p)


def _damaged_flight(p: Path) -> bool:
    """A file a folder scan takes as a flight although it does not read as one, so that the
    table names why: a manifest (``*.toml``) that is not valid TOML, or a file that starts as
    a Crazyflie SD-card log (magic byte, version 1 or 2) but fails its header or CRC check (a
    truncated copy). Before, the scan left both out without a word."""
    if not p.is_file():
        return False
    if p.suffix.lower() == ".toml":
        try:
            tomllib.loads(p.read_text())
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            return True
        return False
    from fgnav.datasets.crazyflie import MAGIC

    try:
        with open(p, "rb") as fh:
            head = fh.read(3)
    except OSError:
        return False
    return len(head) == 3 and head[0] == MAGIC and int.from_bytes(head[1:], "little") in (1, 2)


def flight_name(p: Path) -> str:
    """Name of a flight in the table: its folder name (the parent of ``mav0``) or file stem."""
    p = Path(os.path.abspath(p))
    if p.name == "mav0":
        return p.parent.name
    return p.name if p.is_dir() else p.stem


def _lost_meta(p: Path) -> bool:
    """A folder that looks like a native flight folder but has no ``meta.json``
    (:func:`fgnav.datasets.native.lost_meta_json`): taken as a flight, so that its row names
    the missing file (the scan left it out without a word)."""
    from fgnav.datasets.native import lost_meta_json

    return bool(lost_meta_json(p))


def _scan(folder: Path) -> list[Path]:
    """Flights under ``folder`` (recursively; a flight folder is not searched further),
    damaged ones included (:func:`_damaged_flight`, :func:`_lost_meta`: their rows say why)."""
    found: list[Path] = []
    for root, dirs, files in os.walk(folder):
        dirs.sort()
        here = Path(root)
        keep = []
        for d in dirs:
            if d.startswith("."):
                continue
            if is_flight(here / d) or _lost_meta(here / d):
                found.append(here / d)
            else:
                keep.append(d)
        dirs[:] = keep
        found += [
            here / f for f in sorted(files) if is_flight(here / f) or _damaged_flight(here / f)
        ]
    return found


@dataclass(frozen=True)
class InputProblem:
    """A command-line input that yields no flight: the ``input`` as given and the ``reason``
    (one line naming it)."""

    input: str
    reason: str

    @property
    def name(self) -> str:
        """Its ``flight`` cell: the folder or file name, or the pattern as given."""
        return self.input if glob.has_magic(self.input) else flight_name(Path(self.input))


def find_flights(inputs: Sequence[str]) -> tuple[list[FlightInput], list[InputProblem]]:
    """The flights of the command line's inputs, in order, each once, and the inputs that yield
    none (a path that does not exist, a folder without flights, a pattern that matches nothing
    or only folders without flights), each once.

    Each input is a flight (taken as one even when its format is not recognised: reading it then
    fails with the reason, in the table) or a folder that is not a flight, scanned recursively;
    glob patterns (``logs/**/*.ulg``) are expanded here.
    """
    out: list[FlightInput] = []
    problems: list[InputProblem] = []
    seen: set[Path] = set()

    def add(p: Path, given: str) -> None:
        key = Path(os.path.abspath(p))
        if key not in seen:
            seen.add(key)
            out.append(FlightInput(flight_name(p), given, key))

    def problem(given: str, reason: str) -> None:
        if all(q.input != given for q in problems):
            problems.append(InputProblem(given, f"{given}: {reason}"))

    for given in inputs:
        pattern = glob.has_magic(given)
        if pattern:
            matches = sorted(glob.glob(given, recursive=True))
            if not matches:
                problem(given, "no file or folder matches this pattern")
                continue
            paths = [Path(m) for m in matches]
        else:
            paths = [Path(given)]
        if not paths[0].exists():  # (a pattern's matches exist)
            problem(given, "no such file or folder")
            continue
        n = 0
        for p in paths:
            if p.is_dir() and not is_flight(p) and not _lost_meta(p):
                flights = _scan(p)
                for f in flights:
                    add(f, str(f))
                n += len(flights)
            else:
                add(p, str(p))
                n += 1
        if not n:
            what = "this pattern's folders" if pattern else "this folder"
            problem(given, f"no flights found in {what}")
    return out, problems


def discover(inputs: Sequence[str]) -> list[FlightInput]:
    """The flights of the command line's inputs (:func:`find_flights`), strictly: an input
    that yields no flight is an error.

    Raises:
        FleetError: the first input that does not exist, or a pattern or folder without
            flights (:func:`run_fleet` makes these rows instead and runs the other flights).
    """
    flights, problems = find_flights(inputs)
    if problems:
        raise FleetError(problems[0].reason)
    return flights


# ----------------------------------------------------------------------------------------------
# Hashes (resume)
# ----------------------------------------------------------------------------------------------


def _manifest_files(p: Path) -> list[Path]:
    """The manifest and the files or folders its tables name (``root`` + ``path``)."""
    try:
        doc = tomllib.loads(p.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return [p]
    root = p.parent / str(doc.get("root", "."))
    files = [p]

    def walk(table: Mapping[str, Any]) -> None:
        for key, v in table.items():
            if isinstance(v, Mapping):
                walk(v)
            elif key == "path" and isinstance(v, str):
                files.append(root / v)

    walk(doc)
    return files


def _files_of(p: Path, exclude: Path | None = None) -> list[Path]:
    """The files of a flight input, less those under ``exclude`` (the fleet's output folder)."""
    skip = Path(os.path.abspath(exclude)) if exclude is not None else None

    def kept(f: Path) -> bool:
        return skip is None or not Path(os.path.abspath(f)).is_relative_to(skip)

    if p.is_dir():
        return sorted(f for f in p.rglob("*") if f.is_file() and kept(f))
    if p.suffix.lower() == ".toml":
        out: list[Path] = []
        for f in _manifest_files(p):
            out += _files_of(f, exclude) if f != p else [f]
        return out
    return [p]


def content_hash(path: Path, exclude: Path | None = None) -> str:
    """sha256 (hex) of a flight input's content: the file; a folder's files (relative names and
    bytes); a manifest and the files it names. Unchanged content, same hash, wherever it lies.
    Files under ``exclude`` are left out (the fleet's ``--out`` inside a flight folder: its own
    outputs would change the hash, and a rerun would never skip).

    Raises:
        OSError: a file cannot be read.
    """
    h = hashlib.sha256()
    base = path if path.is_dir() else path.parent
    for f in _files_of(path, exclude):
        h.update(os.path.relpath(f, base).encode() + b"\0")
        if not f.exists():
            h.update(b"<missing>\0")
            continue
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        h.update(b"\0")
    return h.hexdigest()


def options_hash(method: str, config: Mapping[str, Any]) -> str:
    """sha256 (hex) of a method, the config tables and fgnav's version."""
    from fgnav import __version__

    text = json.dumps(
        {"method": method, "config": config, "fgnav": __version__}, sort_keys=True, default=str
    )
    return hashlib.sha256(text.encode()).hexdigest()


# ----------------------------------------------------------------------------------------------
# The Dask task
# ----------------------------------------------------------------------------------------------


_FRAME = re.compile(r'^\s*File "(?P<file>[^"]+)", line (?P<line>\d+) in (?P<func>\S+)')


def _short_path(path: str) -> str:
    """``path`` relative to the folder holding the fgnav package when inside it."""
    root = Path(__file__).resolve().parent.parent
    try:
        return str(Path(path).resolve().relative_to(root))
    except ValueError:
        return path


def crash_summary(stderr: str) -> str:
    """The informative line of a dead child's stderr: faulthandler's ``Fatal Python error``
    with the innermost Python frame of the crashing thread (``... in estimate_homography
    (fgnav/frontends/homography_vo.py:447)``), else the last line that is not faulthandler's
    list of extension modules; empty when there is none."""
    lines = [line.rstrip() for line in (stderr or "").splitlines()]
    for i, line in enumerate(lines):
        if line.startswith("Fatal Python error:"):
            after = lines[i + 1 :]
            start = next((j for j, t in enumerate(after) if t.startswith("Current thread")), 0)
            for t in after[start:]:
                m = _FRAME.match(t)
                if m:
                    where = f"{_short_path(m['file'])}:{m['line']}"
                    return f"{line.strip()} in {m['func']} ({where})"
            return line.strip()
    rest = [t.strip() for t in lines if t.strip() and not t.startswith("Extension modules:")]
    return rest[-1] if rest else ""


def _worker_address() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return ""


def run_flight_job(job: dict[str, Any]) -> list[dict[str, Any]]:
    """Run one flight's methods in a fresh child interpreter and return its rows (plain dicts).

    Args:
        job: see :func:`fgnav.fleet_worker.run_job`, plus ``timeout_s`` (None: no limit).

    Returns:
        The child's rows, or when the child did not finish one row per method with status
        ``timeout`` (killed after ``timeout_s``) or ``crashed`` (killed by a signal, or it exited
        without a result) and the reason; each with ``task_wall_s`` and ``worker``.
    """
    t0 = time.perf_counter()
    from fgnav.fleet_worker import PARENT_PID_ENV

    env = {**os.environ, **SINGLE_THREAD_ENV, PARENT_PID_ENV: str(os.getpid())}
    proc = subprocess.Popen(
        [sys.executable, "-X", "faulthandler", "-m", "fgnav.fleet_worker"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
    )
    status = reason = None
    try:
        out, err = proc.communicate(json.dumps(job), timeout=job.get("timeout_s"))
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        status, reason = TIMEOUT, f"timed out after {job['timeout_s']:g} s (--timeout)"
    rows: list[dict[str, Any]] = []
    if status is None and proc.returncode == 0:
        try:
            rows = json.loads(out)
        except ValueError:
            status, reason = CRASHED, f"child interpreter gave no result: {crash_summary(err)}"
    elif status is None:
        rc = proc.returncode
        if rc < 0:
            try:
                sig = signal.Signals(-rc).name
            except ValueError:
                sig = f"signal {-rc}"
            reason = f"child interpreter killed by {sig}"
        else:
            reason = f"child interpreter exited with code {rc}"
        limit = job.get("memory_limit_mb")
        if limit:
            reason += f" (under --memory-limit {limit:g} MB)"
        last = crash_summary(err)
        status, reason = CRASHED, reason + (f": {last}" if last else "")
    if status is not None:
        rows = [{"method": m, "status": status, "reason": reason} for m in job["methods"]]
    if job.get("out_dir"):
        # The child's log (warnings of the readers and solvers, a crash's traceback).
        Path(job["out_dir"]).mkdir(parents=True, exist_ok=True)
        (Path(job["out_dir"]) / "child-stderr.txt").write_text(err or "")
    wall = time.perf_counter() - t0
    worker = _worker_address()
    for r in rows:
        r.update(task_wall_s=wall, worker=worker)
    return rows


# ----------------------------------------------------------------------------------------------
# The fleet
# ----------------------------------------------------------------------------------------------


def default_workers() -> int:
    """One worker per core this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


@dataclass
class FleetOptions:
    """Options of :func:`run_fleet`.

    Attributes:
        methods: registry names run on every flight (default: the batch smoother).
        config: config tables by name (as ``--config``; see :mod:`fgnav.methods`).
        scheduler: address of an existing Dask scheduler (None: a LocalCluster here).
        workers: LocalCluster workers (None: one per core); ignored with ``scheduler``.
        timeout_s: wall-time limit of one flight's child [s] (None: none).
        memory_limit_mb: address-space limit of one flight's child [MiB] (None: none).
        force: rerun flights a previous run already did.
        flight_files: write each run's ``estimate.tum``, ``states.csv``, ``summary.json``.
        progress: progress bar over completed flights.
        worker_wait_s: how long to wait for a first Dask worker before submitting [s]
            (then a :class:`FleetError`).
        no_worker_s: how long the scheduler may have no worker at all while flights remain
            (all died or were stopped) before those flights become ``crashed`` rows [s].
    """

    methods: tuple[str, ...] = ("batch",)
    config: dict[str, Any] = field(default_factory=dict)
    scheduler: str | None = None
    workers: int | None = None
    timeout_s: float | None = None
    memory_limit_mb: float | None = None
    force: bool = False
    flight_files: bool = True
    progress: bool = True
    worker_wait_s: float = 60.0
    no_worker_s: float = 60.0


@dataclass
class FleetResult:
    """Rows of the fleet table (plain dicts, :data:`COLUMNS`), files written, timings.

    Attributes:
        wall_s: the whole call, hashing and table included [s].
        startup_s: connecting to the scheduler or starting the LocalCluster [s].
        tasks_s: first submission to last result [s] (0 when every run was skipped).
        input_problems: the inputs that yield no flight (each has an ``error`` row per method).
    """

    rows: list[dict[str, Any]]
    out: Path
    n_flights: int
    workers: int
    wall_s: float
    startup_s: float = 0.0
    tasks_s: float = 0.0
    files: dict[str, Path] = field(default_factory=dict)
    input_problems: list[InputProblem] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        """Rows per status."""
        out = {s: 0 for s in (OK, SKIPPED, ERROR, TIMEOUT, CRASHED)}
        for r in self.rows:
            out[r["status"]] = out.get(r["status"], 0) + 1
        return out

    def failure_lines(self) -> list[str]:
        """One line per failed row: ``flight (input) method: status: reason``."""
        return [
            f"{r['flight']} ({r['input']}) {r['method']}: {r['status']}: {r.get('reason') or ''}"
            for r in self.rows
            if r["status"] in FAILED
        ]

    def flagged_lines(self) -> list[str]:
        """One line per finished run whose estimate is implausible (``fgnav compare``'s flags):
        ``flight (input) method: implausible estimate: reasons``."""
        return [
            f"{r['flight']} ({r['input']}) {r['method']}: implausible estimate: "
            + "; ".join(r.get("flags") or [r["flag"]])
            for r in self.rows
            if r["status"] in DONE and r.get("flag")
        ]

    def all_failed(self) -> bool:
        """Every run failed (none ``ok`` or ``skipped``)."""
        return bool(self.rows) and not any(r["status"] in DONE for r in self.rows)

    def summary_line(self) -> str:
        c = self.counts()
        parts = ", ".join(f"{n} {s}" for s, n in c.items())
        flagged = sum(1 for r in self.rows if r["status"] in DONE and r.get("flag"))
        n_bad = len(self.input_problems)
        bad = f" (and {n_bad} input(s) without a flight)" if n_bad else ""
        return (
            f"fleet: {self.n_flights} flights{bad}, {len(self.rows)} runs: {parts}; "
            f"{flagged} flagged implausible; "
            f"{self.wall_s:.1f} s on {self.workers} workers; table {self.files.get('csv', '')}"
        )


#: Largest ``--memory-limit`` [MiB]: RLIMIT_AS takes bytes below 2**63.
MAX_MEMORY_LIMIT_MB = float(2**63 // 2**20 - 1)


def check_limits(timeout_s: float | None, memory_limit_mb: float | None) -> None:
    """``--timeout`` and ``--memory-limit`` are finite, positive and fit what they are passed
    to (a wait's ``threading.TIMEOUT_MAX``, RLIMIT_AS's bytes below 2**63); None is no limit.

    Raises:
        FleetError: one line naming the option.
    """
    for flag, v, hi, unit in (
        ("--timeout", timeout_s, threading.TIMEOUT_MAX, "s"),
        ("--memory-limit", memory_limit_mb, MAX_MEMORY_LIMIT_MB, "MB"),
    ):
        if v is None:
            continue
        if not (isinstance(v, int | float) and math.isfinite(v) and 0 < v <= hi):
            raise FleetError(f"{flag} must be a finite number > 0 and <= {hi:g} {unit}, got {v!r}")


def _check_methods(methods: Iterable[str]) -> None:
    from fgnav.methods import METHODS, REFERENCE_PREFIX

    for m in methods:
        if m not in METHODS and not m.startswith(REFERENCE_PREFIX):
            raise FleetError(f"unknown method {m!r}; valid: {', '.join(METHODS)}")


#: Journal of finished runs in the output folder: one JSON row a line, appended by the client as
#: each ``ok`` result arrives, so that resume survives an interrupted client (no ``fleet.json``
#: written) and runs over other flights into the same folder (``fleet.json`` then holds only
#: those).
JOURNAL = "fleet-runs.jsonl"


def previous_rows(out: Path) -> dict[tuple[str, str, str], dict[str, Any]]:
    """Runs earlier fleets in ``out`` finished (``ok`` or ``skipped``), by (input hash, method,
    options hash), from ``fleet.json`` and the journal (:data:`JOURNAL`; later lines win);
    empty when neither is there. Unreadable files or lines (an interrupted write) are skipped
    with a warning."""
    rows: list[Any] = []
    path = out / "fleet.json"
    if path.is_file():
        try:
            got = json.loads(path.read_text())
            rows += got if isinstance(got, list) else []
        except (OSError, ValueError) as e:
            log.warning("%s: not read (%s); resuming from %s only", path, e, JOURNAL)
    journal = out / JOURNAL
    if journal.is_file():
        bad = []
        for i, line in enumerate(journal.read_text().splitlines(), 1):
            try:
                rows.append(json.loads(line))
            except ValueError:
                bad.append(i)
        if bad:
            log.warning("%s: %d unreadable line(s) skipped: %s", journal, len(bad), bad[:10])
    return {
        (r["input_hash"], r["method"], r["options_hash"]): r
        for r in rows
        if isinstance(r, dict) and r.get("status") in DONE and r.get("input_hash")
    }


def _reusable(prev: Mapping[str, Any] | None, out: Path, flight_files: bool) -> bool:
    """An earlier run can stand for this one: it exists and, when flight files are wanted, its
    ``summary.json`` is still there."""
    if not prev:
        return False
    if not flight_files:
        return True
    return bool(prev.get("out_dir")) and (out / prev["out_dir"] / "summary.json").is_file()


#: Overall deadline of connecting to ``--scheduler`` (the connection, the handshake and the
#: scheduler's first answer) [s].
CONNECT_DEADLINE_S = 20.0


def check_scheduler_address(address: str) -> str:
    """``address`` when it reads as a Dask scheduler address (``tcp://HOST:PORT``; ``HOST:PORT``
    means tcp; other Dask schemes: tls, ws, wss, and ucx when Dask's UCX support is installed),
    without contacting it: its form and that this Dask can use its protocol.

    Raises:
        FleetError: one line naming ``--scheduler`` (an empty address, no HOST:PORT, a scheme
            that is not Dask's or that this installation cannot use).
    """
    from distributed.comm import parse_address
    from distributed.comm.registry import backends

    usage = "expected tcp://HOST:PORT"
    if not address.strip():
        raise FleetError(f"--scheduler {address!r}: an empty address; {usage}")
    try:
        scheme, loc = parse_address(address)
    except ValueError as e:
        raise FleetError(
            f"--scheduler {address}: not a Dask scheduler address ({e}); {usage}"
        ) from None
    if scheme not in backends or scheme == "inproc":
        known = ", ".join(b for b in backends if b != "inproc")
        raise FleetError(
            f"--scheduler {address}: {scheme}:// is not a Dask protocol ({known}); {usage}"
        )
    host, sep, port = loc.rpartition(":")
    if scheme != "ucx" and (not sep or not host or not port.isdigit() or not 0 < int(port) < 65536):
        raise FleetError(f"--scheduler {address}: no HOST:PORT in it; {usage}")
    try:
        # (ucx:// is registered even without its package: the connector is then abstract and
        # the client failed with "TypeError: Can't instantiate abstract class UCXConnector".)
        backends[scheme].get_connector()
    except Exception as e:
        msg = " ".join(str(e).split())[:120]
        raise FleetError(
            f"--scheduler {address}: the {scheme}:// protocol is not usable with this Dask"
            f" installation ({type(e).__name__}: {msg}); {usage}"
        ) from None
    return address


def _tcp_reachable(address: str, deadline_s: float) -> None:
    """Open (and close) a plain TCP connection to the HOST:PORT of a tcp, tls, ws or wss
    ``address``, so that an unknown host, a refused connection or a connection timeout are named
    at once: Dask's connect retries a refused connection for its whole timeout (20 s) and its
    ``OSError`` then read as a reply that is not a Dask scheduler's (tcp) or "cannot connect"
    (ws). (A Dask scheduler logs it at INFO: ``Connection from ... closed before handshake
    completed``.)

    Raises:
        FleetError: one line naming ``--scheduler`` and why.
    """
    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port

    where = f"--scheduler {address}"
    host, port = parse_host_port(parse_address(address)[1])
    try:
        socket.create_connection((host, port), timeout=deadline_s).close()
    except socket.gaierror as e:
        raise FleetError(f"{where}: host {host!r} not found ({e.strerror or e})") from None
    except ConnectionRefusedError:
        raise FleetError(
            f"{where}: no Dask scheduler answers at {host} port {port} (connection refused:"
            " nothing listens there)"
        ) from None
    except TimeoutError:
        raise FleetError(
            f"{where}: no Dask scheduler answers at {host} port {port} (connection timed out"
            f" after {deadline_s:g} s)"
        ) from None
    except OSError as e:
        raise FleetError(
            f"{where}: no Dask scheduler answers at {host} port {port}"
            f" ({e.strerror or type(e).__name__})"
        ) from None


def _probe_scheduler(address: str, deadline_s: float) -> None:
    """Ask the server at a ``tcp://`` ``address`` who it is, all within ``deadline_s``: Dask's
    own connect does not bound the handshake (a web server at the port held it for minutes) nor
    check what it reads (garbage asked numpy for exabytes). A plain TCP connection comes first
    (:func:`_tcp_reachable`).

    Raises:
        FleetError: the host is unknown, the connection is refused or times out, nothing
            answered in time, the answer is not a Dask scheduler's.
    """
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from distributed.comm import connect

    where = f"--scheduler {address}"
    t0 = time.monotonic()
    _tcp_reachable(address, deadline_s)
    left_s = max(1.0, deadline_s - (time.monotonic() - t0))

    async def ask() -> Any:
        comm = await connect(address, timeout=left_s)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    with ThreadPoolExecutor(1) as pool:  # (a thread of its own: the caller may run a loop)
        try:
            got = pool.submit(asyncio.run, asyncio.wait_for(ask(), left_s)).result()
        except TimeoutError:
            raise FleetError(
                f"{where}: no Dask scheduler answered within {deadline_s:g} s (the port accepts"
                " connections but gives no Dask reply)"
            ) from None
        except OSError as e:  # (Dask's connect gave up: the port closed in between)
            msg = " ".join(str(e).split())[:120]
            raise FleetError(f"{where}: no Dask scheduler answers there ({msg})") from None
        except Exception as e:  # (a reply that is not Dask's protocol: any error of its parse)
            msg = " ".join(str(e).split())[:120]
            raise FleetError(
                f"{where}: not a Dask scheduler (its reply does not read as one:"
                f" {type(e).__name__}: {msg})"
            ) from None
    if not isinstance(got, dict) or got.get("type") != "Scheduler":
        kind = got.get("type") if isinstance(got, dict) else type(got).__name__
        raise FleetError(f"{where}: not a Dask scheduler (it is a {kind})")


def local_workers(requested: int | None, n_jobs: int) -> int:
    """LocalCluster workers: ``requested`` (None: one per core), at most one per flight to run;
    a log line when more than the cores are asked for (they then share them)."""
    cores = default_workers()
    if requested is not None and requested > cores:
        log.warning("--workers %d: more than this machine's %d core(s)", requested, cores)
    return max(1, min(requested or cores, n_jobs))


def _dask_client(opts: FleetOptions, n_jobs: int):
    """A Dask client: on ``opts.scheduler``, or on a loopback LocalCluster of single-threaded
    worker processes.

    Raises:
        FleetError: a bad address, nothing or no Dask scheduler answering there in
            :data:`CONNECT_DEADLINE_S`.
    """
    from distributed import Client

    # The scheduler of a LocalCluster runs in this process: its INFO lines are not the user's.
    logging.getLogger("distributed").setLevel(logging.WARNING)
    if opts.scheduler is not None:
        address = check_scheduler_address(opts.scheduler)
        if address.startswith("tcp://") or "://" not in address:
            _probe_scheduler(address, CONNECT_DEADLINE_S)
        elif not address.startswith("ucx://"):  # (tls, ws, wss: TCP underneath)
            _tcp_reachable(address, CONNECT_DEADLINE_S)
        try:
            return Client(address, timeout=f"{CONNECT_DEADLINE_S:g}s"), None
        except Exception as e:
            msg = " ".join(str(e).split())[:160]
            raise FleetError(
                f"--scheduler {address}: cannot connect ({type(e).__name__}: {msg})"
            ) from None
    # The workers (spawned interpreters) inherit SIGINT ignored: a Ctrl-C reaches this process
    # only, which closes the cluster (each worker printed its own traceback before).
    # (Only the main thread may set a handler: run_fleet called from another thread starts the
    # cluster as it is.)
    main = threading.current_thread() is threading.main_thread()
    old_int = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        cluster = _local_cluster(opts, n_jobs)
    finally:
        if main:
            signal.signal(signal.SIGINT, old_int)
    return Client(cluster), cluster


def _local_cluster(opts: FleetOptions, n_jobs: int):
    from distributed import LocalCluster

    return LocalCluster(
        n_workers=local_workers(opts.workers, n_jobs),
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        # The scheduler's HTTP server (health, metrics) starts even without a dashboard, on 8787
        # unless told otherwise (a warning when that port is taken): any free loopback port.
        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        silence_logs=logging.WARNING,
    )


def _progress(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, unit="flight", desc="fleet", disable=not enabled, file=sys.stderr)


def run_fleet(inputs: Sequence[str], out: str | Path, opts: FleetOptions | None = None):
    """Run ``opts.methods`` on every flight of ``inputs`` on Dask; write and return the table.

    Raises:
        FleetError: no flights, an unknown method, an unreachable scheduler.
    """
    opts = opts or FleetOptions()
    # A method named twice runs once (``batch,batch`` ran it twice per flight).
    opts = replace(opts, methods=tuple(dict.fromkeys(opts.methods)))
    check_limits(opts.timeout_s, opts.memory_limit_mb)
    _check_methods(opts.methods)
    if opts.scheduler is not None:
        # Its form now (contacted only when something is to run: a rerun that reuses every row
        # exited 0 with any address, "" ran on a LocalCluster).
        check_scheduler_address(opts.scheduler)
    out = Path(out)
    flights, problems = find_flights(inputs)
    if not flights:
        if len(problems) == 1:
            raise FleetError(problems[0].reason)
        raise FleetError("no flights in the inputs: " + "; ".join(q.reason for q in problems))
    out.mkdir(parents=True, exist_ok=True)
    old = {} if opts.force else previous_rows(out)
    o_hash = {m: options_hash(m, opts.config) for m in opts.methods}
    t_all = time.perf_counter()
    # An input without a flight: one error row per method (as a file that is not a flight), the
    # other inputs' flights run (the first such input stopped the whole fleet).
    rows: list[dict[str, Any]] = [
        {"flight": q.name, "input": q.input, "method": m, "status": ERROR, "reason": q.reason}
        for q in problems
        for m in opts.methods
    ]
    jobs: list[tuple[dict[str, Any], dict[str, Any]]] = []
    # Copies of a flight (same name and content, two places): one job, whose rows each copy
    # gets with its own input (both ran into one flights/<name>-<hash>/ folder at once).
    first_of: dict[tuple[str, str], str] = {}
    copies: list[tuple[dict[str, Any], str, list[str]]] = []
    for f in flights:
        ident = {"flight": f.name, "input": f.input}
        try:
            h = content_hash(f.path, exclude=out)
        except OSError as e:
            for m in opts.methods:
                rows.append({**ident, "method": m, "status": ERROR, "reason": f"{f.path}: {e}"})
            continue
        todo = []
        for m in opts.methods:
            prev = old.get((h, m, o_hash[m]))
            if _reusable(prev, out, opts.flight_files):
                rows.append({**prev, **ident, "status": SKIPPED, "reason": ""})
            else:
                todo.append(m)
        if not todo:
            continue
        if (f.name, h) in first_of:
            copies.append((ident, first_of[(f.name, h)], todo))
            continue
        first_of[(f.name, h)] = f.input
        rel = f"flights/{f.name}-{h[:8]}" if opts.flight_files else ""
        job = {
            "flight": f.name,
            "path": str(f.path),
            "methods": todo,
            "config": opts.config,
            "out_dir": str((out / rel).resolve()) if rel else None,
            "timeout_s": opts.timeout_s,
            "memory_limit_mb": opts.memory_limit_mb,
        }
        jobs.append((job, {**ident, "input_hash": h, "out_base": rel}))
    timing = {"workers": 0, "startup_s": 0.0, "tasks_s": 0.0}
    if jobs:
        rows += _run_jobs(jobs, opts, o_hash, timing, out / JOURNAL)
    for ident, of, todo in copies:
        rows += [{**r, **ident} for r in rows if r["input"] == of and r["method"] in todo]
    order = {m: i for i, m in enumerate(opts.methods)}
    pos = {f.input: i for i, f in enumerate(flights)}
    pos.update({q.input: len(flights) + i for i, q in enumerate(problems)})  # (last)
    rows.sort(key=lambda r: (pos.get(r["input"], 0), order.get(r["method"], 0)))
    rows = [{c: r.get(c) for c in COLUMNS} for r in rows]
    res = FleetResult(rows, out, len(flights), wall_s=time.perf_counter() - t_all, **timing)
    res.input_problems = problems
    res.files = write_table(rows, out)
    res.files["report"] = write_report(
        rows, out, run_context(opts, len(jobs), timing), [q.input for q in problems]
    )
    return res


def run_context(opts: FleetOptions, n_run: int, timing: Mapping[str, Any]) -> str:
    """One line for the report: when, fgnav's version, the methods and where the flights ran."""
    from datetime import UTC, datetime

    from fgnav import __version__

    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    where = f"scheduler {opts.scheduler}" if opts.scheduler else "a LocalCluster"
    ran = (
        f"{n_run} flight(s) run on {timing['workers']} Dask worker(s) of {where}"
        f" in {timing['tasks_s']:.1f} s"
        if n_run
        else "no flight run (all done before)"
    )
    limits = [
        f"{flag} {v:g}"
        for flag, v in (("--timeout", opts.timeout_s), ("--memory-limit", opts.memory_limit_mb))
        if v
    ] + (["--force"] if opts.force else [])
    config = f"; config tables: {', '.join(sorted(opts.config))}" if opts.config else ""
    return (
        f"Run {when}, fgnav {__version__}; methods {', '.join(opts.methods)}; {ran}"
        + (f" ({', '.join(limits)})" if limits else "")
        + config
        + "."
    )


def task_key(run_id: str, i: int, job: Mapping[str, Any]) -> str:
    """Dask key of the ``i``-th flight of the fleet run ``run_id`` (readable in the dashboard,
    unique across fleets sharing a scheduler)."""
    return f"fleet-{job['flight']}-{i}-{run_id}"


def _run_jobs(
    jobs: list[tuple[dict[str, Any], dict[str, Any]]],
    opts: FleetOptions,
    o_hash: dict[str, str],
    timing: dict[str, Any],
    journal: Path,
) -> list[dict[str, Any]]:
    """Submit the jobs, gather their rows as they complete (progress bar; ``ok`` rows appended to
    ``journal`` at once), close the client; ``timing`` gets ``workers``, ``startup_s`` and
    ``tasks_s``."""
    t0 = time.perf_counter()
    from distributed import as_completed

    client, cluster = _dask_client(opts, len(jobs))
    rows: list[dict[str, Any]] = []
    futures: dict[Any, tuple[dict[str, Any], dict[str, Any]]] = {}
    try:
        where = f"--scheduler {opts.scheduler}" if opts.scheduler else "the LocalCluster"
        try:
            client.wait_for_workers(1, timeout=opts.worker_wait_s)
        except TimeoutError:
            raise FleetError(
                f"{where}: no Dask worker joined within {opts.worker_wait_s:g} s"
                " (start `dask worker ADDRESS`)"
            ) from None
        timing["workers"] = len(client.scheduler_info().get("workers", {}))
        t1 = time.perf_counter()
        timing["startup_s"] = t1 - t0
        # Keys unique to this fleet: another fleet on the same scheduler submitting the same
        # key would be handed this one's result (Dask keys name results, not calls).
        run_id = uuid.uuid4().hex
        futures = {
            client.submit(run_flight_job, job, pure=False, key=task_key(run_id, i, job)): (
                job,
                ident,
            )
            for i, (job, ident) in enumerate(jobs)
        }
        failed = 0
        with _progress(len(futures), opts.progress) as bar, open(journal, "a") as log_fh:

            def take(job: dict[str, Any], ident: dict[str, Any], got: list[dict]) -> None:
                nonlocal failed
                for r in got:
                    base = ident["out_base"]
                    written = r["status"] == OK and bool(base)
                    r.update(
                        flight=ident["flight"],
                        input=ident["input"],
                        input_hash=ident["input_hash"],
                        options_hash=o_hash[r["method"]],
                        out_dir=f"{base}/{_method_dir(r['method'])}" if written else "",
                    )
                    rows.append(r)
                    if r["status"] == OK:
                        log_fh.write(json.dumps({c: r.get(c) for c in COLUMNS}) + "\n")
                log_fh.flush()
                failed += any(r["status"] in FAILED for r in got)
                bar.set_postfix(failed=failed)
                bar.update(1)

            # On this client's loop: as_completed's default is the process's default client,
            # another fleet's in the same process (its closing left these results untracked).
            pending = as_completed(futures, loop=client.loop)
            no_worker_since: float | None = None
            next_check = 0.0
            while not pending.is_empty():
                batch = pending.next_batch(block=False)
                for fut in batch:
                    job, ident = futures.pop(fut)
                    try:
                        got = fut.result()
                    except Exception as e:  # the task itself failed (lost worker, bad pickle)
                        msg = " ".join(str(e).split())
                        got = _crashed(job, f"Dask task failed: {type(e).__name__}: {msg}")
                    take(job, ident, got)
                if batch:
                    continue
                now = time.monotonic()
                if now >= next_check:
                    # A task whose worker died waits for another one: with none left, forever.
                    next_check = now + min(1.0, opts.no_worker_s / 4)
                    if _n_workers(client):
                        no_worker_since = None
                    elif no_worker_since is None:
                        no_worker_since = now
                    elif now - no_worker_since >= opts.no_worker_s:
                        reason = (
                            f"no Dask worker left for {opts.no_worker_s:g} s ({where}); the"
                            " flight did not finish: rerun to resume"
                        )
                        log.warning("%s: %d flight(s) not finished", reason, len(futures))
                        for fut, (job, ident) in list(futures.items()):
                            fut.cancel()
                            take(job, ident, _crashed(job, reason))
                        futures.clear()
                        break
                time.sleep(0.05)
        timing["tasks_s"] = time.perf_counter() - t1
    except KeyboardInterrupt:
        # Ctrl-C: the flights not done are cancelled (their children die with the workers,
        # ``fleet_worker._die_with_parent``); the done ones are in the journal.
        for fut in list(futures):
            fut.cancel()
        done = len({(r["flight"], r["input"]) for r in rows})
        raise KeyboardInterrupt(
            f"{done} of {len(jobs)} flight(s) done (their rows in {journal}); run the same "
            "command again to resume"
        ) from None
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return rows


def _crashed(job: Mapping[str, Any], reason: str) -> list[dict[str, Any]]:
    return [{"method": m, "status": CRASHED, "reason": reason} for m in job["methods"]]


def _n_workers(client: Any) -> int:
    """Workers the scheduler has now (0 when it does not answer)."""
    try:
        return len(client.nthreads())
    except Exception:
        return 0


def _method_dir(name: str) -> str:
    from fgnav.compare import method_dirname

    return method_dirname(name)


# ----------------------------------------------------------------------------------------------
# Table and report
# ----------------------------------------------------------------------------------------------


def _cell(column: str, v: Any) -> str:
    if v is None:
        return ""
    if column in JSON_COLUMNS:
        return json.dumps(v, separators=(",", ":"), sort_keys=True)
    if isinstance(v, float):
        return repr(v)
    return str(v)


def write_table(rows: list[dict[str, Any]], out: Path) -> dict[str, Path]:
    """``fleet.csv`` (strings; multi-valued cells as compact JSON; empty = none), ``fleet.json``
    (typed rows) and ``fleet.parquet`` when pyarrow is importable."""
    paths = {"csv": out / "fleet.csv", "json": out / "fleet.json"}
    with open(paths["csv"], "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS)
        for r in rows:
            w.writerow([_cell(c, r.get(c)) for c in COLUMNS])
    paths["json"].write_text(json.dumps(rows, indent=1, allow_nan=False) + "\n")
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return paths
    flat = [
        {c: (_cell(c, r.get(c)) if c in JSON_COLUMNS else r.get(c)) for c in COLUMNS} for r in rows
    ]
    paths["parquet"] = out / "fleet.parquet"
    pq.write_table(pa.Table.from_pylist(flat), paths["parquet"])
    return paths


def _values(rows: list[dict[str, Any]], column: str) -> list[float]:
    return [float(r[column]) for r in rows if isinstance(r.get(column), int | float)]


def hist_bin_edges(values: Sequence[float], log: bool | None = None) -> tuple[Any, bool]:
    """Bin edges shared by every series of a histogram (so that bars of different methods have
    the same widths and line up), and whether they are logarithmic.

    Args:
        values: every value of every series.
        log: logarithmic bins; None: when all values are > 0 and span more than a factor 10.

    Returns:
        ``(edges, log)``: 5 to 20 bins (about two flights per bin) over the values' range.
    """
    import numpy as np

    v = np.asarray([x for x in values if math.isfinite(x)], dtype=float)
    n = int(min(20, max(5, len(v) // 2)))
    lo, hi = (float(v.min()), float(v.max())) if len(v) else (0.0, 1.0)
    if log is None:
        log = bool(len(v)) and lo > 0.0 and hi > 10.0 * lo
    if log:
        return np.geomspace(lo, hi, n + 1), True
    return np.histogram_bin_edges(v, bins=n), False


def _figures(rows: list[dict[str, Any]], out: Path) -> dict[str, Path]:
    """Distributions across flights of the finished runs: ATE, final scale error (one value per
    SLAM session), drag kx vs ky, run time vs flight duration; one colour per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    figdir = out / "figures"
    figdir.mkdir(exist_ok=True)
    done = [r for r in rows if r["status"] in DONE]
    methods = sorted({r["method"] for r in done})
    by = {m: [r for r in done if r["method"] == m] for m in methods}
    figs: dict[str, Path] = {}

    def save(name: str, fig: Any, ax: Any) -> None:
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
        fig.tight_layout()
        figs[name] = figdir / f"{name}.png"
        fig.savefig(figs[name], dpi=90)
        plt.close(fig)

    def hist(name: str, title: str, xlabel: str, ylabel: str, series: dict[str, list[float]]):
        series = {m: v for m, v in series.items() if v}
        if not series:
            return
        edges, log = hist_bin_edges([x for v in series.values() for x in v])
        fig, ax = plt.subplots(figsize=(6, 3.5))
        # One call with every series: bars side by side in shared bins.
        ax.hist(list(series.values()), bins=edges, label=list(series), rwidth=0.9)
        if log:
            ax.set_xscale("log")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set(title=title, xlabel=xlabel + (" (log scale)" if log else ""), ylabel=ylabel)
        save(name, fig, ax)

    hist(
        "ate",
        "ATE RMSE across flights",
        "ATE RMSE [m]",
        "flights",
        {m: _values(v, "ate_rmse_m") for m, v in by.items()},
    )
    scale = {
        m: [e for r in v for e in (r.get("scale_err_pct") or {}).values() if e is not None]
        for m, v in by.items()
    }
    hist(
        "scale_err",
        "final SLAM-scale error across flights",
        "scale error [%]",
        "SLAM sessions",
        scale,
    )
    drag = {
        m: [tuple(r["drag_k_per_s"][:2]) for r in v if len(r.get("drag_k_per_s") or []) >= 2]
        for m, v in by.items()
    }
    if any(drag.values()):
        fig, ax = plt.subplots(figsize=(4.5, 4))
        hi = 1.1 * max([abs(k) for p in drag.values() for xy in p for k in xy] + [1e-3])
        ax.plot([0, hi], [0, hi], color="0.7", lw=0.8, label="kx = ky")
        for m, p in drag.items():
            if p:
                ax.scatter(*zip(*p, strict=True), label=m, s=18, alpha=0.8)
        ax.set(title="drag coefficient per flight", xlabel="kx [1/s]", ylabel="ky [1/s]")
        ax.set_xlim(min(0.0, ax.get_xlim()[0]), hi)
        ax.set_ylim(min(0.0, ax.get_ylim()[0]), hi)
        ax.set_aspect("equal", adjustable="box")
        save("drag_k", fig, ax)
    pts = {
        m: [
            (r["duration_s"], r["runtime_s"])
            for r in v
            if r.get("duration_s") is not None and r.get("runtime_s") is not None
        ]
        for m, v in by.items()
    }
    if any(pts.values()):
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for m, p in pts.items():
            if p:
                ax.scatter(*zip(*p, strict=True), label=m, s=16)
        ax.set(
            title="run time vs flight duration",
            xlabel="flight duration [s]",
            ylabel="method run time [s]",
        )
        ax.set_xlim(left=0)
        ax.set_ylim(bottom=0)
        save("runtime", fig, ax)
    return figs


def _fmt(v: Any, digits: int = 4) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.{digits}g}"
    if isinstance(v, dict | list):
        return json.dumps(v, separators=(",", ":"), sort_keys=True, default=str)
    return str(v)


#: Columns of the Markdown tables of ``fleet.md``.
REPORT_COLUMNS = (
    "flight",
    "method",
    "status",
    "flag",
    "duration_s",
    "ate_rmse_m",
    "scale_err_pct",
    "drag_k_per_s",
    "runtime_s",
    "reason",
)


def markdown_table(rows: list[dict[str, Any]], columns: Sequence[str] = REPORT_COLUMNS) -> str:
    """Rows as a Markdown table (numbers to 4 significant digits, JSON cells rounded)."""

    def cell(c: str, v: Any) -> str:
        if isinstance(v, dict):
            v = {k: (round(x, 3) if isinstance(x, float) else x) for k, x in v.items()}
        elif isinstance(v, list):
            v = [round(x, 4) if isinstance(x, float) else x for x in v]
        return _fmt(v).replace("|", "/")

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(c, r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


#: Flights listed as the worst in the report.
N_WORST = 5


def write_report(
    rows: list[dict[str, Any]],
    out: Path,
    context: str = "",
    no_flight_inputs: Sequence[str] = (),
) -> Path:
    """``fleet.md``: what ran (``context``, one line), counts, the distribution figures, the worst
    flights by ATE per method, the failed runs with their reasons, the whole table and the
    meaning of the columns. ``no_flight_inputs``: inputs that yielded no flight (their rows are
    ``error`` rows; they are not counted as flights)."""
    figs = _figures(rows, out)
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    order = [s for s in (OK, SKIPPED, ERROR, TIMEOUT, CRASHED) if counts.get(s)]
    order += sorted(set(counts) - set(order))
    lines = ["# Fleet report", ""]
    if context:
        lines += [context, ""]
    n_bad = len(set(no_flight_inputs))
    n_flights = len({r["input"] for r in rows} - set(no_flight_inputs))
    lines += [
        f"{n_flights} flights"
        + (f" and {n_bad} input(s) without a flight (see Failed runs)" if n_bad else "")
        + f", {len(rows)} runs: "
        + ", ".join(f"{counts[s]} {s}" for s in order)
        + (
            " (`skipped`: done in an earlier run with the same input and options, figures kept)"
            if counts.get(SKIPPED)
            else ""
        )
        + ". Tables and figures are formatted from `fleet.json`; empty cells are values the"
        " run does not have (no ground truth, drag model off, a failed run).",
        "",
    ]
    if figs:
        lines += ["## Distributions across flights", "", "Runs with status ok or skipped.", ""]
        lines += [f"![{k}](figures/{p.name})" for k, p in figs.items()] + [""]
    done = [r for r in rows if r["status"] in DONE]
    for m in sorted({r["method"] for r in done}):
        scored = [r for r in done if r["method"] == m and r.get("ate_rmse_m") is not None]
        unscored = sum(1 for r in done if r["method"] == m) - len(scored)
        lines += [f"## Worst flights by ATE: {m}", ""]
        if unscored:
            lines += [f"{unscored} finished run(s) without ground truth are not ranked.", ""]
        if scored:
            worst = sorted(scored, key=lambda r: -r["ate_rmse_m"])[:N_WORST]
            lines += [markdown_table(worst), ""]
    flagged = [dict(r, flags="; ".join(r.get("flags") or [])) for r in done if r.get("flag")]
    if flagged:
        cols = ("flight", "input", "method", "flag", "flags")
        lines += ["## Implausible estimates", "", markdown_table(flagged, cols), ""]
    failed = [r for r in rows if r["status"] in FAILED]
    if failed:
        cols = ("flight", "input", "method", "status", "reason")
        lines += ["## Failed runs", "", markdown_table(failed, cols), ""]
    lines += ["## All runs", "", markdown_table(rows), ""]
    lines += ["## Columns of `fleet.csv`", ""]
    lines += [f"- `{c}`: {doc}" for c, doc in COLUMN_DOC.items()] + [""]
    path = out / "fleet.md"
    path.write_text("\n".join(lines))
    return path
