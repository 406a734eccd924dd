"""Onboard log download from the simulated FC through a real pty (pyserial transport, real MAVLink bytes).

The FC serves a dataflash log it wrote itself (from simulator frames at 200 Hz), with its seeded
line noise (also errors the MAVLink CRC-16 cannot see) and a cable pull in the middle; the ground station's bytes to the FC are teed and checked
against the read-only allowlist. Progress, not time, decides when to pull the cable.
"""

from __future__ import annotations

import asyncio
import json
import threading

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.logdownload import DownloadConfig
from firmware_interface.logtransfer import LogTransfer
from firmware_interface.readers import load_log
from firmware_interface.transports import open_link
from groundstation.cli import main as cli_main
from hil_replay.dataflash import DataflashWriter, chirp_plan, rotor_rpm
from hil_replay.fc import FcConfig, SimulatedFCThread
from hil_replay.sim import SimulatedSession


class Idle:
    """No flight: the FC idles disarmed (heartbeats only) and serves its logs."""

    def frames(self):
        return iter(())


class ArmedForever:
    def frames(self):
        k = 0
        while True:
            k += 1
            yield _ArmedFrame(k / 50.0)


class _ArmedFrame:
    armed = True
    flight_index = 0
    available = ()

    def __init__(self, t):
        self.t_boot_s = t

    def build(self, name, mav):
        raise KeyError(name)


@pytest.fixture(scope="module")
def written() -> dict[str, bytes]:
    """Dataflash logs written by the simulated FC's own writer: the first 6 s of a flight (218 kB), and
    its first 1 s (a log closed earlier)."""
    sess = SimulatedSession(seed=11, flight_duration_s=40.0)
    w = DataflashWriter(rotor_rpm(sess), chirp_plan(sess))
    out = {}
    for frame in sess.frames(fast_gyro=True):
        if frame.t_boot_s > 1.0 and "tiny" not in out:
            out["tiny"] = w.getvalue()
        if frame.t_boot_s > 6.0:
            break
        w.add(frame)
    out["short"] = w.getvalue()
    return out


@pytest.fixture(scope="module")
def flight_bin(written):
    return written["short"]


def _tee(fc: SimulatedFCThread, ended: threading.Event) -> list[bytes]:
    """Keep a copy of every byte the FC receives; ``ended`` is set when a LOG_REQUEST_END arrives."""
    sent: list[bytes] = []
    proto = fc.fc.protocol
    original = proto.receive_data
    parser = mavlink2.MAVLink(None, 1, 1)
    parser.robust_parsing = True

    def tee(data: bytes) -> None:
        sent.append(bytes(data))
        if any(m.get_type() == "LOG_REQUEST_END" for m in parser.parse_buffer(data) or []):
            ended.set()
        original(data)

    proto.receive_data = tee
    return sent


def _kinds(chunks: list[bytes]) -> list:
    parser = mavlink2.MAVLink(None, 1, 1)
    parser.robust_parsing = True
    return [m for m in (parser.parse_buffer(b"".join(chunks)) or []) if m.get_type() != "BAD_DATA"]


def test_byte_identical_through_pty_with_one_percent_corruption_and_an_unplug(flight_bin):
    """1 % of bytes get a flipped bit (about 2 in 3 LOG_DATA packets fail their CRC), and 0.5 % of LOG_DATA
    packets carry an error their CRC misses (a wrong block in a valid frame): every block is read twice
    and kept when two copies agree, so the log arrives byte-identical whichever packets the noise hits."""
    fc = SimulatedFCThread(session=Idle(), config=FcConfig(corrupt_rate=0.01, packet_loss=0.0, seed=5,
                                                           crc_blind_rate=0.005))
    fc.fc.protocol.add_log(flight_bin)
    ended = threading.Event()
    to_fc = _tee(fc, ended)
    pulled = threading.Event()

    async def main():
        url = f"serial://{fc.port_path}:921600"
        async with LogTransfer(lambda: open_link(url), config=DownloadConfig(link_lost_give_up_s=30.0)) as tr:
            (entry,) = await tr.list_logs()

            def progress(received, size):
                if received > size // 2 and not pulled.is_set():
                    pulled.set()
                    fc.unplug(1.0)

            return entry, await tr.download(entry, on_progress=progress), tr.check

    with fc:
        entry, data, check = asyncio.run(main())
        assert ended.wait(10), "LOG_REQUEST_END reached the FC"
    assert entry.size_bytes == len(flight_bin)
    assert data == flight_bin
    # the three faults really happened: noise, CRC-blind blocks (more than a few read as first copies), the pull
    assert pulled.is_set() and fc.stats.packets_corrupted > 100 and fc.stats.packets_crc_blind > 10
    reread = dict(check.reread_blocks)
    assert check.verified and check.corrupted_frames > 100 and reread["disagreed"] > 0, check
    assert check.structure == "dataflash records parse end to end"
    msgs = _kinds(to_fc)
    kinds = [m.get_type() for m in msgs]
    assert set(kinds) <= {"HEARTBEAT", "LOG_REQUEST_LIST", "LOG_REQUEST_DATA", "LOG_REQUEST_END"}, set(kinds)
    assert "LOG_REQUEST_END" in kinds
    assert all(m.type == mavlink2.MAV_TYPE_GCS for m in msgs if m.get_type() == "HEARTBEAT")


def test_cli_get_writes_the_verified_log_and_list_shows_it(flight_bin, tmp_path, capsys):
    fc = SimulatedFCThread(session=Idle(), config=FcConfig(packet_loss=0.0, seed=2))
    fc.fc.protocol.add_log(flight_bin)
    url = f"serial://{fc.port_path}:921600"
    with fc:
        assert cli_main(["logs", "list", "--link", url, "--json"]) == 0
        listed = json.loads(capsys.readouterr().out)
        assert listed["logs"] == [{"number": 1, "size_bytes": len(flight_bin), "time_utc_s": 0}]
        assert cli_main(["logs", "get", "1", "--out", str(tmp_path), "--link", url, "--json"]) == 0
        got = json.loads(capsys.readouterr().out)
    path = tmp_path / "log-1.bin"
    assert got["path"] == str(path) and path.read_bytes() == flight_bin
    assert not list(tmp_path.glob("*.part*")) and not list(tmp_path.glob("*.verify"))
    log = load_log(path)
    assert log.has("IMU") and log.has("ROTOR")


def test_a_block_the_fc_serves_differently_every_time_is_saved_unverified_and_said_so(written, tmp_path, capsys):
    tiny = written["tiny"]
    fc = SimulatedFCThread(session=Idle(), config=FcConfig(packet_loss=0.0))
    fc.fc.protocol.add_log(tiny)
    encode = fc.fc.protocol.mav.log_data_encode
    served = [0]

    def changing(lid, ofs, count, data):  # block 5 differs at each read, in a FMT record's padding
        if ofs == 450:
            served[0] += 1
            data = data[:60] + bytes((served[0],)) + data[61:]
        return encode(lid, ofs, count, data)

    fc.fc.protocol.mav.log_data_encode = changing
    url = f"serial://{fc.port_path}:921600"
    with fc:
        code = cli_main(["logs", "get", "1", "--out", str(tmp_path), "--link", url, "--no-progress",
                         "--confirm", "always"])
    out, err = capsys.readouterr()
    path = tmp_path / "log-1.unverified.bin"
    assert code == 3 and out == "" and len(err.strip().splitlines()) == 1, (out, err)
    assert str(path) in err and "NOT verified" in err and "bytes at 450" in err
    got = path.read_bytes()
    assert served[0] == 6 and got[:450] == tiny[:450] and got[540:] == tiny[540:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log-1.unverified.bin"]
    assert load_log(path).has("IMU")


def test_armed_fc_refuses_and_the_tool_says_so_in_one_line(flight_bin, tmp_path, capsys):
    fc = SimulatedFCThread(session=ArmedForever(), config=FcConfig(packet_loss=0.0))
    fc.fc.protocol.add_log(flight_bin)
    with fc:
        code = cli_main(["logs", "get", "1", "--out", str(tmp_path), "--link", f"serial://{fc.port_path}:921600"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "armed" in err[0], err
    assert fc.stats.log_data_sent == 0 and not list(tmp_path.iterdir())


def test_fc_that_stops_answering_names_the_log_and_the_next_get_resumes(flight_bin, tmp_path, capsys):
    n_blocks = -(-len(flight_bin) // 90)
    fc = SimulatedFCThread(session=Idle(), config=FcConfig(packet_loss=0.0, log_stop_after_packets=n_blocks // 3))
    fc.fc.protocol.add_log(flight_bin)
    with fc:
        code = cli_main(["logs", "get", "1", "--out", str(tmp_path), "--give-up-s", "2",
                         "--link", f"serial://{fc.port_path}:921600"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "log 1" in err[0] and "stopped answering" in err[0], err
    part = tmp_path / "log-1.bin.part"
    kept = part.read_bytes()
    assert kept[:90 * (n_blocks // 3 - 1)] == flight_bin[:90 * (n_blocks // 3 - 1)]  # nothing lost
    fc2 = SimulatedFCThread(session=Idle(), config=FcConfig(packet_loss=0.0))
    fc2.fc.protocol.add_log(flight_bin)
    with fc2:
        assert cli_main(["logs", "get", "1", "--out", str(tmp_path), "--no-progress",
                         "--link", f"serial://{fc2.port_path}:921600"]) == 0
    assert (tmp_path / "log-1.bin").read_bytes() == flight_bin
    assert fc2.stats.log_data_sent < n_blocks - n_blocks // 4  # resumed: the first third was not sent again
    assert not part.exists()


def test_simulated_flight_is_logged_at_200_hz_and_served_after_disarm(tmp_path, capsys):
    fc = SimulatedFCThread(speed=20.0, seed=4, flights=1, config=FcConfig(packet_loss=0.0, record_dataflash=True),
                           sim_options={"flight_duration_s": 40.0, "pre_arm_s": 1.0, "post_s": 1.0})
    url = f"serial://{fc.port_path}:921600"
    with fc:
        sess = fc.fc.session
        assert cli_main(["logs", "get", "1", "--out", str(tmp_path), "--no-progress", "--link", url]) != 0
        capsys.readouterr()  # no log yet while armed / flying: one line, checked elsewhere
        done = threading.Event()

        def wait():
            while fc.fc.protocol.armed or not fc.fc.protocol.logs:
                if done.wait(0.05):
                    return

        t = threading.Thread(target=wait)
        t.start()
        t.join(60)
        done.set()
        assert fc.fc.protocol.logs, "the FC finished its flight and closed the log"
        assert cli_main(["logs", "get", "1", "--out", str(tmp_path), "--no-progress", "--link", url]) == 0
    path = tmp_path / "log-1.bin"
    assert path.read_bytes() == fc.fc.protocol.logs[0]
    log = load_log(path)
    imu = log.series["IMU"]
    assert 195 < 1 / float(__import__("numpy").median(__import__("numpy").diff(imu.t_fc_s))) < 205
    assert len(log.flights) == 1 and log.chirps and sess.n_flights == 1
