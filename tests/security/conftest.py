"""Fixtures for the security tests: field certificates made by the shipped script, a real zenoh router.

Every zenoh session opened here is closed in ``finally`` (leaked zenoh threads hang pytest).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from groundstation.sinks.zenoh_sink import free_tcp_port

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "scripts" / "make-field-certs"


def make_field(out: Path, *extra: str) -> Path:
    """Run scripts/make-field-certs into ``out`` (fails the test with the script's stderr)."""
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out), *extra],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return out


def retarget(src: Path, dst: Path, port: int, **edits: str) -> Path:
    """Copy a rendered client config pointing it at ``tls/localhost:port``; ``edits`` replace
    ``key: value`` lines (json5 text), e.g. ``password='"wrong"'``; mode 0600 like the original."""
    text = re.sub(r"tls/[^\"]+:\d+", f"tls/localhost:{port}", src.read_text())
    for key, value in edits.items():
        text, n = re.subn(rf"(\b{key}: )[^,\n}}]+", rf"\g<1>{value}", text)
        assert n, f"{key} not in {src}"
    fd = os.open(dst, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    return dst


def open_router(router_json5: Path, port: int, *, acl: bool = True) -> zenoh.Session:
    cfg = zenoh.Config.from_file(str(router_json5))
    cfg.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
    if not acl:
        cfg.insert_json5("access_control/enabled", "false")
    return zenoh.open(cfg)


def wait_for(pred: Callable[[], bool], timeout_s: float = 10.0, step_s: float = 0.02) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step_s)
    return bool(pred())


@pytest.fixture(scope="session")
def field(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """CA, router, ground station and two viewers ('viewer', 'alice'), rendered configs."""
    return make_field(tmp_path_factory.mktemp("field") / "field", "--viewer", "viewer", "--viewer", "alice")


@pytest.fixture(scope="session")
def rogue_field(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An unrelated CA with the same user names (an outsider who copied our configs' shape)."""
    return make_field(tmp_path_factory.mktemp("rogue") / "field")


@pytest.fixture(scope="module")
def router(field: Path) -> Iterator[int]:
    """A Python zenoh session in router mode with the shipped (rendered) router config; yields port."""
    port = free_tcp_port()
    session = open_router(field / "router.json5", port)
    try:
        yield port
    finally:
        session.close()


@pytest.fixture
def client(tmp_path: Path, field: Path) -> Iterator[Callable[..., zenoh.Session]]:
    """``client(who, port, **edits)`` opens a client session from the rendered config of ``user``."""
    sessions: list[zenoh.Session] = []

    def make(who: str, port: int, base: Path | None = None, **edits: str) -> zenoh.Session:
        path = retarget((base or field) / f"{who}.json5", tmp_path / f"{who}-{len(sessions)}.json5",
                        port, **edits)
        s = zenoh.open(zenoh.Config.from_file(str(path)))
        sessions.append(s)
        return s

    try:
        yield make
    finally:
        for s in sessions:
            s.close()
