"""Flight manifests: one TOML file assembling a flight from separate files of different formats.

Example (``datasets/manifests/euroc_mh01_orbslam3.toml``)::

    name = "MH_01_easy + ORB-SLAM3 mono"
    root = "../../../shared/data/real/euroc_MH_01_easy"   # relative to this file

    [imu]
    format = "euroc"
    path = "imu0/data.cleaned.csv"

    [slam]
    format = "tum_slam"
    path = "orbslam3_mono_runA/f_dataset-MH01_mono.txt"

    [ground_truth]
    format = "tum"
    path = "groundtruth/MH_01_easy.txt"

    [calib]
    format = "orbslam3_yaml"
    path = "calib/EuRoC.yaml"

    [references.rpg_vio_mono]
    format = "tum"
    path = "rpg_vio_mono/stamped_traj_estimate.txt"

    [body]
    frame = "imu"   # or "flu"

Top-level keys: ``name`` (required), ``root`` (folder the ``path`` values are relative to; itself
relative to the manifest's folder; default: the manifest's folder), ``source`` (free text), and
the tables in :data:`TABLE_FORMATS` plus ``[references.<name>]`` (trajectories recorded beside the
flight, e.g. another estimator's output; they become baseline rows), ``[meta]`` (free metadata
copied into ``flight.meta["manifest_meta"]``) and ``[body]``.

``[body]`` (optional) chooses the body frame: ``frame = "imu"`` (the default) keeps the streams'
body as read; ``frame = "flu"`` (needs ``[imu] format = "euroc"`` and ``[calib]``) converts EuRoC's
IMU frame to the FLU multirotor body (:func:`.euroc.to_flu_body`: z along the thrust axis, x toward
cam0's optical axis, same origin), rotating the IMU, attitude, ground truth, references (taken as
IMU-frame body trajectories, as rpg_vio_mono's) and ``body_T_cam``; SLAM camera poses stay.
``thrust_axis = [x, y, z]`` (IMU frame, optional) replaces :data:`.euroc.THRUST_AXIS_IMU`. The
rotation goes to ``flight.meta["body_from_imu"]``. With ``frame = "imu"``, ``thrust_axis`` is only
recorded (``flight.meta["thrust_axis_body"]``, normalised): the filter baselines whose models need
a multirotor body run in one with z along it (:func:`.frames.thrust_body_rotation`).

Keys of a stream table: ``format`` and ``path`` (required), ``time_offset_s`` (added to the
stream's times to put it on the flight's clock; recorded in ``calib.time_offsets``), and per
format: ``session`` (``tum_slam``: map id of its poses), ``time_unit`` (``tum``, ``tum_slam``:
``"auto"``, ``"s"``, ``"ns"``), ``stream`` (``ulog``: which stream of the log's flight to take,
default the table's name, ``ref:<name>`` for ``[references.<name>]``, e.g. ``"ref:px4_ekf2"``;
``crazyflie`` takes the same key, e.g. ``[references.vicon] stream = "ground_truth"``, and
``check_crc``: ``false`` salvages a damaged log, see :func:`.crazyflie.decode_crazyflie_log`) and
``topic`` (``rosbag``, required: the topic of this stream); ``[slam]`` also takes
``slam_rotation`` (``"auto"``, ``"as-is"``, ``"inverse"``) and ``slam_time_offset`` (``"report"``,
``"apply"`` or seconds): this file's SLAM-vs-gyro options (:mod:`.slam_gyro`), which win over a
config's ``[graph]`` table (they go to ``flight.meta["slam_options"]``). A log read by several
tables is read once (ULog, Crazyflie) or once per topic (bags); ``[calib] format = "ulog"`` takes
the log's calibration (rangefinder pose and limits from PX4 parameters), ``[calib] format =
"crazyflie"`` the Crazyflie reader's (:func:`.crazyflie.crazyflie_calibration`); ``[calib] format
= "native"`` (a ``calib.yaml``) sets every calibration value yourself, flow sensor included;
``[calib.imu_noise]`` (any of :class:`.types.ImuNoise`'s fields) replaces the calibration file's
IMU noise values, e.g. with densities measured in flight where the file has the sensor's at rest
(the EuRoC manifests: ``scripts/euroc_imu_noise.py``).
``[flow]`` (``crazyflie``, ``ulog`` or ``native_csv``) is the optical-flow stream. Unknown keys,
tables and formats are errors naming the manifest, table and key and listing the valid ones; a
missing file is an error naming the resolved path.
Reader notes (skipped lines, detected time units) go to ``flight.meta["notes"]``; a whole log's
per-stream summaries that hold counts (samples skipped by reason, kept outside limits) go to
``flight.meta["[<table>] <key>"]`` (``<table>``: the first table that read the log, ``<key>``:
the log reader's ``meta`` key), where ``fgnav info`` finds them.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ._files import read_toml, resolved
from .calib_yaml import read_orbslam3_yaml
from .errors import FlightDataError, FlightFormatError
from .euroc import (
    BODY_FRAMES,
    read_euroc_groundtruth,
    read_euroc_images,
    read_euroc_imu,
    to_flu_body,
)
from .load import lazy_reader
from .native import read_calib_yaml, read_stream_csv
from .slam_gyro import SlamConventionError, check_modes
from .tum import TIME_UNITS, read_tum, read_tum_slam
from .types import Calibration, Flight, ImuNoise, imu_noise_problem

log = logging.getLogger(__name__)

TABLE_FORMATS: dict[str, tuple[str, ...]] = {
    "imu": ("euroc", "native_csv", "ulog", "rosbag", "crazyflie"),
    "attitude": ("native_csv", "ulog", "rosbag"),
    "range": ("native_csv", "ulog", "rosbag", "crazyflie"),
    "yaw": ("native_csv", "ulog"),
    "slam": ("tum_slam", "native_csv", "rosbag"),
    "images": ("euroc", "rosbag"),
    "flow": ("native_csv", "crazyflie", "ulog"),
    "ground_truth": ("tum", "euroc", "native_csv", "ulog", "rosbag", "crazyflie"),
    "calib": ("orbslam3_yaml", "native", "ulog", "crazyflie"),
}
"""Stream tables and the formats each accepts (``[references.<name>]`` takes those of
``ground_truth``)."""

TOP_LEVEL_KEYS = ("name", "root", "source", "references", "meta", "body", *TABLE_FORMATS)

BODY_KEYS = ("frame", "thrust_axis")
"""Keys of the ``[body]`` table (see the module docstring)."""

_COMMON_KEYS = ("format", "path", "time_offset_s")
SLAM_OPTION_KEYS = ("slam_rotation", "slam_time_offset")
"""Keys of ``[slam]`` that set the graph's SLAM-vs-gyro options for this file (they win over the
``[graph]`` table of a config; see :mod:`.slam_gyro`)."""
_FORMAT_KEYS: dict[str, tuple[str, ...]] = {
    "tum": ("time_unit",),
    "tum_slam": ("time_unit", "session"),
    "ulog": ("stream",),
    "crazyflie": ("stream", "check_crc"),
    "rosbag": ("topic",),
}
LOG_FORMATS = ("ulog", "crazyflie", "rosbag")
"""Formats whose file is a whole flight log (read once per manifest, the table's stream taken)."""


def _check_table(manifest: Path, table: str, spec: Any, formats: tuple[str, ...]) -> str:
    if not isinstance(spec, dict):
        raise FlightFormatError(manifest, f"[{table}] must be a table with format and path")
    fmt = spec.get("format")
    if fmt not in formats:
        raise FlightFormatError(
            manifest,
            f"[{table}] format = {fmt!r} is not supported; valid: {', '.join(formats)}",
        )
    if table == "calib":
        valid = ("format", "path", "imu_noise")
        if fmt in ("ulog", "crazyflie"):
            valid += ("stream",)
        if fmt == "crazyflie":
            valid += ("check_crc",)
    else:
        valid = _COMMON_KEYS + _FORMAT_KEYS.get(fmt, ())
        if table == "slam":
            valid += SLAM_OPTION_KEYS
    unknown = [k for k in spec if k not in valid]
    if unknown:
        raise FlightFormatError(
            manifest,
            f"[{table}] unknown key(s) {unknown} for format {fmt!r}; valid: {', '.join(valid)}",
        )
    if "path" not in spec or not isinstance(spec["path"], str):
        raise FlightFormatError(manifest, f"[{table}] path: required (a file path string)")
    if "time_unit" in spec and spec["time_unit"] not in TIME_UNITS:
        raise FlightFormatError(
            manifest, f"[{table}] time_unit = {spec['time_unit']!r}; valid: {', '.join(TIME_UNITS)}"
        )
    off = spec.get("time_offset_s", 0.0)
    if isinstance(off, bool) or not isinstance(off, int | float) or not math.isfinite(off):
        # (true was taken as 1 s, nan failed later naming the stream's first sample)
        raise FlightFormatError(
            manifest, f"[{table}] time_offset_s = {off!r}: expected a finite number of seconds"
        )
    if "session" in spec and not isinstance(spec["session"], int):
        raise FlightFormatError(manifest, f"[{table}] session: expected an integer map id")
    for key in ("stream", "topic"):
        if key in spec and not isinstance(spec[key], str):
            raise FlightFormatError(manifest, f"[{table}] {key}: expected a string")
    if table == "slam":
        try:
            check_modes(
                spec.get("slam_rotation", "auto"), spec.get("slam_time_offset", "report"), "[slam]"
            )
        except SlamConventionError as e:
            raise FlightFormatError(manifest, str(e)) from e
    if fmt == "rosbag" and "topic" not in spec:
        raise FlightFormatError(manifest, f"[{table}] topic: required for format 'rosbag'")
    return fmt


def _imu_noise_override(manifest: Path, base: ImuNoise, spec: Any) -> ImuNoise:
    """``[calib.imu_noise]``: the calibration file's IMU noise with the given fields replaced
    (e.g. densities measured in flight where the file has the sensor's values at rest)."""
    fields = [f.name for f in dataclasses.fields(ImuNoise)]
    if not isinstance(spec, dict):
        raise FlightFormatError(
            manifest, f"[calib.imu_noise] must be a table of {', '.join(fields)}"
        )
    unknown = [k for k in spec if k not in fields]
    if unknown:
        raise FlightFormatError(
            manifest, f"[calib.imu_noise] unknown key(s) {unknown}; valid: {', '.join(fields)}"
        )
    flags = {f.name for f in dataclasses.fields(ImuNoise) if f.type in (bool, "bool")}
    out: dict[str, Any] = {}
    for k, v in spec.items():
        if k in flags:
            if not isinstance(v, bool):
                raise FlightFormatError(
                    manifest, f"[calib.imu_noise] {k}: expected true or false (found {v!r})"
                )
            out[k] = v
            continue
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise FlightFormatError(
                manifest, f"[calib.imu_noise] {k}: expected a number > 0 (found {v!r})"
            )
        problem = imu_noise_problem(k, v)
        if problem is None and not v > 0:
            problem = "expected a number > 0"
        if problem is not None:
            raise FlightFormatError(manifest, f"[calib.imu_noise] {k}: {problem} (found {v!r})")
        out[k] = float(v)
    return dataclasses.replace(base, **out)


def _check_body(manifest: Path, doc: dict[str, Any]) -> dict[str, Any]:
    """The ``[body]`` table, checked (``{}`` when absent or ``frame = "imu"``)."""
    spec = doc.get("body")
    if spec is None:
        return {}
    if not isinstance(spec, dict):
        raise FlightFormatError(manifest, "[body] must be a table (frame, thrust_axis)")
    unknown = [k for k in spec if k not in BODY_KEYS]
    if unknown:
        raise FlightFormatError(
            manifest, f"[body] unknown key(s) {unknown}; valid: {', '.join(BODY_KEYS)}"
        )
    frame = spec.get("frame", "imu")
    if frame not in BODY_FRAMES:
        raise FlightFormatError(
            manifest, f"[body] frame = {frame!r}; valid: {', '.join(BODY_FRAMES)}"
        )
    axis = spec.get("thrust_axis")
    if axis is not None and (
        not isinstance(axis, list)
        or len(axis) != 3
        or not all(
            isinstance(a, int | float) and not isinstance(a, bool) and math.isfinite(a)
            for a in axis
        )
        or not any(axis)
    ):
        raise FlightFormatError(
            manifest,
            f"[body] thrust_axis: expected 3 numbers (finite, not all 0; IMU frame), got {axis!r}",
        )
    if frame == "imu":
        # The body stays; a given thrust axis is recorded for filters that need a thrust body.
        return {} if axis is None else {"frame": "imu", "thrust_axis": axis}
    imu = doc.get("imu")
    if not isinstance(imu, dict) or imu.get("format") != "euroc":
        raise FlightFormatError(
            manifest,
            '[body] frame = "flu" converts EuRoC\'s IMU frame: needs [imu] format = "euroc"',
        )
    if "calib" not in doc:
        raise FlightFormatError(
            manifest, '[body] frame = "flu" needs [calib] (cam0\'s body_T_cam gives body x)'
        )
    return {"frame": frame, "thrust_axis": axis}


def _resolve(manifest: Path, root: Path, table: str, rel: str) -> Path:
    p = resolved(root / rel, manifest, f"[{table}] path")
    if not p.exists():
        raise FlightFormatError(manifest, f"[{table}] path: {p} not found")
    return p


def _has_counts(d: dict[Any, Any], depth: int = 0) -> bool:
    """Whether a reader's summary holds a skip count (``skipped`` in the key) or a count of
    samples kept outside limits (``*_kept``), at most two levels down."""
    for k, v in d.items():
        if isinstance(v, dict):
            if depth < 1 and _has_counts(v, depth + 1):
                return True
        elif "skipped" in str(k) or str(k).endswith("_kept"):
            return True
    return False


class _LogRef(NamedTuple):
    """One manifest table's view of a whole log: its format, file, table name, the stream it
    takes, the bag topic and (Crazyflie) whether the CRC must match."""

    fmt: str
    path: Path
    table: str
    stream: str
    topic: str | None = None
    check_crc: bool = True


class _LogCache:
    """Whole-log readers (ULog, ROS bags) return a Flight; each is read once per manifest and the
    table's stream taken from it. Their notes are added once, prefixed with the table."""

    def __init__(self, manifest: Path) -> None:
        self.manifest = manifest
        self.flights: dict[tuple[str, str, str, bool], Flight] = {}
        self.counts: dict[str, Any] = {}
        """The logs' per-stream summaries that hold counts (samples skipped by reason, kept
        outside limits), as ``"[table] key"`` -> the log reader's ``meta[key]`` (``fgnav info``
        and the runs' "reader skipped" line print them)."""

    def get(self, ref: _LogRef, notes: list[str]) -> Flight:
        key = (ref.fmt, str(ref.path), ref.topic or "", ref.check_crc)
        if key not in self.flights:
            path = ref.path
            if ref.fmt == "ulog":
                flight = lazy_reader("ulog", "read_ulog", path)(path)
            elif ref.fmt == "crazyflie":
                flight = lazy_reader("crazyflie", "read_crazyflie", path)(path, ref.check_crc)
            else:
                topics = {ref.stream: ref.topic}
                flight = lazy_reader("rosbag", "read_bag", path)(path, topics=topics)
            self.flights[key] = flight
            log_notes = flight.meta.get("notes")
            if isinstance(log_notes, list | tuple):
                notes += [f"[{ref.table}] {n}" for n in log_notes]
            elif isinstance(log_notes, dict):
                notes += [f"[{ref.table}] {k}: {v}" for k, v in log_notes.items()]
            for k, v in flight.meta.items():
                if isinstance(v, dict) and _has_counts(v):
                    self.counts[f"[{ref.table}] {k}"] = copy.deepcopy(v)
        return self.flights[key]

    def stream(self, ref: _LogRef, notes: list[str]) -> Any:
        flight = self.get(ref, notes)
        table, path, stream = ref.table, ref.path, ref.stream
        streams = flight.streams()
        if stream not in streams:
            raise FlightFormatError(
                self.manifest,
                f"[{table}] {path} has no stream {stream!r}; it has: "
                + (", ".join(streams) or "none"),
            )
        return streams[stream]


def _check_crc(manifest: Path, table: str, spec: dict[str, Any]) -> bool:
    """A Crazyflie table's ``check_crc`` (default true; false salvages a damaged log)."""
    v = spec.get("check_crc", True)
    if not isinstance(v, bool):
        raise FlightFormatError(manifest, f"[{table}] check_crc must be true or false, got {v!r}")
    return v


def _read_stream(
    kind: str, fmt: str, path: Path, spec: dict[str, Any], calib: Calibration, notes: list[str]
) -> Any:
    time_unit = spec.get("time_unit", "auto")
    if fmt == "native_csv":
        return read_stream_csv(path, "trajectory" if kind == "references" else kind)
    if fmt == "euroc":
        if kind == "imu":
            return read_euroc_imu(path, notes=notes)
        if kind == "images":
            return read_euroc_images(path, calib.camera, notes=notes)
        return read_euroc_groundtruth(path, notes=notes)
    if fmt == "tum":
        return read_tum(path, time_unit=time_unit, notes=notes)
    if fmt == "tum_slam":
        return read_tum_slam(path, spec.get("session", 0), time_unit=time_unit, notes=notes)
    raise AssertionError(f"format {fmt!r} passed the checks but has no reader")


def read_manifest(path: str | Path) -> Flight:
    """Assemble a flight from the files a TOML manifest names (schema: module docstring).

    Raises:
        FlightFormatError: a bad manifest (naming manifest, table and key), a missing file (naming
            the resolved path) or a bad data file (naming that file and line).
        FlightDataError: the assembled flight fails ``flight.check()``.
    """
    manifest = resolved(Path(path), Path(path), "manifest file")
    doc = read_toml(manifest, "manifest file")
    unknown = [k for k in doc if k not in TOP_LEVEL_KEYS]
    if unknown:
        raise FlightFormatError(
            manifest, f"unknown key(s)/table(s) {unknown}; valid: {', '.join(TOP_LEVEL_KEYS)}"
        )
    if not isinstance(doc.get("name"), str):
        raise FlightFormatError(manifest, "name: required (a string)")
    if not isinstance(doc.get("root", "."), str):
        raise FlightFormatError(
            manifest, f"root = {doc['root']!r}: expected a folder path (a string)"
        )
    root = resolved(manifest.parent / doc.get("root", "."), manifest, "root")
    if not root.is_dir():
        raise FlightFormatError(manifest, f"root: folder {root} not found")
    body = _check_body(manifest, doc)

    notes: list[str] = []
    sources: dict[str, dict[str, str]] = {}
    logs = _LogCache(manifest)
    calib = Calibration()
    if "calib" in doc:
        fmt = _check_table(manifest, "calib", doc["calib"], TABLE_FORMATS["calib"])
        p = _resolve(manifest, root, "calib", doc["calib"]["path"])
        if fmt == "orbslam3_yaml":
            calib = read_orbslam3_yaml(p, notes=notes)
        elif fmt in ("ulog", "crazyflie"):
            crc = _check_crc(manifest, "calib", doc["calib"])
            calib = logs.get(_LogRef(fmt, p, "calib", "calib", None, crc), notes).calib
        else:
            calib = read_calib_yaml(p)
        sources["calib"] = {"format": fmt, "path": str(p)}
        if "imu_noise" in doc["calib"]:
            noise = _imu_noise_override(manifest, calib.imu_noise, doc["calib"]["imu_noise"])
            calib = dataclasses.replace(calib, imu_noise=noise)
            sources["calib"]["imu_noise"] = "manifest"

    offsets: dict[str, float] = dict(calib.time_offsets)
    streams: dict[str, Any] = {}
    jobs: list[tuple[str, str, dict[str, Any], tuple[str, ...]]] = [
        (t, t, doc[t], TABLE_FORMATS[t]) for t in TABLE_FORMATS if t != "calib" and t in doc
    ]
    refs = doc.get("references", {})
    if not isinstance(refs, dict):
        raise FlightFormatError(manifest, "[references] must hold tables [references.<name>]")
    jobs += [
        (f"references.{n}", "references", s, TABLE_FORMATS["ground_truth"]) for n, s in refs.items()
    ]
    references = {}
    for table, kind, spec, formats in jobs:
        fmt = _check_table(manifest, table, spec, formats)
        p = _resolve(manifest, root, table, spec["path"])
        if fmt in LOG_FORMATS:
            default = f"ref:{table.split('.', 1)[1]}" if kind == "references" else kind
            ref = _LogRef(
                fmt,
                p,
                table,
                spec.get("stream", default),
                spec.get("topic"),
                _check_crc(manifest, table, spec),
            )
            series = logs.stream(ref, notes)
        else:
            series = _read_stream(kind, fmt, p, spec, calib, notes)
        offset = float(spec.get("time_offset_s", 0.0))
        if offset:
            series = dataclasses.replace(series, t=series.t + offset)
            offsets[table] = offset
        sources[table] = {"format": fmt, "path": str(p)}
        if kind == "references":
            references[table.split(".", 1)[1]] = series
        else:
            streams[kind] = series
    calib = dataclasses.replace(calib, time_offsets=offsets)
    meta: dict[str, Any] = {
        "format": "manifest",
        "manifest": str(manifest),
        "sources": sources,
        "notes": notes,
        **logs.counts,
    }
    if "meta" in doc:
        meta["manifest_meta"] = doc["meta"]
    slam_options = {k: doc["slam"][k] for k in SLAM_OPTION_KEYS if k in doc.get("slam", {})}
    if slam_options:
        meta["slam_options"] = slam_options
    flight = Flight(
        name=doc["name"],
        source=doc.get("source", str(manifest)),
        references=references,
        calib=calib,
        meta=meta,
        **streams,
    )
    if body.get("frame") == "imu":
        a = np.asarray(body["thrust_axis"], float)
        flight.meta["thrust_axis_body"] = (a / np.linalg.norm(a)).tolist()
    elif body:
        try:
            flight = to_flu_body(flight, body["thrust_axis"], where="[body] thrust_axis")
        except FlightDataError as e:
            raise FlightFormatError(manifest, str(e)) from e
    log.info("read manifest %s: %s", manifest, ", ".join(flight.streams()))
    return flight.check()
