"""``groundstation record --link URL --out DIR``: record the FC link until Ctrl-C / SIGTERM.

Opens the link (a serial port not plugged in yet is waited for: ``waiting for /dev/ttyUSB0`` at most
every 10 s), runs the MAVLink session (GCS heartbeat, stream requests unless ``--passive``) through
the link driver :class:`firmware_interface.link.LinkRunner`, writes ``session-*.tlog`` and
``flight-NN.tlog`` per armed interval, survives port loss (LinkLost, reconnect, same files). On exit the files are closed valid; a summary goes to stderr and one JSON
line to stdout: ``{"session_tlog", "flights", "packets", "corrupt_bytes", "bad_crc",
"packets_lost", "link_lost", "fc_reboots", "streams"}``.

A port that delivers only noise (e.g. the wrong baud rate) for ``--noise-timeout`` seconds is an
error (exit 2, what was recorded is kept). Leaves decoding beyond recording to the service.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import json
import signal
import sys
import time

from firmware_interface.errors import TransportError
from firmware_interface.link import LinkRunner
from firmware_interface.recorder import Recorder
from firmware_interface.samples import LinkLost
from firmware_interface.session import DEFAULT_STREAM_RATES_HZ, MavlinkSession, SessionConfig
from firmware_interface.transports import open_link


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--link", required=True, help="serial:///dev/ttyUSB0:921600, udpin://0.0.0.0:14550, tcp://host:5760")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--passive", action="store_true", help="send nothing (no heartbeat, no stream requests)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--rate", action="append", default=[], metavar="MSG=HZ",
                   help="stream rate request, repeatable (default: the ground station's set)")
    p.add_argument("--noise-timeout", type=float, default=10.0,
                   help="fail if the port sends bytes but no valid MAVLink for this long (s)")


def _rates(items: list[str]) -> tuple[tuple[str, float], ...]:
    if not items:
        return DEFAULT_STREAM_RATES_HZ
    out = []
    for it in items:
        name, sep, hz = it.partition("=")
        try:
            out.append((name.strip().upper(), float(hz)))
        except ValueError:
            raise ValueError(f"--rate {it!r}: expected MSG=HZ, e.g. ATTITUDE=50") from None
        if not sep:
            raise ValueError(f"--rate {it!r}: expected MSG=HZ, e.g. ATTITUDE=50")
    return tuple(out)


async def record(args: argparse.Namespace) -> dict:
    config = SessionConfig(stream_rates_hz=_rates(args.rate), request_streams=not args.passive,
                           send_heartbeat=not args.passive)
    session = MavlinkSession(config)
    recorder: Recorder | None = None
    lost = 0
    error: str | None = None

    def on_events(events: list) -> None:
        nonlocal lost
        assert recorder is not None
        recorder.handle(events)
        for ev in events:
            if type(ev) is LinkLost:
                lost += 1
                print(f"record: link lost ({ev.reason}); reconnecting", file=sys.stderr)

    runner = LinkRunner(functools.partial(open_link, args.link), session, on_events,
                        log=lambda m: print(f"record: {m}", file=sys.stderr))
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, runner.stop)
    task: asyncio.Future[None] | None = None
    try:
        await runner.connect()           # waits for a port not plugged in yet; Ctrl-C ends the wait
        recorder = Recorder(args.out)
        task = asyncio.ensure_future(runner.run())
        t0 = time.monotonic()
        while not task.done():
            await asyncio.wait({task}, timeout=0.2)
            recorder.tick()
            elapsed = time.monotonic() - t0
            if args.duration is not None and elapsed >= args.duration:
                runner.stop()
            if (session.stats.packets == 0 and runner.bytes_received >= 256
                    and elapsed >= args.noise_timeout):
                error = (f"{args.link}: {runner.bytes_received} bytes in {elapsed:.0f} s but no valid MAVLink "
                         "frame (wrong baud rate or not a MAVLink port?)")
                runner.stop()
        await task
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        if task is not None and not task.done():
            task.cancel()
        if recorder is not None:
            recorder.close()
        if runner.link is not None:
            await runner.link.close()
    if recorder is None:
        recorder = Recorder(args.out)    # stopped while waiting for the port: an empty, valid session file
        recorder.close()
    st = session.stats
    summary = {
        "session_tlog": str(recorder.session_path),
        "flights": [str(p) for p in recorder.flight_paths],
        "packets": st.packets,
        "corrupt_bytes": st.corrupt_bytes,
        "bad_crc": st.bad_crc,
        "packets_lost": st.packets_lost,
        "link_lost": lost,
        "fc_reboots": st.fc_reboots,
        "streams": session.stream_status.states,
    }
    if error is not None:
        summary["error"] = error
    return summary


def run(args: argparse.Namespace) -> int:
    summary = asyncio.run(record(args))
    print(f"record: session {summary['session_tlog']}; flights {summary['flights'] or 'none'}; "
          f"{summary['packets']} packets, {summary['corrupt_bytes']} corrupt bytes, {summary['bad_crc']} bad CRC, "
          f"{summary['packets_lost']} lost (seq), link lost {summary['link_lost']}x", file=sys.stderr)
    print(json.dumps(summary), flush=True)
    if "error" in summary:
        raise TransportError(summary["error"])
    return 0
