"""Issue 8: the engines' failure model (pipeline/convert/engines.py) with a local process pool.

Retried: an unexpected exception and a worker process that dies; not retried: bad input
(ImupipeError); one task's failure never stops the others.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest

from imupipe.pipeline.convert import engines
from imupipe.pipeline.convert.engines import run_tasks
from imupipe.pipeline.errors import ReadError


def _first_attempt(marker: Path) -> bool:
    """True on the first call for ``marker`` (the marker file then exists)."""
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return False
    os.close(fd)
    return True


def work(task: tuple[str, Path]) -> str:
    """Module-level so the pool's workers can import it."""
    kind, marker = task
    if kind == "flaky" and _first_attempt(marker):
        raise OSError("disk hiccup")
    if kind == "dies" and _first_attempt(marker):
        os._exit(3)
    if kind == "killer":
        os._exit(9)
    if kind == "bad":
        raise ReadError(f"{marker}: not a log")
    if kind == "broken":
        raise RuntimeError("always fails")
    return f"{kind} ok in {os.getpid()}"


def _run(tasks, **kw):
    outcomes = {}
    run_tasks(work, tasks, lambda o: outcomes.__setitem__(o.task[0], o), **kw)
    return outcomes


def test_failures_are_isolated_and_retried(tmp_path):
    tasks = [(k, tmp_path / k) for k in ("ok", "flaky", "dies", "killer", "bad", "broken")]
    out = _run(tasks, engine="local", jobs=2, retries=2)
    assert set(out) == {"ok", "flaky", "dies", "killer", "bad", "broken"}
    assert out["ok"].error is None
    # an exception other than bad input is retried and succeeds the second time; when a
    # neighbour kills the pool before the first failure is delivered, that attempt is lost
    # with the pool and not charged (exact counts: test_exceptions_are_retried_exactly)
    assert out["flaky"].error is None and out["flaky"].attempts in (1, 2)
    # a worker process that dies is replaced and its task run again (tasks that were in flight
    # beside it are not charged an attempt: they are rerun one by one to find the culprit)
    assert out["dies"].error is None and (tmp_path / "dies").exists()
    # a task that kills its worker every time is charged each time, then reported
    assert out["killer"].attempts == 3
    assert out["killer"].error == "the worker process died (killed or out of memory)"
    # bad input is final at once, and says what and where
    assert out["bad"].attempts == 1 and out["bad"].error == f"{tmp_path / 'bad'}: not a log"
    # a persistent failure is tried 1 + retries times, then reported with its cause
    assert out["broken"].attempts == 3
    assert out["broken"].error.startswith("RuntimeError: always fails")


def test_exceptions_are_retried_exactly(tmp_path):
    tasks = [(k, tmp_path / k) for k in ("ok", "flaky", "broken")]
    out = _run(tasks, engine="local", jobs=2, retries=2)
    assert out["ok"].error is None and out["ok"].attempts == 1
    assert out["flaky"].error is None and out["flaky"].attempts == 2
    assert out["broken"].attempts == 3
    assert out["broken"].error.startswith("RuntimeError: always fails")


def test_no_retries(tmp_path):
    out = _run([("flaky", tmp_path / "f")], engine="local", jobs=1, retries=0)
    assert out["flaky"].attempts == 1 and "OSError: disk hiccup" in out["flaky"].error


def pid_after(task: float) -> int:
    """Module-level so the pool's workers can import it: the process that ran the task."""
    time.sleep(task)
    return os.getpid()


def test_driver_works_while_its_pool_starts(tmp_path):
    # issue 39: the driver runs tasks itself until the pool is up, then the pool takes the rest;
    # every task runs once and is reported once, whoever ran it
    outcomes = []
    run_tasks(pid_after, [0.05] * 40, outcomes.append, jobs=2, driver_helps=True)
    assert sorted(o.index for o in outcomes) == list(range(40))
    assert all(o.error is None and o.attempts == 1 for o in outcomes)
    pids = [o.result for o in outcomes]
    assert os.getpid() in pids  # the first task at least: no pool is up at once
    assert set(pids) - {os.getpid()}  # and the pool took the rest (2 s of work inline else)


def test_failures_while_the_driver_helps(tmp_path):
    # the same outcomes for a task run by the driver or by a worker (a task that kills its
    # process is not run here: in the driver it would end the command, as with --jobs 1)
    tasks = [(k, tmp_path / k) for k in ("ok", "flaky", "bad", "broken", "ok2", "ok3")]
    out = _run(tasks, engine="local", jobs=2, retries=2, driver_helps=True)
    assert out["ok"].error is None and out["ok2"].error is None and out["ok3"].error is None
    assert out["flaky"].error is None and out["flaky"].attempts == 2
    assert out["bad"].attempts == 1 and out["bad"].error == f"{tmp_path / 'bad'}: not a log"
    assert out["broken"].attempts == 3
    assert out["broken"].error.startswith("RuntimeError: always fails")


def test_the_probe_sees_an_idle_fork_server_before_its_deadline():
    # the pool's workers start once the fork server has imported its modules; the probe must
    # see that (Linux: the server asleep in epoll_wait), not wait for its time limit
    if not sys.platform.startswith("linux"):
        pytest.skip("the probe reads /proc (Linux); elsewhere it says ready at once")
    engines.start_forkserver(pid_after)
    probe = engines._ForkServerProbe()
    start = time.monotonic()
    while not probe.ready():
        time.sleep(0.01)
    assert time.monotonic() - start < engines.SERVER_WAIT_S - 0.5


def stage_and_wait(folder: str) -> str:
    """A task that stages an output (a temporary file beside it) and stays busy."""
    from imupipe.pipeline.atomic import staged_outputs

    with staged_outputs() as out:
        out.path(Path(folder) / "part.parquet").write_bytes(b"x")
        (Path(folder) / "staged").write_text("")
        time.sleep(30)
    return "done"


def test_a_stopped_pool_lets_busy_workers_remove_their_temporary_files(tmp_path):
    """``_stop_pool`` gives a busy worker SIGTERM and time to unwind its task (its staged output
    discarded). It read the pool's workers after ``shutdown()``, which empties that table, so
    none got SIGTERM and the busy one was SIGKILLed, its temporary file left behind (seen as
    ``survey --jobs 2`` stopped by SIGTERM)."""
    import multiprocessing as mp

    ctx = mp.get_context("forkserver")
    engines._start_forkserver(ctx, [__name__])
    pool = engines._start_pool(ctx, 1)
    future = pool.submit(engines.guarded, stage_and_wait, str(tmp_path))
    deadline = time.monotonic() + 60
    while not (tmp_path / "staged").exists():
        assert time.monotonic() < deadline and not future.done()
        time.sleep(0.02)
    engines._stop_pool(pool)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["staged"]
