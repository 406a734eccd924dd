"""Flights whose departure has no catalogue name: ``unexplained`` with evidence, or the sensor error.

Effects outside the catalogue are injected by the independent simulator; the diagnosis has no
name for them and must not force one onto them (no catalogue name with a shrink above 10 %).
"""

import json

import pytest

from groundstation.cli import main
from groundstation.gap.diagnose import VERDICTS

# two simulated flights diagnosed end to end (model given): minutes on a busy machine
pytestmark = pytest.mark.timeout(1200)


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    from hil_replay.sim import write_tlog

    d = tmp_path_factory.mktemp("unexpl")
    out = {}
    for name, effect in (("asymmetry", "input_asymmetry:input=lon,asymmetry=0.4"),
                         ("gyro_scale", "gyro_scale:output=q,scale_error=0.12")):
        path = d / f"{name}.tlog"
        truth = write_tlog(path, seed=61, flights=1, effects=[effect], flight_duration_s=120.0)
        mpath = d / f"{name}.model.json"
        mpath.write_text(json.dumps({"schema": "heli-hover-model/1", "parameters": truth["parameters"]}))
        rpath = d / f"{name}.json"
        assert main(["diagnose", str(path), "--model", str(mpath), "--out", str(rpath), "--quiet"]) == 0
        out[name] = json.loads(rpath.read_text())
    return out


def _no_confident_catalogue_name(rep):
    return all((e["shrink_pct"] or 0) <= 10 for e in rep["effects"])


def test_asymmetric_input_is_unexplained_with_evidence(reports):
    rep = reports["asymmetry"]
    assert rep["verdict"] == "unexplained", rep["effects"]
    assert _no_confident_catalogue_name(rep)
    ev = rep["unexplained"]
    looks = " ".join(ev["what_it_looks_like"])
    assert "lon" in looks and "asymmetric" in looks
    assert any(t["significant"] and t["input"] == "lon" for t in rep["structure_tests"])


def test_gyro_scale_is_a_sensor_error_not_a_catalogue_effect(reports):
    rep = reports["gyro_scale"]
    assert rep["verdict"] in VERDICTS
    assert rep["verdict"] == "sensor_error", rep["effects"]
    f = rep["data_compatibility"]["findings"]
    assert [(x["kind"], x["channel"]) for x in f] == [("gyro_scale", "q")]
    assert abs(f[0]["estimate"] - 0.12) < 0.03
    assert _no_confident_catalogue_name(rep)
    assert any("undone" in n for n in rep["notes"])
