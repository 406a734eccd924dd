"""Locate the gap: per channel, per time window, per frequency band and per flight condition.

Everything here works on a model's simulation over the windows of :class:`Evaluator`:
``Y`` measured (W, L, 8), ``yhat`` simulated (W, L, 8), ``mask`` (L,) samples scored.

* channels: match degree (paper eq. 19) and Theil's inequality coefficient per output;
* windows: residual energy of each window (channel-normalised) against the flight's nominal level
  (median window); a window is flagged when its log-energy is a robust outlier (median + 3.5 MAD)
  and at least twice the nominal level;
* band: residual spectrum relative to the white-noise floor, summed over channels, in octave bands;
  the band holding the largest share of the excess is reported, with the input-residual coherence
  there;
* conditions: Spearman rank correlation of window residual energy with height, speed, input
  amplitude and input rate; the strongest significant one (Bonferroni) is named.

Pure numpy/scipy.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import stats

from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.fingerprints import averaged_periodogram
from groundstation.sysid.model import OUTPUTS

OCTAVES_HZ = ((0.0, 0.25), (0.25, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, 4.0), (4.0, 8.0), (8.0, 16.0), (16.0, 64.0))


def channel_metrics(Y: np.ndarray, yhat: np.ndarray, mask: np.ndarray, available: np.ndarray) -> dict[str, dict[str, float]]:
    """Match degree (%) and Theil U per available channel; ``mask`` (L,) samples scored, or (W, L, 8)
    per sample (holes of the link left out)."""
    out = {}
    for c, name in enumerate(OUTPUTS):
        if not available[c]:
            continue
        if mask.ndim == 3:
            y, yh = Y[..., c][mask[..., c]], yhat[..., c][mask[..., c]]
        else:
            y = Y[:, mask, c].ravel()
            yh = yhat[:, mask, c].ravel()
        e = y - yh
        ny = np.linalg.norm(y)
        match = float((1 - np.linalg.norm(e) / ny) * 100) if ny > 0 else float("nan")
        den = np.sqrt(np.mean(y ** 2)) + np.sqrt(np.mean(yh ** 2))
        tic = float(np.sqrt(np.mean(e ** 2)) / den) if den > 0 else float("nan")
        out[name] = {"match": round(match, 2), "tic": round(tic, 4)}
    return out


def flag_windows(energy: np.ndarray) -> tuple[np.ndarray, float]:
    """Boolean (W,) outlier windows and the nominal level (median) of per-window energy (W,)."""
    e = np.maximum(energy, 1e-300)
    le = np.log(e)
    med = float(np.median(le))
    mad = float(np.median(np.abs(le - med))) * 1.4826 + 1e-12
    flag = (le > med + 3.5 * mad) & (le > med + np.log(2.0))
    return flag, float(np.exp(med))


def merge_intervals(iv: list[tuple[float, float]], gap_s: float = 1e-6) -> list[list[float]]:
    out: list[list[float]] = []
    for a, b in sorted(iv):
        if out and a <= out[-1][1] + gap_s:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return out


def worst_band(resid: np.ndarray, inputs: np.ndarray, dt_s: float, noise_psd: np.ndarray,
               w8: np.ndarray) -> dict[str, Any]:
    """Octave band with the largest excess of residual power over the noise floor (summed over channels)."""
    f, P = averaged_periodogram(resid * w8, dt_s)
    excess = np.maximum(P - noise_psd[None, :] * w8 ** 2, 0.0).sum(axis=1)
    df = f[1] - f[0]
    best, best_e, tot = None, -1.0, float(excess.sum() * df) + 1e-300
    for lo, hi in OCTAVES_HZ:
        sel = (f >= lo) & (f < hi)
        if not sel.any():
            continue
        e = float(excess[sel].sum() * df)
        if e > best_e:
            best, best_e = (lo, min(hi, f[-1])), e
    coh = input_coherence(resid * w8, inputs, dt_s, best) if best else 0.0
    return {"band_hz": [float(best[0]), float(best[1])] if best else None,
            "excess_share": best_e / tot, "input_coherence": coh, "f_hz": f, "psd": P}


def input_coherence(resid: np.ndarray, inputs: np.ndarray, dt_s: float, band: tuple[float, float]) -> float:
    """Mean magnitude-squared coherence between the inputs and the residuals in a band (max over pairs)."""
    L = resid.shape[1]
    win = np.hanning(L)
    R = np.fft.rfft((resid - resid.mean(1, keepdims=True)) * win[None, :, None], axis=1)
    U = np.fft.rfft((inputs - inputs.mean(1, keepdims=True)) * win[None, :, None], axis=1)
    f = np.fft.rfftfreq(L, dt_s)
    sel = (f >= band[0]) & (f < band[1])
    if not sel.any():
        return 0.0
    Suu = (np.abs(U) ** 2).mean(0)[sel]
    Srr = (np.abs(R) ** 2).mean(0)[sel]
    best = 0.0
    for i in range(U.shape[2]):
        for c in range(R.shape[2]):
            Sur = (U[:, sel, i].conj() * R[:, sel, c]).mean(0)
            den = Suu[:, i] * Srr[:, c]
            ok = den > 0
            if ok.any():
                best = max(best, float(np.mean(np.abs(Sur[ok]) ** 2 / den[ok])))
    return best


def conditions(energy: np.ndarray, features: dict[str, np.ndarray],
               alpha: float = DiagnoseConfig.conditions_alpha) -> dict[str, Any]:
    """Rank correlation of window residual energy with each flight-condition feature (W,)."""
    res: dict[str, Any] = {}
    best_name, best_rho, best_p = "none", 0.0, 1.0
    m = max(len(features), 1)
    for name, x in features.items():
        ok = np.isfinite(x)
        if ok.sum() < 6 or np.ptp(x[ok]) == 0:
            res[name] = None
            continue
        rho, p = stats.spearmanr(x[ok], energy[ok])
        rho, p = float(rho), float(p)
        res[name] = {"rho": round(rho, 3), "p": p}
        if p * m < alpha and abs(rho) > abs(best_rho):
            best_name, best_rho, best_p = name, rho, p
    label = "none"
    if best_name != "none":
        words = {"height_m": ("low height", "high height"), "speed_m_s": ("low speed", "high speed"),
                 "input_amplitude": ("small input amplitude", "large input amplitude"),
                 "input_rate": ("low input rate", "high input rate")}
        lo, hi = words.get(best_name, (f"low {best_name}", f"high {best_name}"))
        label = hi if best_rho > 0 else lo
    return {"label": label, "rho": best_rho, "p": best_p, "features": res}
