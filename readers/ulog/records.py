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

import copy
import functools
import struct
from collections.abc import Callable, Collection
from typing import Any

import numpy as np

from imupipe.readers.record_walk import Walk, gather, ulog_formats, ulog_walk

HEADER = 16
"""The file header's bytes: magic (7), version (1), start timestamp (uint64, us)."""
FLAG_BITS_MAX = 8 + 8 + 3 * 8
"""The flag bits record's payload; pyulog warns about a longer one (not handled here)."""
DATA_SECTION = frozenset(b"ALC")
"""Record types that end the definitions section (pyulog seeks back and reads them as data)."""
DATA_RECORDS = frozenset(b"IMPQALCDOS")
"""Record types of the data section pyulog decodes (any other is "unknown": not handled)."""
ADD, TAGGED, DATA, FORMAT, INFO, LOGGED, MULTI, DROPOUT, PARAM, DEFAULT, SYNC = (
    ord(c) for c in "ACDFILMOPQS"
)
"""The record types (ULog's letters: ``'A'`` subscription, ``'C'`` tagged logging, ``'D'`` data,
``'F'`` format, ``'I'`` info, ``'L'`` logging, ``'M'`` multi-part info, ``'O'`` dropout,
``'P'`` parameter, ``'Q'`` parameter default, ``'S'`` sync)."""


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
    except (struct.error, IndexError, KeyError, ValueError, OverflowError, RecursionError):
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
    walk = ulog_walk(buf, flags_at, appended[0] if appended else size)
    raw = np.frombuffer(buf, dtype=np.uint8)
    starts_data = np.flatnonzero(np.isin(walk.kinds, list(DATA_SECTION)))
    if not len(starts_data):
        return None
    first = int(starts_data[0])
    if not _definitions(log, buf, _part(walk, slice(None, first)), raw):
        return None
    # each data section as pyulog reads it (``_read_file_data``): its own subscriptions (pyulog
    # turns a section's subscriptions into data at its end and starts the next without them)
    seen = _data(log, buf, _part(walk, slice(first, None)), names)
    end = walk.end
    for i, at in enumerate(appended):
        if seen is None:
            return None
        more = ulog_walk(buf, at, appended[i + 1] if i + 1 < len(appended) else size)
        also, end = _data(log, buf, more, names), more.end
        seen = None if also is None else seen | also
    if seen is None:
        return None
    return log, seen, _cut(buf, end)


def _part(walk: Walk, rows: slice) -> Walk:
    """The records ``rows`` of a walk."""
    return walk._replace(
        offsets=walk.offsets[rows],
        sizes=walk.sizes[rows],
        kinds=walk.kinds[rows],
        ids=walk.ids[rows],
    )


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


def _add_info(log: Any, kind: int, data: bytes) -> bool:
    """Add an information (``'I'``), multi-information (``'M'``) or parameter-default (``'Q'``)
    record to ``log`` as pyulog does (its ``_MessageInfo``, ``_add_message_info_multiple``,
    ``_MessageParameterDefault`` and ``_add_parameter_default``, without an object per record),
    in either section; False for any other record type."""
    if kind == INFO:
        kind_name, key, value = _info(data)
        log._msg_info_dict[key] = value
        log._msg_info_dict_types[key] = kind_name
    elif kind == MULTI:
        continued = data[0]
        kind_name, key, value = _info(data[1:])
        multiple = log._msg_info_multiple_dict
        if key not in multiple:
            multiple[key] = [[value]]
            log._msg_info_multiple_dict_types[key] = kind_name
        elif continued:
            multiple[key][-1].append(value)
        else:
            multiple[key].append([value])
    elif kind == DEFAULT:
        bits = data[0]  # the default types, one bit each: pyulog keys bit b's by 2**b - 1
        _, key, value = _info(data[1:])
        while bits:
            low = bits & -bits
            bits ^= low
            log._default_parameters.setdefault(low - 1, {})[key] = value
    else:
        return False
    return True


def _definitions(log: Any, buf: bytes, walk: Walk, raw: np.ndarray) -> bool:
    """Decode the records of the definitions section as pyulog does; False when pyulog would
    not take one as it is (a type it does not know there, flag bits not first). The parameters
    (``'P'``, a thousand in a PX4 log) are decoded at once when they all have the plain form
    :func:`_plain_parameters` takes, else one by one as the other records."""

    offsets, sizes_all, kinds_all = walk.offsets, walk.sizes.astype(np.int64), walk.kinds
    params = log._initial_parameters
    is_param = kinds_all == PARAM
    plain = _plain_parameters(raw, offsets[is_param], sizes_all[is_param])
    if plain is not None:
        params.update(plain)
        offsets, sizes_all, kinds_all = (
            offsets[~is_param],
            sizes_all[~is_param],
            kinds_all[~is_param],
        )
    formats = log._message_formats
    is_format = kinds_all == FORMAT
    split = iter(ulog_formats(buf, offsets[is_format], sizes_all[is_format]) or ())
    for o, n, kind in zip(offsets.tolist(), sizes_all.tolist(), kinds_all.tolist(), strict=True):
        data = buf[o + 3 : o + 3 + n]
        if kind == PARAM:
            _, key, value = _info(data)
            params[key] = value
        elif kind == FORMAT:
            plain = next(split, None)  # split in C (when built and plain), else here
            fmt = _format(data) if plain is None else _format_of(*plain)
            formats[fmt.name] = fmt
        elif not _add_info(log, kind, data):
            return False  # flag bits are read above, only when first; any other is not pyulog's
    return True


PLAIN_PARAMETERS = ((b"float ", "<f4"), (b"int32_t ", "<i4"))
"""The parameter types PX4 logs, as their key's prefix, and their 4-byte value."""


def _plain_parameters(
    raw: np.ndarray, offsets: np.ndarray, sizes: np.ndarray
) -> list[tuple[str, float | int]] | None:
    """(key, value) of the parameter records at ``offsets`` (payload sizes ``sizes``), in file
    order, decoded at once; None unless every one is plain: ``float <key>`` or ``int32_t
    <key>`` with a key of ASCII bytes without a space and a 4-byte value (pyulog's
    ``_MessageInfo`` then gives the same key, and ``struct.unpack('<f'/'<i')`` the value
    numpy's ``tolist`` gives)."""
    if not len(offsets):
        return []
    n = raw[offsets + 3].astype(np.int64)  # the key's length ("type name")
    head = offsets + 4
    which = np.full(len(offsets), -1)
    skip = np.zeros(len(offsets), dtype=np.int64)
    for i, (prefix, _) in enumerate(PLAIN_PARAMETERS):
        fits = (which < 0) & (n >= len(prefix)) & (head + len(prefix) <= len(raw))
        at = head[fits][:, None] + np.arange(len(prefix))
        same = np.zeros(len(offsets), dtype=bool)
        same[fits] = np.all(raw[at] == np.frombuffer(prefix, np.uint8), axis=1)
        which[same], skip[same] = i, len(prefix)
    if bool(np.any(which < 0)) or bool(np.any(sizes != 1 + n + 4)):
        return None
    starts, lengths = head + skip, n - skip
    total = int(lengths.sum())
    index = np.arange(total) + np.repeat(starts - (np.cumsum(lengths) - lengths), lengths)
    text = raw[index]
    if bool(np.any((text <= 0x20) | (text >= 0x7F))):
        return None  # a space, a control or a non-ASCII byte: pyulog's own decoding
    joined = text.tobytes().decode("ascii")
    ends = np.cumsum(lengths).tolist()
    keys = [joined[a:b] for a, b in zip([0, *ends[:-1]], ends, strict=True)]
    four = raw[(head + n)[:, None] + np.arange(4)].copy()
    values: list[Any] = four.view("<f4").ravel().tolist()
    ints = np.flatnonzero(which == 1)
    for i, v in zip(ints.tolist(), four[ints].view("<i4").ravel().tolist(), strict=True):
        values[i] = v
    return list(zip(keys, values, strict=True))


def _data(log: Any, buf: bytes, walk: Walk, names: Collection[str] | None) -> set[str] | None:
    """One data section's records (``walk``, in file order) into ``log``, as one call of
    pyulog's ``_read_file_data`` reads them; the subscribed topic names, or None when pyulog
    would find the section damaged."""
    from pyulog import ULog

    offsets, sizes, kinds = walk.offsets, walk.sizes.astype(np.int64), walk.kinds
    is_data = kinds == DATA
    data_at = np.flatnonzero(is_data)
    if len(data_at) and int(sizes[data_at].min()) < 2:
        return None
    d_offsets = offsets[data_at]
    msg_ids = walk.ids[data_at]  # uint16: numpy's stable sort of it is a radix sort

    # the other records, in file order: subscriptions first (they decide what the data is)
    others = np.flatnonzero(~is_data)
    other_kinds = kinds[others].tolist()
    if not set(other_kinds) <= DATA_RECORDS:
        return None
    # msg_id -> 1 + the index of its subscription record (0: none); zeros, whose pages stay
    # untouched but for the ids used (np.full's 512 kB cost 0.3 ms a read)
    subscribed_plus = np.zeros(1 << 16, dtype=np.int64)
    subs: dict[int, Any] = {}
    seen: set[str] = set()
    filtered_before = set(log._filtered_message_ids)  # by the sections before
    flat: dict[str, list[str]] = {}
    simple: dict[str, bool] = {}
    made: dict[str, Any] = {}
    for i, kind in zip(others.tolist(), other_kinds, strict=True):
        if kind != ADD:
            continue
        o = int(offsets[i])
        data = buf[o + 3 : o + 3 + int(sizes[i])]
        (msg_id,) = struct.unpack("<H", data[1:3])
        name = str(data[3:], "utf-8", "ignore")
        if subscribed_plus[msg_id]:
            return None  # pyulog replaces the first subscription (and drops its data)
        subscribed_plus[msg_id] = i + 1
        seen.add(name)
        if names is None or name in names:
            subs[msg_id] = _subscription(data, name, log._message_formats, made)
        elif _layout_ok(name, log._message_formats, flat, simple):
            log._filtered_message_ids.add(msg_id)
        else:
            return None  # pyulog cannot make the topic's dtype: a corrupt file to it
    # each data record's subscription index (len(offsets): none); every data record follows
    # its subscription in the section, or is of a topic not read subscribed before (else
    # pyulog: "no subscription found")
    plus = subscribed_plus[msg_ids]
    subscribed_at = np.where(plus > 0, plus - 1, len(offsets))
    if len(data_at):
        known = subscribed_at < data_at
        if not bool(np.all(known)):
            earlier = np.zeros(1 << 16, dtype=bool)
            earlier[list(filtered_before)] = True
            if not bool(np.all(known | earlier[msg_ids])):
                return None

    # each read topic's payloads; the timestamps of its records (pyulog's _last_timestamp)
    stamps = np.zeros(len(data_at), dtype=np.uint64)
    expect = np.zeros(1 << 16, dtype=np.int64)  # msg_id -> payload size of a topic read
    for msg_id, sub in subs.items():
        expect[msg_id] = 2 + sub.dtype.itemsize
    taken = (expect[msg_ids] > 0) & (data_at > subscribed_at)
    if bool(np.any(sizes[data_at[taken]] != expect[msg_ids[taken]])):
        return None  # a payload of another size: pyulog's "corrupt data"
    order = np.argsort(msg_ids, kind="stable")
    keys = np.fromiter(subs, dtype=np.int64, count=len(subs))
    bounds = np.searchsorted(msg_ids[order], np.concatenate([keys, keys + 1])).tolist()
    for j, (msg_id, sub) in enumerate(subs.items()):
        rows = order[bounds[j] : bounds[j + len(subs)]]
        rows = rows[data_at[rows] >= subscribed_plus[msg_id]]  # before it: a topic not read then
        if not len(rows):
            continue
        item = sub.dtype.itemsize
        if sub.timestamp_offset + 8 > item:
            return None  # pyulog reads the stamp past the payload: the end of its parse
        at = d_offsets[rows]
        sub.buffer = gather(buf, at, 5, item)
        stamps[rows] = np.frombuffer(gather(buf, at, 5 + sub.timestamp_offset, 8), dtype="<u8")

    # the other records in file order, each with pyulog's _last_timestamp at that point
    running = np.maximum.accumulate(stamps) if len(stamps) else stamps
    start = log._last_timestamp  # the file's start, or where the section before left it
    kinds_other = kinds[others]
    log._sync_seq_cnt += int(np.count_nonzero(kinds_other == SYNC))
    rest = others[(kinds_other != ADD) & (kinds_other != SYNC)]
    before = np.searchsorted(data_at, rest).tolist()  # data records before each record
    for o, n, kind, k in zip(
        offsets[rest].tolist(), sizes[rest].tolist(), kinds[rest].tolist(), before, strict=True
    ):
        data = buf[o + 3 : o + 3 + n]
        if kind in (PARAM, DROPOUT):
            last = max(start, int(running[k - 1])) if k else start
            if kind == PARAM:
                _, key, value = _info(data)
                log._changed_parameters.append((last, key, value))
            else:
                log._dropouts.append(ULog.MessageDropout(data, None, last))
        elif _add_info(log, kind, data):
            pass
        elif kind == LOGGED:
            log._logged_messages.append(ULog.MessageLogging(data, None))
        else:  # C
            tagged = ULog.MessageLoggingTagged(data, None)
            log._logged_messages_tagged.setdefault(tagged.tag, []).append(tagged)
    if len(running):
        log._last_timestamp = max(start, int(running[-1]))

    # pyulog's final representation: subscriptions popped last first, kept when they hold data
    for sub in reversed(list(subs.values())):
        if len(sub.buffer) > 0:
            log._data_list.append(ULog.Data(sub))
    log._data_list.sort(key=lambda ds: (ds.name, ds.multi_id))
    return seen


def _info(data: bytes) -> tuple[str, str, Any]:
    """An info (``'I'``) or parameter (``'P'``) record: (value type, key, value), decoded as
    pyulog's ``_MessageInfo`` decodes it (strings UTF-8 with undecodable bytes dropped, pyulog's
    default; a type pyulog does not know: the raw bytes), without its object per record."""
    n = data[0]
    split = str(data[1 : 1 + n], "utf-8", "ignore").split(" ")
    kind, key = split[0], split[1]
    rest = data[1 + n :]
    if kind.startswith("char["):
        return kind, key, str(rest, "utf-8", "ignore")
    unpack = _unpackers().get(kind)
    if unpack is None:
        return kind, key, rest
    return kind, key, unpack(rest)[0]


@functools.cache
def _pyulog() -> Any:
    """pyulog's ``ULog`` class (imported on first use; a ``from pyulog import ULog`` in a
    function called per record costs a Python-level import step each call)."""
    from pyulog import ULog

    return ULog


@functools.cache
def _unpackers() -> dict[str, Callable[[bytes], tuple[Any, ...]]]:
    """pyulog's value types -> the unpacker of one little-endian value, as pyulog reads them."""
    ULog = _pyulog()

    return {k: struct.Struct("<" + v[0]).unpack for k, v in ULog._UNPACK_TYPES.items()}


def _format(data: bytes) -> Any:
    """A format record (``'F'``): pyulog's ``MessageFormat`` (``name``; ``fields``: (type,
    array size or 0, name) each), split as pyulog splits it, without its calls per field."""
    parts = str(data, "utf-8", "ignore").split(":")
    fields = []
    for entry in parts[1].split(";"):
        if not entry:
            continue
        words = entry.split(" ")
        kind, field = words[0], words[1]
        a = kind.find("[")
        if a == -1:
            fields.append((kind, 0, field))
            continue
        count = int(kind[a + 1 : kind.find("]")])
        if count < 0 or count > 0xFFFF:
            raise ValueError(f"invalid array size: {count}")
        fields.append((kind[:a], count, field))
    return _format_of(parts[0], fields)


def _format_of(name: str, fields: list[tuple[str, int, str]]) -> Any:
    """pyulog's ``MessageFormat`` of a format record split into ``name`` and ``fields``."""
    ULog = _pyulog()
    fmt = ULog.MessageFormat.__new__(ULog.MessageFormat)
    fmt.name = name
    fmt.fields = fields
    return fmt


def _flat(type_name: str, formats: dict[str, Any], memo: dict[str, list[str]]) -> list[str]:
    """The field names pyulog's ``_MessageAddLogged._parse_nested_type`` gives a type (nested
    types flattened: ``a.b``, arrays ``a[0]``), trailing padding kept; KeyError for a type
    without a format, as pyulog's."""
    ULog = _pyulog()

    if type_name in memo:
        return memo[type_name]
    out: list[str] = []
    for kind, count, field in formats[type_name].fields:
        inner = None if kind in ULog._UNPACK_TYPES else _flat(kind, formats, memo)
        heads = [f"{field}[{i}]" for i in range(count)] if count > 0 else [field]
        for head in heads:
            out.extend([head] if inner is None else [f"{head}.{n}" for n in inner])
    memo[type_name] = out
    return out


def _layout_ok(
    name: str, formats: dict[str, Any], memo: dict[str, list[str]], simple: dict[str, bool]
) -> bool:
    """Whether pyulog can make the dtype of a topic this parse does not read (its fields
    resolve and, trailing padding dropped, are unique: numpy's structured dtype refuses a name
    twice), without making it; KeyError for a missing format, as pyulog's."""
    if _simple(name, formats, simple):
        return True
    names = list(_flat(name, formats, memo))
    while names and names[-1].startswith("_padding"):
        names.pop()
    if "" in names:  # numpy names such a field itself: ask pyulog's own class
        ULog = _pyulog()

        try:
            ULog._MessageAddLogged(b"\0\0\0" + name.encode(), None, formats)
        except ValueError:
            return False
        return True
    return len(set(names)) == len(names)


def _simple(type_name: str, formats: dict[str, Any], memo: dict[str, bool]) -> bool:
    """A type whose flattened field names are unique by construction: its field names are
    unique, not empty, hold none of ``.[]``, and its nested types are such types (each
    flattened name then starts with its own field's name, ``field`` or ``field[i]``, up to its
    first ``.``); KeyError for a type without a format, as pyulog's."""
    ULog = _pyulog()

    if type_name in memo:
        return memo[type_name]
    fields = formats[type_name].fields
    names = [f for _, _, f in fields]
    joined = "\0".join(names)
    ok = (
        len(set(names)) == len(names)
        and all(names)
        and "." not in joined
        and "[" not in joined
        and "]" not in joined
    )
    basic = ULog._UNPACK_TYPES
    for kind in {k for k, _, _ in fields if k not in basic}:  # each resolves, else KeyError
        ok = _simple(kind, formats, memo) and ok
    memo[type_name] = ok
    return ok


def _subscription(data: bytes, name: str, formats: dict[str, Any], made: dict[str, Any]) -> Any:
    """pyulog's ``_MessageAddLogged`` of a subscription record; another instance of a topic
    already made in this parse is a copy of it (the same fields and dtype: they depend on the
    topic's format only) with its own ids, field list and buffer."""
    ULog = _pyulog()

    first = made.get(name)
    if first is None:
        made[name] = sub = ULog._MessageAddLogged(data, None, formats)
        return sub
    sub = copy.copy(first)
    (sub.multi_id,) = struct.unpack("<B", data[0:1])
    (sub.msg_id,) = struct.unpack("<H", data[1:3])
    sub.field_data = list(first.field_data)
    sub.buffer = bytearray()
    return sub
