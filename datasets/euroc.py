"""EuRoC MAV / ASL csv files and ``mav0`` folders.

Files (Burri et al., "The EuRoC micro aerial vehicle datasets", IJRR 2016):

- ``imu0/data.csv``: ``#timestamp [ns],w_RS_S_x [rad s^-1],...,a_RS_S_z [m s^-2]``, 200 Hz.
- ``state_groundtruth_estimate0/data.csv``: ``#timestamp, p_RS_R_x..z [m], q_RS_w..z [],
  v_RS_R_x..z [m s^-1], b_w_RS_S_x..z [rad s^-1], b_a_RS_S_x..z [m s^-2]`` (17 columns).
- 8-column pose files ``#timestamp [ns],p_x,p_y,p_z,q_w,q_x,q_y,q_z`` such as the 20 Hz ``*_GT.txt``
  files of ORB-SLAM3's evaluation, which hold the pose of cam0 (not of the IMU) at frame times.
- ``cam0/data.csv`` (``#timestamp [ns],filename``) with images in ``cam0/data/``, and each
  sensor's ``sensor.yaml`` (``T_BS``, intrinsics, IMU noise densities).

Time is integer nanoseconds in the files and float seconds here. Quaternions are ``[w, x, y, z]``
in the files as in fgnav.

Frames: the dataset's body frame is its IMU frame ``S`` (ADIS16448 of the VI-sensor). It is
**not FLU**: from cam0's ``T_BS`` (cam0 x ~ +y_imu, cam0 y ~ -x_imu, cam0 z ~ +z_imu) the IMU axes
are about x up, y right, z forward along cam0's optical axis; the sensor head pitches down about
20 deg, so in hover the accelerometer reads about (+9.2, 0, -3.3) m/s^2. The world frame of the
ground truth (Leica total station / Vicon) is z up, gravity ``(0, 0, -g)``, as fgnav's.

Body frame option (``body=`` of :func:`read_euroc_folder`, ``[body] frame`` of a manifest):

- ``"imu"`` (the default, also of ``datasets/manifests/euroc_mh01_orbslam3.toml``): body = ``S``
  unchanged, nothing rotated.
- ``"flu"``: a FLU multirotor body, ``v_flu = flu_R_imu @ v_imu`` (:func:`flu_R_imu`, recorded
  as ``meta["body_from_imu"]`` and printed by ``fgnav info``): body z = the thrust axis, body x =
  cam0's optical axis projected orthogonal to z (forward), y = z x x (left), origin at the IMU
  (no lever arm: positions and world velocities are unchanged). :func:`to_flu_body` rotates gyro
  and accelerometer, ground-truth orientation and biases, references (taken as IMU-frame body
  trajectories) and ``body_T_cam``; SLAM camera poses and images stay. On MH_01::

      flu_R_imu = [[ 0.3319,  0.0289,  0.9429],
                   [ 0.0141, -0.9996,  0.0257],
                   [ 0.9432,  0.0048, -0.3322]]

  (a turn of 179.4 deg: body x ~ imu z, y ~ -imu y, z ~ imu x; the thrust axis is 19.4 deg
  from imu x toward -imu z).

  The thrust axis (:data:`THRUST_AXIS_IMU`) is the normalised mean specific force of MH_01's
  IMU over its airborne part (45-182 s after the first sample). Thrust acts along the rotor axis
  and its mean direction over a flight that starts and ends near hover is vertical, so the mean
  specific force points along the rotor axis up to the small mean rotor drag. Checks on the data:
  the MH_01 ground truth's mean "up" direction over the same window is 0.84 deg from it, and the
  IMU's mean specific force in flight on V1_01 and V1_02 (same Firefly, same mount) is 0.35 and
  0.7 deg from it. After conversion the MH_01 ground-truth body z is 2.2 deg from vertical on
  average (max 15.2 deg, 95th percentile 5.2 deg) over 45-182 s. The rest on the ground
  (22-30 s) was **not** used: the Firefly stands 5.5 deg tilted on the floor there (ground
  truth and accelerometer agree, 5.3 deg), so the rest specific force reads (0.68, 0.59, 9.74)
  m/s^2 in the FLU body, not the thrust axis.

  Downstream (MH_01, default options): the FLU body switches the graph's rotor-drag factor on
  (its thrust-axis check passes), which has no airborne gate and a model noise (0.05 m/s^2) below
  the Firefly's vibration in a 50 ms accelerometer mean (0.12-0.19 m/s^2): the batch smoother
  then fails and the fixed-lag one diverges. With ``[graph] use_drag = false`` the FLU body gives
  the IMU body's batch and fixed-lag results, and it fixes the filters that use Euler angles
  (seed-003 UKF: ATE 0.22 m instead of diverging at the x-up body's gimbal lock). Hence the
  manifest keeps ``"imu"`` as its default for now.

Bad input policy (decision for the spreadsheet-damaged ``euroc_MH_01_easy/imu0/data.csv``): the
file is **loaded, with warnings**, because nothing in it is ambiguous:

- Time stamps written in scientific notation (``1.40363657975856E+018``) are read exactly as
  decimals (no float64 rounding) and rounded to the ns; a warning states the coarsest resolution
  found (10 us there) and an example line. Time must still be strictly increasing.
- A block of lines at the **end** of the file that are not data rows (``,,,,,,``,
  ``1403636763.853,,,,,,``, ``Step: 0.005 = 1/200,,,,,,``) is skipped; a warning counts them and
  names their line numbers, and the same text goes to the reader ``notes`` (and so to
  ``flight.meta["notes"]``, shown by ``fgnav info``).
- Anything malformed **before** the last data row (a missing value, text, NaN, a wrong column
  count, time going backwards) is an error naming file, line and column: such a file has lost
  data in the middle, which no reader should paper over.
- Lines repeating the previous line exactly are skipped and reported (as in :mod:`.tum`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from . import _tables
from ._files import file_count, file_number, read_text, resolved, yaml_error
from .errors import FlightDataError, FlightFormatError, note
from .frames import rotate_body_frame
from .geometry import invert_pose
from .types import (
    Calibration,
    CameraIntrinsics,
    Flight,
    ImageSeries,
    ImuNoise,
    ImuSeries,
    Trajectory,
    imu_noise_problem,
)

log = logging.getLogger(__name__)

IMU_UNITS = {"gyro": ("rad s^-1", "rads^-1", "rad/s"), "accel": ("m s^-2", "ms^-2", "m/s^2")}
"""Units the IMU header may give (spaces ignored; a column without a unit is taken as these): a
gyro in ``[deg s^-1]`` was read as rad/s."""
IMU_COLUMNS = ("timestamp", "w_RS_S_x", "w_RS_S_y", "w_RS_S_z", "a_RS_S_x", "a_RS_S_y", "a_RS_S_z")
POSE_COLUMNS = 8
STATE_COLUMNS = 17

BODY_FRAMES = ("imu", "flu")
"""Body frames the readers give: ``"imu"`` (EuRoC's IMU frame S, unchanged) or ``"flu"`` (the
multirotor FLU body of :func:`flu_R_imu`; see the module docstring)."""

THRUST_AXIS_IMU = (0.9432, 0.0048, -0.3322)
"""The Firefly's thrust axis (rotor axis, body +z of the FLU body) in EuRoC's IMU frame S: the
normalised mean specific force of MH_01_easy's ``imu0`` over its airborne part, 45-182 s after the
first sample (derivation in the module docstring). Same vehicle and sensor mount in all EuRoC
sequences: V1_01 gives a direction 0.35 deg away, V1_02 0.7 deg."""

#: Smallest angle [deg] between cam0's optical axis and the thrust axis for a usable forward axis.
MIN_FORWARD_ANGLE_DEG = 30.0


# ----------------------------------------------------------------------------------------------
# Shared csv handling
# ----------------------------------------------------------------------------------------------


def _is_data_row(row: list[str], width: int) -> bool:
    if len(row) != width:
        return False
    try:
        return all(math.isfinite(float(tok)) for tok in row)
    except ValueError:
        return False


def _describe_ns(ns: int) -> str:
    for unit, scale in (("s", 10**9), ("ms", 10**6), ("us", 10**3)):
        if ns >= scale:
            return f"{ns / scale:g} {unit}"
    return f"{ns} ns"


def _read_csv(
    path: str | Path, widths: tuple[int, ...], what: str, notes: list[str] | None
) -> tuple[_tables.RawTable, int]:
    """Read an EuRoC csv, skip (and report) a trailing block of non-data lines; return the table
    and its column count."""
    raw = _tables.read_raw(path, sep=",", header="comment")
    if raw.header is None:
        raise FlightFormatError(
            raw.path, f"missing the EuRoC header line ('#timestamp [ns],...' for {what})", line=1
        )
    width = len(raw.header)
    if width not in widths:
        raise FlightFormatError(
            raw.path,
            f"header has {width} columns, expected "
            + " or ".join(str(w) for w in widths)
            + f" ({what}): {raw.header_raw}",
            line=1,
        )
    end = len(raw.rows)
    while end > 0 and not _is_data_row(raw.rows[end - 1], width):
        end -= 1
    if end < len(raw.rows):
        junk = raw.lines[end:]
        sample = ", ".join(repr(",".join(r))[:40] for r in raw.rows[end : end + 3])
        note(
            log,
            notes,
            f"{raw.path}: skipped {len(junk)} trailing non-data line(s) after the last data row "
            f"(lines {junk[0]}-{junk[-1]}: {sample}{' ...' if len(junk) > 3 else ''})",
        )
        raw.rows, raw.lines = raw.rows[:end], raw.lines[:end]
    if not raw.rows:
        raise FlightFormatError(raw.path, "no data lines")
    _tables.check_widths(raw, (width,), what)
    return raw, width


def _times(raw: _tables.RawTable, notes: list[str] | None) -> np.ndarray:
    parsed = _tables.parse_ns(raw, 0)
    if parsed.resolution_ns > 1 and parsed.example is not None:
        line, tok = parsed.example
        note(
            log,
            notes,
            f"{raw.path}: time stamps are not plain integer ns (line {line}: {tok!r}, e.g. from a "
            f"spreadsheet); read exactly, but their resolution is only "
            f"{_describe_ns(parsed.resolution_ns)}",
        )
    return _tables.ns_to_seconds(parsed.ns)


def _series_rows(
    raw: _tables.RawTable, notes: list[str] | None, what: str
) -> tuple[np.ndarray, np.ndarray]:
    values = _tables.to_values(raw, range(len(raw.header or raw.rows[0])))
    t = _times(raw, notes)
    t, values, lines = _tables.drop_repeated_rows(raw, t, values, notes, what)
    _tables.check_increasing(raw, t, lines)
    return t, values


# ----------------------------------------------------------------------------------------------
# Readers
# ----------------------------------------------------------------------------------------------


def read_euroc_imu(path: str | Path, *, notes: list[str] | None = None) -> ImuSeries:
    """Read an EuRoC ``imu0/data.csv``.

    Args:
        path: the csv.
        notes: list to which reader notes (skipped lines, time resolution) are appended.

    Returns:
        ImuSeries in EuRoC's IMU frame (used as body; see the module docstring): ``body_omega``
        [rad/s], ``body_accel`` (specific force) [m/s^2], ``t`` [s].

    Raises:
        FlightFormatError: naming file, line and column (see the module docstring's policy).
    """
    raw, _ = _read_csv(path, (len(IMU_COLUMNS),), "timestamp, w_RS_S_x..z, a_RS_S_x..z", notes)
    for j, expected in enumerate(IMU_COLUMNS[1:], start=1):
        if not raw.header[j].startswith(expected):
            raise FlightFormatError(
                raw.path,
                f"header column {j + 1} is {raw.header_raw[j]!r}, expected {expected!r} "
                f"(EuRoC IMU: {', '.join(IMU_COLUMNS)})",
                line=1,
            )
    for j, name in enumerate(raw.header_raw[1:], start=1):
        unit = _tables.unit_of(name)
        accepted = IMU_UNITS["gyro" if j <= 3 else "accel"]
        if unit is not None and unit.replace(" ", "") not in accepted:
            raise FlightFormatError(
                raw.path,
                f"header column {j + 1} {name!r}: unit [{unit}] is not read (EuRoC IMU units: "
                "[rad s^-1] and [m s^-2]); convert the column or fix the header",
                line=1,
            )
    t, v = _series_rows(raw, notes, "IMU")
    return ImuSeries(t=t, body_omega=v[:, 1:4].copy(), body_accel=v[:, 4:7].copy()).check(
        str(raw.path)
    )


def read_euroc_groundtruth(path: str | Path, *, notes: list[str] | None = None) -> Trajectory:
    """Read an EuRoC ground-truth csv; the kind is detected from the header's column count.

    - 17 columns (``state_groundtruth_estimate0/data.csv``): IMU-frame pose, ``world_v_body``
      [m/s], ``gyro_bias`` [rad/s] and ``accel_bias`` [m/s^2].
    - 8 columns (``#timestamp [ns],p_x,p_y,p_z,q_w,q_x,q_y,q_z``): pose only, of whichever frame the
      file describes (the 20 Hz ``*_GT.txt`` files hold cam0 poses; a note says so).

    Returns:
        Trajectory in the ground truth's world frame (z up), ``t`` [s].
    """
    raw, width = _read_csv(
        path, (POSE_COLUMNS, STATE_COLUMNS), "EuRoC pose or state ground truth", notes
    )
    t, v = _series_rows(raw, notes, "ground-truth")
    kwargs: dict[str, Any] = {}
    if width == STATE_COLUMNS:
        kwargs = dict(world_v_body=v[:, 8:11], gyro_bias=v[:, 11:14], accel_bias=v[:, 14:17])
    else:
        msg = (
            f"{raw.path}: 8-column EuRoC pose file, pose only (no velocity or biases); 20 Hz "
            f"'*_GT.txt' files of this kind hold cam0 poses, not IMU poses"
        )
        note(log, notes, msg, logging.INFO)
    return Trajectory(
        t=t, world_t_body=v[:, 1:4].copy(), world_q_body_wxyz=v[:, 4:8].copy(), **kwargs
    ).check(str(raw.path))


def read_euroc_images(
    path: str | Path, camera: CameraIntrinsics | None, *, notes: list[str] | None = None
) -> ImageSeries:
    """Read ``cam0/data.csv`` (``#timestamp [ns],filename``); images live in ``data/`` beside it.

    Raises:
        FlightFormatError: a listed image file is missing (naming the line), or a bad time stamp.
    """
    raw = _tables.read_raw(path, sep=",", header="comment")
    if raw.header is None or len(raw.header) != 2:
        raise FlightFormatError(raw.path, "expected the header '#timestamp [ns],filename'", line=1)
    _tables.check_widths(raw, (2,), "timestamp, filename")
    t = _times(raw, notes)
    _tables.check_increasing(raw, t)
    folder = Path(path).parent / "data"
    paths = []
    for k, row in enumerate(raw.rows):
        p = resolved(folder / row[1], raw.path, "image file", line=raw.lines[k])
        if not p.is_file():
            raise FlightFormatError(raw.path, f"image file {p} not found", line=raw.lines[k])
        paths.append(p)
    return ImageSeries(t=t, paths=tuple(paths), camera=camera)


def _read_sensor_yaml(path: Path) -> dict[str, Any]:
    text = read_text(path, "sensor file")
    try:
        # The directive line is blanked, not removed, so that an error names the right line.
        d = yaml.safe_load("\n".join("" if ln.startswith("%") else ln for ln in text.splitlines()))
    except yaml.YAMLError as e:
        raise yaml_error(path, e) from None
    if not isinstance(d, dict):
        raise FlightFormatError(path, "expected a YAML mapping")
    return d


def _T_BS(d: dict[str, Any], path: Path) -> np.ndarray:
    try:
        T = np.asarray(d["T_BS"]["data"], dtype=float).reshape(4, 4)
    except (KeyError, TypeError, ValueError) as e:
        raise FlightFormatError(path, f"T_BS: expected a 4x4 'data' list ({e})") from e
    return T


def _imu_noise(d: dict[str, Any], path: Path) -> ImuNoise:
    keys = {
        "gyro_noise_density": "gyroscope_noise_density",
        "accel_noise_density": "accelerometer_noise_density",
        "gyro_random_walk": "gyroscope_random_walk",
        "accel_random_walk": "accelerometer_random_walk",
    }
    missing = [v for v in keys.values() if v not in d]
    if missing:
        raise FlightFormatError(path, f"missing IMU noise key(s) {missing}")
    values = {k: file_number(d[v], v, path) for k, v in keys.items()}
    for k, v in keys.items():
        problem = imu_noise_problem(k, values[k])
        if problem is not None:
            raise FlightFormatError(path, f"{v}: {problem}, got {values[k]}")
    return ImuNoise(**values)


def _camera(d: dict[str, Any], path: Path) -> CameraIntrinsics:
    try:
        fx, fy, cx, cy = (float(x) for x in d["intrinsics"])
        width, height = (file_count(x, "resolution", path) for x in d["resolution"])
        dist = tuple(float(x) for x in d.get("distortion_coefficients", ()))
    except (KeyError, TypeError, ValueError) as e:
        raise FlightFormatError(
            path, f"expected 'intrinsics: [fu, fv, cu, cv]' and 'resolution: [w, h]' ({e})"
        ) from e
    model = d.get("distortion_model", "radial-tangential")
    if model != "radial-tangential":
        raise FlightFormatError(
            path, f"distortion_model {model!r} is not supported (expected 'radial-tangential')"
        )
    return CameraIntrinsics(fx, fy, cx, cy, width, height, dist)


# ----------------------------------------------------------------------------------------------
# FLU body
# ----------------------------------------------------------------------------------------------


def flu_R_imu(
    imu_T_cam: np.ndarray, thrust_axis_imu: Any = THRUST_AXIS_IMU, *, where: str = "thrust_axis"
) -> np.ndarray:
    """Rotation ``flu_R_imu`` (3x3, ``v_flu = flu_R_imu @ v_imu``) to the FLU multirotor body.

    Body z: the thrust axis (normalised); body x: cam0's optical axis (``imu_T_cam[:3, 2]``)
    projected orthogonal to z (forward); body y = z x x (left). The rows of the result are the
    FLU axes in the IMU frame. Same origin as the IMU (no lever arm).

    Raises:
        FlightDataError: naming ``where``: the thrust axis is not 3 finite numbers of non-zero
            length, or it lies within :data:`MIN_FORWARD_ANGLE_DEG` of the optical axis.
    """
    try:
        z = np.asarray(thrust_axis_imu, dtype=float).reshape(3)
    except (TypeError, ValueError) as e:
        raise FlightDataError(
            f"{where}: expected 3 numbers (IMU frame), got {thrust_axis_imu!r}"
        ) from e
    norm = float(np.linalg.norm(z))
    if not np.all(np.isfinite(z)) or norm < 1e-9:
        raise FlightDataError(f"{where}: expected a finite non-zero vector, got {z.tolist()}")
    z = z / norm
    c = np.asarray(imu_T_cam, dtype=float)[:3, 2]
    c = c / np.linalg.norm(c)
    angle = math.degrees(math.acos(float(np.clip(abs(c @ z), 0.0, 1.0))))
    if angle < MIN_FORWARD_ANGLE_DEG:
        raise FlightDataError(
            f"{where}: {np.round(z, 4).tolist()} is {angle:.1f} deg from cam0's optical axis "
            f"(need >= {MIN_FORWARD_ANGLE_DEG:g} deg to define the forward axis)"
        )
    x = c - (c @ z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def to_flu_body(
    flight: Flight, thrust_axis_imu: Any = None, *, where: str = "thrust_axis"
) -> Flight:
    """Convert a flight whose body is EuRoC's IMU frame to the FLU multirotor body.

    The rotation is :func:`flu_R_imu` of ``flight.calib.body_T_cam`` and the thrust axis
    (default :data:`THRUST_AXIS_IMU`), applied by :func:`.frames.rotate_body_frame`. Records
    ``meta["body_frame"] = "flu"``, ``meta["body_from_imu"]`` (the 3x3 ``flu_R_imu`` as nested
    lists) and ``meta["thrust_axis_imu"]``.

    Raises:
        FlightDataError: no camera calibration (the forward axis comes from cam0), a bad thrust
            axis (naming ``where``), or a flight already converted.
    """
    if flight.calib.camera is None:
        raise FlightDataError(
            f"{flight.name}: the FLU body needs cam0's calibration (calib.body_T_cam and the "
            "camera; cam0/sensor.yaml or the manifest's [calib]) for its forward axis"
        )
    if flight.meta.get("body_frame", "imu") != "imu":
        raise FlightDataError(
            f"{flight.name}: body already converted ({flight.meta['body_frame']})"
        )
    axis = THRUST_AXIS_IMU if thrust_axis_imu is None else thrust_axis_imu
    R = flu_R_imu(flight.calib.body_T_cam, axis, where=where)
    out = rotate_body_frame(flight, R)
    meta = dict(flight.meta)
    meta["body_frame"] = "flu"
    meta["body_from_imu"] = R.tolist()
    meta["thrust_axis_imu"] = R[2].tolist()
    meta["thrust_axis_body"] = [0.0, 0.0, 1.0]
    return dataclasses.replace(out, meta=meta)


def read_euroc_folder(
    mav0_dir: str | Path, *, body: str = "imu", thrust_axis_imu: Any = None
) -> Flight:
    """Read an EuRoC/ASL ``mav0`` folder (or the sequence folder holding ``mav0``).

    Reads ``imu0`` (required), ``state_groundtruth_estimate0`` and ``cam0`` when present, with
    their ``sensor.yaml`` files (IMU noise, ``body_T_cam = inv(T_BS_imu0) * T_BS_cam0`` in the IMU
    frame, camera intrinsics). Reader notes go to ``meta["notes"]``.

    Args:
        mav0_dir: the folder.
        body: ``"imu"`` keeps the IMU frame as body; ``"flu"`` converts the flight to the FLU
            multirotor body (:func:`to_flu_body`, needs ``cam0``).
        thrust_axis_imu: thrust axis in the IMU frame for ``body="flu"`` (default
            :data:`THRUST_AXIS_IMU`).
    """
    if body not in BODY_FRAMES:
        raise FlightDataError(f"body = {body!r}; valid: {', '.join(BODY_FRAMES)}")
    root = Path(mav0_dir)
    if not root.is_dir():
        raise FlightFormatError(root, "folder not found")
    if (root / "mav0").is_dir():
        root = root / "mav0"
    imu_csv = root / "imu0" / "data.csv"
    if not imu_csv.is_file():
        raise FlightFormatError(root, "not an EuRoC mav0 folder (imu0/data.csv not found)")
    notes: list[str] = []
    sources: dict[str, str] = {"imu": str(imu_csv)}
    imu = read_euroc_imu(imu_csv, notes=notes)
    calib_kwargs: dict[str, Any] = {}
    imu_yaml = root / "imu0" / "sensor.yaml"
    B_T_imu = np.eye(4)
    if imu_yaml.is_file():
        d = _read_sensor_yaml(imu_yaml)
        calib_kwargs["imu_noise"] = _imu_noise(d, imu_yaml)
        B_T_imu = _T_BS(d, imu_yaml)
    gt = None
    gt_csv = root / "state_groundtruth_estimate0" / "data.csv"
    if gt_csv.is_file():
        gt = read_euroc_groundtruth(gt_csv, notes=notes)
        sources["ground_truth"] = str(gt_csv)
    images = None
    cam_csv = root / "cam0" / "data.csv"
    if cam_csv.is_file():
        cam_yaml = root / "cam0" / "sensor.yaml"
        camera = None
        if cam_yaml.is_file():
            d = _read_sensor_yaml(cam_yaml)
            camera = _camera(d, cam_yaml)
            calib_kwargs["camera"] = camera
            calib_kwargs["body_T_cam"] = invert_pose(B_T_imu) @ _T_BS(d, cam_yaml)
        else:
            raise FlightFormatError(cam_yaml, "file not found (cam0 intrinsics are needed)")
        images = read_euroc_images(cam_csv, camera, notes=notes)
        sources["images"] = str(cam_csv)
    name = root.parent.name if root.name == "mav0" else root.name
    flight = Flight(
        name=name,
        source=str(root),
        imu=imu,
        images=images,
        ground_truth=gt,
        calib=Calibration(**calib_kwargs),
        meta={
            "format": "euroc",
            "sources": sources,
            "notes": notes,
            "thrust_axis_body": list(map(float, THRUST_AXIS_IMU)),
        },
    )
    try:
        if body == "flu":
            flight = to_flu_body(flight, thrust_axis_imu)
        return flight.check()
    except FlightDataError as e:
        raise FlightFormatError(root, str(e)) from e
