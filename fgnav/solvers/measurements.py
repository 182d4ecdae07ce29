"""Measurement preparation for the graph builder: keyframe times, association of measurements to
keyframes, an initial attitude track and the closed-form initial SLAM alignment.

No GTSAM here: numpy in, numpy out. Frames follow ../shared/DESIGN.md section 2 (world z up,
body FLU, SI units, time in seconds).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import (
    ordered_product,
    project_to_so3,
    quat_wxyz_to_matrix,
    rotation_mean,
    rpy_to_matrix,
    slerp_rotations,
    so3_exp,
    so3_log,
    yaw_of,
)
from fgnav.datasets.slam_gyro import hat_kernel_integrals, pose_pairs
from fgnav.datasets.types import AttitudeSeries, ImuSeries, SlamSeries

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# Keyframes and association
# ----------------------------------------------------------------------------------------------


#: Anchors closer than this fraction of a keyframe period to the previous keyframe are skipped by
#: :func:`keyframe_times`; the margin absorbs the jitter of logged time stamps (a 20 Hz stream at a
#: 20 Hz keyframe rate).
MIN_ANCHOR_GAP_PERIODS = 0.75


def keyframe_times(
    t_start: float,
    t_end: float,
    rate_hz: float,
    anchor_t: np.ndarray | None = None,
) -> np.ndarray:
    """Keyframe times: the anchor measurement times (camera frames) decimated to ``rate_hz``, with
    fixed-rate keyframes filling every gap longer than 1.5 periods.

    Args:
        t_start, t_end: time window [s]; keyframes lie in ``[t_start, t_end]``.
        rate_hz: nominal keyframe rate [Hz].
        anchor_t: optional sorted measurement times [s] that should carry keyframes (camera/SLAM
            frames), so that their measurements need no time shift.

    Returns:
        (K,) strictly increasing times [s].
    """
    if rate_hz <= 0:
        raise FlightDataError(f"keyframe rate must be positive, got {rate_hz} Hz")
    if t_end <= t_start:
        raise FlightDataError(f"empty keyframe window [{t_start}, {t_end}] s")
    period = 1.0 / rate_hz
    min_gap = MIN_ANCHOR_GAP_PERIODS * period
    anchors = np.array([]) if anchor_t is None else np.asarray(anchor_t, dtype=float)
    anchors = anchors[(anchors >= t_start) & (anchors <= t_end)]
    out: list[float] = [t_start]
    for ta in [*anchors, t_end]:
        # Fill the gap before this anchor with fixed-rate keyframes.
        while ta - out[-1] > 1.5 * period:
            out.append(out[-1] + period)
        if ta - out[-1] >= min_gap:
            out.append(float(ta))
    if out[-1] < t_end - 1e-9 and t_end - out[-1] >= min_gap:
        out.append(t_end)
    return np.asarray(out)


@dataclass
class Association:
    """Which measurement goes to which keyframe.

    Attributes:
        meas_index: (M,) indices into the measurement stream of the kept measurements.
        keyframe: (M,) keyframe index of each kept measurement.
        dt: (M,) measurement time minus keyframe time [s].
        skipped: reason -> count of measurements not used.
    """

    meas_index: np.ndarray
    keyframe: np.ndarray
    dt: np.ndarray
    skipped: dict[str, int] = field(default_factory=dict)


def associate(
    t_meas: np.ndarray, t_kf: np.ndarray, tolerance: float, one_per_keyframe: bool = True
) -> Association:
    """Associate measurements to their nearest keyframe within ``tolerance`` seconds.

    Measurements farther than ``tolerance`` from every keyframe are counted as
    ``"before-first-keyframe"`` / ``"after-last-keyframe"`` (outside the keyframe window, e.g. a
    stream that outlasts the IMU) or ``"no-keyframe-within-tolerance"``; with
    ``one_per_keyframe`` only the nearest measurement of each keyframe is kept and the others are
    counted as ``"decimated"``.
    """
    t_meas = np.asarray(t_meas, dtype=float)
    if t_meas.size == 0:
        e = np.array([], dtype=int)
        return Association(e, e, np.array([]), {})
    j = np.clip(np.searchsorted(t_kf, t_meas), 1, len(t_kf) - 1) if len(t_kf) > 1 else None
    if j is None:
        nearest = np.zeros(t_meas.shape, dtype=int)
    else:
        left = t_kf[j - 1]
        right = t_kf[j]
        nearest = np.where(np.abs(t_meas - left) <= np.abs(t_meas - right), j - 1, j)
    dt = t_meas - t_kf[nearest]
    ok = np.abs(dt) <= tolerance
    skipped = {}
    before = ~ok & (t_meas < t_kf[0])
    after = ~ok & (t_meas > t_kf[-1])
    for reason, n in (
        ("before-first-keyframe", int(before.sum())),
        ("after-last-keyframe", int(after.sum())),
        ("no-keyframe-within-tolerance", int((~ok & ~before & ~after).sum())),
    ):
        if n:
            skipped[reason] = n
    idx = np.flatnonzero(ok)
    kf = nearest[idx]
    if one_per_keyframe and idx.size:
        order = np.lexsort((np.abs(dt[idx]), kf))
        idx, kf = idx[order], kf[order]
        first = np.ones(idx.size, dtype=bool)
        first[1:] = kf[1:] != kf[:-1]
        n_dec = int((~first).sum())
        if n_dec:
            skipped["decimated"] = n_dec
        idx, kf = idx[first], kf[first]
        order = np.argsort(kf)
        idx, kf = idx[order], kf[order]
    return Association(idx, kf, t_meas[idx] - t_kf[kf], skipped)


def mean_in_windows(
    t: np.ndarray, x: np.ndarray, centers: np.ndarray, half_width: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """Mean of samples ``x`` with ``|t - center| <= half_width`` for each center.

    Returns:
        (means (K, D), counts (K,)); rows with no sample are NaN.
    """
    hw = np.broadcast_to(np.asarray(half_width, dtype=float), centers.shape)
    lo = np.searchsorted(t, centers - hw, side="left")
    hi = np.searchsorted(t, centers + hw, side="right")
    csum = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    counts = hi - lo
    with np.errstate(invalid="ignore", divide="ignore"):
        means = (csum[hi] - csum[lo]) / counts[:, None]
    return means, counts


# ----------------------------------------------------------------------------------------------
# Attitude
# ----------------------------------------------------------------------------------------------


def level_rotation_from_accel(body_accel: np.ndarray, yaw: float = 0.0) -> np.ndarray:
    """``world_R_body`` whose roll/pitch put the mean specific force ``body_accel`` (3,) along world
    +z (quasi-static vehicle), with the given yaw [rad]."""
    f = np.asarray(body_accel, dtype=float)
    roll = float(np.arctan2(f[1], f[2]))
    pitch = float(np.arctan2(-f[0], np.hypot(f[1], f[2])))
    return rpy_to_matrix(roll, pitch, yaw)


def integrate_gyro(
    imu: ImuSeries, world_R_body0: np.ndarray, t_query: np.ndarray, gyro_bias: np.ndarray
) -> np.ndarray:
    """Dead-reckon ``world_R_body`` from the gyro, starting at ``imu.t[0]``; sampled at t_query."""
    R = np.empty((len(imu), 3, 3))
    R[0] = world_R_body0
    dts = np.diff(imu.t)
    for i, dt in enumerate(dts):
        R[i + 1] = R[i] @ so3_exp((imu.body_omega[i] - gyro_bias) * dt)
    return slerp_rotations(imu.t, R, t_query)


def attitude_track(
    imu: ImuSeries,
    attitude: AttitudeSeries | None,
    t_query: np.ndarray,
    initial_yaw: float = 0.0,
    level_window_s: float = 0.5,
) -> np.ndarray:
    """Initial ``world_R_body`` (K, 3, 3) at ``t_query``: the attitude stream when present, else the
    gyro integrated from an accelerometer-levelled start (mean over ``level_window_s``) with
    ``initial_yaw``."""
    if attitude is not None:
        return slerp_rotations(attitude.t, quat_wxyz_to_matrix(attitude.world_q_body_wxyz), t_query)
    m = imu.t <= imu.t[0] + level_window_s
    R0 = level_rotation_from_accel(imu.body_accel[m].mean(axis=0), initial_yaw)
    return integrate_gyro(imu, R0, t_query, np.zeros(3))


def attitude_from_slam(
    imu: ImuSeries,
    slam: SlamSeries,
    body_T_cam: np.ndarray,
    t_query: np.ndarray,
    initial_yaw: float = 0.0,
) -> np.ndarray:
    """``world_R_body`` (K, 3, 3) at ``t_query`` from the SLAM camera orientations of the first
    session, gravity-aligned with the accelerometer.

    The mean over the session of ``slam_R_body f`` (specific force rotated into the SLAM frame)
    is ``slam_R_world (0, 0, g)`` plus the mean kinematic acceleration, which is near zero over a
    flight that starts and ends slowly: its direction is the SLAM frame's "up". The yaw is chosen so
    that the first query's yaw is ``initial_yaw``. Used when the flight has no attitude stream
    (a gyro integrated over minutes drifts with its bias: EuRoC's ADIS16448 about 0.08 rad/s).
    """
    m = slam.session == slam.session[0]
    t_s = slam.t[m]
    body_R_cam = body_T_cam[:3, :3]
    slam_R_body = quat_wxyz_to_matrix(slam.slam_q_cam_wxyz[m]) @ body_R_cam.T
    f = np.column_stack([np.interp(t_s, imu.t, imu.body_accel[:, a]) for a in range(3)])
    up = np.einsum("nij,nj->i", slam_R_body, f)
    up /= np.linalg.norm(up)
    # Rotation taking the SLAM "up" to world +z (Rodrigues between two unit vectors).
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, z)
    sin_a, cos_a = np.linalg.norm(axis), float(up @ z)
    world_R_slam = np.eye(3) if sin_a < 1e-12 else so3_exp(axis / sin_a * np.arctan2(sin_a, cos_a))
    R = slerp_rotations(t_s, world_R_slam @ slam_R_body, t_query)
    dyaw = initial_yaw - float(yaw_of(R[0]))
    return rpy_to_matrix(0.0, 0.0, dyaw) @ R


def gyro_bias_from_slam(
    imu: ImuSeries, slam: SlamSeries, body_T_cam: np.ndarray, window_s: float = 1.0
) -> np.ndarray:
    """Gyroscope bias [rad/s] (3,) from SLAM orientation increments (median over windows).

    Over a window, the gyro integrated without bias gives ``dR_gyro``; SLAM gives the true body
    increment ``dR = body_R_cam dR_cam body_R_cam^T``; to first order
    ``dR_gyro^T dR = Exp(-b dt)``.
    """
    body_R_cam = body_T_cam[:3, :3]
    R_cam = quat_wxyz_to_matrix(slam.slam_q_cam_wxyz)
    # Rotation of each IMU sample over its interval (the last sample has none).
    steps = so3_exp(imu.body_omega[:-1] * np.diff(imu.t)[:, None])
    est = []
    i = 0
    n = len(slam)
    while i < n - 1:
        j = int(np.searchsorted(slam.t, slam.t[i] + window_s))
        if j >= n:
            break
        if slam.session[j] == slam.session[i] and slam.t[i] >= imu.t[0] and slam.t[j] <= imu.t[-1]:
            dR = body_R_cam @ R_cam[i].T @ R_cam[j] @ body_R_cam.T
            k0 = int(np.searchsorted(imu.t, slam.t[i], side="right")) - 1
            k1 = int(np.searchsorted(imu.t, slam.t[j], side="right")) - 1
            G = ordered_product(steps[k0:k1])
            est.append(-so3_log(G.T @ dR) / (imu.t[k1] - imu.t[k0]))
        i = j
    if not est:
        return np.zeros(3)
    return np.median(np.asarray(est), axis=0)


def omega_from_attitude(attitude: AttitudeSeries, t_query: np.ndarray) -> np.ndarray:
    """Body angular rate (N, 3) [rad/s] differentiated from the attitude stream (used when the gyro
    is switched off: seed 000's sensor set is accelerometer + attitude)."""
    R = quat_wxyz_to_matrix(attitude.world_q_body_wxyz)
    w = np.array([so3_log(R[i].T @ R[i + 1]) for i in range(len(R) - 1)])
    w /= np.diff(attitude.t)[:, None]
    tm = 0.5 * (attitude.t[1:] + attitude.t[:-1])
    return np.column_stack([np.interp(t_query, tm, w[:, a]) for a in range(3)])


# ----------------------------------------------------------------------------------------------
# Initial SLAM alignment (closed form)
# ----------------------------------------------------------------------------------------------


@dataclass
class SlamAlignmentInit:
    """Initial ``slam_T_world`` of one session: ``slam_t = scale * slam_R_world @ world_t + t``.

    Attributes:
        scale: SLAM units per metre.
        slam_R_world: (3, 3) rotation.
        slam_t_world: (3,) translation [SLAM units].
        n_pairs: number of acceleration pairs used for the scale.
        excitation: RMS of the metric second differences used [m] (small = scale poorly
            observable from the IMU).
        scale_rel_se: relative standard error of the least-squares scale.
        rotation_spread: with ``rotation="motion"``, the second over the first singular value of
            the pairs' cross-covariance, acceleration and turn pairs together (near 0: one
            direction only, e.g. a climb without turns, the rotation about it undetermined); NaN
            for a rotation from the orientations.
    """

    scale: float
    slam_R_world: np.ndarray
    slam_t_world: np.ndarray
    n_pairs: int
    excitation: float
    scale_rel_se: float = float("nan")
    rotation_spread: float = float("nan")


def world_specific_accel(imu: ImuSeries, world_R_body: np.ndarray, gravity: float) -> np.ndarray:
    """Kinematic acceleration in world (N, 3) [m/s^2]: ``world_R_body f + (0, 0, -g)``."""
    a = np.einsum("nij,nj->ni", world_R_body, imu.body_accel)
    a[:, 2] -= gravity
    return a


@dataclass
class SecondDifferences:
    """Matched second differences of SLAM positions and of the IMU's metric trajectory.

    For three SLAM samples at ``t_i < t_j < t_k`` (``h1 = t_j - t_i``, ``h2 = t_k - t_j``, width
    ``w = (h1 + h2) / 2``) the divided second difference of the positions,
    ``w ((p_k - p_j) / h2 - (p_j - p_i) / h1)``, equals ``w`` times the integral of the
    acceleration against the hat kernel rising from 0 at ``t_i`` to 1 at ``t_j`` and falling to 0
    at ``t_k`` (exact for any twice-differentiable trajectory). With ``h1 = h2 = h`` it is
    ``p(t+h) - 2 p(t) + p(t-h)``. A constant acceleration offset ``b`` adds ``w^2 b``.

    Attributes:
        slam_d2: (P, 3) SLAM second differences [SLAM units].
        world_d2: (P, 3) metric ones from the world acceleration [m].
        centers: (P,) middle sample times ``t_j`` [s].
        width: (P,) ``w`` [s].
    """

    slam_d2: np.ndarray
    world_d2: np.ndarray
    centers: np.ndarray
    width: np.ndarray


def _nearest_index(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Index of the sample of sorted ``t`` nearest each query time."""
    r = np.clip(np.searchsorted(t, q), 1, len(t) - 1)
    return np.where(np.abs(t[r - 1] - q) <= np.abs(t[r] - q), r - 1, r)


def slam_second_differences(
    t_slam: np.ndarray,
    slam_t: np.ndarray,
    imu_t: np.ndarray,
    world_a: np.ndarray,
    h: float,
    step: float,
) -> SecondDifferences:
    """Second differences on the SLAM samples themselves (no interpolation of positions).

    For middle samples at least ``step`` apart, the outer samples are those nearest ``t_j - h``
    and ``t_j + h``; triples with an outer interval outside ``[h / 2, 2 h]`` (a gap, or samples
    too dense to reach) are skipped. Low-rate keyframes (3 Hz) thus give unbiased differences:
    positions interpolated linearly between keyframes would low-pass the motion and bias a
    scale fitted on them low. The metric side integrates the IMU's world acceleration against the
    exact hat kernel (see :class:`SecondDifferences`) on the IMU's own grid.

    Args:
        t_slam, slam_t: (N,) SLAM times [s] and (N, 3) positions [SLAM units] (one session).
        imu_t, world_a: (M,) IMU times [s] and (M, 3) world kinematic acceleration [m/s^2].
        h: nominal half-width [s]; step: least spacing of the middle samples [s].
    """
    t_slam = np.asarray(t_slam, dtype=float)
    empty = SecondDifferences(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    if len(t_slam) < 3:
        return empty
    j = np.arange(1, len(t_slam) - 1)
    i = _nearest_index(t_slam, t_slam[j] - h)
    k = _nearest_index(t_slam, t_slam[j] + h)
    i, k = np.minimum(i, j - 1), np.maximum(k, j + 1)
    h1, h2 = t_slam[j] - t_slam[i], t_slam[k] - t_slam[j]
    ok = (h1 >= 0.5 * h) & (h1 <= 2.0 * h) & (h2 >= 0.5 * h) & (h2 <= 2.0 * h)
    ok &= (t_slam[i] >= imu_t[0]) & (t_slam[k] <= imu_t[-1])
    # Middle samples at least `step` apart.
    keep = np.zeros(len(j), bool)
    last = -np.inf
    for n in np.flatnonzero(ok):
        if t_slam[j[n]] - last >= step - 1e-9:
            keep[n] = True
            last = t_slam[j[n]]
    if not keep.any():
        return empty
    i, j, k, h1, h2 = i[keep], j[keep], k[keep], h1[keep], h2[keep]
    w = 0.5 * (h1 + h2)
    p = np.asarray(slam_t, dtype=float)
    slam_d2 = w[:, None] * ((p[k] - p[j]) / h2[:, None] - (p[j] - p[i]) / h1[:, None])
    tj = t_slam[j]
    world_d2 = w[:, None] * hat_kernel_integrals(imu_t, world_a, t_slam[i], tj, t_slam[k])
    return SecondDifferences(slam_d2, world_d2, tj, w)


def fit_axis_scale(
    t_slam: np.ndarray,
    slam_t: np.ndarray,
    imu_t: np.ndarray,
    world_a: np.ndarray,
    h: float = 0.5,
    step: float = 0.1,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Seed 000's per-axis SLAM scale ``[kx, ky, kz]`` [SLAM units per metre] by least squares of
    the SLAM second differences against the metric ones from the accelerometer (SLAM axes = world
    axes; the means removed, which absorbs a constant accelerometer offset).

    Returns:
        ``(k (3,), rel_se (3,), n_pairs)``: ``rel_se`` the relative standard error of each axis
        (inflated by ``sqrt(2 h / step)`` for the overlap of neighbouring second differences; inf
        for an axis the fit does not determine, rel. s.e. above 1, which starts at the mean of
        the others).

    Raises:
        FlightDataError: fewer than 3 pairs, or no axis determined.
    """
    d = slam_second_differences(t_slam, slam_t, imu_t, world_a, h, step)
    sd2, wd2 = d.slam_d2, d.world_d2
    if len(sd2) < 3:
        raise FlightDataError("per-axis SLAM scale initialisation: fewer than 3 pairs")
    sd2, wd2 = sd2 - sd2.mean(axis=0), wd2 - wd2.mean(axis=0)
    den = (wd2**2).sum(axis=0)
    k = np.where(den > 0, (sd2 * wd2).sum(axis=0) / np.where(den > 0, den, 1.0), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        res = sd2 - k * wd2
        se = np.sqrt((res**2).sum(axis=0) / max(len(sd2) - 2, 1) / den)
        rel_se = se * math.sqrt(2.0 * h / step) / np.abs(k)
    ok = np.isfinite(k) & (k > 0) & (rel_se <= 1.0)
    rel_se = np.where(ok, rel_se, np.inf)
    if not ok.any():
        raise FlightDataError(
            f"per-axis SLAM scale initialisation gave {k}: too little motion on every axis"
        )
    return np.where(ok, k, k[ok].mean()), rel_se, len(sd2)


#: :func:`rotation_increments`: least world-frame rotation of a pair [rad] (SLAM orientation
#: noise is about 0.01 rad; smaller turns only add noise directions to the rotation fit) and the
#: least number of such pairs for :func:`init_slam_alignment` ``rotation="motion"`` to use them.
MOTION_MIN_TURN_RAD = 0.05
MOTION_MIN_TURNS = 3


def rotation_increments(
    slam: SlamSeries,
    imu_t: np.ndarray,
    world_R_body_imu: np.ndarray,
    pair_s: float = 0.25,
    max_pair_s: float = 1.0,
    min_angle_rad: float = MOTION_MIN_TURN_RAD,
) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vectors of the SLAM-frame increments ``slam_R_cam(j) slam_R_cam(i)^T`` and of the
    world-frame ones ``world_R_body(j) world_R_body(i)^T`` of pose pairs. The camera is rigid on
    the body, so the first are the second rotated by ``slam_R_world`` whatever ``body_R_cam``
    is (the SLAM-vs-gyro check's pairs are body-frame, and fit ``body_R_cam`` instead).

    Args:
        slam: the session's poses, ``slam_q_cam_wxyz`` being ``slam_R_cam`` (convention applied).
        imu_t, world_R_body_imu: (N,) times [s] and (N, 3, 3) attitude track, interpolated to the
            pose times.
        pair_s, max_pair_s: a pose is paired with the first one at least ``pair_s`` later, kept
            when at most ``max_pair_s`` later [s].
        min_angle_rad: pairs whose world-frame rotation is smaller are left out [rad].

    Returns:
        ``(slam_rv, world_rv)``, (P, 3) each [rad].
    """
    t = np.asarray(slam.t, float)
    i, j = pose_pairs(t, None, pair_s, max_pair_s)  # the SLAM-vs-gyro check's pairs
    if not len(i):
        return np.zeros((0, 3)), np.zeros((0, 3))
    S = quat_wxyz_to_matrix(np.asarray(slam.slam_q_cam_wxyz, float))
    W = slerp_rotations(imu_t, world_R_body_imu, t)
    tr = (0, 2, 1)
    slam_rv = so3_log(S[j] @ np.transpose(S[i], tr))
    world_rv = so3_log(W[j] @ np.transpose(W[i], tr))
    big = np.linalg.norm(world_rv, axis=1) >= min_angle_rad
    return slam_rv[big], world_rv[big]


def init_slam_alignment(
    slam: SlamSeries,
    imu: ImuSeries,
    world_R_body_imu: np.ndarray,
    body_T_cam: np.ndarray,
    gravity: float,
    h: float = 0.5,
    step: float = 0.1,
    rotation: str = "orientations",
) -> SlamAlignmentInit:
    """Closed-form ``slam_T_world`` of one SLAM session.

    1. ``slam_R_world`` = chordal mean of ``slam_R_cam (world_R_body body_R_cam)^T``; with
       ``rotation="motion"`` instead, without ``body_R_cam``: the rotation that best maps the
       metric second differences onto the SLAM ones and the world-frame rotation increments
       onto the SLAM-frame ones (:func:`rotation_increments`; orthogonal Procrustes, each kind
       weighing the same): determined by two non-parallel directions, e.g. turns about the
       vertical and a horizontal acceleration.
    2. scale = least squares of SLAM second differences against ``slam_R_world`` times the metric
       second differences from the accelerometer (:func:`slam_second_differences`: on the SLAM
       samples themselves, unbiased on low-rate keyframes), jointly with
       the accelerometer bias (a body-frame offset ``h^2 b_a`` of the metric ones).
    3. ``slam_t_world`` from the first SLAM position with the world origin at the first camera.

    Args:
        slam: the session's SLAM poses.
        imu: IMU samples covering the session.
        world_R_body_imu: (N, 3, 3) attitude at the IMU times.
        body_T_cam: 4x4 camera extrinsics.
        gravity: g [m/s^2].
        h: half-width of the second differences [s].
        step: spacing of the second-difference centres [s].
        rotation: ``"orientations"`` (through ``body_T_cam``) or ``"motion"`` (without it; step 1).
    """
    world_a = world_specific_accel(imu, world_R_body_imu, gravity)
    d = slam_second_differences(slam.t, slam.slam_t_cam, imu.t, world_a, h, step)
    slam_d2, world_d2, centers = d.slam_d2, d.world_d2, d.centers
    if len(slam_d2) < 6:
        span = float(slam.t[-1] - slam.t[0]) if len(slam.t) else 0.0
        raise FlightDataError(
            f"SLAM scale initialisation: {len(slam_d2)} acceleration pair(s) from "
            f"{len(slam.t)} SLAM pose(s) over {span:.1f} s, 6 needed (a pair is three poses "
            f"{0.5 * h:g}-{2 * h:g} s apart, their middles {step:g} s apart: at least "
            f"{2 * h + 5 * step:.1f} s of poses without longer gaps); "
            "give an initial scale (front-end priors) or a longer session"
        )
    spread = float("nan")
    if rotation == "motion":
        # Centring removes the part of an accelerometer bias that stays put in the world.
        M = (slam_d2 - slam_d2.mean(axis=0)).T @ (world_d2 - world_d2.mean(axis=0))
        slam_rv, world_rv = rotation_increments(slam, imu.t, world_R_body_imu)
        if len(slam_rv) >= MOTION_MIN_TURNS and (n := float(np.linalg.norm(M))) > 0:
            # Turns well above the orientation noise: each kind of pair weighs the same
            # (metres and radians do not compare).
            M_rot = slam_rv.T @ world_rv
            M = M / n + M_rot / float(np.linalg.norm(M_rot))
        sv = np.linalg.svd(M, compute_uv=False)
        spread = float(sv[1] / sv[0]) if sv[0] > 0 else 0.0
        slam_R_world = project_to_so3(M)
    elif rotation == "orientations":
        world_R_body_slam = slerp_rotations(imu.t, world_R_body_imu, slam.t)
        slam_R_cam = quat_wxyz_to_matrix(slam.slam_q_cam_wxyz)
        slam_R_world = rotation_mean(
            slam_R_cam @ np.transpose(world_R_body_slam @ body_T_cam[:3, :3], (0, 2, 1))
        )
    else:
        raise ValueError(f"init_slam_alignment: rotation={rotation!r}")
    # Joint least squares of the scale s and c = s b_a: an accelerometer bias b_a (body frame)
    # adds h^2 world_R_body b_a to each metric second difference, which SLAM does not see:
    #   slam_d2 = s slam_R_world world_d2 - h^2 slam_R_world world_R_body(t) c.
    R_c = slerp_rotations(imu.t, world_R_body_imu, centers)
    A = np.zeros((len(centers), 3, 4))
    A[:, :, 0] = world_d2 @ slam_R_world.T
    A[:, :, 1:] = -(d.width[:, None, None] ** 2) * (slam_R_world[None] @ R_c)
    A = A.reshape(-1, 4)
    y = slam_d2.reshape(-1)
    x, *_ = np.linalg.lstsq(A, y, rcond=None)
    scale = float(x[0])
    if not np.isfinite(scale) or scale <= 0:
        raise FlightDataError(
            f"SLAM scale initialisation gave {scale}: the SLAM motion does not match the IMU "
            "(wrong body_T_cam, time offset or SLAM frame?)"
        )
    centred = world_d2 - world_d2.mean(axis=0)
    excitation = float(np.sqrt((centred**2).sum(axis=1).mean()))
    resid = y - A @ x
    # Standard error of the scale (residuals of neighbouring pairs overlap: a lower bound).
    dof = max(len(y) - 4, 1)
    cov = np.linalg.pinv(A.T @ A) * float(resid @ resid) / dof
    scale_se = float(np.sqrt(max(cov[0, 0], 0.0)))
    world_t_cam0 = np.zeros(3)
    slam_t_world = slam.slam_t_cam[0] - scale * slam_R_world @ world_t_cam0
    return SlamAlignmentInit(
        scale, slam_R_world, slam_t_world, len(slam_d2), excitation, scale_se / scale, spread
    )
