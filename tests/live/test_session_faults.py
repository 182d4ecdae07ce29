"""The live session and its command on faults, without a socket: a stand-in link hands the
session datagrams packed from the 8 s CLI flight (``cli_folder``), as ``fgnav replay`` sends
them. Checks: an unexpected exception keeps the outputs; a garbage IMU stamp and TIMESYNC;
the angular rates after an IMU clock restart; Ctrl-C in the --batch solve; the datagram parser;
the reader thread on a read error; ``fgnav replay``'s note on a peer that stopped."""

from __future__ import annotations

import errno
import json
import math
import signal
import socket
import time

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from fgnav.datasets.events import AttitudeSample, ImuSample, RangeReading, replay_flight  # noqa: E402
from fgnav.datasets.native import read_flight  # noqa: E402
from fgnav.datasets.types import Trajectory  # noqa: E402

from fgnav.live import convert  # noqa: E402
from fgnav.live.estimators import MsfLive  # noqa: E402
from fgnav.live.link import Parsers, UdpLink, new_mavlink, pack, parse_address  # noqa: E402
from fgnav.live.replay import ReplayResult  # noqa: E402
from fgnav.live.session import LiveError, LiveOptions, LiveSession  # noqa: E402

PEER = ("127.0.0.1", 40001)
STREAMS = ("imu", "attitude", "range", "slam")


class FakeLink:
    """What :class:`LiveSession` uses of a ``UdpLink``: datagrams from a list, sends kept."""

    def __init__(self, datagrams: list[bytes] | None = None, address: str = "udpin:127.0.0.1:9"):
        self.address = parse_address(address)
        self.items = list(datagrams or [])
        self.sent: list[tuple[bytes, object]] = []
        self.peers: dict = {}
        self.datagrams = self.bytes = self.queue_max = 0
        self.send_errors = self.read_errors = 0
        self.rcvbuf_bytes = 0
        self.local_address = (self.address.host, self.address.port)

    def start(self):
        return self

    def get(self, timeout: float):
        if not self.items:
            time.sleep(min(timeout, 0.01))
            return None
        data = self.items.pop(0)
        self.datagrams += 1
        self.peers[PEER] = time.monotonic()
        return data, PEER, time.monotonic()

    def send(self, buf: bytes, to=None) -> bool:
        self.sent.append((bytes(buf), to))
        return True

    def close(self) -> None:
        pass

    def replies(self, name: str) -> list:
        rx = new_mavlink(0, 0)
        out = []
        for buf, _ in self.sent:
            out += [m for m in rx.parse_buffer(buf) or [] if m.get_type() == name]
        return out


def datagrams(flight, t_max: float = math.inf, mutate=None, streams=STREAMS) -> list[bytes]:
    """The flight's messages as fgnav replay packs them (one per datagram), up to ``t_max``;
    ``mutate(ev, name, fields)`` may change the fields or return a list of extra datagrams to
    send after the message."""
    tx, slam_tx = new_mavlink(1, 1), new_mavlink(1, 191)
    c = flight.calib
    out = []
    for ev in replay_flight(flight, streams):
        if ev.arrival > t_max:
            break
        if isinstance(ev, ImuSample):
            name, f, mav = "highres_imu", convert.highres_imu_fields(ev, 0.0), tx
        elif isinstance(ev, AttitudeSample):
            name, f, mav = "attitude_quaternion", convert.attitude_quaternion_fields(ev, 0), tx
        elif isinstance(ev, RangeReading):
            f = convert.distance_sensor_fields(ev, 0.0, c.range_min, c.range_max)
            name, mav = "distance_sensor", tx
        else:
            f = convert.vision_odometry_fields(ev, 0.0, ev.session)
            name, mav = "odometry", slam_tx
        extra = mutate(ev, name, f) if mutate else None
        out.append(pack(mav, getattr(mav, f"{name}_encode")(**f)))
        for e in extra or []:
            out.append(pack(tx, e) if not isinstance(e, bytes) else e)
    return out


@pytest.fixture(scope="module")
def flight(cli_folder):
    return read_flight(cli_folder)


@pytest.fixture
def keep_signals():
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, h in saved.items():
        signal.signal(s, h)


def msf(calib) -> MsfLive:
    """The MSF-style EKF behind the link, its SLAM scale given (8 s are too short to fit it)."""
    from fgnav.baselines.msf_ekf import MsfOptions

    return MsfLive(calib, MsfOptions(initial_scale=1.0))


class Boom:
    """An estimator that fails, unexpectedly, on its ``n``-th event."""

    def __init__(self, inner, n: int) -> None:
        self.inner, self.n = inner, n

    def feed(self, ev):
        self.n -= 1
        if self.n == 0:
            raise ValueError("math domain error (a bug)")
        return self.inner.feed(ev)

    def __getattr__(self, name):
        return getattr(self.inner, name)


def _run_live_command(
    monkeypatch, cli_folder, tmp_path, link, estimator, extra=()
) -> tuple[int, str]:
    import fgnav.live.estimators
    import fgnav.live.link
    from fgnav.cli import main

    monkeypatch.setattr(fgnav.live.link, "UdpLink", lambda address: link)
    monkeypatch.setattr(fgnav.live.estimators, "make_estimator", lambda *a: estimator)
    args = ["live", "--mavlink", "udpin:127.0.0.1:9", "--calib", str(cli_folder / "calib.yaml")]
    args += ["--out", str(tmp_path / "out"), "--idle-timeout", "0.3", *extra]
    return main(args), str(tmp_path / "out")


@pytest.mark.parametrize("streams", [STREAMS, ("imu", "attitude", "slam")])
def test_live_priors_check_the_streams_they_need(
    monkeypatch, cli_folder, flight, tmp_path, capsys, caplog, keep_signals, streams
):
    """``fgnav live`` with ``[priors] sources = ['ml-scale']`` on a link without a rangefinder
    says so in the one line ``fgnav online`` refuses such a flight with (it ran without a word,
    no prior given), once after 5 s of IMU and again under the counts; with the range stream,
    nothing is said."""
    import fgnav.live.link
    from fgnav.cli import main

    link = FakeLink(datagrams(flight, streams=streams))
    monkeypatch.setattr(fgnav.live.link, "UdpLink", lambda address: link)
    cfg = tmp_path / "p.toml"
    cfg.write_text("[priors]\nsources = ['ml-scale']\n")
    args = ["live", "--mavlink", "udpin:127.0.0.1:9", "--calib", str(cli_folder / "calib.yaml")]
    args += ["--out", str(tmp_path / "out"), "--idle-timeout", "0.3", "--config", str(cfg)]
    with caplog.at_level("WARNING", logger="fgnav"):
        assert main(args) == 0
    out = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    stage = summary["info"]["frontend_prior_stage"]
    assert stage["sources"] == ["ml-scale"]
    line = "live: front-end prior 'ml-scale' needs the range stream(s)"
    warned = [r.getMessage() for r in caplog.records if "front-end prior" in r.getMessage()]
    if "range" in streams:
        assert "missing_streams" not in stage and line not in out and warned == []
    else:
        assert stage["missing_streams"] == ["range"]
        assert f"warning: {line}; the link carried none" in out
        assert len(warned) == 1 and warned[0].startswith(f"{line} (none in the first 5 s")


def test_an_unexpected_estimator_exception_keeps_the_outputs(
    monkeypatch, cli_folder, flight, tmp_path, capsys, keep_signals
):
    """Any exception of the estimator (or of sending its state) ends the session: what there
    is written, the error in one line, exit 1 (only FgnavError was caught: a traceback and no
    outputs)."""
    link = FakeLink(datagrams(flight))
    boom = Boom(msf(flight.calib), n=len(link.items) // 2)
    rc, out = _run_live_command(monkeypatch, cli_folder, tmp_path, link, boom)
    err = capsys.readouterr().err
    assert rc == 1
    assert "ValueError on a message: math domain error (a bug)" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["extra"]["live"]["exit"] == "error"
    assert "math domain error" in summary["extra"]["live"]["failure"]
    assert (tmp_path / "out" / "estimate.tum").read_text().strip()


class _StubEstimator:
    def __init__(self) -> None:
        self.events = []

    def feed(self, ev):
        self.events.append(ev)
        return None

    def counts(self):
        return {}

    def result(self):
        raise LiveError("no estimate (a stub)")


def test_a_garbage_imu_stamp_then_timesync(flight):
    """HIGHRES_IMU with time_usec 0xFFFF000000000000, then TIMESYNC requests: answered on the
    IMU's clock (the reply overflowed int64 in struct.pack: a traceback, no outputs)."""
    tx = new_mavlink(1, 1)
    state = {"done": False}

    def mutate(ev, name, f):
        if name == "highres_imu" and ev.t >= 4.0 and not state["done"]:
            state["done"] = True
            f["time_usec"] = 0xFFFF000000000000
            return [tx.timesync_encode(0, 4_000_000_000)]
        return None

    bufs = datagrams(flight, 6.0, mutate)
    link, stub = FakeLink(bufs), _StubEstimator()
    res = LiveSession(link, stub, flight.calib, LiveOptions(idle_timeout_s=0.2)).run()
    assert res.failure is None and res.exit_reason == "idle"
    (reply,) = link.replies("TIMESYNC")
    assert abs(reply.tc1 - 4_000_000_000) < 0.5e9 and reply.ts1 == 4_000_000_000
    c = res.counts()
    assert c["clock_outliers"] == 1 and c["clock_restarts"] == 0
    assert not any(k.endswith(":off_clock") for k in c["dropped"])
    assert c["slam_sessions"] == 1 and c["source"] == "1/1"
    assert len(stub.events) == len(bufs) - 1  # every sensor message passed on
    # A filter behind the link takes the stamp as it is: its output schedule looped for ever
    # on it; now the session ends, its estimate kept (the filter's next state overflows the
    # float32 fields of ODOMETRY: named as the failure, or none).
    t0 = time.monotonic()
    res = LiveSession(
        FakeLink(bufs), msf(flight.calib), flight.calib, LiveOptions(idle_timeout_s=0.2)
    ).run()
    assert time.monotonic() - t0 < 60.0 and res.estimate is not None
    assert res.failure is None or "OverflowError" in res.failure


def test_angular_rates_follow_an_imu_clock_restart(flight):
    """After the autopilot's clock restarts (9.5 s back) the rate sent with a state is the new
    clock's IMU rate at its time (it was the old clock's sample nearest that time)."""
    tx = new_mavlink(1, 1)
    session = LiveSession(FakeLink(), _StubEstimator(), flight.calib)
    parsers = Parsers()

    def imu(t, w):
        s = ImuSample(t, t, np.array(w, float), np.array([0.0, 0.0, 9.81]))
        buf = pack(tx, tx.highres_imu_encode(**convert.highres_imu_fields(s, 0.0)))
        for m in parsers.parse(buf, PEER):
            session._handle(m, PEER)

    for k in range(200):
        imu(round(9.0 + 0.005 * k, 3), (0.5, 0.0, 0.0))
    for k in range(100):
        imu(round(0.5 + 0.005 * k, 3), (0.0, 0.0, -0.3))
    omega, var = session._rate_at(0.7)
    np.testing.assert_allclose(omega, [0.0, 0.0, -0.3], atol=1e-6)
    assert var is not None and session._imu_t[0] >= 0.5
    # One sample an hour ahead does not enter the history either.
    imu(3600.0, (9.0, 9.0, 9.0))
    imu(0.505 + 0.005 * 99, (0.0, 0.0, -0.3))
    assert max(session._imu_t) <= 1.0


def test_ctrl_c_in_the_batch_solve_ends_it(
    monkeypatch, cli_folder, flight, tmp_path, capsys, keep_signals
):
    """--batch: after the live outputs are written, Ctrl-C interrupts the batch solve (one line,
    exit 130); the session's own handler (asking the finished session to stop) had kept it."""
    import fgnav.commands.live as live_cmd

    seen = {}

    def batch(record, config, out):
        seen["handler"] = signal.getsignal(signal.SIGINT)
        signal.raise_signal(signal.SIGINT)
        time.sleep(1.0)
        seen["not interrupted"] = True

    monkeypatch.setattr(live_cmd, "_batch_at_exit", batch)
    link = FakeLink(datagrams(flight, 4.0))
    rc, out = _run_live_command(
        monkeypatch, cli_folder, tmp_path, link, msf(flight.calib), ["--batch"]
    )
    err = capsys.readouterr().err
    assert rc == 130 and "not interrupted" not in seen
    assert seen["handler"] is signal.default_int_handler
    assert "interrupted: the batch solve (the live outputs in" in err
    assert (tmp_path / "out" / "summary.json").exists()


def test_each_datagram_is_parsed_on_its_own(flight):
    """A stray 2-byte datagram ``FD FF`` (a MAVLink 2 start claiming 255 bytes of payload)
    swallowed the valid messages of the datagrams after it."""
    parsers = Parsers()
    bufs = datagrams(flight, 1.0)
    got = []
    for k, buf in enumerate(bufs):
        if k == 10:
            assert parsers.parse(b"\xfd\xff", PEER) == []
        got += parsers.parse(buf, PEER)
    assert len(got) == len(bufs) and parsers.truncated == 1
    assert all(m.get_type() != "BAD_DATA" for m in got)


@pytest.mark.parametrize("chunk", [256, 7])
def test_a_byte_stream_cut_anywhere_is_parsed_whole(flight, chunk):
    """A byte-stream bridge (socat/ser2net from a telemetry radio) cuts the stream at arbitrary
    bytes: a message split across two datagrams is joined (each datagram parsed on its own had
    lost 57 of 200), while stray bytes still swallow nothing; peers do not mix."""
    bufs = datagrams(flight, 1.0)
    stream = b"".join(bufs)
    parsers = Parsers()
    got, other = [], []
    for i in range(0, len(stream), chunk):
        got += parsers.parse(stream[i : i + chunk], PEER)
        other += parsers.parse(stream[i : i + chunk], ("127.0.0.1", 40002))  # interleaved
    assert len(got) == len(other) == len(bufs) and parsers.truncated == 0
    assert [bytes(m.get_msgbuf()) for m in got] == bufs
    # Stray bytes in the stream, then valid datagrams: all of them parsed.
    parsers = Parsers()
    got = parsers.parse(stream[:1000], PEER) + parsers.parse(b"\xfd\xff", PEER)
    got += parsers.parse(bufs[40] + bufs[41], PEER)
    assert [bytes(m.get_msgbuf()) for m in got[-2:]] == bufs[40:42] and parsers.truncated == 1


def test_the_reader_thread_survives_a_read_error():
    """An unexpected OSError of one recvfrom (it killed the reader thread: the session then
    idled out, every datagram after it unread) is counted and the thread goes on."""
    link = UdpLink("udpin:127.0.0.1:0")
    real = link.sock

    class Sock:
        calls = 0

        def recvfrom(self, n):
            Sock.calls += 1
            if Sock.calls == 1:
                raise OSError(errno.ENOBUFS, "No buffer space available")
            return real.recvfrom(n)

        def __getattr__(self, name):
            return getattr(real, name)

    link.sock = Sock()
    with link:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(b"hello", real.getsockname())
            item = link.get(timeout=3.0)
    assert item is not None and item[0] == b"hello"
    assert link.read_errors == 1


def test_replay_notes_a_peer_that_stopped():
    """fgnav live died at 4 s of a 20 s flight: fgnav replay says so, with the part the record
    covers (it printed the score of the first 4 s as the flight's)."""
    t = np.arange(0.0, 4.0, 0.05) + 100.0
    traj = Trajectory(
        t=t,
        world_t_body=np.zeros((len(t), 3)),
        world_q_body_wxyz=np.tile([1.0, 0, 0, 0], (len(t), 1)),
    )
    res = ReplayResult(
        boot_offset_s=100.0,
        sent={},
        flight_s=20.0,
        wall_s=10.0,
        odometry=traj,
        received={},
        lost={},
        send_errors=12,
        flight_start=100.0,
        flight_end=120.0,
        peer_quiet_s=8.0,
    )
    note = res.peer_stopped()
    assert note is not None and "stopped 16.0 s of flight before the end" in note
    assert "covers 20% of the flight" in note and "8.0 s wall" in note
    assert res.covered_fraction() == pytest.approx(0.1975)
    full = Trajectory(
        t=np.arange(100.0, 119.5, 0.05),
        world_t_body=np.zeros((390, 3)),
        world_q_body_wxyz=np.tile([1.0, 0, 0, 0], (390, 1)),
    )
    res.odometry = full
    assert res.peer_stopped() is None
