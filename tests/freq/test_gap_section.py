"""The gap report's frequency section: where in frequency the model departs beyond the random error."""

from __future__ import annotations

import json

from groundstation.cli import main
from groundstation.freq.spectra import estimate_responses
from groundstation.freq.verify import verify
from groundstation.gap.report import frequency_rows, frequency_section
from tests.freq.conftest import flight


def test_section_names_the_delayed_input_and_its_band(truth_theta):
    rs = estimate_responses(flight(150.0, seed=5, delay_samples={1: 6}))  # 120 ms on lon
    sec = frequency_section(verify(truth_theta, rs))
    assert sec["departures"], "a 120 ms delay must leave the bound somewhere"
    worst = sec["departures"][0]
    assert worst["input"] == "lon" and worst["max_ratio"] > 2.45 and worst["phase_deg"] > 10
    assert all(d["input"] == "lon" for d in sec["departures"][:5])
    assert abs(sec["input_delays"]["lon"]["delay_s"] - 0.12) < 0.015
    assert json.loads(json.dumps(sec)) == sec  # plain JSON types
    assert frequency_rows(sec)[0][0] == "lon->" + worst["output"]
    clean = frequency_section(verify(truth_theta, estimate_responses(flight(150.0, seed=5))))
    assert not [d for d in clean["departures"] if d["max_ratio"] > 6]


def test_diagnose_command_writes_the_frequency_section(tmp_path, capsys):
    from hil_replay.sim import write_tlog

    path = tmp_path / "f.tlog"
    truth = write_tlog(path, seed=4, flights=1, effects=["input_delay:input=lon,delay_s=0.12"], flight_duration_s=90.0)
    mpath = tmp_path / "m.json"
    mpath.write_text(json.dumps({"schema": "heli-hover-model/1", "parameters": truth["parameters"]}))
    out = tmp_path / "gap.json"
    assert main(["diagnose", str(path), "--model", str(mpath), "--out", str(out)]) == 0
    fr = json.loads(out.read_text())["frequency"]
    assert fr["departures"] and fr["departures"][0]["input"] == "lon"
    assert {p["input"] for p in fr["pairs"] if not p["pass"]} <= {"lon"}
    assert "leaves the flight's 95 % random-error" in capsys.readouterr().out
