"""Noise floors estimated from the data themselves (no thresholds tuned on a simulator).

* :func:`raw_noise_std` — per-channel white-noise level of the raw outputs from second differences
  (robust: median absolute deviation), which a smooth flight signal barely contributes to at 50 Hz.
* :func:`smoothing_gain` — how much of that noise variance survives the smoothing that produced the
  smoothed outputs, found by matching ``var(smoothed - raw)`` to eq.-18 smoothing of white noise
  with 0..8 passes.
* :func:`noise_floor` — the normalised RMS error a perfect model would still show on the smoothed
  outputs (per channel), i.e. the floor under every gap figure of the report.

A channel sent slower than the grid (``stride`` = source interval / grid step > 1, e.g. a 10 Hz
position estimate on the 50 Hz grid) reaches the grid linearly interpolated: its noise there is not
white (most second differences vanish between source samples). Every estimator then works on the
grid sampled at the source stride and is calibrated on white noise passed through the same
interpolation (a deterministic simulation per stride), so all figures stay "noise std on the grid".

Arrays: ``(n_samples, n_channels)``. Pure numpy.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from groundstation.dsp.smoothing import smooth5
from groundstation.gap.config import DiagnoseConfig

_MAD_TO_STD = 1.4826
_MAX_PASSES = 8


def _step(key: float) -> int:
    """Sub-sampling step of the second differences for a stride key (see :func:`_key`)."""
    return max(1, int(round(key)))


def _mad_std(d2: np.ndarray) -> float:
    if not np.isfinite(d2).any():      # a channel never measured: no noise figure, and no warning
        return float("nan")
    med = np.nanmedian(d2)
    return float(_MAD_TO_STD * np.nanmedian(np.abs(d2 - med)) / np.sqrt(6.0))


def _d2_scale(parts: list[np.ndarray], step: int, offsets: list[int] | None = None) -> float:
    """White-noise std from second differences of 1-D ``parts``, each sampled every ``step`` grid steps.

    With ``step > 1`` the grid is read at every phase 0..step-1 and the estimates combined in
    quadrature: a phase next to a source sample sees the source noise, one half-way between two sees
    their average; over all phases the figure does not depend on where the source samples fell.
    ``offsets``: grid index of each part's first sample, so that a phase means the same grid
    samples in every part (parts split by holes of the link start at any index; read from their own
    first sample, a phase would mix on-source and half-way samples, and the median-based figure of
    such a mixture falls below the noise, by 15 % on a flight with 10 % of its packets lost).
    """
    offs = [0] * len(parts) if offsets is None else [int(o) for o in offsets]
    ests = []
    for ph in range(step):
        d2 = [np.diff(p[(ph - o) % step::step], n=2) for p, o in zip(parts, offs, strict=True)
              if p[(ph - o) % step::step].shape[0] > 3]
        if d2:
            ests.append(_mad_std(np.concatenate(d2)))
    return float(np.sqrt(np.mean(np.square(ests)))) if ests else float("nan")


@lru_cache(maxsize=64)
def _calibration(stride_key: float, seed: int = DiagnoseConfig.noise_calibration_seed) -> tuple[float, np.ndarray]:
    """For unit white noise sent every ``stride`` grid steps and linearly interpolated onto the grid
    (grid noise ``g``): ``(d2 estimate / std(g), [(var(S_p g), var(S_p g - g)) / var(g) per pass])``."""
    rng = np.random.default_rng(seed)
    n = 32768
    if stride_key <= 1.0:
        g = rng.standard_normal(n)
    else:
        m = int(n / stride_key) + 4
        t_src = (np.arange(m) - 1.0 + rng.uniform()) * stride_key
        t_src += rng.uniform(-0.1, 0.1, m) * stride_key   # send-time jitter
        g = np.interp(np.arange(n, dtype=float), np.sort(t_src), rng.standard_normal(m))
    g = g[64:-64]
    sd = float(g.std())
    # white noise: the second-difference estimator is unbiased by construction
    k = 1.0 if stride_key <= 1.0 else _d2_scale([g], _step(stride_key)) / sd
    fac = np.empty((_MAX_PASSES + 1, 2))
    for p in range(_MAX_PASSES + 1):
        s = smooth5(g, p)
        fac[p] = (s[10:-10].var() / sd ** 2, (s - g)[10:-10].var() / sd ** 2)
    return k, fac


def _key(stride: float) -> float:
    """Calibration key of a source stride: 1 at (or within 20 % of) the grid rate, else rounded to 0.05."""
    return 1.0 if not np.isfinite(stride) or stride <= 1.2 else round(float(stride) * 20.0) / 20.0


def raw_noise_std(raw: list[np.ndarray], strides: np.ndarray | None = None,
                  calibration_seed: int = DiagnoseConfig.noise_calibration_seed,
                  offsets: list[int] | None = None) -> np.ndarray:
    """Noise standard deviation on the grid per channel, from second differences of raw segments (n, C).

    ``strides`` (C,) source interval / grid step per channel (None: all sent at the grid rate);
    ``calibration_seed``: seed of the Monte-Carlo calibration for interpolated streams (a constant);
    ``offsets``: grid index of each segment's first sample on its flight's grid (see
    :func:`grid_offsets`; None: every segment starts a grid of its own).
    """
    C = raw[0].shape[1]
    st = np.ones(C) if strides is None else np.asarray(strides, dtype=float)
    offs = [0] * len(raw) if offsets is None else list(offsets)
    out = np.empty(C)
    for c in range(C):
        key = _key(st[c])
        step = _step(key)
        keep = [i for i, r in enumerate(raw) if r.shape[0] > 3 * step]
        out[c] = (_d2_scale([raw[i][:, c] for i in keep], step, [offs[i] for i in keep])
                  / _calibration(key, calibration_seed)[0]) if keep else np.nan
    return out


def grid_offsets(t_starts_s: list[float], flights: list[int], dt_s: float) -> list[int]:
    """Grid index of each segment's first sample, counted from the first segment of its flight.

    Segments of one flight are slices of one grid (``dt_s`` apart), so these are whole numbers."""
    first: dict[int, float] = {}
    for t0, f in zip(t_starts_s, flights, strict=True):
        first[f] = min(first.get(f, t0), t0)
    return [int(round((t0 - first[f]) / dt_s)) for t0, f in zip(t_starts_s, flights, strict=True)]


def smoothing_gain(raw: list[np.ndarray], smoothed: list[np.ndarray], sigma: np.ndarray,
                   strides: np.ndarray | None = None,
                   calibration_seed: int = DiagnoseConfig.noise_calibration_seed) -> np.ndarray:
    """Per channel: fraction of the raw (grid) noise variance left in the smoothed outputs."""
    diff = np.concatenate([s - r for s, r in zip(smoothed, raw, strict=True)])
    seen = np.isfinite(diff).sum(axis=0)
    v = np.full(diff.shape[1], np.nan)
    v[seen > 0] = np.nanvar(diff[:, seen > 0], axis=0)   # a channel never measured stays NaN, quietly
    st = np.ones(v.shape[0]) if strides is None else np.asarray(strides, dtype=float)
    gains = np.empty(v.shape[0])
    for c in range(v.shape[0]):
        if not np.isfinite(sigma[c]) or sigma[c] <= 0:
            gains[c] = 1.0
            continue
        fac = _calibration(_key(st[c]), calibration_seed)[1]
        ratio = v[c] / sigma[c] ** 2
        p = int(np.argmin(np.abs(fac[:, 1] - ratio)))
        gains[c] = fac[p, 0]
    return gains


def noise_floor(raw: list[np.ndarray], smoothed: list[np.ndarray],
                strides: np.ndarray | None = None,
                calibration_seed: int = DiagnoseConfig.noise_calibration_seed,
                offsets: list[int] | None = None) -> dict[str, np.ndarray]:
    """Noise figures per channel: ``sigma_raw``, ``sigma_smoothed``, ``nrmse_floor`` (sigma / signal std).

    ``strides``, ``calibration_seed``, ``offsets``: see :func:`raw_noise_std`.
    """
    sigma = raw_noise_std(raw, strides, calibration_seed, offsets)
    gain = smoothing_gain(raw, smoothed, sigma, strides, calibration_seed)
    sig_s = sigma * np.sqrt(gain)
    y = np.concatenate(smoothed)
    seen = np.isfinite(y).any(axis=0)
    sd = np.full(y.shape[1], np.nan)
    sd[seen] = np.nanstd(y[:, seen], axis=0)      # a channel never measured: NaN, without a warning
    floor = np.where(sd > 0, sig_s / np.where(sd > 0, sd, 1.0), np.inf)
    return {"sigma_raw": sigma, "sigma_smoothed": sig_s, "nrmse_floor": floor, "signal_std": sd}
