"""What part of a flight a run used, scored and left out: nothing is lost without saying so.

Library side of the end-of-run lines of ``fgnav batch``, ``online``, ``compare`` and ``info``
(issue 18 Build 3): the measurements skipped (never used: outside the keyframe window, gated,
decimated ...) and dropped (online: arrived too late, alignment marginalised ...) counted by
reason, the sensor streams that start or end long after / before the others (a truncated file),
and the time span that was scored against the ground truth. Times are printed relative to the
flight's first sample (as ``fgnav info`` does).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from fgnav.datasets.types import STREAMS, Flight
from fgnav.estimate import Estimate

#: A sensor stream ending (starting) more than this before (after) the latest-ending
#: (earliest-starting) sensor stream is reported [s]: longer than the 2 s SLAM segment and
#: default lag, far longer than the rate differences of real logs (EuRoC MH_01's SLAM ends
#: 0.09 s before its IMU).
TRUNCATED_STREAM_S = 2.0


def flight_t0(flight: Flight) -> float:
    """Earliest sample of any stream (the origin of the printed times) [s]."""
    starts = [float(s.t[0]) for s in flight.streams().values() if len(s)]
    return min(starts) if starts else 0.0


def stream_span_notes(flight: Flight, min_s: float = TRUNCATED_STREAM_S) -> list[str]:
    """One line per sensor stream that ends more than ``min_s`` before the latest-ending sensor
    stream or starts more than ``min_s`` after the earliest-starting one."""
    t0 = flight_t0(flight)
    spans = {
        name: (float(s.t[0]), float(s.t[-1]))
        for name in STREAMS
        if name != "ground_truth" and (s := getattr(flight, name)) is not None and len(s)
    }
    if len(spans) < 2:
        return []
    last = max(spans, key=lambda n: spans[n][1])
    first = min(spans, key=lambda n: spans[n][0])
    out = []
    for name, (a, b) in spans.items():
        if spans[last][1] - b > min_s:
            out.append(
                f"{name} ends at {b - t0:.1f} s, {spans[last][1] - b:.1f} s before {last} "
                f"(ends {spans[last][1] - t0:.1f} s)"
            )
        if a - spans[first][0] > min_s:
            out.append(
                f"{name} starts at {a - t0:.1f} s, {a - spans[first][0]:.1f} s after {first} "
                f"(starts {spans[first][0] - t0:.1f} s)"
            )
    return out


def scored_span(flight: Flight, est: Estimate) -> tuple[float, float] | None:
    """``(t_start, t_end)`` [s, flight clock] where the estimate and the ground truth overlap
    (None without ground truth or overlap)."""
    gt = flight.ground_truth
    t = np.asarray(est.trajectory.t, float)
    if gt is None or len(gt) == 0 or t.size == 0:
        return None
    a, b = max(float(t[0]), float(gt.t[0])), min(float(t[-1]), float(gt.t[-1]))
    return (a, b) if b > a else None


def _counts_text(counts: Mapping[str, int]) -> str:
    items = sorted(((k, int(v)) for k, v in counts.items() if v), key=lambda kv: (-kv[1], kv[0]))
    if not items:
        return "none"
    total = sum(v for _, v in items)
    return f"{total} ({', '.join(f'{k} {v}' for k, v in items)})"


def loss_lines(info: Mapping[str, Any], online: bool) -> list[str]:
    """``skipped`` (and, online, ``dropped``) counts by reason from an estimate's ``info``."""
    out = [f"skipped (not used): {_counts_text(info.get('skipped') or {})}"]
    if online or info.get("dropped"):
        out.append(f"dropped (online): {_counts_text(info.get('dropped') or {})}")
    return out


#: Words of a filter's ``info["counts"]`` entries that count measurements it did not use.
_LOSS_WORDS = ("skip", "reject", "drop", "gated", "too_old", "late", "waiting")


def unused_counts(info: Mapping[str, Any]) -> dict[str, int]:
    """Every count of measurements a method did not use, by reason: the smoothers' ``skipped``
    and ``dropped`` tables, and a filter baseline's ``unused`` table (``stream:reason -> count``,
    the one convention of :mod:`fgnav.baselines._inputs`). An ``info`` without ``unused`` (a
    summary written before it) falls back to the entries of ``counts`` whose name says so
    (``skipped`` / ``gated`` tables, ``*_rejected_*``, ``too_old`` ...)."""
    out: dict[str, int] = {}
    for table in ("skipped", "dropped"):
        for k, v in (info.get(table) or {}).items():
            out[k if table == "skipped" else f"dropped:{k}"] = int(v)
    counts = info.get("counts")
    unused = info.get("unused")
    if isinstance(unused, Mapping):
        out.update({str(k): int(v) for k, v in unused.items()})
    elif isinstance(counts, Mapping):
        for k, v in counts.items():
            if isinstance(v, Mapping) and any(w in k for w in _LOSS_WORDS):
                out.update({f"{k}:{kk}": int(n) for kk, n in v.items() if isinstance(n, int)})
            elif isinstance(v, int) and not isinstance(v, bool):
                if any(w in k for w in _LOSS_WORDS):
                    out[k] = v
    return {k: v for k, v in out.items() if v}


def compare_lines(flight: Flight, runs: Mapping[str, Estimate]) -> list[str]:
    """``fgnav compare``'s end lines: short streams once, then per method what it did not use
    and the part of the flight scored."""
    t0 = flight_t0(flight)
    out = [f"stream: {n}" for n in stream_span_notes(flight)]
    for name, est in runs.items():
        span = scored_span(flight, est)
        scored = "not scored" if span is None else f"scored {span[0] - t0:.1f}-{span[1] - t0:.1f} s"
        text = f"{name}: not used {_counts_text(unused_counts(est.info))}"
        if "skipped" not in est.info and not name.startswith("ref:"):
            # A filter that counts only what it rejects: the samples after its last output.
            after = samples_after(flight, est)
            if after:
                text += f", after its estimate ends {_counts_text(after)}"
        out.append(f"{text}; {scored}")
    return out


#: Samples this long after an estimate's last state may still have been used [s].
AFTER_END_TOLERANCE_S = 0.05


def samples_after(flight: Flight, est: Estimate) -> dict[str, int]:
    """Sensor samples later than the estimate's last state (+ ``AFTER_END_TOLERANCE_S``), per
    stream: no method can have used them."""
    t = np.asarray(est.trajectory.t, float)
    if t.size == 0:
        return {}
    out = {}
    for name in STREAMS:
        s = getattr(flight, name)
        if name != "ground_truth" and s is not None:
            n = int(np.count_nonzero(s.t > t[-1] + AFTER_END_TOLERANCE_S))
            if n:
                out[name] = n
    return out


def coverage(flight: Flight, est: Estimate) -> dict[str, Any]:
    """The facts behind :func:`coverage_lines` (for ``summary.json``)."""
    t0 = flight_t0(flight)
    ends = [float(s.t[-1]) for s in flight.streams().values() if len(s)]
    span = scored_span(flight, est)
    t = np.asarray(est.trajectory.t, float)
    return {
        "t0": t0,
        "flight_s": [0.0, (max(ends) - t0) if ends else 0.0],
        "estimate_s": [float(t[0]) - t0, float(t[-1]) - t0] if t.size else None,
        "scored_s": None if span is None else [span[0] - t0, span[1] - t0],
        "stream_notes": stream_span_notes(flight),
    }


def coverage_lines(flight: Flight, est: Estimate) -> list[str]:
    """End-of-run lines: losses by reason, short streams, and the scored part of the flight."""
    from fgnav.info import reader_skips

    c = coverage(flight, est)
    out = loss_lines(est.info, online=est.causal)
    skips = reader_skips(flight.meta)
    if skips:  # (written to the reader's notes, and only `fgnav info` said them)
        out.append("reader skipped: " + ", ".join(f"{n} {v:g}" for n, v in skips))
    out += [f"stream: {n}" for n in c["stream_notes"]]
    f0, f1 = c["flight_s"]
    if c["scored_s"] is not None:
        a, b = c["scored_s"]
        out.append(f"scored: {a:.1f}-{b:.1f} s of the flight's {f0:.1f}-{f1:.1f} s")
    elif c["estimate_s"] is not None:
        a, b = c["estimate_s"]
        why = "no ground truth" if flight.ground_truth is None else "no ground truth overlap"
        out.append(f"estimated: {a:.1f}-{b:.1f} s of the flight's {f0:.1f}-{f1:.1f} s ({why})")
    return out
