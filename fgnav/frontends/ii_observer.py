"""Immersion-and-Invariance velocity and SLAM-scale observer of seed 000 (Gomez-Casasola &
Rodriguez-Cortes), eqs. 13-41.

Measurements (seed 000 sec. 2), in fgnav's frames (world z up, body FLU):

* ``y1 = a_h = -diag(k) V`` (eq. 3): horizontal specific force in body [m/s^2], the rotor drag of
  the horizontal body velocity ``V = [u, v]`` [m/s]; ``k = mu / m`` [1/s] (per axis allowed).
* ``y2 = diag(K) X_h`` (eq. 4): SLAM position x, y [SLAM units]; ``K = [kx, ky]`` SLAM units per
  metre, SLAM axes aligned with world x, y and the SLAM origin at the world origin (the paper's
  model; the camera is taken at the body origin).
* ``y3 = R = world_R_body``, ``y4 = Omega`` body rate [rad/s] (AHRS).
* ``y5 = w`` (eq. 5): body-z velocity [m/s]. The paper differentiates a rangefinder height; here the
  world vertical velocity ``world_vz`` comes from a 2-state Kalman filter on the rangefinder height
  driven by the vertical accelerometer (:func:`vertical_velocity_from_range`), and
  ``w = (world_vz - r31 u - r32 v) / r33`` (third row of ``X_dot = R V^b``, eq. 27).

Velocity observer (eqs. 14-23): ``sigma_dot = y1`` (eq. 15), ``beta_v = Gamma_v sigma`` (eq. 20),
``V_hat_dot = V_dot_model - k Gamma_v (V_hat - beta_v)`` (eq. 18), ``eta = V_hat - beta_v``
(eq. 23), error ``V_tilde_dot = -k Gamma_v V_tilde`` (eq. 22). It is integrated in the equivalent
form ``eta_dot = V_dot_model - k Gamma_v eta - Gamma_v y1`` (``sigma`` and ``V_hat`` grow without
bound with an accelerometer bias; ``eta`` does not).

Scale estimator (eqs. 25-41): ``X_hat_dot = R_h eta + y5 R_k`` (eq. 30 with ``eta`` for ``V``),
``beta = -Gamma_k diag(y2) X_hat_dot`` (eq. 38), ``K_hat_dot = -Gamma_k diag(X_hat_dot)
diag(K_hat - beta) X_hat_dot - Gamma_k diag(y2) X_hat_ddot`` (eq. 36 with the partial derivatives
of eq. 38 written out), ``xi = K_hat - beta`` (eq. 41). With ``V_tilde = 0`` the error obeys
``K_tilde_dot = -Gamma_k diag(X_dot)^2 K_tilde`` (proof of Prop. 1): persistent horizontal motion
(Assumption 1) is needed.

Typos and conventions resolved:

* Eq. 13 reads ``V = g R_v + y1``; it is the derivative: ``V_dot = g R_v + y1`` (from eqs. 12 and
  3), and eq. 17 uses it as such.
* The paper's frames are z-down (gravity ``+g R^T e3`` in eq. 1). In fgnav's z-up world the
  gravity term of the horizontal body dynamics is ``-g R_v`` with ``R_v = [r31, r32]`` (eq. 11),
  so the model is ``V_dot = -g R_v + y1`` (eq. 12/13 in fgnav frames).
* Eq. 16 and 26 print ``-d(V_tilde)/dt`` and ``-d(K_tilde)/dt`` where ``-d(V_hat)/dt`` and
  ``-d(K_hat)/dt`` are meant (the error definitions 14 and 25).
* Eq. 15 ``sigma_dot = -(mu/m) V`` is ``sigma_dot = y1`` (measurable by eq. 3).

Variants (``IIObserverOptions.kinematics``):

* ``"published"``: exactly the paper: Coriolis term neglected (eq. 8) and ``X_hat_ddot =
  R_h (-g R_v + y1)`` (eq. 36's ``d(beta)/d(eta) * V_dot``, with ``R_h``, ``R_k`` and ``y5`` held
  constant). Exact for constant attitude; biased when the body rotates (yawing turns).
* ``"full"``: ``V_dot = -g R_v + y1 - (Omega x V^b)_h`` and ``X_hat_ddot`` the time derivative of
  ``X_hat_dot = (R [eta; w])_h`` through ``R_dot = R Omega^`` and ``w_dot`` from the vertical
  accelerometer. It needs the 3-axis accelerometer; with ``Omega = 0`` it is the published one.

Discrete time. Between samples the ODE in ``(eta, K_hat, y2_pred)`` is integrated with RK4 and
inputs interpolated linearly between the two samples (first-order hold; a zero-order hold lags the
velocity by half a sample, 1.3 mm/s on the circle); ``y2_pred`` is the SLAM position predicted from
the last SLAM sample with ``y2_pred_dot = xi * X_hat_dot`` (a causal prediction, so ``beta`` is
continuous between SLAM samples). At a SLAM sample ``y2`` jumps to the measurement: ``K_hat`` is
kept, so ``xi`` jumps by ``Gamma_k diag(y2 - y2_pred) X_hat_dot`` -- the scale's innovation step.
Stability: the velocity ODE is linear with rate ``lambda_v = k gamma_v`` (plus the rotation rate in
the full variant); RK4 is stable for ``lambda dt < 2.78`` -- at 200 Hz and ``k gamma_v ~ 3 /s``,
``lambda dt ~ 0.015``. The scale step contracts the error by ``1 - gamma_k X_dot_i^2 dt_slam`` per
SLAM sample, stable for ``gamma_k X_dot_i^2 dt_slam < 2``; the step's gain is capped so that this
product stays below ``max_scale_step`` (1: dead-beat), which only acts at high speed (``gamma_k =
8``, 20 Hz SLAM: above ``|X_dot| = 1.6 m/s``). The capped steps are counted. SLAM samples are used
at their image times (``SlamSeries.t``): a sample arriving late is applied there by rolling the
observer back (:class:`IIObserverStepper` with a history; the seed-000 baseline), or at the
current time without one.
Not modelled: accelerometer bias (it biases ``eta`` by ``b / k``), wind, SLAM rotation/offset.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from operator import attrgetter, itemgetter
from typing import Any, Literal, NamedTuple

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import quat_wxyz_to_matrix
from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, RangeLimits
from fgnav.datasets.types import AttitudeSeries, Flight, Trajectory
from fgnav.estimate import Estimate, TimeSeries
from fgnav.frontends.attitude_ekf import GRAVITY

log = logging.getLogger(__name__)

#: Seed 000 sec. 4 gains: gamma_vx = gamma_vy = 7, gamma_kx = gamma_ky = 8.
PAPER_GAMMA_V = (7.0, 7.0)
PAPER_GAMMA_K = (8.0, 8.0)


@dataclass(frozen=True)
class IIObserverOptions:
    """Options of :class:`IIObserver`.

    Attributes:
        gamma_v: velocity gains ``Gamma_v = diag(gamma_vx, gamma_vy)`` (eq. 21) [-].
        gamma_k: scale gains ``Gamma_k = diag(gamma_kx, gamma_ky)`` (eq. 39) [s/m^2].
        drag_k: ``mu / m`` per body axis ``(kx, ky)`` [1/s]; None -> the flight's
            ``meta["drag_k"]`` (a calibration), else an error.
        kinematics: ``"published"`` (eqs. 8, 36 as printed) or ``"full"`` (see module docstring).
        eta0: initial horizontal body velocity estimate [m/s] (paper: 0).
        scale0: ``K_hat`` at the first SLAM sample of a session [SLAM units per metre] (paper:
            0); the first ``xi`` is ``scale0 - beta`` (eq. 41).
        max_scale_step: cap of ``gamma_k X_dot_i^2 dt_slam`` per SLAM sample (stability guard).
        scale_floor: positions are ``y2 / max(xi, scale_floor)`` [SLAM units per metre].
        gravity: [m/s^2].
    """

    gamma_v: tuple[float, float] = PAPER_GAMMA_V
    gamma_k: tuple[float, float] = PAPER_GAMMA_K
    drag_k: tuple[float, float] | None = None
    kinematics: Literal["published", "full"] = "published"
    eta0: tuple[float, float] = (0.0, 0.0)
    scale0: tuple[float, float] = (0.0, 0.0)
    max_scale_step: float = 1.0
    scale_floor: float = 1e-3
    gravity: float = GRAVITY


OBSERVER_DRAG_K_RANGE = (1e-2, 100.0)
"""The ``mu/m`` [1/s] the observer takes (a multirotor's is about 0.1-1; the top is the filters'
``drag_k`` bound): its horizontal velocity is the specific force over ``k``, so ``drag_k =
[1e-300, 1e-300]`` ran to 1e14 m and 1e-3 to 4e13 m (two-turns, 20 s; 0.4 m at the truth)."""


def drag_k_problem(k: Any) -> str | None:
    """What is wrong with an observer drag coefficient ``(kx, ky)`` (None: nothing)."""
    lo, hi = OBSERVER_DRAG_K_RANGE
    try:
        v = np.asarray(k, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        return "expected (kx, ky) [1/s]"
    if v.size != 2 or not np.all(np.isfinite(v)) or np.any(v < lo) or np.any(v > hi):
        return f"expected (kx, ky) in [{lo:g}, {hi:g}] [1/s]"
    return None


#: Layout of the flat input vector: specific force (3), body rate (3), world_R_body row-major (9),
#: world vertical velocity (1).
_N_INPUTS = 16


def _pack_inputs(body_accel, body_omega, world_R_body, world_vz) -> list[float]:
    return [
        *map(float, np.asarray(body_accel, float).reshape(3)),
        *map(float, np.asarray(body_omega, float).reshape(3)),
        *map(float, np.asarray(world_R_body, float).reshape(9)),
        float(world_vz),
    ]


class IIObserver:
    """The I&I observer with a filter shape: ``propagate`` to each input sample, ``update_slam``
    at each SLAM sample.

    State ``rho = (eta, K_hat)`` (paper: ``rho in R^4``) plus the predicted SLAM position
    ``y2_pred`` between SLAM samples. Between two input samples the inputs are interpolated
    linearly (first-order hold, causal: the integration to ``t`` uses inputs up to ``t``); the ODE
    is integrated with one RK4 step per interval. Scalar Python arithmetic (no small numpy arrays)
    keeps a step near 30 us.
    """

    def __init__(self, options: IIObserverOptions, drag_k: tuple[float, float] | None = None):
        """Args:
        options: gains and initial values.
        drag_k: ``mu/m`` per axis [1/s]; overrides ``options.drag_k``.
        """
        self.options = options
        k = drag_k if drag_k is not None else options.drag_k
        if k is None:
            raise FlightDataError(
                "I&I observer: the drag coefficient mu/m is unknown (IIObserverOptions.drag_k or "
                "flight.meta['drag_k'])"
            )
        self.k = np.asarray(k, dtype=float).reshape(2)
        if np.any(self.k <= 0):
            raise FlightDataError(f"I&I observer: drag_k must be positive, got {self.k}")
        problem = drag_k_problem(self.k)
        if problem is not None:  # (a flight's meta drag_k; the options check theirs)
            raise FlightDataError(f"I&I observer: drag_k={list(self.k)}: {problem}")
        if options.kinematics not in ("published", "full"):
            raise FlightDataError(
                f"IIObserverOptions.kinematics={options.kinematics!r}: expected 'published' or "
                "'full'"
            )
        self._full = options.kinematics == "full"
        self._kx, self._ky = map(float, self.k)
        self._gvx, self._gvy = map(float, options.gamma_v)
        self._gkx, self._gky = map(float, options.gamma_k)
        self._g = float(options.gravity)
        # state [eta_x, eta_y, K_hat_x, K_hat_y, y2_pred_x, y2_pred_y]
        self._s = [*map(float, options.eta0), *map(float, options.scale0), 0.0, 0.0]
        self._has_slam = False
        self._u: list[float] | None = None
        self.t: float | None = None
        self.t_last_slam: float | None = None
        self.capped_steps = 0

    @staticmethod
    def run(flight: Flight, options: IIObserverOptions | None = None, **kwargs) -> IIObserverResult:
        """Run over a whole flight: :func:`run_ii_observer` (keyword arguments passed on)."""
        return run_ii_observer(flight, options, **kwargs)

    # -- the paper's quantities -------------------------------------------------------------------

    def _parts(self, s, u):
        """w (y5), X_hat_dot (eq. 30), eta_dot (eq. 18) and X_hat_ddot (eq. 36's last factor)."""
        ex, ey = s[0], s[1]
        f0, f1, f2, o0, o1, o2, r00, r01, r02, r10, r11, r12, r20, r21, r22, vz = u
        g = self._g
        w = (vz - r20 * ex - r21 * ey) / r22  # y5 from the third row of eq. 27
        vdx = -g * r20 + f0  # eq. 13 in z-up frames: V_dot = -g R_v + y1
        vdy = -g * r21 + f1
        if self._full:
            c0 = o1 * w - o2 * ey  # Omega x V^b
            c1 = o2 * ex - o0 * w
            c2 = o0 * ey - o1 * ex
            vdx -= c0
            vdy -= c1
        # eq. 18 with beta_v = Gamma_v sigma (eq. 20), sigma_dot = y1 (eq. 15), eta = V_hat - beta_v
        edx = vdx - self._kx * self._gvx * ex - self._gvx * f0
        edy = vdy - self._ky * self._gvy * ey - self._gvy * f1
        xdx = r00 * ex + r01 * ey + w * r02  # eq. 30
        xdy = r10 * ex + r11 * ey + w * r12
        if self._full:
            a0, a1, a2 = c0 + edx, c1 + edy, c2 + (f2 - g * r22 - c2)
            xddx = r00 * a0 + r01 * a1 + r02 * a2
            xddy = r10 * a0 + r11 * a1 + r12 * a2
        else:
            xddx = r00 * vdx + r01 * vdy  # eq. 36: d(beta)/d(eta) (g R_v + y1)
            xddy = r10 * vdx + r11 * vdy
        return w, xdx, xdy, edx, edy, xddx, xddy

    def _deriv(self, s, u):
        _, xdx, xdy, edx, edy, xddx, xddy = self._parts(s, u)
        if not self._has_slam:
            return [edx, edy, 0.0, 0.0, 0.0, 0.0]
        Kx, Ky, yx, yy = s[2], s[3], s[4], s[5]
        gkx, gky = self._gkx, self._gky
        xix = Kx + gkx * yx * xdx  # eq. 41 with beta of eq. 38
        xiy = Ky + gky * yy * xdy
        # eq. 36: K_hat_dot = d(beta)/d(y2) diag(K_hat - beta) X_hat_dot + d(beta)/d(eta) V_dot
        kdx = -gkx * xdx * xix * xdx - gkx * yx * xddx
        kdy = -gky * xdy * xiy * xdy - gky * yy * xddy
        return [edx, edy, kdx, kdy, xix * xdx, xiy * xdy]

    # -- filter shape -----------------------------------------------------------------------------

    @property
    def eta(self) -> np.ndarray:
        """Horizontal body velocity estimate ``[u, v]`` (eq. 23) [m/s]."""
        return np.array(self._s[:2])

    @property
    def K_hat(self) -> np.ndarray:
        """The integrated scale state ``K_hat`` (eq. 36)."""
        return np.array(self._s[2:4])

    @property
    def y2_pred(self) -> np.ndarray | None:
        """SLAM position predicted since the last SLAM sample [SLAM units], None without SLAM."""
        return np.array(self._s[4:6]) if self._has_slam else None

    @property
    def xi(self) -> np.ndarray:
        """Scale estimate ``xi = K_hat - beta`` (eq. 41) [SLAM units per metre], (kx, ky)."""
        if not self._has_slam or self._u is None:
            return self.K_hat
        _, xdx, xdy, *_ = self._parts(self._s, self._u)
        return np.array(
            [self._s[2] + self._gkx * self._s[4] * xdx, self._s[3] + self._gky * self._s[5] * xdy]
        )

    def body_w(self) -> float:
        """Current ``y5 = w`` [m/s]."""
        return float(self._parts(self._s, self._u)[0])

    def world_velocity(self) -> np.ndarray:
        """``world_R_body [eta; w]`` [m/s]."""
        R = np.array(self._u[6:15]).reshape(3, 3)
        return R @ np.array([self._s[0], self._s[1], self.body_w()])

    def propagate(
        self,
        t: float,
        body_accel: np.ndarray,
        body_omega: np.ndarray,
        world_R_body: np.ndarray,
        world_vz: float,
    ) -> None:
        """Advance to time ``t`` [s], where the inputs take the given values.

        Args:
            t: time of this input sample [s] (the first call only latches the inputs).
            body_accel: (3,) specific force in body [m/s^2] (``y1`` is its x, y part).
            body_omega: (3,) body angular rate [rad/s] (``y4``).
            world_R_body: (3, 3) attitude (``y3``).
            world_vz: world vertical velocity [m/s] (gives ``y5``).
        """
        u1 = _pack_inputs(body_accel, body_omega, world_R_body, world_vz)
        if self._u is None:
            self._u, self.t = u1, float(t)
            return
        dt = float(t) - self.t
        if dt < 0:
            raise FlightDataError(f"I&I observer: time goes backwards ({t} after {self.t})")
        if dt > 0:
            u0 = self._u
            um = [0.5 * (a + b) for a, b in zip(u0, u1, strict=True)]
            s = self._s
            k1 = self._deriv(s, u0)
            k2 = self._deriv([a + 0.5 * dt * b for a, b in zip(s, k1, strict=True)], um)
            k3 = self._deriv([a + 0.5 * dt * b for a, b in zip(s, k2, strict=True)], um)
            k4 = self._deriv([a + dt * b for a, b in zip(s, k3, strict=True)], u1)
            self._s = [
                a + dt / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
                for a, b1, b2, b3, b4 in zip(s, k1, k2, k3, k4, strict=True)
            ]
        self._u, self.t = u1, float(t)

    def update_slam(self, y2: np.ndarray) -> None:
        """A SLAM position ``y2 = (x, y)`` [SLAM units] at the current time (``propagate`` to the
        SLAM time first). The first sample of a session only starts the scale estimator."""
        if self._u is None:
            raise FlightDataError("I&I observer: update_slam() before the first propagate()")
        yx, yy = map(float, np.asarray(y2, dtype=float).reshape(2))
        if not self._has_slam:
            self._has_slam = True
            self._s[4], self._s[5] = yx, yy
            self.t_last_slam = self.t
            return
        _, xdx, xdy, *_ = self._parts(self._s, self._u)
        dt_slam = max(self.t - self.t_last_slam, 1e-9)
        gains = []
        for gk, xd in ((self._gkx, xdx), (self._gky, xdy)):
            limit = self.options.max_scale_step / max(xd * xd * dt_slam, 1e-12)
            if gk > limit:
                self.capped_steps += 1
            gains.append(min(gk, limit))
        # K_hat is continuous, so xi = K_hat - beta(y2) jumps by Gamma_k diag(y2 - y2_pred) X_dot
        # (eqs. 38, 41); with a capped gain K_hat is moved so that xi takes the capped step.
        for i, (gk, gain, xd, y) in enumerate(
            ((self._gkx, gains[0], xdx, yx), (self._gky, gains[1], xdy, yy))
        ):
            innovation = y - self._s[4 + i]
            self._s[2 + i] += (gain - gk) * innovation * xd
            self._s[4 + i] = y
        self.t_last_slam = self.t

    def reset_scale(self) -> None:
        """Forget the SLAM session (map reset): the next ``update_slam`` starts a new scale."""
        self._has_slam = False
        self._s[2], self._s[3] = map(float, self.options.scale0)
        self._s[4] = self._s[5] = 0.0

    def snapshot(self) -> tuple:
        """The observer's whole state (for :meth:`restore`)."""
        return (
            list(self._s),
            self._u,
            self.t,
            self.t_last_slam,
            self._has_slam,
            self.capped_steps,
        )

    def restore(self, snap: tuple) -> None:
        """Go back to a :meth:`snapshot`."""
        s, self._u, self.t, self.t_last_slam, self._has_slam, self.capped_steps = snap
        self._s = list(s)


# ---------------------------------------------------------------------------------------------
# Vertical velocity (y5) from the rangefinder
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VerticalFilterOptions:
    """2-state (height, vertical velocity) Kalman filter on the rangefinder height, driven by the
    vertical specific force.

    Attributes:
        accel_noise: white noise of the vertical acceleration input [m/s^2/sqrt(Hz)] (accelerometer
            noise plus attitude error times g).
        range_sigma: height measurement noise [m].
        gate_sigmas: range readings with a normalised innovation above this are rejected.
        max_tilt: readings with the beam tilted more than this are skipped [rad].
    """

    accel_noise: float = 0.2
    range_sigma: float = 0.03
    gate_sigmas: float = 5.0
    max_tilt: float = np.deg2rad(45.0)


@dataclass(frozen=True, eq=False)
class VerticalVelocity:
    """World vertical velocity (and height above ground) at the IMU times.

    Attributes:
        t: (N,) [s]; world_vz: (N,) [m/s]; height: (N,) [m] (NaN before the first range reading);
        counts: readings used / rejected.
    """

    t: np.ndarray
    world_vz: np.ndarray
    height: np.ndarray
    counts: dict[str, int] = field(default_factory=dict)


class VerticalFilter:
    """The 2-state (height, vertical velocity) Kalman filter of
    :func:`vertical_velocity_from_range`, one step at a time (the whole-flight function and the
    event-fed :class:`fgnav.frontends.prior_stages.FrontendPriorStage` both run it).

    ``update_range(r, world_R_body)`` applies a reading [m] with the attitude at the current
    sample; ``predict(dt, world_R_body, body_accel)`` moves to the next sample with the vertical
    specific force of this one. ``world_vz`` is 0 and ``height`` NaN before the first reading.
    """

    def __init__(
        self,
        body_T_range: np.ndarray,
        range_min: float,
        range_max: float,
        options: VerticalFilterOptions | None = None,
    ) -> None:
        self.options = options or VerticalFilterOptions()
        T = np.asarray(body_T_range, dtype=float)
        self._beam, self._lever = T[:3, 2], T[:3, 3]
        self._limits = RangeLimits(range_min, range_max)
        self.x = np.zeros(2)
        self.P = np.diag([1e6, 1.0])
        self.started = False
        self.counts = {"used": 0, "out_of_limits": 0, "tilt": 0, "outlier": 0}

    @property
    def world_vz(self) -> float:
        return float(self.x[1]) if self.started else 0.0

    @property
    def height(self) -> float:
        return float(self.x[0]) if self.started else float("nan")

    def update_range(self, r: float, R: np.ndarray) -> None:
        options, counts = self.options, self.counts
        self._limits.see(r)
        why = self._limits.refusal(r)
        if why in RANGE_LIMIT_TAGS:
            key = why.replace("-", "_")  # at_min, at_max: no distance (range_refusal)
            counts[key] = counts.get(key, 0) + 1
            return
        if why is not None:
            counts["out_of_limits"] += 1
            return
        cos_tilt = -float(R[2] @ self._beam)
        if cos_tilt < np.cos(options.max_tilt):
            counts["tilt"] += 1
            return
        z = r * cos_tilt - float(R[2] @ self._lever)
        if not self.started:
            self.x = np.array([z, 0.0])
            self.P = np.diag([options.range_sigma**2, 0.25])
            self.started = True
            counts["used"] += 1
            return
        P = self.P
        S = P[0, 0] + options.range_sigma**2
        y = z - self.x[0]
        if y * y > options.gate_sigmas**2 * S:
            counts["outlier"] += 1
            return
        K = P[:, 0] / S
        self.x = self.x + K * y
        self.P = P - np.outer(K, P[0])
        counts["used"] += 1

    def predict(self, dt: float, R: np.ndarray, body_accel: np.ndarray) -> None:
        az = float(R[2] @ body_accel) - GRAVITY
        F = np.array([[1.0, dt], [0.0, 1.0]])
        self.x = F @ self.x + np.array([0.5 * dt * dt, dt]) * az
        q = self.options.accel_noise**2 * dt
        self.P = F @ self.P @ F.T + q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])


def vertical_velocity_from_range(
    flight: Flight,
    world_q_body_wxyz: np.ndarray,
    options: VerticalFilterOptions | None = None,
) -> VerticalVelocity:
    """Causal vertical velocity (seed 000's ``y5``) from the rangefinder and the accelerometer.

    Height from a reading: ``h = r cos(tilt) - (world_R_body body_t_range).z`` (flat ground, beam =
    the z axis of ``calib.body_T_range``); prediction with the world vertical acceleration
    ``(world_R_body f).z - g``. The paper's "numerical derivative of the height" is replaced by
    this filter (same information, no differentiation noise). Runs :class:`VerticalFilter`.

    Args:
        flight: needs ``imu`` and ``range``.
        world_q_body_wxyz: (N, 4) attitude at the IMU times.
        options: filter options.
    """
    imu, rng = flight.imu, flight.range
    if imu is None or rng is None:
        raise FlightDataError(f"{flight.name}: vertical velocity needs the imu and range streams")
    vf = VerticalFilter(
        flight.calib.body_T_range, flight.calib.range_min, flight.calib.range_max, options
    )
    R_all = quat_wxyz_to_matrix(world_q_body_wxyz)
    n = len(imu)
    vz = np.zeros(n)
    hh = np.full(n, np.nan)
    j = 0
    for i in range(n):
        # Range readings up to this IMU time.
        while j < len(rng) and rng.t[j] <= imu.t[i]:
            vf.update_range(float(rng.range[j]), R_all[i])
            j += 1
        if i + 1 < n:
            vf.predict(imu.t[i + 1] - imu.t[i], R_all[i], imu.body_accel[i])
        vz[i] = vf.world_vz
        hh[i] = vf.height
    return VerticalVelocity(t=imu.t.copy(), world_vz=vz, height=hh, counts=dict(vf.counts))


class ObserverOutput(NamedTuple):
    """The observer after one input sample: ``eta`` (2,) [m/s], ``world_v_body`` (3,) [m/s],
    ``xi`` (2,) [SLAM units per metre] and ``world_xy`` (2,) [m] (NaN without SLAM), ``session``
    (-1 before any SLAM)."""

    t: float
    eta: np.ndarray
    world_v_body: np.ndarray
    xi: np.ndarray
    world_xy: np.ndarray
    session: int


class _Step(NamedTuple):
    """One processed input sample in the stepper's history: its time and inputs, the state
    before it, and the SLAM poses it took from the queue."""

    t: float
    inputs: tuple
    before: tuple
    popped: list


class IIObserverStepper:
    """:class:`IIObserver` with the SLAM bookkeeping of :func:`run_ii_observer`, one input
    sample at a time: ``add_slam`` queues a SLAM pose, ``step`` applies the queued poses taken up
    to the sample's time, in capture order (propagating to each pose's time first, inputs
    interpolated between the previous sample and this one) and propagates to the sample. The
    event-fed :class:`fgnav.frontends.prior_stages.FrontendPriorStage` runs it (the seed-000
    baseline and the smoother's observer priors).

    A pose taken before the newest propagated time arrived late. With ``history_s`` > 0 the
    stepper keeps its state before each sample of the last ``history_s`` seconds (with the
    sample's inputs and the poses it took): a late pose rolls it back to the sample at or after
    the pose's time and the samples since are stepped again with the pose among them, so the state
    is what in-order processing gives (seed 004's delay compensation, fig. 2; the outputs already
    returned stay as they were: causal). Those poses are counted ``slam_delayed``. A pose older
    than the history, or any late pose with ``history_s`` = 0, is applied at the current time
    and counted ``slam_late``.
    """

    def __init__(
        self,
        options: IIObserverOptions,
        drag_k: tuple[float, float] | None,
        body_R_cam: np.ndarray,
        align_slam_axes: bool = False,
        history_s: float = 0.0,
    ) -> None:
        self.options = options
        self.observer = IIObserver(options, drag_k=drag_k)
        self.body_R_cam = np.asarray(body_R_cam, dtype=float)
        self.align = align_slam_axes
        self.history_s = float(history_s)
        self.counts = {
            "slam_used": 0,
            "slam_lost": 0,
            "slam_before_imu": 0,
            "scale_resets": 0,
        }
        self._queue: list = []  # (t, slam_t_cam, slam_q_cam_wxyz, session) in capture order
        self._prev: tuple | None = None  # (t, acc, gyr, R, vz) of the previous sample
        self._t_first: float | None = None
        self._current: int | None = None
        self._world_R_slam = np.eye(3)
        self._hist: deque[_Step] = deque()

    def add_slam(self, t: float, slam_t_cam, slam_q_cam_wxyz, session: int) -> None:
        bisect.insort(
            self._queue, (float(t), slam_t_cam, slam_q_cam_wxyz, int(session)), key=itemgetter(0)
        )

    def step(self, t, acc, gyr, R, vz) -> ObserverOutput:
        """One input sample (time [s], specific force, body rate, ``world_R_body``, world
        vertical velocity): the observer's output at it."""
        if self.history_s > 0:
            self._replay_late()
            before = self._snapshot()
        popped: list = []
        out = self._step(t, acc, gyr, R, vz, popped)
        if self.history_s > 0:
            hist = self._hist
            hist.append(_Step(t, (acc, gyr, R, vz), before, popped))
            while hist[0].t < t - self.history_s:
                hist.popleft()
        return out

    def _snapshot(self) -> tuple:
        return (
            self.observer.snapshot(),
            self._prev,
            self._t_first,
            self._current,
            self._world_R_slam,
            dict(self.counts),
        )

    def _restore(self, snap: tuple) -> None:
        obs, self._prev, self._t_first, self._current, self._world_R_slam, counts = snap
        self.observer.restore(obs)
        # What the rolled-back steps counted is counted again as they are stepped again; the
        # count of rolled-back poses is not part of the state.
        delayed = self.counts.get("slam_delayed")
        self.counts.clear()
        self.counts.update(counts)
        if delayed is not None:
            self.counts["slam_delayed"] = delayed

    def _replay_late(self) -> None:
        """Roll back and step again for the queued poses older than the observer (class
        docstring)."""
        obs, queue, hist = self.observer, self._queue, self._hist
        if not queue or not hist or not queue[0][0] < obs.t:
            return
        # Poses older than the history stay queued: applied at the current time (slam_late).
        t_before = hist[0].before[0][2]  # the observer's time before the oldest kept sample
        n_old = 0 if t_before is None else bisect.bisect_right(queue, t_before, key=itemgetter(0))
        n_late = bisect.bisect_left(queue, obs.t, key=itemgetter(0)) - n_old
        if n_late <= 0:
            return
        old, queue[:n_old] = queue[:n_old], []
        k = bisect.bisect_left(hist, queue[0][0], key=attrgetter("t"))  # first sample at or after
        steps = [hist.pop() for _ in range(len(hist) - k)][::-1]
        self._restore(steps[0].before)
        for st in steps:
            for pose in st.popped:
                bisect.insort(queue, pose, key=itemgetter(0))
        for st in steps:
            before, popped = self._snapshot(), []
            self._step(st.t, *st.inputs, popped)
            hist.append(_Step(st.t, st.inputs, before, popped))
        queue[:0] = old
        self.counts["slam_delayed"] = self.counts.get("slam_delayed", 0) + n_late

    def _step(self, t, acc, gyr, R, vz, popped: list) -> ObserverOutput:
        obs = self.observer
        counts = self.counts
        if self._prev is None:
            obs.propagate(t, acc, gyr, R, vz)  # latches the inputs
            self._t_first = t
        prev = self._prev
        while self._queue and self._queue[0][0] <= t:
            pose = self._queue.pop(0)
            popped.append(pose)
            ts, p, q, sid = pose
            if ts < self._t_first:
                counts["slam_before_imu"] += 1
                continue
            if sid < 0:
                counts["slam_lost"] += 1
                continue
            if ts > obs.t:
                # Inputs at the SLAM time, interpolated between the previous sample and this one.
                a = (ts - prev[0]) / (t - prev[0])
                obs.propagate(
                    ts,
                    (1 - a) * prev[1] + a * acc,
                    (1 - a) * prev[2] + a * gyr,
                    (1 - a) * prev[3] + a * R,
                    (1 - a) * prev[4] + a * vz,
                )
            elif prev is not None and ts < obs.t:
                counts["slam_late"] = counts.get("slam_late", 0) + 1
            if sid != self._current:
                if self._current is not None:
                    counts["scale_resets"] += 1
                obs.reset_scale()
                self._current = sid
                if self.align:
                    if prev is None:
                        w_R_b = R
                    else:
                        b = (ts - prev[0]) / (t - prev[0])
                        w_R_b = (1 - b) * prev[3] + b * R
                    m = w_R_b @ self.body_R_cam @ quat_wxyz_to_matrix(np.asarray(q, float)).T
                    U, _, Vt = np.linalg.svd(m)
                    self._world_R_slam = U @ Vt
            p = np.asarray(p, dtype=float)
            obs.update_slam((self._world_R_slam @ p)[:2] if self.align else p[:2])
            counts["slam_used"] += 1
        obs.propagate(t, acc, gyr, R, vz)
        self._prev = (t, acc, gyr, R, vz)
        y2p = obs.y2_pred
        nan2 = np.full(2, np.nan)
        if y2p is None:
            return ObserverOutput(t, obs.eta, obs.world_velocity(), nan2, nan2, -1)
        xi = obs.xi
        return ObserverOutput(
            t,
            obs.eta,
            obs.world_velocity(),
            xi,
            y2p / np.maximum(xi, self.options.scale_floor),
            int(self._current),
        )


# ---------------------------------------------------------------------------------------------
# Whole flight
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class IIObserverResult:
    """Time histories of :func:`run_ii_observer` at the IMU times.

    Attributes:
        t: (N,) [s].
        eta: (N, 2) horizontal body velocity estimate ``[u, v]`` [m/s] (eq. 23).
        xi: (N, 2) scale estimate ``[kx, ky]`` [SLAM units per metre] (eq. 41); NaN before the
            first SLAM sample of a session.
        world_v_body: (N, 3) ``world_R_body [eta; w]`` [m/s].
        world_t_body: (N, 3) position: ``y2_pred / xi`` for x, y [m] (NaN without SLAM) and the
            filtered rangefinder height for z (NaN without range).
        session: (N,) SLAM session id in use (-1 before any).
        world_q_body_wxyz: (N, 4) attitude used.
        counts: diagnostics (capped scale steps, SLAM samples used, skipped).
        options: the options used.
        drag_k: the ``mu/m`` used [1/s].
    """

    t: np.ndarray
    eta: np.ndarray
    xi: np.ndarray
    world_v_body: np.ndarray
    world_t_body: np.ndarray
    session: np.ndarray
    world_q_body_wxyz: np.ndarray
    counts: dict[str, int]
    options: IIObserverOptions
    drag_k: np.ndarray
    runtime_s: float = 0.0

    def final_scale(self) -> dict[int, np.ndarray]:
        """Last ``xi`` (kx, ky) of each SLAM session [SLAM units per metre]."""
        out = {}
        for s in np.unique(self.session):
            if s < 0:
                continue
            rows = np.flatnonzero((self.session == s) & np.isfinite(self.xi[:, 0]))
            if rows.size:
                out[int(s)] = self.xi[rows[-1]].copy()
        return out

    def to_estimate(self) -> Estimate:
        """The result as an :class:`Estimate` (method ``"ii-observer"``, causal).

        Rows where a position is undefined (before the first SLAM sample, or without height) are
        left out of the trajectory and counted in ``info["rows_without_position"]``.
        ``slam_scale`` is the mean of ``(kx, ky)`` per session (the observer's ``s``, SLAM units per
        metre); per-axis values are in ``series["slam_scale_xy"]`` and ``info``.
        """
        ok = np.all(np.isfinite(self.world_t_body), axis=1)
        traj = Trajectory(
            t=self.t[ok],
            world_t_body=self.world_t_body[ok],
            world_q_body_wxyz=self.world_q_body_wxyz[ok],
            world_v_body=self.world_v_body[ok],
        )
        finals = self.final_scale()
        return Estimate(
            method="ii-observer",
            trajectory=traj,
            slam_scale={s: float(np.mean(k)) for s, k in finals.items()},
            drag_k=self.drag_k.copy(),
            series={
                "slam_scale_xy": TimeSeries(t=self.t.copy(), value=self.xi.copy()),
                "body_velocity_xy": TimeSeries(t=self.t.copy(), value=self.eta.copy()),
            },
            runtime_s=self.runtime_s,
            causal=True,
            info={
                "options": self.options,
                "slam_scale_xy": {s: k.tolist() for s, k in finals.items()},
                "rows_without_position": int((~ok).sum()),
                **self.counts,
            },
        ).check()


def run_ii_observer(
    flight: Flight,
    options: IIObserverOptions | None = None,
    world_q_body_wxyz: np.ndarray | None = None,
    world_vz: np.ndarray | None = None,
    vertical: VerticalFilterOptions | None = None,
    align_slam_axes: bool = False,
) -> IIObserverResult:
    """The observer over a flight: its events replayed in time order into the event-fed stage
    (:class:`fgnav.frontends.prior_stages.FrontendPriorStage`, observer only), the SLAM poses at
    their capture times (no delivery latency; the seed-000 baseline,
    :class:`fgnav.baselines.seed000.Seed000`, replays them at their arrival).

    Args:
        flight: needs ``imu`` and ``slam``; ``attitude`` unless ``world_q_body_wxyz`` is given;
            ``range`` unless ``world_vz`` is given (then z is the integral of ``world_vz``
            from 0, counted as ``height_is_relative``). SLAM samples with a negative session id
            (tracking lost) are skipped and counted; a new session id resets the scale.
        options: observer options; ``drag_k`` None -> ``flight.meta["drag_k"]``.
        world_q_body_wxyz: (N, 4) attitude at the IMU times (e.g. from the attitude EKF),
            replayed as the attitude stream; default: ``flight.attitude`` (interpolated at each
            IMU sample once the samples around it have arrived).
        world_vz: (N,) world vertical velocity at the IMU times [m/s] (an analysis input, e.g. the
            truth); default: the rangefinder/accelerometer :class:`VerticalFilter`.
        vertical: options of the vertical filter.
        align_slam_axes: False: the paper's model, SLAM axes are world axes (``y2`` = SLAM x, y).
            True: each session's SLAM positions are first rotated into world axes with
            ``world_R_slam = world_R_body body_R_cam slam_R_cam^T`` at the session's first sample
            (causal), which makes a similarity SLAM (rotated frame, one scale) fit eq. 4 with
            ``kx = ky = s``. A constant SLAM offset does not affect the scale estimate (only
            ``y2_dot`` enters the error dynamics) but shifts the output positions by
            ``offset / xi``; the camera lever arm is not compensated.
    """
    from fgnav.datasets.events import replay, series_events, stream_events
    from fgnav.frontends.prior_stages import FrontendPriorStage, PriorOptions

    options = options or IIObserverOptions()
    imu, slam = flight.imu, flight.slam
    if imu is None or slam is None:
        raise FlightDataError(f"{flight.name}: the I&I observer needs the imu and slam streams")
    drag = options.drag_k if options.drag_k is not None else flight.meta.get("drag_k")
    attitude = flight.attitude
    if world_q_body_wxyz is not None:
        q = np.asarray(world_q_body_wxyz, dtype=float)
        if q.shape != (len(imu), 4):
            raise FlightDataError(
                f"{flight.name}: world_q_body_wxyz must be ({len(imu)}, 4) at the IMU times, "
                f"got {q.shape}"
            )
        attitude = AttitudeSeries(t=imu.t, world_q_body_wxyz=q)
    elif attitude is None:
        raise FlightDataError(
            f"{flight.name}: the I&I observer needs attitude (flight.attitude or the EKF's)"
        )
    given = None
    if world_vz is not None:
        world_vz = np.asarray(world_vz, dtype=float)
        if world_vz.shape != (len(imu),):
            raise FlightDataError(
                f"{flight.name}: world_vz must be ({len(imu)},) at the IMU times, got "
                f"{world_vz.shape}"
            )
        # No rangefinder height: z is the integral of world_vz from 0 (relative height).
        height = np.concatenate(
            [[0.0], np.cumsum(0.5 * (world_vz[1:] + world_vz[:-1]) * np.diff(imu.t))]
        )
        rows = zip(world_vz.tolist(), height.tolist(), strict=True)
        given = dict(zip(imu.t.tolist(), rows, strict=True)).__getitem__
    elif flight.range is None:
        raise FlightDataError(f"{flight.name}: vertical velocity needs the imu and range streams")
    k = None if drag is None else tuple(float(x) for x in np.ravel(drag)[:2])
    stage = FrontendPriorStage(
        flight.calib,
        PriorOptions(sources=("observer",), drag_k=k),
        keep_history=True,
        name=flight.name,
        observer_options=options,
        align_slam_axes=align_slam_axes,
        vertical_options=vertical,
        given_vertical=given,
    )
    t0 = time.perf_counter()
    streams = [
        stream_events(flight, "imu"),
        series_events(attitude, "attitude"),
        stream_events(flight, "range") if given is None else iter(()),
        stream_events(flight, "slam", 0.0),
    ]
    for ev in replay(streams):
        stage.feed(ev)
    stage.flush()
    res = dataclasses.replace(
        stage.observer_result(), options=options, runtime_s=time.perf_counter() - t0
    )
    log.info("I&I observer on %s: %s (%.2f s)", flight.name, res.counts, res.runtime_s)
    return res
