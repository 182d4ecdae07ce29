"""Rendered downward-camera images: exact plane homographies that OpenCV can register."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from fgnav.datasets.geometry import invert_pose, make_pose, rpy_to_matrix
from fgnav.datasets.simulate import SimOptions, SimulationError, simulate, world_T_cam_at
from fgnav.datasets.simulate.render import (
    PATCH_GREY,
    Carpet,
    ground_homography,
    inter_frame_homography,
    pinhole_from_fov,
)
from fgnav.datasets.simulate.simulator import BODY_R_CAM


@pytest.fixture(scope="module")
def turning_flight():
    """10 s of two-turns (the turn starts at 3 s): images at 20 Hz with pixel noise."""
    return simulate("two-turns", seed=11, options=SimOptions(duration=10.0))


def _corners(w, h):
    return np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)


def _transfer(H, pts):
    p = np.c_[pts, np.ones(len(pts))] @ H.T
    return p[:, :2] / p[:, 2:]


def _register(img_i, img_j):
    """Shi-Tomasi + pyramidal Lucas-Kanade + RANSAC homography (seed 002, Algorithm 1)."""
    p0 = cv2.goodFeaturesToTrack(img_i, maxCorners=400, qualityLevel=0.01, minDistance=7)
    p1, status, _ = cv2.calcOpticalFlowPyrLK(img_i, img_j, p0, None, winSize=(21, 21), maxLevel=3)
    ok = status.ravel() == 1
    H, inliers = cv2.findHomography(p0[ok], p1[ok], cv2.RANSAC, 1.0)
    return H, int(inliers.sum())


@pytest.mark.parametrize("gap", [1, 3])
def test_rendered_pair_registers_to_the_true_homography(turning_flight, gap):
    f = turning_flight
    cam = f.images.camera
    i = int(np.flatnonzero(np.isclose(f.images.t, 9.0))[0])
    j = i + gap
    world_T_cam = world_T_cam_at(f, f.images.t[[i, j]])
    H_true = inter_frame_homography(
        world_T_cam[0], world_T_cam[1], cam.K, f.meta["truth"]["ground_height"]
    )
    H_meas, n_inliers = _register(f.images.frames[i], f.images.frames[j])
    corners = _corners(cam.width, cam.height)
    err = np.linalg.norm(_transfer(H_meas, corners) - _transfer(H_true, corners), axis=1)
    motion = np.linalg.norm(_transfer(H_true, corners) - corners, axis=1)
    assert n_inliers > 100
    assert motion.max() > 2.0 * gap  # the camera really moved between the frames
    assert err.max() < 1.0, (err, motion)


def test_plane_homography_projects_ground_points_like_the_pinhole():
    rng = np.random.default_rng(4)
    K = np.array([[250.0, 0.0, 159.5], [0.0, 250.0, 119.5], [0.0, 0.0, 1.0]])
    world_T_body = make_pose(rpy_to_matrix(0.2, -0.1, 1.0), np.array([0.3, -0.4, 2.5]))
    world_T_cam = world_T_body @ make_pose(BODY_R_CAM, np.array([0.05, 0.0, -0.04]))
    ground = 0.3
    texel = np.array([[0.01, 0.0, -5.0], [0.0, 0.01, -6.0], [0.0, 0.0, 1.0]])
    uv = rng.uniform(0, 1000, (20, 2))
    H = ground_homography(world_T_cam, K, ground, texel)
    xy = _transfer(texel, uv)
    P = np.c_[xy, np.full(len(xy), ground)]
    cam_T_world = invert_pose(world_T_cam)
    pc = P @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
    expected = (pc / pc[:, 2:]) @ K.T
    np.testing.assert_allclose(_transfer(H, uv), expected[:, :2], atol=1e-9)


def test_camera_convention_image_up_is_body_forward():
    """Image up = body forward, image right = body right (FLU: -y)."""
    K = np.array([[250.0, 0.0, 159.5], [0.0, 250.0, 119.5], [0.0, 0.0, 1.0]])
    world_T_cam = make_pose(rpy_to_matrix(0.0, 0.0, 0.0), np.array([0.0, 0.0, 2.0])) @ make_pose(
        BODY_R_CAM, np.zeros(3)
    )
    texel = np.eye(3)
    H = ground_homography(world_T_cam, K, 0.0, texel)
    forward, right = _transfer(H, np.array([[1.0, 0.0], [0.0, -1.0]]))
    assert forward[1] < 119.5 and abs(forward[0] - 159.5) < 1e-9
    assert right[0] > 159.5 and abs(right[1] - 119.5) < 1e-9


def test_carpet_is_textured_everywhere_and_patches_are_featureless():
    rng = np.random.default_rng(0)
    carpet = Carpet.make(
        np.array([-2.0, -2.0]), np.array([2.0, 2.0]), 0.0, 0.01, rng, featureless_patches=0
    )
    K = np.array([[256.0, 0.0, 159.5], [0.0, 256.0, 119.5], [0.0, 0.0, 1.0]])
    world_T_cam = make_pose(BODY_R_CAM, np.array([0.0, 0.0, 1.5]))
    img = carpet.render(world_T_cam, K, 320, 240)
    assert 30.0 < img.std() < 70.0
    corners = cv2.goodFeaturesToTrack(np.clip(img, 0, 255).astype(np.uint8), 500, 0.01, 7)
    assert len(corners) > 200
    patched = Carpet.make(
        np.array([-2.0, -2.0]),
        np.array([2.0, 2.0]),
        0.0,
        0.01,
        np.random.default_rng(0),
        featureless_patches=6,
    )
    flat = np.abs(patched.levels[0] - PATCH_GREY) < 1.0
    assert flat.mean() > 0.05  # several square metres of uniform white


def test_motion_blur_and_brightness_options_change_the_images():
    base = SimOptions(duration=5.0, image_rate_hz=10.0, noise_free=True)
    sharp = simulate("figure8", seed=2, options=base)
    blurred = simulate(
        "figure8",
        seed=2,
        options=SimOptions(duration=5.0, image_rate_hz=10.0, noise_free=True, motion_blur_s=0.03),
    )
    bright = simulate(
        "figure8",
        seed=2,
        options=SimOptions(
            duration=5.0,
            image_rate_hz=10.0,
            noise_free=True,
            brightness_amplitude=0.3,
            brightness_period_s=8.0,
        ),
    )

    def sharpness(img):
        return cv2.Laplacian(img.astype(np.float32), cv2.CV_32F).var()

    k = -1  # moving at ~2.5 m/s
    assert sharpness(blurred.images.frames[k]) < 0.7 * sharpness(sharp.images.frames[k])
    ratio = bright.images.frames.mean(axis=(1, 2)) / sharp.images.frames.mean(axis=(1, 2))
    expected = 1.0 + 0.3 * np.sin(2.0 * math.pi * sharp.images.t / 8.0)
    np.testing.assert_allclose(ratio, expected, atol=0.03)


def test_intrinsics_follow_the_field_of_view():
    fx, fy, cx, cy = pinhole_from_fov(320, 240, 64.0)
    assert fx == fy and abs(2.0 * math.degrees(math.atan(160.0 / fx)) - 64.0) < 1e-9
    assert (cx, cy) == (159.5, 119.5)


def test_inter_frame_homography_rejects_a_camera_below_the_ground():
    K = np.eye(3)
    below = make_pose(BODY_R_CAM, np.array([0.0, 0.0, -1.0]))
    with pytest.raises(SimulationError, match="not above the ground"):
        inter_frame_homography(below, below, K, 0.0)


def test_world_T_cam_at_rejects_times_off_the_grid(turning_flight):
    with pytest.raises(SimulationError, match="not a ground-truth sample time"):
        world_T_cam_at(turning_flight, [0.0123])
