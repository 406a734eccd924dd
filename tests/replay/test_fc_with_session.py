"""The simulated FC protocol against the ground station's sans-IO MAVLink session.

No IO: both state machines are stepped on one 50 Hz clock (host time = FC time + offset), bytes
passed straight across. Checks that the ground station's stream setup and the FC agree, including
the REQUEST_DATA_STREAM fallback when SET_MESSAGE_INTERVAL is refused.
"""

from __future__ import annotations

import numpy as np

from firmware_interface.samples import Attitude, Heartbeat
from firmware_interface.session import MavlinkSession, SessionConfig
from hil_replay.fc import FcConfig, FcProtocol
from tests.replay.conftest import FakeHelicopter

RATES = (("ATTITUDE", 50.0), ("SERVO_OUTPUT_RAW", 25.0), ("GPS_RAW_INT", 5.0), ("SYS_STATUS", 1.0))


def _run(fc_config: FcConfig, duration_s: float = 40.0):
    fc = FcProtocol(fc_config)
    gcs = MavlinkSession(SessionConfig(stream_rates_hz=RATES))
    events = []
    offset_s = 1.7e9
    for frame in FakeHelicopter(duration_s, armed_s=((10.0, 30.0),)).frames():
        now = frame.t_boot_s + offset_s
        gcs.receive_data(b"".join(fc.on_frame(frame)), now)
        events += gcs.events()
        fc.receive_data(gcs.data_to_send(now))
    return fc, gcs, events


def _rate(events, cls, t_from_s: float) -> float:
    t = np.array([e.t_fc_s for e in events if isinstance(e, cls) and e.t_fc_s >= t_from_s])
    return (len(t) - 1) / (t[-1] - t[0])


def test_set_message_interval_path():
    fc, gcs, events = _run(FcConfig(packet_loss=0.0))
    assert set(gcs.stream_status.states.values()) == {"ok"}
    assert fc.intervals_s["ATTITUDE"] == 1 / 50 and fc.intervals_s["SYS_STATUS"] == 1.0
    assert abs(_rate(events, Attitude, 10.0) / 50 - 1) < 0.10
    armed = [e.armed for e in events if isinstance(e, Heartbeat)]
    assert armed.count(True) >= 15 and armed[0] is False


def test_fallback_to_request_data_stream():
    fc, gcs, events = _run(FcConfig(packet_loss=0.0, refuse_message_interval=True))
    states = gcs.stream_status.states
    assert set(states.values()) == {"fallback"}, states
    assert gcs.stream_status.data_stream_requests >= 1
    assert abs(_rate(events, Attitude, 20.0) / 50 - 1) < 0.10
