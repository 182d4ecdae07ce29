"""Inbound: arrival times on the boot clock, SLAM sessions from reset_counter, counters, and
lost messages from sequence numbers."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from fgnav.datasets.events import ImuSample, RangeReading, SlamPose  # noqa: E402

from fgnav.live import convert  # noqa: E402
from fgnav.live.inbound import Inbound, SequenceCounter  # noqa: E402
from fgnav.live.link import LinkError, new_mavlink, pack, parse_address  # noqa: E402


def _through(tx, rx, name, fields):
    out = rx.parse_buffer(pack(tx, getattr(tx, f"{name}_encode")(**fields)))
    return out[0]


def _feeder(inb: Inbound):
    """``feed(sender, message name, fields)``: the message through the wire into ``inb``."""
    rx = new_mavlink(0, 0)

    def feed(mav, name, fields):
        msg = _through(mav, rx, name, fields)
        inb.count(msg)
        return inb.event(msg)

    return feed


def test_sequence_counter_counts_gaps_across_the_wrap():
    c = SequenceCounter()
    for seq in (250, 251, 253, 255, 0, 4):  # missing 252, 254, 1, 2, 3
        c.add(1, 1, seq)
    c.add(1, 191, 7)  # another component has its own sequence
    c.add(1, 191, 8)
    assert c.lost == {"1/1": 5}
    assert c.seen == {"1/1": 6, "1/191": 2}


def test_arrival_sessions_and_counts():
    tx, rx = new_mavlink(1, 1), new_mavlink(0, 0)
    slam_tx = new_mavlink(1, 191)
    inb = Inbound()
    feed = _feeder(inb)
    q = np.array([1.0, 0.0, 0.0, 0.0])

    imu = ImuSample(0.0, 0.0, np.zeros(3), np.array([0.0, 0.0, 9.81]))
    for k in range(3):
        ev = feed(tx, "highres_imu", convert.highres_imu_fields(imu._replace(t=0.5 + 0.005 * k), 0))
        assert ev.arrival == ev.t
    assert inb.newest_imu_t == 0.51
    # A SLAM pose of an image taken at 0.4 s arrives now: arrival = newest IMU time.
    pose = SlamPose(0.4, 0.4, np.zeros(3), q, 0)
    ev = feed(slam_tx, "odometry", convert.vision_odometry_fields(pose, 0, reset_counter=5))
    assert (ev.t, ev.arrival, ev.session) == (0.4, 0.51, 0)
    ev = feed(slam_tx, "odometry", convert.vision_odometry_fields(pose, 0, reset_counter=5))
    assert ev.session == 0
    ev = feed(slam_tx, "odometry", convert.vision_odometry_fields(pose, 0, reset_counter=6))
    assert ev.session == 1  # reset_counter rose: a new map
    # A stamp later than the newest IMU sample arrives at its own time.
    pose2 = pose._replace(t=0.6)
    ev = feed(slam_tx, "odometry", convert.vision_odometry_fields(pose2, 0, reset_counter=6))
    assert ev.arrival == 0.6 and ev.session == 1
    # fgnav's own ODOMETRY echoed back is ignored, and counted.
    st = {**convert.vision_odometry_fields(pose, 0, 0), "estimator_type": 3}
    assert feed(tx, "odometry", st) is None
    # An upward rangefinder is dropped, by reason.
    rng = convert.distance_sensor_fields(RangeReading(0.52, 0.52, 1.0), 0, 0.1, 8.0)
    assert feed(tx, "distance_sensor", rng | {"orientation": 24}) is None
    hb = _through(
        tx, rx, "heartbeat", dict(type=2, autopilot=0, base_mode=0, custom_mode=0, system_status=4)
    )
    inb.count(hb)
    assert inb.event(hb) is None
    c = inb.counts()
    assert c["received"] == {"imu": 3, "slam": 4, "range": 1}
    assert c["dropped"] == {"slam:vio_echo": 1, "range:orientation": 1}
    assert c["messages"] == {"HIGHRES_IMU": 3, "ODOMETRY": 5, "DISTANCE_SENSOR": 1, "HEARTBEAT": 1}
    assert c["lost"] == {} and c["slam_sessions"] == 2
    # "Now": the newest IMU stamp plus the wall time since it came (not the SLAM's 0.6 s).
    assert 510_000_000 <= inb.clock_ns() < 510_000_000 + 1_000_000_000


def test_other_odometry_and_off_clock_stamps_leave_the_slam_alone():
    """The autopilot's own ODOMETRY (estimator_type 8, its own reset_counter) interleaved
    with the SLAM's: it had started a new SLAM session at every pose (review 2026-12-07:
    two-turns ATE 0.029 -> 0.60 m). A second SLAM source has its own sessions; a pose stamped
    on the UNIX epoch (MAVROS) is dropped as off the boot clock, and "now" stays right."""
    tx = new_mavlink(1, 1)
    slam_tx, other_tx = new_mavlink(1, 191), new_mavlink(1, 197)
    inb = Inbound()
    feed = _feeder(inb)
    q = np.array([1.0, 0.0, 0.0, 0.0])

    imu = ImuSample(2.0, 2.0, np.zeros(3), np.array([0.0, 0.0, 9.81]))
    feed(tx, "highres_imu", convert.highres_imu_fields(imu, 0))
    pose = SlamPose(1.9, 1.9, np.zeros(3), q, 0)
    autopilot = {**convert.vision_odometry_fields(pose, 0, 0), "estimator_type": 8}
    sessions = []
    for _ in range(5):
        sessions.append(
            feed(slam_tx, "odometry", convert.vision_odometry_fields(pose, 0, 1)).session
        )
        assert feed(tx, "odometry", autopilot) is None
    assert sessions == [0] * 5
    assert feed(other_tx, "odometry", convert.vision_odometry_fields(pose, 0, 1)).session == 1
    assert feed(slam_tx, "odometry", convert.vision_odometry_fields(pose, 0, 1)).session == 0
    epoch = pose._replace(t=1.7e9)
    assert feed(slam_tx, "odometry", convert.vision_odometry_fields(epoch, 0, 1)) is None
    c = inb.counts()
    assert c["dropped"] == {"slam:estimator_type": 5, "slam:off_clock": 1}
    assert c["slam_sessions"] == 2
    assert inb.clock_ns() < 3_000_000_000


def test_lost_messages_are_counted_from_sequence_numbers():
    tx, rx = new_mavlink(1, 1), new_mavlink(0, 0)
    inb = Inbound()
    imu = ImuSample(0.0, 0.0, np.zeros(3), np.zeros(3))
    for k in range(300):
        buf = pack(
            tx, tx.highres_imu_encode(**convert.highres_imu_fields(imu._replace(t=0.005 * k), 0))
        )
        if k % 7 == 3:  # the network drops it
            continue
        for msg in rx.parse_buffer(buf):
            inb.count(msg)
            inb.event(msg)
    dropped = sum(1 for k in range(300) if k % 7 == 3)
    assert inb.counts()["lost"] == {"1/1": dropped}
    assert inb.counts()["received"] == {"imu": 300 - dropped}


def test_address_spelling():
    a = parse_address("udpin:127.0.0.1:14550")
    assert (a.mode, a.host, a.port) == ("udpin", "127.0.0.1", 14550)
    for bad in ("udp:127.0.0.1:1", "udpin:127.0.0.1", "udpout:127.0.0.1:x", "udpin::5"):
        with pytest.raises(LinkError):
            parse_address(bad)
