"""Model-free fingerprints fire on their effect and stay quiet on an effect-free flight."""

import numpy as np

from groundstation.gap.evaluate import cut, window_starts
from groundstation.gap.fingerprints import kinematic_rate_offsets, spectral_lines
from groundstation.gap.noise import noise_floor


def _windows(prep, L=150):
    s = prep.segments[0]
    st = window_starts([s], L)
    return (cut([s.outputs_raw], st, L), cut([s.inputs], st, L), cut([s.outputs], st, L))


def test_spectral_line_found_at_its_frequency(flight_factory):
    prep = flight_factory(T_s=60.0, seed=3, effect=("rotor_vibration", 7.3, 0.006))
    clean = flight_factory(T_s=60.0, seed=3)  # same trajectory and noise, no line
    raw, u, _ = _windows(prep)
    _, _, smooth_clean = _windows(clean)
    lines, spectra = spectral_lines(raw - smooth_clean, u, 0.02, np.ones(8, bool))
    assert lines, "no line found"
    assert abs(lines[0].frequency_hz - 7.3) < 0.2
    assert "p" in lines[0].channels
    assert abs(lines[0].amplitude["p"] - 0.006) < 0.002


def test_no_spectral_line_without_vibration(flight_factory):
    prep = flight_factory(T_s=60.0, seed=3)
    raw, u, sm = _windows(prep)
    lines, _ = spectral_lines(raw - sm, u, 0.02, np.ones(8, bool))
    assert lines == []


def _euler_windows(bias_q=0.0, seed=4, W=30, L=150, dt=0.02):
    """Smooth random attitude with body rates from the exact Euler kinematics, plus noise."""
    from groundstation.dsp.smoothing import smooth5
    rng = np.random.default_rng(seed)
    n = W * L
    t = np.arange(n) * dt
    th = 0.05 + 0.08 * np.sin(0.9 * t) * np.sin(0.13 * t)
    ph = -0.03 + 0.1 * np.sin(1.7 * t + 1) * np.cos(0.07 * t)
    psd = 0.3 * np.sin(0.5 * t)
    thd, phd = np.gradient(th, dt), np.gradient(ph, dt)
    p = phd - psd * np.sin(th)
    q = thd * np.cos(ph) + psd * np.sin(ph) * np.cos(th)
    r = -thd * np.sin(ph) + psd * np.cos(ph) * np.cos(th)
    Y = np.zeros((n, 8))
    Y[:, 3], Y[:, 4], Y[:, 5], Y[:, 6], Y[:, 7] = p, q + bias_q, r, th, ph
    Y[:, 3:6] += 0.01 * rng.standard_normal((n, 3))
    Y[:, 6:] += 0.003 * rng.standard_normal((n, 2))
    return smooth5(Y, 2).reshape(W, L, 8)


def test_kinematic_offset_on_q_only():
    off = kinematic_rate_offsets(_euler_windows(bias_q=0.004), 0.02, np.ones(8, bool))
    assert off["q"].log10_p < -6 and abs(off["q"].offset_rad_s - 0.004) < 0.001
    assert off["p"].log10_p > -3


def test_no_kinematic_offset_without_bias():
    off = kinematic_rate_offsets(_euler_windows(), 0.02, np.ones(8, bool))
    assert off["q"].log10_p > -3 and off["p"].log10_p > -3


def test_noise_floor_recovers_sensor_noise(flight_factory):
    prep = flight_factory(T_s=60.0, seed=5)
    s = prep.segments[0]
    nf = noise_floor([s.outputs_raw], [s.outputs])
    from tests.gap.conftest import NOISE_SD
    np.testing.assert_allclose(nf["sigma_raw"], NOISE_SD, rtol=0.25)
    assert (nf["sigma_smoothed"] < nf["sigma_raw"]).all()
