"""How long a hole of a lossy link the inputs may be bridged over, from the inputs and the rotor.

A hole in the input stream is bridged by a straight line between the samples on either side. The
line is wrong by what the input did inside the hole; the model sees that error through the rotor,
whose flapping follows the input as a first-order lag of time constant ``tau_s`` (eq. 8: the entry
``-1/tau_s``). The limit is the longest hole whose bridge puts no more error into what the rotor
follows than the input already carries where the rotor does not follow it:

* the input's power spectrum ``S(f)`` is measured on the flight (Welch, Hann windows of
  ``segment_s``, over the stretches without holes, at the source's own rate);
* the rotor splits it: ``W(f) = 1 / (1 + (2 pi f tau_s)^2)`` (the lag's power gain) is what it
  follows, ``1 - W(f)`` what it filters out;
* the mean square error of a straight line over a hole of length ``h`` (averaged over the hole) at
  frequency ``f`` is ``G(f, h) = mean_u |1 - (1 - u) e^{-i 2 pi f u h} - u e^{i 2 pi f (1 - u) h}|^2``;
* the limit of one input is the largest ``h`` with ``sum S W G <= sum S (1 - W)``; of the flight, the
  smallest over the inputs that move.

A fast, busy input (a flight controller's servo outputs) carries much above the rotor's band and
allows long bridges; a smooth stick input little, and allows short ones. The rotor is not identified
yet when the data are prepared, so ``1/tau_s`` is the fast end of the prior (nominal + one standard
deviation: the aircraft file's, else the wide prior's 10 + 6 = 16 /s): a faster rotor follows more of
the input and allows shorter bridges. Pure numpy: the logs are read and the in-air stretches chosen by
:mod:`groundstation.dsp.prepare`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = ["BridgeLimit", "bridge_limit", "input_spectrum"]

INPUTS = ("lat", "lon", "col", "ped")


@dataclass(frozen=True)
class BridgeLimit:
    """The derived limit (s), each moving input's own (s), and how much data said so."""

    limit_s: float | None                     # None: too little input without holes to measure it
    by_input_s: dict[str, float] = field(default_factory=dict)
    seconds_used: float = 0.0
    rotor_inv_tau_s: float = 16.0

    def to_json(self) -> dict[str, object]:
        return {"limit_s": self.limit_s, "by_input_s": dict(self.by_input_s),
                "seconds_used": round(self.seconds_used, 1), "rotor_inv_tau_s": self.rotor_inv_tau_s}


def input_spectrum(t_s: np.ndarray, x: np.ndarray, intervals: Sequence[tuple[float, float]], gap_s: float,
                   segment_s: float = 1.28) -> tuple[np.ndarray, np.ndarray, float]:
    """One-sided power spectrum (f (m,) Hz, S (m, k) units^2/Hz) of the inputs ``x (n, k)`` sampled at
    ``t_s (n,)``, over the parts of ``intervals`` without a hole longer than ``gap_s``; and the seconds used.

    Each stretch is put on its own uniform grid at the source's median interval; Welch segments of
    ``segment_s`` with half overlap, Hann window, the mean taken out of each."""
    t_s = np.asarray(t_s, dtype=float)
    x = np.asarray(x, dtype=float)
    d = np.diff(t_s)
    dt = float(np.median(d[d > 0])) if (d > 0).any() else float("nan")
    if not np.isfinite(dt):
        return np.zeros(0), np.zeros((0, x.shape[1])), 0.0
    n_seg = max(16, int(round(segment_s / dt)))
    win = np.hanning(n_seg)
    scale = 1.0 / (np.sum(win ** 2) / dt)         # |FFT|^2 -> density (units^2/Hz)
    acc = np.zeros((n_seg // 2 + 1, x.shape[1]))
    count = 0
    used = 0.0
    ok = np.isfinite(x).all(axis=1)
    for a, b in intervals:
        sel = (t_s >= a) & (t_s <= b) & ok
        ts, xs = t_s[sel], x[sel]
        if ts.size < n_seg:
            continue
        dd = np.diff(ts)
        cut = np.flatnonzero((dd > gap_s) | (dd <= 0)) + 1      # holes, and the clock going back (FC reboot)
        for i, j in zip(np.r_[0, cut], np.r_[cut, ts.size], strict=True):
            if (ts[j - 1] - ts[i]) < n_seg * dt:
                continue
            grid = np.arange(ts[i], ts[j - 1], dt)
            xg = np.stack([np.interp(grid, ts[i:j], xs[i:j, k]) for k in range(x.shape[1])], axis=1)
            used += grid.size * dt
            for s in range(0, grid.size - n_seg + 1, n_seg // 2):
                seg = xg[s:s + n_seg]
                seg = (seg - seg.mean(axis=0)) * win[:, None]
                acc += np.abs(np.fft.rfft(seg, axis=0)) ** 2
                count += 1
    if count == 0:
        return np.zeros(0), np.zeros((0, x.shape[1])), 0.0
    psd = acc * scale / count
    psd[1:-1] *= 2.0                                # one-sided
    return np.fft.rfftfreq(n_seg, dt), psd, used


def _line_error_gain(f_hz: np.ndarray, h_s: np.ndarray, points: int = 9) -> np.ndarray:
    """(len(h), len(f)) mean square error of a straight line over a hole of length h, per unit power at f."""
    u = (np.arange(points) + 0.5) / points
    w = 2j * np.pi * f_hz[None, :, None] * h_s[:, None, None]
    e = 1.0 - (1.0 - u) * np.exp(-w * u) - u * np.exp(w * (1.0 - u))
    return np.mean(np.abs(e) ** 2, axis=2)


def bridge_limit(t_s: np.ndarray, x: np.ndarray, intervals: Sequence[tuple[float, float]], gap_s: float,
                 rotor_inv_tau_s: float, *, min_seconds: float = 10.0, longest_s: float = 1.0,
                 still: float = 1e-3, names: Sequence[str] = INPUTS) -> BridgeLimit:
    """The bridge limit of the inputs ``x (n, k)`` (normalised units) at ``t_s`` in ``intervals`` (see the
    module docstring); ``limit_s`` None with less than ``min_seconds`` of input without holes. An input
    whose standard deviation is below ``still`` does not move and does not limit."""
    f, psd, used = input_spectrum(t_s, x, intervals, gap_s)
    if used < min_seconds or f.size < 3:
        return BridgeLimit(None, {}, used, rotor_inv_tau_s)
    df = float(f[1] - f[0])
    rotor = 1.0 / (1.0 + (2.0 * np.pi * f / rotor_inv_tau_s) ** 2)
    dt = 1.0 / (2.0 * f[-1])
    h = np.arange(2.0 * dt, longest_s + 1e-9, dt)
    gain = _line_error_gain(f, h)                                    # (H, F)
    by: dict[str, float] = {}
    for k, name in enumerate(names):
        s = psd[:, k]
        if np.sqrt(np.sum(s) * df) < still:
            continue
        floor = float(np.sum(s * (1.0 - rotor)) * df)
        err = gain @ (s * rotor) * df                                # (H,)
        over = np.flatnonzero(err > floor)
        by[name] = round(float(h[over[0] - 1] if over.size and over[0] > 0 else (dt if over.size else h[-1])), 3)
    limit = min(by.values()) if by else None
    return BridgeLimit(limit, by, used, rotor_inv_tau_s)
