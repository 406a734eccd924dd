"""The live service end to end: simulated FC on a real pty -> serial transport -> session -> recorder
-> live DSP -> real zenoh subscriber and a real .rrd read back."""

from __future__ import annotations

import asyncio

import numpy as np
from rerun.chunk import RrdReader

from firmware_interface.readers import load_log
from groundstation.service import Service
from tests.service.conftest import ScriptedHelicopter, service_config


def _run(service: Service, subscriber_factory=None, timeout_s: float = 60.0):
    async def main():
        task = asyncio.create_task(service.run())
        await asyncio.wait_for(service.ready.wait(), 10)
        sub = subscriber_factory(service.config.zenoh.listen_port) if subscriber_factory else None
        report = await asyncio.wait_for(task, timeout_s)
        return report, sub

    return asyncio.run(main())


def test_two_scripted_flights_recorded_streamed_and_logged(tmp_path, subscriber_factory):
    rrd = tmp_path / "run.rrd"
    cfg = service_config(tmp_path, service={"exit_after_flights": 2}, sim={"speed": 4.0},
                         identification={"enabled": False}, rerun={"mode": "save", "target": str(rrd), "raw": True})
    heli = ScriptedHelicopter(flights=2, flight_s=4.0, pause_s=2.0)
    service = Service(cfg, frame_source=heli, log=lambda m: None)
    report, sub = _run(service, subscriber_factory)

    # recordings: a session file and one file per flight, all readable
    assert report.flights == 2 and len(report.flight_tlogs) == 2
    for p in report.flight_tlogs:
        log = load_log(p)
        assert log.has("ATTITUDE") and len(log.flights) == 1
        t_att = log.series["ATTITUDE"].t_fc_s
        assert 3.5 < t_att[-1] - t_att[0] < 5.5     # the 4 s armed interval (heartbeats at 1 Hz)
    assert load_log(report.session_tlog).has("SERVO_OUTPUT_RAW")
    assert report.packets > 1000

    # zenoh: status, windows with smoothed outputs, liveliness implied by session; windows flag flights
    status = sub.of("/status")
    windows = sub.of("/telemetry/window")
    assert status and status[-1]["flights_completed"] == 2 and status[-1]["link"]["up"] is True
    assert {"ATTITUDE", "SERVO_OUTPUT_RAW"} <= set(status[-1]["rates_hz"])
    lat = status[-1]["windows"]["latency_ms"]
    assert 0 < lat["median"] <= lat["p99"]
    assert len(windows) > 10
    in_flight = [w for w in windows if w["flight"] is not None]
    assert {w["flight"] for w in in_flight} == {1, 2}
    w = in_flight[-1]
    assert len(w["t_fc_s"]) == 100 and np.allclose(np.diff(w["t_fc_s"]), 0.02, atol=1e-3)
    p_raw = np.array(w["outputs"]["p"]["raw"], dtype=float)
    p_sm = np.array([np.nan if x is None else x for x in w["outputs"]["p"]["smoothed"]])
    assert np.isnan(p_sm[-2:]).all() and np.isfinite(p_sm[:-2]).all()
    assert np.nanmax(np.abs(p_sm[:-2] - p_raw[:-2])) < 0.02     # a smooth signal barely changes
    assert report.windows_dropped == 0

    # Rerun: the expected entities with both timelines
    chunks = RrdReader(rrd).stream().to_chunks()
    ents = {c.entity_path for c in chunks if not c.is_static}
    for c in ("lat", "lon", "col", "ped"):
        assert f"/testheli/inputs/{c}" in ents
    for c in ("u", "v", "w", "p", "q", "r", "theta", "phi"):
        assert f"/testheli/outputs/{c}/raw" in ents and f"/testheli/outputs/{c}/smoothed" in ents
    lat = [c for c in chunks if c.entity_path == "/testheli/inputs/lat" and not c.is_static]
    assert {"fc_time", "host_time"} <= set(lat[0].timeline_names)
    sm = [c for c in chunks if c.entity_path == "/testheli/outputs/q/smoothed" and not c.is_static]
    assert {"fc_time", "host_time"} <= set(sm[0].timeline_names)
    assert sum(c.num_rows for c in lat) == service.live.rows > 400   # every grid row reached the .rrd
