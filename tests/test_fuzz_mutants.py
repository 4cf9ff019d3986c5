"""Mutation fuzzing of real logs against the reference libraries (issue 40; ``tests/mutants.py``).

A quick seeded run of 60 mutants (each ULog and DataFlash seed cut to its first 300 kB) in CI;
the campaign of 1,200 (the seeds cut to 500 kB; about 40 minutes on a busy two-core machine)
is marked slow (``IMUPIPE_MUTANTS=N`` sets its size,
``IMUPIPE_MUTANTS_SEED`` its seed). Every mutant must be refused in one line, read with at
least the reference's count of every stream's topic, or read with fewer and a warning saying
what was skipped: no silent loss, no traceback, no hang.
"""

from __future__ import annotations

import collections
import os
import resource

import pytest
from mutants import FAILURES, campaign, chunked_campaign


def _run(tmp_path, count: int, seed: int, limit: int | None, chunked: bool = False) -> None:
    run = chunked_campaign if chunked else campaign
    results = run(count, seed, tmp_path, limit)
    tally = collections.Counter(v.kind for *_, v in results)
    bad = [
        f"{log} ({what}): {v.kind}: {v.detail}" for log, _, what, v in results if v.kind in FAILURES
    ]
    assert not bad, f"{len(bad)} of {len(results)} mutants failed ({dict(tally)}):\n" + "\n".join(
        bad
    )
    assert sum(tally.values()) == count


def test_quick_mutants(tmp_path):
    _run(tmp_path, 60, 40, 300_000)


@pytest.mark.slow
def test_mutation_campaign(tmp_path):
    _run(
        tmp_path,
        int(os.environ.get("IMUPIPE_MUTANTS", "1200")),
        int(os.environ.get("IMUPIPE_MUTANTS_SEED", "2")),
        500_000,
        chunked=True,
    )
    # memory stays bounded by the readers' batches and the files: far below a GB
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss < 2_000_000
