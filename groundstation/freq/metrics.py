"""Handling-qualities figures from frequency responses: equivalent delay, ADS-33 bandwidth, bands
where model and data differ beyond the random error.

* :func:`phase_slope_delay` - the time delay ``tau`` that best explains the phase of the data
  relative to a reference (the model) as ``-w tau``, fitted on the unit circle
  (``sum w |exp(j dphi) - exp(-j w tau)|^2``, so phase wrapping cannot bias it), weighted by the
  inverse phase variance ``1 / eps^2``; its standard error from the same weights.
* :func:`attitude_bandwidth` - ADS-33 bandwidth of an attitude response: the phase bandwidth
  (phase -135 deg), the gain bandwidth (gain 6 dB above the gain at the -180 deg crossing) and
  the phase delay ``tau_p = -(phase(2 w180) + 180) / (57.3 * 2 w180)``; the response is sign-corrected
  so its low-frequency phase lies in (-180, 0]. Figures beyond the frequencies given are ``None``.
* :func:`deviation_bands` - contiguous frequency bands where ``|H_model - H_data| / (eps |H_data|)``
  exceeds the 95 % bound of a complex normal error (``sqrt(chi2_2(0.95)) = 2.45``).

Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: 95 % bound of |complex error| / (its per-component std): sqrt(chi-square(2 dof) 0.95 quantile).
Z95_COMPLEX = float(np.sqrt(-2.0 * np.log(0.05)))


@dataclass(frozen=True)
class DelayEstimate:
    delay_s: float
    std_s: float
    points: int


def phase_slope_delay(f_hz: np.ndarray, data: np.ndarray, reference: np.ndarray, random_error: np.ndarray,
                      mask: np.ndarray, max_delay_s: float = 0.5) -> DelayEstimate | None:
    """Equivalent delay of ``data`` relative to ``reference`` over the ``mask`` points (None if < 3)."""
    m = np.asarray(mask, bool) & np.isfinite(data) & np.isfinite(reference) & (np.abs(reference) > 0)
    if m.sum() < 3:
        return None
    w_rad = 2.0 * np.pi * np.asarray(f_hz)[m]
    rot = (data[m] / reference[m])
    rot = rot / np.abs(rot)
    var = np.maximum(np.asarray(random_error)[m], 1e-3) ** 2
    wt = 1.0 / var
    # coarse grid wide enough for the slowest point to wrap at most once per step, then refine
    step = min(0.25 / w_rad.max(), 0.005)
    taus = np.arange(-max_delay_s, max_delay_s + step, step)
    score = (wt * np.real(rot[None, :] * np.exp(1j * w_rad[None, :] * taus[:, None]))).sum(axis=1)
    tau = float(taus[int(np.argmax(score))])
    for _ in range(3):  # Gauss-Newton on the phase residual around the coarse optimum
        r = np.angle(rot * np.exp(1j * w_rad * tau))
        tau -= float((wt * w_rad * r).sum() / (wt * w_rad ** 2).sum())
    std = float(1.0 / np.sqrt((wt * w_rad ** 2).sum()))
    return DelayEstimate(delay_s=tau, std_s=std, points=int(m.sum()))


@dataclass(frozen=True)
class Bandwidth:
    bandwidth_hz: float | None
    phase_bandwidth_hz: float | None
    gain_bandwidth_hz: float | None
    f180_hz: float | None
    phase_delay_s: float | None
    note: str = ""


def _crossing(f: np.ndarray, y: np.ndarray, level: float) -> float | None:
    """First frequency where y falls through ``level`` (linear in log f), None if it never does."""
    below = y <= level
    if not below.any():
        return None
    k = int(np.argmax(below))
    if k == 0:
        return float(f[0]) if y[0] == level else None
    lf = np.log(f[k - 1:k + 1])
    frac = (y[k - 1] - level) / (y[k - 1] - y[k])
    return float(np.exp(lf[0] + frac * (lf[1] - lf[0])))


def attitude_bandwidth(f_hz: np.ndarray, response: np.ndarray, mask: np.ndarray | None = None) -> Bandwidth:
    """ADS-33 bandwidth and phase delay of an attitude response over the ``mask`` points."""
    m = np.isfinite(response) & (np.abs(response) > 0)
    if mask is not None:
        m &= np.asarray(mask, bool)
    if m.sum() < 3:
        return Bandwidth(None, None, None, None, None, "fewer than 3 usable points")
    f = np.asarray(f_hz)[m]
    H = np.asarray(response)[m]
    ph = np.degrees(np.unwrap(np.angle(H)))
    # sign-correct and shift by whole turns so the lowest-frequency phase lies in (-180, 0]
    ph = ph - 180.0 * np.ceil(ph[0] / 180.0)
    gain = 20.0 * np.log10(np.abs(H))
    f135 = _crossing(f, ph, -135.0)
    f180 = _crossing(f, ph, -180.0)
    fgain = None
    tau_p = None
    note = ""
    if f180 is not None:
        g180 = float(np.interp(np.log(f180), np.log(f), gain))
        fgain = _crossing(f, gain, g180 + 6.0)
        if 2 * f180 <= f[-1]:
            ph2 = float(np.interp(np.log(2 * f180), np.log(f), ph))
            tau_p = -(ph2 + 180.0) / (360.0 * 2 * f180)
        else:
            note = f"2 x f180 ({2 * f180:.2f} Hz) beyond the last point ({f[-1]:.2f} Hz): no phase delay"
    else:
        note = f"phase never reaches -180 deg up to {f[-1]:.2f} Hz: gain bandwidth and phase delay unknown"
    bws = [b for b in (f135, fgain) if b is not None]
    return Bandwidth(min(bws) if bws else None, f135, fgain, f180, tau_p, note)


@dataclass(frozen=True)
class DeviationBand:
    f_lo_hz: float
    f_hi_hz: float
    points: int
    magnitude_db: float  # mean model minus data, dB
    phase_deg: float  # mean model minus data, deg
    max_ratio: float  # largest |H_model - H_data| / (eps |H_data|)


def deviation_bands(f_hz: np.ndarray, data: np.ndarray, model: np.ndarray, random_error: np.ndarray,
                    mask: np.ndarray, min_points: int = 2) -> list[DeviationBand]:
    """Bands of at least ``min_points`` adjacent coherent points where the model leaves the 95 % bound."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.abs(model - data) / (np.asarray(random_error) * np.abs(data))
    bad = np.asarray(mask, bool) & np.isfinite(ratio) & (ratio > Z95_COMPLEX)
    out = []
    k = 0
    n = bad.size
    while k < n:
        if not bad[k]:
            k += 1
            continue
        e = k
        while e + 1 < n and bad[e + 1]:
            e += 1
        if e - k + 1 >= min_points:
            sl = slice(k, e + 1)
            dmag = 20 * np.log10(np.abs(model[sl]) / np.abs(data[sl]))
            dph = (np.degrees(np.angle(model[sl] / data[sl])) + 180.0) % 360.0 - 180.0
            out.append(DeviationBand(float(f_hz[k]), float(f_hz[e]), e - k + 1, float(np.mean(dmag)),
                                     float(np.mean(dph)), float(np.max(ratio[sl]))))
        k = e + 1
    return out
