from __future__ import annotations

import subprocess
import sys


def _run(*args):
    return subprocess.run(
        [sys.executable, "-m", "fgnav.cli", *args], capture_output=True, text=True, timeout=120
    )


def test_help_lists_subcommands():
    r = _run("--help")
    assert r.returncode == 0
    for name in ("info", "simulate", "batch", "online", "compare", "demo"):
        assert name in r.stdout
