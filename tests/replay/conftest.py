"""Fixtures for the replay tests: a stand-in helicopter frame source and a pyserial GCS reader.

The helicopter is the outside world, so a tiny fake of it is allowed here; everything between it
and the ground station (pty, pyserial, MAVLink bytes via pymavlink) is real.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import pytest
import serial
from pymavlink.dialects.v20 import ardupilotmega as mavlink

# native rates of the stand-in telemetry (Hz)
NATIVE_RATE_HZ = {
    "ATTITUDE": 50, "SERVO_OUTPUT_RAW": 50, "RAW_IMU": 50, "LOCAL_POSITION_NED": 50,
    "GLOBAL_POSITION_INT": 50, "GPS_RAW_INT": 5, "SYS_STATUS": 2, "EXTENDED_SYS_STATE": 5,
}


@dataclass(frozen=True)
class FakeFrame:
    k: int
    t_boot_s: float
    armed: bool
    flight_index: int | None
    available: tuple[str, ...]

    def build(self, name: str, mav: mavlink.MAVLink):
        ms = int(round(self.t_boot_s * 1000))
        us = int(round(self.t_boot_s * 1e6))
        if name == "ATTITUDE":
            return mav.attitude_encode(ms, 0.01, -0.02, 1.0, 0.001, 0.002, 0.003)
        if name == "SERVO_OUTPUT_RAW":
            return mav.servo_output_raw_encode(us & 0xFFFFFFFF, 0, 1500, 1500, 1560 + self.k % 7, 1480,
                                               0, 0, 0, 0)
        if name == "RAW_IMU":
            return mav.raw_imu_encode(us, 1, 2, -1000, 3, 4, 5, 100, 200, 300)
        if name == "LOCAL_POSITION_NED":
            return mav.local_position_ned_encode(ms, 0.0, 0.0, -1.0, 0.1, 0.0, 0.0)
        if name == "GLOBAL_POSITION_INT":
            return mav.global_position_int_encode(ms, 473977420, 85455940, 500000, 1000, 10, 0, 0, 9000)
        if name == "GPS_RAW_INT":
            return mav.gps_raw_int_encode(us, 3, 473977420, 85455940, 500000, 100, 100, 10, 9000, 12)
        if name == "SYS_STATUS":
            return mav.sys_status_encode(0, 0, 0, 500, 16000, 1000, 90, 0, 0, 0, 0, 0, 0)
        if name == "EXTENDED_SYS_STATE":
            landed = mavlink.MAV_LANDED_STATE_IN_AIR if self.armed else mavlink.MAV_LANDED_STATE_ON_GROUND
            return mav.extended_sys_state_encode(0, landed)
        raise KeyError(name)


class FakeHelicopter:
    """50 Hz frames on an FC clock starting at ``t0_s``; armed in ``armed_s`` intervals."""

    def __init__(self, duration_s: float, armed_s: tuple[tuple[float, float], ...] = (), t0_s: float = 3.0):
        self.duration_s = duration_s
        self.armed_s = armed_s
        self.t0_s = t0_s

    def frames(self):
        n = int(round(self.duration_s * 50))
        for k in range(n):
            t = self.t0_s + k / 50
            flight = next((i for i, (a, b) in enumerate(self.armed_s) if a <= t - self.t0_s < b), None)
            avail = tuple(name for name, r in NATIVE_RATE_HZ.items() if k % (50 // r) == 0)
            yield FakeFrame(k, t, flight is not None, flight, avail)


class GcsReader:
    """A pyserial ground-station stand-in: collects every decoded message on a thread."""

    def __init__(self, path: str, baud: int = 921600) -> None:
        self.ser = serial.Serial(path, baud, timeout=0.02)
        self.parser = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self.parser.robust_parsing = True
        self.out = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self.msgs: list = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.ser.read(max(1, self.ser.in_waiting))
            except (serial.SerialException, OSError):
                return
            if data:
                msgs = self.parser.parse_buffer(data) or []
                with self._lock:
                    self.msgs.extend(m for m in msgs if m.get_type() != "BAD_DATA")

    def send(self, msg) -> None:
        self.ser.write(msg.pack(self.out))
        self.out.seq = (self.out.seq + 1) % 256

    def snapshot(self) -> list:
        with self._lock:
            return list(self.msgs)

    def wait_for(self, pred, timeout_s: float = 10.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for m in self.snapshot():
                if pred(m):
                    return m
            time.sleep(0.01)
        raise AssertionError("expected message never arrived")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.ser.close()


@pytest.fixture
def fake_heli():
    return FakeHelicopter


def make_tlog(path, duration_s: float = 2.0, rate_hz: float = 50.0, t0_unix_s: float = 1.7e9) -> list[bytes]:
    """A .tlog of ATTITUDE + SERVO_OUTPUT_RAW at ``rate_hz`` and HEARTBEAT at 1 Hz; returns packets."""
    from firmware_interface.tlog import TlogWriter

    heli = FakeHelicopter(duration_s, armed_s=((0.5, duration_s),), t0_s=10.0)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    packets = []
    step = int(round(50 / rate_hz))
    with TlogWriter(path) as w:
        for fr in heli.frames():
            if fr.k % step:
                continue
            msgs = [fr.build("ATTITUDE", mav), fr.build("SERVO_OUTPUT_RAW", mav)]
            if fr.k % 50 == 0:
                base = mavlink.MAV_MODE_FLAG_SAFETY_ARMED if fr.armed else 0
                msgs.insert(0, mav.heartbeat_encode(mavlink.MAV_TYPE_HELICOPTER,
                                                    mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base, 0, 4))
            for j, m in enumerate(msgs):
                buf = m.pack(mav)
                mav.seq = (mav.seq + 1) % 256
                w.write(buf, t0_unix_s + fr.t_boot_s - 10.0 + 2e-4 * j)
                packets.append(buf)
    return packets


class RawReconnectingReader:
    """Reads raw bytes from a serial path on a thread, reopening it after an unplug."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.chunks: list[tuple[float, bytes]] = []
        self.connections = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ser = serial.Serial(self.path, 921600, timeout=0.02)
            except (serial.SerialException, OSError):
                time.sleep(0.01)
                continue
            self.connections += 1
            try:
                while not self._stop.is_set():
                    # read what is there (at least 1 byte): pyserial's read(n) keeps what it has
                    # gathered while waiting for more and loses it if the port vanishes meanwhile
                    data = ser.read(max(1, ser.in_waiting))
                    if data:
                        self.chunks.append((time.monotonic(), data))
            except (serial.SerialException, OSError):
                pass
            finally:
                ser.close()

    @property
    def data(self) -> bytes:
        return b"".join(c for _, c in self.chunks)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
