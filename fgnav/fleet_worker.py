"""The child interpreter of ``fgnav fleet``: one flight, its methods, plain dicts out.

Run as ``python -m fgnav.fleet_worker`` by :func:`fgnav.fleet.run_flight_job` (inside a Dask task)
with a job as JSON on stdin (see :func:`run_job`); it prints one JSON list of result rows on
stdout and nothing else (anything the library prints goes to stderr). A crash in native code, a
timeout or the memory limit kills only this process; the Dask task turns that into an error row.

The job's ``memory_limit_mb`` is set as this process's ``RLIMIT_AS`` (address space) before
anything heavy is imported. The import path is kept lean (no CLI, no Dask, no plotting): the
per-flight start-up is part of the fleet's overhead.

Test-only hook: when the environment variable :data:`ABORT_ENV` names the job's flight, the child
calls ``os.abort()`` after loading it (a stand-in for a segfault in GTSAM or OpenCV).
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from typing import Any

#: Test hook: ``FGNAV_TEST_ABORT_ON=<flight name>`` makes the child of that flight abort.
ABORT_ENV = "FGNAV_TEST_ABORT_ON"

#: Statuses of a result row.
OK, ERROR, TIMEOUT, CRASHED, SKIPPED = "ok", "error", "timeout", "crashed", "skipped"


def set_memory_limit(memory_limit_mb: float | None) -> None:
    """Limit this process's address space to ``memory_limit_mb`` MiB (``RLIMIT_AS``)."""
    if not memory_limit_mb:
        return
    import resource

    limit = int(memory_limit_mb * 1024 * 1024)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


def one_line(text: str) -> str:
    """``text`` with every run of whitespace (newlines included) made one space."""
    return " ".join(str(text).split())


#: Error texts of a failed allocation (an import under RLIMIT_AS fails to map its library).
MEMORY_HINTS = ("memory", "failed to map", "cannot allocate", "bad_alloc")


def error_reason(e: BaseException, memory_limit_mb: float | None = None) -> str:
    """One line for an exception; fgnav's known errors are given as their message alone; an
    allocation failure under a memory limit says so."""
    from fgnav.datasets.errors import FgnavError

    text = one_line(e)
    # Under RLIMIT_AS an extension whose allocation fails may return NULL without setting
    # MemoryError: CPython then raises SystemError "error return without exception set" (or,
    # from a builtin such as compile(), "... returned NULL without setting an exception").
    alloc_failed = isinstance(e, SystemError) and (
        "without exception set" in text or "without setting an exception" in text
    )
    if isinstance(e, MemoryError) or (
        memory_limit_mb and (alloc_failed or any(h in text.lower() for h in MEMORY_HINTS))
    ):
        limit = f" (--memory-limit {memory_limit_mb:g} MB)" if memory_limit_mb else ""
        return f"out of memory{limit}: {type(e).__name__}: {text}"
    if isinstance(e, FgnavError):
        return text
    return f"{type(e).__name__}: {text}"


def result_row(flight: Any, est: Any, metrics: Any) -> dict[str, Any]:
    """The figures of one method's run on one flight (the table's per-run columns), with
    ``fgnav compare``'s plausibility flags (:func:`fgnav.compare.plausibility_flags`: codes in
    ``flag``, reasons in ``flags``)."""
    from fgnav.compare import plausibility_flags
    from fgnav.coverage import flight_t0

    info = est.info
    dropped = info.get("dropped", info.get("skipped", {}))
    flags = plausibility_flags(est, metrics, flight_t0(flight))
    row: dict[str, Any] = {
        "flag": ",".join(f["code"] for f in flags) or None,
        "flags": [f["reason"] for f in flags] or None,
        "ate_rmse_m": None if metrics is None else metrics.ate_rmse_m,
        "scale_err_pct": None if metrics is None else dict(metrics.scale_final_err_pct),
        "slam_scale": dict(est.slam_scale) or None,
        "drag_k_per_s": None if est.drag_k is None else [float(k) for k in est.drag_k],
        "solver_failures": int(info.get("solver_failures", 0)),
        "dropped": dict(dropped) if isinstance(dropped, dict) else dropped,
        "runtime_s": est.runtime_s,
        "n_states": len(est.trajectory),
    }
    return row


def flight_figures(flight: Any) -> dict[str, Any]:
    """``duration_s`` (overlap of the sensor streams) and ``streams`` of a loaded flight."""
    from fgnav.datasets.errors import FgnavError

    try:
        t0, t1 = flight.time_window()
        duration = float(t1 - t0)
    except FgnavError:
        duration = None
    return {"duration_s": duration, "streams": list(flight.streams())}


def run_job(job: dict[str, Any]) -> list[dict[str, Any]]:
    """Load the job's flight once and run each of its methods; one row per method.

    Args:
        job: ``path`` (flight input), ``flight`` (its name in the table), ``methods`` (registry
            names), ``config`` (config tables), ``out_dir`` (folder of the per-method outputs,
            None for none), ``memory_limit_mb`` (for the reason of an out-of-memory row).

    Returns:
        Rows with ``method``, ``status`` (``ok`` or ``error``), ``reason`` and the figures of
        :func:`result_row` and :func:`flight_figures`; ``work_s`` is the time spent loading the
        flight plus running, scoring and writing the method (the child's useful work).
    """
    from pathlib import Path

    from fgnav.datasets.load import load_flight

    limit = job.get("memory_limit_mb")
    t0 = time.perf_counter()
    try:
        flight = load_flight(job["path"])
        flight.check()
    except Exception as e:  # a bad flight is an error row per method, never a lost worker
        reason = error_reason(e, limit)
        return [
            {"method": m, "status": ERROR, "reason": reason, "work_s": time.perf_counter() - t0}
            for m in job["methods"]
        ]
    load_s = time.perf_counter() - t0
    if os.environ.get(ABORT_ENV) == job["flight"]:
        os.abort()
    from fgnav.compare import method_dirname, score_estimate
    from fgnav.eval.outputs import summary_extra, write_estimate
    from fgnav.methods import get_method

    base = flight_figures(flight)
    rows = []
    for i, name in enumerate(job["methods"]):
        t1 = time.perf_counter()
        row: dict[str, Any] = {"method": name, **base}
        try:
            method = get_method(name, flight)
            est = method.run(flight, job.get("config") or {}, False)
            metrics = score_estimate(
                flight, est, method.alignment, positions_only=method.positions_only
            )
            if job.get("out_dir"):
                out = Path(job["out_dir"]) / method_dirname(name)
                write_estimate(est, out, metrics, summary_extra(flight.name, est, "fleet"))
            row.update(status=OK, reason="", **result_row(flight, est, metrics))
        except Exception as e:  # one method's failure must not stop the flight's others
            row.update(status=ERROR, reason=error_reason(e, limit))
        row["work_s"] = time.perf_counter() - t1 + (load_s if i == 0 else 0.0)
        rows.append(row)
    return rows


#: The environment variable through which the Dask worker gives the child its own pid.
PARENT_PID_ENV = "FGNAV_FLEET_PARENT_PID"


def _die_with_parent() -> None:
    """Linux: this child is killed when the Dask worker that started it dies (it runs in its own
    session, so a Ctrl-C of the fleet or a closed cluster left it running to the end)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    # The parent's pid as the parent gave it (read here it could already be init's, had the
    # worker died while this interpreter started).
    parent = int(os.environ.get(PARENT_PID_ENV, "0") or 0) or os.getppid()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent died before the call
        os._exit(1)


def main() -> int:
    """Read the job from stdin, write the rows as one JSON list to the real stdout."""
    _die_with_parent()
    job = json.loads(sys.stdin.read())
    set_memory_limit(job.get("memory_limit_mb"))
    # Everything the library prints goes to stderr; fd 1 carries the JSON result only.
    result = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    try:
        rows = run_job(job)
    except MemoryError as e:
        rows = [
            {"method": m, "status": ERROR, "reason": error_reason(e, job.get("memory_limit_mb"))}
            for m in job["methods"]
        ]
    from fgnav.eval.metrics import to_jsonable

    result.write(json.dumps(to_jsonable(rows), allow_nan=False))
    result.flush()
    return 0


if __name__ == "__main__":
    code = main()
    sys.stderr.flush()
    # The result is written and flushed: skip the interpreter's teardown (unloading numpy, GTSAM,
    # OpenCV), which is per-flight overhead and nothing else.
    os._exit(code)
