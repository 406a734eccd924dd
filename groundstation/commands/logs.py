"""``groundstation logs list|get``: the flight controller's onboard logs, downloaded over the link.

``logs list --link URL`` prints each log's number, size and date (``--json``: one JSON object).
``logs get N [--out DIR] --link URL`` downloads log N with a progress bar (kB/s, time left) to
``DIR/log-N.bin`` (``.ulg`` for a PX4 ULog), written atomically and verified (size, a parse to its
end, and the download's own check: a second agreeing copy of every block when the link corrupts
frames, the record chain; a log that cannot be verified is written as ``log-N.unverified.bin`` and
said so in one line, exit code 3). A download that fails keeps what arrived beside the file (``log-N.bin.part`` and its
block map) and the next ``logs get N`` resumes from it. The FC must be disarmed (ArduPilot serves no
logs while armed); nothing is ever erased on the FC.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    DownloadColumn,
    Progress,
    TextColumn,
    TimeRemainingColumn,
    TransferSpeedColumn,
)
from rich.table import Table

from firmware_interface.logdownload import DownloadConfig
from firmware_interface.logtransfer import (
    DownloadError,
    LogTransfer,
    load_partial,
    save_partial,
    unverified_path,
    write_verified,
)
from firmware_interface.transports import open_link


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=("list", "get"), help="list the logs, or get one")
    p.add_argument("number", nargs="?", type=int, default=None, help="log number (get)")
    p.add_argument("--link", required=True, help="serial:///dev/ttyUSB0:921600, udpin://0.0.0.0:14550, tcp://host:5760")
    p.add_argument("--out", type=Path, default=Path("."), help="directory for the downloaded log (default .)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--give-up-s", type=float, default=8.0,
                   help="fail (keeping what arrived) when the FC sends nothing for this long (default 8 s)")
    p.add_argument("--confirm", choices=("noisy", "always"), default="noisy",
                   help="read every block a second time and keep it when two copies agree: once the link "
                        "corrupts a frame (noisy, the default) or always (twice the time)")


def log_path(out_dir: Path, number: int, head: bytes = b"") -> Path:
    return out_dir / (f"log-{number}.ulg" if head.startswith(b"ULog") else f"log-{number}.bin")


def run(args: argparse.Namespace) -> int:
    if args.action == "get" and (args.number is None or args.number < 1):
        raise ValueError("logs get: give the log number (>= 1), e.g. groundstation logs get 3 --link URL")
    return asyncio.run(_main(args))


async def _main(args: argparse.Namespace) -> int:
    if not args.give_up_s > 0:
        raise ValueError(f"--give-up-s: {args.give_up_s} must be > 0")
    first = await open_link(args.link)  # a bad URL or port fails here, in one line
    opened = [first]

    async def opener():
        if opened:
            return opened.pop()
        return await open_link(args.link)

    config = DownloadConfig(give_up_s=args.give_up_s, confirm=args.confirm)
    async with LogTransfer(opener, url=args.link, config=config) as tr:
        entries = await tr.list_logs()
        if args.action == "list":
            _print_list(entries, args.json)
            return 0
        return await _get(tr, entries, args)


def _print_list(entries: tuple, as_json: bool) -> None:
    rows = [{"number": e.log_id, "size_bytes": e.size_bytes, "time_utc_s": e.time_utc_s} for e in entries]
    if as_json:
        print(json.dumps({"logs": rows}))
        return

    t = Table(title=f"onboard logs ({len(rows)})")
    for c in ("#", "size", "date (UTC)"):
        t.add_column(c, justify="right")
    for r in rows:
        date = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(r["time_utc_s"])) if r["time_utc_s"] else "-"
        t.add_row(str(r["number"]), f"{r['size_bytes'] / 1024:.1f} kB", date)
    Console().print(t)


async def _get(tr, entries: tuple, args: argparse.Namespace) -> int:
    entry = next((e for e in entries if e.log_id == args.number), None)
    if entry is None:
        have = ", ".join(str(e.log_id) for e in entries) or "none"
        raise ValueError(f"log {args.number}: not on the flight controller (logs there: {have})")
    path = log_path(args.out, entry.log_id)
    partial = load_partial(path, entry.size_bytes)
    t0 = time.monotonic()
    try:
        with _Progress(entry, args.no_progress or args.json, tr) as bar:
            data = await tr.download(entry, partial=partial, on_progress=bar.update)
    except DownloadError as exc:
        if exc.partial is not None:
            kept = save_partial(path, exc.partial)
            raise DownloadError(f"{exc}; kept in {kept} (run the same command again to resume)") from None
        raise
    seconds = time.monotonic() - t0
    final = log_path(args.out, entry.log_id, data[:4])
    check = tr.check
    written = write_verified(final, data, entry.size_bytes, check)
    if final != path:
        for p in (path.with_name(path.name + ".part"), path.with_name(path.name + ".part.blocks")):
            p.unlink(missing_ok=True)
    if written == final:
        unverified_path(final).unlink(missing_ok=True)   # an earlier unverified try of this log
    rate = entry.size_bytes / 1024 / max(seconds, 1e-9)
    summary = check.summary() if check is not None else "verified"
    if args.json:
        print(json.dumps({"number": entry.log_id, "path": str(written), "size_bytes": entry.size_bytes,
                          "seconds": round(seconds, 3), "kB_per_s": round(rate, 1),
                          "verified": written == final, "check": summary,
                          "reread_blocks": dict(check.reread_blocks) if check is not None else {}}))
    elif written == final:
        print(f"wrote {written} ({entry.size_bytes} bytes in {seconds:.1f} s, {rate:.0f} kB/s); {summary}")
    if written != final:
        print(f"log {entry.log_id}: saved as {written}, {summary}", file=sys.stderr)
        return 3
    return 0


class _Progress:
    """A rich progress bar on stderr: bytes, kB/s, time left."""

    def __init__(self, entry, quiet: bool, transfer: Any = None) -> None:
        self.entry = entry
        self.quiet = quiet
        self.transfer = transfer
        self._p: Any = None
        self._task: Any = None

    def __enter__(self) -> _Progress:
        if not self.quiet:
            self._p = Progress(TextColumn("{task.description}"), BarColumn(), DownloadColumn(),
                               TransferSpeedColumn(), TimeRemainingColumn(), console=Console(stderr=True),
                               transient=True)
            self._p.start()
            self._task = self._p.add_task(f"log {self.entry.log_id}", total=self.entry.size_bytes)
        return self

    def update(self, received: int, size: int) -> None:
        if self._p is not None:
            second = getattr(self.transfer, "confirming", False)
            what = f"log {self.entry.log_id}" + (" second copies" if second else "")
            self._p.update(self._task, completed=received, total=size, description=what)

    def __exit__(self, *exc: object) -> None:
        if self._p is not None:
            self._p.stop()
