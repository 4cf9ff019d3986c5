"""Benchmark (issue 24): reading an ArduPilot DataFlash log, imupipe against pymavlink's DFReader.

Measured in one run, on the same file: DFReader's parse of every message (``recv_msg`` until the
end: what a user of pymavlink pays to get a log's IMU records), imupipe's decode of every record
of every type (``DataFlashLog`` + ``records`` of each type: the same work), and imupipe's whole
read into the common table (``read_input``, one IMU instance, its temperature, a magnetometer).
Also the table read with the records found by numpy instead of the compiled walk
(``IMUPIPE_PURE_PYTHON=1``: an install without a C compiler). Prints best-of-N wall times and
the ratios (DFReader / imupipe: above 1 is faster).

    python benchmarks/bench_dataflash.py [LOG.bin ...] [--repeat 3] [--synthetic-mb 20]

Default logs: the largest of ``../shared/data/logs/ardupilot_flights`` (``erle_pxf_218/218.BIN``,
1.9 MB), and a synthetic log of ``--synthetic-mb`` MB written by the tests' writer.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = (
    ROOT.parent / "shared" / "data" / "logs" / "ardupilot_flights" / "erle_pxf_218" / "218.BIN"
)


def _best(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def _dfreader(path: Path) -> int:
    from pymavlink import DFReader

    r = DFReader.DFReader_binary(str(path), zero_time_base=False)
    n = 0
    while r.recv_msg() is not None:
        n += 1
    return n


def _imupipe_all(path: Path) -> int:
    from imupipe.readers.dataflash.reader import DataFlashLog

    f = DataFlashLog(path)
    return sum(len(f.records(name)) for name in set(f.topic_types().values()))


def _imupipe_table(path: Path, imu: str) -> int:
    from imupipe.readers.dispatch import read_input
    from imupipe.readers.spec import InputSpec

    table, _ = read_input(InputSpec(path=path, imu_topic=imu))
    return len(table)


def measure(path: Path, repeat: int, imu: str = "IMU") -> None:
    from imupipe.readers.record_walk import PURE_PYTHON_ENV, compiled

    size = path.stat().st_size / 1e6
    n_ref = _dfreader(path)
    n_ours = _imupipe_all(path)
    ref = _best(lambda: _dfreader(path), repeat)
    ours = _best(lambda: _imupipe_all(path), repeat)
    table = _best(lambda: _imupipe_table(path, imu), repeat)
    os.environ[PURE_PYTHON_ENV] = "1"  # the records found with numpy, as without a compiler
    pure = _best(lambda: _imupipe_table(path, imu), repeat)
    del os.environ[PURE_PYTHON_ENV]
    print(
        f"{path.name} ({size:.1f} MB, {n_ref} messages; imupipe {n_ours}): DFReader {ref:.3f} s, "
        f"imupipe every record {ours:.3f} s ({ref / ours:.1f}x faster), "
        f"imupipe read_input {table:.3f} s ({ref / table:.1f}x faster; compiled walk "
        f"{compiled()}), without the compiled walk {pure:.3f} s ({ref / pure:.1f}x faster)"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("logs", nargs="*", type=Path)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--synthetic-mb", type=float, default=20.0)
    args = p.parse_args()
    logs = args.logs or ([DEFAULT] if DEFAULT.exists() else [])
    for log in logs:
        measure(log, args.repeat)
    if args.synthetic_mb > 0:
        sys.path.insert(0, str(ROOT / "tests"))
        from test_dataflash_reader import write_dataflash

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "synthetic.bin"
            # about 48 kB per second of log (two IMUs at 400 Hz, compass, baro)
            write_dataflash(path, seconds=args.synthetic_mb * 1e6 / 48_000, garbage=False)
            measure(path, args.repeat, imu="IMU_1")


if __name__ == "__main__":
    main()
