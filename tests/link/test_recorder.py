"""Recorder: per-flight files, mavlogdump-readable output, crash safety, the record command."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from firmware_interface.recorder import Recorder
from firmware_interface.session import MavlinkSession, SessionConfig
from firmware_interface.tlogread import TlogScan, scan_tlog

from .conftest import FakeFc

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def _packets(path: Path) -> list[bytes]:
    return [p for _, p in scan_tlog(path.read_bytes())]


def test_session_file_and_one_file_per_armed_interval(tmp_path):
    fc = FakeFc()
    gcs = FakeFc(sysid=255, compid=190)
    plan = ([fc.heartbeat(False)] + [fc.attitude(1000 + k) for k in range(5)]
            + [fc.heartbeat(True)] + [fc.attitude(2000 + k) for k in range(7)]
            + [gcs.pack(gcs.mav.heartbeat_encode(6, 8, 0, 0, 4))]  # a GCS heartbeat must not disarm
            + [fc.heartbeat(True)] + [fc.attitude(3000 + k) for k in range(3)]
            + [fc.heartbeat(False)] + [fc.attitude(4000 + k) for k in range(4)]
            + [fc.heartbeat(True)] + [fc.attitude(5000 + k) for k in range(2)])
    s = MavlinkSession(SessionConfig(request_streams=False, send_heartbeat=False))
    (tmp_path / "flight-01.tlog").write_bytes(b"an older recording")  # must not be overwritten
    rec = Recorder(tmp_path, clock=lambda: 1_700_000_000.0)
    for k, pkt in enumerate(plan):
        s.receive_data(pkt, 1_700_000_000.0 + 0.01 * k)
        rec.handle(s.events())
    assert rec.flight_open
    rec.close()
    assert rec.session_path.name.startswith("session-") and rec.session_path.suffix == ".tlog"
    assert _packets(rec.session_path) == plan
    assert (tmp_path / "flight-01.tlog").read_bytes() == b"an older recording"
    assert [p.name for p in rec.flight_paths] == ["flight-02.tlog", "flight-03.tlog"]
    i_arm, i_dis = 6, 6 + 1 + 7 + 1 + 1 + 3
    assert _packets(rec.flight_paths[0]) == plan[i_arm:i_dis + 1]  # arming .. disarming heartbeat
    assert _packets(rec.flight_paths[1]) == plan[-3:]  # still armed at close: closed valid
    rec2 = Recorder(tmp_path, clock=lambda: 1_700_000_000.0)
    assert rec2.session_path != rec.session_path  # same second: a new name, nothing overwritten
    rec2.close()


def test_recorded_files_are_readable_by_mavlogdump(tmp_path):
    fc = FakeFc()
    s = MavlinkSession(SessionConfig(request_streams=False, send_heartbeat=False))
    rec = Recorder(tmp_path)
    for k in range(20):
        s.receive_data(fc.heartbeat(armed=True) if k % 5 == 0 else fc.attitude(1000 + 20 * k), 1.7e9 + k * 0.02)
        rec.handle(s.events())
    rec.close()
    for path in [rec.session_path, *rec.flight_paths]:
        r = subprocess.run([str(BIN / "mavlogdump.py"), "--types", "ATTITUDE", str(path)],
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        assert r.stdout.count("ATTITUDE {") == 16, r.stdout[:500]


def _wait_for(pred, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.02)
    return False


def _start_record(url: str, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "groundstation.cli", "record", "--link", url,
                             "--out", str(out), *extra],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_kill_9_mid_flight_leaves_a_parsable_file_with_everything_but_the_last_second(bare_pty, tmp_path):
    fc = FakeFc()
    out = tmp_path / "rec"
    proc = _start_record(f"serial://{bare_pty.path}:115200", out)
    try:
        assert _wait_for(lambda: out.exists() and any(out.glob("session-*.tlog")), 30)
        time.sleep(0.3)
        bare_pty.write(fc.heartbeat(armed=True))
        written: list[tuple[float, bytes]] = []
        t_end = time.monotonic() + 2.5
        k = 0
        while time.monotonic() < t_end:  # ~400 packets/s
            pkt = fc.attitude(1000 + 5 * k)
            bare_pty.write(pkt)
            written.append((time.monotonic(), pkt))
            bare_pty.read_available()  # drain what the GCS sends back
            k += 1
            time.sleep(0.0025)
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    session = next(out.glob("session-*.tlog"))
    flight = out / "flight-01.tlog"
    for path in (session, flight):
        scan = TlogScan()
        got = [p for _, p in scan_tlog(path.read_bytes(), scan)]
        assert scan.corrupt_bytes == 0  # at most a truncated tail
        atts = [p for p in got if p[7] == 30]
        expect = [p for _, p in written]
        assert atts == expect[: len(atts)]  # a prefix, in order, nothing garbled
        older = [p for t, p in written if t < t_kill - 1.0]
        assert len(atts) >= len(older), (path.name, len(atts), len(older))


def test_record_command_sigterm_exits_0_with_summary_json(bare_pty, tmp_path):
    fc = FakeFc()
    out = tmp_path / "rec"
    proc = _start_record(f"serial://{bare_pty.path}:115200", out)
    try:
        assert _wait_for(lambda: out.exists() and any(out.glob("session-*.tlog")), 30)
        time.sleep(0.3)
        pkts = [fc.heartbeat(armed=True)] + [fc.attitude(1000 + 20 * k) for k in range(30)]
        bad = bytearray(fc.attitude(5000))
        bad[14] ^= 0x10
        pkts2 = [fc.attitude(6000 + 20 * k) for k in range(10)] + [fc.heartbeat(armed=False)]
        bare_pty.write(b"".join(pkts) + bytes(bad) + b"".join(pkts2))
        session = next(out.glob("session-*.tlog"))           # flushed at least every 0.5 s
        assert _wait_for(lambda: len(_packets(session)) >= len(pkts) + len(pkts2), 30)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["packets"] == len(pkts) + len(pkts2)
    assert summary["bad_crc"] == 1 and summary["corrupt_bytes"] == len(bad)
    assert len(summary["flights"]) == 1
    assert _packets(Path(summary["session_tlog"])) == pkts + pkts2
    assert _packets(Path(summary["flights"][0])) == pkts + pkts2
    assert "record: session" in stderr


def test_record_waits_for_a_port_not_plugged_in_and_ctrl_c_exits_0(tmp_path):
    url = f"serial://{tmp_path}/ttyGONE:57600"
    proc = _start_record(url, tmp_path / "o")
    try:
        line = proc.stderr.readline()                       # the process says it waits
        assert line.strip() == f"record: waiting for {tmp_path}/ttyGONE"
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["packets"] == 0 and summary["flights"] == []


def test_record_path_that_is_not_a_serial_port_one_line_exit_2(tmp_path):
    f = tmp_path / "notes.txt"
    f.write_text("not a tty")
    url = f"serial://{f}:57600"
    r = subprocess.run([sys.executable, "-m", "groundstation.cli", "record", "--link", url, "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and url in lines[0] and "not a serial device" in lines[0]
    assert not (tmp_path / "o").exists()                    # nothing created for a wrong path


def test_record_noise_at_wrong_baud_is_an_error_and_keeps_the_file(bare_pty, tmp_path):
    import random

    out = tmp_path / "rec"
    proc = _start_record(f"serial://{bare_pty.path}:115200", out, "--noise-timeout", "1.0")
    rng = random.Random(1)
    try:
        assert _wait_for(lambda: out.exists() and any(out.glob("session-*.tlog")), 30)
        time.sleep(0.2)
        t_end = time.monotonic() + 8
        while proc.poll() is None and time.monotonic() < t_end:
            # what a 57600-baud stream looks like at 115200: no frame survives
            bare_pty.write(bytes(rng.choice(b"\x00\x80\xf8\x78\xe0\x1e") for _ in range(200)))
            time.sleep(0.02)
        stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 2
    err = [ln for ln in stderr.strip().splitlines() if "error" in ln]
    assert len(err) == 1 and bare_pty.path in err[0] and "no valid MAVLink" in err[0]
    assert any(out.glob("session-*.tlog"))


@pytest.mark.parametrize("rate", ["ATTITUDE", "ATTITUDE=fast"])
def test_record_bad_rate_option(tmp_path, rate, bare_pty):
    r = subprocess.run([sys.executable, "-m", "groundstation.cli", "record", "--link",
                        f"serial://{bare_pty.path}", "--out", str(tmp_path / "o"), "--rate", rate],
                       capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2 and "--rate" in r.stderr


def test_record_unwritable_output_is_one_line_exit_2(bare_pty, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    r = subprocess.run([sys.executable, "-m", "groundstation.cli", "record", "--link",
                        f"serial://{bare_pty.path}", "--out", str(blocker / "sub")],
                       capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(blocker / "sub") in lines[0]
