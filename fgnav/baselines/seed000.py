"""Seed 000 baseline: the Immersion-and-Invariance observer alone (Gomez-Casasola &
Rodriguez-Cortes, ../shared/seeds/000_*.txt, eqs. 13-41).

The observer (:mod:`fgnav.frontends.ii_observer`) estimates the horizontal body velocity ``eta``
(eq. 23) from the accelerometer's rotor-drag model (eq. 3) and the per-axis SLAM scale
``xi = (kx, ky)`` (eq. 41) from the SLAM positions ``y2 = diag(K) X_h`` (eq. 4). This baseline
reports, as the paper does, positions ``x, y = y2 / xi`` (the SLAM position divided by the scale
estimate, predicted between SLAM samples), the rangefinder height for ``z`` (filtered with the
vertical accelerometer, which also gives the observer's ``y5``), the velocity
``world_R_body [eta; w]`` and the attitude it was given (the flight's AHRS stream).

Event-fed (DESIGN.md sec. 7): :class:`Seed000` is fed the measurement events of
:mod:`fgnav.datasets.events` in arrival order (``feed``) and answers with its newest output
(``latest_output``); it runs the front-end stage that also gives the smoother its observer priors
(:class:`fgnav.frontends.prior_stages.FrontendPriorStage`, here with the baseline's options): an
IMU sample is processed once the next one and an attitude sample at or after it have arrived (the
attitude interpolated between the two around it), range readings taken up to it update the
vertical filter first. SLAM poses arrive ``latency`` after their image time: a late pose rolls the
observer back to its image time and the later IMU samples are stepped again
(``slam_history_s``; :class:`fgnav.frontends.ii_observer.IIObserverStepper`), so the state is that
of in-order processing while the outputs already given stay as they were (causal). Without an
attitude sample within ``fgnav.frontends.prior_stages.ATTITUDE_WAIT_S`` of the first IMU sample
the stage runs seed 002's attitude EKF instead (a live link without ``ATTITUDE_QUATERNION``).
:func:`run_seed000` replays a flight's events into it (:meth:`Seed000.run`), after checking the
flight and naming any missing input.

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

import numpy as np

from fgnav.baselines._inputs import Inputs, unused_table
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import Event, replay_flight
from fgnav.datasets.types import Calibration, Flight
from fgnav.estimate import Estimate
from fgnav.frontends.ii_observer import IIObserverOptions, VerticalFilterOptions, drag_k_problem
from fgnav.frontends.prior_stages import FrontendPriorStage, PriorOptions

log = logging.getLogger(__name__)

#: The observer's and its stage's counts of measurements not used (``info["unused"]`` as
#: ``stream:reason``, :mod:`fgnav.baselines._inputs`).
_UNUSED_KEYS = (
    "imu_out_of_order",
    "imu_without_attitude",
    "attitude_out_of_order",
    "slam_before_imu",
    "slam_lost",
    "slam_late",
    "range_late",
    "range_out_of_limits",
    "range_at_min",
    "range_at_max",
    "range_tilt",
    "range_outlier",
)


@dataclass(frozen=True)
class Seed000Options:
    """Options of :class:`Seed000`.

    Attributes:
        observer: gains, initial values and kinematics variant of the I&I observer (default: the
            paper's gains 7 and 8, ``kinematics="published"``).
        drag_k: ``mu/m`` per body axis ``(kx, ky)`` [1/s]; None: ``observer.drag_k``, else (a
            flight's replay) ``flight.meta["drag_k"]``.
        vertical: the rangefinder/accelerometer vertical filter giving height and ``y5``.
        align_slam_axes: rotate each SLAM session into world axes first (needed when the SLAM
            frame is not aligned with the world, i.e. any similarity SLAM; the paper's model and
            the simulated ``circle`` flight have aligned axes).
        slam_history_s: the observer's delay compensation: a SLAM pose arriving up to this late
            [s] is applied at its image time by rolling back and stepping again (0: applied at
            the current time, counted ``slam_late``).
    """

    observer: IIObserverOptions = field(default_factory=IIObserverOptions)
    drag_k: tuple[float, float] | None = None
    vertical: VerticalFilterOptions = field(default_factory=VerticalFilterOptions)
    align_slam_axes: bool = False
    slam_history_s: float = 1.0

    def check(self) -> Seed000Options:
        """Raise ``FlightDataError`` naming a drag coefficient outside
        :data:`~fgnav.frontends.ii_observer.OBSERVER_DRAG_K_RANGE` (the config's ``drag_k``
        bound, [0, 100], is the filters', for which 0 is no drag)."""
        for name, k in (("drag_k", self.drag_k), ("observer.drag_k", self.observer.drag_k)):
            problem = None if k is None else drag_k_problem(k)
            if problem is not None:
                raise FlightDataError(f"Seed000Options.{name}={_fmt(k)}: {problem}")
        return self


def _fmt(k) -> str:
    return "[" + ", ".join(f"{float(v):g}" for v in np.atleast_1d(np.asarray(k, float))) + "]"


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


class Seed000:
    """The I&I observer baseline, event-fed (module docstring): :meth:`start`, :meth:`feed` in
    arrival order, :meth:`latest` / :meth:`latest_output`, :meth:`close` at the end of the input,
    :meth:`result`.

    Args:
        options: the baseline's options; ``drag_k`` (or ``observer.drag_k``) is needed by
            :meth:`start` (:meth:`run` takes a flight's ``meta["drag_k"]`` when neither is set).
    """

    def __init__(self, options: Seed000Options | None = None) -> None:
        self.options = options or Seed000Options()
        self.stage: FrontendPriorStage | None = None

    def start(self, calib: Calibration, name: str = "flight") -> None:
        """Prepare to be fed events of a vehicle with calibration ``calib``."""
        o = self.options.check()
        k = o.drag_k if o.drag_k is not None else o.observer.drag_k
        if k is None:
            raise FlightDataError(
                f"{name}: the seed-000 I&I observer needs the drag coefficient mu/m "
                "(Seed000Options.drag_k)"
            )
        k = np.atleast_1d(np.asarray(k, dtype=float))
        self.name = name
        self.stage = FrontendPriorStage(
            calib,
            PriorOptions(sources=("observer",), drag_k=(float(k[0]), float(k[-1]))),
            keep_history=True,
            name=name,
            observer_options=o.observer,
            align_slam_axes=o.align_slam_axes,
            vertical_options=o.vertical,
            slam_history_s=o.slam_history_s,
        )
        self._t0 = time.perf_counter()
        self._inputs = Inputs("ii-observer", name)

    def feed(self, ev: Event) -> None:
        """One event in arrival order (IMU, attitude, range, SLAM; yaw feeds the attitude EKF
        of a flight without attitude; others are ignored)."""
        if not self._inputs.take(ev):
            return
        self.stage.feed(ev)

    def close(self) -> None:
        """The end of the input: the IMU sample still held (waiting for the next one) is
        processed."""
        self.stage.flush()

    def latest(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
        """The newest output (:meth:`latest_output`: this baseline's state is its output)."""
        return self.latest_output()

    @property
    def output_t(self) -> float | None:
        """Time of the newest processed IMU sample with a position (None before the first
        SLAM pose and range reading)."""
        out = self.latest_output()
        return None if out is None else out[0]

    def latest_output(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
        """``(t, world_t_body, world_q_body_wxyz, world_v_body)`` of the newest processed IMU
        sample, as :meth:`result` reports it: x, y ``y2 / xi``, z the filtered height; None while
        the position is undefined (before the first SLAM pose or range reading)."""
        row = self.stage.latest_row
        if row is None:
            return None
        o, q, h = row
        p = np.array([*o.world_xy, h])
        if o.session < 0 or not np.all(np.isfinite(p)):
            return None
        return o.t, p, np.asarray(q, dtype=float).copy(), np.asarray(o.world_v_body).copy()

    @property
    def counts(self) -> dict[str, int]:
        """The observer's counts (:meth:`result`'s ``info``) with the stage's (events out of
        order, late range readings, IMU samples without attitude)."""
        return {**self.stage.observer_counts(), **self.stage.counts}

    def result(self) -> Estimate:
        """The causal estimate of everything processed so far (``Estimate(method="ii-observer",
        causal=True)``; rows without a position left out and counted in
        ``info["rows_without_position"]``, with every count of the observer and the stage)."""
        res = self.stage.observer_result()
        counts = {**self.stage.observer_counts(), **self.stage.counts}
        unused = unused_table(
            self._inputs.unused,
            {k.replace("_", ":", 1).replace("_", "-"): counts.get(k, 0) for k in _UNUSED_KEYS},
        )
        if not np.all(np.isfinite(res.world_t_body), axis=1).any():
            got = ", ".join(f"{s} {n}" for s, n in sorted(self._inputs.received.items()))
            lost = ", ".join(f"{k} {n}" for k, n in unused.items()) or "none"
            raise FlightDataError(
                f"{self.name}: the I&I observer has no position: it needs a SLAM pose and a "
                f"range reading it can use (received: {got or 'nothing'}; not used: {lost})"
            )
        est = res.to_estimate()
        info = dict(est.info)
        info.update(self.stage.counts)
        info["unused"] = unused
        info.update(self._inputs.info(("slam", "range", "attitude")))
        info["attitude_source"] = self.stage.attitude_mode
        info["align_slam_axes"] = self.options.align_slam_axes
        info["wrapper_options"] = dataclasses.asdict(self.options)
        return dataclasses.replace(est, runtime_s=time.perf_counter() - self._t0, info=info).check()

    def run(self, flight: Flight) -> Estimate:
        """Replay a flight's IMU, attitude, range and SLAM events in arrival order (the SLAM
        poses at their ``latency``), then :meth:`close`; the estimate."""
        check_flight(flight, self.options)
        o = self.options
        if o.drag_k is None and o.observer.drag_k is None:
            k = np.atleast_1d(np.asarray(flight.meta["drag_k"], dtype=float))
            self.options = dataclasses.replace(o, drag_k=(float(k[0]), float(k[-1])))
        self.start(flight.calib, flight.name)
        for ev in replay_flight(flight, ("imu", "attitude", "range", "slam")):
            self.feed(ev)
        self.close()
        return self.result()


def run_seed000(flight: Flight, options: Seed000Options | None = None) -> Estimate:
    """Run the I&I observer over a flight (:meth:`Seed000.run`); return
    ``Estimate(method="ii-observer", causal=True)``.

    Rows before the first SLAM sample or the first range reading have no position; they are left
    out and counted in ``info["rows_without_position"]`` (with every other count of the
    observer: SLAM samples used/lost/delayed, capped scale steps, range readings used/rejected).
    """
    est = Seed000(options).run(flight)
    log.info(
        "seed 000 observer on %s: scale %s, %d rows without position",
        flight.name,
        est.info.get("slam_scale_xy"),
        est.info.get("rows_without_position", 0),
    )
    return est
