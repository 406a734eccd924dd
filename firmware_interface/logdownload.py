"""Onboard log download over MAVLink (the LOG_* protocol ArduPilot and PX4 answer), sans-IO.

Usage (the driver owns IO and the clock; messages out go through
:meth:`firmware_interface.session.MavlinkSession.send_message`, i.e. the read-only allowlist)::

    lister = LogLister(target=(1, 1))
    lister.start(now)
    lister.receive_message(msg, now)        # decoded LOG_ENTRY (others ignored)
    lister.handle_timer(now)
    for m in lister.messages_to_send(): session.send_message(m)
    lister.events()                         # [LogListed(...)] or [LogRequestFailed(...)]

    dl = LogDownloader(entry, target=(1, 1))    # optionally data= and have= to resume a part file
    dl.start(now); dl.receive_message(msg, now); dl.handle_timer(now)
    dl.link_lost(now) / dl.link_restored(now) / dl.fc_armed(armed, now) / dl.abort(now, reason)
    dl.events()       # DownloadProgress ..., then DownloadComplete or DownloadFailed

How a log comes down:

* the whole file is asked for at once (LOG_REQUEST_DATA from the first missing byte to the end);
  every LOG_DATA fills its 90-byte blocks in a received-block bitmap (duplicates counted, never
  written twice);
* when that stream reaches the end of the file, or stalls for ``stall_s``, the missing runs are
  re-requested: spans of at most ``fill_run_bytes`` as single requests (at most ``max_in_flight``
  outstanding, at most ``max_requests_per_s`` sent, each retried after ``retry_s`` unless a later
  answer shows it was answered), and the first run longer than ``stream_run_bytes`` (the tail after
  a lost link) as a new stream after them (the FC answers each request at once and keeps streaming
  the last) — so the last few per cent cost a few round trips, not a timeout each;
* a lost link pauses the download; when it is back the stream restarts at the first missing byte
  (nothing received is asked for again as a stream's start);
* nothing reaches the log on its CRC-16 alone when the link shows it corrupts frames: MAVLink's
  CRC-16 misses some errors of four or more flipped bits, so once the driver reports a corrupted frame
  (:meth:`LogDownloader.link_noise`) during the download (or always, ``confirm = "always"``) every
  block is read a second time and kept only when two copies agree; copies that disagree are read
  again and the first value seen twice is kept (a block whose ``max_copies`` copies all differ is kept
  unverified). A valid LOG_DATA no FC sends (off the 90-byte grid, more than 90 bytes) counts as
  such a corrupted frame. A block received twice on any link must agree too. The log's record chain (dataflash
  or ULog, :mod:`firmware_interface.logcheck`) is walked when every block is in: the blocks where it
  breaks are read again, and a break whose blocks two copies confirm is the FC's own. The outcome
  says how it was verified and what was read again, and why (:class:`DownloadCheck`);
* LOG_REQUEST_END is sent when the download completes, fails or is aborted (always once);
  LOG_ERASE is never sent (nor is it on the allowlist);
* ArduPilot ignores every log message while the vehicle is armed: an armed FC fails the download
  at once with a one-line reason; no LOG_DATA for ``give_up_s`` (link up) fails it naming the log
  and how much arrived — the data and bitmap stay available for a later resume.

Events are frozen dataclasses with units in their names. No IO, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.logcheck import log_kind, record_breaks

__all__ = ["BLOCK_BYTES", "DownloadCheck", "DownloadComplete", "DownloadConfig", "DownloadFailed",
           "DownloadProgress", "LogDownloader", "LogEntry", "LogListed", "LogLister", "LogRequestFailed"]

BLOCK_BYTES = 90  # LOG_DATA payload
# what is known of each block (the ``have`` map, also kept in a part file's block map)
MISSING, ONE_COPY, CONFIRMED, SUSPECT, UNRESOLVED = 0, 1, 2, 3, 4
_NEEDED = bytes(1 if v in (MISSING, SUSPECT) else 0 for v in range(256))   # have -> must be read (again)
_ONE_TO_SUSPECT = bytes(SUSPECT if v == ONE_COPY else v for v in range(256))
_RESUMED = bytes(v if v <= SUSPECT else SUSPECT for v in range(256))       # unknown / unresolved: read again
_REASONS = {"confirm": "for a second copy", "disagreed": "whose copies disagreed",
            "structure": "where the records broke"}
_ARMED_REASON = "the FC is armed: ArduPilot serves no logs while armed (land and disarm, then retry)"


@dataclass(frozen=True)
class DownloadConfig:
    """Timing and pacing of list and download requests (seconds, counts)."""

    list_timeout_s: float = 1.5
    list_retries: int = 3
    stall_s: float = 1.0
    retry_s: float = 0.3
    give_up_s: float = 8.0
    link_lost_give_up_s: float = 60.0
    max_in_flight: int = 24
    max_requests_per_s: float = 400.0
    fill_run_bytes: int = 10 * BLOCK_BYTES
    stream_run_bytes: int = 64 * BLOCK_BYTES
    progress_interval_s: float = 0.1
    confirm: str = "noisy"   # "noisy": a second copy of every block once the link corrupts a frame; "always"
    max_copies: int = 6      # copies of one block read before it is kept unverified

    def __post_init__(self) -> None:
        if self.confirm not in ("noisy", "always") or self.max_copies < 3:
            raise ValueError(f"confirm: {self.confirm!r} not 'noisy' or 'always', or max_copies < 3")
        if self.max_in_flight < 1 or not self.max_requests_per_s > 0:
            raise ValueError("max_in_flight must be >= 1 and max_requests_per_s > 0")
        if self.fill_run_bytes < BLOCK_BYTES or self.fill_run_bytes % BLOCK_BYTES:
            raise ValueError(f"fill_run_bytes: {self.fill_run_bytes} must be a multiple of {BLOCK_BYTES}")


@dataclass(frozen=True)
class LogEntry:
    log_id: int
    size_bytes: int
    time_utc_s: int
    num_logs: int


@dataclass(frozen=True)
class LogListed:
    entries: tuple[LogEntry, ...]
    t_host_s: float


@dataclass(frozen=True)
class LogRequestFailed:
    reason: str
    t_host_s: float


@dataclass(frozen=True)
class DownloadProgress:
    """Bytes received; while ``confirming``, bytes whose second copy agrees (or that need none)."""

    log_id: int
    received_bytes: int
    size_bytes: int
    t_host_s: float
    confirming: bool = False


@dataclass(frozen=True)
class DownloadCheck:
    """How a downloaded log was verified end to end, beyond each packet's CRC-16.

    ``verified`` is False only when some block's copies never agreed (``unresolved_offsets``).
    ``reread_blocks`` counts the blocks read again, by why: ``"confirm"`` (the link corrupted
    frames: a second copy of every block), ``"disagreed"`` (two copies differed), ``"structure"``
    (the record chain broke there). ``fc_breaks`` are offsets where the chain breaks in blocks two
    copies confirm: the log is like that on the FC."""

    verified: bool
    how: str
    corrupted_frames: int
    confirmed_blocks: int
    reread_blocks: tuple[tuple[str, int], ...]
    structure: str
    fc_breaks: tuple[int, ...]
    unresolved_offsets: tuple[int, ...]

    def summary(self) -> str:
        """One line: how it was verified, what was read again and why."""
        again = ", ".join(f"{n} {_REASONS[why]}" for why, n in self.reread_blocks if n) or "none"
        head = "verified" if self.verified else (
            f"NOT verified: the copies of {len(self.unresolved_offsets)} block(s) never agreed "
            f"(bytes at {', '.join(map(str, self.unresolved_offsets[:5]))})")
        return f"{head}: {self.how}; {self.structure}; blocks read again: {again}"


@dataclass(frozen=True)
class DownloadComplete:
    log_id: int
    data: bytes
    t_host_s: float
    requests: int
    duplicate_blocks: int
    check: DownloadCheck


@dataclass(frozen=True)
class DownloadFailed:
    log_id: int
    reason: str
    received_bytes: int
    size_bytes: int
    t_host_s: float


class _Requests:
    """Shared by lister and downloader: a pymavlink encoder (messages are packed by the session)."""

    def __init__(self, target: tuple[int, int]) -> None:
        self.target = target
        self._mav = mavlink2.MAVLink(None, 255, 190)
        self._out: list[Any] = []
        self._events: list[Any] = []

    def messages_to_send(self) -> list[Any]:
        out, self._out = self._out, []
        return out

    def events(self) -> list[Any]:
        ev, self._events = self._events, []
        return ev


class LogLister(_Requests):
    """LOG_REQUEST_LIST -> every LOG_ENTRY; retried, failed with a reason (armed, no answer)."""

    def __init__(self, target: tuple[int, int], config: DownloadConfig | None = None) -> None:
        super().__init__(target)
        self.config = config or DownloadConfig()
        self._entries: dict[int, LogEntry] = {}
        self._expected: int | None = None
        self._deadline = math.inf
        self._tries = 0
        self._armed = False
        self.done = False

    def start(self, now: float) -> None:
        self._send(now)

    def _send(self, now: float) -> None:
        self._tries += 1
        self._out.append(self._mav.log_request_list_encode(self.target[0], self.target[1], 0, 0xFFFF))
        self._deadline = now + self.config.list_timeout_s

    def fc_armed(self, armed: bool, now: float) -> None:
        self._armed = bool(armed)

    def receive_message(self, msg: Any, now: float) -> None:
        if self.done or msg.get_type() != "LOG_ENTRY":
            return
        if msg.num_logs == 0:
            self._finish(LogListed((), now))
            return
        self._expected = int(msg.num_logs)
        if msg.id > 0:
            self._entries[int(msg.id)] = LogEntry(int(msg.id), int(msg.size), int(msg.time_utc), int(msg.num_logs))
        self._deadline = now + self.config.list_timeout_s
        if len(self._entries) >= self._expected:
            self._finish(LogListed(tuple(self._entries[k] for k in sorted(self._entries)), now))

    def handle_timer(self, now: float) -> None:
        if self.done or now < self._deadline:
            return
        if self._entries:  # some entries came, the rest were lost: list what we have
            self._finish(LogListed(tuple(self._entries[k] for k in sorted(self._entries)), now))
        elif self._armed:
            self._finish(LogRequestFailed(_ARMED_REASON, now))
        elif self._tries > self.config.list_retries:
            self._finish(LogRequestFailed(
                f"no answer to LOG_REQUEST_LIST after {self._tries} tries "
                f"({self._tries * self.config.list_timeout_s:g} s)", now))
        else:
            self._send(now)

    def _finish(self, ev: Any) -> None:
        self.done = True
        self._deadline = math.inf
        self._events.append(ev)


class LogDownloader(_Requests):
    """One log, whole and byte-exact; see the module docstring."""

    def __init__(self, entry: LogEntry, target: tuple[int, int], config: DownloadConfig | None = None, *,
                 data: bytes | None = None, have: bytes | None = None) -> None:
        super().__init__(target)
        self.entry = entry
        self.config = config or DownloadConfig()
        self.size = int(entry.size_bytes)
        self.n_blocks = -(-self.size // BLOCK_BYTES)
        self.data = bytearray(self.size)
        self.have = bytearray(self.n_blocks)  # MISSING, ONE_COPY, CONFIRMED, SUSPECT, UNRESOLVED per block
        if data is not None and have is not None and len(data) == self.size and len(have) == self.n_blocks:
            self.data[:] = data
            self.have[:] = bytes(have).translate(_RESUMED)
        self.received_blocks = self.n_blocks - self.have.count(MISSING)
        self._need = bytearray(1 if v == MISSING else 0 for v in self.have)   # 1 = to be read (again)
        self._needed = self._need.count(1)
        self._copies: dict[int, list[bytes]] = {}   # block -> the differing copies seen
        self.corrupted_frames = 0
        self.noisy = False
        self.confirming = False
        self._reread = {"confirm": 0, "disagreed": 0, "structure": 0}
        self._fc_breaks: tuple[int, ...] = ()
        self.requests = 0
        self.duplicate_blocks = 0
        self.state = "idle"  # idle, stream, fill, paused, done
        self._last_rx = -math.inf
        self._stream_t = -math.inf
        self._stream_end = self.n_blocks
        self._paused_at = -math.inf
        self._armed = False
        self._in_flight: dict[tuple[int, int], float] = {}  # (first block, n blocks) -> sent at
        self._tokens = float(self.config.max_in_flight)
        self._token_t = -math.inf
        self._next_progress = -math.inf
        self._end_sent = False

    # ------------------------------------------------------------------ state

    @property
    def received_bytes(self) -> int:
        if self.n_blocks and self.have[-1]:
            return (self.received_blocks - 1) * BLOCK_BYTES + (self.size - (self.n_blocks - 1) * BLOCK_BYTES)
        return self.received_blocks * BLOCK_BYTES

    @property
    def settled_bytes(self) -> int:
        """Bytes of the blocks that need no (further) read."""
        return min(self.size, (self.n_blocks - self._needed) * BLOCK_BYTES)

    @property
    def complete(self) -> bool:
        return self._needed == 0

    def partial(self) -> tuple[bytes, bytes]:
        """(data, block map) to keep for a resume: a single copy from a link that corrupted frames
        is kept as one to confirm."""
        have = bytes(self.have).translate(_ONE_TO_SUSPECT) if self._must_confirm() else bytes(self.have)
        return bytes(self.data), have

    def _first_missing(self, start: int = 0) -> int:
        k = self._need.find(1, start)
        return self.n_blocks if k < 0 else k

    def missing_runs(self, limit: int) -> list[tuple[int, int]]:
        """Up to ``limit`` (first block, n blocks) runs of blocks to read (again), whole (not split)."""
        out: list[tuple[int, int]] = []
        k = self._first_missing()
        while k < self.n_blocks and len(out) < limit:
            end = self._need.find(0, k)
            end = self.n_blocks if end < 0 else end
            out.append((k, end - k))
            k = self._first_missing(end)
        return out

    def gap_spans(self, limit: int) -> list[tuple[int, int]]:
        """Up to ``limit`` spans to re-request: nearby short runs merged into spans of at most
        ``fill_run_bytes`` (a few received blocks inside are cheaper than another request); a run
        longer than that stays whole."""
        cap = self.config.fill_run_bytes // BLOCK_BYTES
        whole = self.config.stream_run_bytes // BLOCK_BYTES
        spans: list[tuple[int, int]] = []
        for k, n in self.missing_runs(limit * cap):
            if spans and n <= cap and spans[-1][1] <= cap and k + n - spans[-1][0] <= cap:
                spans[-1] = (spans[-1][0], k + n - spans[-1][0])
                continue
            if n > whole:
                spans.append((k, n))
            else:
                spans.extend((a, min(cap, k + n - a)) for a in range(k, k + n, cap))
            if len(spans) >= limit:
                break
        return spans[:limit]

    # ------------------------------------------------------------------ inputs

    def start(self, now: float) -> None:
        if self._armed:
            self._fail(_ARMED_REASON, now)
            return
        if self.complete:
            self._settle(now)
            return
        self._stream(now)

    def link_noise(self, frames: int, now: float) -> None:
        """The driver saw ``frames`` more frames fail their CRC on the link during the download."""
        if frames > 0 and self.state != "done":
            self.corrupted_frames += frames
            self.noisy = True

    def fc_armed(self, armed: bool, now: float) -> None:
        self._armed = bool(armed)
        if armed and self.state in ("stream", "fill"):
            self._fail(f"log {self.entry.log_id}: {_ARMED_REASON}", now)

    def link_lost(self, now: float) -> None:
        if self.state in ("stream", "fill"):
            self.state = "paused"
            self._paused_at = now
            self._in_flight.clear()

    def link_restored(self, now: float) -> None:
        if self.state == "paused":
            self._stream(now)

    def abort(self, now: float, reason: str) -> None:
        if self.state != "done":
            self._fail(reason, now)

    def receive_message(self, msg: Any, now: float) -> None:
        if self.state in ("done", "idle") or msg.get_type() != "LOG_DATA" or msg.id != self.entry.log_id:
            return
        if self.state == "paused":  # data flows again before the driver said so
            self.state = "stream"
        self._last_rx = now
        ofs, count = int(msg.ofs), int(msg.count)
        if ofs % BLOCK_BYTES or count > BLOCK_BYTES:
            self.link_noise(1, now)  # no FC sends this (we ask for whole blocks): an error the CRC missed
            return
        if count <= 0 or ofs >= self.size:
            if self.state == "stream":
                self._enter_fill(now)  # end of file reached
            return
        k = ofs // BLOCK_BYTES
        block = bytes(msg.data[:min(count, self.size - ofs)])
        if self.have[k] == MISSING:
            self.data[ofs:ofs + len(block)] = block
            self.have[k] = ONE_COPY
            self.received_blocks += 1
            self._set_need(k, False)
        else:
            self.duplicate_blocks += 1
            self._another_copy(k, block)
        if self.complete:
            self._settle(now)
            return
        if self.state == "stream" and k >= self._stream_end - 1:
            self._enter_fill(now)  # the stream's last block: what is still missing is a gap
        elif self.state == "fill":
            self._resolve(k)
            self._check_in_flight(now)
        self._progress(now)

    def _set_need(self, k: int, need: bool) -> None:
        if self._need[k] != need:
            self._need[k] = need
            self._needed += 1 if need else -1

    def _another_copy(self, k: int, block: bytes) -> None:
        """A further copy of block ``k``: two copies that agree confirm it; copies that differ are
        read again until one value has come twice (that one is kept)."""
        state = self.have[k]
        ofs = k * BLOCK_BYTES
        if state in (CONFIRMED, UNRESOLVED):
            return
        copies = self._copies.get(k)
        if copies is None and bytes(self.data[ofs:ofs + len(block)]) == block:
            self.have[k] = CONFIRMED
            self._set_need(k, False)
            return
        if copies is None:
            copies = self._copies[k] = [bytes(self.data[ofs:ofs + len(block)])]
            self._reread["disagreed"] += 1
        if block in copies:   # the first value seen twice
            self.data[ofs:ofs + len(block)] = block
            self.have[k] = CONFIRMED
            del self._copies[k]
            self._set_need(k, False)
            return
        copies.append(block)
        self.have[k] = SUSPECT if len(copies) < self.config.max_copies else UNRESOLVED
        self._set_need(k, self.have[k] == SUSPECT)

    def _resolve(self, k: int) -> None:
        """The FC answers requests in order: block ``k`` arriving means every gap request sent before
        the one holding ``k`` is answered (what is still missing there was lost), and so is that one
        when ``k`` is its last block."""
        keys = list(self._in_flight)
        hit = next((i for i, (a, n) in enumerate(keys) if a <= k < a + n), None)
        if hit is None:
            return
        a, n = keys[hit]
        for key in keys[:hit + 1 if k == a + n - 1 else hit]:
            del self._in_flight[key]

    def handle_timer(self, now: float) -> None:
        if self.state == "paused":
            if now - self._paused_at > self.config.link_lost_give_up_s:
                self._fail(self._stopped(f"the link stayed down for {self.config.link_lost_give_up_s:g} s"), now)
            return
        if self.state not in ("stream", "fill"):
            return
        if now - self._last_rx > self.config.give_up_s:
            why = _ARMED_REASON if self._armed else f"the FC stopped answering for {self.config.give_up_s:g} s"
            self._fail(self._stopped(why), now)
            return
        if self.state == "stream" and now - max(self._last_rx, self._stream_t) > self.config.stall_s:
            self._enter_fill(now)
        elif self.state == "fill":
            self._check_in_flight(now)

    # ------------------------------------------------------------------ requests

    def _request(self, ofs: int, count: int, now: float) -> None:
        self.requests += 1
        self._out.append(self._mav.log_request_data_encode(self.target[0], self.target[1], self.entry.log_id,
                                                           ofs, count))

    def _stream(self, now: float) -> None:
        self.state = "stream"
        self._last_rx = self._stream_t = now  # give-up and stall are counted from here
        self._in_flight.clear()
        ofs = self._first_missing() * BLOCK_BYTES
        self._stream_end = self.n_blocks
        self._request(ofs, self.size - ofs, now)

    def _enter_fill(self, now: float) -> None:
        self.state = "fill"
        self._in_flight.clear()
        self._check_in_flight(now)

    def _check_in_flight(self, now: float) -> None:
        """Drop answered or expired gap requests; send new ones within the in-flight and rate bounds."""
        cfg = self.config
        for key, sent in list(self._in_flight.items()):
            k, n = key
            if not any(self._need[k:k + n]) or now - sent > cfg.retry_s:
                del self._in_flight[key]
        if self._token_t > -math.inf:
            self._tokens = min(float(cfg.max_in_flight), self._tokens + (now - self._token_t) * cfg.max_requests_per_s)
        self._token_t = now
        free = cfg.max_in_flight - len(self._in_flight)
        if free <= 0 or self._tokens < 1.0:
            return
        cap = cfg.fill_run_bytes // BLOCK_BYTES
        for k, n in self.gap_spans(cfg.max_in_flight + len(self._in_flight)):
            if free <= 0 or self._tokens < 1.0:
                break
            if any(a <= k < a + m for a, m in self._in_flight):
                continue
            self._tokens -= 1.0
            free -= 1
            ofs = k * BLOCK_BYTES
            if n > cap:
                # a long run (the stream was cut): stream it; the FC answers the gap requests sent
                # before this one at once and carries on with this one
                self.state = "stream"
                self._stream_t = now
                self._stream_end = k + n
                self._in_flight.clear()
                self._request(ofs, min(n * BLOCK_BYTES, self.size - ofs), now)
                return
            self._in_flight[(k, n)] = now
            self._request(ofs, min(n * BLOCK_BYTES, self.size - ofs), now)

    # ------------------------------------------------------------------ outcomes

    def _stopped(self, why: str) -> str:
        return (f"log {self.entry.log_id}: {why}; {self.received_bytes} of {self.size} bytes received "
                f"({self.n_blocks - self.received_blocks} blocks missing)")

    def _end(self) -> None:
        if not self._end_sent:
            self._end_sent = True
            self._out.append(self._mav.log_request_end_encode(self.target[0], self.target[1]))

    def _progress(self, now: float) -> None:
        if now >= self._next_progress:
            self._next_progress = now + self.config.progress_interval_s
            got = self.settled_bytes if self.confirming else self.received_bytes
            self._events.append(DownloadProgress(self.entry.log_id, got, self.size, now, self.confirming))

    # ------------------------------------------------------------------ verification

    def _must_confirm(self) -> bool:
        return self.noisy or self.config.confirm == "always"

    def _settle(self, now: float) -> None:
        """Every block is in: ask for second copies (a link that corrupts frames) and for the blocks
        where the record chain breaks; succeed when nothing is left to read."""
        if self._must_confirm():
            self._reread["confirm"] += self.have.count(ONE_COPY)
            self.have[:] = bytes(self.have).translate(_ONE_TO_SUSPECT)
        self._blame_breaks()
        self._need[:] = bytes(self.have).translate(_NEEDED)
        self._needed = self._need.count(1)
        if not self._needed:
            self._succeed(now)
            return
        self.confirming = True
        self._progress(now)
        self._enter_fill(now)

    def _blame_breaks(self) -> None:
        """Single copies where the record chain breaks are read again; breaks within confirmed
        blocks only are the FC's own."""
        fc_breaks = []
        for start, end in record_breaks(self.data):
            blocks = range(start // BLOCK_BYTES, min(self.n_blocks, -(-end // BLOCK_BYTES)))
            single = [k for k in blocks if self.have[k] == ONE_COPY]
            for k in single:
                self.have[k] = SUSPECT
            self._reread["structure"] += len(single)
            if not single and not any(self.have[k] == SUSPECT for k in blocks):
                fc_breaks.append(start)
        self._fc_breaks = tuple(fc_breaks)

    def _check(self) -> DownloadCheck:
        unresolved = tuple(k * BLOCK_BYTES for k in range(self.n_blocks) if self.have[k] == UNRESOLVED)
        confirmed = self.have.count(CONFIRMED)
        single = self.have.count(ONE_COPY)
        if not single:
            how = "every block read twice, two copies agree"
        else:
            how = (f"{single} of {self.n_blocks} blocks on their CRC-16 alone (the link corrupted no frame)"
                   + (f", {confirmed} read twice" if confirmed else ""))
        if self.noisy:
            how += f" ({self.corrupted_frames} corrupted frames on the link)"
        kind = log_kind(self.data)
        if kind == "unknown":
            structure = "record structure not checked (neither dataflash nor ULog)"
        elif self._fc_breaks:
            structure = (f"{kind} records break at {len(self._fc_breaks)} place(s) that two copies confirm "
                         f"(so on the FC; first at byte {self._fc_breaks[0]})")
        else:
            structure = f"{kind} records parse end to end"
        return DownloadCheck(not unresolved, how, self.corrupted_frames, confirmed,
                             tuple(self._reread.items()), structure, self._fc_breaks, unresolved)

    def _succeed(self, now: float) -> None:
        self.state = "done"
        self._end()
        self._events.append(DownloadProgress(self.entry.log_id, self.size, self.size, now, self.confirming))
        self._events.append(DownloadComplete(self.entry.log_id, bytes(self.data), now, self.requests,
                                             self.duplicate_blocks, self._check()))

    def _fail(self, reason: str, now: float) -> None:
        self.state = "done"
        self._end()
        self._events.append(DownloadFailed(self.entry.log_id, reason, self.received_bytes, self.size, now))
