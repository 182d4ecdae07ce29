"""fgnav's own flight folder format (in the spirit of EuRoC/ASL): plain text, one file per stream.

Layout of a flight folder::

    meta.json                  format name and version, flight name, source, streams, flight.meta
    calib.yaml                 body_T_cam, body_T_range, camera, IMU noise, range limits, offsets,
                               body_T_flow, flow_pixels_per_rad
    imu.csv                    t [s], omega_x..z [rad/s], accel_x..z [m/s^2]        (body FLU)
    attitude.csv               t [s], q_w, q_x, q_y, q_z                       (world_R_body)
    range.csv                  t [s], range [m] [, quality [-]]
    yaw.csv                    t [s], yaw [rad]                           (of world_R_body, ZYX)
    slam.csv                   t [s], x, y, z [slam], q_w..q_z, session [-] [, latency [s]]
    flow.csv                   t [s], dt [s], flow_x, flow_y [px] [, quality [-]] (sensor axes)
    ground_truth.csv           t [s], x, y, z [m], q_w..q_z [, v_x..v_z [m/s]]
                               [, bg_x..bg_z [rad/s]] [, ba_x..ba_z [m/s^2]]
    references/<name>.csv      same columns as ground_truth.csv
    images.csv                 t [s], file (relative to the folder)
    cam0/<t_ns>.png            images (named by integer-ns time)

Frames and units are those of :mod:`fgnav.datasets.types` (world z up, body FLU, SI, float
seconds). Each csv starts with a header naming its columns and units; optional column groups are
written only when the series has them. Floats are written with ``repr`` (shortest text that
reads back to the same float64), so ``read_flight(write_flight(f))`` reproduces every array
exactly. ``flight.meta`` goes to ``meta.json``: numpy arrays and tuples become lists, numpy scalars
Python numbers and dict keys strings (JSON has nothing else); anything else is an error.

An :class:`~fgnav.datasets.types.ImageSeries` held in memory (``frames``) is written as PNG files
(lossless); one held as files (``paths``) is copied. Read back, it has absolute ``paths``.

Reading checks, in order: the header of each csv (a missing or unknown column is an error naming
file and column), each value (non-numeric or non-finite -> error naming file, line and column),
time order (error naming the lines), then ``flight.check()``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import shutil
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from . import _tables
from ._files import file_number, read_text, read_yaml, resolved
from .errors import FlightDataError, FlightFormatError
from .types import (
    AttitudeSeries,
    Calibration,
    CameraIntrinsics,
    Flight,
    FlowSeries,
    ImageSeries,
    ImuNoise,
    ImuSeries,
    RangeSeries,
    SlamSeries,
    Trajectory,
    YawSeries,
    check_imu_interval,
)

log = logging.getLogger(__name__)

FORMAT_NAME = "fgnav-flight"
FORMAT_VERSION = 1
META_FILE = "meta.json"
CALIB_FILE = "calib.yaml"
IMAGES_DIR = "cam0"
REFERENCES_DIR = "references"


# ----------------------------------------------------------------------------------------------
# Column layout of each stream kind
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Group:
    """Columns of one dataclass field: its csv column names, unit and whether it is optional."""

    field: str
    columns: tuple[str, ...]
    unit: str
    optional: bool = False
    integer: bool = False


_XYZ = ("x", "y", "z")
_QUAT = ("q_w", "q_x", "q_y", "q_z")

_TRAJECTORY = (
    _Group("world_t_body", _XYZ, "m"),
    _Group("world_q_body_wxyz", _QUAT, "-"),
    _Group("world_v_body", ("v_x", "v_y", "v_z"), "m/s", optional=True),
    _Group("gyro_bias", ("bg_x", "bg_y", "bg_z"), "rad/s", optional=True),
    _Group("accel_bias", ("ba_x", "ba_y", "ba_z"), "m/s^2", optional=True),
)

LAYOUTS: dict[str, tuple[type, tuple[_Group, ...]]] = {
    "imu": (
        ImuSeries,
        (
            _Group("body_omega", ("omega_x", "omega_y", "omega_z"), "rad/s"),
            _Group("body_accel", ("accel_x", "accel_y", "accel_z"), "m/s^2"),
        ),
    ),
    "attitude": (AttitudeSeries, (_Group("world_q_body_wxyz", _QUAT, "-"),)),
    "range": (
        RangeSeries,
        (_Group("range", ("range",), "m"), _Group("quality", ("quality",), "-", optional=True)),
    ),
    "yaw": (YawSeries, (_Group("yaw", ("yaw",), "rad"),)),
    "slam": (
        SlamSeries,
        (
            _Group("slam_t_cam", _XYZ, "slam"),
            _Group("slam_q_cam_wxyz", _QUAT, "-"),
            _Group("session", ("session",), "-", integer=True),
            _Group("latency", ("latency",), "s", optional=True),
        ),
    ),
    "flow": (
        FlowSeries,
        (
            _Group("dt", ("dt",), "s"),
            _Group("flow", ("flow_x", "flow_y"), "px"),
            _Group("quality", ("quality",), "-", optional=True),
        ),
    ),
    "ground_truth": (Trajectory, _TRAJECTORY),
    "trajectory": (Trajectory, _TRAJECTORY),
}
"""Stream kind -> (series class, column groups after ``t [s]``)."""

_SCALAR_FIELDS = {"range", "quality", "yaw", "session", "latency", "dt"}


#: ``imu_noise`` keys a calibration file may leave out (their ``ImuNoise`` defaults).
OPTIONAL_NOISE_KEYS = frozenset({"gyro_bias_sigma", "rest_bias_removed"})
#: ``imu_noise`` keys that are flags (written and read as booleans, the others as numbers).
FLAG_NOISE_KEYS = frozenset({"rest_bias_removed"})


def _flag(v: Any, key: str, path: Path) -> bool:
    """A calibration flag read from YAML: a boolean (or 0 / 1), or an error naming the key."""
    if isinstance(v, bool) or (isinstance(v, int | float) and v in (0, 1)):
        return bool(v)
    raise FlightFormatError(path, f"{key}: expected a boolean, got {v!r}")


def _fmt(x: float) -> str:
    return repr(float(x))


# ----------------------------------------------------------------------------------------------
# One stream <-> one csv
# ----------------------------------------------------------------------------------------------


def write_stream_csv(series: Any, path: str | Path, kind: str) -> Path:
    """Write one series as a native csv (header with units, floats with ``repr``).

    Args:
        series: an ImuSeries, AttitudeSeries, RangeSeries, YawSeries, SlamSeries or Trajectory.
        path: output file.
        kind: its layout: ``"imu"``, ``"attitude"``, ``"range"``, ``"yaw"``, ``"slam"``,
            ``"ground_truth"`` or ``"trajectory"``.
    """
    cls, groups = LAYOUTS[kind]
    header = ["t [s]"]
    cols: list[np.ndarray] = [np.asarray(series.t, dtype=float).reshape(-1, 1)]
    integer_cols: set[int] = set()
    for g in groups:
        a = getattr(series, g.field)
        if a is None:
            continue
        a = np.asarray(a)
        a = a.reshape(-1, 1) if a.ndim == 1 else a
        for c in g.columns:
            if g.integer:
                integer_cols.add(len(header))
            header.append(f"{c} [{g.unit}]")
        cols.append(a)
    n = len(series.t)
    lines = [",".join(header)]
    for i in range(n):
        parts: list[str] = []
        for a in cols:
            parts.extend(str(int(v)) if a.dtype.kind in "iub" else _fmt(v) for v in a[i])
        lines.append(",".join(parts))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text("\n".join(lines) + "\n")
    return p


def read_stream_csv(path: str | Path, kind: str) -> Any:
    """Read one native csv written by :func:`write_stream_csv` and check it.

    Raises:
        FlightFormatError: missing/unknown column (naming it), non-numeric or non-finite value
            (naming line and column), time not strictly increasing (naming the lines).
    """
    fast = _read_stream_fast(path, kind)
    if fast is not None:
        return fast
    cls, groups = LAYOUTS[kind]
    raw = _tables.read_raw(path, sep=",", header="first")
    header = raw.header or []
    index = {name: j for j, name in enumerate(header)}
    if "t" not in index:
        raise FlightFormatError(raw.path, f"missing column 't [s]' in the header {raw.header_raw}")
    known = {"t"} | {c for g in groups for c in g.columns}
    unknown = [h for h in header if h not in known]
    bad = _wrong_units(raw.header_raw or [], kind)
    if bad:
        name, given, want = bad[0]
        raise FlightFormatError(
            raw.path,
            f"column '{name}' is in [{given}], expected [{want}]: native files are SI (seconds, "
            "m, m/s^2, rad/s, ...); convert the column",
            line=1,
        )
    if unknown:
        raise FlightFormatError(
            raw.path,
            f"unknown column(s) {unknown} in the header; expected t and "
            + ", ".join(f"{c} [{g.unit}]" for g in groups for c in g.columns)
            + " (optional groups may be absent)",
            line=1,
        )
    _tables.check_widths(raw, (len(header),), "as many as header columns")
    t = _tables.to_values(raw, [index["t"]])[:, 0]
    _tables.check_increasing(raw, t)
    kwargs: dict[str, Any] = {"t": t}
    for g in groups:
        present = [c for c in g.columns if c in index]
        if not present:
            if g.optional:
                continue
            raise FlightFormatError(
                raw.path, f"missing column '{g.columns[0]} [{g.unit}]' ({kind}.{g.field})", line=1
            )
        if len(present) != len(g.columns):
            missing = next(c for c in g.columns if c not in index)
            raise FlightFormatError(
                raw.path, f"missing column '{missing} [{g.unit}]' ({kind}.{g.field})", line=1
            )
        js = [index[c] for c in g.columns]
        if g.integer:
            a = _read_int_column(raw, js[0])
        else:
            a = _tables.to_values(raw, js)
            if g.field in _SCALAR_FIELDS:
                a = a[:, 0]
        kwargs[g.field] = a
    series = cls(**kwargs)
    try:
        series.check(kind)
    except FlightDataError as e:
        raise FlightFormatError(raw.path, str(e)) from e
    return series


def _fast_header(first: str, kind: str) -> dict[str, int] | None:
    """Column index of a header line that the fast path reads (None: the careful reader)."""
    _, groups = LAYOUTS[kind]
    raw_header = _tables.split_line(first.strip(), ",")
    header = [_tables.strip_unit(h) for h in raw_header]
    index = {name: j for j, name in enumerate(header)}
    known = {"t"} | {c for g in groups for c in g.columns}
    if "t" not in index or any(h not in known for h in header) or _wrong_units(raw_header, kind):
        return None
    return index


def _wrong_units(raw_header: list[str], kind: str) -> list[tuple[str, str, str]]:
    """``(column, its unit, the unit expected)`` of the header's columns whose stated unit is
    not fgnav's (a column without a unit is taken as fgnav's). Before, the units were
    stripped unread: g and deg/s were taken as m/s^2 and rad/s."""
    _, groups = LAYOUTS[kind]
    want = {"t": "s"} | {c: g.unit for g in groups for c in g.columns}
    out = []
    for h in raw_header:
        name, unit = _tables.strip_unit(h), _tables.unit_of(h)
        if not unit or name not in want:
            continue
        if _UNIT_ALIAS.get(_norm_unit(unit), _norm_unit(unit)) != _norm_unit(want[name]):
            out.append((name, unit, want[name]))
    return out


def _norm_unit(unit: str) -> str:
    return unit.replace(" ", "").lower()


#: Other spellings of fgnav's units in a header.
_UNIT_ALIAS = {"m/s2": "m/s^2", "m/s**2": "m/s^2", "sec": "s", "1": "-", "slamunits": "slam"}


def _loadtxt(source: Any, max_rows: int | None = None, header: bool = False) -> np.ndarray:
    """NumPy's C reader on a path or an open file (``header``: skip its first line); warnings
    (an empty file, odd lines) raise."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return np.loadtxt(
            source,
            delimiter=",",
            skiprows=1 if header else 0,
            ndmin=2,
            dtype=float,
            comments=None,
            max_rows=max_rows,
        )


def _fast_series(a: np.ndarray, index: dict[str, int], kind: str) -> Any | None:
    """The series of a parsed block (None when anything is unusual: see
    :func:`_read_stream_fast`)."""
    cls, groups = LAYOUTS[kind]
    if a.shape[0] == 0 or a.shape[1] != len(index) or not np.all(np.isfinite(a)):
        return None
    t = a[:, index["t"]]
    if np.any(np.diff(t) <= 0):
        return None
    kwargs: dict[str, Any] = {"t": t.copy()}
    for g in groups:
        present = [c for c in g.columns if c in index]
        if not present:
            if g.optional:
                continue
            return None
        if len(present) != len(g.columns):
            return None
        v = a[:, [index[c] for c in g.columns]]
        if g.integer:
            if np.any(v[:, 0] != np.round(v[:, 0])):
                return None
            v = v[:, 0].astype(np.int64)
        elif g.field in _SCALAR_FIELDS:
            v = v[:, 0].copy()
        kwargs[g.field] = v
    series = cls(**kwargs)
    try:
        series.check(kind)
    except FlightDataError:
        return None
    return series


def _read_stream_fast(path: str | Path, kind: str) -> Any | None:
    """The common case of :func:`read_stream_csv` in bounded memory: a well-formed file parsed
    by NumPy's C reader (a 1-hour 200 Hz IMU file: tens of MB instead of a Python string per
    value). None when anything is unusual (comments, blank or ragged lines, a non-number, NaN,
    non-increasing time, an unknown or missing column, a non-integer session): the careful
    reader then parses the file and names the line and column in its error."""
    p = Path(path)
    try:
        with p.open(encoding="utf-8-sig") as fh:
            index = _fast_header(fh.readline(), kind)
        if index is None:
            return None
        a = _loadtxt(p, header=True)
    except (OSError, ValueError, UnicodeDecodeError, UserWarning):
        return None
    return _fast_series(a, index, kind)


CHUNK_ROWS = 50_000
"""Rows per chunk of :func:`iter_stream_csv` (a 200 Hz IMU: about 4 minutes, 2.8 MB)."""


def iter_stream_csv(path: str | Path, kind: str, chunk_rows: int = CHUNK_ROWS) -> Iterator[Any]:
    """A native csv as consecutive series of at most ``chunk_rows`` samples, read as they are
    consumed (bounded memory for a long flight). A well-formed file is parsed block by block by
    NumPy's C reader, time checked to increase across blocks too; at the first block that is not,
    the careful reader (:func:`read_stream_csv`) reads the whole file: it raises the
    :class:`FlightFormatError` that names the line and column, or (a file that is only unusual:
    comments, blank lines) its series is yielded in chunks, then in memory whole.
    """
    p = Path(path)
    done = 0  # rows yielded so far
    t_last = -np.inf
    try:
        fh = p.open(encoding="utf-8-sig")
    except OSError as e:
        raise FlightFormatError(p, f"cannot read: {e.strerror or e}") from e
    with fh:
        index = _fast_header(fh.readline(), kind)
        while index is not None:
            try:
                a = _loadtxt(fh, max_rows=chunk_rows)
            except (ValueError, UnicodeDecodeError, UserWarning):
                break
            if a.shape[0] == 0:
                return
            s = _fast_series(a, index, kind)
            if s is None or s.t[0] <= t_last:
                break
            t_last = float(s.t[-1])
            done += len(s)
            yield s
            if a.shape[0] < chunk_rows:
                return
    whole = read_stream_csv(p, kind)  # raises for a bad file, naming the line
    for i in range(done, len(whole), chunk_rows):
        yield whole.select(np.arange(i, min(i + chunk_rows, len(whole))))


def count_rows(path: str | Path) -> int:
    """Data lines of a csv with a header line (newlines counted, no parsing)."""
    n = 0
    last = b"\n"
    with Path(path).open("rb") as fh:
        while block := fh.read(1 << 20):
            n += block.count(b"\n")
            last = block[-1:]
    return max(0, n - 1 + (last != b"\n"))


def _read_int_column(raw: _tables.RawTable, j: int) -> np.ndarray:
    out = np.empty(len(raw.rows), dtype=np.int64)
    for k, row in enumerate(raw.rows):
        try:
            out[k] = int(row[j])
        except ValueError:
            raise _tables.cell_error(raw, k, j, f"expected an integer, found {row[j]!r}") from None
    return out


# ----------------------------------------------------------------------------------------------
# Calibration <-> calib.yaml
# ----------------------------------------------------------------------------------------------


def _camera_to_dict(cam: CameraIntrinsics | None) -> dict[str, Any] | None:
    if cam is None:
        return None
    return {
        "fx": float(cam.fx),
        "fy": float(cam.fy),
        "cx": float(cam.cx),
        "cy": float(cam.cy),
        "width": int(cam.width),
        "height": int(cam.height),
        "distortion": [float(d) for d in cam.distortion],
    }


def _camera_from_dict(d: Any, path: Path, key: str) -> CameraIntrinsics | None:
    if d is None:
        return None
    fields = ("fx", "fy", "cx", "cy", "width", "height", "distortion")
    if not isinstance(d, Mapping):
        raise FlightFormatError(path, f"{key}: expected a mapping with keys {list(fields)}")
    missing = [f for f in fields if f not in d]
    unknown = [k for k in d if k not in fields]
    if missing or unknown:
        raise FlightFormatError(
            path, f"{key}: missing keys {missing}, unknown keys {unknown}; expected {list(fields)}"
        )
    size = {}
    for f in ("width", "height"):
        v = d[f]
        if (
            isinstance(v, bool)
            or not isinstance(v, int | float)
            or not math.isfinite(v)
            or v != int(v)
        ):
            raise FlightFormatError(path, f"{key}.{f}: expected an integer, got {v!r}")
        size[f] = int(v)
    dist = d["distortion"] if d["distortion"] is not None else []
    if not isinstance(dist, list | tuple):
        raise FlightFormatError(path, f"{key}.distortion: expected a list, got {dist!r}")
    return CameraIntrinsics(
        **{f: _number(d[f], f"{key}.{f}", path) for f in ("fx", "fy", "cx", "cy")},
        **size,
        distortion=tuple(_number(x, f"{key}.distortion", path) for x in dist),
    )


def calibration_to_dict(calib: Calibration) -> dict[str, Any]:
    """Calibration as plain YAML-able types (4x4 matrices as nested lists)."""
    return {
        "body_T_cam": np.asarray(calib.body_T_cam, dtype=float).tolist(),
        "body_T_range": np.asarray(calib.body_T_range, dtype=float).tolist(),
        "camera": _camera_to_dict(calib.camera),
        "imu_noise": {
            k: bool(v) if k in FLAG_NOISE_KEYS else float(v)
            for k, v in dataclasses.asdict(calib.imu_noise).items()
        },
        "range_min": float(calib.range_min),
        "range_max": float(calib.range_max),
        "time_offsets": {str(k): float(v) for k, v in calib.time_offsets.items()},
        "body_T_flow": np.asarray(calib.body_T_flow, dtype=float).tolist(),
        "flow_pixels_per_rad": float(calib.flow_pixels_per_rad),
        "flow_rate_gain": [float(x) for x in calib.flow_rate_gain],
    }


def _matrix(d: Mapping, key: str, path: Path) -> np.ndarray:
    try:
        T = np.asarray(d[key], dtype=float)
    except (TypeError, ValueError) as e:
        raise FlightFormatError(path, f"{key}: expected a 4x4 matrix of numbers ({e})") from e
    if T.shape != (4, 4):
        raise FlightFormatError(path, f"{key}: expected a 4x4 matrix, got shape {T.shape}")
    return T


def calibration_from_dict(d: Any, path: Path) -> Calibration:
    """Inverse of :func:`calibration_to_dict`; errors name the file and key. The flow keys
    (``body_T_flow``, ``flow_pixels_per_rad``, ``flow_rate_gain``) are optional (files written
    before the flow stream lack them; the defaults of :class:`Calibration` apply)."""
    keys = (
        "body_T_cam",
        "body_T_range",
        "camera",
        "imu_noise",
        "range_min",
        "range_max",
        "time_offsets",
    )
    optional = ("body_T_flow", "flow_pixels_per_rad", "flow_rate_gain", "images_camera")
    if not isinstance(d, Mapping):
        raise FlightFormatError(path, f"expected a mapping with keys {list(keys)}")
    missing = [k for k in keys if k not in d]
    unknown = [k for k in d if k not in keys and k not in optional]
    if missing or unknown:
        raise FlightFormatError(
            path, f"missing keys {missing}, unknown keys {unknown}; expected {list(keys)}"
        )
    noise_fields = [f.name for f in dataclasses.fields(ImuNoise)]
    noise = d["imu_noise"]
    if not isinstance(noise, Mapping) or not (
        set(noise) <= set(noise_fields) and set(noise_fields) - set(noise) <= OPTIONAL_NOISE_KEYS
    ):
        raise FlightFormatError(
            path,
            f"imu_noise: expected the keys {noise_fields} "
            f"({', '.join(sorted(OPTIONAL_NOISE_KEYS))} optional)",
        )
    flow: dict[str, Any] = {}
    if "body_T_flow" in d:
        flow["body_T_flow"] = _matrix(d, "body_T_flow", path)
    if "flow_pixels_per_rad" in d:
        flow["flow_pixels_per_rad"] = _number(d["flow_pixels_per_rad"], "flow_pixels_per_rad", path)
    if "flow_rate_gain" in d:
        gain = d["flow_rate_gain"]
        if not isinstance(gain, list | tuple) or len(gain) != 2:
            raise FlightFormatError(path, f"flow_rate_gain: expected [a, b], got {gain!r}")
        flow["flow_rate_gain"] = tuple(_number(x, "flow_rate_gain", path) for x in gain)
    offsets = d["time_offsets"] or {}
    if not isinstance(offsets, Mapping):
        raise FlightFormatError(path, f"time_offsets: expected a mapping, got {offsets!r}")
    calib = Calibration(
        body_T_cam=_matrix(d, "body_T_cam", path),
        body_T_range=_matrix(d, "body_T_range", path),
        camera=_camera_from_dict(d["camera"], path, "camera"),
        imu_noise=ImuNoise(
            **{
                k: _flag(v, f"imu_noise.{k}", path)
                if k in FLAG_NOISE_KEYS
                else _number(v, f"imu_noise.{k}", path)
                for k, v in noise.items()
            }
        ),
        range_min=_number(d["range_min"], "range_min", path),
        range_max=_number(d["range_max"], "range_max", path),
        time_offsets={str(k): _number(v, f"time_offsets.{k}", path) for k, v in offsets.items()},
        **flow,
    )
    try:
        return calib.check()
    except FlightDataError as e:
        raise FlightFormatError(path, str(e)) from None


def _number(v: Any, key: str, path: Path) -> float:
    """A calibration value as a float (:func:`file_number`; YAML's true/false is not one)."""
    if isinstance(v, bool):
        raise FlightFormatError(path, f"{key}: expected a number, got {v!r}")
    return file_number(v, key, path)


def read_calib_yaml(path: str | Path) -> Calibration:
    """Read a native ``calib.yaml`` (as written by :func:`write_flight`)."""
    p = Path(path)
    return calibration_from_dict(read_yaml(p), p)


# ----------------------------------------------------------------------------------------------
# meta.json
# ----------------------------------------------------------------------------------------------


def to_json_value(x: Any, where: str = "meta") -> Any:
    """Convert metadata to JSON types: dict keys -> str, tuples and numpy arrays -> lists, numpy
    scalars -> Python numbers, paths -> str, dataclasses -> dicts.

    Raises:
        FlightDataError: naming the entry (``meta["truth"]["k"]``) when a value has no JSON form.
    """
    if x is None or isinstance(x, bool | int | float | str):
        return x
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return to_json_value(x.tolist(), where)
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, Mapping):
        return {str(k): to_json_value(v, f"{where}[{k!r}]") for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [to_json_value(v, f"{where}[{i}]") for i, v in enumerate(x)]
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return to_json_value(dataclasses.asdict(x), where)
    raise FlightDataError(
        f"{where}: cannot store a {type(x).__name__} in meta.json (expected numbers, strings, "
        f"lists, dicts or numpy arrays)"
    )


# ----------------------------------------------------------------------------------------------
# Whole flight
# ----------------------------------------------------------------------------------------------

_STREAM_FILES = {
    "imu": "imu.csv",
    "attitude": "attitude.csv",
    "range": "range.csv",
    "yaw": "yaw.csv",
    "slam": "slam.csv",
    "flow": "flow.csv",
    "ground_truth": "ground_truth.csv",
}


def _image_name(t: float) -> str:
    return str(int(round(t * 1e9)))


def _write_images(images: ImageSeries, folder: Path) -> None:
    import cv2

    cam_dir = folder / IMAGES_DIR
    cam_dir.mkdir(exist_ok=True)
    names: list[str] = []
    for i, t in enumerate(images.t):
        stem = _image_name(float(t))
        if images.frames is not None:
            rel = f"{IMAGES_DIR}/{stem}.png"
            if not cv2.imwrite(str(folder / rel), np.asarray(images.frames[i])):
                raise FlightDataError(f"images.frames[{i}]: OpenCV could not write it as PNG")
        else:
            src = Path(images.paths[i])
            rel = f"{IMAGES_DIR}/{stem}{src.suffix}"
            dst = folder / rel
            if not src.is_file():
                raise FlightDataError(f"images.paths[{i}]: {src} does not exist")
            if src.resolve() != dst.resolve():
                shutil.copyfile(src, dst)
        names.append(rel)
    if len(set(names)) != len(names):
        raise FlightDataError("images.t: two image times round to the same nanosecond")
    lines = ["t [s],file"] + [f"{_fmt(t)},{n}" for t, n in zip(images.t, names, strict=True)]
    (folder / "images.csv").write_text("\n".join(lines) + "\n")


def _read_images(folder: Path, camera: CameraIntrinsics | None) -> ImageSeries:
    path = folder / "images.csv"
    raw = _tables.read_raw(path, sep=",", header="first")
    if raw.header != ["t", "file"]:
        raise FlightFormatError(path, f"expected the header 't [s],file', found {raw.header_raw}")
    _tables.check_widths(raw, (2,), "t, file")
    t = _tables.to_values(raw, [0])[:, 0]
    _tables.check_increasing(raw, t)
    paths = []
    for k, row in enumerate(raw.rows):
        p = resolved(folder / row[1], path, "image file", line=raw.lines[k])
        if not p.is_file():
            raise FlightFormatError(path, f"image file {p} not found", line=raw.lines[k])
        paths.append(p)
    return ImageSeries(t=t, paths=tuple(paths), camera=camera)


def _check_reference_name(name: str) -> None:
    if not name or "/" in name or "\\" in name or name.startswith("."):
        raise FlightDataError(f"references[{name!r}]: the name must be a plain file name")


def write_flight(flight: Flight, folder: str | Path, overwrite: bool = False) -> Path:
    """Write a flight as a native folder.

    Args:
        flight: the flight; it is checked first (a bad flight is not written).
        folder: output folder; created when missing.
        overwrite: allow writing into a non-empty folder (files of this format are replaced;
            other files are left alone).

    Returns:
        The folder.

    Raises:
        FlightDataError: the flight fails its checks, or meta holds a value without a JSON form.
        FileExistsError: the folder is not empty and ``overwrite`` is False.
    """
    flight.check()
    out = Path(folder)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{out}: folder is not empty (pass overwrite=True to replace)")
    out.mkdir(parents=True, exist_ok=True)
    meta_json = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "name": flight.name,
        "source": flight.source,
        "streams": [s for s in (*_STREAM_FILES, "images") if getattr(flight, s) is not None],
        "references": sorted(flight.references),
        "meta": to_json_value(flight.meta),
    }
    for stream, fname in _STREAM_FILES.items():
        series = getattr(flight, stream)
        if series is not None:
            write_stream_csv(series, out / fname, stream)
    for name, traj in flight.references.items():
        _check_reference_name(name)
        write_stream_csv(traj, out / REFERENCES_DIR / f"{name}.csv", "trajectory")
    calib = calibration_to_dict(flight.calib)
    if flight.images is not None:
        calib["images_camera"] = _camera_to_dict(flight.images.camera)
        _write_images(flight.images, out)
    (out / CALIB_FILE).write_text(yaml.safe_dump(calib, sort_keys=False))
    (out / META_FILE).write_text(json.dumps(meta_json, indent=1) + "\n")
    log.info("wrote flight %r to %s (%s)", flight.name, out, ", ".join(meta_json["streams"]))
    return out


def is_native_folder(path: str | Path) -> bool:
    """True when ``path`` is a folder holding a ``meta.json``."""
    p = Path(path)
    return p.is_dir() and (p / META_FILE).is_file()


#: Files of a native flight folder besides ``meta.json`` (:func:`lost_meta_json`).
NATIVE_FILES = (CALIB_FILE, *_STREAM_FILES.values(), "images.csv")


def lost_meta_json(path: str | Path) -> list[str]:
    """The native files of a folder that looks like a native flight folder but has no
    ``meta.json`` (it holds ``imu.csv``, or two of :data:`NATIVE_FILES`), in that order; empty
    for any other path (a folder with ``meta.json``, one without native files, a file)."""
    p = Path(path)
    if not p.is_dir() or (p / META_FILE).exists():
        return []
    have = [f for f in NATIVE_FILES if (p / f).is_file()]
    return have if "imu.csv" in have or len(have) >= 2 else []


def _str_list(v: Any) -> bool:
    return isinstance(v, list) and all(isinstance(x, str) for x in v)


def _short(v: Any) -> str:
    """A JSON value for an error line: ``json.dumps``, cut to 60 characters."""
    text = json.dumps(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _read_header(root: Path) -> tuple[dict[str, Any], Any, Calibration]:
    """``meta.json`` and ``calib.yaml`` of a native folder, checked: (meta, calib dict, calib)."""
    meta_path = root / META_FILE
    if not meta_path.is_file():
        raise FlightFormatError(root, f"not an fgnav flight folder ({META_FILE} not found)")
    try:
        meta = json.loads(read_text(meta_path, META_FILE))
    except json.JSONDecodeError as e:
        raise FlightFormatError(meta_path, f"not valid JSON: {e.msg}", line=e.lineno) from e
    required = ("format", "version", "name", "source", "streams", "references", "meta")
    if not isinstance(meta, dict) or any(k not in meta for k in required):
        raise FlightFormatError(meta_path, f"expected a JSON object with keys {list(required)}")
    if meta["format"] != FORMAT_NAME:
        raise FlightFormatError(
            meta_path, f"format is {meta['format']!r}, expected {FORMAT_NAME!r}"
        )
    if not isinstance(meta["version"], int) or meta["version"] > FORMAT_VERSION:
        raise FlightFormatError(
            meta_path,
            f"format version {meta['version']!r} is not supported (this fgnav reads up to "
            f"{FORMAT_VERSION})",
        )
    for key, kind, ok in (
        ("name", "a string", isinstance(meta["name"], str)),
        ("source", "a string", isinstance(meta["source"], str)),
        ("streams", "a list of stream names", _str_list(meta["streams"])),
        ("references", "a list of reference names", _str_list(meta["references"])),
        ("meta", "an object", isinstance(meta["meta"], dict)),
    ):
        if not ok:
            raise FlightFormatError(
                meta_path, f'"{key}": expected {kind}, found {_short(meta[key])}'
            )
    valid = (*_STREAM_FILES, "images")
    unknown = [s for s in meta["streams"] if s not in valid]
    if unknown:
        raise FlightFormatError(meta_path, f"unknown streams {unknown}; valid: {list(valid)}")
    calib_path = root / CALIB_FILE
    calib_dict = read_yaml(calib_path)
    calib = calibration_from_dict(calib_dict, calib_path)
    return meta, calib_dict, calib


def read_flight(folder: str | Path) -> Flight:
    """Read a native flight folder written by :func:`write_flight`.

    Raises:
        FlightFormatError: naming the file (and line/column) of the first problem found.
        FlightDataError: the assembled flight fails ``flight.check()``.
    """
    root = Path(folder)
    meta, calib_dict, calib = _read_header(root)
    calib_path = root / CALIB_FILE
    streams: dict[str, Any] = {}
    for s in meta["streams"]:
        if s == "images":
            cam = _camera_from_dict(calib_dict.get("images_camera"), calib_path, "images_camera")
            streams[s] = _read_images(root, cam)
        else:
            streams[s] = read_stream_csv(root / _STREAM_FILES[s], s)
    references = {
        name: read_stream_csv(root / REFERENCES_DIR / f"{name}.csv", "trajectory")
        for name in meta["references"]
    }
    flight = Flight(
        name=meta["name"],
        source=meta["source"],
        references=references,
        calib=calib,
        meta=meta["meta"],
        **streams,
    )
    return flight.check()


@dataclass
class FlightStreams:
    """A native flight folder opened as streams, for a run in bounded memory.

    ``outline`` is the flight with each sample stream cut to its first and last sample: the
    calibration, metadata, which streams there are and their time spans, for the checks before a
    run (never an estimator's input; no ground truth nor references). ``events(names)`` reads the
    named streams' files in chunks (:func:`iter_stream_csv`) and merges their events in arrival
    order; ``counts`` has the samples per stream (newlines counted).
    """

    outline: Flight
    files: dict[str, Path]
    counts: dict[str, int]
    chunk_rows: int = CHUNK_ROWS
    root: Path | None = None
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)  # the folder's meta.json

    def scoring_flight(self) -> Flight:
        """The outline with the ground truth and the references read (whole): what scoring
        and the coverage lines read, after the run."""
        meta = self.meta
        gt = None
        if "ground_truth" in meta["streams"]:
            gt = read_stream_csv(self.root / _STREAM_FILES["ground_truth"], "ground_truth")
        references = {
            name: read_stream_csv(self.root / REFERENCES_DIR / f"{name}.csv", "trajectory")
            for name in meta["references"]
        }
        return dataclasses.replace(self.outline, ground_truth=gt, references=references)

    def events(self, names: Any = None) -> Iterator[Any]:
        from .events import EVENT_STREAMS, chunked_events, replay

        names = [n for n in (names or EVENT_STREAMS) if n in self.files]
        return replay(
            {
                n: chunked_events(iter_stream_csv(self.files[n], n, self.chunk_rows), n)
                for n in names
            }
        )


#: Streams :func:`open_flight_streams` reads in chunks (a folder with images is read whole).
STREAMED = ("imu", "attitude", "range", "yaw", "slam", "flow")


def open_flight_streams(folder: str | Path, chunk_rows: int = CHUNK_ROWS) -> FlightStreams:
    """Open a native folder without reading its samples (see :class:`FlightStreams`).

    Raises:
        FlightFormatError: a bad ``meta.json``/``calib.yaml``, a stream file missing or unreadable,
            or a folder with images (read those with :func:`read_flight`).
    """
    root = Path(folder)
    meta, _, calib = _read_header(root)
    if "images" in meta["streams"]:
        raise FlightFormatError(root, "has images: it cannot be opened as streams; read it whole")
    files: dict[str, Path] = {}
    outline: dict[str, Any] = {}
    counts: dict[str, int] = {}
    for name in meta["streams"]:
        if name not in STREAMED:
            continue
        path = root / _STREAM_FILES[name]
        if not path.is_file():
            raise FlightFormatError(path, "file not found")
        first = next(iter_stream_csv(path, name, chunk_rows=1), None)
        if first is None:
            raise FlightFormatError(path, "no samples")
        counts[name] = count_rows(path)
        last = _last_sample(path, name)
        if last is None:
            # The last line does not parse on its own (cut in the middle, text, or a header the
            # fast path does not know): the whole read names a bad line (file:line) and
            # otherwise gives the true last sample. The first sample alone would give the
            # stream a zero span and a misleading "do not overlap" error.
            last = read_stream_csv(path, name)
        outline[name] = _ends(first, last)
        files[name] = path
    if "imu" in outline and counts["imu"] > 1:
        imu_t = outline["imu"].t
        try:
            check_imu_interval(
                f"{meta['name']}.imu", (imu_t[-1] - imu_t[0]) / (counts["imu"] - 1), "mean"
            )
        except FlightDataError as e:  # (the online replay of ns stamps stepped for ever)
            raise FlightFormatError(files["imu"], str(e)) from e
    flight = Flight(
        name=meta["name"], source=meta["source"], calib=calib, meta=meta["meta"], **outline
    )
    return FlightStreams(flight.check(), files, counts, chunk_rows, root, meta)


def _last_sample(path: Path, kind: str) -> Any | None:
    """The series of the file's last line alone (None when it does not parse on its own)."""
    with path.open("rb") as fh:
        header = fh.readline().decode("utf-8-sig")
        fh.seek(0, 2)
        size = fh.tell()
        fh.seek(max(0, size - 4096))
        tail = fh.read().decode("utf-8", errors="replace").strip().splitlines()
    index = _fast_header(header, kind)
    if not tail or index is None:
        return None
    import io

    try:
        a = _loadtxt(io.StringIO(tail[-1]), max_rows=1)
    except (ValueError, UserWarning):
        return None
    return _fast_series(a, index, kind)


def _ends(first: Any, last: Any) -> Any:
    """A series of ``first``'s first sample and ``last``'s last one."""
    a = first.select(np.array([0]))
    b = last.select(np.array([len(last) - 1]))
    if b.t[0] <= a.t[0]:
        return a
    fields = {f.name: getattr(a, f.name) for f in dataclasses.fields(a)}
    for k, v in fields.items():
        if isinstance(v, np.ndarray):
            fields[k] = np.concatenate([v, getattr(b, k)])
    return type(a)(**fields)
