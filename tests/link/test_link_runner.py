"""The link driver (LinkRunner) on the in-memory ScriptedLink with a fake clock and a fake sleep:
no pty, no real waiting. The serial path itself is tested in test_transports.py."""

from __future__ import annotations

import asyncio

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.link import LinkRunner
from firmware_interface.samples import Attitude, LinkLost, LinkRestored
from firmware_interface.session import MavlinkSession, SessionConfig
from firmware_interface.transports import LinkDown, PortMissing, ScriptedLink, TransportError

from .conftest import FakeFc


class FakeTime:
    """Host clock that only moves when the driver sleeps (the backoff)."""

    def __init__(self, t0: float = 1000.0) -> None:
        self.t = t0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.t

    async def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.t += seconds
        await asyncio.sleep(0)


class Opener:
    """Returns the scripted outcomes in turn (a link, or an exception to raise); then waits forever."""

    def __init__(self, *outcomes) -> None:
        self.outcomes = list(outcomes)
        self.calls = 0

    async def __call__(self):
        self.calls += 1
        if not self.outcomes:
            await asyncio.Event().wait()
        item = self.outcomes.pop(0)
        if isinstance(item, BaseException):
            raise item
        return item


def _session() -> MavlinkSession:
    return MavlinkSession(SessionConfig(stream_rates_hz=(("ATTITUDE", 50.0),)))


def test_runner_answers_heartbeat_survives_link_down_and_stops():
    fc = FakeFc()
    first = ScriptedLink([fc.heartbeat() + fc.attitude(1000), LinkDown("script://: gone")])
    second = ScriptedLink([fc.attitude(2000)])
    ft = FakeTime()
    events: list = []
    ups: list = []
    downs: list[str] = []

    def on_events(evs):
        events.extend(evs)
        if sum(isinstance(e, Attitude) for e in events) == 2:
            runner.stop()

    runner = LinkRunner(Opener(first, PortMissing("script://: unplugged", "/dev/ttyX"), second), _session(),
                        on_events, clock=ft.clock, sleep=ft.sleep, tick_s=0.01,
                        on_link_up=ups.append, on_link_down=downs.append)
    asyncio.run(asyncio.wait_for(runner.run(), 10))
    kinds = [type(e) for e in events]
    assert kinds.count(Attitude) == 2
    assert kinds.index(LinkLost) < kinds.index(LinkRestored)
    assert ups == [first, second] and downs == ["script://: gone"] and first.closed
    assert runner.reconnects == 1 and ft.sleeps == [0.1]           # one failed reopen, one backoff step
    p = mavlink2.MAVLink(None)
    sent = [m.get_type() for m in p.parse_buffer(bytes(first.written)) or []]
    assert sent[:2] == ["HEARTBEAT", "COMMAND_LONG"]


def test_missing_port_is_waited_for_with_one_line_at_most_every_10_s():
    ft = FakeTime()
    missing = [PortMissing("serial:///dev/ttyUSB0:921600: no such port", "/dev/ttyUSB0") for _ in range(60)]
    link = ScriptedLink()
    lines: list[tuple[float, str]] = []
    runner = LinkRunner(Opener(*missing, link), _session(), lambda evs: None, clock=ft.clock, sleep=ft.sleep,
                        backoff_s=0.1, backoff_max_s=1.0, log=lambda m: lines.append((ft.t, m)))
    got = asyncio.run(asyncio.wait_for(runner.connect(), 10))
    assert got is link and runner.opens == 1
    waited_s = ft.t - 1000.0
    assert waited_s > 50                                   # 60 failed opens, backoff capped at 1 s
    assert all(m == "waiting for /dev/ttyUSB0" for _, m in lines)
    times = [t for t, _ in lines]
    assert all(b - a >= 10.0 for a, b in zip(times, times[1:], strict=False))
    assert int(waited_s // 10) - 1 <= len(lines) <= int(waited_s // 10) + 1
    assert max(ft.sleeps) == 1.0


def test_stop_ends_the_wait_for_a_port():
    never = PortMissing("serial:///dev/ttyUSB0: no such port", "/dev/ttyUSB0")

    async def main():
        lines: list[str] = []

        async def sleep_forever(seconds):
            await asyncio.Event().wait()

        runner = LinkRunner(Opener(never), _session(), lambda evs: None, sleep=sleep_forever, log=lines.append)
        task = asyncio.ensure_future(runner.connect())
        while not lines:                                   # until it says it is waiting
            await asyncio.sleep(0)
        runner.stop()
        return await asyncio.wait_for(task, 5), lines

    got, lines = asyncio.run(main())
    assert got is None and lines == ["waiting for /dev/ttyUSB0"]


def test_a_first_open_error_other_than_a_missing_port_is_raised():
    bad = TransportError("serial:///tmp/x: /tmp/x is not a serial device")
    runner = LinkRunner(Opener(bad), _session(), lambda evs: None, sleep=FakeTime().sleep)
    with pytest.raises(TransportError, match="not a serial device"):
        asyncio.run(runner.connect())


def test_after_a_loss_any_open_error_is_retried():
    fc = FakeFc()
    first = ScriptedLink([fc.heartbeat(), LinkDown("tcp://x: reset")])
    second = ScriptedLink([fc.attitude(3000)])
    ft = FakeTime()
    events: list = []

    def on_events(evs):
        events.extend(evs)
        if any(isinstance(e, Attitude) for e in events):
            runner.stop()

    refused = [TransportError("tcp://x: cannot connect (refused)") for _ in range(3)]
    runner = LinkRunner(Opener(first, *refused, second), _session(), on_events, clock=ft.clock, sleep=ft.sleep,
                        tick_s=0.01)
    asyncio.run(asyncio.wait_for(runner.run(), 10))
    assert runner.reconnects == 1 and ft.sleeps == [0.1, 0.2, 0.4]
