"""The one home of rotation helpers: batched exp/log, interpolation, means, Euler angles."""

import numpy as np
import pytest
from fgnav.datasets.geometry import (
    interpolate_quat_wxyz,
    matrix_to_quat_wxyz,
    matrix_to_rpy,
    quat_wxyz_to_matrix,
    rotation_mean,
    rpy_to_matrix,
    slerp_rotations,
    slerp_wxyz,
    so3_exp,
    so3_log,
)


@pytest.mark.parametrize("scale", [1e-9, 1e-5, 1e-3, 0.5, 3.0])
def test_exp_log_round_trip_batched_and_single(scale):
    rng = np.random.default_rng(0)
    phi = rng.normal(size=(50, 3))
    phi *= scale / np.linalg.norm(phi, axis=1, keepdims=True)
    R = so3_exp(phi)
    assert R.shape == (50, 3, 3)
    np.testing.assert_allclose(
        R @ np.transpose(R, (0, 2, 1)), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(so3_log(R), phi, atol=1e-12, rtol=1e-9)
    np.testing.assert_allclose(so3_exp(phi[3]), R[3], atol=1e-15)
    np.testing.assert_allclose(so3_log(R[3]), phi[3], atol=1e-12, rtol=1e-9)


def test_log_near_pi():
    phi = np.array([0.0, 0.0, np.pi - 1e-8])
    np.testing.assert_allclose(np.abs(so3_log(so3_exp(phi))), np.abs(phi), atol=1e-6)


def test_rpy_round_trip_and_broadcast():
    rng = np.random.default_rng(1)
    rpy = rng.uniform([-3, -1.4, -3], [3, 1.4, 3], size=(20, 3))
    R = rpy_to_matrix(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    np.testing.assert_allclose(matrix_to_rpy(R), rpy, atol=1e-12)
    np.testing.assert_allclose(rpy_to_matrix(*rpy[0]), R[0], atol=1e-15)


def test_interpolations_agree_on_geodesics():
    rng = np.random.default_rng(2)
    R0 = so3_exp(rng.normal(size=3))
    w = np.array([0.3, -0.2, 0.5])
    t = np.array([0.0, 1.0])
    Rs = np.stack([R0, R0 @ so3_exp(w)])
    tq = np.array([0.25, 0.5, 0.9])
    expected = np.stack([R0 @ so3_exp(a * w) for a in tq])
    np.testing.assert_allclose(slerp_rotations(t, Rs, tq), expected, atol=1e-12)
    q = matrix_to_quat_wxyz(Rs)
    qs = slerp_wxyz(np.repeat(q[:1], 3, 0), np.repeat(q[1:], 3, 0), tq)
    np.testing.assert_allclose(quat_wxyz_to_matrix(qs), expected, atol=1e-12)
    # normalised linear interpolation: close to the geodesic for small steps
    qn = interpolate_quat_wxyz(t, q, tq)
    assert np.abs(quat_wxyz_to_matrix(qn) - expected).max() < 2e-3


def test_rotation_mean_of_symmetric_spread_is_centre():
    rng = np.random.default_rng(3)
    R0 = so3_exp(rng.normal(size=3))
    d = rng.normal(scale=0.05, size=(10, 3))
    Rs = np.concatenate([R0 @ so3_exp(d), R0 @ so3_exp(-d)])
    np.testing.assert_allclose(rotation_mean(Rs), R0, atol=1e-3)


def test_velocity_from_quantised_irregular_positions():
    from fgnav.datasets.geometry import velocity_from_positions

    rng = np.random.default_rng(0)
    # ~276 Hz with jitter and a 45 ms gap, positions quantised to 1 mm (Vicon-like).
    t = np.cumsum(rng.uniform(0.002, 0.0052, 3000))
    t = np.concatenate([t[:1500], t[1500:] + 0.045])
    p_true = np.column_stack([np.sin(1.3 * t), 0.5 * t**2 / t[-1], 0.2 * np.cos(2.0 * t)])
    v_true = np.column_stack([1.3 * np.cos(1.3 * t), t / t[-1], -0.4 * np.sin(2.0 * t)])
    p = np.round(p_true, 3)
    v = velocity_from_positions(t, p)
    inner = (t > t[0] + 0.1) & (t < t[-1] - 0.1)
    err = v[inner] - v_true[inner]
    assert np.sqrt(np.mean(err**2)) < 0.01  # a plain finite difference: ~0.2 m/s
    fd = np.gradient(p, t, axis=0)[inner] - v_true[inner]
    assert np.sqrt(np.mean(fd**2)) > 10 * np.sqrt(np.mean(err**2))


def test_velocity_from_positions_does_not_resample_across_a_clock_jump():
    """Pieces between gaps over a second are differentiated apart: a log with its clock jumping
    by 1e6 s made the resampling grid 15 GB (review 2026-12-07)."""
    from fgnav.datasets.geometry import velocity_from_positions

    t0 = np.arange(0.0, 5.0, 0.004)
    t = np.r_[t0, 1e6 + t0]
    p = np.c_[np.r_[t0, 2.0 * t0], np.zeros(t.size)]
    v = velocity_from_positions(t, p)
    assert v.shape == p.shape
    np.testing.assert_allclose(v[100:1100, 0], 1.0, atol=1e-6)
    np.testing.assert_allclose(v[1350:2350, 0], 2.0, atol=1e-6)


def test_one_quaternion_matrix_is_the_batched_one_bit_for_bit():
    """The single-quaternion path (plain floats, the norm's four squares summed in order) gives
    the same bits as the batched numpy path, normalisation included (the push engine's outputs
    are compared byte for byte across such rewrites)."""
    rng = np.random.default_rng(3)
    q = rng.normal(size=(2000, 4)) * 10.0 ** rng.integers(-3, 4, size=(2000, 1))
    q[::3] /= np.linalg.norm(q[::3], axis=1, keepdims=True)
    batched = quat_wxyz_to_matrix(q)
    single = np.array([quat_wxyz_to_matrix(x) for x in q])
    assert single.tobytes() == batched.tobytes()
    with pytest.raises(ValueError):
        quat_wxyz_to_matrix(np.zeros(4))
