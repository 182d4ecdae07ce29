"""A MAVLink 2 link over UDP: the socket is read on its own thread into a queue.

Addresses follow pymavlink's ``mavutil`` spelling: ``udpin:HOST:PORT`` listens on HOST:PORT and
answers whoever sends to it (``fgnav live``, like a companion computer's MAVLink router
endpoint); ``udpout:HOST:PORT`` sends to HOST:PORT from an ephemeral port and receives the
replies there (``fgnav replay``, the autopilot's side).

Nothing is lost while the consumer is busy: a reader thread does nothing but ``recvfrom`` into
an unbounded queue (datagrams and their source address), and the socket's receive buffer is
asked to be :data:`RCVBUF_BYTES` (the kernel caps it at ``net.core.rmem_max``). Parsing (by
pymavlink's generated MAVLink 2 parser of the ``common`` dialect, one per peer so that streams
never mix) and everything else happen on the consumer's thread. Messages that still go missing
show up in the sequence-number counts (:class:`fgnav.live.inbound.SequenceCounter`).

Datagrams (:class:`Parsers`). An autopilot's datagram holds whole messages, but a byte-stream
bridge (socat or ser2net from a telemetry radio) cuts the stream at arbitrary bytes, and stray
bytes happen (``FD FF``: a MAVLink 2 start claiming a 255-byte payload, which had swallowed the
valid messages of the datagrams after it). So a peer's bytes left at the end of a datagram (a
partial frame) are kept; the next datagram is parsed on its own when it begins with a start
byte (``0xFD``, ``0xFE``) and its first message, from its first byte, passes its CRC check (the
leftover is then dropped and counted ``truncated``), else after the leftover. (A datagram that
begins with a message of another dialect, whose CRC pymavlink cannot check, is parsed after the
leftover.)
"""

from __future__ import annotations

import errno
import logging
import queue
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any

from fgnav.datasets.errors import FgnavError

log = logging.getLogger(__name__)

RCVBUF_BYTES = 4 * 1024 * 1024
"""Receive buffer asked of the kernel [bytes] (Linux's default cap, ``rmem_max``, is 4 MiB)."""

MAX_DATAGRAM = 65535
READ_TIMEOUT_S = 0.2
"""The reader thread's socket timeout: how often it checks that it should stop."""


class LinkError(FgnavError, OSError):
    """A MAVLink address that cannot be used (bad spelling, port taken) or pymavlink missing."""


def mavlink_dialect():
    """pymavlink's generated MAVLink 2 ``common`` dialect module (a clear error without it)."""
    try:
        from pymavlink.dialects.v20 import common
    except ModuleNotFoundError as e:
        raise LinkError("the live link needs pymavlink: pip install -e '.[live]'") from e
    return common


def new_mavlink(system_id: int, component_id: int):
    """A MAVLink 2 encoder/parser (``common``) that marks what it sends as sysid/compid and
    parses robustly (bad bytes become ``BAD_DATA`` messages, never exceptions)."""
    mav = mavlink_dialect().MAVLink(None, srcSystem=int(system_id), srcComponent=int(component_id))
    mav.robust_parsing = True
    return mav


def pack(mav: Any, msg: Any) -> bytes:
    """Encode ``msg`` with ``mav``'s ids and sequence number, then advance the sequence (what
    pymavlink's ``MAVLink.send`` does around ``pack``; ``pack`` alone repeats the number)."""
    buf = msg.pack(mav)
    mav.seq = (mav.seq + 1) % 256
    mav.total_packets_sent += 1
    mav.total_bytes_sent += len(buf)
    return buf


@dataclass(frozen=True)
class Address:
    """A parsed ``udpin:HOST:PORT`` / ``udpout:HOST:PORT``."""

    mode: str  # "udpin" or "udpout"
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.mode}:{self.host}:{self.port}"


def parse_address(text: str) -> Address:
    """``udpin:HOST:PORT`` or ``udpout:HOST:PORT`` -> :class:`Address` (one-line error else)."""
    parts = text.split(":")
    if len(parts) != 3 or parts[0] not in ("udpin", "udpout"):
        raise LinkError(
            f"--mavlink {text!r}: expected udpin:HOST:PORT or udpout:HOST:PORT "
            "(e.g. udpin:127.0.0.1:14550)"
        )
    mode, host, port = parts
    try:
        p = int(port)
    except ValueError:
        p = -1
    if not 0 <= p <= 65535 or not host:
        raise LinkError(f"--mavlink {text!r}: bad host or port")
    return Address(mode, host, p)


class UdpLink:
    """A UDP socket read on a thread (see the module docstring).

    Args:
        address: ``udpin:...`` binds HOST:PORT; ``udpout:...`` connects to HOST:PORT.
        rcvbuf_bytes: receive buffer to ask for.
    """

    def __init__(self, address: str | Address, rcvbuf_bytes: int = RCVBUF_BYTES) -> None:
        self.address = parse_address(address) if isinstance(address, str) else address
        a = self.address
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, int(rcvbuf_bytes))
        self.rcvbuf_bytes = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        try:
            if a.mode == "udpin":
                self.sock.bind((a.host, a.port))
            else:
                self.sock.connect((a.host, a.port))
        except OSError as e:
            self.sock.close()
            raise LinkError(f"--mavlink {a}: {e.strerror or e}") from e
        self.sock.settimeout(READ_TIMEOUT_S)
        self.queue: queue.Queue[tuple[bytes, tuple[str, int], float]] = queue.Queue()
        self.peers: dict[tuple[str, int], float] = {}  # address -> wall time last heard
        self.datagrams = 0
        self.bytes = 0
        self.send_errors = 0
        self.read_errors = 0
        self.queue_max = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="mavlink-reader", daemon=True)

    @property
    def local_address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def start(self) -> UdpLink:
        self._thread.start()
        return self

    def _read(self) -> None:
        sock, q = self.sock, self.queue
        while not self._stop.is_set():
            try:
                data, addr = sock.recvfrom(MAX_DATAGRAM)
            except TimeoutError:
                continue
            except ConnectionRefusedError:  # udpout: nobody listening yet (ICMP unreachable)
                continue
            except OSError as e:
                if self._stop.is_set():
                    return
                # Any other error of one read (a transient ENOBUFS, an ICMP error reported on
                # a udpin socket ...): logged and counted, the thread goes on (it had died, the
                # session then idled out with the datagrams after it unread).
                self.read_errors += 1
                if self.read_errors <= 3 or self.read_errors % 1000 == 0:
                    log.warning("%s: read error %d: %s", self.address, self.read_errors, e)
                time.sleep(0.01)
                continue
            q.put((data, addr, time.monotonic()))

    def get(self, timeout: float) -> tuple[bytes, tuple[str, int], float] | None:
        """The next datagram ``(data, source, wall time)``, or None after ``timeout`` seconds."""
        try:
            item = self.queue.get(timeout=timeout)
        except queue.Empty:
            return None
        self.queue_max = max(self.queue_max, self.queue.qsize() + 1)
        self.datagrams += 1
        self.bytes += len(item[0])
        self.peers[item[1]] = item[2]
        return item

    def send(self, buf: bytes, to: tuple[str, int] | None = None) -> bool:
        """Send one packet (udpout: to the connected peer; udpin: to ``to``, or to every peer
        heard from when None). Returns False when the peer refused (counted)."""
        try:
            if self.address.mode == "udpout":
                self.sock.send(buf)
            elif to is not None:
                self.sock.sendto(buf, to)
            else:
                for peer in list(self.peers):
                    self.sock.sendto(buf, peer)
            return True
        except OSError as e:
            if e.errno in (errno.ECONNREFUSED, errno.EHOSTUNREACH, errno.ENETUNREACH):
                self.send_errors += 1
                return False
            raise

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2 * READ_TIMEOUT_S + 1.0)
        self.sock.close()

    def __enter__(self) -> UdpLink:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()


class Parsers:
    """One MAVLink parser per peer address (a stream parser must not mix two peers' bytes); see
    the module docstring, "Datagrams", for the rule. ``truncated``: partial frames dropped (a
    peer's leftover that the next datagram did not continue)."""

    def __init__(self) -> None:
        self._by_peer: dict[tuple[str, int], Any] = {}
        self._leftover: dict[tuple[str, int], bytes] = {}
        self.truncated = 0

    def parse(self, data: bytes, peer: tuple[str, int]) -> list[Any]:
        p = self._by_peer.get(peer)
        if p is None:
            p = self._by_peer[peer] = new_mavlink(0, 0)
        left = self._leftover.pop(peer, b"")
        out: list[Any] | None = None
        if left and data[:1] in (b"\xfd", b"\xfe"):
            alone = _parse(p, data)
            if alone and _crc_valid(alone[0]) and data.startswith(bytes(alone[0].get_msgbuf())):
                self.truncated += 1  # a new frame starts here: the leftover was cut off
                out = alone
        if out is None:
            out = _parse(p, left + data)
        if p.buf_len() > 0:  # a partial frame at the end: kept for the next datagram
            self._leftover[peer] = bytes(p.buf[p.buf_index :])
        _reset_parser(p)
        return out


def _parse(p: Any, data: bytes) -> list[Any]:
    """The messages of ``data`` from an empty parser (its leftover stays in its buffer)."""
    _reset_parser(p)
    return p.parse_buffer(data) or []


def _crc_valid(msg: Any) -> bool:
    """Whether a parsed message passed its CRC check (``BAD_DATA`` did not; ``UNKNOWN_<id>``, of
    another dialect, was not checked)."""
    name = msg.get_type()
    return name != "BAD_DATA" and not name.startswith("UNKNOWN_")


def _reset_parser(p: Any) -> None:
    """Empty a pymavlink parser's buffer (as its own constructor starts it)."""
    p.buf = bytearray()
    p.buf_index = 0
    p.expected_length = mavlink_dialect().HEADER_LEN_V1 + 2
    p.have_prefix_error = False
