"""Replay a recorded MAVLink link (.tlog) on a virtual serial port, with fault injection.

:class:`TlogPlayer` writes the packets of a .tlog to a :class:`hil_replay.pty.VirtualSerialPort`
with their original timing, ``speed``× faster, or as fast as the reader drains them
(``speed=0``/``inf``). Faults, all seeded:

* ``corrupt_rate``: each byte put on the wire is corrupted with this probability (one random bit
  flipped), so a packet of n bytes is hit with probability 1-(1-rate)^n;
* ``drop_rate``: each packet is left out with this probability;
* ``unplug_at_s`` / ``unplug_for_s``: on the replay clock (seconds of log time since the first
  packet) the port vanishes for that long and comes back at the same path; packets whose log time
  falls in the gap are never sent.

The player only writes while a reader has the port open (``wait_for_reader``, default): it waits
for the ground station to open (or reopen, after an unplug) the port and resumes from there, so
every packet it reports as sent was offered to an open port (without it, bytes written while
nobody has the port open go nowhere and are counted in ``report.unheard_bytes``). :attr:`TlogPlayer.report` lists, by
index into :attr:`TlogPlayer.packets`, exactly which source packets went out intact, corrupted,
dropped or into the unplug gap.

The .tlog framing here is a small self-contained splitter (CRC-checked with pymavlink's codec) so
the player does not depend on the link layer it is used to test. Leaves decoding, recording and
the ground-station side to :mod:`firmware_interface`.
"""

from __future__ import annotations

import json
import math
import os
import select
import struct
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from hil_replay.pty import VirtualSerialPort

__all__ = ["ReplayReport", "TlogPacket", "TlogPlayer", "read_tlog_packets"]

_TS = struct.Struct(">Q")
_MAGIC_V2 = 0xFD
_MAGIC_V1 = 0xFE
# timestamps between 2000 and 2100 (µs since epoch): used to re-synchronise after garbage
_TS_MIN_US = 946_684_800 * 10**6
_TS_MAX_US = 4_102_444_800 * 10**6
# a file with no valid record in its first MiB is not a .tlog (do not scan gigabytes to say so)
_MAX_LEADING_GARBAGE = 1 << 20


@dataclass(frozen=True, slots=True)
class TlogPacket:
    """One .tlog record: host time (µs since the Unix epoch) and the packet bytes."""

    t_us: int
    data: bytes


def _packet_length(blob: bytes | memoryview, j: int) -> int | None:
    """Length of the MAVLink packet starting at ``j`` (None if not a magic byte / header cut)."""
    if j >= len(blob):
        return None
    magic = blob[j]
    if magic == _MAGIC_V2:
        if j + 3 > len(blob):
            return None
        n = 12 + blob[j + 1]
        if blob[j + 2] & 0x01:  # MAVLINK_IFLAG_SIGNED
            n += 13
        return n
    if magic == _MAGIC_V1:
        if j + 2 > len(blob):
            return None
        return 8 + blob[j + 1]
    return None


def _check(pkt: bytes) -> bool | None:
    """CRC check with the dialect's CRC_EXTRA: True/False, or None for a message id the dialect
    does not know (its CRC cannot be checked)."""
    if pkt[0] == _MAGIC_V2:
        msg_id = pkt[7] | (pkt[8] << 8) | (pkt[9] << 16)
        end = 10 + pkt[1]
    else:
        msg_id = pkt[5]
        end = 6 + pkt[1]
    cls = mavlink.mavlink_map.get(msg_id)
    if cls is None:
        return None
    crc = mavlink.x25crc(pkt[1:end])
    crc.accumulate(struct.pack("B", cls.crc_extra))
    return bool(crc.crc == (pkt[end] | (pkt[end + 1] << 8)))


def read_tlog_packets(path: str | os.PathLike[str]) -> list[TlogPacket]:
    """Split a .tlog into its records.

    A record is accepted where the previous one ended (or at the start of the file) when its
    timestamp is plausible and its packet CRC-valid; packets of message ids the dialect does not
    know are kept only there (in step with the record structure). Garbage between records is
    skipped byte by byte until a plausible timestamp + CRC-valid packet of a known message; a
    truncated last record is dropped. Raises ValueError naming the file when it holds no MAVLink
    packet at all (empty, or not a .tlog), OSError when it cannot be read.
    """
    p = Path(path)
    blob = p.read_bytes()
    if not blob:
        raise ValueError(f"{p}: empty file")
    out: list[TlogPacket] = []
    i = 0
    expected = 0          # where the next record starts if the file is in step
    n_blob = len(blob)
    while i + 8 < n_blob:
        n = _packet_length(blob, i + 8)
        if n is not None and i + 8 + n <= n_blob:
            t_us = _TS.unpack_from(blob, i)[0]
            if _TS_MIN_US <= t_us <= _TS_MAX_US:
                pkt = blob[i + 8:i + 8 + n]
                ok = _check(pkt)
                if ok or (ok is None and i == expected):
                    out.append(TlogPacket(t_us, pkt))
                    i += 8 + n
                    expected = i
                    continue
        # else: garbage, or a truncated last record (scanning on finds nothing more there)
        i += 1
        if not out and i > _MAX_LEADING_GARBAGE:
            break
    if not out:
        raise ValueError(f"{p}: no MAVLink packets found (not a .tlog file?)")
    return out


@dataclass
class ReplayReport:
    """What the player did with each source packet (indices into ``TlogPlayer.packets``)."""

    n_packets: int = 0
    intact: list[int] = field(default_factory=list)
    corrupted: list[int] = field(default_factory=list)
    dropped: list[int] = field(default_factory=list)
    unplugged: list[int] = field(default_factory=list)
    corrupt_bytes: int = 0
    bytes_sent: int = 0
    unplugs_s: list[tuple[float, float]] = field(default_factory=list)  # replay-clock intervals
    wall_s: float = 0.0
    log_s: float = 0.0
    finished: bool = False
    # times the reader had not read everything when the port was unplugged or the replay ended
    # (the packets reported as sent may then not all have reached it)
    undrained: int = 0
    # bytes written while no reader had the port open (only with wait_for_reader=False)
    unheard_bytes: int = 0

    @property
    def real_time_factor(self) -> float:
        return self.log_s / self.wall_s if self.wall_s > 0 else math.inf

    def to_json(self) -> str:
        d = asdict(self)
        d["real_time_factor"] = self.real_time_factor if self.wall_s > 0 else None
        return json.dumps(d)


class TlogPlayer:
    """Serve a .tlog on a virtual serial port.

    Parameters
    ----------
    source : a .tlog path or a list of :class:`TlogPacket`
    port : the virtual serial port to write to (the player unplugs/replugs it for the fault)
    speed : 1 = original timing, N = N× faster, ``0`` or ``inf`` = as fast as the reader drains
    corrupt_rate : probability per byte sent of one flipped bit, in [0, 1)
    drop_rate : probability per packet of leaving it out, in [0, 1)
    unplug_at_s, unplug_for_s : unplug the port at this replay time for this long (replay clock)
    seed : seeds all faults (each fault has its own stream)
    wait_for_reader : only write while a reader has the port open (wait for it to (re)open)
    reader_timeout_s : give up waiting for a reader after this long (TimeoutError); None = forever
    drain_timeout_s : before an unplug and at the end, wait at most this long for the reader to
        read what was written (so packets reported as sent were not lost in the pty buffer)
    max_gap_s : shorten longer pauses between packets to this (None = keep the original timing)
    """

    def __init__(self, source: str | os.PathLike[str] | list[TlogPacket], port: VirtualSerialPort, *,
                 speed: float = 1.0, corrupt_rate: float = 0.0, drop_rate: float = 0.0,
                 unplug_at_s: float | None = None, unplug_for_s: float = 0.0, seed: int = 0,
                 wait_for_reader: bool = True, reader_timeout_s: float | None = None,
                 drain_timeout_s: float = 5.0, max_gap_s: float | None = None) -> None:
        for name, rate in (("corrupt_rate", corrupt_rate), ("drop_rate", drop_rate)):
            if not 0.0 <= rate < 1.0:
                raise ValueError(f"{name}: {rate} not in [0, 1)")
        if speed < 0 or math.isnan(speed):
            raise ValueError(f"speed: {speed} must be >= 0 (0 or inf = as fast as possible)")
        if unplug_at_s is not None and (unplug_at_s < 0 or unplug_for_s < 0):
            raise ValueError(f"unplug_at_s/unplug_for_s: {unplug_at_s}/{unplug_for_s} must be >= 0")
        self.packets: list[TlogPacket] = (list(source) if isinstance(source, list)
                                          else read_tlog_packets(source))
        if not self.packets:
            raise ValueError("no packets to replay")
        self.port = port
        self.speed = math.inf if speed == 0 else float(speed)
        self.corrupt_rate = corrupt_rate
        self.drop_rate = drop_rate
        self.unplug_at_s = unplug_at_s
        self.unplug_for_s = unplug_for_s
        self.wait_for_reader = wait_for_reader
        self.reader_timeout_s = reader_timeout_s
        self.drain_timeout_s = drain_timeout_s
        ss = np.random.SeedSequence(seed)
        self._rng_corrupt, self._rng_drop = (np.random.default_rng(s) for s in ss.spawn(2))
        self.report = ReplayReport(n_packets=len(self.packets))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        if max_gap_s is not None and not max_gap_s > 0:
            raise ValueError(f"max_gap_s: {max_gap_s} must be > 0")
        # replay clock of each packet (s since the first): host-clock steps backwards count as 0,
        # gaps longer than max_gap_s (e.g. between two sessions in one file) are shortened to it
        t_us = np.array([p.t_us for p in self.packets], dtype=np.int64)
        steps_s = np.clip(np.diff(t_us) / 1e6, 0.0, np.inf if max_gap_s is None else max_gap_s)
        self.replay_s = np.concatenate(([0.0], np.cumsum(steps_s)))
        self._next_corrupt = self._draw_gap()

    # ------------------------------------------------------------------ faults

    def _draw_gap(self) -> int:
        """Bytes until the next corrupted one (per-byte Bernoulli trials = geometric gaps)."""
        if self.corrupt_rate <= 0:
            return 1 << 62
        return int(self._rng_corrupt.geometric(self.corrupt_rate)) - 1

    def _corrupt(self, pkt: bytes) -> tuple[bytes, int]:
        """Apply the byte corruption stream to one packet; returns (bytes, n_corrupted)."""
        n = len(pkt)
        if self._next_corrupt >= n:
            self._next_corrupt -= n
            return pkt, 0
        buf = bytearray(pkt)
        hits = 0
        pos = self._next_corrupt
        while pos < n:
            buf[pos] ^= 1 << int(self._rng_corrupt.integers(8))
            hits += 1
            pos += 1 + self._draw_gap()
        self._next_corrupt = pos - n
        return bytes(buf), hits

    # ------------------------------------------------------------------ running

    def _await_reader(self) -> None:
        if not self.wait_for_reader:
            return
        deadline = None if self.reader_timeout_s is None else time.monotonic() + self.reader_timeout_s
        while not self._stop.is_set():
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise TimeoutError(f"{self.port.path}: no reader opened the port "
                                   f"within {self.reader_timeout_s} s")
            if self.port.wait_for_reader(0.1 if left is None else min(left, 0.1)):
                return

    def _sleep_until(self, wall_t: float) -> None:
        while not self._stop.is_set():
            left = wall_t - time.monotonic()
            if left <= 0:
                return
            self._stop.wait(min(left, 0.1))

    def _write(self, data: bytes) -> bool:
        """Write everything (back-pressure: waits while the pty is full); False if stopped first."""
        view = memoryview(data)
        while view and not self._stop.is_set():
            n = self.port.write_nowait(view)
            view = view[n:]
            if view:
                select.select([], [self.port.fileno()], [], 0.1)
        return not view

    def run(self, stop: threading.Event | None = None) -> ReplayReport:
        """Play the whole log (or until :meth:`stop` / ``stop`` is set); returns the report."""
        if stop is not None:
            self._stop = stop
        rep = self.report
        wall_start = time.monotonic()
        self._await_reader()
        wall_base = time.monotonic()   # wall time of replay time 0 (shifted by waits)
        replay_s = self.replay_s
        n = len(self.packets)
        unplug_at = self.unplug_at_s if self.unplug_at_s is not None else math.inf
        unplug_end = unplug_at + self.unplug_for_s
        batch: list[tuple[int, bytes, int]] = []   # (index, bytes on the wire, corrupted bytes)
        batch_bytes = 0
        i = 0
        try:
            while i < n and not self._stop.is_set():
                t = replay_s[i]
                if t >= unplug_at and not rep.unplugs_s:
                    self._flush(batch)
                    batch, batch_bytes = [], 0
                    if not self.port.drain(self.drain_timeout_s):  # what was sent must arrive first
                        rep.undrained += 1
                    self.port.unplug()
                    rep.unplugs_s.append((float(unplug_at), float(unplug_end)))
                    while i < n and replay_s[i] < unplug_end:
                        rep.unplugged.append(i)
                        i += 1
                    if math.isfinite(self.speed):
                        self._sleep_until(wall_base + unplug_end / self.speed)
                    self.port.replug()
                    self._await_reader()
                    if i < n and math.isfinite(self.speed):
                        wall_base = time.monotonic() - replay_s[i] / self.speed
                    continue
                if math.isfinite(self.speed):
                    due = wall_base + t / self.speed
                    now = time.monotonic()
                    if due > now + 0.002:
                        self._flush(batch)
                        batch, batch_bytes = [], 0
                        self._sleep_until(due)
                        if self.wait_for_reader and not self.port.reader_attached():
                            self._await_reader()
                            wall_base = time.monotonic() - t / self.speed
                pkt = self.packets[i].data
                if self.drop_rate > 0 and self._rng_drop.random() < self.drop_rate:
                    rep.dropped.append(i)
                else:
                    data, hits = self._corrupt(pkt)
                    batch.append((i, data, hits))
                    batch_bytes += len(data)
                    if batch_bytes >= 4096:
                        self._flush(batch)
                        batch, batch_bytes = [], 0
                i += 1
            self._flush(batch)
            if not self.port.drain(self.drain_timeout_s):
                rep.undrained += 1
            rep.finished = i >= n
        finally:
            rep.wall_s = time.monotonic() - wall_start
            rep.log_s = float(replay_s[min(i, n) - 1]) if i else 0.0
        return rep

    def _flush(self, batch: list[tuple[int, bytes, int]]) -> None:
        """Write a batch; its packets enter the report only once they are all written."""
        if not batch:
            return
        data = b"".join(b for _, b, _ in batch)
        if not self.port.reader_attached():
            if not self.wait_for_reader:
                # nobody has the port open: the bytes go nowhere, as on a real serial line
                self.report.unheard_bytes += len(data)
                self._commit(batch, len(data))
                return
            self._await_reader()
        if self._write(data):
            self._commit(batch, len(data))
        # else: stopped before it was all written; these packets are not reported as sent

    def _commit(self, batch: list[tuple[int, bytes, int]], n_bytes: int) -> None:
        rep = self.report
        rep.bytes_sent += n_bytes
        for i, _, hits in batch:
            if hits:
                rep.corrupted.append(i)
                rep.corrupt_bytes += hits
            else:
                rep.intact.append(i)

    # ------------------------------------------------------------------ thread helpers

    def start(self) -> TlogPlayer:
        """Run on a background thread (see :meth:`join`, :meth:`stop`)."""
        def main() -> None:
            try:
                self.run()
            except BaseException as exc:  # handed to the caller in join()
                self.error = exc

        self._thread = threading.Thread(target=main, name="tlog-player", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout_s: float | None = None) -> ReplayReport:
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise TimeoutError(f"{self.port.path}: player still running after {timeout_s} s")
        if self.error is not None:
            raise self.error
        return self.report
