"""Every config example in the README and the docs is checked, and every tutorial is run.

- Every ```toml block that holds ``[inputs]`` or ``[[stages]]`` is loaded by the config parser
  (input files replaced by empty placeholders), so a renamed or mistyped key fails here.
- Pages under ``docs/tutorials/`` and the README's walk-through run as written: each block
  ```toml title="NAME" is written to NAME in a fresh folder, then the ```bash blocks run in order
  (lines that open a viewer, serve docs or install packages are skipped), in a fresh folder
  that holds the repository's ``tests/`` and ``examples/`` (tutorials run from the repository
  root). A tutorial that cannot run without data from outside the repository says so with
  ``<!-- not run: reason -->``.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from imupipe.pipeline.config import load_config

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
TUTORIALS = [ROOT / "README.md", *sorted((ROOT / "docs" / "tutorials").glob("*.md"))]
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


def tutorial_pages() -> list[Path]:
    return [p for p in TUTORIALS if blocks(p, "bash")]


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
    for _info, body in blocks(page, "bash"):
        lines = [
            line
            for line in body.splitlines()
            if line.strip() and not line.strip().startswith(SKIPPED_COMMANDS)
        ]
        script = "set -euo pipefail\n" + "\n".join(lines)
        done = subprocess.run(
            ["bash", "-c", script],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, f"{page.name}: {script}\n{done.stderr[-3000:]}"
        if page.name == "README.md" and "imupipe run" in script:
            _walkthrough_kept_its_word(text, tmp_path, done.stderr)


def _walkthrough_kept_its_word(readme: str, folder: Path, stderr: str) -> None:
    """The README's walk-through writes only the files it names, and warns about nothing (it
    says "this run has none")."""
    section = readme.split("## Calibrate the IMU in your bag", 1)[1].split("\n## ", 1)[0]
    written = sorted(p.name for p in (folder / "out").iterdir())
    assert written and all(f"`{name}`" in section for name in written), written
    assert "warning" not in stderr, stderr
