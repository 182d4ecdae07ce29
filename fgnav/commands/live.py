"""``fgnav live``: the online estimator fed by a MAVLink link (flight controller or
``fgnav replay``), answering with ``ODOMETRY``.

Thin layer over :class:`fgnav.live.session.LiveSession`. ``--calib`` is a native ``calib.yaml``
(:func:`fgnav.datasets.native.read_calib_yaml`). ``--config`` tables: ``[graph]``, ``[online]``
and ``[priors]`` (the ``online`` estimator; ``[priors] sources``, ``drag_k`` as for ``fgnav
online``: the front-end prior stage is fed the link's events), ``[msf-ekf]``, ``[ekf004]``,
``[ukf003]``, ``[cf-ekf]``, ``[ekf-flow002]`` (the filter baseline of that name,
:mod:`fgnav.live.estimators`), ``[live]`` (:class:`fgnav.live.session.LiveOptions`: idle
timeout, heartbeat rate, MAVLink ids).

It stops on SIGINT/SIGTERM (Ctrl-C), after ``--duration`` wall seconds, or after
``--idle-timeout`` wall seconds (default 5) without a message once the first has come; then
writes ``estimate.tum``, ``states.csv`` and ``summary.json`` with the writers of ``fgnav online``
(:func:`fgnav.eval.outputs.write_estimate`), the link's counts under ``summary.json``'s
``extra.live`` (keys: :meth:`fgnav.live.session.LiveResult.counts`), and prints the counts.
With ``--batch`` every event is also kept (:class:`fgnav.solvers.collect.EventCollector`) and
the whole session is smoothed by ``fgnav batch``'s solver at the end, into ``OUT/batch``
(``[graph]``, ``[lm]``, ``[batch]`` tables), what was kept under ``summary.json``'s
``extra.collected``.
"""

from __future__ import annotations

import argparse
import signal
import threading
from pathlib import Path
from typing import Any

from fgnav.commands import add_config_argument, add_out_argument, nonempty_path

HELP = "run the online estimator on a live MAVLink link (udpin:HOST:PORT)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--mavlink", required=True, help="udpin:HOST:PORT to listen on (e.g. udpin:127.0.0.1:14550)"
    )
    parser.add_argument(
        "--calib",
        type=nonempty_path,
        required=True,
        help="calibration file (a flight's calib.yaml)",
    )
    add_out_argument(parser)
    add_config_argument(
        parser,
        "TOML with [graph], [online], [priors], [live] tables and the --estimator filter's "
        "own ([msf-ekf], [ekf004], [ukf003], [cf-ekf], [ekf-flow002]); with --batch also [lm] "
        "and [batch]",
    )
    parser.add_argument(
        "--batch",
        action="store_true",
        help="also keep every measurement received and, at the end, smooth the whole session "
        "with the batch solver (written to OUT/batch, as fgnav batch writes a flight)",
    )
    parser.add_argument(
        "--duration", type=float, default=None, help="stop after S wall seconds (default: never)"
    )
    parser.add_argument(
        "--idle-timeout",
        type=float,
        default=None,
        help="stop after S wall seconds without a message, once one came (default 5; 0: never)",
    )
    from fgnav.live.estimators import DEFAULT_ESTIMATOR, ESTIMATORS

    parser.add_argument(
        "--estimator",
        default=DEFAULT_ESTIMATOR,
        choices=sorted(ESTIMATORS),
        help=f"what runs on the stream (default {DEFAULT_ESTIMATOR}: the push-API fixed-lag "
        "smoother; msf-ekf: the MSF-style EKF; ekf004: seed 004's EKF (attitude, or the IMU's "
        "estimate without ATTITUDE_QUATERNION; SLAM, range, yaw); ukf003: seed 003's UKF (SLAM, "
        "range, yaw; its states 0.2 s late); cf-ekf: the Crazyflie EKF and ekf-flow002: seed "
        "002's EKF with flow dead reckoning (flow and range))",
    )


def format_counts(counts: dict[str, Any]) -> list[str]:
    """The counts as printed lines: one per stream, then dropped, lost and sent."""
    streams = sorted(set(counts["received"]) | set(counts["used"]) | set(counts["late"]))
    w = max([6, *map(len, streams)])
    lines = [f"{'stream':<{w}} {'received':>9} {'used':>9} {'late':>7}"]
    for s in streams:
        lines.append(
            f"{s:<{w}} {counts['received'].get(s, 0):>9} {counts['used'].get(s, 0):>9} "
            f"{counts['late'].get(s, 0):>7}"
        )
    drop = ", ".join(f"{k} {v}" for k, v in counts["dropped"].items()) or "none"
    lines.append(f"dropped: {drop}")
    lost = ", ".join(f"{k}: {v}" for k, v in counts["lost"].items()) or "none"
    lines.append(f"lost (MAVLink sequence numbers, by sysid/compid): {lost}")
    for key in ("duplicate", "reordered"):
        if counts.get(key):
            lines.append(f"{key}: " + ", ".join(f"{k}: {v}" for k, v in counts[key].items()))
    notes = []
    if counts.get("source"):
        notes.append(f"following {counts['source']}")
    if counts.get("slam_sessions"):
        notes.append(f"SLAM sessions {counts['slam_sessions']}")
    for key in ("clock_restarts", "clock_outliers"):
        if counts.get(key):
            notes.append(f"IMU {key.replace('_', ' ')} {counts[key]}")
    if notes:
        lines.append("; ".join(notes))
    left = ", ".join(f"{k} {v}" for k, v in counts.get("left", {}).items())
    if left:
        lines.append(f"left at the end (still waiting when the stream ended): {left}")
    lines.append("sent: " + (", ".join(f"{k} {v}" for k, v in counts["sent"].items()) or "none"))
    return lines


def run(args: argparse.Namespace) -> int:
    from fgnav.config import check_tables, options_from
    from fgnav.datasets.native import read_calib_yaml
    from fgnav.eval.outputs import summary_extra, write_estimate
    from fgnav.live.estimators import CONFIG_TABLES, make_estimator
    from fgnav.live.link import LinkError, UdpLink, mavlink_dialect
    from fgnav.live.session import LiveError, LiveOptions, LiveSession
    from fgnav.methods import SOURCE_KEY, config_table, load_method_config

    mavlink_dialect()  # pymavlink present, or a one-line error
    tables = ["live", *sorted({t for v in CONFIG_TABLES.values() for t in v})]
    check_tables(args.config, tables + (["graph", "lm", "batch", "priors"] if args.batch else []))
    config = load_method_config(args.config)
    options = options_from(
        LiveOptions,
        config_table(config, "live"),
        source=str(config.get(SOURCE_KEY, "config")),
        section="live",
        duration_s=args.duration,
        idle_timeout_s=args.idle_timeout,
    )
    calib = read_calib_yaml(args.calib)
    estimator = make_estimator(args.estimator, calib, config)
    link = UdpLink(args.mavlink)
    if link.address.mode != "udpin":
        link.close()
        raise LinkError(f"--mavlink {args.mavlink}: fgnav live listens: use udpin:HOST:PORT")
    record = None
    if args.batch:
        from fgnav.methods import check_method_config
        from fgnav.solvers.collect import EventCollector

        check_method_config({k: v for k, v in config.items() if k in ("graph", "lm", "batch")})
        record = EventCollector(calib, name="live")
    session = LiveSession(link, estimator, calib, options, record=record)
    handlers: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            handlers[sig] = signal.signal(sig, lambda *_: session.stop())
    host, port = link.local_address
    idle = "no idle timeout"
    if options.idle_timeout_s:
        idle = f"idle timeout {options.idle_timeout_s:g} s"
    print(
        f"live: listening on udpin:{host}:{port}, estimator {args.estimator}, {idle}; "
        "stop with Ctrl-C",
        flush=True,
    )
    try:
        result = session.run()
    finally:
        # The session is over: Ctrl-C interrupts what follows (writing, --batch's solve; it had
        # only asked the finished session to stop), one line and exit 130 (fgnav.cli).
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    counts = result.counts()
    print(
        f"live: {result.exit_reason} after {result.wall_s:.1f} s wall; "
        f"{result.link['datagrams']} datagrams, queue max {result.link['queue_max']}"
    )
    for line in format_counts(counts):
        print(line)
    if result.estimate is None:
        failed = f" (the session ended on {result.failure})" if result.failure else ""
        raise LiveError(f"no estimate written: {result.error}{failed}")
    est = result.estimate
    stage = est.info.get("frontend_prior_stage") or {}
    if stage.get("missing_streams"):
        # As fgnav online refuses such a flight; the link could not be checked before it ran.
        from fgnav.frontends.prior_stages import missing_streams_message

        line = missing_streams_message("live", stage["sources"], stage["missing_streams"])
        print(f"warning: {line}; the link carried none: no prior from it")
    extra = summary_extra("live", est, "live")
    extra["live"] = {
        "mavlink": str(link.address),
        "estimator": args.estimator,
        "clock": "autopilot boot clock [s] (time_usec / time_boot_ms)",
        "exit": result.exit_reason,
        "wall_s": result.wall_s,
        "link": result.link,
        "options": vars(options),
        **counts,
    }
    if result.failure:
        extra["live"]["failure"] = result.failure
    paths = write_estimate(est, Path(args.out), extra=extra)
    print(f"wrote {', '.join(str(p) for p in paths.values())}")
    if result.failure:
        # The estimate up to there is written; --batch is not run on a session that failed.
        raise LiveError(f"the session ended on an unexpected {result.failure}")
    if record is not None:
        try:
            _batch_at_exit(record, config, Path(args.out) / "batch")
        except KeyboardInterrupt:
            raise KeyboardInterrupt(
                f"the batch solve (the live outputs in {args.out} are written)"
            ) from None
    return 0


def _batch_at_exit(record: Any, config: dict[str, Any], out: Path) -> None:
    """``--batch``: the session's measurements as a flight, smoothed by the batch solver
    (``fgnav batch``'s ``run_batch``), written to ``out``; a failure is one error line (the live
    outputs are written already)."""
    from fgnav.eval.outputs import summary_extra, write_estimate
    from fgnav.methods import run_batch

    flight = record.flight()
    kept = record.counts()
    print(
        "batch: the session's measurements, "
        + ", ".join(f"{s} {n}" for s, n in kept["kept"].items())
        + (f"; left out {kept['dropped']}" if kept["dropped"] else "")
    )
    est = run_batch(flight, config)
    extra = summary_extra(flight.name, est, "batch")
    extra["collected"] = kept
    paths = write_estimate(est, out, extra=extra)
    print(
        f"batch: {len(est.trajectory)} states over {flight.imu.duration:.1f} s; "
        f"wrote {', '.join(str(p) for p in paths.values())}"
    )
