"""``fgnav replay``: send a flight as MAVLink messages, a stand-in autopilot for ``fgnav live``.

Thin layer over :class:`fgnav.live.replay.StandInAutopilot`. ``FLIGHT`` is anything
``fgnav info`` reads. The messages go out in arrival order at ``--speed`` times real time, on a
boot clock that starts at the flight's first sample (the offset is printed). With ``--record``,
the ``ODOMETRY`` the peer sends back is written as a TUM file on the flight's clock in fgnav's
frames, and scored against the flight's ground truth when it has one.
"""

from __future__ import annotations

import argparse
import math

from fgnav.commands import add_flight_argument, nonempty_path

HELP = "send a flight as MAVLink messages to udpout:HOST:PORT (a stand-in autopilot)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_flight_argument(parser)
    parser.add_argument(
        "--mavlink", required=True, help="udpout:HOST:PORT to send to (e.g. udpout:127.0.0.1:14550)"
    )
    parser.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="times real time (default 1; 0: as fast as possible)",
    )
    parser.add_argument(
        "--record", type=nonempty_path, default=None, help="TUM file for the ODOMETRY received back"
    )
    parser.add_argument(
        "--streams",
        default=None,
        help="comma-separated streams to send (default: imu,attitude,range,slam,flow, those the "
        "flight has)",
    )
    parser.add_argument(
        "--wait-peer",
        type=float,
        default=30.0,
        help="wait up to S seconds for the peer's HEARTBEAT before sending (default 30; 0: don't)",
    )
    parser.add_argument(
        "--linger",
        type=float,
        default=2.0,
        help="after the last message, listen for ODOMETRY until none came for S seconds "
        "(default 2)",
    )


def run(args: argparse.Namespace) -> int:
    from fgnav.datasets.errors import FlightDataError
    from fgnav.datasets.load import load_flight
    from fgnav.datasets.tum import write_tum
    from fgnav.live.link import LinkError, UdpLink, mavlink_dialect
    from fgnav.live.replay import SENDABLE_STREAMS, ReplayOptions, StandInAutopilot

    mavlink_dialect()
    if not args.speed >= 0:
        raise LinkError(f"--speed {args.speed}: expected >= 0 (0: as fast as possible)")
    for flag, value in (("--wait-peer", args.wait_peer), ("--linger", args.linger)):
        if not (math.isfinite(value) and value >= 0):
            raise LinkError(f"{flag} {value}: expected a finite number of seconds >= 0")
    streams = (
        SENDABLE_STREAMS
        if args.streams is None
        else tuple(s.strip() for s in args.streams.split(",") if s.strip())
    )
    options = ReplayOptions(
        speed=args.speed, streams=streams, wait_peer_s=args.wait_peer, linger_s=args.linger
    )
    flight = load_flight(args.flight)
    link = UdpLink(args.mavlink)
    if link.address.mode != "udpout":
        link.close()
        raise LinkError(f"--mavlink {args.mavlink}: fgnav replay sends: use udpout:HOST:PORT")
    try:
        autopilot = StandInAutopilot(flight, link, options)
    except Exception:
        link.close()
        raise
    speed = f"{args.speed:g}x real time" if args.speed > 0 else "as fast as possible"
    print(
        f"replay: {flight.name} to {link.address}, streams {','.join(autopilot.streams)}, {speed}; "
        f"boot clock: t_boot = t_flight - {autopilot.offset!r} s",
        flush=True,
    )
    res = autopilot.run()
    sent = ", ".join(f"{k} {v}" for k, v in res.sent.items())
    print(
        f"replay: sent {sent} ({res.flight_s:.1f} s of flight in {res.wall_s:.1f} s wall, "
        f"{res.speed:.2f}x); peer HEARTBEAT {'heard' if res.peer_heartbeat else 'not heard'}"
    )
    n_odo = 0 if res.odometry is None else len(res.odometry)
    lost = ", ".join(f"{k}: {v}" for k, v in res.lost.items()) or "none"
    ts = res.timesync
    ts_txt = (
        f"{ts['replies']} TIMESYNC replies, median tc1 - ts1 {ts['median_tc1_minus_ts1_ms']:.1f} ms"
        if ts["replies"]
        else "no TIMESYNC reply"
    )
    print(f"replay: received {n_odo} ODOMETRY, lost {lost}; {ts_txt}")
    if res.send_errors:
        print(
            f"replay: WARNING: {res.send_errors} packets refused by the peer's host (nobody "
            f"listening on {link.address}: the peer not started yet, or gone)"
        )
    stopped = res.peer_stopped()
    if stopped:
        print(f"replay: WARNING: {stopped}; did the peer die or stall?")
    if args.record is not None:
        if res.odometry is None:
            raise FlightDataError("--record: no ODOMETRY received back; nothing to write")
        write_tum(args.record, res.odometry)
        print(f"wrote {args.record} (flight clock, fgnav frames: world z up, body FLU)")
        if flight.ground_truth is not None:
            from fgnav.estimate import Estimate
            from fgnav.eval.metrics import evaluate

            m = evaluate(Estimate("live", res.odometry, causal=True), flight.ground_truth)
            part = ""
            if stopped:
                part = f", on the first {res.covered_fraction():.0%} of the flight only"
            print(
                f"replay: recorded ODOMETRY vs truth: ATE {m.ate_rmse_m:.4f} m RMSE "
                f"({m.alignment} alignment{part})"
            )
    return 0
