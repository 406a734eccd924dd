"""LinkRunner against an in-memory scripted link (a fake transport, not a mock)."""

from __future__ import annotations

import asyncio

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.link import LinkRunner
from firmware_interface.samples import Attitude, LinkLost, LinkRestored
from firmware_interface.session import MavlinkSession, SessionConfig
from firmware_interface.transports import Link, LinkDown

from .conftest import FakeFc


class ScriptedLink(Link):
    """Delivers scripted chunks; an exception in the script is raised from read()."""

    def __init__(self, script) -> None:
        self.url = "script://"
        self.script = list(script)
        self.written = bytearray()
        self.reconnects = 0
        self.backoff_s = 0.01

    async def read(self) -> bytes:
        while True:
            if self.script:
                item = self.script.pop(0)
                if isinstance(item, BaseException):
                    raise item
                if isinstance(item, float):
                    await asyncio.sleep(item)
                    continue
                return item
            await asyncio.sleep(3600)

    async def write(self, data: bytes) -> None:
        self.written += data

    async def close(self) -> None:
        pass

    async def _open(self) -> None:
        self.reconnects += 1


def test_runner_answers_heartbeat_survives_link_down_and_stops():
    fc = FakeFc()
    script = [fc.heartbeat() + fc.attitude(1000), 0.05, LinkDown("script://: gone"), fc.attitude(2000)]
    link = ScriptedLink(script)
    events: list = []
    t = [100.0]

    def clock() -> float:
        t[0] += 0.01
        return t[0]

    session = MavlinkSession(SessionConfig(stream_rates_hz=(("ATTITUDE", 50.0),)))
    runner = LinkRunner(link, session, events.extend, clock=clock, tick_s=0.01)

    async def main():
        task = asyncio.ensure_future(runner.run())
        await asyncio.sleep(0.3)
        runner.stop()
        await asyncio.wait_for(task, 2.0)

    asyncio.run(main())
    kinds = [type(e) for e in events]
    assert kinds.count(Attitude) == 2
    assert kinds.index(LinkLost) < kinds.index(LinkRestored)
    assert link.reconnects == 1 and runner.reconnects == 1
    p = mavlink2.MAVLink(None)
    sent = [m.get_type() for m in p.parse_buffer(bytes(link.written)) or []]
    assert sent[:2] == ["HEARTBEAT", "COMMAND_LONG"]
