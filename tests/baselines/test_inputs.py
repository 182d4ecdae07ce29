"""What the filter baselines receive and do not use (fgnav.baselines._inputs): corrupted IMU
samples dropped and counted, IMU gaps, persistent gating recovered, flow gated, aiding streams
that end said, one ``info["unused"]`` convention read by the "not used" line, option checks."""

from __future__ import annotations

import dataclasses
import logging
import re

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import ImuSample
from fgnav.datasets.simulate import SimOptions, simulate
from testutil import CRAZYFLIE_LIKE

from fgnav.baselines._inputs import IMU_GAP_S, Inputs, imu_problem
from fgnav.baselines.ekf004 import Ekf004Counts
from fgnav.config import OptionValueError
from fgnav.coverage import unused_counts
from fgnav.eval.metrics import evaluate
from fgnav.methods import METHODS, check_method_config

#: The baselines fed the two-turns flight (IMU, attitude, yaw, range, SLAM).
SLAM_METHODS = ("msf-ekf", "ukf003", "ekf004", "ii-observer")
#: The baselines fed the flow-deck flight (IMU, range, flow).
FLOW_METHODS = ("cf-ekf", "ekf-flow002")
KEY = re.compile(r"^[a-z+]+:[a-z0-9-]+$")


@pytest.fixture(scope="module")
def two_turns():
    return simulate("two-turns", 0, SimOptions(images=False, duration=20.0))


@pytest.fixture(scope="module")
def flowdeck():
    return simulate("flowdeck", seed=0, options=SimOptions(duration=15.0, **CRAZYFLIE_LIKE))


def _run(method, flight):
    return METHODS[method].run(flight, {})


def _ate(est, flight) -> float:
    return evaluate(est, flight.ground_truth).ate_rmse_m


def _with_accel(flight, k: int, value: float):
    a = flight.imu.body_accel.copy()
    a[k, 0] = value
    return dataclasses.replace(flight, imu=dataclasses.replace(flight.imu, body_accel=a))


def test_imu_problem_uses_the_push_smoothers_bound():
    from fgnav.solvers import online
    from fgnav.solvers.fixed_lag import FixedLagOptions

    assert online.IMU_MAX_ACCEL == 50.0 * 9.81 and online.IMU_MAX_RATE == 100.0
    assert IMU_GAP_S == FixedLagOptions().max_imu_gap_s
    z = np.zeros(3)
    assert imu_problem(ImuSample(0.0, 0.0, z, np.array([0.0, 0.0, 9.8]))) is None
    assert imu_problem(ImuSample(0.0, 0.0, z, np.array([600.0, 0, 0]))) == "implausible"
    assert imu_problem(ImuSample(0.0, 0.0, np.array([0, 0, 101.0]), z)) == "implausible"
    assert imu_problem(ImuSample(0.0, 0.0, z, np.array([np.nan, 0, 0]))) == "non-finite"
    assert imu_problem(ImuSample(0.0, 0.0, z, np.array([1e300, 1e300, 0]))) == "non-finite"
    assert imu_problem(ImuSample(0.0, 0.0, z, np.zeros(2))) == "bad-shape"
    inputs = Inputs("m")
    for t in (0.0, 0.01, 0.02, 1.02, 1.03):
        inputs.imu_gap(ImuSample(t, t, z, z))
    assert inputs.gaps == 1 and inputs.gap_max_s == pytest.approx(1.0)


@pytest.mark.parametrize("method", SLAM_METHODS + FLOW_METHODS)
def test_a_corrupted_imu_sample_is_dropped_and_counted(method, two_turns, flowdeck):
    """One accelerometer sample of 1e30 m/s^2 (v_imu1e30: msf-ekf ATE 1.95e28 m) is not used,
    counted as ``imu:implausible``; the estimate is the clean flight's to within 1 cm."""
    flight = flowdeck if method in FLOW_METHODS else two_turns
    k = int(np.searchsorted(flight.imu.t, flight.imu.t[0] + 8.0))
    clean, bad = _run(method, flight), _run(method, _with_accel(flight, k, 1e30))
    assert bad.info["unused"].get("imu:implausible") == 1
    assert "imu:implausible" not in clean.info["unused"]
    assert _ate(bad, flight) == pytest.approx(_ate(clean, flight), rel=0.01, abs=0.01)
    for est in (clean, bad):
        assert all(
            KEY.match(k) and isinstance(v, int) and v > 0 for k, v in est.info["unused"].items()
        )
        assert unused_counts(est.info) == est.info["unused"]


@pytest.mark.parametrize("method", ["msf-ekf", "ukf003"])
def test_persistent_gating_is_recovered(method, two_turns, caplog):
    """One 150 m/s^2 sample (a plausible value: not dropped) made msf-ekf gate every later SLAM
    pose (ATE 2.19 m, 237 gated). Every pose gated for ``slam_reset_s``: the state restarts
    from the SLAM, counted and said. Measured: msf-ekf 0.64 m, ukf003 0.56 m (nominal 0.04)."""
    k = int(np.searchsorted(two_turns.imu.t, two_turns.imu.t[0] + 7.5))
    with caplog.at_level(logging.WARNING):
        est = _run(method, _with_accel(two_turns, k, 150.0))
    assert est.info["counts"]["gating_resets"] >= 1
    assert any(method in r.getMessage() and "gated" in r.getMessage() for r in caplog.records)
    assert _ate(est, two_turns) < 1.0
    assert est.info["unused"]["slam:gated"] < 60


#: After the spike of test_persistent_gating_is_recovered: ATE and final scale. Measured
#: 2026-12-08: msf-ekf 0.296 m, scale 0.7285 (clean 0.7267); ukf003 0.255 m, 0.7333 (0.7235).
#: Before, the reset kept what the poses fused between the fault and the gate's closing had
#: done: msf-ekf 0.643 m, scale 0.538 (0.80 +- 0.08 -> 0.44 +- 0.01 in 0.5 s); ukf003 0.561 m,
#: 0.602, and its position drift for good.
SPIKE_ATE_CAP_M = 0.35


@pytest.mark.parametrize("method", ["msf-ekf", "ukf003"])
def test_a_gating_reset_goes_back_before_the_fault(method, two_turns):
    k = int(np.searchsorted(two_turns.imu.t, two_turns.imu.t[0] + 7.5))
    clean = _run(method, two_turns)
    est = _run(method, _with_accel(two_turns, k, 150.0))
    counts = est.info["counts"]
    assert counts["gating_resets"] == 1 and clean.info["counts"]["gating_resets"] == 0
    key = "gating_alignment_restored" if method == "msf-ekf" else "gating_scale_restored"
    assert counts["extra"][key] == 1
    assert _ate(est, two_turns) < SPIKE_ATE_CAP_M
    assert est.slam_scale[0] == pytest.approx(clean.slam_scale[0], rel=0.02)


@pytest.mark.parametrize("method", ["msf-ekf", "ukf003"])
def test_an_imu_gap_is_counted_and_recovered(method, two_turns):
    """3 s without IMU (v_imugap: msf-ekf 4.2 m). Measured: msf-ekf 1.20 m, ukf003 0.28 m."""
    imu = two_turns.imu
    t0 = imu.t[0]
    keep = ~((imu.t >= t0 + 8.0) & (imu.t < t0 + 11.0))
    est = _run(method, dataclasses.replace(two_turns, imu=imu.select(keep)))
    assert est.info["imu_gaps"]["n"] == 1
    assert est.info["imu_gaps"]["longest_s"] == pytest.approx(3.0, abs=0.01)
    assert _ate(est, two_turns) < 2.0


def _with_flow(flight, k: int, flow=None, dt=None):
    f = flight.flow
    fl, d = f.flow.copy(), f.dt.copy()
    if flow is not None:
        fl[k] = flow
    if dt is not None:
        d[k] = dt
    return dataclasses.replace(flight, flow=dataclasses.replace(f, flow=fl, dt=d))


@pytest.mark.parametrize(
    "change,reason",
    [
        ({"flow": (300.0, 0.0)}, "flow:implausible-rate"),
        ({"dt": 1e-6}, "flow:implausible-rate"),
        ({"flow": (np.nan, 0.0)}, "flow:non-finite"),
        ({"dt": 0.0}, "flow:bad-interval"),
    ],
)
def test_flow_dead_reckoning_gates_a_bad_reading(flowdeck, change, reason):
    """v_flowspike (one 300 px reading: 1.62 m), v_flowdtbig (one dt = 1e-6 s: 80.8 m): the
    reading is not used, counted by reason; the estimate stays the clean flight's."""
    k = len(flowdeck.flow) // 2
    clean = _run("ekf-flow002", flowdeck)
    est = _run("ekf-flow002", _with_flow(flowdeck, k, **change))
    assert est.info["unused"][reason] == 1
    assert _ate(est, flowdeck) == pytest.approx(_ate(clean, flowdeck), abs=0.005)


def test_an_aiding_stream_that_ends_is_said_once(flowdeck, caplog):
    """v_flow1 (flow stops at 1.1 s): cf-ekf dead-reckoned 14 s without a word."""
    f = flowdeck.flow
    short = dataclasses.replace(flowdeck, flow=f.select(f.t < f.t[0] + 3.0))
    with caplog.at_level(logging.WARNING):
        est = _run("cf-ekf", short)
    said = [r.getMessage() for r in caplog.records if "stream ended" in r.getMessage()]
    assert len(said) == 1 and "cf-ekf" in said[0] and "flow" in said[0]
    assert est.info["streams_ended"]["flow"] > 10.0
    assert _run("cf-ekf", flowdeck).info["streams_ended"] == {}


def test_ii_observer_without_a_usable_range_reading_names_it(two_turns):
    """v_range0 (every reading out of limits): was "estimate[ii-observer].trajectory.t: the
    stream is empty"."""
    r = two_turns.range
    bad = dataclasses.replace(two_turns, range=dataclasses.replace(r, range=r.range + 100.0))
    with pytest.raises(FlightDataError, match=r"range.*range:out-of-limits \d+"):
        _run("ii-observer", bad)


def test_ekf004_counts_as_stream_reason():
    c = Ekf004Counts(
        gated={"slam": 3, "vertical_speed": 2},
        skipped={"range": 4, "imu_out_of_order": 1, "slam_too_late": 1, "scale_pair": 7},
    )
    assert c.unused() == {
        "slam:gated": 3,
        "range:vertical-speed-gated": 2,
        "range:rejected": 4,
        "imu:out-of-order": 1,
        "slam:too-late": 1,
        "slam:scale-pair": 7,
    }


def test_unused_counts_reads_the_unused_table():
    info = {"counts": {"slam_rejected_gate": 3}, "unused": {"slam:gated": 3, "range:tilted": 1}}
    assert unused_counts(info) == {"slam:gated": 3, "range:tilted": 1}
    info = {"counts": Ekf004Counts(gated={"slam": 2}), "unused": {"slam:gated": 2}}
    assert unused_counts(info) == {"slam:gated": 2}


@pytest.mark.parametrize(
    "section,table,match",
    [
        # (the config's bounds refuse these before the options' own check)
        (
            "msf-ekf",
            {"initial_scale": -1.0},
            r"\[msf-ekf\]: option initial_scale = -1\.0: expected",
        ),
        ("ukf003", {"initial_scale": 0.0}, r"\[ukf003\]: option initial_scale = 0\.0: expected"),
        ("ekf-flow002", {"height_rate_tau_s": 0.0}, r"height_rate_tau_s=0\.0: expected > 0"),
    ],
)
def test_bad_baseline_options_are_one_line_errors(section, table, match):
    """Were a ZeroDivisionError, a LinAlgError, and a 141 % scale error without a word."""
    with pytest.raises(OptionValueError, match=match) as e:
        check_method_config({section: table})
    assert "\n" not in str(e.value)


def test_filters_check_their_options_from_the_python_api():
    """initial_scale 0 failed deep in the run ('non-finite value at sample 21'), -1 ran to a
    1.34 m ATE (review: only the config path checked it)."""
    from fgnav.baselines.msf_ekf import MsfEkf, MsfOptions
    from fgnav.baselines.ukf003 import Ukf003, Ukf003Options

    for make, opts in ((MsfEkf, MsfOptions), (Ukf003, Ukf003Options)):
        for bad in (0.0, -1.0):
            with pytest.raises(ValueError, match=r"initial_scale=.*expected > 0"):
                make(opts(initial_scale=bad))
        make(opts(initial_scale=0.5))  # a valid one is taken
