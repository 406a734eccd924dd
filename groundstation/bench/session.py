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
import statistics
import tempfile
import time
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from benchkit.telemetry import jittered_flight_tlog
from firmware_interface.readers import load_log
from firmware_interface.session import MavlinkSession, SessionConfig
from firmware_interface.tlogread import scan_tlog

HELP = "MAVLink session parse+decode throughput (messages/s) vs bare pymavlink parse_buffer"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--file", type=Path, default=None, help="a .tlog (default: synthesize ~5 min of 50 Hz telemetry)")
    p.add_argument("--runs", type=int, default=5, help="runs per figure (median printed)")
    p.add_argument("--duration", type=float, default=300.0, help="length of the synthetic flight (s)")


def run(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        path = args.file
        if path is None:
            path = Path(tmp) / "synthetic.tlog"
            jittered_flight_tlog(path, args.duration)
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
