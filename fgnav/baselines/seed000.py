"""Seed 000 baseline: the Immersion-and-Invariance observer alone (Gomez-Casasola &
Rodriguez-Cortes, ../shared/seeds/000_*.txt, eqs. 13-41).

The observer (:mod:`fgnav.frontends.ii_observer`) estimates the horizontal body velocity ``eta``
(eq. 23) from the accelerometer's rotor-drag model (eq. 3) and the per-axis SLAM scale
``xi = (kx, ky)`` (eq. 41) from the SLAM positions ``y2 = diag(K) X_h`` (eq. 4). This baseline
reports, as the paper does, positions ``x, y = y2 / xi`` (the SLAM position divided by the scale
estimate, predicted between SLAM samples), the rangefinder height for ``z`` (filtered with the
vertical accelerometer, which also gives the observer's ``y5``), the velocity
``world_R_body [eta; w]`` and the attitude it was given (the flight's AHRS stream). It is a thin,
documented wrapper around :func:`fgnav.frontends.ii_observer.run_ii_observer` that checks the
flight first and names any missing input.

Inputs: ``imu`` (specific force and body rate), ``slam`` (positions; tracking-lost samples are
skipped and counted by the observer; a new session restarts the scale), ``attitude``
(``y3``), ``range`` (height and ``y5``), and the drag coefficient ``mu/m`` per axis [1/s]
(``Seed000Options.drag_k`` or ``flight.meta["drag_k"]``; the paper takes it as known).

Frames: world z up, body FLU (fgnav's; the paper's z-down equations are converted in the
front-end). The paper's model has the SLAM axes along the world axes and the camera at the body
origin; ``align_slam_axes`` rotates a similarity SLAM into world axes first (front-end option).

Not modelled (see the front-end): accelerometer bias, wind, camera lever arm, covariances (the
observer has none, so ``pose_cov`` is None).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.types import Flight
from fgnav.estimate import Estimate
from fgnav.frontends.ii_observer import (
    IIObserverOptions,
    VerticalFilterOptions,
    run_ii_observer,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Seed000Options:
    """Options of :func:`run_seed000`.

    Attributes:
        observer: gains, initial values and kinematics variant of the I&I observer (default: the
            paper's gains 7 and 8, ``kinematics="published"``).
        drag_k: ``mu/m`` per body axis ``(kx, ky)`` [1/s]; None: ``flight.meta["drag_k"]``
            (else ``observer.drag_k``).
        vertical: the rangefinder/accelerometer vertical filter giving height and ``y5``.
        align_slam_axes: rotate each SLAM session into world axes first (needed when the SLAM
            frame is not aligned with the world, i.e. any similarity SLAM; the paper's model and
            the simulated ``circle`` flight have aligned axes).
    """

    observer: IIObserverOptions = field(default_factory=IIObserverOptions)
    drag_k: tuple[float, float] | None = None
    vertical: VerticalFilterOptions = field(default_factory=VerticalFilterOptions)
    align_slam_axes: bool = False


REQUIRED_STREAMS = ("imu", "slam", "attitude", "range")
"""Streams the observer baseline needs (eq. 3: imu; eq. 4: slam; y3: attitude; y5: range)."""


def check_flight(flight: Flight, options: Seed000Options | None = None) -> None:
    """Raise :class:`FlightDataError` naming every missing input of the seed 000 baseline."""
    options = options or Seed000Options()
    flight.require_streams(REQUIRED_STREAMS, "the seed-000 I&I observer baseline")
    if (
        options.drag_k is None
        and options.observer.drag_k is None
        and flight.meta.get("drag_k") is None
    ):
        raise FlightDataError(
            f"{flight.name}: the seed-000 I&I observer needs the drag coefficient mu/m "
            "(Seed000Options.drag_k or flight.meta['drag_k'])"
        )


def run_seed000(flight: Flight, options: Seed000Options | None = None) -> Estimate:
    """Run the I&I observer over a flight; return ``Estimate(method="ii-observer", causal=True)``.

    Rows before the first SLAM sample or the first range reading have no position; they are left
    out and counted in ``info["rows_without_position"]`` (with every other count of the
    observer: SLAM samples used/lost, capped scale steps, range readings used/rejected).
    """
    options = options or Seed000Options()
    check_flight(flight, options)
    obs_opts = options.observer
    if options.drag_k is not None:
        obs_opts = dataclasses.replace(obs_opts, drag_k=tuple(options.drag_k))
    wall0 = time.perf_counter()
    res = run_ii_observer(
        flight, obs_opts, vertical=options.vertical, align_slam_axes=options.align_slam_axes
    )
    est = res.to_estimate()
    info = dict(est.info)
    info["align_slam_axes"] = options.align_slam_axes
    info["wrapper_options"] = dataclasses.asdict(options)
    out = dataclasses.replace(est, runtime_s=time.perf_counter() - wall0, info=info).check()
    log.info(
        "seed 000 observer on %s: scale %s, %d rows without position",
        flight.name,
        info.get("slam_scale_xy"),
        info.get("rows_without_position", 0),
    )
    return out
