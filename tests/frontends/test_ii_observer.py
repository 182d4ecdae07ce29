"""I&I velocity and scale observer (seed 000): convergence on the paper's own model.

The test flight is seed 000's simulation (sec. 4) written out: a circle of radius 2 m at 1 m/s with
a slow height oscillation, constant yaw, drag ``mu/m``, SLAM ``y2 = diag(0.3, 0.2) X_h`` at 20 Hz,
gains 7 and 8, ``V_hat(0) = 0``, ``K_hat(0) = 0``. The attitude solves the drag model exactly:
the body z axis is along ``a + g e3 + k v`` (then the horizontal specific force is ``-k V``)."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import matrix_to_quat_wxyz, so3_log
from fgnav.datasets.types import AttitudeSeries, Flight, ImuSeries, SlamSeries

from fgnav.frontends.attitude_ekf import GRAVITY
from fgnav.frontends.ii_observer import IIObserver, IIObserverOptions, run_ii_observer

K_TRUE = np.array([0.3, 0.2])  # seed 000 sec. 4
DRAG_K = 0.4  # [1/s], mu/m of a small quadrotor (the simulator's default is 0.38-0.42)
RADIUS, OMEGA = 2.0, 0.5  # circle [m], [rad/s] -> 1 m/s


def _kinematics(t, yaw_rate=0.0):
    c, s = np.cos(OMEGA * t), np.sin(OMEGA * t)
    p = np.stack([RADIUS * s, -RADIUS * c, 1.5 + 0.3 * np.sin(0.3 * t)], axis=-1)
    v = np.stack([RADIUS * OMEGA * c, RADIUS * OMEGA * s, 0.09 * np.cos(0.3 * t)], axis=-1)
    a = np.stack([-RADIUS * OMEGA**2 * s, RADIUS * OMEGA**2 * c, -0.027 * np.sin(0.3 * t)], axis=-1)
    return p, v, a, yaw_rate * t


def _attitude(t, yaw_rate=0.0):
    """(N, 3, 3) world_R_body with body z along a + g e3 + k v (drag model solved exactly)."""
    _, v, a, yaw = _kinematics(t, yaw_rate)
    b3 = a + [0.0, 0.0, GRAVITY] + DRAG_K * v
    b3 /= np.linalg.norm(b3, axis=-1, keepdims=True)
    heading = np.stack([np.cos(yaw), np.sin(yaw), 0.0 * yaw], axis=-1)
    b2 = np.cross(b3, heading)
    b2 /= np.linalg.norm(b2, axis=-1, keepdims=True)
    b1 = np.cross(b2, b3)
    return np.stack([b1, b2, b3], axis=-1)


def paper_flight(
    duration=40.0, rate=200.0, slam_rate=20.0, yaw_rate=0.0, seed=None, noise=(0.0, 0.0)
):
    """Seed 000's simulation as a Flight, plus the truth (body velocity, world v, position)."""
    t = np.arange(int(duration * rate)) / rate
    p, v, a, _ = _kinematics(t, yaw_rate)
    R = _attitude(t, yaw_rate)
    h = 1e-5  # central difference of the analytic attitude -> body rate
    dR = np.einsum("nji,njk->nik", _attitude(t - h, yaw_rate), _attitude(t + h, yaw_rate))
    omega = np.stack([so3_log(m) for m in dR]) / (2 * h)
    accel = np.einsum("nji,nj->ni", R, a + [0.0, 0.0, GRAVITY])
    body_v = np.einsum("nji,nj->ni", R, v)
    np.testing.assert_allclose(accel[:, :2], -DRAG_K * body_v[:, :2], atol=1e-9)
    step = int(rate / slam_rate)
    y2 = K_TRUE * p[::step, :2]
    slam_xyz = np.concatenate([y2, 0.25 * p[::step, 2:]], axis=1)
    if seed is not None:
        rng = np.random.default_rng(seed)
        accel = accel + rng.normal(0, noise[0], accel.shape)
        slam_xyz = slam_xyz + rng.normal(0, noise[1], slam_xyz.shape)
    q = matrix_to_quat_wxyz(R)
    flight = Flight(
        name="seed000-own-model",
        imu=ImuSeries(t=t, body_omega=omega, body_accel=accel),
        attitude=AttitudeSeries(t=t, world_q_body_wxyz=q),
        slam=SlamSeries(
            t=t[::step],
            slam_t_cam=slam_xyz,
            slam_q_cam_wxyz=np.tile([1.0, 0, 0, 0], (len(y2), 1)),
            session=np.zeros(len(y2), dtype=int),
        ),
        meta={"drag_k": [DRAG_K, DRAG_K]},
    ).check()
    return flight, body_v, v, p


@pytest.mark.parametrize("kinematics", ["published", "full"])
def test_noise_free_paper_simulation_converges(kinematics):
    flight, body_v, world_v, p = paper_flight()
    res = run_ii_observer(flight, IIObserverOptions(kinematics=kinematics), world_vz=world_v[:, 2])
    t = res.t
    v_err = np.linalg.norm(res.eta - body_v[:, :2], axis=1)
    k_err = np.abs(res.xi - K_TRUE) / K_TRUE
    # Velocity converges first (rate k gamma_v = 2.8 /s), then the scale (cascade, Fig. 1-2).
    assert v_err[0] > 0.5
    t_v = t[np.argmax(v_err < 0.01)]
    t_k = t[np.argmax(np.all(k_err < 0.01, axis=1))]
    assert 0 < t_v < t_k < 25.0
    late = t > 30.0
    pos_err = np.linalg.norm(res.world_t_body[late, :2] - p[late, :2], axis=1)
    if kinematics == "full":
        # Exact model: errors at the integration's round-off (measured 5e-7 m/s, 6e-7, 1e-6 m).
        assert v_err[late].max() < 1e-4
        assert k_err[late].max() < 1e-4
        assert pos_err.max() < 1e-3
    else:
        # The paper's neglected terms (Coriolis in eq. 8, d(R_h)/dt in eq. 36) leave 1.2 mm/s
        # and scale spikes (measured 4.7 % / 5.7 %) where a velocity component crosses zero.
        assert v_err[late].max() < 3e-3
        assert np.all(k_err[late].mean(axis=0) < 0.02)  # measured 0.8 % and 1.5 %
        assert k_err[late].max() < 0.08
        assert pos_err.max() < 0.2
    est = res.to_estimate()
    assert est.method == "ii-observer" and est.causal
    assert abs(est.slam_scale[0] - K_TRUE.mean()) < 0.01 * K_TRUE.mean()


def test_full_kinematics_handles_yawing_flight_published_does_not():
    """With the body yawing (0.3 rad/s), the Coriolis term the paper neglects (eq. 8) biases the
    published observer; the full variant keeps both errors small."""
    flight, body_v, world_v, _ = paper_flight(duration=30.0, yaw_rate=0.3)
    late = flight.imu.t > 20.0
    errs = {}
    for kin in ("published", "full"):
        res = run_ii_observer(flight, IIObserverOptions(kinematics=kin), world_vz=world_v[:, 2])
        errs[kin] = (
            np.abs(res.eta[late] - body_v[late, :2]).max(),
            (np.abs(res.xi[late] - K_TRUE) / K_TRUE).max(),
        )
    assert errs["full"][0] < 0.01 and errs["full"][1] < 0.01
    assert errs["published"][0] > 5 * errs["full"][0]


def test_noisy_paper_simulation_steady_state_errors():
    flight, body_v, world_v, _ = paper_flight(seed=0, noise=(0.05, 0.003))
    res = run_ii_observer(flight, IIObserverOptions(kinematics="full"), world_vz=world_v[:, 2])
    late = res.t > 30.0
    v_rmse = np.sqrt(np.mean(np.sum((res.eta[late] - body_v[late, :2]) ** 2, axis=1)))
    k_err = np.abs(res.xi[late].mean(axis=0) - K_TRUE) / K_TRUE
    assert v_rmse < 0.1
    assert k_err.max() < 0.03


def test_missing_drag_coefficient_is_an_error():
    with pytest.raises(FlightDataError, match="mu/m"):
        IIObserver(IIObserverOptions())


def test_simulated_circle_noise_free_converges_velocity_first():
    """The simulator's seed-000 circle (closed-loop vehicle, AHRS attitude, rangefinder vertical
    velocity). Measured (full kinematics): velocity < 1 cm/s from 1.1 s, scale < 1 % from 3.5 s,
    then 0.09 mm/s and 0.35 %."""
    from fgnav.datasets.simulate import SimOptions, simulate

    flight = simulate(
        "circle",
        0,
        SimOptions(noise_free=True, images=False, slam_scale_drift_per_s=0.0, duration=20.0),
    )
    truth = flight.meta["truth"]
    K = np.asarray(truth["slam_axis_scale"][:2])
    res = run_ii_observer(
        flight, IIObserverOptions(kinematics="full", drag_k=tuple(truth["drag_k"]))
    )
    gt = flight.ground_truth
    body_v = np.einsum("nji,nj->ni", gt.world_R_body(), gt.world_v_body)
    v_err = np.abs(res.eta - body_v[:, :2]).max(axis=1)
    k_err = (np.abs(res.xi - K) / K).max(axis=1)
    t_v = res.t[np.argmax(v_err < 0.01)]
    t_k = res.t[np.argmax(k_err < 0.01)]
    assert 0.0 < t_v < t_k < 6.0
    late = res.t > 8.0
    assert v_err[late].max() < 2e-3
    assert k_err[late].max() < 0.01


def test_align_slam_axes_handles_a_rotated_offset_slam_frame():
    """A similarity SLAM (rotated frame, offset, one scale) fits eq. 4 once its positions are
    rotated into world axes with the attitude and the SLAM orientation."""
    from dataclasses import replace

    from fgnav.datasets.geometry import quat_wxyz_to_matrix, rpy_to_matrix

    flight, body_v, world_v, p = paper_flight(duration=25.0)
    s_true = 0.6
    slam_R_world = rpy_to_matrix(0.4, -0.2, 2.0)
    k = np.searchsorted(flight.imu.t, flight.slam.t)
    world_R_body = quat_wxyz_to_matrix(flight.attitude.world_q_body_wxyz[k])
    slam = replace(
        flight.slam,
        slam_t_cam=s_true * p[k] @ slam_R_world.T + [3.0, -1.0, 0.5],
        slam_q_cam_wxyz=matrix_to_quat_wxyz(slam_R_world @ world_R_body),  # camera = body
    )
    rotated = replace(flight, slam=slam)
    opts = IIObserverOptions(kinematics="full")
    aligned = run_ii_observer(rotated, opts, world_vz=world_v[:, 2], align_slam_axes=True)
    late = aligned.t > 15.0
    assert np.abs(aligned.xi[late] / s_true - 1).max() < 0.01
    raw = run_ii_observer(rotated, opts, world_vz=world_v[:, 2])
    assert np.abs(raw.xi[late] / s_true - 1).max() > 0.2
