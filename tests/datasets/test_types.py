"""Data model checks: each bad input gives an error naming the stream and field."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets import FlightDataError, ImuSeries, SlamSeries, Trajectory
from fgnav.datasets.geometry import (
    matrix_to_quat_wxyz,
    quat_wxyz_to_matrix,
    rpy_to_matrix,
    so3_exp,
    so3_log,
    wrap_angle,
    yaw_of,
)


def _imu(n=10):
    t = np.arange(n) * 0.005
    return ImuSeries(t, np.zeros((n, 3)), np.tile([0, 0, 9.81], (n, 1)))


def test_good_series_passes():
    assert _imu().check() is not None
    assert _imu().rate_hz == pytest.approx(200.0)


def test_non_increasing_time_is_named():
    imu = _imu()
    imu.t[5] = imu.t[4]
    with pytest.raises(
        FlightDataError, match=r"imu\.t: time must be strictly increasing; sample 5"
    ):
        imu.check()


def test_nan_is_named():
    imu = _imu()
    imu.body_accel[3, 1] = np.nan
    with pytest.raises(FlightDataError, match=r"imu\.body_accel: non-finite value at sample 3"):
        imu.check()


def test_wrong_shape_and_empty():
    with pytest.raises(FlightDataError, match="expected shape"):
        ImuSeries(np.arange(3.0), np.zeros((3, 2)), np.zeros((3, 3))).check()
    with pytest.raises(FlightDataError, match="empty"):
        ImuSeries(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))).check()


def test_non_unit_quaternion_and_float_session():
    n = 4
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    q[2] = [2, 0, 0, 0]
    with pytest.raises(FlightDataError, match="norm 2.0"):
        Trajectory(np.arange(n, dtype=float), np.zeros((n, 3)), q).check()
    with pytest.raises(FlightDataError, match="integer ids"):
        SlamSeries(
            np.arange(n, dtype=float),
            np.zeros((n, 3)),
            np.tile([1.0, 0, 0, 0], (n, 1)),
            np.zeros(n),
        ).check()


def test_quaternion_round_trip_and_so3():
    rng = np.random.default_rng(0)
    for _ in range(20):
        R = so3_exp(rng.normal(size=3))
        q = matrix_to_quat_wxyz(R)
        assert np.allclose(quat_wxyz_to_matrix(q), R, atol=1e-12)
        assert np.allclose(so3_exp(so3_log(R)), R, atol=1e-9)
    R = rpy_to_matrix(0.1, -0.2, 3.0)
    assert yaw_of(R) == pytest.approx(3.0)
    assert wrap_angle(np.pi) == pytest.approx(np.pi)
    assert wrap_angle(-np.pi) == pytest.approx(np.pi)
    assert wrap_angle(3 * np.pi / 2) == pytest.approx(-np.pi / 2)


def test_slam_session_and_latency_must_be_non_negative():
    n = 3
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    with pytest.raises(FlightDataError, match=r"slam\.session: negative id -1 at sample 1"):
        SlamSeries(np.arange(n, dtype=float), np.zeros((n, 3)), q, np.array([0, -1, 0])).check()
    with pytest.raises(FlightDataError, match=r"slam\.latency: negative latency"):
        SlamSeries(
            np.arange(n, dtype=float),
            np.zeros((n, 3)),
            q,
            np.zeros(n, int),
            np.array([0.1, -0.1, 0]),
        ).check()


def test_camera_distortion_counts():
    """Only the distortion lengths OpenCV takes are accepted (3 or 7 coefficients were a
    cv2.error in the VO; review 2026-12-07)."""
    from fgnav.datasets.types import DISTORTION_COUNTS, CameraIntrinsics

    for n in DISTORTION_COUNTS:
        CameraIntrinsics(200.0, 200.0, 16.0, 12.0, 32, 24, (0.01,) * n).check()
    for n in (1, 3, 7, 9):
        cam = CameraIntrinsics(200.0, 200.0, 16.0, 12.0, 32, 24, (0.01,) * n)
        with pytest.raises(FlightDataError, match=rf"cam: {n} distortion coefficients; expected 0"):
            cam.check("cam")


def test_imu_plausibility_limits_are_the_online_smoothers():
    """The readers and the online smoother drop the same samples: one pair of constants."""
    from fgnav.datasets import types

    from fgnav.solvers import online

    assert online.IMU_MAX_RATE is types.IMU_MAX_RATE
    assert online.IMU_MAX_ACCEL is types.IMU_MAX_ACCEL
    w = np.array([[1.0, 2.0, 3.0], [1e30, 0.0, 0.0], [0.0, 0.0, 0.0], [np.nan, 0, 0], [0, 99, 0]])
    a = np.array([[0, 0, 9.81], [0, 0, 9.81], [0, 0, 9.8e30], [0, 0, 9.81], [0, 0, 490]])
    np.testing.assert_array_equal(types.imu_plausible(w, a), [True, False, False, False, True])


def test_select_and_between_cut_every_row_column():
    """``select`` (the tests' way to cut a stream) keeps the picked rows of every per-row column,
    leaves an absent optional column absent and the per-series fields as they are."""
    from pathlib import Path

    from fgnav.datasets import CameraIntrinsics, ImageSeries

    rng = np.random.default_rng(3)
    n = 6
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    slam = SlamSeries(
        np.arange(n) * 0.25,
        rng.normal(size=(n, 3)),
        q,
        np.array([0, 0, 0, 1, 1, 1]),
        latency=np.linspace(0.01, 0.06, n),
    )
    keep = np.array([True, False, True, True, False, True])
    cut = slam.select(keep)
    assert type(cut) is SlamSeries and len(cut) == 4
    for name in ("t", "slam_t_cam", "slam_q_cam_wxyz", "session", "latency"):
        np.testing.assert_array_equal(getattr(cut, name), getattr(slam, name)[keep])
    no_latency = SlamSeries(slam.t, slam.slam_t_cam, q, slam.session)
    assert no_latency.select(keep).latency is None
    np.testing.assert_array_equal(slam.select(np.array([5, 0])).t, [1.25, 0.0])
    np.testing.assert_array_equal(slam.between(0.25, 0.75).t, slam.t[1:4])
    cam = CameraIntrinsics(200.0, 200.0, 160.0, 120.0, 320, 240)
    images = ImageSeries(
        np.arange(3.0), paths=tuple(Path(f"{i}.png") for i in range(3)), camera=cam
    )
    picked = images.select(np.array([False, True, True]))
    assert picked.paths == (Path("1.png"), Path("2.png")) and picked.camera is cam
    assert picked.frames is None
