"""ORB-SLAM3 settings files (OpenCV-style YAML) -> :class:`~fgnav.datasets.types.Calibration`.

ORB-SLAM3 reads its settings with OpenCV's ``FileStorage``: a ``%YAML:1.0`` first line (not valid
YAML 1.1: PyYAML rejects the colon) and matrices tagged ``!!opencv-matrix`` with ``rows``, ``cols``,
``dt`` and row-major ``data``. This reader drops the directive, drops the tag, and parses the rest
with ``yaml.safe_load``.

Keys read (settings format ``File.version: "1.0"``, older names accepted in brackets):

- ``Camera.type``: must be ``PinHole`` (``KannalaBrandt8`` fisheye is not modelled by
  :class:`CameraIntrinsics` and is refused).
- ``Camera1.fx, fy, cx, cy`` [px] and ``Camera1.k1, k2, p1, p2[, k3]`` (``Camera.fx`` ...):
  pinhole with OpenCV radial-tangential distortion.
- ``Camera.width``, ``Camera.height`` [px].
- ``IMU.T_b_c1`` (``Tbc``): 4x4 pose of camera 1 in the IMU frame, i.e. ``body_T_cam`` with
  fgnav's body = the IMU frame of the file. For EuRoC that IMU frame is about x up, y right,
  z forward, not FLU (see :mod:`fgnav.datasets.euroc`); the matrix is used as it is.
- ``IMU.NoiseGyro`` [rad/s/sqrt(Hz)], ``IMU.NoiseAcc`` [m/s^2/sqrt(Hz)], ``IMU.GyroWalk``
  [rad/s^2/sqrt(Hz)], ``IMU.AccWalk`` [m/s^3/sqrt(Hz)]: continuous-time densities, as ImuNoise.

A file without any ``IMU.*`` noise key (a monocular-only configuration) keeps ImuNoise's defaults,
and one without ``IMU.T_b_c1`` keeps ``body_T_cam`` = identity; both cases are logged and noted.
A file with only some of the four noise keys, a missing camera key, or a malformed matrix is an
error naming the file and key. A ``T_b_c1`` rotation that is orthonormal only to the printed
digits (|R R^T - I| up to :data:`ORTHO_REPAIR_TOL`) is projected onto SO(3) by SVD (and noted).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ._files import existing_file, file_count, file_number, read_text, yaml_error
from .errors import FlightDataError, FlightFormatError, note
from .types import Calibration, CameraIntrinsics, ImuNoise, imu_noise_problem

log = logging.getLogger(__name__)

ORTHO_REPAIR_TOL = 1e-4
"""Largest |R R^T - I| of a printed rotation that is silently-but-noted re-orthonormalised; above
it the matrix is refused (it is not a rotation written with too few digits)."""

ORTHO_OK_TOL = 1e-9
"""Rotations closer than this to orthonormal are used exactly as written."""

_NOISE_KEYS = {
    "gyro_noise_density": "IMU.NoiseGyro",
    "accel_noise_density": "IMU.NoiseAcc",
    "gyro_random_walk": "IMU.GyroWalk",
    "accel_random_walk": "IMU.AccWalk",
}

_OPENCV_TAG = re.compile(r"!!opencv-(matrix|nd-matrix)")


def load_opencv_yaml(path: str | Path) -> dict[str, Any]:
    """Parse an OpenCV ``FileStorage`` YAML file into a dict (matrices stay ``{rows, cols, dt,
    data}`` mappings).

    Raises:
        FlightFormatError: missing file or invalid YAML, naming file and line.
    """
    p = existing_file(path, "calibration file")
    # A UTF-8 byte-order mark (some editors write one) hid the %YAML directive below.
    lines = read_text(p, "calibration file").removeprefix("\ufeff").splitlines()
    # Keep line numbers: blank out the directive instead of deleting it.
    lines = ["" if ln.lstrip().startswith("%YAML") else ln for ln in lines]
    text = _OPENCV_TAG.sub("", "\n".join(lines))
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise yaml_error(p, e) from None
    if not isinstance(d, dict):
        raise FlightFormatError(p, "expected a YAML mapping of settings")
    return d


def _first(d: dict[str, Any], keys: tuple[str, ...], path: Path, required: bool = True) -> Any:
    for k in keys:
        if k in d:
            return d[k]
    if required:
        raise FlightFormatError(
            path,
            f"missing key {keys[0]!r}"
            + (f" (or {', '.join(repr(k) for k in keys[1:])})" if len(keys) > 1 else ""),
        )
    return None


def opencv_matrix(value: Any, key: str, path: str | Path) -> np.ndarray:
    """An ``!!opencv-matrix`` mapping (``rows``, ``cols``, ``data``) -> (rows, cols) array."""
    p = Path(path)
    if not isinstance(value, dict) or not {"rows", "cols", "data"} <= set(value):
        raise FlightFormatError(p, f"{key}: expected an opencv-matrix with rows, cols and data")
    rows = file_count(value["rows"], f"{key}.rows", p)
    cols = file_count(value["cols"], f"{key}.cols", p)
    try:
        a = np.asarray(value["data"], dtype=float)
    except (TypeError, ValueError) as e:
        raise FlightFormatError(p, f"{key}.data: {e}") from e
    if a.size != rows * cols:
        raise FlightFormatError(p, f"{key}: {a.size} values in data for a {rows}x{cols} matrix")
    return a.reshape(rows, cols)


def read_orbslam3_yaml(path: str | Path, *, notes: list[str] | None = None) -> Calibration:
    """Read camera intrinsics, ``body_T_cam`` and IMU noise from an ORB-SLAM3 settings file.

    Args:
        path: the ``.yaml`` file (e.g. ORB-SLAM3's ``Examples/Monocular-Inertial/EuRoC.yaml``).
        notes: list to which reader notes (defaults used, repaired rotation) are appended.

    Returns:
        Calibration with ``camera``, ``body_T_cam`` (camera -> IMU body, 4x4, metres) and
        ``imu_noise``; the rangefinder fields keep their defaults.

    Raises:
        FlightFormatError: naming the file and the key that is missing or malformed.
    """
    p = Path(path)
    d = load_opencv_yaml(p)
    cam_type = d.get("Camera.type", "PinHole")
    if cam_type != "PinHole":
        raise FlightFormatError(
            p,
            f"Camera.type {cam_type!r} is not supported: fgnav's CameraIntrinsics is a pinhole "
            "with radial-tangential distortion (Camera.type 'PinHole')",
        )
    intr = {}
    for name in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"):
        keys = (f"Camera1.{name}", f"Camera.{name}")
        intr[name] = file_number(_first(d, keys, p), keys[0], p)
    k3 = _first(d, ("Camera1.k3", "Camera.k3"), p, required=False)
    dist = [intr["k1"], intr["k2"], intr["p1"], intr["p2"]]
    if k3 is not None:
        dist.append(file_number(k3, "Camera1.k3", p))
    width = file_count(_first(d, ("Camera.width",), p), "Camera.width", p)
    height = file_count(_first(d, ("Camera.height",), p), "Camera.height", p)
    try:
        camera = CameraIntrinsics(
            intr["fx"], intr["fy"], intr["cx"], intr["cy"], width, height, tuple(dist)
        ).check("camera (Camera1.fx/fy/cx/cy, Camera.width/height)")
    except FlightDataError as e:
        raise FlightFormatError(p, str(e)) from e

    present = {k: v for k, v in _NOISE_KEYS.items() if v in d}
    if not present:
        imu_noise = ImuNoise()
        note(
            log,
            notes,
            f"{p}: no IMU noise keys ({', '.join(_NOISE_KEYS.values())}); "
            f"using fgnav's defaults {imu_noise}",
        )
    elif len(present) < len(_NOISE_KEYS):
        missing = [v for v in _NOISE_KEYS.values() if v not in d]
        raise FlightFormatError(p, f"missing IMU noise key(s) {missing} (all four or none)")
    else:
        values = {k: file_number(d[v], v, p) for k, v in _NOISE_KEYS.items()}
        for k, v in _NOISE_KEYS.items():
            problem = imu_noise_problem(k, values[k])
            if problem is not None:
                raise FlightFormatError(p, f"{v}: {problem}, got {values[k]}")
        imu_noise = ImuNoise(**values)

    T_raw = _first(d, ("IMU.T_b_c1", "Tbc"), p, required=False)
    T_key = "IMU.T_b_c1" if "IMU.T_b_c1" in d else "Tbc"
    if T_raw is None:
        body_T_cam = np.eye(4)
        note(log, notes, f"{p}: no IMU.T_b_c1; body_T_cam set to identity")
    else:
        body_T_cam = opencv_matrix(T_raw, T_key, p)
        if body_T_cam.shape != (4, 4):
            raise FlightFormatError(p, f"{T_key}: expected 4x4, got {body_T_cam.shape}")
        body_T_cam = _repair_rotation(body_T_cam, p, notes)
    calib = Calibration(body_T_cam=body_T_cam, camera=camera, imu_noise=imu_noise)
    try:
        return calib.check("calibration")
    except FlightDataError as e:  # the fields above are checked: what is left is IMU.T_b_c1's
        raise FlightFormatError(p, str(e).replace("calibration.body_T_cam", T_key)) from e


def _repair_rotation(T: np.ndarray, path: Path, notes: list[str] | None) -> np.ndarray:
    R = T[:3, :3]
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err <= ORTHO_OK_TOL or err > ORTHO_REPAIR_TOL or np.linalg.det(R) <= 0:
        return T
    U, _, Vt = np.linalg.svd(R)
    out = T.copy()
    out[:3, :3] = U @ Vt
    msg = (
        f"{path}: IMU.T_b_c1 rotation orthonormal only to {err:.1e} (printed digits); "
        f"projected onto SO(3)"
    )
    note(log, notes, msg, logging.INFO)
    return out
