"""validate --freq on a simulated .tlog (the hil_replay simulator, known truth): J table, JSON, Bode PNGs,
a Rerun recording read back; bad input."""

from __future__ import annotations

import json

import pytest

from groundstation.cli import main


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    from groundstation.sysid.model import HoverModel
    from hil_replay.sim import write_tlog

    d = tmp_path_factory.mktemp("freqsim")
    tlog = d / "flight.tlog"
    truth = write_tlog(tlog, seed=3, flights=1, effects=(), aircraft=None, flight_duration_s=150.0)
    model = d / "truth.json"
    model.write_text(json.dumps(HoverModel(params=dict(truth["parameters"])).to_json()))
    return tlog, model


def test_validate_freq_json_png_rerun(sim, tmp_path, capsys):
    tlog, model = sim
    rrd = tmp_path / "bode.rrd"
    rc = main(["validate", str(model), str(tlog), "--freq", "--json", "--bode", str(tmp_path / "b.png"),
               "--rerun", "save", str(rrd)])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["J_avg"] is not None and doc["J_avg"] <= 50 and doc["J_avg_good"] is True
    pairs = {(p["input"], p["output"]): p for p in doc["pairs"]}
    assert {("lat", "q"), ("lon", "p"), ("col", "w"), ("ped", "r")} <= set(pairs)
    for p in doc["pairs"]:
        assert set(p) >= {"input", "output", "J", "coherent_points", "delay_s"}
        assert p["coherent_points"] >= 3 and p["J"] <= 200 and abs(p["delay_s"]) < 0.02
    assert all(r["reason"] for r in doc["no_response"])
    for inp in ("lat", "lon", "col", "ped"):
        assert (tmp_path / f"b_{inp}.png").stat().st_size > 20_000
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    static = set()
    for c in RrdReader(rrd).stream().to_chunks():
        if c.is_static:
            static.add(c.entity_path)
        else:
            assert "frequency_mhz" in c.timeline_names
            rows[c.entity_path] = rows.get(c.entity_path, 0) + c.num_rows
    assert "/freq/J" in static
    n = pairs[("lon", "p")]["coherent_points"]
    assert rows["/freq/lon/p/magnitude_db/data"] == n == rows["/freq/lon/p/phase_deg/model"]


def test_validate_freq_table_and_bad_flags(sim, tmp_path, capsys):
    tlog, model = sim
    assert main(["validate", str(model), str(tlog), "--freq"]) == 0
    out = capsys.readouterr().out
    assert "Tischler's J" in out and "no response" in out and "pass" in out
    assert main(["validate", str(model), str(tlog), "--bode", str(tmp_path / "x.png")]) == 2
    assert "--freq" in capsys.readouterr().err
    assert main(["validate", str(model), str(tlog), "--freq", "--rerun", "spawn"]) == 2
    assert "save FILE.rrd" in capsys.readouterr().err
