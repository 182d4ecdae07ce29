"""Typed events and the replay: arrival order, latency applied once, lazy merge."""

import itertools

import numpy as np
from fgnav.datasets.events import (
    ImuSample,
    RangeReading,
    SlamPose,
    flight_streams,
    replay,
    replay_flight,
    stream_events,
)
from fgnav.datasets.types import Flight, ImuSeries, RangeSeries, SlamSeries


def _flight() -> Flight:
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 2.0, 0.005)
    imu = ImuSeries(t, rng.normal(size=(t.size, 3)), rng.normal(size=(t.size, 3)))
    ts = np.arange(0.05, 2.0, 0.1)
    q = np.tile([1.0, 0, 0, 0], (ts.size, 1))
    lat = rng.uniform(0.0, 0.5, ts.size)
    slam = SlamSeries(ts, rng.normal(size=(ts.size, 3)), q, np.zeros(ts.size, int), lat)
    tr = np.arange(0.013, 2.0, 0.02)
    rng_ = RangeSeries(tr, np.full(tr.size, 1.5))
    return Flight("f", imu=imu, slam=slam, range=rng_)


def test_replay_is_in_arrival_order_and_complete():
    f = _flight()
    ev = list(replay_flight(f))
    arr = np.array([e.arrival for e in ev])
    assert np.all(np.diff(arr) >= 0)
    assert sum(isinstance(e, ImuSample) for e in ev) == len(f.imu)
    slam = [e for e in ev if isinstance(e, SlamPose)]
    assert len(slam) == len(f.slam)
    # the SLAM stream's own latency column is applied once
    for e in slam:
        i = int(np.argmin(np.abs(f.slam.t - e.t)))
        assert e.arrival == f.slam.t[i] + f.slam.latency[i]
    assert all(
        isinstance(e, RangeReading) and e.arrival == e.t for e in ev if isinstance(e, RangeReading)
    )


def test_ties_put_imu_first_and_latency_override():
    f = _flight()
    streams = flight_streams(f, ["range", "imu"], latency={"range": 0.0})
    ev = list(itertools.islice(replay(streams), 50))
    for a, b in itertools.pairwise(ev):
        if a.arrival == b.arrival:
            assert not (isinstance(a, RangeReading) and isinstance(b, ImuSample))
    late = list(stream_events(f, "range", latency=0.25))
    assert late[0].arrival == late[0].t + 0.25


def test_replay_is_lazy():
    def endless():
        for i in itertools.count():
            yield ImuSample(i * 0.01, i * 0.01, np.zeros(3), np.zeros(3))

    first = list(itertools.islice(replay({"imu": endless()}), 3))
    assert [e.t for e in first] == [0.0, 0.01, 0.02]
