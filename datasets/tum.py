"""TUM trajectory files: ``t tx ty tz qx qy qz qw``, one pose per line, whitespace separated.

The format of the TUM RGB-D benchmark, evo and ORB-SLAM3's ``f_*.txt``/``kf_*.txt`` outputs.
The pose maps points from the moving frame into the file's world frame (``world_T_body`` for a
body trajectory, ``slam_T_cam`` for SLAM camera poses); the quaternion is Hamilton ``[x, y, z, w]``
in the file and ``[w, x, y, z]`` in fgnav. Lines starting with ``#`` are comments.

Time stamps: seconds (TUM) or integer nanoseconds (ORB-SLAM3 on EuRoC writes
``1403636579913555712.000000``). With ``time_unit="auto"`` a file whose largest stamp is at least
:data:`NS_THRESHOLD` (1e11) is read as nanoseconds: 1e11 s is more than 3,000 years, so no
seconds stamp reaches it, while any ns stamp of an epoch clock does (1.4e18). Nanosecond stamps
counted from boot and smaller than 1e11 (first 100 s) would be misread: pass ``time_unit="ns"``.
The decision is logged and appended to ``notes``. Nanosecond stamps are parsed exactly from the
text (a float64 cannot hold 1.4e18 to the ns) and converted to float seconds.

Rows that repeat the previous row exactly (same time and pose; ORB-SLAM3 writes such lines when
tracking is lost at the end of a sequence) are skipped, counted, logged and noted. Everything else
that is wrong is an error naming file and line: a wrong column count, a non-numeric or non-finite
value, a time stamp not after the previous one, a quaternion whose norm is not 1.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from . import _tables
from .errors import FlightFormatError, note
from .geometry import quat_wxyz_to_xyzw, quat_xyzw_to_wxyz
from .types import SlamSeries, Trajectory

log = logging.getLogger(__name__)

NS_THRESHOLD = 1e11
"""Time stamps at or above this value are nanoseconds (see the module docstring)."""

QUAT_NORM_TOL = 1e-3
"""Largest accepted deviation of a quaternion's norm from 1 (as in ``types._check_quat``)."""

TIME_UNITS = ("auto", "s", "ns")


def _read(
    path: str | Path, time_unit: str, notes: list[str] | None, what: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if time_unit not in TIME_UNITS:
        raise ValueError(f"time_unit must be one of {TIME_UNITS}, got {time_unit!r}")
    raw = _tables.read_raw(path, sep=None, header="none")
    _tables.check_widths(raw, (8,), "t tx ty tz qx qy qz qw")
    values = _tables.to_values(raw, range(8))
    unit = time_unit
    if unit == "auto":
        biggest = float(np.max(np.abs(values[:, 0])))
        unit = "ns" if biggest >= NS_THRESHOLD else "s"
        msg = (
            f"{raw.path}: time stamps read as "
            + ("nanoseconds" if unit == "ns" else "seconds")
            + f" (largest {biggest:.4g} {'>=' if unit == 'ns' else '<'} {NS_THRESHOLD:.0e})"
        )
        note(log, notes, msg, logging.INFO)
    if unit == "ns":
        values[:, 0] = _tables.ns_to_seconds(_tables.parse_ns(raw, 0).ns)
    t, values, lines = _tables.drop_repeated_rows(raw, values[:, 0], values, notes, what)
    _tables.check_increasing(raw, t, lines)
    q_wxyz = quat_xyzw_to_wxyz(values[:, 4:8])
    norms = np.linalg.norm(q_wxyz, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUAT_NORM_TOL)
    if bad.size:
        raise FlightFormatError(
            raw.path,
            f"quaternion qx qy qz qw has norm {norms[bad[0]]:.6f}, expected 1 "
            f"({bad.size} such line(s))",
            line=lines[int(bad[0])],
        )
    return t, values[:, 1:4].copy(), q_wxyz


def read_tum(
    path: str | Path, *, time_unit: str = "auto", notes: list[str] | None = None
) -> Trajectory:
    """Read a TUM file as a body trajectory.

    Args:
        path: the file.
        time_unit: ``"auto"`` (see module docstring), ``"s"`` or ``"ns"``.
        notes: list to which reader notes (time unit, skipped lines) are appended.

    Returns:
        Trajectory with ``t`` [s], ``world_t_body`` [file units, m for metric files] and
        ``world_q_body_wxyz``; no velocity or biases.

    Raises:
        FlightFormatError: naming file and line (see module docstring).
    """
    t, xyz, q = _read(path, time_unit, notes, "pose")
    return Trajectory(t=t, world_t_body=xyz, world_q_body_wxyz=q).check(str(path))


def read_tum_slam(
    path: str | Path,
    session: int = 0,
    *,
    time_unit: str = "auto",
    notes: list[str] | None = None,
) -> SlamSeries:
    """Read a TUM file of camera poses from a monocular SLAM system.

    Args:
        path: the file (e.g. ORB-SLAM3's ``f_dataset-MH01_mono.txt``).
        session: map/session id given to every pose (one map per file).
        time_unit: ``"auto"`` (see module docstring), ``"s"`` or ``"ns"``.
        notes: list to which reader notes are appended.

    Returns:
        SlamSeries with ``slam_t_cam`` [SLAM units] and ``slam_q_cam_wxyz`` (``slam_T_cam``).
    """
    t, xyz, q = _read(path, time_unit, notes, "SLAM pose")
    return SlamSeries(
        t=t,
        slam_t_cam=xyz,
        slam_q_cam_wxyz=q,
        session=np.full(len(t), int(session), dtype=np.int64),
    ).check(str(path))


def write_tum(path: str | Path, trajectory: Trajectory) -> Path:
    """Write ``t [s] tx ty tz qx qy qz qw`` with full precision (``repr`` of each float).

    ``read_tum`` of the file gives back the same arrays exactly (velocity and biases are not part
    of the format and are not written).
    """
    trajectory.check("trajectory")
    q_xyzw = quat_wxyz_to_xyzw(trajectory.world_q_body_wxyz)
    rows = np.column_stack([trajectory.t, trajectory.world_t_body, q_xyzw])
    lines = ["# t[s] tx ty tz qx qy qz qw"]
    lines += [" ".join(repr(float(v)) for v in row) for row in rows]
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text("\n".join(lines) + "\n")
    return p
