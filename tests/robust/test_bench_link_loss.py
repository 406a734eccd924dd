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


def test_rates_table_counts_the_targets_over_seeds():
    from rich.console import Console

    from groundstation.bench.link_loss import _rates

    rows = [
        {"seed": 1, "flight": "none", "kind": "bursty", "loss_pct": 10.0, "key_within_10": 8, "key_lossfree": 8,
         "heldout_vs_lossfree_pct": 99.0, "verdict": "none", "same_verdict": True, "invented": []},
        {"seed": 2, "flight": "none", "kind": "bursty", "loss_pct": 10.0, "key_within_10": 6, "key_lossfree": 5,
         "heldout_vs_lossfree_pct": 95.0, "verdict": "unexplained", "same_verdict": False, "invented": []},
        {"seed": 3, "flight": "none", "kind": "bursty", "loss_pct": 10.0, "crash": "ValueError: x"},
    ]
    con = Console(width=200, record=True)
    con.print(_rates(rows, diagnose=True))
    line = next(ln for ln in con.export_text().splitlines() if "bursty" in ln)
    cells = [c.strip() for c in line.split("│") if c.strip()]
    # flight kind loss cases crash 8/8 as-loss-free >=97% median false-alarm same invented
    assert cells == ["none", "bursty", "10", "3", "1", "1", "2", "1", "97.0", "1", "1", "0"]


def test_a_lossy_case_is_judged_against_the_loss_free_flights_own_spread():
    """A key parameter off by more than 10 % passes when a window layout of the loss-free flight is off
    by as much; one beyond every layout does not."""
    from groundstation.bench.link_loss import KEY, _within_spread

    base = {"key_error_pct": dict.fromkeys(KEY, 2.0), "layout_error_pct": [{**dict.fromkeys(KEY, 3.0), "A_lat": 18.0}]}
    assert _within_spread({"key_error_pct": {**dict.fromkeys(KEY, 5.0), "A_lat": 17.0}}, base) is True
    assert _within_spread({"key_error_pct": {**dict.fromkeys(KEY, 5.0), "M_a": 12.0}}, base) is False
    assert _within_spread({"key_error_pct": dict.fromkeys(KEY, 9.9)}, {"key_error_pct": dict.fromkeys(KEY, 0.0)}) is True
    assert _within_spread({"refused": "x"}, base) is None
