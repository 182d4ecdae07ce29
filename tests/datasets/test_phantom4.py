"""ANSFL Phantom 4 reader and the rotor-drag identification on the real straight-line flight."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.errors import FlightFormatError
from fgnav.datasets.frames import tilt_angle
from fgnav.datasets.geometry import quat_wxyz_to_matrix, so3_log, yaw_of
from fgnav.datasets.phantom4 import (
    DragSamples,
    drag_samples,
    estimate_body_R_imu,
    fit_linear_drag,
    read_phantom4,
    with_body_axes,
)
from fgnav.datasets.time_offset import estimate_time_offset

#: Plausible rotor-drag coefficients k = mu/m of multirotors [1/s], set independently of this
#: flight: PX4 bounds its propeller momentum drag EKF2_MCOEF to [0, 1] 1/s, default 0.15
#: (src/modules/ekf2/params_drag.yaml); seed 000 simulates kx = 0.3, ky = 0.2 1/s. Below 0.1 the
#: drag would be invisible in a 3 m/s flight (< 0.3 m/s^2, under the 0.1 s-mean noise); above 1.0
#: is outside PX4's range. A fit outside the band means a sign, frame, unit or clock error.
PLAUSIBLE_K = (0.1, 1.0)


def test_fit_linear_drag_recovers_synthetic_k():
    rng = np.random.default_rng(11)
    n = 400
    u = np.column_stack([np.linspace(0, 4, n), rng.uniform(-1, 1, n), np.zeros(n)])
    k, b = 0.35, np.array([0.2, -0.1])
    f = np.zeros((n, 3))
    f[:, :2] = -k * u[:, :2] + b + rng.normal(scale=0.05, size=(n, 2))
    s = DragSamples(np.arange(n) * 0.1, f, u, np.full(n, 12))
    fit = fit_linear_drag(s, (0, 1))
    assert fit.k == pytest.approx(k, abs=4 * fit.k_se)
    assert fit.k_se < 0.01
    np.testing.assert_allclose(fit.bias, b, atol=0.02)
    assert fit.r2 > 0.95 and fit.residual_std == pytest.approx(0.05, rel=0.2)
    # No relation at all: k is not significant.
    s_null = DragSamples(s.t, f, rng.permutation(u), s.samples_per_window)
    null = fit_linear_drag(s_null, (0,))
    assert abs(null.k) < 3 * null.k_se_autocorr and null.r2 < 0.05


def test_reader_errors_name_file_and_line(tmp_path):
    folder = tmp_path / "path_1"
    folder.mkdir()
    header = "time,Euler_X,Euler_Y,Euler_Z,Acc_X,Acc_Y,Acc_Z,Gyr_X,Gyr_Y,Gyr_Z\n"
    (folder / "IMU_1.csv").write_text(header + "0.0,0,0,0,0,0,9.8,0,0,0\n0.1,0,0,0,0,0,x,0,0,0\n")
    with pytest.raises(FlightFormatError, match=r"IMU_1.csv:3: column 'Acc_Z': 'x'"):
        read_phantom4(folder, "IMU_1.csv")
    (folder / "IMU_1.csv").write_text("time,Acc_X\n0,1\n")
    with pytest.raises(FlightFormatError, match=r"IMU_1.csv:1: header lacks columns"):
        read_phantom4(folder, "IMU_1.csv")


@pytest.fixture(scope="module")
def folder(real_data):
    return real_data / "ansfl_phantom4_rtk_mimu" / "StraightLine" / "path_1"


@pytest.mark.realdata
def test_read_real_flight(folder):
    f = read_phantom4(folder, "IMU_1.csv")
    assert f.imu.rate_hz == pytest.approx(120.0, rel=1e-3)
    assert f.ground_truth.rate_hz == pytest.approx(10.0, rel=1e-3)
    assert f.meta["euler_yaw_jumps"] == 0
    gt = f.ground_truth
    # Flies about 67 m towards compass heading ~246 deg (WSW): in fgnav's world x east, y north.
    d = gt.world_t_body[-1] - gt.world_t_body[0]
    assert np.hypot(d[0], d[1]) == pytest.approx(67.0, abs=2.0)
    assert np.degrees(np.arctan2(d[0], d[1])) % 360 == pytest.approx(247.0, abs=3.0)
    # Nose along the track: fgnav yaw = 90 deg - compass heading.
    yaw = np.degrees(yaw_of(gt.world_R_body()[-1]))
    assert (yaw - (90.0 - 245.5) + 180) % 360 - 180 == pytest.approx(0.0, abs=0.5)
    # Logged velocity agrees with the RTK track (0.1 m/s resolution).
    v_fd = np.gradient(gt.world_t_body[:, :2], gt.t, axis=0)
    assert np.median(np.abs(v_fd - gt.world_v_body[:, :2])) < 0.1
    # IMU at hover start: specific force (near) +g along z in the IMU's axes.
    assert f.imu.body_accel[:60, 2].mean() == pytest.approx(9.5, abs=0.4)


@pytest.mark.realdata
def test_averaged_imu_yaw_jumps_are_reported(folder):
    f = read_phantom4(folder, "IMUAvg.csv")
    assert f.meta["euler_yaw_jumps"] >= 2  # into and out of a wrapped-average segment
    assert "unreliable" in f.meta["notes"][0]


@pytest.mark.realdata
def test_mount_and_clock(folder):
    f = read_phantom4(folder, "IMU_1.csv")
    mount = estimate_body_R_imu(f)
    # The Xsens is mounted square to the airframe: its z axis within 1.5 deg of the body's, and
    # the attitude residual within 1.5 deg RMS. The mount's yaw is weakly determined on a
    # single-heading flight (it trades off with the world heading offset): only bounded loosely.
    z_tilt = np.degrees(np.arccos(np.clip(mount.body_R_imu[2, 2], -1.0, 1.0)))
    assert z_tilt < 1.5
    assert np.degrees(np.linalg.norm(so3_log(mount.body_R_imu))) < 5.0
    assert mount.residual_rms_deg < 1.5
    # Both worlds are z up: only a heading difference (magnetic vs DJI compass).
    assert abs(mount.gt_world_R_imu_world[2, 2] - 1.0) < 1e-9
    # Clocks agree to within about one ground-truth period.
    att = with_body_axes(f, mount.body_R_imu).attitude
    res = estimate_time_offset(
        f.ground_truth.t,
        tilt_angle(f.ground_truth.world_R_body()),
        att.t,
        tilt_angle(quat_wxyz_to_matrix(att.world_q_body_wxyz)),
        1.0,
        min_overlap_s=10.0,
    )
    assert res.correlation > 0.95
    assert abs(res.offset_s) < 0.15


@pytest.mark.realdata
def test_drag_identification_real(folder):
    raw = read_phantom4(folder, "IMU_1.csv")
    mount = estimate_body_R_imu(raw)
    f = with_body_axes(raw, mount.body_R_imu)
    samples = drag_samples(f, 0.1)
    fx = fit_linear_drag(samples, (0,))
    assert np.isfinite(fx.k)
    assert PLAUSIBLE_K[0] < fx.k < PLAUSIBLE_K[1]
    # Significant against residual autocorrelation, and the drag term explains a real share.
    assert fx.k > 5.0 * fx.k_se_autocorr
    assert fx.r2 > 0.3
    # A second sensor (mean of the four IMUs' accelerometers) gives the same k within 2 SE.
    avg = with_body_axes(read_phantom4(folder, "IMUAvg.csv"), mount.body_R_imu)
    fx_avg = fit_linear_drag(drag_samples(avg, 0.1), (0,))
    assert abs(fx_avg.k - fx.k) < 2.0 * np.hypot(fx.k_se_autocorr, fx_avg.k_se_autocorr)
    # Destroying the pairing (shuffled velocities) destroys the fit: the test can fail.
    rng = np.random.default_rng(0)
    shuffled = DragSamples(
        samples.t,
        samples.mean_body_accel,
        rng.permutation(samples.body_velocity),
        samples.samples_per_window,
    )
    null = fit_linear_drag(shuffled, (0,))
    assert abs(null.k) < 3.0 * null.k_se_autocorr


def test_header_only_and_binary_files_named(tmp_path):
    """A header-only csv was a ValueError/IndexError traceback, a non-UTF-8 one a
    UnicodeDecodeError: one line naming the file."""
    folder = tmp_path / "path_1"
    folder.mkdir()
    header = "time,Euler_X,Euler_Y,Euler_Z,Acc_X,Acc_Y,Acc_Z,Gyr_X,Gyr_Y,Gyr_Z\n"
    (folder / "IMU_1.csv").write_text(header)
    with pytest.raises(FlightFormatError, match=r"IMU_1.csv:1: no data rows after the header"):
        read_phantom4(folder, "IMU_1.csv")
    (folder / "IMU_1.csv").write_bytes(b"\xff\xfe" + header.encode())
    with pytest.raises(FlightFormatError, match=r"IMU_1.csv: not a text file: byte 0"):
        read_phantom4(folder, "IMU_1.csv")
