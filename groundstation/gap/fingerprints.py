"""Model-light fingerprints: statistics that point at one effect, each referred to its own noise floor.

* :func:`spectral_lines` — narrow lines in the raw output residual spectra (rotor vibration aliased
  into the 50 Hz rates): the window-averaged periodogram of each channel against the median of its
  neighbouring bins, significant by the chi-square law of an average of ``W`` periodograms
  (Bonferroni over bins and channels), and not present in the input spectra.
* :func:`line_power_per_window` — a line's power window by window (is it as strong in the second half
  of the flight as in the first?).
* :func:`kinematic_rate_offsets` — a constant offset between a measured body rate and the rate
  implied by the measured Euler angles (eq. 3 inverted:
  ``theta_dot = q cos(phi) - r sin(phi)``, ``phi_dot = p + (q sin(phi) + r cos(phi)) tan(theta)``),
  tested by a t statistic over windows (the between-window scatter is the noise floor). Needs no
  model at all.

Arrays: windows ``(W, L, C)``. Pure numpy/scipy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from groundstation.gap.config import DiagnoseConfig
from groundstation.sysid.model import OUTPUTS


@dataclass
class Line:
    frequency_hz: float
    channels: list[str]
    ratio: float  # peak power / local median (largest channel)
    log10_p: float  # log10 of the Bonferroni-corrected p-value (most significant channel)
    amplitude: dict[str, float] = field(default_factory=dict)  # sinusoid amplitude per channel


def resolvable_lines(lines: list[Line], stride: np.ndarray | None, dt_s: float) -> list[Line]:
    """The lines a channel's own stream can carry: below the Nyquist frequency of the rate it was sent
    at (``stride`` (8,): source interval over grid step per output). A stream sent slower than the
    grid reaches it interpolated; a narrow peak above its source Nyquist is an image of that
    interpolation (and of the send-time jitter), never a vibration: a real rotor line sampled at the
    source rate folds below the source Nyquist. Channels above it are dropped from a line, and a
    line left with none is dropped."""
    if stride is None:
        return lines
    st = np.asarray(stride, float)
    out = []
    for ln in lines:
        ch = [c for c in ln.channels if ln.frequency_hz < 0.5 / (max(float(st[OUTPUTS.index(c)]), 1.0) * dt_s)]
        if ch:
            out.append(Line(ln.frequency_hz, ch, ln.ratio, ln.log10_p, {k: v for k, v in ln.amplitude.items() if k in ch}))
    return out


def _detrend(x: np.ndarray) -> np.ndarray:
    """Remove mean and linear trend along axis 1 of (W, L, C)."""
    L = x.shape[1]
    t = np.linspace(-1, 1, L)
    xm = x - x.mean(axis=1, keepdims=True)
    slope = np.einsum("wlc,l->wc", xm, t) / (t @ t)
    return xm - slope[:, None, :] * t[None, :, None]


def window_periodograms(x: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Hann-tapered periodograms of (W, L, C) windows: (f (F,), P (W, F, C)), one-sided PSD units."""
    L = x.shape[1]
    win = np.hanning(L)
    X = np.fft.rfft(_detrend(x) * win[None, :, None], axis=1)
    P = (np.abs(X) ** 2) * 2 * dt_s / (win @ win)
    return np.fft.rfftfreq(L, dt_s), P


def averaged_periodogram(x: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Hann-tapered periodograms of (W, L, C) windows averaged over W: (f (F,), P (F, C))."""
    f, P = window_periodograms(x, dt_s)
    return f, P.mean(axis=0)


def _line_stats(P: np.ndarray, n_avg: int, half: int = 6, guard: int = 2,
                nyquist_real: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Ratio to the local median and log10 survival probability per bin, (F, C)."""
    F = P.shape[0]
    ratio = np.ones_like(P)
    for k in range(F):
        # a line stands out of BOTH sides (a spectral edge, e.g. where a sweep ends, stands out of one)
        left = list(range(max(0, k - half - guard), k - guard))
        right = list(range(k + guard + 1, min(F, k + half + guard + 1)))
        refs = [np.median(P[side], axis=0) for side in (left, right) if len(side) >= 3]
        if not refs:
            continue
        ref = np.max(refs, axis=0)
        ratio[k] = P[k] / np.where(ref > 0, ref, np.inf)
    dof = np.full(F, 2 * n_avg)
    dof[0] = n_avg  # DC and (even length) Nyquist bins are real: one degree of freedom per window
    if nyquist_real:
        dof[-1] = n_avg
    # the median of chi2_dof/dof sits slightly below its mean: correct the reference
    med = stats.chi2.median(dof) / dof
    logp = stats.chi2.logsf(ratio * (med * dof)[:, None], dof[:, None]) / np.log(10)
    return ratio, np.maximum(logp, -300.0)


def spectral_lines(resid: np.ndarray, inputs: np.ndarray, dt_s: float, available: np.ndarray,
                   *, alpha: float = 1e-3, min_hz: float | None = None, response: Any = None,
                   reach_factor: float = DiagnoseConfig.line_stick_reach_factor) -> tuple[list[Line], dict]:
    """Significant narrow spectral lines in output residuals that the inputs do not explain.

    A line the inputs also carry is left out where the inputs could have put it in the residual: the
    strongest input power at that frequency through the model's largest response from any input to the
    channel, ``max_j |G_j(f)|^2 max_j Pu_j(f)`` (any input: one held still in the log, or not logged,
    may be the one that moved the aircraft), or where a stick's line there is not an echo (its power
    at or above that stick's mean spectral level: a card's or a pilot's oscillation),
    times ``reach_factor`` squared (``[diagnose] line_stick_reach_factor``), is at least the residual's line power (above its local
    median). A residual line the sticks could only have made were the model's response wrong by more
    than that factor in amplitude was not made by the sticks: a stabilising loop passes a vibration the
    gyros see into the servo outputs, where it is the consequence, not the cause (at a rotor line the
    hover model's response is orders of magnitude below that; in the band the card excites it is not). ``response(f_hz) -> (F, 8, 4)`` complex model response; None:
    any input line leaves the bin out.

    Parameters
    ----------
    resid : array (W, L, 8), raw output residuals (measured raw minus model), per window
    inputs : array (W, L, 4), inputs on the same windows
    dt_s : float, sample period (s)
    available : array (8,) bool
    alpha : family-wise false-alarm probability (Bonferroni over bins x channels)
    min_hz : lowest frequency tested (default: 3 frequency bins)

    Returns
    -------
    lines : list of Line, strongest first
    spectra : dict with ``f_hz`` (F,), ``psd`` (F, 8), ``ratio`` (F, 8), ``log10_p`` (F, 8)
    """
    W, L, _ = resid.shape
    f, Pw = window_periodograms(resid, dt_s)
    P = Pw.mean(axis=0)
    # persistence: the median over windows is blind to bursts (a sweep passing through a model-error
    # resonance) but keeps a line present in every window; ~N(ln2, 1/W) relative to the PSD
    ratio_med, _ = _line_stats(np.median(Pw, axis=0), W, nyquist_real=L % 2 == 0)
    z_med = (ratio_med - 1.0) * np.log(2.0) * np.sqrt(W)
    _, Pu = averaged_periodogram(inputs, dt_s)
    ratio, logp = _line_stats(P, W, nyquist_real=L % 2 == 0)
    uratio, ulogp = _line_stats(Pu, W, nyquist_real=L % 2 == 0)
    lo = 3 if min_hz is None else max(3, int(np.ceil(min_hz / (f[1] - f[0]))))
    test = np.zeros_like(ratio, bool)
    test[lo:] = True  # up to Nyquist: rotor lines alias anywhere in the band
    test &= available[None, :]
    n_tests = max(int(test.sum()), 1)
    thr = np.log10(alpha / n_tests)
    z_thr = stats.norm.isf(alpha / n_tests)
    sig = test & (logp < thr) & (z_med > z_thr)
    u_line = ulogp < np.log10(alpha / max(Pu.size, 1))  # (F, 4)
    if response is None:
        sig &= ~u_line.any(axis=1)[:, None]
    elif u_line.any():
        G2 = np.abs(np.asarray(response(f))) ** 2  # (F, 8, 4)
        # what a stick can put in each output at that frequency: the strongest stick power there through the
        # model's largest response to any stick (a stick held still in the log may be the one that moves)
        reach = np.nan_to_num(G2).max(axis=2) * Pu.max(axis=1)[:, None]
        r_exc = P * (1.0 - 1.0 / np.maximum(ratio, 1.0))
        # an echo: every stick's line there lies below that stick's mean spectral level (a card's or a
        # pilot's oscillation is a large part of the stick's motion and is never an echo)
        mean_psd = 2.0 * dt_s * inputs.reshape(-1, inputs.shape[-1]).var(axis=0)
        echo = ~(u_line & (Pu >= mean_psd[None, :])).any(axis=1)
        sig &= ~(u_line.any(axis=1)[:, None] & ((reach_factor ** 2 * reach >= r_exc) | ~echo[:, None]))
    lines: list[Line] = []
    used = np.zeros(len(f), bool)
    order = np.argsort(np.where(sig, logp, 0).min(axis=1))
    for k in order:
        if not sig[k].any() or used[max(0, k - 2):k + 3].any():
            continue
        used[k] = True
        chans = [OUTPUTS[c] for c in np.flatnonzero(sig[k])]
        fk = refine_frequency(resid, dt_s, f[k], f[1] - f[0])
        amp = {OUTPUTS[c]: sinusoid_amplitude(resid[..., c], dt_s, fk) for c in np.flatnonzero(sig[k])}
        cmax = int(np.argmin(np.where(sig[k], logp[k], 0)))
        lines.append(Line(frequency_hz=float(fk), channels=chans, ratio=float(ratio[k, cmax]),
                          log10_p=float(logp[k, cmax] - thr + np.log10(alpha)), amplitude=amp))
    spectra = {"f_hz": f, "psd": P, "ratio": ratio, "log10_p": logp, "threshold_log10_p": thr,
               "z_median": z_med, "threshold_z": z_thr}
    return lines, spectra


def refine_frequency(resid: np.ndarray, dt_s: float, f0: float, df: float) -> float:
    """Frequency (Hz) near f0 maximising the summed per-window sinusoid fit power (all channels)."""
    grid = f0 + np.linspace(-df, df, 41)
    L = resid.shape[1]
    t = np.arange(L) * dt_s
    x = _detrend(resid)
    best, fbest = -1.0, f0
    for fq in grid:
        if fq <= 0:
            continue
        e = np.exp(-2j * np.pi * fq * t)
        pw = float((np.abs(np.einsum("wlc,l->wc", x, e)) ** 2).sum())
        if pw > best:
            best, fbest = pw, fq
    return float(fbest)


def sinusoid_fit(x: np.ndarray, dt_s: float, f_hz: float) -> np.ndarray:
    """Per-window least-squares sinusoid at f_hz: returns the fitted sinusoid, same shape as x (W, L)."""
    L = x.shape[1]
    t = np.arange(L) * dt_s
    B = np.stack([np.cos(2 * np.pi * f_hz * t), np.sin(2 * np.pi * f_hz * t), np.ones(L)], axis=1)
    coef, *_ = np.linalg.lstsq(B, x.T, rcond=None)
    fit = (B[:, :2] @ coef[:2]).T
    return fit


def without_lines(x: np.ndarray, dt_s: float, lines: list[Line], chunk: int) -> np.ndarray:
    """``x`` (n, 8) of one segment with each line's sinusoid removed from its channels, fitted by least
    squares per ``chunk`` samples (amplitude and phase may drift) on the second differences, where the
    noise is measured: the flight's own slow motion is not there to leak into the fit (NaN samples
    are left out).

    A line is a deterministic signal, not sensor noise: second differences read a line near the
    Nyquist frequency as white noise of 1.7 times its amplitude (robust median statistics), which puts the
    noise floor above the gap the line itself makes."""
    out = np.array(x, dtype=float, copy=True)
    if not lines:
        return out
    n = out.shape[0]
    for a in range(0, n, max(chunk, 1)):
        b = min(n, a + chunk)
        w = 2 * np.pi * np.arange(b - a)[:, None] * dt_s * np.array([ln.frequency_hz for ln in lines])[None, :]
        for c in {OUTPUTS.index(ch) for ln in lines for ch in ln.channels}:
            on = [k for k, ln in enumerate(lines) if OUTPUTS[c] in ln.channels]
            B = np.concatenate([np.cos(w[:, on]), np.sin(w[:, on])], axis=1)
            d2y, d2B = np.diff(out[a:b, c], 2), np.diff(B, 2, axis=0)
            ok = np.isfinite(d2y)
            if ok.sum() < 4 * B.shape[1]:
                continue
            coef, *_ = np.linalg.lstsq(d2B[ok], d2y[ok], rcond=None)
            out[a:b, c] -= B @ coef
    return out


def sinusoid_amplitude(x: np.ndarray, dt_s: float, f_hz: float) -> float:
    """RMS-over-windows amplitude of the per-window sinusoid at f_hz in x (W, L)."""
    fit = sinusoid_fit(x, dt_s, f_hz)
    return float(np.sqrt(2.0 * (fit ** 2).mean()))


def line_power_per_window(resid: np.ndarray, dt_s: float, f_hz: float, tol_hz: float,
                          channels: list[str]) -> np.ndarray:
    """Each window's power of a line near ``f_hz``: the largest Hann-tapered Fourier power within
    ``tol_hz`` of it (a wandering line moves between windows), each channel divided by its median over
    the windows (no unit, every channel weighs the same), summed over ``channels``.

    Parameters
    ----------
    resid : array (W, L, 8), raw output residuals per window
    dt_s : float, sample period (s)
    f_hz, tol_hz : float, the line's frequency and how far it may move (Hz)
    channels : names of the output channels the line is in

    Returns
    -------
    array (W,), the line's power per window relative to its median (1 for a steady line)
    """
    W, L, _ = resid.shape
    t = np.arange(L) * dt_s
    grid = f_hz + np.linspace(-tol_hz, tol_hz, 31)
    grid = grid[grid > 0]
    E = np.exp(-2j * np.pi * grid[:, None] * t[None, :]) * np.hanning(L)[None, :]
    x = _detrend(resid)
    out = np.zeros(W)
    for c in channels:
        pw = (np.abs(x[:, :, OUTPUTS.index(c)] @ E.T) ** 2).max(axis=1)
        out += pw / max(float(np.median(pw)), 1e-300)
    return out


@dataclass
class RateOffset:
    channel: str
    offset_rad_s: float
    t_stat: float
    log10_p: float
    n_windows: int


def kinematic_rate_offsets(Y: np.ndarray, dt_s: float, available: np.ndarray,
                           trims: np.ndarray | None = None, start: int = 2) -> dict[str, RateOffset]:
    """Offsets between measured p, q and the Euler-angle kinematics, per window, tested over windows.

    Parameters
    ----------
    Y : array (W, L, 8), smoothed outputs u v w p q r theta phi (trim removed)
    dt_s : sample period (s)
    available : (8,) bool
    trims : (8,) output trims to add back (absolute angles and rates), or None for zeros
    start : samples ignored at each window edge (finite differences)

    Returns
    -------
    dict channel -> RateOffset for p and q (r needs heading, which the prepared data do not carry)
    """
    tr = np.zeros(8) if trims is None else np.asarray(trims, float)
    need = [3, 4, 5, 6, 7]
    if not all(available[c] for c in need):
        return {}
    y = Y + tr
    p, q, r, th, ph = (y[:, :, c] for c in (3, 4, 5, 6, 7))
    thd = np.gradient(th, dt_s, axis=1)
    phd = np.gradient(ph, dt_s, axis=1)
    e_q = thd - (q * np.cos(ph) - r * np.sin(ph))  # = -(b_q cos phi - b_r sin phi)
    e_p = phd - p - (q * np.sin(ph) + r * np.cos(ph)) * np.tan(th)  # = -b_p - ...
    out = {}
    for name, e in (("q", e_q), ("p", e_p)):
        m = -e[:, start:-start].mean(axis=1)  # per-window offset estimate (rad/s)
        n = m.shape[0]
        if n < 4:
            continue
        mu = float(m.mean())
        se = float(m.std(ddof=1) / np.sqrt(n))
        t = mu / se if se > 0 else 0.0
        logp = float(stats.t.logsf(abs(t), n - 1) / np.log(10) + np.log10(2))
        out[name] = RateOffset(name, mu, float(t), logp, n)
    return out


def native_rate_lines(gyro_rad_s: np.ndarray, dt_s: float, *, window_s: float = DiagnoseConfig.native_line_window_s,
                      min_hz: float = DiagnoseConfig.native_line_min_hz,
                      alpha: float = DiagnoseConfig.native_line_alpha) -> list[Line]:
    """Narrow lines in body rates sampled faster than the identification grid (the autopilot's own log).

    A rotor-frequency vibration sits at its true frequency here (below this rate's Nyquist) rather
    than folded onto the 50 Hz grid. Same statistics as :func:`spectral_lines`: the window-averaged
    periodogram against the median of neighbouring bins, significant by the chi-square law of the
    average (Bonferroni over bins and axes) and present in the median over windows too; bins below
    ``min_hz`` (the flown motion) are not tested.

    Parameters
    ----------
    gyro_rad_s : array (n, 3), body rates p q r (rad/s) at a uniform rate
    dt_s : float, their sample period (s)

    Returns
    -------
    list of Line (channels named p, q, r), strongest first; empty when too short for 4 windows
    """
    L = int(round(window_s / dt_s))
    W = gyro_rad_s.shape[0] // max(L, 1)
    if W < 4 or L < 16:
        return []
    x = np.asarray(gyro_rad_s[: W * L], dtype=float).reshape(W, L, 3)
    f, Pw = window_periodograms(x, dt_s)
    ratio, logp = _line_stats(Pw.mean(axis=0), W, nyquist_real=L % 2 == 0)
    ratio_med, _ = _line_stats(np.median(Pw, axis=0), W, nyquist_real=L % 2 == 0)
    z_med = (ratio_med - 1.0) * np.log(2.0) * np.sqrt(W)
    lo = max(3, int(np.ceil(min_hz / (f[1] - f[0]))))
    n_tests = max((len(f) - lo) * 3, 1)
    thr = np.log10(alpha / n_tests)
    sig = (logp < thr) & (z_med > stats.norm.isf(alpha / n_tests))
    sig[:lo] = False
    names = ("p", "q", "r")
    lines: list[Line] = []
    used = np.zeros(len(f), bool)
    for k in np.argsort(np.where(sig, logp, 0).min(axis=1)):
        if not sig[k].any() or used[max(0, k - 2):k + 3].any():
            continue
        used[k] = True
        fk = refine_frequency(x, dt_s, f[k], f[1] - f[0])
        chans = np.flatnonzero(sig[k])
        cmax = int(np.argmin(np.where(sig[k], logp[k], 0)))
        lines.append(Line(frequency_hz=float(fk), channels=[names[c] for c in chans], ratio=float(ratio[k, cmax]),
                          log10_p=float(logp[k, cmax] - thr + np.log10(alpha)),
                          amplitude={names[c]: sinusoid_amplitude(x[..., c], dt_s, fk) for c in chans}))
    return lines
