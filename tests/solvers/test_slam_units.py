"""The push engine's SLAM units check (``OnlineSmoother._units_check``): a SLAM whose units are
not metres, or a provisional scale gone astray, re-seeds the provisional alignment's scale from
the poses' second differences against the IMU's."""

from __future__ import annotations

import math

import pytest
from fgnav.datasets.simulate import SimOptions, simulate

import fgnav.solvers.online as online
from fgnav.eval.metrics import evaluate
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.online import replay_online


def _sources(est) -> list[str]:
    return [p["from"] for p in est.info["slam_provisional_scales"]]


@pytest.fixture(scope="module")
def centimetres():
    """Two-turns, 20 s, its SLAM in centimetres (100 units per metre)."""
    return simulate(
        "two-turns", seed=1, options=SimOptions(duration=20.0, images=False, slam_scale=100.0)
    )


def test_a_slam_in_centimetres_is_found_and_survived(centimetres):
    """Measured 2026-12-07: the default scale 1 made the SLAM noise 100x too tight; the window
    diverged at 0.75 s (speed 364 m/s, health "diverged", ATE infinite). Found on the 4th pose
    (0.13 s): causal ATE 5.0 cm (the same flight in metres 2.4 cm)."""
    f = centimetres
    est = replay_online(f, FixedLagOptions())
    assert _sources(est)[:2] == ["default", "units"]
    assert est.info["health"]["status"] == "ok", est.info["health"]
    assert est.info["used"]["slam:provisional-units"] == 1
    m = evaluate(est, f.ground_truth, alignment="se3")
    assert m.ate_rmse_m < 0.10, m.ate_rmse_m
    assert abs(est.slam_scale[0] / 100.0 - 1.0) < 0.02, est.slam_scale


def test_without_the_check_the_centimetre_slam_diverges(centimetres, monkeypatch):
    """The failing control of the test above."""
    monkeypatch.setattr(online, "UNITS_MIN_RATIO", math.inf)
    monkeypatch.setattr(online, "UNITS_NOISE_MIN_RATIO", math.inf)
    est = replay_online(centimetres, FixedLagOptions())
    assert "units" not in _sources(est)
    assert est.info["health"]["status"] != "ok", est.info["health"]


@pytest.mark.parametrize("noise_m", [0.02, 0.04])
def test_a_noisier_metric_slam_is_left_alone(noise_m):
    """A SLAM in metres 2-4x noisier than ``graph.slam_sigma_m`` (review, 2026-12-07): its
    scatter read 2.4-7.2 units per metre, and the first form of the check re-seeded it
    (figure8, 2 cm: 0.089 -> 0.33 m). Scatter alone now needs ``UNITS_NOISE_MIN_RATIO``."""
    f = simulate(
        "figure8",
        seed=0,
        options=SimOptions(duration=15.0, images=False, slam_scale=1.0, slam_noise_m=noise_m),
    )
    est = replay_online(f, FixedLagOptions())
    assert _sources(est) == ["default"]
    assert evaluate(est, f.ground_truth, alignment="se3").ate_rmse_m < 0.25


@pytest.mark.parametrize("scenario", ["figure8", "hover"])
def test_a_slam_in_metres_is_left_alone(scenario):
    """At a true scale within 0.5-2 (the simulator's default range) at the camera's rate, nothing
    is re-seeded (measured 2026-12-07 on two-turns, figure8, rectangle, hover and vertical,
    seeds 0-3, 30 Hz and 3 Hz: only the case above fired)."""
    f = simulate(scenario, seed=0, options=SimOptions(duration=12.0, images=False))
    est = replay_online(f, FixedLagOptions())
    assert _sources(est) == ["default"]


def test_fgnav_online_exits_1_on_a_diverged_estimate(tmp_path, monkeypatch, capsys):
    """Review, 2026-12-07: ``fgnav online`` exited 0 with health "diverged" (batch exits 1 when
    it does not converge). The diverging centimetre SLAM of the control above, through the
    command: one line, exit 1, the estimate written for inspection."""
    from fgnav.datasets.simulate import simulate_to_folder
    from testutil import command_cli

    folder = simulate_to_folder(
        "two-turns",
        tmp_path / "cm",
        seed=1,
        options=SimOptions(duration=20.0, images=False, slam_scale=100.0),
    )
    monkeypatch.setattr(online, "UNITS_MIN_RATIO", math.inf)
    monkeypatch.setattr(online, "UNITS_NOISE_MIN_RATIO", math.inf)
    out = tmp_path / "out"
    assert command_cli("online", folder, out) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("fgnav online: error: ") and "diverged" in err
    assert (out / "summary.json").exists()
