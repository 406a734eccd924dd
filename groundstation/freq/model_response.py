"""Frequency responses of the eq.-8 hover model, batched over parameter vectors.

``model_response(theta, f_hz, dt_s=None, delays_s=None) -> G`` with ``theta (..., 31)`` and
``G (..., n_freq, 8, 4)`` complex: output ``u v w p q r theta phi`` per input ``lat lon col ped``
(normalised units). Pairs across the two subsystems are exactly zero (the model has no path).

``dt_s`` given: the exact zero-order-hold discrete model at that sample interval,
``C (z I - Ad)^-1 Bd`` at ``z = exp(j 2 pi f dt)`` - what the time-domain identification simulates
and what sampled flight data measure (a held input adds about half a sample of phase lag: 14 deg at
4 Hz on the 50 Hz grid). ``dt_s=None``: the continuous model ``C (j w I - A)^-1 B``. ``delays_s (4,)``
(or ``(..., 4)``): a pure transport delay per input, ``exp(-j w tau)``. Augmentations of a model file
(``{"name": "input_delay", "input": "lon", "delay_s": 0.1}``) map to ``delays_s`` with
:func:`delays_from_augmentations`.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from groundstation.sysid.model import INPUTS, OUTPUTS, build_matrices, discretize

#: (state index, output index) of the horizontal states measured: u v p q theta phi.
_HOR_OUT = ((0, 0), (1, 1), (5, 3), (4, 4), (2, 6), (3, 7))
#: (state index, output index) of the vertical states measured: w r.
_VER_OUT = ((0, 2), (1, 5))


def _subsystem(A: np.ndarray, B: np.ndarray, s_or_z: np.ndarray, dt_s: float | None) -> np.ndarray:
    """(..., nf, n_states, n_inputs) state responses of one subsystem."""
    if dt_s is not None:
        A, B = discretize(A, B, dt_s)
    n = A.shape[-1]
    M = s_or_z[:, None, None] * np.eye(n) - A[..., None, :, :]  # (..., nf, n, n)
    with np.errstate(all="ignore"):
        try:
            return np.linalg.solve(M, np.broadcast_to(B[..., None, :, :], M.shape[:-1] + (B.shape[-1],)))
        except np.linalg.LinAlgError:
            out = np.full(M.shape[:-1] + (B.shape[-1],), np.nan, dtype=complex)
            flat_M = M.reshape((-1, n, n))
            flat_B = np.broadcast_to(B[..., None, :, :], M.shape[:-1] + (B.shape[-1],)).reshape((-1, n, B.shape[-1]))
            flat_o = out.reshape((-1, n, B.shape[-1]))
            for k in range(flat_M.shape[0]):
                try:
                    flat_o[k] = np.linalg.solve(flat_M[k], flat_B[k])
                except np.linalg.LinAlgError:
                    pass
            return out


def model_response(theta: np.ndarray, f_hz: np.ndarray, dt_s: float | None = None,
                   delays_s: np.ndarray | None = None) -> np.ndarray:
    """Model frequency responses ``(..., n_freq, 8, 4)``; see the module docstring."""
    th = np.asarray(theta, dtype=float)
    f = np.asarray(f_hz, dtype=float)
    w = 2.0 * np.pi * f
    s_or_z = np.exp(1j * w * dt_s) if dt_s is not None else 1j * w
    Ah, Bh, Av, Bv = build_matrices(th)
    Gh = _subsystem(Ah, Bh, s_or_z, dt_s)
    Gv = _subsystem(Av, Bv, s_or_z, dt_s)
    G = np.zeros(th.shape[:-1] + (f.size, 8, 4), dtype=complex)
    for s, o in _HOR_OUT:
        G[..., o, 0:2] = Gh[..., s, :]
    for s, o in _VER_OUT:
        G[..., o, 2:4] = Gv[..., s, :]
    if delays_s is not None:
        d = np.asarray(delays_s, dtype=float)
        G = G * np.exp(-1j * w[:, None] * d[..., None, :])[..., :, None, :]
    return G


def delays_from_augmentations(augmentations: Iterable[dict[str, Any]]) -> np.ndarray:
    """Per-input delay (4,) in s from a model file's ``augmentations`` (``input_delay`` entries)."""
    d = np.zeros(4)
    for a in augmentations:
        name = a.get("name", a.get("effect"))
        if name != "input_delay":
            continue
        inp = a.get("input")
        est = a.get("estimate", a)
        delay = est.get("delay_s", a.get("delay_s"))
        if inp in INPUTS and delay is not None:
            d[INPUTS.index(inp)] = float(delay)
    return d


def has_path(inp: str, out: str) -> bool:
    """Whether the model structure connects ``inp`` to ``out`` at all (same subsystem)."""
    i, j = INPUTS.index(inp), OUTPUTS.index(out)
    hor_out = {o for _, o in _HOR_OUT}
    return (i < 2) == (j in hor_out)
