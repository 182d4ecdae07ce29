"""Tests of the pycolmap monocular SLAM source on a short simulated downward-camera sequence."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.geometry import quat_wxyz_to_matrix
from fgnav.datasets.simulate import SimOptions, simulate
from fgnav.datasets.types import ImageSeries

from fgnav.frontends.colmap_slam import (
    IMAGE_NAME,
    ColmapSlamOptions,
    _to_slam_series,
    reconstruct,
    slam_from_flight,
)

#: Frames reconstructed: every 4th 20 Hz image of the first 4 s of the circle flight (5 Hz),
#: about 0.2 m apart at 1.5 m height, 70-80 % overlap.
FRAME_STEP = 4
NUM_FRAMES = 20


def umeyama_sim3(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``dst ~ s R src + t`` (Umeyama 1991), for (N, 3) point sets."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(axis=1).mean())
    return s, R, mu_d - s * R @ mu_s


@pytest.fixture(scope="module")
def flight():
    return simulate(
        "circle",
        seed=4,
        options=SimOptions(duration=NUM_FRAMES * FRAME_STEP / 20.0, slam_rate_hz=0.0),
    )


@pytest.mark.slow
def test_reconstruction_matches_truth_after_sim3(flight):
    images = flight.images.select(np.arange(0, NUM_FRAMES * FRAME_STEP, FRAME_STEP))
    res = reconstruct(images, ColmapSlamOptions(max_num_features=512))
    assert res.num_images == NUM_FRAMES
    assert res.num_registered == NUM_FRAMES, f"unregistered {res.unregistered}"
    assert res.model_sizes == {0: NUM_FRAMES}
    slam = res.slam
    slam.check()
    np.testing.assert_array_equal(slam.t, images.t)
    # Truth camera poses at the image times.
    gt = flight.ground_truth
    k = np.searchsorted(gt.t, slam.t)
    world_R_body = gt.world_R_body()[k]
    body_T_cam = flight.calib.body_T_cam
    world_t_cam = gt.world_t_body[k] + world_R_body @ body_T_cam[:3, 3]
    world_R_cam = world_R_body @ body_T_cam[:3, :3]
    s, R, t = umeyama_sim3(slam.slam_t_cam, world_t_cam)
    err = np.linalg.norm((s * slam.slam_t_cam @ R.T + t) - world_t_cam, axis=1)
    path = np.sum(np.linalg.norm(np.diff(world_t_cam, axis=0), axis=1))
    # Measured: RMS 0.7 mm (max 1.5 mm) over a 2.35 m path. The 5 mm bound fails on a wrong pose
    # convention (cam_from_world translation taken as the camera centre gives decimetres).
    assert path > 2.0
    assert np.sqrt(np.mean(err**2)) < 0.005
    # Orientations: world_R_cam = R slam_R_cam within 0.2 degrees.
    slam_R_cam = quat_wxyz_to_matrix(slam.slam_q_cam_wxyz)
    d = np.einsum("nji,njk->nik", world_R_cam, R @ slam_R_cam)
    angle = np.degrees(np.arccos(np.clip((np.trace(d, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angle.max() < 0.2


@pytest.mark.slow
def test_unregistered_frames_are_reported(flight):
    """Blank frames cannot be registered: they are listed, and the rest is reconstructed."""
    idx = np.arange(0, 12 * FRAME_STEP, FRAME_STEP)
    frames = flight.images.frames[idx].copy()
    frames[[5, 6]] = 128
    images = ImageSeries(t=flight.images.t[idx], frames=frames, camera=flight.images.camera)
    res = slam_from_flight(
        dataclasses.replace(flight, images=images), ColmapSlamOptions(max_num_features=512)
    )
    assert res.num_images == 12
    assert set(res.unregistered.tolist()) >= {5, 6}
    assert res.num_registered == len(res.slam) == 12 - len(res.unregistered)
    assert sum(res.model_sizes.values()) == res.num_registered
    assert not np.isin(images.t[[5, 6]], res.slam.t).any()


def _stub_model(indices, scale):
    """A stand-in for a pycolmap Reconstruction: camera k at slam position (k * scale, 0, 0)."""
    from types import SimpleNamespace

    images = {}
    for k in indices:
        rotation = SimpleNamespace(matrix=lambda: np.eye(3))
        pose = SimpleNamespace(rotation=rotation, translation=np.array([-k * scale, 0.0, 0.0]))
        images[k] = SimpleNamespace(
            name=IMAGE_NAME.format(k), has_pose=True, cam_from_world=lambda p=pose: p
        )
    n = len(images)
    return SimpleNamespace(images=images, num_reg_images=lambda: n)


def test_models_become_time_ordered_sessions_without_duplicates():
    """Model 0 (the mapper's first) covers late frames, model 1 early ones, and they overlap on
    frames 4-5: sessions are numbered by time, each frame appears once (in the larger model)."""
    models = {0: _stub_model(range(4, 12), 2.0), 1: _stub_model(range(0, 6), 0.5)}
    t = np.arange(14) * 0.1
    slam, sizes, registered = _to_slam_series(models, t, 14)
    np.testing.assert_array_equal(registered, np.arange(14) < 12)
    np.testing.assert_array_equal(slam.t, t[:12])
    np.testing.assert_array_equal(slam.session, [0] * 4 + [1] * 8)
    assert sizes == {0: 4, 1: 8}
    np.testing.assert_allclose(
        slam.slam_t_cam[:, 0], [0, 0.5, 1, 1.5] + [8, 10, 12, 14, 16, 18, 20, 22]
    )
