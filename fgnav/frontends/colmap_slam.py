"""Offline monocular SLAM source: pycolmap incremental structure-from-motion over a flight's images.

For logs that have camera images but no SLAM output, this makes the ``SlamSeries`` the graph's SLAM
factors consume (DESIGN.md sec. 5, "Monocular SLAM source"): SIFT features
(``pycolmap.extract_features``), sequential matching (``pycolmap.match_sequential``, the images
are a video) and incremental mapping (``pycolmap.incremental_mapping``) with the known intrinsics
held fixed (one shared camera, no focal/principal-point/distortion refinement).

Output frames and units: COLMAP's world frame is the SLAM frame ``slam`` with an arbitrary
origin, orientation and scale (monocular), so ``slam_t_cam`` is in SLAM units; the camera frame is
COLMAP's (x right, y down, z along the optical axis), the same as fgnav's camera frame
(``Calibration.body_T_cam``). COLMAP stores ``cam_from_world``; this module returns its inverse
``slam_T_cam``. When the mapper produces several models (tracking breaks), each model is a
session (its own frame and scale), numbered in the time order of its first image.

Images that no model registers are not in the series: they are counted, listed in
:attr:`ColmapSlamResult.unregistered` and logged.

Runtime (GTSAM-NOTES "Vision pieces"): about 9 s for 30 images at 320x240 with 1024 SIFT features
on one core; mapping cost grows faster than linearly with the number of images.

Not modelled: rolling shutter, time offsets between the camera and the IMU (the image time is
``ImageSeries.t``), the SLAM latency of an online system (``latency`` is left unset).
"""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from fgnav.datasets.errors import FgnavError, FlightDataError
from fgnav.datasets.geometry import matrix_to_quat_wxyz
from fgnav.datasets.types import CameraIntrinsics, Flight, ImageSeries, SlamSeries

logger = logging.getLogger(__name__)

#: Image file name pattern in the work folder (index in the ImageSeries).
IMAGE_NAME = "{:06d}.png"


class ColmapSlamError(FgnavError, RuntimeError):
    """pycolmap failed or reconstructed nothing."""


@dataclass(frozen=True)
class ColmapSlamOptions:
    """Options of :func:`reconstruct`.

    Attributes:
        max_num_features: SIFT features per image (GTSAM-NOTES: 1024 at 320x240).
        sequential_overlap: each image is matched with this many following images.
        loop_detection: vocabulary-tree loop detection in sequential matching (needs a vocabulary
            tree file, off by default).
        min_model_size: smallest model kept by the mapper [images].
        multiple_models: let the mapper start new models when registration fails (sessions).
        num_threads: threads for extraction, matching and mapping (-1: all cores).
        random_seed: seed of the mapper's RANSAC and of extraction (reproducible runs).
        keep_work_dir: keep the temporary folder with the images and database (debugging).
    """

    max_num_features: int = 1024
    sequential_overlap: int = 5
    loop_detection: bool = False
    min_model_size: int = 5
    multiple_models: bool = True
    num_threads: int = 1
    random_seed: int = 0
    keep_work_dir: bool = False


@dataclass(frozen=True, eq=False)
class ColmapSlamResult:
    """Output of :func:`reconstruct`.

    Attributes:
        slam: camera poses of the registered images (``session`` = model, time-ordered).
        num_images: images given.
        num_registered: images with a pose in ``slam``.
        unregistered: indices (into the ImageSeries) of images no model registered.
        model_sizes: registered images per session id.
        runtime_s: wall time [s] of extraction, matching and mapping.
        work_dir: the work folder when kept, else None.
        info: options used and per-stage times.
    """

    slam: SlamSeries | None
    num_images: int
    num_registered: int
    unregistered: np.ndarray
    model_sizes: dict[int, int]
    runtime_s: float
    work_dir: Path | None = None
    info: dict = field(default_factory=dict)


def _camera_model(cam: CameraIntrinsics) -> tuple[str, str]:
    """COLMAP camera model name and parameter string of fgnav intrinsics."""
    dist = tuple(float(x) for x in cam.distortion)
    if not dist or not any(dist):
        return "PINHOLE", f"{cam.fx},{cam.fy},{cam.cx},{cam.cy}"
    if len(dist) == 4:
        k1, k2, p1, p2 = dist
        return "OPENCV", f"{cam.fx},{cam.fy},{cam.cx},{cam.cy},{k1},{k2},{p1},{p2}"
    if len(dist) == 5:
        k1, k2, p1, p2, k3 = dist
        return (
            "FULL_OPENCV",
            f"{cam.fx},{cam.fy},{cam.cx},{cam.cy},{k1},{k2},{p1},{p2},{k3},0,0,0",
        )
    raise FlightDataError(
        f"camera.distortion: expected 0, 4 or 5 OpenCV coefficients (k1 k2 p1 p2 [k3]), got "
        f"{len(dist)}"
    )


def reconstruct(
    images: ImageSeries,
    options: ColmapSlamOptions | None = None,
    work_dir: Path | None = None,
) -> ColmapSlamResult:
    """Monocular SLAM poses of a camera from its images by pycolmap incremental mapping.

    Args:
        images: the images (in memory or files) and their intrinsics (held fixed).
        options: :class:`ColmapSlamOptions` (defaults when None).
        work_dir: folder for the images, database and models; a temporary folder (removed
            afterwards unless ``keep_work_dir``) when None.

    Returns:
        :class:`ColmapSlamResult`; ``slam`` is None only when no image was registered (then a
        warning is logged and ``unregistered`` lists all images).

    Raises:
        FlightDataError: invalid image series.
        ColmapSlamError: pycolmap raised.
    """
    import pycolmap

    o = options or ColmapSlamOptions()
    images.check("images")
    cam = images.camera
    n = len(images)
    t_start = time.perf_counter()
    tmp = None
    if work_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="fgnav-colmap-")
        work_dir = Path(tmp.name)
    work_dir = Path(work_dir)
    image_dir = work_dir / "images"
    image_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    if database.exists():
        database.unlink()
    try:
        for k in range(n):
            cv2.imwrite(str(image_dir / IMAGE_NAME.format(k)), images.load(k, grey=True))
        times = {}
        model, params = _camera_model(cam)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = model
        reader.camera_params = params
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.sift.max_num_features = o.max_num_features
        extraction.num_threads = o.num_threads
        extraction.use_gpu = False
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = o.num_threads
        matching.use_gpu = False
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = o.sequential_overlap
        pairing.loop_detection = o.loop_detection
        mapping = pycolmap.IncrementalPipelineOptions()
        mapping.ba_refine_focal_length = False
        mapping.ba_refine_principal_point = False
        mapping.ba_refine_extra_params = False
        mapping.mapper.abs_pose_refine_focal_length = False
        mapping.mapper.abs_pose_refine_extra_params = False
        mapping.min_model_size = o.min_model_size
        mapping.multiple_models = o.multiple_models
        mapping.num_threads = o.num_threads
        mapping.random_seed = o.random_seed
        try:
            t0 = time.perf_counter()
            pycolmap.extract_features(
                database,
                image_dir,
                camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
            )
            times["extract_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            pycolmap.match_sequential(
                database,
                matching_options=matching,
                pairing_options=pairing,
                device=pycolmap.Device.cpu,
            )
            times["match_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            models = pycolmap.incremental_mapping(
                database, image_dir, work_dir / "sparse", options=mapping
            )
            times["map_s"] = time.perf_counter() - t0
        except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError
            raise ColmapSlamError(f"pycolmap failed in {work_dir}: {exc}") from exc
        slam, sizes, registered = _to_slam_series(models, images.t, n)
    finally:
        if tmp is not None and not o.keep_work_dir:
            tmp.cleanup()
    unregistered = np.flatnonzero(~registered)
    runtime = time.perf_counter() - t_start
    if unregistered.size:
        logger.warning(
            "pycolmap registered %d of %d images (%d models); unregistered indices: %s",
            n - unregistered.size,
            n,
            len(sizes),
            _short_list(unregistered),
        )
    else:
        logger.info(
            "pycolmap registered all %d images in %d model(s), %.1f s", n, len(sizes), runtime
        )
    return ColmapSlamResult(
        slam=slam,
        num_images=n,
        num_registered=int(registered.sum()),
        unregistered=unregistered,
        model_sizes=sizes,
        runtime_s=runtime,
        work_dir=work_dir if (tmp is None or o.keep_work_dir) else None,
        info={"options": asdict(o), **times},
    )


def slam_from_flight(
    flight: Flight, options: ColmapSlamOptions | None = None, work_dir: Path | None = None
) -> ColmapSlamResult:
    """:func:`reconstruct` over ``flight.images`` (intrinsics from the images or ``calib``)."""
    if flight.images is None:
        raise FlightDataError(f"{flight.name}: the pycolmap SLAM source needs an images stream")
    images = flight.images
    if images.camera is None:
        if flight.calib.camera is None:
            raise FlightDataError(f"{flight.name}.images.camera: intrinsics missing")
        import dataclasses

        images = dataclasses.replace(images, camera=flight.calib.camera)
    return reconstruct(images, options, work_dir)


def _to_slam_series(models: dict, t: np.ndarray, n: int):
    """pycolmap models -> (SlamSeries or None, sizes per session, registered mask).

    An image registered by several models (they may overlap) is kept in the largest one.
    """
    owner = np.full(n, -1)
    poses: dict[int, dict[int, tuple[np.ndarray, np.ndarray]]] = {}
    order = sorted(models, key=lambda k: -models[k].num_reg_images())
    for model_id in order:
        rec = models[model_id]
        poses[model_id] = {}
        for image in rec.images.values():
            if not image.has_pose:
                continue
            k = int(Path(image.name).stem)
            if owner[k] >= 0:
                continue
            cam_from_world = image.cam_from_world()
            cam_R_slam = np.asarray(cam_from_world.rotation.matrix(), float)
            cam_t_slam = np.asarray(cam_from_world.translation, float)
            owner[k] = model_id
            poses[model_id][k] = (cam_R_slam.T, -cam_R_slam.T @ cam_t_slam)
    registered = owner >= 0
    if not registered.any():
        return None, {}, registered
    # Sessions numbered by the time of their first image.
    first = {m: min(p) for m, p in poses.items() if p}
    session_of = {m: s for s, m in enumerate(sorted(first, key=first.get))}
    idx = np.flatnonzero(registered)
    R = np.array([poses[owner[k]][k][0] for k in idx])
    p = np.array([poses[owner[k]][k][1] for k in idx])
    session = np.array([session_of[owner[k]] for k in idx], dtype=np.int64)
    slam = SlamSeries(
        t=np.asarray(t, float)[idx],
        slam_t_cam=p,
        slam_q_cam_wxyz=matrix_to_quat_wxyz(R),
        session=session,
    ).check("colmap_slam")
    sizes = {int(s): int((session == s).sum()) for s in np.unique(session)}
    return slam, sizes, registered


def _short_list(idx: np.ndarray, limit: int = 20) -> str:
    s = ", ".join(str(int(i)) for i in idx[:limit])
    return s + (f", ... ({idx.size} in all)" if idx.size > limit else "")
