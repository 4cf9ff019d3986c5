"""Test helpers: decode an MCAP with the mcap library's ROS 2 decoder; read Rerun recordings;
see which pages of memory are mapped."""

from __future__ import annotations

import collections
import ctypes
import ctypes.util
import mmap
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory


def resident(address: int, size: int) -> float:
    """The share of the whole pages in ``[address, address + size)`` that are mapped (Linux
    ``mincore``): memory written, or mapped ahead, against the kernel's untouched zeros."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_char_p]
    page = mmap.PAGESIZE
    start = -(-address // page) * page
    stop = (address + size) // page * page
    if stop <= start:
        return 0.0
    vec = ctypes.create_string_buffer((stop - start) // page)
    assert libc.mincore(start, stop - start, vec) == 0, ctypes.get_errno()
    return float((np.frombuffer(vec.raw, np.uint8) & 1).mean())


def decode_mcap(path: str | Path) -> dict[str, list]:
    """topic -> list of (log_time, decoded message), with the mcap library's ROS 2 decoder."""
    out: dict[str, list] = collections.defaultdict(list)
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _schema, channel, message, decoded in reader.iter_decoded_messages(
            log_time_order=False
        ):
            out[channel.topic].append((message.log_time, decoded))
    return dict(out)


def mcap_attachments(path: str | Path) -> dict[str, bytes]:
    with open(path, "rb") as fh:
        return {a.name: a.data for a in make_reader(fh).iter_attachments()}


def stamps_ns(messages: list) -> np.ndarray:
    return np.array(
        [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for _, m in messages]
    )


def vec(messages: list, field: str) -> np.ndarray:
    return np.array(
        [[getattr(m, field).x, getattr(m, field).y, getattr(m, field).z] for _, m in messages]
    )


def rrd_rows(path: str | Path) -> dict[str, int]:
    """Entity path -> number of (non-static) rows in a recording, read with rerun.chunk.RrdReader."""
    import rerun.chunk as rc

    rows: collections.Counter = collections.Counter()
    for chunk in rc.RrdReader(str(path)).stream().to_chunks():
        if not chunk.is_static:
            rows[chunk.entity_path] += chunk.num_rows
    return dict(rows)


def rrd_static(path: str | Path) -> dict[str, dict]:
    """Entity path -> {component: its last static value} in a recording (rerun.chunk.RrdReader):
    what views without a time axis show (bar charts, 2D plots, text documents)."""
    import pyarrow as pa
    import rerun.chunk as rc

    out: dict[str, dict] = collections.defaultdict(dict)
    for chunk in rc.RrdReader(str(path)).stream().to_chunks():
        if chunk.is_static:
            batch = chunk.to_record_batch()
            for column in batch.schema.names:
                if ":" in column:
                    value = pa.array(batch.column(column)).to_pylist()[-1]
                    out[chunk.entity_path][column] = value
    return dict(out)


def screenshot_tool():
    """``docs/screenshots/make_screenshots.py`` as a module: its Chromium and Rerun viewer lookups
    and flags, shared with the tests that render in a browser or start a viewer."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "docs" / "screenshots" / "make_screenshots.py"
    spec = importlib.util.spec_from_file_location("make_screenshots", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
