"""The pages made where the analysis already runs: the service's worker writes ``report-flightNN.html``
beside the model and the service publishes its path and summary on zenoh; ``campaign --report-dir``
writes a page per flight and one campaign page linking them. Short simulated flights and a short
search: these tests check the plumbing, the page's content is ``test_report.py``'s."""

from __future__ import annotations

import re
import subprocess
import sys
import time

from groundstation.config import ServiceConfig
from groundstation.report.data import SECTIONS
from groundstation.sinks.zenoh_sink import ZenohSink
from groundstation.worker import IdentifyJob, run_job
from hil_replay.sim import write_tlog
from tests.report.test_report import Page
from tests.sinks.conftest import collector_factory  # noqa: F401 - the fixture, shared

SECTION_IDS = [s for s, _ in SECTIONS]


def test_worker_writes_the_flight_page_beside_the_model_with_earlier_flights(tmp_path):
    cfg = ServiceConfig()
    cfg = cfg.replace("identify", maxiter=4, search_restarts=1)
    cfg = cfg.replace("service", vehicle="pageheli")
    results = []
    for k in range(2):
        p = tmp_path / f"flight{k}.tlog"
        write_tlog(p, seed=70 + k, flights=1, flight_duration_s=30.0)
        res = run_job(IdentifyJob(flight=k + 1, tlogs=(str(p),), out_dir=str(tmp_path), config=cfg))
        assert res.error is None and res.report_error is None, res.error or res.report_error
        results.append(res)
    res = results[1]
    assert res.report_path == str(tmp_path / "report-flight02.html")
    assert (tmp_path / "model-flight02.json").exists()
    assert "held-out" not in res.report_summary or "%" in res.report_summary
    assert "verdict" in res.report_summary and "in air" in res.report_summary
    page = Page((tmp_path / "report-flight02.html").read_text())
    assert page.sections == SECTION_IDS and len(page.figures) >= 8
    assert "across" not in page.unmade          # the campaign table knows flight 1
    assert any(f["id"] == "fig-trends" for f in page.figures)
    # plots off: no page
    (tmp_path / "off").mkdir()
    res = run_job(IdentifyJob(flight=3, tlogs=(str(tmp_path / "flight0.tlog"),), out_dir=str(tmp_path / "off"),
                              config=cfg.replace("identification", plots=False, diagnose=False)))
    assert res.error is None and res.report_path is None and not list((tmp_path / "off").glob("*.html"))


def test_report_path_and_summary_reach_a_zenoh_subscriber(collector_factory):  # noqa: F811
    sink = ZenohSink("rp1")
    try:
        col = collector_factory(sink.endpoint)
        end = time.monotonic() + 20
        while time.monotonic() < end and not col.wait_for(lambda s: any(k == "heli/rp1/status" for k, _ in s), 0.2):
            sink.publish_status({"i": -1})
        doc = {"vehicle": "rp1", "flight": 3, "path": "/data/report-flight03.html", "summary": "140 s in air"}
        sink.publish_report(3, doc)
        assert col.wait_for(lambda s: any(k == "heli/rp1/flight/3/report" for k, _ in s))
        got = next(d for k, d in col.samples if k == "heli/rp1/flight/3/report")
        assert got == doc and sink.sent["report"] == 1
    finally:
        sink.close()


def test_campaign_writes_a_page_per_flight_and_a_campaign_page(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    for k in range(2):
        write_tlog(logs / f"f{k}.tlog", seed=80 + k, flights=1, flight_duration_s=30.0)
    (logs / "broken.tlog").write_bytes(b"not a log" * 10)
    pages = tmp_path / "pages"
    r = subprocess.run([sys.executable, "-m", "groundstation.cli", "campaign", str(logs), "--db",
                        str(tmp_path / "c.sqlite"), "--jobs", "1", "--maxiter", "4", "--restarts", "1",
                        "--report-dir", str(pages), "--no-progress", "--vehicle", "camp"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    html = (pages / "campaign.html").read_text()
    links = re.findall(r'href="([^"#]+)"', html)
    assert sorted(links) == ["f0.tlog.html", "f1.tlog.html"]
    for name in links:
        page = Page((pages / name).read_text())
        assert page.sections == SECTION_IDS and len(page.figures) >= 8
    assert "broken.tlog" in html                      # the failed log is listed with its error
    campaign = Page(html)
    assert campaign.external == ["f0.tlog.html", "f1.tlog.html"] and campaign.scripts == 0
    assert any(f["id"] == "fig-trends" for f in campaign.figures)
