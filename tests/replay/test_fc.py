"""Simulated flight controller protocol over a real pty with a pyserial/pymavlink ground station."""

from __future__ import annotations

import asyncio
import os
import time

import numpy as np
import pytest
import serial
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from hil_replay.fc import FcConfig, FcProtocol, SimulatedFCThread, serve_simulated_fc
from tests.replay.conftest import FakeHelicopter, GcsReader, RawReconnectingReader


def _set_interval(gcs: GcsReader, msg_id: int, interval_us: float) -> None:
    gcs.send(gcs.out.command_long_encode(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                         msg_id, interval_us, 0, 0, 0, 0, 0))


def _wait_fc_time(fc: SimulatedFCThread, t_s: float, timeout_s: float = 30.0) -> None:
    """Wait until the FC clock reaches ``t_s`` (tests wait on FC time, not wall time)."""
    deadline = time.monotonic() + timeout_s
    while fc.stats.last_t_boot_s < t_s:
        assert time.monotonic() < deadline, "simulated FC stalled"
        time.sleep(0.01)


def _fc_times(msgs, kind: str) -> np.ndarray:
    return np.array([m.time_boot_ms / 1000 for m in msgs if m.get_type() == kind])


def test_heartbeats_only_until_asked_then_requested_rates():
    heli = FakeHelicopter(duration_s=60.0, armed_s=((5.0, 40.0),))
    with SimulatedFCThread(speed=10.0, session=heli, config=FcConfig(packet_loss=0.0)) as fc:
        gcs = GcsReader(fc.port_path)
        try:
            gcs.wait_for(lambda m: m.get_type() == "HEARTBEAT")
            _wait_fc_time(fc, fc.stats.last_t_boot_s + 3.0)  # 3 s of FC time with nobody asking
            before = gcs.snapshot()
            assert {m.get_type() for m in before} == {"HEARTBEAT"}
            hb = before[0]
            assert (hb.type, hb.autopilot) == (mavlink.MAV_TYPE_HELICOPTER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
            assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
            n_before = len(before)

            _set_interval(gcs, mavlink.MAVLINK_MSG_ID_ATTITUDE, 1e6 / 20)       # 20 Hz
            _set_interval(gcs, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 1e6 / 10)
            _set_interval(gcs, 9999, 1e6)                                         # unknown id
            acks = []
            deadline = time.monotonic() + 5
            while len(acks) < 3 and time.monotonic() < deadline:
                acks = [m for m in gcs.snapshot() if m.get_type() == "COMMAND_ACK"]
                time.sleep(0.01)
            assert [(a.command, a.result) for a in acks] == [
                (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_ACCEPTED),
                (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_ACCEPTED),
                (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_DENIED)]
            _wait_fc_time(fc, fc.stats.last_t_boot_s + 25.0)
            msgs = gcs.snapshot()[n_before:]
        finally:
            gcs.close()
    kinds = {m.get_type() for m in msgs}
    assert kinds == {"HEARTBEAT", "COMMAND_ACK", "ATTITUDE", "LOCAL_POSITION_NED"}
    for kind, rate_hz in (("ATTITUDE", 20.0), ("LOCAL_POSITION_NED", 10.0)):
        t = _fc_times(msgs, kind)
        assert len(t) > 100
        measured = (len(t) - 1) / (t[-1] - t[0])
        assert abs(measured / rate_hz - 1) < 0.10, (kind, measured)
    # heartbeats carry the armed flag of their frame (armed at FC time 8..43 s): date each heartbeat
    # by the ATTITUDE sent just before it in the same tick stream
    hbs = [m for m in gcs.msgs if m.get_type() == "HEARTBEAT"]
    assert not any(h.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED for h in hbs[:3])
    checked = 0
    t_last = None
    for m in gcs.msgs:
        if m.get_type() == "ATTITUDE":
            t_last = m.time_boot_ms / 1000
        elif m.get_type() == "HEARTBEAT" and t_last is not None:
            if min(abs(t_last - 8.0), abs(t_last - 43.0)) > 0.1:
                assert bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED) == (8.0 <= t_last < 43.0)
                checked += 1
    assert checked >= 20


def test_request_data_stream_fallback_when_interval_refused():
    heli = FakeHelicopter(duration_s=120.0)
    cfg = FcConfig(packet_loss=0.0, refuse_message_interval=True)
    with SimulatedFCThread(speed=10.0, session=heli, config=cfg) as fc:
        gcs = GcsReader(fc.port_path)
        try:
            gcs.wait_for(lambda m: m.get_type() == "HEARTBEAT")
            _set_interval(gcs, mavlink.MAVLINK_MSG_ID_ATTITUDE, 1e6 / 20)
            ack = gcs.wait_for(lambda m: m.get_type() == "COMMAND_ACK")
            assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
            time.sleep(0.2)
            assert not any(m.get_type() == "ATTITUDE" for m in gcs.snapshot())
            gcs.send(gcs.out.request_data_stream_encode(1, 1, mavlink.MAV_DATA_STREAM_EXTRA1, 25, 1))
            gcs.send(gcs.out.request_data_stream_encode(1, 1, mavlink.MAV_DATA_STREAM_EXTENDED_STATUS, 2, 1))
            gcs.wait_for(lambda m: m.get_type() == "ATTITUDE")
            _wait_fc_time(fc, fc.stats.last_t_boot_s + 20.0)
            gcs.send(gcs.out.request_data_stream_encode(1, 1, mavlink.MAV_DATA_STREAM_EXTRA1, 0, 0))

            def quiet_after_last_attitude() -> int:
                kinds = [m.get_type() for m in gcs.snapshot()]
                last = max(i for i, k in enumerate(kinds) if k == "ATTITUDE")
                return kinds[last:].count("HEARTBEAT")

            deadline = time.monotonic() + 10
            while quiet_after_last_attitude() < 4 and time.monotonic() < deadline:
                time.sleep(0.05)
            msgs = gcs.snapshot()
        finally:
            gcs.close()
    # stream stopped: 4 heartbeats (4 s of FC time, 100 ATTITUDE at 25 Hz) with no ATTITUDE
    assert quiet_after_last_attitude() >= 4
    t = _fc_times(msgs, "ATTITUDE")
    assert abs((len(t) - 1) / (t[-1] - t[0]) / 25.0 - 1) < 0.10
    kinds = {m.get_type() for m in msgs}
    assert {"SYS_STATUS", "GPS_RAW_INT", "EXTENDED_SYS_STATE"} <= kinds
    assert "RAW_IMU" not in kinds and "SERVO_OUTPUT_RAW" not in kinds


def _feed(proto: FcProtocol, gcs_mav: mavlink.MAVLink, msg) -> None:
    proto.receive_data(msg.pack(gcs_mav))


def test_protocol_request_message_disable_and_link_loss():
    heli = FakeHelicopter(duration_s=200.0)
    proto = FcProtocol(FcConfig(packet_loss=0.05, seed=3))
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    parser = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    frames = iter(heli.frames())
    out: list[bytes] = []
    for _ in range(10):
        out += proto.on_frame(next(frames))
    _feed(proto, gcs, gcs.command_long_encode(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                              mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 0, 0, 0, 0, 0, 0))
    _feed(proto, gcs, gcs.command_long_encode(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                              mavlink.MAVLINK_MSG_ID_RAW_IMU, 0, 0, 0, 0, 0, 0))
    _feed(proto, gcs, gcs.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                              1, 0, 0, 0, 0, 0, 0))
    _feed(proto, gcs, gcs.command_long_encode(7, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                              mavlink.MAVLINK_MSG_ID_ATTITUDE, 20000, 0, 0, 0, 0, 0))
    for _ in range(5000):
        out += proto.on_frame(next(frames))
    _feed(proto, gcs, gcs.command_long_encode(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                              mavlink.MAVLINK_MSG_ID_RAW_IMU, -1, 0, 0, 0, 0, 0))
    for _ in range(500):
        more = proto.on_frame(next(frames))
        out += more
    msgs = [m for m in parser.parse_buffer(b"".join(out)) or []]
    kinds = [m.get_type() for m in msgs]
    assert kinds.count("GPS_RAW_INT") == 1                    # one-shot
    assert "ATTITUDE" not in kinds                             # command for another system ignored
    acks = [(m.command, m.result) for m in msgs if m.get_type() == "COMMAND_ACK"]
    assert acks == [(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_RESULT_ACCEPTED),
                    (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_ACCEPTED),
                    (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_UNSUPPORTED),
                    (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_ACCEPTED)]
    imu_t = np.array([m.time_usec * 1e-6 for m in msgs if m.get_type() == "RAW_IMU"])
    # default rate (4 Hz) until disabled after frame 5010 (FC time 3 + 100.2 s), thinned by 5 % loss
    assert imu_t.max() < 3.0 + 5010 / 50
    assert abs(np.median(np.diff(imu_t)) - 0.25) < 0.01
    # link loss: seq gaps in the received stream match the loss counter, roughly 5 %
    seqs = np.array([m.get_seq() for m in msgs])
    steps = np.diff(seqs) % 256
    assert np.all(steps >= 1)
    encoded = proto.stats.packets_sent + proto.stats.packets_lost
    last_index = int(seqs[0] + steps.sum())
    missing = int(seqs[0]) + int(np.sum(steps - 1)) + (encoded - 1 - last_index)
    assert missing == proto.stats.packets_lost
    total = proto.stats.packets_lost + len(msgs)
    assert 0.03 < proto.stats.packets_lost / total < 0.07


def test_async_entry_point_runs_session_to_end_without_reader():
    paths: list[str] = []
    heli = FakeHelicopter(duration_s=20.0)
    stats = asyncio.run(serve_simulated_fc(speed=0, session=heli, on_ready=paths.append,
                                           config=FcConfig(idle_after_end=False, packet_loss=0.0)))
    assert stats.frames == 1000
    assert stats.packets_unheard == 20 and stats.bytes_sent == 0   # 20 heartbeats, nobody listening
    assert len(paths) == 1 and not os.path.lexists(paths[0])          # port removed at the end


def test_thread_keeps_heartbeating_after_the_session_ends():
    heli = FakeHelicopter(duration_s=1.0)
    with SimulatedFCThread(speed=0, session=heli, config=FcConfig(packet_loss=0.0)) as fc:
        gcs = GcsReader(fc.port_path)
        try:
            deadline = time.monotonic() + 30      # until a heartbeat and idle frames after the session came
            hbs: list = []
            while time.monotonic() < deadline and not (hbs and fc.stats.frames > 50):
                time.sleep(0.05)
                hbs = [m for m in gcs.snapshot() if m.get_type() == "HEARTBEAT"]
        finally:
            gcs.close()
        assert fc.is_alive()
    assert len(hbs) >= 1
    assert not any(h.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED for h in hbs)
    assert fc.stats.frames > 50  # idle frames kept coming at real time after the 50 session frames


def test_unplug_and_replug_while_serving():
    heli = FakeHelicopter(duration_s=600.0)
    with SimulatedFCThread(speed=5.0, session=heli, config=FcConfig(packet_loss=0.0)) as fc:
        reader = RawReconnectingReader(fc.port_path)
        try:
            deadline = time.monotonic() + 5
            while not reader.data and time.monotonic() < deadline:
                time.sleep(0.01)
            n_before = len(reader.data)
            assert n_before > 0
            fc.unplug(1.0)   # 5 s of FC time at 5x
            parser = mavlink.MAVLink(None)
            deadline = time.monotonic() + 30       # until the reader is back and a heartbeat came through
            after = b""
            while time.monotonic() < deadline and not (
                    reader.connections == 2
                    and any(m.get_type() == "HEARTBEAT" for m in mavlink.MAVLink(None).parse_buffer(after) or [])):
                time.sleep(0.05)
                after = bytes(reader.data[n_before:])
        finally:
            reader.close()
    assert reader.connections == 2
    parser = mavlink.MAVLink(None)
    assert any(m.get_type() == "HEARTBEAT" for m in parser.parse_buffer(after) or [])
    assert fc.stats.packets_unheard >= 1  # heartbeats while unplugged went nowhere


def test_stop_is_prompt_while_the_reader_does_not_read():
    heli = FakeHelicopter(duration_s=600.0)
    fc = SimulatedFCThread(speed=0, session=heli, config=FcConfig(packet_loss=0.0)).start()
    ser = serial.Serial(fc.port_path, 921600, timeout=0.1)  # opened, never read: the pty fills up
    try:
        gcs_mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        deadline = time.monotonic() + 5
        while fc.stats.frames < 100 and time.monotonic() < deadline:
            time.sleep(0.01)
        ser.write(gcs_mav.command_long_encode(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                              mavlink.MAVLINK_MSG_ID_RAW_IMU, 20000, 0, 0, 0, 0, 0).pack(gcs_mav))
        time.sleep(1.0)
        frames = fc.stats.frames
        time.sleep(0.3)
        assert fc.stats.frames == frames          # blocked by back-pressure, not racing ahead
        t0 = time.monotonic()
        fc.stop(timeout_s=2.0)                    # raises TimeoutError if the writer ignores stop
        assert time.monotonic() - t0 < 2.0
    finally:
        ser.close()


def test_reboot_restarts_clock_and_streams():
    heli = FakeHelicopter(duration_s=100.0, t0_s=30.0)
    proto = FcProtocol(FcConfig(packet_loss=0.0))
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    parser = mavlink.MAVLink(None)
    frames = iter(heli.frames())
    _feed(proto, gcs, gcs.command_long_encode(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                              mavlink.MAVLINK_MSG_ID_ATTITUDE, 1e5, 0, 0, 0, 0, 0))
    before = b"".join(b for _ in range(500) for b in proto.on_frame(next(frames)))   # 10 s
    proto.reboot(boot_s=2.0)
    silent = b"".join(b for _ in range(100) for b in proto.on_frame(next(frames)))   # 2 s
    after = b"".join(b for _ in range(250) for b in proto.on_frame(next(frames)))    # 5 s
    _feed(proto, gcs, gcs.command_long_encode(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                              mavlink.MAVLINK_MSG_ID_ATTITUDE, 1e5, 0, 0, 0, 0, 0))
    again = b"".join(b for _ in range(250) for b in proto.on_frame(next(frames)))
    m_before = parser.parse_buffer(before)
    assert silent == b""
    m_after = parser.parse_buffer(after)
    assert {m.get_type() for m in m_after} == {"HEARTBEAT"} and m_after[0].get_seq() == 0
    att_before = [m.time_boot_ms for m in m_before if m.get_type() == "ATTITUDE"]
    att_again = [m.time_boot_ms for m in parser.parse_buffer(again) if m.get_type() == "ATTITUDE"]
    assert att_before[0] >= 30_000 and len(att_again) >= 20
    assert 5_000 < att_again[0] < 6_000        # boot clock restarted: 0.5 s + 5 s after first contact
    assert proto.stats.reboots == 1


def test_line_noise_corrupts_bytes_at_the_configured_rate():
    heli = FakeHelicopter(duration_s=120.0)
    proto = FcProtocol(FcConfig(packet_loss=0.0, corrupt_rate=0.01, seed=4))
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    frames = iter(heli.frames())
    _feed(proto, gcs, gcs.command_long_encode(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                              mavlink.MAVLINK_MSG_ID_ATTITUDE, 20000, 0, 0, 0, 0, 0))
    out = [b for _ in range(6000) for b in proto.on_frame(next(frames))]
    n_bytes = sum(len(b) for b in out)
    st = proto.stats
    assert abs(st.corrupt_bytes - 0.01 * n_bytes) < 4 * np.sqrt(n_bytes * 0.01)
    # every corrupted packet fails its CRC (or turns into an unknown message id), every other decodes
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    bad = 0
    for pkt in out:
        msgs = parser.parse_buffer(pkt) or []
        bad += not any(m.get_type() != "BAD_DATA" and not m.get_type().startswith("UNKNOWN")
                       for m in msgs)
        parser.buf = bytearray()          # each packet on its own: no resync effects
        parser.buf_index = 0
    assert bad == st.packets_corrupted > 100


def test_bad_effect_fails_before_any_port_exists(tmp_path):
    link = tmp_path / "ttyFC"
    with pytest.raises(ValueError, match="bogus"):
        SimulatedFCThread(link_path=str(link), effects=("bogus:x=1",))
    assert not link.exists() and not link.is_symlink()
    with pytest.raises(ValueError, match="packet_loss"):
        FcConfig(packet_loss=1.5)


def test_stop_without_start_and_twice_closes_the_port():
    fc = SimulatedFCThread(session=FakeHelicopter(duration_s=1.0))
    path = fc.port_path
    assert os.path.islink(path)
    fc.stop()
    assert not os.path.lexists(path)
    fc2 = SimulatedFCThread(speed=0, session=FakeHelicopter(duration_s=1.0)).start()
    fc2.stop()
    fc2.stop()
    assert not os.path.lexists(fc2.port_path)
