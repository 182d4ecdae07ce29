"""``fgnav compare``: registry reasons, failure capture, files, report == JSON, reference rows."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from fgnav.datasets.errors import FgnavError
from fgnav.datasets.simulate import SimOptions, simulate
from testutil import compare_cli

from fgnav.compare import compare, truth_slam_scales
from fgnav.eval.metrics import evaluate
from fgnav.methods import METHODS, Method, available_methods, missing_reason
from fgnav.report import COLUMNS, format_cell

#: Position noise of the synthetic onboard estimate [m] (per axis).
REF_NOISE_M = 0.05


def _deliberate_failure(flight, config, progress=False):
    raise RuntimeError("deliberate failure")


@pytest.fixture(scope="module")
def flight():
    """20 s of two-turns (no images), seed 1, with a PX4-EKF2-like reference: the truth at 10 Hz
    with 5 cm of seeded position noise."""
    f = simulate("two-turns", seed=1, options=SimOptions(duration=20.0, images=False))
    gt = f.ground_truth.select(np.arange(0, len(f.ground_truth), 20))
    rng = np.random.default_rng(0)
    ref = dataclasses.replace(
        gt,
        world_t_body=gt.world_t_body + rng.normal(0.0, REF_NOISE_M, gt.world_t_body.shape),
        gyro_bias=None,
        accel_bias=None,
    )
    return dataclasses.replace(f, references={"px4_ekf2": ref})


@pytest.fixture(scope="module")
def registry():
    reg = dict(METHODS)
    reg["boom"] = Method(
        "boom", "always raises", ("imu",), (), True, "fgnav.methods", _deliberate_failure
    )
    return reg


@pytest.fixture(scope="module")
def result(flight, registry):
    return compare(
        flight, ["ekf004", "boom", "px4-ekf2", "ekf-vo002"], progress=False, registry=registry
    )


@pytest.fixture(scope="module")
def written(result, tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    paths = result.write(out)
    return out, paths, json.loads((out / "compare.json").read_text())


def test_missing_stream_reasons(flight):
    no_ref = dataclasses.replace(flight, references={})
    runnable, skipped = available_methods(no_ref)
    assert skipped["ekf-vo002"] == "needs images; the flight has none"
    assert "px4_ekf2" in skipped["px4-ekf2"] and skipped["px4-ekf2"].endswith("the flight has none")
    assert {"batch", "fixed-lag", "msf-ekf", "ekf004"} <= set(runnable)
    assert set(runnable) | set(skipped) == set(METHODS)
    no_slam = dataclasses.replace(no_ref, slam=None, attitude=None)
    _, skipped = available_methods(no_slam, ["batch", "ekf004"])
    assert skipped == {
        "batch": "needs slam; the flight has none",
        "ekf004": "needs slam; the flight has none",
    }
    assert missing_reason(["imu", "slam", "images"]) == (
        "needs imu, slam and images; the flight has none of them"
    )


def test_unknown_method_is_an_error(flight):
    with pytest.raises(FgnavError, match="unknown method 'nope'.*batch"):
        compare(flight, ["nope"], progress=False)


def test_failure_recorded_and_others_run(result, written):
    assert result.runs["boom"].estimate is None
    assert result.runs["boom"].error == "RuntimeError: deliberate failure"
    assert result.runs["ekf004"].ok and result.runs["px4-ekf2"].ok
    assert result.skipped == {"ekf-vo002": "needs images; the flight has none"}
    _, _, data = written
    assert data["methods"]["boom"]["status"] == "failed"
    assert data["methods"]["boom"]["error"] == "RuntimeError: deliberate failure"
    assert "RuntimeError" in data["methods"]["boom"]["traceback"]
    assert data["skipped"] == {"ekf-vo002": "needs images; the flight has none"}
    table = result.table()
    for name in ("ekf004", "boom", "px4-ekf2"):
        assert name in table
    assert "failed" in table.splitlines()[2]
    for col in COLUMNS:
        assert col.title in table.splitlines()[0]


def test_files_written(written):
    out, paths, data = written
    for name in ("ekf004", "px4-ekf2"):
        for f in ("estimate.tum", "states.csv", "summary.json"):
            assert (out / name / f).is_file()
        assert data["methods"][name]["output"] == f"{name}/"
    assert not (out / "boom").exists()
    report = (out / "report.md").read_text()
    for key in ("top_view", "errors", "scale", "latency"):
        assert (out / f"{key}.png").stat().st_size > 10_000
        assert f"]({key}.png)" in report
    # No method estimates drag over time here: said, not silently dropped.
    assert "drag" in data["figure_errors"] and "figure drag not drawn" in report
    assert "**ekf-vo002** (skipped): needs images; the flight has none" in report
    assert "**boom** (failed): `RuntimeError: deliberate failure`" in report


def _markdown_rows(report: str) -> dict[str, list[str]]:
    lines = report.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| method |"))
    rows = {}
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows[cells[0]] = cells
    return rows


def test_report_numbers_equal_json(written):
    out, _, data = written
    rows = _markdown_rows((out / "report.md").read_text())
    assert list(rows) == [r["method"] for r in data["table"]]
    n_numbers = 0
    for row in data["table"]:
        cells = rows[row["method"]]
        assert len(cells) == len(COLUMNS)
        for col, cell in zip(COLUMNS, cells, strict=True):
            value = row.get(col.key)
            if row["status"] == "failed" and col.fmt is not None:
                continue
            assert cell == format_cell(value, col), (row["method"], col.key)
            if col.fmt is not None and value is not None:
                decimals = int(col.fmt.split(".")[1][0])
                assert abs(float(cell) - value) <= 0.5 * 10**-decimals + 1e-12
                n_numbers += 1
    assert n_numbers >= 12


def test_json_metrics_match_evaluate(flight, result, written):
    _, _, data = written
    est = result.runs["ekf004"].estimate
    truth_scale, _ = truth_slam_scales(flight)
    m = evaluate(est, flight.ground_truth, "se3", truth_scale)
    row = next(r for r in data["table"] if r["method"] == "ekf004")
    assert row["alignment"] == "se3" and row["causal"] is True
    assert row["ate_rmse_m"] == pytest.approx(m.ate_rmse_m, rel=1e-12)
    assert row["vel_rmse_mps"] == pytest.approx(m.vel_rmse_mps, rel=1e-12)
    assert data["methods"]["ekf004"]["metrics"]["ate_rmse_m"] == row["ate_rmse_m"]
    # Seed-004 EKF on 20 s of two-turns: a few cm, scale within a few percent.
    assert 0.01 < row["ate_rmse_m"] < 0.1
    assert row["scale_final_abs_err_pct"] < 5.0
    assert row["latency_p50_ms"] > 0 and row["times_real_time"] > 1.0


def test_truth_scale_at_session_end(flight, result):
    s = flight.meta["truth"]["slam_sessions"]["0"]
    expected = s["scale"] * (1.0 + s["scale_drift_per_s"] * (s["t_end"] - s["t_start"]))
    assert s["t_end"] - s["t_start"] == pytest.approx(20.0)
    assert result.truth_scale == {0: pytest.approx(expected, rel=1e-12)}
    assert s["scale_drift_per_s"] > 0
    assert expected / s["scale"] == pytest.approx(1.0 + 20.0 * s["scale_drift_per_s"])


def test_px4_ekf2_row(result, written):
    _, _, data = written
    row = next(r for r in data["table"] if r["method"] == "px4-ekf2")
    assert row["causal"] is True and row["alignment"] == "se3"
    # 5 cm per axis: RMSE of the 3-D error about sqrt(3) * 5 cm, a little less after alignment.
    assert 0.8 * math.sqrt(3) * REF_NOISE_M < row["ate_rmse_m"] < 1.05 * math.sqrt(3) * REF_NOISE_M
    assert row["latency_p50_ms"] is None and row["times_real_time"] is None
    assert row["scale_final_abs_err_pct"] is None
    assert result.runs["px4-ekf2"].estimate.runtime_s == 0.0


def test_no_ground_truth(flight, tmp_path):
    res = compare(dataclasses.replace(flight, ground_truth=None), ["px4-ekf2"], progress=False)
    paths = res.write(tmp_path)
    row = res.rows()[0]
    assert row["ate_rmse_m"] is None and row["alignment"] is None
    data = json.loads(paths["json"].read_text())
    assert data["truth"]["ground_truth"] is False
    assert data["truth"]["slam_scale"] == {"0": pytest.approx(res.truth_scale[0])}
    assert "ground truth: none" in paths["report"].read_text()


def test_cli_compare(flight, tmp_path, capsys):
    from fgnav.datasets.native import write_flight

    folder = write_flight(dataclasses.replace(flight, references={}), tmp_path / "flight")
    out = tmp_path / "out"
    rc = compare_cli(folder, out, "ekf004,ekf-vo002")
    printed = capsys.readouterr().out
    assert rc == 0
    assert printed.splitlines()[0].startswith("method")
    assert "ekf004" in printed.splitlines()[1]
    assert "skipped ekf-vo002: needs images; the flight has none" in printed
    assert f"report: {out / 'report.md'}" in printed
    data = json.loads((out / "compare.json").read_text())
    assert [r["method"] for r in data["table"]] == ["ekf004"]
    rc = compare_cli(folder, out, "nope")
    assert rc == 1
    assert "unknown method 'nope'" in capsys.readouterr().err
    # Named before the flight is read: a missing flight is not what the error says.
    rc = compare_cli(tmp_path / "missing", out, "batch,nope")
    assert rc == 1
    err = capsys.readouterr().err
    assert "unknown method 'nope'" in err and "ref:<reference" in err
    # No method at all is an error too (it ran nothing and wrote an empty report, exit 0).
    for empty in ("", " , "):
        rc = compare_cli(tmp_path / "missing", out, empty)
        assert rc == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "no method named" in err[0]


def test_piecewise_constant_series_held_to_end(flight):
    from fgnav.compare import held_to_end
    from fgnav.estimate import Estimate, TimeSeries

    traj = flight.ground_truth
    est = Estimate(
        "x",
        traj,
        series={"drag_k": TimeSeries(np.array([0.0]), np.array([[0.38, 0.41]]), np.ones((1, 2)))},
    )
    ts = held_to_end(est, "drag_k").series["drag_k"]
    np.testing.assert_array_equal(ts.t, [0.0, traj.t[-1]])
    np.testing.assert_array_equal(ts.value, [[0.38, 0.41], [0.38, 0.41]])
    assert ts.sigma.shape == (2, 2)
    assert held_to_end(est, "slam_scale") is est


def test_seed000_defaults_are_stated(flight):
    from fgnav.methods import DRAG_FROM_SIM_TRUTH

    res = compare(flight, ["ii-observer"], progress=False)
    info = res.runs["ii-observer"].estimate.info
    assert info["compare_defaults"] == {
        "align_slam_axes": True,
        "drag_k": (0.38, 0.42),
        "drag_k_source": DRAG_FROM_SIM_TRUTH,
    }
    res = compare(
        flight, ["ii-observer"], config={"ii-observer": {"drag_k": [0.3, 0.3]}}, progress=False
    )
    run = res.runs["ii-observer"]
    assert run.estimate.info["compare_defaults"] == {"align_slam_axes": True}
    assert list(run.estimate.drag_k) == [0.3, 0.3]
    # A config typo fails that method, naming the valid options; nothing else is affected.
    res = compare(flight, ["ii-observer"], config={"ii-observer": {"dragk": 1}}, progress=False)
    assert "unknown option(s) ['dragk'] for Seed000Options" in res.failed["ii-observer"]


def test_missing_implementation_is_a_skip_reason(flight, registry):
    reg = dict(registry)
    reg["later"] = Method(
        "later", "not written yet", ("imu",), (), True, "fgnav.baselines.nope", _deliberate_failure
    )
    runnable, skipped = available_methods(flight, ["later", "px4-ekf2"], reg)
    assert runnable == ["px4-ekf2"]
    assert skipped == {
        "later": "implementation fgnav.baselines.nope is not available in this version"
    }


def test_smoothers_run_without_slam_when_camera_and_range_exist():
    """Seed 002's sensor set (downward camera + rangefinder, no SLAM) feeds the smoothers; with
    neither SLAM nor images the reason names SLAM."""
    import dataclasses

    from fgnav.datasets.simulate import SimOptions, simulate

    from fgnav.methods import available_methods

    fl = simulate("two-turns", seed=1, options=SimOptions(duration=2.0))
    no_slam = dataclasses.replace(fl, slam=None)
    runnable, skipped = available_methods(no_slam)
    assert {"batch", "fixed-lag", "ekf-vo002"} <= set(runnable)
    assert skipped["msf-ekf"] == "needs slam; the flight has none"
    runnable, skipped = available_methods(dataclasses.replace(no_slam, images=None))
    assert "batch" not in runnable
    assert skipped["batch"] == "needs slam; the flight has none"


def test_fixed_lag_and_its_lagged_output_come_from_one_replay(flight, monkeypatch):
    """``fixed-lag`` and ``fixed-lag@lag`` are the two outputs of one push-engine run: compare
    replays the flight once for both (it ran the smoother twice), with the figures of separate
    runs."""
    import fgnav.solvers.online as online
    from fgnav.solvers.fixed_lag import FixedLagOptions

    calls = []
    real = online.feed_all
    monkeypatch.setattr(online, "feed_all", lambda *a, **k: calls.append(1) or real(*a, **k))
    res = compare(flight, ["fixed-lag", "fixed-lag@lag"], progress=False)
    assert len(calls) == 1
    alone = online.replay_online(flight, FixedLagOptions())
    lagged = online.replay_online(flight, FixedLagOptions(), lagged=True)
    for name, ref in (("fixed-lag", alone), ("fixed-lag@lag", lagged)):
        got = res.runs[name].estimate.trajectory
        np.testing.assert_array_equal(got.t, ref.trajectory.t)
        np.testing.assert_allclose(got.world_t_body, ref.trajectory.world_t_body, atol=1e-12)
    # The entry is dropped once both outputs were taken: a new call replays again, and so does
    # a second request for the output already handed out.
    compare(flight, ["fixed-lag"], progress=False)
    assert len(calls) == 4
    compare(flight, ["fixed-lag"], progress=False)
    assert len(calls) == 5


def test_compare_on_a_vertical_flight():
    """A purely vertical simulated flight: every SE(3) alignment falls back to a translation
    (the rotation about the line is undetermined); the comparison used to abort with
    ``FlightDataError: unknown mode`` from the common-span ATE (review 2026-12-07)."""
    from fgnav.datasets.simulate.options import SimOptions
    from fgnav.datasets.simulate.simulator import simulate

    from fgnav.compare import compare

    f = simulate("vertical", 0, SimOptions(duration=10.0, images=False))
    res = compare(f, ["batch", "ekf004"], progress=False)  # (the span: a causal method's)
    run = res.runs["batch"]
    assert run.metrics.alignment.startswith("translation")
    assert run.ate_common_m == pytest.approx(run.metrics.ate_rmse_m, rel=0.05)
    assert run.metrics.ate_rmse_m < 0.02
    # Too little rotation to tell a SLAM clock offset: none named (it named -0.40 s here).
    assert "slam-clock-offset" not in run.estimate.info["health"]["detectors"]


def test_causal_filters_get_the_slam_check_as_it_arrives_the_batch_the_whole_flights(flight):
    """The SLAM-vs-gyro check reaches each method as it could know it: a causal filter gets each
    pose as decided when it arrived (inverted SLAM rotations: as stated before the decision),
    a non-causal method the whole flight's decision, the push engine the raw file."""
    from fgnav.datasets.slam_gyro import (
        CAUSAL_META_KEY,
        META_KEY,
        apply_slam_check_causal,
        invert_slam_rotations,
    )

    seen = {}

    def record(name):
        def entry(f, config, progress=False):
            seen[name] = f
            raise RuntimeError("recorded")

        return entry

    reg = {
        "causal-filter": Method("causal-filter", "", ("imu", "slam"), (), True, "fgnav.methods",
                                record("causal-filter")),
        "whole-flight": Method("whole-flight", "", ("imu", "slam"), (), False, "fgnav.methods",
                               record("whole-flight")),
    }  # fmt: skip
    bad = dataclasses.replace(flight, slam=invert_slam_rotations(flight.slam))
    compare(bad, list(reg), progress=False, registry=reg)
    causal, whole = seen["causal-filter"], seen["whole-flight"]
    assert CAUSAL_META_KEY in causal.meta and META_KEY not in causal.meta
    assert META_KEY in whole.meta and CAUSAL_META_KEY not in whole.meta
    np.testing.assert_array_equal(
        causal.slam.slam_q_cam_wxyz, apply_slam_check_causal(bad).slam.slam_q_cam_wxyz
    )
    # the first poses as stated (inverted), all of the whole flight's undone
    q0 = flight.slam.slam_q_cam_wxyz[0]
    assert abs(causal.slam.slam_q_cam_wxyz[0] @ q0) < 1.0 - 1e-9
    assert abs(whole.slam.slam_q_cam_wxyz[0] @ q0) == pytest.approx(1.0, abs=1e-12)
