"""imupipe's own parse of a ULog's records: pyulog's result, without pyulog's step per record.

pyulog 1.3 (``pyulog.core.ULog``) reads a ULog record by record in Python (a header read, a
payload read and a record object per message), then makes each topic's arrays with one
``numpy.frombuffer``. Here the record walk is done by :func:`imupipe.readers.record_walk.ulog_walk`
(compiled when built: the records follow each other without an index, so the walk is
sequential), the data records (``'D'``) are sorted by ``msg_id`` with numpy and each read topic's
fixed-size payloads are copied into one buffer (:func:`~imupipe.readers.record_walk.gather`),
which pyulog's own ``ULog.Data`` turns into the arrays. The other records (format definitions
``'F'``, info ``'I'``/``'M'``, parameters ``'P'``/``'Q'``, subscriptions ``'A'``, logging
``'L'``/``'C'``, dropouts ``'O'``, sync ``'S'``, the flag bits ``'B'``: a few hundred in a
flight log) are decoded by pyulog's own record classes, in file order, so that every field of
the result is what pyulog's parse gives: a ``pyulog.ULog`` whose attributes are filled as
``ULog(path, message_name_filter_list=...)`` fills them (``tests/test_ulog_records.py`` checks
them all, on every ULog of ``tests/data`` and ``../shared/data``). The appended-data sections
(flag bits' ``appended_offsets``) are read as pyulog reads them (each section up to the next
offset), and a last record cut by the end of the file is left out, as pyulog leaves it out.

**What this parse does not handle** (:func:`parse` returns None and the caller parses with
pyulog, which reads past such damage in its own way): a file pyulog would say something about
or find corrupt (a header that is not ULog's, a file version above 1, flag bits that are not
the first record or are longer than 40 bytes, a record of a type pyulog does not know or in the
wrong section, ``'R'`` (remove subscription) included, a record whose payload pyulog cannot
decode, a data record of a ``msg_id`` without a subscription, of fewer than 2 bytes or whose
size is not its topic's, a ``msg_id`` subscribed twice, a topic whose timestamp does not lie
in its payload, an appended-data offset past the end of the file) and a file without a data
section.
"""

from __future__ import annotations

import struct
from collections.abc import Collection
from typing import Any

import numpy as np

from imupipe.readers.record_walk import gather, ulog_walk

HEADER = 16
"""The file header's bytes: magic (7), version (1), start timestamp (uint64, us)."""
FLAG_BITS_MAX = 8 + 8 + 3 * 8
"""The flag bits record's payload; pyulog warns about a longer one (not handled here)."""
DEFINITIONS = frozenset(b"IMFPQB")
"""Record types of the definitions section (pyulog's ``_read_file_definitions``)."""
DATA_SECTION = frozenset(b"ALC")
"""Record types that end the definitions section (pyulog seeks back and reads them as data)."""
DATA_RECORDS = frozenset(b"IMPQALCDOS")
"""Record types of the data section pyulog decodes (any other is "unknown": not handled)."""
D = ord("D")


class _Header:
    """pyulog's record header as its record classes read it (``msg_size``)."""

    def __init__(self, size: int, kind: int) -> None:
        self.msg_size = size
        self.msg_type = kind


Parsed = tuple[Any, set[str], tuple[int, int, int] | None]
"""A parse: the ``pyulog.ULog``, the topic names subscribed, the record cut by the end of the
file (offset, bytes claimed, bytes left) or None."""


def parse(path: Any, names: Collection[str] | None) -> Parsed | None:
    """The ``pyulog.ULog`` that ``ULog(path, message_name_filter_list=names)`` gives, the
    subscribed topic names seen (every ``'A'`` record's) and the last record cut by the end of
    the file (pyulog leaves it out without a word); None for a file this parse does not handle
    (see the module docstring)."""
    with open(path, "rb") as fh:
        buf = fh.read()
    try:
        return _parse(buf, names)
    except (struct.error, IndexError, KeyError, ValueError, OverflowError, TypeError):
        return None  # pyulog decodes such a record as damage: its own parse says where


def _parse(buf: bytes, names: Collection[str] | None) -> Parsed | None:
    from pyulog import ULog

    size = len(buf)
    if size < HEADER or buf[:7] != ULog.HEADER_BYTES or buf[7] > 1:
        return None
    log = ULog(None)
    log._file_version = buf[7]
    (log._start_timestamp,) = struct.unpack_from("<Q", buf, 8)
    log._last_timestamp = log._start_timestamp

    flags_at = HEADER
    appended: list[int] = []
    if size >= HEADER + 3 and buf[HEADER + 2] == ord("B"):
        (flag_size,) = struct.unpack_from("<H", buf, HEADER)
        if flag_size > FLAG_BITS_MAX or HEADER + 3 + flag_size > size:
            return None
        data = buf[HEADER + 3 : HEADER + 3 + flag_size]
        bits = ULog._MessageFlagBits(data, _Header(flag_size, ord("B")))
        log._compat_flags = bits.compat_flags
        log._incompat_flags = bits.incompat_flags
        log._appended_offsets = bits.appended_offsets
        if log._incompat_flags[0] & ~1 or any(log._incompat_flags[1:]):
            return None  # pyulog raises ULogIncompatibleFlagException: its parse says so
        if log.has_data_appended:
            appended = list(log._appended_offsets)
        flags_at = HEADER + 3 + flag_size
    if any(o > size for o in appended):
        return None

    # the first section: definitions, then the data up to the first appended offset
    offsets, end = ulog_walk(buf, flags_at, appended[0] if appended else size)
    raw = np.frombuffer(buf, dtype=np.uint8)
    kinds = raw[offsets + 2]
    starts_data = np.flatnonzero(np.isin(kinds, list(DATA_SECTION)))
    if not len(starts_data):
        return None
    first = int(starts_data[0])
    for o in offsets[:first].tolist():
        if not _definition(log, buf, o):
            return None
    sections = [offsets[first:]]
    for i, at in enumerate(appended):
        nxt = appended[i + 1] if i + 1 < len(appended) else size
        more, end = ulog_walk(buf, at, nxt)
        sections.append(more)
    parsed = _data(log, buf, raw, np.concatenate(sections), names)
    if parsed is None:
        return None
    return log, parsed, _cut(buf, int(end))


def _cut(buf: bytes, end: int) -> tuple[int, int, int] | None:
    """The record cut by the end of the file, when the last section's walk stopped before it:
    (its offset, the bytes its header claims, header included, the bytes left); None when the
    records end with the file."""
    left = len(buf) - end
    if left == 0:
        return None
    if left < 3:  # the header itself is cut
        return end, 3, left
    (claimed,) = struct.unpack_from("<H", buf, end)
    return end, 3 + claimed, left


def _definition(log: Any, buf: bytes, o: int) -> bool:
    """Decode one record of the definitions section as pyulog does; False when pyulog would
    not take it as it is (a type it does not know there, flag bits not first)."""
    from pyulog import ULog

    (n, kind) = struct.unpack_from("<HB", buf, o)
    data = buf[o + 3 : o + 3 + n]
    if kind not in DEFINITIONS or kind == ord("B"):  # flag bits: read above, only when first
        return False
    if kind == ord("I"):
        info = ULog._MessageInfo(data, None)
        log._msg_info_dict[info.key] = info.value
        log._msg_info_dict_types[info.key] = info.type
    elif kind == ord("M"):
        log._add_message_info_multiple(ULog._MessageInfo(data, None, is_info_multiple=True))
    elif kind == ord("F"):
        fmt = ULog.MessageFormat(data, None)
        log._message_formats[fmt.name] = fmt
    elif kind == ord("P"):
        info = ULog._MessageInfo(data, None)
        log._initial_parameters[info.key] = info.value
    else:  # Q
        log._add_parameter_default(ULog._MessageParameterDefault(data, None))
    return True


def _data(
    log: Any,
    buf: bytes,
    raw: np.ndarray,
    offsets: np.ndarray,
    names: Collection[str] | None,
) -> set[str] | None:
    """The data section's records (``offsets``, in file order) into ``log``; the subscribed
    topic names, or None when pyulog would find the section damaged."""
    from pyulog import ULog

    sizes = raw[offsets].astype(np.int64) | (raw[offsets + 1].astype(np.int64) << 8)
    kinds = raw[offsets + 2]
    is_data = kinds == D
    data_at = np.flatnonzero(is_data)
    if len(data_at) and int(sizes[data_at].min()) < 2:
        return None
    d_offsets = offsets[data_at]
    msg_ids = raw[d_offsets + 3].astype(np.int64) | (raw[d_offsets + 4].astype(np.int64) << 8)

    # the other records, in file order: subscriptions first (they decide what the data is)
    others = np.flatnonzero(~is_data)
    other_kinds = kinds[others].tolist()
    if not set(other_kinds) <= DATA_RECORDS:
        return None
    subscribed_at = np.full(1 << 16, len(offsets), dtype=np.int64)
    subs: dict[int, Any] = {}
    seen: set[str] = set()
    for i, kind in zip(others.tolist(), other_kinds, strict=True):
        if kind != ord("A"):
            continue
        o = int(offsets[i])
        sub = ULog._MessageAddLogged(buf[o + 3 : o + 3 + int(sizes[i])], None, log._message_formats)
        if subscribed_at[sub.msg_id] < len(offsets):
            return None  # pyulog replaces the first subscription (and drops its data)
        subscribed_at[sub.msg_id] = i
        seen.add(sub.message_name)
        if names is None or sub.message_name in names:
            subs[sub.msg_id] = sub
        else:
            log._filtered_message_ids.add(sub.msg_id)
    # every data record follows its subscription (else pyulog: "no subscription found")
    if len(data_at) and bool(np.any(subscribed_at[msg_ids] > data_at)):
        return None

    # each read topic's payloads; the timestamps of its records (pyulog's _last_timestamp)
    stamps = np.zeros(len(data_at), dtype=np.uint64)
    order = np.argsort(msg_ids, kind="stable")
    sorted_ids = msg_ids[order]
    for msg_id, sub in subs.items():
        lo, hi = np.searchsorted(sorted_ids, [msg_id, msg_id + 1])
        rows = order[lo:hi]
        if not len(rows):
            continue
        item = sub.dtype.itemsize
        if bool(np.any(sizes[data_at[rows]] - 2 != item)):
            return None  # a payload of another size: pyulog's "corrupt data"
        if sub.timestamp_offset + 8 > item:
            return None  # pyulog reads the stamp past the payload: the end of its parse
        at = d_offsets[rows]
        sub.buffer = gather(buf, at, 5, item)
        stamps[rows] = np.frombuffer(gather(buf, at, 5 + sub.timestamp_offset, 8), dtype="<u8")

    # the other records in file order, each with pyulog's _last_timestamp at that point
    running = np.maximum.accumulate(stamps) if len(stamps) else stamps
    before = np.searchsorted(data_at, others)  # data records before each other record
    start = log._start_timestamp
    for i, kind, k in zip(others.tolist(), other_kinds, before.tolist(), strict=True):
        last = max(start, int(running[k - 1])) if k else start
        o = int(offsets[i])
        data = buf[o + 3 : o + 3 + int(sizes[i])]
        if kind == ord("I"):
            info = ULog._MessageInfo(data, None)
            log._msg_info_dict[info.key] = info.value
            log._msg_info_dict_types[info.key] = info.type
        elif kind == ord("M"):
            log._add_message_info_multiple(ULog._MessageInfo(data, None, is_info_multiple=True))
        elif kind == ord("P"):
            info = ULog._MessageInfo(data, None)
            log._changed_parameters.append((last, info.key, info.value))
        elif kind == ord("Q"):
            log._add_parameter_default(ULog._MessageParameterDefault(data, None))
        elif kind == ord("L"):
            log._logged_messages.append(ULog.MessageLogging(data, None))
        elif kind == ord("C"):
            tagged = ULog.MessageLoggingTagged(data, None)
            log._logged_messages_tagged.setdefault(tagged.tag, []).append(tagged)
        elif kind == ord("O"):
            log._dropouts.append(ULog.MessageDropout(data, None, last))
        elif kind == ord("S"):
            log._sync_seq_cnt += 1
    if len(running):
        log._last_timestamp = max(start, int(running[-1]))

    # pyulog's final representation: subscriptions popped last first, kept when they hold data
    for sub in reversed(list(subs.values())):
        if len(sub.buffer) > 0:
            log._data_list.append(ULog.Data(sub))
    log._data_list.sort(key=lambda ds: (ds.name, ds.multi_id))
    return seen
