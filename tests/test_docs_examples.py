"""Every config example in the README and the docs is checked, and every tutorial is run.

- Every ```toml block that holds ``[inputs]`` or ``[[stages]]`` is loaded by the config parser
  (input files replaced by empty placeholders), so a renamed or mistyped key fails here.
- Pages under ``docs/tutorials/`` and ``docs/how-to/`` and the README's walk-through run as
  written: each block ```toml title="NAME" is written to NAME in a fresh folder, then the
  ```bash blocks run in order (lines that open a viewer, serve docs or install packages are
  skipped), then the page's ```python blocks, in order, as one script, in a fresh folder that
  holds the repository's ``tests/`` and ``examples/`` (the pages say to run from the repository
  root). A page that cannot run without data from outside the repository says so with
  ``<!-- not run: reason -->``. After the run, the page's check in ``tests/page_checks.py`` (if
  it has one) holds the figures and messages the page quotes against that folder and the output
  of each block: each page runs once.
- Issue 38, the kind of the fleet tutorial's dead ends: a page's Python imports only what
  ``pip install -e .`` installs (the standard library, imupipe and its dependencies) unless the
  page says ``pip install <package>``; and no page shows a command in a block that is not run
  (an ``imupipe ...`` command line in a ```text block).
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from page_checks import CHECKS

from imupipe.pipeline.config import load_config

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
TUTORIALS = [
    ROOT / "README.md",
    *sorted((ROOT / "docs" / "tutorials").glob("*.md")),
    *sorted((ROOT / "docs" / "how-to").glob("*.md")),
]
INSTALLED = {  # what `pip install -e .` installs, by import name (pyproject's dependencies)
    "imupipe", "numpy", "scipy", "pyarrow", "mcap", "mcap_ros2", "rosbags", "rerun", "rich",
    "lz4", "zstandard", "backports", "pyulog", "yaml", "pygeomag",
}  # fmt: skip
COMMAND = re.compile(r"^\$?\s*imupipe (run|convert|survey|inspect|simulate|import)\b(?!:)")
SLOW_PAGES: set[str] = set()
"""Pages whose run takes more than a minute of CPU (marked slow)."""
BLOCK = re.compile(r"^```(\w+)([^\n]*)\n(.*?)^```", re.MULTILINE | re.DOTALL)
TITLE = re.compile(r'title="([^"]+)"')
SKIPPED_COMMANDS = ("rerun ", "mkdocs ", "pip ", "open ", "xdg-open ", "ray start", "ray stop")


def blocks(page: Path, language: str) -> list[tuple[str, str]]:
    """(info string, body) of every fenced block of ``language`` on ``page``."""
    text = page.read_text(encoding="utf-8")
    return [(info, body) for lang, info, body in BLOCK.findall(text) if lang == language]


def config_blocks() -> list[tuple[str, str]]:
    found = []
    for page in PAGES:
        for i, (_, body) in enumerate(blocks(page, "toml")):
            raw = tomllib.loads(body)
            if "inputs" in raw or "stages" in raw:
                found.append((f"{page.relative_to(ROOT)}#{i}", body))
    return found


def _placeholders(raw: dict, base: Path) -> None:
    """Empty files (or folders) where the config's input paths point."""
    for spec in raw.get("inputs", {}).values():
        paths = [spec.get("path")] + [spec.get("csv", {}).get("gyro_file")]
        for rel in filter(None, paths):
            path = base / rel
            if path.exists():
                continue
            path.parent.mkdir(parents=True, exist_ok=True)
            if path.suffix:
                path.touch()
            else:
                path.mkdir()


@pytest.mark.parametrize(("where", "body"), config_blocks(), ids=lambda v: str(v)[:60])
def test_config_example_is_valid(where: str, body: str, tmp_path: Path) -> None:
    raw = tomllib.loads(body)
    if "inputs" not in raw:  # a fragment showing stages: give it one input
        body = '[inputs.data]\npath = "data.csv"\n\n' + body
        raw = tomllib.loads(body)
    _placeholders(raw, tmp_path)
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(body, encoding="utf-8")
    load_config(cfg)


def tutorial_pages() -> list:
    return [
        pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW_PAGES else p
        for p in TUTORIALS
        if blocks(p, "bash") or blocks(p, "python")
    ]


def imported(code: str) -> set[str]:
    """The top-level modules a Python block imports."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(code)):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("page", TUTORIALS, ids=lambda p: p.name)
def test_page_needs_only_what_it_installs(page: Path) -> None:
    """A page's Python needs nothing beyond ``pip install -e .`` that it does not name, and
    every command it shows is in a block the run below runs (a ```bash block)."""
    text = page.read_text(encoding="utf-8")
    for _info, body in blocks(page, "python"):
        for name in sorted(imported(body) - INSTALLED - set(sys.stdlib_module_names)):
            assert re.search(rf"pip install [^`\n]*\b{name}\b", text), (
                f"{page.name}: imports {name}, which `pip install -e .` does not install: say "
                f"`pip install {name}` on the page"
            )
    for lang in {lang for lang, _, _ in BLOCK.findall(text)} - {"bash"}:
        for _info, body in blocks(page, lang):
            shown = [line for line in body.splitlines() if COMMAND.match(line)]
            assert not shown, f"{page.name}: a command in a ```{lang} block is never run: {shown}"


@pytest.mark.parametrize("page", tutorial_pages(), ids=lambda p: p.name)
def test_tutorial_runs_as_written(page: Path, tmp_path: Path) -> None:
    text = page.read_text(encoding="utf-8")
    reason = re.search(r"<!-- not run: (.*?) -->", text)
    if reason:
        pytest.skip(reason.group(1))
    for folder in ("tests", "examples"):
        (tmp_path / folder).symlink_to(ROOT / folder, target_is_directory=True)
    for info, body in blocks(page, "toml"):
        title = TITLE.search(info)
        if title:
            (tmp_path / title.group(1)).write_text(body, encoding="utf-8")
    bin_dir = str(Path(sys.executable).parent)
    env = {**os.environ, "PATH": bin_dir + os.pathsep + os.environ.get("PATH", "")}
    results = []
    for _info, body in blocks(page, "bash"):
        lines = [
            line
            for line in body.splitlines()
            if line.strip() and not line.strip().startswith(SKIPPED_COMMANDS)
        ]
        script = "set -euo pipefail\n" + "\n".join(lines)
        done = _run(["bash", "-c", script], tmp_path, env)
        assert done.returncode == 0, f"{page.name}: {script}\n{done.stderr[-3000:]}"
        results.append(done)
    script = "\n".join(body for _info, body in blocks(page, "python"))
    if script:  # after the commands that make its files, as a reader runs the page
        done = _run([sys.executable, "-c", script], tmp_path, env)
        assert done.returncode == 0, f"{page.name}: python\n{done.stderr[-3000:]}"
        results.append(done)
    check = CHECKS.get(page.relative_to(ROOT).as_posix())
    if check:  # the figures and messages the page quotes, on this run
        check(tmp_path, text, results)


def _run(args: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
