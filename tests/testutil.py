"""Paths and helpers for tests, resolved from this file (never from the working directory)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fgnav.datasets.simulate.options import CRAZYFLIE_LIKE  # noqa: F401 (re-exported)

PROJECT_ROOT = Path(__file__).resolve().parents[1]
REAL_DATA = PROJECT_ROOT.parent / "shared" / "data" / "real"


def run_cli(*args) -> subprocess.CompletedProcess:
    """``python -m fgnav.cli ARGS`` from the project root (text output captured, 120 s limit)."""
    return subprocess.run(
        [sys.executable, "-m", "fgnav.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=PROJECT_ROOT,
    )


def run_script(name: str, *args, timeout: float = 300) -> str:
    """``python scripts/NAME ARGS``; its stdout (text; a non-zero exit fails the test)."""
    return subprocess.run(
        [sys.executable, str(PROJECT_ROOT / "scripts" / name), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=True,
    ).stdout


def command_cli(command: str, folder, out, *extra, config: str | None = None) -> int:
    """``fgnav COMMAND FOLDER --out OUT --no-progress EXTRA`` in this process (output to the
    test's capsys); with ``config``, that TOML text is written to ``OUT.toml`` and passed as
    ``--config``. Its exit code."""
    from fgnav.cli import main

    args = [command, folder, "--out", out, "--no-progress"]
    if config is not None:
        cfg = Path(out).with_suffix(".toml")
        cfg.write_text(config)
        args += ["--config", cfg]
    return main([str(a) for a in (*args, *extra)])


def compare_cli(folder, out, methods: str, *extra) -> int:
    """``fgnav compare FOLDER --out OUT --methods METHODS --no-figures`` (:func:`command_cli`)."""
    return command_cli("compare", folder, out, "--methods", methods, "--no-figures", *extra)


def require_real_data() -> Path:
    """``../shared/data/real``, or skip the calling test with the reason."""
    if not REAL_DATA.is_dir():
        pytest.skip(f"real data folder {REAL_DATA} is absent (CI has ../shared beside the clone)")
    return REAL_DATA


def local_test_cluster(n_workers: int):
    """A Dask LocalCluster reached by address (threads, loopback, no dashboard)."""
    import logging

    from distributed import LocalCluster

    return LocalCluster(
        n_workers=n_workers,
        threads_per_worker=1,
        processes=False,
        protocol="tcp://",
        host="127.0.0.1",
        dashboard_address=None,
        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        silence_logs=logging.WARNING,
    )


def two_turns_folder(tmp_path_factory, seed: int) -> Path:
    """A simulated 8 s two-turns flight folder without images (the CLI tests' flight)."""
    from fgnav.datasets.simulate.options import SimOptions
    from fgnav.datasets.simulate.simulator import simulate_to_folder

    out = tmp_path_factory.mktemp("flight") / "two_turns"
    simulate_to_folder("two-turns", out, seed=seed, options=SimOptions(duration=8.0, images=False))
    return out


def truth_scale(flight) -> dict[int, float]:
    """The simulator's SLAM scale of each session at its start (``meta["truth"]``)."""
    return {int(k): v["scale"] for k, v in flight.meta["truth"]["slam_sessions"].items()}


def truth_scale_at(flight, t: float, session: int = 0) -> float:
    """The simulator's (drifting) SLAM scale of ``session`` at time ``t``."""
    s = flight.meta["truth"]["slam_sessions"][str(session)]
    return s["scale"] * (1.0 + s["scale_drift_per_s"] * (t - s["t_start"]))


def truth_axis_scale_at(flight, t: float) -> np.ndarray:
    """The simulator's per-axis SLAM scale ``[kx, ky, kz]`` at time ``t`` (session 0's drift
    from t = 0, as the circle scenario applies it)."""
    truth = flight.meta["truth"]
    drift = 1.0 + truth["slam_sessions"]["0"]["scale_drift_per_s"] * t
    return np.asarray(truth["slam_axis_scale"]) * drift


def circle_axis_run(run):
    """Seed 000's circle (per-axis SLAM scale 0.3/0.2/0.25, drifting) with every sensor and the
    rendered downward camera, 20 s, seed 1, through ``run(flight, FixedLagOptions())``, which
    must report no solver failure: ``(flight, estimate, SE(3)-aligned metrics)``."""
    from fgnav.datasets.simulate import SimOptions, simulate

    from fgnav.eval.metrics import evaluate
    from fgnav.solvers.fixed_lag import FixedLagOptions

    f = simulate("circle", seed=1, options=SimOptions(duration=20.0))
    est = run(f, FixedLagOptions())
    assert est.info["solver_failures"] == 0
    return f, est, evaluate(est, f.ground_truth, alignment="se3")


def feed_until(filt, events, t_cut: float):
    """Feed ``events`` (arrival order) to ``filt`` until one arrives after ``t_cut``; the
    filter's result then."""
    for ev in events:
        if ev.arrival > t_cut:
            break
        filt.feed(ev)
    return filt.result()


def assert_same_prefix(
    part, full, min_states: int = 100, t_cut: float | None = None, atol: float = 1e-12
) -> None:
    """``part``'s trajectory is the first states of ``full``'s, to ``atol`` m (0: bit-identical;
    a causality check: the run cut at ``t_cut`` gives the same states before it)."""
    n = len(part.trajectory)
    assert n > min_states, n
    if t_cut is not None:
        assert part.trajectory.t[-1] <= t_cut
    np.testing.assert_array_equal(part.trajectory.t, full.trajectory.t[:n])
    np.testing.assert_allclose(
        part.trajectory.world_t_body, full.trajectory.world_t_body[:n], rtol=0, atol=atol
    )
