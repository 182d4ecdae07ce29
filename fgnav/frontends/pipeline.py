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

Both run as the event-fed :class:`fgnav.frontends.prior_stages.FrontendPriorStage`; the functions
here replay a whole flight into it (the online smoother feeds it as events arrive). The attitude
the front-ends need is the flight's attitude stream when it has one, else seed 002's attitude EKF
run on the IMU (and rangefinder, yaw when present).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import flight_streams, replay
from fgnav.datasets.types import Flight
from fgnav.frontends.prior_stages import (
    ML_SCALE_SIGMAS,
    PRIOR_SOURCES,
    FrontendPriorStage,
    PriorOptions,
    missing_streams_message,
)
from fgnav.frontends.priors import (
    FrontendPriors,
    combine_priors,
    priors_from_observer,
    priors_from_scale,
)

log = logging.getLogger(__name__)

__all__ = [
    "ML_SCALE_SIGMAS",
    "PRIOR_SOURCES",
    "frontend_priors",
    "ml_scale_priors",
    "observer_priors",
]


def replay_stage(flight: Flight, options: PriorOptions) -> FrontendPriorStage:
    """A flight replayed into :class:`FrontendPriorStage` (time order: SLAM poses at their
    capture times, as the whole-flight front-ends always took them), history kept."""
    stage = FrontendPriorStage(flight.calib, options, keep_history=True, name=flight.name)
    streams = flight_streams(flight, ("imu", "attitude", "range", "yaw", "slam"), {"slam": 0.0})
    for ev in replay(streams):
        stage.feed(ev)
    stage.flush()
    return stage


def _require(flight: Flight, source: str, streams: Sequence[str]) -> None:
    missing = [s for s in streams if getattr(flight, s) is None]
    if missing:
        raise FlightDataError(missing_streams_message(flight.name, [source], missing))


def ml_scale_priors(flight: Flight) -> FrontendPriors:
    """Seed 004's closed-form scale per SLAM session from vertical displacement pairs (the
    flight replayed into the ML-scale stage)."""
    _require(flight, "ml-scale", ("imu", "slam", "range"))
    stage = replay_stage(flight, PriorOptions(sources=("ml-scale",)))
    return priors_from_scale(stage.scale_result(), min_pairs=stage.options.min_pairs)


def observer_priors(flight: Flight, drag_k: Sequence[float] | None = None) -> FrontendPriors:
    """Velocity priors from seed 000's I&I observer (``drag_k`` calibrated: argument, else
    ``flight.meta["drag_k"]``; the flight replayed into the observer stage)."""
    _require(flight, "observer", ("imu", "slam", "range"))
    k = drag_k if drag_k is not None else flight.meta.get("drag_k")
    if k is None:
        raise FlightDataError(
            f"{flight.name}: front-end prior 'observer' needs a calibrated drag coefficient "
            "(flight.meta['drag_k'] or [priors] drag_k)"
        )
    k = np.atleast_1d(np.asarray(k, dtype=float))
    opts = PriorOptions(sources=("observer",), drag_k=(float(k[0]), float(k[-1])))
    result = replay_stage(flight, opts).observer_result()
    return dataclasses.replace(
        priors_from_observer(
            result, velocity_sigma=opts.velocity_sigma, settle_time=opts.settle_time
        ),
        slam_scale={},
        slam_scale_sigma={},
        slam_axis_scale={},
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
