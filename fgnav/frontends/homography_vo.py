"""Homography visual odometry of a downward camera over flat ground (seed 002, Algorithms 1-2).

Pipeline per pair of frames (i, j) (seed 002 sec. II-B2, II-B3, III-C):

1. Optional **orthogonal rectification** (sec. III-C): each image is warped by the rotation-only
   homography ``W = K_v virt_R_cam K^-1`` so that it looks taken by a *virtual* camera at the same
   centre, optical axis straight down (world -z), with the camera's yaw and zero roll/pitch. The
   attitude comes from an AHRS/EKF (seed 002's ``[q, h]`` EKF). With ``normalize_scale`` the virtual
   focal length is ``f * h / h_ref`` so one pixel covers the same ground distance at every height
   (the paper's "uniform height" scale adjustment). Areas outside the original image stay black and
   are masked out.
2. Shi-Tomasi corners on frame i (``cv2.goodFeaturesToTrack``), pyramidal Lucas-Kanade into frame j
   (``cv2.calcOpticalFlowPyrLK``; optionally a forward-backward consistency check). When the pair
   that ended at frame i was valid, LK starts at the points its motion predicts and tracks on the
   base image only (``HomographyVOOptions.flow_guess``), otherwise from zero motion through the
   pyramid.
3. RANSAC homography (``cv2.findHomography``, or pycolmap's LO-RANSAC
   ``estimate_homography_matrix``), convention ``p_j ~ H p_i`` in pixels.
4. Decomposition of the calibrated homography ``G = K_j^-1 H K_i = R + (t/d) n^T`` into
   ``(R, t/d) = cam_j_T_cam_i`` and the plane normal ``n`` in cam i (pointing from the camera to the
   ground, ``n^T X_i = d``). ``cv2.decomposeHomographyMat`` returns up to 4 solutions; the one whose
   normal is closest to the ground normal predicted from the attitude (world -z seen from cam i) is
   kept. (A naive "normal along +z" choice picks the sign-flipped solution, see GTSAM-NOTES "Vision
   pieces".) When OpenCV declares the motion a pure rotation (zero normals: translations of a few
   mm at 3 m), :func:`decompose_known_normal` takes over with the predicted normal, so slow motion
   is not zeroed. pycolmap's ``pose_from_homography_matrix`` (cheirality) is a switchable
   alternative, and ``decomposition="attitude"`` (:func:`decompose_level_homography`) takes roll,
   pitch and the normal from the attitude and only yaw and ``t/d`` from the image: best with an
   accurate attitude (true attitude: 2.5 cm after 13.8 m of two-turns), worse with a noisy one
   (the change of the attitude's tilt error between frames becomes translation).
5. Metric translation ``t = (t/d) * d_i`` with ``d_i`` the camera height above the ground at frame
   i (rangefinder or EKF height plus the camera lever arm).

Dead reckoning (Algorithm 1, eqs. 9-10): ``world_R_cam_j = world_R_cam_i R^T`` and
``world_t_cam_j = world_t_cam_i - world_R_cam_j t``. With rectification the roll and pitch of every
frame come from the attitude and only the yaw is integrated from vision (the virtual cameras are
level by construction); without it the full rotation is composed, as in the paper's "traditional"
odometry.

Frames: world z up; body FLU; camera x right, y down, z along the optical axis
(``Calibration.body_T_cam``). Units: metres, radians, seconds, pixels.

Outputs per pair (:class:`HomographyMeasurement`): the homography in the ORIGINAL (undistorted)
image coordinates of frames i -> j for the graph's homography factor, the decomposition, the yaw
increment, inlier and tracked counts and the times. Pairs that fail (too few corners, tracks or
inliers, no attitude/height at the image time, no valid decomposition) are kept, flagged with the
reason, counted in :attr:`VOResult.counts` and logged.

Not modelled: non-planar scenes, sloped ground (the ground normal is world z), rolling shutter,
motion blur, exposure changes.

Reference: Paz & Nesmachnow, "Doble acoplamiento entre sensores inerciales y odometria visual"
(../shared/seeds/002_*.txt), Algorithms 1-2, sec. III-C, Figs. 5-10.
"""

from __future__ import annotations

import bisect
import functools
import logging
import math
import time
from collections import Counter, deque
from dataclasses import asdict, dataclass, field
from operator import attrgetter
from typing import Literal

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import AttitudeSample, Event, ImageFrame, RangeReading, stream_events
from fgnav.datasets.geometry import (
    matrix_to_quat_wxyz,
    quat_wxyz_to_matrix,
    so3_exp,
    so3_log,
    wrap_angle,
    yaw_of,
)
from fgnav.datasets.range_limits import RangeLimits
from fgnav.datasets.types import (
    AttitudeSeries,
    Calibration,
    CameraIntrinsics,
    Flight,
    ImageSeries,
    Trajectory,
    YawSeries,
)
from fgnav.estimate import Estimate, TimeSeries

logger = logging.getLogger(__name__)

#: Ground normal in the world frame, pointing from a camera above the ground down to it.
WORLD_DOWN = np.array([0.0, 0.0, -1.0])

#: Seconds of attitude and height history the event-fed stage keeps before its newest event.
BUFFER_S = 2.0

#: ``cv2.findHomography`` methods selectable by ``HomographyVOOptions.ransac_method``.
RANSAC_METHODS = ("RANSAC", "USAC_DEFAULT", "USAC_FAST", "USAC_ACCURATE", "USAC_MAGSAC")

#: Reasons a pair can be rejected (keys of :attr:`VOResult.counts`).
# Frames all of a wrong size (none of the camera's size yet) that make the second warning.
WRONG_SIZE_ALL_FRAMES = 5

REJECT_REASONS = (
    "no_attitude",
    "no_height",
    "few_corners",
    "few_tracked",
    "few_inliers",
    "no_homography",
    "no_decomposition",
)


@dataclass(frozen=True)
class HomographyVOOptions:
    """Options of :class:`HomographyVO`.

    Attributes:
        rectify: warp each image to a level, straight-down virtual camera using the attitude
            (seed 002 sec. III-C) before tracking.
        normalize_scale: with ``rectify``, also scale each rectified image by ``h / h_ref`` (virtual
            focal length ``f h / h_ref``) so a pixel covers the same ground distance at every
            height (``h_ref``: camera height at the first frame).
        max_corners: Shi-Tomasi corners per frame (GTSAM-NOTES "Vision pieces": 200).
        corner_quality: ``qualityLevel`` of ``cv2.goodFeaturesToTrack`` (OpenCV's example 0.01).
        min_corner_distance_px: minimum distance between corners [px].
        corner_block_size_px: Shi-Tomasi gradient window [px].
        corner_pyramid_level: detect the corners on the image reduced this many times by 2
            (``cv2.pyrDown``; distance and block size scaled alike) and scale them back: a quarter
            of the detection cost per level (0: full resolution).

            Tracking defaults (window 21, 2 levels, one LK pass, corners at level 1) were chosen
            on the trajectory, the 180 s figure8 with the 30 Hz camera of
            ``scripts/bench_online.py`` (fixed-lag / batch ATE [cm]; without the camera 2.46 /
            1.71): OpenCV's usual window 21, 3 levels, a forward-backward check and corners at
            full resolution 1.28 / 1.07 (236 frames/s); the defaults 1.26 / 1.07; window 21 at 3
            levels without the check 1.29 / 1.10; window 15 1.50 / 1.22; window 11 1.48 / 1.21
            (1.82 / 1.53 with corners at level 1). The forward-backward check changed no figure
            and costs a second LK pass. The per-pair corner transfer error against the true
            homographies did not predict these (window 11: 0.0142-0.0173 px against 0.0142-0.0196
            px for window 21 with the check, on two-turns and figure8); with 100 instead of 200
            corners it grew by half.
        lk_window_px: Lucas-Kanade window side [px] (OpenCV's default 21; see below).
        lk_pyramid_levels: LK pyramid levels above the base image without a flow guess
            (OpenCV's lk_track.py: 3).
        lk_max_iterations, lk_epsilon_px: LK stopping criteria per pyramid level (iterations,
            update size [px]). OpenCV's 0.01 px stops early enough to bias small displacements
            low (about -1 % of the translation on the simulated two-turns flight).
        flow_guess: ``"previous"``: start LK at the points predicted by the previous pair's
            homography (constant image motion in original pixels: the previous pair's
            homography scaled to this pair's time interval, mapped into the tracking images by
            the two frames' rectifying warps) and track on ``flow_guess_levels`` pyramid levels
            instead of ``lk_pyramid_levels``; ``"none"``: every pair tracked from zero motion
            through the whole pyramid. Causal: the guess only uses the pair that ended at the
            reference frame and the warps of the two frames.
            Without a previous pair (first pair, after a gap, ``measure_pair``) the pair is
            tracked without a guess, and a guessed pair whose median LK correction of the guess
            exceeds ``flow_guess_max_correction_px`` or that fails (too few tracks or inliers, no
            homography) is tracked again without it (``flow_guess="rejected"`` on the
            measurement).
        flow_guess_levels: LK pyramid levels above the base image when a guess exists (0: the
            base image only).

            Measured (issue 14; 1 OpenCV thread, shared machine, back to back): bench_vo 320x240
            two-turns 12 s, 239 of 240 pairs guessed, none rejected: 425-492 frames/s against
            283-316 without the guess (the LK call 0.6 against 1.6 ms per pair on the captured
            pairs; its cost hardly depends on the iterations, it is the per-point set-up of each
            level), rms corner error 0.0175 / 0.0181 px and radial part unchanged; later, the
            machine slower, 356-399 frames/s with 0 levels and 264-299 with 1. The guess is
            0.02 px off at the median (max 0.18 px) on that flight. Trajectory ATE [cm], VO
            without the guess -> guess on 0 levels (-> 1 level): figure8 180 s 30 Hz camera push
            causal 1.620 -> 1.623 (1.617), prepared fixed-lag 1.501 -> 1.516 (1.497), batch
            1.494 -> 1.498 (1.490); two-turns seeds 0/1/2 batch 0.478/0.302/0.388 ->
            0.479/0.302/0.395 (0.478/0.303/0.387), fixed-lag 0.545/0.604/0.565 ->
            0.546/0.602/0.570 (0.544/0.604/0.564). A null change of the old tracking
            (``lk_epsilon_px`` 0.008-0.012) moves figure8 by up to +0.018 cm and two-turns seed 2
            by -0.002 cm: the figure8 changes are within that, two-turns seed 2's +0.005-0.007 cm
            (0.393-0.395 for eps 0.003-0.012 with the guess) is systematic but small; 1 level
            removes it at 0.45 ms per frame. Those figures are of a guess made in the level frame
            of the attitude: with the simulated AHRS stream (0.005 rad noise) instead of the true
            attitude, 459 of 599 figure8 pairs were rejected (median LK correction 3.2 px: the
            rectified images jitter with the attitude noise). In original pixels through the
            frames' warps (now) all 599 are guessed, median correction 0.28 px; two-turns seeds
            0/2 with the AHRS, 560 pairs, transfer error against the true homographies median
            0.0298 / 0.0303 -> 0.0294 / 0.0300 px; ATE [cm] no guess -> guess, same machine:
            figure8 push / prepared / batch 1.620 / 1.501 / 1.494 -> 1.656 / 1.517 / 1.482,
            two-turns seeds 0/2 batch 0.478 / 0.388 -> 0.489 / 0.401 and fixed-lag 0.545 / 0.565
            -> 0.558 / 0.577 (1 level: the same on two-turns, figure8 push 1.628);
            ``bench_online.py --camera`` 4.7x -> 8.6x real time.
        flow_guess_max_correction_px: median distance between the guessed and the tracked
            points above which the guess is rejected and the pair tracked again [px].
        fb_max_error_px: forward-backward LK round-trip error above which a track is dropped [px].
        forward_backward: track back from j to i and apply ``fb_max_error_px`` (False: one LK
            pass, outliers left to RANSAC).
        redetect_below: reuse the RANSAC inliers of the pair ending at a frame as the points
            tracked from it while at least this many remain, and detect Shi-Tomasi corners afresh
            below (0: detect in every frame, as seed 002's Algorithm 2). Measured on two-turns
            (20 s, 20 Hz): 120 saves a fifth of the time but raises the corner transfer error
            from 0.0173 to 0.0225 px (fewer points, none yet where new ground enters the view).
        estimator: ``"opencv"`` (``cv2.findHomography`` RANSAC) or ``"pycolmap"`` (LO-RANSAC).
        decomposition: ``"opencv"`` (4 solutions, chosen by the predicted ground normal),
            ``"pycolmap"`` (``pose_from_homography_matrix``, cheirality), or ``"attitude"``: roll,
            pitch and ground normal from the attitude, only the yaw increment and ``t/d`` from the
            homography (:func:`decompose_level_homography`); this removes the
            rotation-translation ambiguity of a free decomposition, which on the simulated
            two-turns flight absorbs 1-2 % of the translation into a spurious tilt.
        ransac_threshold_px: RANSAC inlier threshold on the transfer error [px].
        ransac_method: the robust method of ``cv2.findHomography`` (``estimator="opencv"``):
            ``"RANSAC"`` (classic RANSAC, then Levenberg-Marquardt on the inliers) or one of
            OpenCV's USAC variants ``"USAC_DEFAULT"``, ``"USAC_FAST"``, ``"USAC_ACCURATE"``,
            ``"USAC_MAGSAC"``.
        ransac_confidence: RANSAC confidence.
        ransac_seed: seed of pycolmap's RANSAC (OpenCV's RANSAC is deterministic).
        min_corners: fewer Shi-Tomasi corners than this rejects the pair (``few_corners``).
        min_tracked: fewer forward-backward-consistent tracks rejects it (``few_tracked``).
        min_inliers: fewer RANSAC inliers rejects it (``few_inliers``).
        mask_margin_px: corners and tracks closer than this to the image edge or to the border
            of the valid (non-black) area of a rectified image are not used [px] (None: half the
            LK window plus 4 px, 14 px for the default window). No LK window of a kept track then
            reaches the mirrored image border or the black fill: such tracks are biased towards
            zero motion, and since those moving out of the image are lost and those moving in are
            kept, they expanded the homography at the image corners (measured on two-turns against
            the true homographies: a mean radial corner error of +0.0066 px per pair without
            rectification, +0.0052 px with it, -0.0005 and -0.0001 px with the margin).
        rectify_interpolation: OpenCV interpolation flag of the rectifying warp.
        max_reference_failures: after this many consecutive rejected pairs against the same
            reference frame (at once when the reference itself has too few corners), the
            reference moves to the newest frame and the motion across the gap is unknown (counted
            in ``counts["gaps"]``; the new reference is not posed, the position is held).
        tilt_source: where the dead-reckoned roll/pitch come from: ``"attitude"`` (attitude series;
            vision integrates yaw only), ``"vo"`` (compose the full rotation, seed 002 Alg. 1), or
            ``"auto"`` (``"attitude"`` when rectifying, else ``"vo"``).
        range_median_window: running-median length [readings] of the rangefinder height used
            when no height series is given (isolated obstacle spikes).
        max_interp_gap_s: largest gap of the attitude/height series across which they are
            interpolated to an image time [s].
    """

    rectify: bool = True
    normalize_scale: bool = False
    max_corners: int = 200
    corner_quality: float = 0.01
    min_corner_distance_px: float = 7.0
    corner_block_size_px: int = 7
    corner_pyramid_level: int = 1
    lk_window_px: int = 21
    lk_pyramid_levels: int = 2
    lk_max_iterations: int = 30
    lk_epsilon_px: float = 0.01
    flow_guess: Literal["none", "previous"] = "previous"
    flow_guess_levels: int = 0
    flow_guess_max_correction_px: float = 2.0
    fb_max_error_px: float = 0.5
    forward_backward: bool = False
    redetect_below: int = 0
    estimator: Literal["opencv", "pycolmap"] = "opencv"
    decomposition: Literal["opencv", "pycolmap", "attitude"] = "opencv"
    ransac_threshold_px: float = 1.5
    ransac_method: str = "RANSAC"
    ransac_confidence: float = 0.999
    ransac_seed: int = 0
    min_corners: int = 20
    min_tracked: int = 15
    min_inliers: int = 12
    mask_margin_px: int | None = None
    rectify_interpolation: int = cv2.INTER_LINEAR
    max_reference_failures: int = 3
    tilt_source: Literal["auto", "attitude", "vo"] = "auto"
    range_median_window: int = 5
    max_interp_gap_s: float = 0.25

    @property
    def margin_px(self) -> int:
        """The effective ``mask_margin_px`` [px]."""
        if self.mask_margin_px is not None:
            return int(self.mask_margin_px)
        return self.lk_window_px // 2 + 4

    def check(self) -> HomographyVOOptions:
        """Raise ``ValueError`` on an inconsistent option."""
        if self.estimator not in ("opencv", "pycolmap"):
            raise ValueError(f"estimator: expected 'opencv' or 'pycolmap', got {self.estimator!r}")
        if self.decomposition not in ("opencv", "pycolmap", "attitude"):
            raise ValueError(
                f"decomposition: expected 'opencv', 'pycolmap' or 'attitude', got "
                f"{self.decomposition!r}"
            )
        if self.ransac_method not in RANSAC_METHODS:
            raise ValueError(
                f"ransac_method: expected one of {', '.join(RANSAC_METHODS)}, got "
                f"{self.ransac_method!r}"
            )
        if self.flow_guess not in ("none", "previous"):
            raise ValueError(f"flow_guess: expected 'none' or 'previous', got {self.flow_guess!r}")
        if self.tilt_source not in ("auto", "attitude", "vo"):
            raise ValueError(f"tilt_source: expected auto/attitude/vo, got {self.tilt_source!r}")
        if self.normalize_scale and not self.rectify:
            raise ValueError("normalize_scale needs rectify=True")
        if not 0 < self.ransac_confidence < 1:
            # (cv2.findHomography asserted it: 0, -1 or 1e300 were a cv2.error traceback)
            raise ValueError(
                f"ransac_confidence: expected > 0 and < 1, got {self.ransac_confidence!r}"
            )
        if min(self.min_corners, self.min_tracked, self.min_inliers) < 4:
            raise ValueError("a homography needs at least 4 points: min_* must be >= 4")
        most = max(self.min_corners, self.min_tracked, self.min_inliers)
        if self.max_corners > 0 and most > self.max_corners:
            # (every pair was rejected: ekf-vo002 exited 0 without an estimate)
            raise ValueError(
                f"min_corners/min_tracked/min_inliers: expected <= max_corners="
                f"{self.max_corners} (a pair has no more points), got {most}"
            )
        return self


@dataclass(frozen=True, eq=False)
class HomographyMeasurement:
    """One frame pair (i -> j) of the downward camera.

    Attributes:
        index_i, index_j: image indices in the flight's ImageSeries.
        t_i, t_j: image times [s].
        valid: False when the pair was rejected; then ``reason`` says why and the geometric fields
            are NaN.
        reason: ``""`` or one of :data:`REJECT_REASONS`.
        H: (3, 3) homography in the original (undistorted) pixel coordinates, ``p_j ~ H p_i``,
            normalised to ``H[2, 2] = 1``.
        cam_j_R_cam_i: (3, 3) rotation of the decomposition.
        cam_j_t_cam_i_over_d: (3,) translation of ``cam_j_T_cam_i`` divided by the distance ``d``
            of camera i to the ground plane [1].
        cam_i_normal: (3,) unit ground normal in cam i, pointing from the camera to the ground.
        camera_height_i: camera height above the ground at frame i used for the metric scale [m].
        cam_j_t_cam_i: (3,) metric translation ``(t/d) * camera_height_i`` [m].
        yaw_increment: body yaw change from i to j [rad] (world z axis).
        num_corners: Shi-Tomasi corners found in frame i.
        num_tracked: tracks that passed the forward-backward check and stayed in the valid area.
        num_inliers: RANSAC inliers of the homography.
        inlier_rms_px: RMS transfer error ``|p_j - H p_i|`` of the inliers in original pixels (a
            basis for the homography factor's corner noise).
        flow_guess: how LK started (``HomographyVOOptions.flow_guess``): ``""`` from zero motion
            through the whole pyramid, ``"previous"`` from the previous pair's motion,
            ``"rejected"`` the guess was tried and the pair tracked again from zero motion.
    """

    index_i: int
    index_j: int
    t_i: float
    t_j: float
    valid: bool
    reason: str = ""
    H: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    cam_j_R_cam_i: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    cam_j_t_cam_i_over_d: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    cam_i_normal: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    camera_height_i: float = float("nan")
    cam_j_t_cam_i: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    yaw_increment: float = float("nan")
    num_corners: int = 0
    num_tracked: int = 0
    num_inliers: int = 0
    inlier_rms_px: float = float("nan")
    flow_guess: str = ""


@dataclass(frozen=True, eq=False)
class VOResult:
    """Output of :func:`run`.

    Attributes:
        measurements: one :class:`HomographyMeasurement` per attempted pair, valid or not.
        estimate: dead-reckoned body trajectory at the frames that got a pose
            (``method="homography-vo"``, ``causal=True``).
        yaw: integrated yaw of the body at the same frames, for the graph's yaw factor.
        counts: ``frames``, ``posed_frames``, ``pairs``, ``valid_pairs``, ``gaps`` and one count per
            rejection reason.
    """

    measurements: list[HomographyMeasurement]
    estimate: Estimate
    yaw: YawSeries
    counts: dict[str, int]

    @property
    def valid(self) -> list[HomographyMeasurement]:
        """The valid pair measurements."""
        return [m for m in self.measurements if m.valid]


# ----------------------------------------------------------------------------------------------
# Geometry helpers (pure functions)
# ----------------------------------------------------------------------------------------------


def level_camera_rotation(body_R_cam: np.ndarray) -> np.ndarray:
    """Rotation ``body_R_virt`` of a virtual camera looking straight down (body -z) whose image x
    axis is the horizontal projection of the real camera's x axis.

    For a camera mounted exactly downward this is ``body_R_cam`` itself.

    Args:
        body_R_cam: (3, 3) camera orientation in the body frame (camera z = optical axis).

    Returns:
        (3, 3) ``body_R_virt``.
    """
    z = np.array([0.0, 0.0, -1.0])
    x = np.asarray(body_R_cam, dtype=float)[:, 0].copy()
    x[2] = 0.0
    if np.linalg.norm(x) < 1e-6:
        x = np.asarray(body_R_cam, dtype=float)[:, 1].copy()
        x[2] = 0.0
        x = _cross3(x, z)
    x /= np.linalg.norm(x)
    y = _cross3(z, x)
    return np.column_stack([x, y, z])


def _cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (``np.cross`` without its per-call overhead)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def remove_yaw(world_R_body: np.ndarray) -> np.ndarray:
    """``Rz(-yaw) world_R_body``: the roll/pitch part of an attitude (ZYX yaw removed)."""
    psi = float(yaw_of(world_R_body))
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ world_R_body


def rot_z(psi: float) -> np.ndarray:
    """Rotation about z by ``psi`` [rad]."""
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def scaled_intrinsics(K: np.ndarray, scale: float) -> np.ndarray:
    """Camera matrix with focal lengths multiplied by ``scale`` (principal point kept)."""
    Kv = np.array(K, dtype=float)
    Kv[0, 0] *= scale
    Kv[1, 1] *= scale
    return Kv


def rectifying_homography(
    K: np.ndarray,
    world_R_body: np.ndarray,
    body_R_cam: np.ndarray,
    scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation-only homography to the level, straight-down virtual camera (seed 002 III-C).

    The virtual camera has the real camera's centre, orientation
    ``world_R_virt = Rz(yaw(world_R_body)) body_R_virt`` (see :func:`level_camera_rotation`), and
    intrinsics ``K`` with focal lengths times ``scale``.

    Args:
        K: (3, 3) real camera matrix [px].
        world_R_body: (3, 3) body attitude.
        body_R_cam: (3, 3) camera mounting.
        scale: focal-length factor of the virtual camera (``h / h_ref`` for scale normalisation).

    Returns:
        ``(W, virt_R_cam, K_virt)``: ``W`` (3, 3) maps original pixels to rectified pixels
        (``p_v ~ W p``); ``virt_R_cam`` (3, 3); ``K_virt`` (3, 3).
    """
    body_R_virt = level_camera_rotation(body_R_cam)
    world_R_virt = rot_z(float(yaw_of(world_R_body))) @ body_R_virt
    world_R_cam = world_R_body @ body_R_cam
    virt_R_cam = world_R_virt.T @ world_R_cam
    Kv = scaled_intrinsics(K, scale)
    W = Kv @ virt_R_cam @ np.linalg.inv(K)
    return W / W[2, 2], virt_R_cam, Kv


def transfer_error_px(H_a: np.ndarray, H_b: np.ndarray, width: int, height: int) -> float:
    """Largest distance [px] between the images of the four image corners under two homographies."""
    corners = np.array(
        [[0, 0, 1], [width - 1, 0, 1], [width - 1, height - 1, 1], [0, height - 1, 1]], dtype=float
    ).T
    a = H_a @ corners
    b = H_b @ corners
    return float(np.max(np.linalg.norm(a[:2] / a[2] - b[:2] / b[2], axis=0)))


def corner_transfer_components(
    H_meas: np.ndarray, H_true: np.ndarray, width: int, height: int, centre: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Radial and tangential parts [px] of the corner transfer error ``H_meas c - H_true c`` at
    the four image corners ``c`` (pixel centres), along and across the direction from ``centre``
    (the principal point, (2,)) to ``H_true c``. A positive mean radial part is an expansion of the
    measured homography (a spurious approach to the ground), a non-zero mean tangential part a
    spurious rotation.

    Returns:
        ``(radial, tangential)``, each (4,).
    """
    corners = np.array(
        [[0, 0, 1], [width - 1, 0, 1], [width - 1, height - 1, 1], [0, height - 1, 1]], dtype=float
    ).T
    a = H_meas @ corners
    b = H_true @ corners
    a, b = a[:2] / a[2], b[:2] / b[2]
    e = a - b
    r = b - np.asarray(centre, float).reshape(2, 1)
    r /= np.linalg.norm(r, axis=0)
    return np.sum(e * r, axis=0), r[0] * e[1] - r[1] * e[0]


def yaw_increment(
    world_R_body_i: np.ndarray, body_R_cam: np.ndarray, cam_j_R_cam_i: np.ndarray
) -> float:
    """Body yaw change [rad] from frame i to j given the camera rotation ``cam_j_R_cam_i``.

    ``world_R_body_j = world_R_body_i body_R_cam cam_j_R_cam_i^T cam_R_body``; the result is
    ``yaw(world_R_body_j) - yaw(world_R_body_i)``, which depends on the roll and pitch of
    ``world_R_body_i`` but not on its yaw.
    """
    tilt_i = remove_yaw(world_R_body_i)
    world_R_body_j = tilt_i @ body_R_cam @ cam_j_R_cam_i.T @ body_R_cam.T
    # yaw_of is atan2, already in [-pi, pi]; only -pi maps to pi (wrap_angle's convention).
    psi = math.atan2(world_R_body_j[1, 0], world_R_body_j[0, 0])
    return math.pi if psi == -math.pi else psi


# ----------------------------------------------------------------------------------------------
# Image steps
# ----------------------------------------------------------------------------------------------


def detect_corners(
    img: np.ndarray, options: HomographyVOOptions, mask: np.ndarray | None = None
) -> np.ndarray:
    """Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) of a grey image, (M, 1, 2) float32, at
    least ``margin_px`` from the image edge (and inside ``mask`` when given)."""
    if mask is None:
        mask = border_mask(img.shape[:2], options.margin_px)
    level = options.corner_pyramid_level
    if level > 0:
        # Corners of a coarser pyramid level (a quarter of the pixels per level), scaled back:
        # LK only needs texture around a point, not a corner maximum at full resolution.
        small, small_mask = img, mask
        for _ in range(level):
            small = cv2.pyrDown(small)
            small_mask = cv2.resize(
                small_mask, (small.shape[1], small.shape[0]), interpolation=cv2.INTER_NEAREST
            )
        f = float(2**level)
        corners = cv2.goodFeaturesToTrack(
            small,
            maxCorners=options.max_corners,
            qualityLevel=options.corner_quality,
            minDistance=options.min_corner_distance_px / f,
            mask=small_mask,
            blockSize=max(3, int(options.corner_block_size_px / f) | 1),
        )
        if corners is None:
            return np.zeros((0, 1, 2), np.float32)
        return (corners.reshape(-1, 1, 2) * f).astype(np.float32)
    corners = cv2.goodFeaturesToTrack(
        img,
        maxCorners=options.max_corners,
        qualityLevel=options.corner_quality,
        minDistance=options.min_corner_distance_px,
        mask=mask,
        blockSize=options.corner_block_size_px,
    )
    if corners is None:
        return np.zeros((0, 1, 2), np.float32)
    return corners.reshape(-1, 1, 2).astype(np.float32, copy=False)


def track_points(
    img_i: np.ndarray,
    img_j: np.ndarray,
    p_i: np.ndarray,
    options: HomographyVOOptions,
    mask_j: np.ndarray | None = None,
    guess_j: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Points ``p_i`` of ``img_i`` tracked into ``img_j`` by pyramidal Lucas-Kanade.

    A track is kept when LK converges (both ways with ``forward_backward``: the round trip
    j -> i must land within ``fb_max_error_px`` of the start) and the tracked point lies in
    ``mask_j`` (default: at least ``margin_px`` from the edge of ``img_j``).

    Args:
        img_i, img_j: grey uint8 images of the same size.
        p_i: (M, 1, 2) float32 points in ``img_i``.
        options: VO options.
        mask_j: optional uint8 mask of ``img_j`` (non-zero = valid pixels).
        guess_j: optional (M, 1, 2) float32 initial positions in ``img_j``
            (``cv2.OPTFLOW_USE_INITIAL_FLOW``), then tracked on ``flow_guess_levels`` pyramid
            levels (the backward pass starts at ``p_j`` minus the guessed motion).

    Returns:
        ``(pts_i, pts_j)``: (K, 2) float32 pixel positions of the kept tracks.
    """
    if len(p_i) == 0:
        empty = np.zeros((0, 2), np.float32)
        return empty, empty
    lk = dict(
        winSize=(options.lk_window_px, options.lk_window_px),
        maxLevel=options.lk_pyramid_levels if guess_j is None else options.flow_guess_levels,
        criteria=(
            cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT,
            options.lk_max_iterations,
            options.lk_epsilon_px,
        ),
    )
    if guess_j is None:
        p_j, st_f, _ = cv2.calcOpticalFlowPyrLK(img_i, img_j, p_i, None, **lk)
    else:
        p_j, st_f, _ = cv2.calcOpticalFlowPyrLK(
            img_i, img_j, p_i, guess_j.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk
        )
    keep = st_f.ravel() == 1
    if options.forward_backward:
        if guess_j is None:
            p_back, st_b, _ = cv2.calcOpticalFlowPyrLK(img_j, img_i, p_j, None, **lk)
        else:
            p_back, st_b, _ = cv2.calcOpticalFlowPyrLK(
                img_j, img_i, p_j, p_j - (guess_j - p_i), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk
            )
        fb = (p_back - p_i).reshape(-1, 2)
        keep &= (st_b.ravel() == 1) & (np.einsum("ij,ij->i", fb, fb) < options.fb_max_error_px**2)
    pj = p_j.reshape(-1, 2)
    # The LK window of a point near the image edge reaches the mirrored border: such tracks are
    # biased towards zero motion, and the ones kept are mostly those moving inwards (those moving
    # out leave the image), which expands the homography at the image corners. So a track must
    # end inside the mask (default: the image without a margin of ``margin_px``).
    if mask_j is None:
        mask_j = border_mask(img_j.shape[:2], options.margin_px)
    h, w = mask_j.shape
    ij = np.rint(pj).astype(np.intp)
    on_image = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    keep &= on_image
    idx = np.flatnonzero(keep)
    keep[idx[mask_j[ij[idx, 1], ij[idx, 0]] == 0]] = False
    return p_i.reshape(-1, 2)[keep], pj[keep]


def track_features(
    img_i: np.ndarray,
    img_j: np.ndarray,
    options: HomographyVOOptions,
    mask_i: np.ndarray | None = None,
    mask_j: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Shi-Tomasi corners in ``img_i`` (:func:`detect_corners`) tracked into ``img_j``
    (:func:`track_points`).

    Returns:
        ``(pts_i, pts_j, num_corners)``: (M, 2) float32 pixel positions of the kept tracks and the
        number of corners found in ``img_i``.
    """
    corners = detect_corners(img_i, options, mask_i)
    p_i, p_j = track_points(img_i, img_j, corners, options, mask_j)
    return p_i, p_j, int(corners.shape[0])


@functools.lru_cache(maxsize=8)
def border_mask(shape: tuple[int, int], margin: int) -> np.ndarray:
    """uint8 mask (255 inside) of an image of ``shape`` without a ``margin``-pixel border."""
    mask = np.zeros(shape, np.uint8)
    if 2 * margin < min(shape):
        mask[margin : shape[0] - margin, margin : shape[1] - margin] = 255
    mask.setflags(write=False)
    return mask


def rectified_mask(W: np.ndarray, width: int, height: int, margin: int) -> np.ndarray:
    """uint8 mask (255 inside) of the pixels of a rectified image (``p_v ~ W p``) that come from
    the original image at least ``margin`` pixels from its edge, and are themselves at least
    ``margin`` from the rectified image's edge (a convex quadrilateral: no warp of a mask)."""
    m = float(margin)
    inner = np.array(
        [
            [m, m, 1.0],
            [width - 1 - m, m, 1.0],
            [width - 1 - m, height - 1 - m, 1.0],
            [m, height - 1 - m, 1.0],
        ]
    )
    q = inner @ W.T
    poly = np.rint(q[:, :2] / q[:, 2:3] * 16.0).astype(np.int32)
    mask = np.zeros((height, width), np.uint8)
    cv2.fillConvexPoly(mask, poly, 255, lineType=cv2.LINE_8, shift=4)
    return cv2.bitwise_and(mask, border_mask((height, width), margin))


@dataclass(eq=False)
class PreparedFrame:
    """A frame as the VO tracks it.

    Attributes:
        image: grey tracking image (rectified when rectifying).
        mask: uint8 mask of its usable pixels (valid area without a margin).
        W, W_inv: (3, 3) warp original -> tracking pixels and its inverse (identity when not
            rectifying).
        virt_R_cam: rotation of the rectification (identity when not rectifying).
        K_virt: camera matrix of the tracking image.
        level_R_cam: rotation to the level virtual camera from the attitude (None without).
        points: (M, 1, 2) float32 points to track from this frame (the inliers of the pair that
            ended here, or detected corners), None until set.
        motion: ``(H, dt)`` of the valid pair that ended at this frame: its homography in
            original pixels (``p_j ~ H p_i``, undistorted, before rectification) and its time
            interval [s], the source of the next pair's LK guess (``flow_guess``); None until set.
    """

    image: np.ndarray
    mask: np.ndarray
    W: np.ndarray
    W_inv: np.ndarray
    virt_R_cam: np.ndarray
    K_virt: np.ndarray
    level_R_cam: np.ndarray | None
    points: np.ndarray | None = None
    motion: tuple[np.ndarray, float] | None = None


def estimate_homography(
    pts_i: np.ndarray, pts_j: np.ndarray, options: HomographyVOOptions
) -> tuple[np.ndarray | None, np.ndarray]:
    """RANSAC homography ``p_j ~ H p_i`` [px] and the inlier mask, or ``(None, mask)``."""
    n = len(pts_i)
    if n < 4:
        return None, np.zeros(n, bool)
    if options.estimator == "pycolmap":
        import pycolmap

        ransac = pycolmap.RANSACOptions()
        ransac.max_error = options.ransac_threshold_px
        ransac.confidence = options.ransac_confidence
        ransac.random_seed = options.ransac_seed
        res = pycolmap.estimate_homography_matrix(
            np.asarray(pts_i, np.float64), np.asarray(pts_j, np.float64), ransac
        )
        if res is None:
            return None, np.zeros(n, bool)
        H = np.asarray(res["H"], float)
        mask = np.asarray(res["inlier_mask"], bool).ravel()
    else:
        H, m = cv2.findHomography(
            pts_i,
            pts_j,
            getattr(cv2, options.ransac_method),
            options.ransac_threshold_px,
            confidence=options.ransac_confidence,
        )
        if H is None:
            return None, np.zeros(n, bool)
        mask = m.ravel().astype(bool)
    if not np.all(np.isfinite(H)) or abs(H[2, 2]) < 1e-12:
        return None, np.zeros(n, bool)
    return H / H[2, 2], mask


def decompose_homography(
    G: np.ndarray,
    predicted_normal: np.ndarray,
    options: HomographyVOOptions,
    rays_i: np.ndarray | None = None,
    rays_j: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Decompose a calibrated homography ``G ~ R + (t/d) n^T`` (``K = I``).

    Args:
        G: (3, 3) calibrated homography ``K_j^-1 H K_i`` (any scale).
        predicted_normal: (3,) expected ground normal in cam i (camera to ground).
        options: VO options (``decomposition`` switch).
        rays_i, rays_j: (M, 3) inlier bearing vectors in cam i and cam j (needed by pycolmap).

    Returns:
        ``(cam_j_R_cam_i, t_over_d, n)`` or None when no solution has a normal within 90 degrees
        of the prediction.
    """
    if options.decomposition == "pycolmap":
        import pycolmap

        res = pycolmap.pose_from_homography_matrix(G, np.eye(3), np.eye(3), rays_i, rays_j)
        pose = res["cam2_from_cam1"]
        R = np.asarray(pose.rotation.matrix(), float)
        t = np.asarray(pose.translation, float)
        # COLMAP writes H = R - t n^T / d (normal pointing away from the plane): flip n only.
        n = -np.asarray(res["normal"], float)
        n /= np.linalg.norm(n)
        if np.dot(n, predicted_normal) <= 0:
            return None
        return R, t, n
    num, Rs, ts, ns = cv2.decomposeHomographyMat(G, np.eye(3))
    best = None
    best_cos = 0.0
    for R, t, n in zip(Rs, ts, ns, strict=True):
        n = n.ravel()
        norm = float(np.linalg.norm(n))
        if not np.isfinite(norm) or norm == 0.0:
            continue
        c = float(np.dot(n, predicted_normal) / norm)
        if c > best_cos:
            best_cos = c
            best = (np.asarray(R, float), t.ravel().astype(float), n / norm)
    if best is None and num > 0:
        # OpenCV treats a homography whose singular values are nearly equal as a pure rotation and
        # returns zero normals and t = 0, which drops small translations (a few mm at 3 m).
        # Decompose with the predicted normal instead.
        return decompose_known_normal(G, predicted_normal)
    return best


def decompose_known_normal(
    G: np.ndarray, normal: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decompose ``G ~ R + (t/d) n^T`` when the plane normal ``n`` (in cam i) is known.

    For any ``v`` orthogonal to ``n``, ``G v = lambda R v``: two such vectors give ``lambda`` and
    ``R`` (orthogonal Procrustes), then ``t/d = G n / lambda - R n``. Well conditioned for any
    translation, including none (where the free decomposition's normal is undefined).

    Args:
        G: (3, 3) calibrated homography (any non-zero scale).
        normal: (3,) plane normal in cam i (camera to plane).

    Returns:
        ``(cam_j_R_cam_i, t_over_d, n)`` with ``n`` the unit normal.
    """
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    v1 = _cross3(n, helper)
    v1 /= np.linalg.norm(v1)
    v2 = _cross3(n, v1)
    a, b = G @ v1, G @ v2
    lam = 0.5 * (np.linalg.norm(a) + np.linalg.norm(b))
    if np.linalg.det(G) < 0:
        lam = -lam
    A = np.column_stack([a / lam, b / lam, _cross3(a, b) / lam**2])
    B = np.column_stack([v1, v2, _cross3(v1, v2)])
    U, _, Vt = np.linalg.svd(A @ B.T)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return R, G @ n / lam - R @ n, n


def decompose_level_homography(G_level: np.ndarray) -> tuple[float, np.ndarray]:
    """Decompose a calibrated homography between two level, straight-down cameras.

    With both cameras level (optical axis = world down, e.g. the rectified virtual cameras) the
    ground normal is ``e3`` in both and ``G_level ~ Rz(psi) + (t/d) e3^T`` (seed 002 sec. III-C: the
    rectified images differ by a planar rotation, translation and scale). The yaw is the best 2-D
    rotation of the upper-left block (orthogonal Procrustes), the scale ``lambda`` its size, and
    ``t/d = G[:, 2] / lambda - e3``.

    Args:
        G_level: (3, 3) ``level_j_R_cam_j K^-1 H K level_i_R_cam_i^T`` (any non-zero scale).

    Returns:
        ``(psi, t_over_d)``: rotation angle about the level camera's z axis [rad] (positive from
        x to y) and (3,) ``t/d`` in the level camera j.
    """
    A = np.asarray(G_level, float)[:2, :2]
    psi = float(np.arctan2(A[1, 0] - A[0, 1], A[0, 0] + A[1, 1]))
    lam = 0.5 * ((A[0, 0] + A[1, 1]) * np.cos(psi) + (A[1, 0] - A[0, 1]) * np.sin(psi))
    t = np.asarray(G_level, float)[:, 2] / lam - np.array([0.0, 0.0, 1.0])
    return psi, t


# ----------------------------------------------------------------------------------------------
# Input interpolation
# ----------------------------------------------------------------------------------------------


def _interp_valid(t_series: np.ndarray, t_query: np.ndarray, max_gap: float) -> np.ndarray:
    """True where ``t_query`` lies inside ``t_series`` (or within ``max_gap`` of an end) and the
    enclosing gap is at most ``max_gap``."""
    idx = np.searchsorted(t_series, t_query)
    lo = np.clip(idx - 1, 0, len(t_series) - 1)
    hi = np.clip(idx, 0, len(t_series) - 1)
    gap = np.maximum(np.abs(t_query - t_series[lo]), 0) + np.abs(t_series[hi] - t_query)
    near_end = np.minimum(np.abs(t_query - t_series[0]), np.abs(t_query - t_series[-1])) <= max_gap
    inside = (t_query >= t_series[0]) & (t_query <= t_series[-1])
    return (inside & (gap <= max_gap)) | (~inside & near_end)


def interpolate_attitude(
    attitude: AttitudeSeries, t: np.ndarray, max_gap_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """``world_R_body`` (N, 3, 3) at times ``t`` by slerp, and a validity mask (N,)."""
    ok = _interp_valid(attitude.t, t, max_gap_s)
    out = np.tile(np.eye(3), (len(t), 1, 1))
    if len(attitude) == 1:
        out[:] = quat_wxyz_to_matrix(attitude.world_q_body_wxyz[0])
        return out, ok
    q = attitude.world_q_body_wxyz
    rot = Rotation.from_quat(np.column_stack([q[:, 1:4], q[:, 0]]))
    slerp = Slerp(attitude.t, rot)
    tq = np.clip(t, attitude.t[0], attitude.t[-1])
    out[:] = slerp(tq).as_matrix()
    return out, ok


def height_from_range(
    flight: Flight, attitude: AttitudeSeries, max_gap_s: float, median_window: int = 5
) -> TimeSeries:
    """Body height above the ground [m] from the tilted rangefinder (seed 002 eq. 21).

    ``h_body = range * cos(tilt) - (world_R_body body_t_range)_z`` with the beam along the
    sensor's +z axis and ``cos(tilt) = -(world_R_body body_R_range e_z)_z``. Readings outside
    ``[calib.range_min, calib.range_max]``, at its floor (``range_at_min``) or at its maximum
    (``range_at_max``: no echo), without attitude, or with the beam pointing above the horizon
    are skipped and counted (logged). A running median over ``median_window`` readings
    (odd; 1 for none) removes isolated obstacle spikes (a box or a person under the vehicle).
    """
    rng = flight.range
    if rng is None:
        raise FlightDataError(
            f"{flight.name}: homography VO needs a height (argument `height`) or a range stream"
        )
    world_R_body, ok = interpolate_attitude(attitude, rng.t, max_gap_s)
    body_T_range = np.asarray(flight.calib.body_T_range, float)
    beam = world_R_body @ body_T_range[:3, 2]
    cos_tilt = -beam[:, 2]
    lever_z = (world_R_body @ body_T_range[:3, 3])[:, 2]
    # (out of its limits, at its floor or at its maximum: no height, range_refusal)
    c = flight.calib
    in_range = RangeLimits.of_stream(rng.range, c.range_min, c.range_max).mask(rng.range)
    keep = ok & in_range & (cos_tilt > 0)
    skipped = int((~keep).sum())
    if skipped:
        logger.warning(
            "%s: %d of %d range readings not usable for the VO height (out of [%.2f, %.2f] m, "
            "no attitude, or beam above the horizon)",
            flight.name,
            skipped,
            len(rng),
            flight.calib.range_min,
            flight.calib.range_max,
        )
    if not keep.any():
        raise FlightDataError(f"{flight.name}.range: no reading usable as a height")
    h = (rng.range * cos_tilt - lever_z)[keep]
    if median_window > 1 and h.size >= median_window:
        from scipy.ndimage import median_filter

        h = median_filter(h, size=median_window, mode="nearest")
    return TimeSeries(t=rng.t[keep], value=h)


# ----------------------------------------------------------------------------------------------
# The odometer
# ----------------------------------------------------------------------------------------------


class HomographyVO:
    """Homography visual odometry over a flight's downward-camera images.

    Args:
        options: :class:`HomographyVOOptions` (defaults when None).
    """

    def __init__(self, options: HomographyVOOptions | None = None) -> None:
        self.options = (options or HomographyVOOptions()).check()

    # -- one pair --------------------------------------------------------------------------------

    def _prepare(
        self,
        img: np.ndarray,
        K: np.ndarray,
        world_R_body: np.ndarray | None,
        body_R_cam: np.ndarray,
        scale: float,
    ) -> PreparedFrame:
        """The frame as tracked: rectified (or not) image, valid mask, warp and rotations."""
        o = self.options
        h, w = img.shape[:2]
        if not o.rectify:
            eye = np.eye(3)
            level_R_cam = None
            if world_R_body is not None:
                _, level_R_cam, _ = rectifying_homography(K, world_R_body, body_R_cam)
            mask = border_mask((h, w), o.margin_px)
            return PreparedFrame(img, mask, eye, eye, eye, np.asarray(K, float), level_R_cam)
        # The level virtual camera's rotation does not depend on the scale normalisation.
        W, virt_R_cam, Kv = rectifying_homography(K, world_R_body, body_R_cam, scale)
        level_R_cam = virt_R_cam
        warped = cv2.warpPerspective(img, W, (w, h), flags=o.rectify_interpolation)
        return PreparedFrame(
            warped,
            rectified_mask(W, w, h, o.margin_px),
            W,
            np.linalg.inv(W),
            virt_R_cam,
            Kv,
            level_R_cam,
        )

    def measure_pair(
        self,
        img_i: np.ndarray,
        img_j: np.ndarray,
        K: np.ndarray,
        body_R_cam: np.ndarray,
        world_R_body_i: np.ndarray | None,
        world_R_body_j: np.ndarray | None,
        camera_height_i: float,
        camera_height_j: float | None = None,
        height_ref: float | None = None,
        index: tuple[int, int] = (0, 1),
        times: tuple[float, float] = (0.0, 1.0),
    ) -> HomographyMeasurement:
        """Measure the motion between two undistorted grey images of the downward camera.

        Args:
            img_i, img_j: (H, W) uint8 grey images, i earlier.
            K: (3, 3) camera matrix [px].
            body_R_cam: (3, 3) camera mounting.
            world_R_body_i, world_R_body_j: body attitudes (needed to rectify and to predict the
                ground normal; None -> the camera is assumed level, no rectification possible).
            camera_height_i: camera height above the ground at i [m] (metric scale).
            camera_height_j: camera height at j [m] (scale normalisation only).
            height_ref: reference height of the scale normalisation [m] (default
                ``camera_height_i``).
            index, times: image indices and times copied into the result.

        Returns:
            The pair's :class:`HomographyMeasurement` (``valid=False`` with a reason on failure).
        """
        o = self.options
        K = np.asarray(K, float)
        base = dict(index_i=index[0], index_j=index[1], t_i=times[0], t_j=times[1])
        if o.rectify and (world_R_body_i is None or world_R_body_j is None):
            return HomographyMeasurement(valid=False, reason="no_attitude", **base)
        href = camera_height_i if height_ref is None else height_ref
        s_i = camera_height_i / href if o.normalize_scale else 1.0
        s_j = (camera_height_j or camera_height_i) / href if o.normalize_scale else 1.0
        return self._measure_prepared(
            self._prepare(img_i, K, world_R_body_i, body_R_cam, s_i),
            self._prepare(img_j, K, world_R_body_j, body_R_cam, s_j),
            K,
            body_R_cam,
            world_R_body_i,
            camera_height_i,
            base,
        )

    def _measure_prepared(
        self,
        prep_i: PreparedFrame,
        prep_j: PreparedFrame,
        K,
        body_R_cam,
        world_R_body_i,
        cam_h_i,
        base,
    ):
        o = self.options
        Wi, vRc_i, Kv_i, L_i = prep_i.W, prep_i.virt_R_cam, prep_i.K_virt, prep_i.level_R_cam
        vRc_j, Kv_j, L_j = prep_j.virt_R_cam, prep_j.K_virt, prep_j.level_R_cam
        # 1. Track the points of i into j (in rectified images when rectifying): the inlier tracks
        # of the pair that ended at i while enough remain, else fresh Shi-Tomasi corners.
        corners = prep_i.points
        if corners is None or len(corners) < max(o.redetect_below, 1):
            corners = prep_i.points = detect_corners(prep_i.image, o, prep_i.mask)
        n_corners = len(corners)
        guess = None
        if n_corners >= o.min_corners:
            guess = _flow_guess(prep_i, prep_j, base["t_j"] - base["t_i"], o)
        flow_guess = ""
        if guess is not None:
            # From the previous pair's motion, on fewer pyramid levels; rejected (and the pair
            # tracked from zero motion through the whole pyramid) when LK had to move the guessed
            # points far or the pair fails with it.
            p_i, p_j = track_points(
                prep_i.image, prep_j.image, corners, o, prep_j.mask, guess(corners)
            )
            Hv, inl = None, None
            if len(p_i) >= o.min_tracked:
                d = p_j - guess(p_i)
                if np.median(np.einsum("ij,ij->i", d, d)) <= o.flow_guess_max_correction_px**2:
                    Hv, inl = estimate_homography(p_i, p_j, o)
            flow_guess = "previous"
            if Hv is None or inl.sum() < o.min_inliers:
                flow_guess = "rejected"
        if flow_guess != "previous":
            p_i, p_j = track_points(prep_i.image, prep_j.image, corners, o, prep_j.mask)
        counts = dict(num_corners=n_corners, num_tracked=len(p_i), flow_guess=flow_guess)
        if n_corners < o.min_corners:
            return HomographyMeasurement(valid=False, reason="few_corners", **base, **counts)
        if len(p_i) < o.min_tracked:
            return HomographyMeasurement(valid=False, reason="few_tracked", **base, **counts)
        # 2. RANSAC homography in the tracking images (done above for a kept guess).
        if flow_guess != "previous":
            Hv, inl = estimate_homography(p_i, p_j, o)
        if Hv is None:
            return HomographyMeasurement(valid=False, reason="no_homography", **base, **counts)
        counts["num_inliers"] = int(inl.sum())
        if inl.sum() < o.min_inliers:
            return HomographyMeasurement(valid=False, reason="few_inliers", **base, **counts)
        # 3. Back to original pixels: p_j ~ Wj^-1 Hv Wi p_i; inlier residual in original pixels.
        if o.rectify:
            H = prep_j.W_inv @ Hv @ Wi
            H /= H[2, 2]
            orig_i = _warp_points(prep_i.W_inv, p_i[inl])
            orig_j = _warp_points(prep_j.W_inv, p_j[inl])
        else:
            H, orig_i, orig_j = Hv / Hv[2, 2], p_i[inl], p_j[inl]
        # The image motion of this pair in original pixels guesses the next pair's tracks.
        prep_j.motion = (H, base["t_j"] - base["t_i"])
        counts["inlier_rms_px"] = _transfer_rms(H, orig_i, orig_j)
        if o.redetect_below > 0:
            # The inliers carry over as the points of the next pair (from j).
            prep_j.points = p_j[inl].reshape(-1, 1, 2)
        # 4. Decompose.
        if o.decomposition == "attitude":
            if L_i is None or L_j is None:
                return HomographyMeasurement(valid=False, reason="no_attitude", **base, **counts)
            # Level virtual cameras from the attitude: G_level = Rz(psi) + (t/d) e3^T.
            G_cal = np.linalg.solve(K, H @ K)
            psi, t_level = decompose_level_homography(L_j @ G_cal @ L_i.T)
            R = L_j.T @ rot_z(psi) @ L_i
            t_over_d = L_j.T @ t_level
            n = L_i.T @ np.array([0.0, 0.0, 1.0])
            return self._valid(H, R, t_over_d, n, cam_h_i, world_R_body_i, body_R_cam, base, counts)
        # Decompose in the virtual (or real) cameras: G = Kv_j^-1 Hv Kv_i = R_v + t_v n_v^T.
        G = np.linalg.solve(Kv_j, Hv @ Kv_i)
        world_R_cam_i_tilt = (
            remove_yaw(world_R_body_i) @ body_R_cam
            if world_R_body_i is not None
            else level_camera_rotation(body_R_cam)
        )
        n_pred_cam = world_R_cam_i_tilt.T @ WORLD_DOWN
        n_pred_virt = vRc_i @ n_pred_cam
        rays_i = rays_j = None
        if o.decomposition == "pycolmap":
            rays_i = _rays(p_i[inl], Kv_i)
            rays_j = _rays(p_j[inl], Kv_j)
        dec = decompose_homography(G, n_pred_virt, o, rays_i, rays_j)
        if dec is None:
            return HomographyMeasurement(valid=False, reason="no_decomposition", **base, **counts)
        R_v, t_v, n_v = dec
        # virt frames share the camera centres: cam_j_R_cam_i = cam_j_R_virt_j R_v virt_i_R_cam_i.
        R = vRc_j.T @ R_v @ vRc_i
        t_over_d = vRc_j.T @ t_v
        n = vRc_i.T @ n_v
        return self._valid(H, R, t_over_d, n, cam_h_i, world_R_body_i, body_R_cam, base, counts)

    @staticmethod
    def _valid(H, R, t_over_d, n, cam_h_i, world_R_body_i, body_R_cam, base, counts):
        dpsi = yaw_increment(
            world_R_body_i if world_R_body_i is not None else np.eye(3), body_R_cam, R
        )
        return HomographyMeasurement(
            valid=True,
            H=H,
            cam_j_R_cam_i=R,
            cam_j_t_cam_i_over_d=t_over_d,
            cam_i_normal=n,
            camera_height_i=float(cam_h_i),
            cam_j_t_cam_i=t_over_d * cam_h_i,
            yaw_increment=dpsi,
            **base,
            **counts,
        )

    # -- a flight --------------------------------------------------------------------------------

    def run(
        self,
        flight: Flight,
        attitude: AttitudeSeries | None = None,
        height: TimeSeries | None = None,
        initial_world_T_body: np.ndarray | None = None,
    ) -> VOResult:
        """Homography VO over all images of ``flight``: the attitude and height interpolated to
        each image time, then every frame through one :class:`HomographyVoStage` in time order.

        Args:
            flight: a flight with ``images`` (downward camera) and ``calib.body_T_cam``.
            attitude: body attitude (e.g. seed 002's EKF); default ``flight.attitude``. Needed to
                rectify and for ``tilt_source="attitude"``.
            height: body height above the ground [m] (``TimeSeries`` with (N,) values, e.g. the
                EKF's ``h``); default: from ``flight.range`` tilted by the attitude.
            initial_world_T_body: (4, 4) pose of the first posed frame; default: attitude at that
                frame (identity without attitude) at ``(0, 0, height)``.

        Returns:
            :class:`VOResult`.

        Raises:
            FlightDataError: no images, no camera intrinsics, no attitude when rectifying, or no
                height source.
        """
        t_start = time.perf_counter()
        o = self.options
        images = _require_images(flight)
        cam = images.camera if images.camera is not None else flight.calib.camera
        attitude = attitude if attitude is not None else flight.attitude
        tilt_source = _tilt_source(o)
        if attitude is None and (o.rectify or tilt_source == "attitude"):
            raise FlightDataError(
                f"{flight.name}: homography VO with rectify={o.rectify}, tilt_source="
                f"{tilt_source!r} needs an attitude series (argument or flight.attitude)"
            )
        if attitude is not None:
            attitude.check(f"{flight.name}.vo_attitude")
        if height is None:
            if attitude is None:
                raise FlightDataError(
                    f"{flight.name}: homography VO needs a height series or attitude + range"
                )
            height = height_from_range(flight, attitude, o.max_interp_gap_s, o.range_median_window)
        h_t = np.asarray(height.t, float)
        h_v = np.asarray(height.value, float).reshape(-1)
        if h_t.shape != h_v.shape or h_t.size == 0 or not np.all(np.isfinite(h_v)):
            raise FlightDataError(
                f"{flight.name}: VO height series: expected finite (N,) values at (N,) times, "
                f"got t {h_t.shape}, value {h_v.shape}"
            )
        # Attitude and height at image times (None where unavailable).
        if attitude is not None:
            world_R_body_all, att_ok = interpolate_attitude(attitude, images.t, o.max_interp_gap_s)
        else:
            world_R_body_all, att_ok = None, np.ones(len(images), bool)
        h_ok = _interp_valid(h_t, images.t, o.max_interp_gap_s)
        body_h = np.interp(images.t, h_t, h_v)

        stage = HomographyVoStage(
            flight.calib,
            cam,
            o,
            uses_attitude=attitude is not None,
            initial_world_T_body=initial_world_T_body,
            name=flight.name,
        )
        for frame in stream_events(flight, "images"):
            k = frame.index
            R = world_R_body_all[k] if world_R_body_all is not None and att_ok[k] else None
            stage.process(frame, R, float(body_h[k]) if h_ok[k] else None)
        return stage.result(runtime_s=time.perf_counter() - t_start)


class HomographyVoStage:
    """The homography VO as an incremental stage: fed one camera frame at a time, it emits the
    measurement of the pair (reference frame -> this frame) at once and dead-reckons the pose.

    Two ways to feed it (DESIGN.md sec. 7: "front-ends are stages"):

    * :meth:`process` (``frame``, attitude and body height at the frame's time, given by the
      caller): the batch path (:meth:`HomographyVO.run`) interpolates its whole series and calls
      this for every frame;
    * :meth:`feed` (any event in arrival order): attitude samples and range readings are kept in a
      short buffer, and an image waits until the attitude and the height at its time can be
      interpolated from what has arrived (or until ``max_interp_gap_s`` has passed on the event
      clock, then it uses the newest values within that gap). The height is the tilted range
      (seed 002 eq. 21) with a trailing running median of ``range_median_window`` readings: only
      past readings, unlike the batch path's centred median. An upstream stage may give the
      attitude and the height instead (:meth:`add_inputs`: the seed-002 baseline's attitude-and-
      height EKF, its outputs at each IMU sample), with only the images as events.
      :meth:`flush` processes what still waits at the end of a stream.

    Nothing here reads the future or a whole flight; the state is the reference frame (its
    prepared image, pyramid and tracked points), the dead-reckoned pose and counters.

    Args:
        calib: calibration (``body_T_cam``; ``body_T_range`` and the range limits for :meth:`feed`).
        camera: camera intrinsics (default: ``calib.camera``, else the first frame's ``camera``).
        options: VO options.
        uses_attitude: an attitude comes with every frame (None at a frame then means missing:
            ``no_attitude``); False: no attitude at all (camera assumed level, no rectification).
        initial_world_T_body: (4, 4) pose of the first posed frame (default: the attitude at
            that frame at ``(0, 0, height)``).
        name: name used in log messages.
        keep_history: keep every measurement and posed frame for :meth:`result` (False: only
            counts and the newest ones, for unbounded live runs).
    """

    def __init__(
        self,
        calib: Calibration,
        camera: CameraIntrinsics | None = None,
        options: HomographyVOOptions | None = None,
        *,
        uses_attitude: bool = True,
        initial_world_T_body: np.ndarray | None = None,
        name: str = "vo",
        keep_history: bool = True,
    ) -> None:
        self._vo = HomographyVO(options)
        o = self.options = self._vo.options
        self.tilt_source = _tilt_source(o)
        if not uses_attitude and (o.rectify or self.tilt_source == "attitude"):
            raise FlightDataError(
                f"{name}: homography VO with rectify={o.rectify}, tilt_source="
                f"{self.tilt_source!r} needs an attitude"
            )
        self.calib = calib
        self.camera = camera if camera is not None else calib.camera
        self.uses_attitude = bool(uses_attitude)
        self.name = name
        self.keep_history = bool(keep_history)
        body_T_cam = np.asarray(calib.body_T_cam, float)
        self.body_R_cam, self.body_t_cam = body_T_cam[:3, :3], body_T_cam[:3, 3]
        self._initial_world_T_body = initial_world_T_body
        self._undistort = None if self.camera is None else _undistorter(self.camera)
        # Odometry state.
        self._ref: _RefFrame | None = None
        self._failures = 0
        self._height_ref: float | None = None
        self._world_R_cam: np.ndarray | None = None
        self._world_t_cam: np.ndarray | None = None
        self._world_R_body: np.ndarray | None = None
        self._psi = 0.0
        self._size_bad = 0  # frames of another size than the camera's
        self._size_good = False  # a frame of the camera's size has been seen
        # Outputs.
        self.counts: Counter[str] = Counter()
        self._range_limits = RangeLimits(calib.range_min, calib.range_max)
        self.measurements: list[HomographyMeasurement] = []
        self._posed: list[tuple[float, np.ndarray, np.ndarray, float, float]] = []  # t R p yaw h
        self._n_posed = 0
        self.latest_measurement: HomographyMeasurement | None = None
        self.busy_s = 0.0
        # Event mode (feed): short input buffers and frames waiting for their inputs.
        self._att_t: deque[float] = deque()
        self._att_R: deque[np.ndarray] = deque()
        self._h_t: deque[float] = deque()
        self._h_v: deque[float] = deque()
        self._raw_h: deque[float] = deque(maxlen=max(1, o.range_median_window))
        self._pending: list[ImageFrame] = []
        self._clock = -np.inf
        self._last_t = -np.inf

    # -- one frame -------------------------------------------------------------------------------

    def process(
        self,
        frame: ImageFrame,
        world_R_body: np.ndarray | None,
        body_height: float | None,
    ) -> HomographyMeasurement | None:
        """One frame with the attitude ``world_R_body`` (3, 3) and body height above the ground
        ``body_height`` [m] at its time (None: unavailable).

        Returns:
            the measurement of the pair (reference -> this frame), valid or flagged with a
            reason; None when the frame starts the odometry (first usable frame) or is rejected
            before any reference exists.
        """
        t0 = time.perf_counter()
        try:
            return self._process(frame, world_R_body, body_height)
        finally:
            self.busy_s += time.perf_counter() - t0

    def _process(self, frame, world_R_body, body_height):
        o = self.options
        k, t = int(frame.index), float(frame.t)
        self.counts["frames"] += 1
        self._last_t = max(self._last_t, t)
        if self.camera is None:
            if frame.camera is None:
                raise FlightDataError(f"{self.name}: image {k}: camera intrinsics missing")
            self.camera = frame.camera
            self._undistort = _undistorter(self.camera)
        R = None
        if self.uses_attitude:
            R = None if world_R_body is None else np.asarray(world_R_body, float)
        reason = ""
        if self.uses_attitude and R is None:
            reason = "no_attitude"
        elif body_height is None or not np.isfinite(body_height):
            reason = "no_height"
        else:
            lever_z = (R @ self.body_t_cam)[2] if R is not None else self.body_t_cam[2]
            cam_h = float(body_height) + float(lever_z)
            if not cam_h > 0:
                reason = "no_height"
        if not reason:
            try:
                image = frame.load()
            except FlightDataError as e:
                # An unreadable file (corrupt, truncated, missing): the frame is skipped and
                # counted; the reference stays, so the next readable frame pairs with it.
                if self.counts["unreadable_image"] == 0:
                    logger.warning("%s: %s; skipped, counted as unreadable_image", self.name, e)
                self.counts["unreadable_image"] += 1
                return self._reject_frame(k, t, "unreadable_image", count=False)
            if not self._size_ok(k, image):
                self.counts["unreadable_image"] += 1
                return self._reject_frame(k, t, "unreadable_image", count=False)
        else:
            return self._reject_frame(k, t, reason)
        if self._height_ref is None:
            self._height_ref = cam_h
        scale = cam_h / self._height_ref if o.normalize_scale else 1.0
        K = self.camera.K
        prep = self._vo._prepare(self._undistort(image), K, R, self.body_R_cam, scale)
        cur = _RefFrame(k, t, prep, R, cam_h)
        if self._ref is None:
            # First usable frame: the initial pose.
            self._ref = cur
            world_T_body0 = _initial_pose(self._initial_world_T_body, R, float(body_height))
            self._world_R_body = world_T_body0[:3, :3]
            self._world_R_cam = self._world_R_body @ self.body_R_cam
            self._world_t_cam = world_T_body0[:3, 3] + self._world_R_body @ self.body_t_cam
            self._psi = float(yaw_of(self._world_R_body))
            self._append_pose(t, body_height)
            return None
        ref = self._ref
        base = dict(index_i=ref.index, index_j=k, t_i=ref.t, t_j=t)
        m = self._vo._measure_prepared(
            ref.prep, prep, K, self.body_R_cam, ref.world_R_body, ref.cam_h, base
        )
        self._emit(m)
        if m.flow_guess:
            self.counts[f"flow_guess_{m.flow_guess}"] += 1
        if not m.valid:
            self.counts[m.reason] += 1
            self._failures += 1
            # A reference without corners can never match: move on at once.
            if self._failures >= o.max_reference_failures or m.reason == "few_corners":
                self.counts["gaps"] += 1
                logger.warning(
                    "%s: VO lost track from frame %d to %d (%s); reference moves to %d, "
                    "position held across the gap",
                    self.name,
                    ref.index,
                    k,
                    m.reason,
                    k,
                )
                self._ref, self._failures = cur, 0
                if self.tilt_source == "attitude":
                    self._world_R_body = rot_z(self._psi) @ remove_yaw(R)
                    self._world_R_cam = self._world_R_body @ self.body_R_cam
            return m
        self.counts["valid_pairs"] += 1
        self._failures = 0
        # Dead reckoning (seed 002 Alg. 1, eqs. 9-10).
        self._psi = self._psi + m.yaw_increment
        if self.tilt_source == "attitude":
            self._world_R_body = rot_z(self._psi) @ remove_yaw(R)
            self._world_R_cam = self._world_R_body @ self.body_R_cam
        else:
            self._world_R_cam = self._world_R_cam @ m.cam_j_R_cam_i.T
            self._world_R_body = self._world_R_cam @ self.body_R_cam.T
            self._psi = float(yaw_of(self._world_R_body))
        self._world_t_cam = self._world_t_cam - self._world_R_cam @ m.cam_j_t_cam_i
        self._append_pose(t, body_height)
        self._ref = cur
        return m

    def _size_ok(self, k: int, image: np.ndarray) -> bool:
        """True when ``image`` has the camera's size. A frame of another size (another camera, a
        resized file) would be tracked against the reference with the wrong camera matrix (or
        abort OpenCV's optical flow): it is skipped and counted as ``unreadable_image``, with
        one warning naming the sizes, and one more if every frame so far had a wrong size."""
        cam = self.camera
        shape = tuple(np.shape(image)[:2])
        if np.ndim(image) in (2, 3) and shape == (int(cam.height), int(cam.width)):
            self._size_good = True
            return True
        self._size_bad += 1
        got = f"{shape[1]}x{shape[0]}" if len(shape) == 2 else f"shape {np.shape(image)}"
        if self._size_bad == 1:
            logger.warning(
                "%s: image %d is %s px, the calibration's camera is %dx%d px; skipped, counted "
                "as unreadable_image",
                self.name,
                k,
                got,
                cam.width,
                cam.height,
            )
        if not self._size_good and self._size_bad == WRONG_SIZE_ALL_FRAMES:
            logger.warning(
                "%s: every image so far (%d) is %s px, not the calibration's %dx%d px: the "
                "calibration is not this camera's; no frame is used",
                self.name,
                self._size_bad,
                got,
                cam.width,
                cam.height,
            )
        return False

    def _reject_frame(self, k: int, t: float, reason: str, count: bool = True):
        if count:
            self.counts[reason] += 1
        if self._ref is None:
            return None
        m = HomographyMeasurement(
            index_i=self._ref.index, index_j=k, t_i=self._ref.t, t_j=t, valid=False, reason=reason
        )
        self._emit(m)
        return m

    def _emit(self, m: HomographyMeasurement) -> None:
        self.counts["pairs"] += 1
        self.latest_measurement = m
        if self.keep_history:
            self.measurements.append(m)

    def _append_pose(self, t: float, body_height: float) -> None:
        world_t_body = self._world_t_cam - self._world_R_body @ self.body_t_cam
        pose = (t, self._world_R_body.copy(), world_t_body, self._psi, float(body_height))
        self._n_posed += 1
        if self.keep_history or not self._posed:
            self._posed.append(pose)
        else:
            self._posed[-1] = pose

    def latest_pose(self) -> tuple[float, np.ndarray, float] | None:
        """``(t, world_T_body (4, 4), yaw)`` of the newest posed frame, or None."""
        if not self._posed:
            return None
        t, R, p, psi, _ = self._posed[-1]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, p
        return t, T, psi

    @property
    def n_posed(self) -> int:
        """Frames posed so far."""
        return self._n_posed

    def posed_since(self, n: int) -> list[tuple[float, np.ndarray, np.ndarray, float]]:
        """``(t, world_R_body, world_t_body, body_height)`` of the frames posed after the first
        ``n`` (``keep_history``; without it only the newest is kept), ``body_height`` [m] the
        height above the ground the frame was given."""
        k = max(len(self._posed) - (self._n_posed - n), 0)
        return [(t, R, p, h) for t, R, p, _, h in self._posed[k:]]

    # -- events ----------------------------------------------------------------------------------

    def feed(self, event: Event) -> list[HomographyMeasurement]:
        """One event in arrival order (attitude sample, range reading or image frame; others are
        ignored). Returns the pair measurements of the frames processed because of it."""
        if isinstance(event, AttitudeSample):
            self._add_attitude(
                float(event.t), quat_wxyz_to_matrix(np.asarray(event.world_q_body_wxyz))
            )
        elif isinstance(event, RangeReading):
            self._add_range(event)
        elif isinstance(event, ImageFrame):
            if event.t <= self._last_t:
                self.counts["image_out_of_order"] += 1
            else:
                bisect.insort(self._pending, event, key=attrgetter("t"))
        else:
            return []
        self._clock = max(self._clock, float(event.arrival))
        out = self._drain(final=False)
        self._trim()
        return out

    def add_inputs(
        self,
        t: float,
        arrival: float,
        world_R_body: np.ndarray | None = None,
        body_height: float | None = None,
    ) -> list[HomographyMeasurement]:
        """The attitude ``world_R_body`` (3, 3) and/or the body height above the ground [m] at
        time ``t`` from a stage upstream (seed 002's attitude-and-height EKF), in place of
        attitude samples and range readings, available from ``arrival``. Returns the pair
        measurements of the frames that waited for them."""
        if world_R_body is not None:
            self._add_attitude(float(t), np.asarray(world_R_body, float))
        if body_height is not None:
            if self._h_t and t <= self._h_t[-1]:
                self.counts["height_out_of_order"] += 1
            else:
                self._h_t.append(float(t))
                self._h_v.append(float(body_height))
        self._clock = max(self._clock, float(arrival))
        out = self._drain(final=False)
        self._trim()
        return out

    def inputs_at(self, t: float) -> tuple[np.ndarray | None, float | None]:
        """The attitude and the body height at ``t`` as a frame taken then gets them (from the
        buffered inputs; None where unavailable)."""
        gap = self.options.max_interp_gap_s
        return (
            _value_at(self._att_t, self._att_R, t, gap, _slerp2),
            _value_at(self._h_t, self._h_v, t, gap, _lerp2),
        )

    def flush(self) -> list[HomographyMeasurement]:
        """Process every waiting frame with what has arrived (end of the stream)."""
        return self._drain(final=True)

    def _add_attitude(self, t: float, world_R_body: np.ndarray) -> None:
        if not self._att_t or t > self._att_t[-1]:
            self._att_t.append(t)
            self._att_R.append(world_R_body)
        else:
            self.counts["attitude_out_of_order"] += 1

    def _add_range(self, ev: RangeReading) -> None:
        c = self.calib
        # (a reading below the floor: the sensor does not clamp there, see range_at_min)
        self._range_limits.see(ev.range)
        R = _value_at(self._att_t, self._att_R, ev.t, self.options.max_interp_gap_s, _slerp2)
        if R is None or self._range_limits.refusal(float(ev.range)) is not None:
            self.counts["range_unusable"] += 1
            return
        body_T_range = np.asarray(c.body_T_range, float)
        cos_tilt = -(R @ body_T_range[:3, 2])[2]
        if not cos_tilt > 0 or (self._h_t and ev.t <= self._h_t[-1]):
            self.counts["range_unusable"] += 1
            return
        self._raw_h.append(ev.range * cos_tilt - (R @ body_T_range[:3, 3])[2])
        self._h_t.append(float(ev.t))
        self._h_v.append(float(np.median(self._raw_h)))

    def _drain(self, final: bool) -> list[HomographyMeasurement]:
        out = []
        gap = self.options.max_interp_gap_s
        while self._pending:
            f = self._pending[0]
            att_ready = not self.uses_attitude or (self._att_t and self._att_t[-1] >= f.t)
            h_ready = bool(self._h_t) and self._h_t[-1] >= f.t
            if not (att_ready and h_ready) and not final and self._clock <= f.t + gap:
                break
            self._pending.pop(0)
            R, h = self.inputs_at(f.t)
            m = self.process(f, R if self.uses_attitude else None, h)
            if m is not None:
                out.append(m)
        return out

    def _trim(self) -> None:
        """Drop inputs older than ``BUFFER_S`` before the event clock or the oldest waiting frame
        (a frame arriving later than that finds no attitude or height)."""
        keep_from = min([self._clock, *(f.t for f in self._pending[:1])]) - BUFFER_S
        for ts, vs in ((self._att_t, self._att_R), (self._h_t, self._h_v)):
            while len(ts) > 2 and ts[1] < keep_from:
                ts.popleft()
                vs.popleft()

    # -- result ----------------------------------------------------------------------------------

    def result(self, runtime_s: float | None = None) -> VOResult:
        """Everything measured so far as a :class:`VOResult` (needs ``keep_history``).

        Raises:
            FlightDataError: no frame was posed.
        """
        counts = self.counts
        if not self._posed:
            if counts["frames"] and counts["unreadable_image"] == counts["frames"]:
                why = "every image unreadable or not of the calibration camera's size"
            else:
                why = "no attitude/height at any image time"
            raise FlightDataError(
                f"{self.name}: homography VO posed no frame of {counts['frames']} ({why}: "
                f"{dict(counts)})"
            )
        counts["posed_frames"] = len(self._posed)
        for key in ("frames", "pairs", "valid_pairs", "gaps", *REJECT_REASONS):
            counts.setdefault(key, 0)
        rejected = {r: counts[r] for r in REJECT_REASONS if counts[r]}
        if rejected:
            logger.warning(
                "%s: homography VO rejected %d of %d pairs (%s); %d of %d frames posed",
                self.name,
                counts["pairs"] - counts["valid_pairs"],
                counts["pairs"],
                rejected,
                counts["posed_frames"],
                counts["frames"],
            )
        t = np.array([p[0] for p in self._posed])
        traj = Trajectory(
            t=t,
            world_t_body=np.array([p[2] for p in self._posed]),
            world_q_body_wxyz=matrix_to_quat_wxyz(np.array([p[1] for p in self._posed])),
        )
        yaw = YawSeries(t=t, yaw=wrap_angle(np.array([p[3] for p in self._posed])))
        valid = [m for m in self.measurements if m.valid]
        series = {
            "vo_yaw": TimeSeries(t=t, value=yaw.yaw),
            "vo_inliers": TimeSeries(
                t=np.array([m.t_j for m in valid]),
                value=np.array([m.num_inliers for m in valid], float),
            ),
        }
        estimate = Estimate(
            method="homography-vo",
            trajectory=traj,
            series=series,
            runtime_s=self.busy_s if runtime_s is None else runtime_s,
            causal=True,
            info={
                "counts": dict(counts),
                "options": asdict(self.options),
                "tilt_source": self.tilt_source,
            },
        )
        return VOResult(
            measurements=list(self.measurements), estimate=estimate, yaw=yaw, counts=dict(counts)
        )


@dataclass(frozen=True)
class _RefFrame:
    """A prepared frame kept as the reference of the next pair."""

    index: int
    t: float
    prep: PreparedFrame
    world_R_body: np.ndarray | None
    cam_h: float


def _tilt_source(o: HomographyVOOptions) -> str:
    return o.tilt_source if o.tilt_source != "auto" else ("attitude" if o.rectify else "vo")


def _slerp2(R0: np.ndarray, R1: np.ndarray, a: float) -> np.ndarray:
    return R0 @ so3_exp(a * so3_log(R0.T @ R1))


def _lerp2(v0: float, v1: float, a: float) -> float:
    return v0 + a * (v1 - v0)


def _value_at(ts: deque, vs: deque, t: float, max_gap: float, interp):
    """A buffered series at ``t``: interpolated between the samples around it when they are at
    most ``max_gap`` apart, else the nearest end sample within ``max_gap`` (held); else None."""
    if not ts:
        return None
    if t >= ts[-1]:
        return vs[-1] if t - ts[-1] <= max_gap else None
    if t <= ts[0]:
        return vs[0] if ts[0] - t <= max_gap else None
    n = bisect.bisect_right(ts, t)
    t0, t1 = ts[n - 1], ts[n]
    if t1 - t0 > max_gap:
        return None
    return interp(vs[n - 1], vs[n], (t - t0) / (t1 - t0))


def run(
    flight: Flight,
    attitude: AttitudeSeries | None = None,
    height: TimeSeries | None = None,
    options: HomographyVOOptions | None = None,
    initial_world_T_body: np.ndarray | None = None,
) -> VOResult:
    """Homography VO over a flight: ``HomographyVO(options).run(flight, attitude, height, ...)``."""
    return HomographyVO(options).run(flight, attitude, height, initial_world_T_body)


# ----------------------------------------------------------------------------------------------
# Small private helpers
# ----------------------------------------------------------------------------------------------


def _flow_guess(prep_i: PreparedFrame, prep_j: PreparedFrame, dt: float, o: HomographyVOOptions):
    """Function mapping (M, 2) or (M, 1, 2) points of the tracking image i to their float32 guess
    in the tracking image j: the motion of the pair that ended at i in original pixels, scaled
    to ``dt``, between the two frames' rectifying warps; None without such a pair (or
    ``flow_guess="none"``).

    In original pixels, not in the level (rectified) frame: the original image moves with the
    vehicle, smoothly from frame to frame, while a rectified image also moves with the noise of
    the attitude that levelled it (0.005 rad, 1.2 px at f = 240 px, on the simulated AHRS), which
    no constant-motion guess predicts; this frame's warp ``W_j`` is known and maps the guess
    into its rectified image, noise included."""
    if o.flow_guess == "none" or prep_i.motion is None:
        return None
    H_prev, dt_prev = prep_i.motion  # normalised, H[2, 2] = 1
    if not dt_prev > 0 or not dt > 0:
        return None
    r = dt / dt_prev
    # Displacement scaled: u' = u + r (H u - u), linear only for an affine H; as a guess, the
    # scaled homography (1 - r) I + r H is close enough.
    M = H_prev if r == 1.0 else (1.0 - r) * np.eye(3) + r * H_prev
    H = prep_j.W @ M @ prep_i.W_inv

    def guess(pts: np.ndarray) -> np.ndarray:
        shape = pts.shape
        return _warp_points(H, pts.reshape(-1, 2)).astype(np.float32).reshape(shape)

    return guess


def _warp_points(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(M, 2) pixels mapped by a homography."""
    h = pts @ H[:, :2].T + H[:, 2]
    return h[:, :2] / h[:, 2:3]


def _transfer_rms(H: np.ndarray, pts_i: np.ndarray, pts_j: np.ndarray) -> float:
    """RMS of ``|pts_j - H pts_i|`` [px]."""
    d = _warp_points(H, pts_i) - pts_j
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _rays(pts: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(M, 2) pixels -> (M, 3) unit bearing vectors."""
    h = np.column_stack([pts, np.ones(len(pts))]) @ np.linalg.inv(K).T
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def _require_images(flight: Flight) -> ImageSeries:
    if flight.images is None:
        raise FlightDataError(f"{flight.name}: homography VO needs an images stream")
    images = flight.images
    if images.camera is None and flight.calib.camera is None:
        raise FlightDataError(f"{flight.name}.images.camera: intrinsics missing")
    images.check(f"{flight.name}.images")
    return images


def _undistorter(cam: CameraIntrinsics):
    """Function undistorting a grey image to the pinhole ``cam.K`` (identity without
    distortion)."""
    if not cam.distortion or not np.any(np.asarray(cam.distortion)):
        return lambda img: img
    K = cam.K
    map1, map2 = cv2.initUndistortRectifyMap(
        K, np.asarray(cam.distortion, float), None, K, (cam.width, cam.height), cv2.CV_16SC2
    )
    return lambda img: cv2.remap(img, map1, map2, cv2.INTER_LINEAR)


def _initial_pose(
    initial_world_T_body: np.ndarray | None, world_R_body: np.ndarray | None, body_h: float
) -> np.ndarray:
    if initial_world_T_body is not None:
        return np.asarray(initial_world_T_body, float)
    T = np.eye(4)
    if world_R_body is not None:
        T[:3, :3] = world_R_body
    T[2, 3] = body_h
    return T
