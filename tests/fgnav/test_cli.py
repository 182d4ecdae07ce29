from __future__ import annotations

from testutil import run_cli


def test_help_lists_subcommands():
    r = run_cli("--help")
    assert r.returncode == 0
    for name in ("info", "simulate", "batch", "online", "compare", "demo"):
        assert name in r.stdout


def test_printed_ate_names_the_alignment_used(tmp_path, capsys):
    """The ATE line names the alignment the metrics used: a straight-line (vertical) flight
    falls back to translation only, and the line says so instead of SE(3)."""
    import dataclasses

    import numpy as np
    from fgnav.datasets.simulate import SimOptions, simulate
    from fgnav.datasets.types import Trajectory

    from fgnav.commands.batch import score_and_write
    from fgnav.estimate import Estimate
    from fgnav.eval.align import DEGENERATE_MODE

    flight = simulate("vertical", seed=1, options=SimOptions(images=False, duration=6.0))
    gt = flight.ground_truth
    line = gt.world_t_body * np.array([0.0, 0.0, 1.0])  # on the z axis: points on a line
    gt_line = dataclasses.replace(gt, world_t_body=line)
    flight = dataclasses.replace(flight, ground_truth=gt_line)
    est = Estimate(
        "batch", Trajectory(gt.t, line + np.array([0.3, -0.2, 0.1]), gt.world_q_body_wxyz)
    )
    score_and_write(flight, est, tmp_path, {})
    out = capsys.readouterr().out
    assert f"RMSE ({DEGENERATE_MODE} alignment)" in out
    assert "SE(3) alignment" not in out
    turns = simulate("two-turns", seed=1, options=SimOptions(images=False, duration=6.0))
    g2 = turns.ground_truth
    est2 = Estimate("batch", Trajectory(g2.t, g2.world_t_body + 0.01, g2.world_q_body_wxyz))
    score_and_write(turns, est2, tmp_path, {})
    assert "RMSE (SE(3) alignment)" in capsys.readouterr().out


def test_verbose_flag_adds_debug_lines():
    """INFO lines are printed by default; ``-v`` adds fgnav's DEBUG lines, ``-vv`` every
    library's (``-v`` had been the default level, and only ``-vv`` changed anything)."""
    import logging

    from fgnav.cli import build_parser, log_levels

    parser, _ = build_parser()
    assert log_levels(parser.parse_args(["info", "x"]).verbose) == (logging.INFO, None)
    assert log_levels(parser.parse_args(["-v", "info", "x"]).verbose) == (
        logging.INFO,
        logging.DEBUG,
    )
    assert log_levels(parser.parse_args(["-vv", "info", "x"]).verbose) == (logging.DEBUG, None)
    r = run_cli("--help")
    assert "fgnav's DEBUG lines" in " ".join(r.stdout.split())


def test_python_dash_m_fgnav_is_the_command():
    """``python -m fgnav`` runs the same CLI as ``fgnav`` (it said "No module named
    fgnav.__main__" before); an unknown command exits 2 as argparse does."""
    import subprocess
    import sys

    from testutil import PROJECT_ROOT

    r = subprocess.run(
        [sys.executable, "-m", "fgnav", "--help"], capture_output=True, text=True, cwd=PROJECT_ROOT
    )
    assert r.returncode == 0, r.stderr
    assert "usage: fgnav" in r.stdout and "simulate" in r.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "fgnav", "no-such-command"],
        capture_output=True,
        text=True,
        cwd=PROJECT_ROOT,
    )
    assert bad.returncode == 2
