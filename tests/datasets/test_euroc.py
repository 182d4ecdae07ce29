"""EuRoC/ASL readers: the real MH_01 files (including the spreadsheet-damaged IMU csv), the
V1_02 full-state ground truth, a synthetic mav0 folder, and bad inputs named precisely."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from fgnav.datasets import FlightFormatError
from fgnav.datasets.euroc import read_euroc_folder, read_euroc_groundtruth, read_euroc_imu
from fgnav.datasets.geometry import invert_pose

MH01 = "euroc_MH_01_easy"


@pytest.mark.realdata
def test_real_imu_clean(real_data):
    imu = read_euroc_imu(real_data / MH01 / "imu0/data.cleaned.csv")
    assert len(imu) == 36820
    assert imu.rate_hz == pytest.approx(200.0, abs=0.1)
    assert imu.duration == pytest.approx(184.1, abs=0.05)
    assert imu.t[0] == pytest.approx(1403636579.75856, abs=1e-6)
    np.testing.assert_array_equal(imu.body_omega[0], [-0.0991347015, 0.1473057889, 0.0272271363])
    np.testing.assert_array_equal(imu.body_accel[0], [8.1476917083, -0.3759215833, -2.40262925])
    # EuRoC IMU axes: at rest the specific force is mostly along +x (x up), see module docstring.
    mean_f = imu.body_accel[:400].mean(axis=0)
    assert mean_f[0] > 8.0 and mean_f[2] < -1.5


@pytest.mark.realdata
def test_real_spreadsheet_imu_loads_with_warnings(real_data, caplog):
    notes: list[str] = []
    with caplog.at_level(logging.WARNING, logger="fgnav.datasets.euroc"):
        bad = read_euroc_imu(real_data / MH01 / "imu0/data.csv", notes=notes)
    clean = read_euroc_imu(real_data / MH01 / "imu0/data.cleaned.csv")
    assert len(bad) == len(clean) == 36820
    np.testing.assert_array_equal(bad.body_omega, clean.body_omega)
    np.testing.assert_array_equal(bad.body_accel, clean.body_accel)
    # The cleaned file's stamps went through float64 (64 ns off); seconds agree to 1 ulp.
    assert np.abs(bad.t - clean.t).max() <= 2.5e-7
    assert len(notes) == 2
    assert "skipped 7 trailing non-data line(s)" in notes[0] and "lines 36822-36828" in notes[0]
    assert "resolution is only 10 us" in notes[1] and "line 2: '1.40363657975856E+018'" in notes[1]
    assert [r.levelname for r in caplog.records] == ["WARNING", "WARNING"]


@pytest.mark.realdata
def test_real_full_state_groundtruth(real_data):
    gt = read_euroc_groundtruth(real_data / "euroc_V1_02_medium/groundtruth/V102_groundtruth.csv")
    assert len(gt) == 16702
    assert gt.rate_hz == pytest.approx(200.0, abs=0.5)
    q0 = [0.161996, 0.789985, -0.205376, 0.554528]
    np.testing.assert_array_equal(gt.world_q_body_wxyz[0], q0)
    np.testing.assert_array_equal(gt.world_v_body[0], [-0.002276, -0.009616, -0.005214])
    np.testing.assert_array_equal(gt.gyro_bias[0], [-0.002153, 0.020744, 0.075806])
    np.testing.assert_array_equal(gt.accel_bias[0], [-0.013337, 0.103464, 0.093086])
    # Velocity agrees with differentiated position (top speed about 2.2 m/s per the data README).
    dp = np.diff(gt.world_t_body, axis=0) / np.diff(gt.t)[:, None]
    assert np.median(np.linalg.norm(dp - gt.world_v_body[1:], axis=1)) < 0.05
    assert np.linalg.norm(gt.world_v_body, axis=1).max() == pytest.approx(2.2, abs=0.15)


@pytest.mark.realdata
def test_real_cam0_pose_groundtruth(real_data):
    notes: list[str] = []
    gt = read_euroc_groundtruth(real_data / MH01 / "groundtruth/MH01_GT.txt", notes=notes)
    assert len(gt) == 3638 and gt.world_v_body is None
    assert gt.rate_hz == pytest.approx(20.0, abs=0.01)
    assert gt.t[0] == pytest.approx(1403636580.863555584, abs=3e-7)
    assert "cam0 poses" in notes[0]


def _write(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


HEADER = "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
HEADER += "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n"


def _rows(n, t0=1403636579758560000):
    return "".join(f"{t0 + i * 5_000_000},0.1,0.2,0.3,9.0,0.1,-3.0\n" for i in range(n))


@pytest.mark.parametrize(
    "body, match",
    [
        (
            _rows(3) + ",,,,,,\n" + _rows(2, 1403636579800000000),
            r"d\.csv:5: column 1 \('timestamp'\): expected a number, found ''",
        ),
        (_rows(3).replace("0.2,", "nan,", 1), r"d\.csv:2: column 3 \('w_RS_S_y'\): non-finite"),
        (_rows(3).replace(",0.3", "", 1) + _rows(1, 1403636579900000000), r"d\.csv:2: expected 7"),
        (_rows(3)[::-1].split("\n", 1)[1][::-1] + "\n" + _rows(1), r"d\.csv:5: time must be"),
        ("", r"d\.csv: no data lines"),
    ],
    ids=["junk-in-the-middle", "nan", "column-count", "time-backwards", "empty"],
)
def test_bad_imu_named(tmp_path, body, match):
    p = _write(tmp_path / "d.csv", HEADER + body)
    with pytest.raises(FlightFormatError, match=match):
        read_euroc_imu(p)


def test_bad_header_named(tmp_path):
    p = _write(tmp_path / "d.csv", HEADER.replace("w_RS_S_y", "w_y") + _rows(2))
    with pytest.raises(FlightFormatError, match=r"d\.csv:1: header column 3 is 'w_y"):
        read_euroc_imu(p)
    p = _write(tmp_path / "e.csv", _rows(2))
    with pytest.raises(FlightFormatError, match=r"e\.csv:1: missing the EuRoC header"):
        read_euroc_imu(p)


def test_synthetic_mav0_folder(tmp_path):
    import cv2

    mav0 = tmp_path / "MH_99" / "mav0"
    _write(mav0 / "imu0/data.csv", HEADER + _rows(20))
    _write(
        mav0 / "imu0/sensor.yaml",
        "sensor_type: imu\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0,"
        " 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\nrate_hz: 200\n"
        "gyroscope_noise_density: 1.6968e-04\ngyroscope_random_walk: 1.9393e-05\n"
        "accelerometer_noise_density: 2.0000e-3\naccelerometer_random_walk: 3.0000e-3\n",
    )
    T_BS = (
        "[0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,"
        " 0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,"
        " -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,"
        " 0.0, 0.0, 0.0, 1.0]"
    )
    _write(
        mav0 / "cam0/sensor.yaml",
        f"sensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: {T_BS}\nrate_hz: 20\n"
        "resolution: [752, 480]\ncamera_model: pinhole\n"
        "intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        "distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]\n",
    )
    rng = np.random.default_rng(5)
    names = []
    for i in range(2):
        name = f"{1403636579758560000 + i * 50_000_000}.png"
        (mav0 / "cam0/data").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(mav0 / "cam0/data" / name), rng.integers(0, 255, (8, 8), dtype=np.uint8))
        names.append(name)
    _write(
        mav0 / "cam0/data.csv",
        "#timestamp [ns],filename\n" + "".join(f"{n[:-4]},{n}\n" for n in names),
    )
    gt_header = "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
    gt_header += "q_RS_y [], q_RS_z [], v_x, v_y, v_z, bw_x, bw_y, bw_z, ba_x, ba_y, ba_z\n"
    gt_rows = "".join(
        f"{1403636579758560000 + i * 5_000_000},{i * 0.01},0,1,1,0,0,0,2,0,0,0,0,0,0,0,0\n"
        for i in range(10)
    )
    _write(mav0 / "state_groundtruth_estimate0/data.csv", gt_header + gt_rows)

    flight = read_euroc_folder(tmp_path / "MH_99")
    assert flight.name == "MH_99"
    assert len(flight.imu) == 20 and len(flight.ground_truth) == 10 and len(flight.images) == 2
    assert flight.calib.camera.fx == 458.654 and flight.calib.camera.width == 752
    assert flight.calib.imu_noise.gyro_noise_density == 1.6968e-04
    assert flight.calib.body_T_cam[0, 3] == -0.0216401454975
    np.testing.assert_allclose(
        invert_pose(flight.calib.body_T_cam)[:3, :3], flight.calib.body_T_cam[:3, :3].T
    )
    assert flight.images.load(1).shape == (8, 8)
    assert flight.meta["notes"] == []
    (mav0 / "cam0/data" / names[1]).unlink()
    with pytest.raises(FlightFormatError, match=r"cam0/data\.csv:3: image file .* not found"):
        read_euroc_folder(mav0)
    with pytest.raises(FlightFormatError, match="imu0/data.csv not found"):
        read_euroc_folder(tmp_path)


@pytest.mark.parametrize(
    "value, match",
    [
        ("abc", r"expected a number, found 'abc'"),
        ("[1, 2]", r"expected a number, found \[1, 2\]"),
        ("null", r"expected a number, found None"),
        (".nan", r"expected a number in \[0, 1000\], got nan"),
    ],
)
def test_bad_imu_noise_in_sensor_yaml_named(tmp_path, value, match):
    """A wrong value of an IMU noise key was a ValueError/TypeError traceback, a NaN one an
    error naming the mav0 folder: one line naming sensor.yaml and the key."""
    mav0 = tmp_path / "MH_98" / "mav0"
    _write(mav0 / "imu0/data.csv", HEADER + _rows(20))
    yaml_path = _write(
        mav0 / "imu0/sensor.yaml",
        f"sensor_type: imu\ngyroscope_noise_density: {value}\ngyroscope_random_walk: 1.9e-05\n"
        "accelerometer_noise_density: 2.0e-3\naccelerometer_random_walk: 3.0e-3\n",
    )
    with pytest.raises(FlightFormatError) as e:
        read_euroc_folder(tmp_path / "MH_98")
    msg = str(e.value)
    assert msg.startswith(f"{yaml_path}: gyroscope_noise_density: "), msg
    assert "\n" not in msg
    assert __import__("re").search(match, msg), msg


def test_imu_header_units_are_checked(tmp_path):
    """A gyro column in [deg s^-1] was read as rad/s: a unit other than EuRoC's is refused on
    one line naming the file, header line and column; no unit, or EuRoC's, reads as before."""
    p = _write(tmp_path / "d.csv", HEADER.replace("w_RS_S_y [rad s^-1]", "w_RS_S_y [deg s^-1]"))
    p.write_text(p.read_text() + _rows(3))
    with pytest.raises(FlightFormatError) as e:
        read_euroc_imu(p)
    assert str(e.value).startswith(f"{p}:1: header column 3 'w_RS_S_y [deg s^-1]': unit [deg")
    p = _write(tmp_path / "g.csv", HEADER.replace("a_RS_S_z [m s^-2]", "a_RS_S_z [g]") + _rows(3))
    with pytest.raises(FlightFormatError, match=r"g\.csv:1: header column 7 .*unit \[g\]"):
        read_euroc_imu(p)
    bare = "#timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z [m/s^2]\n"
    assert len(read_euroc_imu(_write(tmp_path / "b.csv", bare + _rows(3)))) == 3
