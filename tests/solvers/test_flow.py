"""Optical flow in the graph: the keyframe-window factor (sum, correlated noise, gates by reason),
the builder's association, observability, and the batch smoother on a simulated flow-deck flight
(IMU + flow + range, no SLAM): velocity bound, and flow improves an IMU + range flight."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from fgnav.datasets.events import FlowSample
from fgnav.datasets.geometry import rpy_to_matrix
from fgnav.datasets.simulate import SimOptions, simulate
from fgnav.factors.optical_flow import flow_sum_sigma

from fgnav.keys import G, V, X
from fgnav.solvers.batch import BatchOptions, solve_batch
from fgnav.solvers.flow import (
    FlowFactorOptions,
    FlowRejectWatch,
    flow_keyframe_factor,
    flow_options,
    flow_sensor_height,
    mean_rate_over,
)
from fgnav.solvers.graph import GraphBuilder, GraphOptions, ObservabilityError

FLOW_ONLY = dict(images=False, slam_rate_hz=0.0, attitude_rate_hz=0.0, yaw_rate_hz=0.0)


@pytest.fixture(scope="module")
def clean_flight():
    return simulate(
        "flowdeck", seed=0, options=SimOptions(noise_free=True, duration=8.0, **FLOW_ONLY)
    )


@pytest.fixture(scope="module")
def noisy_flight():
    return simulate("flowdeck", seed=0, options=SimOptions(duration=20.0, **FLOW_ONLY))


def _samples(flight, i0: int, n: int) -> list[FlowSample]:
    fl = flight.flow
    return [
        FlowSample(
            float(fl.t[i]), float(fl.t[i]), float(fl.dt[i]), fl.flow[i], float(fl.quality[i])
        )
        for i in range(i0, i0 + n)
    ]


def _true_values(flight, t: float) -> gtsam.Values:
    gt = flight.ground_truth
    i = int(np.argmin(np.abs(gt.t - t)))
    vals = gtsam.Values()
    vals.insert(X(0), gtsam.Pose3(gtsam.Rot3(gt.world_R_body()[i]), gt.world_t_body[i]))
    vals.insert(V(0), gt.world_v_body[i])
    vals.insert(G(0), np.array([0.0]))
    return vals


def test_mean_rate_over_integrates_the_held_gyro():
    t = np.arange(0.0, 1.0, 0.005)
    w = np.stack([np.sin(7 * t), t, np.ones_like(t)], axis=1)
    got = mean_rate_over(t, w, np.array([0.1, 0.5]), np.array([0.2, 0.5125]))
    # Zero-order hold: sum of w_i * dt over the steps (partial steps at the ends).
    i0, i1 = 20, 40
    np.testing.assert_allclose(got[0], w[i0:i1].sum(axis=0) * 0.005, atol=1e-12)
    np.testing.assert_allclose(
        got[1], w[100] * 0.005 + w[101] * 0.005 + w[102] * 0.0025, atol=1e-12
    )


def test_window_factor_is_zero_at_the_true_state_and_sums_correlated_noise(clean_flight):
    f = clean_flight
    o = FlowFactorOptions()
    i0 = 400  # t = 4 s: moving
    s = _samples(f, i0, 5)
    t_mid = 0.5 * (s[0].t - s[0].dt + s[-1].t)
    res = flow_keyframe_factor(
        s,
        f.imu.t,
        f.imu.body_omega,
        f.calib,
        X(0),
        V(0),
        G(0),
        o,
        height=0.7,
        world_R_body=np.eye(3),
    )
    assert res.reason == "ok" and res.n_used == 5 and res.factor is not None
    ppr = f.calib.flow_pixels_per_rad
    assert res.sigma == pytest.approx(flow_sum_sigma(o.sigma_rad * ppr, 5, -0.3))
    e = res.factor.unwhitenedError(_true_values(f, t_mid))
    signal = np.linalg.norm(np.sum([x.flow for x in s], axis=0))
    assert signal > 1.0  # px over 50 ms
    # The state at the window centre stands for it: error well below the noise (0.34 px).
    assert np.linalg.norm(e) < 0.02 * signal and np.linalg.norm(e) < 0.1 * res.sigma
    # A missing reading splits the window into two independent runs.
    gap = s[:2] + s[3:]
    res2 = flow_keyframe_factor(
        gap, f.imu.t, f.imu.body_omega, f.calib, X(0), V(0), G(0), o, height=0.7
    )
    expected = math.sqrt(2 * flow_sum_sigma(o.sigma_rad * ppr, 2, -0.3) ** 2)
    assert res2.sigma == pytest.approx(expected) and res2.n_used == 4


def test_window_gates_count_readings_by_reason(clean_flight):
    f = clean_flight
    s = _samples(f, 300, 5)
    args = (f.imu.t, f.imu.body_omega, f.calib, X(0), V(0), G(0), FlowFactorOptions())
    low = [s[0]._replace(quality=0.2)] + s[1:]
    r = flow_keyframe_factor(low, *args, height=0.7)
    assert r.reason == "ok" and r.n_used == 4 and r.skipped == {"gated:quality": 1}
    bad = [s[0]._replace(flow=np.array([np.nan, 0.0]))] + s[1:]
    assert flow_keyframe_factor(bad, *args, height=0.7).skipped == {"non-finite": 1}
    # A counter at its rail (PMW3901: 32767 counts, 0.1 px each, over ~10 ms): no measurement.
    rail = [s[0]._replace(flow=np.array([3276.7, 0.0]))] + s[1:]
    r = flow_keyframe_factor(rail, *args, height=0.7)
    assert r.reason == "ok" and r.n_used == 4 and r.skipped == {"implausible-rate": 1}
    r = flow_keyframe_factor(s, *args, height=0.05)
    assert (r.factor, r.reason, r.skipped) == (None, "gated:height", {"gated:height": 5})
    r = flow_keyframe_factor(s, *args, height=0.7, world_R_body=rpy_to_matrix(0.8, 0.0, 0.0))
    assert (r.factor, r.reason, r.skipped) == (None, "gated:tilt", {"gated:tilt": 5})
    r = flow_keyframe_factor(s, *args, height=None)
    assert (r.reason, r.skipped) == ("no-height", {"no-height": 5})
    r = flow_keyframe_factor(s[:1], *args, height=0.7)
    assert (r.factor, r.reason) == (None, "few-readings")
    assert flow_keyframe_factor([], *args, height=0.7).reason == "empty"


def test_flow_sensor_height_from_a_tilted_range_reading():
    R = rpy_to_matrix(0.2, -0.1, 0.5)
    T_range = np.diag([1.0, -1.0, -1.0, 1.0])
    T_range[:3, 3] = [0.03, 0.02, -0.05]
    T_flow = np.diag([1.0, -1.0, -1.0, 1.0])
    T_flow[:3, 3] = [0.0, 0.0, -0.02]
    z_body = 0.9
    z_range = z_body + (R @ T_range[:3, 3])[2]
    r = z_range / -(R @ T_range[:3, 2])[2]
    h = flow_sensor_height(r, R, T_range, T_flow)
    assert h == pytest.approx(z_body + (R @ T_flow[:3, 3])[2], abs=1e-12)


def test_options_from_a_table_name_unknown_keys():
    assert flow_options({"quality_min": 0.3}).quality_min == 0.3
    with pytest.raises(Exception, match="unknown option"):
        flow_options({"qualty_min": 0.3})
    with pytest.raises(Exception, match="lag1_corr"):
        flow_options({"lag1_corr": -0.9})


def test_builder_uses_flow_by_default_and_counts_skips(noisy_flight):
    f = noisy_flight
    b = GraphBuilder(f, GraphOptions())
    assert b.options.use_flow is True and b.flow is not None
    n_low = f.meta["notes"]["flow_low_quality"]
    graph, _ = b.build()
    rep = b.report()
    assert rep["skipped"].get("flow:gated:quality", 0) == n_low > 0
    assert rep["factors"]["flow"] >= 0.98 * b.K
    used = rep["flow"]["flow-readings-used"]
    assert used + sum(v for k, v in rep["skipped"].items() if k.startswith("flow:")) == len(f.flow)
    assert rep["flow"]["all_rejected"] is None
    # Off when asked; refused without the rangefinder.
    assert GraphBuilder(f, GraphOptions(use_flow=False)).flow is None
    with pytest.raises(ObservabilityError, match="rangefinder"):
        GraphBuilder(f, GraphOptions(use_flow=True, use_range=False))
    # A flight without flow: auto is off.
    other = simulate("hover", seed=0, options=SimOptions(images=False, duration=3.0))
    assert GraphBuilder(other, GraphOptions()).options.use_flow is False


def _hvel_rmse(est, flight) -> float:
    gt = flight.ground_truth
    idx = np.searchsorted(gt.t, est.trajectory.t - 1e-9)
    dv = est.trajectory.world_v_body[:, :2] - gt.world_v_body[idx, :2]
    return float(np.sqrt(np.mean(np.sum(dv**2, axis=1))))


#: Batch on flowdeck seed 0, 20 s, IMU + flow + range (+ the drag factor on by default), no SLAM,
#: attitude or yaw stream. Measured 2026-12-02: horizontal velocity RMSE 0.017 m/s with flow,
#: 0.037 m/s without it (IMU + range + drag); 4-DoF ATE 3.9 cm vs 19.2 cm.
HVEL_RMSE_FLOW_BOUND = 0.025


def test_batch_with_flow_and_range_observes_velocity_and_flow_helps(noisy_flight):
    f = noisy_flight
    opts = BatchOptions(graph=GraphOptions(), covariance="none")
    with_flow = solve_batch(f, opts)
    without = solve_batch(f, BatchOptions(graph=GraphOptions(use_flow=False), covariance="none"))
    assert with_flow.info["factors"]["flow"] > 350
    v_flow, v_none = _hvel_rmse(with_flow, f), _hvel_rmse(without, f)
    assert v_flow < HVEL_RMSE_FLOW_BOUND
    assert v_flow < 0.7 * v_none
    # Without drag the IMU + range graph has no horizontal velocity source at all.
    with pytest.raises(ObservabilityError, match="unobservable"):
        GraphBuilder(f, GraphOptions(use_flow=False, use_drag=False))
    no_drag = solve_batch(f, BatchOptions(graph=GraphOptions(use_drag=False), covariance="none"))
    assert _hvel_rmse(no_drag, f) < HVEL_RMSE_FLOW_BOUND


def test_reject_watch_warns_once_when_every_reading_is_rejected_for_5_s(caplog):
    """Windows of 10 readings every 0.1 s: all rejected from 1 s on -> one warning at 6 s naming
    the counts; a window with a usable reading ends the run; a second run is counted, not
    warned again; a window not newer than the last (a rebuild) is ignored."""
    import logging

    w = FlowRejectWatch("f")
    with caplog.at_level(logging.WARNING, logger="fgnav.solvers.flow"):
        for i in range(10):  # usable
            w.add(0.1 * i, 0.1 * i + 0.09, 10, {"gated:quality": 3})
        for i in range(10, 100):
            w.add(0.1 * i, 0.1 * i + 0.09, 10, {"gated:quality": 6, "bad-interval": 4})
            w.add(0.1 * i, 0.1 * i + 0.09, 10, {"gated:quality": 6, "bad-interval": 4})  # again
            if i < 60:
                assert w.report() is None
        assert [r.getMessage() for r in caplog.records] == [
            "f: every flow reading rejected for 5.1 s (1.00-6.09 s, 510 readings: bad-interval "
            "204, gated:quality 306); the flow stream is not used"
        ]
        # Window gating (height, tilt) is not a rejection of the readings.
        w.add(10.0, 10.09, 10, {"gated:height": 10})
        for i in range(101, 170):
            w.add(0.1 * i, 0.1 * i + 0.09, 5, {"non-finite": 5})
    assert len(caplog.records) == 1
    rep = w.report()
    assert rep["since_s"] == 1.0 and rep["readings"] == 900 and rep["runs"] == 2
    assert rep["reasons"] == {"gated:quality": 540, "bad-interval": 360}


def test_builder_reports_a_flow_stream_rejected_entirely(noisy_flight, caplog):
    """Quality 0 on every reading: one warning and ``info["flow"]["all_rejected"]``."""
    import dataclasses
    import logging

    fl = noisy_flight.flow
    f = dataclasses.replace(
        noisy_flight, flow=dataclasses.replace(fl, quality=np.zeros_like(fl.quality))
    )
    b = GraphBuilder(f, GraphOptions())
    with caplog.at_level(logging.WARNING, logger="fgnav.solvers.flow"):
        b.build()
        b.build()
    msgs = [
        r.getMessage() for r in caplog.records if "every flow reading rejected" in r.getMessage()
    ]
    assert len(msgs) == 1
    rep = b.report()["flow"]["all_rejected"]
    assert rep["runs"] == 1 and set(rep["reasons"]) == {"gated:quality"}
    assert rep["until_s"] - rep["since_s"] > 15.0
