"""Seed 003 baseline: UKF with state augmentation for relative measurements (Shen's thesis ch. 5;
Shen, Mulgaonkar, Michael & Kumar, "Multi-sensor fusion for robust autonomous flight in indoor and
outdoor environments with a rotorcraft MAV", ICRA 2014, sec. III-IV).

Main state (seed 003 sec. 5.1, eq. 5.1), 17 entries::

    x = [world_p_body (3), Phi = (yaw, pitch, roll) (3), body_v (3), b_a (3), b_g (3), z_b (1),
         s (1)]

``world_p_body`` [m] in world (z up); ``Phi`` the ZYX Euler angles of ``world_R_body =
Rz(yaw) Ry(pitch) Rx(roll)`` [rad]; ``body_v`` the velocity in body (FLU) [m/s]; ``b_a``
[m/s^2] and ``b_g`` [rad/s] the IMU biases in body; ``z_b`` the altimeter bias in world [m] (here
the height of the ground under the rangefinder, which plays the role of Shen's pressure-altimeter
bias); ``s`` the monocular-SLAM scale [SLAM units per metre] (not in Shen's state: his relative
sensors are metric; see "SLAM scale" below).

Propagation (eq. 5.1, IMU-driven; one unscented transform per ``ut_interval_s`` = 10 ms, inside
which each sigma point is integrated IMU sample by IMU sample): with
``w = omega - b_g``, ``a = f - b_a`` (body), gravity ``(0, 0, -g)``::

    world_v = R body_v;   a_w = R a + g_w
    p+ = p + world_v dt + a_w dt^2 / 2;   R+ = R Exp(w dt);   body_v+ = R+^T (world_v + a_w dt)

biases, ``z_b`` and ``s`` are random walks. Process noise is additive: gyro noise mapped to Euler
rates (``E(Phi) sigma_g^2 dt E^T``), accelerometer noise on ``body_v``, the random walks.

Measurements (Shen: "absolute" and "relative", any rate):

* absolute, rangefinder (tilted, lever arm ``body_T_range``): ``r = (p_z + (R body_t_range)_z -
  z_b) / cos(tilt)``, ``cos(tilt) = -(R beam)_z`` (DESIGN.md 4.4; seed 002 eq. 21);
* absolute, yaw stream: ``yaw`` (residual wrapped to (-pi, pi]);
* absolute, attitude stream (off by default, ``use_attitude``): roll and pitch;
* relative, SLAM displacement between the keyframe pose i and a later pose j of one map, in
  camera i::

      z_t = slam_R_cam_i^T (slam_t_cam_j - slam_t_cam_i)
          = s body_R_cam^T (R_i^T (p_j + R_j body_t_cam - p_i) - body_t_cam)   [SLAM units]
      z_R = Log(slam_R_cam_i^T slam_R_cam_j) = Log(body_R_cam^T R_i^T R_j body_R_cam)

  Both are independent of the SLAM frame's rotation and origin (only the scale ``s`` enters).

State augmentation (stochastic cloning, Shen sec. III-A following Roumeliotis & Burdick 2002):
at the capture time of every image that has a SLAM pose the pose part ``[p, Phi]`` of the main
state is appended to the state (``x_aug = [x, B x]``, ``P_aug = M P M^T`` with ``M = [I; B]``),
together with that image's SLAM pose noise ``[a, rho]`` (``slam_t_cam = t + R a``,
``slam_R_cam = R Exp(rho)``; zero mean, ``(s slam_position_sigma_m)^2`` and
``slam_rotation_sigma^2``, independent of everything else). The relative measurement then predicts
``z_t = Exp(-rho_i) (s d + R_rel a_j - a_i)`` and ``z_R = Log(Exp(-rho_i) R_rel Exp(rho_j))``
exactly, with only a numerical ``1e-6`` of that noise left in ``R``: the keyframe's noise is
shared by every measurement against it and is estimated once, not counted again by each of them.
(Taking each relative measurement as independent, with noise ``2 (s sigma)^2``, made the filter
overconfident: position NEES 7-17 with 2 s keyframes on the simulated flights; with this,
1.2-4.1 on two-turns, rectangle and figure8, seeds 0 and 1, and the ATE halved: see the tests.)
A map that drifts makes later poses see the keyframe's pose offset by the drift since it was
taken: the pose noise of every clone random-walks (``slam_drift_walk_m``, ``slam_drift_walk_rot``,
the order of the MSF baseline's SLAM-frame walks). On EuRoC MH_01 with ORB-SLAM3 this brought the
NEES from 163 to 57 (ATE 0.158 -> 0.147 m): ORB-SLAM drifts more; 2.5 times larger walks give 11
there but NEES 0.5 on the simulated flights, so the defaults stay.
A relative measurement relates two clones (i: the keyframe, j: this image) and is fused when the
SLAM pose *arrives* (``t_j + latency``), so SLAM latency is handled exactly: the clone holds the
state at the image time. Afterwards clone j is marginalised (its rows and columns removed),
unless it is at least ``keyframe_interval_s`` after the keyframe: then the keyframe is
marginalised and j becomes the keyframe (Shen's augmented state is the relative sensor's
keyframe). Measured on two-turns, rectangle and figure8 (seed 1, full length, SLAM noise cloned
as below): ATE 0.061, 0.025, 0.034 m with every pose measured against the previous one
(``keyframe_interval_s=0``; scale -5.7 % after the hover of two-turns) vs 0.077, 0.018, 0.029 m
with 2 s keyframes (scale +1.7, +1.2, +1.8 %, the truth drifting +1.4 to +2 % over the flight);
the default keeps the scale.

Semi-definite covariance (Shen sec. III-B): right after cloning, ``P_aug`` is singular (the clone
equals part of the main state), so its Cholesky factor does not exist and sigma points cannot be
drawn from it. As in Shen's formulation, sigma points are never drawn from the augmented
covariance: propagation draws them from the main block ``P_xx`` only (the clones are static) and
carries the cross-covariances with the statistical linearisation ``F = P_{x+ x} P_xx^-1``
(``P_{x+ c} = F P_{x c}``); each update draws sigma points from the marginal of the variables its
measurement involves (positive definite: the clones of a relative measurement are at different
times, with process noise between them) and extends the gain to the whole augmented state by
Gaussian conditioning, ``P_{a z} = P_{a I} P_II^-1 P_{I z}``. The update is the usual
``K = P_{a z} S^-1``, ``P -= K S K^T``, Mahalanobis-gated (chi-square 0.999).

SLAM scale: Shen's relative sensors are metric; a monocular SLAM is not. The scale ``s`` is a
state (random walk, following a slowly drifting map scale); its initial value, the velocity, the
attitude (without an attitude stream) and the gyro bias come from the same causal closed-form fit
as the MSF baseline (:func:`fgnav.baselines.msf_ekf.initial_fit`): the filter starts at the end of
the first window of the flight that determines the scale, sliding past a static start (EuRoC),
and outputs from the arrival of that window's last SLAM pose (``Ukf003Options.initial_scale``
skips the fit and starts at the first SLAM pose). The measurement multiplies two uncertain
quantities (``s`` and the predicted displacement): without motion this errors-in-variables model
pulls ``s`` towards 0 (on the hover that starts two-turns, seed 1, with a 30 % initial sigma,
``s`` fell to zero within 4 s), so ``s`` is corrected only by displacements whose signal-to-noise
ratio exceeds ``scale_min_snr``; below it ``s`` is a Schmidt "consider" parameter (its
uncertainty enters the innovation covariance, its gain is zero).
A SLAM map reset (new session id) waits for the same closed-form fit on the new map's
data since its first pose, then restarts ``s`` and the clone chain. Tracking-lost samples
(negative session) and poses arriving out of order are skipped and counted.

Not modelled: rotor drag, correlated (drifting) SLAM errors beyond the scale random walk (on
EuRoC MH_01 the filter is overconfident, see the real-data test), IMU-camera time offset,
Euler-angle singularity at pitch +-90 deg (never reached by a multirotor in a FLU body), terrain
steps beyond the ``z_b`` random walk.

Reference: ../shared/seeds/003_*.txt (Shen's thesis ch. 5: state ``[p, Phi, p_dot^b, a_b^b,
omega_b^b, z_b^w]`` and eq. 5.1).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.linalg import cho_solve

from fgnav.baselines._arrived import Arrived
from fgnav.baselines._counts import SlamRangeCounts
from fgnav.baselines._inputs import (
    GAP_ACCEL_SIGMA,
    GAP_RATE_SIGMA,
    IMU_GAP_S,
    Inputs,
    unused_table,
)
from fgnav.baselines._options import SlamRangeOptions
from fgnav.baselines.msf_ekf import (
    FIT_RETRY_S,
    SCALE_INIT_WINDOWS_S,
    InitFit,
    arrived_initial_fit,
    new_map_scale_guess,
)
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import (
    AttitudeSample,
    Event,
    ImuSample,
    RangeReading,
    SlamPose,
    YawReading,
    flight_streams,
    replay,
)
from fgnav.datasets.geometry import (
    GRAVITY,
    matrix_to_quat_wxyz,
    matrix_to_rpy,
    quat_wxyz_to_matrix,
    rpy_to_matrix,
    skew,
    so3_exp,
    so3_log,
    wrap_angle,
)
from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, RangeLimits
from fgnav.datasets.types import Calibration, Flight, Trajectory
from fgnav.estimate import Estimate, TimeSeries, run_in_thrust_body

log = logging.getLogger(__name__)


# Main-state layout.
IP, IPHI, IV, IBA, IBG, IZB, IS = 0, 3, 6, 9, 12, 15, 16

ALIGN_HISTORY_S = 5.0
"""The fused poses are kept this long [s] (a gating reset goes back ``slam_reset_s`` before the
gating began: :meth:`Ukf003._good_before_gating`)."""
N_MAIN = 17
N_CLONE = 12
"""A clone holds ``[world_p_body (3), Phi (3), a (3), rho (3)]``: the pose at an image time and
that image's SLAM pose noise (``a`` translation in its camera frame [SLAM units], ``rho`` rotation
[rad]); its yaw is at offset 3."""
CLONE_POSE = 6
"""Entries of a clone copied from the main state (the pose)."""

CHI2_999 = {1: 10.83, 2: 13.82, 3: 16.27, 6: 22.46}
"""Chi-square quantiles (probability 0.999) for the gates, by measurement dimension."""

MIN_SCALE_REL_SIGMA = 0.02
"""Floor of the initial relative scale uncertainty (the closed-form fit neglects biases)."""

REINIT_GIVE_UP_S = 20.0
"""After a map reset, how long to wait for the closed-form scale before keeping the old one."""

RESET_SCALE_REL_SIGMA = 0.5
"""Relative scale uncertainty when the old scale is kept after a reset (no fit possible)."""


class CameraTrigger(NamedTuple):
    """An image was captured at ``t`` (the camera trigger); its SLAM pose arrives later."""

    t: float
    arrival: float


@dataclass
class Ukf003Options(SlamRangeOptions):
    """Options of :class:`Ukf003`: the shared SLAM and range options
    (:class:`~fgnav.baselines._options.SlamRangeOptions`; a displacement of two SLAM poses gets
    ``sqrt(2) * s * slam_position_sigma_m`` in SLAM units, ``use_slam_rotation`` fuses the
    relative rotation ``z_R``, and ``initial_scale_rel_sigma`` None is twice the closed-form
    fit's standard error) and:

    Attributes:
        slam_drift_walk_m [m/sqrt(s)], slam_drift_walk_rot [rad/sqrt(s)]: random walk of the
            SLAM pose noise of the clones (a map that drifts: later poses see the keyframe's pose
            offset by the drift since it was taken).
        use_yaw, yaw_sigma [rad]: yaw stream (absolute).
        use_attitude, attitude_sigma [rad], attitude_min_interval_s: roll and pitch of the
            attitude stream (absolute), at most one update per interval.
        initial_attitude_sigma [rad] (roll and pitch; yaw gets the yaw stream's sigma or this),
            initial_altimeter_bias_sigma [m]: initial standard deviations.
        altimeter_bias_walk: random walk of ``z_b`` [m / sqrt(s)].
        ut_alpha, ut_beta, ut_kappa: scaled unscented transform parameters (Julier 2002; Wan & van
            der Merwe 2000); alpha = 1, kappa = 0 puts the sigma points at ``sqrt(n)`` sigma.
        output_rate_hz: rate of the reported causal trajectory (Shen: 100 Hz fused output).
        keyframe_interval_s: SLAM poses are measured relative to the keyframe (the clone in the
            state) until one is at least this much later [s]; that one becomes the new keyframe
            (Shen et al. 2014 sec. III-A: the augmented state is the keyframe's; it is replaced
            when the relative sensor changes keyframe). 0: every pose relative to the previous.
        scale_min_snr: a relative measurement corrects the scale only when the keyframe
            displacement is at least this many noise standard deviations (the
            errors-in-variables bias of the scale is about ``1 / snr^2``); below it the scale is
            a "consider" parameter of the update (module docstring).
        ut_interval_s: longest span of IMU samples integrated (strapdown, sample by sample)
            inside one unscented propagation [s]; a measurement always ends a span. Shen's
            filter outputs at 100 Hz, hence 0.01 s.
    """

    slam_drift_walk_m: float = 2e-3
    slam_drift_walk_rot: float = 2e-4
    use_yaw: bool = True
    yaw_sigma: float = 0.03
    use_attitude: bool = False
    attitude_sigma: float = 0.01
    attitude_min_interval_s: float = 0.05
    initial_attitude_sigma: float = 0.02
    initial_altimeter_bias_sigma: float = 0.01
    altimeter_bias_walk: float = 0.005
    ut_alpha: float = 1.0
    ut_beta: float = 2.0
    ut_kappa: float = 0.0
    output_rate_hz: float = 100.0
    ut_interval_s: float = 0.01
    keyframe_interval_s: float = 2.0
    scale_min_snr: float = 10.0


@dataclass
class Ukf003Counts(SlamRangeCounts):
    """What the filter did with its measurements (reported in ``Estimate.info``)."""

    slam_lost: int = 0
    slam_out_of_order: int = 0
    slam_first_of_map: int = 0
    slam_no_clone: int = 0
    keyframes: int = 0
    slam_scale_considered: int = 0
    range_out_of_limits: int = 0
    yaw_updates: int = 0
    yaw_rejected_gate: int = 0
    attitude_updates: int = 0
    attitude_rejected_gate: int = 0
    cholesky_jitter: int = 0


# ----------------------------------------------------------------------------------------------
# Vectorised rotation helpers (rows are sigma points)
# ----------------------------------------------------------------------------------------------


def euler_to_matrix(phi: np.ndarray) -> np.ndarray:
    """(M, 3) ``(yaw, pitch, roll)`` -> (M, 3, 3) ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    return rpy_to_matrix(phi[:, 2], phi[:, 1], phi[:, 0])


def matrix_to_euler(R: np.ndarray) -> np.ndarray:
    """(M, 3, 3) rotations -> (M, 3) ``(yaw, pitch, roll)`` (ZYX)."""
    return matrix_to_rpy(R)[:, ::-1]


def euler_rate_matrix(phi: np.ndarray) -> np.ndarray:
    """3x3 ``E`` with ``(yaw, pitch, roll)_dot = E body_omega`` (ZYX)."""
    _, p, r = phi
    cp, tp, cr, sr = np.cos(p), np.tan(p), np.cos(r), np.sin(r)
    return np.array([[0.0, sr / cp, cr / cp], [0.0, cr, -sr], [1.0, sr * tp, cr * tp]])


def body_rotation_jacobian(phi: np.ndarray) -> np.ndarray:
    """3x3 ``J`` with ``R(phi + dphi) ~ R(phi) Exp(J dphi)`` (inverse of ``E``)."""
    _, p, r = phi
    cp, sp, cr, sr = np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    return np.array([[-sp, 0.0, 1.0], [sr * cp, cr, 0.0], [cr * cp, -sr, 0.0]])


def state_covariances(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose and world-velocity covariances of a main state ``x`` with covariance ``P``.

    Returns ``(pose_cov, vel_cov)``: (6, 6) in GTSAM's Pose3 tangent ``[rot, trans]`` in body
    frame (right perturbation, ``world_R_body Exp(dtheta)``, ``world_t_body + world_R_body
    drho``) and (3, 3) of ``world_v_body = world_R_body body_v``. First order at the mean:
    ``dtheta = J(Phi) dPhi`` (:func:`body_rotation_jacobian`), ``drho = world_R_body^T dp``,
    ``dv = world_R_body dbody_v - world_R_body [body_v]x J(Phi) dPhi``; the UKF's own covariance
    is a statistical linearisation, so this is exact only as the Euler-angle spread goes to 0
    (the neglected terms are of the order of the attitude variance, ~1e-4 at 0.01 rad).
    """
    phi, body_v = x[IPHI : IPHI + 3], x[IV : IV + 3]
    world_R_body = euler_to_matrix(phi[None])[0]
    Jr = body_rotation_jacobian(phi)
    J = np.zeros((6, N_MAIN))  # [rot (body), trans (body)] <- [p (world), Phi]
    J[0:3, IPHI : IPHI + 3] = Jr
    J[3:6, IP : IP + 3] = world_R_body.T
    Jv = np.zeros((3, N_MAIN))
    Jv[:, IV : IV + 3] = world_R_body
    Jv[:, IPHI : IPHI + 3] = -world_R_body @ skew(body_v) @ Jr
    P = P[:N_MAIN, :N_MAIN]
    return J @ P @ J.T, Jv @ P @ Jv.T


# ----------------------------------------------------------------------------------------------
# The filter
# ----------------------------------------------------------------------------------------------


class Ukf003:
    """UKF with stochastic cloning (see the module docstring for model and references).

    Use :meth:`run` on a flight, or drive it with :meth:`initialize`, :meth:`predict`,
    :meth:`clone`, :meth:`update_relative_slam`, :meth:`update_range`, :meth:`update_yaw` and
    :meth:`update_attitude`.
    """

    def __init__(self, options: Ukf003Options | None = None) -> None:
        self.opt = options or Ukf003Options()
        self.opt.check()  # (the config path checks it before; here the Python API)
        self.counts = Ukf003Counts()
        self.x = np.zeros(N_MAIN)
        self.P = np.eye(N_MAIN)
        self.clones: list[float] = []  # clone times, in state order after the main block
        self._session_scale: dict[int, tuple[float, float]] = {}  # final (s, sigma) of old maps
        self._noise = None
        self._body_T_cam = np.eye(4)
        self._body_T_range = np.eye(4)
        self._ut: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}
        self._ut_params = (self.opt.ut_alpha, self.opt.ut_beta, self.opt.ut_kappa)

    @property
    def scale(self) -> float:
        """SLAM scale ``s`` [SLAM units per metre]."""
        return float(self.x[IS])

    @property
    def scale_sigma(self) -> float:
        """Standard deviation of ``s``."""
        return float(np.sqrt(self.P[IS, IS]))

    @property
    def session(self) -> int | None:
        """The SLAM session (map id) the clones and ``s`` belong to; None before its first pose."""
        return self._session

    # -- unscented transform ---------------------------------------------------------------------

    def _weights(self, n: int) -> tuple[float, np.ndarray, np.ndarray]:
        """``(c, Wm, Wc)`` for dimension n: sigma points ``x +- c L_i``."""
        if n not in self._ut:
            a, b, k = self._ut_params
            lam = a * a * (n + k) - n
            wm = np.full(2 * n + 1, 0.5 / (n + lam))
            wc = wm.copy()
            wm[0] = lam / (n + lam)
            wc[0] = lam / (n + lam) + (1.0 - a * a + b)
            self._ut[n] = (float(np.sqrt(n + lam)), wm, wc)
        return self._ut[n]

    def _chol(self, A: np.ndarray) -> np.ndarray:
        """Lower Cholesky factor; adds a small jitter (counted) if A is not numerically PD."""
        try:
            return np.linalg.cholesky(A)
        except np.linalg.LinAlgError:
            self.counts.cholesky_jitter += 1
            eps = 1e-12 * max(1.0, float(np.trace(A)))
            return np.linalg.cholesky(0.5 * (A + A.T) + eps * np.eye(len(A)))

    def _sigma(
        self, mean: np.ndarray, cov: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        n = len(mean)
        c, wm, wc = self._weights(n)
        L = self._chol(cov)
        X = np.empty((2 * n + 1, n))
        X[0] = mean
        X[1 : n + 1] = mean + c * L.T
        X[n + 1 :] = mean - c * L.T
        return X, wm, wc, L

    def _angle_index(self) -> np.ndarray:
        return np.array([IPHI] + [N_MAIN + N_CLONE * k + 3 for k in range(len(self.clones))])

    # -- set-up ----------------------------------------------------------------------------------

    def initialize(
        self,
        world_R_body: np.ndarray,
        world_p_body: np.ndarray,
        world_v_body: np.ndarray,
        scale: float,
        scale_rel_sigma: float,
        body_T_cam: np.ndarray,
        body_T_range: np.ndarray,
        imu_noise,
        yaw_sigma: float | None = None,
    ) -> None:
        """Initial main state and covariance; no clones."""
        o = self.opt
        self._noise = imu_noise
        self._body_T_cam = np.asarray(body_T_cam, float)
        self._body_T_range = np.asarray(body_T_range, float)
        x = np.zeros(N_MAIN)
        x[IP : IP + 3] = world_p_body
        x[IPHI : IPHI + 3] = matrix_to_euler(world_R_body[None])[0]
        x[IV : IV + 3] = world_R_body.T @ np.asarray(world_v_body, float)
        x[IS] = scale
        sa = o.initial_attitude_sigma
        var = np.concatenate(
            [
                [1e-6] * 3,
                [(yaw_sigma or sa) ** 2, sa**2, sa**2],
                [o.initial_velocity_sigma**2] * 3,
                [o.initial_bias_sigma_accel**2] * 3,
                [o.initial_bias_sigma_gyro**2] * 3,
                [o.initial_altimeter_bias_sigma**2],
                [(scale_rel_sigma * scale) ** 2],
            ]
        )
        self.x, self.P, self.clones = x, np.diag(var), []
        nz = imu_noise
        q = np.zeros(N_MAIN)  # per second (position: per s^3, see predict)
        q[IP : IP + 3] = nz.accel_noise_density**2 / 3.0
        q[IV : IV + 3] = nz.accel_noise_density**2
        q[IBA : IBA + 3] = nz.accel_random_walk**2
        q[IBG : IBG + 3] = nz.gyro_random_walk**2
        q[IZB] = o.altimeter_bias_walk**2
        self._Q_unit = np.diag(q)

    # -- propagation -----------------------------------------------------------------------------

    def _f(self, X: np.ndarray, omegas: np.ndarray, fs: np.ndarray, dts: np.ndarray) -> np.ndarray:
        """Eq. 5.1 on (M, 17) sigma points (noise-free part), over the IMU samples ``omegas``,
        ``fs`` (K, 3) held for ``dts`` (K,) each (sequential strapdown steps)."""
        R = euler_to_matrix(X[:, IPHI : IPHI + 3])
        bg, ba = X[:, IBG : IBG + 3], X[:, IBA : IBA + 3]
        v_w = np.einsum("mij,mj->mi", R, X[:, IV : IV + 3])
        p = X[:, IP : IP + 3].copy()
        for omega, f, dt in zip(omegas, fs, dts, strict=True):
            a_w = np.einsum("mij,mj->mi", R, f - ba)
            a_w[:, 2] -= GRAVITY
            p += v_w * dt + 0.5 * dt * dt * a_w
            v_w = v_w + a_w * dt
            R = R @ so3_exp((omega - bg) * dt)
        Y = X.copy()
        Y[:, IP : IP + 3] = p
        phi1 = matrix_to_euler(R)
        phi1[:, 0] = X[:, IPHI] + wrap_angle(phi1[:, 0] - X[:, IPHI])  # keep yaw continuous
        Y[:, IPHI : IPHI + 3] = phi1
        Y[:, IV : IV + 3] = np.einsum("mji,mj->mi", R, v_w)
        return Y

    def predict(self, omega: np.ndarray, f: np.ndarray, dt: float | np.ndarray) -> None:
        """Propagate with body rate ``omega`` [rad/s] and specific force ``f`` [m/s^2] held over
        ``dt`` [s]; or, with (K, 3) ``omega``, ``f`` and (K,) ``dt``, over K consecutive IMU
        samples in one unscented transform. Clones are static; their cross-covariances follow
        ``F = P_{x+ x} P_xx^-1``."""
        omegas = np.atleast_2d(omega)
        fs = np.atleast_2d(f)
        dts = np.atleast_1d(np.asarray(dt, float))
        keep = dts > 0
        if not keep.any():
            return
        omegas, fs, dts = omegas[keep], fs[keep], dts[keep]
        T = float(dts.sum())
        o, nz = self.opt, self._noise
        Pxx = self.P[:N_MAIN, :N_MAIN]
        xm = self.x[:N_MAIN]
        X, wm, wc, _ = self._sigma(xm, Pxx)
        Y = self._f(X, omegas, fs, dts)
        y = wm @ Y
        y[IPHI] = Y[0, IPHI] + wm @ wrap_angle(Y[:, IPHI] - Y[0, IPHI])
        dY = Y - y
        dY[:, IPHI] = wrap_angle(dY[:, IPHI])
        dX = X - xm
        Pyy = (wc[:, None] * dY).T @ dY
        # Additive process noise (module docstring).
        Q = self._Q_unit * T
        Q[IP : IP + 3, IP : IP + 3] *= T * T
        E = euler_rate_matrix(xm[IPHI : IPHI + 3])
        Q[IPHI : IPHI + 3, IPHI : IPHI + 3] = E @ E.T * (nz.gyro_noise_density**2 * T)
        Q[IS, IS] = (o.scale_walk * xm[IS]) ** 2 * T
        gaps = dts[dts > IMU_GAP_S]
        if gaps.size:  # an IMU gap: the held sample says little about the motion over it
            Q[IP : IP + 3, IP : IP + 3] += np.eye(3) * float(
                np.sum((0.5 * GAP_ACCEL_SIGMA * gaps**2) ** 2)
            )
            Q[IV : IV + 3, IV : IV + 3] += np.eye(3) * float(np.sum((GAP_ACCEL_SIGMA * gaps) ** 2))
            Q[IPHI : IPHI + 3, IPHI : IPHI + 3] += np.eye(3) * float(
                np.sum((GAP_RATE_SIGMA * gaps) ** 2)
            )
        if len(self.x) > N_MAIN:
            Pyx = (wc[:, None] * dY).T @ dX
            F = np.linalg.solve(Pxx, Pyx.T).T
            Pxc = F @ self.P[:N_MAIN, N_MAIN:]
            self.P[:N_MAIN, N_MAIN:] = Pxc
            self.P[N_MAIN:, :N_MAIN] = Pxc.T
        self.x[:N_MAIN] = y
        self.P[:N_MAIN, :N_MAIN] = Pyy + Q
        if self.clones:
            # SLAM map drift: the pose noise of every clone (seen by later poses) random-walks.
            k = np.arange(len(self.clones)) * N_CLONE + N_MAIN + CLONE_POSE
            ia, ir = (k[:, None] + np.arange(3)).ravel(), (k[:, None] + 3 + np.arange(3)).ravel()
            self.P[ia, ia] += (o.slam_drift_walk_m * xm[IS]) ** 2 * T
            self.P[ir, ir] += o.slam_drift_walk_rot**2 * T

    # -- augmentation ----------------------------------------------------------------------------

    def clone(self, t: float) -> None:
        """Append ``[p, Phi]`` of the main state as a clone taken at time ``t``
        (``P_aug = M P M^T``, ``M = [I; B]``), with the SLAM pose noise of that image (zero mean,
        ``(s slam_position_sigma_m)^2`` and ``slam_rotation_sigma^2``, independent)."""
        o = self.opt
        n = len(self.x)
        m = CLONE_POSE
        sel = np.r_[IP : IP + 3, IPHI : IPHI + 3]
        self.x = np.concatenate([self.x, self.x[sel], np.zeros(N_CLONE - m)])
        P = np.zeros((n + N_CLONE, n + N_CLONE))
        P[:n, :n] = self.P
        P[n : n + m, :n] = self.P[sel, :]
        P[:n, n : n + m] = self.P[:, sel]
        P[n : n + m, n : n + m] = self.P[np.ix_(sel, sel)]
        noise = [(self.scale * o.slam_position_sigma_m) ** 2] * 3 + [o.slam_rotation_sigma**2] * 3
        P[n + m :, n + m :] = np.diag(noise)
        self.P = P
        self.clones.append(float(t))

    def drop_clone(self, k: int) -> None:
        """Marginalise clone k (remove its rows and columns)."""
        a = N_MAIN + N_CLONE * k
        keep = np.r_[0:a, a + N_CLONE : len(self.x)]
        self.x = self.x[keep]
        self.P = self.P[np.ix_(keep, keep)]
        del self.clones[k]

    def clone_index(self, t: float) -> int | None:
        """Index of the clone taken at time ``t``, or None."""
        for k, tc in enumerate(self.clones):
            if abs(tc - t) < 1e-9:
                return k
        return None

    # -- updates ---------------------------------------------------------------------------------

    def _update(
        self,
        idx: np.ndarray,
        h,
        z: np.ndarray,
        Rm: np.ndarray,
        wrap_z: np.ndarray | None = None,
        consider: np.ndarray | None = None,
    ) -> bool:
        """Unscented update with the measurement ``z = h(x[idx]) + n``, ``n ~ N(0, Rm)``.

        Sigma points come from the marginal of ``x[idx]`` only; the gain of the other state
        entries follows by Gaussian conditioning. ``wrap_z``: components of z that are angles.
        ``consider``: state entries whose uncertainty enters ``S`` but which are not corrected
        (Schmidt "consider" update: zero gain rows, general covariance update). Returns False
        when gated out."""
        P_II = self.P[np.ix_(idx, idx)]
        X, wm, wc, L = self._sigma(self.x[idx], P_II)
        Z = h(X)
        z_hat = wm @ Z
        dZ = Z - z_hat
        r = z - z_hat
        if wrap_z is not None:
            z_hat[wrap_z] = Z[0, wrap_z] + wm @ wrap_angle(Z[:, wrap_z] - Z[0, wrap_z])
            dZ[:, wrap_z] = wrap_angle(Z[:, wrap_z] - z_hat[wrap_z])
            r[wrap_z] = wrap_angle(z[wrap_z] - z_hat[wrap_z])
        dX = X - self.x[idx]
        ang = self._angle_index()
        local = np.flatnonzero(np.isin(idx, ang))
        dX[:, local] = wrap_angle(dX[:, local])
        S = (wc[:, None] * dZ).T @ dZ + Rm
        P_Iz = (wc[:, None] * dX).T @ dZ
        if self.opt.gate:
            d2 = float(r @ np.linalg.solve(S, r))
            if d2 > CHI2_999[len(z)]:
                return False
        P_az = self.P[:, idx] @ cho_solve((L, True), P_Iz)
        K = np.linalg.solve(S, P_az.T).T
        if consider is not None:
            K[consider] = 0.0
            KPza = K @ P_az.T
            self.P = self.P - KPza - KPza.T + K @ S @ K.T
        else:
            self.P = self.P - K @ S @ K.T
        self.x = self.x + K @ r
        self.x[ang] = wrap_angle(self.x[ang])
        self.P = 0.5 * (self.P + self.P.T)
        return True

    def update_range(self, r_meas: float) -> bool:
        """Tilted rangefinder reading [m] (module docstring)."""
        o = self.opt
        R_br = self._body_T_range[:3, :3]
        beam, lever = R_br[:, 2], self._body_T_range[:3, 3]
        c = -(euler_to_matrix(self.x[None, IPHI : IPHI + 3])[0] @ beam)[2]
        if c < np.cos(o.range_max_tilt_rad):
            self.counts.range_rejected_tilt += 1
            return False

        def h(X):  # X columns: p_z, yaw, pitch, roll, z_b
            R = euler_to_matrix(X[:, 1:4])
            cos_t = -(R @ beam)[:, 2]
            return ((X[:, 0] + (R @ lever)[:, 2] - X[:, 4]) / cos_t)[:, None]

        idx = np.array([IP + 2, IPHI, IPHI + 1, IPHI + 2, IZB])
        ok = self._update(idx, h, np.array([r_meas]), np.array([[o.range_sigma**2]]))
        return self.counts.gated("range", ok)

    def update_yaw(self, yaw: float) -> bool:
        """Yaw reading [rad] (residual wrapped)."""
        idx = np.array([IPHI])
        ok = self._update(
            idx,
            lambda X: X[:, :1],
            np.array([yaw]),
            np.array([[self.opt.yaw_sigma**2]]),
            wrap_z=np.array([0]),
        )
        return self.counts.gated("yaw", ok)

    def update_attitude(self, world_R_body: np.ndarray) -> bool:
        """Roll and pitch of an AHRS attitude reading."""
        phi = matrix_to_euler(world_R_body[None])[0]
        idx = np.array([IPHI + 1, IPHI + 2])
        ok = self._update(
            idx, lambda X: X, phi[1:], np.eye(2) * self.opt.attitude_sigma**2, wrap_z=np.array([1])
        )
        return self.counts.gated("attitude", ok)

    def update_relative_slam(
        self,
        k_i: int,
        k_j: int,
        slam_t_cam_i: np.ndarray,
        slam_R_cam_i: np.ndarray,
        slam_t_cam_j: np.ndarray,
        slam_R_cam_j: np.ndarray,
    ) -> bool:
        """Relative SLAM measurement between clones ``k_i`` (earlier) and ``k_j`` (module
        docstring); the SLAM frame's rotation and origin cancel, its scale is ``s``."""
        o = self.opt
        R_bc, b_tc = self._body_T_cam[:3, :3], self._body_T_cam[:3, 3]
        z_t = slam_R_cam_i.T @ (slam_t_cam_j - slam_t_cam_i)
        ai, aj = N_MAIN + N_CLONE * k_i, N_MAIN + N_CLONE * k_j
        idx = np.r_[ai : ai + N_CLONE, aj : aj + N_CLONE, IS]
        rot = o.use_slam_rotation
        c = N_CLONE

        def h(X):
            # Clone i: X[:, 0:12], clone j: X[:, 12:24], s: X[:, 24].
            Ri, Rj = euler_to_matrix(X[:, 3:6]), euler_to_matrix(X[:, c + 3 : c + 6])
            d = X[:, c : c + 3] + Rj @ b_tc - X[:, 0:3]
            body_d = np.einsum("mji,mj->mi", Ri, d) - b_tc
            Rrel = np.einsum("ji,mjk->mik", R_bc, np.einsum("mji,mjk->mik", Ri, Rj)) @ R_bc
            # The SLAM poses' noise: slam_t = t + e, slam_R = R Exp(rho), a = R^T e per image.
            a_j = np.einsum("mij,mj->mi", Rrel, X[:, c + 6 : c + 9])
            t_cam = X[:, 24:25] * (body_d @ R_bc) + a_j - X[:, 6:9]
            E_i = so3_exp(-X[:, 9:12])
            # Predicted minus measured displacement in camera i [SLAM units] (z = 0).
            zt = np.einsum("mij,mj->mi", E_i, t_cam) - z_t
            if not rot:
                return zt
            return np.concatenate([zt, so3_log(E_i @ Rrel @ so3_exp(X[:, c + 9 : c + 12]))], 1)

        s = self.x[IS]
        var_t = (
            2.0 * (s * o.slam_position_sigma_m) ** 2
            + (np.linalg.norm(z_t) * o.slam_rotation_sigma) ** 2
        )
        # The measurement noise is in the clones (a, rho of both images): what remains is numerical.
        eps = 1e-6
        if rot:
            z = np.concatenate([np.zeros(3), so3_log(slam_R_cam_i.T @ slam_R_cam_j)])
            Rm = eps * np.diag(
                [(s * o.slam_position_sigma_m) ** 2] * 3 + [o.slam_rotation_sigma**2] * 3
            )
        else:
            z, Rm = np.zeros(3), eps * np.eye(3) * (s * o.slam_position_sigma_m) ** 2
        # Errors in variables: with a displacement buried in noise, the uncertain predicted
        # displacement enters through the product s d and biases s towards 0 (the scale
        # collapsed on the hover of two-turns); s is only corrected by displacements with a
        # signal-to-noise ratio of at least scale_min_snr.
        excited = np.linalg.norm(z_t) >= o.scale_min_snr * np.sqrt(var_t)
        ok = self._update(idx, h, z, Rm, consider=None if excited else np.array([IS]))
        if ok and not excited:
            self.counts.slam_scale_considered += 1
        return self.counts.gated("slam", ok)

    # -- whole flight ----------------------------------------------------------------------------

    def run(self, flight: Flight) -> Estimate:
        """Run over a flight in arrival order and return the causal estimate.

        When the body's z axis is more than ``MAX_BODY_TILT_DEG`` from the thrust axis
        (:func:`fgnav.datasets.frames.thrust_axis`; EuRoC's IMU frame, x up: the ZYX Euler angles
        would sit near pitch -90 deg), the filter runs in an internal body with z along it
        (:func:`fgnav.estimate.run_in_thrust_body`) and its estimate is rotated back to the
        flight's body.
        """
        return run_in_thrust_body(flight, self._run, MAX_BODY_TILT_DEG)

    def _run(self, flight: Flight) -> Estimate:
        imu, slam = flight.imu, flight.slam
        missing = [n for n, s in (("imu", imu), ("slam", slam)) if s is None]
        if missing:
            raise FlightDataError(
                f"{flight.name}: the seed-003 UKF needs the imu and slam streams; missing "
                f"{', '.join(missing)}"
            )
        self.counts.slam_lost = int(np.count_nonzero(slam.session < 0))
        if np.count_nonzero(slam.session >= 0) < 2:
            raise FlightDataError(f"{flight.name}: fewer than two tracked SLAM poses")
        self.start(flight.calib, flight.name)
        streams = flight_streams(flight, ("imu", "slam", "range", "yaw", "attitude"))
        # The camera trigger: an image's capture time is known when it is taken (the SLAM pose
        # for it arrives later); the filter clones its state then.
        trigger = (CameraTrigger(float(t), float(t)) for t in slam.t)
        order = [streams.pop("imu"), trigger, *streams.values()]
        for ev in replay(order):
            self.feed(ev)
        return self.result()

    # -- event stream (the filter never sees the flight; see fgnav.datasets.events) --------------

    def start(self, calib: Calibration, name: str = "flight") -> None:
        """Prepare to be fed events of a vehicle with calibration ``calib``."""
        self._calib, self._name = calib, name
        self._hist = Arrived()
        self._pre: list[Event] = []  # non-IMU events that arrived before the start
        self._imu_prev: ImuSample | None = None
        self._cur_t = -np.inf
        self._batch: tuple[list, list, list] = ([], [], [])
        self._session: int | None = None
        self._ref: tuple[float, np.ndarray, np.ndarray] | None = None  # reference pose
        self._pending: tuple[int, float] | None = None
        self._t_last_att = -np.inf
        self._next_fit_try = -np.inf
        self._next_out = np.inf
        self._out: tuple[list, list, list, list] = ([], [], [], [])  # t, x, P, altimeter bias
        self._scale_hist: tuple[list, list, list, list] = ([], [], [], [])
        self._lat: list[float] = []
        self._t0 = time.perf_counter()
        self._started = False
        self._redo = False
        self._inputs = Inputs("ukf003", name)
        self._range_limits = RangeLimits(calib.range_min, calib.range_max)
        self._slam_gated_since: float | None = None
        # Each pose whose displacement was fused, by time: (session, its SLAM pose, its clone's
        # world position and attitude and the scale and its variance after the update), what a
        # gating reset goes back to (_reset_from_slam); the last ALIGN_HISTORY_S of them.
        self._good: dict[float, tuple] = {}

    def feed(self, ev: Event) -> None:
        """One event in arrival order: IMU sample, camera trigger, SLAM pose, range, yaw or
        attitude (a corrupted IMU sample is dropped and counted: :mod:`fgnav.baselines._inputs`).
        """
        if not self._started:
            if not self._inputs.take(ev):
                return
            self._hist.add(ev)
            if isinstance(ev, CameraTrigger):
                self._pre.append(ev)
            elif isinstance(ev, ImuSample):
                self._try_start(ev.arrival)
            return
        if not self._redo and not self._inputs.take(ev):
            return
        if isinstance(ev, ImuSample | SlamPose | AttitudeSample):
            self._hist.add(ev)  # for the scale guess of a new map
        if isinstance(ev, ImuSample):
            self._imu_step(ev)
            return
        if self._imu_prev is None:
            return
        t_ev = ev.arrival if isinstance(ev, SlamPose) else ev.t
        if t_ev > self._cur_t:
            self._hold(t_ev - self._cur_t)
            self._cur_t = t_ev
        self._flush()
        w0 = time.perf_counter()
        if isinstance(ev, CameraTrigger):
            self.clone(ev.t)
            return
        if isinstance(ev, SlamPose):
            self._on_slam(ev)
            h = self._scale_hist
            for lst, v in zip(
                h,
                (
                    self._cur_t,
                    self.scale,
                    self.scale_sigma,
                    0 if self._session is None else int(self._session),
                ),
                strict=True,
            ):
                lst.append(v)
        elif isinstance(ev, RangeReading):
            if not self.opt.use_range:
                return
            self._range_limits.see(float(ev.range))
            why = self._range_limits.refusal(float(ev.range))
            if why in RANGE_LIMIT_TAGS:
                key = f"range_{why.replace('-', '_')}"  # range_at_min, range_at_max: no distance
                self.counts.extra[key] = self.counts.extra.get(key, 0) + 1
                return
            if why is not None:
                self.counts.range_out_of_limits += 1
                return
            self.update_range(float(ev.range))
        elif isinstance(ev, YawReading):
            if not self.opt.use_yaw:
                return
            self.update_yaw(float(ev.yaw))
        elif isinstance(ev, AttitudeSample):
            o = self.opt
            if not o.use_attitude or ev.t - self._t_last_att < o.attitude_min_interval_s:
                return
            self._t_last_att = ev.t
            self.update_attitude(quat_wxyz_to_matrix(ev.world_q_body_wxyz))
        else:
            return
        self._lat.append(time.perf_counter() - w0)

    def latest(self) -> np.ndarray | None:
        """The main state vector (module docstring layout), None before the start."""
        return self.x[:N_MAIN].copy() if self._started else None

    @property
    def output_t(self) -> float | None:
        """Time of the newest state of the causal trajectory (None before the first output)."""
        t = self._out[0]
        return t[-1] if t else None

    def latest_output(self) -> tuple[float, np.ndarray, np.ndarray] | None:
        """The newest state of the causal trajectory: ``(t, x, P)`` with the main state and its
        covariance (module docstring layout) at time ``t``, as :meth:`result` reports it; None
        before the first output."""
        t, x, P, _ = self._out
        return (t[-1], x[-1].copy(), P[-1].copy()) if t else None

    def _hold(self, dt: float) -> None:
        """Hold the previous IMU sample for ``dt`` (zero-order hold; batched)."""
        w, f, d = self._batch
        w.append(self._imu_prev.body_omega)
        f.append(self._imu_prev.body_accel)
        d.append(dt)

    def _flush(self) -> None:
        w, f, d = self._batch
        if d:
            self.predict(np.asarray(w), np.asarray(f), np.asarray(d))
            w.clear(), f.clear(), d.clear()

    def _imu_step(self, ev: ImuSample) -> None:
        o = self.opt
        if self._imu_prev is not None:
            self._hold(ev.t - self._cur_t)
            self._cur_t = ev.t
            due = self._cur_t >= self._next_out - 1e-9
            if sum(self._batch[2]) >= o.ut_interval_s - 1e-9 or due:
                self._flush()
            if due:
                t, x, P, zb = self._out
                t.append(self._cur_t)
                x.append(self.x[:N_MAIN].copy())
                P.append(self.P[:N_MAIN, :N_MAIN].copy())
                zb.append(self.x[IZB])
                self._next_out += 1.0 / o.output_rate_hz
        else:
            self._cur_t = ev.t
            self._next_out = max(self._next_out, ev.t)
        self._imu_prev = ev
        t_keep = ev.t - REINIT_GIVE_UP_S - 1.0
        self._hist.trim(t_keep if self._pending is None else min(t_keep, self._pending[1]))

    def _try_start(self, t_now: float) -> None:
        """Start once the arrived data fix the SLAM scale (closed-form fit on the arrived prefix,
        sliding past a static start), or at the first tracked SLAM pose with a given scale."""
        o, h = self.opt, self._hist
        if not h.slam or t_now < self._next_fit_try:
            return
        self._next_fit_try = t_now + FIT_RETRY_S
        prefix = h.flight(self._calib, self._name)
        slam = prefix.slam
        good = np.flatnonzero(slam.session >= 0)
        if len(good) < 2:
            return
        t_start = max(float(prefix.imu.t[0]), float(slam.t[good[0]]))
        t_first_out = t_start
        fit = None
        if o.initial_scale is not None:
            s0, v0, rel0 = float(o.initial_scale), np.zeros(3), 0.15
        else:
            fit = arrived_initial_fit(h, prefix, t_now, self.counts)
            if fit is None:
                return
            s0, v0, rel0 = fit.scale, fit.world_v_body_end, fit.rel_std
            t_start = fit.t_end
            j_end = min(int(np.searchsorted(slam.t, t_start)), len(slam) - 1)
            t_first_out = t_start + max(0.0, float(slam.latency[j_end]))
        R0, yaw_sigma = self._initial_attitude(prefix, t_start, fit)
        if fit is not None:
            # The fit's velocity is in its own world (yaw of its attitude); keep it in body.
            v0 = R0 @ fit.world_R_body_end.T @ v0
        rel = (
            o.initial_scale_rel_sigma
            if o.initial_scale_rel_sigma is not None
            else max(2.0 * rel0, MIN_SCALE_REL_SIGMA)
        )
        c = self._calib
        p0 = np.array([0.0, 0.0, self._initial_height(prefix, t_start, R0)])
        self.initialize(R0, p0, v0, s0, rel, c.body_T_cam, c.body_T_range, c.imu_noise, yaw_sigma)
        self.counts.extra["initial_scale"] = s0
        if fit is not None:
            self.x[IBG : IBG + 3] = fit.gyro_bias
        self._started = True
        self._next_out = t_first_out
        # Re-deliver what arrived since t_start, in arrival order (ties as the replay orders).
        later: list[Event] = [e for e in self._pre if e.t >= t_start]
        later += [e for e in h.slam if e.t >= t_start and e.session >= 0]
        later += [e for e in h.others_from(t_start)]
        rank = {
            ImuSample: 0,
            CameraTrigger: 1,
            SlamPose: 2,
            RangeReading: 3,
            YawReading: 4,
            AttitudeSample: 5,
        }
        redo = sorted(later + h.imu_from(t_start), key=lambda e: (e.arrival, rank[type(e)]))
        self._pre.clear()
        self._redo = True  # (taken and counted when they arrived)
        for e in redo:
            self.feed(e)
        self._redo = False

    def result(self) -> Estimate:
        """The causal estimate of everything fed so far."""
        if not self._started:
            raise FlightDataError(
                f"{self._name}: no window of the flight determines the SLAM scale; pass "
                "Ukf003Options.initial_scale"
            )
        self._flush()
        self.counts.extra["clones_left"] = len(self.clones)
        out_t, out_x, out_P, zb = self._out
        sh_t, sh, ss, sh_sid = self._scale_hist
        series = {
            "slam_scale": TimeSeries(np.asarray(sh_t), np.asarray(sh), np.asarray(ss)),
            "slam_session": TimeSeries(np.asarray(sh_t), np.asarray(sh_sid, dtype=int)),
            "altimeter_bias": TimeSeries(np.asarray(out_t), np.asarray(zb)),
        }
        return self._estimate(
            out_t, out_x, out_P, self._lat, series, self._session, time.perf_counter() - self._t0
        )

    def _on_slam(self, ev: SlamPose) -> None:
        """A SLAM pose arrives: relative update against the reference clone, map resets."""
        if ev.session < 0:
            return
        t_j, sid = float(ev.t), int(ev.session)
        R_j = quat_wxyz_to_matrix(ev.slam_q_cam_wxyz)
        k_j = self.clone_index(t_j)
        if k_j is None:
            self.counts.slam_no_clone += 1
            return
        if self._session is None:
            # First pose: the clone becomes the reference.
            self.counts.slam_first_of_map += 1
            self._keep_only_clone(k_j)
            self._session, self._ref, self._pending = sid, (t_j, ev.slam_t_cam, R_j), None
            return
        if sid != self._session:
            if self._pending is None or self._pending[0] != sid:
                self._pending = (sid, t_j)
            guess = self._reinit_guess(self._pending[1], t_j, self._cur_t)
            if guess is None:
                self.counts.slam_waiting_reinit += 1
                self.drop_clone(k_j)
                return
            s_new, rel = guess
            self._session_scale[self._session] = (self.scale, self.scale_sigma)
            self._reset_scale(s_new, rel)
            self.counts.session_resets += 1
            self._keep_only_clone(self.clone_index(t_j))
            self._session, self._ref, self._pending = sid, (t_j, ev.slam_t_cam, R_j), None
            return
        t_ref, p_ref, R_ref = self._ref
        k_i = self.clone_index(t_ref)
        if k_i is None or t_j <= t_ref:
            self.counts.slam_out_of_order += 1
            self.drop_clone(k_j)
            return
        if self.update_relative_slam(k_i, k_j, p_ref, R_ref, ev.slam_t_cam, R_j):
            self._slam_gated_since = None
            aj = N_MAIN + N_CLONE * k_j
            pose = self.x[aj : aj + 6].copy()
            slam_t = np.asarray(ev.slam_t_cam, float)
            self._good[t_j] = (sid, slam_t, R_j, pose, self.scale, float(self.P[IS, IS]))
            if min(self._good) < t_j - ALIGN_HISTORY_S:
                self._good = {t: g for t, g in self._good.items() if t >= t_j - ALIGN_HISTORY_S}
        elif self._slam_gated_since is None:
            self._slam_gated_since = t_j
        elif t_j - self._slam_gated_since >= self.opt.slam_reset_s:
            self._reset_from_slam(ev, k_j, R_j)
            return
        if t_j - t_ref < self.opt.keyframe_interval_s - 1e-9:
            self.drop_clone(k_j)  # same keyframe: the next pose is measured against it again
            return
        # New keyframe: marginalise the old one; clones older than j can never be used.
        for k in reversed(range(len(self.clones))):
            if self.clones[k] < t_j - 1e-9:
                if k != k_i:
                    self.counts.slam_out_of_order += 1
                self.drop_clone(k)
        self.counts.keyframes += 1
        self._ref = (t_j, ev.slam_t_cam, R_j)

    def _unused(self) -> dict[str, int]:
        """``info["unused"]`` (:mod:`fgnav.baselines._inputs`)."""
        c = self.counts
        return unused_table(
            c.unused(),
            self._inputs.unused,
            {
                "range:out-of-limits": c.range_out_of_limits,
                "range:at-min": c.extra.get("range_at_min", 0),
                "range:at-max": c.extra.get("range_at_max", 0),
                "slam:lost": c.slam_lost,
                "slam:out-of-order": c.slam_out_of_order,
                "slam:no-clone": c.slam_no_clone,
                "yaw:gated": c.yaw_rejected_gate,
                "attitude:gated": c.attitude_rejected_gate,
            },
        )

    def _reset_from_slam(self, ev: SlamPose, k_j: int, R_j: np.ndarray) -> None:
        """Every SLAM displacement gated for ``slam_reset_s``: the filter has diverged (its
        velocity, from a corrupted IMU sample or a gap). The velocity restarts from the SLAM
        displacement since the reference keyframe (through the scale, the extrinsics and the
        attitude), with its initial uncertainty; the biases keep their values with theirs; this
        pose becomes the reference keyframe (counted in ``gating_resets``, a warning). First the
        scale goes back to its value ``slam_reset_s`` before the gating began and the position
        to the SLAM displacement since the newest fused pose (:meth:`_good_before_gating`,
        :meth:`_reset_position`)."""
        o = self.opt
        # The scale and position as the poses fused before the fault left them (the ones
        # fused between the fault and the gate's closing had moved them).
        good = self._good_before_gating(int(ev.session))
        if good is not None:
            self._restore_scale(good)
            newest = self._good[max(self._good)]
            self._reset_position(ev, k_j, newest if newest[0] == int(ev.session) else good)
        t_ref, p_ref, R_ref = self._ref
        R_bc = self._body_T_cam[:3, :3]
        world_R_body = euler_to_matrix(self.x[None, IPHI : IPHI + 3])[0]
        # Displacement in the reference camera, then in the current body frame [m].
        d_cam = R_ref.T @ (np.asarray(ev.slam_t_cam, float) - np.asarray(p_ref, float))
        world_R_cam_ref = world_R_body @ R_bc @ R_j.T @ R_ref
        v_world = world_R_cam_ref @ d_cam / (self.scale * max(float(ev.t) - t_ref, 1e-3))
        main = np.r_[IPHI : IPHI + 3, IV : IV + 3, IBA : IBA + 3, IBG : IBG + 3]
        self.x[IV : IV + 3] = world_R_body.T @ v_world
        self.P[main, :] = 0.0
        self.P[:, main] = 0.0
        sa = o.initial_attitude_sigma
        var = [sa**2] * 3 + [o.initial_velocity_sigma**2] * 3
        var += [o.initial_bias_sigma_accel**2] * 3 + [o.initial_bias_sigma_gyro**2] * 3
        self.P[main, main] = var
        self._keep_only_clone(k_j)
        self._ref = (float(ev.t), ev.slam_t_cam, R_j)
        self._slam_gated_since = None
        self.counts.gating_resets += 1
        if self.counts.gating_resets == 1:
            log.warning(
                "ukf003: %s: every SLAM displacement gated for %.1f s (the filter diverged) at "
                "%.2f s: velocity re-initialised from the SLAM",
                self._name,
                o.slam_reset_s,
                ev.t,
            )

    def _good_before_gating(self, session: int) -> tuple | None:
        """The newest fused pose of this map ``slam_reset_s`` before the poses began to be
        gated (those fused between the fault and the gate's closing had moved the scale and
        the position: after one 150 m/s^2 accelerometer sample the restart kept both and the
        estimate settled 0.44 m off); None without one."""
        if self._slam_gated_since is None:
            return None
        t_back = self._slam_gated_since - self.opt.slam_reset_s
        older = [t for t, g in self._good.items() if t <= t_back and g[0] == session]
        return self._good[max(older)] if older else None

    def _restore_scale(self, good: tuple) -> None:
        """The scale and its variance of ``good`` (:meth:`_good_before_gating`), uncorrelated."""
        self.x[IS] = good[4]
        self.P[IS, :] = 0.0
        self.P[:, IS] = 0.0
        self.P[IS, IS] = good[5]
        self.counts.extra["gating_scale_restored"] = (
            self.counts.extra.get("gating_scale_restored", 0) + 1
        )

    def _reset_position(self, ev: SlamPose, k_j: int, good: tuple) -> None:
        """A gating reset's position: the diverged filter's drift since the fused pose ``good``
        (the newest of this map) replaced by the SLAM displacement since it, through the
        (restored) scale and that pose's fused attitude, in the clone of this pose and in the
        main state alike (the relative measurements never see an absolute position: a drift
        kept as the new reference stayed for good). Their variances grow by the scale's and the
        two poses' noise, as one shared error."""
        _, t_g, R_g_slam, pose_g, _, _ = good
        o = self.opt
        R_bc, b_tc = self._body_T_cam[:3, :3], self._body_T_cam[:3, 3]
        aj = N_MAIN + N_CLONE * k_j
        R_g = euler_to_matrix(pose_g[None, 3:6])[0]
        R_now = euler_to_matrix(self.x[None, aj + 3 : aj + 6])[0]
        z_t = R_g_slam.T @ (np.asarray(ev.slam_t_cam, float) - t_g)  # camera g [SLAM units]
        d = R_g @ (R_bc @ z_t / self.scale + b_tc) - R_now @ b_tc
        delta = pose_g[0:3] + d - self.x[aj : aj + 3]
        self.x[aj : aj + 3] += delta
        self.x[IP : IP + 3] += delta
        var = (np.linalg.norm(d) * self.scale_sigma / self.scale) ** 2
        var += 2.0 * o.slam_position_sigma_m**2
        both = np.r_[IP : IP + 3, aj : aj + 3]
        self.P[np.ix_(both, both)] += var * np.kron(np.ones((2, 2)), np.eye(3))
        self.counts.extra["gating_reset_shift_m"] = float(np.linalg.norm(delta))

    def _keep_only_clone(self, k: int) -> None:
        """Drop every clone except k, and those taken after it (pending images)."""
        t_k = self.clones[k]
        for m in reversed(range(len(self.clones))):
            if self.clones[m] < t_k - 1e-9:
                self.drop_clone(m)

    def _reset_scale(self, scale: float, rel_sigma: float) -> None:
        self.x[IS] = scale
        self.P[IS, :] = 0.0
        self.P[:, IS] = 0.0
        self.P[IS, IS] = (rel_sigma * scale) ** 2

    def _reinit_guess(
        self, t_first: float, t_meas: float, t_now: float
    ) -> tuple[float, float] | None:
        """Scale of a new map (:func:`~fgnav.baselines.msf_ekf.new_map_scale_guess`) from the
        arrived data; None while undetermined; after ``REINIT_GIVE_UP_S`` the old scale with
        ``RESET_SCALE_REL_SIGMA``."""
        if t_meas - t_first > REINIT_GIVE_UP_S:
            self.counts.extra["reinit_gave_up"] = self.counts.extra.get("reinit_gave_up", 0) + 1
            return self.scale, RESET_SCALE_REL_SIGMA
        if t_meas - t_first < SCALE_INIT_WINDOWS_S[0]:
            return None
        prefix = self._hist.flight(self._calib, self._name)
        return new_map_scale_guess(prefix, t_first, t_meas, t_now, MIN_SCALE_REL_SIGMA)

    def _initial_attitude(
        self, flight: Flight, t_start: float, fit: InitFit | None = None
    ) -> tuple[np.ndarray, float | None]:
        """Attitude stream if present, else the closed-form fit's (gyro-integrated from a level
        start) or the accelerometer tilt; yaw from the yaw stream when present. Returns
        ``(world_R_body, yaw sigma or None)``."""
        from fgnav.datasets.geometry import rpy_to_matrix
        from fgnav.solvers.measurements import level_rotation_from_accel

        if flight.attitude is not None:
            att = flight.attitude
            k = min(int(np.searchsorted(att.t, t_start)), len(att) - 1)
            R = quat_wxyz_to_matrix(att.world_q_body_wxyz[k])
        elif fit is not None:
            R = fit.world_R_body_end
        else:
            imu = flight.imu
            k = (imu.t >= t_start) & (imu.t <= t_start + 0.5)
            R = level_rotation_from_accel(imu.body_accel[k].mean(axis=0))
        yaw_sigma = None
        if self.opt.use_yaw and flight.yaw is not None:
            yw = flight.yaw
            k = min(int(np.searchsorted(yw.t, t_start)), len(yw) - 1)
            _, pitch, roll = matrix_to_euler(R[None])[0]
            R = rpy_to_matrix(roll, pitch, float(yw.yaw[k]))
            yaw_sigma = self.opt.yaw_sigma
        return R, yaw_sigma

    def _initial_height(self, flight: Flight, t_start: float, R0: np.ndarray) -> float:
        """Height of the body above the ground (``z_b = 0``) from the first valid range reading
        (0 without a rangefinder)."""
        rng = flight.range
        if rng is None or not self.opt.use_range:
            return 0.0
        c = flight.calib
        usable = RangeLimits.of_stream(rng.range, c.range_min, c.range_max).mask(rng.range)
        ok = np.flatnonzero(usable & (rng.t >= t_start))
        if ok.size == 0:
            return 0.0
        # Median of the first readings resists an obstacle spike.
        r = float(np.median(rng.range[ok[:5]]))
        T = np.asarray(c.body_T_range, float)
        cos_t = -(R0 @ T[:3, 2])[2]
        return r * cos_t - (R0 @ T[:3, 3])[2]

    def _estimate(self, out_t, out_x, out_P, lat, series, session, wall) -> Estimate:
        n = len(out_t)
        X = np.asarray(out_x).reshape(n, N_MAIN)
        R = euler_to_matrix(X[:, IPHI : IPHI + 3])
        v_w = np.einsum("nij,nj->ni", R, X[:, IV : IV + 3])
        pose_cov = np.empty((n, 6, 6))
        vel_cov = np.empty((n, 3, 3))
        for k in range(n):
            pose_cov[k], vel_cov[k] = state_covariances(X[k], out_P[k])
        traj = Trajectory(
            t=np.asarray(out_t, float),
            world_t_body=X[:, IP : IP + 3].copy(),
            world_q_body_wxyz=matrix_to_quat_wxyz(R),
            world_v_body=v_w,
            gyro_bias=X[:, IBG : IBG + 3].copy(),
            accel_bias=X[:, IBA : IBA + 3].copy(),
        )
        sid = 0 if session is None else int(session)
        scales = {**self._session_scale, sid: (self.scale, self.scale_sigma)}
        return Estimate(
            method="ukf003",
            trajectory=traj,
            pose_cov=pose_cov,
            vel_cov=vel_cov,
            slam_scale={k: v[0] for k, v in scales.items()},
            slam_scale_sigma={k: v[1] for k, v in scales.items()},
            ground_height=float(self.x[IZB]),
            series=series,
            update_latency=np.asarray(lat),
            runtime_s=wall,
            causal=True,
            info={
                "options": dataclasses.asdict(self.opt),
                "counts": dataclasses.asdict(self.counts),
                "unused": self._unused(),
                **self._inputs.info(("slam", "range", "yaw", "attitude")),
            },
        ).check()


MAX_BODY_TILT_DEG = 45.0
"""Largest angle of the initial specific force from body z before an internal body is used."""


def run_ukf003(flight: Flight, options: Ukf003Options | None = None) -> Estimate:
    """Run the seed-003 UKF over a flight (library entry point)."""
    return Ukf003(options).run(flight)
