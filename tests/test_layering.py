"""The package layering holds: the Python API (the root package ``imupipe``) -> pipeline ->
stages -> the readers' base, no circles inside a package (the contracts are in pyproject.toml,
checked with import-linter), and nothing below the root imports it.

import-linter reads the package from the folders it finds on disk. An editable install
(``pip install -e .``) maps the root package to ``pipeline/python-api/`` and the subpackages to
their own folders, which a folder walk from the root does not reach; so the check runs on a tree
of links laid out as the wheel is (from pyproject's ``[tool.setuptools.package-dir]``), whatever
the install.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def package_tree(where: Path) -> Path:
    """``where/imupipe``: links to the repository's files laid out as the installed package."""
    dirs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    top = where / "imupipe"
    top.mkdir()
    for name in (ROOT / dirs["imupipe"]).iterdir():
        if name.is_file():
            (top / name.name).symlink_to(name)
    for package, folder in dirs.items():
        if package != "imupipe":
            (where / package.replace(".", "/")).symlink_to(ROOT / folder, target_is_directory=True)
    return where


def test_import_contracts_kept(tmp_path: Path) -> None:
    exe = shutil.which("lint-imports")
    if exe is None:
        pytest.skip("import-linter is not installed (pip install -e '.[test]')")
    env = {**os.environ, "PYTHONPATH": str(package_tree(tmp_path))}
    done = subprocess.run(
        [exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300, env=env
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "0 broken" in done.stdout
    analysed = int(done.stdout.split("Analyzed ")[1].split()[0])
    assert analysed > 100, done.stdout  # every subpackage was reached, not the root alone


def test_nothing_below_imports_the_root(tmp_path: Path) -> None:
    """``imupipe.pipeline``, ``.stages`` and ``.readers`` never import ``imupipe`` itself (its
    ``__init__``), which a layers contract cannot say of a package's own ``__init__``."""
    pytest.importorskip("grimp")
    code = (
        "import grimp; g = grimp.build_graph('imupipe', include_external_packages=False, "
        "cache_dir=None); print('\\n'.join(sorted(g.find_modules_that_directly_import('imupipe'))))"
    )
    env = {**os.environ, "PYTHONPATH": str(package_tree(tmp_path))}
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
    )
    assert done.returncode == 0, done.stderr[-2000:]
    below = [
        m
        for m in done.stdout.split()
        if m.startswith(("imupipe.pipeline", "imupipe.stages", "imupipe.readers"))
    ]
    assert below == []
