"""``fgnav simulate`` and ``simulate_to_folder``: the written folder reads back as the flight."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.native import read_flight
from fgnav.datasets.simulate import SimOptions, simulate, simulate_to_folder

from fgnav.cli import main


def test_cli_writes_the_simulated_flight(tmp_path, capsys):
    out = tmp_path / "two-turns"
    cfg = tmp_path / "sim.toml"
    cfg.write_text("[simulate]\nslam_resets = [1.0]\nslam_reset_gap_s = 0.5\ndrag_k = [0.3, 0.5]\n")
    argv = [
        "simulate",
        "--scenario",
        "two-turns",
        "--seed",
        "1",
        "--out",
        str(out),
        "--duration",
        "2",
        "--no-images",
        "--config",
        str(cfg),
    ]
    assert main(argv) == 0
    f = read_flight(out)
    expected = simulate(
        "two-turns",
        seed=1,
        options=SimOptions(
            duration=2.0, images=False, slam_resets=(1.0,), slam_reset_gap_s=0.5, drag_k=(0.3, 0.5)
        ),
    )
    assert f.images is None
    np.testing.assert_array_equal(f.imu.body_accel, expected.imu.body_accel)
    np.testing.assert_array_equal(f.slam.session, expected.slam.session)
    assert f.meta["truth"]["drag_k"] == [0.3, 0.5]
    assert sorted(f.meta["truth"]["slam_sessions"]) == ["0", "1"]
    # A second run refuses to overwrite without --overwrite: one line, exit code 1.
    capsys.readouterr()
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--overwrite" in err[0]
    assert main([*argv, "--overwrite"]) == 0


def test_cli_rejects_an_unknown_config_key(tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[simulate]\nwarp_speed = 9\n")
    rc = main(
        ["simulate", "--scenario", "hover", "--out", str(tmp_path / "x"), "--config", str(cfg)]
    )
    assert rc == 1
    assert "warp_speed" in capsys.readouterr().err


def test_images_are_written_losslessly(tmp_path):
    opts = SimOptions(duration=0.5, image_rate_hz=10.0)
    folder = simulate_to_folder("vertical", tmp_path / "v", seed=4, options=opts)
    f = read_flight(folder)
    mem = simulate("vertical", seed=4, options=opts)
    assert len(f.images) == len(mem.images) == 6
    for i in range(len(f.images)):
        np.testing.assert_array_equal(f.images.load(i), mem.images.frames[i])
    np.testing.assert_allclose(f.calib.body_T_cam, mem.calib.body_T_cam)
    assert f.calib.camera == mem.calib.camera


def test_cli_rejects_a_negative_seed(tmp_path, capsys):
    """``--seed -1`` (fgnav simulate and fgnav demo) is one line and exit 1; it was numpy's
    ``ValueError: expected non-negative integer`` with a traceback."""
    out = tmp_path / "x"
    argv = ["simulate", "--scenario", "hover", "--seed", "-1", "--out", str(out)]
    assert main([*argv, "--duration", "1", "--no-images"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["fgnav simulate: error: seed -1: expected a non-negative integer"]
    assert not out.exists()
    assert main(["demo", "--out", str(tmp_path / "d"), "--seed", "-1", "--no-images"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["fgnav demo: error: seed -1: expected a non-negative integer"]


@pytest.mark.parametrize(
    ("table", "flags", "needle"),
    [
        ("imu_rate_hz = 1e300", [], "[simulate]: option imu_rate_hz = 1e+300: expected in [0.001"),
        ("slam_rate_hz = 1e-300", [], "option slam_rate_hz = 1e-300: expected in [0.001, 100000]"),
        (
            "gyro_noise_density = -1.0",
            [],
            "option gyro_noise_density = -1.0: expected in [0, 1000]",
        ),
        ("substeps = 100000000", [], "option substeps = 100000000: expected in [1, 1000]"),
        ("slam_scale_range = [-1.0, -1.0]", [], "slam_scale_range=(-1.0, -1.0): expected (low,"),
        # The wrong field was named (image_width, flow_noise_px).
        ("image_height = -1", [], "[simulate]: SimOptions.image_height=-1: expected an image"),
        ("flow_low_quality_noise_factor = -1.0", [], "flow_low_quality_noise_factor=-1.0: exp"),
        ("", ["--duration", "1e9"], "command line: option duration = 1000000000.0: expected <="),
    ],
)
def test_cli_refuses_values_that_make_no_sense(tmp_path, capsys, table, flags, needle):
    """Review 2026-12-07: these ran (for ever) or named another field; one line now, with the
    file and table."""
    cfg = tmp_path / "bad.toml"
    cfg.write_text(f"[simulate]\n{table}\n")
    argv = ["simulate", "--scenario", "hover", "--out", str(tmp_path / "x"), "--config", str(cfg)]
    assert main([*argv, "--no-images", *flags]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err, err
    assert flags or str(cfg) in err
    assert not (tmp_path / "x").exists()
