"""Noise floors estimated from the data themselves (no thresholds tuned on a simulator).

* :func:`raw_noise_std` — per-channel white-noise level of the raw outputs from second differences
  (robust: median absolute deviation), which a smooth flight signal barely contributes to at 50 Hz.
* :func:`smoothing_gain` — how much of that noise variance survives the smoothing that produced the
  smoothed outputs, found by matching ``var(smoothed - raw)`` to eq.-18 smoothing of white noise
  with 0..8 passes.
* :func:`noise_floor` — the normalised RMS error a perfect model would still show on the smoothed
  outputs (per channel), i.e. the floor under every gap figure of the report.

Arrays: ``(n_samples, n_channels)``. Pure numpy.
"""

from __future__ import annotations

import numpy as np

from groundstation.dsp.smoothing import smooth5

_MAD_TO_STD = 1.4826


def raw_noise_std(raw: list[np.ndarray]) -> np.ndarray:
    """White-noise standard deviation per channel from second differences of raw segments (n, C)."""
    d2 = np.concatenate([np.diff(r, n=2, axis=0) for r in raw if r.shape[0] > 3])
    med = np.nanmedian(d2, axis=0)
    mad = np.nanmedian(np.abs(d2 - med), axis=0)
    return _MAD_TO_STD * mad / np.sqrt(6.0)


def _smooth_factors(max_passes: int = 8, n: int = 4096) -> np.ndarray:
    """(passes, [var(S n)/s^2, var(S n - n)/s^2]) for unit white noise (deterministic sequence)."""
    rng = np.random.default_rng(12345)
    x = rng.standard_normal(n)
    out = np.empty((max_passes + 1, 2))
    for p in range(max_passes + 1):
        s = smooth5(x, p)
        out[p] = (s[10:-10].var(), (s - x)[10:-10].var())
    return out


def smoothing_gain(raw: list[np.ndarray], smoothed: list[np.ndarray], sigma: np.ndarray) -> np.ndarray:
    """Per channel: fraction of the raw noise variance left in the smoothed outputs."""
    fac = _smooth_factors()
    diff = np.concatenate([s - r for s, r in zip(smoothed, raw, strict=True)])
    v = np.nanvar(diff, axis=0)
    gains = np.empty(v.shape[0])
    for c in range(v.shape[0]):
        if not np.isfinite(sigma[c]) or sigma[c] <= 0:
            gains[c] = 1.0
            continue
        ratio = v[c] / sigma[c] ** 2
        p = int(np.argmin(np.abs(fac[:, 1] - ratio)))
        gains[c] = fac[p, 0]
    return gains


def noise_floor(raw: list[np.ndarray], smoothed: list[np.ndarray]) -> dict[str, np.ndarray]:
    """Noise figures per channel: ``sigma_raw``, ``sigma_smoothed``, ``nrmse_floor`` (sigma / signal std)."""
    sigma = raw_noise_std(raw)
    gain = smoothing_gain(raw, smoothed, sigma)
    sig_s = sigma * np.sqrt(gain)
    y = np.concatenate(smoothed)
    sd = np.nanstd(y, axis=0)
    floor = np.where(sd > 0, sig_s / np.where(sd > 0, sd, 1.0), np.inf)
    return {"sigma_raw": sigma, "sigma_smoothed": sig_s, "nrmse_floor": floor, "signal_std": sd}
