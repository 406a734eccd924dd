"""The service's live excitation monitor end to end: the built-in simulated FC on a pty, the verdicts
on zenoh (``heli/{vehicle}/excitation``, real loopback session), in the status and the log, and the
Rerun recording's excitation panel."""

from __future__ import annotations

import asyncio
import time

from rerun.chunk import RrdReader

from groundstation.service import Service
from groundstation.worker import JobResult
from tests.service.conftest import service_config


def test_verdicts_on_zenoh_status_log_and_rerun(tmp_path, subscriber_factory):
    rrd = tmp_path / "exc.rrd"
    cfg = service_config(tmp_path, service={"exit_after_flights": 1}, sim={"speed": 10.0, "flights": 1, "seed": 2},
                         identification={"enabled": False}, rerun={"mode": "save", "target": str(rrd)})
    lines: list[str] = []
    service = Service(cfg, sim_options={"flight_duration_s": 40.0}, log=lines.append)
    verdicts = []
    service.on_excitation = verdicts.append

    async def main():
        task = asyncio.create_task(service.run())
        await asyncio.wait_for(service.ready.wait(), 30)
        sub = subscriber_factory(cfg.zenoh.listen_port)
        return await asyncio.wait_for(task, 240), sub

    report, sub = asyncio.run(main())
    assert report.flights == 1 and not report.warnings, (report.warnings, lines)
    # about one verdict per FC second while armed (the last one at the disarm)
    assert len(verdicts) >= 25 and verdicts[-1].flight == 1
    v = f"heli/{service.vehicle}/excitation"
    deadline = time.monotonic() + 30.0          # the subscriber joined after the start: it has most of them
    while time.monotonic() < deadline and not any(d.get("final") for d in sub.of("/excitation")):
        time.sleep(0.05)
    docs = sub.of("/excitation")
    assert len(docs) >= 10 and docs[-1]["final"] is True
    assert all(k == v for k, _, _ in sub.samples if k.endswith("/excitation"))
    for d in docs:
        assert d["flight"] == 1 and d["vehicle"] == service.vehicle and d["t_s"] >= 0
        assert set(d["axes"]) == {"lat", "lon", "col", "ped"}
        for ax in d["axes"].values():
            assert {"enough", "band_hz", "covered_hz", "coherence_min", "missing"} <= set(ax)
            assert ax["band_hz"] == [0.3, 5.0] and (ax["missing"] == "") == ax["enough"]
    # the status carries the verdict's line; the log says it at the end of the flight
    status = [d for d in sub.of("/status") if d.get("excitation")]
    assert status and status[-1]["excitation"]["line"].startswith("excitation flight 1")
    assert any(m.startswith("excitation flight 1 @") for m in lines), lines
    # Rerun: the excitation panel of the live recording
    ents = {c.entity_path for c in RrdReader(rrd).stream().to_chunks()}
    root = f"/{service.vehicle}/excitation"
    assert {f"{root}/lat/coherence", f"{root}/covered/ped", f"{root}/summary"} <= ents


def _report_live_spectra(job):
    """Worker job: says what the service handed over instead of identifying (picklable, module level)."""
    sp = job.live_spectra
    return JobResult(flight=job.flight, tlogs=job.tlogs,
                     error=f"live spectra: {None if sp is None else sp.rows} rows, windows {getattr(sp, 'windows', None) and [w.win_s for w in sp.windows]}")


def test_the_job_of_a_flight_carries_its_live_freq_spectra(tmp_path):
    cfg = service_config(tmp_path, service={"exit_after_flights": 1}, sim={"speed": 10.0, "flights": 1, "seed": 3},
                         identification={"scope": "last"})
    service = Service(cfg, sim_options={"flight_duration_s": 35.0}, log=lambda m: None, job_fn=_report_live_spectra)
    report = asyncio.run(asyncio.wait_for(service.run(), 240))
    said = [w for w in report.warnings if "live spectra:" in w]
    assert len(said) == 1, report.warnings
    rows = int(said[0].split("live spectra: ")[1].split(" rows")[0])
    assert rows > 20 * 50 and "[5.0, 10.0, 20.0]" in said[0]      # the in-air rows, [freq]'s windows
