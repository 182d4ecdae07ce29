"""``--config`` files: TOML tables that fill an options dataclass, flags override them."""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from fgnav.datasets._files import read_toml
from fgnav.datasets.errors import FgnavError, FlightFormatError

T = TypeVar("T")


def load_config(path: str | Path | None, section: str | None = None) -> dict[str, Any]:
    """Read a TOML config file (or ``{}`` for None); return the table ``section`` if given."""
    if path is None:
        return {}
    p = Path(path)
    data = read_toml(p, "config file")
    if section is None:
        return data
    table = data.get(section, {})
    if not isinstance(table, dict):
        raise FlightFormatError(p, f"[{section}] must be a table")
    return table


def options_from(
    cls: type[T],
    table: dict[str, Any],
    source: str = "config",
    section: str | None = None,
    elsewhere: tuple[str, ...] = (),
    **overrides,
) -> T:
    """Build options dataclass ``cls`` from a config table plus non-None overrides.

    Unknown keys raise an error naming them and listing the valid ones; each value's type is
    checked against the field's declaration (:func:`option_type_problem`: a bool for a switch, a
    number for a float, an integer for an int, a list of the declared length for a tuple, a
    table for nested options), then its value by :func:`option_value_problem` (the error names
    the option, the file and table or the flag). ``elsewhere``: fields that come from tables
    of their own (``graph`` of ``[online]`` is ``[graph]``), left out of the valid names shown.
    """
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - names)
    where = f"{source} [{section}]" if section else source
    if unknown:
        raise FlightFormatError(
            where,
            f"unknown option(s) {unknown} for {cls.__name__}; "
            f"valid: {sorted(names - set(elsewhere))}",
        )
    kwargs = dict(table)
    given = {k: v for k, v in overrides.items() if v is not None}
    kwargs.update(given)
    zero_ok = getattr(cls, "ZERO_MEANS_OFF", frozenset()) | ZERO_OK_OPTIONS
    hints = _field_types(cls)
    for name, value in kwargs.items():
        problem = option_type_problem(hints.get(name, Any), value)
        if problem is None:
            problem = option_value_problem(name, value, zero_ok=name in zero_ok)
        if problem is not None:
            origin = "command line" if name in given else where
            raise OptionValueError(f"{origin}: option {name} = {value!r}: {problem}")
        nested = _nested_options_class(hints.get(name, Any))
        if nested is not None and isinstance(value, dict):
            # A table for nested options is built into its dataclass (it was passed on as a
            # dict: `[ii-observer.observer]` failed later in dataclasses.replace).
            sub = f"{section}.{name}" if section else name
            kwargs[name] = options_from(nested, value, source, sub)
    try:
        return cls(**kwargs)
    except FgnavError as e:
        # A rule between fields checked on construction (e.g. SimOptions.validate): named with
        # the file and table too.
        raise OptionValueError(f"{where}: {e}") from None


def _nested_options_class(hint: Any) -> type | None:
    """The options dataclass a field declares (alone, or with None or ``dict``, e.g.
    ``GraphOptions.flow``: a table is built into it here, checked key by key and by type), else
    None."""
    members = (
        typing.get_args(hint)
        if typing.get_origin(hint) in (typing.Union, types.UnionType)
        else (hint,)
    )
    classes = [m for m in members if isinstance(m, type) and dataclasses.is_dataclass(m)]
    others = [
        m
        for m in members
        if m is not type(None)
        and m not in classes
        and m is not dict
        and typing.get_origin(m) is not dict
    ]
    return classes[0] if len(classes) == 1 and not others else None


def check_tables(path: str | Path | None, allowed: list[str]) -> None:
    """Refuse a ``--config`` file with a table the command does not read (a typo such as
    ``[grpah]`` would otherwise be ignored)."""
    unknown = sorted(set(load_config(path)) - set(allowed))
    if unknown:
        raise FlightFormatError(
            path, f"unknown table(s) {unknown} for this command; valid: {sorted(allowed)}"
        )


def _field_types(cls: type) -> dict[str, Any]:
    """The declared type of each field of dataclass ``cls`` (``Any`` where it cannot be
    resolved, e.g. a name imported for type checking only)."""
    try:
        return typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - resolve field by field below
        pass
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        # One field at a time, in the class's module (a throwaway class holding its annotation).
        one = type(
            "_Field", (), {"__annotations__": {f.name: f.type}, "__module__": cls.__module__}
        )
        try:
            out[f.name] = typing.get_type_hints(one)[f.name]
        except Exception:  # noqa: BLE001 - an annotation that cannot be resolved is not checked
            out[f.name] = Any
    return out


def _kind(value: Any) -> str:
    """A value's kind as a config file writes it."""
    if isinstance(value, bool):
        return "true/false"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a decimal number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, (list, tuple)):
        return "a list"
    if isinstance(value, dict):
        return "a table"
    return type(value).__name__


def _accepts(hint: Any, value: Any) -> bool | None:
    """Whether ``value`` fits the declared type ``hint`` (None: the type is not checked here)."""
    if hint is Any or isinstance(hint, TypeVar):
        return None
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        verdicts = [_accepts(h, value) for h in typing.get_args(hint)]
        if any(v is None for v in verdicts):
            return None
        return any(verdicts)
    if origin is typing.Literal:
        return value in typing.get_args(hint)
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is str:
        return isinstance(value, str)
    if hint is dict or origin is dict:
        return isinstance(value, dict)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return isinstance(value, (dict, hint))  # a table fills the nested options class
    if origin in (tuple, list) or hint in (tuple, list):
        if not isinstance(value, (list, tuple)):
            return False
        given = typing.get_args(hint)
        args = [a for a in given if a is not Ellipsis]
        if origin is tuple and Ellipsis not in given and args and len(value) != len(args):
            return False  # a fixed-length tuple such as (kx, ky)
        if len(set(args)) == 1:
            return all(_accepts(args[0], v) is not False for v in value)
        return None
    return None


def _wanted(hint: Any) -> str | None:
    """How an error names what type ``hint`` expects (None: not a type checked here)."""
    simple = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    if hint in simple:
        return simple[hint]
    origin = typing.get_origin(hint)
    if origin in (tuple, list) or hint in (tuple, list):
        given = typing.get_args(hint)
        if origin is tuple and given and Ellipsis not in given:
            return f"a list of {len(given)}"
        return "a list"
    if (
        hint is dict
        or origin is dict
        or (isinstance(hint, type) and dataclasses.is_dataclass(hint))
    ):
        return "a table"
    return None


def option_type_problem(hint: Any, value: Any) -> str | None:
    """What is wrong with the type of an option value against its field's declared type (None:
    it fits, or the type is not one checked: tables, arrays, options classes)."""
    if _accepts(hint, value) is not False:
        return None
    union = typing.get_origin(hint) in (typing.Union, types.UnionType)
    args = [a for a in typing.get_args(hint) if a is not type(None)] if union else [hint]
    names = [_wanted(a) for a in args]
    if any(n is None for n in names):
        return f"unexpected {_kind(value)} (see the option's documentation)"
    return f"expected {' or '.join(dict.fromkeys(names))}, found {_kind(value)}"


class OptionValueError(FgnavError, ValueError):
    """An option value that cannot be meant (non-finite, or <= 0 where only > 0 makes sense)."""


#: Option names (exact) whose value must be > 0 besides the name patterns of
#: :func:`option_value_problem`.
POSITIVE_OPTIONS = frozenset(
    {
        "gravity",
        "robust_k",
        "max_iterations",
        "lambda_init",
        "lambda_factor",
        "lambda_max",
        "lambda_min",
        "rel_tol",
        "cov_pose_stride",
        "relinearize_skip",
        # (ISAM2's relinearizeSkip: 0 on a start without an attitude stream killed the process
        # with SIGFPE; -1 relinearised every update)
        "startup_relinearize_skip",
        # (checked by the push engine once the flight was read)
        "vo_process_delay_keyframes",
        "slow_read_every",
        "fine_levels",
        "slam_provisional_scale",
        "slam_provisional_min_poses",
        "slam_init_max_rel_se",
        "max_imu_gap_s",
        "init_imu_s",
        "drag_scatter_n",
        "max_scale_step",
        "scale_floor",
    }
)

#: Options whose 0 is their default and meaning besides a class's ``ZERO_MEANS_OFF`` (a sigma or
#: walk of 0: none); writing the default was refused as "expected > 0".
ZERO_OK_OPTIONS = frozenset({"slam_gap_origin_sigma_m", "slam_origin_rw_m"})

#: Bounds ``(low, high)`` (inclusive; None: open) of option values that pass the sign rules yet
#: make no sense, by exact option name. Each is generous: no sane value is refused.
OPTION_BOUNDS: dict[str, tuple[float | None, float | None]] = {
    # [m/s^2]: Earth's 9.78-9.83 (1e300 or 1e-300 made the IMU preintegration meaningless).
    "gravity": (1.0, 100.0),
    # GraphOptions.check names its own top (<= 1000) and the run a minimum over the flight's
    # span (methods.check_keyframe_count); 1e-300 was refused by the lag's rule only, naming
    # lag_s (with lag_s = 1e300 not even that, until the flight was read).
    "keyframe_hz": (1e-3, None),
    # [online] ISAM2 relinearisation thresholds (tangent-space units: rad, m, m/s ...): below 0
    # is 0 (every update) written otherwise; above 100 nothing ever relinearises.
    "relinearize_threshold": (0.0, 100.0),
    "relinearize_threshold_position": (0.0, 100.0),
    "relinearize_threshold_slow": (0.0, 100.0),
    "startup_relinearize_threshold": (0.0, 100.0),
    # [online] window length [s]: the smoother lag and the marginalisation block; 1e300 kept
    # every keyframe in the window, each update's cost growing with the flight (a 60 s flight
    # 3.6x / 4.1x slower, quadratic in the flight's length).
    "lag_s": (None, 1e3),
    "marginalize_every_s": (None, 1e3),
    # [online] scale of a provisional SLAM alignment (SLAM units per metre), as the filters'
    # initial_scale: 1e-300 ran 13x worse (8 s two-turns 0.52 m against 0.039 m), health ok.
    "slam_provisional_scale": (1e-6, 1e6),
    # [online] the closed-form SLAM fit's largest relative standard error of the scale: above 1
    # any fit passes (1e300: a start without an attitude stream 4x worse, 0.27 m against 0.067).
    "slam_init_max_rel_se": (None, 1.0),
    # A filter's largest prediction step [s]: 1e-300 split each IMU interval without end.
    "max_predict_dt_s": (1e-4, None),
    # IMU span averaged for the first attitude [s] (0 waited without end).
    "init_imu_s": (1e-3, None),
    # An IMU gap that resets the online smoother [s]: 1e-300 made every interval a gap (ATE 140x
    # worse, exit 0); below a 1 kHz IMU's interval (the flight's own IMU: methods.check_online_imu).
    "max_imu_gap_s": (1e-3, None),
    # Simulated flight length [s] (1e9 s: 2e11 IMU samples), integration sub-steps per IMU sample.
    "duration": (None, 1e5),
    "substeps": (1, 1000),
    # [lm]: Levenberg-Marquardt iterations and stopping rules (2**31-1 iterations ran on without
    # end where it did not converge; a relative decrease is at most 1, so rel_tol = 1e300 or an
    # abs_tol of 1e300 stopped after one step, 18x worse, exit 0; abs_tol = -1 was taken).
    "max_iterations": (1, 100_000),
    "rel_tol": (None, 1.0),
    "abs_tol": (0.0, 1e6),
    # LM damping: 1e-300 retried ~300 damped solves per rejected step; 1e300 stopped at the
    # initial guess (LMOptions.validate: lambda_factor > 1, lambda_init <= lambda_max).
    "lambda_init": (1e-20, 1e20),
    "lambda_min": (1e-20, 1e20),
    "lambda_max": (1e-20, 1e20),
    # Drag coefficients [1/s] (~0.1-1 on a multirotor): [1e300, 1e300] made ekf004 fail with an
    # SVD that did not converge (list elements are checked against these too).
    "drag_k": (0.0, 100.0),
    "drag_k_init": (0.0, 100.0),
    # The filters' initial SLAM scale (SLAM units per metre): 1e300 overflowed (msf-ekf), 0 or
    # 1e-300 ran 25x worse.
    "initial_scale": (1e-6, 1e6),
    # [online] drag-check scatter buffer (2**31-1: a 32 GiB MemoryError traceback).
    "drag_scatter_n": (1, 1_000_000),
    # [ukf003] unscented-transform parameters (alpha 0 or 1e-300, kappa -1: ZeroDivisionError;
    # 1e300: NaN sigma points).
    "ut_alpha": (1e-4, 1.0),
    "ut_beta": (0.0, 10.0),
    "ut_kappa": (0.0, 100.0),
    # [ii-observer.observer] gains, initial state and scale step/floor: 1e300 gave an empty
    # estimate, 0 or -1 ATEs of 400-2500 m (or 3e59 m).
    "gamma_v": (1e-3, 1e3),
    "gamma_k": (1e-3, 1e3),
    "eta0": (-1e3, 1e3),
    "max_scale_step": (1e-6, 1e6),
    "scale_floor": (1e-6, 1e6),
    # [graph] robust kernel width (whitened; Huber 1.345): 1e-300 made every residual an outlier
    # (batch did not converge, online ATE 100x worse, exit 0). Ground-contact height [m]: 1e300
    # put every keyframe on the ground (zero velocity; batch did not converge).
    "robust_k": (1e-2, None),
    "contact_height_m": (None, 1.0),
    # The homography VO (HomographyVOOptions, [graph.homography.vo] and [ekf-vo002.vo]): values
    # OpenCV refuses (a cv2.error traceback: quality, corner distance or RANSAC confidence <= 0,
    # LK window < 3, pyramid levels < 0 or 2**31-1, an interpolation flag other than 0-4), a
    # corner distance of 1e300 (a segmentation fault), 2**31-1 corner pyramid levels (a hang),
    # a block size of 2**31-1 (std::length_error), a guess correction of 1e300 (OverflowError)
    # 0 LK iterations (batch did not converge, ekf-vo002 48x worse); a quality above 1 or a
    # window of 2**31-1 found or tracked nothing (ekf-vo002: exit 0 without an estimate).
    "max_corners": (0, None),
    "corner_quality": (1e-6, 1.0),
    "min_corner_distance_px": (0.0, 1e4),
    "corner_block_size_px": (1, 1000),
    "corner_pyramid_level": (0, 6),  # (a 64th of the image side: 4 gave no corner on 320 px)
    "lk_window_px": (3, 1000),
    "lk_pyramid_levels": (0, 10),
    "flow_guess_levels": (0, 10),
    "lk_max_iterations": (1, 100_000),
    "flow_guess_max_correction_px": (0.0, 1e4),
    # A RANSAC confidence of 1e-300 (ekf-vo002 39x worse), an inlier threshold of 1e-300 or a
    # mask margin of -1 or 2**31-1 (no pair: ekf-vo002 exit 0 without an estimate).
    "ransac_confidence": (0.5, 1.0),  # (< 1: HomographyVOOptions.check)
    "ransac_threshold_px": (1e-3, 1e4),
    "mask_margin_px": (0, 1000),
    "rectify_interpolation": (0, 4),  # cv2.INTER_NEAREST ... INTER_LANCZOS4
    # The flow filters: a quality (in [0, 1]) or sensor height floor of 1e300, an outlier limit
    # <= 1e-300 [rad] dropped every reading (ekf-flow002 FAILED, cf-ekf 220x worse, exit 0), a
    # time-of-flight limit of 0 or 1e-300 [m] every range reading (cf-ekf FAILED); a ground
    # height of 1e300 [m] (ekf-vo002, ekf-flow002) gave exit 0 without an estimate.
    "quality_min": (None, 1.0),
    "height_min": (None, 100.0),
    "outlier_rad": (1e-2, None),
    "tof_outlier_m": (0.05, None),
    "ground_height": (-1e4, 1e4),
}

#: Bounds of options by name pattern (see :data:`OPTION_BOUNDS`): noise sigmas, rates [Hz],
#: segment lengths [s], noise densities and random walks. A sigma of 1e300 has no information
#: (the solver's "indeterminate system"), one of 1e-300 an infinite one; a segment or rate of
#: 1e-300 asks for 1e300 variables or samples.
PATTERN_BOUNDS: tuple[tuple[Callable[[str], bool], tuple[float | None, float | None]], ...] = (
    (lambda n: "sigma" in n, (1e-12, 1e6)),
    (lambda n: n.endswith(("_rw", "_rw_m")), (1e-12, 1e6)),  # random walks, as the sigmas
    (lambda n: n.endswith("_hz"), (1e-3, 1e5)),
    (lambda n: n.endswith("segment_s"), (1e-3, None)),
    (lambda n: n.endswith(("noise_density", "random_walk")), (0.0, 1e3)),
    # The filters' process noises and walks by other names (accel_noise_xy, proc_noise_acc_z,
    # scale_walk, alignment_walk_pos ...): 1e300 overflowed (OverflowError), -1 was taken.
    (
        lambda n: (
            # (not a correlation or a factor: SimOptions checks flow_noise_lag1 and _factor)
            ("noise" in n and not n.endswith(("_lag1", "_factor")))
            or n.endswith(("_walk", "_walk_m", "_walk_rot", "_walk_pos"))
        ),
        (0.0, 1e6),
    ),
    # Tilt and angle limits: 1e300 or -1 were taken; 0 or 1e-300 used no sample (ii-observer:
    # an empty estimate).
    (lambda n: n.endswith(("tilt_deg", "angle_deg", "cone_deg")), (0.1, 90.0)),
    (lambda n: n.endswith(("tilt_rad", "max_tilt")), (1e-3, math.pi / 2)),
)

#: Largest integer option (a C++ ``int`` of GTSAM or OpenCV: larger overflowed in the binding).
INT_MAX = 2**31 - 1


def option_bounds(name: str) -> tuple[float | None, float | None]:
    """The bounds :func:`option_value_problem` applies to option ``name`` (``(None, None)``:
    none beyond the sign rules)."""
    if name in OPTION_BOUNDS:
        return OPTION_BOUNDS[name]
    for matches, bounds in PATTERN_BOUNDS:
        if matches(name):
            return bounds
    return (None, None)


def option_value_problem(name: str, value: Any, zero_ok: bool = False) -> str | None:
    """What is wrong with option ``name = value`` (None: nothing found; ``zero_ok``: 0 switches
    the option's stream off, as a class's ``ZERO_MEANS_OFF`` names).

    Every number (also inside tuples and lists) must be finite. Noise sigmas (``*sigma*``), rates
    (``*_hz``), random walks (``*_rw``, ``*_rw_m``), lags and segment lengths (``lag_s``,
    ``*segment_s``) and :data:`POSITIVE_OPTIONS` must be > 0; durations and lengths (``*_s``,
    ``*_m``, offsets excepted) must be >= 0; then the bounds of :func:`option_bounds` apply
    (an integer at most :data:`INT_MAX`). Booleans, strings and None are not checked here.
    """
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return None
    if isinstance(value, (list, tuple)):
        for v in value:
            # (the elements of a list of a bounded name, e.g. drag_k = [kx, ky], are bounded too)
            p = option_value_problem(name if name in OPTION_BOUNDS else "", v)
            if p is not None:
                return p
        return None
    if not isinstance(value, (int, float)):
        return None
    if not math.isfinite(value):
        return "expected a finite number"
    positive = (
        "sigma" in name
        or name.endswith(("_hz", "_rw", "_rw_m", "lag_s", "segment_s"))
        or name in POSITIVE_OPTIONS
    )
    if positive and not (value > 0 or (zero_ok and value == 0)):
        return "expected >= 0 (0: off)" if zero_ok else "expected > 0"
    if name.endswith(("_s", "_m")) and "offset" not in name and value < 0:
        return "expected >= 0"
    if isinstance(value, int) and abs(value) > INT_MAX:
        return f"expected an integer up to {INT_MAX}"
    lo, hi = option_bounds(name)
    if value == 0 and zero_ok:
        return None
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        if lo is not None and hi is not None:
            return f"expected in [{lo:g}, {hi:g}]"
        return f"expected >= {lo:g}" if lo is not None else f"expected <= {hi:g}"
    return None
