"""Issue 17: a command line that starts fast. ``imupipe --help`` and ``imupipe COMMAND --help``
import only what they show: no numpy, no pyarrow, no Rerun, no Ray (measured with ``python -X
importtime``; the times themselves are in ``benchmarks/bench_startup.py``)."""

from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("numpy", "pyarrow", "rerun", "ray", "scipy", "rosbags", "mcap", "rich")


def imported(*args: str) -> set[str]:
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "imupipe.pipeline.cli", *args],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [line.split("|")[-1].strip() for line in proc.stderr.splitlines() if "|" in line]
    return {name.split(".")[0] for name in lines}


def test_help_imports_nothing_heavy():
    assert not imported("--help") & set(HEAVY)


def test_convert_help_imports_only_its_parser():
    assert not imported("convert", "--help") & set(HEAVY)


def test_read_does_not_import_convert_or_run():
    """Issue 39: ``imupipe.read`` loads the readers, not the fleet conversion (process pool,
    MCAP writer) nor the run (0.05-0.08 s of CPU a process); ``imupipe.convert`` still works."""
    code = (
        "import sys, imupipe; imupipe.read; imupipe.inspect; imupipe.Calibration; "
        "heavy = [m for m in ('imupipe.pipeline.convert.fleet', 'imupipe.pipeline.run', "
        "'multiprocessing', 'zstandard') if m in sys.modules]; "
        "assert not heavy, heavy; "
        "assert imupipe.convert.__module__ == 'imupipe.pipeline.convert.fleet'; "
        "assert imupipe.ConvertSummary.__name__ == 'ConvertSummary'"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]


ONE_LOG_UNNEEDED = (
    "multiprocessing",  # the pool: one log runs in the driver's process
    "tomllib",  # --config only
    "secrets",  # uploads to an object store only
    "ctypes.util",  # prefault's fallback only (it imports subprocess)
    "imupipe.readers.mapped",  # [fields] mappings only
    "imupipe.readers.message_fields",
    "imupipe.readers.prefault",  # tables of 65,536 rows or more only
    "imupipe.pipeline.convert.dataset",  # --parquet only
    "mcap",  # imupipe reads and writes the records it needs (readers/mcap/records.py)
    "lz4",  # the mcap library's reader's
    "hashlib",  # OpenSSL's libcrypto, 3.4-9 ms: imupipe.pipeline.digests
    "_hashlib",
    "imupipe.pipeline.convert.remote",  # --out or logs on an object store only
)
"""What a one-log ``imupipe convert`` of an MCAP never uses (issue 39: the fixed cost a command
pays; each was imported eagerly before)."""


def test_one_log_convert_imports_only_what_it_uses(tmp_path):
    """Issue 39: ``imupipe convert`` of one MCAP log (no --config, --parquet, pool or object
    store) imports none of :data:`ONE_LOG_UNNEEDED`, and converts the log."""
    from imupipe.pipeline.simulate import simulate
    from imupipe.pipeline.writers.mcap import write_mcap

    table, _ = simulate("static", {"duration_s": 0.2, "rate_hz": 100.0, "temperature": None}, 0)
    write_mcap(tmp_path / "log.mcap", table)
    chain = [{"type": "gyro_calibration", "sensor": "gyro", "kind": "linear",
              "matrix": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
              "offset": [0.01, -0.02, 0.005]}]  # fmt: skip
    (tmp_path / "cal.json").write_text(json.dumps({"imupipe_version": "test", "chain": chain}))
    code = (
        "import sys; from imupipe.pipeline.cli import main; "
        "code = main(sys.argv[1:]); "
        f"loaded = [m for m in {ONE_LOG_UNNEEDED!r} if m in sys.modules]; "
        "assert not loaded, loaded; sys.exit(code)"
    )
    argv = ["convert", "-q", "--calibration", str(tmp_path / "cal.json"), "--out"]
    proc = subprocess.run(
        [sys.executable, "-c", code, *argv, str(tmp_path / "out"), str(tmp_path / "log.mcap")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "out" / "log.mcap").is_file()


def test_digests_are_hashlibs():
    """:mod:`imupipe.pipeline.digests` (CPython's own SHA modules, not OpenSSL's) gives
    ``hashlib``'s digests, on the empty input, every length across a block boundary, and 1 MiB."""
    import hashlib
    import os

    from imupipe.pipeline.digests import sha1_hex, sha256_hex

    for data in [b"", *(os.urandom(n) for n in range(1, 130)), os.urandom(1 << 20)]:
        assert sha256_hex(data) == hashlib.sha256(data).hexdigest()
        assert sha1_hex(data) == hashlib.sha1(data).hexdigest()


def test_the_program_freezes_its_objects_at_exit_and_main_does_not(tmp_path):
    """Issue 39: the ``imupipe`` program (:func:`imupipe.pipeline.cli.console`) exits with
    :func:`main`'s status after freezing the objects alive (the interpreter's last collection
    then skips them); ``main`` itself, also called in-process, leaves the collector alone."""
    code = (
        "import atexit, gc, sys\n"
        "atexit.register(lambda: print('frozen', gc.get_freeze_count() > 0, flush=True))\n"
        "from imupipe.pipeline.cli import console, main\n"
        "sys.argv = ['imupipe', *sys.argv[1:]]\n"
        "code = main(sys.argv[1:])\n"
        "print('after main', gc.get_freeze_count(), gc.isenabled(), flush=True)\n"
        "console()\n"
    )
    missing = str(tmp_path / "missing.json")
    argv = ["convert", "-q", "--calibration", missing, "--out", str(tmp_path / "o"), missing]
    proc = subprocess.run(
        [sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2, proc.stderr[-2000:]  # main's status: a missing calibration
    assert "after main 0 True" in proc.stdout
    assert proc.stdout.strip().splitlines()[-1] == "frozen True"
    assert proc.stderr.count("imupipe: error:") == 2  # one line from each call


SURVEY_UNNEEDED = ("hashlib", "_hashlib", "pyarrow.dataset", "pyarrow.compute")
"""What a survey of one log never uses (issue 39): OpenSSL (its settings hash is
:mod:`imupipe.pipeline.digests`'), and ``pyarrow.dataset`` with ``pyarrow.compute`` (60-70 ms:
the parts are read by ``ParquetFile``, the start times viewed as timestamps, not cast)."""


def test_one_log_survey_imports_only_what_it_uses(tmp_path):
    """Issue 39: ``imupipe survey`` of one MCAP log imports none of :data:`SURVEY_UNNEEDED`,
    and writes its dataset."""
    from imupipe.pipeline.simulate import simulate
    from imupipe.pipeline.writers.mcap import write_mcap

    table, _ = simulate("static", {"duration_s": 12.0, "rate_hz": 100.0}, 0)
    write_mcap(tmp_path / "log.mcap", table)
    code = (
        "import sys; from imupipe.pipeline.cli import main; "
        "code = main(sys.argv[1:]); "
        f"loaded = [m for m in {SURVEY_UNNEEDED!r} if m in sys.modules]; "
        "assert not loaded, loaded; sys.exit(code)"
    )
    argv = ["survey", "--quiet", "--no-rerun", "--jobs", "1", "--out", str(tmp_path / "out")]
    proc = subprocess.run(
        [sys.executable, "-c", code, *argv, str(tmp_path / "log.mcap")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "out" / "survey.parquet").is_file()


def test_a_survey_part_reads_as_read_table_reads_it(tmp_path):
    """:func:`imupipe.pipeline.survey.compass.read_part` (``ParquetFile``) gives
    ``pyarrow.parquet.read_table``'s table, Arrow IPC bytes equal (values, NaN, nulls, types,
    field and schema metadata, chunks): a part as the survey writes it (one row group); with
    several row groups, ``read_table`` chunks the columns by row group, the values the same."""
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    from imupipe.pipeline.survey.compass import read_part

    def ipc(table: pa.Table) -> bytes:
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, table.schema) as writer:
            writer.write_table(table)
        return sink.getvalue().to_pybytes()

    n = 1000
    start = pa.array(np.arange(n, dtype=np.int64) * 10**6).view(pa.timestamp("us", "UTC"))
    table = pa.table(
        {
            "log": pa.array([f"log{i % 7}" for i in range(n)]),
            "frame_id": pa.array([None if i % 5 else "imu" for i in range(n)], pa.string()),
            "start": start,
            "gyro_bias_x": pa.array(np.where(np.arange(n) % 3, np.nan, 1.5)),
            "level": pa.array(np.arange(n) % 2 == 0),
        }
    )
    fields = [
        f.with_metadata({"unit": "rad/s"}) if f.name == "gyro_bias_x" else f for f in table.schema
    ]
    table = table.cast(pa.schema(fields, metadata={"imupipe": "x"}))
    for groups, path in ((1, tmp_path / "part.parquet"), (4, tmp_path / "groups.parquet")):
        pq.write_table(table, path, compression="zstd", row_group_size=-(-n // groups))
        want, got = pq.read_table(path), read_part(path)
        if groups == 1:
            assert ipc(got) == ipc(want)
        assert ipc(got.combine_chunks()) == ipc(want.combine_chunks())
        assert ipc(got) == ipc(table)
