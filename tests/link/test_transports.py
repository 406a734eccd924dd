"""Transports over real pseudo-terminals (pyserial), UDP and TCP sockets on loopback."""

from __future__ import annotations

import asyncio
import socket

import pytest

from firmware_interface.errors import TransportError
from firmware_interface.link import LinkRunner
from firmware_interface.recorder import Recorder
from firmware_interface.samples import Attitude, LinkLost, LinkRestored, RawPacket
from firmware_interface.session import MavlinkSession, SessionConfig
from firmware_interface.tlogread import scan_tlog
from firmware_interface.transports import LinkDown, PortMissing, open_link, parse_url

from .conftest import FakeFc


def test_parse_url_forms_and_errors():
    u = parse_url("serial:///dev/ttyUSB0:921600")
    assert (u.scheme, u.path, u.baud) == ("serial", "/dev/ttyUSB0", 921600)
    assert parse_url("serial:///dev/ttyACM0").baud == 115200
    assert parse_url("pty:///tmp/x/ttyFC:57600").path == "/tmp/x/ttyFC"
    v = parse_url("udpin://0.0.0.0:14550")
    assert (v.scheme, v.host, v.port) == ("udpin", "0.0.0.0", 14550)
    assert parse_url("tcp://127.0.0.1:5760").port == 5760
    for bad, needle in [("ftp://x:1", "unknown link scheme"), ("serial:///dev/ttyS0:fast", "baud"),
                        ("udpin://0.0.0.0", "HOST:PORT"), ("serial://", "no device path")]:
        with pytest.raises(TransportError, match=needle) as ei:
            parse_url(bad)
        assert bad in str(ei.value)


def test_nonexistent_serial_port_names_the_port(tmp_path):
    url = f"serial://{tmp_path}/ttyNOPE:115200"
    with pytest.raises(PortMissing, match="no such port") as ei:
        asyncio.run(open_link(url))
    assert url in str(ei.value) and ei.value.path == f"{tmp_path}/ttyNOPE"


def test_a_path_that_is_not_a_serial_device_is_an_error(tmp_path):
    f = tmp_path / "notes.txt"
    f.write_text("hello")
    url = f"serial://{f}:115200"
    with pytest.raises(TransportError, match="is not a serial device") as ei:
        asyncio.run(open_link(url))
    assert not isinstance(ei.value, PortMissing) and url in str(ei.value)
    runner = LinkRunner(lambda: open_link(url), MavlinkSession(), lambda evs: None)
    with pytest.raises(TransportError, match="is not a serial device"):     # the driver does not wait for it
        asyncio.run(runner.connect())


async def _read_until(link, n: int, timeout_s: float = 10.0) -> bytes:
    out = b""
    async with asyncio.timeout(timeout_s):
        while len(out) < n:
            out += await link.read()
    return out


async def _pty_output(port, n: int, timeout_s: float = 10.0) -> bytes:
    """What the link wrote to the pty, once ``n`` bytes are there (polled: the pty has no event)."""
    out = b""
    async with asyncio.timeout(timeout_s):
        while len(out) < n:
            out += port.read_available()
            await asyncio.sleep(0.01)
    return out


def test_serial_over_pty_reads_writes_and_reports_unplug(bare_pty):
    fc = FakeFc()

    async def main():
        link = await open_link(f"serial://{bare_pty.path}:921600")
        a = fc.heartbeat() + fc.attitude(1000)
        bare_pty.write(a)
        assert await _read_until(link, len(a)) == a
        await link.write(b"\xfdhello")
        assert await _pty_output(bare_pty, 6) == b"\xfdhello"
        bare_pty.unplug()                                   # the device vanishes
        with pytest.raises(LinkDown):
            await asyncio.wait_for(link.read(), 5.0)
        await link.close()
        with pytest.raises(PortMissing):
            await open_link(f"serial://{bare_pty.path}:921600")
        bare_pty.replug()
        again = await open_link(f"serial://{bare_pty.path}:921600")
        b = fc.attitude(2000)
        bare_pty.write(b)
        assert await _read_until(again, len(b)) == b
        await again.close()

    asyncio.run(main())


def test_runner_session_recorder_over_pty_with_unplug(bare_pty, tmp_path):
    fc = FakeFc()
    before = [fc.heartbeat(armed=True)] + [fc.attitude(1000 + 20 * k) for k in range(50)]
    after = [fc.attitude(5000 + 20 * k) for k in range(50)] + [fc.heartbeat(armed=False)]
    events: list = []
    rec = Recorder(tmp_path / "out")
    url = f"serial://{bare_pty.path}:115200"

    async def main():
        seen = asyncio.Event()
        lost = asyncio.Event()
        up = asyncio.Event()
        session = MavlinkSession(SessionConfig(stream_rates_hz=(("ATTITUDE", 50.0),), link_timeout_s=30))

        def on_events(evs):
            events.extend(evs)
            rec.handle(evs)
            n = sum(isinstance(e, Attitude) for e in events)
            if n == 50:
                seen.set()
            if n == 100 and any(isinstance(e, LinkRestored) for e in events):
                runner.stop()

        runner = LinkRunner(lambda: open_link(url), session, on_events, tick_s=0.05, backoff_s=0.05,
                            on_link_up=lambda link: up.set(), on_link_down=lambda reason: lost.set())
        task = asyncio.ensure_future(runner.run())
        async with asyncio.timeout(30):
            await up.wait()
            up.clear()
            bare_pty.write(b"".join(before))
            await seen.wait()
            # the GCS side answered the FC heartbeat: heartbeat then a stream request
            sent = await _pty_output(bare_pty, 21 + 45)      # MAVLink 2 HEARTBEAT + COMMAND_LONG
            bare_pty.unplug()
            await lost.wait()
            bare_pty.replug()
            await up.wait()                                 # the runner has reopened the port
            bare_pty.write(b"".join(after))
            await task
        return sent, runner.reconnects

    sent, reconnects = asyncio.run(main())
    rec.close()
    assert reconnects == 1
    kinds = [type(e) for e in events]
    assert kinds.count(LinkLost) == 1 and kinds.count(LinkRestored) == 1
    assert kinds.index(LinkLost) < kinds.index(LinkRestored)
    assert sum(isinstance(e, Attitude) for e in events) == 100
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    p = mavlink2.MAVLink(None)
    out = [m.get_type() for m in p.parse_buffer(sent) or []]
    assert out[:2] == ["HEARTBEAT", "COMMAND_LONG"]
    recorded = [pkt for _, pkt in scan_tlog(rec.session_path.read_bytes())]
    assert recorded == before + after  # one session file across the unplug
    assert len(rec.flight_paths) == 1
    assert [pkt for _, pkt in scan_tlog(rec.flight_paths[0].read_bytes())] == before + after
    assert sum(isinstance(e, RawPacket) for e in events) == len(before) + len(after)


def test_runner_waits_for_a_pty_that_appears_later(tmp_path):
    """The FC is plugged in after the driver started: it says it waits, then opens the port."""
    from .conftest import BarePty

    port = BarePty(tmp_path / "ttyLATE", plugged=False)
    fc = FakeFc()
    lines: list[str] = []

    async def main():
        waiting = asyncio.Event()
        got = asyncio.Event()
        opened = asyncio.Event()

        def log(msg):
            lines.append(msg)
            waiting.set()

        def on_events(evs):
            if any(isinstance(e, Attitude) for e in evs):
                got.set()

        runner = LinkRunner(lambda: open_link(f"serial://{port.path}:115200"), MavlinkSession(), on_events,
                            backoff_s=0.05, backoff_max_s=0.2, log=log, on_link_up=lambda link: opened.set())
        task = asyncio.ensure_future(runner.run())
        async with asyncio.timeout(30):
            await waiting.wait()
            port.replug()                                   # plugged in
            await opened.wait()
            port.write(fc.heartbeat() + fc.attitude(1000))
            await got.wait()
        runner.stop()
        await asyncio.wait_for(task, 5)
        await runner.link.close()

    try:
        asyncio.run(main())
    finally:
        port.close()
    assert lines == [f"waiting for {port.path}"]


def test_udpin_and_udpout_roundtrip():
    fc = FakeFc()

    async def main():
        server = await open_link("udpin://127.0.0.1:0")
        port = server.local_port
        client = await open_link(f"udpout://127.0.0.1:{port}")
        hb = fc.heartbeat()
        await client.write(hb)
        assert await asyncio.wait_for(server.read(), 3.0) == hb
        await server.write(b"reply")  # goes back to the last sender
        assert await asyncio.wait_for(client.read(), 3.0) == b"reply"
        await client.close()
        await server.close()

    asyncio.run(main())


def test_tcp_roundtrip_and_peer_close_is_link_down():
    fc = FakeFc()

    async def main():
        got = asyncio.get_running_loop().create_future()

        async def handle(reader, writer):
            writer.write(fc.heartbeat())
            await writer.drain()
            got.set_result(await reader.read(100))
            writer.close()

        srv = await asyncio.start_server(handle, "127.0.0.1", 0)
        port = srv.sockets[0].getsockname()[1]
        link = await open_link(f"tcp://127.0.0.1:{port}")
        data = await asyncio.wait_for(link.read(), 3.0)
        assert data[0] == 0xFD
        await link.write(b"ping")
        assert await asyncio.wait_for(got, 3.0) == b"ping"
        with pytest.raises(LinkDown):
            await asyncio.wait_for(link.read(), 3.0)
        await link.close()
        srv.close()
        await srv.wait_closed()

    asyncio.run(main())


def test_tcp_connection_refused_names_the_url():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    with pytest.raises(TransportError, match=f"tcp://127.0.0.1:{port}"):
        asyncio.run(open_link(f"tcp://127.0.0.1:{port}"))
