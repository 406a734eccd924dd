"""Log readers: .tlog, ArduPilot dataflash .bin, PX4 .px4log and PX4 .ulg into one :class:`LogData`.

:func:`load_log` picks the reader by content (a dataflash FMT header, the ULog magic (read by
:mod:`firmware_interface.ulog` through pyulog), else .tlog records). The .tlog
path scans records tolerantly (:mod:`firmware_interface.tlogread`) and decodes them through the same
:class:`~firmware_interface.session.MavlinkSession` as the live link (passive: nothing is sent), so
units, clock unwrapping and reboot handling are identical offline and live. Dataflash logs go
through pymavlink's ``DFReader`` and are mapped onto the same MAVLink-named series (pilot inputs:
ArduPilot RCIN and PX4 sdlog2 RC as RC_CHANNELS; PX4's normalised -1..1 sticks as ``1500 + 500 v`` us).

Messages without an FC time field (HEARTBEAT, SYS_STATUS, EXTENDED_SYS_STATE) get ``t_fc_s`` from
the lower envelope of ``host - fc`` over the timed messages, interpolated at their host time.

``LogData.flights``: armed intervals of the FC's HEARTBEAT (dataflash: ARM / EV arming events);
without any arming information the whole log is one flight. In-air time from EXTENDED_SYS_STATE
``landed_state`` (2 in air, 3 taking off, 4 landing), else height > ``in_air_height_m`` above the
height at the start of the armed interval (LOCAL_POSITION_NED z, else GLOBAL_POSITION_INT
relative_alt); NaN when neither exists.

Leaves to others: resampling, trims and smoothing (``groundstation.dsp``).
"""

from __future__ import annotations

import contextlib
import gzip
import io
import lzma
import math
import os
import shutil
import tempfile
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from firmware_interface.errors import LogError
from firmware_interface.flights import _finish, find_flights  # noqa: F401 - find_flights: part of this module's API
from firmware_interface.samples import (
    SERIES_FIELDS,
    SYSID_AXES,
    Attitude,
    ChirpSegment,
    ExtendedSysState,
    FlightInterval,
    GlobalPositionInt,
    GpsRawInt,
    Heartbeat,
    Imu,
    LinkStats,
    LocalPositionNed,
    LogData,
    RcChannels,
    Series,
    ServoOutputRaw,
    SysStatus,
)
from firmware_interface.session import MavlinkSession, SessionConfig
from firmware_interface.tlogread import TlogScan, scan_tlog
from firmware_interface.ulog import ULOG_MAGIC, load_ulog

__all__ = ["build_logdata", "chirp_segments", "find_flights", "load_dataflash", "load_log", "load_tlog_bytes",
           "restrict_to_chirps"]

_UNTIMED = ("HEARTBEAT", "SYS_STATUS", "EXTENDED_SYS_STATE")
_DF_MAGIC = b"\xa3\x95\x80"  # dataflash FMT record header
_MAV_AUTOPILOT_INVALID = 8
_MAV_TYPE_GCS = 6


def load_log(path: str | os.PathLike[str], *, all_topics: bool = False) -> LogData:
    """Read a .tlog, dataflash .bin, PX4 .px4log or PX4 .ulg, or any of them xz- or gzip-compressed, into
    :class:`LogData` (raises LogError).

    ``all_topics``: a ULog's unmapped topics are decoded and counted too (the other formats always are).
    """
    p = Path(path)
    try:
        with p.open("rb") as fh:
            head = fh.read(16)  # the content decides the reader; only a .tlog is read here whole
    except FileNotFoundError:
        raise LogError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise LogError(f"{p}: is a directory, not a log file") from None
    except OSError as exc:
        raise LogError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if not head:
        raise LogError(f"{p}: empty file")
    if head.startswith(_XZ_MAGIC) or head.startswith(_GZ_MAGIC):
        return _load_compressed(p, head, all_topics)
    if head[:3] == _DF_MAGIC:
        return load_dataflash(p)
    if head[:7] == ULOG_MAGIC:
        return load_ulog(p, all_topics=all_topics)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise LogError(f"{p}: cannot read ({exc.strerror or exc})") from None
    return load_tlog_bytes(data, str(p))


_XZ_MAGIC = b"\xfd7zXZ\x00"
_GZ_MAGIC = b"\x1f\x8b"


def _load_compressed(p: Path, head: bytes, all_topics: bool) -> LogData:
    """An xz- or gzip-compressed log (as archives keep them): decompressed to a temporary file, read by
    the reader its content asks for, and named after the compressed file."""
    opener: Any = lzma.open if head.startswith(_XZ_MAGIC) else gzip.open
    with tempfile.TemporaryDirectory(prefix="gs-log-") as td:
        inner = Path(td) / (p.stem if p.suffix in (".xz", ".gz") else p.name)
        try:
            with opener(p, "rb") as src, inner.open("wb") as dst:
                shutil.copyfileobj(src, dst, 1 << 20)
        except (OSError, EOFError, lzma.LZMAError) as exc:
            raise LogError(f"{p}: cannot decompress ({exc})") from None
        if inner.stat().st_size == 0:
            raise LogError(f"{p}: empty file once decompressed")
        log = load_log(inner, all_topics=all_topics)
    return replace(log, source=str(p))


def load_tlog_bytes(data: bytes, source: str = "<bytes>") -> LogData:
    """Decode .tlog content (tolerant) into LogData; raises LogError if no record is valid."""
    scan = TlogScan()
    session = MavlinkSession(SessionConfig(request_streams=False, send_heartbeat=False,
                                           emit_raw_packets=False, link_timeout_s=math.inf))
    events: list[Any] = []
    recv = session.receive_packet
    pull = session.events
    ext = events.extend
    for t_host_s, pkt in scan_tlog(data, scan):
        recv(pkt, t_host_s)
        ext(pull())
    if scan.records == 0:
        raise LogError(f"{source}: not a MAVLink telemetry log (no valid .tlog record in {len(data)} bytes)")
    stats = session.stats
    stats.corrupt_bytes = scan.corrupt_bytes
    stats.truncated_tail_bytes = scan.truncated_tail_bytes
    return build_logdata(events, source, stats, dict(session.message_counts))


# ---------------------------------------------------------------------- events -> columns


_EXTRACT: dict[type, tuple[str, Any]] = {
    Attitude: ("ATTITUDE", lambda e: (e.t_fc_s, e.t_host_s, e.roll_rad, e.pitch_rad, e.yaw_rad, e.p_rad_s,
                                      e.q_rad_s, e.r_rad_s)),
    ServoOutputRaw: ("SERVO_OUTPUT_RAW", lambda e: (e.t_fc_s, e.t_host_s, *e.pwm_us)),
    LocalPositionNed: ("LOCAL_POSITION_NED", lambda e: (e.t_fc_s, e.t_host_s, e.x_m, e.y_m, e.z_m, e.vx_m_s,
                                                        e.vy_m_s, e.vz_m_s)),
    Heartbeat: ("HEARTBEAT", lambda e: (e.t_fc_s, e.t_host_s, float(e.armed), e.base_mode, e.custom_mode,
                                        e.mav_type)),
    GlobalPositionInt: ("GLOBAL_POSITION_INT", lambda e: (e.t_fc_s, e.t_host_s, e.lat_deg, e.lon_deg, e.alt_m,
                                                          e.relative_alt_m, e.vx_m_s, e.vy_m_s, e.vz_m_s)),
    Imu: ("IMU", lambda e: (e.t_fc_s, e.t_host_s, *e.acc_m_s2, *e.gyro_rad_s)),
    GpsRawInt: ("GPS_RAW_INT", lambda e: (e.t_fc_s, e.t_host_s, e.fix_type, e.lat_deg, e.lon_deg, e.alt_m,
                                          e.ground_speed_m_s, e.satellites)),
    ExtendedSysState: ("EXTENDED_SYS_STATE", lambda e: (e.t_fc_s, e.t_host_s, e.landed_state)),
    SysStatus: ("SYS_STATUS", lambda e: (e.t_fc_s, e.t_host_s, e.voltage_v, e.current_a, e.drop_rate_comm_pct)),
    RcChannels: ("RC_CHANNELS", lambda e: (e.t_fc_s, e.t_host_s, *e.pwm_us)),
}
_IMU_PRIORITY = ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3")


def build_logdata(events: Iterable[Any], source: str, stats: LinkStats | None = None,
                  message_counts: dict[str, int] | None = None) -> LogData:
    """Stack typed sample events (from a session) into a :class:`LogData`.

    Only the flight controller's samples are kept: the sysid of the first autopilot HEARTBEAT (all
    sysids when there is none). SERVO_OUTPUT_RAW port 0 only; IMU from the first present of
    RAW_IMU, SCALED_IMU, SCALED_IMU2, SCALED_IMU3.
    """
    by_type: dict[type, list[Any]] = {t: [] for t in _EXTRACT}
    for ev in events:
        lst = by_type.get(type(ev))
        if lst is not None:
            lst.append(ev)
    hbs = [e for e in by_type[Heartbeat] if e.autopilot != _MAV_AUTOPILOT_INVALID and e.mav_type != _MAV_TYPE_GCS]
    by_type[Heartbeat] = hbs
    fc_sysid = hbs[0].sysid if hbs else None
    if fc_sysid is not None:
        for t, lst in by_type.items():
            if any(e.sysid != fc_sysid for e in lst):
                by_type[t] = [e for e in lst if e.sysid == fc_sysid]
    by_type[ServoOutputRaw] = [e for e in by_type[ServoOutputRaw] if e.port == 0]
    imu = by_type[Imu]
    if imu:
        present = {e.source for e in imu}
        first = next((s for s in _IMU_PRIORITY if s in present), sorted(present)[0])
        by_type[Imu] = [e for e in imu if e.source == first]
    series: dict[str, Series] = {}
    for t, (name, fn) in _EXTRACT.items():
        lst = by_type[t]
        if not lst:
            continue
        fields = SERIES_FIELDS[name]
        arr = np.asarray([fn(e) for e in lst], dtype=float).reshape(-1, 2 + len(fields))
        series[name] = Series(arr[:, 0].copy(), arr[:, 1].copy(),
                              {f: arr[:, 2 + k].copy() for k, f in enumerate(fields)})
    series = _fix_untimed(series)
    return _finish(source, series, dict(message_counts or {}), stats or LinkStats())


def _fix_untimed(series: dict[str, Series], untimed: tuple[str, ...] = _UNTIMED) -> dict[str, Series]:
    """Give messages without an FC time field a t_fc_s from the timed messages around them.

    All messages of a log came down one byte stream in the order they were sent, so a message
    without a time field was sent between the timed messages received just before and just
    after it: its FC time is interpolated between theirs on the host clock (timed messages
    received in one read share a host time; the latest FC time of each arrival is used).
    Transport latency cancels, and a link replayed N times faster than real time (FC seconds
    per host second = N) is followed as well as a real one. Before the first / after the last
    timed message the host clock runs on from it at one FC second per host second.
    """
    th, tf = [], []
    for name, s in series.items():
        if name not in untimed and len(s):
            ok = np.isfinite(s.t_fc_s) & np.isfinite(s.t_host_s)
            th.append(s.t_host_s[ok])
            tf.append(s.t_fc_s[ok])
    h = np.concatenate(th) if th else np.zeros(0)
    out = dict(series)
    if h.size == 0:
        base = min((float(s.t_host_s[0]) for s in series.values() if len(s)), default=0.0)
        for name in untimed:
            u = series.get(name)
            if u is not None and len(u):
                out[name] = Series(u.t_host_s - base, u.t_host_s, u.columns)
        return out
    f = np.concatenate(tf)
    order = np.lexsort((f, h))
    h, f = h[order], f[order]
    last = np.r_[h[1:] != h[:-1], True]  # the latest FC time of each arrival
    h, f = h[last], np.maximum.accumulate(f[last])
    for name in untimed:
        u = series.get(name)
        if u is None or not len(u):
            continue
        x = u.t_host_s
        t_fc = np.interp(x, h, f)
        t_fc = np.where(x < h[0], f[0] - (h[0] - x), t_fc)
        t_fc = np.where(x > h[-1], f[-1] + (x - h[-1]), t_fc)
        out[name] = Series(t_fc, u.t_host_s, u.columns)
    return out


# ---------------------------------------------------------------------- dataflash (.bin, .px4log)


def load_dataflash(path: str | os.PathLike[str]) -> LogData:
    """ArduPilot .bin / PX4 sdlog2 .px4log through pymavlink's DFReader, mapped to MAVLink series.

    DFReader indexes the file and reads its formats; an ArduPilot log (TimeUS on every record) is
    then decoded a whole record type at a time (:mod:`firmware_interface.dfcolumns`), anything else
    one DFReader message at a time."""
    # here, not at the top: DFReader brings pymavlink's mavutil and its MAVLink 1 dialect (about 0.03 s
    # of CPU at every start), which only dataflash logs need
    from firmware_interface.dfcolumns import dataflash_series, open_indexed, parsed_end

    p = Path(path)
    noise = io.StringIO()  # DFReader prints damaged records to stdout; keep stdout clean (JSON)
    try:
        with contextlib.redirect_stdout(noise):
            log = open_indexed(str(p))
    except Exception as exc:  # DFReader raises bare exceptions on malformed files
        raise LogError(f"{p}: not a readable dataflash log ({type(exc).__name__}: {exc})") from None
    with contextlib.redirect_stdout(noise):
        fast = dataflash_series(log)
    if fast is not None:  # ArduPilot log: every record of a type at once
        series = {name: Series(tt, tt.copy(), dict(zip(SERIES_FIELDS[name], vals, strict=True)))
                  for name, (tt, vals) in fast["series"].items() if len(tt)}
        counts = {log.id_to_name.get(k, str(k)) if k != 0x80 else "FMT": len(o)
                  for k, o in enumerate(log.offsets) if len(o)}
        rates = fast["rates"]
        sids = fast["sids"]
        tail = max(0, int(log.data_len) - parsed_end(log))
        px4 = False
    else:
        series, counts, rates, sids, px4 = _read_df_records(log, noise)
        tail = _dataflash_tail_bytes(log)
    if "ATTITUDE" in series and not px4 and rates is not None and len(rates[0]):
        att = series["ATTITUDE"]
        for k, c in enumerate(("p_rad_s", "q_rad_s", "r_rad_s")):
            att.columns[c][:] = np.interp(att.t_fc_s, rates[0], rates[k + 1])
    if not series:
        raise LogError(f"{p}: dataflash log holds none of ATT, RCOU, IMU, GPS, XKF1/NKF1, POS, OUT0, LPOS")
    stats = LinkStats(packets=sum(counts.values()))
    stats.truncated_tail_bytes = tail
    out = _finish(str(p), series, counts, stats)
    if tail:
        out.notes.append(f"{p}: the log ends inside a record (last {tail} bytes not a whole record); "
                         "everything before it was read")
    if "HEARTBEAT" not in series:
        out.notes.append(f"{p}: no arming events (ARM, EV or STAT): the whole log is taken as one flight")
    out.chirps.extend(chirp_segments(sids, series.get("SYSID")))
    return out


def _read_df_records(log: Any, noise: io.StringIO) -> tuple[dict[str, Series], dict[str, int], Any, list, bool]:
    """The per-record path (PX4 sdlog2 logs timed by TIME records): one DFReader message at a time."""
    with contextlib.redirect_stdout(noise):
        log.ensure_clock()
    cols: dict[str, list[tuple[float, ...]]] = {}
    tms: dict[str, list[tuple[float, float]]] = {}
    counts: dict[str, int] = {}
    gyro: list[tuple[float, float, float, float]] = []
    rate: list[tuple[float, float, float, float]] = []
    sids: list[tuple[float, ...]] = []

    def add(name: str, t_fc: float, t_host: float, vals: tuple[float, ...]) -> None:
        if name not in cols:
            cols[name], tms[name] = [], []
        cols[name].append(vals)
        tms[name].append((t_fc, t_host))

    with contextlib.redirect_stdout(noise):
        _read_df(log, add, counts, gyro, rate, sids)
    px4 = "_PX4" in counts
    counts.pop("_PX4", None)
    counts.pop("_DFREADER_ERROR", None)  # the import stopped at a damaged record: keep what came before
    series: dict[str, Series] = {}
    for name, rows in cols.items():
        vals = np.asarray(rows, dtype=float)
        tt = np.asarray(tms[name], dtype=float)
        series[name] = Series(tt[:, 0], tt[:, 1], {f: vals[:, k] for k, f in enumerate(SERIES_FIELDS[name])})
    src = rate or gyro
    rates = tuple(np.asarray(src, dtype=float).T) if src else None
    return series, counts, rates, sids, px4


def _dataflash_tail_bytes(log: Any) -> int:
    """Bytes at the end of the file DFReader could not read as a whole record (0 when it ended cleanly)."""
    data_len = int(getattr(log, "data_len", 0) or 0)
    offset = int(getattr(log, "offset", data_len) or 0)
    if offset >= data_len:
        return 0
    left = data_len - offset
    try:  # a record cut short: DFReader consumed its 3-byte header before finding the body missing
        head = bytes(log.data_map[offset - 3:offset - 1]) if offset >= 3 else b""
    except (AttributeError, ValueError):
        head = b""
    return left + 3 if head == _DF_MAGIC[:2] else left


def chirp_segments(sids: list[tuple[float, ...]], sidd: Series | None, *, gap_s: float = 0.5) -> list[ChirpSegment]:
    """The SYSID chirps: each SIDS record (t, axis, magnitude, f_start, f_stop, t_fade_in, t_const,
    t_record, t_fade_out) starts one; it spans the SIDD data that follow it without a gap longer than
    ``gap_s`` (else the settings' own length t_const + t_record + t_fade_out)."""
    out: list[ChirpSegment] = []
    t_d = sidd.t_fc_s if sidd is not None and len(sidd) else np.zeros(0)
    for k, (t0, axis, mag, f0, f1, _fin, tc, tr, tfout) in enumerate(sids):
        end = t0 + tc + tr + tfout
        nxt = sids[k + 1][0] if k + 1 < len(sids) else math.inf
        sel = t_d[(t_d >= t0 - gap_s) & (t_d < nxt)]
        if sel.size >= 2:
            brk = np.flatnonzero(np.diff(sel) > gap_s)
            start, end = float(sel[0]), float(sel[brk[0]] if brk.size else sel[-1])
        else:
            start = t0
        out.append(ChirpSegment(k, int(axis), SYSID_AXES.get(int(axis), f"axis_{int(axis)}"), float(mag),
                                float(f0), float(f1), float(start), float(end)))
    return out


def restrict_to_chirps(log: LogData) -> LogData:
    """The same log with its flights replaced by its SYSID chirps (each one flight, all in the air), so
    identification and validation use just those segments; LogError when the log has none."""
    if not log.chirps:
        raise LogError(f"{log.source}: no SYSID chirp in the log (no SIDS record): nothing for --segments sysid")
    flights = [FlightInterval(c.index, c.start_fc_s, c.end_fc_s, c.duration_s, ((c.start_fc_s, c.end_fc_s),))
               for c in log.chirps]
    return replace(log, flights=flights)


def _px4_rc_us(v: Any) -> float:
    """PX4 sdlog2 RC value (normalised -1..1) as RC_CHANNELS microseconds, 1500 + 500 v (NaN if absent)."""
    return math.nan if v is None else 1500.0 + 500.0 * float(v)


def _read_df(log: Any, add: Any, counts: dict[str, int], gyro: list, rate: list, sids: list) -> None:
    """Walk a DFReader log, mapping records onto MAVLink-named series through ``add``."""
    t0: float | None = None
    px4_time_s: float | None = None
    d2r = math.pi / 180.0
    while True:
        try:
            m = log.recv_msg()
        except Exception as exc:  # a damaged record ends the import, as a truncated tlog does
            counts["_DFREADER_ERROR"] = counts.get("_DFREADER_ERROR", 0) + 1
            del exc
            break
        if m is None:
            break
        typ = m.get_type()
        counts[typ] = counts.get(typ, 0) + 1
        t_host = float(getattr(m, "_timestamp", 0.0) or 0.0)
        if typ == "TIME" and getattr(m, "StartTime", None) is not None:
            px4_time_s = m.StartTime * 1e-6  # PX4 sdlog2: FC time of the records that follow
        tus = getattr(m, "TimeUS", None)
        if tus is None:
            tms_ = getattr(m, "TimeMS", None)
            if tms_ is not None:
                t_fc = tms_ * 1e-3
            elif px4_time_s is not None:
                t_fc = px4_time_s
            else:
                if t0 is None:
                    t0 = t_host
                t_fc = t_host - t0
        else:
            t_fc = tus * 1e-6
        def g(name: str, default: Any = None, _m: Any = m) -> Any:
            v = getattr(_m, name, default)
            return default if v is None else v

        inst = g("I", g("C", 0)) or 0
        if typ == "ATT":
            if g("RollRate") is not None:  # PX4 sdlog2: radians
                counts["_PX4"] = 1
                add("ATTITUDE", t_fc, t_host, (g("Roll"), g("Pitch"), g("Yaw"), g("RollRate"), g("PitchRate"),
                                               g("YawRate")))
            else:
                add("ATTITUDE", t_fc, t_host, (g("Roll", 0.0) * d2r, g("Pitch", 0.0) * d2r, g("Yaw", 0.0) * d2r,
                                               math.nan, math.nan, math.nan))
        elif typ == "RATE":
            rate.append((t_fc, g("R", 0.0) * d2r, g("P", 0.0) * d2r, g("Y", 0.0) * d2r))
        elif typ == "IMU" and inst == 0:
            if g("GyrX") is not None:
                gyro.append((t_fc, g("GyrX"), g("GyrY"), g("GyrZ")))
                add("IMU", t_fc, t_host, (g("AccX"), g("AccY"), g("AccZ"), g("GyrX"), g("GyrY"), g("GyrZ")))
            elif g("GyroX") is not None:  # PX4
                add("IMU", t_fc, t_host, (g("AccX"), g("AccY"), g("AccZ"), g("GyroX"), g("GyroY"), g("GyroZ")))
        elif typ == "RCIN":
            add("RC_CHANNELS", t_fc, t_host, tuple(float(g(f"C{k}", 0) or 0) for k in range(1, 19)))
        elif typ == "HELI":
            add("ROTOR", t_fc, t_host, (g("ERRPM", math.nan), g("DRRPM", math.nan)))
        elif typ == "GYR" and inst == 0:
            add("GYRO_FAST", t_fc, t_host, (g("GyrX"), g("GyrY"), g("GyrZ")))
        elif typ == "SIDS":
            sids.append((t_fc, g("Ax", 0), g("Mag", 0.0), g("FSt", 0.0), g("FSp", 0.0), g("TFin", 0.0), g("TC", 0.0),
                         g("TR", 0.0), g("TFout", 0.0)))
        elif typ == "SIDD":
            add("SYSID", t_fc, t_host, (g("Time", math.nan), g("Targ", math.nan), g("F", math.nan)))
        elif typ == "RCOU":
            add("SERVO_OUTPUT_RAW", t_fc, t_host, tuple(float(g(f"C{k}", 0) or 0) for k in range(1, 17)))
        elif typ == "RC" and g("C0") is not None:  # PX4 sdlog2 pilot sticks, normalised -1..1
            add("RC_CHANNELS", t_fc, t_host, tuple(_px4_rc_us(g(f"C{k}")) for k in range(18)))
        elif typ == "OUT0":
            add("SERVO_OUTPUT_RAW", t_fc, t_host, tuple(float(g(f"Out{k}", 0) or 0) for k in range(16)))
        elif typ == "GPS" and inst == 0:
            if g("Lng") is not None:
                add("GPS_RAW_INT", t_fc, t_host, (g("Status", 0), g("Lat"), g("Lng"), g("Alt"), g("Spd", math.nan),
                                                  g("NSats", 0)))
            elif g("Lon") is not None:  # PX4
                vn, ve = g("VelN", math.nan), g("VelE", math.nan)
                add("GPS_RAW_INT", t_fc, t_host, (g("Fix", 0), g("Lat"), g("Lon"), g("Alt"), math.hypot(vn, ve),
                                                  g("nSat", 0)))
        elif typ in ("XKF1", "NKF1") and inst == 0:
            add("LOCAL_POSITION_NED", t_fc, t_host, (g("PN", math.nan), g("PE", math.nan), g("PD", math.nan),
                                                     g("VN", math.nan), g("VE", math.nan), g("VD", math.nan)))
        elif typ == "LPOS":  # PX4
            add("LOCAL_POSITION_NED", t_fc, t_host, (g("X"), g("Y"), g("Z"), g("VX"), g("VY"), g("VZ")))
        elif typ == "POS":
            rel = g("RelHomeAlt", g("RelOriginAlt", math.nan))
            add("GLOBAL_POSITION_INT", t_fc, t_host, (g("Lat"), g("Lng"), g("Alt"), rel, math.nan, math.nan,
                                                      math.nan))
        elif typ == "ARM":
            add("HEARTBEAT", t_fc, t_host, (float(bool(g("ArmState", 0))), 0, 0, 0))
        elif typ == "EV" and g("Id") in (10, 11):
            add("HEARTBEAT", t_fc, t_host, (1.0 if g("Id") == 10 else 0.0, 0, 0, 0))
        elif typ == "STAT" and g("ArmS") is not None:  # PX4 sdlog2 arming_state: 2 armed, 3 armed error
            add("HEARTBEAT", t_fc, t_host, (1.0 if g("ArmS") in (2, 3) else 0.0, 0, 0, 0))
