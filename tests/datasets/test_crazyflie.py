"""Crazyflie SD-card log reader: synthetic logs written here (both versions) decoded exactly, each
format error as one line, and the seven UTIL flow-deck flights against their README facts."""

from __future__ import annotations

import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from fgnav.datasets.crazyflie import (
    CRAZYFLIE_IMU_NOISE,
    FIRMWARE_FLOW_PIXELS_PER_RAD,
    FIRMWARE_GRAVITY,
    FLOW_PIXELS_PER_RAD,
    STILL_IMU_NOISE,
    TOF_LEVER_Z,
    decode_crazyflie_log,
    is_crazyflie_log,
    pair_imu,
    read_crazyflie,
)
from fgnav.datasets.downward_check import flow_vs_truth, range_vs_truth
from fgnav.datasets.errors import FlightFormatError
from fgnav.datasets.geometry import interpolate_quat_wxyz, quat_wxyz_to_matrix, so3_log
from fgnav.datasets.load import load_flight
from fgnav.datasets.manifest import read_manifest
from fgnav.datasets.native import read_flight, write_flight

# ----------------------------------------------------------------------------------------------
# A log writer (independent of the reader: struct, as the firmware's format is documented)
# ----------------------------------------------------------------------------------------------

TYPES = [
    (5, "estGyroscope", [("gyro.x", "f"), ("gyro.y", "f"), ("gyro.z", "f")]),
    (1, "estAcceleration", [("acc.x", "f"), ("acc.y", "f"), ("acc.z", "f")]),
    (4, "estFlow", [("motion.deltaX", "h"), ("motion.deltaY", "h")]),
    (10, "estTOF", [("range.zrange", "H")]),
    (
        6,
        "estPose",
        [(f"locSrv.{a}", "f") for a in ("x", "y", "z", "qx", "qy", "qz", "qw")],
    ),
    (2, "estBarometer", [("baro.asl", "f")]),
    (9, "estTDOA", [("idA", "B"), ("idB", "B"), ("distanceDiff", "f")]),
    (0, "estAbsoluteHeight", []),
    (
        12,
        "allTypes",
        [
            ("b", "b"),
            ("B", "B"),
            ("h", "h"),
            ("H", "H"),
            ("i", "i"),
            ("I", "I"),
            ("q", "q"),
            ("Q", "Q"),
            ("e", "e"),
            ("f", "f"),
            ("d", "d"),
            ("ok", "?"),
        ],
    ),
]
CODES = {eid: "".join(c for _, c in fields) for eid, _, fields in TYPES}


def header_bytes(version: int, types=TYPES, magic: int = 0xBC) -> bytearray:
    buf = bytearray([magic]) + struct.pack("<HH", version, len(types))
    for eid, name, fields in types:
        buf += struct.pack("<H", eid) + name.encode() + b"\0" + struct.pack("<H", len(fields))
        for fname, code in fields:
            buf += f"{fname}({code})".encode() + b"\0"
    return buf


def record_bytes(version: int, eid: int, stamp: int, values, codes: str | None = None) -> bytes:
    stamp_code = "I" if version == 1 else "Q"
    return struct.pack(
        "<H" + stamp_code + (CODES[eid] if codes is None else codes), eid, stamp, *values
    )


def write_log(
    path: Path, version: int, records, tail: bytes = b"", types=TYPES, crc=True, magic: int = 0xBC
) -> Path:
    buf = header_bytes(version, types, magic)
    for eid, stamp, values in records:
        buf += record_bytes(version, eid, stamp, values)
    buf += tail
    buf += struct.pack("<I", zlib.crc32(bytes(buf)) if crc else 0xDEADBEEF)
    path.write_bytes(bytes(buf))
    return path


def flight_records(version: int) -> tuple[list, dict]:
    """A small flight on integer-ms times (exact in both versions), records in time order."""
    unit = 1000 if version == 1 else 1_000_000  # stamps per second
    recs: list[tuple[int, int, tuple]] = []
    truth: dict = {}
    n_imu = 200
    t_imu = 2.0 + 0.001 * np.arange(n_imu)
    gyro = np.column_stack([np.full(n_imu, 10.0), np.full(n_imu, -20.0), 0.5 * np.arange(n_imu)])
    acc = np.column_stack([np.full(n_imu, 0.01), np.full(n_imu, -0.02), np.full(n_imu, 1.0)])
    for k in range(n_imu):
        recs.append((1, round(t_imu[k] * unit), tuple(acc[k])))
        recs.append((5, round(t_imu[k] * unit), tuple(gyro[k])))
        recs.append((2, round(t_imu[k] * unit), (180.5 + 0.001 * k,)))
    truth.update(t_imu=t_imu, gyro=gyro, acc=acc)
    steps_ms = [10, 10, 11, 10, 40, 10, 10, 9, 10, 10]
    t_flow = 2.01 + np.cumsum([0] + steps_ms) * 1e-3
    dxy = [
        (3, -2),
        (1, 0),
        (-4, 5),
        (0, 0),
        (7, 1),
        (2, 2),
        (-1, -3),
        (0, 1),
        (5, 5),
        (1, -1),
        (2, 0),
    ]
    for t, (dx, dy) in zip(t_flow, dxy, strict=True):
        recs.append((4, round(t * unit), (dx, dy)))
    truth.update(t_flow=t_flow, dxy=np.array(dxy, float))
    t_tof = 2.0 + 0.043 * np.arange(4)
    mm = [512, 0, 530, 1600]
    for t, r in zip(t_tof, mm, strict=True):
        recs.append((10, round(t * unit), (r,)))
    truth.update(t_tof=t_tof, mm=np.array(mm, float))
    s = np.sqrt(0.5)
    poses = [
        (1.0, 2.0, 0.5, 0.0, 0.0, s, s),
        (1.0, 2.0, 0.5, 0.0, 0.0, s, s),  # exact repeat: dropped
        (1.1, 2.0, 0.5, 0.0, 0.0, 0.0, 1.0),
        (1.2, 2.1, 0.6, 0.6, 0.0, 0.0, 0.8),
    ]
    t_pose = 2.0 + 0.004 * np.arange(4) + 0.002
    for t, p in zip(t_pose, poses, strict=True):
        recs.append((6, round(t * unit), p))
    truth.update(t_pose=t_pose, poses=np.array(poses, np.float32).astype(float))
    recs.append((9, round(2.05 * unit), (3, 4, 0.25)))
    recs.append((0, round(2.06 * unit), ()))
    recs.append(
        (
            12,
            round(2.07 * unit),
            (
                -5,
                250,
                -300,
                60000,
                -70000,
                4_000_000_000,
                -(2**40),
                2**50,
                0.5,
                1.25,
                -3.0e-7,
                True,
            ),
        )
    )
    recs.sort(key=lambda r: r[1])
    return recs, truth


# ----------------------------------------------------------------------------------------------
# Synthetic logs
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("version", [1, 2])
def test_synthetic_log_decodes_exactly(tmp_path, version):
    recs, _ = flight_records(version)
    path = write_log(tmp_path / f"log_v{version}", version, recs)
    cf = decode_crazyflie_log(path)
    assert cf.version == version and cf.n_records == len(recs)
    assert {e.name: e.id for e in cf.event_types.values()} == {n: i for i, n, _ in TYPES}
    for eid, name, fields in TYPES:
        want = [r for r in recs if r[0] == eid]
        got = cf.records[name]
        assert len(got) == len(want), name
        np.testing.assert_array_equal(got["_stamp"], [r[1] for r in want])
        for j, (fname, code) in enumerate(fields):
            # The value each record reads back as through struct (float32 rounding included).
            expected = [
                struct.unpack("<" + code, struct.pack("<" + code, r[2][j]))[0] for r in want
            ]
            np.testing.assert_array_equal(got[fname], expected, err_msg=f"{name}.{fname}")
    assert len(cf.records["estAbsoluteHeight"]) == 1
    seconds = 1e-3 if version == 1 else 1e-6
    np.testing.assert_allclose(cf.time_s("estTOF"), cf.records["estTOF"]["_stamp"] * seconds)


@pytest.mark.parametrize("version", [1, 2])
def test_synthetic_flight_in_fgnav_units_and_frames(tmp_path, version):
    recs, truth = flight_records(version)
    path = write_log(tmp_path / "0425-synthetic", version, recs)
    assert is_crazyflie_log(path)
    f = load_flight(path)  # no suffix: recognised by content
    assert f.name == "0425-synthetic" and f.meta["crazyflie_version"] == version
    # IMU: deg/s -> rad/s, g -> m/s^2 with the firmware's 9.81, at the log's times in seconds.
    np.testing.assert_allclose(f.imu.t, truth["t_imu"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(f.imu.body_omega, np.radians(truth["gyro"]), rtol=1e-6)
    np.testing.assert_allclose(f.imu.body_accel, truth["acc"] * FIRMWARE_GRAVITY, rtol=1e-6)
    assert f.imu.body_accel[0, 2] == pytest.approx(9.81, rel=1e-7)
    # Flow: fgnav sensor axes = 0.1 * [deltaY, -deltaX]; dt one loop (10 ms median) after the
    # 40 ms gap and for the first sample, the step itself otherwise (11 ms and 9 ms kept).
    dxy = truth["dxy"]
    np.testing.assert_allclose(f.flow.flow, 0.1 * np.column_stack([dxy[:, 1], -dxy[:, 0]]))
    np.testing.assert_allclose(f.flow.t, truth["t_flow"], atol=1e-12)
    np.testing.assert_allclose(
        f.flow.dt,
        [0.010, 0.010, 0.010, 0.011, 0.010, 0.010, 0.010, 0.010, 0.009, 0.010, 0.010],
        atol=1e-9,
    )
    assert f.meta["flow"]["dt_one_loop_after_gap"] == 1
    assert f.meta["flow"]["loop_period_s"] == pytest.approx(0.010, abs=1e-9)
    assert f.calib.flow_pixels_per_rad == FLOW_PIXELS_PER_RAD  # fitted (firmware: 35 / 0.71674)
    # Range: mm -> m, the 0 mm reading left out and counted.
    np.testing.assert_allclose(f.range.range, [0.512, 0.530, 1.600])
    np.testing.assert_allclose(f.range.t, truth["t_tof"][[0, 2, 3]], atol=1e-12)
    assert f.meta["range"]["skipped_zero"] == 1
    assert f.calib.range_min == 0.04 and f.calib.range_max == 4.0
    # Ground truth: the exact repeat dropped; qx qy qz qw -> w x y z (float32 renormalised).
    p = truth["poses"]
    keep = [0, 2, 3]
    np.testing.assert_allclose(f.ground_truth.t, truth["t_pose"][keep], atol=1e-12)
    np.testing.assert_allclose(f.ground_truth.world_t_body, p[keep, :3])
    q = p[keep][:, [6, 3, 4, 5]]
    np.testing.assert_allclose(
        f.ground_truth.world_q_body_wxyz, q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-12
    )
    assert f.meta["ground_truth"]["skipped_exact_repeat"] == 1
    # Calibration: beam and optical axis down, 39 mm below the body origin.
    for T in (f.calib.body_T_range, f.calib.body_T_flow):
        np.testing.assert_allclose(T[:3, :3], np.diag([1.0, -1.0, -1.0]))
        np.testing.assert_allclose(T[:3, 3], [0.0, 0.0, TOF_LEVER_Z])
    assert f.calib.imu_noise == CRAZYFLIE_IMU_NOISE
    # Other events counted, barometer summarised.
    assert f.meta["crazyflie_events"]["estTDOA"] == 1
    assert any("not read: estTDOA (1 records)" in n for n in f.meta["notes"])
    assert f.meta["barometer"]["samples"] == 200
    assert f.meta["barometer"]["asl_min_m"] == pytest.approx(180.5, abs=1e-4)


def test_pair_imu_nearest_one_to_one():
    t_gyro = np.array([1.0000, 1.0010, 1.0020, 1.0030, 1.0040])
    # Accelerometer 30 us early, the one before 1.0020 missing, an extra one 0.4 ms late on 1.0040.
    t_acc = np.array([0.99997, 1.00097, 1.00297, 1.00397, 1.00440])
    gi, ai = pair_imu(t_gyro, t_acc)
    np.testing.assert_array_equal(gi, [0, 1, 3, 4])
    np.testing.assert_array_equal(ai, [0, 1, 2, 3])


def test_imu_gap_is_counted(tmp_path):
    recs, _ = flight_records(2)
    # Drop the accelerometer record of IMU sample 50: its gyro sample has no partner.
    stamp = round((2.0 + 0.050) * 1_000_000)
    recs = [r for r in recs if not (r[0] == 1 and r[1] == stamp)]
    f = read_crazyflie(write_log(tmp_path / "log", 2, recs))
    assert len(f.imu) == 199
    assert f.meta["imu"]["skipped_gyro_without_accel"] == 1


def _one_line(exc: pytest.ExceptionInfo, path: Path) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(str(path)), msg
    return msg


def _rejected(path: Path, needle: str, load_match: str) -> None:
    """The decoder names ``needle`` in one line, the file is not taken for a Crazyflie log, and
    ``load_flight`` says ``load_match``."""
    with pytest.raises(FlightFormatError) as e:
        decode_crazyflie_log(path)
    assert needle in _one_line(e, path)
    assert not is_crazyflie_log(path)
    with pytest.raises(FlightFormatError, match=load_match):
        load_flight(path)


def test_bad_magic(tmp_path):
    recs, _ = flight_records(2)
    path = write_log(tmp_path / "log", 2, recs, magic=0xAB)
    needle = "bad header: byte 0 is 0xAB, not the Crazyflie log magic 0xBC"
    _rejected(path, needle, "not a recognised flight input")


def test_unknown_version(tmp_path):
    recs, _ = flight_records(2)
    path = write_log(tmp_path / "log", 3, [])
    with pytest.raises(FlightFormatError) as e:
        decode_crazyflie_log(path)
    assert "unknown version 3 at byte 1; supported: 1, 2" in _one_line(e, path)
    with pytest.raises(
        FlightFormatError, match="magic byte 0xBC but is not a readable .*unknown version 3"
    ):
        load_flight(path)


def test_crc_mismatch_and_cut_off_file(tmp_path):
    recs, _ = flight_records(2)
    good = write_log(tmp_path / "good", 2, recs)
    data = bytearray(good.read_bytes())
    data[-40] ^= 0x01  # one flipped bit in a record
    bad = tmp_path / "flipped"
    bad.write_bytes(bytes(data))
    _rejected(bad, "CRC-32 mismatch", "not a readable Crazyflie SD-card log: CRC-32")
    # A file cut in the middle of a record: the CRC fails first; without the check, the record.
    cut = tmp_path / "cut"
    cut.write_bytes(good.read_bytes()[:-11])
    with pytest.raises(FlightFormatError, match="CRC-32 mismatch.*check_crc = false"):
        decode_crazyflie_log(cut)
    # Salvaged: the records before the cut, the damage said (a power loss writes no CRC).
    cf = decode_crazyflie_log(cut, check_crc=False)
    whole = decode_crazyflie_log(good)
    assert cf.n_records == whole.n_records - 1
    assert cf.damage["reason"].startswith(f"truncated record {whole.n_records - 1} at byte")
    assert cf.damage["bytes_dropped"] == len(cut.read_bytes()) - cf.damage["stopped_at_byte"]
    for name, rec in cf.records.items():
        n = len(rec)
        np.testing.assert_array_equal(rec, whole.records[name][:n])
    assert decode_crazyflie_log(good, check_crc=False).damage is None


def test_damaged_log_salvaged_through_a_manifest(tmp_path):
    """``check_crc = false`` reads a cut-off log up to the cut and a log with one flipped stamp
    bit whole but that sample (its stamp jumped ahead: every later sample looked old)."""
    recs, _ = flight_records(2)
    good = write_log(tmp_path / "good", 2, recs)
    data = good.read_bytes()
    whole = read_crazyflie(good)
    # Cut at two thirds: the records before the cut, the rest counted as dropped.
    (tmp_path / "cut").write_bytes(data[: len(data) * 2 // 3])
    # One flipped high bit in the stamp of a gyro record in the middle.
    flipped = bytearray(data)
    k = next(i for i in range(len(recs) // 2, len(recs)) if recs[i][0] == 5)  # a gyro record
    head = len(header_bytes(2))
    at = head + sum(len(record_bytes(2, e, st, v)) for e, st, v in recs[:k]) + 2 + 4
    flipped[at] ^= 0x80  # stamp byte 4 (little endian): +2^39 us
    (tmp_path / "flip").write_bytes(bytes(flipped))
    for name in ("cut", "flip"):
        with pytest.raises(FlightFormatError, match="check_crc = false"):
            load_flight(tmp_path / name)
        manifest = tmp_path / f"{name}.toml"
        manifest.write_text(
            f'name = "{name}"\n[imu]\nformat = "crazyflie"\npath = "{name}"\ncheck_crc = false\n'
        )
        f = read_manifest(manifest)
        notes = [n for n in f.meta["notes"] if "damaged log salvaged" in n]
        assert len(notes) == 1, f.meta["notes"]
        if name == "cut":
            assert 0.5 * len(whole.imu) < len(f.imu) < 0.75 * len(whole.imu)
            np.testing.assert_array_equal(f.imu.t, whole.imu.t[: len(f.imu)])
        else:
            assert len(f.imu) == len(whole.imu) - 1
            assert f.imu.t[-1] == whole.imu.t[-1]
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[imu]\nformat = "crazyflie"\npath = "cut"\ncheck_crc = "no"\n')
    with pytest.raises(FlightFormatError, match=r"\[imu\] check_crc must be true or false"):
        read_manifest(bad)


def test_truncated_record(tmp_path):
    recs, _ = flight_records(2)
    partial = record_bytes(2, 5, 3_000_000, (1.0, 2.0, 3.0))[:15]
    path = write_log(tmp_path / "log", 2, recs, tail=partial)
    with pytest.raises(FlightFormatError) as e:
        decode_crazyflie_log(path)
    n = len(recs)
    end = len(path.read_bytes()) - 4
    msg = _one_line(e, path)
    assert (
        f"truncated record {n} at byte {end - 15}: event 'estGyroscope' needs 22 bytes, 15 "
        "left before the CRC"
    ) in msg


def test_unknown_event_id(tmp_path):
    recs, _ = flight_records(1)
    path = write_log(tmp_path / "log", 1, recs, tail=struct.pack("<HI", 99, 5000))
    with pytest.raises(FlightFormatError) as e:
        decode_crazyflie_log(path)
    assert f"unknown event id 99 in record {len(recs)} at byte" in _one_line(e, path)


@pytest.mark.parametrize(
    ("types", "match"),
    [
        ([(1, "estFoo", [("x", "f")]), (1, "estBar", [])], "repeats id 1"),
        ([(1, "estFoo", [("x", "z")])], "field 'x' of event 'estFoo' at byte 16 has type code 'z'"),
        ([(1, "estFoo", [("xf", "")])], r"is 'xf\(\)', expected 'name\(t\)'"),
    ],
)
def test_bad_event_definitions(tmp_path, types, match):
    path = write_log(tmp_path / "log", 2, [], types=types)
    with pytest.raises(FlightFormatError, match=match) as e:
        decode_crazyflie_log(path)
    _one_line(e, path)


def test_header_cut_short(tmp_path):
    path = tmp_path / "log"
    buf = header_bytes(2)[:30]  # inside the second event type's name
    path.write_bytes(bytes(buf) + struct.pack("<I", zlib.crc32(bytes(buf))))
    with pytest.raises(FlightFormatError, match="bad header: .* has no terminating NUL") as e:
        decode_crazyflie_log(path)
    _one_line(e, path)


def test_no_imu_is_an_error(tmp_path):
    path = write_log(tmp_path / "log", 2, [(10, 1000, (500,))])
    with pytest.raises(FlightFormatError, match="no estGyroscope records: the log has no IMU"):
        read_crazyflie(path)


def test_manifest_and_native_round_trip(tmp_path):
    recs, _ = flight_records(2)
    write_log(tmp_path / "cf.log", 2, recs)
    manifest = tmp_path / "flight.toml"
    manifest.write_text(
        'name = "cf"\n'
        '[calib]\nformat = "crazyflie"\npath = "cf.log"\n'
        '[imu]\nformat = "crazyflie"\npath = "cf.log"\n'
        '[flow]\nformat = "crazyflie"\npath = "cf.log"\n'
        '[range]\nformat = "crazyflie"\npath = "cf.log"\n'
        '[references.vicon]\nformat = "crazyflie"\npath = "cf.log"\nstream = "ground_truth"\n'
    )
    f = read_manifest(manifest)
    direct = read_crazyflie(tmp_path / "cf.log")
    assert set(f.streams()) == {"imu", "range", "flow", "ref:vicon"}
    np.testing.assert_array_equal(f.flow.flow, direct.flow.flow)
    np.testing.assert_array_equal(f.references["vicon"].t, direct.ground_truth.t)
    assert f.calib.flow_pixels_per_rad == direct.calib.flow_pixels_per_rad
    # The native folder keeps the flow stream and its calibration exactly.
    back = read_flight(write_flight(direct, tmp_path / "native"))
    for name in ("t", "dt", "flow"):
        np.testing.assert_array_equal(getattr(back.flow, name), getattr(direct.flow, name))
    np.testing.assert_array_equal(back.calib.body_T_flow, direct.calib.body_T_flow)
    assert back.calib.flow_pixels_per_rad == direct.calib.flow_pixels_per_rad
    # Bad key for the format: named.
    manifest.write_text('name = "cf"\n[flow]\nformat = "crazyflie"\npath = "cf.log"\ntopic = "x"\n')
    with pytest.raises(FlightFormatError, match=r"\[flow\] unknown key\(s\) \['topic'\]"):
        read_manifest(manifest)


# ----------------------------------------------------------------------------------------------
# The seven UTIL flights
# ----------------------------------------------------------------------------------------------

FLIGHTS = (
    "0425-traj1",
    "0425-traj2",
    "0425-traj3",
    "0425-traj5",
    "0425-traj6",
    "0425-traj13",
    "0425-traj14",
)


@pytest.fixture(scope="module")
def util_flights():
    from testutil import require_real_data

    root = require_real_data() / "crazyflie_util_flowdeck"
    if not root.is_dir():
        pytest.skip(f"{root} is absent")
    return {name: read_crazyflie(root / name) for name in FLIGHTS}


def _mean_rate(s) -> float:
    return (len(s) - 1) / s.duration


@pytest.mark.realdata
def test_util_streams_rates_and_counts(util_flights):
    for name, f in util_flights.items():
        assert 940 < _mean_rate(f.imu) < 965, name  # ~950 Hz
        assert 1010 < f.imu.rate_hz < 1030, name  # median step ~0.98 ms
        assert 78 < _mean_rate(f.flow) < 89, name  # ~80 Hz, logged only with valid motion
        assert 22.9 < _mean_rate(f.range) < 23.6, name  # ~23 Hz
        assert 272 < _mean_rate(f.ground_truth) < 280, name  # ~276 Hz
        assert 30 < f.imu.duration < 49, name
        assert 20 <= f.meta["ground_truth"]["skipped_exact_repeat"] <= 60, name
        gaps = np.count_nonzero(np.diff(f.ground_truth.t) > 0.020)
        # README: 3-14 Vicon gaps over 20 ms as logged; dropping a repeat beside a gap makes one
        # more on traj5 (15).
        assert 3 <= gaps <= 15, name
        assert np.diff(f.ground_truth.t).max() < 0.050, name
        assert 7 <= f.meta["range"]["skipped_zero"] <= 14, name
        assert f.meta["flow"]["loop_period_s"] == pytest.approx(0.0099, abs=2e-4), name
        assert np.all((f.flow.dt > 0.008) & (f.flow.dt <= 1.5 * 0.0099 + 1e-9)), name
        assert f.meta["imu"]["skipped_gyro_without_accel"] == 0, name
        # At rest before the motors start: the accelerometer reads +g along body z.
        still = f.imu.t < f.imu.t[0] + 0.05
        assert np.linalg.norm(f.imu.body_accel[still].mean(axis=0)) == pytest.approx(9.81, abs=0.1)
        assert f.imu.body_accel[still, 2].mean() > 9.7, name
    # traj5 loses 0.26 s of IMU in 11 gaps at 8.1-8.5 s (README).
    f = util_flights["0425-traj5"]
    dt = np.diff(f.imu.t)
    gap = dt > 2.5 * np.median(dt)
    assert np.count_nonzero(gap) == 11
    assert np.all((f.imu.t[:-1][gap] - f.imu.t[0] > 8.0) & (f.imu.t[:-1][gap] - f.imu.t[0] < 8.6))
    assert dt[gap].sum() == pytest.approx(0.26, abs=0.03)


@pytest.mark.realdata
def test_util_range_against_vicon(util_flights):
    offsets = []
    for name, f in util_flights.items():
        fit = range_vs_truth(f)
        assert fit.scale == pytest.approx(1.0, abs=0.01), name
        assert -0.042 < fit.offset_fixed_scale < -0.035, name  # README: about -40 mm
        assert 0.006 < fit.noise < 0.0105, name  # README: 7-9 mm (traj3 9.7 here)
        offsets.append(fit.offset_fixed_scale)
    # The calibration's lever arm is the mean offset.
    assert np.mean(offsets) == pytest.approx(TOF_LEVER_Z, abs=0.001)


@pytest.mark.realdata
def test_util_flow_axes_scale_and_interval(util_flights):
    for name, f in util_flights.items():
        fit = flow_vs_truth(f)
        # Both axes positive in fgnav's convention: the axis swap and signs are right; the scale
        # is near the firmware's 48.8 (README: 44-52 per flight, 47.8 pooled).
        assert all(41 < k < 50 for k in fit.pixels_per_rad), (name, fit)
        assert abs(fit.pixels_per_rad[0] - fit.pixels_per_rad[1]) < 2.5, (name, fit)
        assert all(c > 0.45 for c in fit.correlation), (name, fit)
        assert 0.15 < fit.residual_std < 0.26, (name, fit)  # README: about 0.2 px
        assert -0.4 < fit.lag1 < -0.15, (name, fit)  # README: about -0.3
        # The interval after a gap: one loop predicts those samples better than the step since
        # the previous logged sample (scale fixed by the consecutive samples) ...
        step = np.diff(f.flow.t, prepend=f.flow.t[0] - f.flow.dt[0])
        alt = flow_vs_truth(f, dt=step)
        assert alt.pixels_per_rad == fit.pixels_per_rad  # same consecutive samples, same dt
        assert fit.residual_std_after_gap < alt.residual_std_after_gap, (name, fit, alt)
        # ... though they carry 1.2-1.45 loops of motion on average (documented in the reader).
        assert 1.15 < fit.after_gap_interval_ratio < 1.5, (name, fit)
        assert alt.after_gap_interval_ratio < 0.75, (name, alt)
    assert FIRMWARE_FLOW_PIXELS_PER_RAD == pytest.approx(48.83, abs=0.01)
    assert FLOW_PIXELS_PER_RAD == pytest.approx(47.8)  # README: fitted, pooled


@pytest.mark.realdata
def test_util_ground_truth_velocity_integrates_to_the_positions(util_flights):
    for name, f in util_flights.items():
        gt = f.ground_truth
        assert gt.world_v_body is not None and "derived" in f.meta["ground_truth"]["velocity"]
        # Over every 1 s window the integrated velocity matches the displacement.
        steps = np.diff(gt.t)[:, None]
        disp = np.vstack(
            [
                np.zeros(3),
                np.cumsum(0.5 * (gt.world_v_body[1:] + gt.world_v_body[:-1]) * steps, axis=0),
            ]
        )
        k = np.searchsorted(gt.t, gt.t + 1.0)
        ok = k < len(gt)
        err = (disp[k[ok]] - disp[ok]) - (gt.world_t_body[k[ok]] - gt.world_t_body[ok])
        assert np.sqrt(np.mean(err**2)) < 0.002, (name, np.sqrt(np.mean(err**2)))  # 0.8-1.3 mm
        assert np.abs(err).max() < 0.04, (name, np.abs(err).max())  # 0.8-3.2 cm
        speed = np.linalg.norm(gt.world_v_body[:, :2], axis=1)
        assert 0.6 < speed.max() < 2.0, name  # horizontal: 0.67-1.43 m/s


@pytest.mark.realdata
def test_util_gyro_agrees_with_vicon_attitude(util_flights):
    """FLU body and [w, x, y, z]: the body rate of the Vicon attitude over 0.2 s follows the gyro
    with slope 1 on every axis (Vicon rates regressed on the gyro's: Vicon is the noisy one)."""
    T = 0.2
    for name in ("0425-traj1", "0425-traj6"):
        f = util_flights[name]
        gt, imu = f.ground_truth, f.imu
        t0 = np.arange(gt.t[0] + 2.0, gt.t[-1] - 2.0, T)
        q = gt.world_q_body_wxyz
        R0 = quat_wxyz_to_matrix(interpolate_quat_wxyz(gt.t, q, t0))
        R1 = quat_wxyz_to_matrix(interpolate_quat_wxyz(gt.t, q, t0 + T))
        w_vicon = np.array([so3_log(a.T @ b) for a, b in zip(R0, R1, strict=True)]) / T
        integral = np.cumsum(imu.body_omega * np.gradient(imu.t)[:, None], axis=0)
        w_gyro = (
            np.column_stack(
                [
                    np.interp(t0 + T, imu.t, integral[:, i]) - np.interp(t0, imu.t, integral[:, i])
                    for i in range(3)
                ]
            )
            / T
        )
        for i in range(3):
            slope = (w_gyro[:, i] @ w_vicon[:, i]) / (w_gyro[:, i] @ w_gyro[:, i])
            assert slope == pytest.approx(1.0, abs=0.12), (name, i, slope)
            assert np.corrcoef(w_gyro[:, i], w_vicon[:, i])[0, 1] > 0.7, (name, i)


@pytest.mark.realdata
def test_util_still_imu_noise_constant_is_the_pooled_still_estimate(util_flights):
    g2 = a2 = n = 0.0
    for f in util_flights.values():
        m = f.meta["imu_noise"]
        g2 += m["blocks"] * m["gyro_noise_density"] ** 2
        a2 += m["blocks"] * m["accel_noise_density"] ** 2
        n += m["blocks"]
    assert n >= 40
    assert np.sqrt(g2 / n) == pytest.approx(STILL_IMU_NOISE.gyro_noise_density, rel=0.2)
    assert np.sqrt(a2 / n) == pytest.approx(STILL_IMU_NOISE.accel_noise_density, rel=0.2)


@pytest.mark.realdata
def test_cli_info_on_a_raw_log(tmp_path):
    from testutil import require_real_data, run_cli

    path = require_real_data() / "crazyflie_util_flowdeck" / "0425-traj1"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    run = run_cli("info", path)
    assert run.returncode == 0, run.stderr
    out = run.stdout
    assert out.startswith("flight  0425-traj1")
    for row in ("imu ", "range ", "flow ", "ground_truth "):
        assert any(line.startswith(row) for line in out.splitlines()), (row, out)
    assert "body_T_flow   t = [+0.0000, +0.0000, -0.0390] m, rotation 180.00 deg; 47.8 px/rad" in (
        out
    )
    assert "range.skipped_zero = 14" in out
    assert "ground_truth.skipped_exact_repeat = 42" in out
    # A damaged copy: one line, exit 1.
    damaged = tmp_path / "0425-traj1"
    shutil.copyfile(path, damaged)
    data = bytearray(damaged.read_bytes())
    data[1000] ^= 0xFF
    damaged.write_bytes(bytes(data))
    run = run_cli("info", damaged)
    assert run.returncode == 1
    err = [line for line in run.stderr.splitlines() if line.strip()]
    assert len(err) == 1 and "CRC-32 mismatch" in err[0], run.stderr


@pytest.mark.realdata
def test_shipped_manifest(util_flights):
    from testutil import PROJECT_ROOT

    f = read_manifest(PROJECT_ROOT / "datasets" / "manifests" / "crazyflie_traj1.toml")
    raw = util_flights["0425-traj1"]
    assert set(f.streams()) == {"imu", "range", "flow", "ground_truth"}
    np.testing.assert_array_equal(f.flow.dt, raw.flow.dt)
    np.testing.assert_array_equal(f.calib.body_T_range, raw.calib.body_T_range)


def test_a_clock_reset_and_a_stamp_less_imu_are_named(tmp_path):
    """Stamps that go back 2 s in the middle and stay there (a clock reset, CRC valid): the
    samples until the clock passed its old value were left out quietly and the rest read on a
    shifted clock (a real flight went from 0.078 to 0.68 m ATE, health "ok"; review
    2026-12-07). Every gyro and accelerometer stamp equal: the error said "empty keyframe
    window"; it now counts the IMU samples left."""
    recs, _ = flight_records(2)
    cut = round(2.1 * 1_000_000)
    reset = [(e, s - 2_000_000 if s >= cut and e in (1, 5) else s, v) for e, s, v in recs]
    with pytest.raises(FlightFormatError, match=r"estGyroscope: the clock goes back 1\.999 s at "):
        read_crazyflie(write_log(tmp_path / "reset", 2, reset))
    same = [(e, 2_000_000 if e in (1, 5) else s, v) for e, s, v in recs]
    with pytest.raises(FlightFormatError, match=r"1 usable IMU sample\(s\) of 200 \(199 gyro"):
        read_crazyflie(write_log(tmp_path / "same", 2, same))


def test_a_clock_jump_is_named_by_load_flight(tmp_path):
    """Stamps 1e6 s later from the middle on (CRC valid): reading the log resampled the ground
    truth's velocity across the jump and batch grew past 15 GB (review 2026-12-07)."""
    recs, _ = flight_records(2)
    cut = round(2.1 * 1_000_000)
    jump = [(e, s + 10**12 if s >= cut else s, v) for e, s, v in recs]
    path = write_log(tmp_path / "jump", 2, jump)
    with pytest.raises(FlightFormatError, match=r"the clock jumps by 1e\+06 s between samples"):
        load_flight(path)


def test_implausible_imu_tof_and_flow_left_out_and_counted(tmp_path):
    """A finite but absurd sample (gyro 1e30 deg/s, accel 9.8e30, ToF 65535 mm, flow count
    -32768) is a corrupted one: left out, counted and printed by ``fgnav info``; a reading beyond
    the ToF's limits but under 5 m is kept and its count printed too."""
    from fgnav.info import flight_info

    recs, truth = flight_records(2)
    us = 1_000_000
    t_gyro = {round(t * us) for t in truth["t_imu"][[20, 60]]}
    t_acc = round(truth["t_imu"][100] * us)
    t_flow = round(truth["t_flow"][3] * us)
    tof = {round(truth["t_tof"][2] * us): 65535, round(truth["t_tof"][3] * us): 4500}
    out = []
    for eid, stamp, v in recs:
        if eid == 5 and stamp in t_gyro:
            v = (1e30, v[1], v[2])
        elif eid == 1 and stamp == t_acc:
            v = (v[0], v[1], 1e30)
        elif eid == 4 and stamp == t_flow:
            v = (-32768, v[1])
        elif eid == 10 and stamp in tof:
            v = (tof[stamp],)
        out.append((eid, stamp, v))
    f = read_crazyflie(write_log(tmp_path / "log", 2, out))
    assert len(f.imu) == 197 and f.meta["imu"]["skipped_implausible"] == 3
    assert np.all(np.abs(f.imu.body_omega) < 5.0) and np.all(np.abs(f.imu.body_accel) < 20.0)
    assert len(f.flow) == 10 and f.meta["flow"]["skipped_implausible"] == 1
    np.testing.assert_allclose(f.range.range, [0.512, 4.5])
    assert f.meta["range"]["skipped_implausible"] == 1
    assert f.meta["range"]["outside_min_max_kept"] == 1
    notes = flight_info(f).notes
    for line in (
        "imu.skipped_implausible = 3",
        "flow.skipped_implausible = 1",
        "range.skipped_implausible = 1",
        "range.outside_min_max_kept = 1",
    ):
        assert line in notes, notes


def test_skip_counts_survive_a_manifest(tmp_path):
    """A log read through a manifest keeps its reader's skip counts (only the notes were copied):
    ``fgnav info`` prints the same counts, prefixed with the table that read the log."""
    from fgnav.info import flight_info

    recs, _ = flight_records(2)
    write_log(tmp_path / "log", 2, recs)
    manifest = tmp_path / "m.toml"
    manifest.write_text(
        'name = "m"\n[imu]\nformat = "crazyflie"\npath = "log"\n'
        '[range]\nformat = "crazyflie"\npath = "log"\n'
    )
    f = read_manifest(manifest)
    assert f.meta["[imu] range"]["skipped_zero"] == 1
    notes = flight_info(f).notes
    assert "[imu] range.skipped_zero = 1" in notes, notes
    assert "[imu] ground_truth.skipped_exact_repeat = 1" in notes, notes
    # The counts are JSON: the flight saves as a native folder and reads back.
    write_flight(f, tmp_path / "native")
    assert read_flight(tmp_path / "native").meta["[imu] range"]["skipped_zero"] == 1
