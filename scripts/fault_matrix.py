"""Fault matrix (issue 18): faulty copies of a flight through ``fgnav batch`` and ``fgnav online``.

Builds faulty copies of a simulated two-turns flight (seed 1, 24 s, every sensor but the camera;
camera rows render 20 s with the 30 Hz camera) and of the shared EuRoC MH_01 with ORB-SLAM3
(``datasets/manifests/euroc_mh01_orbslam3.toml``, read in place; faulty files are written to a
temporary folder beside a manifest that points at the untouched ones), runs the CLI commands on
each in this process (``fgnav.cli.main``: what a user sees, stdout and stderr captured), and prints
one table: outcome, the detector(s) that fired, ATE against the nominal flight's, counts.

Rows named ``events:*`` are faults a file reader refuses by design (out-of-order and duplicated
stamps, NaN rows: one-line errors, see the ``file:*`` rows), fed instead as events straight into
the push-API smoother (:class:`fgnav.solvers.online.OnlineSmoother`), as a live link would.

Outcomes of one run (the row's ``expect`` says which are acceptable; ``FAIL`` never is):

- ``recovered``: exit 0 and ATE within ``RECOVER_FACTOR`` x the nominal flight's;
- ``named``: the fault is named on screen (a WARNING line or the health line) *and* in
  ``summary.json`` (``info.health`` detectors or status, solver / LM status), whatever the ATE;
  a row that declares the detectors that must name its fault (``names``) is ``named`` when they
  do, whatever the ATE, and otherwise classified as any other;
- ``error``: exit 1 with one line on stderr naming the problem, no traceback, nothing written;
- ``FAIL``: a traceback, or an ATE above ``RECOVER_FACTOR`` x nominal with nothing named, or an
  ATE above 1 m with exit 0 and no warning.

Usage::

    .venv/bin/python scripts/fault_matrix.py            # every row (about 6-10 minutes)
    .venv/bin/python scripts/fault_matrix.py --quick    # the test subset (about 3 minutes)
    .venv/bin/python scripts/fault_matrix.py --only imu-gap-2s,slam-jump-1m --json out.json
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import logging
import math
import shutil
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MH01_MANIFEST = ROOT / "datasets" / "manifests" / "euroc_mh01_orbslam3.toml"

#: A run recovers when its ATE is within this factor of the nominal flight's (issue 18).
RECOVER_FACTOR = 2.0
#: No run may report an ATE above this with exit 0 and no warning [m] (issue 18).
SILENT_ATE_MAX_M = 1.0
SIM_SEED = 1
SIM_DURATION_S = 24.0
SIM_HOVER_DURATION_S = 30.0
SIM_CAMERA_DURATION_S = 20.0
SIM_FLOW_DURATION_S = 20.0
# ----------------------------------------------------------------------------------------------
# Rows
# ----------------------------------------------------------------------------------------------


@dataclass
class Row:
    """One fault: how to build the faulty input and what a run of it may end as.

    Attributes:
        name: row name.
        base: ``"sim"``, ``"sim-camera"``, ``"sim-hover"``, ``"sim-flow"`` or ``"mh01"`` (the
            nominal flight it perturbs).
        build: ``build(ctx, folder) -> argv input`` (a flight path for the CLI), or for
            ``events:*`` rows ``build(ctx) -> (flight, events)``.
        what: one line describing the fault.
        expect: acceptable outcomes per command, e.g. ``{"batch": {"recovered", "named"}}``.
        quick: part of ``--quick``.
        config: TOML text of a ``--config`` file (None: none).
        extra_args: more CLI flags.
        names_input: a bad input file: an ``error`` outcome must name a file of the row's
            input (its path), not only the flight (``file:*`` rows are so by default).
        names: detectors that must name the fault: a run whose ``summary.json`` and screen name
            every one of them is ``named`` whatever its ATE (a fault named but not fixed, whose
            ATE stays within ``RECOVER_FACTOR``), else it is classified as any other run.
    """

    name: str
    base: str
    build: Callable
    what: str
    expect: dict[str, set[str]]
    quick: bool = False
    config: str | None = None
    extra_args: tuple[str, ...] = ()
    names_input: bool = False
    names: tuple[str, ...] = ()


#: The row giving each base flight's nominal ATE.
NOMINAL_ROWS = {
    "sim": "nominal",
    "mh01": "mh01:nominal",
    "sim-camera": "camera-nominal",
    "sim-hover": "hover:nominal",
    "sim-flow": "flow:nominal",
}
OK = {"recovered", "named"}
#: Acceptable where the batch solve may not converge: it says so and exits 1 (nothing written).
OK_OR_STOP = {"recovered", "named", "error"}
ERR = {"error"}
ANY = {"recovered", "named", "error"}


def _both(s: set[str]) -> dict[str, set[str]]:
    return {"batch": s, "online": s}


@dataclass
class Context:
    """Nominal flights (built once) and the temporary folder."""

    tmp: Path
    _cache: dict = field(default_factory=dict)

    def _simulated(self, scenario: str, duration: float):
        """A simulated flight without images (seed ``SIM_SEED``), built once."""
        if scenario not in self._cache:
            from fgnav.datasets.simulate.options import SimOptions
            from fgnav.datasets.simulate.simulator import simulate

            self._cache[scenario] = simulate(
                scenario, SIM_SEED, SimOptions(duration=duration, images=False)
            )
        return self._cache[scenario]

    def sim(self):
        return self._simulated("two-turns", SIM_DURATION_S)

    def sim_folder(self) -> Path:
        """The nominal simulated flight as a native folder."""
        if "sim_folder" not in self._cache:
            from fgnav.datasets.native import write_flight

            self._cache["sim_folder"] = write_flight(
                self.sim(), self.tmp / "nominal-sim", overwrite=True
            )
        return self._cache["sim_folder"]

    def sim_with(self, **sim_options):
        from fgnav.datasets.simulate.options import SimOptions
        from fgnav.datasets.simulate.simulator import simulate

        return simulate(
            "two-turns", SIM_SEED, SimOptions(duration=SIM_DURATION_S, images=False, **sim_options)
        )

    def hover(self):
        """Simulated hover in gusts (``SIM_HOVER_DURATION_S``): little motion, no turns."""
        return self._simulated("hover", SIM_HOVER_DURATION_S)

    def flow_deck(self):
        """The flow-deck base flight (the simulator's Crazyflie-like options: IMU, optical flow,
        rangefinder; seed ``SIM_SEED``), built once."""
        if "flow" not in self._cache:
            from fgnav.datasets.simulate.options import CRAZYFLIE_LIKE, SimOptions
            from fgnav.datasets.simulate.simulator import simulate

            self._cache["flow"] = simulate(
                "flowdeck", SIM_SEED, SimOptions(duration=SIM_FLOW_DURATION_S, **CRAZYFLIE_LIKE)
            )
        return self._cache["flow"]

    def flow_deck_with(self, **sim_options):
        """The flow-deck base flight with more simulator options (the same random draws)."""
        from fgnav.datasets.simulate.options import CRAZYFLIE_LIKE, SimOptions
        from fgnav.datasets.simulate.simulator import simulate

        return simulate(
            "flowdeck",
            SIM_SEED,
            SimOptions(duration=SIM_FLOW_DURATION_S, **CRAZYFLIE_LIKE, **sim_options),
        )

    def camera_folder(self) -> Path:
        """A 20 s simulated flight with the downward camera, as a native folder (PNG files)."""
        if "cam" not in self._cache:
            from fgnav.datasets.native import write_flight
            from fgnav.datasets.simulate.options import SimOptions
            from fgnav.datasets.simulate.simulator import simulate

            f = simulate("two-turns", SIM_SEED, SimOptions(duration=SIM_CAMERA_DURATION_S))
            self._cache["cam"] = write_flight(f, self.tmp / "nominal-camera", overwrite=True)
        return self._cache["cam"]


def _write(flight, folder: Path) -> Path:
    from fgnav.datasets.native import write_flight

    return write_flight(flight, folder, overwrite=True)


def _replace(flight, **streams):
    return dataclasses.replace(flight, **streams)


def _sim_fault(fn: Callable) -> Callable:
    """A row builder from ``fn(flight) -> faulty flight`` on the nominal simulated flight."""

    def build(ctx: Context, folder: Path) -> Path:
        return _write(fn(ctx.sim()), folder)

    return build


# --- simulated-flight faults ------------------------------------------------------------------


def _slam_cut(f, t0: float, t1: float):
    s = f.slam
    return _replace(f, slam=s.select(~((s.t >= t0) & (s.t < t1))))


def _imu_cut(f, t0: float, t1: float):
    s = f.imu
    return _replace(f, imu=s.select(~((s.t >= t0) & (s.t < t1))))


def _gyro_saturated(f, rail: float = 0.5):
    w = np.clip(f.imu.body_omega, -rail, rail)
    return _replace(f, imu=dataclasses.replace(f.imu, body_omega=w))


def _accel_clipped(f, rail: float | None = None):
    a = f.imu.body_accel
    # A rail that clips the thrust axis at the top 10 % of its readings (a +-1 g range would be
    # 9.81: below hover thrust; this is a range just above hover).
    rail = float(np.quantile(np.abs(a), 0.97)) if rail is None else rail
    return _replace(f, imu=dataclasses.replace(f.imu, body_accel=np.clip(a, -rail, rail)))


def _accel_dead(f, t0: float = 10.0, t1: float = 13.0):
    a = f.imu.body_accel.copy()
    a[(f.imu.t >= t0) & (f.imu.t < t1)] = 0.0  # a dead (zeroed) accelerometer
    return _replace(f, imu=dataclasses.replace(f.imu, body_accel=a))


def _slam_jump(f, t_jump: float = 12.0, jump_m: float = 1.0):
    s = f.slam
    scale = float(f.meta["truth"]["slam_sessions"]["0"]["scale"])
    p = s.slam_t_cam.copy()
    p[s.t >= t_jump] += scale * jump_m * np.array([1.0, 0.0, 0.0])
    return _replace(f, slam=dataclasses.replace(s, slam_t_cam=p))


def _slam_mirrored(f, axis: int = 1):
    """A left-handed SLAM frame: the sign of one axis flipped (positions D p, rotations D R D)."""
    from fgnav.datasets.slam_gyro import unmirror_slam  # (its own inverse)

    return _replace(f, slam=unmirror_slam(f.slam, axis))


def _slam_scale_drift(f, rate: float = 0.05):
    """The SLAM scale running away: positions times (1 + rate t) [1/s]."""
    s = f.slam
    k = 1.0 + rate * (s.t - s.t[0])
    return _replace(f, slam=dataclasses.replace(s, slam_t_cam=s.slam_t_cam * k[:, None]))


def _slam_offset(f, dt: float = 0.3):
    s = f.slam
    return _replace(f, slam=dataclasses.replace(s, t=s.t + dt))


def _slam_latency(f, latency: float = 0.5):
    s = f.slam
    return _replace(f, slam=dataclasses.replace(s, latency=np.full(len(s), latency)))


def _range_stuck(f, t_stuck: float = 8.0):
    r = f.range
    v = r.range.copy()
    i = int(np.searchsorted(r.t, t_stuck))
    v[i:] = v[i]
    return _replace(f, range=dataclasses.replace(r, range=v))


def _range_at_min(f):
    """Every range reading at the calibration's ``range_min`` (a rangefinder pinned at its
    floor, which it reports for anything at or below it)."""
    r = f.range
    v = np.full(len(r), float(f.calib.range_min))
    return _replace(f, range=dataclasses.replace(r, range=v))


def _range_at_max(f):
    """Every third range reading at the calibration's ``range_max`` (a rangefinder that reports
    its maximum for a missing echo, intermittently: a poor surface)."""
    r = f.range
    v = np.where(np.arange(len(r)) % 3 == 0, float(f.calib.range_max), r.range)
    return _replace(f, range=dataclasses.replace(r, range=v))


def _flow_fault(fn: Callable) -> Callable:
    """A row builder from ``fn(flight) -> faulty flight`` on the flow-deck base."""

    def build(ctx: Context, folder: Path) -> Path:
        return _write(fn(ctx.flow_deck()), folder)

    return build


def _flow_rejected(f):
    """Every flow reading's quality 0 (below the gate): a stream rejected entirely."""
    fl = f.flow
    return _replace(f, flow=dataclasses.replace(fl, quality=np.zeros(len(fl))))


def _range_blind(ctx: Context, folder: Path) -> Path:
    """The flow deck's rangefinder blinded from 8 to 13 s (no echo at 0.4-1.3 m over the floor,
    within its 8 m reach), reporting its maximum for it (the simulator's ``range_blind`` and
    ``range_no_echo_at_max``: its other readings are the base flight's)."""
    return _write(ctx.flow_deck_with(range_no_echo_at_max=True, range_blind=((8.0, 13.0),)), folder)


def _range_silent(ctx: Context, folder: Path) -> Path:
    """The flow deck's rangefinder silent from 8 to 13 s (no reading at all at 0.4-1.3 m over
    the floor: the simulator's ``range_blind`` without ``range_no_echo_at_max``; its other
    readings are the base flight's)."""
    return _write(ctx.flow_deck_with(range_blind=((8.0, 13.0),)), folder)


def _range_spikes(f, frac: float = 0.05):
    r = f.range
    rng = np.random.default_rng(7)
    v = r.range.copy()
    hit = rng.random(len(v)) < frac
    v[hit] *= rng.uniform(0.2, 0.5, hit.sum())
    return _replace(f, range=dataclasses.replace(r, range=v))


def _body_T_cam_identity(f):
    return _replace(f, calib=dataclasses.replace(f.calib, body_T_cam=np.eye(4)))


def _no_overlap(f):
    s = f.slam
    return _replace(f, slam=dataclasses.replace(s, t=s.t + 1000.0))


def _sim_reset(ctx: Context, folder: Path) -> Path:
    return _write(ctx.sim_with(slam_resets=(12.0,)), folder)


def _sim_platform(ctx: Context, folder: Path) -> Path:
    """The route's half at x > 0 (two-turns spans x -1.1..1.1 m) over a 0.5 m platform: each
    edge a terrain step the rangefinder sees."""
    return _write(ctx.sim_with(terrain_steps=((0.0, -1.0, 2.0, 3.5, 0.5),)), folder)


def _sim_dropout(ctx: Context, folder: Path) -> Path:
    return _write(ctx.sim_with(slam_dropouts=((10.0, 13.0),)), folder)


# --- camera faults ----------------------------------------------------------------------------


def _camera_copy(ctx: Context, folder: Path) -> Path:
    src = ctx.camera_folder()
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(src, folder)
    return folder


def _image_files(folder: Path) -> list[Path]:
    return sorted((folder / "cam0").glob("*.png"))


def _camera_unreadable(ctx: Context, folder: Path) -> Path:
    f = _camera_copy(ctx, folder)
    files = _image_files(f)
    files[len(files) // 2].write_bytes(b"not a png\n")
    return f


def _camera_frozen(ctx: Context, folder: Path) -> Path:
    """The camera delivers the same frame for 4 s (a frozen driver)."""
    f = _camera_copy(ctx, folder)
    files = _image_files(f)
    n = len(files)
    i0 = n // 2
    for p in files[i0 + 1 : i0 + 1 + int(0.2 * n)]:
        shutil.copyfile(files[i0], p)
    return f


def _camera_dropped(ctx: Context, folder: Path) -> Path:
    """30 % of the camera frames lost (deleted with their rows of images.csv)."""
    f = _camera_copy(ctx, folder)
    csv = f / "images.csv"
    lines = csv.read_text().splitlines()
    rng = np.random.default_rng(3)
    keep = [lines[0]]
    for line in lines[1:]:
        if rng.random() < 0.3:
            name = line.split(",")[-1].strip()
            (f / "images" / Path(name).name).unlink(missing_ok=True)
        else:
            keep.append(line)
    csv.write_text("\n".join(keep) + "\n")
    return f


# --- corrupt files ----------------------------------------------------------------------------


def _sim_copy(ctx: Context, folder: Path) -> Path:
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(ctx.sim_folder(), folder)
    return folder


def _edit_line(path: Path, index: int, fn: Callable[[str], str]) -> None:
    lines = path.read_text().splitlines()
    lines[index] = fn(lines[index])
    path.write_text("\n".join(lines) + "\n")


def _file_fault(stream: str, kind: str) -> Callable:
    def build(ctx: Context, folder: Path) -> Path:
        f = _sim_copy(ctx, folder)
        p = f / f"{stream}.csv"
        lines = p.read_text().splitlines()
        i = len(lines) // 2
        if kind == "duplicate":
            lines.insert(i, lines[i])
        elif kind == "out-of-order":
            lines[i], lines[i + 1] = lines[i + 1], lines[i]
        elif kind == "nan":
            parts = lines[i].split(",")
            parts[1] = "nan"
            lines[i] = ",".join(parts)
        elif kind == "truncated":
            lines = lines[:i] + [lines[i][: len(lines[i]) // 2]]
        elif kind == "text":
            lines[i] = "garbage," * (lines[i].count(",")) + "x"
        p.write_text("\n".join(lines) + "\n")
        return f

    return build


def _corrupt_calib(ctx: Context, folder: Path) -> Path:
    f = _sim_copy(ctx, folder)
    calib = next(p for p in f.iterdir() if p.name.startswith("calib"))
    calib.write_text(calib.read_text()[: len(calib.read_text()) // 3] + "\n: [unclosed\n")
    return f


def _corrupt_meta(ctx: Context, folder: Path) -> Path:
    f = _sim_copy(ctx, folder)
    meta = next((p for p in f.iterdir() if p.name.startswith("meta")), None) or f / "meta.json"
    meta.write_text('{"name": "x", ')
    return f


def _binary_file(suffix: str, content: bytes) -> Callable:
    def build(ctx: Context, folder: Path) -> Path:
        folder.mkdir(parents=True, exist_ok=True)
        p = folder / f"corrupt{suffix}"
        p.write_bytes(content)
        return p

    return build


_RANDOM = np.random.default_rng(11).integers(0, 256, 4096, dtype=np.uint8).tobytes()


# --- MH_01 faults -----------------------------------------------------------------------------


def _mh01_doc() -> dict:
    import tomllib

    return tomllib.loads(MH01_MANIFEST.read_text())


def _mh01_root() -> Path:
    return (MH01_MANIFEST.parent / _mh01_doc()["root"]).resolve()


def _write_manifest(doc: dict, folder: Path) -> Path:
    """A manifest with every path absolute (the untouched files are read in place)."""
    folder.mkdir(parents=True, exist_ok=True)
    root = _mh01_root()
    out = [f'name = "{doc["name"]}-fault"', f'root = "{root}"']

    def table(name: str, spec: dict) -> None:
        # Scalars and arrays first, then the sub-tables (e.g. [calib.imu_noise]) as their own.
        out.append(f"[{name}]")
        out.extend(f"{k} = {json.dumps(v)}" for k, v in spec.items() if not isinstance(v, dict))
        for k, v in spec.items():
            if isinstance(v, dict):
                table(f"{name}.{k}", v)

    for name, spec in doc.items():
        if isinstance(spec, dict) and name != "references":
            table(name, spec)
    p = folder / "flight.toml"
    p.write_text("\n".join(out) + "\n")
    return p


def _mh01_with(stream: str, edit: Callable[[list[str]], list[str]]) -> Callable:
    """A MH_01 copy whose ``stream`` file (a text file) went through ``edit(lines)``."""

    def build(ctx: Context, folder: Path) -> Path:
        doc = _mh01_doc()
        src = _mh01_root() / doc[stream]["path"]
        folder.mkdir(parents=True, exist_ok=True)
        dst = folder / src.name
        dst.write_text("\n".join(edit(src.read_text().splitlines())) + "\n")
        doc[stream]["path"] = str(dst)
        return _write_manifest(doc, folder)

    return build


def _mh01_nominal(ctx: Context, folder: Path) -> Path:
    return _write_manifest(_mh01_doc(), folder)


def _tum_rows(lines: list[str]) -> tuple[list[str], np.ndarray, np.ndarray]:
    rows = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    a = np.array([[float(x) for x in ln.split()] for ln in rows])
    return rows, a[:, 0] * 1e-9, a


def _tum_lines(a: np.ndarray) -> list[str]:
    return [f"{int(round(r[0]))}.000000 " + " ".join(f"{x:.9f}" for x in r[1:]) for r in a]


def _slam_gap_lines(t0: float, t1: float) -> Callable:
    def edit(lines):
        _, t, a = _tum_rows(lines)
        rel = t - t[0]
        return _tum_lines(a[~((rel >= t0) & (rel < t1))])

    return edit


def _slam_jump_lines(t_jump: float, jump: float) -> Callable:
    def edit(lines):
        _, t, a = _tum_rows(lines)
        a = a.copy()
        a[t - t[0] >= t_jump, 1] += jump
        return _tum_lines(a)

    return edit


def _slam_shift_lines(dt: float) -> Callable:
    def edit(lines):
        _, _, a = _tum_rows(lines)
        a = a.copy()
        a[:, 0] += dt * 1e9
        return _tum_lines(a)

    return edit


def _imu_half(lines: list[str]) -> list[str]:
    return lines[: len(lines) // 2]


def _mh01_calib_identity(ctx: Context, folder: Path) -> Path:
    """EuRoC.yaml with ``IMU.T_b_c1`` (body_T_cam) set to the identity."""
    import re

    doc = _mh01_doc()
    src = _mh01_root() / doc["calib"]["path"]
    text = src.read_text()
    ident = (
        "[1.0, 0.0, 0.0, 0.0,\n  0.0, 1.0, 0.0, 0.0,\n  0.0, 0.0, 1.0, 0.0,\n  0.0, 0.0, 0.0, 1.0]"
    )
    new, n = re.subn(r"(IMU\.T_b_c1:.*?data:\s*)\[[^\]]*\]", r"\g<1>" + ident, text, flags=re.S)
    if n != 1:
        raise RuntimeError(f"{src}: IMU.T_b_c1 not found")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / src.name).write_text(new)
    doc["calib"]["path"] = str(folder / src.name)
    return _write_manifest(doc, folder)


def _mh01_corrupt(stream: str, kind: str) -> Callable:
    def edit(lines):
        i = len(lines) // 2
        if kind == "text":
            lines[i] = "this is not a number " + lines[i]
        elif kind == "out-of-order":
            lines[i], lines[i + 10] = lines[i + 10], lines[i]
        return lines

    return _mh01_with(stream, edit)


def _mh01_bad_manifest(ctx: Context, folder: Path) -> Path:
    p = _mh01_nominal(ctx, folder)
    p.write_text(p.read_text().replace("[imu]", "[imu\n"))
    return p


# --- events rows (fed straight into the push-API smoother) ------------------------------------


def _events_fault(kind: str) -> Callable:
    """The nominal simulated flight's events, perturbed in the stream a live link delivers."""

    def build(ctx: Context):
        from fgnav.datasets.events import ImuSample, SlamPose, replay_flight

        from fgnav.solvers.online import PUSH_STREAMS

        f = ctx.sim()
        evs = list(replay_flight(f, [n for n in PUSH_STREAMS if getattr(f, n) is not None]))
        rng = np.random.default_rng(5)
        out = []
        for ev in evs:
            if kind == "imu-duplicate" and isinstance(ev, ImuSample) and rng.random() < 0.05:
                out += [ev, ev]
            elif kind == "imu-nan" and isinstance(ev, ImuSample) and rng.random() < 0.02:
                out.append(ev._replace(body_accel=np.full(3, np.nan)))
            elif kind == "imu-out-of-order" and isinstance(ev, ImuSample) and rng.random() < 0.05:
                out.append(ev)
                if len(out) >= 2:
                    out[-1], out[-2] = out[-2], out[-1]
            elif kind == "imu-stamp-outlier" and isinstance(ev, ImuSample) and rng.random() < 0.002:
                # A corrupted stamp, 1000 s ahead or 50 s behind; the next sample is right.
                dt = 1000.0 if rng.random() < 0.5 else -50.0
                out.append(ev._replace(t=ev.t + dt, arrival=ev.arrival + dt))
            elif kind == "implausible" and rng.random() < 0.002:
                # Finite but impossible: 1e30 m/s^2, or a SLAM position 1e30 units out.
                if isinstance(ev, ImuSample):
                    out.append(ev._replace(body_accel=np.array([1e30, 0.0, 9.8])))
                elif isinstance(ev, SlamPose):
                    out.append(ev._replace(slam_t_cam=np.array([-1e30, 0.0, 0.0])))
                else:
                    out.append(ev)
            elif kind == "slam-out-of-order" and isinstance(ev, SlamPose) and rng.random() < 0.1:
                # Delivered 150 ms late: after newer poses.
                out.append(ev._replace(arrival=ev.arrival + 0.15))
            else:
                out.append(ev)
        if kind == "slam-out-of-order":
            out.sort(key=lambda e: e.arrival)
        return f, out

    return build


def _events_flow_no_range(ctx: Context):
    """The flow-deck base's events without its rangefinder stream, as a live link delivers them
    (``fgnav online`` refuses the file: no height for the flow)."""
    from fgnav.datasets.events import replay_flight

    from fgnav.solvers.online import PUSH_STREAMS

    f = _replace(ctx.flow_deck(), range=None)
    return f, list(replay_flight(f, [n for n in PUSH_STREAMS if getattr(f, n) is not None]))


# --- the table of rows ------------------------------------------------------------------------


def rows() -> list[Row]:
    R = Row
    sim = "sim"
    return [
        R("nominal", sim, lambda c, d: c.sim_folder(), "no fault", _both({"recovered"}), True),
        R(
            "slam-gap-3s",
            sim,
            _sim_dropout,
            "SLAM tracking lost 10-13 s (sim option)",
            _both(OK),
            True,
        ),
        R(
            "slam-cut-3s",
            sim,
            _sim_fault(lambda f: _slam_cut(f, 10.0, 13.0)),
            "SLAM poses 10-13 s removed from the file",
            _both(OK),
        ),
        R(
            "body_T_cam-identity",
            sim,
            _sim_fault(_body_T_cam_identity),
            "calibration body_T_cam replaced by the identity",
            {"batch": OK_OR_STOP, "online": OK},
            True,
        ),
        R(
            "hover:nominal",
            "sim-hover",
            lambda c, d: _write(c.hover(), d),
            "no fault (hover in gusts, 30 s)",
            _both({"recovered"}),
        ),
        R(
            "hover:body_T_cam-identity",
            "sim-hover",
            lambda c, d: _write(_body_T_cam_identity(c.hover()), d),
            "hover: body_T_cam replaced by the identity (no turns for the SLAM-vs-gyro check)",
            _both(OK),
        ),
        R(
            "gyro-saturated-0.5",
            sim,
            _sim_fault(_gyro_saturated),
            "gyro clipped at +-0.5 rad/s",
            _both({"recovered"}),
            True,
        ),
        R(
            "accel-clipped",
            sim,
            _sim_fault(_accel_clipped),
            "accelerometer clipped at its 97th |value| percentile",
            _both(OK),
            True,
        ),
        R(
            "accel-dead",
            sim,
            _sim_fault(_accel_dead),
            "accelerometer reads exactly 0 from 10 to 13 s",
            _both(OK),
            True,
        ),
        R(
            "imu-gap-2s",
            sim,
            _sim_fault(lambda f: _imu_cut(f, 10.0, 12.0)),
            "IMU samples 10-12 s missing",
            {"batch": OK, "online": {"recovered"}},
            True,
        ),
        R(
            "imu-gap-10s",
            sim,
            _sim_fault(lambda f: _imu_cut(f, 8.0, 18.0)),
            "IMU samples 8-18 s missing",
            {"batch": OK_OR_STOP, "online": {"recovered"}},
        ),
        R(
            "slam-jump-1m",
            sim,
            _sim_fault(_slam_jump),
            "SLAM positions jump by 1 m (metric) at 12 s",
            _both(OK),
            True,
        ),
        R(
            "slam-mirrored-y",
            sim,
            _sim_fault(_slam_mirrored),
            "SLAM frame left-handed (y sign flipped in positions and rotations)",
            {"batch": OK, "online": {"named"}},
        ),
        R(
            "slam-scale-drift-5pct",
            sim,
            _sim_fault(_slam_scale_drift),
            "SLAM scale running away at 5 %/s (positions times 1 + 0.05 t)",
            _both({"named"}),
        ),
        R(
            "slam-offset-0.3s",
            sim,
            _sim_fault(_slam_offset),
            "SLAM stamps 0.3 s late (clock offset)",
            _both(OK),
            True,
        ),
        R(
            "slam-latency-0.5s",
            sim,
            _sim_fault(_slam_latency),
            "SLAM poses arrive 0.5 s after capture",
            _both(OK),
        ),
        R(
            "range-stuck-8s",
            sim,
            _sim_fault(_range_stuck),
            "rangefinder repeats its 8 s reading to the end",
            {"batch": {"recovered"}, "online": OK},
            True,
        ),
        R(
            "range-at-min",
            sim,
            _sim_fault(_range_at_min),
            "every range reading at the calibration's range_min (pinned at its floor)",
            _both({"recovered"}),
            True,
        ),
        R(
            "range-at-max",
            sim,
            _sim_fault(_range_at_max),
            "every third range reading at the calibration's range_max (missing echoes)",
            _both({"recovered"}),
        ),
        R(
            "range-spikes",
            sim,
            _sim_fault(_range_spikes),
            "5 % of range readings shortened to 20-50 %",
            _both(OK),
        ),
        R(
            "terrain-platform",
            sim,
            _sim_platform,
            "half the route over a 0.5 m platform (terrain steps under the rangefinder)",
            _both(OK),
        ),
        R(
            "slam-reset",
            sim,
            _sim_reset,
            "SLAM map reset at 12 s (new session and scale)",
            _both(OK),
            True,
        ),
        R(
            "no-overlap",
            sim,
            _sim_fault(_no_overlap),
            "SLAM stamps 1000 s later than the IMU",
            _both(ERR),
        ),
        R(
            "lag-0",
            sim,
            lambda c, d: c.sim_folder(),
            "--lag 0",
            {"online": ERR},
            extra_args=("--lag", "0"),
        ),
        R(
            "negative-sigma",
            sim,
            lambda c, d: c.sim_folder(),
            "[graph] slam_sigma_m = -0.01",
            _both(ERR),
            config="[graph]\nslam_sigma_m = -0.01\n",
        ),
        R(
            "camera-unreadable-png",
            "sim-camera",
            _camera_unreadable,
            "one PNG of the camera is not an image",
            _both(OK),
        ),
        R(
            "camera-frozen",
            "sim-camera",
            _camera_frozen,
            "the camera repeats one frame for 4 s",
            _both(OK),
        ),
        R(
            "camera-dropped-30pc",
            "sim-camera",
            _camera_dropped,
            "30 % of the camera frames dropped",
            _both(OK),
        ),
        R(
            "file:imu-duplicate",
            sim,
            _file_fault("imu", "duplicate"),
            "imu.csv: one line repeated",
            _both(ERR),
            True,
        ),
        R(
            "file:imu-out-of-order",
            sim,
            _file_fault("imu", "out-of-order"),
            "imu.csv: two lines swapped",
            _both(ERR),
        ),
        R("file:imu-nan", sim, _file_fault("imu", "nan"), "imu.csv: a nan value", _both(ERR)),
        R(
            "file:slam-truncated",
            sim,
            _file_fault("slam", "truncated"),
            "slam.csv cut in the middle of a line",
            _both(ERR),
            True,
        ),
        R(
            "file:range-text",
            sim,
            _file_fault("range", "text"),
            "range.csv: a line of text",
            _both(ERR),
        ),
        R("file:calib-yaml", sim, _corrupt_calib, "calibration YAML cut", _both(ERR)),
        R("file:meta-json", sim, _corrupt_meta, "meta.json cut", _both(ANY)),
        R(
            "file:ulog-random",
            sim,
            _binary_file(".ulg", _RANDOM),
            "a .ulg of random bytes",
            _both(ERR),
        ),
        R(
            "file:bag-random",
            sim,
            _binary_file(".bag", _RANDOM),
            "a ROS 1 .bag of random bytes",
            _both(ERR),
        ),
        R(
            "file:mcap-random",
            sim,
            _binary_file(".mcap", _RANDOM),
            "a ROS 2 .mcap of random bytes",
            _both(ERR),
        ),
        R(
            "file:manifest-toml",
            "mh01",
            _mh01_bad_manifest,
            "manifest with a broken table",
            _both(ERR),
        ),
        R(
            "events:imu-duplicate",
            sim,
            _events_fault("imu-duplicate"),
            "5 % of IMU samples delivered twice",
            {"online": OK},
            True,
        ),
        R(
            "events:imu-out-of-order",
            sim,
            _events_fault("imu-out-of-order"),
            "5 % of IMU samples swapped with the previous",
            {"online": OK},
        ),
        R(
            "events:imu-nan",
            sim,
            _events_fault("imu-nan"),
            "2 % of IMU samples NaN",
            {"online": OK},
            True,
        ),
        R(
            "events:imu-stamp-outlier",
            sim,
            _events_fault("imu-stamp-outlier"),
            "0.2 % of IMU stamps 1000 s ahead or 50 s behind (one sample each)",
            {"online": {"recovered"}},
            True,
        ),
        R(
            "events:implausible",
            sim,
            _events_fault("implausible"),
            "0.2 % of IMU samples 1e30 m/s^2 and of SLAM positions 1e30 units",
            {"online": {"recovered"}},
            True,
        ),
        R(
            "events:slam-out-of-order",
            sim,
            _events_fault("slam-out-of-order"),
            "10 % of SLAM poses delivered 150 ms late (after newer ones)",
            {"online": OK},
        ),
        R(
            "flow:nominal",
            "sim-flow",
            lambda c, d: _write(c.flow_deck(), d),
            "no fault (Crazyflie-like flow deck: IMU, flow, range)",
            _both({"recovered"}),
        ),
        R(
            "flow:range-blind-5s",
            "sim-flow",
            _range_blind,
            "flow deck: rangefinder blinded 8-13 s at 0.4-1.3 m, reporting its 8 m maximum",
            _both({"named"}),
            True,
            names=("range-at-max",),
        ),
        R(
            "flow:range-silent-5s",
            "sim-flow",
            _range_silent,
            "flow deck: rangefinder silent 8-13 s at 0.4-1.3 m (no readings at all)",
            _both({"named"}),
            True,
            names=("range-silent",),
        ),
        R(
            "flow:rejected",
            "sim-flow",
            _flow_fault(_flow_rejected),
            "flow deck: every flow reading's quality 0 (the stream rejected)",
            _both({"named"}),
        ),
        R(
            "flow:no-range",
            "sim-flow",
            _flow_fault(lambda f: _replace(f, range=None)),
            "flow deck without its rangefinder stream (no height for the flow)",
            _both(ERR),
            True,
        ),
        R(
            "events:flow-no-range",
            "sim-flow",
            _events_flow_no_range,
            "flow deck without its rangefinder, fed to the push API (a live link)",
            {"online": {"named"}},
            True,
        ),
        R("mh01:nominal", "mh01", _mh01_nominal, "no fault", _both({"recovered"})),
        R(
            "mh01:slam-cut-3s",
            "mh01",
            _mh01_with("slam", _slam_gap_lines(60.0, 63.0)),
            "ORB-SLAM3 poses 60-63 s removed",
            _both(OK),
            True,
        ),
        R(
            "mh01:slam-jump",
            "mh01",
            _mh01_with("slam", _slam_jump_lines(90.0, 0.2)),
            "SLAM positions jump by 0.2 SLAM units (~1 m) at 90 s",
            _both({"recovered"}),
            True,
        ),
        R(
            "mh01:slam-offset-0.3s",
            "mh01",
            _mh01_with("slam", _slam_shift_lines(0.3)),
            "SLAM stamps 0.3 s late",
            _both(OK),
        ),
        R("mh01:imu-half", "mh01", _mh01_with("imu", _imu_half), "IMU file cut at half", _both(OK)),
        R(
            "mh01:body_T_cam-identity",
            "mh01",
            _mh01_calib_identity,
            "IMU.T_b_c1 set to the identity",
            {"batch": OK_OR_STOP, "online": OK},
        ),
        R(
            "mh01:imu-text",
            "mh01",
            _mh01_corrupt("imu", "text"),
            "EuRoC imu csv: a text line",
            _both(ERR),
            names_input=True,
        ),
        R(
            "mh01:slam-out-of-order",
            "mh01",
            _mh01_corrupt("slam", "out-of-order"),
            "TUM SLAM file: two lines swapped",
            _both(ANY),
            names_input=True,
        ),
    ]


# ----------------------------------------------------------------------------------------------
# Running
# ----------------------------------------------------------------------------------------------


@dataclass
class Run:
    """One command on one row."""

    row: str
    command: str
    outcome: str
    exit_code: int | None
    ate_m: float | None
    nominal_ate_m: float | None
    detectors: list[str]
    warnings: list[str]
    error: str | None
    counts: str
    seconds: float
    expected: list[str]
    ok: bool


class _Capture(logging.Handler):
    def __init__(self, stream: io.StringIO):
        super().__init__(logging.INFO)
        self.stream = stream
        self.warnings: list[str] = []
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        msg = self.format(record)
        self.stream.write(msg + "\n")
        if record.levelno >= logging.WARNING:
            self.warnings.append(msg)


def _cli(argv: list[str]) -> tuple[int | None, str, str, list[str], str | None]:
    """``fgnav.cli.main(argv)`` in this process: exit code, stdout, stderr, warnings, traceback."""
    from fgnav.cli import main

    out, err = io.StringIO(), io.StringIO()
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    cap = _Capture(err)
    root.handlers = [cap]
    root.setLevel(logging.INFO)
    tb = None
    code = None
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as e:
                code = int(e.code or 0)
            except Exception:  # noqa: BLE001 - a traceback is what the matrix looks for
                tb = traceback.format_exc()
    finally:
        root.handlers, _ = saved
        root.setLevel(saved[1])
    return code, out.getvalue(), err.getvalue(), cap.warnings, tb


def _health_names(info: dict) -> list[str]:
    h = info.get("health") or {}
    names = [f"{k} {v}" for k, v in sorted((h.get("detectors") or {}).items()) if v]
    if h.get("status") not in (None, "ok"):
        names.append(f"status {h['status']}")
    if info.get("lm_converged") is False:
        names.append("lm-not-converged")
    if info.get("reset_counter"):
        names.append(f"resets {info['reset_counter']}")
    return names


def _counts_text(info: dict) -> str:
    parts = []
    d = info.get("dropped") or {}
    sk = info.get("skipped") or {}
    n_d = sum(v for v in d.values() if isinstance(v, int))
    n_s = sum(v for v in sk.values() if isinstance(v, int)) if isinstance(sk, dict) else 0
    if n_d:
        top = sorted(d.items(), key=lambda kv: -kv[1])[:2]
        parts.append(f"dropped {n_d} (" + ", ".join(f"{k} {v}" for k, v in top) + ")")
    if n_s:
        parts.append(f"skipped {n_s}")
    return "; ".join(parts)


def _classify(
    row: Row, command: str, code, stdout: str, stderr: str, warnings, tb, summary, nominal
) -> tuple[str, float | None, list[str], str | None]:
    ate = None
    detectors: list[str] = []
    if summary is not None:
        m = summary.get("metrics") or {}
        ate = m.get("ate_rmse_m")
        detectors = _health_names(summary.get("info") or {})
    if tb is not None:
        return "FAIL", ate, detectors, tb.strip().splitlines()[-1]
    err_lines = [ln for ln in stderr.splitlines() if ": error: " in ln]
    if code == 1 and err_lines and "Traceback" not in stderr + stdout:
        return "error", ate, detectors, err_lines[-1][:160]
    screen_named = bool(warnings) or "health:" in stdout
    named = screen_named and bool(detectors or (summary and _summary_warns(summary)))
    if (
        row.names
        and screen_named
        and all(any(d.split()[0] == n for d in detectors) for n in row.names)
    ):
        return "named", ate, detectors, None
    if ate is not None and nominal is not None and ate <= RECOVER_FACTOR * nominal:
        outcome = "recovered" if code == 0 else ("named" if named else "FAIL")
        return outcome, ate, detectors, None
    if named or (code not in (0, None) and screen_named):
        return "named", ate, detectors, None
    return "FAIL", ate, detectors, (stderr.strip().splitlines() or [""])[-1][:160]


def _summary_warns(summary: dict) -> bool:
    info = summary.get("info") or {}
    return bool(
        info.get("solver_failures")
        or (info.get("slam_gyro_check") or {}).get("body_R_cam_ok") is False
        or info.get("lm_converged") is False
        or (info.get("health") or {}).get("status") not in (None, "ok")
    )


def _run_cli_row(row: Row, command: str, ctx: Context, nominal: dict) -> Run:
    folder = ctx.tmp / row.name.replace(":", "_")
    t0 = time.perf_counter()
    tb = None
    try:
        path = row.build(ctx, folder / "input")
    except Exception:  # noqa: BLE001
        tb = traceback.format_exc()
        path = None
    out = folder / f"out-{command}"
    summary = None
    code, stdout, stderr, warnings = None, "", "", []
    if tb is None:
        argv = [command, str(path), "--out", str(out), "--no-progress", *row.extra_args]
        if row.config:
            cfg = folder / "config.toml"
            folder.mkdir(parents=True, exist_ok=True)
            cfg.write_text(row.config)
            argv += ["--config", str(cfg)]
        code, stdout, stderr, warnings, tb = _cli(argv)
        if (out / "summary.json").exists():
            summary = json.loads((out / "summary.json").read_text())
    nom = nominal.get((row.base, command))
    if nom is None and row.name in NOMINAL_ROWS.values() and summary is not None:
        nom = (summary.get("metrics") or {}).get("ate_rmse_m")
    outcome, ate, det, err = _classify(
        row, command, code, stdout, stderr, warnings, tb, summary, nom
    )
    if (
        outcome != "FAIL"
        and code == 0
        and ate is not None
        and ate > SILENT_ATE_MAX_M
        and not warnings
    ):
        outcome, err = "FAIL", f"ATE {ate:.2f} m with exit 0 and no warning"
    names_input = row.names_input or row.name.startswith("file:")
    if outcome == "error" and names_input and str(folder / "input") not in (err or ""):
        outcome, err = "FAIL", f"the error names no input file: {err}"
    info = (summary or {}).get("info") or {}
    return Run(
        row.name,
        command,
        outcome,
        code,
        ate,
        nom,
        det,
        warnings,
        err,
        _counts_text(info),
        time.perf_counter() - t0,
        sorted(row.expect.get(command, set())),
        outcome in row.expect.get(command, set()),
    )


def _run_events_row(row: Row, ctx: Context, nominal: dict) -> Run:
    from fgnav.compare import score_estimate
    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.online import OnlineSmoother

    t0 = time.perf_counter()
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    err = io.StringIO()
    cap = _Capture(err)
    root.handlers = [cap]
    tb = None
    ate = None
    det: list[str] = []
    info: dict = {}
    try:
        flight, events = row.build(ctx)
        sm = OnlineSmoother(flight.calib, FixedLagOptions(), flight.name)
        for ev in events:
            sm.feed(ev)
        est = sm.result()
        info = est.info
        ate = score_estimate(flight, est).ate_rmse_m
        det = _health_names(info)
    except Exception:  # noqa: BLE001
        tb = traceback.format_exc()
    finally:
        root.handlers, _ = saved
        root.setLevel(saved[1])
    nom = nominal.get((row.base, "online"))
    if tb:
        outcome, msg = "FAIL", tb.strip().splitlines()[-1]
    elif nom is not None and ate is not None and ate <= RECOVER_FACTOR * nom:
        outcome, msg = "recovered", None
    elif det and cap.warnings:
        outcome, msg = "named", None
    else:
        outcome, msg = "FAIL", f"ATE {ate} with nothing named"
    dropped = info.get("dropped") or {}
    counts = ", ".join(f"{k} {v}" for k, v in sorted(dropped.items(), key=lambda kv: -kv[1])[:2])
    return Run(
        row.name,
        "online",
        outcome,
        None,
        ate,
        nom,
        det,
        cap.warnings,
        msg,
        f"dropped {counts}" if counts else "",
        time.perf_counter() - t0,
        sorted(row.expect["online"]),
        outcome in row.expect["online"],
    )


def run_matrix(selected: list[Row], tmp: Path, log_progress: bool = True) -> list[Run]:
    ctx = Context(tmp)
    nominal: dict[tuple[str, str], float] = {}
    bases = {r.base for r in selected}
    # Nominal ATEs first (each base's "nominal" row, run whether selected or not).
    nominal_rows = NOMINAL_ROWS
    all_rows = {r.name: r for r in [*rows(), _camera_nominal_row()]}
    runs: list[Run] = []
    for base in sorted(bases):
        nrow = all_rows[nominal_rows[base]]
        for command in ("batch", "online"):
            r = _run_cli_row(nrow, command, ctx, nominal)
            nominal[(base, command)] = r.ate_m
            if nrow.name in {r.name for r in selected} or base == "sim-camera":
                runs.append(r)
            if log_progress:
                _progress(r)
    for row in selected:
        if row.name in nominal_rows.values():
            continue
        if row.name.startswith("events:"):
            r = _run_events_row(row, ctx, nominal)
            runs.append(r)
            if log_progress:
                _progress(r)
            continue
        for command in ("batch", "online"):
            if command not in row.expect:
                continue
            r = _run_cli_row(row, command, ctx, nominal)
            runs.append(r)
            if log_progress:
                _progress(r)
    return runs


def _camera_nominal_row() -> Row:
    return Row(
        "camera-nominal",
        "sim-camera",
        lambda c, d: c.camera_folder(),
        "no fault (camera)",
        _both({"recovered"}),
    )


def _progress(r: Run) -> None:
    print(
        f"  {r.row:28s} {r.command:6s} {r.outcome:9s} {r.seconds:6.1f} s",
        file=sys.stderr,
        flush=True,
    )


def _fmt_ate(r: Run) -> str:
    if r.ate_m is None:
        return "-"
    if r.nominal_ate_m:
        return f"{r.ate_m:.3f} ({r.ate_m / r.nominal_ate_m:.1f}x)"
    return f"{r.ate_m:.3f}"


def table(runs: list[Run], descriptions: dict[str, str]) -> str:
    lines = [
        "| fault | what | command | outcome | detector / what was said | ATE [m] (x nominal) | "
        "counts |",
        "|:--|:--|:--|:--|:--|--:|:--|",
    ]
    for r in runs:
        said = ", ".join(r.detectors) if r.detectors else ""
        if r.error:
            said = (said + "; " if said else "") + r.error.replace("|", "/")
        elif not said and r.warnings:
            said = r.warnings[0].split(": ", 1)[-1][:90].replace("|", "/")
        mark = "" if r.ok else " (UNEXPECTED)"
        lines.append(
            f"| {r.row} | {descriptions.get(r.row, '')} | {r.command} | {r.outcome}{mark} | "
            f"{said} | {_fmt_ate(r)} | {r.counts} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the test subset (about 3 minutes)")
    ap.add_argument("--only", default=None, help="comma-separated row names")
    ap.add_argument("--no-mh01", action="store_true", help="skip the EuRoC MH_01 rows")
    ap.add_argument("--json", default=None, help="write the runs as JSON here")
    ap.add_argument("--keep", default=None, help="work in this folder (kept) instead of a tmp")
    args = ap.parse_args(argv)
    all_rows = rows()
    if args.only:
        names = {s.strip() for s in args.only.split(",")}
        unknown = names - {r.name for r in all_rows}
        if unknown:
            ap.error(f"unknown rows {sorted(unknown)}")
        selected = [r for r in all_rows if r.name in names]
    elif args.quick:
        selected = [r for r in all_rows if r.quick]
    else:
        selected = all_rows
    mh01_ok = (_mh01_root() / "imu0").is_dir()
    if args.no_mh01 or not mh01_ok:
        if not mh01_ok:
            print(f"MH_01 not found under {_mh01_root()}: its rows skipped", file=sys.stderr)
        selected = [r for r in selected if r.base != "mh01"]
    t0 = time.perf_counter()
    if args.keep:
        tmp = Path(args.keep)
        tmp.mkdir(parents=True, exist_ok=True)
        runs = run_matrix(selected, tmp)
    else:
        with tempfile.TemporaryDirectory(prefix="fault-matrix-") as d:
            runs = run_matrix(selected, Path(d))
    desc = {r.name: r.what for r in [*all_rows, _camera_nominal_row()]}
    print(table(runs, desc))
    bad = [r for r in runs if not r.ok]
    print(
        f"\n{len(runs)} runs, {len(bad)} unexpected, {time.perf_counter() - t0:.0f} s "
        f"(recovered: ATE <= {RECOVER_FACTOR:g}x nominal)"
    )
    if args.json:
        Path(args.json).write_text(
            json.dumps([dataclasses.asdict(r) for r in runs], indent=1, default=_json_default)
        )
    return 1 if bad else 0


def _json_default(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return str(x)


if __name__ == "__main__":
    sys.exit(main())
