"""The fault-injection campaign's contract, checked after every invocation (``tests/test_fault_*``).

After any input, however hostile, a command must:

- exit 0, or exit 2 with exactly one line ``imupipe: error: ...`` on stderr (``convert`` exits 1
  when some logs of a fleet failed: one line per failed log); never a traceback;
- leave its inputs byte for byte as they were (``lost``/``altered`` inputs);
- write nothing outside its output folder, and no temporary file (``.<name>.<pid>@<host>...tmp``)
  anywhere (``left behind``);
- on failure, leave no output at all from that invocation.

Each check adds to :data:`TALLY` (cases, clean, lost, altered, left behind); with
``IMUPIPE_FAULT_TALLY=FILE`` set, the totals are written to FILE as JSON at exit (the figures in
the robustness page of the docs come from it).
"""

from __future__ import annotations

import atexit
import collections
import contextlib
import hashlib
import io
import json
import os
import signal
from collections.abc import Iterable
from pathlib import Path

from imupipe.pipeline.cli import main

TALLY: collections.Counter[str] = collections.Counter()


def _write_tally() -> None:
    target = os.environ.get("IMUPIPE_FAULT_TALLY")
    if target and TALLY:
        old = json.loads(Path(target).read_text()) if Path(target).exists() else {}
        for key, n in TALLY.items():
            old[key] = old.get(key, 0) + n
        Path(target).write_text(json.dumps(old, indent=1, sort_keys=True) + "\n")


atexit.register(_write_tally)


def snapshot(root: Path) -> dict[str, str]:
    """Relative path -> SHA-256 of every file under ``root`` (folders as ``dir``)."""
    out = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        if path.is_file() and not path.is_symlink():
            out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            out[rel] = "dir" if path.is_dir() else "other"
    return out


def temps(root: Path) -> list[str]:
    """Temporary outputs under ``root``."""
    return sorted(p.relative_to(root).as_posix() for p in root.rglob(".*.tmp"))


def cli(*argv: str | os.PathLike[str]) -> tuple[int, str]:
    """Run the command line in this process (fast enough for many generated cases): (exit
    status, stderr)."""
    err = io.StringIO()
    sigterm = signal.getsignal(signal.SIGTERM)  # main() installs its own: give pytest's back
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:  # argparse
            code = exc.code if isinstance(exc.code, int) else 2
        finally:
            signal.signal(signal.SIGTERM, sigterm)
    return code, err.getvalue()


def check(
    case: str,
    code: int,
    stderr: str,
    root: Path,
    before: dict[str, str],
    out_dirs: Iterable[Path],
    *,
    fleet: bool = False,
) -> None:
    """Assert the contract for one invocation in ``root`` (which holds its inputs and its output
    folders ``out_dirs``); ``before`` is :func:`snapshot` of ``root`` taken before it ran."""
    TALLY["cases"] += 1
    after = snapshot(root)
    outs = [Path(d).relative_to(root).as_posix() for d in out_dirs]

    def inside(rel: str) -> bool:
        return any(rel == o or rel.startswith(o + "/") for o in outs)

    lost = [p for p in before if p not in after]
    altered = [p for p in before if p in after and after[p] != before[p] and not inside(p)]
    outside = [p for p in after if p not in before and not inside(p)]
    left = temps(root)
    TALLY["lost"] += bool(lost)
    TALLY["altered"] += bool(altered)
    TALLY["written outside"] += bool(outside)
    TALLY["left behind"] += bool(left)
    lines = stderr.strip().splitlines()
    errors = [line for line in lines if line.startswith("imupipe: error: ")]
    allowed = (0, 1, 2) if fleet else (0, 2)
    one_line = code == 0 or (
        errors and (len(errors) == 1 or (fleet and code == 1)) and "Traceback" not in stderr
    )
    clean = code in allowed and bool(one_line) and not (lost or altered or outside or left)
    TALLY["clean"] += clean
    TALLY[f"exit {code}"] += 1
    assert code in allowed, f"{case}: exit {code}: {stderr}"
    assert "Traceback" not in stderr, f"{case}: {stderr}"
    if code != 0:
        assert errors, f"{case}: exit {code} without an error line: {stderr!r}"
        if not fleet or code == 2:
            assert len(errors) == 1, f"{case}: {len(errors)} error lines: {stderr}"
    assert not lost, f"{case}: inputs lost: {lost}"
    assert not altered, f"{case}: inputs altered: {altered}"
    assert not outside, f"{case}: written outside the output folder: {outside}"
    assert not left, f"{case}: temporary files left: {left}"
    if code == 2:
        new = [p for p in after if p not in before]
        assert not new, f"{case}: a failed command left outputs: {new}"
