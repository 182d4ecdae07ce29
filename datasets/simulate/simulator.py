"""``simulate()``: a whole synthetic flight (sensors + ground truth) in memory.

Frames: world z up (gravity ``(0, 0, -g)``), body FLU. Extrinsics (``flight.calib``):

- Camera ``body_T_cam``: downward, optical axis ``cam z = body -z``; ``cam x = body -y`` (image
  right = body right), ``cam y = body -x`` (image up = body forward); lever arm ``body_t_cam``.
- Rangefinder ``body_T_range``: ``Rx(pi)``, beam ``range z = body -z``, ``range x = body x``;
  lever arm ``body_t_range``.
- Optical flow ``body_T_flow``: ``Rx(pi)`` (``DOWNWARD_FLOW``: x forward, y right, optical axis
  down), lever arm ``body_t_flow``; ``calib.flow_pixels_per_rad`` = ``flow_pixels_per_rad``.

Random streams are independent: each sensor draws from its own child of
``SeedSequence(seed)``, so switching images off does not change the IMU noise.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
from fgnav.datasets.geometry import make_pose, matrix_to_quat_wxyz, so3_exp, so3_log
from fgnav.datasets.types import (
    Calibration,
    CameraIntrinsics,
    Flight,
    ImageSeries,
    ImuNoise,
    Trajectory,
)
from tqdm import tqdm

from .options import DEFAULT_BODY_T_CAM, SimOptions, SimulationError
from .render import Carpet, ground_footprints, pinhole_from_fov, to_uint8
from .scenarios import SCENARIO_TABLE, SCENARIOS
from .sensors import (
    decimation,
    sample_indices,
    simulate_attitude,
    simulate_flow,
    simulate_imu,
    simulate_range,
    simulate_slam,
    simulate_wind,
    simulate_yaw,
)
from .vehicle import GRAVITY, VehicleLog, VehicleParams, simulate_vehicle

log = logging.getLogger(__name__)

#: ``body_R_cam`` of the downward camera (columns: cam x, y, z in body).
BODY_R_CAM = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: ``body_R_range`` of the downward rangefinder (``Rx(pi)``).
BODY_R_RANGE = np.diag([1.0, -1.0, -1.0])
#: ``body_R_flow`` of the downward flow sensor (``Rx(pi)``, as ``types.DOWNWARD_FLOW``).
BODY_R_FLOW = np.diag([1.0, -1.0, -1.0])
#: Order of the child random streams (appending keeps earlier streams unchanged).
_STREAMS = ("wind", "imu", "attitude", "yaw", "range", "slam", "carpet", "images", "flow")
#: Number of poses averaged over the exposure for motion blur.
BLUR_SAMPLES = 7


def _rngs(seed: int) -> dict[str, np.random.Generator]:
    children = np.random.SeedSequence(seed).spawn(len(_STREAMS))
    return {name: np.random.default_rng(c) for name, c in zip(_STREAMS, children, strict=True)}


def _interpolate_pose(vehicle: VehicleLog, t: float) -> np.ndarray:
    """``world_T_body`` at time ``t`` [s]: linear position, geodesic rotation between samples."""
    dt = vehicle.t[1] - vehicle.t[0]
    x = (t - vehicle.t[0]) / dt
    i = int(np.clip(math.floor(x), 0, len(vehicle.t) - 2))
    a = float(np.clip(x - i, 0.0, 1.0))
    R0, R1 = vehicle.world_R_body[i], vehicle.world_R_body[i + 1]
    R = R0 @ so3_exp(a * so3_log(R0.T @ R1))
    p = (1 - a) * vehicle.world_t_body[i] + a * vehicle.world_t_body[i + 1]
    return make_pose(R, p)


def _render_images(
    vehicle: VehicleLog,
    idx: np.ndarray,
    body_T_cam: np.ndarray,
    camera: CameraIntrinsics,
    opts: SimOptions,
    rng_carpet: np.random.Generator,
    rng_images: np.random.Generator,
    progress: bool,
) -> ImageSeries:
    K = camera.K
    W, Hh = camera.width, camera.height
    times = vehicle.t[idx]
    if opts.motion_blur_s > 0:
        offsets = np.linspace(-0.5, 0.5, BLUR_SAMPLES) * opts.motion_blur_s
    else:
        offsets = np.zeros(1)
    poses = np.stack(
        [[_interpolate_pose(vehicle, t + o) @ body_T_cam for o in offsets] for t in times]
    )
    flat = poses.reshape(-1, 4, 4)
    corners = ground_footprints(flat, K, W, Hh, opts.ground_height)
    carpet = Carpet.make(
        corners.reshape(-1, 2).min(axis=0),
        corners.reshape(-1, 2).max(axis=0),
        opts.ground_height,
        opts.texture_resolution_m,
        rng_carpet,
        opts.featureless_patches,
    )
    frames = np.empty((len(times), Hh, W), np.uint8)
    noise_std = 0.0 if opts.noise_free else opts.image_noise_std
    for k in tqdm(range(len(times)), desc="rendering", unit="frame", disable=not progress):
        img = carpet.render(poses[k][0], K, W, Hh)
        for P in poses[k][1:]:
            img += carpet.render(P, K, W, Hh)
        img /= len(poses[k])
        if opts.brightness_amplitude:
            img = img * (
                1.0
                + opts.brightness_amplitude
                * math.sin(2.0 * math.pi * times[k] / opts.brightness_period_s)
            )
        if noise_std > 0:
            img = img + noise_std * rng_images.standard_normal(img.shape, dtype=np.float32)
        frames[k] = to_uint8(img)
    return ImageSeries(t=times.copy(), frames=frames, camera=camera)


def simulate(
    scenario: str, seed: int = 0, options: SimOptions | None = None, progress: bool = False
) -> Flight:
    """Simulate one flight of ``scenario`` with every sensor and its ground truth.

    Args:
        scenario: one of ``SCENARIOS``.
        seed: seed of every random draw (same seed and options -> identical flight).
        options: simulator options (None: defaults).
        progress: show a progress bar while rendering images.

    Returns:
        A checked :class:`Flight`: ``imu`` (IMU rate), ``attitude``, ``yaw``, ``range``, ``slam``,
        ``images`` (when enabled), ``flow`` (when on: ``SimOptions.flow_rate_hz``),
        ``ground_truth`` at the IMU rate with velocity and biases, ``calib``, and
        ``meta["truth"]`` (JSON-serialisable: drag_k, ground_height, terrain_steps,
        slam_sessions, range_outlier_t, wind, options, scenario, seed; ``flow`` with its rate
        and noise when on).

    Raises:
        SimulationError: unknown scenario, negative seed or invalid options.
    """
    if scenario not in SCENARIO_TABLE:
        raise SimulationError(f"unknown scenario {scenario!r}; expected one of {list(SCENARIOS)}")
    if int(seed) < 0:
        raise SimulationError(f"seed {seed!r}: expected a non-negative integer")
    sc = SCENARIO_TABLE[scenario]
    opts = options or SimOptions()
    opts.validate()
    rngs = _rngs(int(seed))
    duration = opts.duration if opts.duration is not None else sc.duration
    dt = 1.0 / opts.imu_rate_hz
    t = np.arange(int(math.floor(duration * opts.imu_rate_hz + 1e-9)) + 1) * dt
    if len(t) < 2:
        raise SimulationError(f"SimOptions.duration={duration!r}: shorter than two IMU samples")

    # 1. Vehicle along the reference, in the wind.
    ref = sc.reference(t)
    wind_mean = np.asarray(sc.wind_mean if opts.wind is None else opts.wind, float)
    gust_std = sc.gust_std if opts.gust_std is None else opts.gust_std
    wind = simulate_wind(len(t), dt, wind_mean, gust_std, opts.gust_tau_s, rngs["wind"])
    v0 = None
    if sc.body_v0 is not None:
        R0_yaw = so3_exp(np.array([0.0, 0.0, ref.yaw[0]]))
        v0 = ref.world_v[0] + R0_yaw @ np.asarray(sc.body_v0, float)
    params = VehicleParams(drag_k=tuple(float(k) for k in opts.drag_k))
    vehicle = simulate_vehicle(
        t,
        ref.world_p,
        ref.world_v,
        ref.world_a,
        ref.yaw,
        ref.yaw_rate,
        wind,
        params,
        int(opts.substeps),
        world_v_body0=v0,
    )

    # 2. Calibration.
    body_t_cam = next(
        x for x in (opts.body_t_cam, sc.body_t_cam, DEFAULT_BODY_T_CAM) if x is not None
    )
    body_T_cam = make_pose(BODY_R_CAM, np.asarray(body_t_cam, float))
    body_T_range = make_pose(BODY_R_RANGE, np.asarray(opts.body_t_range, float))
    fx, fy, cx, cy = pinhole_from_fov(opts.image_width, opts.image_height, opts.camera_hfov_deg)
    camera = CameraIntrinsics(fx, fy, cx, cy, int(opts.image_width), int(opts.image_height))
    calib = Calibration(
        body_T_cam=body_T_cam,
        body_T_range=body_T_range,
        camera=camera,
        imu_noise=ImuNoise(
            opts.gyro_noise_density,
            opts.accel_noise_density,
            opts.gyro_random_walk,
            opts.accel_random_walk,
        ),
        range_min=float(opts.range_min),
        range_max=float(opts.range_max),
        body_T_flow=make_pose(BODY_R_FLOW, np.asarray(opts.body_t_flow, float)),
        flow_pixels_per_rad=float(opts.flow_pixels_per_rad),
    )

    # 3. Sensors.
    imu, imu_truth = simulate_imu(vehicle, opts, rngs["imu"])
    attitude = simulate_attitude(vehicle, opts, rngs["attitude"])
    yaw = simulate_yaw(vehicle, opts, rngs["yaw"])
    range_series, range_truth = simulate_range(vehicle, body_T_range, opts, rngs["range"])
    flow_rate = sc.flow_rate_hz if opts.flow_rate_hz is None else opts.flow_rate_hz
    flow, flow_truth = simulate_flow(vehicle, calib.body_T_flow, opts, flow_rate, rngs["flow"])
    world_T_body = np.zeros((len(t), 4, 4))
    world_T_body[:, :3, :3] = vehicle.world_R_body
    world_T_body[:, :3, 3] = vehicle.world_t_body
    world_T_body[:, 3, 3] = 1.0
    slam, sessions = None, {}
    axis_scale = sc.slam_axis_scale if opts.slam_axis_scale is None else opts.slam_axis_scale
    if opts.slam_rate_hz > 0:
        sidx = sample_indices(opts, opts.slam_rate_hz, len(t))
        slam, sessions = simulate_slam(
            t[sidx], world_T_body[sidx] @ body_T_cam, opts, axis_scale or None, rngs["slam"]
        )
    images = None
    if opts.images and opts.image_rate_hz > 0:
        iidx = sample_indices(opts, opts.image_rate_hz, len(t))
        images = _render_images(
            vehicle, iidx, body_T_cam, camera, opts, rngs["carpet"], rngs["images"], progress
        )

    ground_truth = Trajectory(
        t=t.copy(),
        world_t_body=vehicle.world_t_body,
        world_q_body_wxyz=matrix_to_quat_wxyz(vehicle.world_R_body),
        world_v_body=vehicle.world_v_body,
        gyro_bias=imu_truth.gyro_bias,
        accel_bias=imu_truth.accel_bias,
    )

    # 4. Truth and notes (JSON-serialisable).
    wind_step = max(1, decimation(opts, min(10.0, opts.imu_rate_hz)))
    truth: dict[str, Any] = {
        "scenario": scenario,
        "seed": int(seed),
        "options": dataclasses.asdict(opts),
        "drag_k": [float(k) for k in opts.drag_k],
        "ground_height": float(opts.ground_height),
        "terrain_steps": [list(map(float, s)) for s in opts.terrain_steps],
        "slam_sessions": sessions,
        "slam_axis_scale": [float(k) for k in axis_scale] if axis_scale else None,
        "range_outlier_t": range_truth["range_outlier_t"],
        "wind_mean": wind_mean.tolist(),
        "gust_std": float(gust_std),
        "wind_t": t[::wind_step].tolist(),
        "wind": wind[::wind_step].tolist(),
        "gravity": GRAVITY,
    }
    if flow_rate > 0:
        truth["flow"] = {
            "rate_hz": float(flow_rate),
            "noise_px": float(opts.flow_noise_px),
            "noise_lag1": float(opts.flow_noise_lag1),
            "pixels_per_rad": float(opts.flow_pixels_per_rad),
        }
    n_slam_grid = 0
    if opts.slam_rate_hz > 0:
        n_slam_grid = len(sample_indices(opts, opts.slam_rate_hz, len(t)))
    notes = {
        "range_dropouts": range_truth["range_dropouts"],
        "range_out_of_limits": range_truth["range_out_of_limits"],
        **{k: v for k, v in range_truth.items() if k in ("range_no_echo_at_max", "range_blind")},
        **(dict(flow_truth) if flow_rate > 0 else {}),
        "slam_sessions": len(sessions),
        "slam_lost": n_slam_grid - (len(slam) if slam is not None else 0),
    }
    if range_truth["range_out_of_limits"]:
        log.info(
            "rangefinder: %d readings outside [%g, %g] m not delivered",
            range_truth["range_out_of_limits"],
            opts.range_min,
            opts.range_max,
        )
    flight = Flight(
        name=f"sim-{scenario}-seed{seed}",
        source="simulator",
        imu=imu,
        attitude=attitude,
        range=range_series,
        yaw=yaw,
        slam=slam,
        images=images,
        flow=flow,
        ground_truth=ground_truth,
        calib=calib,
        meta={
            "synthetic": True,
            "scenario": scenario,
            "seed": int(seed),
            "description": sc.description,
            "truth": truth,
            "notes": notes,
            # The SLAM input's model, as a SLAM bridge would declare it (not ground truth).
            **({"slam_model": "axis"} if axis_scale else {}),
        },
    )
    flight.check()
    log.info(
        "simulated %s seed %d: %.1f s, %s; range: %d dropouts, %d out of limits; SLAM: %d "
        "session(s), %d poses lost",
        scenario,
        seed,
        duration,
        ", ".join(f"{k} {len(v)}" for k, v in flight.streams().items()),
        notes["range_dropouts"],
        notes["range_out_of_limits"],
        notes["slam_sessions"],
        notes["slam_lost"],
    )
    return flight


def world_T_cam_at(flight: Flight, t: np.ndarray) -> np.ndarray:
    """True camera poses ``world_T_cam = world_T_body body_T_cam`` (N, 4, 4) of a simulated
    flight at times ``t`` [s] on its ground-truth grid (image, SLAM and range times are).

    Raises:
        SimulationError: a time is not a ground-truth sample time.
    """
    gt = flight.ground_truth
    t = np.atleast_1d(np.asarray(t, float))
    idx = np.clip(np.searchsorted(gt.t, t - 1e-9), 0, len(gt) - 1)
    bad = np.flatnonzero(np.abs(gt.t[idx] - t) > 1e-9)
    if bad.size:
        raise SimulationError(f"time {t[bad[0]]!r} is not a ground-truth sample time")
    world_T_body = np.zeros((len(t), 4, 4))
    world_T_body[:, :3, :3] = gt.world_R_body()[idx]
    world_T_body[:, :3, 3] = gt.world_t_body[idx]
    world_T_body[:, 3, 3] = 1.0
    return world_T_body @ flight.calib.body_T_cam


def simulate_to_folder(
    scenario: str,
    out: str | Path,
    seed: int = 0,
    options: SimOptions | None = None,
    progress: bool = False,
    overwrite: bool = False,
) -> Path:
    """Simulate a flight and write it with ``fgnav.datasets.native.write_flight``.

    Args:
        scenario, seed, options, progress: as :func:`simulate`.
        out: folder to write.
        overwrite: replace an existing flight folder.

    Returns:
        The folder written.
    """
    from fgnav.datasets.native import write_flight

    flight = simulate(scenario, seed=seed, options=options, progress=progress)
    return write_flight(flight, Path(out), overwrite=overwrite)
