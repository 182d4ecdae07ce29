"""Downward sensors against ground truth: the rangefinder's scale/offset/noise and the flow
sensor's pixels per radian, sign and residual correlation, from a flight's truth trajectory.

Diagnostics for a reader's calibration (numpy only, no estimator): the truth supplies height,
tilt and body velocity; the gyro supplies the angular rate over each flow interval.

* :func:`range_vs_truth`: least-squares ``range = scale * z / cos(tilt) + offset`` over the
  airborne samples (truth height above ``min_height``), ``z`` the truth height of the body origin
  over ``ground`` (the floor at ``z = 0`` of the truth frame by default) and ``cos(tilt)`` the
  beam's (body -z) angle from the vertical. The offset is the sensor's position below the body
  origin plus any ranging offset; ``offset_fixed_scale`` is the mean of ``range - z / cos(tilt)``.
* :func:`flow_vs_truth`: prediction in fgnav's flow convention (``FlowSeries``) for a sensor at
  the body origin with ``body_T_flow = DOWNWARD_FLOW`` (per pixel-per-radian):
  ``p = dt [-v_x / d - w_y, -v_y / d + w_x]`` in sensor axes, with ``v`` the truth velocity in
  body axes at the interval's middle (the truth's velocity, or a Savitzky-Golay derivative of
  its positions resampled at 300 Hz, 0.1 s window), ``w`` the mean gyro rate over the interval
  and ``d`` the measured range at the interval's middle (interpolated). Fitted per axis
  ``flow = k p`` through the origin on the samples above ``min_height`` that follow their
  predecessor within a loop (their interval is known); ``k`` is the sensor's pixels per radian
  (positive when the axes are right), the residual is in flow units, and ``lag1`` is the
  correlation of consecutive x residuals. The samples after a gap are scored with the same ``k``
  (see :func:`flow_vs_truth`). The lever arm is not modelled (the sensor is taken at the body
  origin: 4 cm x the angular rate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import FlightDataError
from .geometry import interpolate_quat_wxyz, quat_wxyz_to_matrix, velocity_from_positions
from .types import Flight

RESAMPLE_HZ = 300.0
SAVGOL_WINDOW_S = 0.1
"""Savitzky-Golay derivative window [s] for a truth without velocity (resampled at
:data:`RESAMPLE_HZ`; :func:`.geometry.velocity_from_positions`)."""


@dataclass(frozen=True)
class RangeFit:
    """``range = scale * z / cos(tilt) + offset`` over ``samples`` airborne readings [m]."""

    scale: float
    offset: float
    noise: float
    offset_fixed_scale: float
    noise_fixed_scale: float
    samples: int


@dataclass(frozen=True)
class FlowFit:
    """Per-axis pixels per radian, correlation and residual of the flow against the truth."""

    pixels_per_rad: tuple[float, float]
    correlation: tuple[float, float]
    residual_std: float
    residual_std_after_gap: float
    after_gap_interval_ratio: float
    lag1: float
    samples: int
    samples_after_gap: int


def _need(flight: Flight, *streams: str) -> None:
    missing = [s for s in streams if getattr(flight, s) is None]
    if missing:
        raise FlightDataError(f"{flight.name}: needs the stream(s) {missing}")


def _tilt_cos(flight: Flight, t: np.ndarray) -> np.ndarray:
    gt = flight.ground_truth
    R = quat_wxyz_to_matrix(interpolate_quat_wxyz(gt.t, gt.world_q_body_wxyz, t))
    return R[:, 2, 2]


def range_vs_truth(flight: Flight, min_height: float = 0.15, ground: float = 0.0) -> RangeFit:
    """Fit the range stream to the truth height (module docstring)."""
    _need(flight, "range", "ground_truth")
    gt, rng = flight.ground_truth, flight.range
    inside = (rng.t >= gt.t[0]) & (rng.t <= gt.t[-1])
    t, r = rng.t[inside], rng.range[inside]
    z = np.interp(t, gt.t, gt.world_t_body[:, 2]) - ground
    x = z / _tilt_cos(flight, t)
    air = z > min_height
    if np.count_nonzero(air) < 10:
        raise FlightDataError(f"{flight.name}: fewer than 10 range samples above {min_height} m")
    A = np.column_stack([x[air], np.ones(np.count_nonzero(air))])
    (scale, offset), *_ = np.linalg.lstsq(A, r[air], rcond=None)
    d = r[air] - x[air]
    return RangeFit(
        scale=float(scale),
        offset=float(offset),
        noise=float(np.std(r[air] - A @ [scale, offset])),
        offset_fixed_scale=float(d.mean()),
        noise_fixed_scale=float(d.std()),
        samples=int(np.count_nonzero(air)),
    )


def flow_prediction(flight: Flight, dt: np.ndarray | None = None) -> np.ndarray:
    """(N, 2) flow per pixel-per-radian predicted from the truth, gyro and range (module doc);
    ``dt`` replaces the stream's intervals (e.g. to test another interval convention)."""
    _need(flight, "flow", "ground_truth", "imu", "range")
    gt, imu, flow, rng = flight.ground_truth, flight.imu, flight.flow, flight.range
    dt = flow.dt if dt is None else np.asarray(dt, dtype=float)
    v_gt = gt.world_v_body
    if v_gt is None:
        v_gt = velocity_from_positions(gt.t, gt.world_t_body, SAVGOL_WINDOW_S, RESAMPLE_HZ)
    tm = flow.t - dt / 2
    v = np.column_stack([np.interp(tm, gt.t, v_gt[:, i]) for i in range(3)])
    R = quat_wxyz_to_matrix(interpolate_quat_wxyz(gt.t, gt.world_q_body_wxyz, tm))
    v_body = np.einsum("nji,nj->ni", R, v)
    # Mean gyro over [t - dt, t] from the running integral of the rate.
    step = np.diff(imu.t, prepend=imu.t[0])
    integral = np.cumsum(imu.body_omega * step[:, None], axis=0)
    w = (
        np.column_stack(
            [
                np.interp(flow.t, imu.t, integral[:, i])
                - np.interp(flow.t - dt, imu.t, integral[:, i])
                for i in range(3)
            ]
        )
        / dt[:, None]
    )
    d = np.interp(tm, rng.t, rng.range)
    # Sensor axes (DOWNWARD_FLOW): x = body x, y = -body y; w_sensor = (w_x, -w_y).
    return np.column_stack([dt * (-v_body[:, 0] / d + w[:, 1]), dt * (v_body[:, 1] / d + w[:, 0])])


def flow_vs_truth(
    flight: Flight, min_height: float = 0.3, dt: np.ndarray | None = None, gap_factor: float = 1.5
) -> FlowFit:
    """Fit the flow stream to its truth prediction (module docstring).

    A sample whose step from the previous one exceeds ``gap_factor`` median steps is "after a
    gap": its interval is not known from the stamps. The scale ``k`` is fitted on the other
    (consecutive) samples above ``min_height``; the after-gap samples are scored with that ``k``
    (``residual_std_after_gap``: a test of the interval convention ``dt``), and
    ``after_gap_interval_ratio`` is the scale fitted on them alone over ``k`` (mean of the axes):
    the motion they carry in units of their ``dt``.
    """
    p = flow_prediction(flight, dt)
    flow, gt = flight.flow, flight.ground_truth
    z = np.interp(flow.t, gt.t, gt.world_t_body[:, 2])
    air = (z > min_height) & (flow.t >= gt.t[0]) & (flow.t <= gt.t[-1])
    step = np.diff(flow.t, prepend=-np.inf)
    gap = step > gap_factor * np.median(np.diff(flow.t))
    m, g = air & ~gap, air & gap
    if np.count_nonzero(m) < 10:
        raise FlightDataError(f"{flight.name}: fewer than 10 flow samples above {min_height} m")

    def scale(mask: np.ndarray, i: int) -> float:
        return float(flow.flow[mask, i] @ p[mask, i] / (p[mask, i] @ p[mask, i]))

    k = [scale(m, i) for i in range(2)]
    corr = [float(np.corrcoef(flow.flow[m, i], p[m, i])[0, 1]) for i in range(2)]
    res = flow.flow - p * np.asarray(k)
    rx = res[m, 0]
    has_gap = np.count_nonzero(g) >= 10
    return FlowFit(
        pixels_per_rad=(k[0], k[1]),
        correlation=(corr[0], corr[1]),
        residual_std=float(res[m].std()),
        residual_std_after_gap=float(res[g].std()) if has_gap else float("nan"),
        after_gap_interval_ratio=float(np.mean([scale(g, i) / k[i] for i in range(2)]))
        if has_gap
        else float("nan"),
        lag1=float(np.corrcoef(rx[1:], rx[:-1])[0, 1]),
        samples=int(np.count_nonzero(m)),
        samples_after_gap=int(np.count_nonzero(g)),
    )
