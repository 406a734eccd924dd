"""The whole mission with the real simulator: two short simulated flights through the built-in FC on a
pty at high speed; identification (and diagnosis) in the worker process between and after flights;
a zenoh subscriber gets status, windows, models and gap reports; a late subscriber gets the model from
the queryable; the .rrd has the live, model and gap entities."""

from __future__ import annotations

import asyncio
import functools
import json
import os
import signal
import threading
import time

import pytest
import zenoh
from rerun.chunk import RrdReader

from groundstation.service import Service
from groundstation.sinks.zenoh_sink import loopback_peer_config
from tests.service.conftest import service_config


def test_two_simulated_flights_identified_published_and_logged(tmp_path, subscriber_factory):
    rrd = tmp_path / "mission.rrd"
    cfg = service_config(tmp_path, service={"exit_after_flights": 2}, sim={"speed": 20.0, "flights": 2, "seed": 4},
                         identify={"maxiter": 8}, identification={"refine": False, "scope": "all"},
                         rerun={"mode": "save", "target": str(rrd)})
    lines: list[str] = []
    service = Service(cfg, sim_options={"flight_duration_s": 40.0, "pause_s": 3.0},
                      log=lambda m: lines.append(f"{time.monotonic():.1f} {m}"))
    late_replies: list[dict] = []

    async def main():
        task = asyncio.create_task(service.run())
        await asyncio.wait_for(service.ready.wait(), 20)
        port = cfg.zenoh.listen_port
        sub = subscriber_factory(port)
        # a late subscriber: joins after the first model exists, asks the queryable
        while service.zenoh.latest["model"] is None and not task.done():
            await asyncio.sleep(0.1)
        if not task.done():
            def ask():
                s = zenoh.open(zenoh.Config.from_json5(loopback_peer_config(connect_ports=(port,))))
                try:
                    end = time.monotonic() + 30      # until the queryable is known to the new peer
                    while not late_replies and time.monotonic() < end:
                        for r in s.get(f"heli/{service.vehicle}/model/latest", timeout=1):
                            if r.ok is not None:
                                late_replies.append(json.loads(r.ok.payload.to_string()))
                finally:
                    s.close()
            await asyncio.to_thread(ask)
        report = await asyncio.wait_for(task, 240)
        return report, sub

    report, sub = asyncio.run(main())
    assert report.flights == 2, lines
    errors = [r.error for r in report.results if not r.ok]
    assert not errors, errors
    assert sorted(r.flight for r in report.results) == [1, 2]
    by_flight = {r.flight: r for r in report.results}
    assert list(by_flight[1].tlogs) == report.flight_tlogs[:1]
    assert list(by_flight[2].tlogs) == report.flight_tlogs            # scope "all": every flight so far
    for r in report.results:
        model = json.loads(open(r.model_path).read())
        assert model == r.model
        assert model["schema"] == "heli-hover-model/1" and len(model["parameters"]) == 31
        assert set(r.match_degree) <= {"u", "v", "w", "p", "q", "r", "theta", "phi"}

    # zenoh: status, windows, a model (and gap report) per flight
    assert sub.of("/status") and len(sub.of("/telemetry/window")) > 20
    # live input trim follows the latest model (automatic trim)
    last_model = max(report.results, key=lambda r: r.flight).model
    deadline = time.monotonic() + 30.0         # the final status is published during shutdown
    while (time.monotonic() < deadline
           and sub.of("/status")[-1]["input_trim_pwm"] != pytest.approx(last_model["input_trim_pwm"])):
        time.sleep(0.05)
    assert sub.of("/status")[-1]["input_trim_pwm"] == pytest.approx(last_model["input_trim_pwm"])
    models = {k: d for k, d, _ in sub.samples if k.endswith("/model")}
    assert set(models) == {f"heli/{service.vehicle}/flight/1/model", f"heli/{service.vehicle}/flight/2/model"}
    gaps = {k for k, _, _ in sub.samples if k.endswith("/gap")}
    if any(r.gap is not None for r in report.results):
        assert gaps == {f"heli/{service.vehicle}/flight/1/gap", f"heli/{service.vehicle}/flight/2/gap"}
        for k, d, _ in sub.samples:
            if k.endswith("/gap"):
                assert d["schema"] == "heli-gap-report/2"
    assert late_replies and late_replies[0]["schema"] == "heli-hover-model/1"
    # the frequency-domain check of each flight's model: a J table on heli/{vehicle}/flight/{n}/freq
    assert all(r.freq is not None and r.freq_error is None for r in report.results), [r.freq_error for r in report.results]
    freqs = {k: d for k, d, _ in sub.samples if k.endswith("/freq")}
    assert set(freqs) == {f"heli/{service.vehicle}/flight/1/freq", f"heli/{service.vehicle}/flight/2/freq"}
    for d in freqs.values():
        assert d["schema"] == "heli-freq-verification/1" and "J_avg" in d
        assert all({"input", "output", "J", "coherent_points", "delay_s"} <= set(p) for p in d["pairs"])
        assert len(d["pairs"]) + len(d["no_response"]) + len(d["unmodelled"]) == 32

    # Rerun: live entities, model overlay and residual, flight states, per-flight fit and gap pictures
    chunks = RrdReader(rrd).stream().to_chunks()
    ents = {c.entity_path for c in chunks}
    v = f"/{service.vehicle}"
    for c in ("u", "q", "theta"):
        assert {f"{v}/outputs/{c}/smoothed", f"{v}/outputs/{c}/model", f"{v}/outputs/{c}/residual"} <= ents
    assert f"{v}/flight/state" in ents
    for r in report.results:
        if r.gap is not None:
            n = r.flight
            assert {f"{v}/flights/{n}/fit", f"{v}/flights/{n}/verdict"} <= ents
            for c in r.gap["gap"]["channels"]:
                assert {f"{v}/gap/residual/{c}/residual", f"{v}/flights/{n}/spectrum/{c}/psd"} <= ents


def _blocks_on_flight_1(fifo: str, job):
    """Worker job for the kill test: flight 1 announces its pid on ``fifo`` and then blocks until the
    process is killed; later flights are identified for real."""
    if job.flight != 1:
        from groundstation.worker import run_job

        return run_job(job)
    with open(fifo, "w") as f:            # opens when the test is reading: a rendezvous, not a delay
        f.write(str(os.getpid()))
    threading.Event().wait()              # until killed


def test_worker_killed_mid_identification_is_reported_and_replaced(tmp_path):
    fifo = tmp_path / "job-started.fifo"
    os.mkfifo(fifo)
    cfg = service_config(tmp_path, service={"exit_after_flights": 2}, sim={"speed": 20.0, "flights": 2, "seed": 5},
                         identify={"maxiter": 6}, identification={"refine": False, "diagnose": False, "plots": False},
                         zenoh={"enabled": False})
    service = Service(cfg, sim_options={"flight_duration_s": 40.0, "pause_s": 3.0}, log=lambda m: None,
                      job_fn=functools.partial(_blocks_on_flight_1, str(fifo)))
    killed: list[int] = []

    def job_pid() -> int:
        with open(fifo) as f:            # returns when flight 1's job has started in the worker
            return int(f.read())

    async def main():
        task = asyncio.create_task(service.run())
        try:
            pid = await asyncio.wait_for(asyncio.to_thread(job_pid), 240)
        except BaseException:
            try:                                             # release the reader thread
                os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
            except OSError:
                pass
            raise
        os.kill(pid, signal.SIGKILL)                         # the worker dies (OOM killer, say) mid-job
        killed.append(pid)
        return await asyncio.wait_for(task, 240)

    report = asyncio.run(main())
    assert killed and report.flights == 2
    by_flight = {r.flight: r for r in report.results}
    assert set(by_flight) == {1, 2}
    assert not by_flight[1].ok and "BrokenProcessPool" in by_flight[1].error     # the killed job, by flight
    assert by_flight[2].ok and by_flight[2].model["schema"] == "heli-hover-model/1"
    assert any("worker died" in w for w in report.warnings)
