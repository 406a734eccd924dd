"""Transports over real pseudo-terminals (pyserial), UDP and TCP sockets on loopback."""

from __future__ import annotations

import asyncio
import socket
import time

import pytest

from firmware_interface.errors import TransportError
from firmware_interface.link import LinkRunner
from firmware_interface.recorder import Recorder
from firmware_interface.samples import Attitude, LinkLost, LinkRestored, RawPacket
from firmware_interface.session import MavlinkSession, SessionConfig
from firmware_interface.tlogread import scan_tlog
from firmware_interface.transports import LinkDown, open_link, parse_url

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
    with pytest.raises(TransportError, match="no such port") as ei:
        asyncio.run(open_link(url))
    assert url in str(ei.value)


async def _read_until(link, n: int, timeout_s: float = 3.0) -> bytes:
    out = b""
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        out += await asyncio.wait_for(link.read(), deadline - time.monotonic())
    return out


def test_serial_over_pty_reads_writes_and_survives_unplug(bare_pty):
    fc = FakeFc()

    async def main():
        link = await open_link(f"serial://{bare_pty.path}:921600")
        link.backoff_s = 0.05
        await asyncio.sleep(0.05)
        a = fc.heartbeat() + fc.attitude(1000)
        bare_pty.write(a)
        assert await _read_until(link, len(a)) == a
        await link.write(b"\xfdhello")
        await asyncio.sleep(0.05)
        assert bare_pty.read_available() == b"\xfdhello"
        # unplug: the device vanishes
        bare_pty.unplug()
        with pytest.raises(LinkDown):
            await asyncio.wait_for(link.read(), 3.0)
        recon = asyncio.ensure_future(link.reconnect())
        await asyncio.sleep(0.4)
        assert not recon.done()  # keeps retrying while the path is gone
        bare_pty.replug()
        await asyncio.wait_for(recon, 5.0)
        await asyncio.sleep(0.05)
        b = fc.attitude(2000)
        bare_pty.write(b)
        assert await _read_until(link, len(b)) == b
        await link.close()

    asyncio.run(main())


def test_runner_session_recorder_over_pty_with_unplug(bare_pty, tmp_path):
    fc = FakeFc()
    before = [fc.heartbeat(armed=True)] + [fc.attitude(1000 + 20 * k) for k in range(50)]
    after = [fc.attitude(5000 + 20 * k) for k in range(50)] + [fc.heartbeat(armed=False)]
    events: list = []
    rec = Recorder(tmp_path / "out")

    async def main():
        link = await open_link(f"serial://{bare_pty.path}:115200")
        link.backoff_s = 0.05
        session = MavlinkSession(SessionConfig(stream_rates_hz=(("ATTITUDE", 50.0),), link_timeout_s=30))

        def on_events(evs):
            events.extend(evs)
            rec.handle(evs)

        runner = LinkRunner(link, session, on_events, tick_s=0.05)
        task = asyncio.ensure_future(runner.run())
        await asyncio.sleep(0.1)
        bare_pty.write(b"".join(before))
        await asyncio.sleep(0.3)
        sent = bare_pty.read_available()  # the GCS side answered the FC heartbeat
        bare_pty.unplug()
        await asyncio.sleep(0.5)
        bare_pty.replug()
        for _ in range(100):  # wait until the runner has reopened the port
            await asyncio.sleep(0.05)
            if runner.reconnects:
                break
        await asyncio.sleep(0.1)
        bare_pty.write(b"".join(after))
        await asyncio.sleep(0.3)
        runner.stop()
        await asyncio.wait_for(task, 5.0)
        await link.close()
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
