"""The real TREX 550 flight: responses and coherence for every excited pair at the native ~123 Hz
(the .tlog through the ordinary pipeline, and the raw .csv), J per pair of an identified model, and
one reason for every pair without a response."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_interface.readers import load_log
from groundstation.dsp.prepare import PrepConfig, prepared_from_arrays
from groundstation.freq.identify import FreqIdentifyConfig, identify_frequency
from groundstation.freq.metrics import Z95_COMPLEX
from groundstation.freq.spectra import estimate_responses
from groundstation.freq.verify import verify
from groundstation.pipeline import prepare_native
from tests.realdata import real_log


@pytest.fixture(scope="module")
def tlog_responses():
    prepared = prepare_native([load_log(real_log("trex550/flight1.tlog"))], PrepConfig())
    return prepared, estimate_responses(prepared)


def _csv_prepared():
    body = [ln for ln in real_log("trex550/flight1.csv").read_text().splitlines() if not ln.startswith("#")]
    data = np.loadtxt(body[1:], delimiter=",")
    col = {n: data[:, k] for k, n in enumerate(body[0].split(","))}
    keep = (col["airborne_est"] == 1) & (col["resample_edge_artifact"] == 0)
    dt = float(np.median(np.diff(col["time_s"])))
    u = np.zeros((int(keep.sum()), 4))
    for k, n in ((1, "lon_cyclic_norm"), (2, "collective_norm"), (3, "pedal_norm")):
        u[:, k] = col[n][keep] - np.median(col[n][keep])
    y = np.full((u.shape[0], 8), np.nan)
    for k, n in ((3, "p_radps"), (4, "q_radps"), (5, "r_radps"), (6, "theta_rad"), (7, "phi_rad")):
        y[:, k] = col[n][keep] - (np.median(col[n][keep]) if k >= 6 else 0.0)
    return prepared_from_arrays(u, y, dt, source="flight1.csv")


def test_tlog_native_rate_pairs_and_reasons(tlog_responses):
    prepared, rs = tlog_responses
    assert 115 < 1 / prepared.dt_s < 130  # the log's ~123 Hz, not the 50 Hz grid
    got = {(p.input, p.output) for p in rs.with_response}
    assert {("lon", "q"), ("lon", "theta")} <= got  # the pilot's pitch corrections
    assert not any(i == "lat" for i, _ in got)
    assert all("lat never moves" in p.reason for p in rs.pairs if p.input == "lat")
    for p in rs.without_response:
        assert p.reason and len(p.reason.splitlines()) == 1 and not p.coherent.any()
    q = rs.pair("lon", "q")
    assert q.coherent_points >= 15 and np.all(q.coherence[q.coherent] >= 0.6)


def test_csv_at_123_hz_agrees_with_the_tlog(tlog_responses):
    _, rs_t = tlog_responses
    rs_c = estimate_responses(_csv_prepared())
    a, b = rs_t.pair("lon", "q"), rs_c.pair("lon", "q")
    assert b.has_response and b.coherent_points >= 15
    both = a.coherent & b.coherent
    assert both.sum() >= 10
    err = np.hypot(a.random_error, b.random_error) * np.abs(b.response)
    assert np.mean(np.abs(a.response - b.response)[both] <= Z95_COMPLEX * err[both]) >= 0.9


def test_identified_model_J_per_pair(tlog_responses):
    prepared, rs = tlog_responses
    m = identify_frequency(rs, prepared, seed=0, config=FreqIdentifyConfig(maxiter=20, refine_starts=2))
    v = verify(m.theta, rs)
    doc = v.to_json()
    scored = {(p["input"], p["output"]) for p in doc["pairs"]}
    assert ("lon", "q") in scored and all(np.isfinite(p["J"]) and p["coherent_points"] >= 3 for p in doc["pairs"])
    assert len(doc["pairs"]) + len(doc["no_response"]) + len(doc["unmodelled"]) == 32
    assert {"input": "lat", "output": "p", "reason": "input lat never moves (std below 0.0001)"} in doc["no_response"]
    assert "input lat never moves: X_lat, M_lat, L_lat, A_lat fixed at 0" in m.fit.fixed_reasons
