"""The service downloads each flight's onboard log over its own link while disarmed, with the built-in
simulated FC (which writes a 200 Hz dataflash log of the flight), and every byte it sent the FC is a
heartbeat, a stream request or one of the log-download requests."""

from __future__ import annotations

import asyncio
import itertools

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.readers import load_log
from groundstation.service import Service
from tests.service.conftest import service_config


class TeeService(Service):
    def _start_builtin_sim(self) -> str:
        url = super()._start_builtin_sim()
        self.to_fc: list[bytes] = []
        proto = self.sim.fc.protocol
        original = proto.receive_data

        def tee(data: bytes) -> None:
            self.to_fc.append(bytes(data))
            original(data)

        proto.receive_data = tee
        return url


def test_service_downloads_the_flight_log_between_flights(tmp_path):
    cfg = service_config(tmp_path, service={"exit_after_flights": 1}, sim={"speed": 20.0, "flights": 1, "seed": 6},
                         identification={"enabled": False},
                         # the FC answers within milliseconds; timeouts far beyond that keep a starved
                         # test machine from being mistaken for a silent FC (the defaults stay 1.5 s / 8 s)
                         onboard_logs={"download": True, "after_disarm_s": 0.5,
                                       "list_timeout_s": 60.0, "give_up_s": 120.0})
    lines: list[str] = []
    service = TeeService(cfg, sim_options={"flight_duration_s": 40.0, "pause_s": 2.0}, log=lines.append)
    report = asyncio.run(asyncio.wait_for(service.run(), 240))
    assert report.flights == 1, lines
    fc_logs = service.sim.fc.protocol.logs
    assert len(fc_logs) == 1
    path = tmp_path / "rec" / "onboard" / "log-1.bin"
    assert service.onboard.downloaded == [str(path)], (lines, service._stop_reason)
    assert path.read_bytes() == fc_logs[0]
    log = load_log(path)
    assert log.has("IMU") and log.chirps
    parser = mavlink2.MAVLink(None, 1, 1)
    parser.robust_parsing = True
    kinds = {m.get_type() for m in parser.parse_buffer(b"".join(service.to_fc)) or [] if m.get_type() != "BAD_DATA"}
    assert {"LOG_REQUEST_LIST", "LOG_REQUEST_DATA", "LOG_REQUEST_END"} <= kinds
    assert kinds <= {"HEARTBEAT", "COMMAND_LONG", "REQUEST_DATA_STREAM", "LOG_REQUEST_LIST", "LOG_REQUEST_DATA",
                     "LOG_REQUEST_END"}


def test_the_services_download_reads_every_block_twice_when_its_link_corrupts_frames(tmp_path):
    """OnboardLogs on a real session against the simulated FC's protocol (1 % of bytes flipped, and
    0.5 % of LOG_DATA with an error the CRC misses), one 20 ms tick at a time: the session's failed
    CRCs reach the download, every block is read twice, and the log line says so."""
    from benchkit.onboard_logs import simulated_dataflash
    from firmware_interface.session import MavlinkSession, SessionConfig
    from groundstation.config import OnboardLogsSection
    from groundstation.onboard import OnboardLogs
    from hil_replay.fc import FcConfig, FcProtocol
    from tests.link.test_logdownload import Tick

    data = simulated_dataflash(30_000, 3)
    fc = FcProtocol(FcConfig(packet_loss=0.0, corrupt_rate=0.01, crc_blind_rate=0.005, seed=4))
    fc.add_log(data)
    session = MavlinkSession(SessionConfig(request_streams=False, link_timeout_s=1e9))
    lines: list[str] = []
    ob = OnboardLogs(OnboardLogsSection(after_disarm_s=0.1, list_timeout_s=60.0, give_up_s=60.0), tmp_path,
                     session, lines.append)

    async def run() -> None:
        for k in itertools.count(1):  # the FC idles on after the download until the writer thread is done
            t = k * 0.02
            session.receive_data(b"".join(fc.on_frame(Tick(t))), t)
            ob.on_events(session.events(), t)
            if k == 100:
                ob.flight_ended(t)
            ob.tick(t)
            fc.receive_data(session.data_to_send(t))
            if ob.downloaded:
                return
            await asyncio.sleep(0)  # the writer thread's result comes back through the loop

    asyncio.run(asyncio.wait_for(run(), 120))
    assert (tmp_path / "log-1.bin").read_bytes() == data
    (line,) = [x for x in lines if "wrote" in x]
    assert "verified: every block read twice" in line and session.stats.bad_crc > 100, lines
