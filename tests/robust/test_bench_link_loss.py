"""``groundstation bench link-loss`` runs end to end on a short flight (tiny search budget) and reports
the link, the key parameters and the held-out match against the loss-free flight."""

from __future__ import annotations

import json

import pytest

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
    assert lossy["std_predicted"] > 1.0 and lossy["std_vs_lossfree"] > 0
    assert "held-out match" in capsys.readouterr().out


def test_rates_table_counts_the_targets_over_seeds():
    from rich.console import Console

    from groundstation.bench.link_loss import KEY, _rates

    rows = [
        {"seed": 1, "flight": "none", "kind": "bursty", "loss_pct": 10.0, "key_within_10": 8, "key_lossfree": 8,
         "key_as_determined": 8, "key_z": dict.fromkeys(KEY, 1.0), "std_vs_lossfree": 1.2, "std_predicted": 1.25,
         "heldout_vs_lossfree_pct": 99.0, "verdict": "none", "same_verdict": True, "same_or_edge": True,
         "invented": []},
        {"seed": 2, "flight": "none", "kind": "bursty", "loss_pct": 10.0, "key_within_10": 6, "key_lossfree": 5,
         "key_as_determined": 7, "key_z": dict.fromkeys(KEY, -2.0), "std_vs_lossfree": 1.0, "std_predicted": 1.15,
         "heldout_vs_lossfree_pct": 95.0, "verdict": "unexplained", "same_verdict": False, "same_or_edge": True,
         "invented": []},
        {"seed": 3, "flight": "none", "kind": "bursty", "loss_pct": 10.0, "crash": "ValueError: x"},
    ]
    con = Console(width=200, record=True)
    con.print(_rates(rows, diagnose=True))
    line = next(ln for ln in con.export_text().splitlines() if "bursty" in ln)
    cells = [c.strip() for c in line.split("│") if c.strip()]
    # flight kind loss cases crash 8/8 8/8-as-determined as-loss-free rms-z SE-widening(predicted)
    # >=97% median false-alarm same same-or-borderline invented
    assert cells == ["none", "bursty", "10", "3", "1", "1", "1", "2", "1.58", "1.10 (1.20)", "1", "97.0", "1", "1",
                     "2", "0"]


def test_a_borderline_verdict_counts_as_the_same_only_across_its_own_edge():
    from groundstation.bench.link_loss import _same_or_edge

    base = {"verdict": "rate_limit", "verdict_edge": []}
    assert _same_or_edge({"verdict": "rate_limit"}, base)
    assert _same_or_edge({"verdict": "wind_gust", "verdict_edge": ["none", "rate_limit"]}, base)
    assert not _same_or_edge({"verdict": "none", "verdict_edge": []}, base)
    assert not _same_or_edge({"verdict": "none", "verdict_edge": ["deadband"]}, base)
    assert _same_or_edge({"verdict": "unexplained"}, {"verdict": "wind_gust", "verdict_edge": ["unexplained"]})


def test_key_parameters_are_judged_in_the_model_files_own_standard_errors():
    """A parameter off by more than 10 % but within 3 of its standard errors counts as determined; the
    standard errors' widening is set against what the samples counted predict."""
    from types import SimpleNamespace

    from groundstation.bench.link_loss import KEY, _determined, _widening

    truth = dict.fromkeys(KEY, 10.0)
    params = {**truth, "M_a": 12.0, "A_lat": 8.5}          # M_a +20 %, A_lat -15 %
    std = {**dict.fromkeys(KEY, 0.1), "M_a": 0.8, "A_lat": 0.3, "N_r": None}
    model = SimpleNamespace(params=params, parameter_std=std)
    err = {k: 100.0 * abs(params[k] - truth[k]) / truth[k] for k in KEY}
    d = _determined(model, truth, err)
    assert d["key_z"]["M_a"] == pytest.approx(2.5) and d["key_z"]["A_lat"] == pytest.approx(-5.0)
    assert d["key_z"]["N_r"] is None and d["key_std_pct"]["M_a"] == pytest.approx(8.0)
    assert d["key_as_determined"] == 7                        # A_lat is 5 standard errors off
    base = {"key_std_pct": dict.fromkeys(KEY, 2.0), "counted_samples": 40000}
    lossy = {"key_std_pct": dict.fromkeys(KEY, 2.4), "counted_samples": 25600}
    w = _widening(lossy, base)
    assert w["std_vs_lossfree"] == pytest.approx(1.2) and w["std_predicted"] == pytest.approx((40 / 25.6) ** 0.5)


def test_a_lossy_case_is_judged_against_the_loss_free_flights_own_spread():
    """A key parameter off by more than 10 % passes when a window layout of the loss-free flight is off
    by as much; one beyond every layout does not."""
    from groundstation.bench.link_loss import KEY, _within_spread

    base = {"key_error_pct": dict.fromkeys(KEY, 2.0), "layout_error_pct": [{**dict.fromkeys(KEY, 3.0), "A_lat": 18.0}]}
    assert _within_spread({"key_error_pct": {**dict.fromkeys(KEY, 5.0), "A_lat": 17.0}}, base) is True
    assert _within_spread({"key_error_pct": {**dict.fromkeys(KEY, 5.0), "M_a": 12.0}}, base) is False
    assert _within_spread({"key_error_pct": dict.fromkeys(KEY, 9.9)}, {"key_error_pct": dict.fromkeys(KEY, 0.0)}) is True
    assert _within_spread({"refused": "x"}, base) is None
