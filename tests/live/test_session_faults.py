"""The live session and its command on faults, without a socket: a stand-in link hands the
session datagrams packed from the 8 s CLI flight (``cli_folder``), as ``fgnav replay`` sends
them. Checks: an unexpected exception keeps the outputs; a garbage IMU stamp and TIMESYNC;
the angular rates after an IMU clock restart; Ctrl-C in the --batch solve; the datagram parser;
the reader thread on a read error; ``fgnav replay``'s note on a peer that stopped."""

from __future__ import annotations

import errno
import math
import signal
import socket
import time

import pytest

pytest.importorskip("pymavlink")

from fgnav.datasets.events import AttitudeSample, ImuSample, RangeReading, replay_flight  # noqa: E402
from fgnav.datasets.native import read_flight  # noqa: E402

from fgnav.live import convert  # noqa: E402
from fgnav.live.estimators import MsfLive  # noqa: E402
from fgnav.live.link import Parsers, UdpLink, new_mavlink, pack, parse_address  # noqa: E402
from fgnav.live.session import LiveError  # noqa: E402

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


def datagrams(flight, t_max: float = math.inf, mutate=None) -> list[bytes]:
    """The flight's messages as fgnav replay packs them (one per datagram), up to ``t_max``;
    ``mutate(ev, name, fields)`` may change the fields or return a list of extra datagrams to
    send after the message."""
    tx, slam_tx = new_mavlink(1, 1), new_mavlink(1, 191)
    c = flight.calib
    out = []
    for ev in replay_flight(flight, STREAMS):
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
