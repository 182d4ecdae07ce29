"""EuRoC IMU frame -> FLU multirotor body: the rotation, its checks against the MH_01/V1_0x data
(thrust axis, ground-truth tilt, rest specific force), physics and camera poses unchanged by the
conversion, a synthetic round trip, and bad options named precisely."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from fgnav.datasets import FlightDataError, FlightFormatError
from fgnav.datasets.euroc import (
    THRUST_AXIS_IMU,
    flu_R_imu,
    read_euroc_folder,
    read_euroc_groundtruth,
    read_euroc_imu,
    to_flu_body,
)
from fgnav.datasets.frames import rotate_body_frame, tilt_angle
from fgnav.datasets.geometry import make_pose, quat_wxyz_to_matrix, so3_exp
from fgnav.datasets.manifest import read_manifest
from fgnav.datasets.types import (
    AttitudeSeries,
    Calibration,
    CameraIntrinsics,
    Flight,
    ImuSeries,
    RangeSeries,
    Trajectory,
    YawSeries,
)
from testutil import PROJECT_ROOT

MH01_MANIFEST = PROJECT_ROOT / "datasets" / "manifests" / "euroc_mh01_orbslam3.toml"
G = 9.81
#: MH_01's airborne part and its rest on the floor, seconds after the first IMU sample.
FLIGHT_S = (45.0, 182.0)
REST_S = (22.0, 30.0)


def _window(t: np.ndarray, t0: float, span: tuple[float, float]) -> np.ndarray:
    return (t - t0 >= span[0]) & (t - t0 <= span[1])


def _deg_between(u: np.ndarray, v: np.ndarray) -> float:
    c = u @ v / np.linalg.norm(u) / np.linalg.norm(v)
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@pytest.fixture(scope="module")
def mh01_pair(real_data, tmp_path_factory) -> tuple[Flight, Flight]:
    """MH_01 from the shipped manifest (IMU body) and from a copy with ``frame = "flu"``."""
    raw = read_manifest(MH01_MANIFEST)
    flu = read_manifest(_manifest_copy(real_data, 'frame = "flu"', tmp_path_factory.mktemp("m")))
    return raw, flu


def _manifest_copy(real_data: Path, body_lines: str, tmp_dir: Path) -> Path:
    """The MH_01 manifest with an absolute root and its ``[body]`` table replaced."""
    text = MH01_MANIFEST.read_text()
    head, _, _ = text.partition("\n[body]\n")
    head = head.replace(
        'root = "../../../shared/data/real/euroc_MH_01_easy"',
        f'root = "{real_data / "euroc_MH_01_easy"}"',
    )
    p = tmp_dir / "m.toml"
    p.write_text(head + ("\n[body]\n" + body_lines + "\n" if body_lines else ""))
    return p


# ----------------------------------------------------------------------------------------------
# The rotation
# ----------------------------------------------------------------------------------------------


def test_rotation_orthonormal_and_axes():
    rng = np.random.default_rng(3)
    cam_R = so3_exp(rng.normal(size=3))
    imu_T_cam = make_pose(cam_R, rng.normal(size=3))
    axis = rng.normal(size=3)
    if abs(cam_R[:, 2] @ axis) / np.linalg.norm(axis) > 0.8:
        axis = np.cross(axis, cam_R[:, 2])
    R = flu_R_imu(imu_T_cam, axis)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R[2], axis / np.linalg.norm(axis), atol=1e-12)  # z: thrust axis
    c = cam_R[:, 2]
    assert R[0] @ R[2] == pytest.approx(0.0, abs=1e-12)
    # x lies in the plane of the optical axis and z, on the optical axis' side (forward).
    assert np.cross(c, R[2]) @ R[0] == pytest.approx(0.0, abs=1e-12)
    assert R[0] @ c > 0
    np.testing.assert_allclose(np.cross(R[2], R[0]), R[1], atol=1e-12)


def test_euroc_rotation_values():
    """With EuRoC's cam0 extrinsics (IMU.T_b_c1): body x ~ imu z, y ~ -imu y, z ~ imu x."""
    imu_T_cam = np.array(
        [
            [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
            [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
            [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    R = flu_R_imu(imu_T_cam)
    np.testing.assert_allclose(R[2], np.asarray(THRUST_AXIS_IMU) / np.linalg.norm(THRUST_AXIS_IMU))
    assert _deg_between(R[0], [0, 0, 1]) < 21.0 and _deg_between(R[1], [0, -1, 0]) < 3.0
    # cam0 looks forward and 19 +- 1 deg down in the FLU body; its x (image right) is body -y.
    cam = R @ imu_T_cam[:3, :3]
    assert np.degrees(np.arcsin(-cam[2, 2])) == pytest.approx(19.2, abs=1.0)
    assert cam[1, 0] < -0.99


@pytest.mark.parametrize(
    "axis, match",
    [
        ([0, 0, 0], r"thrust_axis: expected a finite non-zero vector"),
        ([1, 2], r"thrust_axis: expected 3 numbers"),
        ([0.0, 0.1, 1.0], r"thrust_axis: .* deg from cam0's optical axis"),
        ([np.nan, 0, 1], r"thrust_axis: expected a finite"),
    ],
)
def test_bad_thrust_axis_named(axis, match):
    with pytest.raises(FlightDataError, match=match):
        flu_R_imu(np.eye(4), axis)


# ----------------------------------------------------------------------------------------------
# Synthetic round trip and consistency
# ----------------------------------------------------------------------------------------------


def _synthetic_flight(with_range: bool = True) -> Flight:
    rng = np.random.default_rng(11)
    n = 50
    t = np.arange(n) * 0.01
    q = np.array([quat_wxyz_from(so3_exp(rng.normal(size=3))) for _ in range(n)])
    traj = Trajectory(
        t=t,
        world_t_body=rng.normal(size=(n, 3)),
        world_q_body_wxyz=q,
        world_v_body=rng.normal(size=(n, 3)),
        gyro_bias=rng.normal(size=(n, 3)) * 0.01,
        accel_bias=rng.normal(size=(n, 3)) * 0.1,
    )
    calib = Calibration(
        body_T_cam=make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3)),
        body_T_range=make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3)),
        camera=CameraIntrinsics(400.0, 400.0, 320.0, 240.0, 640, 480),
    )
    return Flight(
        name="synthetic",
        imu=ImuSeries(t=t, body_omega=rng.normal(size=(n, 3)), body_accel=rng.normal(size=(n, 3))),
        attitude=AttitudeSeries(t=t, world_q_body_wxyz=q.copy()),
        range=RangeSeries(t=t, range=np.full(n, 2.0)) if with_range else None,
        ground_truth=traj,
        references={"other": dataclasses.replace(traj, world_t_body=traj.world_t_body + 1.0)},
        calib=calib,
    ).check()


def quat_wxyz_from(R: np.ndarray) -> np.ndarray:
    from fgnav.datasets.geometry import matrix_to_quat_wxyz

    return matrix_to_quat_wxyz(R)


def _assert_same_rotation_quats(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_allclose(quat_wxyz_to_matrix(a), quat_wxyz_to_matrix(b), atol=1e-12)


def test_synthetic_round_trip_and_invariants():
    f = _synthetic_flight()
    R = so3_exp(np.array([0.3, -1.2, 2.0]))
    g = rotate_body_frame(f, R).check()
    back = rotate_body_frame(g, R.T).check()
    for name in ("body_omega", "body_accel"):
        np.testing.assert_allclose(getattr(back.imu, name), getattr(f.imu, name), atol=1e-12)
        np.testing.assert_allclose(getattr(g.imu, name), getattr(f.imu, name) @ R.T, atol=1e-12)
    for a, b in (
        (back.ground_truth, f.ground_truth),
        (back.references["other"], f.references["other"]),
    ):
        _assert_same_rotation_quats(a.world_q_body_wxyz, b.world_q_body_wxyz)
        for name in ("world_t_body", "world_v_body", "gyro_bias", "accel_bias"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=1e-12)
    _assert_same_rotation_quats(back.attitude.world_q_body_wxyz, f.attitude.world_q_body_wxyz)
    np.testing.assert_allclose(back.calib.body_T_cam, f.calib.body_T_cam, atol=1e-12)
    np.testing.assert_allclose(back.calib.body_T_range, f.calib.body_T_range, atol=1e-12)
    # World quantities do not change: positions, velocities, the world pose of camera and range.
    gt0, gt1 = f.ground_truth, g.ground_truth
    np.testing.assert_array_equal(gt1.world_t_body, gt0.world_t_body)
    np.testing.assert_array_equal(gt1.world_v_body, gt0.world_v_body)
    for key in ("body_T_cam", "body_T_range"):
        w0 = gt0.world_R_body() @ getattr(f.calib, key)[:3, :3]
        w1 = gt1.world_R_body() @ getattr(g.calib, key)[:3, :3]
        np.testing.assert_allclose(w1, w0, atol=1e-12)
    # Biases and rates are body vectors: their world images do not change.
    np.testing.assert_allclose(
        np.einsum("nij,nj->ni", gt1.world_R_body(), gt1.accel_bias),
        np.einsum("nij,nj->ni", gt0.world_R_body(), gt0.accel_bias),
        atol=1e-12,
    )
    np.testing.assert_array_equal(g.range.range, f.range.range)


def test_default_range_pose_kept_without_range_stream():
    f = _synthetic_flight(with_range=False)
    f = dataclasses.replace(
        f, calib=dataclasses.replace(f.calib, body_T_range=np.diag([1.0, -1, -1, 1]))
    )
    g = rotate_body_frame(f, so3_exp(np.array([0.0, 1.0, 0.0])))
    np.testing.assert_array_equal(g.calib.body_T_range, f.calib.body_T_range)


def test_rotate_refuses_yaw_and_bad_rotation():
    f = _synthetic_flight()
    with pytest.raises(FlightDataError, match="body rotation: expected a proper 3x3 rotation"):
        rotate_body_frame(f, np.diag([1.0, 1.0, -1.0]))
    fy = dataclasses.replace(f, yaw=YawSeries(t=f.imu.t, yaw=np.zeros(len(f.imu))))
    with pytest.raises(FlightDataError, match="synthetic: cannot rotate the body frame .* yaw"):
        rotate_body_frame(fy, np.eye(3))


def test_to_flu_body_meta_and_twice():
    f = _synthetic_flight()
    axis = f.calib.body_T_cam[:3, 0] + 0.2 * f.calib.body_T_cam[:3, 2]
    g = to_flu_body(f, axis)
    R = np.array(g.meta["body_from_imu"])
    assert g.meta["body_frame"] == "flu"
    np.testing.assert_allclose(R, flu_R_imu(f.calib.body_T_cam, axis), atol=1e-15)
    np.testing.assert_allclose(g.imu.body_accel, f.imu.body_accel @ R.T, atol=1e-12)
    with pytest.raises(FlightDataError, match="synthetic: body already converted"):
        to_flu_body(g, axis)
    with pytest.raises(FlightDataError, match="needs cam0's calibration"):
        to_flu_body(dataclasses.replace(f, calib=Calibration()), axis)


def test_synthetic_mav0_folder_flu(tmp_path):
    mav0 = tmp_path / "XX_01" / "mav0"
    (mav0 / "imu0").mkdir(parents=True)
    (mav0 / "cam0" / "data").mkdir(parents=True)
    t0 = 1403636579758560000
    header = "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    header += "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n"
    # Hovering with the thrust axis along THRUST_AXIS_IMU: the IMU reads g along it.
    f_imu = G * np.asarray(THRUST_AXIS_IMU) / np.linalg.norm(THRUST_AXIS_IMU)
    rows = "".join(
        f"{t0 + i * 5_000_000},0.01,0.02,0.03,{f_imu[0]:.17g},{f_imu[1]:.17g},{f_imu[2]:.17g}\n"
        for i in range(10)
    )
    (mav0 / "imu0/data.csv").write_text(header + rows)
    (mav0 / "cam0/sensor.yaml").write_text(
        "T_BS:\n  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,"
        " 0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,"
        " -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,"
        " 0.0, 0.0, 0.0, 1.0]\nresolution: [752, 480]\n"
        "intrinsics: [458.654, 457.296, 367.215, 248.375]\n"
    )
    (mav0 / "cam0/data" / f"{t0}.png").write_bytes(b"")
    (mav0 / "cam0/data.csv").write_text(f"#timestamp [ns],filename\n{t0},{t0}.png\n")
    raw = read_euroc_folder(mav0)
    flu = read_euroc_folder(mav0, body="flu")
    assert "body_from_imu" not in raw.meta and flu.meta["body_frame"] == "flu"
    np.testing.assert_allclose(flu.imu.body_accel, np.tile([0.0, 0.0, G], (10, 1)), atol=1e-12)
    R = np.array(flu.meta["body_from_imu"])
    np.testing.assert_allclose(flu.imu.body_omega, raw.imu.body_omega @ R.T, atol=1e-15)
    np.testing.assert_allclose(flu.calib.body_T_cam[:3, 3], R @ raw.calib.body_T_cam[:3, 3])
    with pytest.raises(FlightDataError, match=r"body = 'FLU'; valid: imu, flu"):
        read_euroc_folder(mav0, body="FLU")
    with pytest.raises(FlightFormatError, match=r"XX_01/mav0: thrust_axis: .* optical axis"):
        read_euroc_folder(mav0, body="flu", thrust_axis_imu=[0, 0, 1])


# ----------------------------------------------------------------------------------------------
# Manifest option
# ----------------------------------------------------------------------------------------------


@pytest.mark.realdata
@pytest.mark.parametrize(
    "body, match",
    [
        ('frame = "ned"', r"\[body\] frame = 'ned'; valid: imu, flu"),
        ('frame = "flu"\nthrust = 1', r"\[body\] unknown key\(s\) \['thrust'\]; valid: frame"),
        ('frame = "flu"\nthrust_axis = [1, 0]', r"\[body\] thrust_axis: expected 3 numbers"),
        ('frame = "flu"\nthrust_axis = [0, 0, 1]', r"m\.toml: \[body\] thrust_axis: .* optical"),
        ('frame = "imu"\nthrust_axis = [0, 0, 0]', r"\[body\] thrust_axis: expected 3 numbers"),
    ],
)
def test_manifest_bad_body_named(real_data, tmp_path, body, match):
    with pytest.raises(FlightFormatError, match=match):
        read_manifest(_manifest_copy(real_data, body, tmp_path))


def test_manifest_imu_body_records_the_thrust_axis(real_data, tmp_path):
    """``frame = "imu"`` with ``thrust_axis``: the body stays, the axis is recorded normalised
    for the filters that need a thrust body (fgnav.datasets.frames.thrust_body_rotation)."""
    from fgnav.datasets.frames import thrust_body_rotation

    f = read_manifest(_manifest_copy(real_data, 'frame = "imu"\nthrust_axis = [2, 0, 0]', tmp_path))
    assert f.meta["thrust_axis_body"] == [1.0, 0.0, 0.0]
    assert "body_from_imu" not in f.meta
    R = thrust_body_rotation(f)
    np.testing.assert_allclose(R[2], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_manifest_flu_needs_euroc_imu(tmp_path):
    (tmp_path / "m.toml").write_text(
        'name = "x"\n[imu]\nformat = "native_csv"\npath = "imu.csv"\n[body]\nframe = "flu"\n'
    )
    with pytest.raises(FlightFormatError, match=r'needs \[imu\] format = "euroc"'):
        read_manifest(tmp_path / "m.toml")


# ----------------------------------------------------------------------------------------------
# Real data: MH_01 (manifest default), V1_01 and V1_02
# ----------------------------------------------------------------------------------------------


@pytest.mark.realdata
def test_mh01_manifest_flu_option(mh01_pair):
    raw, flu = mh01_pair
    assert "body_from_imu" not in raw.meta  # the shipped manifest keeps the IMU body
    assert raw.imu.body_accel[:2000].mean(axis=0)[0] > 8.0  # x up
    assert flu.meta["body_frame"] == "flu"
    R = np.array(flu.meta["body_from_imu"])
    np.testing.assert_allclose(R, flu_R_imu(raw.calib.body_T_cam), atol=1e-15)
    np.testing.assert_allclose(flu.imu.body_accel, raw.imu.body_accel @ R.T, atol=1e-12)
    np.testing.assert_allclose(flu.imu.body_omega, raw.imu.body_omega @ R.T, atol=1e-12)
    np.testing.assert_array_equal(flu.ground_truth.world_t_body, raw.ground_truth.world_t_body)
    np.testing.assert_array_equal(flu.slam.slam_t_cam, raw.slam.slam_t_cam)
    np.testing.assert_array_equal(flu.slam.slam_q_cam_wxyz, raw.slam.slam_q_cam_wxyz)
    ref0, ref1 = raw.references["rpg_vio_mono"], flu.references["rpg_vio_mono"]
    np.testing.assert_allclose(ref1.world_R_body(), ref0.world_R_body() @ R.T, atol=1e-12)


@pytest.mark.realdata
def test_mh01_thrust_axis_and_tilt(mh01_pair):
    """Flight: mean specific force along +z; ground-truth body z near vertical (measured: mean
    2.24 deg, max 15.2 deg, mean axis 0.71 deg from vertical)."""
    _, flu = mh01_pair
    t0 = flu.imu.t[0]
    f_mean = flu.imu.body_accel[_window(flu.imu.t, t0, FLIGHT_S)].mean(axis=0)
    assert _deg_between(f_mean, [0, 0, 1]) < 0.01  # THRUST_AXIS_IMU is this mean (4 digits)
    gt = flu.ground_truth
    R = gt.world_R_body()[_window(gt.t, t0, FLIGHT_S)]
    tilt = np.degrees(tilt_angle(R))
    assert tilt.mean() == pytest.approx(2.24, abs=0.1)
    assert tilt.max() == pytest.approx(15.2, abs=0.3)
    assert np.percentile(tilt, 95) < 6.0
    assert _deg_between(R[:, :, 2].mean(axis=0), [0, 0, 1]) < 1.0
    # Independent of the IMU: the ground truth's mean up direction in the IMU frame (raw body).
    raw_up = (R @ np.array(flu.meta["body_from_imu"]))[:, 2, :].mean(axis=0)
    assert _deg_between(raw_up, THRUST_AXIS_IMU) < 1.0


@pytest.mark.realdata
def test_mh01_rest_specific_force(mh01_pair):
    """At rest on the floor (22-30 s) the vehicle stands tilted, and the FLU accelerometer says so:
    |f| = g within 0.1 m/s^2, tilted 5.3 deg from +z (within 0.6 deg of the ground truth's 5.6 deg
    tilt there; the remainder is accelerometer bias), i.e. f = (0.68, 0.59, 9.74) m/s^2, within
    1 m/s^2 of (0, 0, g) per axis."""
    _, flu = mh01_pair
    t0 = flu.imu.t[0]
    m = _window(flu.imu.t, t0, REST_S)
    assert np.linalg.norm(flu.imu.body_omega[m], axis=1).max() < 0.15  # at rest: gyro bias only
    f = flu.imu.body_accel[m].mean(axis=0)
    assert np.linalg.norm(f) == pytest.approx(G, abs=0.1)
    np.testing.assert_allclose(f, [0.0, 0.0, G], atol=1.0)
    gt = flu.ground_truth
    R_rest = gt.world_R_body()[_window(gt.t, t0, REST_S)]
    gt_tilt = float(np.degrees(tilt_angle(R_rest)).mean())
    f_tilt = _deg_between(f, [0, 0, 1])
    assert 4.0 < f_tilt < 6.5 and abs(f_tilt - gt_tilt) < 0.6
    # The specific force at rest is world up seen from the body: compare directions directly.
    up_body = R_rest[:, 2, :].mean(axis=0)
    assert _deg_between(f, up_body) < 1.2


def _lowpass(x: np.ndarray, n: int) -> np.ndarray:
    k = np.ones(n) / n
    return np.stack([np.convolve(x[:, j], k, mode="same") for j in range(x.shape[1])], axis=1)


def _gt_accel_residual(flight: Flight) -> np.ndarray:
    """``world_R_body(t) @ f_body(t) - g_world - d2p/dt2`` at ground-truth times, both sides
    low-passed (0.25 s box) to remove rotor vibration; edges and the 45 s start cut."""
    gt, imu = flight.ground_truth, flight.imu
    t = gt.t
    f = np.stack([np.interp(t, imu.t, imu.body_accel[:, j]) for j in range(3)], axis=1)
    world_f = np.einsum("nij,nj->ni", gt.world_R_body(), f)
    world_a = np.gradient(np.gradient(gt.world_t_body, t, axis=0), t, axis=0)
    res = _lowpass(world_f - [0.0, 0.0, G], 50) - _lowpass(world_a, 50)
    return res[_window(t, imu.t[0], FLIGHT_S)]


@pytest.mark.realdata
def test_mh01_physics_unchanged(mh01_pair):
    """The conversion changes no physics: the specific force rotated into the world minus gravity
    matches the ground truth's acceleration equally well with either body (measured RMS 0.09,
    0.14, 0.07 m/s^2 in world x, y, z: accelerometer bias and ground-truth attitude error)."""
    raw, flu = mh01_pair
    r_raw, r_flu = _gt_accel_residual(raw), _gt_accel_residual(flu)
    np.testing.assert_allclose(r_flu, r_raw, atol=1e-9)
    rms = np.sqrt(np.mean(r_flu**2, axis=0))
    assert np.all(rms < 0.3), rms


@pytest.mark.realdata
def test_mh01_world_T_cam_unchanged(mh01_pair):
    raw, flu = mh01_pair
    R0, R1 = raw.ground_truth.world_R_body(), flu.ground_truth.world_R_body()
    p = raw.ground_truth.world_t_body
    for T0, T1 in ((raw.calib.body_T_cam, flu.calib.body_T_cam),):
        np.testing.assert_allclose(R1 @ T1[:3, :3], R0 @ T0[:3, :3], atol=1e-12)
        np.testing.assert_allclose(R1 @ T1[:3, 3] + p, R0 @ T0[:3, 3] + p, atol=1e-12)
    # body_T_range is the "look down the body" default on EuRoC (no rangefinder): left as is.
    np.testing.assert_array_equal(flu.calib.body_T_range, raw.calib.body_T_range)


@pytest.mark.realdata
@pytest.mark.parametrize(
    "imu_file, gt_file",
    [
        ("euroc_V1_01_easy/imu0/V101.txt", None),
        ("euroc_V1_02_medium/imu0/V102.txt", "euroc_V1_02_medium/groundtruth/V102_groundtruth.csv"),
    ],
)
def test_other_sequences_same_thrust_axis(real_data, mh01_pair, imu_file, gt_file):
    """Same Firefly and mount: MH_01's thrust axis fits V1_01 and V1_02 (mean specific force in
    flight 0.35 and 0.7 deg from FLU +z); V1_02's full-state ground truth converts with its
    velocity (world) kept and its biases (body) rotated, and its body z is near vertical."""
    _, flu_mh = mh01_pair
    R = np.array(flu_mh.meta["body_from_imu"])
    imu = read_euroc_imu(real_data / imu_file)
    gt = read_euroc_groundtruth(real_data / gt_file) if gt_file else None
    f = Flight(name="v1", imu=imu, ground_truth=gt, calib=flu_mh.calib)
    g = rotate_body_frame(f, R)
    # Airborne from about 5 s after the first sample to 2 s before the end (both sequences).
    m = _window(imu.t, imu.t[0], (5.0, imu.t[-1] - imu.t[0] - 2.0))
    assert _deg_between(g.imu.body_accel[m].mean(axis=0), [0, 0, 1]) < 1.0
    if gt is not None:
        np.testing.assert_array_equal(g.ground_truth.world_v_body, gt.world_v_body)
        np.testing.assert_allclose(g.ground_truth.accel_bias, gt.accel_bias @ R.T, atol=1e-12)
        tilt = np.degrees(tilt_angle(g.ground_truth.world_R_body()))
        assert tilt.mean() < 6.0


def test_info_prints_body_rotation():
    from fgnav.commands.info import body_frame_lines

    assert body_frame_lines({}) == []
    g = to_flu_body(_synthetic_flight(), [1.0, 0.0, 0.0])
    lines = body_frame_lines(g.meta)
    assert lines[1] == "body frame flu (v_body = body_from_imu @ v_imu)"
    R = np.array(g.meta["body_from_imu"])
    assert lines[4] == "  [" + ", ".join(f"{x:+.4f}" for x in R[2]) + "]"
    assert lines[5] == "  thrust axis in the IMU frame: [+1.0000, +0.0000, +0.0000]"
