"""Alignment and time association against known transforms."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.geometry import (
    matrix_to_quat_wxyz,
    quat_wxyz_to_matrix,
    rpy_to_matrix,
    so3_exp,
    so3_log,
)
from fgnav.datasets.types import Trajectory

from fgnav.eval.align import (
    Alignment,
    align,
    associate,
    interpolate_trajectory,
    slerp_wxyz,
    umeyama,
)


def _transform(traj: Trajectory, R: np.ndarray, t: np.ndarray, s: float) -> Trajectory:
    """The trajectory seen from a world frame ``est_world = (gt_world -> s R x + t)^-1``."""
    inv = Alignment(R, t, s, "sim3")
    xyz = (traj.world_t_body - t) @ R / s
    Rb = np.einsum("ji,njk->nik", R, traj.world_R_body())
    assert np.allclose(inv.apply_positions(xyz), traj.world_t_body)
    return Trajectory(
        t=traj.t,
        world_t_body=xyz,
        world_q_body_wxyz=matrix_to_quat_wxyz(Rb),
        world_v_body=traj.world_v_body @ R / s,
    )


@pytest.mark.parametrize("mode", ["se3", "sim3"])
def test_umeyama_recovers_known_transform_exactly(truth, mode):
    R = rpy_to_matrix(0.3, -0.2, 1.1)
    t = np.array([4.0, -2.0, 0.5])
    s = 0.37 if mode == "sim3" else 1.0
    est = _transform(truth, R, t, s)
    al = align(est.world_t_body, truth.world_t_body, mode)
    assert al.mode == mode
    np.testing.assert_allclose(al.R, R, atol=1e-10)
    np.testing.assert_allclose(al.t, t, atol=1e-9)
    assert al.s == pytest.approx(s, rel=1e-10)
    back = al.apply(est)
    np.testing.assert_allclose(back.world_t_body, truth.world_t_body, atol=1e-9)
    np.testing.assert_allclose(back.world_R_body(), truth.world_R_body(), atol=1e-9)
    np.testing.assert_allclose(back.world_v_body, truth.world_v_body, atol=1e-9)


def test_se3_does_not_absorb_scale(truth):
    est = _transform(truth, np.eye(3), np.zeros(3), 0.5)
    al = align(est.world_t_body, truth.world_t_body, "se3")
    assert al.s == 1.0
    err = np.linalg.norm(al.apply_positions(est.world_t_body) - truth.world_t_body, axis=1)
    # Half-size copy: the residual is about half the spread of the positions around their mean.
    assert err.mean() > 2.0


def test_4dof_recovers_yaw_and_translation(truth):
    R = rpy_to_matrix(0.0, 0.0, -2.5)
    t = np.array([1.0, 2.0, -3.0])
    est = _transform(truth, R, t, 1.0)
    al = align(est.world_t_body, truth.world_t_body, "4dof")
    np.testing.assert_allclose(al.R, R, atol=1e-12)
    np.testing.assert_allclose(al.t, t, atol=1e-10)


def test_4dof_keeps_roll_pitch_errors(truth):
    """A world tilted by 0.1 rad: SE(3) removes it, 4-DoF must not (only yaw + translation)."""
    tilt = rpy_to_matrix(0.1, 0.0, 0.4)
    est = _transform(truth, tilt, np.array([0.5, 0.0, 0.0]), 1.0)
    se3 = align(est.world_t_body, truth.world_t_body, "se3")
    dof4 = align(est.world_t_body, truth.world_t_body, "4dof")
    e_se3 = np.linalg.norm(se3.apply_positions(est.world_t_body) - truth.world_t_body, axis=1)
    e_4 = np.linalg.norm(dof4.apply_positions(est.world_t_body) - truth.world_t_body, axis=1)
    assert e_se3.max() < 1e-9
    # The 6 m (y) half-amplitude tilted by 0.1 rad gives about 0.6 m vertical error at the ends.
    assert 0.2 < np.sqrt(np.mean(e_4**2)) < 1.0
    assert np.allclose(dof4.R[2], [0.0, 0.0, 1.0])
    # Orientations keep their roll error: angle between aligned and true rotations ~ 0.1 rad.
    Ra = dof4.apply_rotations(est.world_R_body())
    ang = [np.linalg.norm(so3_log(a.T @ b)) for a, b in zip(Ra, truth.world_R_body(), strict=True)]
    assert np.median(ang) == pytest.approx(0.1, abs=0.02)


def test_none_is_identity(truth):
    al = align(truth.world_t_body, truth.world_t_body + 1.0, "none")
    assert al.mode == "none" and al.s == 1.0
    np.testing.assert_array_equal(al.R, np.eye(3))


def test_bad_inputs_raise_clear_errors(truth):
    with pytest.raises(FlightDataError, match="unknown mode"):
        align(truth.world_t_body, truth.world_t_body, "sim4")
    line = np.outer(np.arange(10.0), [1.0, 2.0, 3.0])
    with pytest.raises(FlightDataError, match="degenerate"):
        umeyama(line, line, with_scale=False)
    with pytest.raises(FlightDataError, match="equal shape"):
        align(truth.world_t_body, truth.world_t_body[:-1], "se3")


def test_slerp_halfway_about_z():
    q0 = matrix_to_quat_wxyz(np.eye(3))[None]
    q1 = matrix_to_quat_wxyz(so3_exp([0.0, 0.0, 1.2]))[None]
    q = slerp_wxyz(q0, q1, np.array([0.25]))
    np.testing.assert_allclose(quat_wxyz_to_matrix(q[0]), so3_exp([0, 0, 0.3]), atol=1e-12)
    # Sign-flipped q1 (same rotation) gives the same result (shortest arc).
    q = slerp_wxyz(q0, -q1, np.array([0.25]))
    np.testing.assert_allclose(quat_wxyz_to_matrix(q[0]), so3_exp([0, 0, 0.3]), atol=1e-12)


def test_interpolation_linear_and_slerp(truth):
    t = 0.5 * (truth.t[10:20] + truth.t[11:21])
    g = interpolate_trajectory(truth, t)
    np.testing.assert_allclose(
        g.world_t_body, 0.5 * (truth.world_t_body[10:20] + truth.world_t_body[11:21]), atol=1e-12
    )
    R0, R1, Rm = truth.world_R_body()[10:20], truth.world_R_body()[11:21], g.world_R_body()
    for a, b, m in zip(R0, R1, Rm, strict=True):
        np.testing.assert_allclose(a @ so3_exp(0.5 * so3_log(a.T @ b)), m, atol=1e-12)
    with pytest.raises(FlightDataError, match="leave the span"):
        interpolate_trajectory(truth, truth.t[-1:] + 1.0)


def test_associate_counts_unmatched(truth):
    # Truth with a 1 s hole; estimate at 10 Hz starting 2 s before and ending 3 s after the truth.
    keep = (truth.t < 1020.0) | (truth.t > 1021.0)
    gt = truth.select(keep)
    t_est = np.arange(truth.t[0] - 2.0, truth.t[-1] + 3.0, 0.1) + 0.013
    est = interpolate_trajectory(truth, np.clip(t_est, truth.t[0], truth.t[-1]))
    est = Trajectory(t_est, est.world_t_body, est.world_q_body_wxyz)
    a = associate(est, gt, max_gap_s=0.1)
    assert a.n_before == 20
    assert a.n_after == int(np.sum(t_est > truth.t[-1]))
    hole = (gt.t[gt.t < 1020.0][-1], gt.t[gt.t > 1021.0][0])  # (1019.95, 1021.05)
    assert a.n_gap == int(np.sum((t_est > hole[0]) & (t_est < hole[1]))) == 11
    assert a.n_matched + a.n_unmatched == len(est)
    np.testing.assert_allclose(a.gt.t, est.t[a.est_index])
    # Interpolated truth matches the truth curve to second order (20 Hz samples, 2 m/s).
    assert np.abs(a.gt.world_t_body - est.world_t_body[a.est_index]).max() < 1e-2
    with pytest.raises(FlightDataError, match="same clock"):
        associate(Trajectory(est.t + 1e4, est.world_t_body, est.world_q_body_wxyz), gt)


def test_unmatched_samples_warn_only_in_truth_gaps(truth, caplog):
    """Estimate samples before or after the truth's span are common (a mocap started late):
    said at INFO; samples in a truth gap are a WARNING."""
    t_est = np.arange(truth.t[0] - 1.0, truth.t[-1], 0.1) + 0.013
    est = interpolate_trajectory(truth, np.clip(t_est, truth.t[0], truth.t[-1]))
    est = Trajectory(t_est, est.world_t_body, est.world_q_body_wxyz)
    with caplog.at_level("INFO", logger="fgnav.eval.align"):
        associate(est, truth, max_gap_s=0.1)
    (rec,) = [r for r in caplog.records if "unmatched" in r.getMessage()]
    assert rec.levelname == "INFO" and "10 before the truth" in rec.getMessage()
    caplog.clear()
    holed = truth.select((truth.t < 1020.0) | (truth.t > 1021.0))
    with caplog.at_level("INFO", logger="fgnav.eval.align"):
        associate(est, holed, max_gap_s=0.1)
    (rec,) = [r for r in caplog.records if "unmatched" in r.getMessage()]
    assert rec.levelname == "WARNING" and "11 in truth gaps" in rec.getMessage()


def test_line_trajectory_falls_back_to_translation_and_says_so():
    """A purely vertical flight: the rotation about the line is undetermined."""
    from fgnav.eval.align import DEGENERATE_MODE, align

    z = np.linspace(0.0, 2.0, 50)
    gt = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    est = gt + np.array([1.0, -2.0, 0.5])
    al = align(est, gt, "se3")
    assert al.mode == DEGENERATE_MODE
    assert np.allclose(al.apply_positions(est), gt)
