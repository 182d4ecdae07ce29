"""A mirrored (left-handed) SLAM frame: named ``slam-mirrored`` with its axis and un-mirrored by
the batch's SLAM-vs-gyro step, not misnamed as the inverse convention or a wrong body_T_cam."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fgnav.datasets.geometry import quat_wxyz_to_matrix
from fgnav.datasets.simulate import SimOptions, simulate
from fgnav.datasets.slam_gyro import (
    META_KEY,
    SlamConventionError,
    apply_slam_check,
    check_flight,
    check_mirror,
    position_scale,
    unmirror_slam,
)

from fgnav.health import FaultDetectors, HealthOptions


@pytest.fixture(scope="module")
def flight():
    return simulate("two-turns", seed=1, options=SimOptions(duration=28.0, images=False))


def _mirrored(f, axis):
    # unmirror_slam is its own inverse: D p, D R D
    return dataclasses.replace(f, slam=unmirror_slam(f.slam, axis))


def _x(f):
    return np.asarray(f.calib.body_T_cam, float)[:3, :3]


def test_position_scale_sign_tells_a_mirror(flight):
    s = flight.slam
    R = quat_wxyz_to_matrix(s.slam_q_cam_wxyz)
    k, rel, n, _ = position_scale(
        flight.imu.t, flight.imu.body_accel, s.t, s.slam_t_cam, R, _x(flight)
    )
    assert n == 271 and 0.80 < k < 0.87 and rel < 0.05  # simulated scale 0.74 +- drift/latency
    m = _mirrored(flight, 1).slam
    # the mirrored positions with the orientations the gyro fits best (the file's, given X):
    # a negative scale
    k2, _, _, _ = position_scale(
        flight.imu.t,
        flight.imu.body_accel,
        m.t,
        m.slam_t_cam,
        quat_wxyz_to_matrix(m.slam_q_cam_wxyz),
        _x(flight),
    )
    assert k2 < -0.6


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_mirror_named_with_its_axis(flight, axis):
    f = _mirrored(flight, axis)
    d = check_flight(f)
    # before: named as something else (two-turns: inverse convention, or the z flip as a
    # body_T_cam rotation 80 deg off)
    assert d.convention == "inverse" or not d.body_R_cam_ok
    v = check_mirror(f.imu, f.slam, _x(f))
    assert v is not None and v.mirrored and v.axis == axis
    assert v.message() == f"slam-mirrored: the SLAM frame is left-handed (axis {'xyz'[axis]} sign?)"


def test_no_mirror_on_right_inverted_or_turned_camera(flight):
    assert check_mirror(flight.imu, flight.slam, _x(flight)).mirrored is False
    q = np.array(flight.slam.slam_q_cam_wxyz)
    q[:, 1:] *= -1  # inverse convention: a real fork's, not a mirror
    inv = dataclasses.replace(flight.slam, slam_q_cam_wxyz=q)
    assert check_mirror(flight.imu, inv, _x(flight)).mirrored is False
    # a camera really mounted 180 deg turned about its y axis (rotations as a y mirror's,
    # positions right-handed): not a mirror
    from fgnav.datasets.geometry import matrix_to_quat_wxyz

    R = quat_wxyz_to_matrix(flight.slam.slam_q_cam_wxyz) @ np.diag([-1.0, 1.0, -1.0])
    turned = dataclasses.replace(flight.slam, slam_q_cam_wxyz=matrix_to_quat_wxyz(R))
    v = check_mirror(flight.imu, turned, _x(flight))
    assert v is not None and v.mirrored is False


def test_batch_step_unmirrors_and_names_it(flight, caplog):
    f = _mirrored(flight, 1)
    with caplog.at_level("WARNING"):
        out = apply_slam_check(f)
    rec = out.meta[META_KEY]
    assert rec["mirrored"]["axis"] == "y" and rec["convention"] == "as-is" and rec["body_R_cam_ok"]
    assert not rec["inverted"] and not rec["body_R_cam_replaced"]
    np.testing.assert_allclose(out.slam.slam_t_cam, flight.slam.slam_t_cam, atol=1e-15)
    assert "slam-mirrored: the SLAM frame is left-handed (axis y sign?): un-mirrored" in caplog.text
    det = FaultDetectors(HealthOptions())
    det.slam_check(rec)
    rep = det.report()
    assert rep["detectors"] == {"slam-mirrored": 1}
    # off: as before (named as the inverse convention)
    out2 = apply_slam_check(f, mirror="off")
    assert "mirrored" not in out2.meta[META_KEY] and out2.meta[META_KEY]["inverted"]
    with pytest.raises(SlamConventionError, match="slam_mirror = 'no'"):
        apply_slam_check(f, mirror="no")


def test_clean_flight_record_unchanged(flight):
    rec = apply_slam_check(flight).meta[META_KEY]
    assert "mirrored" not in rec and rec["convention"] == "as-is"


def test_unidentified_axis_leaves_the_slam_out(flight, monkeypatch, caplog):
    """A mirror whose axis the motion does not tell (forced here: the tie of two flips):
    the batch goes on without the SLAM and says so in one line."""
    from fgnav.datasets import slam_gyro

    from fgnav.solvers.batch import BatchOptions, solve_batch

    monkeypatch.setattr(
        slam_gyro, "check_mirror", lambda *a, **k: slam_gyro.MirrorVerdict(True, None, {})
    )
    f = _mirrored(flight, 1)
    with caplog.at_level("WARNING"):
        out = apply_slam_check(f)
    assert out.slam is None and out.meta[META_KEY]["mirrored"]["axis"] is None
    assert "which one the motion does not tell): SLAM not used" in caplog.text
    est = solve_batch(f, BatchOptions())  # through GraphBuilder: no SLAM factors, no crash
    assert est.info["factors"].get("slam", 0) == 0 and not est.slam_scale
    det = FaultDetectors(HealthOptions())
    det.slam_check(est.info["slam_gyro_check"])
    assert det.report()["details"]["slam-mirrored"] == [
        "the SLAM frame is left-handed (an axis sign flipped; which one the motion does not "
        "tell): SLAM not used"
    ]


def test_a_wrong_camera_rotation_is_no_mirror_on_real_data(real_data):
    """EuRoC MH_01 with the identity given for body_T_cam (173 deg off): no hypothesis fits the
    gyro through it (3.0-5.1 deg against the free fit's 0.09), so no mirror is named. Before the
    noise floor took the free fit, the push engine named an x flip 4 s in, un-mirrored and
    diverged (fault matrix mh01:body_T_cam-identity: 'slam_t_world: non-finite value')."""
    from fgnav.datasets.load import load_flight
    from fgnav.datasets.types import ImuSeries, SlamSeries
    from testutil import PROJECT_ROOT

    f = load_flight(PROJECT_ROOT / "datasets" / "manifests" / "euroc_mh01_orbslam3.toml")
    t_end = f.slam.t[0] + 4.0
    mi, ms = f.imu.t <= t_end, f.slam.t <= t_end
    imu = ImuSeries(f.imu.t[mi], f.imu.body_omega[mi], f.imu.body_accel[mi])
    s = f.slam
    slam = SlamSeries(
        t=s.t[ms],
        slam_t_cam=s.slam_t_cam[ms],
        slam_q_cam_wxyz=s.slam_q_cam_wxyz[ms],
        session=s.session[ms],
    )
    v = check_mirror(imu, slam, np.eye(3))
    assert v is not None and not v.mirrored and not v.conclusive
    assert min(h[0] for h in v.hypotheses.values()) > 2.5
    v = check_mirror(imu, slam, _x(f))
    assert not v.mirrored and v.conclusive and v.hypotheses["as-is/none"][0] < 0.2
