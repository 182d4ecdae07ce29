"""The package layout: fgnav.factors and fgnav.datasets map to top-level folders, nothing is
installed as a top-level `factors` or `datasets`, and every package folder is listed."""

from __future__ import annotations

import importlib
import importlib.util
import tomllib

from testutil import PROJECT_ROOT


def test_subpackages_import_under_fgnav():
    f = importlib.import_module("fgnav.factors")
    d = importlib.import_module("fgnav.datasets")
    assert "factors" in str(f.__file__)
    assert "datasets" in str(d.__file__)


def test_every_package_folder_is_listed_in_pyproject():
    cfg = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(cfg["packages"])
    mapping = {v: k for k, v in cfg["package-dir"].items()}  # folder -> package
    found = set()
    for top, pkg in mapping.items():
        for init in (PROJECT_ROOT / top).rglob("__init__.py"):
            rel = init.parent.relative_to(PROJECT_ROOT / top).parts
            found.add(".".join((pkg, *rel)))
    assert found <= listed, f"package folders missing from pyproject packages: {found - listed}"
    assert "factors" not in listed and "datasets" not in listed
