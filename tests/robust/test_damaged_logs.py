"""Damaged telemetry logs through every offline command: a result or one clear line, never a traceback.

A small simulated flight (40 s, reduced search budget) is damaged the way field logs are: cut off
mid-packet or mid-flight, bursts of packets lost (every message type alike, as a radio fade), chunks
duplicated (a copy resumed twice), packets reordered, bytes corrupted, the FC rebooted mid-log
(timestamps jump back). Each damaged log goes through ``log-info``, ``identify``, ``validate`` and
``diagnose`` in-process: ``main`` must return 0 or 2, and when it is 2 stderr is one line naming
the command. A crash shows as an exception escaping ``main``. Few examples, bounded budgets.
"""

from __future__ import annotations

import json
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groundstation.cli import main

pytestmark = pytest.mark.filterwarnings("ignore")

FAST = ["--folds", "2", "--no-plot", "--quiet", "--jobs", "1"]  # + --config: tiny search, no selection


def split_records(data: bytes) -> list[bytes]:
    """Split a .tlog into (8-byte time + MAVLink 2 frame) records (unsigned frames, as the simulator writes)."""
    out, i = [], 0
    while i + 8 + 12 <= len(data):
        n = 8 + 12 + data[i + 9] + (13 if data[i + 10] & 1 else 0)
        out.append(data[i:i + n])
        i += n
    return out


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    from hil_replay.sim import write_tlog

    d = tmp_path_factory.mktemp("damaged")
    cfg = d / "fast.toml"
    cfg.write_text("[identify]\nselect_folds = 0\nsearch_restarts = 1\nmaxiter = 4\n")
    FAST.extend(["--config", str(cfg)])
    path = d / "clean.tlog"
    write_tlog(path, seed=7, flights=1, flight_duration_s=40.0, rates_hz={"ATTITUDE": 25, "SERVO_OUTPUT_RAW": 25,
                                                                         "LOCAL_POSITION_NED": 25})
    model = d / "clean.json"
    assert main(["identify", str(path), "--out", str(model), *FAST]) == 0
    return d, path.read_bytes(), model


def damage(data: bytes, kind: str, a: float, b: float, n: int) -> bytes:
    recs = split_records(data)
    i = int(a * len(recs))
    if kind == "cut":  # at any byte: mid-packet, mid-flight
        return data[:max(1, int(a * len(data)))]
    if kind == "bursts":  # n fades of ~8 packets anywhere
        drop: set[int] = set()
        for k in range(n):
            s = int(((a + k * b) % 1.0) * len(recs))
            drop.update(range(s, s + 8))
        return b"".join(r for j, r in enumerate(recs) if j not in drop)
    if kind == "duplicate":  # a chunk of packets written twice
        j = min(len(recs), i + 1 + int(b * 400))
        return b"".join(recs[:j] + recs[i:j] + recs[j:])
    if kind == "reorder":  # neighbouring packets swapped
        recs = list(recs)
        for k in range(i, min(len(recs) - 1, i + 40 * n), 2):
            recs[k], recs[k + 1] = recs[k + 1], recs[k]
        return b"".join(recs)
    if kind == "corrupt":
        buf = bytearray(data)
        for k in range(n * 50):
            buf[int(((a + k * b * 0.618) % 1.0) * (len(buf) - 1))] ^= 0x5A
        return bytes(buf)
    if kind == "reboot":  # the FC restarts: later packets' boot time starts again near zero
        return b"".join(recs[:i] + recs[:i // 2] + recs[i:])
    if kind == "empty":
        return b""
    raise AssertionError(kind)


KINDS = st.sampled_from(["cut", "bursts", "duplicate", "reorder", "corrupt", "reboot"])
SETTINGS = settings(max_examples=5, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _run(argv: list[str], capsys) -> tuple[int, str]:
    rc = main(argv)  # an internal error escapes here as an exception and fails the test
    err = capsys.readouterr().err.strip()
    assert rc in (0, 2), (rc, err)
    if rc == 2:
        lines = [x for x in err.splitlines() if x.strip()]
        assert lines and lines[-1].startswith(f"groundstation {argv[0]}: error: "), err
        assert "Traceback" not in err and "not JSON compliant" not in err, err
    return rc, err


@SETTINGS
@given(kind=KINDS, a=st.floats(0.05, 0.95), b=st.floats(0.01, 0.5), n=st.integers(1, 40))
def test_log_info_and_identify_on_damaged_log(flight, tmp_path, capsys, kind, a, b, n):
    d, data, _ = flight
    path = tmp_path / f"{kind}.tlog"
    path.write_bytes(damage(data, kind, a, b, n))
    _run(["log-info", str(path), "--json"], capsys)
    out = tmp_path / "model.json"
    rc, _ = _run(["identify", str(path), "--out", str(out), *FAST], capsys)
    if rc == 0:
        json.loads(out.read_text())  # strict JSON: NaN would not parse back in other tools either


@settings(max_examples=3, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(kind=KINDS, a=st.floats(0.1, 0.9), b=st.floats(0.01, 0.5), n=st.integers(1, 40))
def test_validate_and_diagnose_on_damaged_log(flight, tmp_path, capsys, kind, a, b, n):
    d, data, model = flight
    path = tmp_path / f"{kind}.tlog"
    path.write_bytes(damage(data, kind, a, b, n))
    _run(["validate", str(model), str(path), "--json"], capsys)
    out = tmp_path / "gap.json"
    rc, _ = _run(["diagnose", str(path), "--model", str(model), "--out", str(out), "--jobs", "1"], capsys)
    if rc == 0:
        json.loads(out.read_text())


@pytest.mark.parametrize("kind", ["empty", "cut"])
def test_tiny_logs_one_line(flight, tmp_path, capsys, kind):
    d, data, model = flight
    path = tmp_path / "tiny.tlog"
    path.write_bytes(damage(data, kind, 0.001, 0.0, 1))
    for argv in (["log-info", str(path)], ["identify", str(path), "--out", str(tmp_path / "m.json"), *FAST],
                 ["validate", str(model), str(path)], ["diagnose", str(path), "--out", str(tmp_path / "g.json")]):
        rc, err = _run(argv, capsys)
        assert rc == 2 or argv[0] == "log-info"


def test_record_split_roundtrip(flight):
    _, data, _ = flight
    recs = split_records(data)
    assert b"".join(recs) == data and len(recs) > 1000
    assert struct.unpack(">Q", recs[0][:8])[0] > 0
