"""Fixtures for sink tests: a real zenoh subscriber session on loopback (scouting off)."""

from __future__ import annotations

import json
import threading
import time

import pytest
import zenoh

from groundstation.sinks.zenoh_sink import loopback_peer_config


class Collector:
    """A real zenoh peer that records every sample under a key expression."""

    def __init__(self, connect_endpoint: str, key: str = "heli/**") -> None:
        port = int(connect_endpoint.rsplit(":", 1)[1])
        self.session = zenoh.open(zenoh.Config.from_json5(loopback_peer_config(connect_ports=(port,))))
        self.samples: list[tuple[str, dict]] = []
        self._lock = threading.Lock()
        self.sub = self.session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        with self._lock:
            self.samples.append((str(sample.key_expr), json.loads(sample.payload.to_string())))

    def keys(self) -> list[str]:
        with self._lock:
            return [k for k, _ in self.samples]

    def wait_for(self, pred, timeout_s: float = 10.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            with self._lock:
                if pred(self.samples):
                    return True
            time.sleep(0.02)
        return False

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def collector_factory():
    made: list[Collector] = []

    def make(endpoint: str, key: str = "heli/**") -> Collector:
        c = Collector(endpoint, key)
        made.append(c)
        return c

    yield make
    for c in made:
        c.close()
