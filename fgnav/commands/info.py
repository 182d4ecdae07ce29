"""``fgnav info FLIGHT``: streams, rates, durations, gaps and time overlap of a flight."""

from __future__ import annotations

import argparse
from typing import Any

from fgnav.commands import nonempty_path
from fgnav.datasets.errors import FgnavError
from fgnav.datasets.load import SUPPORTED, load_flight
from fgnav.info import flight_info

HELP = "streams, rates, durations, gaps and time overlap of a flight"


def parse_topics(pairs: list[str] | None) -> dict[str, str] | None:
    """``["imu=/mavros/imu/data", ...]`` -> ``{"imu": "/mavros/imu/data"}`` (None when empty)."""
    if not pairs:
        return None
    topics: dict[str, str] = {}
    for pair in pairs:
        name, sep, topic = pair.partition("=")
        if not sep or not name or not topic:
            raise FgnavError(f"--topics: expected name=topic, got {pair!r}")
        topics[name] = topic
    return topics


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("flight", type=nonempty_path, help="flight input: " + "; ".join(SUPPORTED))
    parser.add_argument(
        "--topics",
        nargs="+",
        metavar="NAME=TOPIC",
        help="ROS bags: fgnav stream name -> topic, e.g. imu=/mavros/imu/data",
    )


def body_frame_lines(meta: dict[str, Any]) -> list[str]:
    """Lines describing a converted body frame (``meta["body_from_imu"]``), or none."""
    R = meta.get("body_from_imu")
    if R is None:
        return []
    out = ["", f"body frame {meta.get('body_frame', '?')} (v_body = body_from_imu @ v_imu)"]
    out += [f"  [{', '.join(f'{x:+.4f}' for x in row)}]" for row in R]
    if "thrust_axis_imu" in meta:
        axis = ", ".join(f"{x:+.4f}" for x in meta["thrust_axis_imu"])
        out.append(f"  thrust axis in the IMU frame: [{axis}]")
    return out


def run(args: argparse.Namespace) -> int:
    flight = load_flight(args.flight, topics=parse_topics(args.topics))
    print("\n".join([flight_info(flight).format(), *body_frame_lines(flight.meta)]))
    return 0
