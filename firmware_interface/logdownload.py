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

__all__ = ["BLOCK_BYTES", "DownloadComplete", "DownloadConfig", "DownloadFailed", "DownloadProgress",
           "LogDownloader", "LogEntry", "LogListed", "LogLister", "LogRequestFailed"]

BLOCK_BYTES = 90  # LOG_DATA payload
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

    def __post_init__(self) -> None:
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
    log_id: int
    received_bytes: int
    size_bytes: int
    t_host_s: float


@dataclass(frozen=True)
class DownloadComplete:
    log_id: int
    data: bytes
    t_host_s: float
    requests: int
    duplicate_blocks: int


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
        self.have = bytearray(self.n_blocks)  # 1 = block received
        if data is not None and have is not None and len(data) == self.size and len(have) == self.n_blocks:
            self.data[:] = data
            self.have[:] = have
        self.received_blocks = sum(self.have)
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
    def complete(self) -> bool:
        return self.received_blocks == self.n_blocks

    def _first_missing(self, start: int = 0) -> int:
        k = self.have.find(0, start)
        return self.n_blocks if k < 0 else k

    def missing_runs(self, limit: int) -> list[tuple[int, int]]:
        """Up to ``limit`` (first block, n blocks) runs of missing blocks, whole (not split)."""
        out: list[tuple[int, int]] = []
        k = self._first_missing()
        while k < self.n_blocks and len(out) < limit:
            end = self.have.find(1, k)
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
            self._succeed(now)
            return
        self._stream(now)

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
        if ofs % BLOCK_BYTES or count <= 0 or ofs >= self.size:
            if self.state == "stream" and (count == 0 or ofs >= self.size):
                self._enter_fill(now)  # end of file reached
            return
        k = ofs // BLOCK_BYTES
        n = min(count, self.size - ofs)
        if self.have[k]:
            self.duplicate_blocks += 1
        else:
            self.data[ofs:ofs + n] = bytes(msg.data[:n])
            self.have[k] = 1
            self.received_blocks += 1
        if self.complete:
            self._succeed(now)
            return
        if self.state == "stream" and k >= self._stream_end - 1:
            self._enter_fill(now)  # the stream's last block: what is still missing is a gap
        elif self.state == "fill":
            self._resolve(k)
            self._check_in_flight(now)
        self._progress(now)

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
            if all(self.have[k:k + n]) or now - sent > cfg.retry_s:
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
            self._events.append(DownloadProgress(self.entry.log_id, self.received_bytes, self.size, now))

    def _succeed(self, now: float) -> None:
        self.state = "done"
        self._end()
        self._events.append(DownloadProgress(self.entry.log_id, self.size, self.size, now))
        self._events.append(DownloadComplete(self.entry.log_id, bytes(self.data), now, self.requests,
                                             self.duplicate_blocks))

    def _fail(self, reason: str, now: float) -> None:
        self.state = "done"
        self._end()
        self._events.append(DownloadFailed(self.entry.log_id, reason, self.received_bytes, self.size, now))
