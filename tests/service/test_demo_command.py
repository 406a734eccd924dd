"""``groundstation demo`` as a user runs it (subprocess), shortened: two 30 s flights at 20x."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from rerun.chunk import RrdReader

ROOT = Path(__file__).resolve().parents[2]


def test_demo_records_identifies_publishes_and_prints_the_match_table(tmp_path):
    out = tmp_path / "demo_out"
    proc = subprocess.run([sys.executable, "-m", "groundstation.cli", "demo", "--out", str(out),
                           "--flight-s", "30", "--speed", "20"],
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
    assert table[0].split()[3:] == ["u", "v", "w", "p", "q", "r", "theta", "phi"]
    assert table[1].startswith("flight 1") and table[2].startswith("flight 2")
    assert len(table[1].split()) == 10
    ents = {c.entity_path for c in RrdReader(out / "demo.rrd").stream().to_chunks() if not c.is_static}
    assert {"/heli/inputs/lat", "/heli/outputs/q/raw", "/heli/outputs/q/smoothed", "/heli/outputs/q/model"} <= ents
