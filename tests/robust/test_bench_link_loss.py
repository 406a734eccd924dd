"""``groundstation bench link-loss`` runs end to end on a short flight (tiny search budget) and reports
the link, the key parameters and the held-out match against the loss-free flight."""

from __future__ import annotations

import json

from groundstation.cli import main


def test_bench_link_loss_smoke(tmp_path, capsys):
    cfg = tmp_path / "fast.toml"
    cfg.write_text("[identify]\nselect_folds = 0\nsearch_restarts = 1\nmaxiter = 4\n")
    out = tmp_path / "ll.json"
    rc = main(["bench", "link-loss", "--losses", "0,10", "--kinds", "bursty", "--seeds", "3", "--duration-s", "40",
               "--config", str(cfg), "--json", str(out)])
    assert rc == 0
    rows = json.loads(out.read_text())
    assert [r["loss_pct"] for r in rows] == [0, 10]
    lossy = rows[1]
    assert "crash" not in lossy and "refused" not in lossy, lossy
    assert lossy["link"]["in_air_holes"] > 0 and lossy["link"]["unmeasured_pct"] > 0
    assert 0 <= lossy["key_within_10"] <= 8 and lossy["heldout_vs_lossfree_pct"] > 0
    assert "held-out match" in capsys.readouterr().out
