"""Attitude-and-height EKF of seed 002 (Paz & Nesmachnow), section III-B.

State ``x = [q0, q1, q2, q3, h]``: the unit quaternion ``world_q_body_wxyz`` (Hamilton, ``[w, x, y,
z]``, body FLU to world z-up) and the height ``h`` [m] of the body origin above the ground plane
under the vehicle.

Prediction (seed 002 eqs. 11-15): ``q_k = (I + 0.5 * Omega(omega) * dt) q_{k-1}`` with the gyro rate
``omega`` in body [rad/s] and ``Omega`` of eq. 14; constant height ``h_k = h_{k-1}`` (``F_s = 1``).
Process noise: gyro white noise mapped into the quaternion, ``Q_q = (dt^2 / 4) sigma_w^2 Xi Xi^T``
with ``sigma_w^2 = N_g^2 / dt`` (``N_g`` the gyro noise density), and a height random walk.

Updates (seed 002 eqs. 4-8), each "measurement -> residual and Jacobian -> gate -> update":

* accelerometer, eq. 16: ``f = g * body_R_world * e3``: the specific force of a non-accelerating
  vehicle is gravity's reaction, ``+g`` along world z up. Used only while ``| |f| - g |`` is below
  ``accel_gate`` (the paper: valid in hover and at constant velocity).
* yaw, eqs. 18-19: the vector ``[cos(psi), sin(psi)]``, never a raw angle difference.
* tilted rangefinder, eqs. 20-21: ``r = z_sensor / cos(tilt)`` with
  ``cos(tilt) = -(world_R_body d).z`` for the beam direction ``d`` in body (``body_T_range`` z
  axis; body -z for a downward sensor) and ``z_sensor = h + (world_R_body body_t_range).z``.
  With ``d = -e3`` and no lever arm this is the paper's ``s = p_z / R33``.

After every step the quaternion is renormalised (the paper's linear quaternion model does not keep
unit norm) and its sign fixed to ``q0 >= 0``.

Typos resolved (documented so the equations can be checked against the paper):

* Eq. 19 writes ``[cos, sin] = [1, gamma] / sqrt(1 + gamma^2)`` with ``gamma = tan(psi)``: that
  loses the quadrant (it forces ``cos(psi) >= 0``). The correct model, used here, is
  ``[a, b] / sqrt(a^2 + b^2)`` with ``a = q0^2 + q1^2 - q2^2 - q3^2``, ``b = 2 (q0 q3 + q1 q2)``
  (the numerator and denominator of eq. 17), which equals ``[cos(psi), sin(psi)]`` everywhere.
* The paper's gravity vector ``g^n = [0, 0, g]`` and ``R_n^b`` give eq. 16; in fgnav's z-up world
  the accelerometer at rest reads ``+g`` along world z, so eq. 16 holds with
  ``R_n^b = world_R_body^T``.

Deviation from the paper (option ``accel_corrects_yaw``): gravity carries no yaw information, but in
a sustained turn the centripetal acceleration violates the gravity model and the tilt-yaw
correlation that the gyro propagation builds up lets the accelerometer innovations rotate the yaw:
on the simulated ``two-turns`` flight (noise-free, no yaw updates) the plain update unwound 367
degrees of yaw. By default the component of the accelerometer correction about world z is removed
from the gain (the Joseph-form covariance update stays consistent for any gain).

Not modelled: gyro bias (the paper's state has none; yaw drifts without yaw updates), vehicle
acceleration in the accelerometer update (gated instead), terrain slope (flat ground).
"""

from __future__ import annotations

import bisect
import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import ImuSample, RangeReading, YawReading, replay_flight
from fgnav.datasets.geometry import (
    GRAVITY,
    interpolate_quat_wxyz,
    quat_wxyz_to_matrix,
    wrap_angle,
    yaw_of,
)
from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS, RangeLimits
from fgnav.datasets.types import AttitudeSeries, Calibration, Flight

log = logging.getLogger(__name__)


#: Default downward beam direction in body FLU (DESIGN.md section 4.4).
BEAM_DOWN_BODY = np.array([0.0, 0.0, -1.0])


@dataclass(frozen=True)
class AttitudeEkfOptions:
    """Noise and gating parameters of :class:`AttitudeHeightEkf`.

    Attributes:
        gyro_noise_density: gyro white noise [rad/s/sqrt(Hz)]; None -> the flight's
            ``calib.imu_noise.gyro_noise_density`` (or 1.7e-4, the EuRoC ADIS16448 value, when
            filtering without a flight).
        gyro_noise_floor: extra gyro noise [rad/s/sqrt(Hz)] added to the density: it covers the
            unmodelled gyro bias (the state has none) so that yaw and gravity updates keep their
            weight; 3e-3 held a 0.01 rad/s bias to < 2 deg of yaw with 10 Hz yaw readings on the
            simulated two-turns flight (1e-3: 6.4 deg).
        accel_sigma: standard deviation of each axis of the gravity observation [m/s^2]; it covers
            sensor noise and the unmodelled vehicle acceleration and drag.
        accel_gate: the accelerometer update is skipped when ``| |f| - g |`` exceeds this [m/s^2].
        accel_corrects_yaw: False (default) removes the world-yaw component of the accelerometer
            correction; True is the paper's plain EKF update (see module docstring).
        yaw_sigma: standard deviation of each component of ``[cos, sin]`` of a yaw reading [-]
            (about the yaw error in rad).
        range_sigma: rangefinder noise [m].
        range_gate_sigmas: a range update whose normalised innovation exceeds this many standard
            deviations is rejected (obstacles under the vehicle).
        max_tilt: no range update when the beam is tilted more than this from vertical [rad].
        height_random_walk: process noise of the constant-height model [m/sqrt(s)].
        gravity: gravity magnitude [m/s^2].
        init_attitude_sigma: initial standard deviation of each quaternion component [-].
        init_height_sigma: initial height standard deviation [m].
        estimate_gyro_bias: extension (not in the paper): append the gyro bias ``b_g`` [rad/s] to
            the state, ``omega_true = omega - b_g``, random walk ``gyro_bias_random_walk``
            [rad/s^2/sqrt(Hz)], initial sigma ``init_gyro_bias_sigma`` [rad/s]. It recovers a
            constant bias when gravity and yaw are observed (tests). Without a yaw sensor and with
            strong vehicle accelerations it does not help: EuRoC V1_02 (0.076 rad/s bias, 2 m/s^2
            RMS acceleration), tilt RMS 5.5 deg plain, 7.4 deg with the bias (4.2 deg with
            ``accel_sigma = 2``); V1_01: 2.9 deg plain, 4.3 deg with the bias.
    """

    gyro_noise_density: float | None = None
    gyro_noise_floor: float = 3.0e-3
    accel_sigma: float = 0.5
    accel_gate: float = 1.5
    accel_corrects_yaw: bool = False
    yaw_sigma: float = 0.03
    range_sigma: float = 0.05
    range_gate_sigmas: float = 5.0
    max_tilt: float = np.deg2rad(45.0)
    height_random_walk: float = 0.5
    gravity: float = GRAVITY
    init_attitude_sigma: float = 0.1
    init_height_sigma: float = 1.0
    estimate_gyro_bias: bool = False
    gyro_bias_random_walk: float = 1.0e-4
    init_gyro_bias_sigma: float = 0.05


#: Fallback gyro noise density [rad/s/sqrt(Hz)] (EuRoC ADIS16448, Kalibr yaml).
DEFAULT_GYRO_NOISE_DENSITY = 1.7e-4


def omega_matrix(omega: np.ndarray) -> np.ndarray:
    """Seed 002 eq. 14: the 4x4 matrix with ``q_dot = 0.5 * Omega(omega) q`` (body rates, wxyz)."""
    wx, wy, wz = omega
    return np.array(
        [
            [0.0, -wx, -wy, -wz],
            [wx, 0.0, wz, -wy],
            [wy, -wz, 0.0, wx],
            [wz, wy, -wx, 0.0],
        ]
    )


def xi_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """4x3 ``Xi(q)`` with ``q (x) [0, v] = Xi(q) v``: maps a body rotation vector into ``dq``."""
    q0, q1, q2, q3 = q_wxyz
    return np.array([[-q1, -q2, -q3], [q0, -q3, q2], [q3, q0, -q1], [-q2, q1, q0]])


def gravity_model(q_wxyz: np.ndarray, gravity: float = GRAVITY) -> tuple[np.ndarray, np.ndarray]:
    """Seed 002 eq. 16: accelerometer reading ``g * body_R_world e3`` [m/s^2] and its 3x4 Jacobian
    with respect to ``q_wxyz`` (taken without normalisation)."""
    q0, q1, q2, q3 = q_wxyz
    h = gravity * np.array(
        [
            2.0 * (q1 * q3 - q0 * q2),
            2.0 * (q2 * q3 + q0 * q1),
            q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3,
        ]
    )
    H = 2.0 * gravity * np.array([[-q2, q3, -q0, q1], [q1, q0, q3, q2], [q0, -q1, -q2, q3]])
    return h, H


def yaw_vector_model(q_wxyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Seed 002 eqs. 17-19 (quadrant-correct form): ``[cos(psi), sin(psi)]`` of ``world_R_body`` and
    its 2x4 Jacobian with respect to ``q_wxyz``."""
    q0, q1, q2, q3 = q_wxyz
    a = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3
    b = 2.0 * (q0 * q3 + q1 * q2)
    n2 = a * a + b * b
    n = np.sqrt(n2)
    if n < 1e-9:
        raise FlightDataError("attitude EKF: yaw undefined (body x axis vertical)")
    da = 2.0 * np.array([q0, q1, -q2, -q3])
    db = 2.0 * np.array([q3, q2, q1, q0])
    # d(a/n) = (b^2 da - a b db) / n^3, d(b/n) = (a^2 db - a b da) / n^3
    H = np.vstack([(b * b * da - a * b * db), (a * a * db - a * b * da)]) / (n2 * n)
    return np.array([a / n, b / n]), H


def range_model(
    x: np.ndarray, beam_body: np.ndarray, body_t_range: np.ndarray
) -> tuple[float, float, np.ndarray]:
    """Seed 002 eqs. 20-21 with a lever arm: slant range [m], cos(tilt) and the 1x5 Jacobian.

    Args:
        x: state ``[q0, q1, q2, q3, h]`` (``h`` body height above ground [m]).
        beam_body: unit beam direction in body.
        body_t_range: sensor position in body [m].
    """
    q = x[:4]
    q0, q1, q2, q3 = q
    # Third row of R(q) written without normalisation, consistent with the Jacobian below.
    r2 = np.array(
        [
            2.0 * (q1 * q3 - q0 * q2),
            2.0 * (q2 * q3 + q0 * q1),
            q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3,
        ]
    )
    cos_tilt = -float(r2 @ beam_body)
    z_sensor = x[4] + float(r2 @ body_t_range)
    r = z_sensor / cos_tilt
    dR2 = _row2_jacobian(q)  # d(R[2] @ v)/dq = v^T dR2
    d_cos = -(beam_body @ dR2)
    d_z = body_t_range @ dR2
    H = np.zeros(5)
    H[:4] = d_z / cos_tilt - z_sensor * d_cos / cos_tilt**2
    H[4] = 1.0 / cos_tilt
    return r, cos_tilt, H


def _row2_jacobian(q_wxyz: np.ndarray) -> np.ndarray:
    """3x4 derivative of the third row of ``R(q)`` (world z of body axes) with respect to q."""
    q0, q1, q2, q3 = q_wxyz
    return 2.0 * np.array([[-q2, q3, -q0, q1], [q1, q0, q3, q2], [q0, -q1, -q2, q3]])


@dataclass(frozen=True, eq=False)
class AttitudeHeightResult:
    """Time histories of :meth:`AttitudeHeightEkf.run`.

    Attributes:
        t: (N,) output times [s] (the IMU times).
        world_q_body_wxyz: (N, 4) attitude ``world_R_body`` as ``[w, x, y, z]``.
        height: (N,) body height above the ground plane [m] (NaN before the first range reading).
        covariance: (N, 5, 5) state covariance of ``[q0, q1, q2, q3, h]`` ((N, 8, 8) with the
            gyro bias appended when ``estimate_gyro_bias``).
        rotation_cov: (N, 3, 3) attitude covariance as a body-frame rotation vector
            (``world_R_body * Exp(dtheta)``, GTSAM's Pose3 convention) [rad^2].
        counts: numbers of updates applied and skipped, by kind.
        gyro_bias: (N, 3) gyro bias estimate [rad/s] with ``estimate_gyro_bias``, else None.
    """

    t: np.ndarray
    world_q_body_wxyz: np.ndarray
    height: np.ndarray
    covariance: np.ndarray
    rotation_cov: np.ndarray
    counts: dict[str, int]
    gyro_bias: np.ndarray | None = None

    def attitude_series(self) -> AttitudeSeries:
        """The attitude as an :class:`AttitudeSeries` (e.g. for image rectification)."""
        return AttitudeSeries(t=self.t.copy(), world_q_body_wxyz=self.world_q_body_wxyz.copy())

    def attitude_at(self, t: np.ndarray) -> np.ndarray:
        """Attitude ``[w, x, y, z]`` at times ``t`` [s] by normalised linear interpolation of the
        quaternions (the output rate is the IMU rate, so the chord error is negligible)."""
        return interpolate_quat_wxyz(self.t, self.world_q_body_wxyz, np.atleast_1d(t))

    def height_at(self, t: np.ndarray) -> np.ndarray:
        """Height [m] at times ``t`` [s] by linear interpolation."""
        return np.interp(np.atleast_1d(t), self.t, self.height)


class AttitudeHeightEkf:
    """The EKF of seed 002 sec. III-B: ``predict`` on each gyro sample, ``update_*`` per sensor.

    Example::

        ekf = AttitudeHeightEkf(AttitudeEkfOptions(), q0_wxyz, h0)
        ekf.predict(omega, dt); ekf.update_accel(f); ekf.update_yaw(psi); ekf.update_range(r)
        ekf.world_q_body_wxyz, ekf.height, ekf.P
    """

    def __init__(
        self,
        options: AttitudeEkfOptions,
        q0_wxyz: np.ndarray,
        h0: float = 0.0,
        beam_body: np.ndarray = BEAM_DOWN_BODY,
        body_t_range: np.ndarray | None = None,
        gyro_noise_density: float | None = None,
    ) -> None:
        """Initial state.

        Args:
            options: noises and gates.
            q0_wxyz: initial ``world_q_body_wxyz``.
            h0: initial height above ground [m].
            beam_body: rangefinder beam direction in body (unit).
            body_t_range: rangefinder position in body [m] (zero by default).
            gyro_noise_density: overrides ``options.gyro_noise_density`` [rad/s/sqrt(Hz)].
        """
        self.options = options
        q = np.asarray(q0_wxyz, dtype=float)
        self.n = 8 if options.estimate_gyro_bias else 5
        self.x = np.zeros(self.n)
        self.x[:4] = q / np.linalg.norm(q)
        self.x[4] = float(h0)
        var = [options.init_attitude_sigma**2] * 4 + [options.init_height_sigma**2]
        self.P = np.diag(var + [options.init_gyro_bias_sigma**2] * (self.n - 5))
        self.beam_body = np.asarray(beam_body, dtype=float) / np.linalg.norm(beam_body)
        self.body_t_range = np.zeros(3) if body_t_range is None else np.asarray(body_t_range, float)
        nd = gyro_noise_density or options.gyro_noise_density or DEFAULT_GYRO_NOISE_DENSITY
        self._gyro_density = float(nd) + options.gyro_noise_floor
        self.counts = {
            "accel": 0,
            "accel_gated": 0,
            "yaw": 0,
            "range": 0,
            "range_out_of_limits": 0,
            "range_tilt": 0,
            "range_outlier": 0,
        }

    @staticmethod
    def run(
        flight: Flight, options: AttitudeEkfOptions | None = None, **kwargs
    ) -> AttitudeHeightResult:
        """Run over a whole flight: :func:`run_attitude_ekf` (keyword arguments passed on)."""
        return run_attitude_ekf(flight, options, **kwargs)

    @property
    def world_q_body_wxyz(self) -> np.ndarray:
        """Current attitude ``[w, x, y, z]``."""
        return self.x[:4].copy()

    @property
    def gyro_bias(self) -> np.ndarray:
        """Current gyro bias estimate [rad/s] in body (zeros without ``estimate_gyro_bias``)."""
        return self.x[5:8].copy() if self.n == 8 else np.zeros(3)

    @property
    def height(self) -> float:
        """Current height of the body above ground [m]."""
        return float(self.x[4])

    def rotation_cov(self) -> np.ndarray:
        """3x3 attitude covariance as a body rotation vector [rad^2]: ``4 Xi^T P_q Xi``."""
        Xi = xi_matrix(self.x[:4])
        return 4.0 * Xi.T @ self.P[:4, :4] @ Xi

    # 1. prediction -------------------------------------------------------------------------------

    def predict(self, omega: np.ndarray, dt: float) -> None:
        """Propagate with body angular rate ``omega`` [rad/s] over ``dt`` [s] (seed 002 eqs. 11-15,
        1-3)."""
        if dt < 0:
            raise ValueError(f"attitude EKF: negative time step {dt}")
        if dt == 0:
            return
        omega = np.asarray(omega, dtype=float) - self.gyro_bias
        F = np.eye(self.n)
        F[:4, :4] += 0.5 * omega_matrix(omega) * dt  # eq. 13, 15
        Xi = xi_matrix(self.x[:4])
        Q = np.zeros((self.n, self.n))
        Q[:4, :4] = 0.25 * dt * self._gyro_density**2 * (Xi @ Xi.T)
        Q[4, 4] = self.options.height_random_walk**2 * dt
        if self.n == 8:
            F[:4, 5:8] = -0.5 * dt * Xi  # d q_k / d b_g, since Omega(w) q = Xi(q) w
            Q[5:8, 5:8] = np.eye(3) * self.options.gyro_bias_random_walk**2 * dt
        self.x[:4] = F[:4, :4] @ self.x[:4]  # eq. 12 (eq. 1); h and b_g are constant
        self.P = F @ self.P @ F.T + Q  # eq. 3
        self._normalise()

    # 2. updates ----------------------------------------------------------------------------------

    def update_accel(self, body_accel: np.ndarray) -> bool:
        """Gravity update from a specific force reading in body [m/s^2] (eq. 16). Returns False when
        gated out (vehicle accelerating)."""
        f = np.asarray(body_accel, dtype=float)
        if abs(np.linalg.norm(f) - self.options.gravity) > self.options.accel_gate:
            self.counts["accel_gated"] += 1
            return False
        h, Hq = gravity_model(self.x[:4], self.options.gravity)
        H = np.zeros((3, self.n))
        H[:, :4] = Hq
        q = self.x[:4]
        # Direction in q-space of a rotation about world z: [0, 0, 0, 1] (x) q.
        yaw_dir = None if self.options.accel_corrects_yaw else np.array([-q[3], -q[2], q[1], q[0]])
        self._kalman(f - h, H, np.eye(3) * self.options.accel_sigma**2, yaw_dir)
        self.counts["accel"] += 1
        return True

    def update_yaw(self, yaw: float, sigma: float | None = None) -> None:
        """Yaw update with the ``[cos, sin]`` vector (eqs. 18-19); ``yaw`` [rad] of world_R_body."""
        s = self.options.yaw_sigma if sigma is None else sigma
        h, Hq = yaw_vector_model(self.x[:4])
        z = np.array([np.cos(yaw), np.sin(yaw)])
        H = np.zeros((2, self.n))
        H[:, :4] = Hq
        self._kalman(z - h, H, np.eye(2) * s**2)
        self.counts["yaw"] += 1

    def update_range(self, measured_range: float) -> bool:
        """Tilted rangefinder update (eqs. 20-21), ``measured_range`` [m] along the beam. Returns
        False when gated (beam too tilted, or innovation beyond ``range_gate_sigmas``)."""
        r_pred, cos_tilt, Hr = range_model(self.x, self.beam_body, self.body_t_range)
        if cos_tilt < np.cos(self.options.max_tilt):
            self.counts["range_tilt"] += 1
            return False
        H = np.zeros((1, self.n))
        H[0, :5] = Hr
        Rm = np.array([[self.options.range_sigma**2]])
        y = np.array([measured_range - r_pred])
        S = H @ self.P @ H.T + Rm
        if y[0] ** 2 > self.options.range_gate_sigmas**2 * S[0, 0]:
            self.counts["range_outlier"] += 1
            return False
        self._kalman(y, H, Rm)
        self.counts["range"] += 1
        return True

    def reset_height(self, measured_range: float) -> None:
        """Set the height from one range reading and the current attitude (initialisation)."""
        R = quat_wxyz_to_matrix(self.x[:4])
        cos_tilt = -float(R[2] @ self.beam_body)
        self.x[4] = measured_range * cos_tilt - float(R[2] @ self.body_t_range)
        self.P[4, :] = 0.0
        self.P[:, 4] = 0.0
        self.P[4, 4] = self.options.range_sigma**2

    def _kalman(
        self, y: np.ndarray, H: np.ndarray, Rm: np.ndarray, remove_dir: np.ndarray | None = None
    ) -> None:
        # eqs. 6-8; Joseph form, which stays valid for the projected (suboptimal) gain.
        S = H @ self.P @ H.T + Rm
        K = np.linalg.solve(S, H @ self.P).T
        if remove_dir is not None:
            u = remove_dir / np.linalg.norm(remove_dir)
            K[:4] -= np.outer(u, u @ K[:4])
            if self.n == 8:
                # Nor the bias about world z (seen in body): it only acts on yaw.
                z_body = quat_wxyz_to_matrix(self.x[:4])[2]
                K[5:8] -= np.outer(z_body, z_body @ K[5:8])
        self.x = self.x + K @ y
        IKH = np.eye(self.n) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ Rm @ K.T
        self._normalise()

    def _normalise(self) -> None:
        n = np.linalg.norm(self.x[:4])
        J = (np.eye(4) - np.outer(self.x[:4], self.x[:4]) / n**2) / n
        self.x[:4] /= n
        if self.x[0] < 0:
            self.x[:4] = -self.x[:4]
            J = -J
        self.P[:4, :] = J @ self.P[:4, :]
        self.P[:, :4] = self.P[:, :4] @ J.T


def initial_attitude_from_accel(body_accel: np.ndarray, yaw: float = 0.0) -> np.ndarray:
    """``world_q_body_wxyz`` with roll and pitch from a mean specific force reading in body
    [m/s^2] (gravity reaction, z up) and the given yaw [rad]."""
    from fgnav.datasets.geometry import matrix_to_quat_wxyz, rpy_to_matrix

    f = np.asarray(body_accel, dtype=float)
    roll = np.arctan2(f[1], f[2])
    pitch = np.arctan2(-f[0], np.hypot(f[1], f[2]))
    return matrix_to_quat_wxyz(rpy_to_matrix(roll, pitch, yaw))


#: Seconds of IMU data averaged for the initial roll and pitch.
INIT_ACCEL_WINDOW_S = 0.2


YAW_HISTORY_SAMPLES = 2048
"""IMU-rate yaw estimates the stage keeps for late yaw readings (about 2 s at 1 kHz)."""


class AttitudeEstimate(NamedTuple):
    """The stage's output at one IMU sample: the filter after that sample's updates."""

    t: float
    arrival: float
    world_q_body_wxyz: np.ndarray
    height: float
    covariance: np.ndarray
    gyro_bias: np.ndarray
    rotation_cov: np.ndarray


class AttitudeEkfStage:
    """:class:`AttitudeHeightEkf` as an event-fed stage (no whole-flight pass).

    Fed IMU samples, yaw and range readings in arrival order (``feed``), it predicts on every IMU
    sample, applies the accelerometer update there and the yaw and range updates at their own
    times, and returns one :class:`AttitudeEstimate` per IMU sample processed. Without ``q0_wxyz``
    it waits for ``INIT_ACCEL_WINDOW_S`` of IMU data and starts with roll and pitch from their mean
    specific force and the yaw of the first yaw reading that has arrived by then (0 without one);
    the events of that wait are then processed in order, so the outputs lag by the window only at
    the start. Readings taken before the first IMU sample are skipped; a yaw or range reading
    older than the filter's time is applied at the filter's time (counted ``late``; a late yaw
    reading keeps its innovation against the filter's yaw at its own time, from a short history,
    so the vehicle's turn since then is not taken for an error); an IMU sample older than the
    filter's time is skipped (counted ``imu_late``); range readings out of ``[range_min,
    range_max]`` are skipped and counted (``range_out_of_limits``), as are those at the sensor's
    floor or maximum (``range_at_min``, ``range_at_max``: no distance,
    :func:`fgnav.datasets.range_limits.range_refusal`).
    """

    def __init__(
        self,
        calib: Calibration,
        options: AttitudeEkfOptions | None = None,
        q0_wxyz: np.ndarray | None = None,
        use_yaw: bool = True,
        use_range: bool = True,
        name: str = "flight",
    ) -> None:
        self.options = options or AttitudeEkfOptions()
        self.calib = calib
        self.name = name
        self.use_yaw, self.use_range = use_yaw, use_range
        T = np.asarray(calib.body_T_range, dtype=float)
        self._beam_body = T[:3, :3] @ np.array([0.0, 0.0, 1.0])
        self._body_t_range = T[:3, 3]
        if use_range:
            self._check_beam()  # a wrong calibration is said before any event
        self._q0 = None if q0_wxyz is None else np.asarray(q0_wxyz, dtype=float)
        self.ekf: AttitudeHeightEkf | None = None
        self._wait: list = []  # events held until the initial attitude is known
        self._t_prev = math.nan
        self._omega_prev = np.zeros(3)
        self._height_init = False
        self._n_late = 0
        self._n_imu_late = 0
        self._yaw_hist: deque[tuple[float, float]] = deque(maxlen=YAW_HISTORY_SAMPLES)
        self._range_limits = RangeLimits(calib.range_min, calib.range_max)

    @property
    def counts(self) -> dict[str, int]:
        """Updates applied and skipped, by kind (the EKF's counts, ``late`` yaw and range
        readings and ``imu_late``: IMU samples older than the filter, skipped)."""
        c = dict(self.ekf.counts) if self.ekf is not None else {}
        c["late"] = self._n_late
        c["imu_late"] = self._n_imu_late
        return c

    def feed(self, ev) -> list[AttitudeEstimate]:
        """One event (IMU sample, yaw or range reading; others are ignored); returns the
        estimates at the IMU samples it completed (none while waiting for the start)."""
        if not isinstance(ev, (ImuSample, YawReading, RangeReading)):
            return []
        if isinstance(ev, YawReading) and not self.use_yaw:
            return []
        if isinstance(ev, RangeReading) and not self.use_range:
            return []
        if self.ekf is None:
            self._wait.append(ev)
            if not self._try_start():
                return []
            held, self._wait = self._wait, []
            out: list[AttitudeEstimate] = []
            for e in held:
                out += self._process(e)
            return out
        return self._process(ev)

    def _check_beam(self) -> None:
        if self._beam_body[2] > 0:
            raise FlightDataError(
                f"{self.name}.calib.body_T_range: the rangefinder beam (its z axis) points up in "
                f"body ({self._beam_body.round(3).tolist()}); expected a downward sensor (beam "
                "near body -z)"
            )

    def _try_start(self) -> bool:
        imu = [e for e in self._wait if isinstance(e, ImuSample)]
        if not imu:
            return False
        q0 = self._q0
        if q0 is None:
            if imu[-1].t < imu[0].t + INIT_ACCEL_WINDOW_S:
                return False
            first = [e for e in imu if e.t < imu[0].t + INIT_ACCEL_WINDOW_S] or imu[:1]
            yaws = [e.yaw for e in self._wait if isinstance(e, YawReading)]
            q0 = initial_attitude_from_accel(
                np.mean([e.body_accel for e in first], axis=0), float(yaws[0]) if yaws else 0.0
            )
        o = self.options
        self.ekf = AttitudeHeightEkf(
            o,
            q0,
            0.0,
            beam_body=self._beam_body,
            body_t_range=self._body_t_range,
            gyro_noise_density=o.gyro_noise_density or self.calib.imu_noise.gyro_noise_density,
        )
        self._t_prev = float(imu[0].t)
        self._omega_prev = np.asarray(imu[0].body_omega, dtype=float)
        return True

    def _process(self, ev) -> list[AttitudeEstimate]:
        ekf = self.ekf
        t = float(ev.t)
        late = t < self._t_prev
        if late:
            if isinstance(ev, ImuSample):
                self._n_imu_late += 1
                return []
            if not math.isfinite(self._t_prev):
                return []
            self._n_late += 1
            t_meas, t = t, self._t_prev
        ekf.predict(self._omega_prev, t - self._t_prev)
        self._t_prev = t
        if isinstance(ev, ImuSample):
            self._omega_prev = np.asarray(ev.body_omega, dtype=float)
            ekf.update_accel(ev.body_accel)
            self._yaw_hist.append((t, yaw_of(quat_wxyz_to_matrix(ekf.x[:4]))))
            return [
                AttitudeEstimate(
                    t,
                    float(ev.arrival),
                    ekf.world_q_body_wxyz,
                    ekf.height if self._height_init else math.nan,
                    ekf.P.copy(),
                    ekf.gyro_bias,
                    ekf.rotation_cov(),
                )
            ]
        if isinstance(ev, YawReading):
            yaw = float(ev.yaw)
            if late and self._yaw_hist:
                # The innovation at the reading's own time, carried to now.
                ts = [h[0] for h in self._yaw_hist]
                k = min(bisect.bisect_left(ts, t_meas), len(ts) - 1)
                yaw_then, yaw_now = self._yaw_hist[k][1], self._yaw_hist[-1][1]
                yaw = yaw_now + wrap_angle(yaw - yaw_then)
            ekf.update_yaw(yaw)
            return []
        r = float(ev.range)
        self._range_limits.see(r)
        why = self._range_limits.refusal(r)
        if why in RANGE_LIMIT_TAGS:
            key = f"range_{why.replace('-', '_')}"  # range_at_min, range_at_max
            ekf.counts[key] = ekf.counts.get(key, 0) + 1
        elif why is not None:
            ekf.counts["range_out_of_limits"] += 1
        elif not self._height_init:
            ekf.reset_height(r)
            self._height_init = True
        else:
            ekf.update_range(r)
        return []


def run_attitude_ekf(
    flight: Flight,
    options: AttitudeEkfOptions | None = None,
    q0_wxyz: np.ndarray | None = None,
    use_yaw: bool = True,
    use_range: bool = True,
) -> AttitudeHeightResult:
    """Replay a flight into :class:`AttitudeEkfStage`: predict on every IMU sample, accelerometer
    update on every IMU sample, yaw and range updates at their own times (prediction to the exact
    time first).

    Args:
        flight: needs ``imu``; uses ``yaw`` and ``range`` when present (and enabled); the range beam
            and lever arm come from ``flight.calib.body_T_range`` (beam = its z axis), readings out
            of ``[range_min, range_max]`` or at its floor or maximum are skipped and counted.
        options: EKF options (defaults when None).
        q0_wxyz: initial attitude; default roll/pitch from the first ``INIT_ACCEL_WINDOW_S`` of
            accelerometer data and yaw from the first yaw reading that has arrived by then.
        use_yaw, use_range: switch the yaw / range updates off.

    Returns:
        :class:`AttitudeHeightResult` at the IMU times. Counts of applied/skipped updates are
        logged and returned in ``counts``.
    """
    imu = flight.imu
    if imu is None:
        raise FlightDataError(f"{flight.name}: the attitude EKF needs an IMU stream (flight.imu)")
    use_range = use_range and flight.range is not None
    stage = AttitudeEkfStage(flight.calib, options, q0_wxyz, use_yaw, use_range, flight.name)
    # Ties in arrival: the IMU sample first, then yaw, then range.
    out: list[AttitudeEstimate] = []
    for ev in replay_flight(flight, ("imu", "yaw", "range"), named_order=True):
        out += stage.feed(ev)
    counts = stage.counts
    log.info("attitude EKF on %s: %s", flight.name, counts)
    n = stage.ekf.n if stage.ekf is not None else 5
    return AttitudeHeightResult(
        t=np.array([o.t for o in out]),
        world_q_body_wxyz=np.array([o.world_q_body_wxyz for o in out]).reshape(-1, 4),
        height=np.array([o.height for o in out]),
        covariance=np.array([o.covariance for o in out]).reshape(-1, n, n),
        gyro_bias=np.array([o.gyro_bias for o in out]).reshape(-1, 3) if n == 8 else None,
        rotation_cov=np.array([o.rotation_cov for o in out]).reshape(-1, 3, 3),
        counts=counts,
    )


def attitude_errors_rad(
    world_q_body_wxyz: np.ndarray, truth_q_wxyz: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rotation angle error [rad] and yaw error [rad] between two aligned quaternion stacks."""
    Ra = quat_wxyz_to_matrix(world_q_body_wxyz)
    Rb = quat_wxyz_to_matrix(truth_q_wxyz)
    Rd = np.einsum("nji,njk->nik", Rb, Ra)
    angle = np.arccos(np.clip((np.trace(Rd, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    return angle, np.abs(wrap_angle(yaw_of(Ra) - yaw_of(Rb)))
