"""Flights whose departure has no catalogue name: ``unexplained`` with evidence, or the sensor error.

Effects outside the catalogue are injected by the independent simulator; the diagnosis has no
name for them and must not force one onto them (no catalogue name with a shrink above 10 %).
Each flight is diagnosed once, through the library (the command's own path is covered by
test_cli.py), with the simulator's parameters as the given model.
"""

import pytest

from groundstation.gap.diagnose import VERDICTS, diagnose
from groundstation.sysid.model import HoverModel


def _report(tmp_path_factory, name: str, effect: str) -> dict:
    from firmware_interface.readers import load_log
    from groundstation.dsp.prepare import prepare
    from hil_replay.sim import write_tlog

    path = tmp_path_factory.mktemp("unexpl") / f"{name}.tlog"
    truth = write_tlog(path, seed=61, flights=1, effects=[effect], flight_duration_s=120.0)
    return diagnose(HoverModel(params=dict(truth["parameters"])), prepare([load_log(path)]), seed=61)


@pytest.fixture(scope="module")
def asymmetry(tmp_path_factory):
    return _report(tmp_path_factory, "asymmetry", "input_asymmetry:input=lon,asymmetry=0.4")


@pytest.fixture(scope="module")
def gyro_scale(tmp_path_factory):
    return _report(tmp_path_factory, "gyro_scale", "gyro_scale:output=q,scale_error=0.12")


def _no_confident_catalogue_name(rep):
    return all((e["shrink_pct"] or 0) <= 10 for e in rep["effects"])


def test_asymmetric_input_is_unexplained_with_evidence(asymmetry):
    rep = asymmetry
    assert rep["verdict"] == "unexplained", rep["effects"]
    assert _no_confident_catalogue_name(rep)
    ev = rep["unexplained"]
    looks = " ".join(ev["what_it_looks_like"])
    assert "lon" in looks and "asymmetric" in looks
    assert any(t["significant"] and t["input"] == "lon" for t in rep["structure_tests"])
    # the whiteness of what is left is part of the evidence, one entry per excited output
    assert ev["whiteness"] and all({"q", "lags", "log10_p", "white"} <= set(w) for w in ev["whiteness"])


def test_gyro_scale_is_a_sensor_error_not_a_catalogue_effect(gyro_scale):
    rep = gyro_scale
    assert rep["verdict"] in VERDICTS
    assert rep["verdict"] == "sensor_error", rep["effects"]
    f = rep["data_compatibility"]["findings"]
    assert [(x["kind"], x["channel"]) for x in f] == [("gyro_scale", "q")]
    assert abs(f[0]["estimate"] - 0.12) < 0.03
    assert _no_confident_catalogue_name(rep)
    assert any("undone" in n for n in rep["notes"])
