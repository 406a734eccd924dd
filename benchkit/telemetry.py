"""Synthetic MAVLink telemetry logs (.tlog) for the throughput benchmarks and the recorder tests.

Plain sines through pymavlink's encoder, no flight physics (the simulator, ``hil_replay.sim``, writes
flights with physics): what they measure is how fast bytes are framed, decoded and recorded.
"""

from __future__ import annotations

import math
import random
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.tlog import TlogWriter


def sine_flight_tlog(path: Path, duration_s: float, t0_unix_s: float = 1.7e9) -> int:
    """Write a synthetic flight, every telemetry stream at 50 Hz (GPS 5 Hz, status 2 Hz, heartbeat
    1 Hz), armed from 5 s to 5 s before the end; returns the packet count."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    n = 0
    with TlogWriter(path) as w:
        for k in range(int(round(duration_s * 50))):
            t = k / 50
            ms, us = int(t * 1000) + 5000, int(t * 1e6) + 5_000_000
            armed = 5.0 <= t < duration_s - 5.0
            s = math.sin(2 * math.pi * 0.3 * t)
            msgs = [
                mav.attitude_encode(ms, 0.05 * s, -0.03 * s, 1.0, 0.1 * s, 0.05 * s, 0.01),
                mav.servo_output_raw_encode(us & 0xFFFFFFFF, 0, 1500 + int(40 * s), 1500 - int(30 * s),
                                            1560, 1480, 0, 0, 0, 0),
                mav.raw_imu_encode(us, int(100 * s), 2, -1000, 3, 4, 5, 100, 200, 300),
                mav.local_position_ned_encode(ms, s, 0.5 * s, -2.0, 0.3 * s, 0.1, 0.0),
                mav.global_position_int_encode(ms, 473977420, 85455940, 500000, 2000, 30, 10, 0, 9000),
            ]
            if k % 10 == 0:
                msgs.append(mav.gps_raw_int_encode(us, 3, 473977420, 85455940, 500000, 100, 100, 30,
                                                   9000, 12))
            if k % 25 == 0:
                msgs.append(mav.sys_status_encode(0, 0, 0, 500, 16000, 1000, 90, 0, 0, 0, 0, 0, 0))
                msgs.append(mav.extended_sys_state_encode(0, 2 if armed else 1))
            if k % 50 == 0:
                base = (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0) | 1
                msgs.append(mav.heartbeat_encode(mavlink.MAV_TYPE_HELICOPTER,
                                                 mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base, 0, 4))
            for j, m in enumerate(msgs):
                w.write(m.pack(mav), t0_unix_s + t + 1e-4 * j)
                mav.seq = (mav.seq + 1) % 256
                n += 1
    return n


def jittered_flight_tlog(path: Path, duration_s: float = 300.0, seed: int = 0) -> int:
    """Write a synthetic flight (attitude, servo, IMU, local position at 50 Hz, global position
    10 Hz, GPS and extended state 5 Hz, heartbeat and status 1 Hz) with up to 2 ms of random jitter
    on the log time stamps, armed from 10 s to 10 s before the end; returns the packet count."""
    rng = random.Random(seed)
    mav = mavlink.MAVLink(None, 1, 1)
    t0 = 1.7e9
    n = 0
    with TlogWriter(path) as w:
        def put(msg, t_s: float) -> None:
            nonlocal n
            w.write(msg.pack(mav), t0 + t_s + 0.002 * rng.random())
            mav.seq = (mav.seq + 1) & 0xFF
            n += 1

        for k in range(int(duration_s * 50)):
            t = k / 50.0
            ms = int(t * 1000) + 1000
            armed = 10.0 < t < duration_s - 10.0
            a = math.sin(t)
            if k % 50 == 0:
                put(mav.heartbeat_encode(4, 3, 0x81 if armed else 0x01, 0, 4), t)
                put(mav.sys_status_encode(0, 0, 0, 200, 16800, 1500, 80, 0, 0, 0, 0, 0, 90), t)
            if k % 10 == 0:
                put(mav.gps_raw_int_encode(ms * 1000, 3, 473977420, 85455940, 500000, 100, 100, 50, 9000, 12), t)
                put(mav.extended_sys_state_encode(0, 2 if armed else 1), t)
            if k % 5 == 0:
                put(mav.global_position_int_encode(ms, 473977420, 85455940, 500000, 2000, 10, -5, 1, 9000), t)
            put(mav.attitude_encode(ms, 0.1 * a, -0.05 * a, 1.0, 0.2 * a, 0.1, -0.01), t)
            put(mav.servo_output_raw_encode(ms * 1000, 0, 1500 + int(100 * a), 1500, 1600, 1480,
                                            0, 0, 0, 0), t)
            put(mav.raw_imu_encode(ms * 1000, 10, -20, -1000, 5, -3, 2, 200, 100, -300), t)
            put(mav.local_position_ned_encode(ms, a, 0.5, -2.0, 0.3 * a, 0.1, -0.05), t)
    return n
