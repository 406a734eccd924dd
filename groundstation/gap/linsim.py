"""Windowed output-error simulation of the eq.-8 hover model with the extras a diagnosis needs.

Why a variant of ``groundstation.sysid.simulate.simulate_windows``: hypotheses need (a) extra
forcing columns entering the u, v, w rows (drag, ground effect, air-mass motion), (b) per-window
nuisance columns estimated together with the unmeasured initial states, and (c) the same code for a
batch of parameter vectors (finite-difference Jacobians in one pass). It calls
:func:`groundstation.sysid.model.discretize` and :func:`~groundstation.sysid.model.build_matrices`
and nothing else from sysid.

Array conventions
-----------------
* ``theta`` (C, 31) parameter vectors (C candidates), order of ``model.PARAM_NAMES``.
* ``inputs`` (W, L, 4) lat lon col ped (normalised, trim removed), W windows of L samples.
* ``outputs`` (W, L, 8) u v w p q r theta phi (trim removed), used for the initial states.
* ``forcing`` (W, L, 11) optional state-derivative forcing (SI units per second) on every state.
* returns ``yhat`` (C, W, L, 8).

The full state is ``u v theta phi q p a_s b_s w r r_fb`` (horizontal then vertical block).
Measured initial states come from ``outputs[:, 0]``; a_s, b_s, r_fb and any unavailable channel's
state are estimated per window by weighted least squares (the outputs are linear in them).
"""

from __future__ import annotations

import numpy as np

from groundstation.sysid.model import build_matrices, discretize

N_STATES = 11
#: state index of each output channel (u v w p q r theta phi)
OUT_STATE = np.array([0, 1, 8, 5, 4, 9, 2, 3])
UNMEASURED = (6, 7, 10)


def full_matrices(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Block-diagonal continuous A (C, 11, 11) and B (C, 11, 15): 4 inputs then 11 forcing columns."""
    th = np.atleast_2d(np.asarray(theta, dtype=float))
    Ah, Bh, Av, Bv = build_matrices(th)
    C = th.shape[0]
    A = np.zeros((C, N_STATES, N_STATES))
    B = np.zeros((C, N_STATES, 4 + N_STATES))
    A[:, :8, :8] = Ah
    A[:, 8:, 8:] = Av
    B[:, :8, 0:2] = Bh
    B[:, 8:, 2:4] = Bv
    B[:, :, 4:] = np.eye(N_STATES)
    return A, B


def simulate(
    theta: np.ndarray,
    inputs: np.ndarray,
    outputs: np.ndarray,
    dt_s: float,
    *,
    forcing: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    available: np.ndarray | None = None,
    nuisance: np.ndarray | None = None,
    start: int = 0,
    stop: int | None = None,
    fit_initial: bool = True,
    all_initial: bool = True,
    return_coef: bool = False,
    fit_mask: np.ndarray | None = None,
    nuisance_prec: np.ndarray | None = None,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Simulate windows for a batch of parameter vectors.

    Parameters
    ----------
    theta : array (C, 31) or (31,)
    inputs : array (W, L, 4), normalised inputs
    outputs : array (W, L, 8), measured outputs (initial states and the LS target)
    dt_s : float, sample period (s)
    forcing : array (W, L, 11) or None, state-derivative forcing added to every state row
    weights : array (8,) or None, per-channel weights (1/scale) of the initial-state least squares
    available : array (8,) bool or None, measured channels (others are estimated, not copied)
    nuisance : array (W, L, 8, K) or None, extra per-window output columns estimated with the
        unmeasured initial states (e.g. disturbance responses)
    start, stop : int, the least squares uses samples ``start:stop`` of each window
    fit_initial : bool, False: measured initial states only, unknown ones zero, no least squares
    all_initial : bool, True: every initial state is fitted (the measured value is only the
        starting point), so that sensor noise at the window start does not seed a divergence

    Returns
    -------
    yhat : array (C, W, L, 8); NaN for a candidate whose simulation runs away (an unstable
        parameter vector whose states overflow within a window): callers reject non-finite costs
    coef : array (C, W, n_unknown + K), only with ``return_coef``: fitted initial-state corrections
        then the K nuisance coefficients
    """
    th = np.atleast_2d(np.asarray(theta, dtype=float))
    Wn, L, _ = inputs.shape
    avail = np.ones(8, bool) if available is None else np.asarray(available, bool)
    w8 = np.ones(8) if weights is None else np.asarray(weights, float)
    w8 = np.where(avail, w8, 0.0)
    A, B = full_matrices(th)
    Ad, Bd = discretize(A, B, dt_s)  # (C,11,11), (C,11,15)
    C = th.shape[0]
    u_all = inputs if forcing is None else np.concatenate([inputs, forcing], axis=2)
    Bd_use = Bd[:, :, : u_all.shape[2]]
    AdT = np.swapaxes(Ad, 1, 2)
    BdT = np.swapaxes(Bd_use, 1, 2)
    # unknown initial states: unmeasured ones and unavailable channels
    unknown = list(UNMEASURED) + [int(OUT_STATE[c]) for c in range(8) if not avail[c] or all_initial]
    nu = len(unknown)
    x = np.zeros((C, Wn, N_STATES))
    x[:, :, OUT_STATE[avail]] = outputs[None, :, 0, avail]
    # free responses of the unknown initial states: (C, nu, 11) propagated alongside
    e = np.zeros((C, nu, N_STATES))
    for j, s in enumerate(unknown):
        e[:, j, s] = 1.0
    forced_u = np.einsum("wlm,cmn->lcwn", u_all, BdT, optimize=True)  # (L, C, W, 11)
    ys = np.empty((L, C, Wn, N_STATES))
    fs = np.empty((L, C, nu, N_STATES))
    # an unstable candidate (a search or a Levenberg-Marquardt trial step) can overflow within a
    # window: it is simulated without warnings, zeroed for the least squares and returned as NaN
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(L):
            ys[k] = x
            fs[k] = e
            x = np.matmul(x, AdT) + forced_u[k]
            e = np.matmul(e, AdT)
    runaway = ~(np.isfinite(ys).all(axis=(0, 2, 3)) & np.isfinite(fs).all(axis=(0, 2, 3))
                & (np.abs(ys).max(axis=(0, 2, 3), initial=0.0) < 1e150))
    if runaway.any():
        ys[:, runaway] = 0.0
        fs[:, runaway] = 0.0
    yhat = np.moveaxis(ys[..., OUT_STATE], 0, 2)  # (C, W, L, 8)
    if not fit_initial:
        if runaway.any():
            yhat[runaway] = np.nan
        return yhat
    S = np.moveaxis(fs[..., OUT_STATE], 0, 2)  # (C, nu, L, 8): the same in every window
    r = outputs[None] - yhat  # (C, W, L, 8)
    sel = slice(start, stop) if fit_mask is None else np.flatnonzero(fit_mask)
    # normal equations in blocks: the free responses S do not depend on the window, so their Gram
    # matrix is formed once and never broadcast over the windows (the nuisance columns do)
    Sw = (S[:, :, sel, :] * w8).reshape(C, nu, -1)  # (C, nu, n)
    rw = (r[:, :, sel, :] * w8).reshape(C, Wn, -1)  # (C, W, n)
    Gss = np.einsum("cil,cjl->cij", Sw, Sw)
    hs = np.einsum("cil,cwl->cwi", Sw, rw)
    if nuisance is None:
        G = np.broadcast_to(Gss[:, None], (C, Wn, nu, nu))
        h = hs
    else:
        K = nuisance.shape[-1]
        Nw = (np.moveaxis(nuisance, 3, 1)[:, :, sel, :] * w8).reshape(Wn, K, -1)  # (W, K, n)
        Gsn = np.einsum("cil,wkl->cwik", Sw, Nw)
        Gnn = np.einsum("wkl,wml->wkm", Nw, Nw)
        G = np.empty((C, Wn, nu + K, nu + K))
        G[:, :, :nu, :nu] = Gss[:, None]
        G[:, :, :nu, nu:] = Gsn
        G[:, :, nu:, :nu] = np.swapaxes(Gsn, 2, 3)
        G[:, :, nu:, nu:] = Gnn[None]
        h = np.concatenate([hs, np.einsum("wkl,cwl->cwk", Nw, rw)], axis=2)
    ridge = 1e-9 * np.trace(G, axis1=2, axis2=3)[..., None, None] / G.shape[-1] + 1e-12
    Gr = G + ridge * np.eye(G.shape[-1])
    if nuisance is not None and nuisance_prec is not None:
        idx = np.arange(G.shape[-1] - K, G.shape[-1])
        Gr[..., idx, idx] += np.asarray(nuisance_prec, float)
    a = np.linalg.solve(Gr, h[..., None])[..., 0]
    yhat = yhat + np.einsum("cwi,cilk->cwlk", a[..., :nu], S)
    if nuisance is not None:
        yhat = yhat + np.einsum("cwk,wlmk->cwlm", a[..., nu:], nuisance)
    if runaway.any():
        yhat[runaway] = np.nan
    if return_coef:
        return yhat, a
    return yhat
