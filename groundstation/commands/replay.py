"""``groundstation replay FILE.tlog``: serve a recorded link on a virtual serial port.

Prints the port path (one line on stdout, flushed) and serves the log with its original timing,
``--speed`` times faster, with optional fault injection, until the log ends or Ctrl-C. A summary
goes to stderr at the end (and, with ``--report``, the per-packet report as JSON). The work is
done by :class:`hil_replay.player.TlogPlayer` on a :class:`hil_replay.pty.VirtualSerialPort`.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from hil_replay.player import TlogPlayer, read_tlog_packets
from hil_replay.pty import VirtualSerialPort


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("tlog", type=Path, help="the .tlog file to replay")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="replay speed factor (1 = original timing; 0 or inf = as fast as read)")
    parser.add_argument("--corrupt", type=float, default=0.0, metavar="RATE",
                        help="probability per byte of a flipped bit (e.g. 0.01)")
    parser.add_argument("--drop", type=float, default=0.0, metavar="RATE",
                        help="probability per packet of dropping it")
    parser.add_argument("--unplug-at", type=float, default=None, metavar="S",
                        help="unplug the port at this replay time (s of log time)")
    parser.add_argument("--unplug-for", type=float, default=3.0, metavar="S",
                        help="how long the port stays unplugged (s of log time, default 3)")
    parser.add_argument("--link-path", type=Path, default=None,
                        help="symlink path for the port (default: a new /tmp/gs-replay-*/ttyFC)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fault injection")
    parser.add_argument("--no-wait", action="store_true",
                        help="start at once instead of waiting for a reader to open the port")
    parser.add_argument("--max-gap", type=float, default=None, metavar="S",
                        help="shorten pauses longer than S seconds of log time (default: keep them)")
    parser.add_argument("--report", type=Path, default=None,
                        help="write the per-packet replay report (JSON) to this file")


def run(args: argparse.Namespace) -> int:
    if args.speed < 0 or math.isnan(args.speed):
        raise ValueError(f"--speed: {args.speed} must be >= 0")
    for flag, rate in (("--corrupt", args.corrupt), ("--drop", args.drop)):
        if not 0.0 <= rate < 1.0:
            raise ValueError(f"{flag}: {rate} not in [0, 1)")
    if args.unplug_at is not None and (args.unplug_at < 0 or args.unplug_for < 0):
        raise ValueError("--unplug-at/--unplug-for: must be >= 0")
    if args.max_gap is not None and not args.max_gap > 0:
        raise ValueError(f"--max-gap: {args.max_gap} must be > 0")
    if not args.tlog.is_file():
        raise FileNotFoundError(f"{args.tlog}: no such file")
    packets = read_tlog_packets(args.tlog)  # bad input fails here, before a port exists

    with VirtualSerialPort(args.link_path) as port:
        player = TlogPlayer(packets, port, speed=args.speed, corrupt_rate=args.corrupt,
                            drop_rate=args.drop, unplug_at_s=args.unplug_at,
                            unplug_for_s=args.unplug_for, seed=args.seed,
                            wait_for_reader=not args.no_wait, max_gap_s=args.max_gap)
        print(port.path, flush=True)
        interrupted = False
        try:
            rep = player.run()
        except KeyboardInterrupt:
            interrupted = True
            rep = player.report
        finally:
            if args.report is not None:
                args.report.write_text(player.report.to_json())
    sent = len(rep.intact) + len(rep.corrupted)
    print(f"replay {args.tlog}: {sent}/{rep.n_packets} packets sent ({len(rep.corrupted)} corrupted, "
          f"{rep.corrupt_bytes} bytes), {len(rep.dropped)} dropped, {len(rep.unplugged)} in unplug gap; "
          f"{rep.log_s:.1f} s of log in {rep.wall_s:.1f} s"
          f"{' (interrupted)' if interrupted else ''}", file=sys.stderr, flush=True)
    return 130 if interrupted else 0
