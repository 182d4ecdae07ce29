"""Front-end outputs as priors and initial values for the smoother: pure data, no GTSAM.

The front-ends (I&I observer of seed 000, attitude-and-height EKF of seed 002, closed-form ML scale
of seed 004) each give part of a :class:`FrontendPriors`; :func:`combine_priors` merges them. The
graph builder (``fgnav.solvers.graph``) reads the fields it knows:

* ``velocity``: :class:`~fgnav.estimate.TimeSeries` of ``world_v_body`` [m/s], (N, 3), with
  per-axis ``sigma`` [m/s] -> velocity priors / initial values on ``V(k)`` at the nearest keyframe.
* ``slam_scale``: ``{session: s}`` with ``s`` SLAM units per metre (fgnav's ``S`` variable; the
  metric size of a SLAM unit is ``1 / s``), ``slam_scale_sigma`` its standard deviation ->
  initial value and prior of ``S(j)``.
* ``attitude``: :class:`~fgnav.datasets.types.AttitudeSeries` with ``attitude_sigma`` (N, 3) [rad],
  the standard deviation of a body-frame rotation vector (``world_R_body * Exp(dtheta)``, GTSAM's
  Pose3 convention) -> initial rotations / rotation priors of ``X(k)``.
* ``height``: :class:`~fgnav.estimate.TimeSeries` of the body height above ground [m] with sigma.
* ``body_velocity_xy``: the observer's native output ``[u, v]`` (body x, y) [m/s] for factors
  written in body axes; ``slam_axis_scale``: per-axis ``(kx, ky)`` of seed 000's SLAM model.
* ``drag_k``: rotor drag ``mu / m`` [1/s] used by the front-end (a calibration, not an estimate).

Sigmas of deterministic observers (the I&I observer has no covariance) are set by the caller and
documented as such in ``sources``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.types import AttitudeSeries
from fgnav.estimate import TimeSeries
from fgnav.frontends.attitude_ekf import AttitudeHeightResult
from fgnav.frontends.ii_observer import IIObserverResult
from fgnav.frontends.scale_ml import ScaleResult


@dataclass(frozen=True, eq=False)
class FrontendPriors:
    """Priors and initial values from the front-ends (all optional).

    Attributes:
        velocity: ``world_v_body`` [m/s] (N, 3) with ``sigma`` (N, 3).
        body_velocity_xy: horizontal body velocity ``[u, v]`` [m/s] (N, 2) with ``sigma``.
        slam_scale: ``s`` [SLAM units per metre] per SLAM session.
        slam_scale_sigma: standard deviation of ``s`` per session.
        slam_axis_scale: per-axis ``(kx, ky)`` [SLAM units per metre] per session (seed 000).
        attitude: ``world_q_body_wxyz`` over time.
        attitude_sigma: (N, 3) standard deviation of the body rotation vector [rad].
        height: body height above ground [m] (N,) with ``sigma``.
        drag_k: ``mu / m`` per axis [1/s] the front-end assumed.
        sources: provenance of each field, e.g. ``{"velocity": "ii-observer (sigma set: 0.2)"}``.
    """

    velocity: TimeSeries | None = None
    body_velocity_xy: TimeSeries | None = None
    slam_scale: dict[int, float] = field(default_factory=dict)
    slam_scale_sigma: dict[int, float] = field(default_factory=dict)
    slam_axis_scale: dict[int, np.ndarray] = field(default_factory=dict)
    attitude: AttitudeSeries | None = None
    attitude_sigma: np.ndarray | None = None
    height: TimeSeries | None = None
    drag_k: np.ndarray | None = None
    sources: dict[str, str] = field(default_factory=dict)

    def check(self) -> FrontendPriors:
        """Raise :class:`FlightDataError` naming the field on bad shapes or values."""
        for name, width in (("velocity", 3), ("body_velocity_xy", 2), ("height", None)):
            ts = getattr(self, name)
            if ts is None:
                continue
            n = len(ts.t)
            shape = (n,) if width is None else (n, width)
            if ts.value.shape != shape or not np.all(np.isfinite(ts.value)):
                raise FlightDataError(f"FrontendPriors.{name}: expected finite values {shape}")
            if ts.sigma is not None and (ts.sigma.shape != shape or np.any(ts.sigma <= 0)):
                raise FlightDataError(f"FrontendPriors.{name}.sigma: expected positive {shape}")
        if self.attitude is not None:
            self.attitude.check("FrontendPriors.attitude")
            n = len(self.attitude)
            if self.attitude_sigma is None or self.attitude_sigma.shape != (n, 3):
                raise FlightDataError(f"FrontendPriors.attitude_sigma: expected ({n}, 3)")
        for sid, s in self.slam_scale.items():
            if not (np.isfinite(s) and s > 0):
                raise FlightDataError(f"FrontendPriors.slam_scale[{sid}]={s}: expected s > 0")
            sig = self.slam_scale_sigma.get(sid)
            if sig is not None and not sig > 0:
                raise FlightDataError(f"FrontendPriors.slam_scale_sigma[{sid}]={sig}: not > 0")
        return self


def priors_from_observer(
    result: IIObserverResult,
    velocity_sigma: float = 0.2,
    scale_rel_sigma: float = 0.1,
    settle_time: float = 5.0,
    stride: int = 1,
) -> FrontendPriors:
    """Velocity and per-session scale priors from the I&I observer (seed 000).

    Args:
        result: :func:`~fgnav.frontends.ii_observer.run_ii_observer` output.
        velocity_sigma: standard deviation given to each velocity component [m/s] (the observer is
            deterministic; 0.2 m/s covers an accelerometer bias of ~0.08 m/s^2 at ``k = 0.4``).
        scale_rel_sigma: relative standard deviation of the scale prior [-], widened to half the
            gap between ``kx`` and ``ky`` when larger (the graph's ``s`` is one number).
        settle_time: samples earlier than this after the start (and after each SLAM session's
            first sample, for the scale) are left out: the observer has not converged yet [s].
        stride: keep every ``stride``-th sample.
    """
    t = result.t
    keep = np.zeros(len(t), bool)
    keep[::stride] = True
    keep &= t >= t[0] + settle_time
    vel = TimeSeries(
        t=t[keep].copy(),
        value=result.world_v_body[keep].copy(),
        sigma=np.full((int(keep.sum()), 3), float(velocity_sigma)),
    )
    body = TimeSeries(
        t=t[keep].copy(),
        value=result.eta[keep].copy(),
        sigma=np.full((int(keep.sum()), 2), float(velocity_sigma)),
    )
    scale, sigma, axis = {}, {}, {}
    for sid, k in result.final_scale().items():
        rows = np.flatnonzero(result.session == sid)
        if result.t[rows[-1]] - result.t[rows[0]] < settle_time or np.any(k <= 0):
            continue
        s = float(np.mean(k))
        scale[sid] = s
        sigma[sid] = max(scale_rel_sigma * s, 0.5 * float(abs(k[0] - k[1])))
        axis[sid] = k.copy()
    return FrontendPriors(
        velocity=vel,
        body_velocity_xy=body,
        slam_scale=scale,
        slam_scale_sigma=sigma,
        slam_axis_scale=axis,
        drag_k=result.drag_k.copy(),
        sources={
            "velocity": f"ii-observer (sigma set: {velocity_sigma} m/s)",
            "slam_scale": f"ii-observer mean of (kx, ky) (relative sigma set: {scale_rel_sigma})",
        },
    ).check()


def priors_from_scale(result: ScaleResult, min_pairs: int = 3) -> FrontendPriors:
    """SLAM scale priors ``(s, sigma)`` per session from the closed-form ML estimator (seed 004).

    Sessions with fewer than ``min_pairs`` accepted pairs are left out.
    """
    scale, sigma = {}, {}
    for sid, s in result.scale.items():
        hist = result.history.get(sid)
        if hist is None or len(hist) < min_pairs or not (np.isfinite(s) and s > 0):
            continue
        scale[sid] = float(s)
        sigma[sid] = float(result.sigma[sid])
    return FrontendPriors(
        slam_scale=scale,
        slam_scale_sigma=sigma,
        sources={"slam_scale": "ml-scale (Fisher sigma)"},
    ).check()


def priors_from_attitude_ekf(result: AttitudeHeightResult, stride: int = 1) -> FrontendPriors:
    """Attitude (with its EKF sigma) and height priors from the seed 002 EKF.

    Height samples before the first range reading (NaN) are left out.
    """
    idx = np.arange(0, len(result.t), stride)
    att_sigma = np.sqrt(np.maximum(np.diagonal(result.rotation_cov[idx], axis1=1, axis2=2), 0.0))
    h = result.height[idx]
    ok = np.isfinite(h)
    h_sigma = np.sqrt(np.maximum(result.covariance[idx, 4, 4], 1e-12))
    height = (
        TimeSeries(t=result.t[idx][ok].copy(), value=h[ok].copy(), sigma=h_sigma[ok].copy())
        if ok.any()
        else None
    )
    return FrontendPriors(
        attitude=AttitudeSeries(
            t=result.t[idx].copy(), world_q_body_wxyz=result.world_q_body_wxyz[idx].copy()
        ),
        attitude_sigma=np.maximum(att_sigma, 1e-9),
        height=height,
        sources={"attitude": "attitude-ekf (EKF sigma)", "height": "attitude-ekf (EKF sigma)"},
    ).check()


def combine_priors(*parts: FrontendPriors) -> FrontendPriors:
    """Merge priors from several front-ends: series fields from the last part that has them; SLAM
    scale per session from the part with the smallest sigma."""
    out: dict = {}
    scale, sigma, axis, sources = {}, {}, {}, {}
    for p in parts:
        for f in dataclasses.fields(FrontendPriors):
            v = getattr(p, f.name)
            if f.name in ("slam_scale", "slam_scale_sigma", "slam_axis_scale", "sources"):
                continue
            if v is not None:
                out[f.name] = v
        for sid, s in p.slam_scale.items():
            sig = p.slam_scale_sigma.get(sid, np.inf)
            if sid not in scale or sig < sigma.get(sid, np.inf):
                scale[sid] = s
                sigma[sid] = sig
                sources[f"slam_scale[{sid}]"] = p.sources.get("slam_scale", "")
        axis.update(p.slam_axis_scale)
        sources.update({k: v for k, v in p.sources.items() if k != "slam_scale"})
    return FrontendPriors(
        slam_scale=scale,
        slam_scale_sigma={k: v for k, v in sigma.items() if np.isfinite(v)},
        slam_axis_scale=axis,
        sources=sources,
        **out,
    ).check()
