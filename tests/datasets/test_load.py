"""load_flight dispatches on what the path is; unknown inputs are named with the supported list."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
from fgnav.datasets import Flight, FlightFormatError, ImuSeries
from fgnav.datasets.load import load_flight
from fgnav.datasets.native import write_flight


def _imu(n=5):
    return ImuSeries(np.arange(n) * 0.005, np.zeros((n, 3)), np.zeros((n, 3)))


def test_native_folder(tmp_path):
    write_flight(Flight(name="nat", imu=_imu()), tmp_path / "f")
    assert load_flight(tmp_path / "f").name == "nat"


def test_manifest_and_euroc_folder(tmp_path):
    mav0 = tmp_path / "seq" / "mav0"
    (mav0 / "imu0").mkdir(parents=True)
    (mav0 / "imu0/data.csv").write_text(
        "#timestamp [ns],w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z\n"
        "1000000000,0,0,0,9.8,0,0\n1005000000,0,0,0,9.8,0,0\n"
    )
    for p in (tmp_path / "seq", mav0):
        f = load_flight(p)
        assert f.name == "seq" and len(f.imu) == 2 and f.imu.t[1] == 1.005
    (tmp_path / "m.toml").write_text(
        'name = "man"\n[imu]\nformat = "euroc"\npath = "seq/mav0/imu0/data.csv"\n'
    )
    assert load_flight(tmp_path / "m.toml").name == "man"


def _fake_module(monkeypatch, name, function, calls):
    mod = types.ModuleType(f"fgnav.datasets.{name}")

    def reader(path, **kwargs):
        calls.append((function, path, kwargs))
        return Flight(name=function, imu=_imu())

    setattr(mod, function, reader)
    monkeypatch.setitem(sys.modules, f"fgnav.datasets.{name}", mod)


def test_ulog_and_bags_dispatch_lazily(tmp_path, monkeypatch):
    calls: list = []
    _fake_module(monkeypatch, "ulog", "read_ulog", calls)
    _fake_module(monkeypatch, "rosbag", "read_bag", calls)
    (tmp_path / "a.ulg").write_bytes(b"ULog")
    (tmp_path / "b.bag").write_bytes(b"#ROSBAG")
    (tmp_path / "ros2").mkdir()
    (tmp_path / "ros2/metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    assert load_flight(tmp_path / "a.ulg").name == "read_ulog"
    topics = {"imu": "/imu"}
    assert load_flight(tmp_path / "b.bag", topics=topics).name == "read_bag"
    assert load_flight(tmp_path / "ros2").name == "read_bag"
    assert calls == [
        ("read_ulog", tmp_path / "a.ulg", {}),
        ("read_bag", tmp_path / "b.bag", {"topics": topics}),
        ("read_bag", tmp_path / "ros2", {"topics": None}),
    ]


def test_unknown_and_missing(tmp_path):
    (tmp_path / "x.csv").write_text("1,2\n")
    with pytest.raises(
        FlightFormatError,
        match=r"x\.csv: not a recognised flight input; "
        r"supported: fgnav flight folder .*PX4 ULog \(\*\.ulg\).*ROS 2 bag",
    ):
        load_flight(tmp_path / "x.csv")
    with pytest.raises(FlightFormatError, match="not a recognised flight input"):
        load_flight(tmp_path)
    with pytest.raises(FlightFormatError, match=r"nothere\.ulg: no such file or folder"):
        load_flight(tmp_path / "nothere.ulg")
    write_flight(Flight(name="nat", imu=_imu()), tmp_path / "f")
    with pytest.raises(FlightFormatError, match="--topics applies to ROS bags only"):
        load_flight(tmp_path / "f", topics={"imu": "/imu"})


def test_native_folder_without_meta_json_names_the_missing_file(tmp_path):
    """A native flight folder that lost its meta.json was "not a recognised flight input" (and
    the fleet's folder scan left it out without a word); a folder with one unrelated native
    file name is still not taken for a flight."""
    from fgnav.datasets.native import lost_meta_json

    write_flight(Flight(name="nat", imu=_imu()), tmp_path / "f")
    assert lost_meta_json(tmp_path / "f") == []  # (has its meta.json)
    (tmp_path / "f" / "meta.json").unlink()
    assert lost_meta_json(tmp_path / "f") == ["calib.yaml", "imu.csv"]
    with pytest.raises(
        FlightFormatError,
        match=r"/f: no meta\.json: a native flight folder needs it \(this one has calib\.yaml, "
        r"imu\.csv\)$",
    ):
        load_flight(tmp_path / "f")
    (tmp_path / "g").mkdir()
    (tmp_path / "g" / "range.csv").write_text("t [s],range [m]\n0,1\n")
    assert lost_meta_json(tmp_path / "g") == []
    (tmp_path / "g" / "slam.csv").write_text("x\n")
    assert lost_meta_json(tmp_path / "g") == ["range.csv", "slam.csv"]
    (tmp_path / "h").mkdir()
    (tmp_path / "h" / "imu.csv").write_text("x\n")
    assert lost_meta_json(tmp_path / "h") == ["imu.csv"]
    assert lost_meta_json(tmp_path / "h" / "imu.csv") == []
    with pytest.raises(FlightFormatError, match="not a recognised flight input"):
        load_flight(tmp_path / "g" / "range.csv")
