"""Write a common table's magnetometer and flight streams as an ArduPilot DataFlash log
(``.bin``), as ``AP_Logger`` lays it out: ``FMT`` records first, then every record in time
order, each ``0xA3 0x95 type`` followed by its little-endian fields (pymavlink's ``DFReader``
and imupipe's reader read it back).

Messages (ArduPilot 4.x layouts; units as ``LogStructure.h`` states them):

- ``MAG``: ``MagX/Y/Z`` int16 milligauss (the table's tesla, rounded);
- ``ATT``: ``Roll``/``Pitch`` int16 and ``Yaw`` uint16 centidegrees (from the ``attitude``
  quaternion, Z-Y-X Euler angles, yaw in [0, 360));
- ``GPS``: ``Status`` 3 (3D fix), ``GMS``/``GWk`` GPS time of week (ms) and week from the table's
  ``gps_year`` metadata, ``Lat``/``Lng`` int32 1e-7 deg, ``Alt`` int32 cm;
- ``BAT``: ``Curr`` float A;
- ``CTUN``: a copter's ``ThI``/``ThO`` float 0..1 (the ``throttle`` flight stream, both);
- ``PARM``: :data:`PARAMETERS`, then the table's ``ardupilot.parameters`` metadata (a simulated
  vehicle's own calibration, already applied to ``MAG``, whose ``Ofs*`` hold its
  ``COMPASS_OFS_*``), before the first sample.

Records are built as numpy structured arrays and interleaved by time with one scatter: no
Python loop over samples.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa

from imupipe.readers.arrays import to_numpy
from imupipe.readers.dataflash.reader import GPS_EPOCH_UNIX_S
from imupipe.readers.table import flight_stream, has_flight_stream, metadata, sensor

FORMATS: dict[str, tuple[int, str, str, list[tuple[str, str]]]] = {
    "MAG": (
        130,
        "QBhhhhhh",
        "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ",
        [("TimeUS", "<u8"), ("I", "u1")]
        + [(f"{k}{a}", "<i2") for k in ("Mag", "Ofs") for a in "XYZ"],
    ),
    "ATT": (
        131,
        "QccC",
        "TimeUS,Roll,Pitch,Yaw",
        [("TimeUS", "<u8"), ("Roll", "<i2"), ("Pitch", "<i2"), ("Yaw", "<u2")],
    ),
    "GPS": (
        132,
        "QBBIHLLe",
        "TimeUS,I,Status,GMS,GWk,Lat,Lng,Alt",
        [
            ("TimeUS", "<u8"),
            ("I", "u1"),
            ("Status", "u1"),
            ("GMS", "<u4"),
            ("GWk", "<u2"),
            ("Lat", "<i4"),
            ("Lng", "<i4"),
            ("Alt", "<i4"),
        ],
    ),
    "BAT": (
        133,
        "QBf",
        "TimeUS,Inst,Curr",
        [("TimeUS", "<u8"), ("Inst", "u1"), ("Curr", "<f4")],
    ),
    "CTUN": (
        135,
        "Qff",
        "TimeUS,ThI,ThO",
        [("TimeUS", "<u8"), ("ThI", "<f4"), ("ThO", "<f4")],
    ),
    "PARM": (
        134,
        "QNf",
        "TimeUS,Name,Value",
        [("TimeUS", "<u8"), ("Name", "S16"), ("Value", "<f4")],
    ),
}
"""Message -> (type id, format characters, columns, payload dtype)."""
PARAMETERS = {
    "AHRS_TRIM_X": 0.0,
    "AHRS_TRIM_Y": 0.0,
    "AHRS_TRIM_Z": 0.0,
    "COMPASS_OFS_X": 0.0,
    "COMPASS_OFS_Y": 0.0,
    "COMPASS_OFS_Z": 0.0,
}
"""The parameters written at the start: the logged field is the raw one (no compass
correction in force, ``MAG`` ``Ofs*`` zero), the attitude untrimmed (what MagFit reads)."""
FMT_DTYPE = [
    ("type", "u1"),
    ("length", "u1"),
    ("name", "S4"),
    ("format", "S16"),
    ("columns", "S64"),
]


def _records(type_id: int, payload: np.ndarray) -> np.ndarray:
    """(n, 3 + payload size) uint8: the header bytes then each record's payload."""
    n = len(payload)
    head = np.tile(np.array([0xA3, 0x95, type_id], dtype=np.uint8), (n, 1))
    body = payload.view(np.uint8).reshape(n, payload.dtype.itemsize)
    return np.hstack([head, body])


def _quaternion_euler(q: np.ndarray) -> np.ndarray:
    """(n, 3) roll, pitch, yaw (rad) of unit quaternions (w, x, y, z) body -> NED."""
    w, x, y, z = q.T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.column_stack([roll, pitch, yaw])


def _payloads(table: pa.Table) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Message -> (t_ns, payload structured array) for what the table holds."""
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def empty(name: str, n: int, t_ns: np.ndarray) -> np.ndarray:
        rec = np.zeros(n, dtype=np.dtype(FORMATS[name][3]))
        rec["TimeUS"] = t_ns // 1000
        return rec

    t0 = int(to_numpy(table.column("t_ns")).min(initial=0))
    params = PARAMETERS | ((metadata(table).get("ardupilot") or {}).get("parameters") or {})
    rec = empty("PARM", len(params), np.full(len(params), t0))
    rec["Name"] = [k.encode() for k in params]
    rec["Value"] = list(params.values())
    out["PARM"] = (np.full(len(params), t0 - 1), rec)
    mag = sensor(table, "mag")
    rec = empty("MAG", len(mag), mag.t_ns)
    for i, a in enumerate("XYZ"):
        rec[f"Mag{a}"] = np.clip(np.rint(mag.values[:, i] * 1e7), -32768, 32767)
        rec[f"Ofs{a}"] = np.rint(params.get(f"COMPASS_OFS_{a}", 0.0))
    out["MAG"] = (mag.t_ns, rec)
    if has_flight_stream(table, "attitude"):
        att = flight_stream(table, "attitude")
        deg = np.degrees(_quaternion_euler(att.values))
        rec = empty("ATT", len(att), att.t_ns)
        rec["Roll"] = np.rint(deg[:, 0] * 100)
        rec["Pitch"] = np.rint(deg[:, 1] * 100)
        rec["Yaw"] = np.rint(np.mod(deg[:, 2], 360.0) * 100) % 36000
        out["ATT"] = (att.t_ns, rec)
    if has_flight_stream(table, "position"):
        pos = flight_stream(table, "position")
        rec = empty("GPS", len(pos), pos.t_ns)
        rec["Status"] = 3
        year = metadata(table).get("gps_year")
        if year is not None:
            unix = (float(year) - 1970.0) * 365.2425 * 86400.0
            gps_s = unix - GPS_EPOCH_UNIX_S + (pos.t_ns - pos.t_ns[0]) * 1e-9
            rec["GWk"] = gps_s // 604_800
            rec["GMS"] = np.rint((gps_s % 604_800) * 1000)
        rec["Lat"] = np.rint(pos.values[:, 0] * 1e7)
        rec["Lng"] = np.rint(pos.values[:, 1] * 1e7)
        rec["Alt"] = np.rint(pos.values[:, 2] * 100)
        out["GPS"] = (pos.t_ns, rec)
    if has_flight_stream(table, "current"):
        cur = flight_stream(table, "current")
        rec = empty("BAT", len(cur), cur.t_ns)
        rec["Curr"] = cur.values[:, 0]
        out["BAT"] = (cur.t_ns, rec)
    if has_flight_stream(table, "throttle"):
        thr = flight_stream(table, "throttle")
        rec = empty("CTUN", len(thr), thr.t_ns)
        rec["ThI"] = rec["ThO"] = thr.values[:, 0]
        out["CTUN"] = (thr.t_ns, rec)
    return out


def write_dataflash(path: Path, table: pa.Table) -> None:
    """Write ``table``'s magnetometer and flight streams to ``path`` as DataFlash."""
    fmt = np.zeros(len(FORMATS) + 1, dtype=np.dtype(FMT_DTYPE))
    fmt[0] = (128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns")
    payloads = _payloads(table)
    for i, (name, (tid, chars, cols, dtype)) in enumerate(FORMATS.items(), start=1):
        fmt[i] = (tid, 3 + np.dtype(dtype).itemsize, name.encode(), chars.encode(), cols.encode())
    head = _records(128, fmt).reshape(-1)
    blocks = [_records(FORMATS[n][0], rec) for n, (_, rec) in payloads.items()]
    times = np.concatenate([t for t, _ in payloads.values()])
    lengths = np.concatenate([np.full(len(b), b.shape[1]) for b in blocks])
    order = np.argsort(times, kind="stable")
    start = np.empty(len(order), dtype=np.int64)
    start[order] = np.concatenate([[0], np.cumsum(lengths[order])[:-1]])
    body = np.empty(int(lengths.sum()), dtype=np.uint8)
    at = 0
    for block in blocks:
        rows = start[at : at + len(block)]
        body[rows[:, None] + np.arange(block.shape[1])] = block
        at += len(block)
    Path(path).write_bytes(head.tobytes() + body.tobytes())
