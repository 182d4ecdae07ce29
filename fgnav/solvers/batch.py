"""Batch smoother: the whole flight's graph solved by Levenberg-Marquardt written in Python.

GTSAM's C++ optimizers call Python ``CustomFactor`` callbacks at a cost that grows with the problem
size (../shared/GTSAM-NOTES.md), so the loop lives here: ``graph.linearize(values)`` (callbacks
from Python: a few us each), damping added as unit Jacobian factors ``sqrt(lambda) I`` on every
variable, ``GaussianFactorGraph.optimize()`` (multifrontal Cholesky, COLAMD ordering) and
``values.retract(delta)``. A step is accepted when the nonlinear error decreases; lambda then
shrinks by ``lambda_factor``, else it grows and the step is retried.

Cholesky's false alarm on long flights: GTSAM 4.3's dense Cholesky of a clique calls the system
"indeterminate" as soon as a pivot falls below 2^-24 (6.0e-8) of its diagonal entry (measured:
``[[1, c], [c, h]]`` fails once ``h - c^2 < 6.0e-8 h``, whatever ``h``), a test on round-off, not
on rank. On a 900 s figure8 at 20 Hz keyframes the information of the last clique (x17999,
v17999, b17999, d0, x18000, v18000, b18000; 32x32, eigenvalues 47 to 1.1e11: well posed, QR and
numpy's Cholesky factor it) has a pivot at 5.3e-8 of its diagonal (the IMU ties consecutive
keyframes with information ~1e9, the conditional information left is ~1e2); at 750 s the same
clique passes. So every undamped solve and the marginals (even damped by 1e-4) failed "near" the
last keyframe. The covariances now come from QR after Cholesky and the damped Cholesky failed.
The LM loop keeps retrying with more damping (the damped steps converge to the same estimate,
at about 1.5x the time of QR steps); ``LMOptions.qr_fallback`` solves the system by QR instead
(a QR step that is not finite or has a component above :data:`QR_STEP_MAX` is refused: the
damping then grows as before).

Covariances: ``gtsam.Marginals`` on the final linearization (a ``GaussianFactorGraph``, so no
callbacks inside C++), for the slow variables and every ``cov_pose_stride``-th keyframe; when
Cholesky fails (and a tiny damping does not help), a multifrontal QR Bayes tree of the same
linearization (:class:`QrMarginals`; the wrapper has no ``Marginals(..., QR)``).
"""

from __future__ import annotations

import logging
import math
import re
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import gtsam
import numpy as np

from fgnav.datasets.errors import FgnavError
from fgnav.datasets.geometry import matrix_to_quat_wxyz
from fgnav.datasets.types import Flight, Trajectory
from fgnav.estimate import Estimate, TimeSeries
from fgnav.keys import B, D, G, S, V, X, describe
from fgnav.solvers.graph import GraphBuilder, GraphOptions

log = logging.getLogger(__name__)

#: Damping (information per unit tangent) added when the final system is indeterminate, so that the
#: observable marginals can still be computed: sigma of an unobservable direction = 100.
COVARIANCE_REGULARISATION = 1e-4
#: A regularised marginal sigma above this fraction of ``1/sqrt(COVARIANCE_REGULARISATION)`` marks
#: the variable as unobservable (reported in ``Estimate.info["covariance_unobservable"]``).
UNOBSERVABLE_SIGMA_FRACTION = 0.1
#: Largest tangent component of a QR step taken after Cholesky called the system indeterminate;
#: a larger (or non-finite) one means the system really is indeterminate (QR divided by a round-off
#: pivot) and the step is refused.
QR_STEP_MAX = 1e6


class SolverError(FgnavError, RuntimeError):
    """The solver could not produce an estimate (indeterminate system, divergence)."""


@dataclass
class LMOptions:
    """Levenberg-Marquardt loop options.

    Attributes:
        max_iterations: most outer iterations (linearizations).
        rel_tol: stop when the relative error decrease is below this (1e-4: on a 60 s figure8
            the iterations after that changed the error by 7e-5 relative and the ATE by 0.02 mm,
            at 0.4 s each per flight minute).
        abs_tol: stop when the error is below this.
        lambda_init: damping tried after the first rejected Gauss-Newton step.
        lambda_factor: multiplier of lambda on rejection (divisor on acceptance).
        lambda_max: give up the iteration (converged as far as possible) above this.
        lambda_min: below this the damping is dropped (pure Gauss-Newton).
        qr_fallback: when Cholesky calls a linear system indeterminate, solve the same system
            by QR (``EliminateQR``) and keep QR for the rest of the run, instead of retrying
            with more damping (see the module docstring: long flights). Off by default: on a
            weakly observable problem (30 s circle, seed 000 sensors, per-axis SLAM scale) QR
            converges in 7 iterations to a lower error (574.66 against 575.36 after 25 damped
            iterations) whose per-axis scale differs from the damped one (ky mean -5.2 % against
            the truth instead of within 5 %).
    """

    max_iterations: int = 30
    rel_tol: float = 1e-4
    abs_tol: float = 1e-9
    lambda_init: float = 1e-4
    lambda_factor: float = 10.0
    lambda_max: float = 1e8
    lambda_min: float = 1e-8
    qr_fallback: bool = False

    def validate(self) -> None:
        """The rules between fields (run when the options are read; the single values' bounds
        are :data:`fgnav.config.OPTION_BOUNDS`)."""
        if not 1.0 < self.lambda_factor <= 1e6:
            # <= 1: lambda never grew past lambda_max, a rejected step was retried without end.
            raise ValueError(
                f"LMOptions.lambda_factor={self.lambda_factor:g}: expected > 1 and <= 1e6 (the "
                "damping must grow on a rejected step)"
            )
        if self.lambda_init > self.lambda_max:
            # The first damped try was above lambda_max: the loop stopped at the initial guess
            # and called it converged.
            raise ValueError(
                f"LMOptions.lambda_init={self.lambda_init:g}: expected <= lambda_max = "
                f"{self.lambda_max:g}"
            )


@dataclass
class BatchOptions:
    """Options of the batch smoother.

    Attributes:
        graph: graph builder options.
        lm: Levenberg-Marquardt options.
        covariance: ``"all"`` (slow variables and poses), ``"slow"`` or ``"none"``.
        cov_pose_stride: marginal pose covariance every n-th keyframe (others NaN).
    """

    graph: GraphOptions = field(default_factory=GraphOptions)
    lm: LMOptions = field(default_factory=LMOptions)
    covariance: str = "all"
    cov_pose_stride: int = 1

    def validate(self) -> None:
        """The choice of ``covariance`` (run when the options are read; a bad name computed
        the covariances as "slow")."""
        if self.covariance not in ("all", "slow", "none"):
            raise ValueError(
                f"BatchOptions.covariance={self.covariance!r}: expected all, slow or none"
            )


@dataclass
class LMResult:
    """Result of :func:`levenberg_marquardt`."""

    values: gtsam.Values
    linear: gtsam.GaussianFactorGraph
    errors: list[float]
    iterations: int
    converged: bool
    #: linear solves that needed damping (indeterminate without it, with Cholesky and QR)
    n_damped: int = 0
    #: the variable GTSAM named when Cholesky first failed and QR took over (None: Cholesky
    #: throughout)
    qr_after: str | None = None


def _damping_graph(
    gfg: gtsam.GaussianFactorGraph, dims: dict[int, int], lam: float
) -> gtsam.GaussianFactorGraph:
    g = gtsam.GaussianFactorGraph()
    g.push_back(gfg)
    unit = {d: gtsam.noiseModel.Unit.Create(d) for d in set(dims.values())}
    s = math.sqrt(lam)
    for key, d in dims.items():
        g.add(gtsam.JacobianFactor(key, s * np.eye(d), np.zeros(d), unit[d]))
    return g


def levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, options: LMOptions | None = None
) -> LMResult:
    """Minimise ``graph.error`` from ``values`` with a Levenberg-Marquardt loop in Python.

    Raises:
        SolverError: the linear system is indeterminate even with damping.
    """
    o = options or LMOptions()
    err = graph.error(values)
    errors = [err]
    lam = 0.0
    zero = values.zeroVectors()
    dims = {k: int(zero.at(k).shape[0]) for k in values.keys()}
    n_fail = 0
    qr_after: str | None = None
    converged = False
    it = 0
    gfg = graph.linearize(values)
    for it in range(1, o.max_iterations + 1):
        accepted = False
        while True:
            try:
                lin = gfg if lam == 0.0 else _damping_graph(gfg, dims, lam)
                if qr_after is None:
                    try:
                        delta = lin.optimize()
                    except RuntimeError as e:
                        if not o.qr_fallback:
                            raise
                        delta = _qr_step(lin)
                        if delta is None:
                            raise
                        qr_after = _indeterminate_key(" ".join(str(e).split())) or "?"
                        log.info(
                            "LM: Cholesky called the system indeterminate near %s (damping "
                            "%.0e), QR solved it: QR from now on (qr_fallback)",
                            qr_after,
                            lam,
                        )
                else:
                    delta = _qr_step(lin)
                    if delta is None:
                        raise RuntimeError("QR step not finite or above QR_STEP_MAX")
            except RuntimeError as e:
                # Indeterminate (or badly conditioned) without damping: retry damped.
                n_fail += 1
                if lam >= o.lambda_max / o.lambda_factor:
                    raise SolverError(
                        "batch: indeterminate linear system even with damping "
                        f"({str(e).strip().splitlines()[0]}); some variable is unconstrained "
                        "(see the observability of the sensors used)"
                    ) from e
                delta = None
            if delta is not None:
                new_values = values.retract(delta)
                new_err = graph.error(new_values)
                if np.isfinite(new_err) and new_err <= err:
                    accepted = True
                    break
            lam = o.lambda_init if lam == 0.0 else lam * o.lambda_factor
            if lam > o.lambda_max:
                break
        if not accepted:
            log.info("LM: no decreasing step at lambda %.1e: stop", lam)
            converged = True
            break
        rel = (err - new_err) / max(err, 1e-300)
        log.info("LM iteration %d: error %.6g -> %.6g (lambda %.1e)", it, err, new_err, lam)
        values, err = new_values, new_err
        errors.append(err)
        lam = 0.0 if lam / o.lambda_factor < o.lambda_min else lam / o.lambda_factor
        gfg = graph.linearize(values)
        if rel < o.rel_tol or err < o.abs_tol:
            converged = True
            break
    if n_fail:
        log.info("LM: %d linear solves needed damping (indeterminate without it)", n_fail)
    return LMResult(values, gfg, errors, it, converged, n_fail, qr_after)


def _qr_step(lin: gtsam.GaussianFactorGraph) -> gtsam.VectorValues | None:
    """The Gauss-Newton step of ``lin`` by multifrontal QR, or None when it is not finite or has
    a component above :data:`QR_STEP_MAX` (the system is indeterminate indeed)."""
    try:
        delta = lin.optimize(gtsam.EliminateQR)
    except RuntimeError:
        return None
    v = delta.vector()
    if not np.all(np.isfinite(v)) or (v.size and float(np.max(np.abs(v))) > QR_STEP_MAX):
        return None
    return delta


def solve_batch(
    flight: Flight, options: BatchOptions | None = None, priors: Any = None, progress: bool = False
) -> Estimate:
    """Smooth a whole flight.

    Args:
        flight: the flight (ground truth, if any, is never used).
        options: batch options.
        priors: optional front-end priors (see :class:`GraphBuilder`).
        progress: show a progress bar while building the graph.

    Returns:
        ``Estimate(method="batch")`` at the keyframe times, with covariances per
        ``options.covariance``, SLAM scale per session, drag k and ground height.
    """
    o = options or BatchOptions()
    t_start = time.perf_counter()
    builder = GraphBuilder(flight, o.graph, priors)
    guess = builder.initial_guess()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=builder.K, desc="graph", unit="kf")
    graph, values = builder.build(guess, progress=(lambda k: bar.update(1)) if bar else None)
    if bar:
        bar.close()
    t_built = time.perf_counter()
    log.info(
        "graph: %d factors, %d variables, %d keyframes (%.2f s)",
        graph.size(),
        values.size(),
        builder.K,
        t_built - t_start,
    )
    res = levenberg_marquardt(graph, values, o.lm)
    t_solved = time.perf_counter()
    log.info(
        "LM: %d iterations, error %.6g -> %.6g (%.2f s)",
        res.iterations,
        res.errors[0],
        res.errors[-1],
        t_solved - t_built,
    )
    est = estimate_from_values(builder, res.values, method="batch")
    marg = None
    cov_info: dict[str, Any] = {"covariance_regularised": False}
    if o.covariance != "none":
        marg, cov_info = _marginals(res.linear, res.values, prefer_qr=res.qr_after is not None)
    pose_cov = vel_cov = None
    slow_sigma: dict[int, np.ndarray] = {}
    if marg is not None:
        wanted = list(_slow_keys(res.values))
        pose_ks = range(0, builder.K, max(1, o.cov_pose_stride)) if o.covariance == "all" else []
        wanted += [key for k in pose_ks for key in (X(k), V(k))]
        covs = _marginal_covariances(marg, res.linear, res.values, wanted, cov_info)
        slow_sigma = {k: np.sqrt(np.diag(covs[k])) for k in _slow_keys(res.values) if k in covs}
        if cov_info["covariance_regularised"] or cov_info.get("covariance_qr"):
            weak = [
                describe(k)
                for k, sg in slow_sigma.items()
                if np.max(sg) > UNOBSERVABLE_SIGMA_FRACTION / math.sqrt(COVARIANCE_REGULARISATION)
            ]
            cov_info["covariance_unobservable"] = weak
            if weak:
                log.warning(
                    "unobservable slow variables (sigma set by the regularisation): %s",
                    ", ".join(weak),
                )
        if o.covariance == "all":
            pose_cov = np.full((builder.K, 6, 6), np.nan)
            vel_cov = np.full((builder.K, 3, 3), np.nan)
            for k in pose_ks:
                pose_cov[k] = covs.get(X(k), np.nan)
                vel_cov[k] = covs.get(V(k), np.nan)
    t_cov = time.perf_counter()
    est = _with_slow(builder, res.values, est, slow_sigma)
    info = dict(est.info)
    info.update(
        {
            "lm_iterations": res.iterations,
            "lm_converged": res.converged,
            "lm_errors": [float(e) for e in res.errors],
            "lm_damped_solves": res.n_damped,
            "lm_qr_after": res.qr_after,
            "n_factors": int(graph.size()),
            "n_variables": int(values.size()),
            "time_build_s": t_built - t_start,
            "time_solve_s": t_solved - t_built,
            "time_covariance_s": t_cov - t_solved,
            "covariance": o.covariance,
            **cov_info,
            "cov_pose_stride": o.cov_pose_stride,
            "lm_options": asdict(o.lm),
        }
    )
    return replace(
        est,
        method="batch",
        pose_cov=pose_cov,
        vel_cov=vel_cov,
        runtime_s=time.perf_counter() - t_start,
        causal=False,
        info=info,
    ).check()


def _indeterminate_key(message: str) -> str | None:
    """The variable GTSAM names in an "Indeterminate linear system" message (``x12``), if any."""
    m = re.search(r"Symbol: ([A-Za-z]\d+)", message)
    return m.group(1) if m else None


class QrMarginals:
    """Marginal covariances from a multifrontal QR elimination (COLAMD ordering) of a linear
    graph: what ``gtsam.Marginals(graph, values, Marginals.QR)`` does in C++ (not wrapped).

    QR has no pivot test: a variable whose marginal is not finite and positive definite raises
    ``RuntimeError`` (as an indeterminate Cholesky would)."""

    def __init__(self, linear: gtsam.GaussianFactorGraph):
        ordering = gtsam.Ordering.ColamdGaussianFactorGraph(linear)
        self.bayes_tree = linear.eliminateMultifrontal(ordering, gtsam.EliminateQR)

    def marginalCovariance(self, key: int) -> np.ndarray:  # noqa: N802 (gtsam.Marginals' name)
        # The marginal eliminated by QR too: GaussianBayesTree.marginalCovariance eliminates the
        # shortcuts by Cholesky, which fails its pivot test there as well (900 s figure8: d0).
        info = np.asarray(self.bayes_tree.marginalFactor(key, gtsam.EliminateQR).information())
        try:
            cov = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            cov = np.full(info.shape, np.nan)
        if not np.all(np.isfinite(cov)) or np.min(np.diag(cov)) <= 0.0:
            raise RuntimeError(
                f"QR marginal covariance of {describe(key)} not finite and positive "
                "(Symbol: " + gtsam.DefaultKeyFormatter(key) + ")"
            )
        return cov


def _marginals(
    linear: gtsam.GaussianFactorGraph, values: gtsam.Values, prefer_qr: bool = False
) -> tuple[gtsam.Marginals | QrMarginals | None, dict[str, Any]]:
    """``gtsam.Marginals`` of the final linearization, never raising.

    An indeterminate system (an unobservable direction: the vertical SLAM scale at constant
    altitude, drag ky on a forward-only flight) is retried with a tiny damping
    (``COVARIANCE_REGULARISATION``) on every variable, so that the observable marginals can still
    be reported; the variable GTSAM names is logged and recorded. When that fails too (Cholesky's
    pivot test on a long flight, see the module docstring), the marginals come from QR
    (:class:`QrMarginals`). ``prefer_qr`` (the solve itself needed QR): QR first, the damped
    Cholesky after it. Returns the marginals (None when every way fails) and the
    ``Estimate.info`` entries.
    """
    info: dict[str, Any] = {"covariance_regularised": False}
    if prefer_qr:
        marg = _qr_marginals(linear, info)
        if marg is not None:
            return marg, info
    else:
        try:
            return gtsam.Marginals(linear, values), info
        except RuntimeError as e:
            msg = " ".join(str(e).split())
            near = _indeterminate_key(msg)
            info["covariance_indeterminate_near"] = near
    marg = _regularised_marginals(linear, values, info)
    if marg is None and not prefer_qr:
        marg = _qr_marginals(linear, info)
    if marg is None:
        _unavailable(info)
    return marg, info


def _qr_marginals(linear: gtsam.GaussianFactorGraph, info: dict[str, Any]) -> QrMarginals | None:
    """:class:`QrMarginals` (None when the elimination fails); records it in ``info``."""
    try:
        marg = QrMarginals(linear)
    except RuntimeError as e:
        info["covariance_qr_error"] = " ".join(str(e).split())
        return None
    info["covariance_qr"] = True
    near = info.get("covariance_indeterminate_near")
    log.info(
        "marginal covariances by QR (%s)",
        f"Cholesky called the system indeterminate near {near}" if near else "the solve needed QR",
    )
    return marg


def _unavailable(info: dict[str, Any]) -> None:
    """Record and log (whole message) that no marginal covariance could be computed."""
    msg = info.get("covariance_cholesky_error") or info.get("covariance_qr_error") or "?"
    info["covariance_unavailable"] = msg
    log.warning(
        "marginal covariances unavailable (indeterminate near %s): %s",
        info.get("covariance_indeterminate_near"),
        msg,
    )


def _regularised_marginals(
    linear: gtsam.GaussianFactorGraph, values: gtsam.Values, info: dict[str, Any]
) -> gtsam.Marginals | None:
    """Marginals with a ``COVARIANCE_REGULARISATION`` damping on every variable (None when even
    that fails); records and logs the outcome in ``info``."""
    near = info.get("covariance_indeterminate_near")
    zero = values.zeroVectors()
    dims = {k: int(zero.at(k).shape[0]) for k in values.keys()}
    try:
        marg = gtsam.Marginals(_damping_graph(linear, dims, COVARIANCE_REGULARISATION), values)
    except RuntimeError as e:
        # GTSAM's message, whole (it was cut at 160 characters, mid-sentence).
        info["covariance_cholesky_error"] = " ".join(str(e).split())
        return None
    info["covariance_regularised"] = True
    log.warning(
        "indeterminate system near %s: covariances computed with a %.0e damping (unobservable "
        "directions have sigma ~ %.0f)",
        near,
        COVARIANCE_REGULARISATION,
        1.0 / math.sqrt(COVARIANCE_REGULARISATION),
    )
    return marg


def _marginal_covariances(
    marg: gtsam.Marginals | QrMarginals,
    linear: gtsam.GaussianFactorGraph,
    values: gtsam.Values,
    keys: list[int],
    info: dict[str, Any],
) -> dict[int, np.ndarray]:
    """Marginal covariance of each key, never raising: GTSAM may only find an indeterminate
    system when a marginal is queried (after ``Marginals`` was built); then the regularised
    marginals are used (see :func:`_marginals`; QR after them), and a key whose covariance still
    fails is left out (counted in ``info["covariance_failed_keys"]``)."""
    if isinstance(marg, QrMarginals):
        return _each_covariance(marg, keys, info)
    try:
        return {k: marg.marginalCovariance(k) for k in keys}
    except RuntimeError as e:
        info["covariance_indeterminate_near"] = _indeterminate_key(" ".join(str(e).split()))
    out: dict[int, np.ndarray] = {}
    reg = (
        None if info.get("covariance_regularised") else _regularised_marginals(linear, values, info)
    )
    if reg is None and not info.get("covariance_qr"):
        reg = _qr_marginals(linear, info)
    if reg is None:
        _unavailable(info)
        return out
    return _each_covariance(reg, keys, info)


def _each_covariance(
    marg: gtsam.Marginals | QrMarginals, keys: list[int], info: dict[str, Any]
) -> dict[int, np.ndarray]:
    """Marginal covariance of each key that has one (failures counted in ``info``)."""
    out: dict[int, np.ndarray] = {}
    failed = 0
    for k in keys:
        try:
            out[k] = marg.marginalCovariance(k)
        except RuntimeError:
            failed += 1
    if failed:
        info["covariance_failed_keys"] = failed
    return out


def _slow_keys(values: gtsam.Values) -> list[int]:
    return [k for k in values.keys() if chr(gtsam.Symbol(k).chr()) in "sdg"]


def estimate_from_values(
    builder: GraphBuilder, values: gtsam.Values, method: str, keyframes: np.ndarray | None = None
) -> Estimate:
    """Trajectory (pose, velocity, biases) at the keyframes present in ``values``."""
    ks = np.arange(builder.K) if keyframes is None else np.asarray(keyframes, int)
    n = len(ks)
    pos, R = np.zeros((n, 3)), np.zeros((n, 3, 3))
    vel, bg, ba = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
    for i, k in enumerate(ks):
        p = values.atPose3(X(int(k)))
        pos[i], R[i] = p.translation(), p.rotation().matrix()
        vel[i] = values.atVector(V(int(k)))
        b = values.atConstantBias(B(int(k)))
        bg[i], ba[i] = b.gyroscope(), b.accelerometer()
    traj = Trajectory(builder.t_kf[ks].copy(), pos, matrix_to_quat_wxyz(R), vel, bg, ba)
    return Estimate(method=method, trajectory=traj, info=builder.report())


def axis_scale_summary(k: np.ndarray, sigma: np.ndarray) -> tuple[float, float | None]:
    """A session's scale from its per-axis scales ``k`` (3,) and their sigmas (3,): the geometric
    mean (the cube root of the product, negative when an odd number of axes are) and its sigma
    (first order, never negative; None when a sigma is unknown or an axis is 0)."""
    k = np.asarray(k, float)
    sigma = np.asarray(sigma, float)
    s = float(np.cbrt(np.prod(k)))
    if not (np.all(np.isfinite(sigma)) and np.all(k != 0)):
        return s, None
    return s, float(abs(s) * np.sqrt(np.sum((sigma / k) ** 2)) / 3.0)


def _with_slow(
    builder: GraphBuilder, values: gtsam.Values, est: Estimate, sigma: dict[int, np.ndarray]
) -> Estimate:
    """Fill SLAM scale, drag k and ground height (final values and series) from ``values``."""
    from fgnav.factors.slam_scale import slam_alignment_parts

    series: dict[str, TimeSeries] = dict(est.series)
    scale, scale_sigma = {}, {}
    nonpositive: dict[int, list[float]] = {}  # session -> its final per-axis scales
    t_kf = builder.t_kf
    if builder.use_slam:
        if builder.slam_model == "axis":
            # A chain of per-axis scale segments per session (seed 000's model); a session's
            # scale is its last segment's geometric mean.
            ts, ks, sgs = [], [], []
            a = builder.slam_assoc
            sess_of = builder.flight.slam.session[a.meas_index]
            for (sess, seg), j in sorted(builder.slam_var.items(), key=lambda kv: kv[1]):
                if not values.exists(S(j)):
                    continue
                rows = np.flatnonzero((builder.slam_chain == seg) & (sess_of == sess))
                ts.append(float(np.mean(t_kf[a.keyframe[rows]])) if len(rows) else t_kf[0])
                ks.append(values.atVector(S(j))[:3])
                sg = sigma.get(S(j))
                sgs.append(np.full(3, np.nan) if sg is None else np.asarray(sg, float)[:3])
                k, sg = ks[-1], sgs[-1]
                scale[sess], s_sig = axis_scale_summary(k, sg)
                if s_sig is not None:
                    scale_sigma[sess] = s_sig
                if not np.all(k > 0):
                    nonpositive[sess] = [float(v) for v in k]
                else:
                    nonpositive.pop(sess, None)
            if ks:
                order = np.argsort(ts, kind="stable")
                series["slam_axis_scale"] = TimeSeries(
                    np.asarray(ts)[order], np.asarray(ks)[order], np.asarray(sgs)[order]
                )
        else:
            ts, vs, ss, sess_ids = [], [], [], []
            slam = builder.flight.slam
            a = builder.slam_assoc
            for (sess, seg), j in sorted(builder.slam_var.items(), key=lambda kv: kv[1]):
                if not values.exists(S(j)):
                    continue
                s, _, _ = slam_alignment_parts(values.atSimilarity3(S(j)))
                sg = sigma.get(S(j))
                # Tangent lambda is the log scale: sigma_s = s sigma_lambda.
                s_sig = float(s * sg[6]) if sg is not None else np.nan
                rows = np.flatnonzero(
                    [
                        (int(slam.session[a.meas_index[r]]), int(builder.slam_chain[r]))
                        == (sess, seg)
                        for r in range(len(a.meas_index))
                    ]
                )
                t_mid = float(np.mean(t_kf[a.keyframe[rows]])) if len(rows) else float(t_kf[0])
                ts.append(t_mid)
                vs.append(s)
                ss.append(s_sig)
                sess_ids.append(sess)
                scale[sess] = float(s)
                if sg is not None:
                    scale_sigma[sess] = s_sig
            if ts:
                series["slam_scale"] = TimeSeries(np.asarray(ts), np.asarray(vs), np.asarray(ss))
                series["slam_session"] = TimeSeries(np.asarray(ts), np.asarray(sess_ids, float))
    drag_k = drag_sig = None
    if builder.drag_vars:
        segs = np.unique(builder.drag_segment)
        vals = np.array([values.atVector(D(int(j))) for j in segs])
        sg = [sigma.get(D(int(j))) for j in segs]
        drag_k = vals[-1]
        drag_sig = sg[-1]
        t_seg = np.array([t_kf[builder.drag_segment == j][0] for j in segs])
        series["drag_k"] = TimeSeries(
            t_seg, vals, None if any(x is None for x in sg) else np.array(sg)
        )
    ground = None
    if builder.use_range:
        segs = np.unique(builder.ground_segment)
        segs = [j for j in segs if values.exists(G(int(j)))]
        if segs:
            vals = np.array([values.atVector(G(int(j)))[0] for j in segs])
            sg = [sigma.get(G(int(j))) for j in segs]
            ground = float(vals[-1])
            t_seg = np.array([t_kf[builder.ground_segment == j][0] for j in segs])
            series["ground_height"] = TimeSeries(
                t_seg, vals, None if any(x is None for x in sg) else np.array([x[0] for x in sg])
            )
    info = est.info
    if nonpositive:
        for sess, k in sorted(nonpositive.items()):
            log.warning(
                "%s: SLAM session %d: per-axis scale %s SLAM units per metre: not positive on "
                "axis %s (the SLAM alignment failed; the scale summary is meaningless)",
                builder.flight.name,
                sess,
                ", ".join(f"{v:.4g}" for v in k),
                ", ".join("xyz"[i] for i in range(3) if not k[i] > 0),
            )
        info = {**info, "slam_axis_scale_nonpositive": {int(s): k for s, k in nonpositive.items()}}
    return replace(
        est,
        info=info,
        slam_scale=scale,
        slam_scale_sigma=scale_sigma,
        drag_k=drag_k,
        drag_k_sigma=drag_sig,
        ground_height=ground,
        series=series,
    )


__all__ = [
    "BatchOptions",
    "LMOptions",
    "LMResult",
    "SolverError",
    "levenberg_marquardt",
    "solve_batch",
    "estimate_from_values",
    "describe",
]
