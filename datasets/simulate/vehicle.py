"""Rigid-body multirotor with linear rotor drag, tracking a smooth reference.

Model (per unit mass; world z up, body FLU; seed 000 eq. 1 and Martin & Salaun 2010):

    world_a_body = world_R_body (thrust * e3 + drag_body) + (0, 0, -g)
    drag_body    = (-kx * body_v_air_x, -ky * body_v_air_y, 0)
    body_v_air   = body_R_world (world_v_body - world_v_wind)

``thrust`` [m/s^2] is the collective thrust divided by the mass and acts along body +z; rotor drag
``k = mu / m`` [1/s] acts on the air-relative velocity expressed in the body frame (no vertical
drag, no quadratic drag). The accelerometer reads the specific force ``thrust * e3 + drag_body``,
so ``f_xy = -k * body_v_air_xy`` holds exactly for the noise-free signal.

Controller: a PD position loop with acceleration feed-forward (drag compensated with the
ground-relative velocity, the wind is unknown to it) gives the desired force direction; the
attitude loop makes the body z axis follow it with the reference yaw (first-order attitude
kinematics with a first-order lag on the body rate). Tilt is therefore what moves the vehicle.

Integration: the controller runs at the output (IMU) rate and its body rate and thrust are held
over each sample interval (zero-order hold), so the rotation is propagated exactly
(``R exp(omega dt)``: preintegrating the noise-free gyro reproduces the true attitude) and the
translation, whose drag varies continuously, with RK4 on ``substeps`` sub-steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from fgnav.datasets.geometry import GRAVITY

#: Lowest commanded vertical force when the position loop asks for less (fraction of g): the
#: vehicle never free-falls or flips to follow a reference.
MIN_VERTICAL_FORCE_FRACTION = 0.2


@dataclass(frozen=True)
class ControllerGains:
    """Gains of the position/attitude controller.

    Attributes:
        kp: position gain [1/s^2] (natural frequency 2 rad/s with ``kd``).
        kd: velocity gain [1/s] (damping ~0.9).
        k_att: attitude gain [1/s] (attitude error -> commanded body rate).
        tau_rate: time constant of the body-rate response [s].
        max_tilt: limit of the commanded tilt [rad].
    """

    kp: float = 4.0
    kd: float = 3.6
    k_att: float = 10.0
    tau_rate: float = 0.05
    max_tilt: float = math.radians(35.0)


@dataclass
class VehicleLog:
    """Vehicle state sampled at the output rate (columns, N rows).

    Attributes:
        t: (N,) time [s].
        world_t_body: (N, 3) position [m].
        world_v_body: (N, 3) velocity [m/s].
        world_R_body: (N, 3, 3) attitude.
        body_omega: (N, 3) body rate, constant until the next sample [rad/s].
        body_specific_force: (N, 3) true specific force at the sample [m/s^2] (thrust held until
            the next sample, drag of the sample's state).
        world_v_wind: (N, 3) wind velocity [m/s].
    """

    t: np.ndarray
    world_t_body: np.ndarray
    world_v_body: np.ndarray
    world_R_body: np.ndarray
    body_omega: np.ndarray
    body_specific_force: np.ndarray
    world_v_wind: np.ndarray


@dataclass(frozen=True)
class VehicleParams:
    """Physical parameters of the simulated vehicle.

    Attributes:
        drag_k: rotor drag ``(kx, ky) = mu / m`` [1/s], per body axis.
        gains: controller gains.
    """

    drag_k: tuple[float, float] = (0.38, 0.42)
    gains: ControllerGains = field(default_factory=ControllerGains)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (``np.cross`` is slow for single vectors)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for one rotation vector (scalar maths, for the integration loop)."""
    x, y, z = float(phi[0]), float(phi[1]), float(phi[2])
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:
        a, b = 1.0, 0.5
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    return np.array(
        [
            [1.0 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z],
            [a * z + b * x * y, 1.0 - b * (x * x + z * z), -a * x + b * y * z],
            [-a * y + b * x * z, a * x + b * y * z, 1.0 - b * (x * x + y * y)],
        ]
    )


def _log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of R (angles below pi - 1e-6, as in the attitude loop)."""
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = max(-1.0, min(1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    th = math.acos(c)
    if th < 1e-8:
        return 0.5 * w
    return th / (2.0 * math.sin(th)) * w


def drag_body(
    world_R_body: np.ndarray, world_v_body: np.ndarray, world_v_wind: np.ndarray, drag_k
) -> np.ndarray:
    """Rotor drag per unit mass in body [m/s^2]: ``(-kx v_air_x, -ky v_air_y, 0)``."""
    body_v_air = (world_v_body - world_v_wind) @ world_R_body
    return np.array([-drag_k[0] * body_v_air[0], -drag_k[1] * body_v_air[1], 0.0])


_G_WORLD = np.array([0.0, 0.0, -GRAVITY])


def _world_accel(world_R_body, world_v_body, thrust_body, world_v_wind, drag_k) -> np.ndarray:
    """World acceleration [m/s^2] for held thrust (body, per unit mass) with rotor drag."""
    f_body = thrust_body + drag_body(world_R_body, world_v_body, world_v_wind, drag_k)
    return world_R_body @ f_body + _G_WORLD


def desired_rotation(world_f: np.ndarray, yaw: float) -> np.ndarray:
    """Rotation whose z axis is along force ``world_f`` and whose heading is ``yaw`` [rad]."""
    z = world_f / math.sqrt(float(world_f @ world_f))
    x_c = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    y = _cross(z, x_c)
    y /= math.sqrt(float(y @ y))
    x = _cross(y, z)
    return np.column_stack([x, y, z])


def simulate_vehicle(
    t_ref: np.ndarray,
    ref_p: np.ndarray,
    ref_v: np.ndarray,
    ref_a: np.ndarray,
    ref_yaw: np.ndarray,
    ref_yaw_rate: np.ndarray,
    wind: np.ndarray,
    params: VehicleParams,
    substeps: int,
    world_v_body0: np.ndarray | None = None,
) -> VehicleLog:
    """Fly the vehicle along a reference sampled on the output grid ``t_ref``.

    Args:
        t_ref: (N,) output times [s], uniform spacing.
        ref_p, ref_v, ref_a: (N, 3) reference position [m], velocity [m/s], acceleration [m/s^2]
            in world.
        ref_yaw, ref_yaw_rate: (N,) reference yaw [rad] and its rate [rad/s].
        wind: (N, 3) world wind velocity [m/s] on the output grid (held over each sample).
        params: vehicle parameters.
        substeps: integration sub-steps per output sample (>= 1).
        world_v_body0: initial velocity [m/s] (default: the reference velocity).

    Returns:
        The state at every output time.
    """
    n = t_ref.shape[0]
    dt_out = float(t_ref[1] - t_ref[0]) if n > 1 else 0.005
    h = dt_out / substeps
    g_world = np.array([0.0, 0.0, -GRAVITY])
    k = params.drag_k
    gains = params.gains
    tan_max = math.tan(gains.max_tilt)

    p = ref_p[0].astype(float).copy()
    v = (ref_v[0] if world_v_body0 is None else np.asarray(world_v_body0, float)).copy()
    R = desired_rotation(ref_a[0] - g_world, float(ref_yaw[0]))
    omega = np.zeros(3)
    no_wind = np.zeros(3)

    out_p = np.empty((n, 3))
    out_v = np.empty((n, 3))
    out_R = np.empty((n, 3, 3))
    out_w = np.empty((n, 3))
    out_f = np.empty((n, 3))

    for i in range(n):
        w_air = wind[i]
        # 1. Position loop: desired force per unit mass (drag compensated without wind).
        a_des = ref_a[i] + gains.kp * (ref_p[i] - p) + gains.kd * (ref_v[i] - v)
        f_des = a_des - g_world - R @ drag_body(R, v, no_wind, k)
        horiz = math.hypot(f_des[0], f_des[1])
        if f_des[2] <= 0.0 or horiz > tan_max * f_des[2]:
            fz = max(f_des[2], MIN_VERTICAL_FORCE_FRACTION * GRAVITY)
            scale = min(1.0, tan_max * fz / max(horiz, 1e-12))
            f_des = np.array([f_des[0] * scale, f_des[1] * scale, fz])
        thrust_body = np.array([0.0, 0.0, float(f_des @ R[:, 2])])
        # 2. Attitude loop: body rate towards the desired attitude, with yaw-rate feed-forward.
        R_des = desired_rotation(f_des, float(ref_yaw[i]))
        omega_cmd = gains.k_att * _log(R.T @ R_des) + R.T @ np.array([0.0, 0.0, ref_yaw_rate[i]])
        omega = omega + (omega_cmd - omega) * min(1.0, dt_out / gains.tau_rate)
        out_p[i], out_v[i], out_R[i] = p, v, R
        out_w[i] = omega
        out_f[i] = thrust_body + drag_body(R, v, w_air, k)
        # 3. Integrate over the sample interval: body rate and thrust held (exact rotation
        #    R(s) = R exp(omega s)), translation with RK4 on sub-steps of length h.
        R_half = _exp(omega * (0.5 * h))
        R_a = R
        for _ in range(substeps):
            R_b = R_a @ R_half
            R_c = R_b @ R_half
            a1 = _world_accel(R_a, v, thrust_body, w_air, k)
            a2 = _world_accel(R_b, v + 0.5 * h * a1, thrust_body, w_air, k)
            a3 = _world_accel(R_b, v + 0.5 * h * a2, thrust_body, w_air, k)
            a4 = _world_accel(R_c, v + h * a3, thrust_body, w_air, k)
            p = p + h * v + (h * h / 6.0) * (a1 + a2 + a3)
            v = v + (h / 6.0) * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            R_a = R_c
        R = R @ _exp(omega * dt_out)
        # Re-orthonormalise once per output sample to keep round-off from accumulating.
        u, _, vt = np.linalg.svd(R)
        R = u @ vt

    return VehicleLog(
        t=t_ref.copy(),
        world_t_body=out_p,
        world_v_body=out_v,
        world_R_body=out_R,
        body_omega=out_w,
        body_specific_force=out_f,
        world_v_wind=np.asarray(wind, float).copy(),
    )
