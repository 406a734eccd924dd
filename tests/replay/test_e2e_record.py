"""End to end: replay a flight through a real pty with 1 % corrupted bytes and a 3 s unplug
into ``groundstation record`` (subprocess, real pyserial); the recording must hold every packet
that was neither corrupted nor sent during the unplug, compared packet by packet with the source,
and the record summary must report the corruption.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from benchkit.telemetry import sine_flight_tlog
from hil_replay.player import TlogPlayer, read_tlog_packets
from hil_replay.pty import VirtualSerialPort


def _src(pkt: bytes) -> tuple[int, int]:
    return (pkt[5], pkt[6]) if pkt[0] == 0xFD else (pkt[3], pkt[4])


def _wait_recorded(rec_dir: Path, n: int, timeout_s: float = 60.0) -> None:
    """Until the session file holds ``n`` packets from the FC (the recorder flushes at least every
    0.5 s): the stop then comes after the data, whatever the machine's speed."""
    from firmware_interface.tlogread import scan_tlog

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        files = sorted(rec_dir.glob("session-*.tlog"))
        if files and sum(_src(p) == (1, 1) for _, p in scan_tlog(files[0].read_bytes())) >= n:
            return
        time.sleep(0.05)
    raise AssertionError(f"{rec_dir}: fewer than {n} packets from the FC recorded after {timeout_s} s")


def test_corrupted_unplugged_replay_into_record(tmp_path):
    sine_flight_tlog(tmp_path / "flight.tlog", duration_s=20.0)
    packets = read_tlog_packets(tmp_path / "flight.tlog")
    out_dir = tmp_path / "rec"
    with VirtualSerialPort(tmp_path / "ttyFC") as port:
        proc = subprocess.Popen(
            [sys.executable, "-m", "groundstation.cli", "record", "--link", f"serial://{port.path}:921600",
             "--out", str(out_dir)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            player = TlogPlayer(packets, port, speed=8.0, corrupt_rate=0.01, unplug_at_s=8.0,
                                unplug_for_s=3.0, seed=11, reader_timeout_s=30.0)
            report = player.run()
            _wait_recorded(out_dir, len(report.intact))
            proc.send_signal(signal.SIGINT)
            stdout, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert proc.returncode == 0, stderr
    assert report.finished and len(report.unplugged) > 500 and len(report.corrupted) > 100
    assert report.undrained == 0

    summary = json.loads(stdout.strip().splitlines()[-1])
    recorded = [p.data for p in read_tlog_packets(summary["session_tlog"])]
    from_fc = [p for p in recorded if _src(p) == (1, 1)]       # leave out anything the GCS itself logs
    expected = [packets[i].data for i in report.intact]
    assert from_fc == expected                                 # every intact packet, in order, nothing else

    assert summary["corrupt_bytes"] > 0
    # each corrupted packet fails its CRC (or breaks its framing): the bad-CRC count is of that order
    assert 0.5 * len(report.corrupted) <= summary["bad_crc"] <= 1.5 * len(report.corrupted)


def test_replay_command_into_record_command(tmp_path):
    """The same through the two commands only (flags --corrupt --drop --unplug-at --report)."""
    sine_flight_tlog(tmp_path / "flight.tlog", duration_s=12.0)
    packets = read_tlog_packets(tmp_path / "flight.tlog")
    link = tmp_path / "ttyREPLAY"
    replay = subprocess.Popen(
        [sys.executable, "-m", "groundstation.cli", "replay", str(tmp_path / "flight.tlog"), "--speed", "8",
         "--corrupt", "0.005", "--drop", "0.01", "--unplug-at", "4", "--unplug-for", "3", "--seed", "5",
         "--link-path", str(link), "--report", str(tmp_path / "report.json")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    record = None
    try:
        assert replay.stdout.readline().strip() == str(link)
        record = subprocess.Popen(
            [sys.executable, "-m", "groundstation.cli", "record", "--link", f"serial://{link}:921600",
             "--out", str(tmp_path / "rec")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert replay.wait(timeout=60) == 0
        _wait_recorded(tmp_path / "rec", len(json.loads((tmp_path / "report.json").read_text())["intact"]))
        record.send_signal(signal.SIGINT)
        stdout, stderr = record.communicate(timeout=30)
    finally:
        for p in (replay, record):
            if p is not None and p.poll() is None:
                p.kill()
                p.communicate()
    assert record.returncode == 0, stderr
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["dropped"] and report["corrupted"] and report["unplugged"] and report["undrained"] == 0
    summary = json.loads(stdout.strip().splitlines()[-1])
    from_fc = [p.data for p in read_tlog_packets(summary["session_tlog"]) if _src(p.data) == (1, 1)]
    assert from_fc == [packets[i].data for i in report["intact"]]
    assert summary["link_lost"] >= 1
