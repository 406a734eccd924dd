"""Dataflash (.bin) import through pymavlink's DFReader, on a log written here with struct.

The file is built per the DataFlash format: records ``0xA3 0x95 TYPE payload``; FMT records
(type 128) define each message's name, struct format and columns. A PX4 sdlog2 .px4log uses the same
record format with PX4 message names (ATT with rates in rad/s, OUT0, LPOS, STAT ArmS); a small
sdlog2-style file is built the same way.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from firmware_interface.errors import LogError
from firmware_interface.readers import load_log

_STRUCT = {"Q": "Q", "B": "B", "H": "H", "I": "I", "f": "f", "L": "i", "n": "4s", "N": "16s", "Z": "64s"}


def _fmt(typ: int, name: str, fmt: str, cols: str) -> bytes:
    length = 3 + struct.calcsize("<" + "".join(_STRUCT[c] for c in fmt))
    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", typ, length, name.encode(), fmt.encode(), cols.encode())


def _rec(typ: int, fmt: str, *vals) -> bytes:
    return b"\xa3\x95" + bytes([typ]) + struct.pack("<" + "".join(_STRUCT[c] for c in fmt), *vals)


def ardupilot_bin(n: int = 500) -> bytes:
    out = _fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
    out += _fmt(130, "ATT", "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")
    out += _fmt(131, "IMU", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ")
    out += _fmt(132, "RCOU", "QHHHH", "TimeUS,C1,C2,C3,C4")
    out += _fmt(133, "EV", "QB", "TimeUS,Id")
    out += _fmt(134, "XKF1", "QBffffff", "TimeUS,C,VN,VE,VD,PN,PE,PD")
    out += _fmt(135, "GPS", "QBBIHLLffB", "TimeUS,I,Status,GMS,GWk,Lat,Lng,Alt,Spd,NSats")
    for k in range(n):
        t = 1_000_000 + k * 20_000
        if k == 100:
            out += _rec(133, "QB", t, 10)  # armed
        if k == 400:
            out += _rec(133, "QB", t, 11)  # disarmed
        out += _rec(130, "Qffffff", t, 0, 5.0, 0, -3.0, 0, 90.0)
        out += _rec(131, "QBffffff", t, 0, 0.1, 0.2, 0.3, 0, 0, -9.8)
        out += _rec(132, "QHHHH", t, 1500, 1600, 1700, 1400)
        out += _rec(134, "QBffffff", t, 0, 1.0, 2.0, 0.5, 10, 20, -2.0 if 150 < k < 350 else 0.0)
        if k % 10 == 0:
            out += _rec(135, "QBBIHLLffB", t, 0, 3, 100_000_000 + t // 1000, 2300, 473977420, 85455940,
                        500.0, 2.0, 12)
    return out


def test_ardupilot_bin_maps_to_mavlink_series_in_si_units(tmp_path):
    path = tmp_path / "00000001.BIN"
    path.write_bytes(ardupilot_bin())
    log = load_log(path)
    att = log.series["ATTITUDE"]
    assert len(att) == 500
    assert att["roll_rad"][0] == pytest.approx(np.radians(5.0))
    assert att["pitch_rad"][0] == pytest.approx(np.radians(-3.0))
    assert att["yaw_rad"][0] == pytest.approx(np.pi / 2)
    assert att["q_rad_s"] == pytest.approx(np.full(500, 0.2))  # body rates from IMU gyro
    assert np.diff(att.t_fc_s) == pytest.approx(np.full(499, 0.02))
    assert log.series["SERVO_OUTPUT_RAW"]["pwm_us_3"][0] == 1700
    lp = log.series["LOCAL_POSITION_NED"]
    assert (lp["vx_m_s"][0], lp["vy_m_s"][0], lp["vz_m_s"][0], lp["x_m"][0]) == pytest.approx((1.0, 2.0, 0.5, 10.0))
    gps = log.series["GPS_RAW_INT"]
    assert gps["lat_deg"][0] == pytest.approx(47.397742) and gps["satellites"][0] == 12
    assert log.series["IMU"]["az_m_s2"][0] == pytest.approx(-9.8)
    assert len(log.flights) == 1
    f = log.flights[0]
    assert (f.start_fc_s, f.end_fc_s) == pytest.approx((3.0, 9.0))
    assert f.in_air_s == pytest.approx(3.98, abs=0.03)  # height 2 m from k=151 to 349


def test_px4_sdlog2_style_log(tmp_path):
    # sdlog2 records carry no time field: the TIME record (StartTime, µs) stamps what follows
    out = _fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
    out += _fmt(129, "TIME", "Q", "StartTime")
    out += _fmt(130, "ATT", "ffffff", "Roll,Pitch,Yaw,RollRate,PitchRate,YawRate")
    out += _fmt(131, "OUT0", "HHHH", "Out0,Out1,Out2,Out3")
    out += _fmt(132, "LPOS", "ffffff", "X,Y,Z,VX,VY,VZ")
    out += _fmt(133, "STAT", "BB", "MainState,ArmS")
    for k in range(200):
        t = 2_000_000 + k * 10_000
        out += _rec(129, "Q", t)
        if k % 20 == 0:
            out += _rec(133, "BB", 0, 2 if 40 <= k < 160 else 1)
        out += _rec(130, "ffffff", 0.1, -0.2, 1.0, 0.01, 0.02, 0.03)
        out += _rec(131, "HHHH", 1100, 1200, 1300, 1400)
        out += _rec(132, "ffffff", 1.0, 2.0, -3.0, 0.1, 0.2, 0.3)
    path = tmp_path / "flight.px4log"
    path.write_bytes(out)
    log = load_log(path)
    att = log.series["ATTITUDE"]
    assert len(att) == 200
    assert (att["roll_rad"][0], att["p_rad_s"][0], att["r_rad_s"][0]) == pytest.approx((0.1, 0.01, 0.03))
    assert np.median(np.diff(att.t_fc_s)) == pytest.approx(0.01, abs=1e-6)
    assert log.series["SERVO_OUTPUT_RAW"]["pwm_us_1"][0] == 1100
    assert log.series["SERVO_OUTPUT_RAW"]["pwm_us_3"][0] == 1300
    assert log.series["LOCAL_POSITION_NED"]["vz_m_s"][0] == pytest.approx(0.3)
    assert len(log.flights) == 1
    f = log.flights[0]
    assert f.end_fc_s - f.start_fc_s == pytest.approx(1.2, abs=0.011)


def test_truncated_bin_still_loads_what_is_whole(tmp_path):
    data = ardupilot_bin()
    path = tmp_path / "cut.bin"
    path.write_bytes(data[: len(data) // 2 + 7])
    log = load_log(path)
    assert 200 < len(log.series["ATTITUDE"]) < 300


def test_bin_without_known_messages_is_a_log_error(tmp_path):
    path = tmp_path / "empty.bin"
    path.write_bytes(_fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))
    with pytest.raises(LogError, match="empty.bin"):
        load_log(path)


def test_log_info_json_on_a_bin_keeps_stdout_clean(tmp_path, capsys):
    import json

    from groundstation.cli import main as cli_main

    data = ardupilot_bin()
    path = tmp_path / "flight.bin"
    path.write_bytes(data[:-5] + b"\xa3\x95\x86garbage")  # damaged tail: DFReader complains on stdout
    assert cli_main(["log-info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["messages"]["ATT"]["count"] == 500 and len(info["flights"]) == 1


def heli_sysid_bin() -> bytes:
    """An ArduPilot heli log in SYSID mode: RCIN, HELI, GYR at 400 Hz and one roll-mixer chirp."""
    out = _fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
    out += _fmt(130, "ATT", "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")
    out += _fmt(131, "RCIN", "QHHHH", "TimeUS,C1,C2,C3,C4")
    out += _fmt(132, "HELI", "Qffff", "TimeUS,DRRPM,ERRPM,Gov,Throt")
    out += _fmt(133, "GYR", "QBIfff", "TimeUS,I,SampleUS,GyrX,GyrY,GyrZ")
    out += _fmt(134, "SIDS", "QBfffffff", "TimeUS,Ax,Mag,FSt,FSp,TFin,TC,TR,TFout")
    out += _fmt(135, "SIDD", "Qfffffffff", "TimeUS,Time,Targ,F,Gx,Gy,Gz,Ax,Ay,Az")
    out += _fmt(136, "EV", "QB", "TimeUS,Id")
    for k in range(4000):  # 10 s at 400 Hz
        t = 1_000_000 + k * 2_500
        if k == 0:
            out += _rec(136, "QB", t, 10)
        if k == 800:
            out += _rec(134, "QBfffffff", t, 10, 0.1, 0.5, 6.0, 0.5, 0.5, 5.0, 0.5)
        if k % 8 == 0:
            out += _rec(130, "Qffffff", t, 0, 1.0, 0, 2.0, 0, 3.0)
            out += _rec(131, "QHHHH", t, 1500, 1510, 1520, 1530)
            out += _rec(132, "Qffff", t, 1500.0, 1490.0 + (k % 3), 0.5, 0.6)
        out += _rec(133, "QBIfff", t, 0, t, 0.01 * np.sin(2 * np.pi * 24.9 * t * 1e-6), 0.0, 0.0)
        if 800 <= k < 800 + 6 * 400:  # 6 s of chirp data at 400 Hz
            out += _rec(135, "Qfffffffff", t, (k - 800) / 400, 0.05, 0.5 + (k - 800) / 400, 0, 0, 0, 0, 0, 0)
    return out


def test_heli_sysid_log_chirps_rotor_speed_rc_and_fast_gyro(tmp_path, capsys):
    import json

    from firmware_interface.readers import restrict_to_chirps
    from groundstation.cli import main as cli_main

    path = tmp_path / "sysid.bin"
    path.write_bytes(heli_sysid_bin())
    log = load_log(path)
    assert log.series["RC_CHANNELS"]["pwm_us_4"][0] == 1530
    assert log.series["ROTOR"]["desired_rotor_speed_rpm"][0] == 1500.0
    assert np.median(np.diff(log.series["GYRO_FAST"].t_fc_s)) == pytest.approx(0.0025)
    (c,) = log.chirps
    assert (c.axis_name, c.f_start_hz, c.f_stop_hz) == ("mixer_roll", 0.5, 6.0)
    assert c.start_fc_s == pytest.approx(3.0) and c.duration_s == pytest.approx(6.0, abs=0.01)
    only = restrict_to_chirps(log)
    assert [(f.start_fc_s, f.end_fc_s) for f in only.flights] == [(c.start_fc_s, c.end_fc_s)]
    assert cli_main(["log-info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["chirps"][0]["axis"] == "mixer_roll" and info["chirps"][0]["duration_s"] == pytest.approx(6.0, abs=0.01)


def test_segments_sysid_without_chirps_is_one_line(tmp_path, capsys):
    from groundstation.cli import main as cli_main

    path = tmp_path / "plain.bin"
    path.write_bytes(ardupilot_bin())
    assert cli_main(["identify", str(path), "--segments", "sysid", "--out", str(tmp_path / "m.json")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "plain.bin" in err[0] and "SYSID" in err[0]


def test_truncated_mid_record_is_one_note_and_keeps_everything_before(tmp_path, capsys):
    import json

    from groundstation.cli import main as cli_main

    data = ardupilot_bin()
    whole = load_log_bytes(tmp_path, data)
    path = tmp_path / "cut.bin"
    path.write_bytes(data[:-7])  # the last record (RCOU/XKF1/GPS) loses its tail
    log = load_log(path)
    assert len(log.series["ATTITUDE"]) == len(whole.series["ATTITUDE"])
    assert log.stats.truncated_tail_bytes > 0
    assert len(log.notes) == 1 and "cut.bin" in log.notes[0] and "ends inside a record" in log.notes[0]
    assert cli_main(["log-info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["truncated_tail_bytes"] == log.stats.truncated_tail_bytes


def load_log_bytes(tmp_path, data):
    p = tmp_path / "whole.bin"
    p.write_bytes(data)
    return load_log(p)


def test_bench_log_without_arming_is_one_flight_and_says_so(tmp_path):
    out = _fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
    out += _fmt(130, "ATT", "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw")
    for k in range(100):
        out += _rec(130, "Qffffff", 1_000_000 + k * 20_000, 0, 1.0, 0, 2.0, 0, 3.0)
    path = tmp_path / "bench.bin"
    path.write_bytes(out)
    log = load_log(path)
    assert len(log.flights) == 1 and log.flights[0].duration_s == pytest.approx(1.98)
    assert any("bench.bin" in n and "no arming events" in n for n in log.notes)
