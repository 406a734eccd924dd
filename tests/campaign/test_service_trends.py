"""The service's worker puts each identified flight into the campaign table and returns the trend
summary the service publishes (real worker function, real SQLite file, simulated flights)."""

import sqlite3

from groundstation.campaign.store import table_name
from groundstation.config import ServiceConfig
from groundstation.worker import IdentifyJob, run_job
from hil_replay.sim import write_tlog


def test_worker_records_flights_and_returns_trends(tmp_path):
    cfg = ServiceConfig()
    cfg = cfg.replace("identify", maxiter=4, search_restarts=1)
    cfg = cfg.replace("identification", diagnose=False, plots=False)
    cfg = cfg.replace("service", vehicle="trendheli")
    out = []
    for k in range(2):
        p = tmp_path / f"flight{k}.tlog"
        write_tlog(p, seed=60 + k, flights=1, flight_duration_s=30.0)
        res = run_job(IdentifyJob(flight=k + 1, tlogs=(str(p),), out_dir=str(tmp_path), config=cfg))
        assert res.error is None and res.trends_error is None, res.error or res.trends_error
        out.append(res.trends)
    assert out[0]["schema"] == "heli-trends/1" and out[0]["aircraft"] == "trendheli"
    assert out[1]["flights"] == ["flight0.tlog#1", "flight1.tlog#2"]
    assert "Z_w" in out[1]["series"]
    con = sqlite3.connect(tmp_path / "campaign.sqlite")
    n = con.execute(f'SELECT COUNT(*) FROM "{table_name("trendheli")}"').fetchone()[0]
    con.close()
    assert n == 2
    # off: no table, no trends
    (tmp_path / "off").mkdir()
    res = run_job(IdentifyJob(flight=3, tlogs=(str(tmp_path / "flight0.tlog"),), out_dir=str(tmp_path / "off"),
                              config=cfg.replace("service", campaign_db="")))
    assert res.error is None and res.model is not None
    assert res.trends is None and not (tmp_path / "off" / "campaign.sqlite").exists()
