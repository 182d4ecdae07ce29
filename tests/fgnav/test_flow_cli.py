"""End to end on a simulated flow-deck flight: ``fgnav simulate`` -> folder -> ``fgnav batch`` and
``fgnav compare`` with the flow rows (the CLI as a user runs it)."""

from __future__ import annotations

import json

from testutil import compare_cli

from fgnav.cli import main


def test_simulate_batch_and_compare_a_flow_deck_flight(tmp_path, capsys):
    cfg = tmp_path / "sim.toml"
    cfg.write_text(
        "[simulate]\nslam_rate_hz = 0\nattitude_rate_hz = 0\nyaw_rate_hz = 0\n"
        "range_noise_m = 0.008\nrange_outlier_prob = 0.0\n"
    )
    folder = tmp_path / "flight"
    rc = main(
        [
            "simulate",
            "--scenario",
            "flowdeck",
            "--out",
            str(folder),
            "--duration",
            "12",
            "--no-images",
            "--config",
            str(cfg),
        ]
    )
    assert rc == 0 and (folder / "flow.csv").is_file()
    out = tmp_path / "batch"
    assert main(["batch", str(folder), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    info = summary["info"]
    assert info["options"]["use_flow"] is True
    assert info["factors"]["flow"] > 0.95 * info["keyframes"]
    assert info["flow"]["flow-readings-used"] > 1100
    cmp_out = tmp_path / "cmp"
    rc = compare_cli(folder, cmp_out, "batch,cf-ekf,ekf-flow002,ekf-vo002")
    printed = capsys.readouterr().out
    assert rc == 0
    data = json.loads((cmp_out / "compare.json").read_text())
    rows = {r["method"]: r for r in data["table"]}
    assert set(rows) == {"batch", "cf-ekf", "ekf-flow002"}
    assert "skipped ekf-vo002: needs images; the flight has none" in printed
    # The smoother beats both filters on this flight (ATE after the table's alignment).
    ate = {m: r["ate_rmse_m"] for m, r in rows.items()}
    assert ate["batch"] < min(ate["cf-ekf"], ate["ekf-flow002"])
