"""MavlinkSession fed from tables, one byte at a time, with time injected (no IO, no event loop)."""

from __future__ import annotations

import math
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.errors import LocalProtocolError
from firmware_interface.samples import (
    Attitude,
    CommandAck,
    FcRebooted,
    GlobalPositionInt,
    GpsRawInt,
    Heartbeat,
    Imu,
    LinkLost,
    LinkRestored,
    LocalPositionNed,
    RawPacket,
    ServoOutputRaw,
    StatusText,
    SysStatus,
)
from firmware_interface.session import MavlinkSession, SessionConfig, check_outgoing

from .conftest import FakeFc


def feed_bytewise(s: MavlinkSession, data: bytes, now: float = 100.0) -> list:
    for b in data:
        s.receive_data(bytes([b]), now)
    return s.events()


def parse_out(data: bytes) -> list:
    p = mavlink2.MAVLink(None)
    p.robust_parsing = True
    msgs = p.parse_buffer(data) or []
    assert all(m.get_type() != "BAD_DATA" for m in msgs)
    return msgs


def passive() -> MavlinkSession:
    return MavlinkSession(SessionConfig(request_streams=False, send_heartbeat=False))


# ------------------------------------------------------------------ decoding tables


def _table(fc: FakeFc):
    m = fc.mav
    return [
        (m.heartbeat_encode(4, 3, 0x81, 5, 4), Heartbeat,
         dict(mav_type=4, autopilot=3, base_mode=0x81, custom_mode=5, armed=True)),
        (m.attitude_encode(2500, 0.1, -0.2, 1.5, 0.01, -0.02, 0.3), Attitude,
         dict(t_fc_s=2.5, roll_rad=0.1, pitch_rad=-0.2, yaw_rad=1.5, p_rad_s=0.01, q_rad_s=-0.02, r_rad_s=0.3)),
        (m.local_position_ned_encode(2600, 1.0, 2.0, -3.0, 0.5, -0.5, 0.25), LocalPositionNed,
         dict(t_fc_s=2.6, x_m=1.0, y_m=2.0, z_m=-3.0, vx_m_s=0.5, vy_m_s=-0.5, vz_m_s=0.25)),
        (m.global_position_int_encode(2700, 473977420, 85455940, 512000, 2500, 150, -250, 30, 9000),
         GlobalPositionInt,
         dict(t_fc_s=2.7, lat_deg=47.397742, lon_deg=8.545594, alt_m=512.0, relative_alt_m=2.5,
              vx_m_s=1.5, vy_m_s=-2.5, vz_m_s=0.3, hdg_deg=90.0)),
        (m.servo_output_raw_encode(2_800_000, 0, 1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800),
         ServoOutputRaw, dict(t_fc_s=2.8, port=0)),
        (m.raw_imu_encode(2_900_000, 1000, -500, 0, 100, -200, 300, 0, 0, 0), Imu,
         dict(t_fc_s=2.9, source="RAW_IMU")),
        (m.gps_raw_int_encode(3_000_000, 3, 473977420, 85455940, 512000, 100, 100, 250, 18000, 11), GpsRawInt,
         dict(t_fc_s=3.0, fix_type=3, alt_m=512.0, ground_speed_m_s=2.5, course_deg=180.0, satellites=11)),
        (m.sys_status_encode(0, 0, 0, 250, 16800, 1234, 77, 1500, 7, 0, 0, 0, 0), SysStatus,
         dict(voltage_v=16.8, current_a=12.34, battery_pct=77, drop_rate_comm_pct=15.0, errors_comm=7,
              load_pct=25.0)),
        (m.statustext_encode(6, b"PreArm: good"), StatusText, dict(severity=6, text="PreArm: good")),
        (m.command_ack_encode(511, 0), CommandAck, dict(command=511, result=0)),
    ]


@pytest.mark.parametrize("v1", [False, True], ids=["mavlink2", "mavlink1"])
def test_table_bytewise_decodes_every_message_in_si_units(v1):
    fc = FakeFc(v1=v1)
    rows = _table(fc)
    s = passive()
    frames = [fc.pack(msg) for msg, _, _ in rows]
    assert all(f[0] == (0xFE if v1 else 0xFD) for f in frames)
    events = feed_bytewise(s, b"".join(frames))
    raws = [e for e in events if isinstance(e, RawPacket)]
    typed = [e for e in events if not isinstance(e, RawPacket)]
    assert [r.data for r in raws] == frames  # exact bytes as received
    assert [r.msg_type for r in raws] == [msg.get_type() for msg, _, _ in rows]
    assert len(typed) == len(rows)
    for ev, (_, cls, expect) in zip(typed, rows, strict=True):
        assert type(ev) is cls
        for k, v in expect.items():
            got = getattr(ev, k)
            if isinstance(v, float):
                assert got == pytest.approx(v, rel=1e-6, abs=1e-6), k
            else:
                assert got == v, k
        assert ev.sysid == 1 and ev.compid == 1
    imu = next(e for e in typed if isinstance(e, Imu))
    assert imu.acc_m_s2[0] == pytest.approx(9.80665) and imu.acc_m_s2[1] == pytest.approx(-0.5 * 9.80665)
    assert imu.gyro_rad_s == pytest.approx((0.1, -0.2, 0.3))
    servo = next(e for e in typed if isinstance(e, ServoOutputRaw))
    assert servo.pwm_us[:8] == (1100, 1200, 1300, 1400, 1500, 1600, 1700, 1800)
    assert s.stats.packets == len(rows) and s.stats.corrupt_bytes == 0 and s.stats.bad_crc == 0


def test_mixed_v1_v2_stream_with_garbage_counts_garbage_bytes():
    a, b = FakeFc(v1=True), FakeFc(sysid=2)
    garbage = b"\x00\x01hello\xfd\x05"  # includes a stray magic with an impossible frame
    data = a.heartbeat() + garbage + b.attitude(1000) + b"\x55" * 7 + a.attitude(2000)
    s = passive()
    events = feed_bytewise(s, data)
    assert [type(e).__name__ for e in events if not isinstance(e, RawPacket)] == ["Heartbeat", "Attitude", "Attitude"]
    assert s.stats.corrupt_bytes == len(garbage) + 7
    assert s.stats.packets == 3


def test_bad_crc_is_counted_and_the_next_packet_survives():
    fc = FakeFc()
    good1, bad, good2 = fc.attitude(1000), bytearray(fc.attitude(1020)), fc.attitude(1040)
    bad[15] ^= 0x40  # payload bit flip
    short = bytearray(fc.attitude(1060))
    short[1] = 200  # corrupted length byte: claims a long frame that would swallow good3
    good3 = fc.attitude(1080)
    s = passive()
    events = feed_bytewise(s, good1 + bytes(bad) + good2 + bytes(short) + good3 + bytes(300))
    att = [e.t_fc_s for e in events if isinstance(e, Attitude)]
    assert att == pytest.approx([1.0, 1.04, 1.08])
    assert s.stats.bad_crc == 2
    assert s.stats.corrupt_bytes == len(bad) + len(short) + 300
    # the frames that did not check are counted as sequence loss too
    assert s.stats.packets_lost == 2 and s.stats.loss_by_source == {"1:1": 2}


def test_seq_gaps_counted_per_source():
    a, b = FakeFc(1, 1), FakeFc(1, 154)
    s = passive()
    data = a.heartbeat() + b.heartbeat()
    for _ in range(3):
        a.heartbeat()  # encoded but never delivered: 3 lost from 1:1
    data += a.heartbeat() + b.heartbeat()
    b.mav.seq = (b.mav.seq + 250) & 0xFF  # skip 250 across the wrap of seq
    data += b.heartbeat()
    feed_bytewise(s, data)
    assert s.stats.loss_by_source == {"1:1": 3, "1:154": 250}
    assert s.stats.packets_lost == 253


def test_time_boot_ms_wrap_is_unwrapped_not_a_reboot():
    fc = FakeFc()
    s = passive()
    top = 2**32 - 40
    t = [top, top + 20, (top + 40) % 2**32, (top + 60) % 2**32]
    events = feed_bytewise(s, b"".join(fc.attitude(ms) for ms in t))
    times = [e.t_fc_s for e in events if isinstance(e, Attitude)]
    assert times == pytest.approx([top * 1e-3 + k * 0.02 for k in range(4)])
    assert not any(isinstance(e, FcRebooted) for e in events)
    assert s.stats.fc_reboots == 0


def test_servo_time_usec_uint32_wrap():
    fc = FakeFc()
    s = passive()
    top = 2**32 - 15_000
    frames = b""
    for k in range(3):
        frames += fc.pack(fc.mav.servo_output_raw_encode((top + k * 10_000) % 2**32, 0, 1500, 1500, 1500, 1500,
                                                         0, 0, 0, 0))
    ts = [e.t_fc_s for e in feed_bytewise(s, frames) if isinstance(e, ServoOutputRaw)]
    assert ts == pytest.approx([top * 1e-6 + k * 0.01 for k in range(3)])


def test_fc_reboot_detected_time_base_stays_monotone_and_streams_rerequested(fc):
    s = MavlinkSession(SessionConfig(stream_rates_hz=(("ATTITUDE", 50.0),)))
    s.receive_data(fc.heartbeat() + fc.attitude(600_000), 1000.0)
    out = parse_out(s.data_to_send(1000.0))
    assert [m.get_type() for m in out] == ["HEARTBEAT", "COMMAND_LONG"]
    s.receive_data(fc.ack(511, 0), 1000.1)
    assert s.stream_status.states == {"ATTITUDE": "ok"}
    s.events()
    # reboot: 5 s of silence, then time_boot_ms restarts at 300 ms
    s.receive_data(fc.attitude(300), 1005.0)
    ev = s.events()
    reb = [e for e in ev if isinstance(e, FcRebooted)]
    assert len(reb) == 1 and reb[0].previous_t_fc_s == pytest.approx(600.0)
    att = [e for e in ev if isinstance(e, Attitude)]
    assert att[0].t_fc_s == pytest.approx(605.0)  # continues by the host-measured gap
    assert s.stats.fc_reboots == 1
    out = parse_out(s.data_to_send(1005.0))
    cmds = [(m.command, int(m.param1)) for m in out if m.get_type() == "COMMAND_LONG"]
    assert cmds == [(511, mavlink2.MAVLINK_MSG_ID_ATTITUDE)]
    assert s.stream_status.states == {"ATTITUDE": "sent"}


def test_clock_offset_and_drift_estimated_from_lower_envelope(fc):
    rng = random.Random(3)
    s = passive()
    offset, drift = 1.7e9, 50e-6  # host = fc + offset + drift * fc, plus positive latency
    for k in range(3000):  # 60 s at 50 Hz
        t_fc = 10.0 + k * 0.02
        host = t_fc + offset + drift * t_fc + 0.002 + rng.expovariate(1 / 0.01)
        s.receive_data(fc.attitude(int(round(t_fc * 1000))), host)
    s.events()
    host_now = 70.0 + offset + drift * 70.0
    assert s.clock.drift == pytest.approx(drift, abs=2e-5)
    assert s.clock.host_to_fc(host_now) == pytest.approx(70.0, abs=0.006)
    # an untimed message gets its FC time from the model
    s.receive_data(fc.heartbeat(), host_now + 0.03)
    hb = [e for e in s.events() if isinstance(e, Heartbeat)][0]
    assert hb.t_fc_s == pytest.approx(70.0, abs=0.04)


# ------------------------------------------------------------------ outgoing: read-only allowlist


FORBIDDEN = [
    lambda m: m.command_long_encode(1, 1, mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0),
    lambda m: m.command_long_encode(1, 1, mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0),
    lambda m: m.command_long_encode(1, 1, mavlink2.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0),
    lambda m: m.command_long_encode(1, 1, mavlink2.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 10),
    lambda m: m.command_int_encode(1, 1, 0, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 0, 30, 1e4, 0, 0, 0, 0, 0),
    lambda m: m.set_mode_encode(1, 1, 4),
    lambda m: m.param_set_encode(1, 1, b"ARMING_CHECK", 0, 9),
    lambda m: m.rc_channels_override_encode(1, 1, 1500, 1500, 1900, 1500, 0, 0, 0, 0),
    lambda m: m.set_position_target_local_ned_encode(0, 1, 1, 1, 0, 1, 2, -3, 0, 0, 0, 0, 0, 0, 0, 0),
    lambda m: m.mission_item_encode(1, 1, 0, 0, 16, 1, 1, 0, 0, 0, 0, 47.0, 8.0, 10.0),
    lambda m: m.manual_control_encode(1, 0, 0, 800, 0, 0),
    lambda m: m.heartbeat_encode(mavlink2.MAV_TYPE_HELICOPTER, 3, 0x81, 0, 4),  # pretending to be an FC
]


@pytest.mark.parametrize("make", FORBIDDEN)
def test_forbidden_messages_cannot_be_sent(make, fc):
    s = MavlinkSession()
    s.receive_data(fc.heartbeat(), 10.0)
    s.data_to_send(10.0)
    with pytest.raises(LocalProtocolError):
        s.send_message(make(s._mav))
    # nothing leaked into the output queue
    assert all(m.get_type() in ("HEARTBEAT", "COMMAND_LONG", "REQUEST_DATA_STREAM")
               for m in parse_out(s.data_to_send(10.5)))


_ALLOWED_IDS = {mavlink2.MAVLINK_MSG_ID_HEARTBEAT, mavlink2.MAVLINK_MSG_ID_COMMAND_LONG,
                mavlink2.MAVLINK_MSG_ID_REQUEST_DATA_STREAM,
                # log download: list, read, end -- and nothing else of the LOG_* family
                mavlink2.MAVLINK_MSG_ID_LOG_REQUEST_LIST, mavlink2.MAVLINK_MSG_ID_LOG_REQUEST_DATA,
                mavlink2.MAVLINK_MSG_ID_LOG_REQUEST_END}


def test_allowlist_grew_by_exactly_the_log_download_requests():
    from firmware_interface.session import ALLOWED_MESSAGES

    assert set(ALLOWED_MESSAGES) == _ALLOWED_IDS
    mav = mavlink2.MAVLink(None, 255, 190)
    for msg in (mav.log_erase_encode(1, 1), mav.log_request_data_encode(1, 1, 1, 0, 90)):
        if msg.get_type() == "LOG_ERASE":
            with pytest.raises(LocalProtocolError, match="LOG_ERASE"):
                check_outgoing(msg)
        else:
            check_outgoing(msg)


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(sorted(set(mavlink2.mavlink_map) - _ALLOWED_IDS)))
def test_any_other_message_type_is_refused(msg_id):
    cls = mavlink2.mavlink_map[msg_id]
    msg = cls.__new__(cls)
    mavlink2.MAVLink_message.__init__(msg, msg_id, cls.msgname)
    with pytest.raises(LocalProtocolError):
        check_outgoing(msg)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 65535).filter(lambda c: c not in (511, 512)), st.floats(-1e6, 1e6))
def test_any_other_command_long_is_refused(command, p1):
    mav = mavlink2.MAVLink(None, 255, 190)
    with pytest.raises(LocalProtocolError):
        check_outgoing(mav.command_long_encode(1, 1, command, 0, p1, 0, 0, 0, 0, 0, 0))


# ------------------------------------------------------------------ stream setup and heartbeats


def test_nothing_is_sent_before_the_fc_heartbeat(fc):
    s = MavlinkSession()
    gcs = FakeFc(sysid=200)
    s.receive_data(fc.attitude(1000) + gcs.pack(gcs.mav.heartbeat_encode(6, 8, 0, 0, 4)), 1.0)
    assert s.data_to_send(1.0) == b"" and s.data_to_send(5.0) == b""
    s.receive_data(fc.heartbeat(), 5.5)
    out = parse_out(s.data_to_send(5.5))
    assert out[0].get_type() == "HEARTBEAT" and out[0].type == mavlink2.MAV_TYPE_GCS
    assert out[1].get_type() == "COMMAND_LONG" and out[1].target_system == 1


def test_heartbeat_cadence_one_hertz(fc):
    s = MavlinkSession(SessionConfig(request_streams=False, link_timeout_s=1e9))
    s.receive_data(fc.heartbeat(), 0.0)
    sent_at = []
    for k in range(0, 1001):  # 10 s in 10 ms steps
        now = k * 0.01
        if parse_out(s.data_to_send(now)):
            sent_at.append(round(now, 2))
    assert sent_at == [float(k) for k in range(11)]


def _drive(s: MavlinkSession, fc: FakeFc, replies, t_end: float, dt: float = 0.05):
    """Run the session to t_end; ``replies(msg) -> list[bytes]`` plays the FC."""
    sent = []
    now = 0.0
    while now <= t_end:
        for m in parse_out(s.data_to_send(now)):
            sent.append((round(now, 3), m))
            for pkt in replies(m):
                s.receive_data(pkt, now)
        now += dt
    return sent


RATES = (("ATTITUDE", 50.0), ("SERVO_OUTPUT_RAW", 50.0), ("EXTENDED_SYS_STATE", 5.0))


def test_stream_setup_acked_sets_every_interval_without_fallback(fc):
    s = MavlinkSession(SessionConfig(stream_rates_hz=RATES))
    s.receive_data(fc.heartbeat(), 0.0)

    def replies(m):
        if m.get_type() == "COMMAND_LONG":
            return [fc.ack(m.command, mavlink2.MAV_RESULT_ACCEPTED)]
        return [fc.heartbeat()] if m.get_type() == "HEARTBEAT" else []

    sent = _drive(s, fc, replies, 3.0)
    cmds = [m for _, m in sent if m.get_type() == "COMMAND_LONG"]
    assert [(int(m.param1), m.param2) for m in cmds] == [
        (mavlink2.MAVLINK_MSG_ID_ATTITUDE, 20000.0), (mavlink2.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, 20000.0),
        (mavlink2.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 200000.0)]
    assert all(m.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL for m in cmds)
    assert not any(m.get_type() == "REQUEST_DATA_STREAM" for _, m in sent)
    assert s.stream_status.states == {n: "ok" for n, _ in RATES}


def test_stream_setup_no_ack_retries_then_falls_back_to_request_data_stream(fc):
    cfg = SessionConfig(stream_rates_hz=RATES, ack_timeout_s=0.5, ack_retries=2, link_timeout_s=1e9)
    s = MavlinkSession(cfg)
    s.receive_data(fc.heartbeat(), 0.0)
    sent = _drive(s, fc, lambda m: [], 8.0)
    cmds = [(t, int(m.param1), m.confirmation) for t, m in sent if m.get_type() == "COMMAND_LONG"]
    assert len(cmds) == 3 * 3  # each message tried 1 + 2 retries
    assert [c[2] for c in cmds[:3]] == [0, 1, 2]  # confirmation counts the retries
    assert cmds[1][0] - cmds[0][0] == pytest.approx(0.5, abs=0.06)
    rds = [m for _, m in sent if m.get_type() == "REQUEST_DATA_STREAM"]
    groups = {(m.req_stream_id, m.req_message_rate, m.start_stop) for m in rds}
    assert groups == {(mavlink2.MAV_DATA_STREAM_EXTRA1, 50, 1), (mavlink2.MAV_DATA_STREAM_RC_CHANNELS, 50, 1),
                      (mavlink2.MAV_DATA_STREAM_EXTENDED_STATUS, 5, 1)}
    assert s.stream_status.states == {n: "fallback" for n, _ in RATES}


def test_stream_setup_denied_for_one_unsupported_for_all(fc):
    s = MavlinkSession(SessionConfig(stream_rates_hz=RATES))
    s.receive_data(fc.heartbeat(), 0.0)
    answers = iter([mavlink2.MAV_RESULT_ACCEPTED, mavlink2.MAV_RESULT_DENIED, mavlink2.MAV_RESULT_ACCEPTED])

    def replies(m):
        if m.get_type() == "COMMAND_LONG":
            return [fc.ack(511, next(answers))]
        return []

    sent = _drive(s, fc, replies, 3.0)
    assert s.stream_status.states == {"ATTITUDE": "ok", "SERVO_OUTPUT_RAW": "fallback", "EXTENDED_SYS_STATE": "ok"}
    rds = {m.req_stream_id for _, m in sent if m.get_type() == "REQUEST_DATA_STREAM"}
    assert rds == {mavlink2.MAV_DATA_STREAM_RC_CHANNELS}

    s2 = MavlinkSession(SessionConfig(stream_rates_hz=RATES))
    s2.receive_data(fc.heartbeat(), 0.0)
    sent2 = _drive(s2, fc, lambda m: [fc.ack(511, mavlink2.MAV_RESULT_UNSUPPORTED)]
                   if m.get_type() == "COMMAND_LONG" else [], 3.0)
    assert sum(m.get_type() == "COMMAND_LONG" for _, m in sent2) == 1
    assert s2.stream_status.states == {n: "fallback" for n, _ in RATES}


def test_link_timeout_lost_then_restored_and_streams_requested_again(fc):
    s = MavlinkSession(SessionConfig(stream_rates_hz=(("ATTITUDE", 50.0),), link_timeout_s=2.0))
    s.receive_data(fc.heartbeat(), 0.0)
    parse_out(s.data_to_send(0.0))
    s.receive_data(fc.ack(511, 0), 0.1)
    s.events()
    assert [m.get_type() for m in parse_out(s.data_to_send(1.9))] == ["HEARTBEAT"]  # link still up
    assert not [e for e in s.events() if isinstance(e, LinkLost)]
    s.handle_timer(2.5)
    lost = [e for e in s.events() if isinstance(e, LinkLost)]
    assert len(lost) == 1 and lost[0].t_host_s == 2.5
    assert s.data_to_send(3.0) == b""  # nothing is sent into a dead link
    s.receive_data(fc.attitude(5000), 6.0)
    ev = s.events()
    assert isinstance(ev[0], LinkRestored) and ev[0].t_host_s == 6.0
    out = parse_out(s.data_to_send(6.0))
    assert ("COMMAND_LONG", 511) in [(m.get_type(), getattr(m, "command", None)) for m in out]


def test_link_down_from_driver_drops_partial_frame(fc):
    s = passive()
    pkt = fc.attitude(1000)
    s.receive_data(pkt[:10], 1.0)
    s.link_down(1.5, "port vanished")
    s.receive_data(pkt[10:] + fc.attitude(1020), 2.0)
    ev = s.events()
    assert [type(e).__name__ for e in ev] == ["LinkLost", "LinkRestored", "RawPacket", "Attitude"]
    assert ev[0].reason == "port vanished"
    assert s.stats.corrupt_bytes == len(pkt)


def test_unknown_message_id_is_not_trusted(fc):
    # a v2 frame with a message id outside the dialect cannot be CRC-checked: skipped, counted
    s = passive()
    frame = bytearray(fc.attitude(1000))
    frame[7], frame[8] = 0x34, 0x12
    events = feed_bytewise(s, bytes(frame) + fc.attitude(1020))
    assert [e.t_fc_s for e in events if isinstance(e, Attitude)] == pytest.approx([1.02])
    assert s.stats.corrupt_bytes == len(frame)


def test_config_rejects_unknown_message_name():
    with pytest.raises(ValueError, match="NOT_A_MESSAGE"):
        SessionConfig(stream_rates_hz=(("NOT_A_MESSAGE", 5.0),))
    assert math.isfinite(SessionConfig().link_timeout_s)


def test_session_module_is_pure():
    import ast
    from pathlib import Path

    import firmware_interface.codec as codec
    import firmware_interface.session as session

    for mod in (session, codec):
        tree = ast.parse(Path(mod.__file__).read_text())
        names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert not names & {"asyncio", "serial", "zenoh", "rerun", "time", "socket", "os"}, mod.__name__
        assert "open(" not in Path(mod.__file__).read_text()


def test_signed_link_records_but_does_not_decode_unverified_frames():
    from firmware_interface.signing import SignatureVerifier, SigningKey, make_signer

    key = SigningKey(bytes(range(32)))
    now = 1_790_000_000.0
    fc_mav = mavlink2.MAVLink(None, 1, 1)
    fc_mav.signing.secret_key = key.secret()
    fc_mav.signing.sign_outgoing = True
    fc_mav.signing.timestamp = int((now - 1420070400) * 1e5)
    good = bytes(fc_mav.heartbeat_encode(4, 3, 0x81, 0, 4).pack(fc_mav))
    fc_mav.seq += 1
    unsigned = FakeFc().attitude(1000)
    s = MavlinkSession(SessionConfig(stream_rates_hz=(("ATTITUDE", 50.0),)),
                       verifier=SignatureVerifier(key), signer=make_signer(key, now_unix_s=now))
    ev = feed_bytewise(s, good + unsigned, now)
    raws = [e for e in ev if isinstance(e, RawPacket)]
    assert [(r.msg_type, r.signature_ok) for r in raws] == [("HEARTBEAT", True), ("ATTITUDE", False)]
    assert [type(e).__name__ for e in ev if not isinstance(e, RawPacket)] == ["Heartbeat"]
    assert s.stats.unsigned_dropped == 1
    out = s.data_to_send(now + 0.1)
    rx = mavlink2.MAVLink(None, 1, 1)
    rx.signing.secret_key = key.secret()
    rx.signing.allow_unsigned_callback = lambda mav, msg_id: False
    msgs = rx.parse_buffer(out)
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "COMMAND_LONG"] and all(m.get_signed() for m in msgs)


def test_companion_computer_clock_on_the_same_sysid_is_not_a_reboot():
    fc, companion = FakeFc(1, 1), FakeFc(1, 191)
    s = passive()
    data = b""
    for k in range(50):
        data += fc.attitude(900_000 + 20 * k) + companion.attitude(5_000 + 20 * k)
    events = feed_bytewise(s, fc.heartbeat() + data)
    assert not any(isinstance(e, FcRebooted) for e in events) and s.stats.fc_reboots == 0
    by_src = {}
    for e in events:
        if isinstance(e, Attitude):
            by_src.setdefault(e.compid, []).append(e.t_fc_s)
    assert by_src[1][0] == pytest.approx(900.0) and by_src[191][0] == pytest.approx(5.0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(1, 80), min_size=1, max_size=40), st.binary(max_size=30))
def test_chunking_does_not_change_what_is_decoded(cuts, junk):
    fc = FakeFc()
    stream = b"".join(fc.attitude(1000 + 20 * k) for k in range(12)) + junk + fc.heartbeat() + fc.attitude(2000)
    ref = passive()
    ref.receive_data(stream, 5.0)
    expect = [e.data for e in ref.events() if isinstance(e, RawPacket)]
    s = passive()
    pos, k = 0, 0
    while pos < len(stream):
        n = cuts[k % len(cuts)]
        s.receive_data(stream[pos:pos + n], 5.0)
        pos += n
        k += 1
    got = [e.data for e in s.events() if isinstance(e, RawPacket)]
    assert got == expect
    # frames before the junk always; after it unless the junk opened a long frame still waiting for bytes
    assert len(expect) >= 12
    assert s.stats.corrupt_bytes == ref.stats.corrupt_bytes


def test_frames_held_behind_a_corrupt_length_byte_are_released_when_the_line_goes_quiet(fc):
    s = passive()
    bad = bytearray(fc.attitude(1000))
    bad[1] = 250  # claims 262 bytes: the parser waits for them
    tail = fc.attitude(1020) + fc.attitude(1040)
    s.receive_data(bytes(bad) + tail, 10.0)
    assert not [e for e in s.events() if isinstance(e, Attitude)]
    s.handle_timer(10.1)  # not stale yet
    assert not [e for e in s.events() if isinstance(e, Attitude)]
    s.handle_timer(10.3)
    assert [e.t_fc_s for e in s.events() if isinstance(e, Attitude)] == pytest.approx([1.02, 1.04])
    assert s.stats.corrupt_bytes == len(bad)
    # the same when the driver reports the link down
    s2 = passive()
    s2.receive_data(bytes(bad) + tail, 10.0)
    s2.link_down(10.05, "port vanished")
    ev = s2.events()
    assert [type(e).__name__ for e in ev if not isinstance(e, RawPacket)] == ["Attitude", "Attitude", "LinkLost"]


@settings(max_examples=100, deadline=None)
@given(st.binary(max_size=400), st.integers(1, 64))
def test_arbitrary_bytes_never_raise_and_are_all_accounted(noise, chunk):
    fc = FakeFc()
    hb, att = fc.heartbeat(), fc.attitude(1000)
    good = hb + att
    data = noise + good + bytes(300)  # trailing zeros force any pending candidate to resolve
    s = MavlinkSession()
    for i in range(0, len(data), chunk):
        s.receive_data(data[i:i + chunk], 1.0)
        s.data_to_send(1.0)
    raws = [e for e in s.events() if isinstance(e, RawPacket)]
    assert sum(len(r.data) for r in raws) + s.stats.corrupt_bytes + s._framer.buffered == len(data)
    assert [r.data for r in raws[-2:]] == [hb, att]  # noise never swallows the good frames after it


def test_reboot_seen_in_servo_time_usec_after_long_uptime_is_not_taken_for_a_wrap():
    fc = FakeFc()
    s = passive()
    up_us = 3_000_000_000  # 3000 s of uptime: past half of the uint32 µs period
    s.receive_data(fc.attitude(up_us // 1000), 500.0)
    s.receive_data(fc.pack(fc.mav.servo_output_raw_encode(up_us + 10_000, 0, 1500, 1500, 1500, 1500,
                                                          0, 0, 0, 0)), 500.01)
    s.receive_data(fc.pack(fc.mav.servo_output_raw_encode(2_000_000, 0, 1500, 1500, 1500, 1500,
                                                          0, 0, 0, 0)), 505.0)  # rebooted 2 s ago
    ev = s.events()
    servo = [e.t_fc_s for e in ev if isinstance(e, ServoOutputRaw)]
    assert servo[0] == pytest.approx(3000.01)
    assert [type(e).__name__ for e in ev].count("FcRebooted") == 1
    assert servo[1] == pytest.approx(3005.01, abs=0.02)  # continues by the host-measured gap


def test_late_sample_from_before_a_wrap_keeps_its_time():
    fc = FakeFc()
    s = passive()
    top = 2**32
    frames = b"".join(fc.pack(fc.mav.servo_output_raw_encode(us % top, 0, 1500, 1500, 1500, 1500, 0, 0, 0, 0))
                      for us in (top - 5000, top + 5000, top - 2000, top + 8000))
    ts = [e.t_fc_s for e in feed_bytewise(s, frames) if isinstance(e, ServoOutputRaw)]
    assert ts == pytest.approx([(top + d) * 1e-6 for d in (-5000, 5000, -2000, 8000)])
    assert s.stats.fc_reboots == 0


def test_brief_reboot_without_link_timeout_gets_streams_requested_again(fc):
    """An FC that reboots in under the link timeout and comes back sending heartbeats only (as
    ArduPilot does on a fresh boot) shows no backward time step; the silence of the requested
    streams is what tells, and the set-up is sent again once, not on every timer tick."""
    s = MavlinkSession(SessionConfig(stream_rates_hz=(("ATTITUDE", 50.0),), link_timeout_s=3.0))
    s.receive_data(fc.heartbeat(), 0.0)
    parse_out(s.data_to_send(0.0))
    s.receive_data(fc.ack(511, 0), 0.05)
    now, ms = 0.1, 100
    while now < 5.0:  # streams flowing
        s.receive_data(fc.attitude(ms), now)
        s.data_to_send(now)
        now, ms = round(now + 0.02, 3), ms + 20
    sent = []
    while now < 12.0:  # rebooted in 1 s: heartbeats every 0.5 s, no ATTITUDE
        if now >= 6.0 and round(now * 100) % 50 == 0:
            s.receive_data(fc.heartbeat(), now)
        sent += [(now, m) for m in parse_out(s.data_to_send(now))]
        now = round(now + 0.02, 3)
    assert not [e for e in s.events() if isinstance(e, LinkLost)]
    req = [t for t, m in sent if m.get_type() == "COMMAND_LONG" and m.command == 511]
    assert req and 7.0 <= req[0] <= 7.3  # 2 s after the last ATTITUDE
    assert s.stream_rerequests == 1
    # no ack and still no streams: ordinary retries and fallback, no re-request loop
    assert len(req) <= 1 + SessionConfig().ack_retries
