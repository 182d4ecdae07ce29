"""The numerical-Jacobian helper itself: it must catch a wrong Jacobian and a wrong shape."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from fgnav.keys import X

from .numdiff import assert_jacobians_close, unit_noise


def _translation_factor(jacobian_scale: float) -> gtsam.CustomFactor:
    """e = world_t_body; true Jacobian [0, R]; ``jacobian_scale`` != 1 makes it wrong."""

    def error_fn(this, values, H):
        pose = values.atPose3(X(0))
        if H is not None:
            H[0] = np.hstack([np.zeros((3, 3)), jacobian_scale * pose.rotation().matrix()])
        return pose.translation()

    return gtsam.CustomFactor(unit_noise(3), [X(0)], error_fn)


def test_helper_accepts_a_correct_and_rejects_a_wrong_jacobian() -> None:
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.2, 0.1), np.array([1.0, 2.0, 3.0])))
    assert_jacobians_close(_translation_factor(1.0), values, [6])
    with pytest.raises(AssertionError, match="analytic - numeric"):
        assert_jacobians_close(_translation_factor(1.0 + 1e-4), values, [6])
    with pytest.raises(AssertionError, match="columns"):
        assert_jacobians_close(_translation_factor(1.0), values, [7])
