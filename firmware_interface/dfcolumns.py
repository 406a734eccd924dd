"""Dataflash records as numpy columns: DFReader's own index and formats, decoded all at once.

pymavlink's ``DFReader_binary`` reads the FMT records and indexes every record of the file (with its
compiled indexer) when it opens a log; decoding one message object per record after that is what
makes a 100 MB log take minutes. :func:`columns` instead gathers every record of one type from the
memory map at DFReader's offsets and views them through a numpy dtype built from DFReader's format
(struct characters and multipliers from ``DFReader.FORMAT_TO_STRUCT``): the same values
DFReader would return, as arrays.

:func:`dataflash_series` maps an ArduPilot log with ``TimeUS`` on every mapped record onto the
MAVLink-named series of :mod:`firmware_interface.readers` (``None`` for anything else, e.g. PX4
sdlog2 logs timed by TIME records, which the per-record path handles). No IO beyond the log's map.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pymavlink import DFReader
from pymavlink.DFReader import FORMAT_TO_STRUCT

__all__ = ["columns", "dataflash_series", "open_indexed", "parsed_end"]

_NP = {"b": "i1", "B": "u1", "e": "<f2", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4", "f": "<f4", "d": "<f8",
       "q": "<i8", "Q": "<u8", "4s": "S4", "16s": "S16", "64s": "S64"}
_D2R = math.pi / 180.0
# the record types mapped onto series (all must carry TimeUS for the columnar path)
_MAPPED = ("ATT", "RATE", "IMU", "RCOU", "RCIN", "HELI", "GYR", "SIDS", "SIDD", "GPS", "XKF1", "NKF1", "POS",
           "ARM", "EV")


def open_indexed(path: str) -> Any:
    """A ``DFReader_binary`` whose time base is worked out only when asked (``ensure_clock()``):
    DFReader finds it by reading messages one by one, the whole file when it has no GPS time."""
    class _Indexed(DFReader.DFReader_binary):  # type: ignore[misc,name-defined]
        def init_clock(self) -> None:
            self.clock = None

        def ensure_clock(self) -> None:
            if self.clock is None:
                DFReader.DFReader_binary.init_clock(self)
                self._rewind(keep_messages=True)

    return _Indexed(path, zero_time_base=False)


def _complete_offsets(log: Any, mtype: int) -> np.ndarray:
    offs = np.asarray(log.offsets[mtype], dtype=np.int64)
    return offs[offs + log.formats[mtype].len <= log.data_len]


def parsed_end(log: Any) -> int:
    """Byte offset just past the last whole record of the log."""
    end = 0
    for mtype, offs in enumerate(log.offsets):
        if len(offs) and mtype in log.formats:
            ok = _complete_offsets(log, mtype)
            if ok.size:
                end = max(end, int(ok[-1]) + log.formats[mtype].len)
    return end


def columns(log: Any, name: str) -> dict[str, np.ndarray] | None:
    """Every record of type ``name`` as float columns (multipliers applied), or None when absent."""
    mtype = log.name_to_id.get(name)
    if mtype is None:
        return None
    fmt = log.formats[mtype]
    offs = _complete_offsets(log, mtype)
    if not offs.size:
        return None
    names, formats, offsets, mults = [], [], [], []
    pos = 0
    for col, ch in zip(fmt.columns, fmt.format, strict=False):
        sc, mult, _ = FORMAT_TO_STRUCT[ch]
        dt = np.dtype(_NP[sc])
        names.append(col)
        formats.append(dt)
        offsets.append(pos)
        mults.append(mult)
        pos += dt.itemsize
    body = fmt.len - 3
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": body})
    buf = np.frombuffer(log.data_map, dtype=np.uint8)
    # every byte position as the start of a body-long row (a view); one row copied per record
    raw = np.lib.stride_tricks.sliding_window_view(buf, body)[offs + 3]
    rec = raw.view(dtype).reshape(-1)
    out: dict[str, np.ndarray] = {}
    for col, dt, mult in zip(names, formats, mults, strict=True):
        if dt.kind == "S":
            continue
        v = rec[col].astype(float)
        out[col] = v * mult if mult is not None else v
    return out


def _inst0(c: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    key = "I" if "I" in c else ("C" if "C" in c else None)
    if key is None:
        return c
    sel = c[key] == 0
    return {k: v[sel] for k, v in c.items()}


def _get(c: dict[str, np.ndarray], name: str, default: float = math.nan) -> np.ndarray:
    v = c.get(name)
    return v if v is not None else np.full(len(c["TimeUS"]), default)


def dataflash_series(log: Any) -> dict[str, Any] | None:
    """``{"series": {NAME: (t_s, columns...)}, "rates": (t, p, q, r) | None, "sids": [...]}`` or None."""
    cols: dict[str, dict[str, np.ndarray]] = {}
    for name in _MAPPED:
        c = columns(log, name)
        if c is None:
            continue
        if "TimeUS" not in c:
            return None
        cols[name] = c
    if "ATT" in cols and "RollRate" in cols["ATT"]:
        return None  # PX4-style ATT with rates: the per-record path knows it
    series: dict[str, tuple[np.ndarray, list[np.ndarray]]] = {}

    def t(c: dict[str, np.ndarray]) -> np.ndarray:
        return c["TimeUS"] * 1e-6

    if "ATT" in cols:
        c = cols["ATT"]
        nan = np.full(len(c["TimeUS"]), math.nan)
        series["ATTITUDE"] = (t(c), [_get(c, "Roll", 0.0) * _D2R, _get(c, "Pitch", 0.0) * _D2R,
                                     _get(c, "Yaw", 0.0) * _D2R, nan, nan.copy(), nan.copy()])
    rates = None
    if "RATE" in cols:
        c = cols["RATE"]
        rates = (t(c), _get(c, "R", 0.0) * _D2R, _get(c, "P", 0.0) * _D2R, _get(c, "Y", 0.0) * _D2R)
    if "IMU" in cols and "GyrX" in cols["IMU"]:
        c = _inst0(cols["IMU"])
        series["IMU"] = (t(c), [c["AccX"], c["AccY"], c["AccZ"], c["GyrX"], c["GyrY"], c["GyrZ"]])
        if rates is None:
            rates = (t(c), c["GyrX"], c["GyrY"], c["GyrZ"])
    for src, dst, n in (("RCOU", "SERVO_OUTPUT_RAW", 16), ("RCIN", "RC_CHANNELS", 18)):
        if src in cols:
            c = cols[src]
            series[dst] = (t(c), [_get(c, f"C{k}", 0.0) for k in range(1, n + 1)])
    if "HELI" in cols:
        c = cols["HELI"]
        series["ROTOR"] = (t(c), [_get(c, "ERRPM"), _get(c, "DRRPM")])
    if "GYR" in cols:
        c = _inst0(cols["GYR"])
        series["GYRO_FAST"] = (t(c), [c["GyrX"], c["GyrY"], c["GyrZ"]])
    if "SIDD" in cols:
        c = cols["SIDD"]
        series["SYSID"] = (t(c), [_get(c, "Time"), _get(c, "Targ"), _get(c, "F")])
    if "GPS" in cols and "Lng" in cols["GPS"]:
        c = _inst0(cols["GPS"])
        series["GPS_RAW_INT"] = (t(c), [_get(c, "Status", 0.0), c["Lat"], c["Lng"], _get(c, "Alt"), _get(c, "Spd"),
                                        _get(c, "NSats", 0.0)])
    ekf = cols.get("XKF1", cols.get("NKF1"))
    if ekf is not None:
        c = _inst0(ekf)
        series["LOCAL_POSITION_NED"] = (t(c), [_get(c, k) for k in ("PN", "PE", "PD", "VN", "VE", "VD")])
    if "POS" in cols:
        c = cols["POS"]
        rel = c.get("RelHomeAlt", c.get("RelOriginAlt", np.full(len(c["TimeUS"]), math.nan)))
        nan = np.full(len(rel), math.nan)
        series["GLOBAL_POSITION_INT"] = (t(c), [c["Lat"], c["Lng"], _get(c, "Alt"), rel, nan, nan, nan])
    arm_t, arm_v = [], []
    if "ARM" in cols:
        arm_t.append(t(cols["ARM"]))
        arm_v.append((_get(cols["ARM"], "ArmState", 0.0) != 0).astype(float))
    if "EV" in cols:
        c = cols["EV"]
        sel = np.isin(_get(c, "Id", 0.0), (10, 11))
        arm_t.append(t(c)[sel])
        arm_v.append((c["Id"][sel] == 10).astype(float))
    if arm_t:
        tt, vv = np.concatenate(arm_t), np.concatenate(arm_v)
        z = np.zeros_like(vv)
        series["HEARTBEAT"] = (tt, [vv, z, z.copy(), z.copy()])
    sids = []
    if "SIDS" in cols:
        c = cols["SIDS"]
        keys = ("Ax", "Mag", "FSt", "FSp", "TFin", "TC", "TR", "TFout")
        arr = np.stack([t(c)] + [_get(c, k, 0.0) for k in keys], axis=1)
        sids = [tuple(float(x) for x in row) for row in arr]
    return {"series": series, "rates": rates, "sids": sids}
