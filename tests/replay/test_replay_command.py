"""``groundstation replay`` as a subprocess: prints the port path, serves the log, bad input exits 2."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from tests.replay.conftest import RawReconnectingReader, make_tlog

CLI = [sys.executable, "-m", "groundstation.cli", "replay"]


def test_serves_log_on_printed_path(tmp_path):
    packets = make_tlog(tmp_path / "a.tlog", duration_s=2.0)
    link = tmp_path / "dev" / "ttyREPLAY"
    proc = subprocess.Popen([*CLI, str(tmp_path / "a.tlog"), "--speed", "20", "--link-path", str(link),
                             "--report", str(tmp_path / "rep.json")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        path = proc.stdout.readline().strip()
        assert path == str(link)
        reader = RawReconnectingReader(path)
        try:
            assert proc.wait(timeout=30) == 0
        finally:
            reader.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert reader.data == b"".join(packets)
    rep = json.loads((tmp_path / "rep.json").read_text())
    assert rep["intact"] == list(range(len(packets))) and rep["finished"]
    assert f"{len(packets)}/{len(packets)} packets sent" in proc.stderr.read()
    assert not link.exists()  # the port is gone when the replay ends


@pytest.mark.parametrize("content,expect", [
    (None, "missing.tlog: no such file"),
    (b"", "empty.tlog: empty file"),
    (b"hello, not mavlink\n" * 50, "text.tlog: no MAVLink packets"),
])
def test_bad_input_one_line_exit_2(tmp_path, content, expect):
    name = expect.split(":")[0]
    f = tmp_path / name
    if content is not None:
        f.write_bytes(content)
    res = subprocess.run([*CLI, str(f)], capture_output=True, text=True, timeout=30)
    assert res.returncode == 2
    assert res.stdout == ""
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and expect in lines[0] and str(f) in lines[0]


def test_bad_rate_rejected(tmp_path):
    make_tlog(tmp_path / "a.tlog", duration_s=0.5)
    res = subprocess.run([*CLI, str(tmp_path / "a.tlog"), "--corrupt", "1.5"], capture_output=True,
                         text=True, timeout=30)
    assert res.returncode == 2 and "--corrupt" in res.stderr and len(res.stderr.strip().splitlines()) == 1


def test_ctrl_c_stops_cleanly(tmp_path):
    make_tlog(tmp_path / "a.tlog", duration_s=30.0)
    proc = subprocess.Popen([*CLI, str(tmp_path / "a.tlog"), "--report", str(tmp_path / "rep.json")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        path = proc.stdout.readline().strip()
        reader = RawReconnectingReader(path)
        try:
            time.sleep(1.0)
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=10) == 130
        finally:
            reader.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "(interrupted)" in proc.stderr.read()
    rep = json.loads((tmp_path / "rep.json").read_text())
    assert not rep["finished"] and 0 < len(rep["intact"]) < rep["n_packets"]
    assert not os.path.lexists(path)


def test_no_wait_serves_into_the_void_and_says_so(tmp_path):
    make_tlog(tmp_path / "a.tlog", duration_s=20.0)   # more than a pty buffer holds
    res = subprocess.run([*CLI, str(tmp_path / "a.tlog"), "--speed", "0", "--no-wait",
                          "--report", str(tmp_path / "rep.json")], capture_output=True, text=True, timeout=30)
    assert res.returncode == 0, res.stderr
    rep = json.loads((tmp_path / "rep.json").read_text())
    # nobody read it, and the report says so
    assert rep["finished"] and rep["undrained"] == 1 and rep["unheard_bytes"] == rep["bytes_sent"] > 30_000


def test_unusable_link_path_one_line_exit_2(tmp_path):
    make_tlog(tmp_path / "a.tlog", duration_s=0.5)
    taken = tmp_path / "regular-file"
    taken.write_text("not a port")
    for bad in (taken, "/proc/no-such-dir/ttyFC"):
        res = subprocess.run([*CLI, str(tmp_path / "a.tlog"), "--link-path", str(bad)], capture_output=True,
                             text=True, timeout=30)
        assert res.returncode == 2 and res.stdout == ""
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and str(bad).rsplit("/", 1)[0] in lines[0]
    assert taken.read_text() == "not a port"
