"""Issue 39: the convert worker's memory. The MCAP writer encodes a slice's chunks one at a
time (never the slice's records all at once) and must give the bytes that encoding the whole
slice and cutting it gave; applying a temperature step imports no scipy (the lag fit's
``minimize_scalar`` alone needs it: 43 MB and about 1 s of imports in every worker)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from imupipe.pipeline.writers import mcap as writer_module
from imupipe.pipeline.writers.mcap import (
    DEFAULT_TOPICS,
    RECORD_HEADER,
    STREAM_TYPES,
    McapTableWriter,
    _fill_record_headers,
    _meta,
    encode_stream,
    message_times,
    msgdef,
    written_streams,
)
from imupipe.readers.table import make_table


class WholeSliceWriter(McapTableWriter):
    """The writer as it was before issue 39: every record of a slice encoded at once
    (:func:`encode_stream`), then cut into chunks: the reference for the bytes."""

    def _encode_rows(self, table: pa.Table) -> np.ndarray:
        topics = {**DEFAULT_TOPICS, **_meta(table).get("topics", {}), **self.topics}
        log_all, pub_all = message_times(table)
        pending = []
        for stream in written_streams(table):
            rows, groups = encode_stream(table, stream, prefix=RECORD_HEADER)
            if not len(rows):
                continue
            msgtype = STREAM_TYPES[stream]
            cid = self._channel(
                topics[stream], "cdr", (msgtype, "ros2msg", msgdef(msgtype).encode())
            )
            seq = self._sequence(cid, len(rows))
            for sel, recs in groups:
                log = log_all[rows[sel]]
                _fill_record_headers(recs, cid, seq[sel], log, pub_all[rows[sel]])
                if np.any(log[1:] < log[:-1]):
                    order = np.argsort(log, kind="stable")
                    recs, log = recs[order], log[order]
                per_chunk = max(1, self.chunk_bytes // recs.shape[1])
                for a in range(0, len(log), per_chunk):
                    b = min(a + per_chunk, len(log))
                    pending.append((int(log[a]), len(pending), cid, recs[a:b], log[a:b]))
        pending.sort(key=lambda p: (p[0], p[1]))
        for _, _, cid, recs, log in pending:
            m, size = recs.shape
            self._write_chunk(
                recs.reshape(-1),
                np.arange(m, dtype=np.int64) * size,
                m * size,
                np.full(m, cid, dtype=np.int64),
                log,
            )
        return log_all


def _mixed_table(n: int, seed: int) -> pa.Table:
    """IMU, magnetometer and temperature rows, two frame_ids of different lengths (and nulls),
    log times that go back now and then, a covariance column, NaN values."""
    rng = np.random.default_rng(seed)
    t = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 5_000_000
    kind = rng.integers(0, 10, n)
    log = t + rng.integers(0, 3, n) * 1_000_000
    log[rng.random(n) < 0.05] -= 40_000_000  # out of order in the log
    gyro = rng.normal(0, 1e-3, (n, 3))
    gyro[rng.random(n) < 0.01, 1] = np.nan
    frames = np.where(rng.random(n) < 0.3, "imu_link_long", "imu")
    frame_ids = pa.array([None if rng.random() < 0.02 else f for f in frames], pa.string())
    cov = pa.FixedSizeListArray.from_arrays(pa.array(rng.random(9 * n)), 9)
    return make_table(
        t,
        gyro=gyro,
        accel=rng.normal(0, 1e-2, (n, 3)) + [0, 0, 9.8],
        mag=rng.normal(0, 5e-5, (n, 3)),
        temperature=25 + rng.normal(0, 0.1, n),
        valid={"imu": kind < 7, "mag": kind == 7, "temperature": kind >= 8},
        extra={"log_time_ns": log, "frame_id": frame_ids, "gyro_cov": cov},
        metadata={"frame_id": {"imu": "imu", "mag": "mag", "temperature": "temp"}},
    )


@pytest.mark.parametrize(("chunk_bytes", "slice_rows"), [(4096, 700), (1 << 20, 65_536), (1, 50)])
def test_chunk_by_chunk_encoding_gives_the_whole_slice_bytes(
    tmp_path: Path, chunk_bytes: int, slice_rows: int
) -> None:
    table = _mixed_table(3_000, seed=chunk_bytes)
    paths = []
    for cls in (McapTableWriter, WholeSliceWriter):
        path = tmp_path / f"{cls.__name__}.mcap"
        with cls(path, chunk_bytes=chunk_bytes, slice_rows=slice_rows) as w:
            for start in range(0, table.num_rows, 997):  # batches unlike the slices
                w.write_table(table.slice(start, 997))
        paths.append(path)
    ours, reference = (p.read_bytes() for p in paths)
    assert len(ours) > 100_000
    assert ours == reference


def test_a_slice_is_encoded_a_chunk_at_a_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No encode call of the writer holds more than one chunk's records."""
    table = _mixed_table(4_000, seed=3)
    sizes: list[int] = []
    encode = writer_module.cdr.encode

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        out = encode(*args, **kwargs)
        sizes.append(out.nbytes)
        return out

    monkeypatch.setattr(writer_module.cdr, "encode", counted)
    with McapTableWriter(tmp_path / "out.mcap", chunk_bytes=8192) as w:
        w.write_table(table)
    assert len(sizes) > 20
    assert max(sizes) <= 8192


TEMPERATURE_PROBE = """
import json, sys
import numpy as np
from imupipe.readers.table import make_table
from imupipe.pipeline.calibration_file import on_device
from imupipe.stages.steps import apply_chain_stream, steps_from_json
chain = json.loads(sys.argv[1])
n = 4000
i = np.arange(n)
t = i / 200.0
table = make_table(
    1_700_000_000_000_000_000 + np.round(t * 1e9).astype(np.int64),
    gyro=np.zeros((n, 3)), accel=np.zeros((n, 3)) + [0, 0, 9.8],
    temperature=25 + 5 * np.sin(t / 10.0),
    valid={"imu": i % 20 != 19, "temperature": i % 20 == 19},
)
steps = on_device(steps_from_json(chain), chain, lenient=True)
out = list(apply_chain_stream([table.slice(0, 1500), table.slice(1500)], steps))
print(sum(len(p) for p in out), sorted(m for m in sys.modules if m.split(".")[0] == "scipy")[:3])
"""


def test_applying_a_lag_model_temperature_step_imports_no_scipy() -> None:
    axes = [{"terms": ["1", "Ts", "dTs", "dT"], "coefficients": [1e-4, 2e-5, 0.1, 0.05]}] * 3
    chain = [
        {
            "type": "temperature",
            "sensor": "gyro",
            "kind": "temperature",
            "model": "lag",
            "tref": 25.0,
            "window": None,
            "window_s": 2.0,
            "lag_s": 20.0,
            "ranges": {"Ts": [5.0, 45.0], "dTs": [-1.0, 1.0], "dT": [-1.0, 1.0], "T": [5, 45]},
            "knots": None,
            "scale": None,
            "axes": axes,
            "reference": [0.0, 0.0, 0.0],
        }
    ]
    proc = subprocess.run(
        [sys.executable, "-c", TEMPERATURE_PROBE, json.dumps(chain)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split()[-2:] == ["4000", "[]"], proc.stdout
