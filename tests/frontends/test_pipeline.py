"""Front-end priors for the smoother, against simulator truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.frontends.pipeline import frontend_priors


@pytest.fixture(scope="module")
def vertical():
    return simulate("vertical", seed=1, options=SimOptions(images=False, duration=30.0))


def test_ml_scale_prior_on_vertical_flight(vertical):
    p = frontend_priors(vertical, ["ml-scale"])
    s_true = vertical.meta["truth"]["slam_sessions"]["0"]["scale"]
    assert p.slam_scale[0] == pytest.approx(s_true, rel=0.02)
    # The stated sigma covers the error (3 sigma).
    assert abs(p.slam_scale[0] - s_true) < 3 * p.slam_scale_sigma[0] + 0.005 * s_true


def test_observer_gives_velocity_priors_only(vertical):
    fl = dataclasses.replace(
        vertical, meta={**vertical.meta, "drag_k": vertical.meta["truth"]["drag_k"]}
    )
    p = frontend_priors(fl, ["observer"])
    assert p.slam_scale == {}
    v = p.velocity
    gt = fl.ground_truth
    idx = np.clip(np.searchsorted(gt.t, v.t), 0, len(gt) - 1)
    # Horizontal velocity of the observer (after its settle time) within its stated sigma.
    err = np.linalg.norm(v.value[:, :2] - gt.world_v_body[idx, :2], axis=1)
    assert np.sqrt(np.mean(err**2)) < float(v.sigma[0, 0])


def test_bad_requests_are_named(vertical):
    with pytest.raises(FlightDataError, match="unknown front-end prior"):
        frontend_priors(vertical, ["magic"])
    with pytest.raises(FlightDataError, match="needs the range stream"):
        frontend_priors(dataclasses.replace(vertical, range=None), ["ml-scale"])
    with pytest.raises(FlightDataError, match="calibrated drag coefficient"):
        frontend_priors(vertical, ["observer"])
    assert frontend_priors(vertical, []) is None
