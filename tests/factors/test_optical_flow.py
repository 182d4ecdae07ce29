"""Optical-flow factor: camera-over-plane simulation, Jacobians, zero error, floors and gating."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from fgnav.datasets.types import DOWNWARD_FLOW
from fgnav.factors.optical_flow import (
    MIN_HEIGHT,
    FlowMeasurement,
    FlowSensor,
    flow_sum_sigma,
    gate_flow,
    make_optical_flow_factor,
    optical_flow_error,
    predict_flow,
)

from fgnav.keys import G, V, X

from .numdiff import assert_jacobians_close, unit_noise


def _random_state(rng: np.random.Generator) -> tuple[gtsam.Pose3, np.ndarray, float, np.ndarray]:
    pose = gtsam.Pose3(
        gtsam.Rot3.Expmap(rng.uniform(-0.4, 0.4, 3)), np.r_[rng.uniform(-3, 3, 2), 1.5]
    )
    return pose, rng.uniform(-2, 2, 3), float(rng.uniform(-0.5, 0.3)), rng.uniform(-1, 1, 3)


def _random_sensor(rng: np.random.Generator, ppr: float = 48.0) -> FlowSensor:
    body_T_flow = gtsam.Pose3(
        gtsam.Rot3(DOWNWARD_FLOW[:3, :3]).compose(gtsam.Rot3.Expmap(rng.uniform(-0.15, 0.15, 3))),
        rng.uniform(-0.1, 0.1, 3),
    )
    return FlowSensor(body_T_flow.matrix(), ppr)


def _camera_angles(world_T_body: np.ndarray, sensor: FlowSensor, world_p: np.ndarray) -> np.ndarray:
    """Image angles [rad] (x, y) of a world point seen by the pinhole sensor (axis = +z)."""
    world_T_flow = world_T_body @ sensor.body_T_flow
    p = world_T_flow[:3, :3].T @ (world_p - world_T_flow[:3, 3])
    return np.array([p[0] / p[2], p[1] / p[2]])


def _propagate(world_T_body: np.ndarray, v: np.ndarray, omega: np.ndarray, tau: float):
    out = np.eye(4)
    out[:3, :3] = world_T_body[:3, :3] @ gtsam.Rot3.Expmap(omega * tau).matrix()
    out[:3, 3] = world_T_body[:3, 3] + v * tau
    return out


@pytest.mark.parametrize("seed", range(4))
def test_signs_match_a_camera_moving_over_a_plane(seed: int) -> None:
    """Finite-difference simulation: track the ground point on the optical axis through a pinhole
    sensor moving with (v, omega); its image motion over dt equals the model's flow."""
    rng = np.random.default_rng(100 + seed)
    pose, v, ground, omega = _random_state(rng)
    sensor = _random_sensor(rng)
    m = pose.matrix()
    world_T_flow = m @ sensor.body_T_flow
    axis = world_T_flow[:3, 2]
    sensor_p = world_T_flow[:3, 3]
    # Ground point on the optical axis.
    world_p = sensor_p + (ground - sensor_p[2]) / axis[2] * axis
    assert np.allclose(_camera_angles(m, sensor, world_p), 0.0, atol=1e-12)
    tau, dt = 1e-5, 0.01
    plus = _camera_angles(_propagate(m, v, omega, tau), sensor, world_p)
    minus = _camera_angles(_propagate(m, v, omega, -tau), sensor, world_p)
    rate = (plus - minus) / (2 * tau)  # tan(angle) = angle to first order at the axis
    expected = sensor.pixels_per_rad * dt * rate
    got = predict_flow(pose, v, ground, dt, omega, sensor)
    assert got == pytest.approx(expected, rel=1e-6, abs=1e-9)


def test_level_forward_flight_and_roll_rate_signs() -> None:
    sensor = FlowSensor(DOWNWARD_FLOW, 1.0)
    pose = gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 2.0]))
    # Forward at 1 m/s, 2 m up: the ground moves backwards (-x) at 0.5 rad/s.
    f = predict_flow(pose, np.array([1.0, 0.0, 0.0]), 0.0, 0.1, np.zeros(3), sensor)
    assert f == pytest.approx([-0.05, 0.0])
    # Left (+y body FLU) is -y in the sensor (y right): ground moves +y in the image.
    f = predict_flow(pose, np.array([0.0, 1.0, 0.0]), 0.0, 0.1, np.zeros(3), sensor)
    assert f == pytest.approx([0.0, 0.05])
    # Climbing moves the axis point nowhere.
    f = predict_flow(pose, np.array([0.0, 0.0, 1.0]), 0.0, 0.1, np.zeros(3), sensor)
    assert f == pytest.approx([0.0, 0.0])


def test_tilt_divides_distance_by_cos() -> None:
    sensor = FlowSensor(DOWNWARD_FLOW, 1.0)
    roll = np.deg2rad(20.0)
    # Rolled body moving along body x (horizontal): d = h / cos(roll).
    pose = gtsam.Pose3(gtsam.Rot3.Roll(roll), np.array([0.0, 0.0, 1.0]))
    f = predict_flow(pose, np.array([1.0, 0.0, 0.0]), 0.0, 1.0, np.zeros(3), sensor)
    assert f[0] == pytest.approx(-np.cos(roll) / 1.0)


@pytest.mark.parametrize("seed", range(6))
def test_jacobians_match_central_differences(seed: int) -> None:
    rng = np.random.default_rng(400 + seed)
    pose, v, ground, omega = _random_state(rng)
    sensor = _random_sensor(rng)
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(V(0), v)
    values.insert(G(0), np.array([ground]))
    meas = FlowMeasurement(rng.normal(0, 3, 2), 0.05)
    factor = make_optical_flow_factor(X(0), V(0), G(0), meas, omega, sensor, unit_noise(2))
    assert_jacobians_close(factor, values, [6, 3, 1])


def test_zero_error_at_a_consistent_state() -> None:
    rng = np.random.default_rng(7)
    pose, v, ground, omega = _random_state(rng)
    sensor = _random_sensor(rng)
    z = predict_flow(pose, v, ground, 0.012, omega, sensor)
    e, J = optical_flow_error(pose, v, np.array([ground]), omega, FlowMeasurement(z, 0.012), sensor)
    assert np.abs(e).max() < 1e-12
    assert [j.shape for j in J] == [(2, 6), (2, 3), (2, 1)]
    # A wrong velocity gives an error.
    e2, _ = optical_flow_error(
        pose, v + [0.1, 0, 0], np.array([ground]), omega, FlowMeasurement(z, 0.012), sensor
    )
    assert np.abs(e2).max() > 1e-3


def test_height_is_floored() -> None:
    sensor = FlowSensor(DOWNWARD_FLOW, 1.0)
    pose = gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 0.0, 0.0]))
    e, J = optical_flow_error(
        pose,
        np.array([1.0, 0, 0]),
        np.array([0.5]),
        np.zeros(3),
        FlowMeasurement(np.zeros(2), 0.01),
        sensor,
    )
    assert e[0] == pytest.approx(-0.01 / MIN_HEIGHT)
    assert np.all(np.isfinite(J[0])) and J[2][0, 0] == 0.0


def test_bad_measurement_raises() -> None:
    sensor = FlowSensor(DOWNWARD_FLOW, 1.0)
    with pytest.raises(ValueError, match="dt"):
        make_optical_flow_factor(
            X(0),
            V(0),
            G(0),
            FlowMeasurement(np.zeros(2), 0.0),
            np.zeros(3),
            sensor,
            unit_noise(2),
        )
    with pytest.raises(ValueError, match="flow"):
        make_optical_flow_factor(
            X(0),
            V(0),
            G(0),
            FlowMeasurement(np.array([np.nan, 0]), 0.01),
            np.zeros(3),
            sensor,
            unit_noise(2),
        )


def test_sum_sigma_of_ma1_matches_monte_carlo() -> None:
    rng = np.random.default_rng(3)
    rho, n = -0.3, 5
    # MA(1) e_i = a_i + theta a_{i-1} with theta / (1 + theta^2) = rho.
    theta = (1 - np.sqrt(1 - 4 * rho**2)) / (2 * rho)
    a = rng.normal(size=(200_000, n + 1))
    e = (a[:, 1:] + theta * a[:, :-1]) / np.sqrt(1 + theta**2)
    assert np.corrcoef(e[:, 0], e[:, 1])[0, 1] == pytest.approx(rho, abs=0.01)
    measured = float(e.sum(axis=1).std())
    assert flow_sum_sigma(1.0, n, rho) == pytest.approx(measured, rel=0.01)


@pytest.mark.parametrize(
    ("height", "cos_tilt", "quality", "ok", "reason"),
    [
        (1.0, 1.0, -1.0, True, "ok"),
        (1.0, 1.0, 0.8, True, "ok"),
        (0.02, 1.0, -1.0, False, "height"),
        (5.0, 1.0, -1.0, False, "height"),
        (1.0, np.cos(np.deg2rad(40)), -1.0, False, "tilt"),
        (1.0, 1.0, 0.1, False, "quality"),
        (np.nan, 1.0, 0.5, False, "non-finite"),
    ],
)
def test_gate_flow(height, cos_tilt, quality, ok, reason) -> None:
    accepted, why = gate_flow(height, cos_tilt, quality, 0.1, 4.0, np.deg2rad(30), 0.3)
    assert accepted is ok
    assert why.startswith(reason)
