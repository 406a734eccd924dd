"""The async link driver: opens the transport, pumps bytes between it and a :class:`MavlinkSession`,
reconnects with backoff. Used by ``groundstation record`` and by the service.

:class:`LinkRunner` opens the link from an opener (``lambda: open_link(url)``), reads from it, stamps
each chunk with the injected host clock, feeds the session, hands the session's events to a
callback, and writes whatever the session wants to send (heartbeats, stream requests) -- checking
the session's timers every ``tick_s`` even while the link is silent. When the transport raises
:class:`~firmware_interface.transports.LinkDown` it tells the session (LinkLost event), closes the
link and opens it again with exponential backoff (``backoff_s`` doubling up to ``backoff_max_s``);
the session emits LinkRestored on the first valid frame after that.

A serial port that does not exist yet (:class:`~firmware_interface.transports.PortMissing`: the
flight controller is not plugged in) is waited for, with one line ``waiting for PATH`` at most
every ``wait_log_s`` seconds; any other error opening the link the first time is raised (a path that
is not a serial device, a bad URL). :meth:`LinkRunner.stop` ends waiting and pumping at once.

Time is injected (``clock`` for timestamps and the log interval, ``sleep`` for the backoff), so the
driver runs in tests on a :class:`~firmware_interface.transports.ScriptedLink` with a fake clock.
Leaves recording and processing to the callback's owner.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any

from firmware_interface.session import MavlinkSession
from firmware_interface.transports import Link, LinkDown, PortMissing, TransportError

__all__ = ["LinkRunner"]


class LinkRunner:
    """Drive ``session`` over the link ``opener`` opens; ``on_events(list)`` receives every batch of events.

    Parameters
    ----------
    opener : ``async () -> Link``, called for the first open and after each loss; or an already
        open :class:`Link` (it is then only reopened if it is lost -- which needs an opener)
    clock : host clock in Unix seconds (injectable)
    sleep : ``async sleep(seconds)`` used for the backoff (injectable)
    tick_s : how often timers run while no bytes arrive
    log : one-line messages for the operator (waiting for the port, link lost, reopened)
    on_link_up, on_link_down : called with the open link / the reason it was lost
    """

    def __init__(self, opener: Callable[[], Awaitable[Link]] | Link, session: MavlinkSession,
                 on_events: Callable[[list[Any]], None], *, clock: Callable[[], float] = time.time,
                 sleep: Callable[[float], Awaitable[Any]] = asyncio.sleep, tick_s: float = 0.1,
                 backoff_s: float = 0.1, backoff_max_s: float = 2.0, wait_log_s: float = 10.0,
                 log: Callable[[str], None] | None = None,
                 on_link_up: Callable[[Link], None] | None = None,
                 on_link_down: Callable[[str], None] | None = None) -> None:
        if isinstance(opener, Link):
            self.link: Link | None = opener
            self.opener: Callable[[], Awaitable[Link]] | None = None
        else:
            self.link, self.opener = None, opener
        self.session = session
        self.on_events = on_events
        self.clock = clock
        self.sleep = sleep
        self.tick_s = tick_s
        self.backoff_s, self.backoff_max_s, self.wait_log_s = backoff_s, backoff_max_s, wait_log_s
        self.log = log or (lambda msg: None)
        self.on_link_up = on_link_up
        self.on_link_down = on_link_down
        self.bytes_received = 0
        self.reconnects = 0
        self.opens = 0
        self._stop = asyncio.Event()

    def stop(self) -> None:
        """Ask :meth:`connect` / :meth:`run` to return after the current step."""
        self._stop.set()

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    # ------------------------------------------------------------------ opening

    async def connect(self) -> Link | None:
        """Open the link if it is not open: waits for a missing serial port and retries a lost one
        with backoff; returns ``None`` if stopped first. The first failure other than a missing port
        is raised (TransportError naming the URL)."""
        if self.link is not None:
            return self.link
        if self.opener is None:
            raise TransportError("link lost and no way to reopen it (LinkRunner was given a link, not an opener)")
        delay, next_wait_log = self.backoff_s, float("-inf")
        while not self.stopped:
            try:
                link = await self.opener()
            except PortMissing as exc:
                now = self.clock()
                if now >= next_wait_log:
                    self.log(f"waiting for {exc.path}")
                    next_wait_log = now + self.wait_log_s
            except OSError:
                if self.opens == 0:
                    raise                           # never opened: a wrong path or URL, not a cable
            else:
                self._opened(link)
                return link
            await self._sleep(delay)
            delay = min(2 * delay, self.backoff_max_s)
        return None

    def _opened(self, link: Link) -> None:
        self.link = link
        self.opens += 1
        if self.opens > 1:
            self.reconnects += 1
        if self.on_link_up is not None:
            self.on_link_up(link)

    async def _sleep(self, seconds: float) -> None:
        """The injected sleep, cut short by :meth:`stop`."""
        nap = asyncio.ensure_future(self.sleep(seconds))
        waiter = asyncio.ensure_future(self._stop.wait())
        try:
            await asyncio.wait({nap, waiter}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in (nap, waiter):
                t.cancel()

    # ------------------------------------------------------------------ pumping

    def _flush_events(self) -> None:
        ev = self.session.events()
        if ev:
            self.on_events(ev)

    async def run(self) -> None:
        """Open (see :meth:`connect`) and pump until :meth:`stop` (or cancellation)."""
        if self.link is not None and self.opens == 0:
            self._opened(self.link)
        next_tick = 0.0
        while not self.stopped:
            link = self.link or await self.connect()
            if link is None:
                break
            try:
                data = await self._read_or_tick(link)
                now = self.clock()
                if data:
                    self.bytes_received += len(data)
                    self.session.receive_data(data, now)
                if data or now >= next_tick:
                    out = self.session.data_to_send(now)
                    if out:
                        await link.write(out)
                    next_tick = now + self.tick_s
            except LinkDown as exc:
                self._flush_events()
                await self._link_down(link, str(exc))
                continue
            self._flush_events()
        self._flush_events()

    async def _read_or_tick(self, link: Link) -> bytes:
        """The next chunk, or b"" after ``tick_s`` of silence or on :meth:`stop`."""
        read = asyncio.ensure_future(link.read())
        waiter = asyncio.ensure_future(self._stop.wait())
        try:
            done, _ = await asyncio.wait({read, waiter}, timeout=self.tick_s, return_when=asyncio.FIRST_COMPLETED)
        except BaseException:          # cancelled from outside: the read must not outlive us
            read.cancel()
            raise
        finally:
            waiter.cancel()
        if read in done:
            return read.result()
        read.cancel()
        try:
            await read
        except (asyncio.CancelledError, LinkDown):
            pass
        return b""

    async def _link_down(self, link: Link, reason: str) -> None:
        self.session.link_down(self.clock(), reason)
        self._flush_events()
        self.link = None
        try:
            await link.close()
        except OSError:
            pass
        if self.on_link_down is not None:
            self.on_link_down(reason)
