"""The diagnosis on the real TREX 550 log (no label): what the data support, said per channel.

The truth we can check without a label: the raw body rates of this log carry a narrow line
(rotor 1/rev, about 29 Hz at the log's native ~123 Hz), which on the 50 Hz analysis grid folds
to 50 - f; the lateral stick was not logged (held at trim); height hardly varies (hover), so
ground effect cannot be tested. The diagnosis must find the line where the folding puts it, call
lat unexcited and ground effect untestable, and write a schema-valid report.
"""

import json
import warnings

import numpy as np
import pytest
from scipy.signal import welch

from firmware_interface.readers import load_log
from groundstation.cli import main
from groundstation.gap.diagnose import VERDICTS
from tests.realdata import real_log


def _native_line_hz(path) -> float:
    att = load_log(path).series["ATTITUDE"]
    t = att.t_fc_s
    sel = (t > 60.0) & (t < 200.0)
    fs = (sel.sum() - 1) / (t[sel][-1] - t[sel][0])  # mean rate: the ms time stamps jitter
    p = np.asarray(att["p_rad_s"])[sel]
    f, P = welch(p - p.mean(), fs=fs, nperseg=2048)
    band = f > 5.0
    return float(f[band][np.argmax(P[band])])


@pytest.fixture(scope="module")
def real_report(tmp_path_factory):
    """The diagnosis of the bundled real log (once for the module) and the warnings it raised."""
    path = real_log("trex550/flight1.tlog")
    out = tmp_path_factory.mktemp("real") / "gap.json"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["diagnose", str(path), "--out", str(out), "--quiet"]) == 0
    return json.loads(out.read_text()), caught


def test_real_trex550_diagnosis(real_report):
    path = real_log("trex550/flight1.tlog")
    rep, caught = real_report
    # a runaway simulation (an unstable trial step of a search) is handled, not printed
    assert not [w for w in caught if "overflow" in str(w.message) or "invalid value" in str(w.message)]
    assert rep["schema"] == "heli-gap-report/2"
    assert rep["verdict"] in VERDICTS
    # what the log can test and what it cannot, said explicitly
    assert "ground_effect" not in rep["tested"] and "input_delay" in rep["tested"]
    dc = rep["data_compatibility"]
    assert {(e["sensor"], e["parameter"]) for e in dc["estimates"]} >= {("p", "scale"), ("q", "scale")}
    assert all(e["se"] > 0 for e in dc["estimates"])
    assert "r" in dc["untestable"]
    # a found sensor error is a calibration-sized one, never a blow-up of an ill-posed regression
    assert all(abs(f["estimate"]) < 0.5 for f in dc["findings"])
    # the departure is far above the noise on this flight: the report says where, whatever the verdict
    assert rep["gap"]["significant"]
    assert rep["departure"]["channels_above_noise"]
    if rep["verdict"] == "unexplained":
        ux = rep["unexplained"]
        assert ux["channels_above_noise"] or ux["what_it_looks_like"]
    assert rep["excitation"]["inputs"]["lat"] == "too little excitation"
    assert "ground_effect" in rep["untestable"]
    native = _native_line_hz(path)
    assert 25.0 < native < 35.0
    lines = rep["fingerprints"]["spectral_lines"]
    assert lines, "no spectral line found"
    assert abs(lines[0]["frequency_hz"] - (50.0 - native)) < 0.3
    assert "p" in lines[0]["channels"]
    vib = [e for e in rep["effects"] + rep["partial_findings"] if e["effect"] == "rotor_vibration"]
    assert vib and vib[0]["per_channel_shrink"]["p"] > 0
    untouched = [c for c in vib[0]["per_channel_shrink"] if c not in lines[0]["channels"]]
    # channels without the line are not "explained" by it (the velocity check leaves u, v, w out of
    # this log, so the line may be in every channel that remains)
    assert all(vib[0]["per_channel_shrink"][c] == 0 for c in untouched)
    assert set(vib[0]["per_channel_shrink"]) <= {"p", "q", "r", "theta", "phi"}


def verdict_agrees_with_shares(rep: dict, min_pct: float = 50.0) -> bool:
    """The naming rule of docs/diagnosis.md section 3b, read back from a report: effects are named
    unless their share of the gap above noise is clearly (whole interval) below ``min_pct``; partial
    findings only with the verdict ``unexplained``; a headline that states the share."""
    sh = rep["shares"]
    if sh["explained_pct"] is None:
        return "noise floor" in sh["headline"]
    lo, hi = sh["interval_pct"]
    if rep["effects"]:
        return hi >= min_pct and rep["verdict"] == rep["effects"][0]["effect"] and "is explained by" in sh["headline"]
    if rep["partial_findings"]:
        changes = rep["through_flight"]["changes"]
        below = (sh["partial_explained_pct"] is not None and hi < min_pct) or bool(changes)
        return below and rep["verdict"] == "unexplained" and sh["headline"].startswith("unexplained")
    return rep["verdict"] in ("none", "unexplained", "sensor_error")


def test_real_trex550_verdict_agrees_with_the_shares(real_report):
    """On the real flight the departure (theta 76x, phi 46x its noise) is far larger than anything the
    catalogue explains: the headline says how much is explained and the verdict follows the shares."""
    rep, _ = real_report
    sh = rep["shares"]
    assert verdict_agrees_with_shares(rep)
    assert sh["explained_pct"] is not None and sh["headline"]
    # what is left is said: the channels holding most of the gap, with their ratio to the noise
    assert {c["channel"] for c in sh["rest"]["channels"]} & {"theta", "phi"}
    assert rep["through_flight"]["halves"] and len(rep["through_flight"]["halves"]) == 2
    # every named effect or partial finding carries its share and whether it holds through the flight
    for e in rep["effects"] + rep["partial_findings"]:
        assert "share_pct" in e and e["consistency"]["status"] in ("holds", "changes", "not_checked")
