"""The registry of estimation methods ``fgnav compare`` can run on a flight.

Every method takes a :class:`~fgnav.datasets.types.Flight` and a config mapping (the tables of a
TOML ``--config`` file) and returns an :class:`~fgnav.estimate.Estimate`. A :class:`Method` states
the streams it needs (``requires``), the ones it uses when present (``optional``), whether its
output is causal, and where its implementation lives (``"module:function"``). Implementations are
imported only when a method runs, so a missing or broken module makes that one method unavailable
or failed, with the reason, and never stops the others.

Stream names are those of :data:`fgnav.datasets.types.STREAMS` (``imu``, ``attitude``, ``range``,
``yaw``, ``slam``, ``images``, ``flow``); a reference trajectory recorded in a log is ``ref:<name>``
(``ref:px4_ekf2``: the onboard EKF2 estimate of a PX4 ULog).

Config tables read by each method (fields of its options dataclass, unknown keys are errors):

==============  =================================================================
method          tables
==============  =================================================================
batch           ``[graph]``, ``[lm]``, ``[batch]`` (as ``fgnav batch``)
fixed-lag       ``[graph]``, ``[online]`` (as ``fgnav online``)
msf-ekf         ``[msf-ekf]`` (:class:`~fgnav.baselines.msf_ekf.MsfOptions`)
ekf004          ``[ekf004]`` (:class:`~fgnav.baselines.ekf004.Ekf004Options`)
ukf003          ``[ukf003]`` (:class:`~fgnav.baselines.ukf003.Ukf003Options`)
ii-observer     ``[ii-observer]`` (:class:`~fgnav.baselines.seed000.Seed000Options`)
ekf-vo002       ``[ekf-vo002]`` (:class:`~fgnav.baselines.seed002.Seed002Options`)
ekf-flow002     ``[ekf-flow002]`` (:class:`~fgnav.baselines.seed002_flow.Seed002FlowOptions`)
cf-ekf          ``[cf-ekf]`` (:class:`~fgnav.baselines.cf_ekf.CfEkfOptions`)
px4-ekf2        none (the log's own estimate; nothing is run)
==============  =================================================================
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fgnav.datasets.errors import FgnavError, FlightDataError, FlightFormatError
from fgnav.datasets.types import STREAMS, Flight, Trajectory
from fgnav.estimate import Estimate

log = logging.getLogger(__name__)

#: Human names of the streams, used in the reasons a method cannot run.
STREAM_NAMES: dict[str, str] = {
    **{s: s for s in STREAMS},
    "ref:px4_ekf2": "the onboard EKF2 estimate of a PX4 log (reference 'px4_ekf2')",
}

#: Prefix of method names that replay a reference trajectory recorded in the flight.
REFERENCE_PREFIX = "ref:"


class MethodUnavailableError(FgnavError, RuntimeError):
    """A method's implementation cannot be imported, or the flight lacks a stream it needs."""


@dataclass(frozen=True)
class Method:
    """One estimation method of the comparison.

    Attributes:
        name: registry name (``"batch"``, ``"msf-ekf"`` ...).
        description: one line: what it is and where it comes from.
        requires: streams that must all be present (``"imu"``, ``"slam"``, ``"ref:px4_ekf2"``).
        optional: streams used when present.
        causal: True when each output state only uses measurements up to its time.
        implementation: module holding the implementation, imported only when the method runs.
        entry: adapter ``entry(flight, config, progress) -> Estimate`` (reads the method's config
            tables and calls the implementation).
        alignment: trajectory alignment used to score it against truth (``"se3"`` for metric
            estimates, DESIGN.md section 9).
        any_of: alternative stream sets, at least one of which must be present besides
            ``requires`` (the smoothers: ``slam``, or ``images`` with ``range`` for the homography
            and rangefinder factors).
        positions_only: score the positions only (the ``ref:<name>`` rows: another system's
            trajectory whose orientations may be of another body frame, as the EuRoC V1_02
            references'): the orientation-based metrics (RPE, yaw RMSE, NEES) are left out.
    """

    name: str
    description: str
    requires: tuple[str, ...]
    optional: tuple[str, ...]
    causal: bool
    implementation: str
    entry: Callable[[Flight, Mapping[str, Any], bool], Estimate]
    alignment: str = "se3"
    any_of: tuple[tuple[str, ...], ...] = ()
    positions_only: bool = False

    def missing(self, flight: Flight) -> list[str]:
        """The required streams the flight does not have (``[]`` when it can run); for
        ``any_of``, those of the alternative closest to being complete."""
        present = set(flight.streams())
        out = [s for s in self.requires if s not in present]
        if self.any_of:
            gaps = [[s for s in alt if s not in present] for alt in self.any_of]
            if all(gaps):
                # Closest first; on a tie the alternative whose own stream the flight has (a
                # flow deck without its rangefinder needs the range, not a SLAM stream; a
                # stream two alternatives share decides nothing).
                def own(i: int) -> int:
                    others = {s for k, alt in enumerate(self.any_of) if k != i for s in alt}
                    return sum(1 for s in self.any_of[i] if s in present and s not in others)

                n = min(range(len(gaps)), key=lambda i: (len(gaps[i]), -own(i)))
                out += gaps[n]
        return out

    def implementation_problem(self) -> str | None:
        """Why the implementation module cannot be found (None when it exists)."""
        try:
            found = importlib.util.find_spec(self.implementation) is not None
        except ModuleNotFoundError:
            found = False
        if found:
            return None
        return f"implementation {self.implementation} is not available in this version"

    def run(
        self, flight: Flight, config: Mapping[str, Any] | None = None, progress: bool = False
    ) -> Estimate:
        """Run the method on ``flight`` and return its checked estimate, named after the method.

        Raises:
            MethodUnavailableError: a required stream is missing or the implementation is absent.
        """
        missing = self.missing(flight)
        if missing:
            raise MethodUnavailableError(f"{self.name}: {missing_reason(missing)}")
        problem = self.implementation_problem()
        if problem:
            raise MethodUnavailableError(f"{self.name}: {problem}")
        config = dict(config or {})
        if "slam" in self.requires + self.optional and not self.name.startswith("fixed-lag"):
            # (the fixed-lag smoother checks the SLAM file itself: causally on the push engine)
            flight = slam_checked(flight, config, causal=self.causal)
        est = self.entry(flight, config, progress)
        if est.method != self.name:
            est = _renamed(est, self.name)
        return est.check()


def slam_checked(flight: Flight, config: Mapping[str, Any], causal: bool = False) -> Flight:
    """The flight with the SLAM-vs-gyro options of the config's ``[graph]`` table applied, so
    that the filters get the SLAM rotations and clock the smoothers use: over the whole flight
    (:func:`fgnav.datasets.slam_gyro.apply_slam_check`, the batch's), or with ``causal`` each
    pose as decided when it arrives (:func:`~fgnav.datasets.slam_gyro.apply_slam_check_causal`,
    the causal filters': poses before the decision as stated)."""
    from fgnav.datasets.slam_gyro import apply_slam_check, apply_slam_check_causal

    table = config.get("graph", {})
    if not isinstance(table, Mapping) or not table.get("use_slam", True):
        return flight
    return (apply_slam_check_causal if causal else apply_slam_check)(
        flight,
        table.get("slam_rotation", "auto"),
        table.get("slam_time_offset", "report"),
        table.get("slam_extrinsic", "auto"),
        **({} if causal else {"mirror": table.get("slam_mirror", "auto")}),
    )


def _renamed(est: Estimate, name: str) -> Estimate:
    import dataclasses

    return dataclasses.replace(est, method=name)


def _join(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


#: The smoothers need a position or velocity source: monocular SLAM, the downward camera's
#: homographies made metric by the rangefinder (seed 002's sensor set), or optical flow made
#: metric by the rangefinder (a flow deck: the position is dead-reckoned).
SMOOTHER_ALTERNATIVES = (("slam",), ("images", "range"), ("flow", "range"))
#: Streams the smoothers use when the flight has them (besides the IMU they all require).
SMOOTHER_OPTIONAL = ("slam", "attitude", "range", "yaw", "images", "flow")


def smoother_method(
    name: str, description: str, causal: bool, implementation: str, entry: Entry
) -> Method:
    """A factor-graph smoother's :class:`Method`: every smoother has the same stream contract
    (the IMU, one of :data:`SMOOTHER_ALTERNATIVES`, and :data:`SMOOTHER_OPTIONAL` when present)."""
    return Method(
        name,
        description,
        ("imu",),
        SMOOTHER_OPTIONAL,
        causal,
        implementation,
        entry,
        any_of=SMOOTHER_ALTERNATIVES,
    )


def require_streams(name: str, flight: Flight) -> None:
    """Raise :class:`MethodUnavailableError` naming the flight when it lacks the streams method
    ``name`` needs: ``fgnav batch`` and ``fgnav online`` refuse what ``compare`` and ``fleet``
    skip (an IMU-only flight ran to a 14 m online estimate with health "ok-after-recovery", and
    30 LM iterations in batch)."""
    missing = METHODS[name].missing(flight)
    if missing:
        raise MethodUnavailableError(f"{flight.name}: {name}: {missing_reason(missing)}")


def missing_reason(missing: list[str]) -> str:
    """``"needs images; the flight has none"`` for the missing streams."""
    names = [STREAM_NAMES.get(s, s) for s in missing]
    if len(names) == 1:
        return f"needs {names[0]}; the flight has none"
    tail = "neither" if len(names) == 2 else "none of them"
    return f"needs {_join(names)}; the flight has {tail}"


# ----------------------------------------------------------------------------------------------
# Entry points (thin adapters: config tables -> options dataclass -> library call)
# ----------------------------------------------------------------------------------------------


def _options(cls: type, config: Mapping[str, Any], section: str, **overrides) -> Any:
    from fgnav.config import options_from

    table = config_table(config, section)
    # Options built from tables of their own ([graph] for [online] and [batch], [lm] for
    # [batch]): a sub-table or value here was silently replaced by them.
    own = sorted(set(table) & set(overrides))
    if own:
        raise FlightFormatError(
            str(config.get(SOURCE_KEY, "config")),
            f"[{section}]: option(s) {own} are tables of their own: write "
            + ", ".join(f"[{k}]" for k in own)
            + f", not [{section}.{own[0]}] or {own[0]} = ... in [{section}]",
        )
    # Values written in from command-line flags are passed as overrides, so an error names the
    # flag's value as coming from the command line.
    flagged = {k: table.pop(k) for k in config.get(FLAGS_KEY, {}).get(section, ()) if k in table}
    source = str(config.get(SOURCE_KEY, "config"))
    options = options_from(
        cls,
        table,
        source=source,
        section=section,
        elsewhere=tuple(overrides),
        **flagged,
        **overrides,
    )
    # A file names where the value may come from; without one it came from a flag or a default.
    where = f"{source} [{section}]" if SOURCE_KEY in config else f"[{section}]"
    _self_check(options, where, tuple(flagged))
    return options


def config_table(config: Mapping[str, Any], section: str) -> dict[str, Any]:
    """A copy of the table ``section`` of ``config`` (``{}`` when absent); a scalar or a list
    where a table belongs (``graph = 5``) is one error naming the file and the table (it was a
    TypeError)."""
    table = config.get(section, {})
    if not isinstance(table, Mapping):
        from fgnav.config import _kind

        raise FlightFormatError(
            str(config.get(SOURCE_KEY, "config")),
            f"[{section}] must be a table, found {_kind(table)} ({section} = {table!r})",
        )
    return dict(table)


def _self_check(options: Any, where: str, flagged: tuple[str, ...] = ()) -> None:
    """Run an options object's own ``validate()`` or ``check()`` (the rules between fields,
    the choices of a string) now, so that ``fgnav compare`` refuses a bad value before any method
    runs; the error names the file and table."""
    from fgnav.config import OptionValueError

    for name in ("validate", "check"):
        fn = getattr(options, name, None)
        if not callable(fn):
            continue
        required = [
            p
            for p in inspect.signature(fn).parameters.values()
            if p.default is inspect.Parameter.empty
            and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
        ]
        if required:
            continue
        try:
            fn()
        except (FgnavError, ValueError) as e:
            msg = str(e)
            # The options' own messages name the field as ``Class.name=value``.
            if any(f".{name}=" in msg for name in flagged):
                where = "command line"
            raise OptionValueError(f"{where}: {msg}") from None
        return


#: The options class each filter baseline's table fills (module, class).
_BASELINE_OPTIONS = {
    "msf-ekf": ("fgnav.baselines.msf_ekf", "MsfOptions"),
    "ekf004": ("fgnav.baselines.ekf004", "Ekf004Options"),
    "ukf003": ("fgnav.baselines.ukf003", "Ukf003Options"),
    "ii-observer": ("fgnav.baselines.seed000", "Seed000Options"),
    "ekf-vo002": ("fgnav.baselines.seed002", "Seed002Options"),
    "ekf-flow002": ("fgnav.baselines.seed002_flow", "Seed002FlowOptions"),
    "cf-ekf": ("fgnav.baselines.cf_ekf", "CfEkfOptions"),
}


METHOD_TABLES = ("graph", "lm", "batch", "online", "priors", *_BASELINE_OPTIONS)
"""The ``--config`` tables the methods read (``fgnav compare``, ``demo`` and ``fleet`` refuse any
other): the smoothers' ``[graph]``, ``[lm]``, ``[batch]``, ``[online]`` and ``[priors]``, and one
per filter baseline, named after it."""


def check_method_config(config: Mapping[str, Any]) -> None:
    """Build the options of every table of ``config`` without a flight, so that an unknown
    option or a bad value is one error before any method runs (``fgnav compare``, ``demo``,
    ``fleet``; the tables themselves are checked by :func:`fgnav.config.check_tables`).

    Raises:
        FgnavError: the first table with an unknown option or a bad value, named.
    """
    if any(t in config for t in ("graph", "lm", "batch")):
        batch_options(config)
    if "online" in config:
        fixed_lag_options(config)
    if "priors" in config:
        check_priors(config)
    for table, (module, name) in _BASELINE_OPTIONS.items():
        if table in config:
            _options(getattr(importlib.import_module(module), name), config, table)


def check_priors(config: Mapping[str, Any]) -> None:
    """Check the ``[priors]`` table without a flight (names and types of ``sources`` and
    ``drag_k``), so that a bad value is one error before the flight is read."""
    from fgnav.frontends.prior_stages import prior_options

    table = _priors_table(config)
    # Without drag_k in the table the flight's calibration may give it (checked on the run).
    _named_priors(config, prior_options, table, None if "drag_k" in table else (1.0, 1.0))


FLAGS_KEY = "__flags__"
"""Key of a method config that lists, per table, the values written in from command-line flags."""

SOURCE_KEY = "__source__"
"""Key of a method config that names the file it was read from (for error messages)."""


def load_method_config(path: str | Path | None) -> dict[str, Any]:
    """The tables of a ``--config`` file (empty without one), marked with the file's name so
    that option errors name it."""
    from fgnav.config import load_config

    config = load_config(path)
    if path is not None:
        config[SOURCE_KEY] = str(path)
    return config


def with_flags(config: Mapping[str, Any], **tables: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of ``config`` with command-line flags written into their tables; None values (flags
    not given) leave the config's own value, e.g. ``with_flags(cfg, graph={"keyframe_hz": None})``.
    """
    out = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in config.items()}
    marks = out.setdefault(FLAGS_KEY, {})
    for section, flags in tables.items():
        given = {k: v for k, v in flags.items() if v is not None}
        if given:
            table = config_table(out, section)
            out[section] = table
            table.update(given)
            marks[section] = sorted(set(marks.get(section, ())) | set(given))
    return out


def graph_options(config: Mapping[str, Any]):
    """:class:`~fgnav.solvers.graph.GraphOptions` from the ``[graph]`` table."""
    from fgnav.solvers.graph import GraphOptions

    return _options(GraphOptions, config, "graph")


def batch_options(config: Mapping[str, Any]):
    """:class:`~fgnav.solvers.batch.BatchOptions` from ``[graph]``, ``[lm]`` and ``[batch]``."""
    from fgnav.solvers.batch import BatchOptions, LMOptions

    check_priors(config)
    return _options(
        BatchOptions,
        config,
        "batch",
        graph=graph_options(config),
        lm=_options(LMOptions, config, "lm"),
    )


def fixed_lag_options(config: Mapping[str, Any]):
    """:class:`~fgnav.solvers.fixed_lag.FixedLagOptions` from ``[graph]`` and ``[online]``."""
    from fgnav.solvers.fixed_lag import FixedLagOptions

    check_priors(config)
    return _options(FixedLagOptions, config, "online", graph=graph_options(config))


def check_keyframe_count(flight: Flight, graph: Any) -> None:
    """Refuse a keyframe rate that leaves fewer than 2 keyframes on the flight's IMU span (one
    keyframe was "not scored", health ok, exit 0: ``--keyframe-hz 0.01`` on an 8 s flight)."""
    imu = getattr(flight, "imu", None)
    t = getattr(imu, "t", None)
    if t is None or len(t) < 2:
        return  # the solver names a flight without IMU
    span = float(t[-1] - t[0])
    if span * graph.keyframe_hz < 1.0:
        raise FlightDataError(
            f"{flight.name}: keyframe_hz={graph.keyframe_hz:g} leaves fewer than 2 keyframes on "
            f"the flight's {span:.3g} s of IMU; expected keyframe_hz >= {1.0 / span:.3g}"
        )


def check_online_imu(flight: Flight, opts: Any, intervals: bool = True) -> None:
    """Refuse ``[online]`` IMU spans the flight's IMU cannot meet: a ``max_imu_gap_s`` below twice
    its median interval (every interval was a gap: 1e-300 ran 20x longer, ATE 0.65 m vs
    0.005 m, exit 0) and an ``init_imu_s`` longer than its IMU ("produced no state").
    ``intervals`` False: ``flight`` is a streamed flight's outline (first and last samples)."""
    imu = getattr(flight, "imu", None)
    t = getattr(imu, "t", None)
    if t is None or len(t) < 2:
        return  # the solver names a flight without IMU (or the streams are read as replayed)
    dt = float(np.median(np.diff(t)))
    if intervals and dt > 0 and opts.max_imu_gap_s < 2.0 * dt:
        raise FlightDataError(
            f"{flight.name}: max_imu_gap_s={opts.max_imu_gap_s:g} is below twice the flight's "
            f"median IMU interval ({dt:.3g} s): every interval would be a gap; expected "
            f"max_imu_gap_s >= {2.0 * dt:.3g}"
        )
    span = float(t[-1] - t[0])
    if opts.init_imu_s >= span:
        raise FlightDataError(
            f"{flight.name}: init_imu_s={opts.init_imu_s:g} is not shorter than the flight's "
            f"{span:.3g} s of IMU; expected init_imu_s < {span:.3g}"
        )


def run_batch(flight: Flight, config: Mapping[str, Any], progress: bool = False) -> Estimate:
    """The batch smoother (``fgnav batch``) with the ``[graph]``, ``[lm]``, ``[batch]`` and
    ``[priors]`` tables."""
    from fgnav.health import (
        HealthOptions,
        check_batch,
        fixed_flight,
        stuck_range_candidates,
        terrain_steps,
    )
    from fgnav.solvers.batch import solve_batch

    opts = batch_options(config)
    check_keyframe_count(flight, opts.graph)
    priors = frontend_priors(flight, config)
    est = solve_batch(flight, opts, priors=priors, progress=progress)
    health = check_batch(flight, est)
    fixes = health.pop("_fixes")
    candidates = stuck_range_candidates(flight, fixes["stuck_range_t"])
    probe = None
    if candidates:
        fixes["stuck_range_t"], n_stuck, probe = _confirm_stuck_range(
            flight, candidates, fixes, opts, priors
        )
        if n_stuck:
            det = health["detectors"]
            det["range-stuck"] = det.get("range-stuck", 0) + n_stuck
            health["dropped"]["range:stuck"] = len(fixes["stuck_range_t"])
            if fixes["ground_steps_t"]:
                # A stuck run that unfreezes jumps like a step: the steps looked for again
                # without the stuck readings.
                steps = [
                    t
                    for t, _ in terrain_steps(flight, est, HealthOptions(), fixes["stuck_range_t"])
                ]
                if steps != fixes["ground_steps_t"]:
                    probe = None  # solved with the old steps: the fixed flight is solved anew
                fixes["ground_steps_t"] = steps
                if fixes["ground_steps_t"]:
                    det["terrain-step"] = len(fixes["ground_steps_t"])
                else:
                    det.pop("terrain-step", None)
    fixed = fixed_flight(flight, fixes)
    if fixed is not None:
        # The detectors' fixes (SLAM jumps as new sessions, stuck range readings and frozen
        # images dropped): solved once more, the first solve's report kept.
        try:
            est2 = (
                probe
                if probe is not None
                else solve_batch(fixed, opts, priors=priors, progress=progress)
            )
        except FgnavError as e:
            log.warning(
                "%s: batch with the detectors' fixes failed (%s): the first solve kept",
                flight.name,
                e,
            )
            health["resolved"] = f"failed: {e}"
        else:
            log.warning("%s: batch solved again with the detectors' fixes", flight.name)
            second = check_batch(fixed, est2)
            second.pop("_fixes")
            est = est2
            health = {
                **health,
                "status": second["status"],
                "resolved": True,
                "error_per_factor": second["error_per_factor"],
            }
    return _with_priors(_with_info(est, health=health), priors)


def _confirm_stuck_range(flight, runs, fixes, opts, priors):
    """The constant range runs ``runs`` (index runs the batch's detector did not call stuck)
    tested: the flight solved once without their readings (and with the detectors' other
    fixes); a run over which that solve's height moves by more than ``range_stuck_motion_m`` is
    stuck (said as the detector says it), the others keep their readings. Returns the stuck
    readings' times (the detector's and these), the number of runs found stuck here, and the
    probe solve when it is the solve of the fixed flight (every run stuck), else None."""
    from fgnav.health import HealthOptions, confirm_stuck_range, fixed_flight
    from fgnav.solvers.batch import solve_batch

    t = np.asarray(flight.range.t, float)
    declared = fixes["stuck_range_t"]
    test_t = sorted(set(declared).union(*(t[i:j].tolist() for i, j in runs)))
    try:
        est = solve_batch(
            fixed_flight(flight, {**fixes, "stuck_range_t": test_t}), opts, priors=priors
        )
    except FgnavError as e:
        log.warning("%s: the stuck-range test solve failed (%s): readings kept", flight.name, e)
        return declared, 0, None
    stuck = confirm_stuck_range(flight, runs, est)
    r = np.asarray(flight.range.range, float)
    moved = HealthOptions().range_stuck_motion_m
    for i, j in stuck:
        log.warning(
            "%s: health: range-stuck: rangefinder constant at %.3f m from t=%.2f to %.2f s while "
            "the solve without those readings moves by more than %.2f m: readings dropped",
            flight.name,
            r[i],
            t[i],
            t[j - 1],
            moved,
        )
    out = sorted(set(declared).union(*(t[i:j].tolist() for i, j in stuck)))
    return out, len(stuck), est if len(stuck) == len(runs) else None


def run_fixed_lag(
    flight: Flight, config: Mapping[str, Any], progress: bool = False, source: Any = None
) -> Estimate:
    """The online fixed-lag smoother (``fgnav online``) with ``[graph]``, ``[online]`` and
    ``[priors]``. ``source``: the flight opened as streams
    (:func:`fgnav.datasets.native.open_flight_streams`, ``flight`` its outline), for the push
    engine only."""
    from fgnav.solvers.fixed_lag import run_fixed_lag as _run
    from fgnav.solvers.online import replay_online, resolve_engine

    opts = fixed_lag_options(config)
    check_keyframe_count(flight, opts.graph)
    check_online_imu(flight, opts, intervals=source is None)
    engine = resolve_engine(opts)
    if engine == "push":
        if source is None and opts.lagged_output:
            est = _push_output(flight, config, progress, lagged=False)
        else:
            popts = online_prior_options(flight, config)
            est = replay_online(flight, opts, progress=progress, source=source, priors=popts)
        est = _with_info(est, engine=engine)
        return _with_stage_priors(est)
    if source is not None:
        raise MethodUnavailableError("fixed-lag: the prepared engine needs the whole flight")
    priors = frontend_priors(flight, config)
    est = _run(flight, opts, priors=priors, progress=progress)
    est = _with_info(est, engine=engine)
    return _with_priors(est, priors)


def run_fixed_lag_lagged(
    flight: Flight, config: Mapping[str, Any], progress: bool = False
) -> Estimate:
    """The push-API smoother's second output, ``fixed-lag@lag``: each keyframe's state as smoothed
    just before it leaves the window (delayed by the lag; ``[graph]`` and ``[online]``)."""
    return _push_output(flight, config, progress, lagged=True)


#: The output a push-engine replay has not handed out yet: ``(flight, config key, lagged,
#: estimate or error)``. ``fixed-lag`` and ``fixed-lag@lag`` are the two outputs of one run: when
#: a caller asks for the other one next, on the same flight and config (``fgnav compare``), it
#: comes from here and the entry is dropped; any other request replays again.
_PENDING_PUSH: tuple | None = None


def _push_output(flight: Flight, config: Mapping[str, Any], progress: bool, lagged: bool):
    """The causal (``lagged`` False) or the ``fixed-lag@lag`` estimate of a push-engine replay of
    ``flight`` with ``config``; the other output is kept for the next call (see above)."""
    import json

    from fgnav.solvers.online import replay_smoother

    global _PENDING_PUSH
    key = json.dumps(config, sort_keys=True, default=repr)
    pending, _PENDING_PUSH = _PENDING_PUSH, None
    if pending is not None and pending[0] is flight and pending[1:3] == (key, lagged):
        out = pending[3]
    else:
        opts = fixed_lag_options(config)
        check_keyframe_count(flight, opts.graph)
        check_online_imu(flight, opts)
        popts = online_prior_options(flight, config)
        sm = replay_smoother(flight, opts, progress=progress, priors=popts)
        outputs = {}
        for which, get in ((False, sm.result), (True, sm.lagged_result)):
            try:
                outputs[which] = get()
            except FgnavError as e:  # e.g. a run shorter than the lag: no lagged state
                outputs[which] = e
        out = outputs[lagged]
        _PENDING_PUSH = (flight, key, not lagged, outputs[not lagged])
    if isinstance(out, FgnavError):
        raise out
    return out


def online_prior_options(flight: Flight | None, config: Mapping[str, Any]):
    """The ``[priors]`` table as :class:`fgnav.frontends.prior_stages.PriorOptions` for the
    push engine and the live link (None without sources). ``drag_k`` when the table has none:
    the flight's calibration ``flight.meta["drag_k"]`` (never its ground truth)."""
    from fgnav.frontends.prior_stages import (
        PRIOR_STREAMS,
        missing_streams_message,
        prior_options,
    )

    table = _priors_table(config)
    meta = getattr(flight, "meta", None)
    k = meta.get("drag_k") if isinstance(meta, dict) else None
    opts = _named_priors(config, prior_options, table, k)
    if opts is not None and flight is not None:
        # A configuration fact (which streams the log has), as the whole-flight front-ends say.
        missing = [n for n in PRIOR_STREAMS if getattr(flight, n, None) is None]
        if missing:
            raise FlightDataError(missing_streams_message(flight.name, opts.sources, missing))
    return opts


def _named_priors(config: Mapping[str, Any], make: Callable, table: dict, drag_k: Any) -> Any:
    """``make(table, drag_k=drag_k)`` (the ``[priors]`` options), its error naming the config
    file (when there is one: ``--priors`` alone has none) and the table once."""
    try:
        return make(table, drag_k=drag_k)
    except FlightFormatError:
        raise
    except FgnavError as e:
        msg = str(e) if str(e).startswith("[priors]") else f"[priors]: {e}"
        if SOURCE_KEY in config:
            raise FlightFormatError(str(config[SOURCE_KEY]), msg) from None
        raise FlightDataError(msg) from None


def _priors_table(config: Mapping[str, Any]) -> dict[str, Any]:
    table = config_table(config, "priors")
    unknown = sorted(set(table) - {"sources", "drag_k"})
    if unknown:
        raise FlightFormatError(
            str(config.get(SOURCE_KEY, "config")),
            f"[priors]: unknown option(s) {unknown}; valid: ['drag_k', 'sources']",
        )
    return table


def _with_stage_priors(est: Estimate) -> Estimate:
    """``info["frontend_priors"]`` of the push engine: the stage's sources and the ML scale it
    had at the end (causal: fed in arrival order)."""
    rep = est.info.get("frontend_prior_stage")
    if not rep:
        return est
    return _with_info(
        est,
        frontend_priors={
            "sources": {s: "stage fed in arrival order (causal)" for s in rep["sources"]},
            "slam_scale": {int(k): v["scale"] for k, v in rep["ml_scale"].items()},
        },
    )


def frontend_priors(flight: Flight, config: Mapping[str, Any]):
    """Front-end priors of the smoothers from the ``[priors]`` table (``sources``, ``drag_k``);
    None when no source is named."""
    from fgnav.frontends.pipeline import frontend_priors as _priors
    from fgnav.frontends.prior_stages import prior_drag_k, prior_sources

    table = _priors_table(config)
    sources = _named_priors(config, lambda t, drag_k: prior_sources(t.get("sources")), table, None)
    drag_k = _named_priors(config, lambda t, drag_k: prior_drag_k(t.get("drag_k")), table, None)
    return _priors(flight, sources, drag_k=drag_k)


def _with_priors(est: Estimate, priors: Any) -> Estimate:
    """``info["frontend_priors"]`` (sources and SLAM scale) when front-end priors were used."""
    if priors is None:
        return est
    return _with_info(
        est, frontend_priors={"sources": priors.sources, "slam_scale": priors.slam_scale}
    )


def run_msf_ekf(flight: Flight, config: Mapping[str, Any], progress: bool = False) -> Estimate:
    """The MSF-style error-state EKF with ``[msf-ekf]``."""
    from fgnav.baselines.msf_ekf import MsfOptions, run_msf

    return run_msf(flight, _options(MsfOptions, config, "msf-ekf"))


def run_ekf004(flight: Flight, config: Mapping[str, Any], progress: bool = False) -> Estimate:
    """Seed 004's EKF with ``[ekf004]``; like the seed-000 observer it takes the drag coefficient
    as calibrated (:func:`calibrated_drag_k`). Without an attitude stream, roll and pitch are
    estimated from the IMU and the scale comes from closed-form IMU-SLAM fits (stated in
    ``info["compare_defaults"]``, shown in the report)."""
    from fgnav.baselines.ekf004 import ATTITUDE_SOURCES, Ekf004Options
    from fgnav.baselines.ekf004 import run_ekf004 as _run

    table = config_table(config, "ekf004")
    defaults = calibrated_drag_k(flight, table)
    fields = {k: v for k, v in defaults.items() if k != "drag_k_source"}
    est = _run(flight, _options(Ekf004Options, {"ekf004": {**fields, **table}}, "ekf004"))
    if est.info.get("attitude_source") != ATTITUDE_SOURCES["stream"]:
        # Said in the report: the paper's vehicle logged its attitude, this flight does not.
        defaults["attitude"] = est.info.get("attitude_source")
        defaults["scale_source"] = est.info.get("scale_source")
        log.info("ekf004: roll and pitch %s", est.info.get("attitude_source"))
    return _with_info(est, compare_defaults=defaults)


def run_ukf003(flight: Flight, config: Mapping[str, Any], progress: bool = False) -> Estimate:
    """Seed 003's UKF with ``[ukf003]``."""
    from fgnav.baselines.ukf003 import Ukf003Options
    from fgnav.baselines.ukf003 import run_ukf003 as _run

    return _run(flight, _options(Ukf003Options, config, "ukf003"))


#: Where a calibrated drag coefficient came from when the config does not give it.
DRAG_FROM_SIM_TRUTH = "simulator truth: seeds 000 and 004 take mu/m as known (calibrated)"


def run_ii_observer(flight: Flight, config: Mapping[str, Any], progress: bool = False) -> Estimate:
    """Seed 000's I&I observer alone with ``[ii-observer]`` (fields of ``Seed000Options``).

    Defaults filled here (stated in ``info["compare_defaults"]``): ``align_slam_axes`` is True
    unless the flight's SLAM declares the paper's per-axis model (``meta["slam_model"] =
    "axis"``: SLAM axes are the world's); ``drag_k``, which the paper takes as known,
    comes from ``flight.meta["drag_k"]`` or, on a simulated flight, from the simulator's value.
    """
    from fgnav.baselines.seed000 import Seed000Options, run_seed000
    from fgnav.solvers.graph import declared_slam_model

    table = config_table(config, "ii-observer")
    defaults: dict[str, Any] = {}
    if "align_slam_axes" not in table:
        defaults["align_slam_axes"] = declared_slam_model(flight) != "axis"
    defaults.update(calibrated_drag_k(flight, table))
    fields = {k: v for k, v in defaults.items() if k != "drag_k_source"}
    opts = _options(Seed000Options, {"ii-observer": {**fields, **table}}, "ii-observer")
    est = run_seed000(flight, opts)
    return _with_info(est, compare_defaults=defaults)


def calibrated_drag_k(flight: Flight, table: Mapping[str, Any]) -> dict[str, Any]:
    """The drag coefficient of the methods that take it as calibrated (seeds 000 and 004), when
    their config table does not give it: the flight's calibration ``flight.meta["drag_k"]``, else
    on a simulated flight the simulator's value; returned with its ``drag_k_source``."""
    if "drag_k" in table or not isinstance(flight.meta, dict):
        return {}
    if flight.meta.get("drag_k") is not None:
        k = np.atleast_1d(np.asarray(flight.meta["drag_k"], dtype=float))
        return {"drag_k": (float(k[0]), float(k[-1])), "drag_k_source": "flight.meta drag_k"}
    truth = flight.meta.get("truth")
    if isinstance(truth, dict) and truth.get("drag_k"):
        return {
            "drag_k": tuple(float(k) for k in truth["drag_k"]),
            "drag_k_source": DRAG_FROM_SIM_TRUTH,
        }
    return {}


def _with_info(est: Estimate, **items: Any) -> Estimate:
    import dataclasses

    return dataclasses.replace(est, info={**est.info, **items})


def run_ekf_vo002(flight: Flight, config: Mapping[str, Any], progress: bool = False) -> Estimate:
    """Seed 002's attitude-height EKF + homography VO dead reckoning with ``[ekf-vo002]``."""
    from fgnav.baselines.seed002 import Seed002Options, run_seed002

    return run_seed002(flight, _options(Seed002Options, config, "ekf-vo002"))


def run_ekf_flow002(flight: Flight, config: Mapping[str, Any], progress: bool = False) -> Estimate:
    """Seed 002's attitude-height EKF + optical-flow dead reckoning with ``[ekf-flow002]``."""
    from fgnav.baselines.seed002_flow import Seed002FlowOptions, run_seed002_flow

    return run_seed002_flow(flight, _options(Seed002FlowOptions, config, "ekf-flow002"))


def run_cf_ekf(flight: Flight, config: Mapping[str, Any], progress: bool = False) -> Estimate:
    """The Crazyflie onboard EKF model (kalman_core, mm_flow, mm_tof) with ``[cf-ekf]``."""
    from fgnav.baselines.cf_ekf import CfEkfOptions
    from fgnav.baselines.cf_ekf import run_cf_ekf as _run

    return _run(flight, _options(CfEkfOptions, config, "cf-ekf"))


def reference_estimate(flight: Flight, ref: str, method: str) -> Estimate:
    """A trajectory recorded in the flight (``flight.references[ref]``) as an :class:`Estimate`.

    Nothing is run: ``runtime_s`` is 0 and there is no update latency. The onboard estimate of a
    PX4 log (``px4_ekf2``) is causal (EKF2 output as flown); other references are taken as
    non-causal (their origin is unknown).
    """
    traj: Trajectory = flight.references[ref]
    info: dict[str, Any] = {"reference": ref, "source": flight.source}
    meta = flight.meta.get(ref) if isinstance(flight.meta, dict) else None
    if meta is not None:
        info["meta"] = meta
    return Estimate(
        method=method, trajectory=traj, causal=ref == "px4_ekf2", runtime_s=0.0, info=info
    ).check()


#: Signature of a method's entry point: ``entry(flight, config, progress) -> Estimate``.
Entry = Callable[[Flight, Mapping[str, Any], bool], Estimate]


def _reference_entry(ref: str, method: str) -> Entry:
    def entry(flight: Flight, config: Mapping[str, Any], progress: bool = False) -> Estimate:
        return reference_estimate(flight, ref, method)

    entry.__doc__ = f"Replay ``flight.references[{ref!r}]`` as the estimate of {method!r}."
    return entry


def reference_method(ref: str) -> Method:
    """The replay method of ``flight.references[ref]``: ``px4-ekf2`` for ``px4_ekf2``, else
    ``ref:<ref>`` (e.g. another system's estimate given in a manifest), scored on its positions
    only (``positions_only``: its body frame is not known to be the flight's; the EuRoC V1_02
    references' orientations are of another one)."""
    if ref == "px4_ekf2":
        return METHODS["px4-ekf2"]
    name = f"{REFERENCE_PREFIX}{ref}"
    return Method(
        name,
        f"trajectory {ref!r} recorded with the flight (nothing is run; scored on positions only)",
        (name,),
        (),
        False,
        __name__,
        _reference_entry(ref, name),
        positions_only=True,
    )


#: Every method, in the order of the comparison table.
METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        smoother_method(
            "batch",
            "factor-graph smoother over the whole flight (Levenberg-Marquardt)",
            False,
            "fgnav.solvers.batch",
            run_batch,
        ),
        smoother_method(
            "fixed-lag",
            "online iSAM2 fixed-lag smoother, newest state after each update",
            True,
            "fgnav.solvers.fixed_lag",
            run_fixed_lag,
        ),
        smoother_method(
            "fixed-lag@lag",
            "the online smoother's states as smoothed when they leave the window (delayed by "
            "the lag)",
            False,
            "fgnav.solvers.online",
            run_fixed_lag_lagged,
        ),
        Method(
            "msf-ekf",
            "MSF-style error-state EKF with scale and SLAM-frame drift in the state",
            ("imu", "slam"),
            ("attitude", "range"),
            True,
            "fgnav.baselines.msf_ekf",
            run_msf_ekf,
        ),
        Method(
            "ekf004",
            "seed 004 EKF: drag-model prediction, ML scale, delay compensation (without an "
            "attitude stream: attitude estimated from the IMU by the seed-002 attitude EKF, not "
            "logged, and scale from closed-form IMU-SLAM fits)",
            ("slam",),
            ("attitude", "imu", "yaw", "range"),
            True,
            "fgnav.baselines.ekf004",
            run_ekf004,
            any_of=(("attitude",), ("imu",)),
        ),
        Method(
            "ukf003",
            "seed 003 UKF with state augmentation for relative measurements",
            ("imu", "slam"),
            ("attitude", "range", "yaw"),
            True,
            "fgnav.baselines.ukf003",
            run_ukf003,
        ),
        Method(
            "ii-observer",
            "seed 000 Immersion-and-Invariance velocity and per-axis scale observer",
            ("imu", "slam", "attitude", "range"),
            (),
            True,
            "fgnav.baselines.seed000",
            run_ii_observer,
        ),
        Method(
            "ekf-vo002",
            "seed 002 attitude-height EKF + homography visual odometry (dead reckoning)",
            ("imu", "range", "images"),
            ("yaw",),
            True,
            "fgnav.baselines.seed002",
            run_ekf_vo002,
        ),
        Method(
            "ekf-flow002",
            "seed 002 attitude-height EKF + optical-flow dead reckoning (the paper's system on a "
            "flow deck)",
            ("imu", "flow", "range"),
            ("yaw",),
            True,
            "fgnav.baselines.seed002_flow",
            run_ekf_flow002,
        ),
        Method(
            "cf-ekf",
            "Crazyflie onboard EKF model (kalman_core with mm_flow and mm_tof updates)",
            ("imu", "flow", "range"),
            (),
            True,
            "fgnav.baselines.cf_ekf",
            run_cf_ekf,
        ),
        Method(
            "px4-ekf2",
            "onboard PX4 EKF2 estimate recorded in the log (nothing is run)",
            ("ref:px4_ekf2",),
            (),
            True,
            __name__,
            _reference_entry("px4_ekf2", "px4-ekf2"),
        ),
    )
}


def reference_methods(flight: Flight) -> dict[str, Method]:
    """A ``ref:<name>`` replay method for each of the flight's references other than
    ``px4_ekf2`` (which is the registered ``px4-ekf2``)."""
    return {m.name: m for m in map(reference_method, flight.references) if m.name not in METHODS}


def get_method(
    name: str, flight: Flight | None = None, registry: Mapping[str, Method] | None = None
) -> Method:
    """The method ``name`` from ``registry`` (default :data:`METHODS`), or a ``ref:<name>``
    replay of one of the flight's references.

    Raises:
        MethodUnavailableError: unknown name (the message lists the valid ones).
    """
    reg = METHODS if registry is None else registry
    if name in reg:
        return reg[name]
    refs = reference_methods(flight) if flight is not None else {}
    if name in refs:
        return refs[name]
    raise MethodUnavailableError(f"unknown method {name!r}; valid: {', '.join([*reg, *refs])}")


def available_methods(
    flight: Flight,
    methods: list[str] | None = None,
    registry: Mapping[str, Method] | None = None,
) -> tuple[list[str], dict[str, str]]:
    """Which methods can run on ``flight``.

    Args:
        flight: the flight.
        methods: names to consider (None: every method of the registry plus a ``ref:<name>`` row
            for each of the flight's references other than ``px4_ekf2``).
        registry: the methods (default :data:`METHODS`).

    Returns:
        ``(runnable, skipped)``: runnable names in the given order, and ``{name: reason}`` for
        the others, e.g. ``{"ekf-vo002": "needs images; the flight has none"}``.
    """
    reg = METHODS if registry is None else registry
    names = list(methods) if methods is not None else [*reg, *reference_methods(flight)]
    runnable: list[str] = []
    skipped: dict[str, str] = {}
    for name in names:
        m = get_method(name, flight, reg)
        missing = m.missing(flight)
        problem = missing_reason(missing) if missing else m.implementation_problem()
        if problem:
            skipped[name] = problem
        else:
            runnable.append(name)
    return runnable, skipped
