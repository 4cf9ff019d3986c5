"""Benchmark (issue 17 item 3, issue 39): MCAP reads against the decompression + CRC limit.

Measured in one run, on the same files:

- **limit**: every chunk of the file read, zstd-decompressed and CRC-checked (``zlib.crc32``),
  nothing else, in one thread: the issue's floor; a read that decodes the messages with the
  same decompressor and CRC cannot be faster on one core;
- **limit with the read's CRC**: the same with the CRC the read computes
  (``imupipe.readers.chunk_fill.crc32``, carry-less multiply when the helper is built: 4x
  zlib 1.2's speed); the read's ratio to it is printed too, since a read that checks CRCs
  faster than zlib gains against the first limit by that alone;
- **read**: ``imupipe.readers.mcap.reader.read_mcap`` of the whole file into the common table;
  ratio read / limit for 1 M and 5 M ``sensor_msgs/Imu`` messages at 400 Hz (goal, issue 39:
  the read's process CPU, all threads, <= 1.5x the limit's, on one core and on two);
- **multi-topic**: the same Imu messages plus a 1 Hz ``sensor_msgs/Temperature`` topic in one
  MCAP, read / Imu-only read (goal: <= 1.20);
- **peak memory**: VmHWM growth of a fresh process reading the file, over the decoded table.

The messages carry what imupipe's writer writes for a table without orientation or covariances:
orientation (0, 0, 0, 1), orientation covariance (-1, 0, ...), zero gyro and accel covariances
(a driver's "unknown"). The reader leaves columns that are all zeros unwritten (their pages are
never touched); ``--dense`` writes random orientations and covariances instead, so that every
byte of the table is written.

Each side runs ``--repeat`` times, interleaved (the 2-core machine is shared); the best wall time
counts. CPU time is reported too: the whole process (all threads) and the reading thread alone.
``--fallback`` times the numpy path too (``IMUPIPE_PURE_PYTHON=1``: what a read does without
the compiled helper ``imupipe.readers._chunks``), interleaved with the others. Besides the best
wall times, each repeat's ratios to the limit of the same repeat are printed as min / median:
wall, process CPU (all threads: the work on one core) and the reading thread's CPU.
The reading thread is the critical path when the helper threads (decompression, page mapping)
find a free core; ``max(reading thread, process / 2)`` is what the read would take on two idle
cores, printed as the "idle estimate". ``--load K`` starts K busy processes for the run, to
measure on a loaded machine on purpose. ``--cpus 0`` runs the whole benchmark on CPU 0 only
(as ``taskset -c 0``; the reader then decompresses in its reading thread, as it does when the
load average says no CPU is free; ``--threads on`` / ``off`` decides instead). The minor page faults
of each side (``ru_minflt`` of the process) are printed too: the table's fresh pages are most of
a read's.

    python benchmarks/bench_read_limits.py [--n 1000000 5000000] [--repeat 3] [--load 0] [--dense]
        [--fallback] [--cpus 0] [--threads auto|on|off]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import resource
import struct
import tempfile
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
from bench_read_write import memory

from imupipe.readers.record_walk import PURE_PYTHON_ENV

RATE_HZ = 400.0


def make_table(n: int, temperature_hz: float | None = None, dense: bool = False):
    """n Imu messages at 400 Hz, random values, one frame_id; optionally a Temperature stream
    at ``temperature_hz`` interleaved in time (its own rows, as a bag's messages are);
    ``dense``: random orientations and covariances too."""
    import pyarrow as pa

    from imupipe.readers.table import make_table as mk

    rng = np.random.default_rng(0)
    t = 1_700_000_000_000_000_000 + np.round(np.arange(n) * 1e9 / RATE_HZ).astype(np.int64)
    gyro = rng.normal(0, 0.01, (n, 3))
    accel = rng.normal(0, 0.1, (n, 3)) + [0, 0, 9.81]
    if temperature_hz is None:
        extra = {"frame_id": pa.array(np.full(n, "imu_link"))}
        if dense:
            extra.update({f"orientation_{a}": rng.normal(size=n) for a in "xyzw"})
            for name in ("orientation_cov", "gyro_cov", "accel_cov"):
                extra[name] = rng.normal(0, 1e-3, (n, 9))
        return mk(
            t,
            gyro=gyro,
            accel=accel,
            extra=extra,
            metadata={"topics": {"imu": "/imu/data"}},
        )
    m = int(n / RATE_HZ * temperature_hz)
    tt = t[0] + np.round((np.arange(m) + 0.5) * 1e9 / temperature_hz).astype(np.int64)
    t_all = np.concatenate([t, tt])
    order = np.argsort(t_all, kind="stable")
    k = n + m
    imu = order < n
    g = np.zeros((k, 3))
    a = np.zeros((k, 3))
    g[imu], a[imu] = gyro[order[imu]], accel[order[imu]]
    temp = np.zeros(k)
    temp[~imu] = 25 + rng.normal(0, 0.1, m)
    return mk(
        t_all[order],
        gyro=g,
        accel=a,
        temperature=temp,
        valid={"imu": imu, "temperature": ~imu},
        extra={"frame_id": pa.array(np.full(k, "imu_link"))},
        metadata={"topics": {"imu": "/imu/data", "temperature": "/imu/temperature"}},
    )


def limit(path: Path, crc32: Callable[[bytes], int] = zlib.crc32) -> int:
    """Read every chunk record, decompress it and check its CRC (``crc32``: zlib's, the
    issue's floor); returns the bytes produced."""
    import zstandard

    total = 0
    dctx = zstandard.ZstdDecompressor()
    with open(path, "rb") as fh:
        fh.seek(8)
        while True:
            head = fh.read(9)
            if len(head) < 9:
                break
            op, length = head[0], int.from_bytes(head[1:9], "little")
            if op == 0x0F:  # data end
                break
            body = fh.read(length)
            if op != 0x06:
                continue
            usize, crc = struct.unpack_from("<QI", body, 16)
            (clen,) = struct.unpack_from("<I", body, 28)
            compression = body[32 : 32 + clen]
            (dlen,) = struct.unpack_from("<Q", body, 32 + clen)
            data = memoryview(body)[40 + clen : 40 + clen + dlen]
            raw = dctx.decompress(data, max_output_size=usize) if compression else bytes(data)
            if crc and crc32(raw) != crc:
                raise SystemExit(f"{path}: CRC mismatch")
            total += len(raw)
    return total


def limit_same_crc(path: Path) -> int:
    """:func:`limit` with the CRC the read computes (``chunk_fill.crc32``: carry-less multiply
    where the compiled helper is built, 4x zlib 1.2's speed): the floor of a read that does the
    same work no faster than the read does it."""
    from imupipe.readers.chunk_fill import crc32

    return limit(path, crc32)


def ours(path: Path) -> int:
    from imupipe.readers.mcap.reader import read_mcap
    from imupipe.readers.spec import InputSpec

    table, _ = read_mcap(InputSpec(path=path))
    return table.num_rows


def numpy_path(path: Path) -> int:
    """:func:`ours` on the numpy path (the fallback when the compiled helper is not built)."""
    os.environ[PURE_PYTHON_ENV] = "1"
    try:
        return ours(path)
    finally:
        del os.environ[PURE_PYTHON_ENV]


def timed(fn, path: Path) -> tuple[float, float, float, int]:
    """(wall, process CPU, this thread's CPU) seconds of ``fn(path)``, and the minor page faults
    of the process (all threads) meanwhile."""
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    wall, cpu, thread = time.perf_counter(), time.process_time(), time.thread_time()
    fn(path)
    return (
        time.perf_counter() - wall,
        time.process_time() - cpu,
        time.thread_time() - thread,
        resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults,
    )


def _burn() -> None:
    while True:
        pass


Run = tuple[float, float, float, int]


def _fmt(runs: list[Run]) -> str:
    return ", ".join(f"{w:.2f}/{c:.2f}/{m:.2f}/{f // 1000}k" for w, c, m, f in runs)


def _ratios(runs: dict[str, list[Run]], key: str, floor: str = "lim") -> str:
    """Per repeat, ``key``'s wall, process CPU and reading-thread CPU over the limit's
    (``floor``) in the same repeat (the limit has one thread: its CPU is its one core's work):
    min / median."""
    out = []
    for i, what in enumerate(("wall", "process CPU", "reading thread CPU")):
        r = [a[i] / lim[1 if i else 0] for a, lim in zip(runs[key], runs[floor], strict=True)]
        out.append(f"{what} {min(r):.2f}x / {float(np.median(r)):.2f}x")
    faults = [a[3] for a in runs[key]]
    out.append(f"minor faults {int(np.median(faults)):,}")
    return ", ".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[1_000_000, 5_000_000])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--load", type=int, default=0, help="busy processes during the run")
    parser.add_argument("--keep", type=Path, default=None)
    parser.add_argument(
        "--dense", action="store_true", help="random orientations and covariances (Imu only)"
    )
    parser.add_argument(
        "--cpus",
        type=int,
        nargs="+",
        default=None,
        help="run on these CPUs only (as taskset -c; the reader then decompresses inline)",
    )
    parser.add_argument(
        "--threads",
        choices=("auto", "on", "off"),
        default="auto",
        help="decompression threads: as the reader decides (auto: none when no CPU is free, "
        "compression.no_spare_cpu), always, or never",
    )
    parser.add_argument(
        "--fallback",
        action="store_true",
        help=f"also time the numpy path ({PURE_PYTHON_ENV}=1: no compiled helper)",
    )
    args = parser.parse_args()
    if args.cpus:
        os.sched_setaffinity(0, args.cpus)  # before any thread starts; the probes inherit it
    from imupipe.readers.compression import no_spare_cpu
    from imupipe.readers.mcap import fast

    if args.threads != "auto":
        fast.no_spare_cpu = lambda: args.threads == "off"  # type: ignore[assignment]

    from imupipe.pipeline.writers.mcap import write_mcap

    work = args.keep or Path(tempfile.mkdtemp(prefix="imupipe-limits-"))
    work.mkdir(parents=True, exist_ok=True)
    kind = "imu_dense" if args.dense else "imu"
    for n in args.n:
        if not (work / f"{kind}_{n}.mcap").exists():
            write_mcap(work / f"{kind}_{n}.mcap", make_table(n, dense=args.dense))
        if not args.dense and not (work / f"imu_temp_{n}.mcap").exists():
            write_mcap(work / f"imu_temp_{n}.mcap", make_table(n, temperature_hz=1.0))
    burners = [multiprocessing.Process(target=_burn, daemon=True) for _ in range(args.load)]
    for p in burners:
        p.start()
    try:
        cpus = sorted(os.sched_getaffinity(0))
        print(
            f"load average before: {os.getloadavg()[0]:.2f}; busy processes added: {args.load}; "
            f"CPUs {cpus}; decompression threads: {args.threads} (now: "
            f"{'no' if fast.no_spare_cpu() else 'yes'}; no_spare_cpu() {no_spare_cpu()})"
        )
        for n in args.n:
            imu_only, multi = work / f"{kind}_{n}.mcap", work / f"imu_temp_{n}.mcap"
            runs: dict[str, list[Run]] = {"lim": [], "same": [], "read": [], "multi": []}
            if args.fallback:
                runs["numpy"] = []
            for _ in range(args.repeat):  # interleaved: the load changes under us
                runs["lim"].append(timed(limit, imu_only))
                runs["same"].append(timed(limit_same_crc, imu_only))
                runs["read"].append(timed(ours, imu_only))
                runs["multi"].append(timed(ours, imu_only if args.dense else multi))
                if args.fallback:
                    runs["numpy"].append(timed(numpy_path, imu_only))
            lim, read, mul = (min(r[0] for r in runs[k]) for k in ("lim", "read", "multi"))
            lim_cpu = min(r[1] for r in runs["lim"])
            idle = min(max(m, c / 2) for _, c, m, _ in runs["read"])
            mem = memory(imu_only)
            growth = (mem["peak"] - mem["base"]) / mem["table"]
            second = "Imu again" if args.dense else "+1 Hz Temperature"
            print(
                f"{n:>9,} {kind} ({imu_only.stat().st_size / 1e6:.0f} MB): limit {lim:.2f} s, "
                f"read {read:.2f} s -> {read / lim:.2f}x the limit; idle estimate "
                f"{idle:.2f} s -> {idle / lim_cpu:.2f}x; {second} {mul:.2f} s -> "
                f"{mul / read:.2f}x Imu-only (goal <= 1.20); peak growth "
                f"{(mem['peak'] - mem['base']) / 1e6:.0f} MB = {growth:.2f}x the "
                f"{mem['table'] / 1e6:.0f} MB table"
            )
            print(
                "          read / limit per repeat, min / median (goal: process CPU <= 1.5x): "
                f"{_ratios(runs, 'read')}"
            )
            print(
                "          read / limit with the read's own CRC (compiled, zstd + that CRC), "
                f"min / median: {_ratios(runs, 'read', 'same')}"
            )
            if args.fallback:
                print(f"          numpy path / limit, min / median: {_ratios(runs, 'numpy')}")
            labels = [
                ("lim", "limit"),
                ("same", "same CRC"),
                ("read", "read"),
                ("multi", "multi"),
                ("numpy", "numpy"),
            ]
            for k, label in labels:
                if k in runs:
                    print(
                        f"          {label:8s} wall/process CPU/reading thread CPU (s)/faults: "
                        f"{_fmt(runs[k])}"
                    )
        print(f"load average after: {os.getloadavg()[0]:.2f}")
    finally:
        for p in burners:
            p.kill()


if __name__ == "__main__":
    main()
