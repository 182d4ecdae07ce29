"""NED/FRD and Y-up mocap conversions into fgnav's z-up world and FLU body."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.frames import (
    ENU_R_NED,
    FLU_R_FRD,
    align_rotation_sequences,
    frd_to_flu,
    ned_q_frd_to_world_q_body,
    ned_R_frd_to_world_R_body,
    ned_to_enu,
    tilt_angle,
    yup_q_to_zup_q,
    yup_to_zup,
)
from fgnav.datasets.geometry import (
    matrix_to_quat_wxyz,
    quat_wxyz_to_matrix,
    rpy_to_matrix,
    so3_exp,
    yaw_of,
)

G = 9.80665


def test_vectors_ned_frd():
    np.testing.assert_array_equal(ned_to_enu([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    np.testing.assert_array_equal(frd_to_flu([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])
    # Stacks keep their shape; the matrices agree with the functions and are proper rotations.
    v = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_allclose(ned_to_enu(v), v @ ENU_R_NED.T)
    np.testing.assert_allclose(frd_to_flu(v), v @ FLU_R_FRD.T)
    assert np.linalg.det(ENU_R_NED) == pytest.approx(1.0)
    assert np.linalg.det(FLU_R_FRD) == pytest.approx(1.0)


def test_px4_yaw_zero_is_north():
    # PX4: yaw 0 means nose north. In fgnav (x east, y north) the nose points along +y: yaw +pi/2.
    world_R_body = ned_R_frd_to_world_R_body(np.eye(3))
    assert yaw_of(world_R_body) == pytest.approx(np.pi / 2)
    np.testing.assert_allclose(world_R_body @ [1, 0, 0], [0, 1, 0], atol=1e-15)  # nose north
    np.testing.assert_allclose(world_R_body @ [0, 0, 1], [0, 0, 1], atol=1e-15)  # top up
    # PX4 yaw +90 deg is east (clockwise from above): fgnav yaw 0.
    q = ned_q_frd_to_world_q_body([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    assert yaw_of(quat_wxyz_to_matrix(q)) == pytest.approx(0.0, abs=1e-12)


def test_right_roll_frd_maps_to_flu_rotation():
    # 30 deg right roll in FRD (right wing down), nose north. In FLU the body rotates about its
    # forward axis so that the right side (-y_FLU) goes down, i.e. the left side goes up.
    roll = np.deg2rad(30.0)
    ned_R_frd = rpy_to_matrix(roll, 0.0, 0.0)
    world_R_body = ned_R_frd_to_world_R_body(ned_R_frd)
    right_wing = world_R_body @ [0, -1, 0]
    assert right_wing[2] == pytest.approx(-np.sin(roll))
    # Same as fgnav's own rotation: yaw +90 deg, then roll +30 deg about the FLU x axis.
    np.testing.assert_allclose(world_R_body, rpy_to_matrix(roll, 0.0, np.pi / 2), atol=1e-12)
    # Quaternion path equals the matrix path.
    q = ned_q_frd_to_world_q_body(matrix_to_quat_wxyz(ned_R_frd))
    np.testing.assert_allclose(quat_wxyz_to_matrix(q), world_R_body, atol=1e-12)


def test_gravity_at_rest_is_plus_g_up_after_conversion():
    # A PX4 accelerometer at rest reads -g on z (FRD, z down): specific force points up.
    frd_accel = np.array([0.0, 0.0, -G])
    np.testing.assert_allclose(frd_to_flu(frd_accel), [0.0, 0.0, G])
    # Tilted at rest: world_R_body @ f equals (0, 0, +g) for any attitude.
    ned_R_frd = rpy_to_matrix(0.3, -0.2, 1.0)
    frd_f = ned_R_frd.T @ np.array([0.0, 0.0, -G])  # specific force = -gravity_ned in body
    world_R_body = ned_R_frd_to_world_R_body(ned_R_frd)
    np.testing.assert_allclose(world_R_body @ frd_to_flu(frd_f), [0.0, 0.0, G], atol=1e-12)


def test_yup_mocap_to_zup():
    np.testing.assert_array_equal(yup_to_zup([1.0, 2.0, 3.0]), [1.0, -3.0, 2.0])
    # A rigid body rotated 90 deg about the mocap's vertical (Y) axis turns about fgnav's z.
    q_yup = [np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0]
    R = quat_wxyz_to_matrix(yup_q_to_zup_q(q_yup))
    np.testing.assert_allclose(R, rpy_to_matrix(0.0, 0.0, np.pi / 2), atol=1e-12)
    assert tilt_angle(R) == pytest.approx(0.0, abs=1e-7)


def test_align_rotation_sequences_recovers_fixed_rotations():
    rng = np.random.default_rng(3)
    a_R_b = so3_exp([0.0, 0.0, 0.7])
    y_R_x = so3_exp([0.1, -0.05, 2.0])
    b_R_y = np.stack([so3_exp(rng.normal(scale=0.6, size=3)) for _ in range(200)])
    noise = np.stack([so3_exp(rng.normal(scale=0.002, size=3)) for _ in range(200)])
    a_R_x = a_R_b @ b_R_y @ y_R_x @ noise
    est_a_R_b, est_y_R_x, resid = align_rotation_sequences(a_R_x, b_R_y)
    np.testing.assert_allclose(est_a_R_b, a_R_b, atol=2e-3)
    np.testing.assert_allclose(est_y_R_x, y_R_x, atol=2e-3)
    assert np.sqrt(np.mean(resid**2)) < 0.006


def test_align_world_yaw_only_on_single_heading_motion():
    # One heading, small tilts only: a world tilt and a body tilt trade off unless the world
    # rotation is restricted to yaw (both worlds z up).
    rng = np.random.default_rng(5)
    a_R_b = so3_exp([0.0, 0.0, -0.2])
    y_R_x = so3_exp([0.01, -0.015, 0.02])
    b_R_y = np.stack(
        [rpy_to_matrix(*rng.normal(scale=[0.03, 0.1, 0.01]) + [0.0, 0.0, 1.2]) for _ in range(300)]
    )
    a_R_x = a_R_b @ b_R_y @ y_R_x
    est_a_R_b, est_y_R_x, resid = align_rotation_sequences(a_R_x, b_R_y, world_yaw_only=True)
    np.testing.assert_allclose(est_a_R_b, a_R_b, atol=1e-6)
    np.testing.assert_allclose(est_y_R_x, y_R_x, atol=1e-6)
    assert resid.max() < 1e-6
