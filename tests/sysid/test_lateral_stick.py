"""``bench lateral-stick`` on the real TREX 550 segments that carry the lateral stick: identified on one
segment and predicting the other, the model that sees the lateral stick predicts roll far better than
the same identification with the stick held at trim (what a log without it gives)."""

import json
from pathlib import Path

from groundstation.bench.lateral_stick import load_segments
from groundstation.cli import main
from tests.realdata import real_log

AIRCRAFT = Path(__file__).resolve().parents[2] / "groundstation" / "configs" / "aircraft" / "trex550.toml"


def test_segments_file_holds_two_windows_with_a_moving_lateral_stick():
    segs = load_segments(real_log("trex550/flight1_segments_filtered.csv"))
    assert list(segs) == ["Hovertest", "Pitchtest"]
    assert all(s["lat_cyclic_norm_f"].std() > 0.01 for s in segs.values())


def test_lateral_stick_lifts_held_out_roll_prediction(tmp_path):
    out = tmp_path / "lat.json"
    rc = main(["bench", "lateral-stick", str(real_log("trex550/flight1_segments_filtered.csv")), "--aircraft",
               str(AIRCRAFT), "--train", "Hovertest", "--json", str(out), "--set", "maxiter=4",
               "--set", "search_restarts=1", "--set", "refine_max_nfev=8", "--set", 'select_candidates=""'])
    assert rc == 0
    (pair,) = json.loads(out.read_text())["pairs"]
    assert (pair["train"], pair["predict"]) == ("Hovertest", "Pitchtest")
    off, on = pair["without_lateral"], pair["with_lateral"]
    assert not any(off["lateral_terms"].values()) and on["lateral_terms"]["L_lat"] != 0.0
    for c in ("p", "phi"):
        assert on["match"][c] > off["match"][c] + 20.0, (c, off["match"][c], on["match"][c])
    assert on["mean"] > off["mean"] + 5.0
