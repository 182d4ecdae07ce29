"""A native folder read as streams in chunks (bounded memory): the same samples and events as the
whole read, arrival order kept across chunks, a bad line named after chunks went out, and the
online smoother fed from the chunks giving the same estimate."""

from __future__ import annotations

import numpy as np
import pytest
from fgnav.datasets.errors import FlightFormatError
from fgnav.datasets.events import replay_flight
from fgnav.datasets.native import (
    count_rows,
    iter_stream_csv,
    open_flight_streams,
    read_flight,
    read_stream_csv,
    write_flight,
)
from fgnav.datasets.simulate import SimOptions, simulate


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    flight = simulate(
        "rectangle", 3, SimOptions(images=False, duration=12.0, slam_latency_jitter_s=0.15)
    )
    return write_flight(flight, tmp_path_factory.mktemp("native") / "f")


def test_chunks_equal_the_whole_read(folder):
    whole = read_stream_csv(folder / "slam.csv", "slam")
    chunks = list(iter_stream_csv(folder / "slam.csv", "slam", chunk_rows=37))
    assert len(chunks) == -(-len(whole) // 37) and all(len(c) <= 37 for c in chunks)
    for field in ("t", "slam_t_cam", "slam_q_cam_wxyz", "session", "latency"):
        np.testing.assert_array_equal(
            np.concatenate([getattr(c, field) for c in chunks]), getattr(whole, field)
        )
    assert count_rows(folder / "imu.csv") == len(read_stream_csv(folder / "imu.csv", "imu"))


def test_events_from_chunks_equal_the_replay_of_the_whole_flight(folder):
    """SLAM latencies of 0-0.3 s put poses out of capture order: the merge across chunk
    boundaries must still give the whole replay's order exactly."""
    flight = read_flight(folder)
    fs = open_flight_streams(folder, chunk_rows=50)
    names = ["imu", "attitude", "range", "yaw", "slam"]
    a = [(type(e).__name__, e.t, e.arrival) for e in fs.events(names)]
    b = [(type(e).__name__, e.t, e.arrival) for e in replay_flight(flight, names)]
    assert len(a) == len(b) == sum(fs.counts[n] for n in names)
    assert a == b
    lat = flight.slam.latency
    assert np.ptp(lat) > 0.1  # the test needs poses that arrive out of capture order
    out = fs.outline
    assert out.imu.t.tolist() == [flight.imu.t[0], flight.imu.t[-1]]
    assert out.ground_truth is None and out.slam.t[-1] == flight.slam.t[-1]


def test_a_bad_line_after_the_first_chunks_is_named(folder, tmp_path):
    lines = (folder / "imu.csv").read_text().splitlines()
    lines[300] = lines[300].replace(",", ",x", 1)
    bad = tmp_path / "imu.csv"
    bad.write_text("\n".join(lines) + "\n")
    got = []
    with pytest.raises(FlightFormatError, match=r"imu.csv:301: column 2"):
        for c in iter_stream_csv(bad, "imu", chunk_rows=100):
            got.append(len(c))
    assert got == [100, 100]  # the chunks before the bad one went out


def test_online_fed_from_chunks_equals_the_whole_flight_replay(folder):
    from fgnav.solvers.online import replay_online

    flight = read_flight(folder)
    fs = open_flight_streams(folder, chunk_rows=500)
    a = replay_online(fs.outline, source=fs)
    b = replay_online(flight)
    np.testing.assert_array_equal(a.trajectory.t, b.trajectory.t)
    np.testing.assert_allclose(a.trajectory.world_t_body, b.trajectory.world_t_body, atol=1e-9)
    assert a.info["received"] == b.info["received"]


def test_a_file_cut_in_its_last_line_is_named_when_opened_as_streams(folder, tmp_path):
    """``fgnav online`` opens a native folder as streams: a stream file cut in the middle of its
    last line is named with its line (as the whole read names it), not read as a stream of one
    sample (which failed later with "the imu and slam streams do not overlap")."""
    import shutil

    cut = tmp_path / "cut"
    shutil.copytree(folder, cut)
    lines = (cut / "slam.csv").read_text().splitlines()
    (cut / "slam.csv").write_text("\n".join(lines[:200] + [lines[200][:30]]) + "\n")
    with pytest.raises(FlightFormatError, match=r"slam\.csv:201: expected 10 columns"):
        open_flight_streams(cut)
    with pytest.raises(FlightFormatError, match=r"slam\.csv:201: expected 10 columns"):
        read_flight(cut)
