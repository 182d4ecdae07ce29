"""Accuracy, consistency and timing metrics of an :class:`~fgnav.estimate.Estimate` against truth.

Definitions (all computed after associating the estimate with ground truth interpolated at the
estimate's times, then aligning it with the stated mode, see :mod:`fgnav.eval.align`):

- **ATE** (absolute trajectory error): ``e_i = |gt_t_i - (s R est_t_i + t)|`` [m]; RMSE, mean,
  median and max over the matched samples. Equal to evo's APE ``translation_part`` with the same
  alignment (``evo_ape --align [--correct_scale]``). ``ate_4dof_m`` is the RMSE after a 4-DoF
  (yaw + translation) alignment whatever the stated mode: DESIGN.md sec. 9's mode for
  visual-inertial estimates, whose roll and pitch are observable (gravity) and must not be fitted
  away; SE(3) may turn a tilt error into a smaller ATE.
- **RPE per distance**: for every matched sample ``i`` the sample ``j > i`` whose distance travelled
  along the ground truth from ``i`` is closest to ``delta_m`` (pairs more than ``RPE_REL_TOL *
  delta_m`` off are not used); the error of the pair is the translation norm of the relative pose
  error ``(gt_i^-1 gt_j)^-1 (est_i^-1 est_j)`` [m] (evo's RPE ``translation_part`` with
  ``--delta_unit m --all_pairs --pairs_from_reference``, which gives the same pairs and errors).
  ``rpe_pct`` is the mean of ``100 * e_ij / d_ij`` with ``d_ij`` the true path length between the
  pair (the KITTI drift measure divides by the nominal segment length instead; the two differ by
  at most ``RPE_REL_TOL``). ``rpe_rmse_m`` is the RMSE of ``e_ij``.
- **Scale error** per SLAM session: ``100 (s_est - s_true) / s_true`` [%], final value from
  ``Estimate.slam_scale``; mean of its absolute value over time from ``series["slam_scale"]``.
- **Velocity RMSE** [m/s] of ``|gt_v - s R est_v|`` when both carry velocity.
- **Yaw RMSE** [deg] of the heading (ZYX yaw) of the world-frame rotation error
  ``R_o R_est R_true^T``: the difference of the yaws for a pure heading error, and independent
  of the body axes (EuRoC's x-up IMU body has no meaningful ZYX yaw). ``R_o`` is the constant
  rotation fitted to the orientations (:func:`~fgnav.eval.align.align_rotations`: about z for
  ``"4dof"``, none for ``"none"``), not the positions' fit: on a small trajectory that one is set
  by the positions' noise (simulated hover: 12.8 deg of yaw RMSE from the fit, 0.3 deg from
  the estimate). evo applies the positions' fit to both.
- **NEES** (normalised estimation error squared, Bar-Shalom et al. 2001, sec. 5.4) where
  ``pose_cov`` exists: position ``e^T P^-1 e`` with ``P = s^2 R world_R_body P_tt world_R_body^T
  R^T`` (expected 3 for a consistent estimator), and pose ``xi^T P^-1 xi`` with ``xi =
  Local(est_pose, gt_pose)`` in GTSAM's Pose3 tangent ``[rot, trans]`` (expected 6; the
  orientations aligned by ``R_o`` as for the yaw). Alignment fits a few degrees of freedom to the
  errors, which lowers NEES slightly. The interval ``nees_pos_interval`` treats the samples as
  independent; consecutive states of a smoother are not, so it is narrower than it should be.
- **Timing**: median, 99th percentile and max of ``update_latency`` [s]; times real time =
  estimate duration / ``runtime_s``.
- **Positions only** (``evaluate(..., positions_only=True)``, e.g. another system's trajectory
  whose orientations are of another body frame): the metrics that use the estimate's
  orientations are left out (NaN): RPE (relative poses), yaw RMSE and both NEES (the position
  NEES rotates the body-frame covariance by the estimate's orientation). ATE, ATE 4-DoF and
  velocity RMSE use positions and velocities only.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from enum import Enum
from typing import Any

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import quat_wxyz_to_matrix, wrap_angle, yaw_of
from fgnav.datasets.types import SlamSeries, Trajectory
from fgnav.estimate import Estimate, TimeSeries
from fgnav.eval.align import (
    DEFAULT_MAX_GT_GAP_S,
    Alignment,
    align,
    align_rotations,
    associate,
    umeyama,
)

logger = logging.getLogger(__name__)

#: Default RPE segment length [m]. Our flights are 30-100 m long (EuRoC MH_01: 80.6 m), so 10 m
#: segments give many pairs; KITTI uses 100-800 m for cars.
DEFAULT_RPE_DELTA_M = 10.0
#: Relative tolerance on the path length of an RPE pair (evo's default ``rel_delta_tol``).
RPE_REL_TOL = 0.1
#: Coverage of the two-sided chi-square interval reported for the average NEES.
NEES_CONFIDENCE = 0.95


def _nan() -> float:
    return float("nan")


@dataclass
class Metrics:
    """Scores of one estimate against ground truth (see the module docstring for definitions).

    Unavailable metrics are NaN (or empty dicts); counts say how many samples each used.
    """

    method: str
    alignment: str
    align_scale: float = 1.0
    causal: bool = False
    positions_only: bool = False
    n_est: int = 0
    n_matched: int = 0
    n_unmatched_before: int = 0
    n_unmatched_after: int = 0
    n_unmatched_gap: int = 0
    duration_s: float = field(default_factory=_nan)
    path_length_m: float = field(default_factory=_nan)
    ate_rmse_m: float = field(default_factory=_nan)
    ate_mean_m: float = field(default_factory=_nan)
    ate_median_m: float = field(default_factory=_nan)
    ate_max_m: float = field(default_factory=_nan)
    ate_4dof_m: float = field(default_factory=_nan)
    rpe_delta_m: float = field(default_factory=_nan)
    rpe_pct: float = field(default_factory=_nan)
    rpe_rmse_m: float = field(default_factory=_nan)
    rpe_n_pairs: int = 0
    scale_final_err_pct: dict[int, float] = field(default_factory=dict)
    scale_mean_abs_err_pct: dict[int, float] = field(default_factory=dict)
    vel_rmse_mps: float = field(default_factory=_nan)
    n_vel: int = 0
    yaw_rmse_deg: float = field(default_factory=_nan)
    nees_pos: float = field(default_factory=_nan)
    nees_pose: float = field(default_factory=_nan)
    nees_pos_interval: tuple[float, float] = (math.nan, math.nan)
    n_nees: int = 0
    latency_p50_s: float = field(default_factory=_nan)
    latency_p99_s: float = field(default_factory=_nan)
    latency_max_s: float = field(default_factory=_nan)
    runtime_s: float = field(default_factory=_nan)
    times_real_time: float = field(default_factory=_nan)

    @property
    def scale_final_abs_err_pct(self) -> float:
        """Largest absolute final scale error over sessions [%] (NaN without truth)."""
        v = [abs(x) for x in self.scale_final_err_pct.values()]
        return max(v) if v else math.nan

    @property
    def scale_mean_err_pct(self) -> float:
        """Largest per-session mean absolute scale error over time [%] (NaN without truth)."""
        v = list(self.scale_mean_abs_err_pct.values())
        return max(v) if v else math.nan

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (NaN becomes None; session keys become strings)."""
        d = asdict(self)
        d["scale_final_abs_err_pct"] = self.scale_final_abs_err_pct
        d["scale_mean_err_pct"] = self.scale_mean_err_pct
        return to_jsonable(d)

    COLUMNS = (
        ("method", "{:<14}", "method"),
        ("align", "{:>5}", "alignment"),
        ("ATE[m]", "{:>8.3f}", "ate_rmse_m"),
        ("RPE[%]", "{:>7.2f}", "rpe_pct"),
        ("scale[%]", "{:>8.2f}", "scale_final_abs_err_pct"),
        ("vel[m/s]", "{:>8.3f}", "vel_rmse_mps"),
        ("yaw[deg]", "{:>8.2f}", "yaw_rmse_deg"),
        ("NEESpos", "{:>7.2f}", "nees_pos"),
        ("p50[ms]", "{:>7.2f}", "latency_p50_ms"),
        ("p99[ms]", "{:>7.2f}", "latency_p99_ms"),
        ("xRT", "{:>7.1f}", "times_real_time"),
        ("N", "{:>6d}", "n_matched"),
    )

    @property
    def latency_p50_ms(self) -> float:
        return 1e3 * self.latency_p50_s

    @property
    def latency_p99_ms(self) -> float:
        return 1e3 * self.latency_p99_s

    @classmethod
    def header(cls) -> str:
        """Column titles matching :meth:`row`."""
        cells = []
        for title, fmt, _ in cls.COLUMNS:
            width = int("".join(ch for ch in fmt.split(".")[0] if ch.isdigit()))
            cells.append(title.ljust(width) if "<" in fmt else title.rjust(width))
        return " ".join(cells)

    def row(self) -> str:
        """One line of a fixed-width table (NaN shown as ``-``)."""
        cells = []
        for _, fmt, attr in self.COLUMNS:
            v = getattr(self, attr)
            width = int("".join(ch for ch in fmt.split(".")[0] if ch.isdigit()))
            if isinstance(v, float) and not math.isfinite(v):
                cells.append("-".rjust(width))
            else:
                cells.append(fmt.format(v))
        return " ".join(cells)


def format_table(metrics: list[Metrics]) -> str:
    """Fixed-width table: a header and one :meth:`Metrics.row` per estimate."""
    return "\n".join([Metrics.header(), *(m.row() for m in metrics)])


def to_jsonable(x: Any) -> Any:
    """Recursively convert a value for ``json.dump``: numpy scalars and arrays, tuples, dataclasses
    (as dicts), paths, enums, non-string keys; non-finite floats become None; any other object
    becomes its ``repr``."""
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple | set | frozenset):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, np.bool_ | bool):
        return bool(x)
    if isinstance(x, np.integer | int):
        return int(x)
    if isinstance(x, np.floating | float):
        f = float(x)
        return f if math.isfinite(f) else None
    if x is None or isinstance(x, str):
        return x
    if is_dataclass(x) and not isinstance(x, type):
        return to_jsonable({f.name: getattr(x, f.name) for f in fields(x)})
    if isinstance(x, Enum):
        return to_jsonable(x.value)
    if hasattr(x, "__fspath__"):
        return str(x)
    return repr(x)


# ----------------------------------------------------------------------------------------------
# Individual metrics (pure functions on arrays)
# ----------------------------------------------------------------------------------------------


def accumulated_distances(xyz: np.ndarray) -> np.ndarray:
    """(N,) path length [m] from the first position to each position."""
    steps = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def rpe_pairs(gt_xyz: np.ndarray, delta_m: float, rel_tol: float = RPE_REL_TOL) -> np.ndarray:
    """(P, 2) index pairs ``(i, j)``: for each ``i``, the ``j > i`` whose path length along
    ``gt_xyz`` from ``i`` is closest to ``delta_m`` (first such index on ties), kept when within
    ``rel_tol * delta_m`` of it (the pairs of evo's ``filter_pairs_by_path(all_pairs=True)``)."""
    if delta_m <= 0:
        raise FlightDataError(f"rpe: delta_m must be positive, got {delta_m}")
    D = accumulated_distances(np.asarray(gt_xyz, dtype=float))
    n = D.size
    pairs = []
    for i in range(n - 1):
        target = D[i] + delta_m
        k = int(np.searchsorted(D, target, side="left"))
        best_j, best_err = -1, math.inf
        if k - 1 > i:
            j_lo = max(int(np.searchsorted(D, D[k - 1], side="left")), i + 1)
            best_j, best_err = j_lo, abs(D[j_lo] - D[i] - delta_m)
        if k < n and k > i:
            err = abs(D[k] - D[i] - delta_m)
            if err < best_err:
                best_j, best_err = k, err
        if best_j > i and best_err <= rel_tol * delta_m:
            pairs.append((i, best_j))
    return np.asarray(pairs, dtype=int).reshape(-1, 2)


def _poses(xyz: np.ndarray, R: np.ndarray) -> np.ndarray:
    T = np.zeros((xyz.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = xyz
    T[:, 3, 3] = 1.0
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    Ti = np.zeros_like(T)
    Rt = np.transpose(T[:, :3, :3], (0, 2, 1))
    Ti[:, :3, :3] = Rt
    Ti[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    Ti[:, 3, 3] = 1.0
    return Ti


def rpe_translation_errors(
    gt_xyz: np.ndarray,
    gt_R: np.ndarray,
    est_xyz: np.ndarray,
    est_R: np.ndarray,
    pairs: np.ndarray,
) -> np.ndarray:
    """(P,) translation norms [m] of ``(gt_i^-1 gt_j)^-1 (est_i^-1 est_j)`` for the pairs."""
    if pairs.shape[0] == 0:
        return np.zeros(0)
    i, j = pairs[:, 0], pairs[:, 1]
    G = _poses(gt_xyz, gt_R)
    P = _poses(est_xyz, est_R)
    gt_rel = np.einsum("nij,njk->nik", _inv(G[i]), G[j])
    est_rel = np.einsum("nij,njk->nik", _inv(P[i]), P[j])
    E = np.einsum("nij,njk->nik", _inv(gt_rel), est_rel)
    return np.linalg.norm(E[:, :3, 3], axis=1)


def nees_interval(n: int, dof: int, confidence: float = NEES_CONFIDENCE) -> tuple[float, float]:
    """Two-sided interval of the average NEES of ``n`` independent samples of a consistent
    estimator with ``dof`` degrees of freedom (``n * avg ~ chi2(n * dof)``)."""
    if n <= 0:
        return (math.nan, math.nan)
    a = (1.0 - confidence) / 2.0
    # chi2.ppf(q, k) == chdtri(k, 1 - q); scipy.special imports in half the time of scipy.stats
    # (the per-flight start-up of `fgnav fleet` children counts).
    from scipy.special import chdtri

    k = n * dof
    return (float(chdtri(k, 1.0 - a) / n), float(chdtri(k, a) / n))


def position_nees(
    err_world: np.ndarray, world_R_body: np.ndarray, pose_cov: np.ndarray, al: Alignment
) -> np.ndarray:
    """(N,) position NEES ``e^T P^-1 e``.

    Args:
        err_world: (N, 3) ``gt - aligned estimate`` in the truth's world [m].
        world_R_body: (N, 3, 3) estimated orientations (estimate's world).
        pose_cov: (N, 6, 6) body-frame Pose3 covariance ``[rot, trans]``.
        al: alignment used (rotates and scales the covariance into the truth's world).
    """
    P_body = pose_cov[:, 3:6, 3:6]
    A = np.einsum("ij,njk->nik", al.R, world_R_body)
    P = al.s**2 * np.einsum("nij,njk,nlk->nil", A, P_body, A)
    return _quadratic_forms(err_world, P)


def _quadratic_forms(x: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(N,) ``x_n^T P_n^-1 x_n``; NaN for a row whose ``P_n`` is singular (an estimator that
    reports an infinite or degenerate covariance) instead of failing the whole scoring."""
    try:
        sol = np.linalg.solve(P, x[:, :, None])[:, :, 0]
        return np.einsum("ni,ni->n", x, sol)
    except np.linalg.LinAlgError:
        out = np.full(x.shape[0], np.nan)
        for n in range(x.shape[0]):
            try:
                out[n] = x[n] @ np.linalg.solve(P[n], x[n])
            except np.linalg.LinAlgError:
                pass
        return out


def pose_nees(
    est_xyz: np.ndarray,
    est_R: np.ndarray,
    gt_xyz: np.ndarray,
    gt_R: np.ndarray,
    pose_cov: np.ndarray,
    scale: float = 1.0,
) -> np.ndarray:
    """(N,) pose NEES ``xi^T P^-1 xi`` with ``xi = est_pose.localCoordinates(gt_pose)`` (GTSAM
    Pose3 tangent ``[rot, trans]``, the same chart as the covariance). Poses are the aligned
    estimate and the truth in the truth's world; the translation block is scaled by ``scale**2``."""
    import gtsam

    D = np.diag([1.0, 1.0, 1.0, scale, scale, scale])
    out = np.empty(est_xyz.shape[0])
    for n in range(est_xyz.shape[0]):
        est = gtsam.Pose3(gtsam.Rot3(est_R[n]), est_xyz[n])
        gt = gtsam.Pose3(gtsam.Rot3(gt_R[n]), gt_xyz[n])
        xi = est.localCoordinates(gt)
        try:
            out[n] = xi @ np.linalg.solve(D @ pose_cov[n] @ D, xi)
        except np.linalg.LinAlgError:
            out[n] = np.nan  # a singular covariance (as in position_nees)
    return out


def _rmse(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else math.nan


def common_span_ate(
    trajectories: Mapping[str, Trajectory],
    causal: Mapping[str, bool],
    truth: Trajectory,
    alignments: Mapping[str, str] | None = None,
    max_gap_s: float = DEFAULT_MAX_GT_GAP_S,
) -> tuple[float | None, dict[str, float]]:
    """ATE RMSE [m] of each trajectory over one common span: from the latest first matched
    sample of the causal ones to the end, each aligned (``alignments``, default SE(3)) over that
    span only.

    A filter that emits nothing before its initialisation (a SLAM scale fit) is otherwise scored
    over a shorter, easier span than a smoother that emits from its start; on this span every
    causal method is scored over the same stretch of the flight.

    Returns:
        ``(t_start, {name: ate})``: the span's start on the flight's clock [s] (None, with an
        empty dict, when no trajectory is causal or none matches the truth); trajectories with
        fewer than 3 matched samples on the span are left out.
    """
    matched: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for name, traj in trajectories.items():
        try:
            a = associate(traj, truth, max_gap_s=max_gap_s, log=False)
        except FlightDataError:  # nothing inside the truth's span: no ATE at all
            continue
        idx = a.est_index
        matched[name] = (traj.t[idx], traj.world_t_body[idx], a.gt.world_t_body)
    starts = [float(m[0][0]) for n, m in matched.items() if causal.get(n)]
    if not starts:
        return None, {}
    t_c = max(starts)
    out: dict[str, float] = {}
    for name, (t, x, g) in matched.items():
        k = t >= t_c
        if int(k.sum()) < 3:
            continue
        try:
            al = align(x[k], g[k], (alignments or {}).get(name, "se3"))
        except FlightDataError as e:  # e.g. no horizontal motion on the span for "4dof"
            logger.warning("ATE over the common span: %s left out (%s)", name, e)
            continue
        out[name] = _rmse(np.linalg.norm(g[k] - al.apply_positions(x[k]), axis=1))
    return t_c, out


def scale_series(estimate: Estimate, sessions: list[int] | None = None) -> dict[int, TimeSeries]:
    """The scale-over-time series of each session present in ``estimate.series``.

    Accepted layouts: ``series["slam_scale/<id>"]`` per session; or ``series["slam_scale"]`` (N,)
    with ``series["slam_session"]`` (N,) giving the active session at each time; or
    ``series["slam_scale"]`` (N,) alone when the estimate has a single session.
    """
    out: dict[int, TimeSeries] = {}
    for key, ts in estimate.series.items():
        if key.startswith("slam_scale/"):
            out[int(key.split("/", 1)[1])] = ts
    base = estimate.series.get("slam_scale")
    if base is None:
        return out
    value = np.asarray(base.value, dtype=float)
    if value.ndim != 1:
        raise FlightDataError(
            f"estimate[{estimate.method}].series['slam_scale']: expected (N,) values, got "
            f"{value.shape}; use one series 'slam_scale/<session>' per session"
        )
    sess_ts = estimate.series.get("slam_session")
    if sess_ts is not None:
        sess = np.asarray(sess_ts.value).astype(int)
        if sess.shape != value.shape:
            raise FlightDataError(
                f"estimate[{estimate.method}].series['slam_session']: expected shape "
                f"{value.shape} like 'slam_scale', got {sess.shape}"
            )
        for sid in np.unique(sess):
            m = sess == sid
            sigma = None if base.sigma is None else np.asarray(base.sigma)[m]
            out.setdefault(int(sid), TimeSeries(np.asarray(base.t)[m], value[m], sigma))
        return out
    known = sorted(estimate.slam_scale) or list(sessions or [])
    if len(known) != 1:
        raise FlightDataError(
            f"estimate[{estimate.method}].series['slam_scale'] has no 'slam_session' series "
            f"and the estimate has sessions {known}: cannot tell the session of each value"
        )
    out.setdefault(known[0], TimeSeries(np.asarray(base.t), value, base.sigma))
    return out


def scale_errors(
    estimate: Estimate,
    truth_scale: dict[int, float],
    truth_scale_at: Mapping[int, Callable[[np.ndarray], np.ndarray]] | None = None,
) -> tuple[dict[int, float], dict[int, float]]:
    """Final and time-averaged absolute scale errors [%] per session in ``truth_scale``.

    ``truth_scale`` holds the true scale at the session's end (compared with the estimate's
    final scale). ``truth_scale_at`` optionally gives the true scale as a function of time per
    session (a drifting simulated SLAM scale): the time average then compares each value of the
    estimate's scale series with the truth at its own time, else with the constant
    ``truth_scale``.
    """
    final: dict[int, float] = {}
    mean_abs: dict[int, float] = {}
    for sid, s_true in truth_scale.items():
        if not s_true > 0:
            raise FlightDataError(f"truth_scale[{sid}] = {s_true}: a scale must be positive")
        if sid in estimate.slam_scale:
            final[int(sid)] = 100.0 * (estimate.slam_scale[sid] - s_true) / s_true
        else:
            logger.warning("estimate[%s] has no scale for SLAM session %s", estimate.method, sid)
    for sid, ts in scale_series(estimate, sorted(truth_scale)).items():
        if sid in truth_scale and np.asarray(ts.value).size:
            fn = (truth_scale_at or {}).get(sid)
            s_true = truth_scale[sid] if fn is None else np.asarray(fn(np.asarray(ts.t)), float)
            rel = np.abs(np.asarray(ts.value, float) - s_true) / s_true
            mean_abs[sid] = float(np.mean(rel) * 100.0)
    return final, mean_abs


# ----------------------------------------------------------------------------------------------
# Entry points
# ----------------------------------------------------------------------------------------------


def evaluate(
    estimate: Estimate,
    truth: Trajectory,
    alignment: str = "se3",
    truth_scale: dict[int, float] | None = None,
    delta_m: float = DEFAULT_RPE_DELTA_M,
    max_gap_s: float = DEFAULT_MAX_GT_GAP_S,
    truth_scale_at: Mapping[int, Callable[[np.ndarray], np.ndarray]] | None = None,
    positions_only: bool = False,
) -> Metrics:
    """Score an estimate against ground truth.

    Args:
        estimate: the estimate (its trajectory in its own world frame).
        truth: ground-truth body trajectory on the same clock.
        alignment: ``"se3"``, ``"sim3"``, ``"4dof"`` or ``"none"`` (always reported).
        truth_scale: true SLAM scale ``s`` (SLAM units per metre) per session, when known (its
            value at the session's end).
        truth_scale_at: optional true scale as a function of time per session (see
            :func:`scale_errors`).
        delta_m: RPE segment length [m].
        max_gap_s: largest truth gap [s] interpolated across (see :func:`associate`).
        positions_only: leave out the metrics that use the estimate's orientations (RPE, yaw
            RMSE, NEES; see the module docstring).

    Returns:
        The :class:`Metrics`.
    """
    estimate.check()
    est = estimate.trajectory
    assoc = associate(est, truth, max_gap_s=max_gap_s)
    idx = assoc.est_index
    gt = assoc.gt
    est_xyz = est.world_t_body[idx]
    est_R = est.world_R_body()[idx]
    al = align(est_xyz, gt.world_t_body, alignment)
    a_xyz = al.apply_positions(est_xyz)
    a_R = al.apply_rotations(est_R)
    gt_R = gt.world_R_body()

    m = Metrics(
        method=estimate.method,
        alignment=al.mode,
        align_scale=al.s,
        causal=estimate.causal,
        positions_only=positions_only,
    )
    m.n_est = len(est)
    m.n_matched = assoc.n_matched
    m.n_unmatched_before = assoc.n_before
    m.n_unmatched_after = assoc.n_after
    m.n_unmatched_gap = assoc.n_gap
    m.duration_s = est.duration

    err = gt.world_t_body - a_xyz
    e = np.linalg.norm(err, axis=1)
    m.ate_rmse_m = _rmse(e)
    m.ate_mean_m = float(e.mean())
    m.ate_median_m = float(np.median(e))
    m.ate_max_m = float(e.max())
    if al.mode == "4dof":
        m.ate_4dof_m = m.ate_rmse_m
    else:
        try:
            a4 = align(est_xyz, gt.world_t_body, "4dof")
        except FlightDataError:  # no horizontal motion: the yaw is undetermined (NaN)
            a4 = None
        if a4 is not None:
            e4 = np.linalg.norm(gt.world_t_body - a4.apply_positions(est_xyz), axis=1)
            m.ate_4dof_m = _rmse(e4)

    D = accumulated_distances(gt.world_t_body)
    m.path_length_m = float(D[-1])
    m.rpe_delta_m = float(delta_m)
    pairs = rpe_pairs(gt.world_t_body, delta_m)
    if positions_only:  # (relative poses use the orientations)
        pairs = pairs[:0]
    m.rpe_n_pairs = int(pairs.shape[0])
    if pairs.shape[0]:
        rpe = rpe_translation_errors(gt.world_t_body, gt_R, a_xyz, a_R, pairs)
        d = D[pairs[:, 1]] - D[pairs[:, 0]]
        m.rpe_rmse_m = _rmse(rpe)
        m.rpe_pct = float(np.mean(100.0 * rpe / d))
    elif not positions_only:
        logger.warning(
            "evaluate[%s]: no RPE pair over %.1f m (true path %.1f m)",
            estimate.method,
            delta_m,
            m.path_length_m,
        )

    if truth_scale:
        m.scale_final_err_pct, m.scale_mean_abs_err_pct = scale_errors(
            estimate, truth_scale, truth_scale_at
        )

    if est.world_v_body is not None and gt.world_v_body is not None:
        dv = gt.world_v_body - al.apply_velocities(est.world_v_body[idx])
        m.vel_rmse_mps = _rmse(np.linalg.norm(dv, axis=1))
        m.n_vel = int(dv.shape[0])

    # Heading of the world-frame rotation error: independent of the body axes (a body whose x
    # is vertical, as EuRoC's IMU frame, has no ZYX yaw to compare). The orientations are
    # aligned by the rotation fitted to them (align_rotations), not the positions' fit.
    mode_R = alignment if alignment in ("none", "4dof") else "se3"
    o_R = np.einsum("ij,njk->nik", align_rotations(est_R, gt_R, mode_R), est_R)
    if not positions_only:
        dyaw = wrap_angle(yaw_of(np.einsum("nij,nkj->nik", o_R, gt_R)))
        m.yaw_rmse_deg = math.degrees(_rmse(dyaw))

    if estimate.pose_cov is not None and not positions_only:
        # Only samples with a covariance (solvers may compute it on a stride and leave NaN rows).
        has = np.all(np.isfinite(estimate.pose_cov[idx]), axis=(1, 2))
        if has.any():
            cov = estimate.pose_cov[idx][has]
            nees = position_nees(err[has], est_R[has], cov, al)
            ok = np.isfinite(nees)
            if not ok.all():
                logger.info(
                    "%s: NEES of %d of %d samples left out (singular covariance)",
                    estimate.method,
                    int((~ok).sum()),
                    ok.size,
                )
            m.nees_pos = float(np.mean(nees[ok])) if ok.any() else math.nan
            pn = pose_nees(a_xyz[has], o_R[has], gt.world_t_body[has], gt_R[has], cov, al.s)
            pn = pn[np.isfinite(pn)]
            m.nees_pose = float(np.mean(pn)) if pn.size else math.nan
            m.n_nees = int(ok.sum())
            m.nees_pos_interval = nees_interval(m.n_nees, 3)

    if estimate.update_latency is not None and np.asarray(estimate.update_latency).size:
        lat = np.asarray(estimate.update_latency, dtype=float)
        m.latency_p50_s = float(np.percentile(lat, 50))
        m.latency_p99_s = float(np.percentile(lat, 99))
        m.latency_max_s = float(lat.max())
    if estimate.runtime_s > 0:
        m.runtime_s = float(estimate.runtime_s)
        m.times_real_time = est.duration / estimate.runtime_s
    return m


def _slam_truth_pairs(
    slam: SlamSeries,
    gt: Trajectory,
    body_T_cam: np.ndarray,
    max_gap_s: float,
    min_samples: int,
    caller: str,
) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per SLAM session: ``(t (N,), world_t_cam (N, 3) [m], slam_t_cam (N, 3))`` at the SLAM times
    matched to truth (truth interpolated, camera = body + ``world_R_body body_t_cam``); sessions
    with fewer than ``min_samples`` matches are skipped and logged."""
    slam.check(f"{caller}.slam")
    body_T_cam = np.asarray(body_T_cam, dtype=float)
    out: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for sid in np.unique(slam.session):
        m = slam.session == sid
        t = slam.t[m]
        fake = Trajectory(
            t=t,
            world_t_body=slam.slam_t_cam[m],
            world_q_body_wxyz=slam.slam_q_cam_wxyz[m],
        )
        assoc = associate(fake, gt, max_gap_s=max_gap_s)
        if assoc.n_matched < min_samples:
            logger.warning(
                "%s: session %d has %d samples matched to truth (< %d): skipped",
                caller,
                sid,
                assoc.n_matched,
                min_samples,
            )
            continue
        g = assoc.gt
        world_t_cam = g.world_t_body + np.einsum("nij,j->ni", g.world_R_body(), body_T_cam[:3, 3])
        idx = assoc.est_index
        out[int(sid)] = (t[idx], world_t_cam, slam.slam_t_cam[m][idx])
        if assoc.n_unmatched:
            logger.info("%s: session %d: %d samples unmatched", caller, sid, assoc.n_unmatched)
    return out


def slam_scale_vs_truth(
    slam: SlamSeries,
    gt: Trajectory,
    body_T_cam: np.ndarray,
    max_gap_s: float = DEFAULT_MAX_GT_GAP_S,
    min_samples: int = 10,
) -> dict[int, float]:
    """True SLAM scale per session from ground truth, by Sim(3) alignment.

    For each session, the true camera positions ``world_t_cam = world_t_body + world_R_body
    body_t_cam`` (truth interpolated at the SLAM times) are aligned to the SLAM camera positions
    with Umeyama's Sim(3): ``slam_t_cam ~ s slam_R_world world_t_cam + slam_t_world`` (the SLAM
    model of DESIGN.md section 4.2, noise on the SLAM side), so ``s`` is SLAM units per metre.

    Args:
        slam: SLAM camera poses.
        gt: ground-truth body trajectory on the same clock [m].
        body_T_cam: 4x4 camera pose in the body frame.
        max_gap_s: largest truth gap [s] interpolated across.
        min_samples: sessions with fewer matched samples are skipped (and logged).

    Returns:
        ``{session id: s}``.
    """
    out: dict[int, float] = {}
    pairs = _slam_truth_pairs(slam, gt, body_T_cam, max_gap_s, min_samples, "slam_scale_vs_truth")
    for sid, (t, world_t_cam, slam_t_cam) in pairs.items():
        _, _, s = umeyama(world_t_cam, slam_t_cam, with_scale=True)
        out[sid] = s
        logger.info(
            "slam_scale_vs_truth: session %d: s = %.6g SLAM units per metre from %d samples",
            sid,
            s,
            len(t),
        )
    return out


@dataclass
class ScaleDrift:
    """Scale drift of one SLAM session against ground truth (:func:`slam_scale_drift`).

    Attributes:
        session: SLAM session id.
        scale: Sim(3) scale of the whole session [SLAM units per metre].
        t: (W,) mid time of each window used [s from the session's first pose].
        rel_scale: (W,) Sim(3) scale of each window relative to ``scale`` minus one.
        path_m: (W,) camera path length in each window [m].
        n_skipped: windows skipped for too short a camera path (scale not determined).
        slope_per_s: least-squares trend of ``rel_scale`` [1/s]; NaN with fewer than 3 windows.
        slope_sigma_per_s: its standard error from the residual scatter [1/s].
        scatter: standard deviation of ``rel_scale`` about the trend.
    """

    session: int
    scale: float
    t: np.ndarray
    rel_scale: np.ndarray
    path_m: np.ndarray
    n_skipped: int
    slope_per_s: float
    slope_sigma_per_s: float
    scatter: float


def slam_scale_drift(
    slam: SlamSeries,
    gt: Trajectory,
    body_T_cam: np.ndarray,
    window_s: float = 10.0,
    min_path_m: float = 2.0,
    max_gap_s: float = DEFAULT_MAX_GT_GAP_S,
) -> dict[int, ScaleDrift]:
    """How a SLAM run's scale changes over time: Sim(3) scale in consecutive, non-overlapping
    windows of ``window_s`` (truth camera positions aligned to the SLAM ones, as
    :func:`slam_scale_vs_truth`) and its linear trend.

    Windows where the camera moved less than ``min_path_m`` (hover, SLAM initialisation) do
    not determine a scale: they are skipped and counted. A window's scale also carries the SLAM
    noise, so ``scatter`` bounds the scale's wander from above.
    """
    if not window_s > 0 or not min_path_m >= 0:
        raise ValueError(f"window_s must be > 0 and min_path_m >= 0, got {window_s}, {min_path_m}")
    out: dict[int, ScaleDrift] = {}
    pairs = _slam_truth_pairs(slam, gt, body_T_cam, max_gap_s, 10, "slam_scale_drift")
    for sid, (t, x, y) in pairs.items():
        _, _, s_all = umeyama(x, y, with_scale=True)
        tw, rel, path = [], [], []
        skipped = 0
        t0 = t[0]
        for a in np.arange(t[0], t[-1] - window_s + 1e-9, window_s):
            m = (t >= a) & (t < a + window_s)
            d = float(np.linalg.norm(np.diff(x[m], axis=0), axis=1).sum()) if m.sum() > 1 else 0.0
            if m.sum() < 10 or d < min_path_m:
                skipped += 1
                continue
            _, _, s = umeyama(x[m], y[m], with_scale=True)
            tw.append(a + 0.5 * window_s - t0)
            rel.append(s / s_all - 1.0)
            path.append(d)
        tw_a, rel_a = np.asarray(tw), np.asarray(rel)
        slope = slope_sig = scatter = math.nan
        if len(tw_a) >= 3:
            A = np.column_stack([tw_a, np.ones_like(tw_a)])
            coef, *_ = np.linalg.lstsq(A, rel_a, rcond=None)
            r = rel_a - A @ coef
            var = float(r @ r) / (len(r) - 2)
            slope, scatter = float(coef[0]), math.sqrt(var)
            slope_sig = math.sqrt(var * float(np.linalg.inv(A.T @ A)[0, 0]))
        out[sid] = ScaleDrift(
            sid, s_all, tw_a, rel_a, np.asarray(path), skipped, slope, slope_sig, scatter
        )
    return out


def flow_flight_figures(
    estimate: Estimate,
    truth: Trajectory,
    alignment: str = "4dof",
    velocity_average_s: float = 0.0,
    max_gap_s: float = DEFAULT_MAX_GT_GAP_S,
) -> dict[str, float]:
    """Figures of a flow-and-range flight (issue 17): after one alignment of the whole trajectory
    (``alignment``, default 4-DoF: yaw + translation), the RMSE of the horizontal velocity
    [m/s] (the estimate's ``world_v_body`` rotated by the alignment; optionally both averaged over
    trailing ``velocity_average_s`` windows), of the height [m] (aligned z against true z) and
    the ATE [m]; plus the end drift: horizontal distance between the last aligned and true
    positions [m] and as a percentage of the true horizontal path length; and the end drift with
    the start pose known (``start_drift_m``, ``start_drift_pct``): the estimate rotated about z and
    moved so that its first pose has the truth's first yaw and position, no other alignment.

    Returns:
        ``{"hvel_rmse_mps", "height_rmse_m", "ate_m", "end_drift_m", "end_drift_pct",
        "start_drift_m", "start_drift_pct", "path_m"}``.
    """
    estimate.check()
    est = estimate.trajectory
    assoc = associate(est, truth, max_gap_s=max_gap_s)
    idx = assoc.est_index
    gt = assoc.gt
    al = align(est.world_t_body[idx], gt.world_t_body, alignment)
    p = al.apply_positions(est.world_t_body[idx])
    out: dict[str, float] = {}
    e = np.linalg.norm(gt.world_t_body - p, axis=1)
    out["ate_m"] = _rmse(e)
    out["height_rmse_m"] = _rmse(gt.world_t_body[:, 2] - p[:, 2])
    out["hvel_rmse_mps"] = float("nan")
    if est.world_v_body is not None and gt.world_v_body is not None:
        v = al.apply_velocities(est.world_v_body[idx])[:, :2]
        vt = gt.world_v_body[:, :2]
        if velocity_average_s > 0:
            t = gt.t
            # Samples in [t - velocity_average_s, t], the edge with a tolerance: float rounding
            # had dropped the sample exactly 0.1 s back from 70 of 401 windows at 20 Hz.
            j = np.searchsorted(t, t - velocity_average_s - 1e-9, side="left")
            cv = np.vstack([np.zeros((1, 2)), np.cumsum(v, axis=0)])
            ct = np.vstack([np.zeros((1, 2)), np.cumsum(vt, axis=0)])
            n = (np.arange(len(t)) + 1 - j)[:, None]
            v = (cv[1:] - cv[j]) / n
            vt = (ct[1:] - ct[j]) / n
        out["hvel_rmse_mps"] = _rmse(np.linalg.norm(v - vt, axis=1))
    path = float(np.sum(np.linalg.norm(np.diff(gt.world_t_body[:, :2], axis=0), axis=1)))
    out["path_m"] = path
    out["end_drift_m"] = float(np.linalg.norm(p[-1, :2] - gt.world_t_body[-1, :2]))
    out["end_drift_pct"] = 100.0 * out["end_drift_m"] / path if path > 0 else float("nan")
    # Start pose known: the estimate placed at the truth's first pose (yaw and position) only.
    q0 = est.world_q_body_wxyz[idx[0]]
    dyaw = float(yaw_of(quat_wxyz_to_matrix(gt.world_q_body_wxyz[0]))) - float(
        yaw_of(quat_wxyz_to_matrix(q0))
    )
    c, s_ = math.cos(dyaw), math.sin(dyaw)
    Rz = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    e_end = Rz @ (est.world_t_body[idx[-1]] - est.world_t_body[idx[0]]) + gt.world_t_body[0]
    out["start_drift_m"] = float(np.linalg.norm(e_end[:2] - gt.world_t_body[-1, :2]))
    out["start_drift_pct"] = 100.0 * out["start_drift_m"] / path if path > 0 else float("nan")
    return out
