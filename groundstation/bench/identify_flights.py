"""``groundstation bench identify-flights [--flights 1,2,4] [--jobs 1] [--repeat 1] [--diagnose]``.

What ``groundstation identify`` (and with ``--diagnose`` ``groundstation diagnose``) costs on N
flights of one aircraft identified together (one simulated log per flight, ``hil_replay.sim``, seeds
1..N): each run is the real command in a fresh child process, measured by the kernel
(``os.wait4``): wall time, user and system CPU seconds of the command and the worker processes it
waited for, and the peak resident memory of the largest of them. Prints one row per N with the
cost per flight, and the ratios to one flight (linear cost: CPU per flight constant; bounded memory:
peak memory well under N times one flight's).

``--jobs J`` is passed to the command (worker processes; 1 = all in one process). On a shared
machine compare CPU seconds rather than wall time; the load average is printed with each row.
The command runs from the installed package, or from the checkout ``$PYTHONPATH`` names first
(that is how a before/after pair is measured).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from hil_replay.sim import write_tlog

HELP = "identify (and diagnose) on 1, 2, 4 ... flights together: wall, user/sys CPU and peak memory per run"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--flights", default="1,2,4", help="comma-separated numbers of flights")
    parser.add_argument("--duration-s", type=float, default=60.0, help="armed time per simulated flight")
    parser.add_argument("--jobs", type=int, default=None,
                        help="--jobs of the command (default: not given, the command's default)")
    parser.add_argument("--repeat", type=int, default=1, help="runs per N (medians are printed)")
    parser.add_argument("--diagnose", action="store_true", help="time `diagnose` (identify + gap report) instead")
    parser.add_argument("--keep", type=Path, default=None, help="write the simulated logs here and keep them")


def _simulate(folder: Path, n: int, duration_s: float) -> list[Path]:
    paths = []
    for k in range(n):
        p = folder / f"flight{k + 1:02d}.tlog"
        if not p.exists():
            write_tlog(p, seed=k + 1, flights=1, flight_duration_s=duration_s)
        paths.append(p)
    return paths


def _measure(argv: list[str]) -> dict[str, float]:
    """Run ``argv`` as a child; wall, user, sys (s) and peak RSS (MB) from the kernel's accounting."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    assert proc.stderr is not None
    err = proc.stderr.read()
    _, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed: {err.decode(errors='replace').strip().splitlines()[-1:]}")
    return {"wall_s": wall, "user_s": ru.ru_utime, "sys_s": ru.ru_stime, "peak_mb": ru.ru_maxrss / 1024.0,
            "load1": os.getloadavg()[0]}


def _command(logs: list[Path], out: Path, args: argparse.Namespace) -> list[str]:
    base = [sys.executable, "-m", "groundstation.cli"]
    jobs = [] if args.jobs is None else ["--jobs", str(args.jobs)]
    if args.diagnose:
        return base + ["diagnose", *map(str, logs), "--out", str(out), "--quiet", *jobs]
    return base + ["identify", *map(str, logs), "--out", str(out), "--no-plot", "--quiet", *jobs]


def run(args: argparse.Namespace) -> int:
    ns = sorted({int(x) for x in args.flights.split(",") if x.strip()})
    if not ns or ns[0] < 1:
        raise ValueError(f"--flights {args.flights!r}: give positive numbers of flights, e.g. 1,2,4")
    with tempfile.TemporaryDirectory(prefix="bench-identify-flights-") as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        logs = _simulate(folder, ns[-1], args.duration_s)
        rows: dict[int, dict[str, Any]] = {}
        what = "diagnose" if args.diagnose else "identify"
        print(f"{what} --jobs {args.jobs or 'default'} on N simulated flights of {args.duration_s:g} s "
              f"(medians of {args.repeat}; CPU = user + sys of the command and its workers)")
        print(f"{'N':>3} {'wall s':>8} {'user s':>8} {'sys s':>7} {'CPU/flight s':>13} {'sys/flight s':>13} "
              f"{'peak MB':>8} {'load':>5}")
        for n in ns:
            runs = [_measure(_command(logs[:n], Path(tmp) / f"out{n}.json", args)) for _ in range(args.repeat)]
            med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
            rows[n] = med
            cpu = med["user_s"] + med["sys_s"]
            print(f"{n:>3} {med['wall_s']:>8.1f} {med['user_s']:>8.1f} {med['sys_s']:>7.2f} {cpu / n:>13.2f} "
                  f"{med['sys_s'] / n:>13.3f} {med['peak_mb']:>8.0f} {med['load1']:>5.1f}", flush=True)
        one = rows[ns[0]]
        cpu1 = (one["user_s"] + one["sys_s"]) / ns[0]
        for n in ns[1:]:
            r = rows[n]
            print(f"N={n} vs N={ns[0]}: CPU per flight x{(r['user_s'] + r['sys_s']) / n / cpu1:.2f}, "
                  f"sys per flight x{r['sys_s'] / n / max(one['sys_s'] / ns[0], 1e-9):.2f}, "
                  f"peak memory x{r['peak_mb'] / one['peak_mb']:.2f} for x{n / ns[0]:g} the data")
    return 0
