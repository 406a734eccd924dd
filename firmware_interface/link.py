"""The async driver that pumps bytes between a transport and a :class:`MavlinkSession`.

:class:`LinkRunner` reads from a :class:`~firmware_interface.transports.Link`, stamps each chunk with
the host clock, feeds the session, hands the session's events to a callback, and writes whatever the
session wants to send (heartbeats, stream requests) — checking the session's timers every
``tick_s`` even while the link is silent. When the transport raises
:class:`~firmware_interface.transports.LinkDown` it tells the session (LinkLost event), reconnects
with backoff, and carries on; the session emits LinkRestored on the first valid frame after that.

Used by ``groundstation record`` and by the service. Leaves recording and processing to the
callback's owner.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

from firmware_interface.session import MavlinkSession
from firmware_interface.transports import Link, LinkDown

__all__ = ["LinkRunner"]


class LinkRunner:
    """Drive ``session`` over ``link``; ``on_events(list)`` receives every batch of events.

    Parameters
    ----------
    clock : host clock in Unix seconds (injectable)
    tick_s : how often timers run while no bytes arrive
    """

    def __init__(self, link: Link, session: MavlinkSession, on_events: Callable[[list[Any]], None], *,
                 clock: Callable[[], float] = time.time, tick_s: float = 0.1) -> None:
        self.link = link
        self.session = session
        self.on_events = on_events
        self.clock = clock
        self.tick_s = tick_s
        self.bytes_received = 0
        self.reconnects = 0
        self._stop = asyncio.Event()

    def stop(self) -> None:
        """Ask :meth:`run` to return after the current step."""
        self._stop.set()

    def _flush_events(self) -> None:
        ev = self.session.events()
        if ev:
            self.on_events(ev)

    async def _send(self, now: float) -> None:
        out = self.session.data_to_send(now)
        if out:
            await self.link.write(out)

    async def run(self) -> None:
        """Pump until :meth:`stop` (or cancellation)."""
        session = self.session
        stop = self._stop
        next_tick = 0.0
        while not stop.is_set():
            read = asyncio.ensure_future(self.link.read())
            waiter = asyncio.ensure_future(stop.wait())
            try:
                done, _ = await asyncio.wait({read, waiter}, timeout=self.tick_s,
                                             return_when=asyncio.FIRST_COMPLETED)
            finally:
                waiter.cancel()
            data = b""
            if read in done:
                try:
                    data = read.result()
                except LinkDown as exc:
                    await self._link_down(str(exc))
                    continue
            else:
                read.cancel()
                try:
                    await read
                except (asyncio.CancelledError, LinkDown):
                    pass
            now = self.clock()
            if data:
                self.bytes_received += len(data)
                session.receive_data(data, now)
            if data or now >= next_tick:
                try:
                    await self._send(now)
                except LinkDown as exc:
                    self._flush_events()
                    await self._link_down(str(exc))
                    continue
                next_tick = now + self.tick_s
            self._flush_events()
        self._flush_events()

    async def _link_down(self, reason: str) -> None:
        self.session.link_down(self.clock(), reason)
        self._flush_events()
        recon = asyncio.ensure_future(self.link.reconnect())
        waiter = asyncio.ensure_future(self._stop.wait())
        try:
            await asyncio.wait({recon, waiter}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            waiter.cancel()
        if recon.done():
            recon.result()
            self.reconnects += 1
        else:
            recon.cancel()
            try:
                await recon
            except asyncio.CancelledError:
                pass
