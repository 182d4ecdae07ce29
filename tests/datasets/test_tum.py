"""TUM reader/writer: real files (seconds and ns stamps), exact round trip, bad lines named."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets import FlightFormatError, Trajectory
from fgnav.datasets.tum import read_tum, read_tum_slam, write_tum


def test_round_trip_exact(tmp_path):
    rng = np.random.default_rng(3)
    n = 40
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    traj = Trajectory(1.4e9 + np.cumsum(rng.uniform(0.01, 0.02, n)), rng.normal(size=(n, 3)), q)
    back = read_tum(write_tum(tmp_path / "t.txt", traj))
    np.testing.assert_array_equal(back.t, traj.t)
    np.testing.assert_array_equal(back.world_t_body, traj.world_t_body)
    np.testing.assert_array_equal(back.world_q_body_wxyz, traj.world_q_body_wxyz)


def test_nanoseconds_detected_and_exact(tmp_path):
    p = tmp_path / "ns.txt"
    p.write_text(
        "# t tx ty tz qx qy qz qw\n"
        "1403636579913555712.000000 1 2 3 0 0 0 1\n"
        "1403636579963555584 1 2 3 0 0 0 1\n"
    )
    notes: list[str] = []
    traj = read_tum(p, notes=notes)
    # 1403636579.913555712 s: the seconds part is exact, the ns remainder added once.
    assert traj.t[0] == 1403636579.0 + 0.913555712
    assert traj.t[1] - traj.t[0] == pytest.approx(0.049999872, abs=3e-7)
    assert "nanoseconds" in notes[0]
    np.testing.assert_array_equal(traj.world_q_body_wxyz[0], [1, 0, 0, 0])
    assert read_tum(p, time_unit="s").t[0] == pytest.approx(1.403636579913555712e18)


@pytest.mark.realdata
def test_real_groundtruth_seconds(real_data):
    notes: list[str] = []
    gt = read_tum(real_data / "euroc_MH_01_easy/groundtruth/MH_01_easy.txt", notes=notes)
    assert len(gt) == 36382
    assert gt.rate_hz == pytest.approx(200.0, abs=0.5)
    assert gt.duration == pytest.approx(181.9, abs=0.1)
    assert gt.t[0] == 1403636580.83856
    np.testing.assert_allclose(gt.world_t_body[0], [4.688319, -1.786938, 0.783338])
    np.testing.assert_allclose(gt.world_q_body_wxyz[0], [0.534108, -0.153029, -0.827383, -0.082152])
    path_length = np.linalg.norm(np.diff(gt.world_t_body, axis=0), axis=1).sum()
    assert path_length == pytest.approx(80.6, abs=0.1)
    assert "seconds" in notes[0]


@pytest.mark.realdata
def test_real_orbslam3_ns_with_repeated_lines(real_data):
    notes: list[str] = []
    path = real_data / "euroc_MH_01_easy/orbslam3_mono_runA/f_dataset-MH01_mono.txt"
    slam = read_tum_slam(path, session=2, notes=notes)
    # 3,679 lines; 10 lines at the end repeat the line before exactly (lost tracking).
    assert len(slam) == 3679 - 10
    assert "skipped 10 SLAM pose line(s)" in notes[1]
    assert "lines 3663, 3664, 3665, 3668, 3669" in notes[1]
    assert slam.rate_hz == pytest.approx(20.0, abs=0.1)
    assert slam.t[0] == pytest.approx(1403636579.913555712, abs=3e-7)
    assert set(slam.session.tolist()) == {2}
    np.testing.assert_allclose(slam.slam_t_cam[0], [0.000093245, 0.011393300, 0.004320038])


@pytest.mark.realdata
def test_real_rpg_scientific_seconds(real_data):
    est = read_tum(real_data / "euroc_MH_01_easy/rpg_vio_mono/stamped_traj_estimate.txt")
    assert est.t[0] == pytest.approx(1403636579.763555527)
    assert est.rate_hz == pytest.approx(20.0, abs=0.5)


@pytest.mark.parametrize(
    "body, match",
    [
        ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n", r"x\.txt:2: expected 8 columns"),
        ("1 0 0 0 0 0 0 1\n2 0 zero 0 0 0 0 1\n", r"x\.txt:2: column 3: expected a number"),
        ("1 0 0 0 0 0 0 1\n2 0 nan 0 0 0 0 1\n", r"x\.txt:2: column 3: non-finite"),
        ("# c\n2 0 0 0 0 0 0 1\n\n1 0 0 0 0 0 0 1\n", r"x\.txt:4: time must be strictly"),
        ("1 0 0 0 0 0 0 1\n1 0 0 1 0 0 0 1\n", r"x\.txt:2: time must be strictly increasing"),
        ("1 0 0 0 0 0 0 2\n", r"x\.txt:1: quaternion qx qy qz qw has norm 2"),
        ("# only a comment\n", r"x\.txt: no data lines"),
        # Nanoseconds beyond int64 (a stamp with two lines run together, found by a fuzz).
        (
            "1403636579763555584 0 0 0 0 0 0 1\n14036365797635555841403636579 0 0 0 0 0 0 1\n",
            r"x\.txt:2: column 1: time stamp '14036365797635555841403636579' ns out of range",
        ),
    ],
)
def test_bad_inputs_named(tmp_path, body, match):
    p = tmp_path / "x.txt"
    p.write_text(body)
    with pytest.raises(FlightFormatError, match=match):
        read_tum(p)


def test_missing_file(tmp_path):
    with pytest.raises(FlightFormatError, match="file not found"):
        read_tum(tmp_path / "none.txt")
