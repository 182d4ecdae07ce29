"""Downward-camera images of a textured ground plane, rendered exactly as plane homographies.

The ground is the plane ``z = ground_height`` (world, z up) covered by a seeded random-noise
"carpet" (seed 002, sec. IV-A: views of a large noise image). A carpet texel ``(u, v)`` (column,
row) sits at ground point ``(x0 + u * res, y0 + v * res, ground_height)``: the 3x3 map
``world_xy1_from_texel = [[res, 0, x0], [0, res, y0], [0, 0, 1]]``.

A ground point ``P = (X, Y, z_g)`` is seen by a pinhole camera ``world_T_cam = (R, c)`` with
intrinsics ``K`` at ``K cam_R_world (P - c) = K [m1 m2 m3 z_g - cam_R_world c] (X, Y, 1)`` where
``m_i`` are the columns of ``cam_R_world = R^T``; so image <- texel is the homography

    H = K [m1, m2, z_g m3 - R^T c] world_xy1_from_texel

and ``cv2.warpPerspective(texture, H, (W, H))`` renders the image (bilinear sampling of a
band-limited texture; a texture pyramid level is picked from the ground footprint of a pixel so
that the texture is never under-sampled). Pixel ``(u, v)`` of an image is the pixel centre, as in
OpenCV, so ``K`` uses ``cx = (W - 1) / 2`` for a centred principal point.

Between two cameras i and j looking at the plane, pixels map by
``H_ji = K (R + t n^T / d) K^-1`` with ``(R, t) = cam_j_T_cam_i``, ``n`` the unit plane normal in
cam i pointing away from the camera (towards the ground) and ``d`` the distance of camera i to
the plane (:func:`inter_frame_homography`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from fgnav.datasets.geometry import invert_pose

from .options import SimulationError

log = logging.getLogger(__name__)

#: Blob scales of the carpet [m] and their weights: fine grain to trackable corners at 1-4 m of
#: height with a 64-degree 320-pixel camera (1 pixel ~ 4-16 mm) plus coarse shading.
CARPET_SCALES_M = (0.03, 0.1, 0.3, 1.0)
CARPET_WEIGHTS = (1.0, 0.8, 0.6, 0.4)
#: Grey-level mean and standard deviation of the carpet.
CARPET_MEAN = 128.0
CARPET_STD = 45.0
#: Grey level of the featureless patches (seed 003's white walls) and their size range [m].
PATCH_GREY = 235.0
PATCH_SIZE_M = (0.5, 1.5)
#: Largest carpet side [texels]; the texel grows beyond it.
MAX_TEXTURE_SIDE = 8192
#: Number of pyramid levels kept.
PYRAMID_LEVELS = 5
#: Margin added around the area seen by the camera [m].
FOOTPRINT_MARGIN_M = 0.5


def pinhole_from_fov(width: int, height: int, hfov_deg: float) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` [px] of a centred square-pixel pinhole with horizontal FOV [deg]."""
    fx = 0.5 * width / math.tan(math.radians(hfov_deg) / 2.0)
    return fx, fx, (width - 1) / 2.0, (height - 1) / 2.0


def ground_homography(
    world_T_cam: np.ndarray, K: np.ndarray, ground_height: float, world_xy1_from_texel: np.ndarray
) -> np.ndarray:
    """3x3 homography image pixel <- texel (see the module docstring)."""
    R = world_T_cam[:3, :3]
    c = world_T_cam[:3, 3]
    M = R.T
    P = np.column_stack([M[:, 0], M[:, 1], ground_height * M[:, 2] - M @ c])
    return K @ P @ world_xy1_from_texel


def inter_frame_homography(
    world_T_cam_i: np.ndarray, world_T_cam_j: np.ndarray, K: np.ndarray, ground_height: float
) -> np.ndarray:
    """Homography mapping pixels of image i to image j for the plane ``z = ground_height``.

    ``H = K (R + t n^T / d) K^-1`` with ``(R, t) = cam_j_T_cam_i``, ``n = -cam_i_R_world e3``
    (world down in cam i) and ``d`` the height of camera i above the plane [m]. Normalised so
    that ``H[2, 2] = 1``.
    """
    cam_j_T_cam_i = invert_pose(world_T_cam_j) @ world_T_cam_i
    R = cam_j_T_cam_i[:3, :3]
    t = cam_j_T_cam_i[:3, 3]
    n = -world_T_cam_i[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    d = world_T_cam_i[2, 3] - ground_height
    if d <= 0:
        raise SimulationError(f"camera i is not above the ground plane (height {d:.3f} m)")
    H = K @ (R + np.outer(t, n) / d) @ np.linalg.inv(K)
    return H / H[2, 2]


def image_corner_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(4, 3) camera-frame rays through the corner pixel centres."""
    corners = np.array(
        [
            [0.0, 0.0, 1.0],
            [width - 1.0, 0.0, 1.0],
            [width - 1.0, height - 1.0, 1.0],
            [0.0, height - 1.0, 1.0],
        ]
    )
    return corners @ np.linalg.inv(K).T


def ground_footprints(
    world_T_cam: np.ndarray, K: np.ndarray, width: int, height: int, ground_height: float
) -> np.ndarray:
    """(N, 4, 2) ground points [m] seen at the image corners of every camera pose (N, 4, 4).

    Raises:
        SimulationError: a camera is below the ground or a corner ray does not hit the ground.
    """
    rays = image_corner_rays(K, width, height)
    world_d = np.einsum("nij,kj->nki", world_T_cam[:, :3, :3], rays)
    h = world_T_cam[:, 2, 3] - ground_height
    if np.any(h <= 0):
        i = int(np.flatnonzero(h <= 0)[0])
        raise SimulationError(f"camera pose {i} is not above the ground (height {h[i]:.3f} m)")
    down = -world_d[..., 2]
    if np.any(down <= 1e-6):
        i = int(np.flatnonzero((down <= 1e-6).any(axis=1))[0])
        raise SimulationError(
            f"camera pose {i} sees above the horizon (tilt too large for the field of view)"
        )
    lam = h[:, None] / down
    return world_T_cam[:, None, :2, 3] + lam[..., None] * world_d[..., :2]


@dataclass
class Carpet:
    """A seeded noise texture on the ground, with its pyramid.

    Attributes:
        levels: texture pyramid (float32 grey, level 0 finest).
        resolution_m: texel size of level 0 [m].
        x0, y0: ground position of texel (0, 0) [m].
        ground_height: z of the ground plane in world [m].
    """

    levels: list[np.ndarray]
    resolution_m: float
    x0: float
    y0: float
    ground_height: float

    @classmethod
    def make(
        cls,
        xy_min: np.ndarray,
        xy_max: np.ndarray,
        ground_height: float,
        resolution_m: float,
        rng: np.random.Generator,
        featureless_patches: int = 0,
    ) -> Carpet:
        """Carpet covering the box ``[xy_min, xy_max]`` [m] (plus ``FOOTPRINT_MARGIN_M``)."""
        lo = np.asarray(xy_min, float) - FOOTPRINT_MARGIN_M
        hi = np.asarray(xy_max, float) + FOOTPRINT_MARGIN_M
        res = float(resolution_m)
        side = float(np.max(hi - lo))
        if side / res > MAX_TEXTURE_SIDE:
            new_res = side / MAX_TEXTURE_SIDE
            log.info("carpet of %.1f m: texel enlarged from %.4f to %.4f m", side, res, new_res)
            res = new_res
        w, h = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
        tex = np.zeros((h, w), np.float32)
        for scale_m, weight in zip(CARPET_SCALES_M, CARPET_WEIGHTS, strict=True):
            # White noise on a grid of half the blob size, blurred, then upsampled: band-limited.
            cell = max(scale_m / 2.0, res)
            gw = max(2, int(math.ceil(w * res / cell)) + 1)
            gh = max(2, int(math.ceil(h * res / cell)) + 1)
            grid = rng.standard_normal((gh, gw)).astype(np.float32)
            grid = cv2.GaussianBlur(grid, (0, 0), 1.0)
            layer = cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
            layer /= max(float(layer.std()), 1e-6)
            tex += weight * layer
        tex = (tex - tex.mean()) / max(float(tex.std()), 1e-6) * CARPET_STD + CARPET_MEAN
        for _ in range(int(featureless_patches)):
            size = rng.uniform(*PATCH_SIZE_M, 2) / res
            cx, cy = rng.uniform(0, w), rng.uniform(0, h)
            p0 = (int(cx - size[0] / 2), int(cy - size[1] / 2))
            p1 = (int(cx + size[0] / 2), int(cy + size[1] / 2))
            cv2.rectangle(tex, p0, p1, PATCH_GREY, thickness=-1)
        # Final band limit: no detail finer than ~2 texels survives (no aliasing at level 0).
        tex = cv2.GaussianBlur(tex, (0, 0), 1.0)
        levels = [tex]
        for _ in range(PYRAMID_LEVELS - 1):
            if min(levels[-1].shape) < 16:
                break
            levels.append(cv2.pyrDown(levels[-1]))
        return cls(levels, res, float(lo[0]), float(lo[1]), float(ground_height))

    def world_xy1_from_texel(self, level: int) -> np.ndarray:
        """3x3 map (u, v, 1) of pyramid ``level`` -> (X, Y, 1) on the ground [m]."""
        r = self.resolution_m * (2**level)
        return np.array([[r, 0.0, self.x0], [0.0, r, self.y0], [0.0, 0.0, 1.0]])

    def render(self, world_T_cam: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """Float32 grey image (height, width) seen from ``world_T_cam`` (pinhole ``K``)."""
        depth = world_T_cam[2, 3] - self.ground_height
        optical_down = max(-world_T_cam[2, 2], 1e-3)
        pixel_m = depth / optical_down / K[0, 0]
        level = int(
            np.clip(
                math.floor(math.log2(max(pixel_m / (2.0 * self.resolution_m), 1.0))),
                0,
                len(self.levels) - 1,
            )
        )
        H = ground_homography(world_T_cam, K, self.ground_height, self.world_xy1_from_texel(level))
        return cv2.warpPerspective(
            self.levels[level],
            H,
            (width, height),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REFLECT_101,
        )


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Round and clip a float image to uint8."""
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
