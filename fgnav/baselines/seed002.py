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

Not modelled: non-planar ground, gyro bias in the EKF (its option ``estimate_gyro_bias`` is an
fgnav extension, off here as in the paper), time offsets between camera and IMU.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.types import Flight, Trajectory
from fgnav.estimate import Estimate, TimeSeries
from fgnav.frontends.attitude_ekf import AttitudeEkfOptions, run_attitude_ekf
from fgnav.frontends.homography_vo import HomographyVOOptions
from fgnav.frontends.homography_vo import run as run_vo

log = logging.getLogger(__name__)


def _published_vo() -> HomographyVOOptions:
    """The paper's VO: rectified images, OpenCV's free decomposition (Algorithm 2)."""
    return HomographyVOOptions(rectify=True, decomposition="opencv")


@dataclass(frozen=True)
class Seed002Options:
    """Options of :func:`run_seed002`.

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


REQUIRED_STREAMS = ("imu", "range", "images")
"""Streams the baseline needs: IMU (EKF prediction and gravity), range (height: VO scale),
images (VO)."""


def check_flight(flight: Flight) -> None:
    """Raise :class:`FlightDataError` naming every missing input of the seed 002 baseline."""
    flight.require_streams(REQUIRED_STREAMS, "the seed-002 EKF + homography VO baseline")
    if flight.images.camera is None and flight.calib.camera is None:
        raise FlightDataError(f"{flight.name}.images.camera: camera intrinsics missing")


def run_seed002(flight: Flight, options: Seed002Options | None = None) -> Estimate:
    """Run the EKF, then the VO on its attitude and height; return the dead-reckoned estimate
    (module docstring)."""
    options = options or Seed002Options()
    check_flight(flight)
    wall0 = time.perf_counter()
    ekf = run_attitude_ekf(flight, options.ekf)
    ok = np.isfinite(ekf.height)
    if not ok.any():
        raise FlightDataError(
            f"{flight.name}: the seed-002 EKF got no valid range reading (all out of "
            f"[{flight.calib.range_min}, {flight.calib.range_max}] m), so the VO has no scale"
        )
    height = TimeSeries(t=ekf.t[ok], value=ekf.height[ok])
    vo = run_vo(flight, attitude=ekf.attitude_series(), height=height, options=options.vo)
    traj = vo.estimate.trajectory
    p = traj.world_t_body.copy()
    if options.height_from_ekf:
        p[:, 2] = np.interp(traj.t, height.t, height.value) + options.ground_height
    v = np.zeros_like(p)
    if len(p) > 1:
        v[1:] = np.diff(p, axis=0) / np.diff(traj.t)[:, None]
        v[0] = v[1]
    out = Trajectory(
        t=traj.t.copy(),
        world_t_body=p,
        world_q_body_wxyz=traj.world_q_body_wxyz.copy(),
        world_v_body=v,
    )
    series = dict(vo.estimate.series)
    series["ekf_height"] = height
    info = {
        "options": dataclasses.asdict(options),
        "vo_counts": dict(vo.counts),
        "ekf_counts": dict(ekf.counts),
        "rows_without_pose": int(vo.counts.get("frames", len(flight.images)) - len(traj)),
        "ekf_rows_without_height": int((~ok).sum()),
    }
    log.info(
        "seed 002 on %s: %d of %d frames posed; VO %s",
        flight.name,
        len(traj),
        len(flight.images),
        vo.counts,
    )
    return Estimate(
        method="ekf-vo002",
        trajectory=out,
        series=series,
        runtime_s=time.perf_counter() - wall0,
        causal=True,
        info=info,
    ).check()
