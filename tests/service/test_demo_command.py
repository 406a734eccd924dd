"""``groundstation demo`` as a user runs it (subprocess), shortened: two 30 s flights at 20x."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

from rerun.chunk import RrdReader

from benchkit.rerun_inspect import chunk_check, read_layout

ROOT = Path(__file__).resolve().parents[2]


def test_demo_records_identifies_publishes_and_prints_the_match_table(tmp_path):
    out = tmp_path / "demo_out"
    cfg = tmp_path / "fair.toml"  # the worker at a fair share: at the lowest priority the suite's load starves it
    cfg.write_text("[service]\nworker_nice = 0\n")
    proc = subprocess.run([sys.executable, "-m", "groundstation.cli", "demo", "--out", str(out),
                           "--flight-s", "30", "--speed", "20", "--config", str(cfg)],
                          capture_output=True, text=True, timeout=240, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout
    rec = out / "recordings"
    assert sorted(p.name for p in rec.glob("flight-*.tlog")) == ["flight-01.tlog", "flight-02.tlog"]
    for n in (1, 2):
        model = json.loads((rec / f"model-flight{n:02d}.json").read_text())
        assert model["schema"] == "heli-hover-model/1"
        assert (rec / f"model-flight{n:02d}.png").stat().st_size > 10_000
        assert f"heli/heli/flight/{n}/model: model received" in text     # the in-process subscriber
    assert "late subscriber: heli/heli/model/latest answered" in text
    table = text[text.index("match degree (%)"):].splitlines()
    assert table[0].split()[3:] == ["u", "v", "w", "p", "q", "r", "theta", "phi", "held-out"]
    assert table[1].startswith("flight 1") and table[2].startswith("flight 2")
    assert len(table[1].split()) == 11
    listed = text[text.index("recordings: "):text.index("match degree (%)")]
    for path in rec.iterdir():          # every file the demo wrote is named in its closing summary
        assert str(path) in listed, path.name
    assert "Rerun: " in text and f"{out / 'demo.rrd'}" in text.splitlines()[-2]
    ents = {c.entity_path for c in RrdReader(out / "demo.rrd").stream().to_chunks() if not c.is_static}
    assert {"/heli/inputs/lat", "/heli/outputs/q/smoothed", "/heli/outputs/q/model", "/heli/outputs/q/residual"} <= ents
    _check_demo_recording(out / "demo.rrd", rec)


def _check_demo_recording(rrd: Path, rec: Path) -> None:
    """The recording as the viewer opens it: the latest flight's tab, units, the flight's span, gap pictures."""
    lay = read_layout(rrd)
    tabs = [lay.name(c) for c in lay.children(lay.root)]
    assert tabs[0].startswith("flight 2") and tabs[1].startswith("flight 1")
    assert tabs[2].startswith("session") and tabs[3:] == ["excitation"]     # the live excitation monitor last
    opening = lay.opening_tab()
    assert lay.name(opening).startswith("flight 2")
    views = [v for c in lay.children(lay.root) for v in lay.views_under(c)]
    for v in views:
        if v.kind in ("TimeSeries", "BarChart"):
            assert re.search(r"\[[^\]]+\]", v.name), f"no unit in view title {v.name!r}"
    spans = {}
    for v in lay.views_under(opening):
        if v.kind == "TimeSeries":
            assert v.fc_range_s is not None, v.name
            spans[v.fc_range_s] = v.name
    q = next(v for v in lay.views_under(opening) if v.origin == "/heli/outputs/q")
    assert "[rad/s]" in q.name and "fit " in q.name and "held-out" in q.name   # flight 1's model on flight 2
    assert len(spans) == 1                      # every plot of the tab shows the same window: the whole flight
    (t0, t1), = spans
    assert 25.0 < t1 - t0 < 40.0                # the 30 s flight (padded), not a 60 s window at t = 0
    for n in (1, 2):
        gap = json.loads((rec / f"gap-flight{n:02d}.json").read_text()) if (rec / f"gap-flight{n:02d}.json").exists() else None
        if gap is None:
            continue
        for c in gap["gap"]["channels"]:
            assert lay.rows.get(f"/heli/gap/residual/{c}/residual", 0) > 0 and f"/heli/flights/{n}/spectrum/{c}/psd" in lay.entities
        assert f"/heli/flights/{n}/verdict" in lay.entities
        assert lay.rows.get("/heli/gap/flagged", 0) > 0 or not gap["gap"]["windows_s"]
    check = chunk_check(rrd)
    assert check.factor <= 10.0, check


def test_summary_names_every_file_of_a_flight_and_its_held_out_match():
    from groundstation.commands.run import print_report
    from groundstation.service import RunReport
    from groundstation.worker import JobResult

    model = {"fit": {"heldout": {"mean_match": 70.57}}}
    res = JobResult(flight=1, model=model, model_path="rec/model-flight01.json", gap={"verdict": "none"},
                    gap_path="rec/gap-flight01.json", freq_path="rec/freq-flight01.json",
                    report_path="rec/report-flight01.html", png=("rec/model-flight01.png",),
                    match_degree={"u": 97.0, "w": 87.04})
    failed = JobResult(flight=2, error="flight 2: nothing to identify")
    lines: list[str] = []
    print_report(RunReport(record_dir="rec", results=[res, failed], campaign_db="rec/campaign.sqlite"), lines.append)
    text = "\n".join(lines)
    for name in ("model-flight01.json", "gap-flight01.json", "freq-flight01.json", "report-flight01.html",
                 "model-flight01.png", "campaign.sqlite"):
        assert f"rec/{name}" in text
    assert "flight 2: identification failed" in text
    header, row = lines[lines.index(next(x for x in lines if x.startswith("match degree")))::][:2]
    assert header.split()[-1] == "held-out" and row.split() == ["flight", "1", "97.0", "87.0", "70.6"]
