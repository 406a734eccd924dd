"""The service on the link driver: an in-memory scripted link (no pty, no sleep) for the logic, and a
real pty that appears after the service started (the flight controller plugged in late)."""

from __future__ import annotations

import asyncio

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.readers import load_log
from firmware_interface.transports import LinkDown, ScriptedLink
from groundstation.service import Service
from hil_replay.fc import FcConfig, SimulatedFCThread
from tests.service.conftest import ScriptedHelicopter, service_config


def _flight_bytes(heli: ScriptedHelicopter) -> list[bytes]:
    """The FC's byte stream, one chunk per 50 Hz frame (heartbeats at 5 Hz)."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    chunks = []
    for fr in heli.frames():
        out = b""
        if fr.k % 10 == 0:
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if fr.armed else 0)
            out += mav.heartbeat_encode(mavlink.MAV_TYPE_HELICOPTER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base, 0,
                                        mavlink.MAV_STATE_ACTIVE).pack(mav)
        for name in fr.available:
            out += fr.build(name, mav).pack(mav)
        chunks.append(out)
    return chunks


def test_service_over_a_scripted_link_records_one_flight_across_a_link_loss(tmp_path):
    heli = ScriptedHelicopter(flights=1, flight_s=6.0, pause_s=1.0)
    chunks = _flight_bytes(heli)
    half = len(chunks) // 2
    first = ScriptedLink([*chunks[:half], LinkDown("script://fc: cable pulled")], url="script://fc")
    second = ScriptedLink(chunks[half:], url="script://fc")
    links = [first, second]

    async def opener():
        return links.pop(0)

    cfg = service_config(tmp_path, service={"exit_after_flights": 1}, identification={"enabled": False},
                         zenoh={"enabled": False})
    lines: list[str] = []
    service = Service(cfg, link_opener=opener, log=lines.append)
    windows = []
    service.on_window = windows.append

    report = asyncio.run(asyncio.wait_for(service.run(), 60))
    assert report.flights == 1 and report.stopped_by == "1 flight(s) done"
    assert service.link_drops == 1 and first.closed and not links
    assert any("link lost (script://fc: cable pulled)" in m for m in lines)
    assert any(m == "link script://fc reopened" for m in lines)
    log = load_log(report.flight_tlogs[0])
    # every ATTITUDE of the armed interval, from both links, in one flight file
    armed = [fr for fr in heli.frames() if fr.armed and "ATTITUDE" in fr.available]
    t = log.series["ATTITUDE"].t_fc_s
    assert len(t) >= len(armed) - 10 and t[0] <= armed[0].t_boot_s + 0.2 and t[-1] >= armed[-1].t_boot_s - 0.2
    assert windows and {w.flight for w in windows} >= {1}
    assert bytes(first.written)                           # the ground station talked (heartbeat, streams)


def test_service_waits_for_a_port_plugged_in_later(tmp_path):
    late = tmp_path / "ttyACM0"
    cfg = service_config(tmp_path, service={"exit_after_flights": 1}, link={"url": f"serial://{late}:115200"},
                         identification={"enabled": False}, zenoh={"enabled": False})
    lines: list[str] = []
    fcs: list[SimulatedFCThread] = []

    async def main():
        waiting = asyncio.Event()

        def log(m: str) -> None:
            lines.append(m)
            if m.startswith("waiting for"):
                waiting.set()

        service = Service(cfg, log=log)
        task = asyncio.create_task(service.run())
        await asyncio.wait_for(waiting.wait(), 30)
        assert not service.ready.is_set() and not task.done()
        fc = SimulatedFCThread(str(late), speed=4.0, session=ScriptedHelicopter(flights=1, flight_s=3.0, pause_s=1.0),
                               config=FcConfig(packet_loss=0.0))       # plugged in now
        fcs.append(fc)
        fc.start()
        return await asyncio.wait_for(task, 60)

    try:
        report = asyncio.run(main())
    finally:
        for fc in fcs:
            fc.stop()
    assert lines.count(f"waiting for {late}") == 1
    assert report.flights == 1 and load_log(report.flight_tlogs[0]).has("ATTITUDE")


def test_ctrl_c_while_waiting_for_the_port_stops_cleanly(tmp_path):
    cfg = service_config(tmp_path, link={"url": f"serial://{tmp_path}/ttyNEVER:115200"},
                         identification={"enabled": False}, zenoh={"enabled": False})

    async def main():
        waiting = asyncio.Event()
        service = Service(cfg, log=lambda m: waiting.set() if m.startswith("waiting for") else None)
        task = asyncio.create_task(service.run())
        await asyncio.wait_for(waiting.wait(), 30)
        service.request_stop("SIGINT")
        return await asyncio.wait_for(task, 10)

    report = asyncio.run(main())
    assert report.stopped_by == "SIGINT" and report.flights == 0 and not report.warnings


def test_a_path_that_is_not_a_serial_device_is_one_line_exit_2(tmp_path, capsys):
    from groundstation.cli import main

    f = tmp_path / "notes.txt"
    f.write_text("x")
    assert main(["run", "--link", f"serial://{f}:115200", "--record-dir", str(tmp_path / "rec"), "--no-zenoh"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(f) in err[0] and "not a serial device" in err[0]
