"""The simulated FC on a real pty, recorded by ``groundstation record`` (subprocess, pyserial):
stream setup over SET_MESSAGE_INTERVAL completes, two armed intervals give two flight files,
and the recorded ATTITUDE stream runs at the requested rate on the FC clock.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from hil_replay.fc import FcConfig, SimulatedFCThread
from hil_replay.player import read_tlog_packets
from tests.replay.conftest import FakeHelicopter


def test_simulated_fc_into_record(tmp_path):
    heli = FakeHelicopter(duration_s=40.0, armed_s=((8.0, 18.0), (24.0, 34.0)))
    with SimulatedFCThread(speed=10.0, session=heli, config=FcConfig(packet_loss=0.0)) as fc:
        proc = subprocess.Popen(
            [sys.executable, "-m", "groundstation.cli", "record", "--link", f"serial://{fc.port_path}:921600",
             "--out", str(tmp_path / "rec"), "--rate", "ATTITUDE=50", "--rate", "GPS_RAW_INT=5"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 30
            while fc.stats.last_t_boot_s < 3.0 + 40.0 - 0.1 and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.3)
            proc.send_signal(signal.SIGINT)
            stdout, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["streams"] == {"ATTITUDE": "ok", "GPS_RAW_INT": "ok"}
    assert len(summary["flights"]) == 2
    parser = mavlink.MAVLink(None)
    msgs = [parser.decode(bytearray(p.data)) for p in read_tlog_packets(summary["session_tlog"])]
    att_t = np.array([m.time_boot_ms / 1000 for m in msgs if m.get_type() == "ATTITUDE"])
    assert abs((len(att_t) - 1) / (att_t[-1] - att_t[0]) / 50 - 1) < 0.10
    gps_t = np.array([m.time_usec / 1e6 for m in msgs if m.get_type() == "GPS_RAW_INT"])
    assert abs((len(gps_t) - 1) / (gps_t[-1] - gps_t[0]) / 5 - 1) < 0.10
    assert {m.get_type() for m in msgs} <= {"HEARTBEAT", "COMMAND_ACK", "ATTITUDE", "GPS_RAW_INT"}


def test_fc_reboot_is_detected_and_streams_requested_again(tmp_path):
    # the reboot is silent for 50 s of FC time (5 s wall at 10x, at least 4 s even if the FC had
    # fallen behind and catches up): longer than the ground station's 3 s link timeout, as a real
    # reboot (bootloader + init) is on a radio link
    heli = FakeHelicopter(duration_s=80.0, t0_s=20.0)
    with SimulatedFCThread(speed=10.0, session=heli, config=FcConfig(packet_loss=0.0)) as fc:
        proc = subprocess.Popen(
            [sys.executable, "-m", "groundstation.cli", "record", "--link", f"serial://{fc.port_path}:921600",
             "--out", str(tmp_path / "rec"), "--rate", "ATTITUDE=10"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 30
            while fc.stats.last_t_boot_s < 20.0 + 15.0 and time.monotonic() < deadline:
                time.sleep(0.02)
            fc.reboot(boot_s=50.0)
            while fc.stats.last_t_boot_s < 20.0 + 80.0 - 0.1 and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.3)
            proc.send_signal(signal.SIGINT)
            stdout, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["fc_reboots"] == 1
    parser = mavlink.MAVLink(None)
    msgs = [parser.decode(bytearray(p.data)) for p in read_tlog_packets(summary["session_tlog"])]
    att_ms = np.array([m.time_boot_ms for m in msgs if m.get_type() == "ATTITUDE"])
    k = int(np.argmin(np.diff(att_ms)))                # the step back of the reboot
    assert att_ms[k] > 30_000 and att_ms[k + 1] < 5_000
    after = att_ms[k + 1:]
    assert len(after) > 50                            # streams requested again and flowing
    assert abs((len(after) - 1) / ((after[-1] - after[0]) / 1000) / 10 - 1) < 0.10


def test_real_simulator_two_flights_into_record(tmp_path):
    """hil_replay.sim's SimulatedSession behind the FC: default ground-station rates, two flights."""
    with SimulatedFCThread(speed=20.0, seed=3, flights=2,
                           sim_options={"flight_duration_s": 30.0, "pause_s": 5.0}) as fc:
        end_s = fc.fc.session.end_s
        proc = subprocess.Popen(
            [sys.executable, "-m", "groundstation.cli", "record", "--link", f"serial://{fc.port_path}:921600",
             "--out", str(tmp_path / "rec")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 60
            while fc.stats.last_t_boot_s < end_s - 0.1 and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.3)
            proc.send_signal(signal.SIGINT)
            stdout, stderr = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert set(summary["streams"].values()) == {"ok"}, summary["streams"]
    assert len(summary["flights"]) == 2
    parser = mavlink.MAVLink(None)
    msgs = [parser.decode(bytearray(p.data)) for p in read_tlog_packets(summary["session_tlog"])]
    att_t = np.array([m.time_boot_ms / 1000 for m in msgs if m.get_type() == "ATTITUDE"])
    att_t = att_t[att_t > att_t[0] + 5.0]   # after stream setup
    rate_hz = (len(att_t) - 1) / (att_t[-1] - att_t[0])
    assert abs(rate_hz / 50 - 1) < 0.10
