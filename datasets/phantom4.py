"""Reader for the ANSFL "DJI Phantom 4 RTK with Xsens IMUs" recordings (CC BY 4.0).

One flight folder (e.g. ``StraightLine/path_1``) holds:

* ``IMU_1.csv`` .. ``IMU_4.csv`` and ``IMUAvg.csv`` (the mean of the four; it has an extra
  leading index column): ``time`` [s], ``Euler_X/Y/Z`` [deg] (the Xsens AHRS roll, pitch, yaw of the
  IMU), ``Acc_X/Y/Z`` [m/s^2] (specific force), ``Gyr_X/Y/Z`` [deg/s], 120 Hz, **in the IMU's own
  axes**. The Xsens convention is a z-up local frame (ENU) and sensor axes x forward, y left,
  z up, Euler ZYX (``R = Rz(yaw) Ry(pitch) Rx(roll)``): the same as fgnav's, so positive
  ``Euler_Y`` is nose down. The rotation between these axes and the airframe is not given.
* ``GT.csv`` (``time`` [s], distance, speed, ``compass_heading``/``pitch``/``roll`` [deg],
  height, ``North``/``East``/``Down`` [m]) and ``GTExtended.csv`` (``time(millisecond)``,
  latitude, longitude, altitude, North/East/Down, ``xSpeed/ySpeed/zSpeed`` [m/s] north/east/down,
  roll/pitch/heading [deg]): the DJI flight record with RTK positions, 10 Hz. Attitude is the
  Phantom's own (aerospace NED/FRD, ZYX), converted by :mod:`fgnav.datasets.frames`.

Clocks: both files count from 0 at the start of the recording; ``GT.csv``'s time is
``GTExtended``'s ``time(millisecond)`` minus its first value. They are taken as one clock; the
check is in ``scripts/drag_real_phantom4.py`` (tilt cross-correlation).

:func:`read_phantom4` returns a :class:`Flight` with ``imu`` and ``attitude`` in the IMU's axes
unless ``body_R_imu`` is given (then rotated into the airframe FLU body), and ``ground_truth``
(RTK position, DJI velocity and attitude) in fgnav's z-up world. :func:`estimate_body_R_imu`
fits the IMU-to-airframe rotation from the two attitude sources.
"""

from __future__ import annotations

import csv
import io
import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ._files import read_text
from .errors import FlightFormatError
from .frames import align_rotation_sequences, ned_R_frd_to_world_R_body, ned_to_enu
from .geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix, rpy_to_matrix
from .types import AttitudeSeries, Flight, ImuSeries, Trajectory
from .ulog import interpolate_attitude

log = logging.getLogger(__name__)

IMU_COLUMNS = (
    "time",
    "Euler_X",
    "Euler_Y",
    "Euler_Z",
    "Acc_X",
    "Acc_Y",
    "Acc_Z",
    "Gyr_X",
    "Gyr_Y",
    "Gyr_Z",
)
GT_COLUMNS = (
    "time",
    "compass_heading(degrees)",
    "pitch(degrees)",
    "roll(degrees)",
    "North",
    "East",
    "Down",
)
GT_EXT_COLUMNS = ("time(millisecond)", "xSpeed(m/s)", "ySpeed(m/s)", "zSpeed(m/s)")
MS_TO_S = 1e-3
#: Largest plausible change of Xsens yaw between two 120 Hz samples [deg]: 30 deg in 8.3 ms is
#: 3600 deg/s, far above any multirotor's yaw rate. Larger steps are counted in
#: ``meta["euler_yaw_jumps"]`` (``IMUAvg.csv`` averages wrapped yaw angles and jumps by ~90 deg).
MAX_YAW_STEP_DEG = 30.0


def _read_csv(path: Path, required: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Columns by header name (header cells stripped); every cell of a required column numeric."""
    rows = list(csv.reader(io.StringIO(read_text(path).removeprefix("\ufeff"))))
    if not rows:
        raise FlightFormatError(path, "empty file", 1)
    if len(rows) < 2:
        raise FlightFormatError(path, "no data rows after the header", 1)
    header = [h.strip() for h in rows[0]]
    missing = [c for c in required if c not in header]
    if missing:
        raise FlightFormatError(
            path, f"header lacks columns {missing}; expected {list(required)}", 1
        )
    idx = {c: header.index(c) for c in required}
    out = {c: np.empty(len(rows) - 1) for c in required}
    for i, row in enumerate(rows[1:]):
        if len(row) != len(header):
            raise FlightFormatError(path, f"{len(row)} cells, expected {len(header)}", i + 2)
        for c, j in idx.items():
            try:
                out[c][i] = float(row[j])
            except ValueError as exc:
                raise FlightFormatError(
                    path, f"column {c!r}: {row[j]!r} is not a number", i + 2
                ) from exc
    return out


def _xsens_euler_to_R(
    roll_deg: np.ndarray, pitch_deg: np.ndarray, yaw_deg: np.ndarray
) -> np.ndarray:
    r, p, y = (np.deg2rad(a) for a in (roll_deg, pitch_deg, yaw_deg))
    return np.stack([rpy_to_matrix(a, b, c) for a, b, c in zip(r, p, y, strict=True)])


def read_phantom4(
    folder: str | Path, imu_file: str = "IMUAvg.csv", body_R_imu: np.ndarray | None = None
) -> Flight:
    """Read one ANSFL Phantom 4 flight folder.

    Args:
        folder: the folder with the IMU and GT csv files.
        imu_file: ``IMUAvg.csv`` (mean of the four IMUs) or ``IMU_<n>.csv``.
        body_R_imu: 3x3 rotation from the IMU axes into the airframe FLU body; None keeps the IMU
            axes (``meta["imu_axes"]`` says which).

    Returns:
        The checked flight: ``imu`` [rad/s, m/s^2], ``attitude`` (Xsens AHRS; of the IMU axes, or of
        the body when ``body_R_imu`` is given, in the Xsens magnetic ENU world), ``ground_truth``
        (RTK position relative to take-off, DJI velocity and attitude, z-up world: x east, y north).

    Raises:
        FlightFormatError: a missing file or column, or a non-numeric cell (file and line named).
    """
    folder = Path(folder)
    imu = _read_csv(folder / imu_file, IMU_COLUMNS)
    gt = _read_csv(folder / "GT.csv", GT_COLUMNS)
    meta = {
        "format": "ansfl-phantom4",
        "imu_file": imu_file,
        "imu_axes": "IMU (Xsens) axes; airframe rotation unknown"
        if body_R_imu is None
        else "body FLU",
        "clock": "IMU and GT times both start at 0 at the start of the recording (one clock)",
        "attitude_source": "Xsens AHRS Euler angles (ZYX, ENU magnetic world)",
        "ground_truth": "RTK North/East/Down -> z-up; DJI roll/pitch/heading; DJI speeds",
    }
    t_imu = imu["time"]
    yaw_steps = np.abs((np.diff(imu["Euler_Z"]) + 180.0) % 360.0 - 180.0)
    meta["euler_yaw_jumps"] = int(np.count_nonzero(yaw_steps > MAX_YAW_STEP_DEG))
    if meta["euler_yaw_jumps"]:
        meta["notes"] = [
            f"{imu_file}: Euler_Z jumps by more than {MAX_YAW_STEP_DEG:.0f} deg between samples "
            f"{meta['euler_yaw_jumps']} times: its attitude is unreliable "
            "(averaged wrapped angles?)"
        ]
        log.warning("%s", meta["notes"][0])
    gyro = np.deg2rad(np.column_stack([imu[f"Gyr_{a}"] for a in "XYZ"]))
    accel = np.column_stack([imu[f"Acc_{a}"] for a in "XYZ"])
    world_R_imu = _xsens_euler_to_R(imu["Euler_X"], imu["Euler_Y"], imu["Euler_Z"])
    ned_R_frd = np.stack(
        [
            rpy_to_matrix(np.deg2rad(r), np.deg2rad(p), np.deg2rad(y))
            for r, p, y in zip(
                gt["roll(degrees)"],
                gt["pitch(degrees)"],
                gt["compass_heading(degrees)"],
                strict=True,
            )
        ]
    )
    world_q_body = matrix_to_quat_wxyz(ned_R_frd_to_world_R_body(ned_R_frd))
    pos = ned_to_enu(np.column_stack([gt["North"], gt["East"], gt["Down"]]))
    vel = None
    ext_path = folder / "GTExtended.csv"
    if ext_path.exists():
        ext = _read_csv(ext_path, GT_EXT_COLUMNS)
        t_ext = (ext["time(millisecond)"] - ext["time(millisecond)"][0]) * MS_TO_S
        if t_ext.shape != gt["time"].shape or np.abs(t_ext - gt["time"]).max() > 1e-6:
            raise FlightFormatError(
                ext_path, "rows do not match GT.csv's times (time(millisecond) - first)"
            )
        vel = ned_to_enu(np.column_stack([ext[f"{a}Speed(m/s)"] for a in "xyz"]))
        meta["velocity"] = "GTExtended xSpeed/ySpeed/zSpeed (north/east/down, 0.1 m/s resolution)"
    flight = Flight(
        name=f"phantom4_{folder.parent.name}_{folder.name}",
        source=str(folder),
        imu=ImuSeries(t=t_imu, body_omega=gyro, body_accel=accel),
        attitude=AttitudeSeries(t=t_imu, world_q_body_wxyz=matrix_to_quat_wxyz(world_R_imu)),
        ground_truth=Trajectory(
            t=gt["time"], world_t_body=pos, world_q_body_wxyz=world_q_body, world_v_body=vel
        ),
        meta=meta,
    )
    if body_R_imu is not None:
        flight = with_body_axes(flight, body_R_imu)
    return flight.check()


@dataclass(frozen=True)
class MountFit:
    """Result of :func:`estimate_body_R_imu`.

    Attributes:
        body_R_imu: rotation from IMU axes into the airframe FLU body.
        gt_world_R_imu_world: rotation from the Xsens world into the ground-truth world (the two
            headings differ: magnetic model, yaw origin).
        residual_rms_deg: RMS attitude residual after the fit [deg].
        samples: ground-truth samples used.
    """

    body_R_imu: np.ndarray
    gt_world_R_imu_world: np.ndarray
    residual_rms_deg: float
    samples: int


def estimate_body_R_imu(
    flight: Flight, t0: float | None = None, t1: float | None = None
) -> MountFit:
    """Fit the IMU-to-airframe rotation by aligning the Xsens attitude (IMU axes) with the DJI
    attitude (airframe) at the ground-truth times in ``[t0, t1]``:
    ``gt_world_R_body(t) = gt_world_R_imu_world @ imu_world_R_imu(t) @ imu_R_body``
    (:func:`~fgnav.datasets.frames.align_rotation_sequences`). Both worlds are z up, so
    ``gt_world_R_imu_world`` is restricted to a rotation about z: on a straight flight with one
    heading a world tilt and a mount tilt would otherwise trade off. The mount's yaw still trades
    off with the heading offset on such a flight (weakly determined: a few degrees); its tilt is
    well determined.

    ``flight`` must have been read without ``body_R_imu``.
    """
    gt = flight.ground_truth
    lo = gt.t[0] if t0 is None else t0
    hi = gt.t[-1] if t1 is None else t1
    sel = (gt.t >= max(lo, flight.attitude.t[0])) & (gt.t <= min(hi, flight.attitude.t[-1]))
    gt_sel = gt.select(sel)
    R_imu = quat_wxyz_to_matrix(interpolate_attitude(flight.attitude, gt_sel.t))
    a_R_b, imu_R_body, resid = align_rotation_sequences(
        gt_sel.world_R_body(), R_imu, world_yaw_only=True
    )
    return MountFit(
        body_R_imu=imu_R_body.T,
        gt_world_R_imu_world=a_R_b,
        residual_rms_deg=float(np.degrees(np.sqrt(np.mean(resid**2)))),
        samples=int(sel.sum()),
    )


def with_body_axes(flight: Flight, body_R_imu: np.ndarray) -> Flight:
    """The same flight with ``imu`` and ``attitude`` rotated from IMU axes into the body."""
    R = np.asarray(body_R_imu, dtype=float)
    imu = replace(
        flight.imu, body_omega=flight.imu.body_omega @ R.T, body_accel=flight.imu.body_accel @ R.T
    )
    world_R_body = quat_wxyz_to_matrix(flight.attitude.world_q_body_wxyz) @ R.T
    att = replace(flight.attitude, world_q_body_wxyz=matrix_to_quat_wxyz(world_R_body))
    return replace(flight, imu=imu, attitude=att, meta={**flight.meta, "imu_axes": "body FLU"})


# ----------------------------------------------------------------------------------------------
# Rotor-drag identification (linear least squares, numpy only)
# ----------------------------------------------------------------------------------------------

#: PX4 EKF2's default ``EKF2_MCOEF`` (rotor momentum drag coefficient [1/s]; PX4 parameter
#: reference, and the value in ``px4_cubeorange_quad_flight/test.ulg``); printed for context only.
PX4_DEFAULT_MCOEF = 0.15


@dataclass(frozen=True, eq=False)
class DragSamples:
    """Specific force and body velocity at the ground-truth times.

    Attributes:
        t: (N,) ground-truth times [s].
        mean_body_accel: (N, 3) mean accelerometer reading over the window around t, body axes
            [m/s^2].
        body_velocity: (N, 3) ``world_R_body^T world_v_body`` from ground truth [m/s].
        samples_per_window: (N,) accelerometer samples averaged.
    """

    t: np.ndarray
    mean_body_accel: np.ndarray
    body_velocity: np.ndarray
    samples_per_window: np.ndarray

    def select(self, mask: np.ndarray) -> DragSamples:
        return DragSamples(
            self.t[mask],
            self.mean_body_accel[mask],
            self.body_velocity[mask],
            self.samples_per_window[mask],
        )


def drag_samples(flight: Flight, window_s: float, imu_time_shift_s: float = 0.0) -> DragSamples:
    """Average the body-axes accelerometer over ``window_s`` centred at each ground-truth time
    and pair it with the ground-truth body-frame velocity.

    Args:
        flight: a flight whose ``imu`` is in body axes and ``ground_truth`` has velocity.
        window_s: averaging window [s] (the ground-truth period suits: 0.1 s at 10 Hz).
        imu_time_shift_s: added to IMU times to put them on the ground-truth clock [s].

    Returns:
        Samples for the windows that hold at least half the expected IMU samples (windows at the
        ends of the recording are left out).
    """
    gt = flight.ground_truth
    if gt is None or gt.world_v_body is None:
        raise ValueError("drag_samples needs ground truth with velocity")
    t_imu = flight.imu.t + imu_time_shift_s
    lo = np.searchsorted(t_imu, gt.t - window_s / 2, side="left")
    hi = np.searchsorted(t_imu, gt.t + window_s / 2, side="left")
    counts = hi - lo
    csum = np.vstack([np.zeros((1, 3)), np.cumsum(flight.imu.body_accel, axis=0)])
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (csum[hi] - csum[lo]) / counts[:, None]
    expected = window_s * flight.imu.rate_hz
    ok = counts >= 0.5 * expected
    body_v = np.einsum("nji,nj->ni", gt.world_R_body(), gt.world_v_body)
    return DragSamples(gt.t, mean, body_v, counts).select(ok)


@dataclass(frozen=True, eq=False)
class DragFit:
    """Least-squares fit of ``f_a = -k_a u_a + b_a`` (a in the fitted axes).

    Attributes:
        axes: fitted body axes, e.g. ``(0, 1)`` for a joint x-y fit with one ``k``.
        k: drag coefficient [1/s].
        k_se: its standard error from the residual variance, assuming independent residuals.
        k_se_autocorr: the same inflated by ``sqrt((1 + rho1) / (1 - rho1))`` for lag-1
            autocorrelation ``rho1`` of the residuals (an AR(1) effective-sample-size correction).
        bias: (len(axes),) intercepts ``b_a`` [m/s^2] (accelerometer bias plus mount error).
        r2: coefficient of determination, with the variance taken about each axis' mean (what
            the drag term explains beyond the intercepts).
        residual_std: residual standard deviation [m/s^2].
        rho1: lag-1 autocorrelation of the residuals (per axis, averaged).
        n: samples per axis.
        velocity_range: (min, max) of the regressor over the fitted axes [m/s].
    """

    axes: tuple[int, ...]
    k: float
    k_se: float
    k_se_autocorr: float
    bias: np.ndarray
    r2: float
    residual_std: float
    rho1: float
    n: int
    velocity_range: tuple[float, float]

    def predict(self, body_velocity: np.ndarray) -> np.ndarray:
        """Predicted specific force on the fitted axes (N, len(axes)) [m/s^2]."""
        return -self.k * np.asarray(body_velocity)[:, list(self.axes)] + self.bias


def fit_linear_drag(samples: DragSamples, axes: tuple[int, ...] = (0, 1)) -> DragFit:
    """Fit one drag coefficient ``k`` and one intercept per axis to ``f_a = -k u_a + b_a``.

    Args:
        samples: paired specific force and body velocity.
        axes: body axes to fit jointly (0 = x forward, 1 = y left).

    Returns:
        The fit with standard errors (see :class:`DragFit`).
    """
    n = len(samples.t)
    m = len(axes)
    if n < m + 3:
        raise ValueError(f"fit_linear_drag: {n} samples are too few for {m + 1} parameters")
    A = np.zeros((n * m, 1 + m))
    y = np.empty(n * m)
    for j, a in enumerate(axes):
        rows = slice(j * n, (j + 1) * n)
        A[rows, 0] = -samples.body_velocity[:, a]
        A[rows, 1 + j] = 1.0
        y[rows] = samples.mean_body_accel[:, a]
    p, *_ = np.linalg.lstsq(A, y, rcond=None)
    r = y - A @ p
    dof = y.size - A.shape[1]
    s2 = float(r @ r / dof)
    cov = s2 * np.linalg.inv(A.T @ A)
    rho = [
        float(np.corrcoef(r[j * n : (j + 1) * n - 1], r[j * n + 1 : (j + 1) * n])[0, 1])
        for j in range(m)
    ]
    rho1 = float(np.clip(np.mean(rho), -0.99, 0.99))
    k_se = float(np.sqrt(cov[0, 0]))
    # Variance about each axis' own mean: R^2 measures what the drag term explains beyond the
    # intercepts.
    sst = sum(
        float(np.sum((y[j * n : (j + 1) * n] - y[j * n : (j + 1) * n].mean()) ** 2))
        for j in range(m)
    )
    u = -A[:, 0]
    return DragFit(
        axes=tuple(axes),
        k=float(p[0]),
        k_se=k_se,
        k_se_autocorr=k_se * float(np.sqrt((1 + max(rho1, 0.0)) / (1 - max(rho1, 0.0)))),
        bias=p[1:],
        r2=float(1.0 - r @ r / sst),
        residual_std=float(np.sqrt(s2)),
        rho1=rho1,
        n=n,
        velocity_range=(float(u.min()), float(u.max())),
    )
