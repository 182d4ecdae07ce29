"""One entry point that reads a flight from any supported input, chosen by what the path is.

- folder with ``meta.json``: :func:`fgnav.datasets.native.read_flight`;
- ``*.toml`` file: :func:`fgnav.datasets.manifest.read_manifest`;
- EuRoC ``mav0`` folder (or its parent): :func:`fgnav.datasets.euroc.read_euroc_folder`;
- ``*.ulg`` file: ``fgnav.datasets.ulog.read_ulog``;
- ``*.bag`` file, ROS 2 bag folder (has ``metadata.yaml``) or its ``*.db3``/``*.mcap`` file:
  ``fgnav.datasets.rosbag.read_bag`` (``topics`` maps fgnav stream names to topic names);
- any other file that is a Crazyflie SD-card log (recognised by its content, not its name:
  magic byte, version, the whole header and the CRC-32 check;
  :func:`fgnav.datasets.crazyflie.is_crazyflie_log`): ``fgnav.datasets.crazyflie.read_crazyflie``.
  A file that starts with the log's magic byte but fails a check is an error giving the reason.

The ULog and ROS readers are imported only when such a file is read (their dependencies are
heavier). Anything else is an error naming the path and listing these formats.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from .errors import FlightDataError, FlightFormatError
from .types import Flight, check_imu_clock

SUPPORTED = (
    "fgnav flight folder (with meta.json)",
    "flight manifest (*.toml)",
    "EuRoC/ASL mav0 folder",
    "PX4 ULog (*.ulg)",
    "ROS 1 bag (*.bag)",
    "ROS 2 bag folder (with metadata.yaml) or its *.db3/*.mcap file",
    "Crazyflie SD-card log (any name; recognised by header and CRC)",
)

BAG_SUFFIXES = (".bag", ".db3", ".mcap")


def lazy_reader(module: str, function: str, path: Path):
    """``fgnav.datasets.<module>.<function>``, imported now; a missing module is an error naming
    ``path``."""
    try:
        mod = importlib.import_module(f"fgnav.datasets.{module}")
    except ModuleNotFoundError as e:
        if e.name == f"fgnav.datasets.{module}":
            raise FlightFormatError(
                path, f"reading this format needs fgnav.datasets.{module}, which this install lacks"
            ) from e
        raise
    return getattr(mod, function)


def _is_euroc(p: Path) -> bool:
    return (p / "imu0" / "data.csv").is_file() or (p / "mav0" / "imu0" / "data.csv").is_file()


def _starts_with(p: Path, byte: int) -> bool:
    with p.open("rb") as f:
        return f.read(1) == bytes([byte])


def load_flight(path: str | Path, topics: dict[str, str] | None = None) -> Flight:
    """Read a flight from any supported input (see the module docstring).

    Args:
        path: file or folder.
        topics: for ROS bags only: fgnav stream name -> topic, e.g. ``{"imu": "/mavros/imu/data"}``.

    Raises:
        FlightFormatError: the path is missing, its format is not recognised (the message lists the
            supported ones), ``topics`` was given for a format without topics, or the reader's own
            errors.
    """
    p = Path(path)
    if not p.exists():
        raise FlightFormatError(p, "no such file or folder")
    flight = _load(p, topics)
    if flight.imu is not None:
        try:
            check_imu_clock(f"{flight.name}.imu", flight.imu.t)
        except FlightDataError as e:
            raise FlightFormatError(p, str(e)) from e
    return flight


def _load(p: Path, topics: dict[str, str] | None) -> Flight:
    suffix = p.suffix.lower()
    is_bag = (p.is_file() and suffix in BAG_SUFFIXES) or (
        p.is_dir() and (p / "metadata.yaml").is_file()
    )
    if topics and not is_bag:
        raise FlightFormatError(p, "--topics applies to ROS bags only")
    if p.is_dir():
        if (p / "meta.json").is_file():
            from .native import read_flight

            return read_flight(p)
        if is_bag:
            return lazy_reader("rosbag", "read_bag", p)(p, topics=topics)
        if _is_euroc(p):
            from .euroc import read_euroc_folder

            return read_euroc_folder(p)
        from .native import META_FILE, lost_meta_json

        if have := lost_meta_json(p):
            raise FlightFormatError(
                p,
                f"no {META_FILE}: a native flight folder needs it (this one has "
                + ", ".join(have)
                + ")",
            )
    elif suffix == ".toml":
        from .manifest import read_manifest

        return read_manifest(p)
    elif suffix == ".ulg":
        return lazy_reader("ulog", "read_ulog", p)(p)
    elif is_bag:
        return lazy_reader("rosbag", "read_bag", p)(p, topics=topics)
    elif p.is_file():
        from . import crazyflie

        problem = crazyflie.check_crazyflie_log(p)
        if problem is None:
            return crazyflie.read_crazyflie(p)
        if _starts_with(p, crazyflie.MAGIC):
            raise FlightFormatError(
                p,
                f"starts with the Crazyflie log magic byte 0x{crazyflie.MAGIC:X} but is not "
                f"a readable Crazyflie SD-card log: {problem}",
            )
    raise FlightFormatError(p, "not a recognised flight input; supported: " + "; ".join(SUPPORTED))
