"""``fgnav replay``'s option checks: one line and exit 1 before anything is read or sent."""

from __future__ import annotations

import pytest

pytest.importorskip("pymavlink")

from fgnav.cli import main  # noqa: E402


@pytest.mark.parametrize(
    ("flag", "value"),
    [("--wait-peer", "-1"), ("--wait-peer", "nan"), ("--linger", "-2"), ("--linger", "inf")],
)
def test_replay_refuses_a_negative_or_non_finite_wait(tmp_path, capsys, flag, value):
    """A negative ``--wait-peer`` / ``--linger`` was taken as 0 and a NaN one waited without
    end; both are refused as ``--speed`` is. The flight path does not exist: the check comes
    first."""
    argv = ["replay", str(tmp_path / "none"), "--mavlink", "udpout:127.0.0.1:14599"]
    assert main([*argv, flag, value]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith(f"fgnav replay: error: {flag} ")
    assert "expected a finite number of seconds >= 0" in err[0]


def test_replay_names_the_streams_asked_for_when_the_flight_has_none(tmp_path, capsys):
    """``--streams flow`` on a flight without flow named an empty list (``none of the streams []
    to send``); it names the streams asked for and those the flight has."""
    from fgnav.datasets.native import write_flight
    from fgnav.datasets.simulate import SimOptions, simulate

    flight = simulate("hover", seed=0, options=SimOptions(duration=1.0, images=False))
    folder = write_flight(flight, tmp_path / "hover")
    argv = ["replay", str(folder), "--mavlink", "udpout:127.0.0.1:14599", "--wait-peer", "0"]
    assert main([*argv, "--streams", "flow"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "has none of the streams ['flow'] to send" in err[0]
    assert "'imu'" in err[0] and "'slam'" in err[0]
