"""Native flight folder: exact round trip of every stream type, and bad inputs named precisely."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from fgnav.datasets import (
    AttitudeSeries,
    Calibration,
    CameraIntrinsics,
    Flight,
    FlightDataError,
    FlightFormatError,
    ImageSeries,
    ImuNoise,
    ImuSeries,
    RangeSeries,
    SlamSeries,
    Trajectory,
    YawSeries,
)
from fgnav.datasets.geometry import make_pose, rpy_to_matrix
from fgnav.datasets.native import read_flight, write_flight


def _unit_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q


def _times(rng: np.random.Generator, n: int, rate: float) -> np.ndarray:
    # Awkward floats (not multiples of the period) so that repr round trips are exercised.
    return 1.7e9 + np.cumsum(rng.uniform(0.9, 1.1, n) / rate)


def make_full_flight(seed: int = 0) -> Flight:
    """A flight with every stream type and every optional column, random values."""
    rng = np.random.default_rng(seed)
    n = 50
    cam = CameraIntrinsics(200.5, 201.25, 16.0, 12.0, 32, 24, (-0.28, 0.07, 1e-4, 2e-5))
    frames = rng.integers(0, 256, size=(3, 24, 32), dtype=np.uint8)
    calib = Calibration(
        body_T_cam=make_pose(rpy_to_matrix(0.1, -0.2, 1.3), [0.05, -0.01, 0.02]),
        body_T_range=make_pose(rpy_to_matrix(np.pi, 0.05, 0.0), [0.0, 0.0, -0.03]),
        camera=cam,
        imu_noise=ImuNoise(1.1e-4, 2.2e-3, 3.3e-5, 4.4e-3),
        range_min=0.1,
        range_max=float("inf"),
        time_offsets={"slam": -0.0125},
    )
    traj_kwargs = dict(
        world_t_body=rng.normal(size=(n, 3)),
        world_q_body_wxyz=_unit_quats(rng, n),
    )
    return Flight(
        name="full",
        source="unit test",
        imu=ImuSeries(_times(rng, n, 200), rng.normal(size=(n, 3)), rng.normal(size=(n, 3))),
        attitude=AttitudeSeries(_times(rng, n, 50), _unit_quats(rng, n)),
        range=RangeSeries(_times(rng, n, 30), rng.uniform(0.2, 5, n), rng.uniform(0, 1, n)),
        yaw=YawSeries(_times(rng, n, 10), rng.uniform(-np.pi, np.pi, n)),
        slam=SlamSeries(
            _times(rng, n, 20),
            rng.normal(size=(n, 3)),
            _unit_quats(rng, n),
            np.repeat([0, 1], n // 2).astype(np.int64),
            rng.uniform(0.01, 0.2, n),
        ),
        images=ImageSeries(_times(rng, 3, 20), frames=frames, camera=cam),
        ground_truth=Trajectory(
            _times(rng, n, 100),
            **traj_kwargs,
            world_v_body=rng.normal(size=(n, 3)),
            gyro_bias=rng.normal(size=(n, 3)) * 1e-3,
            accel_bias=rng.normal(size=(n, 3)) * 1e-2,
        ),
        references={"px4_ekf2": Trajectory(_times(rng, n, 10), **traj_kwargs)},
        calib=calib,
        meta={
            "truth": {"drag_k": np.array([0.3, 0.2]), "slam_scale": {"0": 1.5, "1": 0.7}},
            "note": "hello",
            "count": np.int64(3),
        },
    )


def _assert_series_equal(a, b) -> None:
    assert type(a) is type(b)
    for f in (
        "t",
        "body_omega",
        "body_accel",
        "world_q_body_wxyz",
        "range",
        "quality",
        "yaw",
        "slam_t_cam",
        "slam_q_cam_wxyz",
        "session",
        "latency",
        "world_t_body",
        "world_v_body",
        "gyro_bias",
        "accel_bias",
    ):
        if hasattr(a, f):
            va, vb = getattr(a, f), getattr(b, f)
            if va is None:
                assert vb is None, f
            else:
                np.testing.assert_array_equal(va, vb, err_msg=f)
                assert va.dtype.kind == vb.dtype.kind, f


def test_round_trip_is_exact(tmp_path):
    flight = make_full_flight()
    folder = write_flight(flight, tmp_path / "f")
    back = read_flight(folder)
    assert back.name == flight.name and back.source == flight.source
    for s in ("imu", "attitude", "range", "yaw", "slam", "ground_truth"):
        _assert_series_equal(getattr(flight, s), getattr(back, s))
    _assert_series_equal(flight.references["px4_ekf2"], back.references["px4_ekf2"])
    # Images: written from memory as PNG, read back as absolute paths with identical pixels.
    assert back.images.frames is None
    assert all(p.is_absolute() and p.suffix == ".png" for p in back.images.paths)
    np.testing.assert_array_equal(back.images.t, flight.images.t)
    for i in range(3):
        np.testing.assert_array_equal(back.images.load(i), flight.images.frames[i])
    assert back.images.camera == flight.images.camera
    # Calibration.
    np.testing.assert_array_equal(back.calib.body_T_cam, flight.calib.body_T_cam)
    np.testing.assert_array_equal(back.calib.body_T_range, flight.calib.body_T_range)
    assert back.calib.camera == flight.calib.camera
    assert back.calib.imu_noise == flight.calib.imu_noise
    assert back.calib.range_max == float("inf") and back.calib.range_min == 0.1
    assert back.calib.time_offsets == {"slam": -0.0125}
    # Meta: numpy values become JSON lists/numbers.
    assert back.meta == {
        "truth": {"drag_k": [0.3, 0.2], "slam_scale": {"0": 1.5, "1": 0.7}},
        "note": "hello",
        "count": 3,
    }
    # Header names columns and units.
    assert (
        (folder / "imu.csv")
        .read_text()
        .splitlines()[0]
        .startswith("t [s],omega_x [rad/s],omega_y [rad/s],omega_z [rad/s],accel_x [m/s^2]")
    )


def test_optional_columns_absent_and_image_files_copied(tmp_path):
    full = make_full_flight(1)
    minimal = Flight(
        name="min",
        range=RangeSeries(full.range.t, full.range.range),
        slam=SlamSeries(
            full.slam.t, full.slam.slam_t_cam, full.slam.slam_q_cam_wxyz, full.slam.session
        ),
        ground_truth=Trajectory(
            full.ground_truth.t, full.ground_truth.world_t_body, full.ground_truth.world_q_body_wxyz
        ),
        images=full.images,
    )
    first = read_flight(write_flight(minimal, tmp_path / "a"))
    assert "quality" not in (tmp_path / "a" / "range.csv").read_text()
    assert first.range.quality is None and first.slam.latency is None
    assert first.ground_truth.world_v_body is None
    # An image series held as files is copied.
    second = read_flight(write_flight(first, tmp_path / "b"))
    assert second.images.paths[0].parent == (tmp_path / "b" / "cam0").resolve()
    np.testing.assert_array_equal(second.images.load(2), full.images.frames[2])


def test_refuses_non_empty_folder_and_bad_meta(tmp_path):
    flight = make_full_flight()
    write_flight(flight, tmp_path / "f")
    with pytest.raises(FileExistsError):
        write_flight(flight, tmp_path / "f")
    write_flight(flight, tmp_path / "f", overwrite=True)
    bad = Flight(name="bad", imu=flight.imu, meta={"x": {"y": object()}})
    with pytest.raises(FlightDataError, match=r"meta\['x'\]\['y'\]: cannot store a object"):
        write_flight(bad, tmp_path / "g")


def _write_min(tmp_path):
    f = make_full_flight()
    return write_flight(Flight(name="m", imu=f.imu), tmp_path / "m")


def _edit_line(path, line_no, new):
    lines = path.read_text().splitlines()
    lines[line_no - 1] = new(lines[line_no - 1])
    path.write_text("\n".join(lines) + "\n")


def test_missing_column_named(tmp_path):
    folder = _write_min(tmp_path)
    imu = folder / "imu.csv"
    _edit_line(imu, 1, lambda s: s.replace(",accel_y [m/s^2]", ""))
    lines = imu.read_text().splitlines()
    imu.write_text(
        "\n".join([lines[0]] + [",".join(r.split(",")[:5] + r.split(",")[6:]) for r in lines[1:]])
        + "\n"
    )
    with pytest.raises(FlightFormatError, match=r"imu\.csv:1: missing column 'accel_y \[m/s\^2\]'"):
        read_flight(folder)


def test_unknown_column_named(tmp_path):
    folder = _write_min(tmp_path)
    _edit_line(folder / "imu.csv", 1, lambda s: s.replace("omega_z", "omega_q"))
    with pytest.raises(FlightFormatError, match=r"unknown column\(s\) \['omega_q'\]"):
        read_flight(folder)


def test_nan_and_text_named_with_line(tmp_path):
    folder = _write_min(tmp_path)
    _edit_line(
        folder / "imu.csv", 5, lambda s: ",".join(s.split(",")[:3] + ["nan"] + s.split(",")[4:])
    )
    with pytest.raises(FlightFormatError, match=r"imu\.csv:5: column 4 \('omega_z'\): non-finite"):
        read_flight(folder)
    folder = write_flight(Flight(name="m", imu=make_full_flight().imu), tmp_path / "n")
    _edit_line(folder / "imu.csv", 7, lambda s: s.split(",", 1)[0] + ",abc," + s.split(",", 2)[2])
    msg = r"imu\.csv:7: column 2 \('omega_x'\): expected a number, found 'abc'"
    with pytest.raises(FlightFormatError, match=msg):
        read_flight(folder)


def test_non_increasing_time_and_wrong_width(tmp_path):
    folder = _write_min(tmp_path)
    lines = (folder / "imu.csv").read_text().splitlines()
    lines[9], lines[10] = lines[10], lines[9]
    (folder / "imu.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(FlightFormatError, match=r"imu\.csv:11: time must be strictly increasing"):
        read_flight(folder)
    folder = write_flight(Flight(name="m", imu=make_full_flight().imu), tmp_path / "w")
    _edit_line(folder / "imu.csv", 3, lambda s: s + ",1.0")
    with pytest.raises(FlightFormatError, match=r"imu\.csv:3: expected 7 columns"):
        read_flight(folder)


def test_empty_file_and_missing_folder(tmp_path):
    folder = _write_min(tmp_path)
    (folder / "imu.csv").write_text("t [s],omega_x [rad/s]\n")
    with pytest.raises(FlightFormatError, match=r"imu\.csv: no data lines"):
        read_flight(folder)
    with pytest.raises(FlightFormatError, match="meta.json not found"):
        read_flight(tmp_path / "nowhere")
    meta = json.loads((folder / "meta.json").read_text())
    meta["format"] = "other"
    (folder / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(FlightFormatError, match="expected 'fgnav-flight'"):
        read_flight(folder)


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        # Each calibration value's error names its key (found by fuzzing `fgnav live --calib`:
        # "float() argument must be a string or a real number, not 'list'" named none).
        (lambda c: c["imu_noise"].update(gyro_noise_density=[1, 2]), "imu_noise.gyro_noise_de"),
        (lambda c: c.update(flow_pixels_per_rad={"a": 1}), "flow_pixels_per_rad: expected a nu"),
        (lambda c: c.update(flow_rate_gain=0.5), "flow_rate_gain: expected [a, b], got 0.5"),
        (lambda c: c["camera"].update(width=320.5), "camera.width: expected an integer"),
        (lambda c: c["camera"].update(fy=True), "camera.fy: expected a number, got True"),
        # Values the file reads but no sensor can have, checked on reading (were accepted).
        (lambda c: c.update(range_max=float("nan")), "expected 0 <= range_min < range_max"),
        (lambda c: c.update(range_min=-1.0), "expected 0 <= range_min < range_max"),
        (lambda c: c["imu_noise"].update(accel_noise_density=-1.0), "accel_noise_density: expe"),
        (lambda c: c.update(time_offsets={"slam": float("inf")}), "time_offsets.slam: expected"),
    ],
)
def test_bad_calibration_values_named(tmp_path, edit, needle):
    import yaml
    from fgnav.datasets.errors import FlightFormatError
    from fgnav.datasets.native import read_calib_yaml

    folder = tmp_path / "f"
    write_flight(make_full_flight(), folder)
    calib = yaml.safe_load((folder / "calib.yaml").read_text())
    edit(calib)
    bad = tmp_path / "calib.yaml"
    bad.write_text(yaml.safe_dump(calib))
    with pytest.raises(FlightFormatError) as e:
        read_calib_yaml(bad)
    msg = str(e.value)
    assert needle in msg and msg.count(str(bad)) == 1 and "\n" not in msg


def test_header_units_are_read_and_stamps_must_be_seconds(tmp_path):
    """A native file whose header states other units (deg/s, g, ms, mm) was read as SI with the
    units stripped; an IMU stamped in ns with a "[s]" header asked for 7 TiB in batch and made
    the online replay step for ever (review 2026-12-07). Both are one-line errors now."""
    from fgnav.datasets.load import load_flight
    from fgnav.datasets.native import open_flight_streams, write_flight
    from fgnav.datasets.types import Flight, ImuSeries

    t = 0.005 * np.arange(400)
    imu = ImuSeries(t, np.zeros((400, 3)), np.tile([0.0, 0.0, 9.81], (400, 1)))
    good = write_flight(Flight(name="u", imu=imu), tmp_path / "good")
    assert len(load_flight(good).imu) == 400
    text = (good / "imu.csv").read_text()
    deg = tmp_path / "deg"
    write_flight(Flight(name="u", imu=imu), deg)
    (deg / "imu.csv").write_text(text.replace("omega_x [rad/s]", "omega_x [deg/s]", 1))
    with pytest.raises(FlightFormatError, match=r"imu\.csv:1: column 'omega_x' is in \[deg/s\]"):
        load_flight(deg)
    ns = tmp_path / "ns"
    write_flight(Flight(name="u", imu=dataclasses.replace(imu, t=t * 1e9)), ns)
    for read in (load_flight, open_flight_streams):
        with pytest.raises(FlightFormatError, match=r"sample interval 5e\+06 s .* not an IMU's"):
            read(ns)


@pytest.mark.parametrize(
    "key, value, needle",
    [
        ("streams", 5, '"streams": expected a list of stream names, found 5'),
        ("streams", "imu", '"streams": expected a list of stream names, found "imu"'),
        ("references", 3, '"references": expected a list of reference names, found 3'),
        ("references", {"a": 1}, '"references": expected a list of reference names'),
        ("meta", "x", '"meta": expected an object, found "x"'),
        ("meta", None, '"meta": expected an object, found null'),
        ("name", 5, '"name": expected a string, found 5'),
    ],
)
def test_meta_json_value_types_named(tmp_path, key, value, needle):
    """A wrong value type in meta.json: one line naming meta.json and the key (TypeError and
    AttributeError tracebacks in the reader, ``fgnav info`` and the online run), for the
    whole-flight reader and the stream reader alike."""
    from fgnav.datasets.native import open_flight_streams

    folder = _write_min(tmp_path)
    meta = json.loads((folder / "meta.json").read_text())
    meta[key] = value
    (folder / "meta.json").write_text(json.dumps(meta))
    for read in (read_flight, open_flight_streams):
        with pytest.raises(FlightFormatError) as e:
            read(folder)
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith(str(folder / "meta.json")), msg
        assert needle in msg, msg


def test_meta_json_not_text_named(tmp_path):
    folder = _write_min(tmp_path)
    (folder / "meta.json").write_bytes(b"\xff\xfe{}")
    with pytest.raises(FlightFormatError, match=r"meta\.json: not a text meta\.json: byte 0"):
        read_flight(folder)
