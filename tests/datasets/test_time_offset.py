"""Clock offset by cross-correlation, the Motive CSV reader, and the handheld ULog vs OptiTrack."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError, FlightFormatError
from fgnav.datasets.frames import align_rotation_sequences, tilt_angle
from fgnav.datasets.geometry import quat_wxyz_to_matrix
from fgnav.datasets.time_offset import (
    align_mocap,
    body_rate_magnitude,
    estimate_time_offset,
    read_motive_csv,
)
from fgnav.datasets.ulog import interpolate_attitude, read_ulog

# Reference clock offset (t_ulog = t_mocap + offset) of log008.ulg vs the OptiTrack take, in PX4
# boot seconds. Established with scripts/align_mocap.py by three methods: tilt-angle correlation
# 5.8424 s (r = 0.94), angular-rate-magnitude correlation 5.8422 s (r = 0.999), and the minimum of
# the full 3-D attitude residual (after fitting fixed world and body rotations) at 5.835 s on a
# 5 ms scan, whose minimum is flat within +-5 ms. Mocap t=0 is then 0.78 s after the log's first
# vehicle_attitude sample: the "about 0.8 s" of the data README.
REFERENCE_OFFSET_S = 5.842
TOLERANCE_S = 0.020


def test_offset_recovered_sub_sample_on_synthetic_signal():
    rng = np.random.default_rng(7)
    true_offset = 1.2345  # t_a = t_b + offset
    t_b = np.arange(0.0, 40.0, 1.0 / 180.0)
    # A band-limited random signal: smoothed noise.
    raw = np.convolve(rng.normal(size=t_b.size + 200), np.ones(60) / 60, mode="same")[100:-100]
    t_a = np.arange(2.0, 38.0, 1.0 / 200.0)
    signal_a = np.interp(t_a - true_offset, t_b, raw) * 3.0 + 1.0  # gain and bias do not matter
    signal_a += rng.normal(scale=0.01, size=t_a.size)
    res = estimate_time_offset(t_a, signal_a, t_b, raw, max_offset_s=3.0, dt_s=0.01)
    assert res.offset_s == pytest.approx(true_offset, abs=0.002)  # 5x below the 10 ms grid
    assert res.correlation > 0.95
    assert res.lags_s.shape == res.correlations.shape


def test_offset_errors():
    t = np.arange(0.0, 10.0, 0.01)
    with pytest.raises(FlightDataError, match="overlap"):
        estimate_time_offset(t, np.sin(t), t, np.sin(t), max_offset_s=1.0, min_overlap_s=20.0)
    with pytest.raises(FlightDataError, match="strictly increasing"):
        estimate_time_offset(t[::-1], np.sin(t), t, np.sin(t), max_offset_s=1.0)


def test_body_rate_magnitude_constant_spin():
    t = np.arange(0.0, 1.0, 0.01)
    rate = 2.0  # rad/s about z
    q = np.column_stack(
        [np.cos(rate * t / 2), np.zeros_like(t), np.zeros_like(t), np.sin(rate * t / 2)]
    )
    t_mid, w = body_rate_magnitude(t, q)
    np.testing.assert_allclose(w, rate, rtol=1e-9)
    np.testing.assert_allclose(t_mid, t[:-1] + 0.005)


MOTIVE_HEADER = (
    "Format Version,1.23,Take Name,Take,Capture Frame Rate,200.000000,Export Frame Rate,100.000000,"
    "Rotation Type,{rot},Length Units,Millimeters,Coordinate Space,Global\n"
    "\n"
    ",Type,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body\n"
    ",Name,Drone,Drone,Drone,Drone,Drone,Drone,Drone\n"
    ",ID,1,1,1,1,1,1,1\n"
    ",,Rotation,Rotation,Rotation,Rotation,Position,Position,Position\n"
    "Frame,Time (Seconds),X,Y,Z,W,X,Y,Z\n"
)


def _write_motive(path, rows, rot="Quaternion"):
    path.write_text(MOTIVE_HEADER.format(rot=rot) + "".join(rows))
    return path


def test_motive_csv_units_frames_and_missing_rows(tmp_path):
    # Rigid body turned 90 deg about Motive's vertical Y axis, 1 m above the floor (Y = 1000 mm).
    s = np.sin(np.pi / 4)
    rows = [
        f"0,0.000,0,{s},0,{s},100,1000,200\n",
        "1,0.010,,,,,,,\n",  # untracked frame
        f"2,0.020,0,{s},0,{s},100,1000,200\n",
    ]
    take = read_motive_csv(_write_motive(tmp_path / "take.csv", rows))
    assert take.rigid_body == "Drone" and take.skipped_rows == 1
    assert take.frame_rate_hz == 100.0
    traj = take.trajectory
    np.testing.assert_allclose(traj.t, [0.0, 0.02])
    np.testing.assert_allclose(traj.world_t_body[0], [0.1, -0.2, 1.0])  # (X, -Z, Y) in m
    R = quat_wxyz_to_matrix(traj.world_q_body_wxyz[0])
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-9)  # yawed +90 deg about z


def test_motive_csv_errors(tmp_path):
    rows = ["0,0.000,0,0,0,1,0,0,0\n"]
    with pytest.raises(FlightFormatError, match="Quaternion"):
        read_motive_csv(_write_motive(tmp_path / "euler.csv", rows, rot="XYZ"))
    path = _write_motive(tmp_path / "ok.csv", rows)
    with pytest.raises(FlightFormatError, match="'Drone'"):
        read_motive_csv(path, rigid_body="Quad")
    bad = _write_motive(tmp_path / "bad.csv", ["0,0.000,0,0,zero,1,0,0,0\n"])
    with pytest.raises(FlightFormatError, match=r"bad.csv:8: column 5"):
        read_motive_csv(bad)
    not_motive = tmp_path / "x.csv"
    not_motive.write_text("time,x,y\n0,1,2\n")
    with pytest.raises(FlightFormatError, match="Format Version"):
        read_motive_csv(not_motive)


@pytest.fixture(scope="module")
def handheld(real_data):
    folder = real_data / "px4_fmuv5_quad_handheld_optitrack"
    flight = read_ulog(folder / "log008.ulg")
    take = read_motive_csv(folder / "optitrack_take_2023-04-16.csv")
    return flight, take


@pytest.mark.realdata
def test_motive_take_real(handheld):
    _, take = handheld
    assert take.rigid_bodies == ("Frame", "RigidBody")
    assert take.rigid_body == "RigidBody"  # "Frame" never moves
    assert take.frame_rate_hz == 180.0 and take.skipped_rows == 1
    assert take.trajectory.rate_hz == pytest.approx(180.0, rel=1e-3)
    z = take.trajectory.world_t_body[:, 2]
    assert 0.0 < z.min() and z.max() < 2.5  # heights in metres above the mocap floor


@pytest.mark.realdata
def test_handheld_ulog_vs_optitrack_offset(handheld):
    flight, take = handheld
    mocap = take.trajectory
    al = align_mocap(flight, mocap, max_offset_s=3.0)
    tilt, gyro = al.tilt, al.rate
    assert tilt.correlation > 0.9 and gyro.correlation > 0.98
    assert abs(tilt.offset_s - gyro.offset_s) < TOLERANCE_S
    assert tilt.offset_s == pytest.approx(REFERENCE_OFFSET_S, abs=TOLERANCE_S)
    assert gyro.offset_s == pytest.approx(REFERENCE_OFFSET_S, abs=TOLERANCE_S)
    assert al.offset_s - flight.attitude.t[0] == pytest.approx(0.8, abs=0.05)  # data README

    # Applying the offset makes the attitudes agree (after fixed world/body rotations): tilt within
    # a degree RMS; half a second off, they do not.
    def tilt_rms_deg(offset_s: float) -> float:
        t = mocap.t + offset_s
        sel = np.flatnonzero((t > flight.attitude.t[0]) & (t < flight.attitude.t[-1]))[::10]
        R_px4 = quat_wxyz_to_matrix(interpolate_attitude(flight.attitude, t[sel]))
        R_mocap = mocap.world_R_body()[sel]
        a_R_b, y_R_x, _ = align_rotation_sequences(R_px4, R_mocap)
        d = tilt_angle(R_px4) - tilt_angle(a_R_b @ R_mocap @ y_R_x)
        return float(np.degrees(np.sqrt(np.mean(d**2))))

    assert al.tilt_rms_deg < 1.0
    assert tilt_rms_deg(al.offset_s - 0.5) > 5.0 * al.tilt_rms_deg
    # The mocap ground truth on the flight clock, in the vehicle's body axes: its attitude matches
    # the flight's up to the fixed world rotation.
    gt = al.ground_truth(mocap)
    assert gt.t[0] == pytest.approx(mocap.t[0] + al.offset_s)
    sel = slice(1000, 8000, 100)
    R_flight = quat_wxyz_to_matrix(interpolate_attitude(flight.attitude, gt.t[sel]))
    R_gt = al.world_R_mocap @ gt.world_R_body()[sel]
    angle = np.degrees(
        np.arccos(
            np.clip((np.trace(R_flight.transpose(0, 2, 1) @ R_gt, axis1=1, axis2=2) - 1) / 2, -1, 1)
        )
    )
    assert np.sqrt(np.mean(angle**2)) < 2.0 * al.attitude_rms_deg
