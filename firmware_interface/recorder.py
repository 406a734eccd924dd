"""Flight recorder: a session .tlog with every packet plus one .tlog per armed interval.

Feed it the session's events (:meth:`Recorder.handle`): every
:class:`~firmware_interface.samples.RawPacket` goes to ``session-YYYYmmdd-HHMMSS.tlog`` exactly as
received; the FC's :class:`~firmware_interface.samples.Heartbeat` ``armed`` flag opens
``flight-NN.tlog`` on arming (starting with the arming heartbeat) and closes it after the disarming
heartbeat. Files never overwrite existing ones (the next free name is used). Data are flushed at
least every ``flush_interval_s`` (call :meth:`Recorder.tick` while idle) and fsync'd at disarm, on
link loss and on :meth:`Recorder.close`; each record is one ``write`` of timestamp+packet, so a
``kill -9`` leaves files that parse up to their last whole packet.

Leaves the link and decoding to :mod:`firmware_interface.link` / :mod:`firmware_interface.session`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from firmware_interface.samples import Heartbeat, LinkLost, RawPacket
from firmware_interface.tlog import TlogWriter

__all__ = ["Recorder"]

_MAV_AUTOPILOT_INVALID = 8
_MAV_TYPE_GCS = 6


class Recorder:
    """Record events into ``out_dir`` (created if needed).

    Parameters
    ----------
    out_dir : directory for the session and flight files
    fc_sysid : the FC's system id; None = the first autopilot heartbeat's
    clock : Unix clock used for the session file name
    flush_interval_s : at most this much data sits in process buffers (≤ 1 s)
    """

    def __init__(self, out_dir: str | os.PathLike[str], *, fc_sysid: int | None = None,
                 clock: Callable[[], float] = time.time, flush_interval_s: float = 0.5) -> None:
        self.out_dir = Path(out_dir)
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OSError(f"{self.out_dir}: cannot create output directory ({exc.strerror or exc})") from None
        if not os.access(self.out_dir, os.W_OK):
            raise OSError(f"{self.out_dir}: output directory is not writable")
        self.fc_sysid = fc_sysid
        self._flush_s = flush_interval_s
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(clock()))
        self.session_path = self._free(f"session-{stamp}", "")
        self._session = TlogWriter(self.session_path, flush_interval_s=flush_interval_s)
        self._flight: TlogWriter | None = None
        self.flight_paths: list[Path] = []
        self.armed = False
        self._last_raw: RawPacket | None = None
        self.packets = 0

    def _free(self, stem: str, _suffix: str) -> Path:
        p = self.out_dir / f"{stem}.tlog"
        k = 1
        while p.exists():
            p = self.out_dir / f"{stem}-{k}.tlog"
            k += 1
        return p

    def _next_flight_path(self) -> Path:
        k = len(self.flight_paths) + 1
        while True:
            p = self.out_dir / f"flight-{k:02d}.tlog"
            if not p.exists():
                return p
            k += 1

    @property
    def flight_open(self) -> bool:
        return self._flight is not None

    def handle(self, events: Iterable[Any]) -> None:
        """Record a batch of session events."""
        sess = self._session
        for ev in events:
            t = type(ev)
            if t is RawPacket:
                sess.write(ev.data, ev.t_host_s)
                self.packets += 1
                if self._flight is not None:
                    self._flight.write(ev.data, ev.t_host_s)
                self._last_raw = ev
            elif t is Heartbeat:
                self._on_heartbeat(ev)
            elif t is LinkLost:
                self.sync()

    def _on_heartbeat(self, hb: Heartbeat) -> None:
        if hb.autopilot == _MAV_AUTOPILOT_INVALID or hb.mav_type == _MAV_TYPE_GCS:
            return
        if self.fc_sysid is None:
            self.fc_sysid = hb.sysid
        elif hb.sysid != self.fc_sysid:
            return
        if hb.armed and self._flight is None:
            path = self._next_flight_path()
            self._flight = TlogWriter(path, flush_interval_s=self._flush_s)
            self.flight_paths.append(path)
            raw = self._last_raw
            if raw is not None and raw.sysid == hb.sysid and raw.msg_type == "HEARTBEAT":
                self._flight.write(raw.data, raw.t_host_s)
        elif not hb.armed and self._flight is not None:
            self._flight.close()  # fsync'd
            self._flight = None
            self._session.sync()
        self.armed = hb.armed

    def tick(self) -> None:
        """Flush if the flush interval has passed (call about every 0.1 s)."""
        self._session.tick()
        if self._flight is not None:
            self._flight.tick()

    def sync(self) -> None:
        self._session.sync()
        if self._flight is not None:
            self._flight.sync()

    def close(self) -> None:
        """Close (fsync) every file; safe to call twice."""
        if self._flight is not None:
            self._flight.close()
            self._flight = None
        self._session.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
