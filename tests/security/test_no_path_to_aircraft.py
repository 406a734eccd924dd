"""No path from the network to the aircraft: flood every key the live service declares (and heli/**)
with garbage while it runs against the simulated FC, and check every byte it wrote to the FC.

The attacker is a zenoh peer connected straight to the service's own session (no router, no ACL):
the guarantee must hold even when the network layer's access control is missing. The bytes the
service writes reach the real simulated FC on a real pty; a tee on the FC's input keeps a copy.
"""

from __future__ import annotations

import asyncio
import json
import random
import threading

import zenoh
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from groundstation.service import Service
from groundstation.sinks.zenoh_sink import loopback_peer_config
from tests.service.conftest import ScriptedHelicopter, service_config

ALLOWED_COMMANDS = {mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink2.MAV_CMD_REQUEST_MESSAGE}


class TeeService(Service):
    """The real service; the built-in FC's input is teed into ``to_fc`` (bytes still reach the FC)."""

    to_fc: list[bytes]

    def _start_builtin_sim(self) -> str:
        url = super()._start_builtin_sim()
        self.to_fc = []
        proto = self.sim.fc.protocol
        original = proto.receive_data

        def tee(data: bytes) -> None:
            self.to_fc.append(bytes(data))
            original(data)

        proto.receive_data = tee
        return url


def _evil_payloads(rng: random.Random) -> list[bytes]:
    mav = mavlink2.MAVLink(None, 255, 190)
    arm = mav.command_long_encode(1, 1, mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 21196, 0, 0, 0, 0, 0)
    mode = mav.set_mode_encode(1, mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)
    rc = mav.rc_channels_override_encode(1, 1, 2000, 1000, 2000, 1000, 0, 0, 0, 0)
    reboot = mav.command_long_encode(1, 1, mavlink2.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 0, 1, 0, 0, 0, 0, 0, 0)
    param = mav.param_set_encode(1, 1, b"ARMING_CHECK", 0, mavlink2.MAV_PARAM_TYPE_REAL32)
    frames = [m.pack(mav) for m in (arm, mode, rc, reboot, param)]
    return [
        *frames,
        b"".join(frames),
        json.dumps({"command": "arm", "mavlink": frames[0].hex()}).encode(),
        json.dumps({"schema": "heli-hover-model/1", "send": "COMMAND_LONG", "command": 400}).encode(),
        b"\x00" * 70_000,
        bytes(rng.getrandbits(8) for _ in range(4096)),
        b"{not json",
    ]


def test_flooding_every_key_sends_nothing_beyond_the_allowlist(tmp_path):
    cfg = service_config(tmp_path, service={"exit_after_flights": 1}, sim={"speed": 2.0},
                         identification={"enabled": False})
    service = TeeService(cfg, frame_source=ScriptedHelicopter(flights=1, flight_s=6.0, pause_s=1.0),
                         log=lambda m: None)
    vehicle = cfg.service.vehicle
    keys = [f"heli/{vehicle}/{k}" for k in ("status", "telemetry/window", "flight/1/model", "flight/1/gap",
                                             "model/latest", "gap/latest", "alive", "command", "mavlink",
                                             "link/tx", "flight/1/command")]
    keys += ["heli/**", f"heli/{vehicle}/**", "**", "@/**"]
    rng = random.Random(7)
    payloads = _evil_payloads(rng)
    stats = {"puts": 0, "gets": 0, "replies": 0, "status_seen": 0, "passes": 0}
    stop = threading.Event()

    def flood(port: int) -> None:
        session = zenoh.open(zenoh.Config.from_json5(loopback_peer_config(connect_ports=(port,))))
        try:
            session.declare_subscriber(f"heli/{vehicle}/status", lambda s: stats.__setitem__(
                "status_seen", stats["status_seen"] + 1))
            tokens = [session.liveliness().declare_token(f"heli/{vehicle}/alive")]
            evil_q = session.declare_queryable(f"heli/{vehicle}/**", lambda q: q.reply(q.key_expr, payloads[0]))
            while not stop.is_set():
                for key in keys:
                    concrete = key.replace("/**", "/x").replace("**", "heli/x")
                    if concrete.startswith("@"):
                        concrete = f"heli/{vehicle}/@x"
                    for p in payloads:
                        session.put(concrete, p)
                        stats["puts"] += 1
                    session.delete(concrete)
                for key in (f"heli/{vehicle}/model/latest", f"heli/{vehicle}/gap/latest", f"heli/{vehicle}/**"):
                    replies = session.get(f"{key}?arm=1;cmd=COMMAND_LONG", payload=payloads[0], timeout=0.5)
                    stats["gets"] += 1
                    stats["replies"] += sum(1 for _ in replies)
                stats["passes"] += 1
            evil_q.undeclare()
            for t in tokens:
                t.undeclare()
        finally:
            session.close()

    async def main():
        task = asyncio.create_task(service.run())
        await asyncio.wait_for(service.ready.wait(), 15)
        th = threading.Thread(target=flood, args=(cfg.zenoh.listen_port,), daemon=True)
        th.start()
        try:
            report = await asyncio.wait_for(task, 60)
            stats["passes_while_running"] = stats["passes"]
            return report
        finally:
            stop.set()
            await asyncio.to_thread(th.join, 10)

    report = asyncio.run(main())

    # the flood reached the service's session: it was connected, queried, and saw statuses
    # at least one whole pass over every key and payload while the service was running
    assert stats["passes_while_running"] >= 1 and stats["replies"] > 0 and stats["status_seen"] > 0
    assert service.zenoh.queries_served > 0
    assert report.flights == 1 and report.packets > 300   # the service really ran a flight meanwhile

    sent = b"".join(service.to_fc)
    assert sent, "the service talks to the FC (heartbeats, stream requests)"
    parser = mavlink2.MAVLink(None, 1, 1)
    parser.robust_parsing = True
    msgs = parser.parse_buffer(sent) or []
    kinds: dict[str, int] = {}
    for m in msgs:
        kind = m.get_type()
        kinds[kind] = kinds.get(kind, 0) + 1
        assert kind in ("HEARTBEAT", "COMMAND_LONG", "REQUEST_DATA_STREAM"), kind
        if kind == "COMMAND_LONG":
            assert m.command in ALLOWED_COMMANDS, m.command
        if kind == "HEARTBEAT":
            assert m.type == mavlink2.MAV_TYPE_GCS
    assert kinds.get("HEARTBEAT", 0) >= 2 and kinds.get("COMMAND_LONG", 0) >= 1
    # every byte belongs to one of those frames: nothing unparsed slipped through
    assert sum(len(m.get_msgbuf()) for m in msgs) == len(sent)
    for p in payloads[:5]:
        assert p not in sent
