"""Smoke tests of ``fgnav batch`` and ``fgnav online`` (in-process, short simulated flight)."""

from __future__ import annotations

import json

import pytest
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate_to_folder
from testutil import command_cli, two_turns_folder

from fgnav.cli import main


@pytest.fixture(scope="module")
def flight_folder(tmp_path_factory):
    return two_turns_folder(tmp_path_factory, seed=3)


def test_batch_command_writes_outputs(flight_folder, tmp_path, capsys):
    out = tmp_path / "batch"
    cfg = '[graph]\nkeyframe_hz = 10.0\n[batch]\ncovariance = "slow"\n'
    assert command_cli("batch", flight_folder, out, config=cfg) == 0
    text = capsys.readouterr().out
    assert "ATE" in text and "SE(3) alignment" in text
    for name in ("estimate.tum", "states.csv", "summary.json"):
        assert (out / name).is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "batch"
    assert summary["metrics"]["ate_rmse_m"] < 0.05
    assert summary["info"]["options"]["keyframe_hz"] == 10.0
    # drag k is printed with its sigma: an axis left at its prior reads as such
    import re

    line = next(ln for ln in text.splitlines() if ln.startswith("drag k: "))
    pairs = re.findall(r"(-?[\d.]+) \+/- ([\d.e-]+)", line)
    assert len(pairs) == 2, line
    sig = [float(e) for _, e in pairs]
    assert summary["drag_k_sigma_per_s"] == pytest.approx(sig, rel=0.05)


def test_online_command_prints_latency(flight_folder, tmp_path, capsys):
    out = tmp_path / "online"
    assert command_cli("online", flight_folder, out, "--lag", "1.5") == 0
    text = capsys.readouterr().out
    assert "p50" in text and "p99" in text and "real time" in text
    # A native folder without images: read in chunks as it is replayed, scored all the same.
    assert "read in chunks" in text and "scored:" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "fixed-lag" and summary["causal"] is True
    assert summary["info"]["lag_s"] == 1.5
    assert summary["metrics"]["ate_rmse_m"] < 0.1


def test_bad_config_is_one_line_error(flight_folder, tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[graph]\nkeyframe_hzz = 10.0\n")
    assert (
        main(["batch", str(flight_folder), "--out", str(tmp_path / "x"), "--config", str(cfg)]) == 1
    )
    err = capsys.readouterr().err
    assert "keyframe_hzz" in err and len(err.strip().splitlines()) == 1


def test_frontend_priors_flag(tmp_path, capsys):
    """``--priors ml-scale`` runs seed 004's closed-form scale on a vertical flight and the
    smoother starts from it; an unknown source is a one-line error."""
    folder = tmp_path / "vertical"
    simulate_to_folder("vertical", folder, seed=2, options=SimOptions(duration=12.0, images=False))
    out = tmp_path / "online"
    args = ["online", str(folder), "--out", str(out), "--priors", "ml-scale", "--no-progress"]
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "fixed-lag"
    truth = json.loads((folder / "meta.json").read_text())["meta"]["truth"]["slam_sessions"]["0"]
    prior = summary["extra"]["frontend_priors"]["slam_scale"]["0"]
    assert abs(prior / truth["scale"] - 1.0) < 0.05
    assert main(["batch", str(folder), "--out", str(tmp_path / "b"), "--priors", "magic"]) == 1
    assert "unknown front-end prior" in capsys.readouterr().err
