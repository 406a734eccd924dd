"""Where a held-out prediction misses: per channel, how far from the noise floor and in what band.

``residual_table(windows)`` takes a model's held-out prediction before scoring
(:class:`groundstation.sysid.heldout.PredictedWindows`: measured and predicted outputs (W, L, 8) on
windows started from the measured states) and returns, per scored channel:

* ``match``: eq. 19, ``(1 - ||e|| / ||y||) * 100`` over the measured samples, as ``predict`` scores it;
* ``noise_floor``: the match a prediction off by the measurement noise alone would reach,
  ``(1 - sigma sqrt(N) / ||y||) * 100``, with ``sigma`` the white-noise level measured in the data
  (robust MAD of the second differences within each window over sqrt(6): white noise of variance
  sigma^2 has second differences of variance 6 sigma^2; smooth motion at 50 Hz adds little);
* the residual's energy split into three shares (%, summing to 100): ``drift`` (a constant and a ramp
  per window, least squares: what varies slower than the window, below about 1 / window), ``in_band``
  (the rest up to ``band_hz``: the rigid-body and pilot band) and ``high`` (above ``band_hz``); and
  ``noise`` (%), the noise floor's energy ``N sigma^2`` against the residual's;
* ``match_no_drift``: the match with the drift part removed (what an offset and a trend per window
  and channel could reach at most, estimated from the window's own outputs: a caveat figure, not a
  prediction);
* ``match_active`` / ``match_calm``: the match over the windows with the stick activity (RMS of the
  inputs' sample-to-sample change, each input scaled by its own over all windows) above / below the
  median: which conditions the mismatch comes from.

Spectral shares come from windows with the channel measured throughout (holes of the link left
out). Pure numpy; the models and the splits are the caller's (``groundstation bench heldout
--residuals``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from groundstation.sysid.model import OUTPUTS

#: upper edge of the in-band part of the residual, Hz (hover rigid-body and pilot band)
BAND_HZ = 2.0


def noise_sigma(y: np.ndarray) -> float:
    """White-noise standard deviation of ``y`` (W, L) from the MAD of its second differences per window."""
    d2 = np.diff(y, n=2, axis=1).ravel()
    if d2.size == 0:
        return 0.0
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return 1.4826 * mad / np.sqrt(6.0)


def _drift(e: np.ndarray, dt_s: float) -> np.ndarray:
    """(W, L) least-squares constant plus ramp of each window of ``e`` (W, L)."""
    t = np.arange(e.shape[1]) * dt_s
    X = np.column_stack([np.ones_like(t), t - t.mean()])
    coef, *_ = np.linalg.lstsq(X, e.T, rcond=None)
    return (X @ coef).T


def _band_shares(rest: np.ndarray, dt_s: float, band_hz: float) -> tuple[float, float]:
    """Energy of ``rest`` (W, L) below and above ``band_hz`` (Parseval over each window's rfft)."""
    L = rest.shape[1]
    F = np.fft.rfft(rest, axis=1)
    f = np.fft.rfftfreq(L, dt_s)
    wgt = np.full(f.size, 2.0)
    wgt[0] = 1.0
    if L % 2 == 0:
        wgt[-1] = 1.0
    P = (np.abs(F) ** 2) * wgt[None, :] / L
    return float(P[:, f <= band_hz].sum()), float(P[:, f > band_hz].sum())


def _activity(inputs: np.ndarray) -> np.ndarray:
    """(W,) stick activity per window: RMS of each input's change, scaled by that input's over all windows."""
    du = np.diff(inputs, axis=1)
    rms = np.sqrt((du ** 2).mean(axis=1))                      # (W, 4)
    scale = np.sqrt((du ** 2).mean(axis=(0, 1)))
    moving = scale > 0
    return (rms[:, moving] / scale[moving]).mean(axis=1) if moving.any() else np.zeros(inputs.shape[0])


def _match(e: np.ndarray, y: np.ndarray) -> float:
    den = float(np.linalg.norm(y))
    return (1.0 - float(np.linalg.norm(e)) / den) * 100.0 if den > 0 else float("nan")


def channel_residuals(y: np.ndarray, yhat: np.ndarray, mask: np.ndarray, dt_s: float, active: np.ndarray,
                      band_hz: float = BAND_HZ) -> dict[str, float]:
    """The figures of the module docstring for one channel: ``y``, ``yhat``, ``mask`` (W, L), ``active`` (W,) bool."""
    e = np.where(mask, yhat - y, 0.0)
    yy = np.where(mask, y, 0.0)
    full = mask.all(axis=1)
    out = {"match": _match(e, yy)}
    sigma = noise_sigma(y[full]) if full.any() else 0.0
    n = int(mask.sum())
    out["noise_floor"] = (1.0 - sigma * np.sqrt(n) / max(float(np.linalg.norm(yy)), 1e-300)) * 100.0
    ef = e[full]
    drift = _drift(ef, dt_s) if full.any() else np.zeros_like(ef)
    low, high = _band_shares(ef - drift, dt_s, band_hz)
    d = float((drift ** 2).sum())
    tot = max(d + low + high, 1e-300)
    out |= {"drift": 100.0 * d / tot, "in_band": 100.0 * low / tot, "high": 100.0 * high / tot,
            "noise": 100.0 * n * sigma ** 2 / max(float((e ** 2).sum()), 1e-300)}
    e_nd = e.copy()
    e_nd[full] = ef - drift
    out["match_no_drift"] = _match(e_nd, yy)
    out["match_active"] = _match(e[active], yy[active]) if active.any() else float("nan")
    out["match_calm"] = _match(e[~active], yy[~active]) if (~active).any() else float("nan")
    return out


def residual_table(windows: Any, band_hz: float = BAND_HZ) -> dict[str, dict[str, float]]:
    """Per scored channel (in :data:`OUTPUTS` order) the figures of the module docstring."""
    act = _activity(windows.inputs)
    active = act > np.median(act)
    out = {}
    for j, ch in enumerate(OUTPUTS):
        m = np.asarray(windows.mask[:, :, j], dtype=bool)
        if not m.any() or not np.any(windows.outputs[:, :, j][m]):
            continue
        out[ch] = channel_residuals(windows.outputs[:, :, j], windows.predicted[:, :, j], m, windows.dt_s,
                                    active, band_hz)
    return out
