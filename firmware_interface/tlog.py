"""The .tlog format (MAVProxy/QGC): records of 8-byte big-endian microseconds since the Unix epoch
followed by the MAVLink packet bytes exactly as received.

This module holds the writer. It is crash-safe by construction: each record is written with one
``write`` call of timestamp+packet, the file is flushed at least every ``flush_interval_s`` (checked
on each write and by :meth:`TlogWriter.tick`) and fsync'd on :meth:`TlogWriter.sync` and close, so a
``kill -9`` leaves a file that parses up to its last whole packet.
"""

from __future__ import annotations

import os
import struct
import time
from pathlib import Path

_TS = struct.Struct(">Q")


class TlogWriter:
    """Append MAVLink packets to a .tlog file.

    Parameters
    ----------
    path : output file (parent directories are created)
    flush_interval_s : the OS buffer is flushed at least this often (default 0.5 s)
    clock : monotonic clock for the flush schedule (injectable for tests)
    """

    def __init__(self, path: str | os.PathLike[str], *, flush_interval_s: float = 0.5,
                 append: bool = False, clock=time.monotonic) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # buffering=0 would cost a syscall per packet; a user-space buffer plus timed flushes keeps
        # at most flush_interval_s of data in the process at any moment.
        self._f = open(self.path, "ab" if append else "wb", buffering=64 * 1024)  # noqa: SIM115
        self._clock = clock
        self._flush_interval_s = flush_interval_s
        self._last_flush = clock()
        self.packets = 0
        self.bytes = 0

    def write(self, packet: bytes, t_host_s: float) -> None:
        """Write one record; ``t_host_s`` is the host receive time (Unix seconds)."""
        self._f.write(_TS.pack(int(round(t_host_s * 1e6))) + packet)
        self.packets += 1
        self.bytes += 8 + len(packet)
        self.tick()

    def tick(self) -> None:
        """Flush if the flush interval has passed (call periodically when idle)."""
        now = self._clock()
        if now - self._last_flush >= self._flush_interval_s:
            self._f.flush()
            self._last_flush = now

    def flush(self) -> None:
        self._f.flush()
        self._last_flush = self._clock()

    def sync(self) -> None:
        """Flush and fsync (at disarm and shutdown)."""
        self._f.flush()
        os.fsync(self._f.fileno())
        self._last_flush = self._clock()

    @property
    def closed(self) -> bool:
        return self._f.closed

    def close(self) -> None:
        if not self._f.closed:
            self.sync()
            self._f.close()

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
