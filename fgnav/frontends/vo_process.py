"""The homography VO stage in a worker process, for the push engine's camera loop.

:class:`HomographyVoStage` is half OpenCV (which releases the GIL) and half Python; on a
worker *thread* its Python hands the GIL back and forth with the smoother's factor callbacks,
and the loop got slower (``bench_online.py --camera`` 8.3x -> 7.4x real time). In a worker
*process* the two run side by side on two cores: the parent sends each frame with the attitude
and height it computed for it (from what has arrived), the child runs the stage and sends back the
measurement, in order. The child holds the stage's whole state (reference frame, pyramid,
dead-reckoned pose); the parent only the frames in flight.

The parent decides when it waits for a frame's measurement (``FixedLagOptions.vo_worker`` and
``vo_process_delay_keyframes``: at the keyframe update that many keyframes after the one that
closes past the frame), so the estimate does not depend on the child's timing. The child is a
fresh interpreter with one OpenCV thread (the parent's smoother has the other core); a frame it
cannot process comes back as the stage's one-line :class:`FlightDataError`.
"""

from __future__ import annotations

import logging
import os
import pickle
import subprocess
import sys
import traceback
import weakref
from collections import deque
from typing import Any

import numpy as np

from fgnav.datasets.errors import FlightDataError

log = logging.getLogger(__name__)
#: Environment variable that passes the parent's logging level to the child.
LOG_LEVEL_ENV = "FGNAV_VO_LOG_LEVEL"
#: The child's log format: the CLI's (``fgnav.cli``), marked as the VO process's.
CHILD_LOG_FORMAT = "%(levelname)s %(name)s (VO process): %(message)s"


def _serve(inp, out, threads: int = 1) -> None:
    """The child: a :class:`HomographyVoStage` made from the first message ``(args, kwargs)``,
    then fed ``(frame, R, h)`` until ``None``; one reply per message."""
    import cv2

    from fgnav.frontends.homography_vo import HomographyVoStage

    cv2.setNumThreads(threads)

    def send(obj) -> None:
        pickle.dump(obj, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()

    try:
        args, kwargs = pickle.load(inp)
        stage = HomographyVoStage(*args, **kwargs)
    except Exception as e:  # noqa: BLE001 - reported to the parent, raised there
        send(("error", type(e).__name__, str(e), traceback.format_exc()))
        return
    send(("ready",))
    while True:
        msg = pickle.load(inp)
        if msg is None:
            send(("done", None, stage.busy_s, dict(stage.counts)))
            return
        try:
            m = stage.process(*msg)
        except Exception as e:  # noqa: BLE001 - reported to the parent, raised there
            send(("error", type(e).__name__, str(e), traceback.format_exc()))
            return
        send(("ok", m, stage.busy_s, dict(stage.counts)))


PIPE_BYTES = 1 << 20
"""Capacity asked for the pipe to the child (Linux ``F_SETPIPE_SZ``; its default limit): a
320x240 frame is 77 kB, more than the default 64 kB, so without it every send waits until the
child has finished the frame before and reads (2.7 ms per frame, the loop serialised again)."""


def _widen_pipe(f) -> None:
    try:
        import fcntl

        fcntl.fcntl(f.fileno(), fcntl.F_SETPIPE_SZ, PIPE_BYTES)
    except (ImportError, AttributeError, OSError):
        pass  # not Linux, or over the system's limit: sends wait for the child


class VoProcess:
    """A :class:`~fgnav.frontends.homography_vo.HomographyVoStage` in a child process.

    Same arguments as the stage. :meth:`submit` sends a frame with its attitude and height,
    :meth:`take` returns the measurements in submission order (waiting for the next one),
    :meth:`close` stops the child and keeps its final ``counts`` and ``busy_s``.

    ``busy_s`` (the child's own time in the stage, wall, on its core) and ``counts`` (the stage's
    counters) are as of the last measurement taken.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.name = kwargs.get("name", "vo")
        # A fresh interpreter (``python -m fgnav.frontends.vo_process``), not multiprocessing:
        # "spawn" re-imports the caller's main module, "fork" copies a process whose OpenCV and
        # GTSAM thread pools may hold locks.
        # The child logs at the parent's level, in the CLI's format (``LOG_LEVEL_ENV``).
        env = {**os.environ, LOG_LEVEL_ENV: str(logging.getLogger().getEffectiveLevel())}
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "fgnav.frontends.vo_process"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        self._out, self._in = self._proc.stdin, self._proc.stdout
        _widen_pipe(self._out)
        self._send((args, kwargs))
        self._inflight: deque[float] = deque()
        self.busy_s = 0.0
        self.counts: dict[str, int] = {}
        self._closed = False
        self._ready = False
        weakref.finalize(self, VoProcess._stop, self._proc)

    def __len__(self) -> int:
        """Frames sent and not yet taken."""
        return len(self._inflight)

    def submit(self, frame, world_R_body: np.ndarray | None, body_height: float | None) -> None:
        if self._closed:
            raise RuntimeError(f"{self.name}: VO process closed")
        self._send((frame, world_R_body, body_height))
        self._inflight.append(float(frame.t))

    def oldest_time(self) -> float | None:
        """Time of the oldest frame in flight (None when none is)."""
        return self._inflight[0] if self._inflight else None

    def take(self):
        """The measurement of the oldest frame in flight (waits for it)."""
        self._inflight.popleft()
        reply = self._recv()
        self.busy_s, self.counts = reply[2], reply[3]
        return reply[1]

    def close(self) -> None:
        """Stop the child (after the frames in flight, whose measurements are dropped) and keep
        its final counters."""
        if self._closed:
            return
        self._closed = True
        while self._inflight:
            self.take()
        self._send(None)
        reply = self._recv()
        self.busy_s, self.counts = reply[2], reply[3]
        self._proc.wait(timeout=10.0)

    def _send(self, obj) -> None:
        try:
            pickle.dump(obj, self._out, protocol=pickle.HIGHEST_PROTOCOL)
            self._out.flush()
        except (BrokenPipeError, OSError):
            self._closed = True
            raise FlightDataError(
                f"{self.name}: the VO process ended unexpectedly (exit code {self._proc.poll()})"
            ) from None

    def _recv(self):
        try:
            if not self._ready:
                self._ready = True
                self._check(pickle.load(self._in))
            reply = pickle.load(self._in)
        except EOFError:
            self._closed = True
            raise FlightDataError(
                f"{self.name}: the VO process ended unexpectedly (exit code {self._proc.poll()})"
            ) from None
        return self._check(reply)

    def _check(self, reply):
        if reply[0] == "error":
            self._closed = True
            kind, msg, tb = reply[1:]
            if kind == "FlightDataError":
                raise FlightDataError(msg)  # a bad frame or option: its one-line message
            log.debug("%s: VO process traceback:\n%s", self.name, tb)
            raise FlightDataError(f"{self.name}: the VO process failed: {kind}: {msg}")
        return reply

    @staticmethod
    def _stop(proc) -> None:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=5.0)
        for f in (proc.stdin, proc.stdout):
            try:
                f.close()
            except OSError:
                pass


if __name__ == "__main__":
    logging.basicConfig(
        level=int(os.environ.get(LOG_LEVEL_ENV, logging.WARNING)), format=CHILD_LOG_FORMAT
    )
    # Replies go to the original stdout only; anything the stage prints goes to stderr.
    _out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    _serve(sys.stdin.buffer, _out)
