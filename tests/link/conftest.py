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


@pytest.fixture
def fc() -> FakeFc:
    return FakeFc()


@pytest.fixture
def fc_v1() -> FakeFc:
    return FakeFc(v1=True)
