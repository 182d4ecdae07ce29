"""What a flight holds: per-stream samples, rates, time spans and gaps, the sensors' common time
window, a calibration summary and the readers' notes. The library side of ``fgnav info``.

Times in the table are relative to the earliest sample of any stream (``t0``, printed in absolute
seconds of the flight's clock) so that streams can be compared at a glance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from fgnav.coverage import stream_span_notes
from fgnav.datasets.geometry import so3_log
from fgnav.datasets.types import (
    STREAMS,
    Calibration,
    Flight,
    FlowSeries,
    ImageSeries,
    RangeSeries,
    SlamSeries,
    Trajectory,
)

GAP_FACTOR = 2.5
"""A time step longer than ``GAP_FACTOR`` times the stream's median step counts as a gap (project
issue 2's definition: well above the jitter of a steady rate, below one dropped sample of 3)."""


@dataclass(frozen=True)
class StreamInfo:
    """Summary of one stream.

    Attributes:
        name: stream name (``imu``, ``slam``, ``ref:px4_ekf2`` ...).
        role: ``"sensor"``, ``"ground truth"`` or ``"reference"``.
        samples: number of samples.
        rate_hz: median rate [Hz] (0 for fewer than 2 samples).
        t_start, t_end: first and last sample time [s, flight clock].
        gaps: number of steps longer than ``GAP_FACTOR`` x the median step.
        largest_step_s: longest time step [s] (0 for fewer than 2 samples).
        largest_step_at: time at the start of that step [s, flight clock].
        details: stream-specific remarks (SLAM sessions, optional columns, value ranges).
    """

    name: str
    role: str
    samples: int
    rate_hz: float
    t_start: float
    t_end: float
    gaps: int
    largest_step_s: float
    largest_step_at: float
    details: str = ""

    @property
    def duration(self) -> float:
        """Seconds between the first and last sample."""
        return self.t_end - self.t_start


@dataclass(frozen=True)
class FlightInfo:
    """Summary of a flight (see :func:`flight_info`).

    Attributes:
        name, source: of the flight.
        streams: one row per stream (sensors in ``STREAMS`` order, ground truth, references).
        t0: earliest sample time of all streams [s]; the table's times are relative to it.
        overlap: ``(t_start, t_end)`` common to all sensor streams [s, flight clock], or None when
            the sensors do not overlap or there is no sensor stream.
        overlap_streams: the sensor streams the overlap is taken over.
        calibration: readable calibration lines.
        notes: reader notes (skipped lines, detected units ...) from ``flight.meta``.
        stream_notes: sensor streams that end or start long before / after the others (a
            truncated file; :func:`fgnav.coverage.stream_span_notes`).
    """

    name: str
    source: str
    streams: tuple[StreamInfo, ...]
    t0: float
    overlap: tuple[float, float] | None
    overlap_streams: tuple[str, ...]
    calibration: tuple[str, ...]
    notes: tuple[str, ...]
    stream_notes: tuple[str, ...] = ()

    def stream(self, name: str) -> StreamInfo:
        """The row of stream ``name``; KeyError when absent."""
        for s in self.streams:
            if s.name == name:
                return s
        raise KeyError(name)

    def format(self) -> str:
        """A readable report: header, stream table, overlap, calibration and notes."""
        out = [f"flight  {self.name}"]
        if self.source:
            out.append(f"source  {self.source}")
        out.append(f"t0      {self.t0:.6f} s (stream times below are relative to t0)")
        out.append("")
        head = (
            f"{'stream':<20} {'role':<12} {'samples':>8} {'rate [Hz]':>9} {'start [s]':>10} "
            f"{'end [s]':>10} {'dur. [s]':>9} {'gaps':>5} {'max dt [s]':>10} {'at [s]':>9}  details"
        )
        out += [head, "-" * len(head)]
        for s in self.streams:
            out.append(
                f"{s.name:<20} {s.role:<12} {s.samples:>8d} {s.rate_hz:>9.2f} "
                f"{s.t_start - self.t0:>10.3f} {s.t_end - self.t0:>10.3f} {s.duration:>9.3f} "
                f"{s.gaps:>5d} {s.largest_step_s:>10.3f} {s.largest_step_at - self.t0:>9.3f}  "
                f"{s.details}".rstrip()
            )
        out.append("")
        if self.overlap is None:
            out.append(
                "sensor overlap: none"
                + (
                    f" (streams {', '.join(self.overlap_streams)} do not overlap)"
                    if self.overlap_streams
                    else " (no sensor stream)"
                )
            )
        else:
            a, b = self.overlap
            out.append(
                f"sensor overlap: {a - self.t0:.3f} .. {b - self.t0:.3f} s ({b - a:.3f} s; "
                f"absolute {a:.6f} .. {b:.6f}) over {', '.join(self.overlap_streams)}"
            )
        out += [f"short stream: {n}" for n in self.stream_notes]
        out += ["", "calibration"] + [f"  {line}" for line in self.calibration]
        if self.notes:
            out += ["", "notes (flight.meta)"] + [f"  - {n}" for n in self.notes]
        return "\n".join(out)


def _stream_info(name: str, role: str, s: Any) -> StreamInfo:
    t = np.asarray(s.t, dtype=float)
    n = len(t)
    gaps, largest, at = 0, 0.0, float(t[0]) if n else math.nan
    rate = 0.0
    if n >= 2:
        dt = np.diff(t)
        med = float(np.median(dt))
        rate = 1.0 / med if med > 0 else 0.0
        gaps = int(np.count_nonzero(dt > GAP_FACTOR * med))
        k = int(np.argmax(dt))
        largest, at = float(dt[k]), float(t[k])
    return StreamInfo(
        name=name,
        role=role,
        samples=n,
        rate_hz=rate,
        t_start=float(t[0]) if n else math.nan,
        t_end=float(t[-1]) if n else math.nan,
        gaps=gaps,
        largest_step_s=largest,
        largest_step_at=at,
        details=_details(s),
    )


def _details(s: Any) -> str:
    if isinstance(s, SlamSeries):
        ids, counts = np.unique(s.session, return_counts=True)
        parts = [
            f"sessions {len(ids)} ("
            + ", ".join(f"{i}: {c}" for i, c in zip(ids.tolist(), counts.tolist(), strict=True))
            + ")"
        ]
        if s.latency is not None:
            parts.append(f"latency median {float(np.median(s.latency)) * 1e3:.0f} ms")
        return "; ".join(parts)
    if isinstance(s, Trajectory):
        extra = [
            f
            for f, a in (
                ("velocity", s.world_v_body),
                ("gyro bias", s.gyro_bias),
                ("accel bias", s.accel_bias),
            )
            if a is not None
        ]
        return "pose" + "".join(f" + {e}" for e in extra)
    if isinstance(s, RangeSeries):
        return f"range {float(np.min(s.range)):.2f} .. {float(np.max(s.range)):.2f} m" + (
            "; quality" if s.quality is not None else ""
        )
    if isinstance(s, FlowSeries):
        return (
            f"dt median {float(np.median(s.dt)) * 1e3:.2f} ms; |flow| max "
            # Flow units: the calibration's (px, or rad at 1 px/rad; see body_T_flow below).
            f"{float(np.abs(s.flow).max()):.3g}" + ("; quality" if s.quality is not None else "")
        )
    if isinstance(s, ImageSeries):
        where = "in memory" if s.frames is not None else "files"
        cam = f"{s.camera.width}x{s.camera.height} " if s.camera is not None else ""
        return f"{cam}{where}"
    return ""


def _calibration_lines(c: Calibration, streams: set[str] | None = None) -> list[str]:
    """The calibration as lines; the mounts and limits of the rangefinder, the flow sensor
    and the camera only when the flight has that stream (``streams``; None: all), the camera
    also with SLAM (it is the SLAM's camera)."""

    def has(*names: str) -> bool:
        return streams is None or any(n in streams for n in names)

    def pose(T: np.ndarray) -> str:
        T = np.asarray(T, dtype=float)
        if np.array_equal(T, np.eye(4)):
            return "identity"
        angle = float(np.degrees(np.linalg.norm(so3_log(T[:3, :3]))))
        t = ", ".join(f"{v:+.4f}" for v in T[:3, 3])
        return f"t = [{t}] m, rotation {angle:.2f} deg"

    lines = []
    if has("slam", "images"):
        lines.append(f"body_T_cam    {pose(c.body_T_cam)}")
    if has("range"):
        lines.append(f"body_T_range  {pose(c.body_T_range)}")
    k = c.camera
    if has("slam", "images") and k is None:
        lines.append("camera        none")
    elif has("slam", "images"):
        dist = ", ".join(f"{d:.6g}" for d in k.distortion) or "none"
        lines.append(
            f"camera        {k.width}x{k.height} px, fx {k.fx:g} fy {k.fy:g} cx {k.cx:g} "
            f"cy {k.cy:g}, distortion [{dist}]"
        )
    n = c.imu_noise
    lines.append(
        f"imu noise     gyro {n.gyro_noise_density:.3g} rad/s/sqrt(Hz), accel "
        f"{n.accel_noise_density:.3g} m/s^2/sqrt(Hz), gyro walk {n.gyro_random_walk:.3g} "
        f"rad/s^2/sqrt(Hz), accel walk {n.accel_random_walk:.3g} m/s^3/sqrt(Hz)"
    )
    if has("range"):
        lines.append(f"range limits  {c.range_min:g} .. {c.range_max:g} m")
    if has("flow"):
        lines.append(f"body_T_flow   {pose(c.body_T_flow)}; {c.flow_pixels_per_rad:.4g} px/rad")
    offsets = ", ".join(f"{k} {v:+.6f} s" for k, v in c.time_offsets.items()) or "none"
    lines.append(f"time offsets  {offsets}")
    return lines


def _notes(meta: dict[str, Any]) -> list[str]:
    out: list[str] = []
    notes = meta.get("notes")
    if isinstance(notes, list | tuple):
        out += [str(n) for n in notes]
    elif isinstance(notes, dict):
        out += [f"{k}: {v}" for k, v in notes.items()]
    elif notes:
        out.append(str(notes))
    out += [f"{name} = {v}" for name, v in reader_skips(meta)]
    out += [f"{name} = {v}" for name, v in reader_skips(meta, KEPT_COUNT_KEYS)]
    return out


KEPT_COUNT_KEYS = ("outside_min_max_kept",)
"""Counts of samples a reader kept but flagged (a range outside the sensor's limits: the range
factor gates it), printed beside the skip counts by ``fgnav info``."""


def reader_skips(
    meta: dict[str, Any], keys: tuple[str, ...] | None = None
) -> list[tuple[str, int | float]]:
    """The readers' non-zero skip counts of per-stream summaries (e.g. the ULog and Crazyflie
    readers' ``meta["imu"]``, the bag reader's ``meta["bag_streams"]["imu"]``), as
    ``("imu.skipped_...", n)`` (nested summaries: ``"bag_streams.imu.repeated_stamp_skipped"``).
    ``keys``: the count names to take instead (exact names), e.g. :data:`KEPT_COUNT_KEYS`."""

    def take(k: Any, v: Any) -> bool:
        if not isinstance(v, int | float) or isinstance(v, bool) or not v:
            return False
        return "skipped" in str(k) if keys is None else str(k) in keys

    def walk(prefix: str, d: dict[Any, Any], depth: int) -> list[tuple[str, int | float]]:
        out: list[tuple[str, int | float]] = []
        for k, v in d.items():
            if isinstance(v, dict) and depth < 2:
                out += walk(f"{prefix}{k}.", v, depth + 1)
            elif depth > 0 and take(k, v):
                out.append((f"{prefix}{k}", v))
        return out

    return walk("", meta, 0)


def flight_info(flight: Flight) -> FlightInfo:
    """Summarise a flight's streams, sensor time overlap, calibration and reader notes."""
    rows: list[StreamInfo] = []
    for name in STREAMS:
        s = getattr(flight, name)
        if s is not None:
            role = "ground truth" if name == "ground_truth" else "sensor"
            rows.append(_stream_info(name, role, s))
    for name, traj in flight.references.items():
        rows.append(_stream_info(f"ref:{name}", "reference", traj))
    sensors = tuple(r.name for r in rows if r.role == "sensor" and r.samples)
    overlap = None
    if sensors:
        a = max(r.t_start for r in rows if r.name in sensors)
        b = min(r.t_end for r in rows if r.name in sensors)
        overlap = (a, b) if b > a else None
    starts = [r.t_start for r in rows if r.samples]
    return FlightInfo(
        name=flight.name,
        source=flight.source,
        streams=tuple(rows),
        t0=min(starts) if starts else 0.0,
        overlap=overlap,
        overlap_streams=sensors,
        calibration=tuple(_calibration_lines(flight.calib, set(flight.streams()))),
        notes=tuple(_notes(flight.meta)),
        stream_notes=tuple(stream_span_notes(flight)),
    )
