"""flight_info numbers on a constructed flight, and ``fgnav info`` end to end (subprocess)."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets import Flight, ImuSeries, RangeSeries, SlamSeries, Trajectory
from fgnav.datasets.native import write_flight
from testutil import PROJECT_ROOT, run_cli

from fgnav.info import GAP_FACTOR, flight_info

MH01_MANIFEST = PROJECT_ROOT / "datasets" / "manifests" / "euroc_mh01_orbslam3.toml"


def _flight() -> Flight:
    rng = np.random.default_rng(2)
    t_imu = 10.0 + np.arange(1000) * 0.005  # 200 Hz, 10.0 .. 14.995
    t_slam = 10.5 + np.arange(80) * 0.05  # 20 Hz, 10.5 .. 14.45
    drop = np.r_[np.arange(20, 23), np.arange(50, 51)]  # a 0.2 s gap at 11.45 and 0.1 s at 12.95
    t_slam = np.delete(t_slam, drop)
    n = len(t_slam)
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    return Flight(
        name="constructed",
        imu=ImuSeries(t_imu, rng.normal(size=(1000, 3)), rng.normal(size=(1000, 3))),
        slam=SlamSeries(
            t_slam,
            rng.normal(size=(n, 3)),
            q,
            np.r_[np.zeros(40), np.ones(n - 40)].astype(np.int64),
        ),
        range=RangeSeries(9.0 + np.arange(50) * 0.1, np.linspace(0.5, 3.0, 50)),
        ground_truth=Trajectory(
            t_imu, rng.normal(size=(1000, 3)), np.tile([1.0, 0, 0, 0], (1000, 1))
        ),
        references={"ekf": Trajectory(t_slam, rng.normal(size=(n, 3)), q)},
        meta={"notes": ["reader skipped 3 lines"], "imu": {"imu_samples_skipped_nonfinite": 2}},
    )


def test_flight_info_numbers():
    info = flight_info(_flight())
    imu, slam, rng_ = info.stream("imu"), info.stream("slam"), info.stream("range")
    assert imu.samples == 1000 and imu.rate_hz == pytest.approx(200.0) and imu.gaps == 0
    assert imu.duration == pytest.approx(4.995)
    assert slam.rate_hz == pytest.approx(20.0) and slam.samples == 76
    # Steps above 2.5 x 0.05 s = 0.125 s count: the 0.2 s one (3 frames dropped) does, the 0.1 s
    # one (1 frame dropped) does not.
    assert GAP_FACTOR == 2.5
    assert slam.gaps == 1
    assert slam.largest_step_s == pytest.approx(0.2)
    assert slam.largest_step_at == pytest.approx(11.45)
    assert slam.details == "sessions 2 (0: 40, 1: 36)"
    assert rng_.details == "range 0.50 .. 3.00 m"
    assert info.stream("ref:ekf").role == "reference"
    assert info.stream("ground_truth").role == "ground truth"
    assert info.t0 == 9.0
    assert info.overlap == (10.5, pytest.approx(13.9))
    assert info.overlap_streams == ("imu", "range", "slam")
    assert info.notes == ("reader skipped 3 lines", "imu.imu_samples_skipped_nonfinite = 2")
    text = info.format()
    assert "sensor overlap: 1.500 .. 4.900 s (3.400 s;" in text
    assert "\nslam " in text and "reader skipped 3 lines" in text


def _run(*args):
    return run_cli("info", *args)


@pytest.mark.realdata
def test_cli_info_mh01(real_data):
    r = _run(MH01_MANIFEST)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("---")) + 1
    last = lines.index("", first)
    # Columns: stream role samples rate start end duration gaps max-dt at details.
    rows = {line.split()[0]: line.split() for line in lines[first:last]}
    assert list(rows) == ["imu", "slam", "ground_truth", "ref:rpg_vio_mono"]
    assert rows["imu"][2:4] == ["36820", "200.00"]
    assert float(rows["imu"][6]) == pytest.approx(184.1, abs=0.05)
    assert rows["slam"][2:4] == ["3669", "20.00"] and int(rows["slam"][7]) == 3
    assert rows["ground_truth"][1:2] == ["ground"] and rows["ground_truth"][4] == "200.00"
    assert "sensor overlap: 0.155 .. 184.005 s (183.850 s;" in r.stdout
    assert "skipped 10 SLAM pose line(s)" in r.stdout
    assert "camera        752x480 px, fx 458.654" in r.stdout
    # No rangefinder or flow sensor on this flight: their mounts and limits are not listed.
    assert "body_T_cam" in r.stdout
    for absent in ("body_T_range", "range limits", "body_T_flow"):
        assert absent not in r.stdout


def test_cli_info_native_folder_and_errors(tmp_path):
    write_flight(_flight(), tmp_path / "f")
    r = _run(tmp_path / "f")
    assert r.returncode == 0, r.stderr
    assert "flight  constructed" in r.stdout and "reader skipped 3 lines" in r.stdout
    r = _run(tmp_path / "nothere")
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        f"fgnav info: error: {tmp_path / 'nothere'}: no such file or folder"
    ]
    r = _run(tmp_path / "f", "--topics", "imu")
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [
        "fgnav info: error: --topics: expected name=topic, got 'imu'"
    ]
