"""Fault in the pages of freshly allocated columns from a thread of their own.

A new array's memory is mapped lazily: the first write to each 4 KiB page traps into the kernel,
which zeroes the page and maps it. Reading 1 M ``sensor_msgs/Imu`` messages writes ~300 MB of
columns, ~73,000 page faults that cost as much as the copy they interrupt (0.22 s against
0.025 s for the same copy into memory already mapped, measured on the 2-core test machine).
Huge pages cost more here, not less (see :func:`imupipe.readers.table_buffer.small_pages`);
columns that stay all zeros are not written at all, so their pages are never mapped (see
:meth:`imupipe.readers.table_buffer._Stream.add`: they are given to :meth:`Prefault.add` only
once a value in them is not zero).

:class:`Prefault` moves that kernel work off the reading thread: a helper thread asks the kernel
to map the pages (``madvise(MADV_POPULATE_WRITE)``, Linux 5.14+, one call per block of rows),
a bounded distance ahead of the rows being filled, while the reader decompresses and decodes.
On a machine without that call (or not Linux) it does nothing. The total work is the same;
with a free core the read is faster.
"""

from __future__ import annotations

import ctypes
import errno
import sys
import threading
import weakref

import numpy as np

MADV_POPULATE_WRITE = 23
PAGE = 4096
STEP_ROWS = 1 << 15
"""Rows mapped per call."""
AHEAD_ROWS = 1 << 18
"""How far ahead of the filled rows the pages are mapped (bounds the memory mapped for rows a
wrong message count promised but the log never fills)."""

_madvise = None
if sys.platform.startswith("linux"):
    try:
        try:  # glibc's name, loaded without find_library, which runs `ldconfig -p` (2 ms)
            _libc = ctypes.CDLL("libc.so.6", use_errno=True)
        except OSError:
            import ctypes.util  # the fallback only: it imports subprocess (issue 39)

            _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so", use_errno=True)
        _madvise = _libc.madvise
        _madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        _madvise.restype = ctypes.c_int
    except (OSError, AttributeError):
        _madvise = None


def _populate(array: np.ndarray, lo: int, hi: int) -> int:
    """Map the pages of rows ``lo:hi`` of ``array`` (C-contiguous): 0 (nothing to map when
    ``hi <= lo``), or the kernel's errno (a call interrupted is tried again, up to three
    times)."""
    if hi <= lo:
        return 0
    row = array.strides[0] if array.ndim else array.itemsize
    start = array.ctypes.data + lo * row
    end = array.ctypes.data + hi * row
    base = start & ~(PAGE - 1)
    if end <= base:
        return 0
    error = 0
    for _ in range(3):
        if _madvise(base, end - base, MADV_POPULATE_WRITE) == 0:  # type: ignore[misc]
            return 0
        error = ctypes.get_errno()
        if error not in (errno.EINTR, errno.EAGAIN):
            break
    return error


class Prefault:
    """Maps the pages of ``arrays`` (equal row counts) row block by row block, up to
    :data:`AHEAD_ROWS` past the rows reported filled with :meth:`advance`; arrays given later
    with :meth:`add` from the row given on. The thread ends at :meth:`close`, when everything
    is mapped, or when this object is garbage collected."""

    def __init__(self, arrays: list[np.ndarray], rows: int | None = None) -> None:
        self.arrays = arrays
        self.rows = len(arrays[0]) if arrays else rows or 0
        """The arrays' rows (``rows``: for arrays all given later, with :meth:`add`)."""
        self.filled = 0
        self.woken = 0
        """``filled`` when the thread was last woken."""
        self.added: list[tuple[np.ndarray, int]] = []
        """Arrays to map from a row on (given while the thread runs), for the thread to take."""
        self.closed = _madvise is None or self.rows == 0
        self.error = 0
        """The errno with which the kernel refused to map pages (the thread then stopped; the
        reader maps them itself, as without this helper), or 0."""
        self.cond = threading.Condition()
        self.thread = None
        if not self.closed:
            self.thread = threading.Thread(
                target=_run, args=(weakref.ref(self), self.cond), daemon=True
            )
            self.thread.start()

    def advance(self, filled: int) -> None:
        """The rows below ``filled`` are written: the thread maps ahead of them. It is woken
        once per :data:`STEP_ROWS` rows (a wake-up per chunk cost more than it mapped)."""
        if self.closed:
            return
        if filled < self.woken + STEP_ROWS and filled < self.rows:
            self.filled = filled  # read under the lock when the thread next looks
            return
        with self.cond:
            self.filled = self.woken = filled
            self.cond.notify()

    def add(self, array: np.ndarray, start: int) -> None:
        """Map ``array`` (as many rows as the others) too, from row ``start`` on: the rows
        before it stay as they are (untouched zeros stay unmapped)."""
        if self.closed:
            return
        with self.cond:
            self.added.append((array, start))
            self.cond.notify()

    def close(self) -> None:
        """Stop (waits for the call in progress)."""
        with self.cond:
            self.closed = True
            self.cond.notify()
        if self.thread is not None:
            self.thread.join()


def _run(ref: weakref.ref, cond: threading.Condition) -> None:
    done = 0
    arrays: list[np.ndarray] | None = None
    while True:
        with cond:
            while True:
                owner = ref()
                if owner is None or owner.closed or done >= owner.rows:
                    return
                target = min(owner.rows, owner.filled + AHEAD_ROWS)
                if done < target or owner.added:
                    break
                del owner
                cond.wait(0.2)
            if arrays is None:
                arrays = list(owner.arrays)
            added, owner.added = owner.added, []
            hi = min(target, done + STEP_ROWS)
            del owner
        for array, start in added:  # catch up with the others
            error = _populate(array, start, done)
            if error:
                return _failed(ref, error)
            arrays.append(array)
        for array in arrays:
            error = _populate(array, done, hi)
            if error:
                return _failed(ref, error)
        done = max(done, hi)


def _failed(ref: weakref.ref, error: int) -> None:
    """Record on the owner (if it is still there) why the thread stopped."""
    owner = ref()
    if owner is not None:
        owner.error = error
