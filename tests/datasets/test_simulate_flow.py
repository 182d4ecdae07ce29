"""Simulated optical flow: consistent with the flow factor's model, correlated noise as measured on
the real Crazyflie (lag-1 about -0.3), height gate, quality, native round trip, off by default."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from fgnav.datasets.native import read_flight, write_flight
from fgnav.datasets.simulate import SimOptions, SimulationError, simulate
from fgnav.factors.optical_flow import FlowSensor, predict_flow


def _flow_only(**kw) -> SimOptions:
    base = dict(images=False, slam_rate_hz=0.0, attitude_rate_hz=0.0, yaw_rate_hz=0.0)
    base.update(kw)
    return SimOptions(**base)


@pytest.fixture(scope="module")
def noise_free():
    return simulate("flowdeck", seed=0, options=_flow_only(noise_free=True, duration=12.0))


def test_noise_free_flow_matches_the_factor_model_at_the_true_state(noise_free):
    f = noise_free
    gt = f.ground_truth
    R = gt.world_R_body()
    calib = FlowSensor(f.calib.body_T_flow, f.calib.flow_pixels_per_rad)
    assert f.calib.flow_pixels_per_rad == 48.0
    assert len(f.flow) == 1200 and np.allclose(f.flow.dt, 0.01)
    err, sig = [], []
    for j in range(0, len(f.flow), 5):
        i1 = int(np.searchsorted(gt.t, f.flow.t[j] - 1e-9))
        i0 = int(np.searchsorted(gt.t, f.flow.t[j] - f.flow.dt[j] - 1e-9))
        T = np.eye(4)
        T[:3, :3] = R[i0]
        T[:3, 3] = 0.5 * (gt.world_t_body[i0] + gt.world_t_body[i1])
        v = 0.5 * (gt.world_v_body[i0] + gt.world_v_body[i1])
        omega = f.imu.body_omega[i0:i1].mean(axis=0)  # noise-free gyro = true rate
        err.append(predict_flow(T, v, 0.0, f.flow.dt[j], omega, calib) - f.flow.flow[j])
        sig.append(f.flow.flow[j])
    rms_err = np.sqrt(np.mean(np.square(err)))
    rms_sig = np.sqrt(np.mean(np.square(sig)))
    # Measured: 3e-4 px against 0.5 px of signal (interval-midpoint state vs integration).
    assert rms_sig > 0.3
    assert rms_err < 0.01 * rms_sig


def test_flow_dead_reckoning_with_true_attitude_and_height_recovers_the_path(noise_free):
    f = noise_free
    gt = f.ground_truth
    R = gt.world_R_body()
    idx = np.searchsorted(gt.t, f.flow.t - 1e-9)
    # Level sensor approximation inverted: body velocity from flow, true height and rate.
    ppr = f.calib.flow_pixels_per_rad
    h = gt.world_t_body[idx, 2] + (R[idx] @ f.calib.body_T_flow[:3, 3])[:, 2]
    c = R[idx][:, 2, 2]
    omega = f.imu.body_omega[idx - 1]
    # flow = ppr dt [-v_x c / h - w_y, -v_y c / h + w_x] in the sensor frame (x fwd, y right).
    vs_x = -(f.flow.flow[:, 0] / (ppr * f.flow.dt) + omega[:, 1]) * h / c
    vs_y = -(f.flow.flow[:, 1] / (ppr * f.flow.dt) - omega[:, 0]) * h / c
    body_v = np.stack([vs_x, -vs_y, np.zeros_like(vs_x)], axis=1)  # sensor y right -> body y left
    world_v = np.einsum("nij,nj->ni", R[idx], body_v)
    true_v = gt.world_v_body[idx]
    err = np.linalg.norm(world_v[:, :2] - true_v[:, :2], axis=1)
    # Vertical velocity and lever-arm rate terms are neglected here: a few cm/s at most.
    assert np.sqrt(np.mean(err**2)) < 0.05
    assert np.linalg.norm(true_v[:, :2], axis=1).max() > 1.0


def test_noise_has_the_requested_std_and_negative_lag1_correlation():
    opts = _flow_only(duration=20.0, flow_dropout_prob=0.0, flow_low_quality_prob=0.0)
    noisy = simulate("flowdeck", seed=3, options=opts)
    clean = simulate("flowdeck", seed=3, options=_flow_only(duration=20.0, noise_free=True))
    n = noisy.flow.flow - clean.flow.flow
    assert n.shape == (2000, 2)
    std = n.std(axis=0)
    rho = [np.corrcoef(n[1:, a], n[:-1, a])[0, 1] for a in range(2)]
    rho2 = [np.corrcoef(n[2:, a], n[:-2, a])[0, 1] for a in range(2)]
    np.testing.assert_allclose(std, 0.2, rtol=0.06)
    np.testing.assert_allclose(rho, -0.3, atol=0.05)
    np.testing.assert_allclose(rho2, 0.0, atol=0.06)
    # The sum of 5 consecutive readings: variance 0.2^2 (5 - 2.4) = 0.104 px^2, not 0.2 px^2.
    s5 = n[: 2000 // 5 * 5].reshape(-1, 5, 2).sum(axis=1)
    np.testing.assert_allclose(s5.var(axis=0), 0.04 * 2.6, rtol=0.2)
    assert np.all((noisy.flow.quality >= 0.6) & (noisy.flow.quality <= 1.0))


def test_height_gate_dropouts_and_low_quality_are_counted():
    # vertical: 1 m .. 3 m; a 1.8 m minimum height drops the low part of every cycle.
    opts = SimOptions(
        images=False,
        duration=12.0,
        flow_rate_hz=50.0,
        flow_height_min=1.8,
        flow_dropout_prob=0.1,
        flow_low_quality_prob=0.2,
    )
    f = simulate("vertical", seed=1, options=opts)
    notes = f.meta["notes"]
    gt = f.ground_truth
    idx = np.searchsorted(gt.t, f.flow.t - 1e-9)
    h = gt.world_t_body[idx, 2] - 0.02  # sensor 2 cm under the body origin, level flight
    assert h.min() >= 1.8 - 1e-3
    assert notes["flow_out_of_height"] > 100 and notes["flow_dropouts"] > 20
    n_grid = 12 * 50
    assert len(f.flow) + notes["flow_out_of_height"] + notes["flow_dropouts"] == n_grid
    low = f.flow.quality < 0.5
    assert low.sum() == notes["flow_low_quality"] > 10
    assert f.meta["truth"]["flow"]["rate_hz"] == 50.0


def test_flow_is_off_by_default_except_on_flowdeck_and_other_streams_unchanged():
    base = SimOptions(images=False, duration=3.0)
    off = simulate("two-turns", seed=4, options=base)
    on = simulate(
        "two-turns", seed=4, options=SimOptions(images=False, duration=3.0, flow_rate_hz=100.0)
    )
    assert off.flow is None and "flow" not in off.meta["truth"]
    assert on.flow is not None and len(on.flow) > 250
    for s in ("imu", "range", "slam", "yaw", "attitude"):
        a, b = getattr(off, s), getattr(on, s)
        np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(off.imu.body_accel, on.imu.body_accel)
    np.testing.assert_array_equal(off.range.range, on.range.range)
    np.testing.assert_array_equal(off.slam.slam_t_cam, on.slam.slam_t_cam)
    assert simulate("flowdeck", seed=0, options=base).flow is not None
    assert (
        simulate(
            "flowdeck", seed=0, options=SimOptions(images=False, duration=3.0, flow_rate_hz=0.0)
        ).flow
        is None
    )


def test_terrain_step_under_the_sensor_raises_the_flow():
    box = ((-10.0, -10.0, 10.0, 10.0, 0.3),)  # the whole floor raised by 0.3 m
    plain = simulate("flowdeck", seed=0, options=_flow_only(noise_free=True, duration=4.0))
    raised = simulate(
        "flowdeck", seed=0, options=_flow_only(noise_free=True, duration=4.0, terrain_steps=box)
    )
    gt = plain.ground_truth
    idx = np.searchsorted(gt.t, plain.flow.t - 1e-9)
    h = gt.world_t_body[idx, 2] - 0.02
    moving = np.abs(plain.flow.flow[:, 0]) > 0.05
    ratio = raised.flow.flow[moving, 0] / plain.flow.flow[moving, 0]
    # Pure translation scales with 1 / height (rotation parts are small in this hover ramp).
    np.testing.assert_allclose(np.median(ratio / (h[moving] / (h[moving] - 0.3))), 1.0, atol=0.05)


def test_flow_round_trips_through_the_native_folder(tmp_path):
    f = simulate("flowdeck", seed=2, options=_flow_only(duration=2.0))
    back = read_flight(write_flight(f, tmp_path / "fl"))
    for a in ("t", "dt", "flow", "quality"):
        np.testing.assert_array_equal(getattr(back.flow, a), getattr(f.flow, a))
    np.testing.assert_array_equal(back.calib.body_T_flow, f.calib.body_T_flow)
    assert back.calib.flow_pixels_per_rad == 48.0
    assert (
        (tmp_path / "fl" / "flow.csv")
        .read_text()
        .startswith("t [s],dt [s],flow_x [px],flow_y [px],quality [-]")
    )
    # A calib.yaml written before the flow fields existed still reads (defaults).
    path = tmp_path / "fl" / "calib.yaml"
    d = yaml.safe_load(path.read_text())
    del d["body_T_flow"], d["flow_pixels_per_rad"]
    path.write_text(yaml.safe_dump(d))
    old = read_flight(tmp_path / "fl")
    assert old.calib.flow_pixels_per_rad == 1.0


@pytest.mark.parametrize(
    "field,value",
    [
        ("flow_noise_lag1", -0.7),
        ("flow_noise_lag1", 0.2),
        ("flow_pixels_per_rad", 0.0),
        ("flow_height_min", 6.0),
        ("flow_rate_hz", 500.0),
        ("flow_dropout_prob", 1.5),
    ],
)
def test_bad_flow_options_are_named(field, value):
    with pytest.raises(SimulationError, match=field):
        SimOptions(**{field: value})
