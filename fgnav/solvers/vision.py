"""Downward-camera homography motion in the smoother graph (seed 002's "double coupling" as one
graph; ../shared/DESIGN.md sec. 4.5 and 5).

The homography visual odometry (:mod:`fgnav.frontends.homography_vo`, seed 002 Algorithms 1-2) is
the front-end, an incremental stage (``HomographyVoStage``) fed frame by frame. Here, on the batch
path, it runs over a flight's frames once (cached per flight object and VO options, so the batch
and the replayed fixed-lag smoother of the same flight share it; an online caller feeds the stage
itself and gates each pair with :func:`gate_measurement`) and gives, per pair of consecutive usable
frames ``(i, j)``, the homography ``H`` (original pixels, ``p_j ~ H p_i``), its inlier count and
inlier RMS. This module turns those pairs into corner-transfer factors
(:func:`fgnav.factors.homography_motion.make_homography_factor`) on ``X(k_i), X(k_j), G(g_i)``:

1. **Gate** each VO pair (:func:`gate_pair`): the VO's own rejection (``vo-<reason>``), fewer
   than ``min_inliers`` RANSAC inliers, an inlier RMS above ``max_inlier_rms_px``, an image corner
   mapped behind the camera or to infinity, or a corner moved by more than
   ``max_corner_shift_frac`` of the image size (no LK pyramid tracks that far between two frames:
   such a model is a wrong RANSAC fit).
2. **Keyframes**: the image times of the gated pairs are anchors of the builder's keyframe policy
   (:func:`fgnav.solvers.measurements.keyframe_times`), so at equal camera and keyframe rates every
   frame has its keyframe. When the camera is faster than the keyframes, the anchors closer than
   0.75 keyframe periods are dropped by that policy; the homographies of a chain of pairs between
   two keyframed frames are then composed (``H_ac = H_bc H_ab``) into one factor. A chain that
   breaks (rejected pair) before it reaches a keyframe is counted as ``homography:no-keyframe``.
3. **Noise**: isotropic on the 8 corner coordinates, ``sigma = max(corner_sigma_floor_px,
   corner_sigma_per_rms * inlier_rms)`` [px] (composed chains: root sum of squares of the RMS), or a
   fixed ``corner_sigma_px``; the graph's robust kernel (Huber by default) on top, because a wrong
   RANSAC model moves all four corners at once. On the simulated two-turns flight the corner
   transfer error at the true poses was about half the inlier RMS (0.02 px RMS against a median
   inlier RMS of 0.04 px), so ``corner_sigma_per_rms = 1`` is conservative for one pair; but the
   errors of consecutive pairs are correlated (their mean is not zero: a tracking bias that
   accumulates like VO drift), so the floor is higher than one pair's error. Batch ATE [cm] on
   simulated two-turns flights (10 s seed 1, 20 s seeds 2 and 3, 30 s seed 4) against the floor,
   all sensors / seed 002's sensors (no SLAM, no drag): 0.05 px: 0.26 0.62 0.43 0.64 / 0.41 0.76
   0.78 1.08; 0.1 px: 0.29 0.58 0.30 0.50 / 0.58 0.80 0.66 1.00; 0.2 px: 0.24 0.56 0.35 0.50 /
   0.69 0.81 0.62 0.73; 0.5 px: 0.57 0.57 0.59 0.72 / 0.73 0.91 1.26 1.00; without homography
   (all sensors): 2.05 0.57 0.70 0.79 (measured before the VO's image-border margin, when the
   pairs shared a radial bias of about 0.01 px). The floor was 0.2 px for that bias; the VO's
   image-border margin removed it (mean radial part within +-0.0015 px), and with it the default
   floor is 0.05 px: ATE [cm] of the full simulated flights (seed 1 unless said; images, every
   sensor), floor 0.2 / 0.1 / 0.05 px, batch: two-turns seeds 0/1/2 0.50/0.72/0.38,
   0.49/0.36/0.35, 0.52/0.32/0.40; figure8 0.78, 0.44, 0.32; fixed-lag (push engine, newest
   state): two-turns 0.63/0.97/0.69, 0.58/0.56/0.50, 0.55/0.48/0.50; rectangle 0.70, 0.52, 0.44;
   figure8 1.13, 0.70, 0.52 (2026-12-02). ``scripts/bench_vision.py`` gives the comparison of a
   flight.
4. **Ground**: the factor's plane is the ground-height variable of camera i's keyframe segment,
   the one the rangefinder measures: metric translation comes from the height (first coupling);
   the rotation and yaw of the homography constrain the attitude (second coupling).

Arrival time of a pair: ``t_j + latency_s``; in the fixed-lag smoother both keyframes must still
be in the window (else ``homography:dropped-too-late`` / ``variable-marginalized``).

VO inputs: the attitude (rectification and the normal used by its decomposition) is the flight's
attitude stream, or seed 002's ``[q, h]`` EKF (:mod:`fgnav.frontends.attitude_ekf`) when the
flight has none (``attitude="auto"``); the height is the VO's rangefinder height. The graph uses
only ``H``, which is in original pixels whatever the rectification.

Not modelled: sloped or non-planar ground (the ground normal is world z), camera-IMU time offset,
rolling shutter. The VO yaw increments are not added as separate factors: the homography already
constrains the relative rotation, yaw included.
"""

from __future__ import annotations

import logging
import time
import weakref
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.types import Flight
from fgnav.factors.homography_motion import image_corners, make_homography_factor
from fgnav.frontends.homography_vo import HomographyMeasurement, HomographyVOOptions, VOResult
from fgnav.keys import X

log = logging.getLogger(__name__)

#: Smallest ``w`` of a transferred corner relative to the largest ``|q|`` (``H`` normalised to
#: ``H[2, 2] = 1``): below it the corner is at infinity or behind camera j.
MIN_CORNER_W_REL = 1e-6


@dataclass
class HomographyFactorOptions:
    """Options of the homography factors (``GraphOptions.homography``; None there: defaults).

    Attributes:
        vo: options of the homography VO front-end (default: rectified images, OpenCV
            decomposition, as seed 002 publishes it).
        attitude: VO attitude source: ``"flight"`` (attitude stream, required), ``"ekf"`` (seed
            002's attitude-and-height EKF) or ``"auto"`` (the stream when present, else the EKF).
        min_inliers: fewer RANSAC inliers rejects a pair (``homography:few-inliers``).
        max_inlier_rms_px: inlier RMS transfer error above this rejects it [px]
            (``homography:large-inlier-rms``).
        max_corner_shift_frac: an image corner moved by more than this fraction of the larger image
            side rejects it (``homography:corner-shift``).
        corner_sigma_px: fixed corner noise [px] (None: from the inlier RMS, below).
        corner_sigma_per_rms: corner sigma per pixel of inlier RMS.
        corner_sigma_floor_px: smallest corner sigma [px].
        frame_tolerance_s: largest time between an image and its keyframe [s].
        latency_s: delay between the exposure of frame j and the arrival of the pair [s].
    """

    vo: HomographyVOOptions = field(default_factory=HomographyVOOptions)
    attitude: str = "auto"
    min_inliers: int = 30
    max_inlier_rms_px: float = 1.0
    max_corner_shift_frac: float = 0.25
    corner_sigma_px: float | None = None
    corner_sigma_per_rms: float = 1.0
    corner_sigma_floor_px: float = 0.05
    frame_tolerance_s: float = 0.005
    latency_s: float = 0.0

    def check(self) -> HomographyFactorOptions:
        if self.attitude not in ("auto", "flight", "ekf"):
            raise FlightDataError(
                f"homography.attitude={self.attitude!r}: expected auto, flight or ekf"
            )
        if self.corner_sigma_px is not None and not self.corner_sigma_px > 0:
            raise FlightDataError(
                f"homography.corner_sigma_px={self.corner_sigma_px}: expected > 0"
            )
        if not self.corner_sigma_floor_px > 0:
            raise FlightDataError(
                f"homography.corner_sigma_floor_px={self.corner_sigma_floor_px}: expected > 0"
            )
        self.vo.check()
        return self


def homography_options(value: Any) -> HomographyFactorOptions:
    """``GraphOptions.homography`` as options: None -> defaults; a dict (TOML table) by name, its
    ``vo`` entry filling :class:`HomographyVOOptions`."""
    if value is None:
        return HomographyFactorOptions().check()
    if isinstance(value, HomographyFactorOptions):
        return value.check()
    if isinstance(value, dict):
        from fgnav.config import options_from

        # Unknown keys and values of the wrong type (also in its ``vo`` table) are one error
        # naming them (they were a TypeError or a cv2.error in the VO).
        opts = options_from(HomographyFactorOptions, value, "homography")
        return opts.check()
    raise FlightDataError(
        f"GraphOptions.homography: expected HomographyFactorOptions, a table or None, got "
        f"{type(value).__name__}"
    )


def homography_available(flight: Flight) -> bool:
    """True when the flight has what the homography factors need: images with intrinsics, a
    rangefinder (metric height) and an IMU (attitude for the VO)."""
    if flight.images is None or flight.range is None or flight.imu is None:
        return False
    return flight.images.camera is not None or flight.calib.camera is not None


def resolve_use_homography(flight: Flight, use_homography: bool | None, use_range: bool) -> bool:
    """``GraphOptions.use_homography``: None ("auto") is True when the flight has images, a
    rangefinder that the graph uses, and an IMU; an explicit value is kept."""
    if use_homography is None:
        return bool(use_range) and homography_available(flight)
    return bool(use_homography)


# ----------------------------------------------------------------------------------------------
# Front-end (run once per flight)
# ----------------------------------------------------------------------------------------------

_VO_CACHE: weakref.WeakKeyDictionary[Flight, dict[tuple, tuple[VOResult, float]]] = (
    weakref.WeakKeyDictionary()
)


def run_homography_frontend(
    flight: Flight, options: HomographyFactorOptions | None = None
) -> tuple[VOResult, float]:
    """The homography VO of ``flight`` and its wall time [s], computed once per flight object and
    (VO options, attitude source); later calls return the cached result (time of the first run).

    Raises:
        FlightDataError: no images/intrinsics, no IMU, ``attitude="flight"`` without an attitude
            stream, or no usable height.
    """
    o = (options or HomographyFactorOptions()).check()
    key = (o.vo, o.attitude)
    per_flight = _VO_CACHE.setdefault(flight, {})
    if key in per_flight:
        return per_flight[key]
    from fgnav.frontends.homography_vo import run as run_vo

    t0 = time.perf_counter()
    if flight.images is None:
        raise FlightDataError(f"{flight.name}: homography factors need an images stream")
    attitude = flight.attitude
    source = "flight"
    if o.attitude == "ekf" or (o.attitude == "auto" and attitude is None):
        from fgnav.frontends.attitude_ekf import run_attitude_ekf

        if flight.imu is None:
            raise FlightDataError(f"{flight.name}: the VO attitude EKF needs an IMU stream")
        attitude = run_attitude_ekf(flight).attitude_series()
        source = "ekf"
    elif attitude is None:
        raise FlightDataError(
            f"{flight.name}: homography.attitude='flight' but the flight has no attitude stream"
        )
    vo = run_vo(flight, attitude=attitude, options=o.vo)
    wall = time.perf_counter() - t0
    log.info(
        "%s: homography VO (attitude from %s) in %.2f s: %d of %d pairs valid",
        flight.name,
        source,
        wall,
        vo.counts.get("valid_pairs", 0),
        vo.counts.get("pairs", 0),
    )
    per_flight[key] = (vo, wall)
    return vo, wall


def clear_frontend_cache() -> None:
    """Forget every cached VO result."""
    _VO_CACHE.clear()


# ----------------------------------------------------------------------------------------------
# Gating and pairs
# ----------------------------------------------------------------------------------------------


def gate_pair(
    H: np.ndarray,
    num_inliers: int,
    inlier_rms_px: float,
    image_size: tuple[int, int],
    options: HomographyFactorOptions,
) -> str:
    """Reason a VO pair is not used (``""``: use it).

    Args:
        H: (3, 3) homography image i -> image j [px].
        num_inliers: RANSAC inliers.
        inlier_rms_px: RMS transfer error of the inliers [px].
        image_size: ``(width, height)`` [px].
        options: gate thresholds.
    """
    if not np.all(np.isfinite(H)):
        return "non-finite"
    if num_inliers < options.min_inliers:
        return "few-inliers"
    if not inlier_rms_px <= options.max_inlier_rms_px:
        return "large-inlier-rms"
    H = np.asarray(H, float)
    if H[2, 2] == 0.0:
        return "corner-at-infinity"
    corners = image_corners(image_size)
    q = corners @ (H / H[2, 2]).T
    if np.any(q[:, 2] <= MIN_CORNER_W_REL * np.max(np.abs(q))):
        return "corner-at-infinity"
    shift = np.linalg.norm(q[:, :2] / q[:, 2:3] - corners[:, :2], axis=1)
    if np.max(shift) > options.max_corner_shift_frac * max(image_size):
        return "corner-shift"
    return ""


def gate_measurement(
    m: HomographyMeasurement, image_size: tuple[int, int], options: HomographyFactorOptions
) -> str:
    """Reason one VO pair measurement (e.g. from :class:`HomographyVoStage`, frame by frame) is
    not used: ``vo-<reason>`` when the VO rejected it, else :func:`gate_pair`'s; ``""``: use it."""
    if not m.valid:
        return "vo-" + m.reason.replace("_", "-")
    return gate_pair(m.H, m.num_inliers, m.inlier_rms_px, image_size, options)


@dataclass(frozen=True)
class HomographyPair:
    """One homography factor's measurement: frames ``frame_i -> frame_j`` on keyframes
    ``keyframe_i -> keyframe_j``.

    Attributes:
        frame_i, frame_j: image indices.
        keyframe_i, keyframe_j: keyframe indices.
        t_j: time of frame j [s].
        H: (3, 3) homography image i -> image j [px] (``H[2, 2] = 1``).
        num_inliers: smallest inlier count of the composed VO pairs.
        inlier_rms_px: root sum of squares of their inlier RMS [px].
        links: number of VO pairs composed (1: consecutive frames).
    """

    frame_i: int
    frame_j: int
    keyframe_i: int
    keyframe_j: int
    t_j: float
    H: np.ndarray
    num_inliers: int
    inlier_rms_px: float
    links: int


class HomographyFactors:
    """Homography factors of one flight (see module docstring).

    Args:
        flight: the flight (images with intrinsics, calibration ``body_T_cam``).
        options: factor options (None: defaults).
        skip: ``skip(reason, n)`` records unused measurements (the builder's ``_skip``); reasons
            are prefixed ``homography:``.
        vo: the VO output to use (e.g. ``HomographyVoStage.result()`` of frames fed one at a
            time); None: :func:`run_homography_frontend` over the flight.
    """

    def __init__(
        self,
        flight: Flight,
        options: HomographyFactorOptions | None = None,
        skip: Callable[[str, int], None] | None = None,
        vo: VOResult | None = None,
    ) -> None:
        self.options = (options or HomographyFactorOptions()).check()
        self._skip = skip or (lambda reason, n=1: None)
        if vo is None:
            self.vo, self.vo_time_s = run_homography_frontend(flight, self.options)
        else:
            self.vo, self.vo_time_s = vo, float(vo.estimate.runtime_s)
        images = flight.images
        cam = images.camera if images.camera is not None else flight.calib.camera
        self.K = np.asarray(cam.K, float)
        self.image_size = (int(cam.width), int(cam.height))
        self.body_T_cam = np.asarray(flight.calib.body_T_cam, float)
        self.image_t = np.asarray(images.t, float)
        self.counts: Counter[str] = Counter()
        # 1. Gate every VO pair; keep (frame_i, frame_j, H, inliers, rms) of the good ones.
        self.links: list[tuple[int, int, np.ndarray, int, float]] = []
        for m in self.vo.measurements:
            reason = gate_measurement(m, self.image_size, self.options)
            if reason:
                self.counts[reason] += 1
                self._skip(f"homography:{reason}", 1)
                continue
            self.links.append(
                (
                    m.index_i,
                    m.index_j,
                    np.asarray(m.H, float),
                    m.num_inliers,
                    float(m.inlier_rms_px),
                )
            )
        self.counts["vo-pairs"] = len(self.vo.measurements)
        self.counts["gated-pairs"] = len(self.links)
        self.pairs: list[HomographyPair] = []
        self._by_keyframe: dict[int, list[int]] = {}

    def anchor_times(
        self, priority_t: np.ndarray | None = None, min_gap_s: float = 0.0
    ) -> np.ndarray:
        """Sorted image times of the frames of the gated pairs [s] (keyframe anchors).

        Args:
            priority_t: times that keep their keyframes first (SLAM frames): an image closer
                than ``min_gap_s`` to one of them, but not at the same time (within
                ``frame_tolerance_s``), is left out, because the keyframe policy keeps only the
                earlier of two anchors closer than its minimum gap. Its pairs are then composed
                across it, or counted as ``homography:no-keyframe``.
            min_gap_s: that minimum gap [s].
        """
        frames = sorted({f for i, j, *_ in self.links for f in (i, j)})
        t = self.image_t[np.asarray(frames, int)] if frames else np.array([])
        if priority_t is None or len(priority_t) == 0 or len(t) == 0:
            return t
        p = np.sort(np.asarray(priority_t, float))
        n = np.clip(np.searchsorted(p, t), 1, len(p) - 1) if len(p) > 1 else np.zeros(len(t), int)
        d = np.abs(p[n] - t)
        if len(p) > 1:
            d = np.minimum(d, np.abs(p[n - 1] - t))
        keep = (d <= self.options.frame_tolerance_s) | (d >= min_gap_s)
        return t[keep]

    def associate(self, t_kf: np.ndarray) -> None:
        """Pairs between keyframed frames (composing chains across frames without a keyframe)."""
        t_kf = np.asarray(t_kf, float)
        kf_of_frame: dict[int, int] = {}
        if len(t_kf):
            idx = np.clip(np.searchsorted(t_kf, self.image_t), 1, len(t_kf) - 1)
            idx = np.where(
                np.abs(t_kf[idx - 1] - self.image_t) <= np.abs(t_kf[idx] - self.image_t),
                idx - 1,
                idx,
            )
            if len(t_kf) == 1:
                idx = np.zeros(len(self.image_t), int)
            ok = np.abs(t_kf[idx] - self.image_t) <= self.options.frame_tolerance_s
            kf_of_frame = {int(f): int(idx[f]) for f in np.flatnonzero(ok)}
        self.pairs = []
        start: int | None = None
        chain: list[tuple[int, int, np.ndarray, int, float]] = []

        def drop_chain() -> None:
            if chain:
                self.counts["no-keyframe"] += len(chain)
                self._skip("homography:no-keyframe", len(chain))

        for link in self.links:
            i, j = link[0], link[1]
            if start is None or not chain or chain[-1][1] != i:
                drop_chain()
                chain = []
                start = i if i in kf_of_frame else None
                if start is None:
                    self.counts["no-keyframe"] += 1
                    self._skip("homography:no-keyframe", 1)
                    continue
            chain.append(link)
            if j in kf_of_frame and kf_of_frame[j] != kf_of_frame[start]:
                H = np.eye(3)
                for _, _, Hl, _, _ in chain:
                    H = Hl @ H
                self.pairs.append(
                    HomographyPair(
                        frame_i=start,
                        frame_j=j,
                        keyframe_i=kf_of_frame[start],
                        keyframe_j=kf_of_frame[j],
                        t_j=float(self.image_t[j]),
                        H=H / H[2, 2],
                        num_inliers=min(c[3] for c in chain),
                        inlier_rms_px=float(np.sqrt(sum(c[4] ** 2 for c in chain))),
                        links=len(chain),
                    )
                )
                start, chain = j, []
        drop_chain()
        self._by_keyframe = {}
        for n, p in enumerate(self.pairs):
            self._by_keyframe.setdefault(p.keyframe_j, []).append(n)
        self.counts["factors"] = len(self.pairs)
        self.counts["composed"] = sum(1 for p in self.pairs if p.links > 1)

    def sigma_px(self, pair: HomographyPair) -> float:
        """Corner noise of a pair [px] (module docstring, step 3)."""
        o = self.options
        if o.corner_sigma_px is not None:
            return float(o.corner_sigma_px)
        return float(max(o.corner_sigma_floor_px, o.corner_sigma_per_rms * pair.inlier_rms_px))

    def arrival(self, pair: HomographyPair) -> float:
        return pair.t_j + self.options.latency_s

    def stream_rows(self) -> list[tuple[float, int, str, int]]:
        """``(arrival, keyframe_j, "homography", pair index)`` of every pair (fixed-lag stream)."""
        return [(self.arrival(p), p.keyframe_j, "homography", n) for n, p in enumerate(self.pairs)]

    def factors_at(
        self,
        k: int,
        ground_key: Callable[[int], int],
        robust: Callable[[gtsam.noiseModel.Base], gtsam.noiseModel.Base],
    ) -> list[tuple[float, gtsam.NonlinearFactor, tuple[int, ...]]]:
        """``(arrival, factor, keys)`` of the pairs ending at keyframe k.

        Args:
            k: keyframe index (frame j's).
            ground_key: ground-height key of a keyframe index (the segment of camera i's frame).
            robust: wraps the Gaussian noise in the graph's robust kernel.
        """
        out = []
        for n in self._by_keyframe.get(k, []):
            p = self.pairs[n]
            gk = ground_key(p.keyframe_i)
            noise = robust(gtsam.noiseModel.Isotropic.Sigma(8, self.sigma_px(p)))
            fac = make_homography_factor(
                X(p.keyframe_i),
                X(p.keyframe_j),
                gk,
                p.H,
                self.K,
                self.body_T_cam,
                self.image_size,
                noise,
            )
            out.append((self.arrival(p), fac, (X(p.keyframe_i), X(p.keyframe_j), gk)))
        return out

    def initial_positions(self, t_kf: np.ndarray) -> np.ndarray | None:
        """VO dead-reckoned body positions interpolated to ``t_kf`` (held at the ends), or None
        when the VO posed fewer than two frames (initial values only: non-causal)."""
        traj = self.vo.estimate.trajectory
        if len(traj) < 2:
            return None
        return np.column_stack([np.interp(t_kf, traj.t, traj.world_t_body[:, a]) for a in range(3)])

    def report(self) -> dict[str, Any]:
        """Counts of the VO pairs, gates and factors, and the VO's wall time."""
        return {
            "counts": dict(self.counts),
            "vo_counts": dict(self.vo.counts),
            "vo_time_s": float(self.vo_time_s),
            "median_sigma_px": float(np.median([self.sigma_px(p) for p in self.pairs]))
            if self.pairs
            else None,
        }
