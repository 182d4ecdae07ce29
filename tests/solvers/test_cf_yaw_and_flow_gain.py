"""Issue 17 (a): the yaw-rate bias held at its prior under a thrust-only prediction with no yaw
source; the flow sensor's rate-dependent gain (``Calibration.flow_rate_gain``) undone on each
keyframe window."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fgnav.datasets.crazyflie import FLOW_PIXELS_PER_RAD, FLOW_RATE_GAIN, crazyflie_calibration
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.native import calibration_from_dict, calibration_to_dict
from fgnav.datasets.types import Calibration, ImuNoise

from fgnav.solvers.flow import linearise_flow
from fgnav.solvers.graph import GraphOptions, gyro_bias_prior_sigmas


def test_yaw_rate_bias_prior_lowered_only_when_unobserved():
    calib = Calibration(imu_noise=ImuNoise(gyro_bias_sigma=3e-3))
    o = GraphOptions()
    np.testing.assert_allclose(gyro_bias_prior_sigmas(o, calib, False), [3e-3] * 3)
    np.testing.assert_allclose(gyro_bias_prior_sigmas(o, calib, True), [3e-3, 3e-3, 1e-4])
    off = GraphOptions(thrust_only_gyro_z_sigma=None)
    np.testing.assert_allclose(gyro_bias_prior_sigmas(off, calib, True), [3e-3] * 3)
    # Never above the calibration's sigma.
    wide = GraphOptions(thrust_only_gyro_z_sigma=0.1)
    np.testing.assert_allclose(gyro_bias_prior_sigmas(wide, calib, True), [3e-3] * 3)
    with pytest.raises(FlightDataError, match="thrust_only_gyro_z_sigma"):
        GraphOptions(thrust_only_gyro_z_sigma=0.0).check()


@pytest.mark.parametrize("rate", [0.05, 0.3, 0.56, 0.9, 1.3])
def test_linearise_flow_inverts_the_gain(rate):
    rng = np.random.default_rng(17)
    a, b = FLOW_RATE_GAIN
    ppr, dt = FLOW_PIXELS_PER_RAD, 0.05
    d = rng.normal(size=2)
    r = rate * d / np.linalg.norm(d)
    measured = (a + b * np.linalg.norm(r)) * r * ppr * dt
    np.testing.assert_allclose(
        linearise_flow(measured, dt, ppr, FLOW_RATE_GAIN), r * ppr * dt, rtol=1e-12, atol=1e-12
    )


def test_linearise_flow_identity_zero_and_clamp():
    f = np.array([1.5, -2.0])
    np.testing.assert_array_equal(linearise_flow(f, 0.05, 48.0, (1.0, 0.0)), f)
    np.testing.assert_array_equal(
        linearise_flow(np.zeros(2), 0.05, 48.0, FLOW_RATE_GAIN), np.zeros(2)
    )
    np.testing.assert_allclose(linearise_flow(f, 0.05, 48.0, (2.0, 0.0)), f / 2)
    # Beyond the top of the curve (a^2 / (4 |b|) = 1.36 rad/s): the rate at the top.
    a, b = FLOW_RATE_GAIN
    big = np.array([3.0, 0.0]) * 48.0 * 0.05
    np.testing.assert_allclose(
        linearise_flow(big, 0.05, 48.0, FLOW_RATE_GAIN), [a / (-2 * b) * 48.0 * 0.05, 0.0]
    )


def test_flow_rate_gain_in_the_crazyflie_calibration_and_native_files():
    c = crazyflie_calibration()
    assert c.flow_rate_gain == FLOW_RATE_GAIN
    a, b = FLOW_RATE_GAIN
    assert a + b * 0.56 == pytest.approx(1.0, abs=0.005)  # gain 1 near 0.56 rad/s
    d = calibration_to_dict(c)
    back = calibration_from_dict(d, Path("calib.yaml"))
    assert back.flow_rate_gain == pytest.approx(FLOW_RATE_GAIN)
    del d["flow_rate_gain"]  # a file written before the key existed: linear
    assert calibration_from_dict(d, Path("calib.yaml")).flow_rate_gain == (1.0, 0.0)
    with pytest.raises(FlightDataError, match="flow_rate_gain"):
        Calibration(flow_rate_gain=(0.0, 0.1)).check()
