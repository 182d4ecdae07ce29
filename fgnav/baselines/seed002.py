"""Seed 002 baseline: attitude-and-height EKF + homography visual odometry with orthogonal
rectification, dead reckoning (Paz & Nesmachnow, ../shared/seeds/002_*.txt, sec. III-B, III-C,
Algorithms 1-2) -- the paper's "double coupling" as published.

1. The ``[q0 q1 q2 q3 h]`` EKF (:mod:`fgnav.frontends.attitude_ekf`; eqs. 11-21): gyro
   prediction, accelerometer gravity update (eq. 16), yaw ``[cos, sin]`` update (eq. 19, when the
   flight has a yaw stream), tilted-rangefinder height update (eq. 21). Its attitude rectifies the
   images and its height ``h`` gives the VO its metric scale (first coupling).
2. Homography VO (:mod:`fgnav.frontends.homography_vo`; Algorithms 1-2) on the downward camera:
   each image warped to a level, straight-down virtual camera by the EKF attitude (sec. III-C),
   Shi-Tomasi corners, pyramidal Lucas-Kanade, RANSAC homography, OpenCV decomposition (the
   paper's), metric translation ``(t/d) * camera height``; dead reckoning (eqs. 9-10) with roll
   and pitch from the EKF and the yaw integrated from vision (second coupling).

Output, ``Estimate(method="ekf-vo002", causal=True)`` at the posed image times:

* x, y: the VO's dead-reckoned position (eqs. 9-10), starting at the world origin;
* z: the EKF height ``h`` (``height_from_ekf``, default: the paper's system estimates ``h`` in its
  EKF; the dead-reckoned VO z is used otherwise);
* attitude: the VO's (EKF roll and pitch, vision yaw), as dead reckoning gives it;
* ``world_v_body``: backward difference of consecutive posed positions (causal; the paper
  reports positions only, so this is the velocity a user of its output would have);
* no covariance (neither part propagates one to the position).

Needs ``imu`` (EKF), ``range`` (EKF height, hence the VO scale) and ``images`` (with intrinsics);
``yaw`` is used when present. A missing stream raises :class:`FlightDataError` naming it. Every
VO pair rejected, and every EKF update skipped, is counted in ``info``.

Event-fed (DESIGN.md sec. 7): :class:`Seed002Vo` is fed IMU samples, yaw and range readings and
image frames in arrival order (``feed``) and answers with its newest posed frame
(``latest_output``). The EKF runs as a stage
(:class:`fgnav.frontends.attitude_ekf.AttitudeEkfStage`: one estimate per IMU sample) whose
attitude and height go to the VO stage the online smoother runs
(:class:`fgnav.frontends.homography_vo.HomographyVoStage`, :meth:`~fgnav.frontends.homography_vo.
HomographyVoStage.add_inputs`); a frame waits there until the EKF estimates around its time have
come (or ``max_interp_gap_s`` of arrival time has passed), then it is rectified, paired with the
reference frame and dead-reckoned. :func:`run_seed002` replays a flight's events into it.

Not modelled: non-planar ground, gyro bias in the EKF (its option ``estimate_gyro_bias`` is an
fgnav extension, off here as in the paper), time offsets between camera and IMU.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from fgnav.baselines._inputs import Inputs, unused_table
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import (
    Event,
    ImageFrame,
    ImuSample,
    RangeReading,
    YawReading,
    replay_flight,
)
from fgnav.datasets.geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix
from fgnav.datasets.types import Calibration, Flight, Trajectory
from fgnav.estimate import Estimate, TimeSeries
from fgnav.frontends.attitude_ekf import AttitudeEkfOptions, AttitudeEkfStage
from fgnav.frontends.homography_vo import (
    BUFFER_S,
    REJECT_REASONS,
    HomographyVOOptions,
    HomographyVoStage,
)

log = logging.getLogger(__name__)

#: The VO's counts of frames not posed, and the attitude EKF's of measurements not used
#: (``info["unused"]`` as ``stream:reason``, :mod:`fgnav.baselines._inputs`).
_VO_UNUSED = ("gaps", *REJECT_REASONS)
_EKF_UNUSED = {
    "accel_gated": "imu:accel-gated",
    "imu_late": "imu:late",
    "late": "range+yaw:late",
    "range_out_of_limits": "range:out-of-limits",
    "range_at_min": "range:at-min",
    "range_at_max": "range:at-max",
    "range_tilt": "range:tilted",
    "range_outlier": "range:outlier",
}


def _published_vo() -> HomographyVOOptions:
    """The paper's VO: rectified images, OpenCV's free decomposition (Algorithm 2)."""
    return HomographyVOOptions(rectify=True, decomposition="opencv")


@dataclass(frozen=True)
class Seed002Options:
    """Options of :class:`Seed002Vo`.

    Attributes:
        ekf: options of the ``[q, h]`` EKF.
        vo: options of the homography VO (default: rectified, OpenCV decomposition, as
            published).
        height_from_ekf: report z from the EKF height (True) or from VO dead reckoning.
        ground_height: world z of the ground plane under the vehicle [m], added to the EKF
            height (the EKF estimates the height above ground).
    """

    ekf: AttitudeEkfOptions = field(default_factory=AttitudeEkfOptions)
    vo: HomographyVOOptions = field(default_factory=_published_vo)
    height_from_ekf: bool = True
    ground_height: float = 0.0

    def check(self) -> None:
        """Raise ``ValueError`` on an inconsistent VO option (``[ekf-vo002.vo]``: its rules
        between fields were not checked before the run)."""
        self.vo.check()


REQUIRED_STREAMS = ("imu", "range", "images")
"""Streams the baseline needs: IMU (EKF prediction and gravity), range (height: VO scale),
images (VO)."""


def check_flight(flight: Flight) -> None:
    """Raise :class:`FlightDataError` naming every missing input of the seed 002 baseline."""
    flight.require_streams(REQUIRED_STREAMS, "the seed-002 EKF + homography VO baseline")
    if flight.images.camera is None and flight.calib.camera is None:
        raise FlightDataError(f"{flight.name}.images.camera: camera intrinsics missing")


class Seed002Vo:
    """The attitude-and-height EKF plus homography VO dead reckoning (module docstring),
    event-fed: :meth:`start`, :meth:`feed` in arrival order, :meth:`latest` /
    :meth:`latest_output`, :meth:`close` at the end of the input, :meth:`result`."""

    def __init__(self, options: Seed002Options | None = None) -> None:
        self.opt = options or Seed002Options()

    def start(self, calib: Calibration, name: str = "flight") -> None:
        """Prepare to be fed events of a vehicle with calibration ``calib``."""
        self._calib = calib
        self._name = name
        self._ekf = AttitudeEkfStage(calib, self.opt.ekf, name=name)
        self._vo: HomographyVoStage | None = None  # made at the first frame (its intrinsics)
        self._early: deque = deque()  # the EKF's estimates before it, the last BUFFER_S
        self._ekf_t: list[float] = []  # the EKF's heights (finite), for the result's series
        self._ekf_h: list[float] = []
        self._ekf_no_height = 0
        self._out: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []
        self._t0 = time.perf_counter()
        self._inputs = Inputs("ekf-vo002", name)

    def feed(self, ev: Event) -> None:
        """One event in arrival order (IMU, yaw, range, image; others ignored; a corrupted IMU
        sample is dropped and counted: :mod:`fgnav.baselines._inputs`)."""
        if not self._inputs.take(ev):
            return
        if isinstance(ev, (ImuSample, YawReading, RangeReading)):
            for est in self._ekf.feed(ev):
                h = est.height if math.isfinite(est.height) else None
                if h is None:
                    self._ekf_no_height += 1
                else:
                    self._ekf_t.append(est.t)
                    self._ekf_h.append(h)
                if self._vo is not None:
                    R = quat_wxyz_to_matrix(est.world_q_body_wxyz)
                    self._vo.add_inputs(est.t, est.arrival, R, h)
                    self._took()
                else:
                    early = self._early
                    early.append((est.t, est.arrival, est.world_q_body_wxyz, h))
                    while early[0][1] < est.arrival - BUFFER_S:
                        early.popleft()
        elif isinstance(ev, ImageFrame):
            if self._vo is None:
                self._start_vo(ev)
            self._vo.feed(ev)
            self._took()

    def close(self) -> None:
        """The end of the input: the frames still waiting for EKF estimates are processed
        with what has arrived."""
        if self._vo is not None:
            self._vo.flush()
            self._took()

    def latest(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
        """The newest output (:meth:`latest_output`: this baseline's state is its output)."""
        return self.latest_output()

    @property
    def output_t(self) -> float | None:
        """Time of the newest posed frame (None before the first)."""
        return self._out[-1][0] if self._out else None

    def latest_output(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
        """``(t, world_t_body, world_q_body_wxyz, world_v_body)`` of the newest posed frame, as
        :meth:`result` reports it (the velocity the backward difference from the previous posed
        frame: zero at the first, where :meth:`result` repeats the second); None before."""
        if not self._out:
            return None
        t, p, q, v = self._out[-1]
        return t, p.copy(), q.copy(), v.copy()

    @property
    def ekf_counts(self) -> dict[str, int]:
        """The attitude EKF's updates applied and skipped (``late`` included)."""
        return self._ekf.counts

    @property
    def vo_counts(self) -> dict[str, int]:
        """The VO's frames, pairs and rejections by reason."""
        return dict(self._vo.counts) if self._vo is not None else {}

    # -- steps ------------------------------------------------------------------------------------

    def _start_vo(self, frame: ImageFrame) -> None:
        """The VO stage, with the first frame's intrinsics (else the calibration's), given the
        EKF estimates so far."""
        cam = frame.camera if frame.camera is not None else self._calib.camera
        if cam is None:
            raise FlightDataError(f"{self._name}.images.camera: camera intrinsics missing")
        self._vo = HomographyVoStage(
            self._calib, cam, self.opt.vo, uses_attitude=True, name=self._name
        )
        early, self._early = self._early, deque()
        for t, arrival, q, h in early:
            self._vo.add_inputs(t, arrival, quat_wxyz_to_matrix(q), h)

    def _took(self) -> None:
        """The frames the VO posed because of one event: their outputs."""
        vo = self._vo
        n = len(self._out)
        if vo.n_posed <= n:
            return
        o = self.opt
        for t, R, p, h in vo.posed_since(n):
            p = p.copy()
            if o.height_from_ekf:
                p[2] = h + o.ground_height
            v = np.zeros(3)
            if self._out:
                t0, p0 = self._out[-1][:2]
                v = (p - p0) / (t - t0)
            self._out.append((t, p, matrix_to_quat_wxyz(R), v))

    # -- whole flight -----------------------------------------------------------------------------

    def run(self, flight: Flight) -> Estimate:
        """Replay a flight's IMU, yaw, range and image events in arrival order, then
        :meth:`close`; the estimate."""
        check_flight(flight)
        self.start(flight.calib, flight.name)
        # Ties in arrival: the IMU sample first, then yaw, then range (as the attitude EKF's
        # own replay), then the image.
        for ev in replay_flight(flight, ("imu", "yaw", "range", "images"), named_order=True):
            self.feed(ev)
        self.close()
        return self.result()

    def result(self) -> Estimate:
        """The causal estimate of everything processed so far (module docstring)."""
        if not self._ekf_t:
            c = self._calib
            raise FlightDataError(
                f"{self._name}: the seed-002 EKF got no valid range reading (all out of "
                f"[{c.range_min}, {c.range_max}] m), so the VO has no scale"
            )
        if self._vo is None:
            raise FlightDataError(f"{self._name}: the seed-002 VO got no image")
        vo = self._vo.result(runtime_s=self._vo.busy_s)
        out = self._out
        v = np.array([o[3] for o in out]).reshape(-1, 3)
        if len(out) > 1:
            v[0] = v[1]
        traj = Trajectory(
            t=np.array([o[0] for o in out]),
            world_t_body=np.array([o[1] for o in out]).reshape(-1, 3),
            world_q_body_wxyz=np.array([o[2] for o in out]).reshape(-1, 4),
            world_v_body=v,
        )
        series = dict(vo.estimate.series)
        series["ekf_height"] = TimeSeries(t=np.asarray(self._ekf_t), value=np.asarray(self._ekf_h))
        info = {
            "options": dataclasses.asdict(self.opt),
            "vo_counts": dict(vo.counts),
            "ekf_counts": self.ekf_counts,
            "rows_without_pose": int(vo.counts.get("frames", 0) - len(traj)),
            "ekf_rows_without_height": self._ekf_no_height,
            "unused": unused_table(
                self._inputs.unused,
                {f"images:{k.replace('_', '-')}": vo.counts.get(k, 0) for k in _VO_UNUSED},
                {key: self.ekf_counts.get(k, 0) for k, key in _EKF_UNUSED.items()},
            ),
            **self._inputs.info(("range", "yaw", "images")),
        }
        log.info("seed 002 on %s: %d frames posed; VO %s", self._name, len(traj), vo.counts)
        return Estimate(
            method="ekf-vo002",
            trajectory=traj,
            series=series,
            runtime_s=time.perf_counter() - self._t0,
            causal=True,
            info=info,
        ).check()


def run_seed002(flight: Flight, options: Seed002Options | None = None) -> Estimate:
    """Run the EKF and the VO on its attitude and height over a flight, fed its events
    (:meth:`Seed002Vo.run`); return the dead-reckoned estimate (module docstring)."""
    return Seed002Vo(options).run(flight)
