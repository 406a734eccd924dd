"""Fixtures for service tests.

The helicopter is the outside world, so a small scripted stand-in (:class:`ScriptedHelicopter`) is
allowed when a test does not need flight physics; the simulated FC protocol, the pty, pyserial,
pymavlink bytes, zenoh sessions and .rrd files are all real.
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass

import pytest
import zenoh
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from groundstation.config import ServiceConfig
from groundstation.sinks.zenoh_sink import free_tcp_port, loopback_peer_config

NATIVE_RATE_HZ = {"ATTITUDE": 50, "SERVO_OUTPUT_RAW": 50, "LOCAL_POSITION_NED": 50,
                  "GLOBAL_POSITION_INT": 10, "EXTENDED_SYS_STATE": 5, "SYS_STATUS": 1}


@dataclass(frozen=True)
class ScriptedFrame:
    k: int
    t_boot_s: float
    armed: bool
    flight_index: int | None
    available: tuple[str, ...]

    def build(self, name: str, mav: mavlink.MAVLink):
        t = self.t_boot_s
        ms = int(round(t * 1000))
        us = int(round(t * 1e6))
        a = 1.0 if self.armed else 0.0
        if name == "ATTITUDE":
            return mav.attitude_encode(ms, 0.05 * a * math.sin(1.3 * t), 0.04 * a * math.sin(0.7 * t), 0.3,
                                       0.2 * a * math.cos(1.3 * t), 0.1 * a * math.cos(0.7 * t), 0.0)
        if name == "SERVO_OUTPUT_RAW":
            return mav.servo_output_raw_encode(us & 0xFFFFFFFF, 0, int(1500 + 80 * a * math.sin(1.3 * t)),
                                               int(1500 + 60 * a * math.sin(0.7 * t)), 1560, 1480, 0, 0, 0, 0)
        if name == "LOCAL_POSITION_NED":
            return mav.local_position_ned_encode(ms, 0.0, 0.0, -2.0 * a, a * math.sin(0.5 * t), 0.3 * a, 0.0)
        if name == "GLOBAL_POSITION_INT":
            return mav.global_position_int_encode(ms, 473977420, 85455940, 500000, int(2000 * a), 0, 0, 0, 9000)
        if name == "SYS_STATUS":
            return mav.sys_status_encode(0, 0, 0, 500, 16000, 1000, 90, 0, 0, 0, 0, 0, 0)
        if name == "EXTENDED_SYS_STATE":
            landed = mavlink.MAV_LANDED_STATE_IN_AIR if self.armed else mavlink.MAV_LANDED_STATE_ON_GROUND
            return mav.extended_sys_state_encode(0, landed)
        raise KeyError(name)


class ScriptedHelicopter:
    """50 Hz frames; armed during ``flight_s`` seconds, ``flights`` times, with ``pause_s`` between."""

    def __init__(self, flights: int = 2, flight_s: float = 4.0, pause_s: float = 2.0, t0_s: float = 5.0):
        self.flights, self.flight_s, self.pause_s, self.t0_s = flights, flight_s, pause_s, t0_s

    def armed_intervals(self) -> list[tuple[float, float]]:
        out = []
        t = self.t0_s + self.pause_s
        for _ in range(self.flights):
            out.append((t, t + self.flight_s))
            t += self.flight_s + self.pause_s
        return out

    def frames(self):
        iv = self.armed_intervals()
        end = iv[-1][1] + self.pause_s
        n = int(round((end - self.t0_s) * 50))
        for k in range(n):
            t = self.t0_s + k / 50
            flight = next((i for i, (a, b) in enumerate(iv) if a <= t < b), None)
            avail = tuple(name for name, r in NATIVE_RATE_HZ.items() if k % (50 // r) == 0)
            yield ScriptedFrame(k, t, flight is not None, flight, avail)


def service_config(tmp_path, **sections) -> ServiceConfig:
    """A test config: files under tmp_path, a fixed zenoh port, small windows, and the worker at a fair
    share of the cores (at the lowest priority it can starve behind the suite's other processes)."""
    cfg = ServiceConfig()
    cfg = cfg.replace("service", record_dir=str(tmp_path / "rec"), vehicle="testheli", status_rate_hz=5.0,
                      worker_nice=0)
    cfg = cfg.replace("zenoh", listen_port=free_tcp_port())
    cfg = cfg.replace("live", window_s=2.0, hop_s=0.25)
    for name, changes in sections.items():
        cfg = cfg.replace(name, **changes)
    return cfg


class Subscriber:
    """A real zenoh peer on loopback (scouting off) recording every sample under heli/**."""

    def __init__(self, port: int) -> None:
        self.session = zenoh.open(zenoh.Config.from_json5(loopback_peer_config(connect_ports=(port,))))
        self.samples: list[tuple[str, dict, float]] = []
        self._lock = threading.Lock()
        self.sub = self.session.declare_subscriber("heli/**", self._on)

    def _on(self, sample) -> None:
        doc = json.loads(sample.payload.to_string())
        with self._lock:
            self.samples.append((str(sample.key_expr), doc, time.time()))

    def of(self, suffix: str) -> list[dict]:
        with self._lock:
            return [d for k, d, _ in self.samples if k.endswith(suffix)]

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def subscriber_factory():
    made: list[Subscriber] = []

    def make(port: int) -> Subscriber:
        s = Subscriber(port)
        made.append(s)
        return s

    yield make
    for s in made:
        s.close()
