"""``groundstation simulate``: --out writes .tlog + truth and says so; bad input exits 2 with one line;
--serve prints a port path on which a simulated FC speaks MAVLink."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from groundstation.cli import main


def test_simulate_out_writes_tlog_and_truth(tmp_path, capsys) -> None:
    out = tmp_path / "f.tlog"
    rc = main(["simulate", "--out", str(out), "--seed", "4", "--duration-s", "30",
               "--effect", "input_delay:input=col,delay_s=0.08", "--effect", "gyro_bias:output=p,bias_rad_s=0.005"])
    assert rc == 0
    text = capsys.readouterr().out
    truth = json.loads(out.with_suffix(".truth.json").read_text())
    assert out.stat().st_size > 100_000
    assert str(out) in text and str(out.with_suffix(".truth.json")) in text
    assert "input_delay on col" in text and "gyro_bias on p" in text
    assert truth["seed"] == 4 and [e["effect"] for e in truth["effects"]] == ["input_delay", "gyro_bias"]


@pytest.mark.parametrize("argv, must_contain", [
    (["--effect", "wind"], ["wind", "wind_gust"]),
    (["--effect", "deadband:half_width=0.5"], ["half_width", "0.2"]),
    (["--effect", "gyro_bias:output=w"], ["output", "'p'"]),
    (["--aircraft", "nope"], ["nope", "trex600"]),
    (["--duration-s", "5"], ["--duration-s", "30"]),
])
def test_simulate_bad_input_exits_2_with_one_line(tmp_path, capsys, argv, must_contain) -> None:
    out = tmp_path / "x.tlog"
    rc = main(["simulate", "--out", str(out), *argv])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("groundstation simulate: error:")
    for s in must_contain:
        assert s in err
    assert not out.exists()


def test_simulate_bad_aircraft_file(tmp_path, capsys) -> None:
    bad = tmp_path / "heli.toml"
    bad.write_text("name = 'x'\n[parameters]\nX_u = -0.1\n")
    rc = main(["simulate", "--out", str(tmp_path / "x.tlog"), "--aircraft", str(bad)])
    assert rc == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "missing" in err and "Y_v" in err


def test_simulate_serve_prints_a_port_with_a_heartbeating_fc(tmp_path) -> None:
    link = tmp_path / "ttySIM"
    proc = subprocess.Popen([sys.executable, "-m", "groundstation.cli", "simulate", "--serve", "--speed", "5",
                             "--duration-s", "30", "--link-path", str(link)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 20.0)
        assert ready, "no port path printed"
        line = proc.stdout.readline().strip()
        assert line and os.path.exists(line)
        assert Path(line) == link or Path(line).resolve() == link.resolve()
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        beats = []
        with serial.Serial(line, 115200, timeout=0.2) as ser:
            deadline = time.monotonic() + 8.0
            while time.monotonic() < deadline and len(beats) < 2:
                for msg in parser.parse_buffer(ser.read(4096)) or []:
                    if msg.get_type() == "HEARTBEAT":
                        beats.append(msg)
        assert len(beats) >= 2
        assert beats[0].type == mavlink.MAV_TYPE_HELICOPTER
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    assert proc.returncode in (0, 130)


def test_simulate_rates_and_bad_rates(tmp_path, capsys) -> None:
    out = tmp_path / "r.tlog"
    assert main(["simulate", "--out", str(out), "--duration-s", "30", "--rate", "local_position_ned=10",
                 "--rate", "RAW_IMU=0"]) == 0
    truth = json.loads(out.with_suffix(".truth.json").read_text())
    assert truth["tlog_rates_hz"]["LOCAL_POSITION_NED"] == 10.0 and truth["tlog_rates_hz"]["RAW_IMU"] == 0.0
    from pymavlink import mavutil

    m = mavutil.mavlink_connection(str(out))
    n = {"LOCAL_POSITION_NED": 0, "ATTITUDE": 0, "RAW_IMU": 0}
    while (msg := m.recv_match()) is not None:
        if msg.get_type() in n:
            n[msg.get_type()] += 1
    assert n["RAW_IMU"] == 0 and 4.5 < n["ATTITUDE"] / n["LOCAL_POSITION_NED"] < 5.5
    capsys.readouterr()
    for bad, words in ((["--rate", "FOO=3"], ["FOO", "ATTITUDE"]), (["--rate", "ATTITUDE=100"], ["100", "50"]),
                       (["--rate", "ATTITUDE"], ["MESSAGE=HZ"])):
        assert main(["simulate", "--out", str(tmp_path / "bad.tlog"), *bad]) == 2
        err = capsys.readouterr().err
        assert all(w in err for w in words) and "--rate" in err
    assert not (tmp_path / "bad.tlog").exists()
