"""The push engine's homography VO in a child process (``FixedLagOptions.vo_worker``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError
from fgnav.datasets.events import ImageFrame
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.eval.metrics import evaluate
from fgnav.frontends.homography_vo import HomographyVOOptions
from fgnav.frontends.vo_process import VoProcess
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.graph import GraphOptions
from fgnav.solvers.online import replay_online


@pytest.fixture(scope="module")
def figure8_camera():
    return simulate(
        "figure8",
        seed=0,
        options=SimOptions(duration=20.0, images=True, image_rate_hz=30.0, slam_rate_hz=20.0),
    )


def _run(flight, **kw):
    opts = FixedLagOptions(lag_s=2.0, graph=GraphOptions(keyframe_hz=20.0), **kw)
    est = replay_online(flight, opts)
    return est, evaluate(est, flight.ground_truth, alignment="se3")


# Measured (20 s figure8, 30 Hz camera): ATE inline 0.525 cm, process 0.529 cm (delay 1, the
# default) and 0.581 cm (delay 2); 296 / 295 / 294 homography factors of 594 valid pairs. 180 s
# (bench_online.py's flight): 1.656 / 1.598 / 1.657 cm.
def test_vo_process_is_deterministic_and_as_accurate_as_inline(figure8_camera):
    flight = figure8_camera
    inline, m_inline = _run(flight, vo_worker="inline")
    runs = [_run(flight, vo_worker="process") for _ in range(2)]
    (a, m_a), (b, _) = runs
    # Which frames an update waits for depends on the keyframes only, not on the child's speed.
    np.testing.assert_array_equal(a.trajectory.world_t_body, b.trajectory.world_t_body)
    np.testing.assert_array_equal(a.trajectory.t, b.trajectory.t)
    # Same VO (the stage state lives in the child), pairs attached a keyframe later.
    assert a.info["vo_counts"] == inline.info["vo_counts"]
    assert a.info["vo_counts"]["valid_pairs"] >= 590
    n_in, n_a = inline.info["used"]["homography"], a.info["used"]["homography"]
    assert n_in - 3 <= n_a <= n_in
    assert a.info["vo_time_s"] > 0.0
    assert m_inline.ate_rmse_m < 0.007
    assert m_a.ate_rmse_m < 1.05 * m_inline.ate_rmse_m + 0.0002
    two, m_two = _run(flight, vo_worker="process", vo_process_delay_keyframes=2)
    assert m_two.ate_rmse_m < 1.2 * m_inline.ate_rmse_m
    assert two.info["vo_counts"] == inline.info["vo_counts"]


def test_vo_process_reports_a_bad_frame_as_the_stages_one_line_error(figure8_camera):
    flight = figure8_camera
    calib = dataclasses.replace(flight.calib, camera=None)
    vo = VoProcess(calib, None, HomographyVOOptions(), uses_attitude=True, name="bad")
    frame = ImageFrame(t=0.0, arrival=0.0, index=7, camera=None, image=flight.images.frames[0])
    vo.submit(frame, np.eye(3), 1.0)
    with pytest.raises(FlightDataError) as err:
        vo.take()
    assert str(err.value) == "bad: image 7: camera intrinsics missing"
    vo._proc.wait(timeout=10.0)
    assert vo._proc.returncode == 0  # the child reported and ended


def test_vo_process_close_stops_the_child(figure8_camera):
    flight = figure8_camera
    vo = VoProcess(flight.calib, None, HomographyVOOptions(), uses_attitude=True, name="vo")
    R = np.eye(3)
    for k in range(3):
        img = flight.images.frames[k]
        vo.submit(ImageFrame(k / 30.0, k / 30.0, k, flight.images.camera, img), R, 1.0)
    assert len(vo) == 3
    vo.close()  # the frames in flight are waited for, then the child ends
    assert vo._proc.returncode == 0 and len(vo) == 0
    assert vo.counts["frames"] == 3


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("vo_worker", "thread", "online.vo_worker='thread': expected inline or process"),
        ("vo_process_delay_keyframes", 0, "expected an integer >= 1"),
    ],
)
def test_bad_vo_worker_options_are_one_line_errors(figure8_camera, field, value, message):
    with pytest.raises(FlightDataError, match=message) as err:
        replay_online(figure8_camera, FixedLagOptions(**{field: value}))
    assert "\n" not in str(err.value)


def test_images_after_the_imu_ended_do_not_block_the_vo_process(figure8_camera):
    """The IMU stops at 8 s, the camera goes on to 20 s (360 frames without a keyframe update):
    without a cap on the frames in flight the pipes to and from the child fill and both
    processes wait for each other."""
    flight = figure8_camera
    imu = flight.imu
    cut = dataclasses.replace(flight, imu=imu.select(imu.t <= imu.t[0] + 8.0))
    est, _ = _run(cut, vo_worker="process")
    inline, _ = _run(cut, vo_worker="inline")
    assert est.info["vo_counts"] == inline.info["vo_counts"]
    assert est.info["vo_counts"]["frames"] > 550  # every frame went through the child
    assert est.trajectory.t[-1] <= imu.t[0] + 8.0 + 1e-6


def test_vo_process_logs_in_the_cli_format_at_the_parents_level(figure8_camera, tmp_path, capfd):
    """The child's log records (here: an unreadable image, skipped and counted) reach stderr in
    the CLI's ``LEVEL name: message`` format, marked as the VO process's."""
    import logging

    flight = figure8_camera
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not an image")
    root = logging.getLogger()
    old = root.level
    root.setLevel(logging.INFO)
    try:
        vo = VoProcess(flight.calib, None, HomographyVOOptions(), uses_attitude=True, name="vo")
        vo.submit(ImageFrame(0.0, 0.0, 0, flight.images.camera, path=bad), np.eye(3), 1.0)
        assert vo.take() is None
        vo.close()
    finally:
        root.setLevel(old)
    assert vo.counts["unreadable_image"] == 1
    err = capfd.readouterr().err
    assert "WARNING fgnav.frontends.homography_vo (VO process): vo: cannot read image" in err
