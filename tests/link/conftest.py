"""Fixtures of the link tests: pymavlink encoders standing in for a flight controller."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from pymavlink.dialects.v20 import ardupilotmega as mavlink2


class FakeFc:
    """Encodes FC messages with pymavlink (MAVLink 2 by default, MAVLink 1 with v1=True)."""

    def __init__(self, sysid: int = 1, compid: int = 1, v1: bool = False) -> None:
        mod = mavlink1 if v1 else mavlink2
        self.mav = mod.MAVLink(None, sysid, compid)

    def pack(self, msg) -> bytes:
        b = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) & 0xFF
        return bytes(b)

    def heartbeat(self, armed: bool = False) -> bytes:
        return self.pack(self.mav.heartbeat_encode(4, 3, 0x81 if armed else 0x01, 0, 4))

    def attitude(self, ms: int, roll: float = 0.1) -> bytes:
        return self.pack(self.mav.attitude_encode(ms, roll, 0.2, 0.3, 0.01, 0.02, 0.03))

    def ack(self, command: int, result: int) -> bytes:
        return self.pack(self.mav.command_ack_encode(command, result))


@pytest.fixture(scope="session")
def df_log() -> bytes:
    """20 kB of the simulated FC's own dataflash log (its writer, simulator records at 200 Hz)."""
    from benchkit.onboard_logs import simulated_dataflash

    return simulated_dataflash(20_000, 0)


@pytest.fixture
def fc() -> FakeFc:
    return FakeFc()


@pytest.fixture
def fc_v1() -> FakeFc:
    return FakeFc(v1=True)


class BarePty:
    """A bare pseudo-terminal at a symlink path, to stand in for a USB serial adapter.

    ``unplug()`` closes the master and removes the symlink (the reader gets EIO, the path is gone);
    ``replug()`` makes a new pty behind the same path.
    """

    def __init__(self, link_path, plugged: bool = True) -> None:
        self.path = str(link_path)
        self.master = -1
        if plugged:
            self.replug()

    def replug(self) -> None:
        import os
        import tty

        master, slave = os.openpty()
        tty.setraw(slave)
        name = os.ttyname(slave)
        os.close(slave)
        os.set_blocking(master, False)
        self.master = master
        tmp = self.path + ".new"
        os.symlink(name, tmp)
        os.replace(tmp, self.path)

    def unplug(self) -> None:
        import os

        if os.path.lexists(self.path):
            os.unlink(self.path)
        if self.master >= 0:
            os.close(self.master)
            self.master = -1

    def write(self, data: bytes) -> None:
        import os
        import select

        view = memoryview(data)
        while view:
            select.select([], [self.master], [], 1.0)
            try:
                view = view[os.write(self.master, view):]
            except BlockingIOError:
                continue

    def read_available(self) -> bytes:
        import os

        out = b""
        while True:
            try:
                chunk = os.read(self.master, 65536)
            except (BlockingIOError, OSError):
                return out
            if not chunk:
                return out
            out += chunk

    def close(self) -> None:
        self.unplug()


@pytest.fixture
def bare_pty(tmp_path):
    port = BarePty(tmp_path / "ttyFC")
    yield port
    port.close()
