"""Where conversion tasks run: a local process pool, or a Ray cluster.

An engine calls ``fn(task)`` once per task in worker processes and hands each finished task's
:class:`Outcome` to ``on_done`` in the driver as soon as it is known (in completion order). The
function does all the work (read, correct, write) and returns only a small picklable result.

Failure model, the same for both engines:

- ``fn`` runs inside :func:`guarded`, so an exception never escapes a worker: an
  :class:`~imupipe.pipeline.errors.ImupipeError` (bad input: corrupt file, unknown topic, ...)
  is final and is reported at once; any other exception (a full disk, a network file system
  hiccup, a bug) is retried.
- A worker process that dies (killed, out of memory, segfault; a lost Ray node) fails the tasks
  it was running; they are retried in a fresh worker.
- A task is tried at most ``1 + retries`` times; then its Outcome carries the last error.

One task's failure never stops the others.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import socket
import traceback
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from imupipe.pipeline.errors import ConfigError, ImupipeError

ENGINES = ("local", "ray")


@dataclass
class Outcome:
    """What became of one task: ``result`` (what ``fn`` returned) or ``error`` (one line)."""

    index: int
    task: Any
    result: Any = None
    error: str | None = None
    attempts: int = 1
    host: str | None = None


@dataclass
class _Attempt:
    ok: bool
    value: Any
    retryable: bool
    host: str


def guarded(fn: Callable[[Any], Any], task: Any) -> _Attempt:
    """Run ``fn(task)`` in a worker and turn any exception into a one-line, picklable error."""
    host = socket.gethostname()
    try:
        return _Attempt(True, fn(task), False, host)
    except ImupipeError as exc:
        return _Attempt(False, str(exc), False, host)
    except Exception as exc:  # noqa: BLE001 - a worker reports every failure as data
        where = traceback.extract_tb(exc.__traceback__)[-1]
        message = " ".join(str(exc).split())
        detail = f"{type(exc).__name__}: {message} (at {os.path.basename(where.filename)}:{where.lineno})"
        return _Attempt(False, detail, True, host)


def default_jobs() -> int:
    """The CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


SINGLE_THREADED = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""BLAS thread pools, read once when numpy loads: a worker is one of many, so each gets one thread
(several BLAS threads per worker on a busy machine spin against each other)."""


def _worker_init() -> None:
    """Each worker is one of many: Arrow's own thread pool gets one thread too."""
    import pyarrow as pa

    pa.set_cpu_count(1)


def _start_forkserver(ctx: Any, preload: list[str]) -> None:
    """Start the fork server, with single-threaded BLAS, preloading the modules the tasks need
    (once per process: workers fork from it with those modules imported)."""
    from multiprocessing import forkserver

    saved = {var: os.environ.get(var) for var in SINGLE_THREADED}
    os.environ.update(dict.fromkeys(SINGLE_THREADED, "1"))
    try:
        ctx.set_forkserver_preload(preload)
        forkserver.ensure_running()
    finally:
        for var, value in saved.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


class _Tracker:
    """Attempts per task and the decision to retry or give up."""

    def __init__(self, tasks: Sequence[Any], retries: int, on_done: Callable[[Outcome], None]):
        self.tasks, self.retries, self.on_done = tasks, retries, on_done
        self.attempts = [0] * len(tasks)
        self.queue: deque[int] = deque(range(len(tasks)))

    def start(self, i: int) -> None:
        self.attempts[i] += 1

    def finish(self, i: int, attempt: _Attempt) -> None:
        if attempt.ok:
            self.on_done(
                Outcome(i, self.tasks[i], attempt.value, None, self.attempts[i], attempt.host)
            )
        else:
            self.failed(i, attempt.value, attempt.retryable, attempt.host)

    def failed(self, i: int, error: str, retryable: bool, host: str | None = None) -> None:
        if retryable and self.attempts[i] <= self.retries:
            self.queue.append(i)
        else:
            self.on_done(Outcome(i, self.tasks[i], None, error, self.attempts[i], host))


def run_local(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    on_done: Callable[[Outcome], None],
    *,
    jobs: int | None = None,
    retries: int = 2,
    preload: Sequence[str] = (),
) -> None:
    """Run every task in a pool of ``jobs`` worker processes (``forkserver`` start; the fork
    server imports ``fn``'s module and ``preload`` once, so workers start warm).

    When a worker dies the pool breaks and every task in flight fails with it. If only one task
    was in flight it is to blame and is charged an attempt; otherwise the tasks in flight become
    suspects, uncharged, and are run again one at a time until the culprit is found.
    """
    tracker = _Tracker(tasks, retries, on_done)
    jobs = max(1, min(jobs or default_jobs(), len(tasks) or 1))
    ctx = mp.get_context("forkserver")
    _start_forkserver(ctx, [fn.__module__, *preload])
    suspects: deque[int] = deque()
    while tracker.queue or suspects:
        crashed: list[int] = []
        with cf.ProcessPoolExecutor(jobs, mp_context=ctx, initializer=_worker_init) as pool:
            running: dict[cf.Future, int] = {}
            while True:
                if not crashed:
                    if suspects and not running:
                        i = suspects.popleft()
                        tracker.start(i)
                        running[pool.submit(guarded, fn, tasks[i])] = i
                    while tracker.queue and not suspects:
                        i = tracker.queue.popleft()
                        tracker.start(i)
                        running[pool.submit(guarded, fn, tasks[i])] = i
                if not running:
                    break
                done, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
                for future in done:
                    i = running.pop(future)
                    try:
                        tracker.finish(i, future.result())
                    except cf.process.BrokenProcessPool:
                        crashed.append(i)
        if len(crashed) == 1:
            tracker.failed(crashed[0], "the worker process died (killed or out of memory)", True)
        else:
            for i in crashed:
                tracker.attempts[i] -= 1
                suspects.append(i)


def run_ray(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    on_done: Callable[[Outcome], None],
    *,
    address: str | None = None,
    jobs: int | None = None,
    retries: int = 2,
) -> None:
    """Run every task on a Ray cluster, one CPU each.

    ``address``: ``auto`` (the cluster this machine belongs to), ``ray://host:10001`` (Ray
    Client) or ``None`` (join an already initialised Ray, else start a local one with ``jobs``
    CPUs, default all). Workers write
    their outputs themselves, so the logs and the output folder must be on storage every node
    sees at the same path.
    """
    try:
        import ray
    except ModuleNotFoundError:
        raise ConfigError(
            "--engine ray needs Ray: pip install 'imupipe[ray]' (on every node of the cluster)"
        ) from None
    if not ray.is_initialized():
        try:
            local = {"num_cpus": jobs} if address is None and jobs else {}
            ray.init(address=address, log_to_driver=False, logging_level="WARNING", **local)
        except ConnectionError as exc:
            raise ConfigError(f"--address {address}: cannot connect to Ray: {exc}") from None
    remote = ray.remote(num_cpus=1, max_retries=0)(guarded)
    tracker = _Tracker(tasks, retries, on_done)
    running: dict[Any, int] = {}
    while tracker.queue or running:
        while tracker.queue:
            i = tracker.queue.popleft()
            tracker.start(i)
            running[remote.remote(fn, tasks[i])] = i
        (ref,), _ = ray.wait(list(running), num_returns=1)
        i = running.pop(ref)
        try:
            tracker.finish(i, ray.get(ref))
        except ray.exceptions.RayError as exc:  # the worker or its node died
            tracker.failed(i, f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}", True)


def run_tasks(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    on_done: Callable[[Outcome], None],
    *,
    engine: str = "local",
    jobs: int | None = None,
    address: str | None = None,
    retries: int = 2,
    preload: Sequence[str] = (),
) -> None:
    """Run ``fn`` over ``tasks`` on ``engine`` (``local`` or ``ray``); see the module docstring.
    ``preload``: modules the local workers should have imported before they start."""
    if not tasks:
        return
    if engine == "local":
        run_local(fn, tasks, on_done, jobs=jobs, retries=retries, preload=preload)
    elif engine == "ray":
        run_ray(fn, tasks, on_done, address=address, jobs=jobs, retries=retries)
    else:
        raise ConfigError(f"--engine {engine}: unknown engine (known: {', '.join(ENGINES)})")
