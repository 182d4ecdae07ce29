"""fgnav's flight data model: frozen dataclasses of column arrays, one per sensor stream.

Frames and units follow ../shared/DESIGN.md section 2: world z up (ENU-like), body FLU, SI units,
time in float seconds on one clock. Quaternions are Hamilton ``[w, x, y, z]`` (field names end in
``_wxyz``). Readers in this package return these types and know nothing of GTSAM.

Every series has ``check(name)``, which raises :class:`FlightDataError` naming the stream and
field when a value is non-finite, a shape is wrong, or time is not strictly increasing.
Construction does not check (readers build, then call ``check``), so a bad series can be built
and reported.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import FlightDataError

# ----------------------------------------------------------------------------------------------
# Checks shared by all series
# ----------------------------------------------------------------------------------------------


def _check_time(name: str, t: np.ndarray) -> None:
    if t.ndim != 1:
        raise FlightDataError(f"{name}.t: expected a 1-D array of times, got shape {t.shape}")
    if t.size == 0:
        raise FlightDataError(f"{name}.t: the stream is empty (no samples)")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise FlightDataError(f"{name}.t: non-finite time at sample {bad[0]} ({t[bad[0]]})")
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        i = int(bad[0])
        raise FlightDataError(
            f"{name}.t: time must be strictly increasing; sample {i + 1} (t={t[i + 1]!r}) "
            f"does not follow sample {i} (t={t[i]!r}) ({bad.size} such samples)"
        )


#: An IMU's median sample interval lies in this range [s] (10 kHz to 5 Hz): outside it the
#: stamps are not in seconds (ns stamps read as seconds: a 7 TiB allocation, or a hang online).
IMU_DT_RANGE_S = (1e-4, 0.2)
#: An IMU interval longer than this [s] is a clock jump, not a pause of the log.
IMU_CLOCK_JUMP_S = 3600.0


#: Largest IMU sample a reader keeps [rad/s, m/s^2] (norm of the 3 axes): beyond any MEMS IMU's
#: full scale (gyros: 2000-4000 deg/s, 35-70 rad/s; accelerometers: 16-32 g); a larger finite
#: value is a corrupted sample (a MAVLink HIGHRES_IMU with 1e30 in a field overflowed the
#: accelerometer check's sums; a Crazyflie log's gyro of 1e30 deg/s wrecked the batch). The
#: binary readers skip such samples and count them (``skipped_implausible``); the online smoother
#: drops them as ``imu:implausible``.
IMU_MAX_RATE = 100.0
IMU_MAX_ACCEL = 50.0 * 9.81


def imu_plausible(body_omega: np.ndarray, body_accel: np.ndarray) -> np.ndarray:
    """(N,) bool: the rows whose rate and specific-force norms are within :data:`IMU_MAX_RATE`
    and :data:`IMU_MAX_ACCEL` (False for non-finite rows too)."""
    w = np.asarray(body_omega, dtype=float)
    a = np.asarray(body_accel, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        w_sq = np.sum(w * w, axis=-1)
        a_sq = np.sum(a * a, axis=-1)
        return (w_sq <= IMU_MAX_RATE**2) & (a_sq <= IMU_MAX_ACCEL**2)


def check_imu_interval(name: str, dt: float, what: str = "median") -> None:
    """One-line error for an IMU sample interval ``dt`` [s] outside ``IMU_DT_RANGE_S``."""
    lo, hi = IMU_DT_RANGE_S
    if not lo <= dt <= hi:
        raise FlightDataError(
            f"{name}.t: {what} sample interval {dt:.6g} s ({1.0 / dt:.3g} Hz) is not an IMU's "
            f"({lo:g}-{hi:g} s): are the stamps in seconds (not ns, us or ms)?"
        )


def check_imu_clock(name: str, t: np.ndarray) -> None:
    """One-line errors for IMU stamps not in seconds and for a clock jump inside the log (the
    readers' check, :func:`fgnav.datasets.load.load_flight`; not :meth:`ImuSeries.check`,
    which also sees outlines and hand-made series)."""
    if t.size < 2:
        return
    dt = np.diff(t)
    check_imu_interval(name, float(np.median(dt)))
    i = int(np.argmax(dt))
    if dt[i] > IMU_CLOCK_JUMP_S:
        raise FlightDataError(
            f"{name}.t: the clock jumps by {dt[i]:.6g} s between samples {i} and {i + 1} "
            f"(t={t[i]:.6g} -> {t[i + 1]:.6g} s): split the log there"
        )


def _check_column(
    name: str, field_name: str, a: np.ndarray | None, n: int, width: int | None, optional=False
) -> None:
    if a is None:
        if optional:
            return
        raise FlightDataError(f"{name}.{field_name}: missing")
    expected = (n,) if width is None else (n, width)
    if a.shape != expected:
        raise FlightDataError(f"{name}.{field_name}: expected shape {expected}, got {a.shape}")
    if a.dtype.kind in "fc":
        bad = np.argwhere(~np.isfinite(a))
        if bad.size:
            i = int(bad[0][0])
            raise FlightDataError(
                f"{name}.{field_name}: non-finite value at sample {i} (t index {i}): {a[i]}"
            )


def _check_quat(name: str, field_name: str, q: np.ndarray | None, n: int, optional=False) -> None:
    _check_column(name, field_name, q, n, 4, optional)
    if q is None:
        return
    norms = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if bad.size:
        i = int(bad[0])
        raise FlightDataError(
            f"{name}.{field_name}: quaternion at sample {i} has norm {norms[i]:.6f}, expected a "
            f"unit quaternion [w, x, y, z]"
        )


def _as_array(x: Any, dtype=float) -> np.ndarray | None:
    return None if x is None else np.asarray(x, dtype=dtype)


class _Series:
    """Mixin: common helpers of time series (``t`` is always the first field)."""

    t: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def duration(self) -> float:
        """Seconds between the first and last sample."""
        return float(self.t[-1] - self.t[0]) if len(self) else 0.0

    @property
    def rate_hz(self) -> float:
        """Median sample rate [Hz]."""
        if len(self) < 2:
            return 0.0
        return float(1.0 / np.median(np.diff(self.t)))

    def select(self, mask_or_index: np.ndarray):
        """A new series of the same type with the rows picked by a boolean mask or index array."""
        n = len(self)
        changes = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == n:
                changes[f.name] = v[mask_or_index]
            elif isinstance(v, tuple) and len(v) == n:
                idx = np.arange(n)[mask_or_index]
                changes[f.name] = tuple(v[i] for i in idx)
        return dataclasses.replace(self, **changes)

    def between(self, t0: float, t1: float):
        """Rows with ``t0 <= t <= t1``."""
        return self.select((self.t >= t0) & (self.t <= t1))


# ----------------------------------------------------------------------------------------------
# Streams
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ImuSeries(_Series):
    """IMU samples in the body frame (FLU).

    Attributes:
        t: (N,) time [s].
        body_omega: (N, 3) angular rate of body w.r.t. world, in body [rad/s].
        body_accel: (N, 3) specific force (accelerometer reading: acceleration minus gravity), in
            body [m/s^2]; about (0, 0, +9.81) at rest with z up.
    """

    t: np.ndarray
    body_omega: np.ndarray
    body_accel: np.ndarray

    def check(self, name: str = "imu") -> ImuSeries:
        _check_time(name, self.t)
        _check_column(name, "body_omega", self.body_omega, len(self), 3)
        _check_column(name, "body_accel", self.body_accel, len(self), 3)
        return self


@dataclass(frozen=True, eq=False)
class AttitudeSeries(_Series):
    """Attitude from an AHRS or onboard filter.

    Attributes:
        t: (N,) time [s].
        world_q_body_wxyz: (N, 4) unit quaternion ``[w, x, y, z]`` of ``world_R_body``.
    """

    t: np.ndarray
    world_q_body_wxyz: np.ndarray

    def check(self, name: str = "attitude") -> AttitudeSeries:
        _check_time(name, self.t)
        _check_quat(name, "world_q_body_wxyz", self.world_q_body_wxyz, len(self))
        return self


@dataclass(frozen=True, eq=False)
class RangeSeries(_Series):
    """Rangefinder readings along the sensor's axis (see ``Calibration.body_T_range``).

    Attributes:
        t: (N,) time [s].
        range: (N,) measured distance along the beam [m].
        quality: optional (N,) signal quality in [0, 1] (-1 when unknown).
    """

    t: np.ndarray
    range: np.ndarray
    quality: np.ndarray | None = None

    def check(self, name: str = "range") -> RangeSeries:
        _check_time(name, self.t)
        _check_column(name, "range", self.range, len(self), None)
        _check_column(name, "quality", self.quality, len(self), None, optional=True)
        return self


@dataclass(frozen=True, eq=False)
class YawSeries(_Series):
    """Heading measurements (magnetometer-like, or from visual odometry).

    Attributes:
        t: (N,) time [s].
        yaw: (N,) yaw of ``world_R_body`` [rad], ZYX convention, in (-pi, pi].
    """

    t: np.ndarray
    yaw: np.ndarray

    def check(self, name: str = "yaw") -> YawSeries:
        _check_time(name, self.t)
        _check_column(name, "yaw", self.yaw, len(self), None)
        return self


@dataclass(frozen=True, eq=False)
class SlamSeries(_Series):
    """Camera poses from a monocular SLAM system, in the SLAM frame at an unknown scale.

    Attributes:
        t: (N,) image time [s] (the time the image was taken, not when the pose arrived).
        slam_t_cam: (N, 3) camera position in the SLAM frame [SLAM units].
        slam_q_cam_wxyz: (N, 4) camera orientation ``slam_R_cam`` as ``[w, x, y, z]``.
        session: (N,) int map/session id >= 0; a new id at every map reset (new frame and
            scale). Tracking losses are gaps (no sample), never a special id.
        latency: optional (N,) seconds >= 0 between image time and the pose's arrival (online
            mode feeds the pose at ``t + latency``).
    """

    t: np.ndarray
    slam_t_cam: np.ndarray
    slam_q_cam_wxyz: np.ndarray
    session: np.ndarray
    latency: np.ndarray | None = None

    def check(self, name: str = "slam") -> SlamSeries:
        _check_time(name, self.t)
        _check_column(name, "slam_t_cam", self.slam_t_cam, len(self), 3)
        _check_quat(name, "slam_q_cam_wxyz", self.slam_q_cam_wxyz, len(self))
        _check_column(name, "session", self.session, len(self), None)
        if self.session.dtype.kind not in "iu":
            raise FlightDataError(f"{name}.session: expected integer ids, got {self.session.dtype}")
        bad = np.flatnonzero(self.session < 0)
        if bad.size:
            raise FlightDataError(
                f"{name}.session: negative id {self.session[bad[0]]} at sample {bad[0]}; ids are "
                ">= 0 (a tracking loss is a gap, not an id)"
            )
        _check_column(name, "latency", self.latency, len(self), None, optional=True)
        if self.latency is not None and np.any(self.latency < 0):
            i = int(np.flatnonzero(self.latency < 0)[0])
            raise FlightDataError(
                f"{name}.latency: negative latency {self.latency[i]} s at sample {i}; expected the "
                "delay (>= 0) between image time and arrival"
            )
        return self


@dataclass(frozen=True, eq=False)
class FlowSeries(_Series):
    """Integrated optical flow of a downward flow sensor (PMW3901, PX4Flow, ARK Flow).

    Convention (fgnav's own; readers convert to it): the sensor frame is given by
    ``Calibration.body_T_flow`` (default ``DOWNWARD_FLOW``: x forward, y right, z down along the
    optical axis, i.e. FRD for a level vehicle). ``flow`` is the image motion of the ground point
    on the optical axis over the interval, in the sensor's x and y image directions, in units of
    ``Calibration.flow_pixels_per_rad`` per radian (1.0 when the reader delivers radians). With
    the sensor's velocity ``v`` and angular rate ``w`` in the sensor frame and ``d`` the distance
    along the optical axis to the ground, the ideal reading is::

        flow = pixels_per_rad * dt * [-v_x / d - w_y,  -v_y / d + w_x]

    Attributes:
        t: (N,) end time of each integration interval [s].
        dt: (N,) integration interval [s] (> 0).
        flow: (N, 2) integrated flow [px, or rad when ``flow_pixels_per_rad`` is 1].
        quality: optional (N,) quality in [0, 1] (-1 when unknown).
    """

    t: np.ndarray
    dt: np.ndarray
    flow: np.ndarray
    quality: np.ndarray | None = None

    def check(self, name: str = "flow") -> FlowSeries:
        _check_time(name, self.t)
        _check_column(name, "dt", self.dt, len(self), None)
        _check_column(name, "flow", self.flow, len(self), 2)
        _check_column(name, "quality", self.quality, len(self), None, optional=True)
        bad = np.flatnonzero(self.dt <= 0)
        if bad.size:
            raise FlightDataError(
                f"{name}.dt: interval {self.dt[bad[0]]} s at sample {bad[0]}; intervals are > 0"
            )
        return self


#: Numbers of distortion coefficients OpenCV accepts (0: none).
DISTORTION_COUNTS = (0, 4, 5, 8, 12, 14)


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole camera with optional radial-tangential distortion (OpenCV order k1 k2 p1 p2 [k3]).

    Attributes:
        fx, fy, cx, cy: intrinsics [px].
        width, height: image size [px].
        distortion: distortion coefficients, empty for none.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = ()

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def check(self, name: str = "camera") -> CameraIntrinsics:
        vals = [self.fx, self.fy, self.cx, self.cy, *self.distortion]
        if not all(np.isfinite(vals)):
            raise FlightDataError(f"{name}: non-finite intrinsics {vals}")
        if self.fx <= 0 or self.fy <= 0 or self.width <= 0 or self.height <= 0:
            raise FlightDataError(f"{name}: fx, fy, width, height must be positive")
        if len(self.distortion) not in DISTORTION_COUNTS:
            # OpenCV's undistortion takes these counts only (3 or 7 were a cv2.error).
            raise FlightDataError(
                f"{name}: {len(self.distortion)} distortion coefficients; expected "
                + ", ".join(str(n) for n in DISTORTION_COUNTS)
                + " (OpenCV order k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]])"
            )
        return self


@dataclass(frozen=True, eq=False)
class ImageSeries(_Series):
    """Images of one camera (grey or colour), as files or in memory.

    Attributes:
        t: (N,) exposure time [s].
        paths: N image file paths (absolute, or relative to the flight folder), or None.
        frames: (N, H, W) or (N, H, W, 3) uint8 array in memory, or None.
        camera: intrinsics of the camera.
    Exactly one of ``paths`` and ``frames`` is set.
    """

    t: np.ndarray
    paths: tuple[Path, ...] | None = None
    frames: np.ndarray | None = None
    camera: CameraIntrinsics | None = None

    def check(self, name: str = "images") -> ImageSeries:
        _check_time(name, self.t)
        if (self.paths is None) == (self.frames is None):
            raise FlightDataError(f"{name}: exactly one of paths and frames must be set")
        if self.paths is not None and len(self.paths) != len(self):
            raise FlightDataError(f"{name}.paths: {len(self.paths)} paths for {len(self)} times")
        if self.frames is not None and (self.frames.shape[0] != len(self)):
            raise FlightDataError(
                f"{name}.frames: {self.frames.shape[0]} frames for {len(self)} times"
            )
        if self.camera is None:
            raise FlightDataError(f"{name}.camera: intrinsics missing")
        self.camera.check(f"{name}.camera")
        return self

    def load(self, i: int, grey: bool = True) -> np.ndarray:
        """Image i as a uint8 array (grey by default)."""
        if self.frames is not None:
            img = self.frames[i]
        else:
            import cv2

            flag = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_UNCHANGED
            img = cv2.imread(str(self.paths[i]), flag)
            if img is None:
                raise FlightDataError(
                    f"cannot read image {self.paths[i]} (missing or not an image)"
                )
            return img
        if grey and img.ndim == 3:
            import cv2

            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        return img


@dataclass(frozen=True, eq=False)
class Trajectory(_Series):
    """A body trajectory: ground truth, an onboard estimate, or an fgnav estimate.

    Attributes:
        t: (N,) time [s].
        world_t_body: (N, 3) body position in world [m].
        world_q_body_wxyz: (N, 4) body orientation ``world_R_body`` as ``[w, x, y, z]``.
        world_v_body: optional (N, 3) body velocity in world [m/s].
        gyro_bias: optional (N, 3) gyroscope bias [rad/s].
        accel_bias: optional (N, 3) accelerometer bias [m/s^2].
    """

    t: np.ndarray
    world_t_body: np.ndarray
    world_q_body_wxyz: np.ndarray
    world_v_body: np.ndarray | None = None
    gyro_bias: np.ndarray | None = None
    accel_bias: np.ndarray | None = None

    def check(self, name: str = "trajectory") -> Trajectory:
        _check_time(name, self.t)
        n = len(self)
        _check_column(name, "world_t_body", self.world_t_body, n, 3)
        _check_quat(name, "world_q_body_wxyz", self.world_q_body_wxyz, n)
        for f in ("world_v_body", "gyro_bias", "accel_bias"):
            _check_column(name, f, getattr(self, f), n, 3, optional=True)
        return self

    def world_R_body(self) -> np.ndarray:
        """(N, 3, 3) rotation matrices."""
        from .geometry import quat_wxyz_to_matrix

        return quat_wxyz_to_matrix(self.world_q_body_wxyz)


# ----------------------------------------------------------------------------------------------
# Calibration and flight
# ----------------------------------------------------------------------------------------------


DOWNWARD_RANGE = np.diag([1.0, -1.0, -1.0, 1.0])
"""Default ``body_T_range``: no lever arm, sensor +z (the beam) along body -z."""

DOWNWARD_FLOW = np.diag([1.0, -1.0, -1.0, 1.0])
"""Default ``body_T_flow``: no lever arm, sensor x forward, y right, z (optical axis) down."""


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise densities (Kalibr/EuRoC convention).

    Attributes:
        gyro_noise_density: [rad/s/sqrt(Hz)].
        accel_noise_density: [m/s^2/sqrt(Hz)].
        gyro_random_walk: [rad/s^2/sqrt(Hz)].
        accel_random_walk: [m/s^3/sqrt(Hz)].
        gyro_bias_sigma: 1-sigma of the gyro bias left in the stream at the start [rad/s] (the
            smoothers' prior on the first gyro bias unless ``GraphOptions.prior_gyro_bias_sigma``
            is set): small for an autopilot that removes the bias measured at rest before it
            logs the rates (the Crazyflie firmware).
        rest_bias_removed: the autopilot has already subtracted the gyro bias it measured at
            rest from the logged rates (the Crazyflie firmware): the push engine's start then
            keeps the first gyro bias at the prior's zero mean instead of the mean rate of a
            still stretch before the start (on a vehicle standing on its legs with the rotors
            spinning that mean is its rocking, not the in-flight bias).
    """

    gyro_noise_density: float = 1.7e-4
    accel_noise_density: float = 2.0e-3
    gyro_random_walk: float = 1.94e-5
    accel_random_walk: float = 3.0e-3
    gyro_bias_sigma: float = 0.01
    rest_bias_removed: bool = False


#: Largest IMU noise density or random walk accepted (SI units): a consumer MEMS gyro's density
#: is ~1e-4 rad/s/sqrt(Hz), an accelerometer's ~1e-3 m/s^2/sqrt(Hz); 1e300 left the IMU factors
#: without information.
IMU_NOISE_MAX = 1e3


def imu_noise_problem(field_name: str, value: float) -> str | None:
    """What is wrong with an :class:`ImuNoise` number (None: nothing): densities must be finite,
    >= 0 and at most :data:`IMU_NOISE_MAX`; random walks also > 0 (a zero bias walk fixes the
    biases: the smoothers then stopped on an "indeterminate system")."""
    if not (math.isfinite(value) and 0 <= value <= IMU_NOISE_MAX):
        return f"expected a number in [0, {IMU_NOISE_MAX:g}]"
    if field_name.endswith("random_walk") and not value > 0:
        return f"expected a number > 0 (and <= {IMU_NOISE_MAX:g})"
    return None


@dataclass(frozen=True, eq=False)
class Calibration:
    """Fixed extrinsics and intrinsics.

    Attributes:
        body_T_cam: 4x4 pose of the camera in the body frame (camera: x right, y down, z forward
            along the optical axis).
        body_T_range: 4x4 pose of the rangefinder; its beam is the sensor's +z axis. The default
            (``DOWNWARD_RANGE``: a rotation of pi about body x) points the beam along body -z.
        camera: camera intrinsics, or None.
        imu_noise: IMU noise densities.
        range_min, range_max: valid rangefinder interval [m].
        body_T_flow: 4x4 pose of the optical-flow sensor (see ``FlowSeries``).
        flow_pixels_per_rad: flow units per radian of image motion (1.0 for radians).
        time_offsets: per-stream clock offsets [s] already applied by the reader (metadata).
        flow_rate_gain: ``(a, b)``: the flow sensor reads an image rate ``r`` [rad/s] (a
            2-vector, translation and rotation) as ``(a + b |r|) r`` times
            ``flow_pixels_per_rad``; ``(1, 0)``: linear. The smoothers undo it on each keyframe
            window's mean rate (``fgnav.solvers.flow.linearise_flow``).
    """

    body_T_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    body_T_range: np.ndarray = field(default_factory=lambda: DOWNWARD_RANGE.copy())
    camera: CameraIntrinsics | None = None
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    range_min: float = 0.0
    range_max: float = float("inf")
    body_T_flow: np.ndarray = field(default_factory=lambda: DOWNWARD_FLOW.copy())
    flow_pixels_per_rad: float = 1.0
    time_offsets: dict[str, float] = field(default_factory=dict)
    flow_rate_gain: tuple[float, float] = (1.0, 0.0)

    def check(self, name: str = "calib") -> Calibration:
        for f in ("body_T_cam", "body_T_range", "body_T_flow"):
            T = np.asarray(getattr(self, f), dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise FlightDataError(f"{name}.{f}: expected a finite 4x4 matrix, got {T.shape}")
            R = T[:3, :3]
            if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
                raise FlightDataError(f"{name}.{f}: rotation part is not a proper rotation")
            if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-12:
                raise FlightDataError(f"{name}.{f}: last row must be [0, 0, 0, 1]")
        a, b = (float(x) for x in self.flow_rate_gain)
        if not (np.isfinite(a) and np.isfinite(b) and a > 0):
            raise FlightDataError(
                f"{name}.flow_rate_gain: expected (a > 0, b) finite, got {self.flow_rate_gain}"
            )
        if not (np.isfinite(self.flow_pixels_per_rad) and 0 < self.flow_pixels_per_rad <= 1e6):
            # 1e6: far above any sensor's (PMW3901 ~48 flow units/rad, a camera ~500 px/rad).
            raise FlightDataError(
                f"{name}.flow_pixels_per_rad: expected a positive number up to 1e6, got "
                f"{self.flow_pixels_per_rad}"
            )
        lo, hi = float(self.range_min), float(self.range_max)
        if not (math.isfinite(lo) and lo >= 0 and hi > lo):
            raise FlightDataError(
                f"{name}.range_min, range_max: expected 0 <= range_min < range_max (range_max "
                f"may be inf), got {self.range_min}, {self.range_max}"
            )
        for f in dataclasses.fields(self.imu_noise):
            v = getattr(self.imu_noise, f.name)
            if isinstance(v, bool):
                continue
            problem = imu_noise_problem(f.name, v)
            if problem is not None:
                raise FlightDataError(f"{name}.imu_noise.{f.name}: {problem}, got {v}")
        for stream, v in self.time_offsets.items():
            if not math.isfinite(v):
                raise FlightDataError(f"{name}.time_offsets.{stream}: expected a finite offset")
        if self.camera is not None:
            self.camera.check(f"{name}.camera")
        return self


STREAMS = ("imu", "attitude", "range", "yaw", "slam", "images", "flow", "ground_truth")


@dataclass(frozen=True, eq=False)
class Flight:
    """One logged or simulated flight: whichever streams the log has, plus metadata.

    Attributes:
        name: short name.
        source: where it came from (file path, "simulator", ...).
        imu, attitude, range, yaw, slam, images, flow: sensor streams, each optional.
        ground_truth: reference body trajectory, optional (never used by estimators).
        references: other trajectories recorded in the log, e.g. ``{"px4_ekf2": Trajectory}``;
            they become baseline rows, never estimator inputs.
        calib: calibration.
        meta: free metadata: frames, units, truth values of the simulator (drag k, SLAM
            similarity per session, ...), reader notes (skipped lines), etc.
    """

    name: str
    source: str = ""
    imu: ImuSeries | None = None
    attitude: AttitudeSeries | None = None
    range: RangeSeries | None = None
    yaw: YawSeries | None = None
    slam: SlamSeries | None = None
    images: ImageSeries | None = None
    flow: FlowSeries | None = None
    ground_truth: Trajectory | None = None
    references: dict[str, Trajectory] = field(default_factory=dict)
    calib: Calibration = field(default_factory=Calibration)
    meta: dict[str, Any] = field(default_factory=dict)

    def streams(self) -> dict[str, _Series]:
        """The streams present, by name (``STREAMS`` order), references as ``ref:<name>``."""
        out = {s: getattr(self, s) for s in STREAMS if getattr(self, s) is not None}
        out.update({f"ref:{k}": v for k, v in self.references.items()})
        return out

    def check(self) -> Flight:
        for name, s in self.streams().items():
            s.check(f"{self.name}.{name}")
        self.calib.check(f"{self.name}.calib")
        return self

    def require_streams(self, streams: tuple[str, ...], who: str) -> None:
        """A one-line error naming every one of ``streams`` the flight lacks, and ``who`` (the
        method that needs them)."""
        missing = [s for s in streams if getattr(self, s) is None]
        if missing:
            raise FlightDataError(
                f"{self.name}: {who} needs the streams {', '.join(streams)}; "
                f"missing: {', '.join(missing)}"
            )

    def require_overlap(self, a: str, b: str) -> tuple[float, float]:
        """Time overlap ``(t0, t1)`` of streams ``a`` and ``b``; a one-line error naming both
        streams and their spans when they do not overlap (or one of them is empty)."""
        sa, sb = getattr(self, a), getattr(self, b)
        for name, st in ((a, sa), (b, sb)):
            if st is None or len(st) == 0:
                raise FlightDataError(f"{self.name}: the {name} stream is empty")
        t0, t1 = max(sa.t[0], sb.t[0]), min(sa.t[-1], sb.t[-1])
        if not t1 > t0:
            raise FlightDataError(
                f"{self.name}: the {a} and {b} streams do not overlap in time ({a} "
                f"{sa.t[0]:.3f}-{sa.t[-1]:.3f} s, {b} {sb.t[0]:.3f}-{sb.t[-1]:.3f} s); "
                "check the files and their clocks"
            )
        return float(t0), float(t1)

    def time_window(self) -> tuple[float, float]:
        """Overlap ``(t0, t1)`` of all sensor streams (ground truth and references excluded)."""
        sensors = [getattr(self, s) for s in STREAMS[:-1] if getattr(self, s) is not None]
        if not sensors:
            raise FlightDataError(f"{self.name}: the flight has no sensor stream")
        return max(s.t[0] for s in sensors), min(s.t[-1] for s in sensors)
