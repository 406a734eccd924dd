"""The simulated FC on a real pty, recorded by ``groundstation record`` (subprocess, pyserial):
stream setup over SET_MESSAGE_INTERVAL completes, two armed intervals give two flight files,
the recorded streams run at the requested rates on the FC clock, and an FC reboot is detected
and followed by a new stream request.

The FC starts only once ``record`` has the port open (a slow interpreter start must not make the
recorder miss the first flight); waits are on the FC clock, not on wall time.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from hil_replay.fc import FcConfig, SimulatedFCThread
from hil_replay.player import read_tlog_packets
from tests.replay.conftest import FakeHelicopter


@contextmanager
def _fc_recorded(fc: SimulatedFCThread, out_dir, *rates: str) -> Iterator[dict]:
    """Start ``groundstation record`` on the FC's port, then the FC; yields a dict that holds
    the record summary (``summary``) and messages (``msgs``) once the block has ended."""
    args = [sys.executable, "-m", "groundstation.cli", "record", "--link", f"serial://{fc.port_path}:921600",
            "--out", str(out_dir)]
    for r in rates:
        args += ["--rate", r]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    result: dict = {}
    try:
        assert fc.port.wait_for_reader(60.0), "groundstation record never opened the port"
        fc.start()
        yield result
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        fc.stop()
    assert proc.returncode == 0, stderr
    result["summary"] = summary = json.loads(stdout.strip().splitlines()[-1])
    parser = mavlink.MAVLink(None)
    result["msgs"] = [parser.decode(bytearray(p.data)) for p in read_tlog_packets(summary["session_tlog"])]


def _wait(cond: Callable[[], bool], timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "simulated FC stalled"
        time.sleep(0.02)


def _rate_hz(t_s: np.ndarray) -> float:
    return (len(t_s) - 1) / (t_s[-1] - t_s[0])


def test_simulated_fc_into_record(tmp_path):
    heli = FakeHelicopter(duration_s=40.0, armed_s=((8.0, 18.0), (24.0, 34.0)))
    fc = SimulatedFCThread(speed=10.0, session=heli, config=FcConfig(packet_loss=0.0))
    with _fc_recorded(fc, tmp_path / "rec", "ATTITUDE=50", "GPS_RAW_INT=5") as rec:
        _wait(lambda: fc.stats.last_t_boot_s >= 3.0 + 40.0 - 0.1)
    summary, msgs = rec["summary"], rec["msgs"]
    assert summary["streams"] == {"ATTITUDE": "ok", "GPS_RAW_INT": "ok"}
    assert len(summary["flights"]) == 2
    att_t = np.array([m.time_boot_ms / 1000 for m in msgs if m.get_type() == "ATTITUDE"])
    assert abs(_rate_hz(att_t) / 50 - 1) < 0.10
    gps_t = np.array([m.time_usec / 1e6 for m in msgs if m.get_type() == "GPS_RAW_INT"])
    assert abs(_rate_hz(gps_t) / 5 - 1) < 0.10
    assert {m.get_type() for m in msgs} <= {"HEARTBEAT", "COMMAND_ACK", "ATTITUDE", "GPS_RAW_INT"}


@pytest.mark.parametrize("boot_s", [50.0, 5.0], ids=["longer-than-link-timeout", "brief"])
def test_fc_reboot_is_detected_and_streams_requested_again(tmp_path, boot_s):
    heli = FakeHelicopter(duration_s=300.0, t0_s=20.0)
    fc = SimulatedFCThread(speed=10.0, session=heli, config=FcConfig(packet_loss=0.0))
    with _fc_recorded(fc, tmp_path / "rec", "ATTITUDE=10") as rec:
        _wait(lambda: fc.stats.sent_by_type.get("ATTITUDE", 0) >= 30)   # streaming before the reboot
        t_reboot = fc.stats.last_t_boot_s
        # 50 s of FC time: 5 s wall at 10x (at least 4 s even if the FC had fallen behind and
        # catches up), longer than the ground station's 3 s link timeout, as a real reboot
        # (bootloader + init) on a radio link; 5 s of FC time: 0.5 s wall, the link never times
        # out and the FC comes back with heartbeats only, so the silence of the streams must tell
        fc.reboot(boot_s=boot_s)
        _wait(lambda: fc.stats.last_t_boot_s >= t_reboot + boot_s)
        n_before = fc.stats.sent_by_type.get("ATTITUDE", 0)
        _wait(lambda: fc.stats.sent_by_type.get("ATTITUDE", 0) >= n_before + 100)   # streams again
    summary, msgs = rec["summary"], rec["msgs"]
    assert summary["fc_reboots"] == 1
    att_ms = np.array([m.time_boot_ms for m in msgs if m.get_type() == "ATTITUDE"])
    k = int(np.argmin(np.diff(att_ms)))                # the step back of the reboot
    # the boot clock restarted near 0 (plus what passed before the streams were asked for again)
    assert att_ms[k] > 20_000 and att_ms[k + 1] < att_ms[k] - 5_000
    after = att_ms[k + 1:] / 1000
    assert len(after) >= 100 and abs(_rate_hz(after) / 10 - 1) < 0.10


def test_real_simulator_two_flights_into_record(tmp_path):
    """hil_replay.sim's SimulatedSession behind the FC: default ground-station rates, two flights."""
    fc = SimulatedFCThread(speed=20.0, seed=3, flights=2,
                           sim_options={"flight_duration_s": 30.0, "pause_s": 5.0})
    end_s = fc.fc.session.end_s
    with _fc_recorded(fc, tmp_path / "rec") as rec:
        _wait(lambda: fc.stats.last_t_boot_s >= end_s - 0.1)
    summary, msgs = rec["summary"], rec["msgs"]
    assert set(summary["streams"].values()) == {"ok"}, summary["streams"]
    assert len(summary["flights"]) == 2
    att_t = np.array([m.time_boot_ms / 1000 for m in msgs if m.get_type() == "ATTITUDE"])
    att_t = att_t[att_t > att_t[0] + 5.0]   # after stream setup
    assert abs(_rate_hz(att_t) / 50 - 1) < 0.10
