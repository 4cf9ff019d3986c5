"""Issue 17: every chain streams in ``convert``. A log several batches long converts to the same
messages, byte for byte, whatever the batch size (one batch = the whole log), with the carried-over
topics interleaved as they are read."""

from __future__ import annotations

import json

from test_convert import CHAIN, _status_messages, raw_messages

from imupipe.pipeline.convert.fleet import convert
from imupipe.pipeline.convert.manifest import read_manifest
from imupipe.pipeline.simulate import simulate
from imupipe.pipeline.writers.mcap import write_mcap
from imupipe.readers.dispatch import iter_input
from imupipe.readers.spec import InputSpec


def test_batches_change_nothing(tmp_path):
    table, _ = simulate("mag", {"duration_s": 20.0, "rate_hz": 200.0}, seed=5)
    status = _status_messages(30, int(table.column("t_ns")[0].as_py()))
    log = tmp_path / "long.mcap"
    write_mcap(log, table, carry_over=status, chunk_bytes=1 << 15, slice_rows=500)
    batches = [b.num_rows for b, _ in iter_input(InputSpec(path=log), batch_rows=700)]
    assert len(batches) >= 4, batches  # the log really is several batches long
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"chain": CHAIN}))
    outputs = {}
    for rows in (700, 10**9):
        out = tmp_path / f"out{rows}"
        summary = convert([log], cal, out, jobs=1, batch_rows=rows)
        assert not summary.failed and len(summary.converted) == 1
        (line,) = read_manifest(out)
        assert line["mode"] == "streamed"
        outputs[rows] = raw_messages(out / "long.mcap")
    assert outputs[700] == outputs[10**9]
    assert len(outputs[700]["/status"]) == 30
    assert len(outputs[700]["/imu/data"]) == table.num_rows - table.column("gyro_x").null_count
