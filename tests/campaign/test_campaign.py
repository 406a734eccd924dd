"""``groundstation campaign`` end to end on short simulated flights: table, skip by content hash,
Parquet, trends files, a bad log as an error row, and the same rows from a Dask cluster on loopback."""

import json
import shutil
import sqlite3

import numpy as np
import pytest

from groundstation.campaign.store import CampaignStore, table_name
from groundstation.cli import main
from hil_replay.sim import write_tlog

FAST = ["--maxiter", "4", "--restarts", "1", "--no-diagnose", "--no-progress", "--quiet", "--jobs", "1"]


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("campaign_logs")
    for k in range(2):
        write_tlog(d / f"flight{k}.tlog", seed=40 + k, flights=1, flight_duration_s=30.0)
    return d


def _rows(db, aircraft="aircraft"):
    con = sqlite3.connect(db)
    con.row_factory = sqlite3.Row
    rows = [dict(r) for r in con.execute(f'SELECT * FROM "{table_name(aircraft)}" ORDER BY log_name')]
    con.close()
    return rows


def test_campaign_table_skip_parquet_and_trends(logs, tmp_path, capsys):
    db = tmp_path / "c.sqlite"
    assert main(["campaign", str(logs), "--db", str(db), "--parquet", str(tmp_path / "pq"), *FAST]) == 0
    rows = _rows(db)
    assert [r["log_name"] for r in rows] == ["flight0.tlog", "flight1.tlog"]
    for r in rows:
        assert r["error"] is None
        assert r["date_utc"].startswith("20") and r["date_source"] == "tlog timestamp"
        assert np.isfinite(r["p_Z_w"]) and r["se_Z_w"] > 0
        assert r["in_air_s"] > 20
    # the second flight's model is scored on the first (cross-flight fit); the first has no reference
    assert rows[0]["cross_match_pct"] is None and rows[1]["cross_log"] == "flight0.tlog"
    assert np.isfinite(rows[1]["cross_match_pct"])
    # scored by the caller on the first log as its own job prepared it: the match of that log read again
    from groundstation.campaign.job import cross_fit
    from groundstation.config import ServiceConfig
    from groundstation.pipeline import prepare_logs
    from groundstation.sysid.model import HoverModel

    ref = prepare_logs([str(logs / "flight0.tlog")], ServiceConfig())
    again = cross_fit(HoverModel.from_json(json.loads(rows[1]["model"])), ref, "flight0.tlog")
    assert again["cross_match_pct"] == pytest.approx(rows[1]["cross_match_pct"], rel=1e-9, abs=0)
    import pyarrow.parquet as pq

    t = pq.read_table(tmp_path / "pq" / "aircraft.parquet")
    assert t.num_rows == 2 and t.column("p_Z_w").to_pylist() == [r["p_Z_w"] for r in rows]
    trends = json.loads((tmp_path / "trends.json").read_text())
    assert trends["schema"] == "heli-trends/1" and len(trends["flights"]) == 2
    assert (tmp_path / "trends.png").stat().st_size > 0 and (tmp_path / "trends.rrd").stat().st_size > 0

    # nothing changed: a re-run skips both logs by content hash and leaves the rows as they were
    capsys.readouterr()
    assert main(["campaign", str(logs), "--db", str(db), "--no-progress", "--jobs", "1", "--maxiter", "4",
                 "--restarts", "1", "--no-diagnose"]) == 0
    assert "2 already done, 0 to analyse" in capsys.readouterr().err
    assert _rows(db) == rows


def test_bad_log_is_an_error_row_and_the_rest_is_kept(logs, tmp_path):
    d = tmp_path / "logs"
    shutil.copytree(logs, d)
    (d / "broken.tlog").write_bytes(b"\x00" * 300)
    db = tmp_path / "c.sqlite"
    assert main(["campaign", str(d), "--db", str(db), *FAST]) == 0
    rows = _rows(db)
    bad = [r for r in rows if r["log_name"] == "broken.tlog"]
    assert len(bad) == 1 and "broken.tlog" in bad[0]["error"]
    assert sum(r["error"] is None for r in rows) == 2
    store = CampaignStore(db)
    assert not store.done("aircraft", bad[0]["sha256"], bad[0]["settings_key"])  # retried next time
    store.close()


def test_dask_local_cluster_gives_the_same_rows(logs, tmp_path):
    from groundstation.campaign import runner
    from groundstation.campaign.job import FlightJob, Settings, file_sha256, find_logs
    from groundstation.config import ServiceConfig

    s = Settings(config=ServiceConfig().replace("identify", maxiter=4, search_restarts=1), diagnose=False)
    jobs = [FlightJob(str(p), file_sha256(p), "aircraft", s, None) for p in find_logs([logs])]
    serial = runner.run(jobs, workers=1)
    dask = runner.run(jobs, workers=1, scheduler="local", local_processes=False)
    for a, b in zip(serial, dask, strict=True):
        assert [r["p_X_u"] for r in a] == [r["p_X_u"] for r in b]
        assert [r["model"] for r in a] == [r["model"] for r in b]


def test_bad_scheduler_and_jobs_are_one_line(logs, tmp_path, capsys):
    assert main(["campaign", str(logs), "--db", str(tmp_path / "c.sqlite"), "--scheduler", "udp://x", *FAST]) == 2
    assert "--scheduler 'udp://x'" in capsys.readouterr().err
    assert main(["campaign", str(logs), "--db", str(tmp_path / "c.sqlite"), *FAST[:-2], "--jobs", "0"]) == 2
    assert "--jobs: 0" in capsys.readouterr().err
    assert main(["campaign", str(tmp_path / "nothing"), "--db", str(tmp_path / "c.sqlite"), *FAST]) == 2
    assert "nothing: no such file or directory" in capsys.readouterr().err


def test_pool_workers_are_forked_here_and_pool_and_local_cluster_give_the_serial_rows(logs):
    """The pool's workers are forked from this process once it has imported the analysis (a local Dask
    cluster's, separate processes on loopback, from the fork server that imported it); each log is
    analysed in a worker and gives the serial rows."""
    import os

    from groundstation.campaign import runner
    from groundstation.campaign.job import FlightJob, Settings, file_sha256, find_logs
    from groundstation.config import ServiceConfig

    s = Settings(config=ServiceConfig().replace("identify", maxiter=4, search_restarts=1), diagnose=False)
    jobs = [FlightJob(str(p), file_sha256(p), "aircraft", s, None) for p in find_logs([logs])]
    serial = runner.run(jobs, workers=1)
    with runner.open_executor(2) as ex:
        ex.warm()
        pids = set(ex.pids)  # type: ignore[attr-defined]
        parent = ex.ex.submit(os.getppid).result()  # type: ignore[attr-defined]
        pool = runner.run(jobs, executor=ex)
    assert len(pids) == 2 and os.getpid() not in pids
    # forked here when no other thread ran at the fork (an earlier test's Dask threads may): else the fork server
    assert (parent == os.getpid()) == ex.forked_here  # type: ignore[attr-defined]
    dask = runner.run(jobs, workers=2, scheduler="local")
    for a, b, c in zip(serial, pool, dask, strict=True):
        assert [r["model"] for r in a] == [r["model"] for r in b] == [r["model"] for r in c]
        assert all(r["cpu_s"] > 0 for r in b + c)


_PROBE = """
import sys
from groundstation.campaign import runner
from groundstation.cli import main

opened = runner._Pool.__init__

def init(self, *args):
    opened(self, *args)
    print("forked here", self.forked_here, self.workers, flush=True)

runner._Pool.__init__ = init
sys.exit(main(sys.argv[1:]))
"""


def test_the_campaign_command_forks_its_workers_from_itself_before_its_progress_bar_starts(tmp_path):
    """``groundstation campaign`` opens its pool before the progress bar's thread runs, so the workers are
    forked from the command itself (no fork server importing the analysis a second time). Two logs
    that are not logs keep it short: each is analysed, in a worker, into its error row."""
    import subprocess
    import sys

    for k in range(2):
        (tmp_path / f"junk{k}.tlog").write_bytes(f"not a log {k}".encode())
    db = tmp_path / "c.sqlite"
    out = subprocess.run([sys.executable, "-c", _PROBE, "campaign", str(tmp_path), "--db", str(db), "--progress",
                          "--quiet", "--jobs", "2"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "forked here True 2" in out.stdout
    store = CampaignStore(db)
    assert sorted(e["log_name"] for e in store.errors("aircraft")) == ["junk0.tlog", "junk1.tlog"]
    store.close()
