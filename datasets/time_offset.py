"""Clock offsets between two recordings of one motion, and the OptiTrack/Motive CSV reader.

:func:`estimate_time_offset` cross-correlates two scalar signals of the same motion recorded on
different clocks (e.g. tilt angle or angular-rate magnitude from a flight log and from motion
capture). Both are resampled on a common grid; for each candidate offset on that grid the Pearson
correlation over the overlap is computed; the best grid offset is refined to sub-sample precision
by a parabola through the correlation at the peak and its two neighbours.

Convention: ``t_a = t_b + offset_s`` for the same physical event, i.e. **add** ``offset_s`` to
clock-b times to express them on clock a.

:func:`read_motive_csv` reads a Motive "CSV export" (metadata line, then Type/Name/ID/kind/axis
header rows, then one row per frame) into a :class:`MotiveTake` whose trajectory is in fgnav's
z-up world (see :mod:`fgnav.datasets.frames`).

:func:`align_mocap` puts a mocap take on a flight log's clock: offset from tilt and from
angular-rate magnitude (two independent signals), then the fixed world and body rotations; its
result gives the mocap ground truth in the vehicle's body axes on the flight's clock
(``scripts/align_mocap.py`` prints it for the handheld PX4 + OptiTrack set).
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import FlightDataError, FlightFormatError
from .frames import MM_TO_M, align_rotation_sequences, tilt_angle, yup_q_to_zup_q, yup_to_zup
from .geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix
from .types import Flight, Trajectory
from .ulog import interpolate_attitude

log = logging.getLogger(__name__)

#: Motive ``Length Units`` header value -> metres per unit.
MOTIVE_LENGTH_UNITS = {"Millimeters": MM_TO_M, "Centimeters": 1e-2, "Meters": 1.0}


@dataclass(frozen=True, eq=False)
class OffsetResult:
    """Result of :func:`estimate_time_offset`.

    Attributes:
        offset_s: clock offset [s]: ``t_a = t_b + offset_s``.
        correlation: Pearson correlation of the two signals at the best grid offset.
        dt_s: grid step [s].
        overlap_s: overlap of the two signals at the offset [s].
        lags_s: (M,) candidate offsets evaluated [s].
        correlations: (M,) correlation at each candidate (NaN where the overlap was too short).
    """

    offset_s: float
    correlation: float
    dt_s: float
    overlap_s: float
    lags_s: np.ndarray
    correlations: np.ndarray


#: The resampling grid of one signal holds at most this many samples (almost 6 days at the
#: default 10 ms step; a flight's IMU stamped in ns asked for 7 TiB).
MAX_GRID_SAMPLES = 5e7


def _moving_average(x: np.ndarray, n: int) -> np.ndarray:
    if n <= 1:
        return x
    return np.convolve(x, np.ones(n) / n, mode="same")


def _masked_average(x: np.ndarray, valid: np.ndarray, n: int) -> np.ndarray:
    """Moving average of ``x`` over its ``valid`` samples only (the others are not filled)."""
    if n <= 1 or valid.all():
        return _moving_average(x, n)
    total = _moving_average(np.where(valid, x, 0.0), n)
    count = _moving_average(valid.astype(float), n)
    return np.where(count > 0, total / np.where(count > 0, count, 1.0), 0.0)


def _outside_gaps(grid: np.ndarray, t: np.ndarray, max_gap_s: float | None) -> np.ndarray:
    """Grid points not inside a gap longer than ``max_gap_s`` between samples ``t``."""
    if max_gap_s is None:
        return np.ones(grid.shape, bool)
    j = np.clip(np.searchsorted(t, grid), 1, len(t) - 1)
    return (t[j] - t[j - 1]) <= max_gap_s


def estimate_time_offset(
    t_a: np.ndarray,
    signal_a: np.ndarray,
    t_b: np.ndarray,
    signal_b: np.ndarray,
    max_offset_s: float,
    *,
    initial_offset_s: float = 0.0,
    dt_s: float = 0.01,
    smooth_s: float = 0.0,
    min_overlap_s: float = 5.0,
    max_gap_s: float | None = None,
) -> OffsetResult:
    """Clock offset between two recordings of one scalar signal, by cross-correlation.

    Args:
        t_a, signal_a: (N,) times [s, clock a] and values of the first recording.
        t_b, signal_b: (M,) times [s, clock b] and values of the second (same unit as a's up to
            an affine change: correlation ignores gain and bias).
        max_offset_s: search ``offset_s`` in ``initial_offset_s +- max_offset_s`` [s].
        initial_offset_s: centre of the search [s].
        dt_s: common grid step [s]; the offset is refined below it.
        smooth_s: moving-average width applied to both resampled signals [s] (0: none).
        min_overlap_s: candidate offsets overlapping less than this are not scored [s].
        max_gap_s: a signal's samples more than this apart bound a gap, left out of the
            correlation (None: gaps are bridged by a straight line). A SLAM tracking loss of
            10 s bridged so correlated best at -0.47 s on a synchronous flight.

    Returns:
        The offset with ``t_a = t_b + offset_s``.

    Raises:
        FlightDataError: times not increasing, or no candidate overlaps ``min_overlap_s``.
    """
    t_a, signal_a, t_b, signal_b = (
        np.asarray(x, dtype=float) for x in (t_a, signal_a, t_b, signal_b)
    )
    for name, t, s in (("a", t_a, signal_a), ("b", t_b, signal_b)):
        if t.shape != s.shape or t.ndim != 1 or t.size < 2:
            raise FlightDataError(f"signal {name}: expected matching 1-D times and values")
        if np.any(np.diff(t) <= 0):
            raise FlightDataError(f"signal {name}: times must be strictly increasing")
        n_grid = (t[-1] - t[0]) / dt_s
        if n_grid > MAX_GRID_SAMPLES:
            raise FlightDataError(
                f"signal {name}: {t[-1] - t[0]:.6g} s at a {dt_s:g} s step is {n_grid:.3g} grid "
                f"samples (at most {MAX_GRID_SAMPLES:g}): stamps not in seconds, or a clock jump"
            )
    grid = np.arange(t_a[0], t_a[-1], dt_s)
    n_smooth = int(round(smooth_s / dt_s))
    ok_a = _outside_gaps(grid, t_a, max_gap_s)
    a = _masked_average(np.interp(grid, t_a, signal_a), ok_a, n_smooth)
    b_grid = np.arange(t_b[0], t_b[-1], dt_s)
    ok_b = _outside_gaps(b_grid, t_b, max_gap_s).astype(float)
    b = _masked_average(np.interp(b_grid, t_b, signal_b), ok_b > 0, n_smooth)

    n_lags = int(np.ceil(max_offset_s / dt_s))
    lags = initial_offset_s + dt_s * np.arange(-n_lags, n_lags + 1)
    corr = np.full(lags.shape, np.nan)
    min_samples = int(min_overlap_s / dt_s)
    for i, lag in enumerate(lags):
        # signal b on clock a: b(t_a - lag)
        tb = grid - lag
        inside = (tb >= b_grid[0]) & (tb <= b_grid[-1]) & ok_a
        if max_gap_s is not None:
            inside[inside] = np.interp(tb[inside], b_grid, ok_b) >= 1.0
        if np.count_nonzero(inside) < min_samples:
            continue
        bi = np.interp(tb[inside], b_grid, b)
        ai = a[inside]
        sa, sb = ai.std(), bi.std()
        if sa > 0 and sb > 0:
            corr[i] = float(np.mean((ai - ai.mean()) * (bi - bi.mean())) / (sa * sb))
    if np.all(np.isnan(corr)):
        raise FlightDataError(
            f"no offset within {initial_offset_s:+.3f} +- {max_offset_s:.3f} s gives "
            f"{min_overlap_s:.1f} s of overlap between the signals"
        )
    k = int(np.nanargmax(corr))
    offset = float(lags[k])
    if 0 < k < len(lags) - 1 and np.isfinite(corr[k - 1]) and np.isfinite(corr[k + 1]):
        c0, c1, c2 = corr[k - 1], corr[k], corr[k + 1]
        denom = c0 - 2.0 * c1 + c2
        if denom < 0:
            offset += 0.5 * (c0 - c2) / denom * dt_s
    overlap = min(t_a[-1], t_b[-1] + offset) - max(t_a[0], t_b[0] + offset)
    return OffsetResult(
        offset_s=offset,
        correlation=float(corr[k]),
        dt_s=dt_s,
        overlap_s=float(overlap),
        lags_s=lags,
        correlations=corr,
    )


def body_rate_magnitude(
    t: np.ndarray, world_q_body_wxyz: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Angular-rate magnitude [rad/s] from consecutive orientations (finite differences).

    Invariant to fixed rotations of the world and body frames, so it compares a gyro's norm with
    a mocap rigid body whose axes differ from the vehicle's.

    Returns:
        ``(t_mid, rate)``: mid-times (N-1,) [s] and ``|log(R_k^T R_k+1)| / dt`` (N-1,).
    """
    R = quat_wxyz_to_matrix(world_q_body_wxyz)
    dR = np.swapaxes(R[:-1], -1, -2) @ R[1:]
    cos = np.clip((np.trace(dR, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    t = np.asarray(t, dtype=float)
    return 0.5 * (t[1:] + t[:-1]), np.arccos(cos) / np.diff(t)


# ----------------------------------------------------------------------------------------------
# OptiTrack / Motive CSV
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class MotiveTake:
    """One rigid body of a Motive CSV export, in fgnav frames.

    Attributes:
        trajectory: rigid-body poses; world z up (Motive's Y-up world and rigid-body axes
            converted by :func:`~fgnav.datasets.frames.yup_q_to_zup_q`), positions [m], time [s]
            from the take's start (``frame / export rate``).
        rigid_body: name of the rigid body read.
        rigid_bodies: all rigid-body names in the file.
        frame_rate_hz: export frame rate [Hz].
        skipped_rows: frames with missing (untracked) values, left out.
        header: the metadata line as key -> value.
    """

    trajectory: Trajectory
    rigid_body: str
    rigid_bodies: tuple[str, ...]
    frame_rate_hz: float
    skipped_rows: int
    header: dict[str, str] = field(default_factory=dict)


def read_motive_csv(path: str | Path, rigid_body: str | None = None) -> MotiveTake:
    """Read a rigid body from an OptiTrack Motive CSV export (quaternion rotation type).

    Args:
        path: the CSV file.
        rigid_body: name of the rigid body; by default the one whose position varies most
            (exports often carry static or untracked bodies too).

    Returns:
        The take (see :class:`MotiveTake`).

    Raises:
        FlightFormatError: not a Motive export, rotation type not Quaternion, unknown length unit,
            unknown rigid body, or a non-numeric cell.
    """
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise FlightFormatError(path, f"cannot read as a Motive CSV export ({exc})") from exc
    if not rows or not rows[0] or rows[0][0] != "Format Version":
        raise FlightFormatError(
            path, "expected a Motive CSV export starting with 'Format Version'", 1
        )
    first = rows[0]
    header = {first[i]: first[i + 1] for i in range(0, len(first) - 1, 2) if first[i]}
    if header.get("Rotation Type", "Quaternion") != "Quaternion":
        raise FlightFormatError(
            path, f"Rotation Type is {header['Rotation Type']!r}; export with Quaternion", 1
        )
    unit = header.get("Length Units", "Millimeters")
    if unit not in MOTIVE_LENGTH_UNITS:
        raise FlightFormatError(
            path, f"Length Units {unit!r} not one of {sorted(MOTIVE_LENGTH_UNITS)}", 1
        )
    labels = {r[1]: i for i, r in enumerate(rows[:20]) if len(r) > 1 and r[1] in ("Type", "Name")}
    axis_row = next(
        (
            i
            for i, r in enumerate(rows[:20])
            if len(r) > 1 and r[0] == "Frame" and r[1].startswith("Time")
        ),
        None,
    )
    if "Name" not in labels or "Type" not in labels or axis_row is None:
        raise FlightFormatError(
            path, "missing the Type/Name/'Frame,Time' header rows of a Motive export"
        )
    types, names = rows[labels["Type"]], rows[labels["Name"]]
    kinds, axes = rows[axis_row - 1], rows[axis_row]
    columns: dict[str, dict[str, int]] = {}
    for j in range(2, len(axes)):
        if j < len(types) and types[j] == "Rigid Body" and j < len(kinds):
            columns.setdefault(names[j], {})[f"{kinds[j]}.{axes[j]}"] = j
    needed = [f"Rotation.{a}" for a in "XYZW"] + [f"Position.{a}" for a in "XYZ"]
    bodies = tuple(n for n, c in columns.items() if all(k in c for k in needed))
    if not bodies:
        raise FlightFormatError(
            path, "no rigid body with Rotation X,Y,Z,W and Position X,Y,Z columns"
        )
    if rigid_body is not None and rigid_body not in bodies:
        raise FlightFormatError(
            path, f"no rigid body named {rigid_body!r}; the file has {list(bodies)}"
        )

    data_start = axis_row + 1
    width = len(axes)
    values = np.full((len(rows) - data_start, width), np.nan)
    for i, r in enumerate(rows[data_start:]):
        for j, cell in enumerate(r[:width]):
            if cell == "":
                continue
            try:
                values[i, j] = float(cell)
            except ValueError as exc:
                raise FlightFormatError(
                    path,
                    f"column {j + 1} ({axes[j]!r}): {cell!r} is not a number",
                    data_start + i + 1,
                ) from exc

    def position_spread(name: str) -> float:
        cols = [columns[name][f"Position.{a}"] for a in "XYZ"]
        return float(np.nansum(np.nanstd(values[:, cols], axis=0)))

    chosen = rigid_body or max(bodies, key=position_spread)
    if rigid_body is None and len(bodies) > 1:
        log.info("%s: rigid bodies %s, reading %r (largest motion)", path.name, bodies, chosen)
    c = columns[chosen]
    quat_xyzw = values[:, [c[f"Rotation.{a}"] for a in "XYZW"]]
    pos = values[:, [c[f"Position.{a}"] for a in "XYZ"]]
    frame = values[:, 0]
    ok = (
        np.isfinite(frame)
        & np.all(np.isfinite(quat_xyzw), axis=1)
        & np.all(np.isfinite(pos), axis=1)
    )
    rate = float(header.get("Export Frame Rate", "nan"))
    if np.isfinite(rate) and rate > 0:
        t = frame / rate
    else:
        t = values[:, 1]
        rate = float(1.0 / np.median(np.diff(t[ok])))
    q_wxyz = np.column_stack([quat_xyzw[:, 3], quat_xyzw[:, :3]])
    traj = Trajectory(
        t=t[ok],
        world_t_body=yup_to_zup(pos[ok]) * MOTIVE_LENGTH_UNITS[unit],
        world_q_body_wxyz=yup_q_to_zup_q(q_wxyz[ok]),
    ).check(f"{path.name}:{chosen}")
    skipped = int(np.count_nonzero(~ok))
    if skipped:
        log.info("%s: %d frames with missing values left out", path.name, skipped)
    return MotiveTake(
        trajectory=traj,
        rigid_body=chosen,
        rigid_bodies=bodies,
        frame_rate_hz=rate,
        skipped_rows=skipped,
        header=header,
    )


# ----------------------------------------------------------------------------------------------
# A flight log against a motion-capture take of the same motion
# ----------------------------------------------------------------------------------------------

#: Moving average applied to angular-rate magnitudes before correlating [s]: differentiated mocap
#: orientations are noisy at 180 Hz.
RATE_SMOOTH_S = 0.05
#: Every n-th mocap frame used when fitting the fixed rotations (speed; 180 Hz is oversampled for
#: handheld motion).
ALIGN_STRIDE = 5


@dataclass(frozen=True, eq=False)
class MocapAlignment:
    """Clock offset and fixed rotations between a flight's attitude and a mocap rigid body.

    Attributes:
        offset_s: ``t_flight = t_mocap + offset_s`` (mean of the two signals' estimates) [s].
        tilt: offset from tilt-angle correlation (flight ``attitude`` vs mocap).
        rate: offset from angular-rate-magnitude correlation (flight gyro vs mocap).
        world_R_mocap: rotation from the mocap world (z up) into the flight's attitude world.
        rb_R_body: rotation from the vehicle body (FLU) into the rigid body's axes.
        attitude_rms_deg: RMS attitude residual after the fit [deg].
        tilt_rms_deg: RMS tilt difference after the fit [deg].
    """

    offset_s: float
    tilt: OffsetResult
    rate: OffsetResult
    world_R_mocap: np.ndarray
    rb_R_body: np.ndarray
    attitude_rms_deg: float
    tilt_rms_deg: float

    def ground_truth(self, mocap: Trajectory) -> Trajectory:
        """The mocap trajectory on the flight's clock with the vehicle body's axes
        (``mocap_R_body = mocap_R_rb @ rb_R_body``), in the mocap world. Positions stay those of
        the rigid body's origin (the lever arm to the IMU is not known)."""
        R = mocap.world_R_body() @ self.rb_R_body
        return Trajectory(
            t=mocap.t + self.offset_s,
            world_t_body=mocap.world_t_body,
            world_q_body_wxyz=matrix_to_quat_wxyz(R),
        )


def align_mocap(flight: Flight, mocap: Trajectory, max_offset_s: float = 10.0) -> MocapAlignment:
    """Find the clock offset and fixed rotations between a flight and a mocap take.

    The offset is searched within ``max_offset_s`` of the difference of the two start times, by
    two independent signals: tilt angle (flight ``attitude`` vs mocap orientation) and
    angular-rate magnitude (flight gyro vs differentiated mocap orientation). Then the fixed
    world and body rotations are fitted
    (:func:`~fgnav.datasets.frames.align_rotation_sequences`) at the mean offset.

    Args:
        flight: a :class:`~fgnav.datasets.types.Flight` with ``imu`` and ``attitude``.
        mocap: rigid-body trajectory (e.g. ``read_motive_csv(...).trajectory``).
        max_offset_s: search half-width [s].
    """
    if flight.attitude is None or flight.imu is None:
        raise FlightDataError(f"{flight.name}: align_mocap needs the flight's imu and attitude")
    guess = float(flight.attitude.t[0] - mocap.t[0])
    tilt = estimate_time_offset(
        flight.attitude.t,
        tilt_angle(quat_wxyz_to_matrix(flight.attitude.world_q_body_wxyz)),
        mocap.t,
        tilt_angle(mocap.world_R_body()),
        max_offset_s,
        initial_offset_s=guess,
    )
    t_mid, rate = body_rate_magnitude(mocap.t, mocap.world_q_body_wxyz)
    rate_res = estimate_time_offset(
        flight.imu.t,
        np.linalg.norm(flight.imu.body_omega, axis=1),
        t_mid,
        rate,
        max_offset_s,
        initial_offset_s=guess,
        smooth_s=RATE_SMOOTH_S,
    )
    offset = 0.5 * (tilt.offset_s + rate_res.offset_s)
    t = mocap.t + offset
    sel = np.flatnonzero((t > flight.attitude.t[0]) & (t < flight.attitude.t[-1]))[::ALIGN_STRIDE]
    if sel.size < 10:
        raise FlightDataError(f"{flight.name}: the mocap take hardly overlaps the flight")
    R_flight = quat_wxyz_to_matrix(interpolate_attitude(flight.attitude, t[sel]))
    R_mocap = mocap.world_R_body()[sel]
    world_R_mocap, rb_R_body, resid = align_rotation_sequences(R_flight, R_mocap)
    tilt_diff = tilt_angle(R_flight) - tilt_angle(world_R_mocap @ R_mocap @ rb_R_body)
    return MocapAlignment(
        offset_s=offset,
        tilt=tilt,
        rate=rate_res,
        world_R_mocap=world_R_mocap,
        rb_R_body=rb_R_body,
        attitude_rms_deg=float(np.degrees(np.sqrt(np.mean(resid**2)))),
        tilt_rms_deg=float(np.degrees(np.sqrt(np.mean(tilt_diff**2)))),
    )
