"""ORB-SLAM3 settings YAML: the real EuRoC.yaml, older key names, and bad files named."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets import FlightFormatError
from fgnav.datasets.calib_yaml import read_orbslam3_yaml


@pytest.mark.realdata
def test_real_euroc_yaml(real_data):
    notes: list[str] = []
    calib = read_orbslam3_yaml(real_data / "euroc_MH_01_easy/calib/EuRoC.yaml", notes=notes)
    cam = calib.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (458.654, 457.296, 367.215, 248.375)
    assert (cam.width, cam.height) == (752, 480)
    assert cam.distortion == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    assert calib.imu_noise.gyro_noise_density == 1.7e-4
    assert calib.imu_noise.accel_noise_density == 2.0e-3
    assert calib.imu_noise.gyro_random_walk == 1.9393e-05
    assert calib.imu_noise.accel_random_walk == 3.0e-3
    T = calib.body_T_cam
    np.testing.assert_array_equal(
        T[0], [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975]
    )
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    # Camera optical axis (z) ~ IMU +z, camera x (right) ~ IMU +y, camera y (down) ~ IMU -x.
    assert T[2, 2] > 0.99 and T[1, 0] > 0.99 and T[0, 1] < -0.99
    assert notes == []


OLD_STYLE = """%YAML:1.0
---
Camera.type: "PinHole"
Camera.fx: 400.0
Camera.fy: 401.0
Camera.cx: 320.0
Camera.cy: 240.0
Camera.k1: 0.0
Camera.k2: 0.0
Camera.p1: 0.0
Camera.p2: 0.0
Camera.k3: 1e-3
Camera.width: 640
Camera.height: 480
Tbc: !!opencv-matrix
   rows: 4
   cols: 4
   dt: f
   data: [0.0, 0.0, 1.0, 0.1,
          -1.0, 0.0, 0.0, 0.0,
          0.0, -1.000001, 0.0, 0.0,
          0.0, 0.0, 0.0, 1.0]
"""


def test_old_key_names_defaults_and_repair(tmp_path):
    p = tmp_path / "old.yaml"
    p.write_text(OLD_STYLE)
    notes: list[str] = []
    calib = read_orbslam3_yaml(p, notes=notes)
    assert calib.camera.distortion == (0.0, 0.0, 0.0, 0.0, 1e-3)
    assert calib.camera.fy == 401.0
    R = calib.body_T_cam[:3, :3]
    np.testing.assert_allclose(R, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    assert calib.body_T_cam[0, 3] == 0.1
    assert "no IMU noise keys" in notes[0]
    assert "projected onto SO(3)" in notes[1]


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda s: s.replace("Camera.fy: 401.0\n", ""), r"missing key 'Camera1\.fy'"),
        (lambda s: s.replace("400.0", "four hundred"), r"Camera1\.fx: expected a number"),
        (lambda s: s.replace('"PinHole"', '"KannalaBrandt8"'), r"KannalaBrandt8.*not supported"),
        (lambda s: s + "IMU.NoiseGyro: 1.7e-4\n", r"missing IMU noise key\(s\) \['IMU\.NoiseAcc'"),
        (lambda s: s.replace("0.0, 0.0, 0.0, 1.0]", "0.0, 0.0, 1.0]"), r"15 values .* 4x4"),
        (lambda s: s.replace("-1.000001", "-1.5"), r"old\.yaml: Tbc: .*not a proper rotation"),
        (lambda s: s.replace("Camera.cx: 320.0", "Camera.cx: [320.0"), r"old\.yaml:\d+: not valid"),
    ],
)
def test_bad_files_named(tmp_path, edit, match):
    p = tmp_path / "old.yaml"
    p.write_text(edit(OLD_STYLE))
    with pytest.raises(FlightFormatError, match=match):
        read_orbslam3_yaml(p)


def test_binary_and_bad_yaml_files_are_one_line(tmp_path):
    """A binary file given as a config, manifest or calibration was a UnicodeDecodeError; a YAML
    error was four lines (PyYAML's copy of the text and a caret): now one line naming the file,
    line and column (review 2026-12-07)."""
    from fgnav.datasets._files import read_toml, read_yaml

    binary = tmp_path / "x.bin"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00")
    for read in (read_toml, read_yaml, read_orbslam3_yaml):
        with pytest.raises(FlightFormatError, match=r"x\.bin: not a text .*byte 0 is not UTF-8"):
            read(binary)
    bad = tmp_path / "calib.yaml"
    bad.write_text("imu:\n  rate_hz: [1, 2\n  other: 3\n")
    with pytest.raises(FlightFormatError) as e:
        read_yaml(bad)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{bad}:3: not valid YAML, column 8: expected")
    p = tmp_path / "old.yaml"
    p.write_text(OLD_STYLE.replace("Camera.cx: 320.0", "Camera.cx: [320.0"))
    with pytest.raises(FlightFormatError) as e:
        read_orbslam3_yaml(p)
    assert "\n" not in str(e.value) and "not valid YAML" in str(e.value)


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda s: s.replace("rows: 4", "rows: .inf"), r"old\.yaml: Tbc\.rows: expected a whole"),
        (lambda s: s.replace("cols: 4", "cols: [4]"), r"old\.yaml: Tbc\.cols: expected a whole"),
        (lambda s: s.replace("width: 640", "width: .inf"), r"Camera\.width: expected a whole"),
        (lambda s: s.replace("width: 640", "width: 640.5"), r"Camera\.width: expected a whole"),
        (lambda s: s.replace("height: 480", "height: true"), r"Camera\.height: expected a whole"),
        (lambda s: s.replace("fx: 400.0", "fx: 0.0"), r"old\.yaml: camera \(Camera1\.fx"),
        (
            lambda s: s + "IMU.NoiseGyro: .nan\nIMU.NoiseAcc: 1\nIMU.GyroWalk: 1\nIMU.AccWalk: 1\n",
            r"old\.yaml: IMU\.NoiseGyro: expected a number in \[0, 1000\], got nan",
        ),
        (
            lambda s: s.replace("0.0, 0.0, 1.0, 0.1,", "0.0, 0.0, 1.0, .nan,"),
            r"old\.yaml: Tbc: expected a finite 4x4",
        ),
    ],
    ids=[
        "rows-inf",
        "cols-list",
        "width-inf",
        "width-fraction",
        "height-bool",
        "fx-zero",
        "noise-nan",
        "T-nan",
    ],
)
def test_wrong_value_types_name_the_key(tmp_path, edit, match):
    """Wrong value types were OverflowError tracebacks (``.inf`` rows or width) or accepted
    (``width: true`` read as 1); every calibration check failed as "IMU.T_b_c1:" (a NaN noise
    or a zero fx too): each now names its own key, on one line."""
    p = tmp_path / "old.yaml"
    p.write_text(edit(OLD_STYLE))
    with pytest.raises(FlightFormatError, match=match) as e:
        read_orbslam3_yaml(p)
    assert "\n" not in str(e.value)


def test_byte_order_mark_is_read(tmp_path):
    """A UTF-8 byte-order mark before ``%YAML:1.0`` hid the directive (a YAML error about a
    directive): it is skipped, the file reads as without it."""
    p = tmp_path / "bom.yaml"
    p.write_text("\ufeff" + OLD_STYLE, encoding="utf-8")
    assert read_orbslam3_yaml(p).camera.fx == 400.0
