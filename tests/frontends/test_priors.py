"""Front-end priors: built from each front-end's result, checked, merged."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from frontends.test_attitude_ekf import _synthetic_flight
from frontends.test_ii_observer import K_TRUE, paper_flight

from fgnav.estimate import TimeSeries
from fgnav.frontends.attitude_ekf import run_attitude_ekf
from fgnav.frontends.ii_observer import IIObserverOptions, run_ii_observer
from fgnav.frontends.priors import (
    FrontendPriors,
    combine_priors,
    priors_from_attitude_ekf,
    priors_from_observer,
    priors_from_scale,
)
from fgnav.frontends.scale_ml import ScaleResult


def test_observer_priors_match_truth_after_settling():
    flight, body_v, world_v, _ = paper_flight(duration=15.0)
    res = run_ii_observer(flight, IIObserverOptions(kinematics="full"), world_vz=world_v[:, 2])
    p = priors_from_observer(res, velocity_sigma=0.15, settle_time=5.0, stride=10)
    assert p.velocity.t[0] >= 5.0 and len(p.velocity.t) == np.sum(res.t[::10] >= 5.0)
    rows = np.searchsorted(res.t, p.velocity.t)
    np.testing.assert_allclose(p.velocity.value, world_v[rows], atol=1e-3)
    np.testing.assert_allclose(p.body_velocity_xy.value, body_v[rows, :2], atol=1e-3)
    assert np.all(p.velocity.sigma == 0.15)
    assert p.slam_scale[0] == pytest.approx(K_TRUE.mean(), rel=1e-3)
    # kx and ky differ: the single-scale sigma is widened to half their gap.
    assert p.slam_scale_sigma[0] == pytest.approx(0.5 * (K_TRUE[0] - K_TRUE[1]), rel=1e-2)
    np.testing.assert_allclose(p.slam_axis_scale[0], K_TRUE, rtol=1e-3)


def test_attitude_priors_carry_ekf_sigma_and_height():
    flight, q_true, h_true = _synthetic_flight(seed=4, duration=6.0)
    res = run_attitude_ekf(flight)
    p = priors_from_attitude_ekf(res, stride=20)
    assert len(p.attitude) == len(res.t[::20])
    assert p.attitude_sigma.shape == (len(p.attitude), 3)
    # Sigma shrinks from the initial 0.1-per-component to well under a degree.
    assert p.attitude_sigma[0].max() > 5 * p.attitude_sigma[-1].max()
    assert np.rad2deg(p.attitude_sigma[-1].max()) < 1.0
    ok = p.height.t > 2.0
    idx = np.searchsorted(res.t, p.height.t[ok])
    assert np.abs(p.height.value[ok] - h_true[idx]).max() < 0.1


def test_scale_priors_and_merge_keep_the_tighter_scale():
    ml = ScaleResult(
        scale={0: 0.26, 1: 1.5},
        sigma={0: 0.002, 1: 0.05},
        history={0: np.zeros((10, 4)), 1: np.zeros((2, 4))},
        counts={0: {}, 1: {}},
    )
    p_ml = priors_from_scale(ml, min_pairs=3)
    assert p_ml.slam_scale == {0: 0.26}  # session 1 has too few pairs
    p_obs = FrontendPriors(
        slam_scale={0: 0.25, 2: 0.9},
        slam_scale_sigma={0: 0.02, 2: 0.1},
        velocity=TimeSeries(t=np.arange(3.0), value=np.zeros((3, 3)), sigma=np.ones((3, 3))),
        sources={"slam_scale": "obs"},
    )
    merged = combine_priors(p_obs, p_ml)
    assert merged.slam_scale == {0: 0.26, 2: 0.9}
    assert merged.slam_scale_sigma == {0: 0.002, 2: 0.1}
    assert merged.velocity is p_obs.velocity
    assert merged.sources["slam_scale[0]"].startswith("ml-scale")


def test_bad_priors_are_rejected_with_the_field_name():
    with pytest.raises(FlightDataError, match="slam_scale\\[3\\]"):
        FrontendPriors(slam_scale={3: -1.0}).check()
    with pytest.raises(FlightDataError, match="velocity"):
        FrontendPriors(velocity=TimeSeries(t=np.arange(2.0), value=np.zeros((2, 2)))).check()
