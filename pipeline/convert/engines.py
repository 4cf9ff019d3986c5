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
- An error marked ``fatal`` (an :class:`ImupipeError` with ``fatal = True``: the output folder is
  full or read-only, so every other task would fail the same way) is final and its Outcome says
  so; the caller decides to stop (``on_done`` may raise: the engine then stops its workers).

One task's failure never stops the others (unless ``on_done`` raises).

**One log, or ``jobs == 1``** (local engine): the task runs in the driver's own process
(:func:`run_inline`), with the same outcomes, and no pool is started (its start-up, about 0.6 s,
was a third of a one-log conversion). A crash of that process (SIGKILL, out of memory) ends the
command instead of being retried.

**The driver helps while its pool starts** (``driver_helps``, local engine; the survey uses it):
the fork server imports its modules (about 0.6 s) while the driver runs tasks as
:func:`run_inline` does; a thread of the driver starts the workers once the server is ready and
hands them every task left (:func:`_start_pool_working`). A queue emptied first starts no worker.
A task the driver ran is not isolated from it, as with ``jobs == 1``.

**Start-up.** A pool's workers are all started and initialised before any task is sent, with
SIGINT and SIGTERM held back meanwhile (:func:`_start_pool`): a worker still unpickling its
queues when the driver ends found their semaphores gone and printed a ``SemLock._rebuild``
traceback.

**No orphans** (local engine). Workers ignore SIGINT (the driver decides) and turn SIGTERM into
:class:`~imupipe.pipeline.signals.Terminated`, so a worker stopped in the middle of a log removes
its temporary files. When the driver ends for any reason (an exception, SIGINT, SIGTERM), it
sends SIGTERM to its workers, waits for them a few seconds, then kills what is left. Each
worker watches the driver's process (a pidfd on Linux): when the driver is gone, even killed
with SIGKILL, an idle worker exits at once and a busy one as soon as its current log is done
(its output is complete; the next run records it as already done).

**Ray on loopback.** With no ``address``, the Ray started here listens on 127.0.0.1 only
(Ray's local-only mode: its servers bind the loopback address), with no dashboard unless asked.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import os
import select
import signal
import socket
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from imupipe.pipeline.convert.options import ENGINES
from imupipe.pipeline.errors import ConfigError, ImupipeError
from imupipe.pipeline.signals import Terminated, signals_deferred
from imupipe.stages.cores import usable_cores

STOP_GRACE_S = 5.0
"""How long stopped workers get to remove their temporary files before they are killed."""

START_TIMEOUT_S = 120.0
"""How long a pool's workers may take to start (signals are held back meanwhile)."""


@dataclass
class Outcome:
    """What became of one task: ``result`` (what ``fn`` returned) or ``error`` (one line)."""

    index: int
    task: Any
    result: Any = None
    error: str | None = None
    attempts: int = 1
    host: str | None = None
    fatal: bool = False
    """The error concerns every task alike (e.g. the output folder is full): stop."""
    pid: int | None = None
    """The process that ran the task (``os.getpid()`` of the driver: run in the driver)."""


@dataclass
class _Attempt:
    ok: bool
    value: Any
    retryable: bool
    host: str
    fatal: bool = False
    pid: int = 0


class _WorkerState:
    """A local worker's state for its signal handler and its watchdog."""

    lock = threading.RLock()  # re-entrant: the SIGTERM handler runs in the main thread
    busy = False
    orphaned = False


def attempt(fn: Callable[[Any], Any], task: Any) -> _Attempt:
    """Run ``fn(task)`` and turn any exception into a one-line, picklable error (SIGINT and
    SIGTERM, BaseExceptions, pass through): an :class:`ImupipeError` is final (``fatal`` when it
    says so), any other exception is retryable."""
    host = socket.gethostname()
    try:
        return _Attempt(True, fn(task), False, host, pid=os.getpid())
    except ImupipeError as exc:
        return _Attempt(False, str(exc), False, host, bool(getattr(exc, "fatal", False)))
    except Exception as exc:  # noqa: BLE001 - a task reports every failure as data
        where = traceback.extract_tb(exc.__traceback__)[-1]
        message = " ".join(str(exc).split())
        detail = f"{type(exc).__name__}: {message} (at {os.path.basename(where.filename)}:{where.lineno})"
        return _Attempt(False, detail, True, host)


def guarded(fn: Callable[[Any], Any], task: Any) -> _Attempt:
    """:func:`attempt` in a worker process.

    SIGTERM during the task (:class:`Terminated`) has let the task remove its temporary files;
    the worker then exits. A worker whose driver has died exits after the task."""
    with _WorkerState.lock:
        _WorkerState.busy = True
    try:
        return attempt(fn, task)
    except Terminated:
        os._exit(Terminated.exit_code)
    finally:
        with _WorkerState.lock:
            _WorkerState.busy = False
            if _WorkerState.orphaned:
                os._exit(0)  # nobody will take the result: the driver is gone


def _ready(_: int) -> int:
    """A no-op task: a worker that returns it has started (its bootstrap and initializer done)."""
    time.sleep(0.02)
    return os.getpid()


SINGLE_THREADED = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""BLAS thread pools, read once when numpy loads: a worker is one of many, so each gets one thread
(several BLAS threads per worker on a busy machine spin against each other)."""


def _on_sigterm(signum: int, frame: Any) -> None:
    """A worker's SIGTERM: a busy worker unwinds its task (its temporary files are removed), an
    idle one exits at once."""
    with _WorkerState.lock:
        if not _WorkerState.busy:
            os._exit(Terminated.exit_code)
    raise Terminated()


def _wait_for_exit(pid: int) -> None:
    """Return when process ``pid`` has ended (a pidfd on Linux; else polling once a second)."""
    try:
        fd = os.pidfd_open(pid)
    except (AttributeError, OSError):
        while True:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return
            except PermissionError:
                pass
            time.sleep(1.0)
    try:
        select.select([fd], [], [])
    finally:
        os.close(fd)


def _watch_driver(driver: int) -> None:
    """The worker's watchdog thread: when the driver is gone, an idle worker exits now, a busy
    one after its current task (see :func:`guarded`)."""
    _wait_for_exit(driver)
    with _WorkerState.lock:
        _WorkerState.orphaned = True
        if not _WorkerState.busy:
            os._exit(0)


def _worker_init(driver: int) -> None:
    """Each worker is one of many: Arrow's own thread pool gets one thread too. SIGINT is left to
    the driver, SIGTERM unwinds the current task, and a thread watches the driver."""
    import pyarrow as pa

    pa.set_cpu_count(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_sigterm)
    threading.Thread(target=_watch_driver, args=(driver,), daemon=True, name="watch-driver").start()


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


def start_forkserver(fn: Callable[[Any], Any], preload: Sequence[str] = ()) -> None:
    """Start the local engine's fork server now, importing ``fn``'s module and ``preload`` (as
    :func:`run_local` does; it then finds the server running): a caller that has more to do
    before it runs its tasks lets the server import meanwhile."""
    import multiprocessing as mp  # a pool only: one log or --jobs 1 runs inline (issue 39)

    _start_forkserver(mp.get_context("forkserver"), [fn.__module__, *preload])


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
                Outcome(
                    i,
                    self.tasks[i],
                    attempt.value,
                    None,
                    self.attempts[i],
                    attempt.host,
                    pid=attempt.pid,
                )  # fmt: skip
            )
        else:
            self.failed(i, attempt.value, attempt.retryable, attempt.host, attempt.fatal)

    def failed(
        self, i: int, error: str, retryable: bool, host: str | None = None, fatal: bool = False
    ) -> None:
        if retryable and self.attempts[i] <= self.retries:
            self.queue.append(i)
        else:
            self.on_done(Outcome(i, self.tasks[i], None, error, self.attempts[i], host, fatal))


def _stop_pool(pool: cf.ProcessPoolExecutor) -> None:
    """Stop a pool that is broken (one of its workers died) or abandoned (the driver is ending
    on an exception, SIGINT or SIGTERM), without waiting forever.

    Its workers first get SIGTERM and :data:`STOP_GRACE_S` seconds to remove their temporary
    files. On Python 3.11 the broken pool's own clean-up joins each worker, and a worker spawned
    while the pool was breaking is never told to stop: ``shutdown(wait=True)`` then hung (seen
    in the test suite, about one run in twenty under load). So: stop without waiting, kill the
    pool's workers and any other child of the fork server (only this pool's workers exist at
    this point), and wait for the pool's manager thread with a time limit, repeating until it
    has ended."""
    manager = getattr(pool, "_executor_manager_thread", None)
    # before shutdown(), which drops the pool's process table (``_processes = None``): read
    # after it, no worker got SIGTERM and its grace, and a busy one was SIGKILLed below with its
    # temporary files left behind
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        with contextlib.suppress(OSError, AttributeError):
            process.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for process in processes:
        process.join(timeout=max(0.0, deadline - time.monotonic()))
    for _ in range(10):
        for process in processes:
            if process.is_alive():
                process.kill()
        _kill_forkserver_children()
        if manager is None:
            return
        manager.join(timeout=2.0)
        if not manager.is_alive():
            return


def _forkserver_pid() -> int | None:
    """The running fork server's process id (None: not started), from multiprocessing's
    module state (no public accessor)."""
    from multiprocessing import forkserver

    return getattr(getattr(forkserver, "_forkserver", None), "_forkserver_pid", None)


def _kill_forkserver_children() -> None:
    """SIGKILL every process the fork server has forked and not yet reaped (Linux /proc)."""
    pid = _forkserver_pid()
    if not pid:
        return
    try:
        children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        return
    for child in children:
        with contextlib.suppress(OSError):
            os.kill(int(child), signal.SIGKILL)


def _submit(
    pool: cf.ProcessPoolExecutor,
    running: dict[cf.Future, int],
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    queue: deque[int],
    tracker: _Tracker,
) -> bool:
    """Send the task at the head of ``queue`` to ``pool``; False (the task stays queued,
    uncharged) when the pool has broken meanwhile."""
    i = queue[0]
    try:
        running[pool.submit(guarded, fn, tasks[i])] = i
    except cf.process.BrokenProcessPool:
        return False
    queue.popleft()
    tracker.start(i)
    return True


def run_inline(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    on_done: Callable[[Outcome], None],
    *,
    retries: int = 2,
) -> None:
    """Run every task in this process, one after the other (one log, or ``--jobs 1``): no pool
    to start. The same outcomes as the pool (an :class:`ImupipeError` is final, another
    exception retried); SIGINT and SIGTERM unwind the task (its temporary files are removed) and
    end the run."""
    tracker = _Tracker(tasks, retries, on_done)
    while tracker.queue:
        i = tracker.queue.popleft()
        tracker.start(i)
        tracker.finish(i, attempt(fn, tasks[i]))


def _open_pool(ctx: Any, jobs: int) -> cf.ProcessPoolExecutor:
    """A pool of ``jobs`` workers, every one of them started and initialised before this
    returns (a pool that fails to start is stopped here)."""
    pool = None
    try:
        pool = cf.ProcessPoolExecutor(
            jobs, mp_context=ctx, initializer=_worker_init, initargs=(os.getpid(),)
        )
        seen: set[int] = set()
        for _ in range(50):
            seen.update(pool.map(_ready, range(jobs), timeout=START_TIMEOUT_S))
            live = {p.pid for p in (getattr(pool, "_processes", None) or {}).values()}
            if live <= seen:
                break
    except BaseException:
        if pool is not None:
            _stop_pool(pool)
        raise
    return pool


def _start_pool(ctx: Any, jobs: int) -> cf.ProcessPoolExecutor:
    """:func:`_open_pool` with SIGINT and SIGTERM held back meanwhile: a worker still starting
    when the driver ends would find the pool's semaphores gone (a ``SemLock._rebuild`` traceback
    on stderr), so the pool starts no worker it cannot stop cleanly."""
    pool = None
    try:
        with signals_deferred():  # a signal held here is raised when the block ends
            pool = _open_pool(ctx, jobs)
    except BaseException:
        if pool is not None:
            _stop_pool(pool)
        raise
    return pool


SERVER_WAIT_S = 3.0
"""The longest a pool waits for its fork server to look ready (:class:`_ForkServerProbe`; it
takes about 0.6 s) before its workers are started anyway: a probe that cannot tell must not keep
the pool from starting (its start then waits for the server, on a thread, as before)."""


class _ForkServerProbe:
    """Whether the fork server has imported its preload modules and waits for requests.

    Linux (/proc): its main thread then sleeps in ``epoll_wait`` (``wchan``: ``do_epoll_wait``,
    ``ep_poll`` on older kernels), or, where the kernel hides ``wchan``, sleeps (state ``S``) with
    its CPU time unchanged since the last look. Where /proc cannot be read (not Linux), and after
    :data:`SERVER_WAIT_S`, it counts as ready. Only time depends on it: a server taken for ready
    too soon makes the pool's start wait for it (on the starting thread, while the driver works)."""

    def __init__(self) -> None:
        self.pid = _forkserver_pid()
        self.ticks: str | None = None
        self.deadline = time.monotonic() + SERVER_WAIT_S

    def ready(self) -> bool:
        if not self.pid or time.monotonic() > self.deadline:
            return True
        try:
            wchan = Path(f"/proc/{self.pid}/wchan").read_text()
            stat = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            return True
        if "epoll" in wchan or "ep_poll" in wchan:
            return True
        ticks = " ".join(stat[11:13])  # utime, stime
        idle = stat[0] == "S" and ticks == self.ticks
        self.ticks = ticks
        return idle


class _Starter(threading.Thread):
    """Starts a pool on a thread of the driver while the driver works through the queue itself
    (:func:`_start_pool_working`), then hands the pool every task still queued."""

    def __init__(
        self,
        ctx: Any,
        jobs: int,
        fn: Callable[[Any], Any],
        tasks: Sequence[Any],
        tracker: _Tracker,
        running: dict[cf.Future, int],
        lock: threading.Lock,
    ) -> None:
        super().__init__(name="imupipe-start-pool", daemon=True)
        self.ctx, self.jobs, self.fn, self.tasks = ctx, jobs, fn, tasks
        self.tracker, self.running, self.lock = tracker, running, lock
        self.cancelled = threading.Event()
        self.pool: cf.ProcessPoolExecutor | None = None
        self.took_over = False

    def run(self) -> None:
        probe = _ForkServerProbe()
        while not probe.ready():  # no worker is forked before the server can fork it at once
            if self.cancelled.wait(0.01):
                return
        if self.cancelled.is_set():
            return
        try:
            self.pool = _open_pool(self.ctx, self.jobs)
        except BaseException:  # noqa: BLE001 - the driver goes on with the queue alone
            return
        with self.lock:
            queue = self.tracker.queue
            while queue and _submit(
                self.pool, self.running, self.fn, self.tasks, queue, self.tracker
            ):
                pass
            self.took_over = True


def _start_pool_working(
    ctx: Any,
    jobs: int,
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    tracker: _Tracker,
    running: dict[cf.Future, int],
) -> cf.ProcessPoolExecutor | None:
    """Start a pool while the driver runs tasks itself, as :func:`run_inline` does: the fork
    server imports its modules and the workers start (about 0.6 s) while the queue goes down.
    Once the pool is up it takes every task still queued (``running``: their futures) and the
    driver ends the task under way; a queue emptied first leaves no pool to start (None).

    A pool that fails to start leaves the driver working alone. On an exception (SIGINT,
    SIGTERM, ``on_done`` raising) the driver waits for a start under way, signals held back as
    in :func:`_start_pool`, then stops the pool."""
    lock = threading.Lock()
    starter = _Starter(ctx, jobs, fn, tasks, tracker, running, lock)
    starter.start()
    ok = False
    try:
        while True:
            with lock:
                if starter.took_over or not tracker.queue:
                    break
                i = tracker.queue.popleft()
                tracker.start(i)
            done = attempt(fn, tasks[i])
            with lock:
                tracker.finish(i, done)
        starter.cancelled.set()
        with signals_deferred():
            starter.join()
        ok = True
    finally:
        if not ok:
            starter.cancelled.set()
            with signals_deferred():
                starter.join()
            if starter.pool is not None:
                _stop_pool(starter.pool)
    return starter.pool


def run_local(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    on_done: Callable[[Outcome], None],
    *,
    jobs: int | None = None,
    retries: int = 2,
    preload: Sequence[str] = (),
    driver_helps: bool = False,
) -> None:
    """Run every task in a pool of ``jobs`` worker processes (``forkserver`` start; the fork
    server imports ``fn``'s module and ``preload`` once, so workers start warm).

    ``driver_helps``: while the first pool starts, the driver runs tasks itself
    (:func:`_start_pool_working`), so that a pool's start-up never makes a run slower than one
    process would be; a task run there is not isolated (a crash of the driver ends the command,
    as with ``--jobs 1``).

    When a worker dies the pool breaks and every task in flight fails with it. If only one task
    was in flight it is to blame and is charged an attempt; otherwise the tasks in flight become
    suspects, uncharged, and are run again one at a time until the culprit is found.
    """
    import multiprocessing as mp  # a pool only: one log or --jobs 1 runs inline (issue 39)

    tracker = _Tracker(tasks, retries, on_done)
    jobs = max(1, min(jobs or usable_cores(), len(tasks) or 1))
    ctx = mp.get_context("forkserver")
    _start_forkserver(ctx, [fn.__module__, *preload])
    suspects: deque[int] = deque()
    first = driver_helps
    while tracker.queue or suspects:
        crashed: list[int] = []
        refused = False  # the pool broke before it took a task: the task stays queued
        running: dict[cf.Future, int] = {}
        if first:
            first = False
            helped = _start_pool_working(ctx, jobs, fn, tasks, tracker, running)
            if helped is None:
                continue  # the driver has emptied the queue, or the pool could not start
            pool = helped
        else:
            pool = _start_pool(ctx, jobs)
        clean = False
        try:
            while True:
                if not crashed and not refused:
                    if suspects and not running:
                        refused = not _submit(pool, running, fn, tasks, suspects, tracker)
                    while tracker.queue and not suspects and not refused:
                        refused = not _submit(pool, running, fn, tasks, tracker.queue, tracker)
                if not running:
                    break
                done, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
                for future in done:
                    i = running.pop(future)
                    try:
                        tracker.finish(i, future.result())
                    except cf.process.BrokenProcessPool:
                        crashed.append(i)
            clean = not crashed and not refused
        finally:
            if clean:
                pool.shutdown(wait=True)
            else:
                _stop_pool(pool)
        if len(crashed) == 1:
            tracker.failed(crashed[0], "the worker process died (killed or out of memory)", True)
        else:
            for i in crashed:
                tracker.attempts[i] -= 1
                suspects.append(i)


LOCAL_ONLY_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
"""Ray's switch between cluster mode and local-only mode (its name is historical: it applies on
Linux too). ``0``: the node's address is 127.0.0.1 and Ray's servers (GCS, raylet, workers,
dashboard agent, runtime-env agent) bind the loopback address instead of every interface."""


@contextlib.contextmanager
def _local_only_ray() -> Any:
    """Start-up settings for a Ray that only this machine can reach (restored afterwards)."""
    saved = os.environ.get(LOCAL_ONLY_ENV)
    os.environ[LOCAL_ONLY_ENV] = "0"  # read by the Ray processes started now
    from ray._private import ray_constants  # read when ray was imported: set it too

    saved_const = ray_constants.ENABLE_RAY_CLUSTER
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = saved_const
        if saved is None:
            os.environ.pop(LOCAL_ONLY_ENV, None)
        else:
            os.environ[LOCAL_ONLY_ENV] = saved


def run_ray(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    on_done: Callable[[Outcome], None],
    *,
    address: str | None = None,
    jobs: int | None = None,
    retries: int = 2,
    dashboard: bool = False,
    log: Path | None = None,
) -> None:
    """Run every task on a Ray cluster, one CPU each.

    ``address``: ``auto`` (the cluster this machine belongs to), ``ray://host:10001`` (Ray
    Client) or ``None`` (join an already initialised Ray, else start a local one with ``jobs``
    CPUs, default all, listening on 127.0.0.1 only, with the dashboard on 127.0.0.1 when
    ``dashboard``; it is shut down at the end). Workers write their outputs themselves, so the
    logs and the output folder must be on storage every node sees at the same path.

    ``log``: where Ray's own output goes (:func:`_ray_output`). A local Ray started here runs
    under a folder of its own, and a reaper ends its processes and removes the folder when this
    function returns or the process dies, SIGKILL included
    (:mod:`imupipe.pipeline.convert.ray_reaper`). SIGINT and SIGTERM are held back while Ray starts
    (Ray's own SIGTERM handler, which exits 15 with its own lines, is replaced by the caller's
    again), so a terminated command exits 143 like the local engine.
    """
    try:
        import ray
    except ModuleNotFoundError:
        raise ConfigError(
            "--engine ray needs Ray: pip install 'imupipe[ray]' (on every node of the cluster)"
        ) from None
    if address is not None and not ray.is_initialized():
        _check_reachable(address)
    with _ray_output(log), contextlib.ExitStack() as stack:
        if not ray.is_initialized():
            if address is None:
                root = stack.enter_context(_reaped_ray_root())
                # before init: a signal held back while Ray starts is raised as init returns,
                # and Ray started must still be shut down by us (not later, at exit, when its
                # shutdown makes the session folder again)
                stack.callback(ray.shutdown)
                with _local_only_ray(), _no_ray_sigterm(ray), signals_deferred():
                    ray.init(
                        num_cpus=jobs,
                        _node_ip_address="127.0.0.1",
                        _temp_dir=str(root),
                        include_dashboard=dashboard,
                        dashboard_host="127.0.0.1",
                        log_to_driver=False,
                        logging_level="WARNING",
                    )
            else:
                try:
                    with _no_ray_sigterm(ray), signals_deferred():
                        ray.init(address=address, log_to_driver=False, logging_level="WARNING")
                except ConnectionError as exc:
                    raise ConfigError(
                        f"--address {address}: cannot connect to Ray: {' '.join(str(exc).split())}"
                    ) from None
                stack.callback(ray.shutdown)
        _run_on_ray(ray, fn, tasks, on_done, retries)


@contextlib.contextmanager
def _no_ray_sigterm(ray: Any) -> Any:
    """``ray.init`` installs a SIGTERM handler that exits with status 15 and prints Ray's own
    lines; while this block runs it installs none, so the command's handler stays (a terminated
    command exits 143 and says so in one line, as with the local engine)."""
    utils = ray._private.utils
    saved = utils.set_sigterm_handler
    utils.set_sigterm_handler = lambda handler: None
    try:
        yield
    finally:
        utils.set_sigterm_handler = saved


CONNECT_TIMEOUT_S = 5.0
"""How long ``--address`` may take to accept a connection before the command gives up."""


def _check_reachable(address: str) -> None:
    """ConfigError within :data:`CONNECT_TIMEOUT_S` when ``address`` (``ray://host:port`` or
    ``host:port``) accepts no TCP connection (Ray's own client waits 30 s, then prints its
    warnings before the error)."""
    if address == "auto":
        return
    hostport = address.split("://", 1)[-1].rstrip("/")
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"--address {address}: expected 'auto', ray://HOST:PORT or HOST:PORT")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        raise ConfigError(f"--address {address}: cannot connect to Ray: {why}") from None


@contextlib.contextmanager
def _reaped_ray_root() -> Any:
    """A fresh folder for the local Ray's files, and the reaper that ends that Ray's processes
    and removes the folder when the driver is done or dies (:mod:`imupipe.pipeline.convert.ray_reaper`)."""
    import subprocess
    import sys
    import tempfile

    root = Path(
        tempfile.mkdtemp(prefix="imupipe-ray-", dir="/tmp" if os.path.isdir("/tmp") else None)
    )
    reaper = subprocess.Popen(
        [sys.executable, "-m", "imupipe.pipeline.convert.ray_reaper", str(root), str(os.getpid())],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    import shutil

    try:
        yield root
    finally:  # after ray.shutdown(): the reaper ends what is left and removes the folder
        assert reaper.stdin is not None
        reaper.stdin.close()
        with contextlib.suppress(Exception):
            reaper.wait(timeout=30)
        shutil.rmtree(root, ignore_errors=True)


@contextlib.contextmanager
def _ray_output(log: Path | None) -> Any:
    """Ray's own output (its Python warnings, its C++ core's lines on file descriptor 2) goes to
    ``log`` (appended; never through a symbolic link), not to the user's stderr; imupipe's own
    lines (``sys.stderr`` as looked up when printing: warnings, errors) still reach the user's
    stderr (Ray's logging handlers keep the old ``sys.stderr`` object, which writes to file
    descriptor 2: the log). ``None``: leave stderr as it is."""
    if log is None:
        yield
        return
    import sys

    made = [d for d in [log.parent, *log.parent.parents] if not d.exists()]
    log.parent.mkdir(parents=True, exist_ok=True)
    created = not os.path.lexists(log)
    fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o666)
    sys.stderr.flush()
    saved = os.dup(2)
    user_stderr = os.fdopen(os.dup(saved), "w", buffering=1)
    previous = sys.stderr
    os.dup2(fd, 2)
    os.close(fd)
    sys.stderr = user_stderr
    try:
        yield
    except ImupipeError:  # a refusal (exit 2) leaves nothing behind: a log made for it neither
        if created:
            with contextlib.suppress(OSError):
                log.unlink()
            for folder in made:  # deepest first, if left empty
                with contextlib.suppress(OSError):
                    folder.rmdir()
        raise
    finally:
        sys.stderr = previous
        user_stderr.close()
        os.dup2(saved, 2)
        os.close(saved)


def _run_on_ray(
    ray: Any,
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    on_done: Callable[[Outcome], None],
    retries: int,
) -> None:
    remote = ray.remote(num_cpus=1, max_retries=0)(guarded)
    tracker = _Tracker(tasks, retries, on_done)
    running: dict[Any, int] = {}
    try:
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
                error = f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
                tracker.failed(i, error, True)
    except SystemError as exc:
        # SIGINT/SIGTERM while Ray waits: Ray's signal check raises the handler's exception
        # inside its C++ call, which Python reports as a SystemError caused by it
        cause = exc.__cause__ or exc.__context__
        if isinstance(cause, KeyboardInterrupt | Terminated):
            raise cause from None
        raise
    finally:
        for ref in running:  # the driver is ending early: stop what is still running
            with contextlib.suppress(Exception):
                ray.cancel(ref)


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
    dashboard: bool = False,
    engine_log: Path | None = None,
    driver_helps: bool = False,
) -> None:
    """Run ``fn`` over ``tasks`` on ``engine`` (``local`` or ``ray``); see the module docstring.
    ``preload``: modules the local workers should have imported before they start;
    ``dashboard``: start Ray's dashboard (on 127.0.0.1) with a local Ray; ``engine_log``: the
    file Ray's own output goes to instead of stderr; ``driver_helps``: the local engine's driver
    runs tasks while its pool starts (:func:`run_local`)."""
    if not tasks:
        return
    if engine == "local" and (len(tasks) == 1 or jobs == 1):
        run_inline(fn, tasks, on_done, retries=retries)
    elif engine == "local":
        run_local(
            fn,
            tasks,
            on_done,
            jobs=jobs,
            retries=retries,
            preload=preload,
            driver_helps=driver_helps,
        )
    elif engine == "ray":
        run_ray(
            fn,
            tasks,
            on_done,
            address=address,
            jobs=jobs,
            retries=retries,
            dashboard=dashboard,
            log=engine_log,
        )
    else:
        raise ConfigError(f"--engine {engine}: unknown engine (known: {', '.join(ENGINES)})")
