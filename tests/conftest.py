"""Shared fixtures: paths to the shared real data (skipped when absent) and a CLI runner."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import settings

settings.register_profile("default", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile("default")
"""Hypothesis draws the same examples on every run of the suite (a CI result can be reproduced);
``--hypothesis-profile=explore`` draws new ones each run, to look for new faults."""

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
TEST_DATA = Path(__file__).resolve().parent / "data"


def shared_path(*parts: str) -> Path:
    """A file under ../shared/data; the test is skipped (with the reason) when it is absent."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.skip(
            f"shared data not present: {path} (data kept out of the repository: its licence "
            "does not allow copying it, or it is large; see docs/how-to/test-data.md)"
        )
    return path


def run_cli(
    *args: str, cwd: Path | None = None, timeout: float = 600
) -> subprocess.CompletedProcess:
    """Run ``imupipe ARGS`` in a subprocess (as a user would); returns the completed process."""
    return subprocess.run(
        [sys.executable, "-m", "imupipe.pipeline.cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=timeout,
    )


@pytest.fixture
def cli():
    return run_cli
