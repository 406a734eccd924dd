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

HELP = "read a 100 MB dataflash and ULog log: MB/s of our reader vs mavlogdump and ulog_info"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--size-mb", type=float, default=100.0, help="dataflash log size (MB)")
    p.add_argument("--ulog-mb", type=float, default=100.0, help="ULog size (MB, approximate)")
    p.add_argument("--tool-timeout-s", type=float, default=900.0, help="give up on an external tool after this")
    p.add_argument("--no-tools", action="store_true", help="time only this project's reader")
    p.add_argument("--only", choices=("bin", "ulog"), default=None, help="time only this kind of log")
    p.add_argument("--repeat", type=int, default=1, help="time each reader this many times; report the median")


def write_dataflash(path: Path, size_bytes: int, seed: int = 0) -> int:
    """A dataflash log of about ``size_bytes`` (400 Hz IMU/ATT/RATE/RCOU/HELI, 10 Hz XKF1)."""
    from hil_replay.dataflash import _FORMATS, _PACK, _fmt_record

    ids = {name: typ for typ, name, _, _ in _FORMATS}
    names = ("IMU", "ATT", "RATE", "RCOU", "HELI")
    parts = []
    for nm in names:
        parts.append((f"h_{nm}", "S3"))
        parts.append((f"b_{nm}", f"S{_PACK[nm].size}"))
    tick = np.dtype(parts)
    per_tick = tick.itemsize
    xkf = _PACK["XKF1"]
    n = int(size_bytes / (per_tick + (3 + xkf.size) / 40))
    rng = np.random.default_rng(seed)
    t_us = (1_000_000 + np.arange(n) * 2500).astype(np.uint64)
    ts = t_us * 1e-6
    w = 2 * np.pi * 25.0
    gyro = 0.05 * np.sin(np.outer(ts, [0.7, 1.1, 0.4])) + 0.01 * np.sin(w * ts)[:, None] \
        + 0.002 * rng.standard_normal((n, 3))
    arr = np.zeros(n, dtype=tick)

    def body(dtype_fields: list[tuple[str, str]], cols: list[np.ndarray]) -> np.ndarray:
        d = np.dtype(dtype_fields)
        a = np.zeros(n, dtype=d)
        for (name, _), c in zip(dtype_fields, cols, strict=True):
            a[name] = c
        return a.view(f"S{d.itemsize}")

    f = "<f4"
    for nm in names:
        arr[f"h_{nm}"] = b"\xa3\x95" + bytes([ids[nm]])
    arr["b_IMU"] = body([("t", "<u8"), ("i", "u1")] + [(f"g{k}", f) for k in range(6)],
                        [t_us, np.zeros(n), gyro[:, 0], gyro[:, 1], gyro[:, 2], np.zeros(n), np.zeros(n),
                         np.full(n, -9.8)])
    deg = np.degrees(np.cumsum(gyro, axis=0) * 0.0025)
    arr["b_ATT"] = body([("t", "<u8")] + [(f"a{k}", f) for k in range(6)],
                        [t_us, np.zeros(n), deg[:, 0], np.zeros(n), deg[:, 1], np.zeros(n), deg[:, 2] % 360])
    rate = np.degrees(gyro)
    arr["b_RATE"] = body([("t", "<u8")] + [(f"r{k}", f) for k in range(9)],
                         [t_us, np.zeros(n), rate[:, 0], np.zeros(n), np.zeros(n), rate[:, 1], np.zeros(n),
                          np.zeros(n), rate[:, 2], np.zeros(n)])
    pwm = (1500 + 200 * np.sin(np.outer(ts, [0.5, 0.8, 0.3, 1.2]))).astype(np.uint16)
    arr["b_RCOU"] = body([("t", "<u8")] + [(f"c{k}", "<u2") for k in range(8)],
                         [t_us, *pwm.T, np.zeros(n), np.zeros(n), np.zeros(n), np.full(n, 1850)])
    arr["b_HELI"] = body([("t", "<u8")] + [(f"h{k}", f) for k in range(4)],
                         [t_us, np.full(n, 1500.0), 1500 + rng.standard_normal(n), np.ones(n), np.ones(n)])
    head = b"".join(_fmt_record(*fm) for fm in _FORMATS)
    blocks = arr.view(np.uint8).reshape(n, per_tick)
    with path.open("wb") as fh:
        fh.write(head)
        step = 40  # one XKF1 per 40 ticks (10 Hz)
        for k0 in range(0, n, 40_000):
            k1 = min(n, k0 + 40_000)
            out = bytearray()
            for a in range(k0, k1, step):
                b = min(k1, a + step)
                out += blocks[a:b].tobytes()
                out += b"\xa3\x95" + bytes([ids["XKF1"]]) + xkf.pack(int(t_us[a]), 0, 0.1, 0.2, 0.0, 1.0, 2.0, -3.0)
            fh.write(out)
    return path.stat().st_size


def write_ulog(path: Path, size_bytes: int) -> int:
    """The pyulog sample's topics repeated (timestamps moved on) until about ``size_bytes``."""
    import lzma

    from pyulog import ULog

    src = Path(__file__).resolve().parents[2] / "tests" / "data" / "px4" / "pyulog_sample.ulg.xz"
    if not src.is_file():
        raise FileNotFoundError(f"{src}: the sample ULog is missing from the checkout")
    sample = path.with_name("sample.ulg")
    sample.write_bytes(lzma.decompress(src.read_bytes()))
    ulog = ULog(str(sample))
    k = max(1, int(round(size_bytes / sample.stat().st_size)))
    span = int(ulog.last_timestamp - ulog.start_timestamp) + 1000
    for d in ulog.data_list:
        for key, v in list(d.data.items()):
            if key == "timestamp":
                d.data[key] = np.concatenate([v + np.uint64(span * i) for i in range(k)])
            else:
                d.data[key] = np.tile(v, k)
    ulog._last_timestamp = ulog.last_timestamp + span * (k - 1)
    ulog.write_ulog(str(path))
    sample.unlink()
    return path.stat().st_size


def _tool(cmd: list[str], timeout_s: float) -> float | None:
    t0 = time.perf_counter()
    try:
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        return None
    return time.perf_counter() - t0


def _ours(path: Path, all_topics: bool = False) -> float:
    from firmware_interface.readers import load_log

    t0 = time.perf_counter()
    load_log(path, all_topics=all_topics)
    return time.perf_counter() - t0


def _median_s(fn: Callable[[], float | None], repeat: int) -> float | None:
    """Median of ``repeat`` timings; None when any run timed out."""
    times = [fn() for _ in range(max(1, repeat))]
    return None if any(t is None for t in times) else float(np.median([t for t in times if t is not None]))


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    con = Console()
    bindir = Path(sys.executable).parent
    tmp = Path(tempfile.mkdtemp(prefix="bench-log-read-"))
    rows: list[dict[str, Any]] = []
    try:
        binp, ulg = tmp / "big.bin", tmp / "big.ulg"
        t0 = time.perf_counter()
        todo: list[tuple[str, Path, int, str, list[str] | None]] = []
        if args.only != "ulog":
            size = write_dataflash(binp, int(args.size_mb * 1e6))
            todo.append(("dataflash .bin", binp, size, "groundstation load_log", None))
            if not args.no_tools:
                todo.append(("dataflash .bin", binp, size, "mavlogdump.py --quiet",
                             [str(bindir / "mavlogdump.py"), "--quiet", str(binp)]))
        if args.only != "bin":
            size = write_ulog(ulg, int(args.ulog_mb * 1e6))
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
