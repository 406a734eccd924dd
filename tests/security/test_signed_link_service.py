"""The live service with a MAVLink signing key against an FC that does not sign: every frame is
recorded raw but flagged and not decoded, the status reports it, the key never shows."""

from __future__ import annotations

import asyncio
import json
import os

from firmware_interface.readers import load_log
from firmware_interface.tlogread import scan_tlog
from groundstation.cli import main as cli_main
from groundstation.service import Service
from tests.service.conftest import ScriptedHelicopter, service_config

SECRET = bytes(range(100, 132))


def _key_file(path, mode=0o600):
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "w") as f:
        f.write(SECRET.hex())
    os.chmod(path, mode)
    return path


def test_unsigned_fc_frames_are_recorded_flagged_not_decoded_and_reported(tmp_path):
    key = _key_file(tmp_path / "fc.key")
    cfg = service_config(tmp_path, link={"signing_key_file": str(key)}, sim={"speed": 4.0},
                         identification={"enabled": False}, zenoh={"enabled": False})
    service = Service(cfg, frame_source=ScriptedHelicopter(flights=1, flight_s=3.0, pause_s=1.0),
                      log=lambda m: None)

    async def main():
        task = asyncio.create_task(service.run())
        await asyncio.wait_for(service.ready.wait(), 15)
        for _ in range(400):
            if service.session.stats.packets >= 4:
                break
            await asyncio.sleep(0.02)
        status = service.status()
        service.request_stop("test")
        return status, await asyncio.wait_for(task, 30)

    status, report = asyncio.run(main())
    sig = status["signing"]
    # the simulated FC only sends heartbeats until asked for streams, and an unverified heartbeat
    # never makes the session ask
    assert sig["enabled"] is True and sig["unsigned"] >= 4 and sig["ok"] == 0
    assert sig["dropped"] == sig["unsigned"] + sig["bad_signature"] + sig["replayed"]
    assert SECRET.hex() not in json.dumps(status)
    # nothing decoded: no heartbeat, so no flight, and the session never asked for streams
    assert status["armed"] is False and report.flights == 0
    assert service.session.message_counts.get("HEARTBEAT", 0) > 0        # framed and counted ...
    assert service.session.target is None            # ... but no heartbeat accepted: no FC, no requests
    # ... but every frame is in the session .tlog
    records = list(scan_tlog(open(report.session_tlog, "rb").read()))
    assert len(records) >= sig["unsigned"] > 0
    assert load_log(report.session_tlog).message_counts.get("HEARTBEAT", 0) >= 4


def test_group_readable_key_stops_the_service_with_one_line(tmp_path, capsys):
    key = _key_file(tmp_path / "fc.key", 0o644)
    rc = cli_main(["run", "--signing-key", str(key), "--no-zenoh", "--no-identify",
                   "--record-dir", str(tmp_path / "rec"), "--speed", "8"])
    err = capsys.readouterr().err
    assert rc == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(key) in lines[0] and "chmod 600" in lines[0]
    assert SECRET.hex() not in err
