"""``groundstation bench simulate``: wall time to simulate ten minutes of flight into a .tlog.

Flies :func:`hil_replay.sim.write_tlog` (nonlinear model at 200 Hz RK4, pilot, card, all telemetry
at their native rates, or ``--rates default``) for ``--minutes`` of armed flight, ``--repeat`` times, and prints the
median wall and CPU time, the real-time factor and the packet count. Target: < 10 s for 10 minutes on one core.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from hil_replay.sim import parse_effect, write_tlog
from hil_replay.sim.telemetry import NATIVE_RATE_HZ

HELP = "time ten minutes of simulated flight written to .tlog (median of 3)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--minutes", type=float, default=10.0, help="armed flight time to simulate (min)")
    parser.add_argument("--repeat", type=int, default=3, help="runs (the median is reported)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--effect", action="append", default=[], help="effects to inject (as in simulate)")
    parser.add_argument("--rates", choices=("native", "default"), default="native",
                        help="native: every message at its native rate (50 Hz for most); default: write_tlog's rates")


def run(args: argparse.Namespace) -> int:
    if args.repeat < 1 or not args.minutes > 0.5:
        raise ValueError("--repeat must be >= 1 and --minutes > 0.5")
    effects = tuple(parse_effect(e) for e in args.effect)
    times, cpu, packets, fc_s, size = [], [], 0, 0.0, 0
    with tempfile.TemporaryDirectory() as td:
        for i in range(args.repeat):
            path = Path(td) / f"bench{i}.tlog"
            t0, c0 = time.perf_counter(), time.process_time()
            truth = write_tlog(path, seed=args.seed, flights=1, effects=effects, flight_duration_s=args.minutes * 60.0,
                               rates_hz=NATIVE_RATE_HZ if args.rates == "native" else None)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            packets = truth["packets_written"]
            fc_s = truth["flights"][-1]["end_fc_s"] + 2.0
            size = path.stat().st_size
    med = statistics.median(times)
    print(f"simulate: {fc_s:.0f} s of FC time ({args.minutes:g} min armed), {packets} packets, {size / 1e6:.1f} MB "
          f"({args.rates} rates)")
    print(f"  wall time median {med:.2f} s over {args.repeat} runs (min {min(times):.2f}, max {max(times):.2f})")
    print(f"  CPU time median {statistics.median(cpu):.2f} s (single-threaded; wall > CPU means a busy machine)")
    print(f"  real-time factor {fc_s / med:.0f}x; target < 10 s for 10 min: {'PASS' if med < 10.0 else 'FAIL'}")
    return 0
