"""Options of the flight simulator (one dataclass, TOML-friendly: scalars and tuples)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

from fgnav.datasets.errors import FgnavError
from fgnav.datasets.types import ImuNoise

_IMU_DEFAULTS = ImuNoise()

#: Default camera lever arm in body [m] (a few cm forward and below the IMU).
DEFAULT_BODY_T_CAM = (0.05, 0.0, -0.04)
#: Default rangefinder lever arm in body [m].
DEFAULT_BODY_T_RANGE = (0.03, 0.02, -0.05)
#: Default optical-flow sensor lever arm in body [m] (under the body centre, as a flow deck).
DEFAULT_BODY_T_FLOW = (0.0, 0.0, -0.02)


class SimulationError(FgnavError, ValueError):
    """Invalid simulator options or scenario name."""


@dataclass(frozen=True)
class SimOptions:
    """Everything the simulator can vary. ``None`` means "the scenario's default".

    Rates are in Hz, up to ``imu_rate_hz``: every stream is sampled on the IMU grid, at every
    ``imu_rate_hz / rate``-th tick, or at the tick nearest each ``j / rate`` when that ratio is
    not an integer (irregular intervals, e.g. a 30 Hz camera at 200 Hz: 30 or 35 ms).
    A rate of 0 turns a stream off. Noise levels are one standard deviation.

    Attributes:
        duration: flight length [s] (None: the scenario's).
        imu_rate_hz: IMU and ground-truth rate [Hz].
        substeps: integration sub-steps per IMU sample.
        noise_free: zero every noise, bias, outlier and dropout (truth-only signals).
        gyro_noise_density, accel_noise_density, gyro_random_walk, accel_random_walk: IMU noise
            densities (Kalibr/EuRoC convention, defaults of :class:`ImuNoise`); white noise is
            discretised as ``density / sqrt(dt)`` and the bias walk as ``walk * sqrt(dt)``.
        gyro_bias0_std [rad/s], accel_bias0_std [m/s^2]: spread of the initial biases.
        attitude_rate_hz, attitude_noise_rad: AHRS attitude stream (rotation-vector noise).
        yaw_rate_hz, yaw_noise_rad: magnetometer-like yaw stream.
        range_rate_hz, range_noise_m, range_min, range_max: downward rangefinder; readings outside
            ``[range_min, range_max]`` are not delivered (counted in ``meta``).
        range_dropout_prob: probability that a reading is missing.
        range_no_echo_at_max: a reading without an echo (a dropout, or the ground beyond
            ``range_max``) is delivered as ``range_max`` instead of left out, as many
            rangefinders report it (:func:`fgnav.datasets.range_limits.range_at_max`; counted
            ``range_no_echo_at_max`` in ``meta``).
        range_blind: spans ``(t0, t1)`` [s] in which the rangefinder gets no echo whatever the
            height (a blinded, covered or failed sensor): its readings there are missing, or
            ``range_max`` with ``range_no_echo_at_max`` (counted ``range_blind`` in ``meta``).
        range_outlier_prob: probability of an obstacle spike (reading shortened to a uniform
            fraction ``range_outlier_fraction`` of the true range); times kept in the truth.
        body_t_range: rangefinder lever arm in body [m]; its beam is along body -z.
        ground_height: height of the flat ground in world [m].
        terrain_steps: raised boxes ``(x0, y0, x1, y1, height)`` [m] the rangefinder sees (the
            camera renders the flat ground only).
        slam_rate_hz: monocular SLAM rate (poses at image times when it equals the image rate).
        slam_noise_m: position noise before scaling [m]; slam_rot_noise_rad: orientation noise.
        slam_scale: SLAM units per metre of the first session (None: log-uniform in
            ``slam_scale_range``, seeded); later sessions always draw a new one.
        slam_axis_scale: per-axis scale ``(kx, ky, kz)`` of seed 000 (None: the scenario's; an
            empty tuple forces the similarity model).
        slam_scale_drift_per_s: relative scale drift per second within a session (linear in
            time). Default 1e-4 (0.6 % per minute): above the 2-sigma bound of the trend of a real
            run, ORB-SLAM3 monocular on EuRoC MH_01 (-2.7e-5 +- 2.6e-5 per second in 10 s
            windows, ``scripts/slam_scale_drift.py``). Up to 2026-11 the default was 5e-4, 6x that
            bound; keep it for stress tests of scale tracking.
        slam_origin_rw_m: map drift: the SLAM frame's origin follows a Brownian walk of this
            density [m/sqrt(s)] per axis (in metres before scaling, zero at each session's
            first pose, continuous in time); 0 (default, the seeded flights and figures as
            before): the map is rigid and every pose has only its white noise. Real monocular
            SLAM drifts: ORB-SLAM3 on EuRoC MH_01 (run A, whole-run Sim(3) fit to the truth
            camera positions) has a white part of about 2.9 mm per axis and a residual whose
            increments grow with the lag, ``E|r(t + tau) - r(t)|^2`` per axis 1.6e-5 m^2 at
            50 ms, 4.2e-5 at 0.5 s, 7.5e-5 at 2 s, 2.7e-4 at 10 s (about 7 mm/sqrt(s) over
            0.5 s, 5 mm/sqrt(s) over 10 s; ``scripts/nees_breakdown.py --slam-drift``); the
            smoothers model it as the alignment's origin walk ``graph.slam_trans_rw_m``.
        slam_latency_s, slam_latency_jitter_s: delivery delay of SLAM poses [s].
        slam_resets: times of map resets [s]: tracking is lost for ``slam_reset_gap_s``, then a
            new session starts with a new similarity and scale.
        slam_dropouts: tracking losses ``(t0, t1)`` [s] without a new session.
        images: render downward camera images.
        image_rate_hz, image_width, image_height, camera_hfov_deg: camera (pinhole, no
            distortion; default 320x240 and 64 degrees like seed 004's downward camera).
        body_t_cam: camera lever arm in body [m] (None: the scenario's or the default).
        image_noise_std: pixel noise [grey levels]; motion_blur_s: exposure time [s] (0: none);
            brightness_amplitude: relative sinusoidal gain change, period brightness_period_s;
            featureless_patches: number of uniform white patches on the carpet (seed 003's white
            walls); texture_resolution_m: carpet texel size [m].
        flow_rate_hz: downward optical-flow sensor (PMW3901-like) [Hz]; None: the scenario's
            (100 Hz for ``flowdeck``, off for the others, so that their seeded
            flights and figures stay as they were); 0: off. Each reading is the flow integrated
            over the interval since the previous flow tick from the true velocity, rate, attitude
            and the distance along the optical axis to the (stepped) terrain, times
            ``flow_pixels_per_rad`` (``FlowSeries`` convention, ``sensors.simulate_flow``).
        flow_pixels_per_rad: flow units per radian of image motion (a Crazyflie flow deck: 47.8
            fitted on real flights, 48.8 in its firmware).
        flow_noise_px: standard deviation of one reading's noise [px].
        flow_noise_lag1: lag-1 correlation of consecutive readings' noise, in [-0.5, 0] (real
            PMW3901 on a Crazyflie: about -0.3): a differenced white noise (counts carried from
            one read to the next) plus a white noise.
        flow_height_min, flow_height_max: readings whose sensor height above the terrain is
            outside this interval [m] are not delivered (no valid motion; counted in ``meta``).
        flow_dropout_prob: probability that a reading is missing (a Crazyflie logs flow only when
            valid).
        flow_low_quality_prob: probability that a reading has low texture: quality uniform in
            [0, 0.3] and noise ``flow_low_quality_noise_factor`` times larger (delivered: the
            estimator gates on quality). Other readings have quality in [0.6, 1].
        body_t_flow: flow sensor lever arm in body [m]; optical axis along body -z.
        drag_k: rotor drag ``(kx, ky)`` [1/s].
        wind: mean wind in world [m/s] (None: the scenario's); gust_std [m/s] (None: the
            scenario's) and gust_tau_s [s]: Ornstein-Uhlenbeck gusts on the horizontal axes.
    """

    #: Rates for which 0 switches the stream off (``fgnav.config`` accepts 0 for these).
    ZERO_MEANS_OFF: ClassVar[frozenset[str]] = frozenset(
        {
            "attitude_rate_hz",
            "yaw_rate_hz",
            "range_rate_hz",
            "slam_rate_hz",
            "image_rate_hz",
            "flow_rate_hz",
        }
    )

    duration: float | None = None
    imu_rate_hz: float = 200.0
    substeps: int = 2
    noise_free: bool = False
    gyro_noise_density: float = _IMU_DEFAULTS.gyro_noise_density
    accel_noise_density: float = _IMU_DEFAULTS.accel_noise_density
    gyro_random_walk: float = _IMU_DEFAULTS.gyro_random_walk
    accel_random_walk: float = _IMU_DEFAULTS.accel_random_walk
    gyro_bias0_std: float = 0.003
    accel_bias0_std: float = 0.05
    attitude_rate_hz: float = 100.0
    attitude_noise_rad: float = 0.005
    yaw_rate_hz: float = 10.0
    yaw_noise_rad: float = 0.02
    range_rate_hz: float = 25.0
    range_noise_m: float = 0.01
    range_min: float = 0.1
    range_max: float = 8.0
    range_dropout_prob: float = 0.02
    range_no_echo_at_max: bool = False
    range_blind: tuple[tuple[float, float], ...] = ()
    range_outlier_prob: float = 0.01
    range_outlier_fraction: tuple[float, float] = (0.2, 0.8)
    body_t_range: tuple[float, float, float] = DEFAULT_BODY_T_RANGE
    ground_height: float = 0.0
    terrain_steps: tuple[tuple[float, float, float, float, float], ...] = ()
    slam_rate_hz: float = 20.0
    slam_noise_m: float = 0.01
    slam_rot_noise_rad: float = 0.003
    slam_scale: float | None = None
    slam_scale_range: tuple[float, float] = (0.5, 2.0)
    slam_axis_scale: tuple[float, ...] | None = None
    slam_scale_drift_per_s: float = 1e-4
    slam_origin_rw_m: float = 0.0
    slam_latency_s: float = 0.1
    slam_latency_jitter_s: float = 0.01
    slam_resets: tuple[float, ...] = ()
    slam_reset_gap_s: float = 1.0
    slam_dropouts: tuple[tuple[float, float], ...] = ()
    images: bool = True
    image_rate_hz: float = 20.0
    image_width: int = 320
    image_height: int = 240
    camera_hfov_deg: float = 64.0
    body_t_cam: tuple[float, float, float] | None = None
    image_noise_std: float = 2.0
    motion_blur_s: float = 0.0
    brightness_amplitude: float = 0.0
    brightness_period_s: float = 10.0
    featureless_patches: int = 0
    texture_resolution_m: float = 0.01
    flow_rate_hz: float | None = None
    flow_pixels_per_rad: float = 48.0
    flow_noise_px: float = 0.2
    flow_noise_lag1: float = -0.3
    flow_height_min: float = 0.08
    flow_height_max: float = 5.0
    flow_dropout_prob: float = 0.02
    flow_low_quality_prob: float = 0.01
    flow_low_quality_noise_factor: float = 10.0
    body_t_flow: tuple[float, float, float] = DEFAULT_BODY_T_FLOW
    drag_k: tuple[float, float] = (0.38, 0.42)
    wind: tuple[float, float, float] | None = None
    gust_std: float | None = None
    gust_tau_s: float = 2.0

    def __post_init__(self) -> None:
        # TOML gives lists; store tuples so the options stay hashable and comparable.
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, list):
                v = tuple(tuple(x) if isinstance(x, list) else x for x in v)
                object.__setattr__(self, f.name, v)
        self._check_types()
        self.validate()

    def _check_types(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            default = f.default
            if isinstance(default, bool):
                ok = isinstance(v, bool)
                expected = "true or false"
            elif isinstance(default, int | float):
                ok = isinstance(v, int | float) and not isinstance(v, bool)
                expected = "a number"
            elif isinstance(default, tuple):
                ok = isinstance(v, tuple)
                expected = "a list"
            elif default is None and v is not None:
                ok = isinstance(v, int | float | tuple) and not isinstance(v, bool)
                expected = "a number or a list"
            else:
                continue
            if not ok:
                raise SimulationError(f"SimOptions.{f.name}={v!r}: expected {expected}")

    def validate(self) -> None:
        """Raise :class:`SimulationError` naming the first invalid field."""

        def bad(name: str, expected: str) -> SimulationError:
            return SimulationError(
                f"SimOptions.{name}={getattr(self, name)!r}: expected {expected}"
            )

        if self.duration is not None and not self.duration > 0:
            raise bad("duration", "a positive number of seconds")
        if not self.imu_rate_hz > 0:
            raise bad("imu_rate_hz", "a positive rate")
        if int(self.substeps) != self.substeps or self.substeps < 1:
            raise bad("substeps", "an integer >= 1")
        for name in sorted(self.ZERO_MEANS_OFF):
            rate = getattr(self, name)
            if rate is None:
                continue
            if rate < 0 or rate > self.imu_rate_hz:
                raise bad(name, f"0 (off) or a rate up to imu_rate_hz={self.imu_rate_hz}")
        for name in (
            "range_dropout_prob",
            "range_outlier_prob",
            "flow_dropout_prob",
            "flow_low_quality_prob",
        ):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise bad(name, "a probability in [0, 1]")
        if not 0 <= self.range_min < self.range_max:
            raise bad("range_min", f"0 <= range_min < range_max={self.range_max}")
        lo, hi = self.slam_scale_range
        if not 0 < lo <= hi:
            raise bad("slam_scale_range", "(low, high) with 0 < low <= high")
        if len(self.drag_k) != 2 or min(self.drag_k) < 0:
            raise bad("drag_k", "two non-negative coefficients (kx, ky) [1/s]")
        if self.slam_axis_scale not in (None, ()) and (
            len(self.slam_axis_scale) != 3 or min(self.slam_axis_scale) <= 0
        ):
            raise bad("slam_axis_scale", "None, () or three positive scales (kx, ky, kz)")
        if not (math.isfinite(self.slam_origin_rw_m) and self.slam_origin_rw_m >= 0):
            raise bad("slam_origin_rw_m", "a non-negative walk density [m/sqrt(s)]")
        if self.slam_scale is not None and not self.slam_scale > 0:
            raise bad("slam_scale", "a positive scale (SLAM units per metre)")
        for name in ("slam_dropouts", "range_blind"):
            for t0, t1 in getattr(self, name):
                if not t1 > t0:
                    raise bad(name, "intervals (t0, t1) with t1 > t0")
        for step in self.terrain_steps:
            if len(step) != 5 or not (step[2] > step[0] and step[3] > step[1]):
                raise bad("terrain_steps", "boxes (x0, y0, x1, y1, height) with x1 > x0, y1 > y0")
        for name in ("image_width", "image_height"):
            if getattr(self, name) < 16:
                raise bad(name, "an image of at least 16 x 16 pixels")
        if not 0 < self.camera_hfov_deg < 170:
            raise bad("camera_hfov_deg", "a horizontal field of view in (0, 170) degrees")
        if not self.texture_resolution_m > 0:
            raise bad("texture_resolution_m", "a positive texel size [m]")
        if self.motion_blur_s < 0:
            raise bad("motion_blur_s", "a non-negative exposure time [s]")
        if not (math.isfinite(self.flow_pixels_per_rad) and self.flow_pixels_per_rad > 0):
            raise bad("flow_pixels_per_rad", "a positive number of flow units per radian")
        if not self.flow_noise_px >= 0:
            raise bad("flow_noise_px", "a non-negative noise [px]")
        if not self.flow_low_quality_noise_factor >= 0:
            raise bad("flow_low_quality_noise_factor", "a non-negative factor")
        if not -0.5 <= self.flow_noise_lag1 <= 0.0:
            raise bad("flow_noise_lag1", "a lag-1 correlation in [-0.5, 0]")
        if not 0 <= self.flow_height_min < self.flow_height_max:
            raise bad(
                "flow_height_min", f"0 <= flow_height_min < flow_height_max={self.flow_height_max}"
            )
        if not math.isfinite(self.ground_height):
            raise bad("ground_height", "a finite height [m]")


#: Keyword arguments of :class:`SimOptions` for a Crazyflie-like flow-deck flight (with the
#: ``flowdeck`` scenario): IMU, optical flow and rangefinder only (no camera, SLAM, attitude or
#: yaw stream), the rangefinder as measured on the real flow-deck flights (8 mm noise, no airborne
#: outliers). Used by the fault matrix's flow-deck base and the tests.
CRAZYFLIE_LIKE = dict(
    images=False,
    slam_rate_hz=0.0,
    attitude_rate_hz=0.0,
    yaw_rate_hz=0.0,
    range_noise_m=0.008,
    range_outlier_prob=0.0,
)
