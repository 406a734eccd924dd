"""Tolerant .tlog reading, load_log on real and project-written logs, log-info, bad input."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.errors import LogError
from firmware_interface.readers import load_log, load_tlog_bytes
from firmware_interface.tlog import TlogWriter
from firmware_interface.tlogread import TlogScan, scan_tlog
from groundstation.cli import main as cli_main
from tests.realdata import real_log

REPO = Path(__file__).resolve().parents[2]
T0_US = 1_700_000_000_000_000


def _records(n: int = 50, t0_us: int = T0_US, step_us: int = 20_000) -> list[tuple[int, bytes]]:
    mav = mavlink2.MAVLink(None, 1, 1)
    out = []
    for k in range(n):
        if k % 10 == 0:
            msg = mav.heartbeat_encode(4, 3, 0x81 if 10 <= k < 40 else 0x01, 0, 4)
        else:
            msg = mav.attitude_encode(1000 + 20 * k, 0.01 * k, 0, 0, 0, 0, 0)
        out.append((t0_us + k * step_us, bytes(msg.pack(mav))))
        mav.seq = (mav.seq + 1) & 0xFF
    return out


def _blob(records) -> bytes:
    return b"".join(struct.pack(">Q", t) + p for t, p in records)


def _scan(data: bytes) -> tuple[list[tuple[float, bytes]], TlogScan]:
    st = TlogScan()
    return list(scan_tlog(data, st)), st


def test_clean_tlog_scans_every_record_with_its_timestamp():
    recs = _records()
    got, st = _scan(_blob(recs))
    assert [p for _, p in got] == [p for _, p in recs]
    assert [round(t * 1e6) for t, _ in got] == [t for t, _ in recs]
    assert st.corrupt_bytes == 0 and st.truncated_tail_bytes == 0 and st.resyncs == 0


@pytest.mark.parametrize("cut", [1, 5, 9, 20])
def test_truncated_last_record(cut):
    recs = _records()
    data = _blob(recs)
    last_len = 8 + len(recs[-1][1])
    got, st = _scan(data[: len(data) - last_len + cut])
    assert [p for _, p in got] == [p for _, p in recs[:-1]]
    assert st.truncated_tail_bytes == cut


def test_garbage_between_records_is_skipped_and_counted():
    recs = _records()
    junk = [b"\xfd\x10\x00junk", b"\x00" * 3, bytes(range(250, 256)) * 4, b"\xfe\x05"]
    data = b""
    k = 0
    for i, (t, p) in enumerate(recs):
        data += struct.pack(">Q", t) + p
        if i in (3, 17, 29, 40):
            data += junk[k]
            k += 1
    got, st = _scan(data)
    assert [p for _, p in got] == [p for _, p in recs]
    assert st.corrupt_bytes == sum(len(j) for j in junk)


def test_timestamps_containing_magic_bytes_do_not_confuse_the_scanner():
    # timestamps whose bytes are 0xFD/0xFE (plus one record damaged, forcing a resync through them)
    t0 = int.from_bytes(b"\x00\x06\x0a\xfd\xfe\xfd\xfe\x00", "big")
    recs = _records(t0_us=t0, step_us=1)
    assert all(b"\xfd" in struct.pack(">Q", t) for t, _ in recs)
    data = bytearray(_blob(recs))
    rec_len = [8 + len(p) for _, p in recs]
    start = sum(rec_len[:12])
    data[start + 8 + 12] ^= 0xFF  # corrupt the payload of record 12
    got, st = _scan(bytes(data))
    expect = [p for i, (_, p) in enumerate(recs) if i != 12]
    assert [p for _, p in got] == expect
    assert st.corrupt_bytes == rec_len[12]
    assert [round(t * 1e6) for t, _ in got][12] == recs[13][0]


def test_host_clock_jump_is_followed_not_treated_as_garbage():
    recs = _records(20) + [(t + 10 * 86400 * 10**6, p) for t, p in _records(20, t0_us=T0_US + 400_000)]
    got, st = _scan(_blob(recs))
    assert len(got) == 40 and st.corrupt_bytes == 0


@pytest.mark.parametrize("speed", [1.0, 10.0])
def test_untimed_messages_get_fc_times_from_their_neighbours_even_when_replayed_fast(speed):
    """HEARTBEAT and EXTENDED_SYS_STATE carry no time: they take the FC time of the timed messages
    around them in the stream. A link replayed at 10x (10 FC seconds per host second) must not
    shift them by the drift over a clock bin (it did: arming and landing came out 9 s late)."""
    mav = mavlink2.MAVLink(None, 1, 1)
    rng = np.random.default_rng(1)
    recs = []
    arm_s, takeoff_s, land_s, disarm_s = 3.0, 7.0, 20.0, 22.0
    for k in range(int(25.0 / 0.02)):
        t_fc = k * 0.02
        host_us = T0_US + int((t_fc / speed + rng.exponential(0.004)) * 1e6)  # 4 ms mean latency
        msgs = [mav.attitude_encode(int(round(t_fc * 1000)), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)]
        if k % 50 == 0:
            armed = arm_s <= t_fc < disarm_s
            msgs.append(mav.heartbeat_encode(4, 3, 0x81 if armed else 0x01, 0, 4))
        if k % 10 == 5:
            state = 2 if takeoff_s <= t_fc < land_s else 1
            msgs.append(mav.extended_sys_state_encode(0, state))
        for m in msgs:
            recs.append((host_us, bytes(m.pack(mav))))
            mav.seq = (mav.seq + 1) & 0xFF
    recs.sort(key=lambda r: r[0])
    log = load_tlog_bytes(_blob(recs))
    f = log.flights[0]
    assert f.start_fc_s == pytest.approx(arm_s, abs=0.05) and f.end_fc_s == pytest.approx(disarm_s, abs=1.05)
    es = log.series["EXTENDED_SYS_STATE"]
    air = np.asarray(es["landed_state"]) == 2
    assert es.t_fc_s[air][0] == pytest.approx(takeoff_s + 0.1, abs=0.05)
    assert es.t_fc_s[air][-1] == pytest.approx(land_s - 0.1, abs=0.05)


def test_project_written_tlog_loads_with_flights(tmp_path):
    path = tmp_path / "w.tlog"
    with TlogWriter(path) as w:
        for t, p in _records(200):
            w.write(p, t * 1e-6)
    log = load_log(path)
    att = log.series["ATTITUDE"]
    assert len(att) == 180
    assert np.all(np.diff(att.t_fc_s) > 0)
    assert log.message_counts == {"HEARTBEAT": 20, "ATTITUDE": 180}
    assert len(log.flights) == 1
    f = log.flights[0]
    assert f.start_fc_s == pytest.approx(1.2, abs=0.03) and f.end_fc_s == pytest.approx(1.8, abs=0.03)
    assert np.isnan(f.in_air_s)  # no landed state, no altitude: unknown, not zero


def test_load_log_on_real_trex550_log():
    log = load_log(real_log("trex550/flight1.tlog"))
    att = log.series["ATTITUDE"]
    assert len(att) == 39810
    rate = (len(att) - 1) / (att.t_fc_s[-1] - att.t_fc_s[0])
    assert rate == pytest.approx(123.5, abs=0.5)
    assert len(log.flights) >= 1
    assert log.flights[0].duration_s > 200 and log.flights[0].in_air_s > 200
    assert log.has("SERVO_OUTPUT_RAW") and log.has("LOCAL_POSITION_NED")
    assert log.stats.corrupt_bytes == 0 and log.stats.packets == 120074


def test_log_info_json_on_real_log(capsys):
    assert cli_main(["log-info", str(real_log("trex550/flight1.tlog")), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert len(info["flights"]) >= 1
    f = info["flights"][0]
    assert set(f) == {"index", "start_s", "end_s", "duration_s", "in_air_s", "on_ground_evidence"}
    assert f["on_ground_evidence"] is None  # a real flight: the aircraft moves
    assert info["messages"]["ATTITUDE"]["count"] == 39810
    assert info["messages"]["ATTITUDE"]["rate_hz"] == pytest.approx(123.5, abs=0.5)
    assert info["corrupt_bytes"] == 0 and info["packet_loss"]["lost"] == 0


def test_log_info_reports_gaps_corruption_and_loss(tmp_path, capsys):
    recs = _records(200)
    keep = [r for i, r in enumerate(recs) if not 100 <= i < 110]  # 0.2 s hole, also a seq gap
    data = bytearray(_blob(keep))
    data[8 * 5 + sum(len(p) for _, p in keep[:5]) + 15] ^= 0x01  # one bad record
    path = tmp_path / "holes.tlog"
    path.write_bytes(bytes(data) + b"\xfd\x1c\x00")  # and a truncated tail
    assert cli_main(["log-info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    gaps = [g for g in info["gaps"] if g["message"] == "ATTITUDE"]
    assert len(gaps) == 1 and gaps[0]["duration_s"] == pytest.approx(0.24, abs=0.001)  # 99 -> 111 (110 is a heartbeat)
    assert gaps[0]["start_s"] == pytest.approx(1.0 + 99 * 0.02, abs=0.001)
    assert info["corrupt_bytes"] == 8 + len(keep[5][1])
    assert info["truncated_tail_bytes"] == 3
    assert info["packet_loss"]["lost"] == 11 and info["packet_loss"]["by_source"] == {"1:1": 11}
    assert cli_main(["log-info", str(path)]) == 0  # table form
    out = capsys.readouterr().out
    assert "ATTITUDE" in out and "flights" in out


@pytest.mark.parametrize("content,needle", [(None, "no such file"), (b"", "empty file"),
                                            (b"hello world, this is not MAVLink\n" * 40, "not a MAVLink")])
def test_bad_input_one_line_exit_2(tmp_path, content, needle):
    path = tmp_path / "bad.tlog"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(LogError, match=needle):
        load_log(path)
    r = subprocess.run([sys.executable, "-m", "groundstation.cli", "log-info", str(path)],
                       capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and needle in lines[0]


def test_truncated_file_in_the_middle_of_the_first_record():
    data = _blob(_records(3))[:12]
    with pytest.raises(LogError, match="no valid"):
        load_tlog_bytes(data, "cut.tlog")


def test_damaged_timestamp_keeps_the_packet_at_the_previous_time():
    recs = _records(30)
    data = bytearray(_blob(recs))
    off = sum(8 + len(p) for _, p in recs[:10])
    data[off + 1] ^= 0x40  # a high timestamp byte of record 10: years off
    data2 = bytearray(_blob(recs))
    data2[off + 4] ^= 0x80  # record 10 about 36 min off
    for blob in (data, data2):
        st = TlogScan()
        got = list(scan_tlog(bytes(blob), st))
        assert [p for _, p in got] == [p for _, p in recs]
        assert st.bad_timestamps == 1 and st.corrupt_bytes == 0
        assert round(got[10][0] * 1e6) == recs[9][0]


@pytest.mark.parametrize("seed", range(5))
def test_randomly_damaged_tlog_yields_an_ordered_subset_of_the_original_packets(seed):
    import random

    rng = random.Random(seed)
    recs = _records(400)
    data = bytearray(_blob(recs))
    for _ in range(len(data) // 100):  # 1 % of the bytes hit
        data[rng.randrange(len(data))] = rng.randrange(256)
    cut = rng.randrange(len(data) - 50, len(data))
    st = TlogScan()
    got = [p for _, p in scan_tlog(bytes(data[:cut]), st)]
    original = [p for _, p in recs]
    it = iter(original)
    assert all(any(p == q for q in it) for p in got)  # in order, each one an original packet
    # every record whose frame bytes survived is found (bar the cut tail)
    intact, pos = [], 0
    for _, pkt in recs:
        start = pos + 8
        if start + len(pkt) <= cut and bytes(data[start:start + len(pkt)]) == pkt:
            intact.append(pkt)
        pos = start + len(pkt)
    assert len(got) >= len(intact) - 1 and len(intact) > 0.6 * len(original)
    log = load_tlog_bytes(bytes(data[:cut]), "damaged.tlog")
    assert np.all(np.diff(log.series["ATTITUDE"].t_fc_s) >= 0)


@settings(max_examples=80, deadline=None)
@given(st.binary(max_size=600), st.lists(st.integers(0, 39), max_size=8), st.integers(0, 2000))
def test_arbitrary_bytes_give_logdata_or_log_error_nothing_else(noise, picks, where):
    recs = _records(40)
    blob = bytearray(noise)
    for k in picks:  # splice whole records into the noise
        t, p = recs[k]
        pos = where % (len(blob) + 1)
        blob[pos:pos] = struct.pack(">Q", t) + p
    try:
        log = load_tlog_bytes(bytes(blob), "fuzz.tlog")
    except LogError as exc:
        assert "fuzz.tlog" in str(exc)
        return
    assert sum(log.message_counts.values()) >= 1
    for s in log.series.values():
        assert np.all(np.diff(s.t_fc_s) >= 0)
