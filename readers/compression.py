"""Chunk decompression shared by the MCAP and ROS 1 bag readers.

Any decompressor failure, an unknown compression or a size other than the one the chunk header
states is a :class:`ReadError` naming the chunk (``where``), never a crash. The decompressors
release the GIL: the MCAP and bag readers run them in worker threads, :data:`PREFETCH` chunks
ahead of the chunk they decode.
"""

from __future__ import annotations

import bz2
import concurrent.futures
import contextlib
import os
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from imupipe.readers.errors import ReadError

PREFETCH = 3
"""Chunks a reader has decompressed (or in decompression) ahead of the one it decodes."""
DECOMPRESS_THREADS = 2
"""Worker threads that decompress chunks for one reader."""

_POOL: tuple[int, concurrent.futures.ThreadPoolExecutor] | None = None
_POOL_LOCK = threading.Lock()


class DecompressWorkers:
    """One reader's share of the process's decompression threads: what it submitted, so that
    it can wait for them before it closes its file."""

    def __init__(self, pool: concurrent.futures.ThreadPoolExecutor) -> None:
        self.pool = pool
        self.futures: list[concurrent.futures.Future] = []

    def submit(self, fn: Callable, *args: object) -> concurrent.futures.Future:
        future = self.pool.submit(fn, *args)
        if self.futures and self.futures[0].done():  # a done future holds its result (a
            self.futures = [f for f in self.futures if not f.done()]  # pooled chunk buffer)
        self.futures.append(future)
        return future


LOADED = 0.5
"""A decompression thread is started only while the machine's 1-minute load average is below
its CPU count minus this (:func:`no_spare_cpu`)."""


def no_spare_cpu() -> bool:
    """Whether no CPU is free for a decompression thread: the process may run on one CPU only
    (``taskset -c 0``, a container's cpuset), or the machine's load average says every CPU is
    busy (``os.getloadavg()[0] >= os.cpu_count() - LOADED``: other processes, or a fleet's
    other workers). A decompression thread then only adds hand-offs, GIL changes and chunks
    read from another core's cache to the same work: a 1 M-message MCAP read cost 0.05 s more
    process CPU with it on one core, and 0.1 s more (the same wall time) on two busy cores,
    than decompressing in the reading thread (issue 39). With a core free, the thread
    overlaps decompression with decoding (wall time)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        cpus = os.cpu_count() or 1
    if cpus < 2:
        return True
    try:
        return os.getloadavg()[0] >= (os.cpu_count() or cpus) - LOADED
    except (AttributeError, OSError):  # no load average (Windows)
        return False


def done(result: object) -> concurrent.futures.Future:
    """A future already holding ``result`` (work done in the reader's own thread)."""
    future: concurrent.futures.Future = concurrent.futures.Future()
    future.set_result(result)
    return future


@contextlib.contextmanager
def decompress_workers() -> Iterator[DecompressWorkers]:
    """The :data:`DECOMPRESS_THREADS` decompression threads, started once per process and kept
    for the next file (a thread pool per file cost 5-10 ms of thread start and join for each
    log of a fleet, issue 39); a forked child starts its own. On leaving, what the reader
    submitted and no thread has started is cancelled and what runs is waited for (it reads
    the reader's file)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL[0] != os.getpid():
            pool = concurrent.futures.ThreadPoolExecutor(
                DECOMPRESS_THREADS, thread_name_prefix="imupipe-decompress"
            )
            _POOL = (os.getpid(), pool)
    workers = DecompressWorkers(_POOL[1])
    try:
        yield workers
    finally:
        for future in workers.futures:
            future.cancel()
        concurrent.futures.wait(workers.futures)


def _zstd(data: bytes | memoryview, size: int) -> bytes:
    import zstandard

    return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)


def _lz4(data: bytes | memoryview, size: int) -> bytes:
    import lz4.frame

    return lz4.frame.decompress(data)


DECOMPRESSORS = {
    "zstd": _zstd,
    "lz4": _lz4,
    "bz2": lambda data, size: bz2.decompress(data),
    "": lambda data, size: bytes(data),
    "none": lambda data, size: bytes(data),
}
"""Compression name (as MCAP and ROS 1 bags spell it) -> decompress(data, expected_size)."""


def decompress_chunk(
    data: bytes | memoryview, compression: str, size: int, where: str
) -> np.ndarray:
    """Decompress one chunk to a uint8 array of exactly ``size`` bytes."""
    if compression not in DECOMPRESSORS:
        raise ReadError(f"{where}: unsupported chunk compression '{compression}'")
    try:
        raw = DECOMPRESSORS[compression](data, size)
    except Exception as exc:  # noqa: BLE001 - any decompressor failure is a corrupt chunk
        raise ReadError(f"{where}: corrupt {compression or 'uncompressed'} chunk ({exc})") from None
    if len(raw) != size:
        raise ReadError(f"{where}: chunk decompressed to {len(raw)} bytes, expected {size}")
    return np.frombuffer(raw, dtype=np.uint8)


_local = threading.local()


def decompress_into(
    data: bytes | memoryview, compression: str, out: np.ndarray, where: str
) -> np.ndarray:
    """:func:`decompress_chunk` into ``out`` (uint8, at least the chunk's size): the chunk's
    bytes as ``out[:size]``. zstd decompresses straight into it (one decompressor per thread);
    other compressions are decompressed as :func:`decompress_chunk` does, then copied."""
    size = len(out)
    if compression != "zstd":
        out[:] = decompress_chunk(data, compression, size, where)
        return out
    dctx = getattr(_local, "zstd", None)
    if dctx is None:
        import zstandard

        dctx = _local.zstd = zstandard.ZstdDecompressor()
    view = memoryview(out)
    got = 0
    try:
        reader = dctx.stream_reader(data, read_across_frames=False)
        while got < size:
            k = reader.readinto(view[got:])
            if not k:
                break
            got += k
        more = reader.read(1) if got == size else b""
    except Exception as exc:  # noqa: BLE001 - any decompressor failure is a corrupt chunk
        raise ReadError(f"{where}: corrupt zstd chunk ({exc})") from None
    if got != size or more:
        said = f"more than {size}" if more else str(got)
        raise ReadError(f"{where}: chunk decompressed to {said} bytes, expected {size}")
    return out


class BufferPool:
    """Chunk buffers used again once nothing refers to them: a chunk decompressed into memory
    already mapped costs no page faults (a fresh buffer per chunk cost the workers ~40,000 page
    faults per million Imu messages). A buffer is handed out again only when the pool holds the
    last reference to it (no chunk, no view into it left: a caller that keeps a chunk's views
    keeps its buffer), checked with ``sys.getrefcount``.

    ``arena``: chunks are carved one after the other from buffers of that many bytes, so that
    chunks taken in a row lie back to back in memory and a reader can take them as one
    (:meth:`adjacent`); a chunk larger than an arena gets a buffer of its own."""

    KEEP = 16
    """Buffers kept at most (the oldest beyond that are left to the garbage collector)."""
    ROUND = 1 << 16
    ALIGN = 64
    """Chunks carved from an arena start at a multiple of this many bytes."""

    def __init__(self, arena: int = 0) -> None:
        self.spent: list[np.ndarray] = []
        self.arena = arena
        self.current: np.ndarray | None = None
        """The arena chunks are carved from (``arena``), and the first byte still free in it."""
        self.free = 0
        self.start = -1
        """Where the buffer :meth:`take` handed out last starts in its arena (-1: a buffer of
        its own)."""
        self._kept: set[int] = set()

    def _buffer(self, size: int) -> np.ndarray:
        """A whole buffer of at least ``size`` bytes, pooled or new."""
        for i in range(len(self.spent)):  # the oldest first: the most likely free
            if len(self.spent[i]) >= size and sys.getrefcount(self.spent[i]) == 2:
                found = self.spent.pop(i)  # only the list and the call held it
                self._kept.discard(id(found))  # kept again when given back
                return found
        return np.empty(-(-max(size, 1) // self.ROUND) * self.ROUND, np.uint8)

    def take(self, size: int) -> np.ndarray:
        """A buffer of ``size`` bytes (a view of a pooled or new one)."""
        self.start = -1
        if not self.arena or size > self.arena:
            return self._buffer(size)[:size]
        if self.current is None or self.free + size > len(self.current):
            if self.current is not None:
                self._keep(self.current)
            self.current, self.free = self._buffer(self.arena), 0
        self.start = start = self.free
        self.free = self.after(start, size)
        return self.current[start : start + size]

    @classmethod
    def after(cls, start: int, size: int) -> int:
        """Where the buffer after one of ``size`` bytes at ``start`` of an arena starts."""
        return -(-(start + size) // cls.ALIGN) * cls.ALIGN

    def give(self, buf: np.ndarray) -> None:
        """``buf`` (from :meth:`take`) may be used again once nothing refers to it."""
        base = buf.base
        if isinstance(base, np.ndarray) and base.base is None and base is not self.current:
            self._keep(base)

    def _keep(self, base: np.ndarray) -> None:
        if id(base) in self._kept:
            return
        self.spent.append(base)
        self._kept.add(id(base))
        if len(self.spent) > self.KEEP:
            self._kept.discard(id(self.spent.pop(0)))


def inflate_messages(
    buf: np.ndarray | bytes, starts: np.ndarray, lengths: np.ndarray, where: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decompress messages that are each one zstd frame (rosbag2's ``compression_mode: message``)
    lying at ``buf[starts[i] : starts[i] + lengths[i]]``: returns ``(buffer, starts, lengths)``
    of the decompressed payloads, one after the other in one uint8 buffer.

    zstandard's ``multi_decompress_to_buffer`` decompresses all of them in C (worker threads,
    no Python call per message) when every frame states its content size, as rosbag2's and
    rosbags' one-shot compressors write it; frames without one are decompressed one by one.
    A payload that is not a whole zstd frame is a :class:`ReadError` naming ``where``."""
    import zstandard

    n = len(starts)
    if n == 0:
        return np.zeros(0, np.uint8), np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.asarray(starts, np.int64)
    lengths = np.asarray(lengths, np.int64)
    dctx = zstandard.ZstdDecompressor()
    segments = np.stack([starts, lengths], axis=1).astype("<u8")
    try:
        frames = zstandard.BufferWithSegments(buf, segments)
        out = dctx.multi_decompress_to_buffer(frames, threads=DECOMPRESS_THREADS)
        parts: list = [out[i] for i in range(len(out))]
    except Exception:  # noqa: BLE001 - frames without a content size, or damaged: one by one
        parts = _inflate_each(dctx, buf, starts, lengths, where)
    sizes = np.fromiter(map(len, parts), np.int64, len(parts))
    out_starts = np.zeros(n, np.int64)
    np.cumsum(sizes[:-1], out=out_starts[1:])
    return np.frombuffer(b"".join(parts), np.uint8), out_starts, sizes


def _inflate_each(
    dctx: object, buf: np.ndarray | bytes, starts: np.ndarray, lengths: np.ndarray, where: str
) -> list[bytes]:
    """:func:`inflate_messages` one frame at a time (frames that do not state their size)."""
    view = memoryview(buf if isinstance(buf, bytes) else np.ascontiguousarray(buf)).cast("B")
    parts = []
    for i, (s, k) in enumerate(zip(starts.tolist(), lengths.tolist(), strict=True)):
        obj = dctx.decompressobj()  # type: ignore[attr-defined]
        try:
            parts.append(obj.decompress(view[s : s + k]))
        except Exception as exc:  # noqa: BLE001 - any decompressor failure
            raise ReadError(
                f"{where}: message {i} is not a valid zstd frame, though the bag says its "
                f"messages are zstd-compressed ({exc})"
            ) from None
        if not obj.eof:
            raise ReadError(f"{where}: message {i} is a cut-off zstd frame")
    return parts


def inflate_file(src: Path, dst: Path, block: int = 1 << 20) -> None:
    """Decompress the zstd file ``src`` (rosbag2's ``compression_mode: file``) to ``dst``,
    streaming ``block`` bytes at a time (Python's ``compression.zstd``, its backport before
    3.14): memory stays at a block and the decompressor's window whatever the size of the file.
    A cut-off or damaged file is a :class:`ReadError` naming ``src``; a ``dst`` that cannot be
    written raises :class:`OSError`."""
    if sys.version_info >= (3, 14):
        from compression import zstd
    else:
        from backports import zstd

    try:
        with zstd.open(src, "rb") as fin, open(dst, "wb") as fout:
            while data := fin.read(block):
                fout.write(data)
    except EOFError:
        raise ReadError(f"{src}: truncated zstd file (it ends inside a compressed frame)") from None
    except zstd.ZstdError as exc:
        raise ReadError(f"{src}: corrupt zstd file ({exc})") from None
