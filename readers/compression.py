"""Chunk decompression shared by the MCAP and ROS 1 bag readers.

Any decompressor failure, an unknown compression or a size other than the one the chunk header
states is a :class:`ReadError` naming the chunk (``where``), never a crash. The decompressors
release the GIL: the MCAP and bag readers run them in worker threads, :data:`PREFETCH` chunks
ahead of the chunk they decode.
"""

from __future__ import annotations

import bz2

import numpy as np

from imupipe.readers.errors import ReadError

PREFETCH = 3
"""Chunks a reader has decompressed (or in decompression) ahead of the one it decodes."""
DECOMPRESS_THREADS = 2
"""Worker threads that decompress chunks for one reader."""


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
