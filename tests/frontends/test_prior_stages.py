"""The front-ends that supply priors as an event-fed stage: causal, and the whole-flight
functions are a replay into it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import ImuSample, flight_streams, replay, replay_flight
from fgnav.datasets.geometry import interpolate_quat_wxyz
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.frontends.ii_observer import IIObserverOptions, run_ii_observer
from fgnav.frontends.pipeline import replay_stage
from fgnav.frontends.prior_stages import FrontendPriorStage, PriorOptions, prior_options


@pytest.fixture(scope="module")
def vertical():
    return simulate("vertical", seed=1, options=SimOptions(images=False, duration=30.0))


def _opts(flight):
    return PriorOptions(
        sources=("observer", "ml-scale"), drag_k=tuple(flight.meta["truth"]["drag_k"])
    )


def _feed(flight, opts, t_stop=None):
    stage = FrontendPriorStage(flight.calib, opts, keep_history=True)
    checks = []
    for ev in replay_flight(flight, ("imu", "attitude", "range", "yaw", "slam")):
        if t_stop is not None and ev.arrival > t_stop:
            break
        stage.feed(ev)
        if ev.arrival >= 8.0 and not checks:
            checks.append((ev.arrival, stage.velocity_at(ev.arrival, 0.05)))
    return stage, checks


def test_stage_fed_up_to_T_gives_the_full_runs_outputs_at_T(vertical):
    """Causality: the outputs at T of a stage fed the events arriving up to T are those of the
    stage fed the whole flight (nothing depends on later events)."""
    opts = _opts(vertical)
    full, _ = _feed(vertical, opts)
    full.flush()
    T = 17.3
    part, _ = _feed(vertical, opts, t_stop=T)
    rows_p, rows_f = part.observer_result(), full.observer_result()
    n = len(rows_p.t)
    assert n > 0 and rows_p.t[-1] <= T
    np.testing.assert_array_equal(rows_p.t, rows_f.t[:n])
    np.testing.assert_array_equal(rows_p.world_v_body, rows_f.world_v_body[:n])
    np.testing.assert_array_equal(rows_p.xi, rows_f.xi[:n])
    # The ML scale at T is the full run's history entry at the last pair ending by T.
    hp = part.scale_result().history[0]
    hf = full.scale_result().history[0]
    assert len(hp) >= opts.min_pairs
    np.testing.assert_array_equal(hp, hf[: len(hp)])
    s, sig, n_pairs = part.scale(0)
    assert (s, sig) == (hp[-1, 1], hp[-1, 2]) and n_pairs == len(hp)
    # Before the settle time no velocity; after it, the value in the full history.
    assert part.velocity_at(2.0, 0.05) is None
    v, sigma = part.velocity_at(15.0, 0.05)
    i = int(np.argmin(np.abs(rows_f.t - 15.0)))
    np.testing.assert_array_equal(v, rows_f.world_v_body[i])
    assert sigma == opts.velocity_sigma


def test_stage_outputs_are_accurate_against_truth(vertical):
    stage, _ = _feed(vertical, _opts(vertical))
    s_true = vertical.meta["truth"]["slam_sessions"]["0"]["scale"]
    s, sig, _ = stage.scale(0)
    assert s == pytest.approx(s_true, rel=0.02)
    assert abs(s - s_true) < 3 * sig + 0.005 * s_true
    gt = vertical.ground_truth
    res = stage.observer_result()
    keep = res.t >= res.t[0] + stage.options.settle_time
    j = np.clip(np.searchsorted(gt.t, res.t[keep]), 0, len(gt) - 1)
    err = np.linalg.norm(res.world_v_body[keep, :2] - gt.world_v_body[j, :2], axis=1)
    assert np.sqrt(np.mean(err**2)) < stage.options.velocity_sigma
    # velocity_at gives the newest outputs (the last HISTORY_S).
    v, _ = stage.velocity_at(res.t[-1] - 1.0, 0.05)
    np.testing.assert_array_equal(
        v, res.world_v_body[int(np.argmin(np.abs(res.t - res.t[-1] + 1.0)))]
    )


def test_whole_flight_observer_is_a_replay_into_the_stage(vertical):
    """run_ii_observer (the compare row) and the stage replay agree sample by sample."""
    fl = vertical
    k = tuple(fl.meta["truth"]["drag_k"])
    ref = run_ii_observer(
        fl,
        IIObserverOptions(kinematics="full", drag_k=k),
        world_q_body_wxyz=interpolate_quat_wxyz(
            fl.attitude.t, fl.attitude.world_q_body_wxyz, fl.imu.t
        ),
        align_slam_axes=True,
    )
    res = replay_stage(fl, PriorOptions(sources=("observer",), drag_k=k)).observer_result()
    np.testing.assert_array_equal(res.t, ref.t)
    np.testing.assert_allclose(res.world_v_body, ref.world_v_body, atol=1e-9)
    np.testing.assert_allclose(res.xi, ref.xi, atol=1e-9)
    assert res.counts["slam_used"] == ref.counts["slam_used"]


def test_stage_without_attitude_stream_runs_the_attitude_ekf(vertical):
    fl = dataclasses.replace(vertical, attitude=None)
    stage = FrontendPriorStage(fl.calib, _opts(fl))
    for ev in replay(flight_streams(fl, ("imu", "range", "yaw", "slam"))):
        stage.feed(ev)
    assert stage.all_counts.get("attitude_ekf") == 1
    assert stage.velocity_at(20.0, 0.05) is not None
    assert stage.scale(0) is not None


def test_attitude_stream_that_stops_hands_over_to_the_ekf_and_buffers_stay_bounded(
    vertical, caplog
):
    """The attitude stream stops at 6 s: the stage waited for it for ever (IMU, range and SLAM
    buffered without bound, no output after 6 s). Now, after 1 s of IMU time without it: one
    warning, the attitude EKF takes over, the stage keeps up; and with the IMU stopping too, the
    range and SLAM buffers stay bounded."""
    import logging

    from fgnav.frontends.prior_stages import HOLD_MAX_S

    att = vertical.attitude
    fl = dataclasses.replace(vertical, attitude=att.select(att.t <= 6.0))
    stage = FrontendPriorStage(fl.calib, _opts(fl))
    with caplog.at_level(logging.WARNING, logger="fgnav.frontends.prior_stages"):
        for ev in replay_flight(fl, ("imu", "attitude", "range", "yaw", "slam")):
            stage.feed(ev)
            assert len(stage._imu) < 2000 and len(stage._range) < 500
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 1 and "the attitude stream stopped at t=6.000 s" in msgs[0]
    assert stage.attitude_mode == "ekf" and stage.counts["attitude_stream_stopped"] == 1
    assert stage._t_done > 29.9
    assert stage.velocity_at(25.0, 0.05) is not None
    sc = stage.scale(0)
    full, _ = _feed(vertical, _opts(vertical))
    assert sc is not None and abs(sc[0] / full.scale(0)[0] - 1) < 0.02
    # The IMU stops at 5 s as well: what arrives after is held at most HOLD_MAX_S.
    stage = FrontendPriorStage(fl.calib, _opts(fl))
    for ev in replay_flight(fl, ("imu", "attitude", "range", "yaw", "slam")):
        if isinstance(ev, ImuSample) and ev.t > 5.0:
            continue
        stage.feed(ev)
    assert stage._range[-1][0] - stage._range[0][0] <= HOLD_MAX_S
    assert stage._slam_ml[-1].t - stage._slam_ml[0].t <= HOLD_MAX_S
    assert stage.counts["range_held_too_long"] > 0 and stage.counts["ml_slam_held_too_long"] > 0


def test_prior_options_from_table():
    assert prior_options({}) is None
    o = prior_options({"sources": ["observer"], "drag_k": [0.4, 0.5]})
    assert o.drag_k == (0.4, 0.5)
    with pytest.raises(FlightDataError, match="calibrated drag"):
        prior_options({"sources": ["observer"]})
    with pytest.raises(FlightDataError, match="unknown front-end prior"):
        prior_options({"sources": ["magic"]})
