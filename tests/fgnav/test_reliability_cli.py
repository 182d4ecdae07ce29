"""Bad options and bad flights through the CLI (issue 18 Build 3): one line, exit 1, no
traceback; nothing lost without saying so."""

from __future__ import annotations

import pytest
from fgnav.datasets.simulate.options import SimOptions
from fgnav.datasets.simulate.simulator import simulate_to_folder

from fgnav.cli import main


def _one_line_error(capsys, argv: list[str]) -> str:
    assert main(argv) == 1
    cap = capsys.readouterr()
    err = cap.err.strip()
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in err + cap.out
    return err


def _config_error(capsys, tmp_path, command: str, flight, table: str) -> str:
    """``fgnav COMMAND FLIGHT --out TMP/o --config TMP/bad.toml`` with ``table`` as the config
    file: exit 1 with one line (:func:`_one_line_error`) that names the file; that line."""
    cfg = tmp_path / "bad.toml"
    cfg.write_text(table)
    argv = [command, str(flight), "--out", str(tmp_path / "o"), "--config", str(cfg)]
    err = _one_line_error(capsys, argv)
    assert str(cfg) in err, err
    return err


@pytest.mark.parametrize(
    ("flags", "needle"),
    [
        (["--lag", "0"], "option lag_s = 0.0: expected > 0"),
        (["--lag", "-1"], "option lag_s = -1.0: expected > 0"),
        (["--lag", "nan"], "option lag_s = nan: expected a finite number"),
        (["--keyframe-hz", "0"], "option keyframe_hz = 0.0: expected > 0"),
        # 1e9 ran without end (found by fuzzing the command line).
        (["--keyframe-hz", "1e9"], "keyframe_hz=1000000000.0: expected > 0 and <= 1000"),
    ],
)
def test_bad_flag_values(cli_folder, tmp_path, capsys, flags, needle):
    err = _one_line_error(capsys, ["online", str(cli_folder), "--out", str(tmp_path / "o"), *flags])
    assert "command line" in err and needle in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("command", "table", "needle"),
    [
        ("batch", "[graph]\nslam_sigma_m = -0.01\n", "[graph]: option slam_sigma_m = -0.01"),
        ("online", "[graph]\nrange_sigma = 0.0\n", "[graph]: option range_sigma = 0.0: expected"),
        ("online", "[graph]\nyaw_sigma = inf\n", "option yaw_sigma = inf: expected a finite"),
        ("online", "[online]\nlag_s = 0\n", "[online]: option lag_s = 0: expected > 0"),
        ("batch", "[graph]\nslam_scale_rw = 0.0\n", "option slam_scale_rw = 0.0: expected > 0"),
        ("batch", "[graph]\nslam_segment_s = -2.0\n", "option slam_segment_s = -2.0"),
        ("batch", "[lm]\nmax_iterations = 0\n", "[lm]: option max_iterations = 0"),
        ("online", "[online]\nslam_init_window_s = -1.0\n", "expected >= 0"),
        # Types, from the options' declarations (a string sigma crashed at the start; a number
        # for a switch was taken as true).
        (
            "online",
            '[graph]\nprior_position_sigma = "x"\n',
            "option prior_position_sigma = 'x': expected a number, found a string",
        ),
        ("batch", "[graph]\nuse_drag = -1\n", "option use_drag = -1: expected true or false"),
        ("online", "[online]\nrelinearize_skip = 2.5\n", "expected an integer, found a decimal"),
        ("compare", "[ukf003]\nuse_yaw = 'yes'\n", "use_yaw = 'yes': expected true or false"),
        ("compare", "[ii-observer]\ndrag_k = [0.4]\n", "drag_k = [0.4]: expected a list of 2"),
        # An options class's own validate()/check() runs before any method (ekf004 failed at
        # its start, after the other methods had run).
        ("compare", "[ekf004]\nposition_noise = -1.0\n", "position_noise = -1.0: expected in [0"),
        ("compare", "[ekf004]\nposition_noise = 0\n", "position_noise=0: must be > 0"),
        # Unknown tables and options.
        ("online", "[online]\nlag = 2.0\n", "unknown option(s) ['lag'] for FixedLagOptions"),
        ("batch", "[grpah]\nkeyframe_hz = 10.0\n", "unknown table(s) ['grpah']"),
        ("online", "[batch]\ncovariance = 'none'\n", "unknown table(s) ['batch']"),
        ("batch", "[priors]\nsource = ['ml-scale']\n", "[priors]: unknown option(s) ['source']"),
        ("compare", "[msf_ekf]\nrange_sigma = 0.1\n", "unknown table(s) ['msf_ekf']"),
        # compare and fleet check every table's options before any method (or worker) runs.
        ("compare", "[ukf003]\nbogus = 1\n", "unknown option(s) ['bogus'] for Ukf003Options"),
        ("compare", "[graph]\nyaw_sigma = inf\n", "option yaw_sigma = inf: expected a finite"),
        ("compare", "[cf-ekf]\nbogus = 1\n", "unknown option(s) ['bogus'] for CfEkfOptions"),
        ("fleet", "[nosuch]\nx = 1\n", "unknown table(s) ['nosuch']"),
        ("fleet", "[graph]\nbogus = 1\n", "unknown option(s) ['bogus'] for GraphOptions"),
        ("fleet", "[priors]\nsources = ['nosuch']\n", "unknown front-end prior(s) ['nosuch']"),
    ],
)
def test_bad_config_values_and_keys(cli_folder, tmp_path, capsys, command, table, needle):
    assert needle in _config_error(capsys, tmp_path, command, cli_folder, table)


def test_unknown_option_lists_only_keys_valid_in_that_table(cli_folder, tmp_path, capsys):
    """An unknown ``[online]`` key's error lists the keys that table takes: not ``graph``, which
    comes from ``[graph]`` (``[online.graph]`` and ``graph = ...`` in ``[online]`` are refused)."""
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[online]\nlagx = 2.0\n")
    err = _one_line_error(
        capsys, ["online", str(cli_folder), "--out", str(tmp_path / "o"), "--config", str(cfg)]
    )
    valid = err.split("valid: ", 1)[1]
    assert "'lag_s'" in valid and "'graph'" not in valid


@pytest.mark.parametrize("command", ["batch", "online"])
def test_observer_prior_without_a_drag_k_names_priors_once(cli_folder, tmp_path, capsys, command):
    """``--priors observer`` on a flight without a calibrated drag k: one line naming ``[priors]``
    once (the push engine's said ``config: [priors]: [priors]: ...`` with no config file), and
    the config file when the sources come from one."""
    out = tmp_path / "o"
    err = _one_line_error(
        capsys, [command, str(cli_folder), "--out", str(out), "--priors", "observer"]
    )
    assert "needs a calibrated drag coefficient" in err
    assert err.count("[priors]") <= 2 and "[priors]: [priors]" not in err  # the hint names it too
    assert "config:" not in err
    cfg = tmp_path / "p.toml"
    cfg.write_text("[priors]\nsources = ['observer']\n")
    err = _one_line_error(
        capsys, [command, str(cli_folder), "--out", str(out), "--config", str(cfg)]
    )
    assert "needs a calibrated drag coefficient" in err and "[priors]: [priors]" not in err
    assert not out.exists()


def test_compare_reads_every_filter_table(cli_folder, tmp_path, capsys):
    """Each filter baseline's table is accepted by ``fgnav compare`` (``[ekf-flow002]`` and
    ``[cf-ekf]`` were refused as unknown tables), and a ``[priors]`` source that needs the
    flight's drag coefficient is not refused before the flight is read."""
    cfg = tmp_path / "ok.toml"
    cfg.write_text(
        "[cf-ekf]\npredict_rate_hz = 100.0\n[ekf-flow002]\nheight_min = 0.1\n"
        "[ekf004]\nuse_yaw = true\n[priors]\nsources = ['ml-scale']\n"
    )
    argv = ["compare", str(cli_folder), "--out", str(tmp_path / "o"), "--methods", "batch"]
    assert main([*argv, "--no-figures", "--no-progress", "--config", str(cfg)]) == 0
    assert "Traceback" not in capsys.readouterr().err


def test_option_value_rules():
    from fgnav.datasets.simulate.options import SimOptions

    from fgnav.config import OptionValueError, options_from
    from fgnav.solvers.graph import GraphOptions

    # 0 switches a simulated stream off; a negative rate is still refused.
    assert options_from(SimOptions, {"slam_rate_hz": 0.0}).slam_rate_hz == 0.0
    with pytest.raises(OptionValueError, match="slam_rate_hz = -1.0: expected >= 0"):
        options_from(SimOptions, {"slam_rate_hz": -1.0})
    with pytest.raises(
        OptionValueError, match="command line: option keyframe_hz = 0.0: expected > 0"
    ):
        options_from(GraphOptions, {}, keyframe_hz=0.0)
    # Offsets and angles may be negative; tuples are checked for finiteness.
    assert options_from(GraphOptions, {"initial_yaw": -1.0}).initial_yaw == -1.0
    with pytest.raises(OptionValueError, match="expected a finite number"):
        options_from(SimOptions, {"drag_k": [0.3, float("nan")]})
    # Types: an integer fills a float option, a list a tuple; a bool is not a number, a string
    # is not a list of numbers, a nested options table takes a table only.
    assert options_from(GraphOptions, {"slam_sigma_m": 1}).slam_sigma_m == 1
    assert tuple(options_from(SimOptions, {"drag_k": [0.3, 0.4]}).drag_k) == (0.3, 0.4)
    with pytest.raises(OptionValueError, match="slam_sigma_m = True: expected a number"):
        options_from(GraphOptions, {"slam_sigma_m": True})
    with pytest.raises(OptionValueError, match="drag_k = 'x': expected a list"):
        options_from(SimOptions, {"drag_k": "x"})
    from fgnav.solvers.fixed_lag import FixedLagOptions

    with pytest.raises(OptionValueError, match="graph = \\[1\\]: expected a table, found a list"):
        options_from(FixedLagOptions, {"graph": [1]})


@pytest.mark.parametrize("command", ["batch", "online"])
def test_streams_without_overlap(tmp_path, capsys, command):
    import dataclasses

    from fgnav.datasets.native import write_flight
    from fgnav.datasets.simulate.simulator import simulate

    f = simulate("two-turns", seed=5, options=SimOptions(duration=6.0, images=False))
    slam = dataclasses.replace(f.slam, t=f.slam.t + 1000.0)
    folder = write_flight(dataclasses.replace(f, slam=slam), tmp_path / "flight")
    err = _one_line_error(capsys, [command, str(folder), "--out", str(tmp_path / "o")])
    assert "the imu and slam streams do not overlap in time" in err
    assert "imu 0.000-6.000 s, slam 1000.000-1006.000 s" in err


def test_unreadable_image_is_skipped_and_counted(tmp_path, capsys):
    """One truncated PNG in a flight folder: the run continues (it aborted before), the frame is
    counted by reason in summary.json and the VO pairs the next frame with the last good one."""
    import json

    folder = simulate_to_folder(
        "two-turns",
        tmp_path / "flight",
        seed=1,
        options=SimOptions(duration=4.0, image_rate_hz=10.0),
    )
    pngs = sorted((folder / "cam0").glob("*.png"), key=lambda p: int(p.stem))
    bad = pngs[10]
    bad.write_bytes(bad.read_bytes()[:200])
    out = tmp_path / "batch"
    assert main(["batch", str(folder), "--out", str(out), "--no-progress"]) == 0
    info = json.loads((out / "summary.json").read_text())["info"]
    assert info["skipped"]["homography:vo-unreadable-image"] == 1
    vo = info["homography"]["vo_counts"]
    assert vo["unreadable_image"] == 1 and vo["frames"] == len(pngs)
    assert vo["valid_pairs"] == len(pngs) - 2


def test_online_scores_a_flight_with_a_slam_reset(tmp_path, capsys):
    """A SLAM map reset at 10 s: ``fgnav online`` scores the run per session as ``fgnav batch``
    does (before: "cannot tell the session of each value", not scored)."""
    import json

    folder = simulate_to_folder(
        "two-turns",
        tmp_path / "flight",
        seed=4,
        options=SimOptions(duration=20.0, images=False, slam_resets=(10.0,)),
    )
    out = tmp_path / "online"
    assert main(["online", str(folder), "--out", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "fixed-lag: ATE" in text
    summary = json.loads((out / "summary.json").read_text())
    m = summary["metrics"]
    assert m["ate_rmse_m"] < 0.15
    # Both sessions scored (measured: ATE 4.6 cm, final scale error +1.7 % and +0.4 %).
    assert set(m["scale_final_err_pct"]) == {"0", "1"}
    assert set(m["scale_mean_abs_err_pct"]) == {"0", "1"}
    assert all(abs(v) < 5.0 for v in m["scale_final_err_pct"].values())


@pytest.mark.parametrize("command", ["batch", "online", "compare", "simulate"])
def test_empty_out_is_refused(cli_folder, tmp_path, capsys, monkeypatch, command):
    """``--out ""`` (an unset shell variable) wrote the outputs into the current folder."""
    monkeypatch.chdir(tmp_path)
    argv = [command, "--out", ""] + (
        ["--scenario", "hover"] if command == "simulate" else [str(cli_folder)]
    )
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert "argument --out: empty path" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("command", ["batch", "online", "compare", "fleet", "simulate"])
def test_out_that_is_a_file_is_refused_before_anything_runs(cli_folder, tmp_path, capsys, command):
    """``--out`` naming a file (or a path inside one) failed with a traceback when the outputs
    were written, after the whole solve (review 2026-12-07)."""
    f = tmp_path / "afile"
    f.write_text("x")
    for out, said in ((f, "is a file"), (f / "sub", "is inside")):
        argv = [command, "--out", str(out)] + (
            ["--scenario", "hover"] if command == "simulate" else [str(cli_folder)]
        )
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert "argument --out:" in err and said in err and "Traceback" not in err


def test_every_option_refuses_a_value_of_the_wrong_type():
    """Each option of every ``--config`` table, given a value of another type than it declares,
    is one error naming it before anything runs (a string sigma crashed the online start; a
    number for a switch was taken as true)."""
    import dataclasses
    import typing

    from fgnav.datasets.errors import FgnavError

    from fgnav.config import _field_types
    from fgnav.methods import _BASELINE_OPTIONS, check_method_config
    from fgnav.solvers.batch import BatchOptions
    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.graph import GraphOptions

    classes = {"graph": GraphOptions, "online": FixedLagOptions, "batch": BatchOptions}
    for table, (module, name) in _BASELINE_OPTIONS.items():
        classes[table] = getattr(__import__(module, fromlist=[name]), name)
    wrong = {bool: "yes", int: "many", float: "much", str: 3}
    checked = 0
    for table, cls in classes.items():
        hints = _field_types(cls)
        for f in dataclasses.fields(cls):
            hint = hints.get(f.name)
            args = set(typing.get_args(hint)) - {type(None)} or {hint}
            kinds = [k for k in args if k in wrong]
            if len(kinds) != 1 or len(args) != 1:
                continue  # unions of several types, tables, lists: not this test
            value = wrong[kinds[0]]
            with pytest.raises(FgnavError) as e:
                check_method_config({table: {f.name: value}})
            msg = str(e.value)
            assert f"option {f.name} = {value!r}: expected" in msg and "\n" not in msg, msg
            checked += 1
    assert checked > 200


@pytest.mark.parametrize(
    ("argv", "argument"),
    [
        (["info", ""], "flight"),
        (["batch", "", "--out", "o"], "flight"),
        (["online", "{flight}", "--out", "o", "--config", ""], "--config"),
        (["live", "--mavlink", "udpin:127.0.0.1:9", "--calib", "", "--out", "o"], "--calib"),
        (["replay", "{flight}", "--mavlink", "udpout:127.0.0.1:9", "--record", ""], "--record"),
    ],
)
def test_empty_paths_are_refused(cli_folder, tmp_path, capsys, monkeypatch, argv, argument):
    """An empty path argument is named (``--calib ""`` was read as the folder ``.``)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        main([a.replace("{flight}", str(cli_folder)) for a in argv])
    assert e.value.code == 2
    assert f"argument {argument}: empty path" in capsys.readouterr().err


def test_a_folder_where_a_file_is_expected_is_named(cli_folder, tmp_path, capsys):
    """A folder given for a file (``--config``, a calibration, a Crazyflie log) was reported as
    "not found" (review 2026-12-07)."""
    from fgnav.datasets.crazyflie import decode_crazyflie_log
    from fgnav.datasets.errors import FlightFormatError

    argv = ["batch", str(cli_folder), "--config", str(tmp_path), "--out", str(tmp_path / "o")]
    assert main(argv) == 1
    assert f"{tmp_path}: is a folder, not a config file" in capsys.readouterr().err
    with pytest.raises(FlightFormatError, match="is a folder, not a Crazyflie SD-card log"):
        decode_crazyflie_log(tmp_path)


def test_a_nested_options_table_is_built_into_its_options():
    """``[ii-observer.observer] kinematics = "full"`` passed the table on as a dict: the run
    failed in ``dataclasses.replace`` with a TypeError (review 2026-12-07). It is now built into
    ``IIObserverOptions`` and checked there (an unknown key named with its table)."""
    from fgnav.datasets.errors import FlightFormatError

    from fgnav.baselines.seed000 import Seed000Options
    from fgnav.config import options_from
    from fgnav.frontends.ii_observer import IIObserverOptions

    o = options_from(Seed000Options, {"observer": {"kinematics": "full"}}, "c.toml", "ii-observer")
    assert isinstance(o.observer, IIObserverOptions) and o.observer.kinematics == "full"
    with pytest.raises(FlightFormatError, match=r"c\.toml \[ii-observer\.observer\]: unknown"):
        options_from(Seed000Options, {"observer": {"kinematic": "full"}}, "c.toml", "ii-observer")


@pytest.mark.parametrize("command", ["batch", "online", "compare"])
@pytest.mark.parametrize(
    ("table", "needle"),
    [
        (
            "[graph.flow]\nsigma_rad = 'x'\n",
            "[graph]: flow: option sigma_rad = 'x': expected a num",
        ),
        ("[graph.flow]\nbogus = 1\n", "unknown option(s) ['bogus'] for FlowFactorOptions"),
        ("[graph.flow]\nsigma_rad = -1.0\n", "sigma_rad = -1.0: expected > 0"),
        ("[graph.homography]\nmin_inliers = 2.5\n", "option min_inliers = 2.5: expected an int"),
        ("[graph.homography]\nbogus = 1\n", "for HomographyFactorOptions"),
        ("[graph.homography.vo]\nmax_corners = 'x'\n", "homography [vo]: option max_corners"),
        ("[graph.homography.vo]\nbogus = 1\n", "['bogus'] for HomographyVOOptions"),
    ],
)
def test_flow_and_homography_tables_are_checked_up_front(tmp_path, capsys, command, table, needle):
    """``[graph.flow]``, ``[graph.homography]`` and ``[graph.homography.vo]`` are checked (keys,
    types, values) before the flight is read: a wrong type was a TypeError or a cv2.error at
    the first factor (review 2026-12-07)."""
    assert needle in _config_error(capsys, tmp_path, command, tmp_path / "nosuch", table)


@pytest.mark.parametrize("command", ["batch", "online", "compare"])
@pytest.mark.parametrize(
    ("table", "needle"),
    [
        # A scalar where a table belongs was a TypeError in dict().
        ("graph = 5\n", "[graph] must be a table, found an integer (graph = 5)"),
        ("priors = 5\n", "[priors] must be a table, found an integer"),
        ("graph = [1]\n", "[graph] must be a table, found a list"),
        # [priors] values were not checked (a TypeError, a ValueError, an IndexError, or three
        # drag coefficients cut to two).
        ("[priors]\nsources = 5\n", "[priors]: option sources = 5: expected a list of front"),
        ("[priors]\nsources = [1]\n", "option sources = [1]: expected a list of front-end"),
        ("[priors]\ndrag_k = 'abc'\n", "[priors]: option drag_k = 'abc': expected a number > 0"),
        ("[priors]\nsources = ['observer']\ndrag_k = []\n", "option drag_k = []: expected"),
        ("[priors]\nsources = ['observer']\ndrag_k = nan\n", "option drag_k = nan: expected"),
        ("[priors]\ndrag_k = [0.4, 0.5, 9.0]\n", "option drag_k = [0.4, 0.5, 9.0]: expected"),
        ("[priors]\ndrag_k = [-0.4, 0.5]\n", "option drag_k = [-0.4, 0.5]: expected"),
        ("[priors]\nsources = 'nosuch'\n", "unknown front-end prior(s) ['nosuch']"),
    ],
)
def test_tables_and_priors_are_checked_up_front(tmp_path, capsys, command, table, needle):
    assert needle in _config_error(capsys, tmp_path, command, tmp_path / "nosuch", table)


def test_one_prior_source_may_be_a_string():
    """``sources = "ml-scale"`` is the one source (it was read letter by letter)."""
    from fgnav.frontends.prior_stages import prior_options

    assert prior_options({"sources": "ml-scale"}).sources == ("ml-scale",)
    o = prior_options({"sources": ["observer"], "drag_k": 0.4})
    assert o.drag_k == (0.4, 0.4)
    assert prior_options({"sources": ["observer"]}, drag_k=[0.3, 0.5]).drag_k == (0.3, 0.5)


@pytest.mark.parametrize(
    ("table", "needle"),
    [
        ("[online]\nmax_imu_gap_s = 0\n", "[online]: option max_imu_gap_s = 0: expected > 0"),
        ("[online]\ninit_imu_s = 0\n", "option init_imu_s = 0: expected > 0"),  # hung
        ("[online]\ninit_imu_s = 1e-300\n", "option init_imu_s = 1e-300: expected >= 0.001"),
        ("[online]\ndrag_scatter_n = 0\n", "option drag_scatter_n = 0: expected > 0"),
        ("[graph]\ndrag_model_sigma = 1e300\n", "drag_model_sigma = 1e+300: expected in [1e-12,"),
        ("[graph]\nprior_position_sigma = 1e300\n", "prior_position_sigma = 1e+300: expected"),
        ("[graph]\nprior_gyro_bias_sigma = 1e300\n", "prior_gyro_bias_sigma = 1e+300: expec"),
        ("[graph]\nground_segment_s = 1e-300\n", "ground_segment_s = 1e-300: expected >= 0.001"),
        ("[graph]\ndrag_segment_s = 1e-300\n", "drag_segment_s = 1e-300: expected >= 0.001"),
        ("[graph]\nslam_segment_s = 1e-300\n", "slam_segment_s = 1e-300: expected >= 0.001"),
        ("[online]\nrelinearize_skip = 9223372036854775807\n", "expected an integer up to 21"),
        ("[graph]\ngravity = 1e300\n", "option gravity = 1e+300: expected in [1, 100]"),
        ("[graph]\nslam_scale_rw = 1e300\n", "option slam_scale_rw = 1e+300: expected in [1e-12"),
        ("[graph]\ngravity = 1e-300\n", "option gravity = 1e-300: expected in [1, 100]"),
        ("[ekf004]\nmax_predict_dt_s = 1e-300\n", "max_predict_dt_s = 1e-300: expected >= 0.0001"),
        # [lm] (review 2026-12-07, ninth session): a lambda_factor <= 1 retried a rejected step
        # without end; lambda_init above lambda_max stopped at the initial guess, "converged".
        ("[lm]\nlambda_factor = 0.5\n", "lambda_factor=0.5: expected > 1 and <= 1e6"),
        ("[lm]\nlambda_factor = 1e300\n", "lambda_factor=1e+300: expected > 1 and <= 1e6"),
        ("[lm]\nlambda_init = 1e3\nlambda_max = 1e2\n", "lambda_init=1000: expected <= lambda"),
        ("[lm]\nlambda_init = 1e300\n", "option lambda_init = 1e+300: expected in [1e-20, 1e+20]"),
        ("[lm]\nlambda_max = 1e-300\n", "option lambda_max = 1e-300: expected in [1e-20, 1e+20]"),
        ("[lm]\nlambda_min = 1e300\n", "option lambda_min = 1e+300: expected in [1e-20, 1e+20]"),
        ("[lm]\nmax_iterations = 2147483647\n", "max_iterations = 2147483647: expected in [1, 1"),
        ("[lm]\nrel_tol = 1e300\n", "option rel_tol = 1e+300: expected <= 1"),
        ("[lm]\nabs_tol = -1\n", "option abs_tol = -1: expected in [0, 1e+06]"),
        ("[lm]\nabs_tol = 1e300\n", "option abs_tol = 1e+300: expected in [0, 1e+06]"),
        ("[online]\nmax_imu_gap_s = 1e-300\n", "max_imu_gap_s = 1e-300: expected >= 0.001"),
        ("[online]\ndrag_scatter_n = 2147483647\n", "drag_scatter_n = 2147483647: expected in"),
        # The filters' process noises and walks, tilt limits, initial scale and drag_k: 1e300
        # overflowed or failed an SVD (a FAILED row, exit 0), -1 or 0 were taken.
        ("[msf-ekf]\nscale_walk = 1e300\n", "option scale_walk = 1e+300: expected in [0, 1e+06]"),
        ("[ukf003]\naltimeter_bias_walk = -1\n", "altimeter_bias_walk = -1: expected in [0, 1e+"),
        ("[ekf004]\naccel_noise_xy = 1e300\n", "accel_noise_xy = 1e+300: expected in [0, 1e+06]"),
        ("[cf-ekf]\nproc_noise_acc_z = -1\n", "proc_noise_acc_z = -1: expected in [0, 1e+06]"),
        ("[ii-observer.vertical]\naccel_noise = 1e300\n", "accel_noise = 1e+300: expected in"),
        ("[msf-ekf]\ninitial_scale = 1e300\n", "initial_scale = 1e+300: expected in [1e-06, 1e+"),
        ("[ukf003]\ninitial_scale = 0\n", "option initial_scale = 0: expected in [1e-06, 1e+06]"),
        ("[ekf004]\ndrag_k = [1e300, 1e300]\n", "drag_k = [1e+300, 1e+300]: expected in [0, 100]"),
        ("[ii-observer]\ndrag_k = [-1, -1]\n", "option drag_k = [-1, -1]: expected in [0, 100]"),
        # The observer's velocity is the specific force over k: [1e-300, 1e-300] ran to 1e14 m
        # (two-turns 20 s; 0.4 m at the truth), as online priors 30.9 m on circle (0.4: cm).
        (
            "[ii-observer]\ndrag_k = [1e-300, 1e-300]\n",
            "Seed000Options.drag_k=[1e-300, 1e-300]: expected (kx, ky) in [0.01, 100] [1/s]",
        ),
        (
            "[ii-observer.observer]\ndrag_k = [0.4, 1e-3]\n",
            "Seed000Options.observer.drag_k=[0.4, 0.001]: expected (kx, ky) in [0.01, 100]",
        ),
        ("[priors]\ndrag_k = 1e-300\n", "option drag_k = 1e-300: expected (kx, ky) in [0.01, 1"),
        ("[graph]\nrange_max_tilt_deg = -1\n", "range_max_tilt_deg = -1: expected in [0.1, 90]"),
        (
            "[graph]\ndrag_max_tilt_deg = 1e300\n",
            "drag_max_tilt_deg = 1e+300: expected in [0.1, 90",
        ),
        ("[cf-ekf]\ntof_cone_deg = 1e300\n", "tof_cone_deg = 1e+300: expected in [0.1, 90]"),
        (
            "[ekf004]\nrange_max_tilt_rad = 1e300\n",
            "range_max_tilt_rad = 1e+300: expected in [0.001,",
        ),
        ("[ekf-vo002.ekf]\nmax_tilt = -1\n", "option max_tilt = -1: expected in [0.001, 1.5708]"),
        ("[ii-observer.vertical]\nmax_tilt = 0\n", "max_tilt = 0: expected in [0.001, 1.5708]"),
        ("[ukf003]\nut_alpha = 0\n", "option ut_alpha = 0: expected in [0.0001, 1]"),
        ("[ukf003]\nut_kappa = -1\n", "option ut_kappa = -1: expected in [0, 100]"),
        ("[ukf003]\nut_beta = 1e300\n", "option ut_beta = 1e+300: expected in [0, 10]"),
        ("[ii-observer.observer]\ngamma_v = [0, 0]\n", "gamma_v = [0, 0]: expected in [0.001, 1"),
        ("[ii-observer.observer]\ngamma_k = [1e300, 1e300]\n", "gamma_k = [1e+300, 1e+300]: exp"),
        ("[ii-observer.observer]\neta0 = [1e300, 1e300]\n", "eta0 = [1e+300, 1e+300]: expected"),
        ("[ii-observer.observer]\nmax_scale_step = -1\n", "max_scale_step = -1: expected > 0"),
        ("[ii-observer.observer]\nscale_floor = 1e-300\n", "scale_floor = 1e-300: expected in"),
        # The second fuzz on runs: [graph], the VO ([graph.homography.vo], [ekf-vo002.vo]), flow.
        ("[graph]\nrobust_k = 1e-300\n", "option robust_k = 1e-300: expected >= 0.01"),
        ("[graph]\ncontact_height_m = 1e300\n", "contact_height_m = 1e+300: expected <= 1"),
        ("[graph.homography.vo]\nmax_corners = -1\n", "max_corners = -1: expected >= 0"),
        ("[ekf-vo002.vo]\ncorner_quality = 0\n", "corner_quality = 0: expected in [1e-06, 1]"),
        ("[ekf-vo002.vo]\ncorner_quality = 1e300\n", "corner_quality = 1e+300: expected in"),
        (
            "[graph.homography.vo]\nmin_corner_distance_px = 1e300\n",
            "min_corner_distance_px = 1e+300: expected in [0, 10000]",
        ),
        ("[ekf-vo002.vo]\nmin_corner_distance_px = -1\n", "min_corner_distance_px = -1: expe"),
        (
            "[graph.homography.vo]\ncorner_block_size_px = 2147483647\n",
            "corner_block_size_px = 2147483647: expected in [1, 1000]",
        ),
        (
            "[graph.homography.vo]\ncorner_pyramid_level = 2147483647\n",
            "corner_pyramid_level = 2147483647: expected in [0, 6]",
        ),
        ("[graph.homography.vo]\nlk_window_px = 0\n", "lk_window_px = 0: expected in [3, 1000]"),
        ("[ekf-vo002.vo]\nlk_pyramid_levels = -1\n", "lk_pyramid_levels = -1: expected in [0,"),
        (
            "[graph.homography.vo]\nflow_guess_levels = 2147483647\n",
            "flow_guess_levels = 2147483647: expected in [0, 10]",
        ),
        ("[graph.homography.vo]\nlk_max_iterations = 0\n", "lk_max_iterations = 0: expected in"),
        (
            "[graph.homography.vo]\nflow_guess_max_correction_px = 1e300\n",
            "flow_guess_max_correction_px = 1e+300: expected in [0, 10000]",
        ),
        ("[ekf-vo002.vo]\nransac_confidence = 0\n", "ransac_confidence = 0: expected in [0.5,"),
        ("[graph.homography.vo]\nransac_confidence = 1\n", "ransac_confidence: expected > 0 an"),
        ("[ekf-vo002.vo]\nransac_confidence = 1\n", "ransac_confidence: expected > 0 and <"),
        ("[graph.homography.vo]\nrectify_interpolation = -1\n", "rectify_interpolation = -1"),
        ("[ekf-vo002.vo]\nrectify_interpolation = 5\n", "rectify_interpolation = 5: expected"),
        ("[ekf-vo002.vo]\nmin_inliers = 0\n", "min_* must be >= 4"),
        ("[ekf-vo002.vo]\nmin_corners = 2147483647\n", "expected <= max_corners=200"),
        ("[ekf-vo002.vo]\nransac_confidence = 1e-300\n", "expected in [0.5, 1]"),
        ("[ekf-vo002.vo]\nransac_threshold_px = 1e-300\n", "ransac_threshold_px = 1e-300: ex"),
        ("[graph.homography.vo]\nmask_margin_px = -1\n", "mask_margin_px = -1: expected in"),
        ("[ekf-flow002]\nquality_min = 1e300\n", "quality_min = 1e+300: expected <= 1"),
        ("[cf-ekf]\nquality_min = 1e300\n", "quality_min = 1e+300: expected <= 1"),
        ("[ekf-flow002]\nheight_min = 1e300\n", "height_min = 1e+300: expected <= 100"),
        ("[cf-ekf]\noutlier_rad = 0\n", "option outlier_rad = 0: expected >= 0.01"),
        ("[cf-ekf]\ntof_outlier_m = 1e-300\n", "tof_outlier_m = 1e-300: expected >= 0.05"),
        ("[ekf-vo002]\nground_height = 1e300\n", "ground_height = 1e+300: expected in [-1"),
        ("[ekf-flow002]\nground_height = 1e300\n", "ground_height = 1e+300: expected in"),
    ],
)
def test_values_that_pass_the_sign_rules_but_make_no_sense(tmp_path, capsys, table, needle):
    """Values > 0 and finite that crashed or hung a run (review 2026-12-07) are refused up front
    by the bounds of :func:`fgnav.config.option_bounds`."""
    assert needle in _config_error(capsys, tmp_path, "compare", tmp_path / "nosuch", table)


def test_option_bounds_refuse_no_default():
    """The bounds are generous: every options class's default passes them, and so do the
    sigmas of 1e6 and segments of 1 ms (a sigma that large ran to the end on a flight)."""
    import dataclasses

    from fgnav.config import ZERO_OK_OPTIONS, option_bounds, option_value_problem
    from fgnav.frontends.homography_vo import HomographyVOOptions
    from fgnav.methods import _BASELINE_OPTIONS
    from fgnav.solvers.batch import BatchOptions, LMOptions
    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.flow import FlowFactorOptions
    from fgnav.solvers.graph import GraphOptions
    from fgnav.solvers.vision import HomographyFactorOptions

    classes = [GraphOptions, FixedLagOptions, BatchOptions, LMOptions, SimOptions]
    classes += [HomographyVOOptions, FlowFactorOptions, HomographyFactorOptions]
    classes += [getattr(__import__(m, fromlist=[n]), n) for m, n in _BASELINE_OPTIONS.values()]
    for cls in classes:
        zero_ok = getattr(cls, "ZERO_MEANS_OFF", frozenset()) | ZERO_OK_OPTIONS
        for f in dataclasses.fields(cls):
            if f.default is dataclasses.MISSING or option_bounds(f.name) == (None, None):
                continue
            assert option_value_problem(f.name, f.default, f.name in zero_ok) is None, f.name
    assert option_value_problem("prior_position_sigma", 1e6) is None
    # (ekf-vo002's published VO, a factory default, passes too)
    from fgnav.baselines.seed002 import Seed002Options

    vo = Seed002Options().vo
    assert all(
        option_value_problem(f.name, getattr(vo, f.name)) is None for f in dataclasses.fields(vo)
    )
    assert option_value_problem("ground_segment_s", 1e-3) is None
    assert option_value_problem("gravity", 9.81) is None
    # [lm]: the widest sensible values pass (one iteration, no tolerance, little damping).
    assert option_value_problem("max_iterations", 100_000) is None
    assert option_value_problem("rel_tol", 1.0) is None
    assert option_value_problem("abs_tol", 0.0) is None
    assert option_value_problem("lambda_min", 1e-20) is None
    LMOptions().validate()
    # The nested options classes' defaults too ([ekf004.scale], [ekf-vo002.ekf] ...).
    from fgnav.config import _field_types, _nested_options_class

    nested = [_nested_options_class(h) for c in classes for h in _field_types(c).values()]
    for cls in {n for n in nested if n is not None}:
        for f in dataclasses.fields(cls):
            if f.default is not dataclasses.MISSING:
                assert option_value_problem(f.name, f.default) is None, (cls, f.name)
    assert option_value_problem("drag_k", [0.0, 100.0]) is None
    assert option_value_problem("flow_noise_lag1", -0.3) is None  # a correlation, not a noise
    assert option_value_problem("range_max_tilt_deg", 90.0) is None
    LMOptions(lambda_factor=1.01, lambda_init=1e8).validate()


@pytest.mark.parametrize(
    ("command", "table", "needle"),
    [
        ("batch", "[batch]\ncovariance = 'bogus'\n", "covariance='bogus': expected all, slow or"),
        ("online", "[online]\nfactorization = 'bogus'\n", "factorization='bogus': expected one"),
        ("online", "[online]\nfallback_factorization = 'x'\n", "fallback_factorization='x': exp"),
        ("online", "[online]\nsmoother = 'bogus'\n", "smoother='bogus': expected one of time"),
        # engine and vo_worker were refused after the flight was read (compare then ran batch
        # and exited 0 with a FAILED row).
        ("compare", "[online]\nengine = 'bogus'\n", "engine='bogus': expected one of auto, push"),
        ("compare", "[online]\nvo_worker = 'bogus'\n", "vo_worker='bogus': expected one of in"),
        # Sub-tables of options built from their own tables were silently replaced.
        ("online", "[online.graph]\nkeyframe_hz = 5.0\n", "['graph'] are tables of their own"),
        ("batch", "[batch.lm]\nmax_iterations = 5\n", "['lm'] are tables of their own: write [lm]"),
        ("batch", "[batch]\ngraph = 'abc'\n", "[batch]: option(s) ['graph'] are tables of their"),
    ],
)
def test_choices_and_sub_tables_are_checked_up_front(tmp_path, capsys, command, table, needle):
    assert needle in _config_error(capsys, tmp_path, command, tmp_path / "nosuch", table)


def test_online_imu_spans_the_flight_cannot_meet_are_refused(cli_folder, tmp_path, capsys):
    """``max_imu_gap_s`` below the IMU interval made every interval a gap (1e-300: 20x longer,
    ATE 140x worse, exit 0); ``init_imu_s`` past the flight's IMU was "produced no state"
    (review 2026-12-07, ninth session)."""
    from fgnav.datasets.errors import FlightDataError
    from fgnav.datasets.load import load_flight

    from fgnav.methods import check_online_imu
    from fgnav.solvers.fixed_lag import FixedLagOptions

    cfg = tmp_path / "c.toml"
    cfg.write_text("[online]\ninit_imu_s = 100\n")
    argv = ["online", str(cli_folder), "--out", str(tmp_path / "o"), "--config", str(cfg)]
    err = _one_line_error(capsys, argv)
    assert "init_imu_s=100 is not shorter than the flight's 8 s of IMU; expected" in err
    flight = load_flight(cli_folder)
    with pytest.raises(FlightDataError, match=r"max_imu_gap_s=0.003 is below twice the flight's"):
        check_online_imu(flight, FixedLagOptions(max_imu_gap_s=0.003))
    check_online_imu(flight, FixedLagOptions())  # the defaults pass
    check_online_imu(flight, FixedLagOptions(max_imu_gap_s=0.01, init_imu_s=7.9))


def test_factorization_names_are_matched_without_case():
    from fgnav.methods import check_method_config

    check_method_config({"online": {"factorization": "qr", "fallback_factorization": "cholesky"}})


def test_a_lag_or_keyframe_rate_that_leaves_no_window_is_refused(cli_folder, tmp_path, capsys):
    """``online --lag 0.001`` ran with an ATE 17x worse and health ok; ``--keyframe-hz 0.01``
    made 1 keyframe, "not scored", exit 0 (review 2026-12-07)."""
    out = tmp_path / "o"
    err = _one_line_error(
        capsys, ["online", str(tmp_path / "nosuch"), "--out", str(out), "--lag", "0.001"]
    )
    assert "command line: FixedLagOptions.lag_s=0.001: expected >= 2 / keyframe_hz = 0.1 s" in err
    for command in ("batch", "online"):
        flags = ["--keyframe-hz", "0.01"] + (["--lag", "300"] if command == "online" else [])
        err = _one_line_error(capsys, [command, str(cli_folder), "--out", str(out), *flags])
        assert "keyframe_hz=0.01 leaves fewer than 2 keyframes on the flight's" in err
    assert not out.exists()


def test_a_history_shorter_than_the_slam_fit_is_refused(tmp_path, capsys):
    """``[online] history_s = 0`` ran (simulated two-turns / circle, seed 1, 24 s, no camera:
    causal ATE 2.3x / 4.1x nominal, health "ok"): the history must hold the span a closed-form
    SLAM fit uses (``slam_fit_max_s``) and its IMU margin. One line, exit 1, before the flight is
    read; a longer fit asks for a longer history; from the Python API the same rule."""
    from fgnav.solvers.fixed_lag import FixedLagOptions

    out = tmp_path / "o"
    for table, needle in (
        ("history_s = 0\n", "history_s=0: expected >= slam_fit_max_s + 0.6 = 20.6 s (the IMU"),
        ("history_s = 20.5\n", "history_s=20.5: expected >= slam_fit_max_s + 0.6 = 20.6 s"),
        ("slam_fit_max_s = 40.0\n", "history_s=30: expected >= slam_fit_max_s + 0.6 = 40.6 s"),
    ):
        cfg = tmp_path / "bad.toml"
        cfg.write_text("[online]\n" + table)
        argv = ["online", str(tmp_path / "nosuch"), "--out", str(out), "--config", str(cfg)]
        err = _one_line_error(capsys, argv)
        assert err.startswith(f"fgnav online: error: {cfg} [online]: FixedLagOptions.")
        assert needle in err, err
    assert not out.exists()
    with pytest.raises(ValueError, match=r"history_s=5: expected >= slam_fit_max_s \+ 0.6"):
        FixedLagOptions(history_s=5.0).validate()
    FixedLagOptions(history_s=20.6).validate()
    FixedLagOptions(history_s=40.6, slam_fit_max_s=40.0).validate()


@pytest.mark.parametrize(
    ("table", "needle"),
    [
        # The relinearisation thresholds took any number (-1: 0 written otherwise; 1e300: never).
        ("relinearize_threshold = -1\n", "option relinearize_threshold = -1: expected in [0, 100]"),
        ("relinearize_threshold = 1e300\n", "relinearize_threshold = 1e+300: expected in [0, 100]"),
        ("relinearize_threshold_position = -0.1\n", "relinearize_threshold_position = -0.1: ex"),
        ("relinearize_threshold_slow = 1e300\n", "relinearize_threshold_slow = 1e+300: expec"),
        ("startup_relinearize_threshold = -1\n", "startup_relinearize_threshold = -1: expected"),
        # relinearizeSkip 0 killed the process with SIGFPE (a start without an attitude stream).
        ("startup_relinearize_skip = 0\n", "option startup_relinearize_skip = 0: expected > 0"),
        ("startup_relinearize_skip = -1\n", "option startup_relinearize_skip = -1: expected > 0"),
        # Refused only once the flight was read.
        ("vo_process_delay_keyframes = 0\n", "option vo_process_delay_keyframes = 0: expected > 0"),
        # The window kept every keyframe (cost growing with the flight).
        ("lag_s = 1e300\n", "option lag_s = 1e+300: expected <= 1000"),
        ("marginalize_every_s = 1e300\n", "option marginalize_every_s = 1e+300: expected <= 1000"),
        # 4x worse without an attitude stream.
        ("slam_init_max_rel_se = 1e300\n", "option slam_init_max_rel_se = 1e+300: expected <= 1"),
        # 13x worse, health ok.
        (
            "slam_provisional_scale = 1e-300\n",
            "slam_provisional_scale = 1e-300: expected in [1e-06",
        ),
    ],
)
def test_online_options_are_bounded_when_the_config_is_read(tmp_path, capsys, table, needle):
    """``fgnav online --config F`` names the table and key of each in one line, exit 1, before
    the flight is read (it does not exist here)."""
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[online]\n" + table)
    argv = ["online", str(tmp_path / "nosuch"), "--out", str(tmp_path / "o"), "--config", str(cfg)]
    err = _one_line_error(capsys, argv)
    assert err.startswith(f"fgnav online: error: {cfg} [online]: option ") and needle in err
    assert not (tmp_path / "o").exists()


def test_keyframe_rate_is_bounded_when_the_config_is_read(tmp_path, capsys):
    """``keyframe_hz = 1e-300`` was refused by the lag's rule only (naming lag_s), and with
    ``lag_s = 1e300`` not before the flight was read."""
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[graph]\nkeyframe_hz = 1e-300\n[online]\nlag_s = 1000.0\n")
    argv = ["online", str(tmp_path / "nosuch"), "--out", str(tmp_path / "o"), "--config", str(cfg)]
    err = _one_line_error(capsys, argv)
    assert str(cfg) in err and "[graph]: option keyframe_hz = 1e-300: expected >= 0.001" in err
    flags = ["--keyframe-hz", "1e-300", "--lag", "1000"]
    err = _one_line_error(capsys, ["online", str(tmp_path / "nosuch"), "--out", "o", *flags])
    assert "command line: option keyframe_hz = 1e-300: expected >= 0.001" in err


def test_push_engine_refuses_a_relinearize_skip_below_one():
    """From the Python API too (relinearizeSkip 0: SIGFPE, the process gone)."""
    from fgnav.datasets.errors import FlightDataError
    from fgnav.datasets.types import Calibration

    from fgnav.solvers.fixed_lag import FixedLagOptions
    from fgnav.solvers.online import OnlineSmoother

    for skip in ("relinearize_skip", "startup_relinearize_skip"):
        with pytest.raises(FlightDataError, match=f"online.{skip}=0: expected an integer >= 1"):
            OnlineSmoother(Calibration(), FixedLagOptions(**{skip: 0}))
    OnlineSmoother(Calibration(), FixedLagOptions(startup_relinearize_skip=1))


@pytest.mark.parametrize("command", ["batch", "online"])
def test_a_flight_without_the_streams_a_smoother_needs_is_refused(
    cli_folder, tmp_path, capsys, command
):
    """``fgnav batch`` / ``fgnav online`` on an IMU-only flight: one line naming the flight and
    the missing stream, as ``compare`` and ``fleet`` skip it (online ran to a 14 m estimate on a
    Crazyflie log with its flow and range removed, batch to 30 LM iterations)."""
    import json
    import shutil

    flight = tmp_path / "imu-only"
    flight.mkdir()
    for name in ("imu.csv", "ground_truth.csv", "calib.yaml"):
        shutil.copy(cli_folder / name, flight / name)
    meta = json.loads((cli_folder / "meta.json").read_text())
    meta["streams"] = ["imu", "ground_truth"]
    (flight / "meta.json").write_text(json.dumps(meta))
    err = _one_line_error(capsys, [command, str(flight), "--out", str(tmp_path / "o")])
    assert "needs slam; the flight has none" in err and meta["name"] in err
    assert not (tmp_path / "o" / "estimate.tum").exists()


def test_a_flow_deck_without_its_rangefinder_is_told_it_needs_the_range():
    """The smoothers need imu + slam, or images + range, or flow + range: a flow deck whose
    rangefinder is gone needs the range (the message said "needs slam", the first of three
    alternatives one stream short); an IMU-only flight still needs the SLAM."""
    import dataclasses

    from fgnav.datasets.simulate import SimOptions, simulate

    from fgnav.methods import METHODS

    f = simulate("flowdeck", seed=0, options=SimOptions(duration=3.0, images=False))
    assert METHODS["batch"].missing(dataclasses.replace(f, range=None, slam=None)) == ["range"]
    bare = dataclasses.replace(f, range=None, flow=None, slam=None)
    assert METHODS["fixed-lag"].missing(bare) == ["slam"]
