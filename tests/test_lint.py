"""ruff (configured in pyproject.toml) passes on the whole project."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from testutil import PROJECT_ROOT


def test_ruff_check_is_clean():
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    r = subprocess.run(
        [ruff, "check", "fgnav", "factors", "datasets", "scripts", "tests"],
        cwd=PROJECT_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-1000:]
