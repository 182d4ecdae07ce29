from __future__ import annotations

from testutil import run_cli


def test_help_lists_subcommands():
    r = run_cli("--help")
    assert r.returncode == 0
    for name in ("info", "simulate", "batch", "online", "compare", "demo"):
        assert name in r.stdout
