"""The service's onboard-log download between flights (``[onboard_logs] download = true``).

After each disarm (and a short wait for the FC to close its log), the newest onboard log is listed
and downloaded over the service's own link and MAVLink session, with the sans-IO
:class:`~firmware_interface.logdownload.LogLister` and
:class:`~firmware_interface.logdownload.LogDownloader`: the service hands this object its session
events (:meth:`OnboardLogs.on_events`) and calls :meth:`OnboardLogs.tick` from its timer; requests
leave through the session's read-only allowlist. Only while disarmed: arming stops the download (the
FC would not answer anyway), keeps what arrived, and the next disarm resumes it. The session's
failed-CRC count goes to the downloader (a link that corrupts frames: every block confirmed by a
second copy). A finished log is written atomically and verified in a thread
(:func:`firmware_interface.logtransfer.write_verified`); one whose download could not be verified is
written as ``log-N.unverified.bin`` and the log line says so.

A flight whose telemetry lost too much (``suggest_above_loss_pct``) can have its log fetched for
analysis (``[onboard_logs] analyse``, :func:`analyse_onboard`): the log listed after that flight's
disarm is remembered as that flight's, and when it is written the ``on_log(flight, path)`` callback
hands it to the service, which analyses it instead of the telemetry. Whether the link is a USB cable
or a slow radio is :func:`link_kind`'s answer.
"""

from __future__ import annotations

import asyncio
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.errors import TransportError
from firmware_interface.logdownload import (
    DownloadComplete,
    DownloadConfig,
    DownloadFailed,
    LogDownloader,
    LogEntry,
    LogListed,
    LogLister,
    LogRequestFailed,
)
from firmware_interface.logtransfer import write_verified
from firmware_interface.samples import Heartbeat, LinkLost, LinkRestored, RawPacket
from firmware_interface.transports import parse_url
from groundstation.config import OnboardLogsSection

__all__ = ["OnboardLogs", "OnboardLogsSection", "analyse_onboard", "link_kind"]

#: serial devices of the autopilot's own USB port (USB CDC-ACM: Linux ttyACM, macOS usbmodem) and
#: virtual ports (a pty: the built-in simulated FC, a local SITL bridge)
_USB_DEVICE = re.compile(r"(^ttyACM\d*$)|(usbmodem)|(^pts/)|(^ttys\d+$)|(^ptmx$)")


def link_kind(url: str, configured: str = "auto") -> tuple[str, str]:
    """``("usb" | "radio", why)``: what carries the link at ``url``, as ``[link] kind`` says or, with
    ``auto``, from the port. The port's name (symlinks such as /dev/serial/by-id resolved) decides:
    the autopilot's own USB port enumerates as a CDC-ACM device (``/dev/ttyACM0``,
    ``/dev/cu.usbmodem1``) and a virtual port is a pty; a telemetry radio (SiK, RFD900) comes through a
    USB-serial adapter or a UART (``/dev/ttyUSB0``, ``cu.usbserial``, ``ttyS``, ``COM3``) and WiFi
    telemetry through udp/tcp, all taken as radio. The baud rate is not used: CDC-ACM ignores it and a
    radio's serial side runs at the same rates as a wire."""
    if configured in ("usb", "radio"):
        return configured, f"[link] kind = {configured!r}"

    try:
        u = parse_url(url)
    except TransportError:
        return "radio", f"{url or 'no link'}: not a serial port"
    if u.scheme != "serial":
        return "radio", f"{u.scheme} link (network telemetry); set [link] kind = \"usb\" for a local one"
    real = os.path.realpath(u.path) if os.path.islink(u.path) else u.path
    name = real.removeprefix("/dev/")
    if _USB_DEVICE.search(name):
        return "usb", f"{real} is a USB CDC-ACM or virtual port"
    return "radio", (f"{real} is a USB-serial adapter or UART, the way telemetry radios connect; "
                     "set [link] kind = \"usb\" for a cable")


def analyse_onboard(config: OnboardLogsSection, kind: str) -> bool:
    """Whether a lossy flight's onboard log is to be analysed instead of its telemetry over a link of ``kind``."""
    return config.analyse == "always" or (config.analyse == "usb" and kind == "usb")


class OnboardLogs:
    """See the module docstring. ``session`` is the service's MavlinkSession; ``log`` one-line messages."""

    def __init__(self, config: OnboardLogsSection, out_dir: Path, session: Any, log: Callable[[str], None],
                 on_log: Callable[[int, str], None] | None = None) -> None:
        self.config = config
        self.out_dir = out_dir
        self.session = session
        self.log = log
        self.dl_config = DownloadConfig(give_up_s=config.give_up_s, list_timeout_s=config.list_timeout_s,
                                        list_retries=config.list_retries, confirm=config.confirm)
        self._decoder = mavlink2.MAVLink(None, 255, 190)
        self._decoder.robust_parsing = True
        self._fc: tuple[int, int] | None = None
        self.armed = False
        self._start_at: float | None = None
        self._machine: Any = None
        self._partial: dict[int, tuple[bytes, bytes]] = {}
        self._done: set[int] = set()
        self._writing: set[asyncio.Future[Any]] = set()
        self._last: LogDownloader | None = None
        self.downloaded: list[str] = []
        self.on_log = on_log
        self._flight: tuple[int, bool] | None = None    # (flight, analyse it) of the listing to come
        self._for_analysis: dict[int, int] = {}         # log id -> flight whose analysis waits for it
        self._bad_crc = 0                               # the session's failed CRCs handed on so far

    @property
    def busy(self) -> bool:
        return self._start_at is not None or self._machine is not None or bool(self._writing)

    def flight_ended(self, now: float, flight: int | None = None, analyse: bool = False) -> None:
        """List (after ``after_disarm_s``) and fetch the newest log; with ``analyse`` it is ``flight``'s log
        and goes to ``on_log`` once written."""
        self._start_at = now + self.config.after_disarm_s
        self._flight = (flight, analyse) if flight is not None else None

    def on_events(self, events: list[Any], now: float) -> None:
        m = self._machine
        bad_crc = int(getattr(getattr(self.session, "stats", None), "bad_crc", 0))
        bad, self._bad_crc = bad_crc - self._bad_crc, bad_crc
        if bad > 0 and isinstance(m, LogDownloader):
            m.link_noise(bad, now)
        for ev in events:
            t = type(ev)
            if t is RawPacket:
                if m is not None and ev.msg_type in ("LOG_ENTRY", "LOG_DATA") and self._fc and ev.sysid == self._fc[0]:
                    m.receive_message(self._decoder.decode(bytearray(ev.data)), now)
            elif t is Heartbeat:
                if ev.autopilot != mavlink2.MAV_AUTOPILOT_INVALID and ev.mav_type != mavlink2.MAV_TYPE_GCS:
                    self._fc = self._fc or (ev.sysid, ev.compid)
                    if ev.sysid == self._fc[0]:
                        self.armed = bool(ev.armed)
                        if m is not None:
                            m.fc_armed(self.armed, now)
            elif t is LinkLost and isinstance(m, LogDownloader):
                m.link_lost(now)
            elif t is LinkRestored and isinstance(m, LogDownloader):
                m.link_restored(now)

    def tick(self, now: float) -> None:
        if self._machine is None and self._start_at is not None and now >= self._start_at:
            self._start_at = None
            if self.armed or self._fc is None:
                return
            self._machine = LogLister(self._fc, self.dl_config)
            self._machine.start(now)
        m = self._machine
        if m is None:
            return
        m.handle_timer(now)
        for msg in m.messages_to_send():
            self.session.send_message(msg)
        for ev in m.events():
            self._on_result(ev, now)

    def _on_result(self, ev: Any, now: float) -> None:
        if not isinstance(ev, (LogListed, LogRequestFailed, DownloadFailed, DownloadComplete)):
            return  # progress
        self._machine = None
        if isinstance(ev, LogListed):
            flight, self._flight = self._flight, None
            if flight is not None and flight[1]:
                if not ev.entries:
                    self.log(f"flight {flight[0]}: the FC offers no onboard log; the telemetry's analysis stands")
                else:   # the newest log after this flight's disarm is this flight's
                    self._for_analysis[max(e.log_id for e in ev.entries)] = flight[0]
            todo = [e for e in ev.entries if e.log_id not in self._done]
            if todo:
                self._download(max(todo, key=lambda e: e.log_id), now)
        elif isinstance(ev, LogRequestFailed):
            flight, self._flight = self._flight, None
            self.log(f"onboard log: {ev.reason}" + (f"; flight {flight[0]}'s telemetry analysis stands"
                                                    if flight is not None and flight[1] else ""))
        elif isinstance(ev, DownloadFailed):
            last = self._last
            if last is not None and last.received_blocks:
                self._partial[ev.log_id] = last.partial()
            flight_no = self._for_analysis.get(ev.log_id)
            stands = f"; flight {flight_no}'s telemetry analysis stands" if flight_no is not None else ""
            self.log(f"onboard {ev.reason} (kept; resumes after the next disarm){stands}")
        elif isinstance(ev, DownloadComplete):
            self._done.add(ev.log_id)
            self._partial.pop(ev.log_id, None)
            self._write(ev)

    def _download(self, entry: LogEntry, now: float) -> None:
        part = self._partial.get(entry.log_id)
        data, have = part if part is not None else (None, None)
        dl = LogDownloader(entry, self._fc or (1, 1), self.dl_config, data=data, have=have)
        self._last = self._machine = dl
        dl.fc_armed(self.armed, now)
        dl.start(now)
        self.log(f"onboard log {entry.log_id}: downloading {entry.size_bytes / 1024:.0f} kB")

    def _write(self, ev: DownloadComplete) -> None:
        path = self.out_dir / f"log-{ev.log_id}.bin"
        fut = asyncio.get_running_loop().run_in_executor(None, write_verified, path, ev.data, len(ev.data),
                                                         ev.check)
        self._writing.add(fut)

        def done(f: asyncio.Future[Any]) -> None:
            exc = f.exception()
            if exc is not None:
                self.log(f"onboard log {ev.log_id}: {exc}")
            else:
                written = f.result()
                self.downloaded.append(str(written))
                said = "wrote" if written == path else "saved as"
                self.log(f"onboard log {ev.log_id}: {said} {written}, {ev.check.summary()}")
                flight = self._for_analysis.pop(ev.log_id, None)
                if flight is not None and self.on_log is not None:
                    self.on_log(flight, str(written))     # before busy ends: the service's exit waits for its job
            self._writing.discard(f)

        fut.add_done_callback(done)
