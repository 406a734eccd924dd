"""PX4 ULog (``.ulg``) import through pyulog, mapped onto the same MAVLink-named series as every reader.

pyulog (the PX4 project's own parser) reads the file; this module only maps its topics (uORB
messages, ``timestamp`` in µs since FC boot) onto :class:`~firmware_interface.samples.LogData`:

=====================  ===================================================================
series                 ULog topics (first present wins)
=====================  ===================================================================
ATTITUDE               ``vehicle_attitude`` quaternion ``q[0..3]`` (w x y z) -> roll/pitch/yaw;
                       body rates from ``vehicle_angular_velocity`` ``xyz[0..2]`` (interpolated
                       to the attitude times), else the older ``rollspeed/pitchspeed/yawspeed``
SERVO_OUTPUT_RAW       ``actuator_outputs`` (instance 0) ``output[k]`` in µs, else
                       ``actuator_servos`` ``control[k]`` (-1..1) as 1500 + 500·control µs
RC_CHANNELS            ``input_rc`` ``values[k]`` in µs, else ``manual_control_setpoint``
                       roll, pitch, throttle, yaw as channels 1-4 (1500 + 500·stick µs;
                       throttle 0..1 as 1000 + 1000·throttle)
LOCAL_POSITION_NED     ``vehicle_local_position`` x y z vx vy vz
IMU                    ``sensor_combined`` ``accelerometer_m_s2[k]``, ``gyro_rad[k]``
GPS_RAW_INT            ``vehicle_gps_position`` else ``sensor_gps``: fix, position, speed, satellites
HEARTBEAT              ``vehicle_status`` ``arming_state`` (2 = armed): flights
EXTENDED_SYS_STATE     ``vehicle_land_detected`` ``landed`` (1 on ground, else 2 in air): in-air time
=====================  ===================================================================

pyulog decodes only these topics unless ``all_topics`` is asked for (``log-info``): the rest of a
PX4 log is skipped. The logger's own dropout records become ``LogData.dropouts_s`` and one note.

The aircraft's channel map then picks the channels out of SERVO_OUTPUT_RAW or RC_CHANNELS, as
for any other log. ``message_counts`` holds pyulog's own per-topic counts (``topic`` for multi
instance 0, ``topic/N`` for instance N). A log whose ``vehicle_status`` never shows the vehicle
armed (a bench log) is one flight over its whole span, and says so in ``LogData.notes``; a
missing optional topic is one note naming the file and the topic; a ULog without
``vehicle_attitude`` raises :class:`~firmware_interface.errors.LogError` naming the file and topic.

The host time of a sample (``t_host_s``) is its FC time: a ULog has no ground-station clock.
Leaves to others: resampling and trims (``groundstation.dsp``).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
from pathlib import Path

import numpy as np

from firmware_interface.errors import LogError
from firmware_interface.flights import _finish
from firmware_interface.samples import SERIES_FIELDS, LinkStats, LogData, Series

__all__ = ["ULOG_MAGIC", "ULOG_TOPICS", "load_ulog"]

ULOG_MAGIC = b"ULog\x01\x12\x35"

#: The topics this reader maps (anything else is only counted).
ULOG_TOPICS = ("vehicle_attitude", "vehicle_angular_velocity", "actuator_outputs", "actuator_servos",
               "input_rc", "manual_control_setpoint", "vehicle_local_position", "sensor_combined",
               "vehicle_status", "vehicle_land_detected", "vehicle_gps_position", "sensor_gps")

_ARMED = 2  # vehicle_status.arming_state ARMING_STATE_ARMED (every PX4 version)


def load_ulog(path: str | os.PathLike[str], *, all_topics: bool = False) -> LogData:
    """Read a PX4 .ulg through pyulog into :class:`LogData` (raises LogError naming the file).

    By default pyulog decodes only :data:`ULOG_TOPICS` (what every command maps; the other topics'
    records are skipped unread, which is most of a PX4 log), so ``message_counts`` holds those;
    ``all_topics`` decodes every topic and counts them all (``log-info``).
    """
    from pyulog import ULog

    p = Path(path)
    noise = io.StringIO()  # pyulog prints damaged-message notices to stdout; keep stdout clean
    try:
        with contextlib.redirect_stdout(noise):
            ulog = ULog(str(p), None if all_topics else list(ULOG_TOPICS), True)
    except Exception as exc:  # pyulog raises bare exceptions on malformed files
        raise LogError(f"{p}: not a readable ULog ({type(exc).__name__}: {exc})") from None
    topics: dict[str, dict[str, np.ndarray]] = {}
    counts: dict[str, int] = {}
    for d in ulog.data_list:
        counts[d.name if d.multi_id == 0 else f"{d.name}/{d.multi_id}"] = len(d.data["timestamp"])
        if d.multi_id == 0 and d.name in ULOG_TOPICS and len(d.data["timestamp"]):
            topics[d.name] = d.data
    if "vehicle_attitude" not in topics:
        seen = ", ".join(sorted(counts)) or "none"
        raise LogError(f"{p}: ULog has no vehicle_attitude topic (attitude and body rates); "
                       f"{'topics' if all_topics else 'mapped topics present'}: {seen}")
    notes: list[str] = []
    series = {name: s for name, s in _map_topics(topics, p, notes).items() if len(s)}

    stats = LinkStats(packets=sum(counts.values()))
    log = _finish(str(p), series, counts, stats)
    log.notes.extend(notes)
    log.dropouts_s.extend(_dropouts(ulog))
    if log.dropouts_s:
        lost = sum(d for _, d in log.dropouts_s)
        t0, d0 = max(log.dropouts_s, key=lambda x: x[1])
        log.notes.append(f"{p}: the FC's logger lost data {len(log.dropouts_s)} times, {lost * 1e3:.0f} ms in "
                         f"all (longest {d0 * 1e3:.0f} ms at {t0:.1f} s)")
    if ulog.file_corruption:
        log.notes.append(f"{p}: pyulog found damaged records and skipped them")
    return log


def _dropouts(ulog: object) -> list[tuple[float, float]]:
    """(start s, duration s) of each ULog dropout record of positive duration (FC clock)."""
    return [(float(d.timestamp) * 1e-6, float(d.duration) * 1e-3)
            for d in getattr(ulog, "dropouts", ()) if d.duration > 0]


def _t(d: dict[str, np.ndarray]) -> np.ndarray:
    return np.asarray(d["timestamp"], dtype=float) * 1e-6


def _cols(d: dict[str, np.ndarray], fmt: str, n: int) -> list[np.ndarray] | None:
    """Columns ``fmt.format(k)`` for k < n, or None when the first is absent."""
    if fmt.format(0) not in d:
        return None
    nan = np.full(len(d["timestamp"]), math.nan)
    return [np.asarray(d[fmt.format(k)], dtype=float) if fmt.format(k) in d else nan for k in range(n)]


def _series(name: str, t: np.ndarray, cols: list[np.ndarray]) -> Series:
    fields = SERIES_FIELDS[name]
    return Series(t, t.copy(), {f: np.asarray(c, dtype=float) for f, c in zip(fields, cols, strict=True)})


def _map_topics(topics: dict[str, dict[str, np.ndarray]], p: Path, notes: list[str]) -> dict[str, Series]:
    out: dict[str, Series] = {"ATTITUDE": _attitude(topics, p, notes)}
    servo = _servo(topics)
    if servo is not None:
        out["SERVO_OUTPUT_RAW"] = servo
    else:
        notes.append(f"{p}: ULog has no actuator_outputs or actuator_servos topic (servo inputs)")
    rc = _rc(topics)
    if rc is not None:
        out["RC_CHANNELS"] = rc
    lp = topics.get("vehicle_local_position")
    if lp is not None:
        out["LOCAL_POSITION_NED"] = _series("LOCAL_POSITION_NED", _t(lp), [lp[k] for k in ("x", "y", "z", "vx",
                                                                                          "vy", "vz")])
    else:
        notes.append(f"{p}: ULog has no vehicle_local_position topic (velocities and height)")
    sc = topics.get("sensor_combined")
    if sc is not None:
        acc = _cols(sc, "accelerometer_m_s2[{}]", 3)
        gyr = _cols(sc, "gyro_rad[{}]", 3)
        if acc is not None and gyr is not None:
            out["IMU"] = _series("IMU", _t(sc), [*acc, *gyr])
    else:
        notes.append(f"{p}: ULog has no sensor_combined topic (IMU accelerations and gyros)")
    vs = topics.get("vehicle_status")
    if vs is not None and "arming_state" in vs and np.any(vs["arming_state"] == _ARMED):
        armed = (np.asarray(vs["arming_state"]) == _ARMED).astype(float)
        z = np.zeros_like(armed)
        out["HEARTBEAT"] = _series("HEARTBEAT", _t(vs), [armed, z, np.asarray(vs.get("nav_state", z), float), z])
    else:
        what = "no vehicle_status topic" if vs is None else "vehicle_status never shows the vehicle armed"
        notes.append(f"{p}: {what}: the whole log is taken as one flight")
    gps = _gps(topics)
    if gps is not None:
        out["GPS_RAW_INT"] = gps
    else:
        notes.append(f"{p}: ULog has no vehicle_gps_position or sensor_gps topic (GPS)")
    ld = topics.get("vehicle_land_detected")
    if ld is not None and "landed" in ld:
        landed = np.asarray(ld["landed"], dtype=float)
        out["EXTENDED_SYS_STATE"] = _series("EXTENDED_SYS_STATE", _t(ld), [np.where(landed > 0.5, 1.0, 2.0)])
    return out


def _attitude(topics: dict[str, dict[str, np.ndarray]], p: Path, notes: list[str]) -> Series:
    va = topics["vehicle_attitude"]
    t = _t(va)
    q = _cols(va, "q[{}]", 4)
    if q is None:
        raise LogError(f"{p}: ULog vehicle_attitude has no quaternion q[0..3]")
    w, x, y, z = q
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    av = topics.get("vehicle_angular_velocity")
    rates: list[np.ndarray]
    if av is not None and _cols(av, "xyz[{}]", 3) is not None:
        ta = _t(av)
        rates = [np.interp(t, ta, c, left=math.nan, right=math.nan) for c in _cols(av, "xyz[{}]", 3) or []]
    elif "rollspeed" in va:
        rates = [np.asarray(va[k], dtype=float) for k in ("rollspeed", "pitchspeed", "yawspeed")]
    else:
        notes.append(f"{p}: ULog has no vehicle_angular_velocity topic (body rates)")
        rates = [np.full(len(t), math.nan)] * 3
    return _series("ATTITUDE", t, [roll, pitch, yaw, *rates])


def _servo(topics: dict[str, dict[str, np.ndarray]]) -> Series | None:
    ao = topics.get("actuator_outputs")
    if ao is not None:
        cols = _cols(ao, "output[{}]", 16)
        if cols is not None:
            return _series("SERVO_OUTPUT_RAW", _t(ao), cols)
    srv = topics.get("actuator_servos")
    if srv is not None:
        cols = _cols(srv, "control[{}]", 16)
        if cols is not None:
            return _series("SERVO_OUTPUT_RAW", _t(srv), [1500.0 + 500.0 * c for c in cols])
    return None


def _rc(topics: dict[str, dict[str, np.ndarray]]) -> Series | None:
    rc = topics.get("input_rc")
    if rc is not None:
        cols = _cols(rc, "values[{}]", 18)
        if cols is not None:
            return _series("RC_CHANNELS", _t(rc), cols)
    ms = topics.get("manual_control_setpoint")
    if ms is None:
        return None
    names = ("roll", "pitch", "throttle", "yaw") if "roll" in ms else ("y", "x", "z", "r")  # PX4 >= 1.14 / older
    if not all(k in ms for k in names):
        return None
    sticks = [np.asarray(ms[k], dtype=float) for k in names]
    thr = sticks[2]
    thr_us = 1500.0 + 500.0 * thr if np.nanmin(thr, initial=0.0) < -0.01 else 1000.0 + 1000.0 * thr
    nan = np.full(len(thr), math.nan)
    return _series("RC_CHANNELS", _t(ms), [1500.0 + 500.0 * sticks[0], 1500.0 + 500.0 * sticks[1], thr_us,
                                           1500.0 + 500.0 * sticks[3], *([nan] * 14)])


def _gps(topics: dict[str, dict[str, np.ndarray]]) -> Series | None:
    """``vehicle_gps_position`` (else ``sensor_gps``): integer 1e-7 deg / mm fields (PX4 < 1.14) or
    ``latitude_deg``/``longitude_deg``/``altitude_msl_m`` (PX4 >= 1.14)."""
    g = topics.get("vehicle_gps_position", topics.get("sensor_gps"))
    if g is None:
        return None
    n = len(g["timestamp"])
    nan = np.full(n, math.nan)

    def col(*names: str, scale: float = 1.0) -> np.ndarray:
        for k in names:
            if k in g:
                return np.asarray(g[k], dtype=float) * scale
        return nan

    lat = col("latitude_deg") if "latitude_deg" in g else col("lat", scale=1e-7)
    lon = col("longitude_deg") if "longitude_deg" in g else col("lon", scale=1e-7)
    alt = col("altitude_msl_m") if "altitude_msl_m" in g else col("alt", scale=1e-3)
    return _series("GPS_RAW_INT", _t(g), [col("fix_type"), lat, lon, alt, col("vel_m_s"),
                                          col("satellites_used")])
