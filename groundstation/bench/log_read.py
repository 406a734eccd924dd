"""``groundstation bench log-read``: reading a large dataflash ``.bin`` and a large ULog ``.ulg``.

Generates both files in a temporary directory (removed afterwards):

* a dataflash log of ``--size-mb`` with the records an ArduPilot helicopter logs at 400 Hz (IMU,
  ATT, RATE, RCOU, HELI) and 10 Hz (XKF1), FMT-described, built with numpy;
* a ULog of about ``--ulog-mb``: the real pyulog sample log's topics repeated end to end with their
  timestamps moved on, written by pyulog itself.

Then times, on the same files in one run: this project's reader (``load_log``, what identify,
validate and diagnose use; for a ULog also with every topic decoded, as log-info reads it),
pymavlink's ``mavlogdump.py --quiet`` (every record decoded) and pyulog's ``ulog_info``. MB/s =
file size / wall time (target >= 20 MB/s for our reader); ``--repeat N`` gives the median of N
runs of each. Each external tool runs as its own process (its start-up included) with
``--tool-timeout-s``; ``--only bin|ulog`` times one kind of log.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from benchkit import onboard_logs
from firmware_interface.readers import load_log

HELP = "read a 100 MB dataflash and ULog log: MB/s of our reader vs mavlogdump and ulog_info"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--size-mb", type=float, default=100.0, help="dataflash log size (MB)")
    p.add_argument("--ulog-mb", type=float, default=100.0, help="ULog size (MB, approximate)")
    p.add_argument("--tool-timeout-s", type=float, default=900.0, help="give up on an external tool after this")
    p.add_argument("--no-tools", action="store_true", help="time only this project's reader")
    p.add_argument("--only", choices=("bin", "ulog"), default=None, help="time only this kind of log")
    p.add_argument("--repeat", type=int, default=1, help="time each reader this many times; report the median")


def _tool(cmd: list[str], timeout_s: float) -> float | None:
    t0 = time.perf_counter()
    try:
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        return None
    return time.perf_counter() - t0


def _ours(path: Path, all_topics: bool = False) -> float:
    t0 = time.perf_counter()
    load_log(path, all_topics=all_topics)
    return time.perf_counter() - t0


def _median_s(fn: Callable[[], float | None], repeat: int) -> float | None:
    """Median of ``repeat`` timings; None when any run timed out."""
    times = [fn() for _ in range(max(1, repeat))]
    return None if any(t is None for t in times) else float(np.median([t for t in times if t is not None]))


def run(args: argparse.Namespace) -> int:
    con = Console()
    bindir = Path(sys.executable).parent
    tmp = Path(tempfile.mkdtemp(prefix="bench-log-read-"))
    rows: list[dict[str, Any]] = []
    try:
        binp, ulg = tmp / "big.bin", tmp / "big.ulg"
        t0 = time.perf_counter()
        todo: list[tuple[str, Path, int, str, list[str] | None]] = []
        if args.only != "ulog":
            size = onboard_logs.write_dataflash(binp, int(args.size_mb * 1e6))
            todo.append(("dataflash .bin", binp, size, "groundstation load_log", None))
            if not args.no_tools:
                todo.append(("dataflash .bin", binp, size, "mavlogdump.py --quiet",
                             [str(bindir / "mavlogdump.py"), "--quiet", str(binp)]))
        if args.only != "bin":
            size = onboard_logs.write_ulog(ulg, int(args.ulog_mb * 1e6))
            todo.append(("ULog .ulg", ulg, size, "groundstation load_log", None))
            todo.append(("ULog .ulg", ulg, size, "load_log all topics (log-info)", []))
            if not args.no_tools:
                todo.append(("ULog .ulg", ulg, size, "ulog_info", [str(bindir / "ulog_info"), str(ulg)]))
        made = ", ".join(f"{s / 1e6:.1f} MB {k}" for k, _, s, _, c in todo if c is None)
        con.print(f"generated {made} in {time.perf_counter() - t0:.1f} s; median of {max(1, args.repeat)} run(s) each")
        for kind, path, size, who, cmd in todo:
            def once(path: Path = path, cmd: list[str] | None = cmd) -> float | None:
                if not cmd:  # None: the mapped topics; []: every topic
                    return _ours(path, all_topics=cmd is not None)
                return _tool([sys.executable, *cmd], args.tool_timeout_s)

            secs = _median_s(once, args.repeat)
            rows.append({"file": kind, "reader": who, "mb": round(size / 1e6, 1),
                         "seconds": None if secs is None else round(secs, 2),
                         "mb_per_s": None if secs is None else round(size / 1e6 / secs, 1)})
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    t = Table(title="reading large logs (wall time, one process each for the external tools)")
    for c in ("file", "reader", "MB", "seconds", "MB/s"):
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(r["file"], r["reader"], f"{r['mb']:.1f}",
                  f"> {args.tool_timeout_s:g}" if r["seconds"] is None else f"{r['seconds']:.2f}",
                  "-" if r["mb_per_s"] is None else f"{r['mb_per_s']:.1f}")
    con.print(t)
    print(json.dumps({"rows": rows}))
    return 0
