"""Sensor models of the simulator: IMU, AHRS attitude, yaw, tilted rangefinder, optical flow,
monocular SLAM.

Every function takes the true vehicle states (on the IMU grid), the options and its own seeded
generator, and returns the stream plus the truth it used. All streams share the IMU clock.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from fgnav.datasets.geometry import matrix_to_quat_wxyz, so3_exp, wrap_angle, yaw_of
from fgnav.datasets.types import (
    AttitudeSeries,
    FlowSeries,
    ImuSeries,
    RangeSeries,
    SlamSeries,
    YawSeries,
)

from .options import SimOptions, SimulationError
from .vehicle import VehicleLog

log = logging.getLogger(__name__)


def decimation(opts: SimOptions, rate_hz: float) -> int:
    """Number of IMU samples between two samples of a stream at ``rate_hz`` (rounded)."""
    return int(round(opts.imu_rate_hz / rate_hz))


def sample_indices(opts: SimOptions, rate_hz: float, n: int) -> np.ndarray:
    """Indices of the IMU ticks (of ``n``) that carry a stream at ``rate_hz``: every
    ``imu_rate_hz / rate_hz``-th tick when that is an integer, else the tick nearest each
    ``j / rate_hz`` (irregular intervals on the IMU grid, e.g. 30 Hz at 200 Hz: 30 or 35 ms)."""
    ratio = opts.imu_rate_hz / rate_hz
    if abs(ratio - round(ratio)) < 1e-9:
        return np.arange(0, n, int(round(ratio)))
    idx = np.unique(np.floor(np.arange(0.0, n / ratio) * ratio + 0.5).astype(int))
    return idx[idx < n]


# ---------------------------------------------------------------------------------------------
# IMU
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuTruth:
    """Biases of the simulated IMU at every sample: gyro [rad/s], accel [m/s^2], (N, 3)."""

    gyro_bias: np.ndarray
    accel_bias: np.ndarray


def _random_walk(rng, n: int, x0_std: float, step_std: float) -> np.ndarray:
    x0 = rng.normal(0.0, x0_std, 3) if x0_std > 0 else np.zeros(3)
    steps = rng.normal(0.0, step_std, (n, 3)) if step_std > 0 else np.zeros((n, 3))
    steps[0] = 0.0
    return x0 + np.cumsum(steps, axis=0)


def simulate_imu(
    vehicle: VehicleLog, opts: SimOptions, rng: np.random.Generator
) -> tuple[ImuSeries, ImuTruth]:
    """Gyro and accelerometer in body: ``true + bias + white noise``.

    White noise is ``density / sqrt(dt)`` per sample; the bias is a random walk with step
    ``random_walk * sqrt(dt)`` from an initial bias of spread ``*_bias0_std``.
    """
    n = len(vehicle.t)
    dt = 1.0 / opts.imu_rate_hz
    if opts.noise_free:
        zeros = np.zeros((n, 3))
        imu = ImuSeries(
            vehicle.t.copy(), vehicle.body_omega.copy(), vehicle.body_specific_force.copy()
        )
        return imu, ImuTruth(zeros, zeros.copy())
    gyro_bias = _random_walk(rng, n, opts.gyro_bias0_std, opts.gyro_random_walk * math.sqrt(dt))
    accel_bias = _random_walk(rng, n, opts.accel_bias0_std, opts.accel_random_walk * math.sqrt(dt))
    gyro = (
        vehicle.body_omega
        + gyro_bias
        + rng.normal(0.0, opts.gyro_noise_density / math.sqrt(dt), (n, 3))
    )
    accel = (
        vehicle.body_specific_force
        + accel_bias
        + rng.normal(0.0, opts.accel_noise_density / math.sqrt(dt), (n, 3))
    )
    return ImuSeries(vehicle.t.copy(), gyro, accel), ImuTruth(gyro_bias, accel_bias)


# ---------------------------------------------------------------------------------------------
# Attitude and yaw
# ---------------------------------------------------------------------------------------------


def _orientation_samples(
    vehicle: VehicleLog,
    opts: SimOptions,
    rng: np.random.Generator,
    rate_hz: float,
    sigma: float,
    noise_dim: tuple[int, ...],
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
    """``(t, world_R_body, n)`` of a stream of the vehicle's orientation at ``rate_hz``, with
    its noise ``n ~ N(0, sigma^2)`` of shape ``(N, *noise_dim)`` (None with ``noise_free`` or
    ``sigma`` 0: nothing drawn); None when the stream is off (``rate_hz <= 0``)."""
    if rate_hz <= 0:
        return None
    idx = sample_indices(opts, rate_hz, len(vehicle.t))
    sigma = 0.0 if opts.noise_free else sigma
    n = rng.normal(0.0, sigma, (len(idx), *noise_dim)) if sigma > 0 else None
    return vehicle.t[idx].copy(), vehicle.world_R_body[idx], n


def simulate_attitude(
    vehicle: VehicleLog, opts: SimOptions, rng: np.random.Generator
) -> AttitudeSeries | None:
    """AHRS attitude ``world_R_body Exp(n)``, ``n ~ N(0, attitude_noise_rad^2 I)``."""
    s = _orientation_samples(
        vehicle, opts, rng, opts.attitude_rate_hz, opts.attitude_noise_rad, (3,)
    )
    if s is None:
        return None
    t, R, n = s
    return AttitudeSeries(t, matrix_to_quat_wxyz(R if n is None else R @ so3_exp(n)))


def simulate_yaw(
    vehicle: VehicleLog, opts: SimOptions, rng: np.random.Generator
) -> YawSeries | None:
    """Magnetometer-like yaw ``wrap(yaw_of(world_R_body) + n)``."""
    s = _orientation_samples(vehicle, opts, rng, opts.yaw_rate_hz, opts.yaw_noise_rad, ())
    if s is None:
        return None
    t, R, n = s
    return YawSeries(t, wrap_angle(yaw_of(R) if n is None else yaw_of(R) + n))


# ---------------------------------------------------------------------------------------------
# Rangefinder
# ---------------------------------------------------------------------------------------------


def beam_range(
    world_t_sensor: np.ndarray,
    world_d_beam: np.ndarray,
    ground_height: float,
    terrain_steps: tuple[tuple[float, float, float, float, float], ...] = (),
) -> np.ndarray:
    """Distance [m] along unit beams ``world_d_beam`` (N, 3) from ``world_t_sensor`` (N, 3) to the
    ground plane ``z = ground_height`` or the top of a raised box ``(x0, y0, x1, y1, height)``
    (top at ``ground_height + height``); ``inf`` when the beam does not point down."""
    down = -world_d_beam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(down > 0, (world_t_sensor[:, 2] - ground_height) / down, np.inf)
        for x0, y0, x1, y1, height in terrain_steps:
            rb = np.where(down > 0, (world_t_sensor[:, 2] - ground_height - height) / down, np.inf)
            hit = world_t_sensor[:, :2] + rb[:, None] * world_d_beam[:, :2]
            inside = (
                (rb > 0)
                & (hit[:, 0] >= x0)
                & (hit[:, 0] <= x1)
                & (hit[:, 1] >= y0)
                & (hit[:, 1] <= y1)
            )
            r = np.where(inside & (rb < r), rb, r)
    return np.where(r > 0, r, np.inf)


def simulate_range(
    vehicle: VehicleLog, body_T_range: np.ndarray, opts: SimOptions, rng: np.random.Generator
) -> tuple[RangeSeries | None, dict[str, Any]]:
    """Downward rangefinder along the sensor's +z axis, with lever arm.

    True reading: distance along the beam to the ground (``height_of_sensor / cos(tilt)`` on flat
    ground). Then: Gaussian noise, dropouts (missing readings), obstacle spikes (reading times a
    uniform fraction), and readings outside ``[range_min, range_max]`` are not delivered; in a
    ``range_blind`` span no reading has an echo (truth ``range_blind``: how many); with
    ``range_no_echo_at_max`` a dropout, a blinded reading or a reading beyond ``range_max`` (no
    echo) is delivered as ``range_max`` instead (truth ``range_no_echo_at_max``: how many).

    Returns:
        The series (None when off or empty) and the truth: ``range_outlier_t`` (times of the
        injected spikes that were delivered) and counts of what was not delivered.
    """
    truth: dict[str, Any] = {"range_outlier_t": [], "range_dropouts": 0, "range_out_of_limits": 0}
    if opts.range_rate_hz <= 0:
        return None, truth
    idx = sample_indices(opts, opts.range_rate_hz, len(vehicle.t))
    R = vehicle.world_R_body[idx]
    origin = vehicle.world_t_body[idx] + R @ body_T_range[:3, 3]
    beam = R @ body_T_range[:3, 2]
    true_r = beam_range(origin, beam, opts.ground_height, opts.terrain_steps)
    n = len(idx)
    r = true_r.copy()
    outlier = np.zeros(n, bool)
    keep = np.ones(n, bool)
    if not opts.noise_free:
        r = r + rng.normal(0.0, opts.range_noise_m, n)
        outlier = rng.random(n) < opts.range_outlier_prob
        lo, hi = opts.range_outlier_fraction
        r = np.where(outlier, true_r * rng.uniform(lo, hi, n), r)
        dropped = rng.random(n) < opts.range_dropout_prob
        keep &= ~dropped
        truth["range_dropouts"] = int(dropped.sum())
    if opts.range_blind:
        # A blinded sensor: no echo in these spans (after the random draws, which stay those of
        # the flight without it).
        t_r = vehicle.t[idx]
        blind = np.zeros(n, bool)
        for t0, t1 in opts.range_blind:
            blind |= (t_r >= t0) & (t_r < t1)
        r = np.where(blind, np.inf, r)
        truth["range_blind"] = int(blind.sum())
    if opts.range_no_echo_at_max:
        # No echo (a dropout, or no ground within range_max): the sensor reports its maximum.
        no_echo = ~keep | ~np.isfinite(r) | (r > opts.range_max)
        r = np.where(no_echo, opts.range_max, r)
        outlier &= ~no_echo
        keep |= no_echo
        truth["range_no_echo_at_max"] = int(no_echo.sum())
    in_limits = np.isfinite(r) & (r >= opts.range_min) & (r <= opts.range_max)
    truth["range_out_of_limits"] = int((keep & ~in_limits).sum())
    keep &= in_limits
    truth["range_outlier_t"] = [float(x) for x in vehicle.t[idx][keep & outlier]]
    if not keep.any():
        log.warning("rangefinder: no reading within [%g, %g] m", opts.range_min, opts.range_max)
        return None, truth
    return RangeSeries(vehicle.t[idx][keep].copy(), r[keep]), truth


# ---------------------------------------------------------------------------------------------
# Optical flow
# ---------------------------------------------------------------------------------------------

#: Quality of a reading with normal texture: uniform in this interval.
FLOW_QUALITY_OK = (0.6, 1.0)
#: Quality of a low-texture reading: uniform in this interval.
FLOW_QUALITY_LOW = (0.0, 0.3)


def flow_rate_of_image_motion(
    vehicle: VehicleLog, body_T_flow: np.ndarray, opts: SimOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Instantaneous image motion [rad/s] (N, 2) of the ground point on the flow sensor's optical
    axis, and the sensor's height above the terrain under it [m] (N,), at every vehicle sample.

    ``FlowSeries`` convention: with the sensor-frame velocity ``v`` (body velocity plus
    ``omega x lever arm``), rate ``w`` and the distance ``d`` along the optical axis to the ground
    or a terrain step (``beam_range``): ``[-v_x / d - w_y, -v_y / d + w_x]``. ``d`` is inf (no
    ground seen) when the axis does not point down.
    """
    body_R_flow = body_T_flow[:3, :3]
    body_t_flow = body_T_flow[:3, 3]
    R = vehicle.world_R_body
    omega = vehicle.body_omega
    u = np.einsum("nji,nj->ni", R, vehicle.world_v_body) + np.cross(omega, body_t_flow)
    v = u @ body_R_flow  # (A u) with A = body_R_flow^T
    w = omega @ body_R_flow
    origin = vehicle.world_t_body + R @ body_t_flow
    axis = R @ body_R_flow[:, 2]
    d = beam_range(origin, axis, opts.ground_height, opts.terrain_steps)
    cos_tilt = -axis[:, 2]
    height = np.where(np.isfinite(d), d * np.maximum(cos_tilt, 0.0), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        rate = np.stack([-v[:, 0] / d - w[:, 1], -v[:, 1] / d + w[:, 0]], axis=1)
    return rate, height


def simulate_flow(
    vehicle: VehicleLog,
    body_T_flow: np.ndarray,
    opts: SimOptions,
    rate_hz: float,
    rng: np.random.Generator,
) -> tuple[FlowSeries | None, dict[str, Any]]:
    """Downward optical-flow sensor (PMW3901-like): integrated flow per interval [px].

    Reading ``j`` at IMU tick ``i_j`` integrates the instantaneous image motion of
    :func:`flow_rate_of_image_motion` over ``(t[i_{j-1}], t[i_j]]`` on the vehicle grid (the
    translational part by the trapezoid rule between samples, the rotational part with the
    body rate held over each step, as the IMU's), times ``flow_pixels_per_rad``. Then:

    1. noise ``a (e_j - e_{j-1}) + b w_j`` with white ``e, w``: standard deviation
       ``flow_noise_px`` and lag-1 correlation ``flow_noise_lag1 = -a^2 / sigma^2`` (the
       differenced part is what a sensor that carries unreported sub-count motion into the next
       read gives), none beyond lag 1;
    2. low-texture readings (``flow_low_quality_prob``): quality in ``FLOW_QUALITY_LOW``, noise
       ``flow_low_quality_noise_factor`` times larger; the others quality in ``FLOW_QUALITY_OK``;
    3. readings with the sensor height above the terrain outside ``[flow_height_min,
       flow_height_max]`` (or no ground in view) are not delivered, nor dropouts
       (``flow_dropout_prob``).

    Returns:
        The series (None when off or empty) and the truth: counts of readings not delivered by
        reason (``flow_out_of_height``, ``flow_dropouts``), ``flow_low_quality`` (delivered
        low-texture readings) and the noise parameters.
    """
    truth: dict[str, Any] = {
        "flow_out_of_height": 0,
        "flow_dropouts": 0,
        "flow_low_quality": 0,
    }
    if rate_hz <= 0:
        return None, truth
    n = len(vehicle.t)
    idx = sample_indices(opts, rate_hz, n)
    if len(idx) < 2:
        return None, truth
    rate, height = flow_rate_of_image_motion(vehicle, body_T_flow, opts)
    t = vehicle.t
    dt_step = np.diff(t)
    # Translational part by the trapezoid rule, rotational (rate held) by the rectangle rule:
    # split the rate into both parts again from the vehicle's rate to integrate each correctly.
    w = vehicle.body_omega @ body_T_flow[:3, :3]
    rot = np.stack([-w[:, 1], w[:, 0]], axis=1)
    trans = rate - rot
    finite = np.all(np.isfinite(trans), axis=1)
    trans_f = np.where(finite[:, None], trans, 0.0)
    step = 0.5 * (trans_f[1:] + trans_f[:-1]) * dt_step[:, None] + rot[:-1] * dt_step[:, None]
    cum = np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    bad_cum = np.concatenate([[0], np.cumsum(~finite)])
    j0, j1 = idx[:-1], idx[1:]
    flow = (cum[j1] - cum[j0]) * opts.flow_pixels_per_rad
    dt = t[j1] - t[j0]
    saw_ground = (bad_cum[j1 + 1] - bad_cum[j0]) == 0
    h_end = height[j1]
    m = len(j1)
    quality = np.full(m, 1.0)
    keep = np.ones(m, bool)
    low = np.zeros(m, bool)
    if not opts.noise_free:
        sigma = opts.flow_noise_px
        rho = opts.flow_noise_lag1
        a = sigma * math.sqrt(-rho)
        b = sigma * math.sqrt(max(1.0 + 2.0 * rho, 0.0))
        e = rng.normal(0.0, 1.0, (m + 1, 2))
        noise = a * (e[1:] - e[:-1]) + b * rng.normal(0.0, 1.0, (m, 2))
        low = rng.random(m) < opts.flow_low_quality_prob
        noise = np.where(low[:, None], noise * opts.flow_low_quality_noise_factor, noise)
        quality = np.where(low, rng.uniform(*FLOW_QUALITY_LOW, m), rng.uniform(*FLOW_QUALITY_OK, m))
        flow = flow + noise
        dropped = rng.random(m) < opts.flow_dropout_prob
        keep &= ~dropped
        truth["flow_dropouts"] = int(dropped.sum())
    in_height = saw_ground & (h_end >= opts.flow_height_min) & (h_end <= opts.flow_height_max)
    truth["flow_out_of_height"] = int((keep & ~in_height).sum())
    keep &= in_height
    truth["flow_low_quality"] = int((keep & low).sum())
    if not keep.any():
        log.warning(
            "optical flow: no reading with the sensor within [%g, %g] m of the ground",
            opts.flow_height_min,
            opts.flow_height_max,
        )
        return None, truth
    series = FlowSeries(t=t[j1][keep].copy(), dt=dt[keep], flow=flow[keep], quality=quality[keep])
    return series, truth


# ---------------------------------------------------------------------------------------------
# Monocular SLAM
# ---------------------------------------------------------------------------------------------


@dataclass
class SlamSession:
    """Truth of one SLAM session (map): ``slam_t_cam = s(t) slam_R_world world_t_cam +
    slam_t_world`` with ``s(t) = scale (1 + scale_drift_per_s (t - t_start))``; per-axis model:
    ``slam_t_cam = (1 + drift (t - t_start)) diag(axis_scale) world_t_cam`` (identity rotation,
    zero translation)."""

    scale: float
    slam_R_world: np.ndarray
    slam_t_world: np.ndarray
    scale_drift_per_s: float
    t_start: float
    axis_scale: tuple[float, float, float] | None = None
    t_end: float = field(default=float("nan"))

    def to_json(self) -> dict[str, Any]:
        out = {
            "model": "per_axis" if self.axis_scale else "similarity",
            "scale": float(self.scale),
            "slam_R_world": self.slam_R_world.tolist(),
            "slam_t_world": self.slam_t_world.tolist(),
            "scale_drift_per_s": float(self.scale_drift_per_s),
            "t_start": float(self.t_start),
            "t_end": float(self.t_end),
        }
        if self.axis_scale:
            out["axis_scale"] = [float(k) for k in self.axis_scale]
        return out


def slam_session_masks(t: np.ndarray, opts: SimOptions) -> tuple[np.ndarray, np.ndarray]:
    """Session id per sample (-1: no output: reset gap or dropout) and the dropout mask."""
    session = np.zeros(len(t), int)
    for j, r in enumerate(sorted(opts.slam_resets)):
        session[t >= r] = j + 1
        session[(t >= r) & (t < r + opts.slam_reset_gap_s)] = -1
    dropout = np.zeros(len(t), bool)
    for t0, t1 in opts.slam_dropouts:
        dropout |= (t >= t0) & (t < t1)
    session[dropout] = -1
    return session, dropout


def simulate_slam(
    t: np.ndarray,
    world_T_cam: np.ndarray,
    opts: SimOptions,
    axis_scale: tuple[float, float, float] | None,
    rng: np.random.Generator,
) -> tuple[SlamSeries | None, dict[str, dict[str, Any]]]:
    """Monocular SLAM camera poses at image times ``t`` from true ``world_T_cam`` (N, 4, 4).

    Each session's SLAM frame is the camera frame at its first pose (the pose of the first frame is
    the identity up to noise), with a new scale drawn log-uniformly in ``slam_scale_range``
    (session 0 uses ``slam_scale`` when given). With ``axis_scale`` the seed-000 model is used
    instead (every session keeps the same per-axis scale, identity rotation, zero offset).
    Position error: white ``slam_noise_m`` per pose plus, with ``slam_origin_rw_m``, the map's
    origin drift (a Brownian walk in metres from the session's first pose).
    Latency: ``slam_latency_s + |N(0, jitter^2)|``.

    Returns:
        The series (None when no pose is delivered) and ``{str(session): truth}``.
    """
    session, _ = slam_session_masks(t, opts)
    noise_free = opts.noise_free
    sessions: dict[str, dict[str, Any]] = {}
    slam_t = np.zeros((len(t), 3))
    slam_R = np.zeros((len(t), 3, 3))
    lo, hi = opts.slam_scale_range
    for sid in sorted(set(session[session >= 0].tolist())):
        idx = np.flatnonzero(session == sid)
        i0 = idx[0]
        if sid == 0 and opts.slam_scale is not None:
            scale = float(opts.slam_scale)
        else:
            scale = float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
        if axis_scale:
            truth = SlamSession(
                scale=float(np.prod(axis_scale)) ** (1.0 / 3.0),
                slam_R_world=np.eye(3),
                slam_t_world=np.zeros(3),
                scale_drift_per_s=opts.slam_scale_drift_per_s,
                t_start=float(t[i0]),
                axis_scale=tuple(float(k) for k in axis_scale),
            )
        else:
            slam_R_world = world_T_cam[i0, :3, :3].T
            truth = SlamSession(
                scale=scale,
                slam_R_world=slam_R_world,
                slam_t_world=-scale * slam_R_world @ world_T_cam[i0, :3, 3],
                scale_drift_per_s=opts.slam_scale_drift_per_s,
                t_start=float(t[i0]),
            )
        truth.t_end = float(t[idx[-1]])
        sessions[str(sid)] = truth.to_json()
        world_t_cam = world_T_cam[idx, :3, 3]
        world_R_cam = world_T_cam[idx, :3, :3]
        if not noise_free and opts.slam_noise_m > 0:
            world_t_cam = world_t_cam + rng.normal(0.0, opts.slam_noise_m, world_t_cam.shape)
        if not noise_free and opts.slam_origin_rw_m > 0 and len(idx) > 1:
            # The map's slow drift: a Brownian offset of the SLAM frame's origin [m], zero at
            # the session's first pose (real monocular SLAM, see SimOptions.slam_origin_rw_m).
            steps = rng.normal(0.0, 1.0, (len(idx) - 1, 3)) * (
                opts.slam_origin_rw_m * np.sqrt(np.diff(t[idx]))[:, None]
            )
            world_t_cam = world_t_cam + np.vstack([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
        if not noise_free and opts.slam_rot_noise_rad > 0:
            world_R_cam = world_R_cam @ so3_exp(
                rng.normal(0.0, opts.slam_rot_noise_rad, (len(idx), 3))
            )
        drift = 1.0 + truth.scale_drift_per_s * (t[idx] - truth.t_start)
        if axis_scale:
            slam_t[idx] = drift[:, None] * world_t_cam * np.asarray(axis_scale)
        else:
            slam_t[idx] = (truth.scale * drift)[:, None] * (
                world_t_cam @ truth.slam_R_world.T
            ) + truth.slam_t_world
        slam_R[idx] = truth.slam_R_world @ world_R_cam
    keep = session >= 0
    if not keep.any():
        return None, sessions
    n = int(keep.sum())
    jitter = 0.0 if noise_free else opts.slam_latency_jitter_s
    latency = opts.slam_latency_s + (np.abs(rng.normal(0.0, jitter, n)) if jitter > 0 else 0.0)
    series = SlamSeries(
        t=t[keep].copy(),
        slam_t_cam=slam_t[keep],
        slam_q_cam_wxyz=matrix_to_quat_wxyz(slam_R[keep]),
        session=session[keep].astype(np.int64),
        latency=np.broadcast_to(latency, (n,)).astype(float),
    )
    return series, sessions


# ---------------------------------------------------------------------------------------------
# Wind
# ---------------------------------------------------------------------------------------------


def simulate_wind(
    n: int, dt: float, mean: np.ndarray, gust_std: float, tau_s: float, rng: np.random.Generator
) -> np.ndarray:
    """(n, 3) wind in world [m/s]: ``mean`` plus Ornstein-Uhlenbeck gusts on x and y with
    stationary standard deviation ``gust_std`` and correlation time ``tau_s``."""
    wind = np.tile(np.asarray(mean, float), (n, 1))
    if gust_std <= 0 or n == 0:
        return wind
    if tau_s <= 0:
        raise SimulationError(f"SimOptions.gust_tau_s={tau_s!r}: expected a positive time [s]")
    a = math.exp(-dt / tau_s)
    b = gust_std * math.sqrt(1.0 - a * a)
    noise = rng.normal(0.0, 1.0, (n, 2))
    gust = np.empty((n, 2))
    gust[0] = gust_std * noise[0]
    for i in range(1, n):
        gust[i] = a * gust[i - 1] + b * noise[i]
    wind[:, :2] += gust
    return wind
