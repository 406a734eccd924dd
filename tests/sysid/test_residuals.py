"""Where a held-out prediction misses (benchkit.residuals): noise floor and band shares on windows with a
known residual."""

from __future__ import annotations

import numpy as np

from benchkit.residuals import channel_residuals, noise_sigma

DT = 0.02
W, L = 40, 250


def _signal(rng: np.random.Generator) -> np.ndarray:
    t = np.arange(L) * DT
    f = rng.uniform(0.3, 1.5, size=(W, 1))
    return 0.2 * np.sin(2 * np.pi * f * t[None, :] + rng.uniform(0, 6, size=(W, 1)))


def test_noise_sigma_reads_white_noise_under_smooth_motion() -> None:
    rng = np.random.default_rng(0)
    y = _signal(rng) + 0.01 * rng.standard_normal((W, L))
    assert abs(noise_sigma(y) - 0.01) < 0.001


def test_a_prediction_off_by_noise_alone_sits_at_the_noise_floor_in_the_high_band() -> None:
    rng = np.random.default_rng(1)
    s = _signal(rng)
    y = s + 0.01 * rng.standard_normal((W, L))
    mask = np.ones((W, L), dtype=bool)
    r = channel_residuals(y, s, mask, DT, np.arange(W) % 2 == 0)
    assert abs(r["match"] - r["noise_floor"]) < 1.0
    assert 85 < r["noise"] < 115
    assert r["high"] > 80 and r["drift"] < 5                     # white noise: 2-25 Hz of 0-25 Hz
    assert abs(r["drift"] + r["in_band"] + r["high"] - 100) < 1e-9


def test_offset_and_ramp_per_window_are_drift_and_removing_them_recovers_the_match() -> None:
    rng = np.random.default_rng(2)
    s = _signal(rng)
    t = np.arange(L) * DT
    drift = rng.normal(0, 0.05, size=(W, 1)) + rng.normal(0, 0.02, size=(W, 1)) * t[None, :]
    mask = np.ones((W, L), dtype=bool)
    active = np.arange(W) < W // 2
    yhat = s + np.where(active[:, None], drift, 0.0)
    r = channel_residuals(s, yhat, mask, DT, active)
    assert r["drift"] > 99
    assert r["match_no_drift"] > 99 > r["match"]
    assert r["match_calm"] > 99 > r["match_active"]        # the residual is in the "active" half only


def test_in_band_misfit_is_in_band_and_holes_are_not_scored() -> None:
    rng = np.random.default_rng(3)
    s = _signal(rng)
    mask = np.ones((W, L), dtype=bool)
    mask[0, 100:120] = False                                    # a hole: its window leaves the band shares
    yhat = 0.7 * s                                              # a gain error at 0.3-1.5 Hz
    r = channel_residuals(s, yhat, mask, DT, np.ones(W, dtype=bool))
    assert r["in_band"] > 80
    assert 65 < r["match"] < 75
