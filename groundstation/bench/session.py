"""``groundstation bench session [--file X.tlog]``: MAVLink session parse+decode throughput.

Takes the packets of a .tlog (default: a synthetic ~5 min flight of pymavlink-encoded 50 Hz
telemetry: ATTITUDE, SERVO_OUTPUT_RAW, RAW_IMU, LOCAL_POSITION_NED at 50 Hz, GLOBAL_POSITION_INT
10 Hz, GPS_RAW_INT and EXTENDED_SYS_STATE 5 Hz, SYS_STATUS and HEARTBEAT 1 Hz), joins them into one
byte stream as a serial link would deliver it, and times, on one core, median of ``--runs``:

* ``session``: :meth:`MavlinkSession.receive_data` in 4 KiB chunks + :meth:`events` (framing, CRC,
  typed events, clock, loss accounting) — target >= 40,000 messages/s;
* ``pymavlink``: bare ``MAVLink.parse_buffer`` on the same chunks (reference);
* ``load_log``: the whole .tlog reader (record scan + session decode + columns).
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time
from pathlib import Path

HELP = "MAVLink session parse+decode throughput (messages/s) vs bare pymavlink parse_buffer"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--file", type=Path, default=None, help="a .tlog (default: synthesize ~5 min of 50 Hz telemetry)")
    p.add_argument("--runs", type=int, default=5, help="runs per figure (median printed)")
    p.add_argument("--duration", type=float, default=300.0, help="length of the synthetic flight (s)")


def synth_tlog(path: Path, duration_s: float = 300.0, seed: int = 0) -> int:
    """Write a synthetic 50 Hz full-telemetry .tlog; returns the packet count."""
    import random

    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from firmware_interface.tlog import TlogWriter

    rng = random.Random(seed)
    mav = mavlink2.MAVLink(None, 1, 1)
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


def run(args: argparse.Namespace) -> int:
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from firmware_interface.readers import load_log
    from firmware_interface.session import MavlinkSession, SessionConfig
    from firmware_interface.tlogread import scan_tlog

    with tempfile.TemporaryDirectory() as tmp:
        path = args.file
        if path is None:
            path = Path(tmp) / "synthetic.tlog"
            synth_tlog(path, args.duration)
        data = path.read_bytes()
        stream = b"".join(pkt for _, pkt in scan_tlog(data))
        chunks = [stream[i:i + 4096] for i in range(0, len(stream), 4096)]

        def t_session() -> tuple[float, int]:
            s = MavlinkSession(SessionConfig(request_streams=False, send_heartbeat=False))
            t0 = time.perf_counter()
            now = 1.7e9
            for c in chunks:
                s.receive_data(c, now)
                s.events()
                now += 0.01
            return time.perf_counter() - t0, s.stats.packets

        def t_pymavlink() -> tuple[float, int]:
            m = mavlink2.MAVLink(None)
            m.robust_parsing = True
            n = 0
            t0 = time.perf_counter()
            for c in chunks:
                r = m.parse_buffer(c)
                if r:
                    n += len(r)
            return time.perf_counter() - t0, n

        def t_load() -> tuple[float, int]:
            t0 = time.perf_counter()
            log = load_log(path)
            return time.perf_counter() - t0, log.stats.packets

        what = str(path) if args.file else f"synthetic {args.duration:.0f} s flight"
        print(f"bench session: {what}, {len(data) / 1e6:.1f} MB")
        # runs interleaved so a busy machine slows every contender alike
        fns = (("session", t_session), ("pymavlink", t_pymavlink), ("load_log", t_load))
        rates: dict[str, list[float]] = {name: [] for name, _ in fns}
        counts: dict[str, int] = {}
        for _ in range(args.runs):
            for name, fn in fns:
                dt, counts[name] = fn()
                rates[name].append(counts[name] / dt)
        res = {name: statistics.median(r) for name, r in rates.items()}
        for name, _ in fns:
            print(f"  {name:10s} {res[name]:10,.0f} messages/s  (median of {args.runs}, {counts[name]} messages)")
        ratios = [a / b for a, b in zip(rates["session"], rates["pymavlink"], strict=True)]
        print(f"  ratio session/pymavlink = {statistics.median(ratios):.2f} (median of per-run ratios; "
              f"target: session >= 40,000 messages/s)")
    return 0
