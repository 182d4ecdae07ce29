"""Run the front-ends a smoother run asks for and merge their priors (DESIGN.md section 5).

``frontend_priors(flight, sources)`` is what ``fgnav batch/online --priors ...`` and the
``[priors]`` config table call. Sources:

* ``"ml-scale"``: seed 004's closed-form maximum-likelihood SLAM scale per session, from vertical
  SLAM/rangefinder displacement pairs (needs ``slam`` and ``range``) -> initial value and prior of
  each session's scale.
* ``"observer"``: seed 000's I&I observer (full kinematics, SLAM axes aligned by attitude; needs
  ``imu``, ``slam``, ``range`` and a calibrated drag coefficient) -> velocity priors only: the
  observer has no covariance, and its scale is unobservable without horizontal acceleration (on
  the ``vertical`` flight it ends at 0.3 % of the truth), so a scale prior from it with a
  caller-set sigma could be confidently wrong.

The attitude the front-ends need is the flight's attitude stream when it has one, else seed 002's
attitude EKF run on the IMU (and rangefinder, yaw when present).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import interpolate_quat_wxyz
from fgnav.datasets.types import Flight
from fgnav.frontends.attitude_ekf import run_attitude_ekf
from fgnav.frontends.priors import (
    FrontendPriors,
    combine_priors,
    priors_from_observer,
    priors_from_scale,
)

log = logging.getLogger(__name__)

PRIOR_SOURCES = ("ml-scale", "observer")
"""Front-ends that can feed the smoother (see the module docstring)."""

ML_SCALE_SIGMAS = (0.015, 0.02)
"""Displacement noises ``(SLAM units, m)`` of the vertical scale pairs: SLAM position noise of
~1 cm at scale ~1 at both ends; rangefinder height after the vertical filter ~2 cm
(scripts/reproduce_seed004.py uses the same)."""


def _attitude_at(flight: Flight, t: np.ndarray) -> np.ndarray:
    if flight.attitude is not None:
        att = flight.attitude
    else:
        att = run_attitude_ekf(flight).attitude_series()
    return interpolate_quat_wxyz(att.t, att.world_q_body_wxyz, np.asarray(t, float))


def _require(flight: Flight, source: str, streams: Sequence[str]) -> None:
    missing = [s for s in streams if getattr(flight, s) is None]
    if missing:
        raise FlightDataError(
            f"{flight.name}: front-end prior '{source}' needs the {', '.join(missing)} stream(s)"
        )


def ml_scale_priors(flight: Flight) -> FrontendPriors:
    """Seed 004's closed-form scale per SLAM session from vertical displacement pairs."""
    from fgnav.frontends.ii_observer import vertical_velocity_from_range
    from fgnav.frontends.scale_ml import (
        MLScaleOptions,
        PairOptions,
        estimate_scale,
        scale_pairs_from_flight,
    )

    _require(flight, "ml-scale", ("imu", "slam", "range"))
    vv = vertical_velocity_from_range(flight, _attitude_at(flight, flight.imu.t))
    pairs = scale_pairs_from_flight(
        flight,
        _attitude_at(flight, flight.slam.t),
        height=(vv.t, vv.height),
        options=PairOptions(components="vertical"),
    )
    sx, sy = ML_SCALE_SIGMAS
    return priors_from_scale(estimate_scale(pairs, MLScaleOptions(sigma_slam=sx, sigma_metric=sy)))


def observer_priors(flight: Flight, drag_k: Sequence[float] | None = None) -> FrontendPriors:
    """Velocity and scale priors from seed 000's I&I observer (``drag_k`` calibrated: argument,
    else ``flight.meta["drag_k"]``)."""
    from fgnav.frontends.ii_observer import IIObserverOptions, run_ii_observer

    _require(flight, "observer", ("imu", "slam", "range"))
    k = drag_k if drag_k is not None else flight.meta.get("drag_k")
    if k is None:
        raise FlightDataError(
            f"{flight.name}: front-end prior 'observer' needs a calibrated drag coefficient "
            "(flight.meta['drag_k'] or [priors] drag_k)"
        )
    result = run_ii_observer(
        flight,
        IIObserverOptions(kinematics="full", drag_k=tuple(float(x) for x in np.atleast_1d(k))),
        world_q_body_wxyz=_attitude_at(flight, flight.imu.t),
        align_slam_axes=True,
    )
    return dataclasses.replace(
        priors_from_observer(result), slam_scale={}, slam_scale_sigma={}, slam_axis_scale={}
    )


def frontend_priors(
    flight: Flight, sources: Sequence[str], drag_k: Sequence[float] | None = None
) -> FrontendPriors | None:
    """Run the front-ends named in ``sources`` (``PRIOR_SOURCES``) and merge their priors;
    None for no sources. Unknown names or missing streams raise :class:`FlightDataError`."""
    unknown = [s for s in sources if s not in PRIOR_SOURCES]
    if unknown:
        raise FlightDataError(f"unknown front-end prior(s) {unknown}; valid: {list(PRIOR_SOURCES)}")
    parts = []
    for source in sources:
        part = ml_scale_priors(flight) if source == "ml-scale" else observer_priors(flight, drag_k)
        log.info("front-end priors from %s: scale %s", source, part.slam_scale)
        parts.append(part)
    return combine_priors(*parts) if parts else None
