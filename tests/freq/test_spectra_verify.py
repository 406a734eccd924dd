"""Frequency responses, Tischler's J, delay and bandwidth against known truth (fixed seeds)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import coherence as sp_coherence
from scipy.signal import csd as sp_csd
from scipy.signal import lfilter

from groundstation.dsp.prepare import prepared_from_arrays
from groundstation.freq.cost import coherence_weight, error_residuals, tischler_cost
from groundstation.freq.metrics import Z95_COMPLEX, attitude_bandwidth, phase_slope_delay
from groundstation.freq.model_response import model_response
from groundstation.freq.spectra import FreqConfig, _miso, _window_spectra, estimate_responses
from groundstation.freq.verify import verify
from groundstation.sysid.model import INPUTS, OUTPUTS
from tests.freq.conftest import flight


def test_window_spectra_and_coherence_match_scipy():
    rng = np.random.default_rng(0)
    n, dt, L = 6000, 0.02, 500
    x = rng.standard_normal(n)
    y = lfilter([0.3, 0.2], [1.0, -0.7], x) + 0.5 * rng.standard_normal(n)
    u = np.zeros((n, 4))
    u[:, 1] = x
    out = np.full((n, 8), np.nan)
    out[:, 3] = y
    f_bins = np.arange(3, 100) / (L * dt)
    cfg = FreqConfig(overlap=0.5, detrend="constant")
    X, valid, counts = _window_spectra([(u, out)], L, L // 2, f_bins, dt, cfg)
    assert counts == [(n - L) // (L // 2) + 1] and valid[:, 1].all() and valid[:, 7].all()
    Gxy = np.mean(X[:, :, 1].conj() * X[:, :, 7], axis=0)
    _, Pxy = sp_csd(x, y, fs=1 / dt, nperseg=L, detrend="constant")
    np.testing.assert_allclose(Gxy, Pxy[3:100], rtol=1e-9, atol=1e-12)
    H, g2 = _miso(X[:, :, [1]], X[:, :, 7])
    _, Cxy = sp_coherence(x, y, fs=1 / dt, nperseg=L)
    np.testing.assert_allclose(g2[:, 0], Cxy[3:100], rtol=1e-9)


def test_conditioning_separates_correlated_inputs():
    """Two inputs that share a component; the output depends on one only. Ordinary coherence of the
    other is high, its conditioned (partial) coherence is not, and H of the true one is recovered."""
    rng = np.random.default_rng(1)
    n, dt = 9000, 0.02
    a = rng.standard_normal(n)
    b = 0.8 * a + 0.6 * rng.standard_normal(n)
    u = np.zeros((n, 4))
    u[:, 0], u[:, 1] = a, b
    out = np.full((n, 8), np.nan)
    out[:, 4] = 2.0 * a + 0.3 * rng.standard_normal(n)
    rs = estimate_responses(prepared_from_arrays(u, out, dt),
                            FreqConfig(window_s=(5.0, 10.0), min_cycles=2))
    true_pair, other = rs.pair("lat", "q"), rs.pair("lon", "q")
    m = true_pair.coherent
    assert true_pair.has_response and m.sum() > 40
    z = np.abs(true_pair.response - 2.0) / (true_pair.random_error * 2.0)
    assert np.mean(z[m] <= Z95_COMPLEX) >= 0.95 and np.allclose(true_pair.response[m], 2.0, rtol=0.1)
    assert not other.has_response and "coherence below 0.6" in other.reason
    assert np.nanmax(sp_coherence(b, out[:, 4], fs=1 / dt, nperseg=250)[1]) > 0.5


def test_truth_within_random_error_and_low_J(responses150, truth_theta):
    rs = responses150
    G = model_response(truth_theta, rs.f_hz, dt_s=rs.dt_s)
    inside = total = 0
    for p in rs.with_response:
        g = G[:, OUTPUTS.index(p.output), INPUTS.index(p.input)]
        assert np.any(g != 0), f"coherent response {p.input}->{p.output} where the truth has no path"
        z = np.abs(g - p.response) / (p.random_error * np.abs(p.response))
        inside += int((z[p.coherent] <= Z95_COMPLEX).sum())
        total += p.coherent_points
    assert total > 400
    assert inside / total >= 0.95
    v = verify(truth_theta, rs)
    assert v.J_avg is not None and v.J_avg <= 50 and v.good
    assert {(p.input, p.output) for p in v.pairs} >= {("lat", "q"), ("lon", "p"), ("col", "w"), ("ped", "r")}
    assert not v.unmodelled
    doc = v.to_json()
    assert doc["J_avg"] == pytest.approx(v.J_avg)
    assert all({"input", "output", "J", "coherent_points", "delay_s"} <= set(p) for p in doc["pairs"])


def test_wrong_model_fails_J(responses150, truth_theta):
    from groundstation.sysid.model import PARAM_INDEX

    th = truth_theta.copy()
    th[PARAM_INDEX["L_b"]] *= 0.5  # roll flapping stiffness: lon -> p, phi
    th[PARAM_INDEX["M_a"]] *= 0.5  # pitch flapping stiffness: lat -> q, theta
    v = verify(th, responses150)
    bad = {(p.input, p.output) for p in v.pairs if not p.passed}
    assert {("lon", "p"), ("lat", "q")} <= bad and v.J_avg > 100 and not v.good
    assert any(p.deviations for p in v.pairs if p.input == "lon")


def test_input_delay_from_phase_slope(truth_theta, lon_delayed150):
    _, rs = lon_delayed150  # 100 ms on lon
    v = verify(truth_theta, rs)
    assert abs(v.input_delays["lon"].delay_s - 0.100) <= 0.015
    assert abs(v.input_delays["lat"].delay_s) <= 0.015
    v2 = verify(truth_theta, rs, delays_s=np.array([0.0, 0.1, 0.0, 0.0]))
    assert v2.J_avg < v.J_avg / 5


def test_tischler_cost_values():
    f = np.geomspace(0.1, 10, 20)
    data = np.exp(1j * 0.1 * f)
    model = data * 10 ** (1 / 20)  # +1 dB, no phase error
    J = tischler_cost(model, data, np.ones(20), np.ones(20, bool))
    assert J == pytest.approx(20 * coherence_weight(np.array(1.0)), rel=1e-9)
    model = data * np.exp(1j * np.radians(10.0))  # 10 deg at half the points only
    mask = np.arange(20) % 2 == 0
    assert tischler_cost(model, data, np.full(20, 0.6), mask) == pytest.approx(
        20 * coherence_weight(np.array(0.6)) * 0.01745 * 100, rel=1e-9)
    assert coherence_weight(np.array(0.6)) == pytest.approx((1.58 * (1 - np.exp(-0.6))) ** 2)


def test_error_residuals_in_standard_deviations():
    f = np.geomspace(0.1, 10, 20)
    data = np.exp(1j * 0.1 * f)
    eps = np.full(20, 0.05)
    model = data * np.exp(0.05) * np.exp(1j * 0.1)  # magnitude one std high, phase two std late
    r = error_residuals(model, data, eps, np.ones(20, bool))
    assert r.shape == (40,)
    np.testing.assert_allclose(r[:20], 1.0, rtol=1e-9)
    np.testing.assert_allclose(r[20:], 2.0, rtol=1e-9)
    assert np.isinf(error_residuals(np.zeros(20), data, eps, np.ones(20, bool))[:20]).all()  # no path


def test_phase_slope_and_bandwidth_on_analytic_response():
    f = np.geomspace(0.1, 20, 200)
    s = 2j * np.pi * f
    tau = 0.06
    H = 5.0 / (s * (0.1 * s + 1)) * np.exp(-s * tau)
    ref = 5.0 / (s * (0.1 * s + 1))
    d = phase_slope_delay(f, H, ref, np.full(f.size, 0.05), np.ones(f.size, bool))
    assert d is not None and d.delay_s == pytest.approx(tau, abs=1e-6)
    bw = attitude_bandwidth(f, H)
    w = 2 * np.pi * f
    phase = -90 - np.degrees(np.arctan(0.1 * w)) - np.degrees(w * tau)
    f180 = np.interp(-180, phase[::-1], f[::-1])
    assert bw.f180_hz == pytest.approx(f180, rel=1e-3)
    ph2 = -90 - np.degrees(np.arctan(0.1 * 2 * np.pi * 2 * f180)) - np.degrees(2 * np.pi * 2 * f180 * tau)
    assert bw.phase_delay_s == pytest.approx(-(ph2 + 180) / (360 * 2 * f180), rel=1e-2)
    f135 = np.interp(-135, phase[::-1], f[::-1])
    assert bw.phase_bandwidth_hz == pytest.approx(f135, rel=1e-3)
    neg = attitude_bandwidth(f, -H)  # sign-corrected: same figures
    assert neg.f180_hz == pytest.approx(bw.f180_hz)


def test_bad_input_one_reason_per_pair():
    short = flight(20.0, seed=3)
    rs = estimate_responses(short)
    assert not rs.with_response and len(rs.pairs) == 32
    assert all("too short" in p.reason for p in rs.pairs)
    assert all(any(f"window {w:g} s not used" in n for n in rs.notes) for w in (5, 10, 20))

    prep = flight(150.0, seed=4)
    seg = prep.segments[0]
    u = seg.inputs.copy()
    u[:, 3] = 0.0  # pedal never moves
    y = seg.outputs_raw.copy()
    y[:, 5] = np.random.default_rng(0).standard_normal(y.shape[0]) * 0.01  # r is pure noise
    rs = estimate_responses(prepared_from_arrays(u, y, prep.dt_s))
    for p in rs.pairs:
        if p.input == "ped":
            assert p.reason == "input ped never moves (std below 0.0001)"
        elif p.output == "r":
            assert p.reason.startswith("coherence below 0.6") and not p.coherent.any()
    assert all(len(p.reason.splitlines()) <= 1 for p in rs.pairs)
