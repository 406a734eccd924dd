"""Tischler's frequency-response cost J, per input-output pair and averaged.

``J = 20/n * sum_k W_g(k) [W_mag (|T_c| - |T|)^2 + W_phase (angle T_c - angle T)^2]`` over the
pair's ``n`` coherent frequencies, magnitudes in dB and phases in degrees (the phase difference
wrapped into [-180, 180)), ``T`` the flight-data response and ``T_c`` the model's;
``W_g = (1.58 (1 - exp(-g2)))^2`` the coherence weighting, ``W_mag = 1``, ``W_phase = 0.01745``
(1 dB counts as much as 7.57 deg). Guidelines (Tischler & Remple): ``J_avg <= 100`` is a good
model, an individual pair ``J <= 200`` is acceptable; both are reported as pass/fail.

Array conventions: responses ``(..., n)`` complex, coherence ``(n,)``, mask ``(n,)`` bool; the
batched form takes a leading candidate dimension for the optimisers. Pure numpy.
"""

from __future__ import annotations

import numpy as np

W_MAG = 1.0
W_PHASE = 0.01745
J_AVG_GOOD = 100.0
J_PAIR_ACCEPTABLE = 200.0


def coherence_weight(coherence: np.ndarray) -> np.ndarray:
    """``W_g = (1.58 (1 - exp(-g2)))^2`` (about 1 at g2 = 1, 0.47 at g2 = 0.6)."""
    g2 = np.clip(np.nan_to_num(np.asarray(coherence, dtype=float)), 0.0, 1.0)
    return (1.58 * (1.0 - np.exp(-g2))) ** 2


def wrap_deg(x: np.ndarray) -> np.ndarray:
    return (np.asarray(x) + 180.0) % 360.0 - 180.0


def pair_residuals(model: np.ndarray, data: np.ndarray, coherence: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Weighted residuals ``(..., 2 n)`` whose sum of squares is J (magnitude part, phase part).

    model (..., N) and data (N,) complex responses; coherence (N,); mask (N,) the points used.
    A model response of exactly zero (no path) gives infinite residuals.
    """
    m = np.asarray(mask, dtype=bool)
    n = int(m.sum())
    if n == 0:
        return np.zeros(np.shape(model)[:-1] + (0,))
    Tc = np.asarray(model)[..., m]
    T = np.asarray(data)[m]
    scale = np.sqrt(20.0 / n * coherence_weight(np.asarray(coherence)[m]))
    with np.errstate(divide="ignore", invalid="ignore"):
        dmag = 20.0 * np.log10(np.abs(Tc)) - 20.0 * np.log10(np.abs(T))
    dph = wrap_deg(np.degrees(np.angle(Tc) - np.angle(T)))
    r = np.concatenate([np.sqrt(W_MAG) * scale * dmag, np.sqrt(W_PHASE) * scale * dph], axis=-1)
    return np.where(np.isfinite(r), r, np.inf)


def error_residuals(model: np.ndarray, data: np.ndarray, random_error: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Residuals ``(..., 2 n)`` weighted by each point's random error (the maximum-likelihood form).

    ``ln|T_c/T| / eps`` and ``angle(T_c/T) / eps`` (rad) over the ``n`` points of ``mask``:
    ``eps`` is the normalised random error of the composite (std of ``|T|/|T|``, and of the phase in
    rad), so each residual is in standard deviations of the flight data's estimate. Infinite where
    the model has no path.
    """
    m = np.asarray(mask, dtype=bool)
    Tc = np.asarray(model)[..., m]
    T = np.asarray(data)[m]
    w = 1.0 / np.asarray(random_error, dtype=float)[m]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = Tc / T
        r = np.concatenate([w * np.log(np.abs(ratio)), w * np.angle(ratio)], axis=-1)
    return np.where(np.isfinite(r), r, np.inf)


def tischler_cost(model: np.ndarray, data: np.ndarray, coherence: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """J of one pair (batched over the leading dimensions of ``model``); see the module docstring."""
    r = pair_residuals(model, data, coherence, mask)
    with np.errstate(over="ignore", invalid="ignore"):
        return np.sum(r ** 2, axis=-1)
