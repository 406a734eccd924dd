"""Closed-loop flights of the linear eq.-8 model with known truth (tests and the benchmark's fallback).

A stabilising LQR pilot (on the true state, so no noise feedback) plus a flight-test card that
excites one input after another (frequency sweeps and doublets), simulated exactly (ZOH) and
measured with white noise. Returns arrays in the conventions of :mod:`groundstation.dsp.prepare`:
``inputs (n, 4)``, ``outputs (n, 8)``. This is *our* model, so it only checks the estimator
against itself; the independent truth is the nonlinear simulator (``hil_replay.sim``).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_discrete_are

from groundstation.errors import SysidError
from groundstation.sysid.model import PARAM_NAMES, build_matrices, discretize

#: A plausible small-helicopter truth in the paper's naming (a_s acts on pitch via M_a, b_s on roll via L_b).
EXAMPLE_TRUTH: dict[str, float] = {
    "X_u": -0.12, "Y_v": -0.18, "M_u": 0.45, "M_v": 0.12, "M_q": -1.2, "M_a": 60.0, "M_b": 6.0,
    "L_u": -0.15, "L_v": -0.55, "L_p": -2.5, "L_a": -9.0, "L_b": 120.0, "k1": 0.12, "inv_tau_s": 12.0,
    "X_lat": -0.6, "Y_lon": 0.5, "M_lat": 1.5, "M_lon": -0.8, "L_lat": 0.6, "L_lon": 2.5,
    "A_lat": 4.0, "B_lon": 4.5,
    "Z_w": -0.8, "Z_r": 0.15, "N_w": 0.25, "N_r": -1.5, "k_r": 3.0,
    "Z_col": -25.0, "Z_ped": 1.2, "N_col": 3.5, "N_ped": 10.0,
}

#: Measurement noise std per output channel u v w (m/s), p q r (rad/s), theta phi (rad).
DEFAULT_NOISE = np.array([0.05, 0.05, 0.05, 0.01, 0.01, 0.01, 0.004, 0.004])

_HOR_OUT = ((0, 0), (1, 1), (5, 3), (4, 4), (2, 6), (3, 7))
_VER_OUT = ((0, 2), (1, 5))


def _card(n: int, dt_s: float, rng: np.random.Generator, amplitude: float) -> np.ndarray:
    """Excitation (n, 4): each input in turn gets a sweep 0.2-4 Hz and two doublets."""
    e = np.zeros((n, 4))
    part = n // 4
    for ch in range(4):
        a, b = ch * part, (ch + 1) * part
        m = b - a
        t = np.arange(m) * dt_s
        T = t[-1] if m > 1 else 1.0
        f0, f1 = 0.2, 4.0
        phase = 2 * np.pi * (f0 * t + (f1 - f0) * t ** 2 / (2 * T))
        sweep = np.sin(phase) * np.clip(np.minimum(t, T - t) / 1.0, 0, 1)
        e[a:b, ch] = amplitude * sweep * 0.8
        # doublets at 1/5 and 3/5 of the stretch
        w = max(1, int(round(0.5 / dt_s)))
        for frac in (0.2, 0.6):
            s0 = a + int(frac * m)
            e[s0:s0 + w, ch] += amplitude
            e[s0 + w:s0 + 2 * w, ch] -= amplitude
    e += 0.1 * amplitude * rng.standard_normal((n, 4))
    return e


def simulate_flight(theta: np.ndarray, duration_s: float = 60.0, dt_s: float = 0.02, *, seed: int = 0,
                    noise: np.ndarray | None = None, amplitude: float = 0.2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-loop flight of the true model ``theta (31,)``.

    Returns
    -------
    inputs (n, 4), outputs_true (n, 8), outputs_measured (n, 8)
    """
    rng = np.random.default_rng(seed)
    th = np.asarray(theta, dtype=float)
    if th.shape != (len(PARAM_NAMES),):
        raise SysidError("theta must have 31 entries")
    n = int(round(duration_s / dt_s))
    Ah, Bh, Av, Bv = build_matrices(th)
    exc = _card(n, dt_s, rng, amplitude)
    u_all = np.zeros((n, 4))
    y = np.zeros((n, 8))
    for (A, B, cols, meas, q) in ((Ah, Bh, (0, 1), _HOR_OUT, np.array([0.2, 0.2, 5, 5, 0.5, 0.5, 0.01, 0.01])),
                                  (Av, Bv, (2, 3), _VER_OUT, np.array([1.0, 2.0, 0.1]))):
        Ad, Bd = discretize(A, B, dt_s)
        R = np.eye(2) * 20.0
        P = solve_discrete_are(Ad, Bd, np.diag(q), R)
        K = np.linalg.solve(R + Bd.T @ P @ Bd, Bd.T @ P @ Ad)
        x = np.zeros(A.shape[0])
        for k in range(n):
            for s, o in meas:
                y[k, o] = x[s]
            uk = -K @ x + exc[k, list(cols)]
            u_all[k, list(cols)] = uk
            x = Ad @ x + Bd @ uk
    nz = DEFAULT_NOISE if noise is None else np.asarray(noise, dtype=float)
    ym = y + rng.standard_normal(y.shape) * nz
    return u_all, y, ym
