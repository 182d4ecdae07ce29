"""``fgnav compare`` review findings (2026-12-08): exit code when nothing ran, the SLAM scale of a
flight without SLAM, repeated ``--methods``, reference rows scored on positions only, and the
implausible-estimate flags."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from fgnav.datasets.simulate import SimOptions, simulate
from testutil import compare_cli

from fgnav.compare import compare, truth_slam_scales
from fgnav.methods import METHODS, reference_estimate


@pytest.fixture(scope="module")
def flight():
    """12 s of two-turns without images, seed 3."""
    return simulate("two-turns", seed=3, options=SimOptions(duration=12.0, images=False))


@pytest.fixture(scope="module")
def imu_only(flight):
    """The same flight with the IMU (and truth) only: no SLAM, attitude, yaw, range, flow."""
    return dataclasses.replace(flight, slam=None, attitude=None, yaw=None, range=None, flow=None)


def test_no_slam_no_true_slam_scale(imu_only, tmp_path):
    """A flight without SLAM has no true SLAM scale, though the simulator's metadata lists the
    sessions it drew (report.md stated "true SLAM scale ... session 0: 0.246991")."""
    assert imu_only.meta["truth"]["slam_sessions"]
    assert truth_slam_scales(imu_only) == (None, "the flight has no SLAM stream")
    res = compare(imu_only, ["msf-ekf"], progress=False)
    paths = res.write(tmp_path, figures=False)
    data = json.loads(paths["json"].read_text())
    assert data["truth"]["slam_scale"] is None
    report = paths["report"].read_text()
    assert "true SLAM scale: not available (the flight has no SLAM stream)" in report
    assert "session 0:" not in report


def _counting(calls: list[str], name: str = "ekf004"):
    """A method entry that records its call and replays the truth (fast)."""

    def entry(flight, config, progress=False):
        calls.append("run")
        est = reference_estimate(
            dataclasses.replace(flight, references={"truth": flight.ground_truth}), "truth", "x"
        )
        return dataclasses.replace(est, method=name)

    return entry


def test_repeated_methods_run_once(cli_folder, tmp_path, capsys, monkeypatch):
    """``--methods ekf004,ekf004,ekf004`` ran the method three times and kept one row: now it
    runs once, with a one-line note (``fgnav fleet`` also runs a repeated name once)."""
    calls: list[str] = []
    monkeypatch.setitem(
        METHODS, "ekf004", dataclasses.replace(METHODS["ekf004"], entry=_counting(calls))
    )
    rc = compare_cli(cli_folder, tmp_path / "out", "ekf004,ekf004, ekf004")
    captured = capsys.readouterr()
    assert rc == 0 and calls == ["run"]
    assert captured.err.strip() == (
        "fgnav compare: note: --methods names ekf004 3 times; it runs once"
    )
    data = json.loads((tmp_path / "out" / "compare.json").read_text())
    assert [r["method"] for r in data["table"]] == ["ekf004"]
    # The API does the same.
    res = compare(
        simulate("two-turns", 4, SimOptions(duration=4.0, images=False)),
        ["ekf004"] * 2,
        progress=False,
    )
    assert list(res.runs) == ["ekf004"] and calls == ["run", "run"]


def _raises(flight, config, progress=False):
    raise RuntimeError("deliberate failure")


def test_exit_1_when_no_method_produced_a_row(cli_folder, tmp_path, capsys, monkeypatch):
    """Every method failed or was skipped: the table and files are written, then one line on
    stderr and exit 1 (it was exit 0, as ``fgnav fleet`` is not); one row is enough for 0."""
    monkeypatch.setitem(METHODS, "msf-ekf", dataclasses.replace(METHODS["msf-ekf"], entry=_raises))
    monkeypatch.setitem(METHODS, "ukf003", dataclasses.replace(METHODS["ukf003"], entry=_raises))
    rc = compare_cli(cli_folder, tmp_path / "a", "msf-ekf,ukf003")
    captured = capsys.readouterr()
    assert rc == 1
    assert "FAILED msf-ekf: RuntimeError: deliberate failure" in captured.out
    assert captured.err.strip() == (
        "fgnav compare: no method produced a result (2 failed, 0 skipped; see the lines above)"
    )
    assert (tmp_path / "a" / "report.md").is_file()
    # Skipped only (the flight has no flow): exit 1 too.
    rc = compare_cli(cli_folder, tmp_path / "b", "ekf-flow002,cf-ekf")
    captured = capsys.readouterr()
    assert rc == 1
    assert "skipped cf-ekf: needs flow; the flight has none" in captured.out
    assert captured.err.strip().splitlines() == [
        "fgnav compare: no method produced a result (0 failed, 2 skipped; see the lines above)"
    ]
    # One method with a row: exit 0, the failure still printed.
    calls: list[str] = []
    monkeypatch.setitem(
        METHODS, "ekf004", dataclasses.replace(METHODS["ekf004"], entry=_counting(calls))
    )
    rc = compare_cli(cli_folder, tmp_path / "c", "msf-ekf,ekf004")
    captured = capsys.readouterr()
    assert rc == 0 and calls == ["run"] and "no method produced" not in captured.err
    assert "FAILED msf-ekf: RuntimeError: deliberate failure" in captured.out


def _other_body_frame(flight, noise_m: float = 0.03):
    """The truth at 20 Hz with seeded position noise and the orientations of another body frame
    (90 deg about body y, as an x-up IMU frame against a z-up body)."""
    from fgnav.datasets.geometry import matrix_to_quat_wxyz

    gt = flight.ground_truth.select(np.arange(0, len(flight.ground_truth), 10))
    rng = np.random.default_rng(1)
    R_y = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    R = np.einsum("nij,jk->nik", gt.world_R_body(), R_y)
    return dataclasses.replace(
        gt,
        world_t_body=gt.world_t_body + rng.normal(0.0, noise_m, gt.world_t_body.shape),
        world_q_body_wxyz=matrix_to_quat_wxyz(R),
        world_v_body=None,
        gyro_bias=None,
        accel_bias=None,
    )


def test_reference_rows_score_positions_only(flight, tmp_path):
    """A ``ref:<name>`` row (another system's trajectory: EuRoC V1_02's VINS-Mono and SVO 2,
    whose orientations are of another body frame) is scored on positions only: RPE, yaw RMSE
    and NEES blank (``ref:vins_mono`` read RPE 31.7 % and yaw RMSE 44.3 deg); its ATE is the
    same as a full scoring's."""
    from fgnav.compare import score_estimate
    from fgnav.report import COLUMNS

    ref = _other_body_frame(flight)
    fl = dataclasses.replace(flight, references={"vio": ref, "px4_ekf2": ref})
    res = compare(fl, ["px4-ekf2", "ref:vio"], progress=False)
    paths = res.write(tmp_path, figures=False)
    data = json.loads(paths["json"].read_text())
    rows = {r["method"]: r for r in data["table"]}
    full, only = rows["px4-ekf2"], rows["ref:vio"]
    assert only["positions_only"] is True and full["positions_only"] is False
    assert only["ate_rmse_m"] == pytest.approx(full["ate_rmse_m"], rel=1e-12)
    assert only["ate_4dof_m"] == pytest.approx(full["ate_4dof_m"], rel=1e-12)
    assert 0.03 < only["ate_rmse_m"] < 0.06
    # The px4-ekf2 row (the onboard estimate of the flight's own body) keeps its orientations:
    # 90 deg of body rotation is 90 deg of yaw error there.
    assert full["yaw_rmse_deg"] > 45.0
    for key in ("rpe_pct", "yaw_rmse_deg", "nees_pos"):
        assert only[key] is None, key
    metrics = data["methods"]["ref:vio"]["metrics"]
    assert metrics["positions_only"] is True and metrics["rpe_n_pairs"] == 0
    assert metrics["nees_pose"] is None and metrics["rpe_rmse_m"] is None
    # RPE over 2 m segments (the flight is shorter than 10 m): orientation-based, left out.
    est = res.runs["ref:vio"].estimate
    m_full = score_estimate(fl, est, delta_m=2.0)
    m_pos = score_estimate(fl, est, delta_m=2.0, positions_only=True)
    assert m_full.rpe_n_pairs > 10 and m_full.rpe_pct > 20.0
    assert m_pos.rpe_n_pairs == 0 and np.isnan(m_pos.rpe_pct) and np.isnan(m_pos.yaw_rmse_deg)
    assert m_pos.ate_rmse_m == m_full.ate_rmse_m and m_pos.ate_max_m == m_full.ate_max_m
    # report.md: '-' in those cells, and the rows named as scored on positions only.
    report = paths["report"].read_text()
    line = next(x for x in report.splitlines() if x.startswith("| ref:vio |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    titles = [c.title for c in COLUMNS]
    for title in ("RPE [%]", "yaw RMSE [deg]", "NEES"):
        assert cells[titles.index(title)] == "-"
    assert cells[titles.index("ATE [m]")] == f"{only['ate_rmse_m']:.3f}"
    assert "ref:vio: another system's trajectory, scored on its positions only" in report


def _diverging(factor: float, t_from: float = 4.0):
    """A method entry replaying the truth whose positions grow by ``factor`` per second after
    ``t_from`` seconds (a diverged filter)."""

    def entry(flight, config, progress=False):
        est = reference_estimate(
            dataclasses.replace(flight, references={"truth": flight.ground_truth}), "truth", "x"
        )
        traj = est.trajectory
        dt = np.clip(traj.t - traj.t[0] - t_from, 0.0, None)
        with np.errstate(over="ignore"):
            grow = np.minimum(factor**dt, 1e300)
        traj = dataclasses.replace(
            traj, world_t_body=traj.world_t_body * grow[:, None], world_v_body=None
        )
        return dataclasses.replace(est, trajectory=traj, method="ekf004", causal=True)

    return entry


def test_plausibility_flags(flight):
    """The flags: speed (no truth needed), ATE above max(1 m, 10 % of the path), non-finite."""
    from fgnav.compare import FLAG_MAX_SPEED_MPS, max_speed, plausibility_flags
    from fgnav.estimate import Estimate

    truth = flight.ground_truth
    ok = Estimate("ok", truth)
    assert plausibility_flags(ok, None) == []
    v, _ = max_speed(truth)
    assert 0.5 < v < 5.0  # the simulator's two-turns
    # A position jump of 20 cm between two outputs 5 ms apart is no speed (1 s spans) ...
    p = truth.world_t_body.copy()
    p[len(p) // 2 :] += 0.2
    assert (
        plausibility_flags(Estimate("jump", dataclasses.replace(truth, world_t_body=p)), None) == []
    )
    # ... 80 m is.
    p[len(p) // 2 :] += 80.0
    flags = plausibility_flags(Estimate("far", dataclasses.replace(truth, world_t_body=p)), None)
    assert [f["code"] for f in flags] == ["speed"]
    assert f"below {FLAG_MAX_SPEED_MPS:g} m/s" in flags[0]["reason"]


def test_implausible_rows_flagged(flight, cli_folder, tmp_path, capsys, monkeypatch):
    """Rows with ATE of 61 m ... 1.95e28 m printed as normal rows, exit 0, no warning: now a
    WARNING line per such row, the row's ``flag``, compare.json's ``flags`` and report.md's
    section say why; the numbers stay as computed and the exit code 0."""
    reg = dict(METHODS)
    reg["ekf004"] = dataclasses.replace(METHODS["ekf004"], entry=_diverging(10.0))
    reg["msf-ekf"] = dataclasses.replace(METHODS["msf-ekf"], entry=_diverging(1e300, 6.0))
    reg["ukf003"] = dataclasses.replace(METHODS["ukf003"], entry=_counting([], "ukf003"))
    res = compare(flight, ["ekf004", "msf-ekf", "ukf003"], progress=False, registry=reg)
    paths = res.write(tmp_path / "api", figures=False)
    data = json.loads(paths["json"].read_text())
    rows = {r["method"]: r for r in data["table"]}
    assert rows["ekf004"]["flag"] == "speed,ate" and rows["ekf004"]["ate_rmse_m"] > 1e3
    assert rows["msf-ekf"]["flag"] == "non-finite,speed" and rows["msf-ekf"]["ate_rmse_m"] is None
    assert rows["ukf003"]["flag"] is None and rows["ukf003"]["ate_rmse_m"] < 1e-9
    assert set(data["flags"]) == {"ekf004", "msf-ekf"}
    assert data["flags"]["ekf004"][1].startswith("ATE ")
    assert "m > 1 m (the larger of 1 m and 10 % of the" in data["flags"]["ekf004"][1]
    assert data["methods"]["ukf003"]["flags"] == []
    assert data["flag_bounds"]["max_speed_mps"] == 50.0
    m = res.runs["ekf004"].metrics  # the number is the scoring's, unchanged
    assert rows["ekf004"]["ate_rmse_m"] == pytest.approx(m.ate_rmse_m, rel=1e-15)
    report = paths["report"].read_text()
    assert "## Implausible estimates" in report
    assert f"- **ekf004**: {'; '.join(data['flags']['ekf004'])}" in report
    line = next(x for x in report.splitlines() if x.startswith("| ekf004 |"))
    assert line.rstrip(" |").endswith("speed,ate")
    # The command: WARNING lines, exit 0 (rows exist).
    for name in ("ekf004", "msf-ekf"):
        monkeypatch.setitem(METHODS, name, reg[name])
    rc = compare_cli(cli_folder, tmp_path / "cli", "ekf004,msf-ekf")
    out = capsys.readouterr().out
    assert rc == 0
    warn = [x for x in out.splitlines() if x.startswith("WARNING")]
    assert len(warn) == 2
    assert warn[0].startswith("WARNING ekf004: implausible estimate: speed ")
    assert warn[1].startswith("WARNING msf-ekf: implausible estimate: non-finite ATE (inf)")
