"""The thrust-only IMU prediction's drag dynamics (``GraphOptions.thrust_only_drag_sigma``: the
body x, y accelerometer bias tied to ``k u_xy`` by the drag factor with a zero measurement) in the
batch and push smoothers, and the gyro-bias prior taken from the calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fgnav.datasets.crazyflie import CRAZYFLIE_IMU_NOISE
from fgnav.datasets.errors import FlightFormatError
from fgnav.datasets.native import calibration_from_dict, calibration_to_dict
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate
from fgnav.datasets.types import Calibration, ImuNoise

from fgnav.eval.flow_table import flow_figures
from fgnav.solvers.batch import BatchOptions, solve_batch
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.graph import GraphOptions, gyro_bias_prior_sigma
from fgnav.solvers.online import replay_online

TRUE_DRAG_K = SimOptions().drag_k


@pytest.fixture(scope="module")
def flight():
    # Crazyflie-like: flow + range, 0.4-1.3 m over the floor; the accelerometer's horizontal
    # channels thrown away by a forced thrust-only prediction.
    return simulate("flowdeck", seed=1, options=SimOptions(duration=20.0, images=False))


def _graph(sigma: float | None) -> GraphOptions:
    return GraphOptions(
        use_slam=False, use_drag=False, accel_horizontal="thrust-only", thrust_only_drag_sigma=sigma
    )


def test_batch_drag_dynamics_estimate_drag_and_velocity(flight):
    with_dyn = solve_batch(flight, BatchOptions(graph=_graph(0.1)))
    without = solve_batch(flight, BatchOptions(graph=_graph(None)))
    assert without.drag_k is None
    np.testing.assert_allclose(with_dyn.drag_k, TRUE_DRAG_K, atol=0.1)
    assert with_dyn.info["factors"].get("drag-dynamics", 0) > 300
    v_dyn = flow_figures(with_dyn, flight.ground_truth)["hvel100_rmse_mps"]
    v_none = flow_figures(without, flight.ground_truth)["hvel100_rmse_mps"]
    # Measured: 0.024 vs 0.033 m/s.
    assert v_dyn < 0.03 and v_dyn < 0.85 * v_none, (v_dyn, v_none)


def test_push_drag_dynamics_halve_the_causal_velocity_error(flight):
    with_dyn = replay_online(flight, FixedLagOptions(graph=_graph(0.1)))
    without = replay_online(flight, FixedLagOptions(graph=_graph(None)))
    assert with_dyn.info["used"].get("drag-dynamics", 0) > 300
    assert "drag-dynamics" not in without.info["used"]
    v_dyn = flow_figures(with_dyn, flight.ground_truth)["hvel100_rmse_mps"]
    v_none = flow_figures(without, flight.ground_truth)["hvel100_rmse_mps"]
    # Measured: 0.050 vs 0.094 m/s.
    assert v_dyn < 0.065 and v_dyn < 0.7 * v_none, (v_dyn, v_none)


def test_push_auto_ends_the_provisional_thrust_only_on_a_usable_accelerometer(flight):
    est = replay_online(flight, FixedLagOptions(graph=GraphOptions(use_slam=False)))
    assert est.info["accel_check"]["decision"] == "usable"
    assert est.info["accel_horizontal"] == "measured"
    assert "drag" in est.info["used"]


def test_gyro_bias_prior_from_the_calibration():
    calib = Calibration(imu_noise=ImuNoise(gyro_bias_sigma=0.003))
    assert gyro_bias_prior_sigma(GraphOptions(), calib) == 0.003
    assert gyro_bias_prior_sigma(GraphOptions(prior_gyro_bias_sigma=0.02), calib) == 0.02
    assert gyro_bias_prior_sigma(GraphOptions(), Calibration()) == 0.01
    assert CRAZYFLIE_IMU_NOISE.gyro_bias_sigma == pytest.approx(3e-3)


def test_native_calibration_without_gyro_bias_sigma_reads_the_default():
    d = calibration_to_dict(Calibration(imu_noise=ImuNoise(gyro_bias_sigma=0.004)))
    assert calibration_from_dict(d, Path("calib.yaml")).imu_noise.gyro_bias_sigma == 0.004
    del d["imu_noise"]["gyro_bias_sigma"]  # a file written before the key existed
    assert calibration_from_dict(d, Path("calib.yaml")).imu_noise.gyro_bias_sigma == 0.01
    d["imu_noise"]["bogus"] = 1.0
    with pytest.raises(FlightFormatError, match="imu_noise"):
        calibration_from_dict(d, Path("calib.yaml"))


def test_native_calibration_rest_bias_removed_flag_round_trips():
    d = calibration_to_dict(Calibration(imu_noise=ImuNoise(rest_bias_removed=True)))
    assert d["imu_noise"]["rest_bias_removed"] is True  # written as a boolean
    assert calibration_from_dict(d, Path("calib.yaml")).imu_noise.rest_bias_removed is True
    del d["imu_noise"]["rest_bias_removed"]  # a file written before the key existed
    assert calibration_from_dict(d, Path("calib.yaml")).imu_noise.rest_bias_removed is False
    d["imu_noise"]["rest_bias_removed"] = "yes"
    with pytest.raises(FlightFormatError, match="imu_noise.rest_bias_removed: expected a boolean"):
        calibration_from_dict(d, Path("calib.yaml"))
    assert CRAZYFLIE_IMU_NOISE.rest_bias_removed
