"""Onboard log listing and download over a live link: the IO around :mod:`firmware_interface.logdownload`.

:class:`LogTransfer` takes an opener (``async () -> Link``, so a pulled cable is reopened) or an open
:class:`~firmware_interface.transports.Link`, runs a passive-streams :class:`~firmware_interface.session.MavlinkSession` over it with
:class:`~firmware_interface.link.LinkRunner` (GCS heartbeat only; every request goes through the
session's read-only allowlist), waits for the FC's heartbeat, and then:

* :meth:`LogTransfer.list_logs` -> the FC's :class:`~firmware_interface.logdownload.LogEntry` list;
* :meth:`LogTransfer.download` -> the bytes of one log, with progress callbacks (how they were
  verified, beyond each packet's CRC, in :attr:`LogTransfer.check`); the session's failed-CRC count
  is handed to the downloader, which then confirms every block with a second copy; on failure a
  :class:`DownloadError` (one line naming the log) that carries the partial data and its block
  bitmap, so :func:`save_partial` keeps it and a later call resumes from it.

:func:`write_verified` writes a downloaded log atomically (temporary file, size check, a full
dataflash/ULog parse, rename); a log whose check is not verified goes to ``log-N.unverified.bin``. LOG_REQUEST_END is sent whenever a download ends, also when it is
cancelled. Leaves the progress display and file naming to the caller.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.errors import LinkError, LogError
from firmware_interface.link import LinkRunner
from firmware_interface.logdownload import (
    DownloadCheck,
    DownloadComplete,
    DownloadConfig,
    DownloadFailed,
    DownloadProgress,
    LogDownloader,
    LogEntry,
    LogListed,
    LogLister,
    LogRequestFailed,
)
from firmware_interface.readers import load_log
from firmware_interface.samples import Heartbeat, LinkLost, LinkRestored, RawPacket
from firmware_interface.session import MavlinkSession, SessionConfig
from firmware_interface.transports import Link

__all__ = ["DownloadError", "LogTransfer", "load_partial", "save_partial", "unverified_path", "write_verified"]

_MAV_AUTOPILOT_INVALID = 8
_LOG_TYPES = ("LOG_ENTRY", "LOG_DATA")


class DownloadError(LinkError):
    """A list or download that did not finish; ``partial`` is (data, have-bitmap) when some arrived."""

    def __init__(self, message: str, partial: tuple[bytes, bytes] | None = None) -> None:
        super().__init__(message)
        self.partial = partial


class LogTransfer:
    """List and download onboard logs over ``link`` (see the module docstring)."""

    def __init__(self, link: Link | Callable[[], Awaitable[Link]], *, config: DownloadConfig | None = None,
                 url: str = "", clock: Callable[[], float] = time.time, heartbeat_timeout_s: float = 10.0) -> None:
        self.url = url or "the link"
        self.config = config or DownloadConfig()
        self.clock = clock
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.session = MavlinkSession(SessionConfig(request_streams=False, link_timeout_s=2.0))
        self._decoder = mavlink2.MAVLink(None, 255, 190)
        self._decoder.robust_parsing = True
        # an opener (``async () -> Link``) lets the driver reopen a port that vanished (cable pulled)
        self._runner = LinkRunner(link, self.session, self._on_events, clock=clock, tick_s=0.02,
                                  backoff_s=0.05, backoff_max_s=0.5)
        self._task: asyncio.Task[None] | None = None
        self._fc: tuple[int, int] | None = None
        self._have_fc = asyncio.Event()
        self.armed = False
        self._machine: Any = None
        self._wake = asyncio.Event()
        self._bad_crc = 0
        self.check: DownloadCheck | None = None   # the last completed download's
        self.confirming = False                    # the running download reads second copies

    # ------------------------------------------------------------------ lifecycle

    async def __aenter__(self) -> LogTransfer:
        self._task = asyncio.ensure_future(self._runner.run())
        try:
            await asyncio.wait_for(self._have_fc.wait(), self.heartbeat_timeout_s)
        except TimeoutError:
            await self.close()
            raise DownloadError(f"{self.url}: no flight-controller heartbeat within {self.heartbeat_timeout_s:g} s") \
                from None
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        self._runner.stop()
        if self._task is not None:
            try:
                await asyncio.wait_for(self._task, 2.0)
            except (TimeoutError, asyncio.CancelledError, LinkError, OSError):
                pass
            self._task = None
        link = self._runner.link
        if link is not None:
            try:
                await link.close()
            except (LinkError, OSError):
                pass

    # ------------------------------------------------------------------ events from the link

    def _on_events(self, events: list[Any]) -> None:
        now = self.clock()
        m = self._machine
        bad, self._bad_crc = self.session.stats.bad_crc - self._bad_crc, self.session.stats.bad_crc
        if bad > 0 and isinstance(m, LogDownloader):
            m.link_noise(bad, now)
        for ev in events:
            t = type(ev)
            if t is RawPacket:
                if ev.msg_type in _LOG_TYPES and m is not None and self._fc and ev.sysid == self._fc[0]:
                    msg = self._decoder.decode(bytearray(ev.data))
                    m.receive_message(msg, now)
            elif t is Heartbeat:
                if ev.autopilot != _MAV_AUTOPILOT_INVALID and ev.mav_type != mavlink2.MAV_TYPE_GCS:
                    if self._fc is None:
                        self._fc = (ev.sysid, ev.compid)
                        self._have_fc.set()
                    if ev.sysid == self._fc[0]:
                        self.armed = bool(ev.armed)
                        if m is not None:
                            m.fc_armed(self.armed, now)
            elif t is LinkLost and isinstance(m, LogDownloader):
                m.link_lost(now)
            elif t is LinkRestored and isinstance(m, LogDownloader):
                m.link_restored(now)
        if m is not None:
            self._pump(now)

    def _pump(self, now: float) -> None:
        m = self._machine
        m.handle_timer(now)
        for msg in m.messages_to_send():
            self.session.send_message(msg)
        self._wake.set()

    async def _drive(self, machine: Any, done: tuple[type, ...], on_event: Callable[[Any], None] | None = None
                     ) -> Any:
        """Run ``machine`` until one of ``done`` events; timers every 20 ms."""
        self._machine = machine
        try:
            machine.fc_armed(self.armed, self.clock())
            machine.start(self.clock())
            while True:
                self._pump(self.clock())
                for ev in machine.events():
                    if on_event is not None:
                        on_event(ev)
                    if isinstance(ev, done):
                        return ev
                self._wake.clear()
                try:
                    await asyncio.wait_for(self._wake.wait(), 0.02)
                except TimeoutError:
                    pass
        finally:
            self._machine = None
            if isinstance(machine, LogDownloader):
                machine.abort(self.clock(), "cancelled")  # sends LOG_REQUEST_END if not sent yet
            for msg in machine.messages_to_send():
                self.session.send_message(msg)
            out = self.session.data_to_send(self.clock())
            link = self._runner.link
            if out and link is not None:
                try:
                    await link.write(out)
                except (LinkError, OSError):
                    pass

    # ------------------------------------------------------------------ API

    async def list_logs(self) -> tuple[LogEntry, ...]:
        assert self._fc is not None
        ev = await self._drive(LogLister(self._fc, self.config), (LogListed, LogRequestFailed))
        if isinstance(ev, LogRequestFailed):
            raise DownloadError(f"{self.url}: listing the onboard logs failed: {ev.reason}")
        return tuple(ev.entries)

    async def download(self, entry: LogEntry, *, partial: tuple[bytes, bytes] | None = None,
                       on_progress: Callable[[int, int], None] | None = None) -> bytes:
        """The whole log ``entry`` (byte-exact); DownloadError with the partial data otherwise."""
        assert self._fc is not None
        data, have = partial if partial is not None else (None, None)
        dl = LogDownloader(entry, self._fc, self.config, data=data, have=have)
        self._bad_crc = self.session.stats.bad_crc   # count from here
        self.check = None

        def seen(ev: Any) -> None:
            if isinstance(ev, DownloadProgress):
                self.confirming = ev.confirming
                if on_progress is not None:
                    on_progress(ev.received_bytes, ev.size_bytes)

        ev = await self._drive(dl, (DownloadComplete, DownloadFailed), seen)
        if isinstance(ev, DownloadFailed):
            raise DownloadError(ev.reason, dl.partial() if dl.received_blocks else None)
        self.check = ev.check
        return bytes(ev.data)


# ---------------------------------------------------------------------- files


def _part_paths(path: Path) -> tuple[Path, Path]:
    return path.with_name(path.name + ".part"), path.with_name(path.name + ".part.blocks")


def save_partial(path: Path, partial: tuple[bytes, bytes]) -> Path:
    """Keep a partial download beside ``path`` (data and block bitmap) for a later resume."""
    data_p, map_p = _part_paths(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    for p, blob in ((data_p, partial[0]), (map_p, partial[1])):
        tmp = p.with_name(p.name + ".tmp")
        tmp.write_bytes(blob)
        os.replace(tmp, p)
    return data_p


def load_partial(path: Path, size_bytes: int) -> tuple[bytes, bytes] | None:
    """A partial download of the same size kept by :func:`save_partial`, or None."""
    data_p, map_p = _part_paths(path)
    if not (data_p.is_file() and map_p.is_file()):
        return None
    data, have = data_p.read_bytes(), map_p.read_bytes()
    if len(data) != size_bytes or len(have) != -(-size_bytes // 90):
        return None
    return data, have


def unverified_path(path: Path) -> Path:
    """``log-1.bin`` -> ``log-1.unverified.bin``: where a log whose download could not be verified goes."""
    return path.with_name(f"{path.stem}.unverified{path.suffix}")


def write_verified(path: Path, data: bytes, size_bytes: int, check: DownloadCheck | None = None) -> Path:
    """Write ``data`` to ``path`` atomically after checking its size and parsing it to its end;
    returns the path written: :func:`unverified_path` when ``check`` says the download is not verified.

    Raises LogError (naming the file) when the size differs or the log does not parse whole; the
    bytes are then kept as ``path.part`` so nothing downloaded is lost.
    """
    final = unverified_path(path) if check is not None and not check.verified else path
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".verify")
    tmp.write_bytes(data)
    try:
        if len(data) != size_bytes:
            raise LogError(f"{path}: {len(data)} bytes downloaded, the FC listed {size_bytes}")
        log = load_log(tmp)
        if log.stats.truncated_tail_bytes:
            raise LogError(f"{path}: the downloaded log does not parse to its end "
                           f"({log.stats.truncated_tail_bytes} bytes left over)")
    except LogError as exc:
        os.replace(tmp, _part_paths(path)[0])
        raise LogError(str(exc).replace(str(tmp), str(path))) from None
    os.replace(tmp, final)
    for p in _part_paths(path):
        p.unlink(missing_ok=True)
    return final
