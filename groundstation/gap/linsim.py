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

from dataclasses import dataclass

import numpy as np

from groundstation.sysid.model import N_PARAMS, build_matrices, discretize

N_STATES = 11
#: state index of each output channel (u v w p q r theta phi)
OUT_STATE = np.array([0, 1, 8, 5, 4, 9, 2, 3])
UNMEASURED = (6, 7, 10)


@dataclass(frozen=True)
class Block:
    """One of the model's two uncoupled subsystems: its ``states`` (of the 11), the output channels it
    drives (of the 8, in channel order) and the inputs that enter it (of the 4). A parameter of one
    block leaves the other block's outputs unchanged: a finite-difference Jacobian simulates only the
    block it perturbs (:func:`simulate` with ``block``)."""

    states: tuple[int, ...]
    outputs: tuple[int, ...]
    inputs: tuple[int, ...]


HORIZONTAL = Block(states=tuple(range(8)), outputs=(0, 1, 3, 4, 6, 7), inputs=(0, 1))
VERTICAL = Block(states=(8, 9, 10), outputs=(2, 5), inputs=(2, 3))


def _param_blocks() -> tuple[np.ndarray, np.ndarray]:
    """Indices of the parameters in the horizontal block's matrices and of those in the vertical's
    (read off :func:`groundstation.sysid.model.build_matrices`; no parameter is in both)."""
    th = 1.0 + np.arange(N_PARAMS, dtype=float)
    base = build_matrices(th)
    bumped = build_matrices(th + 0.5 * np.eye(N_PARAMS))
    moves = [np.array([not np.array_equal(bumped[k][i], base[k]) for i in range(N_PARAMS)]) for k in range(4)]
    hor, ver = moves[0] | moves[1], moves[2] | moves[3]
    if (hor & ver).any():
        raise AssertionError("a parameter enters both subsystems")
    return np.flatnonzero(hor), np.flatnonzero(ver)


#: the parameters of :data:`HORIZONTAL` and those of :data:`VERTICAL` (indices into theta)
PARAM_BLOCKS = _param_blocks()


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


#: time-lifting block (samples): the block-start states come from a recursion over L / LIFT_BLOCK
#: blocks and every output sample from one product per candidate (see :func:`_lifted_outputs`)
LIFT_BLOCK = 10
#: windows are simulated in chunks of about this many bytes of output per candidate batch, so that
#: product, residual and least squares stay in cache and a large batch of variants needs no
#: multi-hundred-megabyte temporaries
CHUNK_BYTES = 4e6


def _lift(Ad: np.ndarray, Bd: np.ndarray, b: int, nb: int, out_state: np.ndarray = OUT_STATE):
    """Lifted maps of blocks of ``b`` samples, per candidate.

    Returns ``AbT`` (C, 11, 11) = (A^b)^T; ``CbT`` (C, b m, 11): block input-to-state map transposed
    (row ``(l, input)``: ``(A^(b-1-l) B)^T``); ``TT`` (C, b m, b 8): block-Toeplitz Markov parameters
    transposed (``y_j = sum_{l<j} C A^(j-1-l) B u_l``); ``ObT`` (C, 11, b 8): ``(C A^j)^T``;
    ``Phi`` (C, nb b, 8, 11): free response ``C A^t`` of every initial state at every sample (of a
    block: its outputs and states, ``out_state`` each output's state among ``Ad``'s).
    """
    C, n, m = Bd.shape
    pw = [np.broadcast_to(np.eye(n), (C, n, n)), Ad]
    for _ in range(b - 1):
        pw.append(np.matmul(Ad, pw[-1]))
    Apow = np.stack(pw, axis=1)  # (C, b+1, n, n)
    AB = np.matmul(Apow[:, :b], Bd[:, None])  # (C, b, n, m): A^q B
    Cb = AB[:, ::-1].transpose(0, 2, 1, 3).reshape(C, n, b * m)  # column block l: A^(b-1-l) B
    ny = len(out_state)
    CAB = np.concatenate([AB[:, :, out_state, :], np.zeros((C, 1, ny, m))], axis=1)  # (C, b+1, 8, m)
    jj, ll = np.meshgrid(np.arange(b), np.arange(b), indexing="ij")
    Tq = CAB[:, np.where(ll < jj, jj - 1 - ll, b)]  # (C, b(j), b(l), 8, m)
    TT = np.ascontiguousarray(Tq.transpose(0, 2, 4, 1, 3).reshape(C, b * m, b * ny))
    Ob = Apow[:, :b][:, :, out_state, :]  # (C, b, 8, n): C A^j
    ObT = np.ascontiguousarray(Ob.reshape(C, b * ny, n).transpose(0, 2, 1))
    # free responses C A^j (A^b)^i at t = i b + j
    Abp = [np.broadcast_to(np.eye(n), (C, n, n))]
    for _ in range(nb - 1):
        Abp.append(np.matmul(Abp[-1], Apow[:, b]))
    Phi = np.matmul(Ob.reshape(C, 1, b * ny, n), np.stack(Abp, axis=1)).reshape(C, nb * b, ny, n)
    return np.swapaxes(Apow[:, b], 1, 2), np.swapaxes(Cb, 1, 2), TT, ObT, Phi


def _lifted_outputs(x0: np.ndarray, u: np.ndarray, AbT: np.ndarray, CbT: np.ndarray, TT: np.ndarray,
                    ObT: np.ndarray, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Outputs (C, W, nb b, 8) of ``x[k+1] = A x[k] + B u[k]``, ``y[k] = x[k][OUT_STATE]`` from ``x0``
    (C, W, 11) and inputs ``u`` (W, nb b, m) (zero-padded to whole blocks), by time lifting: the
    block-start states ``x_(i+1) = A^b x_i + Cb U_i`` (nb - 1 small steps) and then every sample of every
    block ``Y_i = Ob x_i + T U_i`` in two products. The same numbers as stepping sample by sample, up to
    round-off. Also returns the block-start states (C, W, nb, 11) (for the runaway check)."""
    C, W, n = x0.shape
    nb = u.shape[1] // b
    Ub = u.reshape(W * nb, -1)  # rows (window, block), columns (sample in block, input)
    UC = np.matmul(Ub, CbT).reshape(C, W, nb, n)  # block input contributions to the next block start
    xs = np.empty((C, W, nb, n))
    xs[:, :, 0] = x0
    for i in range(nb - 1):
        xs[:, :, i + 1] = np.matmul(xs[:, :, i], AbT) + UC[:, :, i]
    Y = np.matmul(Ub, TT)  # (C, W nb, b 8)
    Y += np.matmul(xs.reshape(C, W * nb, n), ObT)
    return Y.reshape(C, W, nb * b, -1), xs


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
    block: Block | None = None,
    ridge_extra: tuple[float, int] | None = None,
    gram: dict | None = None,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Simulate windows for a batch of parameter vectors.

    Parameters
    ----------
    theta : array (C, 31) or (31,)
    inputs : array (W, L, 4), normalised inputs
    outputs : array (W, L, 8), measured outputs (initial states and the LS target); or (W0, L, 8)
        with W0 dividing W: window w's are ``outputs[w % W0]`` (input variants of the same windows)
    dt_s : float, sample period (s)
    forcing : array (W, L, 11) or None, state-derivative forcing added to every state row
    weights : array (8,) or None, per-channel weights (1/scale) of the initial-state least squares
    available : array (8,) bool or None, measured channels (others are estimated, not copied)
    nuisance : array (W, L, 8, K) or None, extra per-window output columns estimated with the
        unmeasured initial states (e.g. disturbance responses); (1, L, 8, K): the same columns in every
        window (one normal matrix per candidate)
    start, stop : int, the least squares uses samples ``start:stop`` of each window
    fit_initial : bool, False: measured initial states only, unknown ones zero, no least squares
    all_initial : bool, True: every initial state is fitted (the measured value is only the
        starting point), so that sensor noise at the window start does not seed a divergence
    block : :data:`HORIZONTAL` or :data:`VERTICAL`: that subsystem alone (its states, inputs and
        forcing; ``yhat`` and ``coef`` then hold its output channels and unknown states only)
    ridge_extra : (trace, count) of the unknowns outside this block (the other block's initial states,
        nuisance columns that only the other block's outputs see): the least squares' ridge is then
        relative to the whole model's, as in a simulation of both blocks (no per-window nuisance)
    gram : a dict that receives ``unknown`` (the unknown initial states, indices of the 11), ``diag``
        (C, n_unknown), the diagonal of the initial states' normal matrix, and with nuisance columns
        shared by every window ``nuisance_diag`` (K,), theirs (the traces set the ridge)

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
    out_state, unmeasured = OUT_STATE, UNMEASURED
    if block is not None:
        A, B, inputs, forcing, outputs, avail, w8, nuisance, out_state, unmeasured = _restrict(
            block, A, B, inputs, forcing, outputs, avail, w8, nuisance)
    nx, ny = A.shape[1], len(out_state)
    Ad, Bd = discretize(A, B, dt_s)  # (C,11,11), (C,11,15)
    C = th.shape[0]
    u_all = inputs if forcing is None else np.concatenate([inputs, forcing], axis=2)
    m = u_all.shape[2]
    b = max(1, min(LIFT_BLOCK, L))
    nb = -(-L // b)
    up = np.zeros((Wn, nb * b, m))
    up[:, :L] = u_all
    # unknown initial states: unmeasured ones and unavailable channels
    unknown = list(unmeasured) + [int(out_state[c]) for c in range(ny) if not avail[c] or all_initial]
    nu = len(unknown)
    W0 = outputs.shape[0]
    if Wn % W0:
        raise ValueError(f"outputs: {W0} windows do not divide the inputs' {Wn}")
    x0 = np.zeros((Wn, nx))
    x0[:, out_state[avail]] = np.tile(outputs[:, 0, avail], (Wn // W0, 1))
    yhat = np.empty((C, Wn, L, ny))
    runaway = np.zeros(C, bool)
    # an unstable candidate (a search or a Levenberg-Marquardt trial step) can overflow within a
    # window: it is simulated without warnings, zeroed for the least squares and returned as NaN
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        AbT, CbT, TT, ObT, Phi = _lift(Ad, Bd[:, :, :m], b, nb, out_state)
        S = np.ascontiguousarray(np.moveaxis(Phi[:, :L, :, unknown], 3, 1))  # (C, nu, L, 8), every window
        # a NaN propagates through max and fails the comparison like an overflow does
        runaway |= ~(np.abs(S).max(axis=(1, 2, 3), initial=0.0) < 1e150)
        wc = max(1, min(Wn, int(CHUNK_BYTES // (8 * C * L * 8))))
        for w0 in range(0, Wn, wc):
            w1 = min(Wn, w0 + wc)
            y, xs = _lifted_outputs(np.broadcast_to(x0[None, w0:w1], (C, w1 - w0, nx)), up[w0:w1],
                                    AbT, CbT, TT, ObT, b)
            yhat[:, w0:w1] = y[:, :, :L]
            runaway |= ~((np.abs(y).max(axis=(1, 2, 3), initial=0.0) < 1e150)
                         & (np.abs(xs).max(axis=(1, 2, 3), initial=0.0) < 1e150))
    if runaway.any():
        yhat[runaway] = 0.0
        S[runaway] = 0.0
    if not fit_initial:
        if runaway.any():
            yhat[runaway] = np.nan
        return yhat
    sel = slice(start, stop) if fit_mask is None else np.flatnonzero(fit_mask)
    Sw = np.ascontiguousarray((S[:, :, sel, :] * w8).reshape(C, nu, -1))  # (C, nu, n)
    SwT = np.swapaxes(Sw, 1, 2)
    # the free responses S do not depend on the window: their Gram matrix is formed once
    Gss = np.matmul(Sw, SwT)  # (C, nu, nu)
    if gram is not None:
        gram.update(unknown=unknown if block is None else [block.states[i] for i in unknown],
                    diag=np.diagonal(Gss, axis1=1, axis2=2).copy())
    S2 = S.reshape(C, nu, L * ny)
    K = 0 if nuisance is None else nuisance.shape[-1]
    coef = np.empty((C, Wn, nu + K)) if return_coef else None
    if nuisance is None:
        # one normal matrix per candidate: one factorisation, every window a right-hand side
        tr, n_tr = np.trace(Gss, axis1=1, axis2=2), nu
        if ridge_extra is not None:
            tr, n_tr = tr + ridge_extra[0], nu + ridge_extra[1]
        ridge = 1e-9 * tr[:, None, None] / n_tr + 1e-12
        Gr = Gss + ridge * np.eye(nu)
    else:
        Nall = np.moveaxis(nuisance, 3, 1)  # (W or 1, K, L, 8) view
        prec = None if nuisance_prec is None else np.asarray(nuisance_prec, float)
        shared = nuisance.shape[0] == 1
        if shared:  # the same columns in every window: one normal matrix per candidate, as without them
            N1 = np.ascontiguousarray((Nall[0][:, sel, :] * w8).reshape(K, -1))  # (K, n)
            Gn = _nuisance_normal(Sw, Gss, N1[None], prec, ridge_extra)[:, 0]  # (C, nu + K, nu + K)
            if gram is not None:
                gram["nuisance_diag"] = (N1 ** 2).sum(axis=1)
            N2 = np.ascontiguousarray(nuisance[0].reshape(L * ny, K).T)  # (K, L 8)
    for w0 in range(0, Wn, wc):
        w1 = min(Wn, w0 + wc)
        Wc = w1 - w0
        yc = yhat[:, w0:w1]  # view: corrected in place
        yo = outputs[w0:w1] if W0 == Wn else outputs[np.arange(w0, w1) % W0]
        rw = ((yo[None] - yc)[:, :, sel, :] * w8).reshape(C, Wc, -1)  # (C, Wc, n)
        hs = np.matmul(rw, SwT)  # (C, Wc, nu)
        if nuisance is None:
            a = np.swapaxes(np.linalg.solve(Gr, np.swapaxes(hs, 1, 2)), 1, 2)  # (C, Wc, nu)
            yc += np.matmul(a, S2).reshape(C, Wc, L, ny)
        elif shared:
            h = np.concatenate([hs, np.matmul(rw, N1.T)], axis=2)  # (C, Wc, nu + K)
            a = np.swapaxes(np.linalg.solve(Gn, np.swapaxes(h, 1, 2)), 1, 2)
            yc += np.matmul(a[..., :nu], S2).reshape(C, Wc, L, ny)
            yc += np.matmul(a[..., nu:], N2).reshape(C, Wc, L, ny)
        else:
            Nw = np.ascontiguousarray((Nall[w0:w1, :, sel, :] * w8).reshape(Wc, K, -1))  # (Wc, K, n)
            hn = np.matmul(Nw[None], rw[..., None])[..., 0]  # (C, Wc, K)
            h = np.concatenate([hs, hn], axis=2)
            a = np.linalg.solve(_nuisance_normal(Sw, Gss, Nw, prec), h[..., None])[..., 0]  # (C, Wc, nu + K)
            yc += np.matmul(a[..., :nu], S2).reshape(C, Wc, L, ny)
            # nuisance responses: per window (L 8, K) @ (K, C)
            yc += np.moveaxis(np.matmul(nuisance[w0:w1].reshape(Wc, L * ny, K),
                                        np.moveaxis(a[..., nu:], 0, 2)), 2, 0).reshape(C, Wc, L, ny)
        if coef is not None:
            coef[:, w0:w1] = a
    if runaway.any():
        yhat[runaway] = np.nan
    if coef is not None:
        return yhat, coef
    return yhat


def free_responses(theta: np.ndarray, L: int, dt_s: float, available: np.ndarray | None = None,
                   all_initial: bool = True) -> np.ndarray:
    """(n_unknown, L, 8) output responses to a unit value of each initial state :func:`simulate` fits
    (the unmeasured states and unavailable channels' states, or all with ``all_initial``), in the
    order it fits them: the same in every window, so a caller can form the least squares of the
    initial states with other shared columns itself. ``theta`` (31,)."""
    A, B = full_matrices(np.atleast_2d(np.asarray(theta, dtype=float)))
    Ad, Bd = discretize(A, B, dt_s)
    b = max(1, min(LIFT_BLOCK, L))
    avail = np.ones(8, bool) if available is None else np.asarray(available, bool)
    unknown = list(UNMEASURED) + [int(OUT_STATE[c]) for c in range(8) if not avail[c] or all_initial]
    Phi = _lift(Ad, Bd[:, :, :4], b, -(-L // b))[4]  # (1, nb b, 8, 11)
    return np.ascontiguousarray(np.moveaxis(Phi[0, :L][:, :, unknown], 2, 0))


def _restrict(block: Block, A: np.ndarray, B: np.ndarray, inputs: np.ndarray, forcing: np.ndarray | None,
              outputs: np.ndarray, avail: np.ndarray, w8: np.ndarray, nuisance: np.ndarray | None) -> tuple:
    """:func:`simulate`'s matrices and arrays cut to one block: A, B (its input then forcing columns),
    inputs, forcing, outputs, available, weights, nuisance, each output's state and the unmeasured
    states (as indices among the block's states)."""
    st, oc = list(block.states), list(block.outputs)
    cols = list(block.inputs) + [4 + i for i in st]
    out_state = np.array([st.index(int(OUT_STATE[c])) for c in oc])
    return (A[:, st][:, :, st], B[:, st][:, :, cols], inputs[..., list(block.inputs)],
            None if forcing is None else forcing[..., st], outputs[..., oc], avail[oc], w8[oc],
            None if nuisance is None else nuisance[..., oc, :], out_state,
            tuple(st.index(i) for i in UNMEASURED if i in st))


def _nuisance_normal(Sw: np.ndarray, Gss: np.ndarray, Nw: np.ndarray, prec: np.ndarray | None,
                     ridge_extra: tuple[float, int] | None = None) -> np.ndarray:
    """Normal matrices (C, Wc, nu + K, nu + K) of the initial states (weighted free responses ``Sw``
    (C, nu, n), their Gram ``Gss`` (C, nu, nu)) and the nuisance columns ``Nw`` (Wc, K, n), with the
    relative ridge (relative also to ``ridge_extra``, see :func:`simulate`) and the nuisance's prior
    precision ``prec`` (K,) added."""
    C, nu = Gss.shape[:2]
    Wc, K = Nw.shape[:2]
    Gsn = np.matmul(Sw[:, None], np.swapaxes(Nw, 1, 2)[None])  # (C, Wc, nu, K)
    G = np.empty((C, Wc, nu + K, nu + K))
    G[:, :, :nu, :nu] = Gss[:, None]
    G[:, :, :nu, nu:] = Gsn
    G[:, :, nu:, :nu] = np.swapaxes(Gsn, 2, 3)
    G[:, :, nu:, nu:] = np.matmul(Nw, np.swapaxes(Nw, 1, 2))[None]
    tr, n_tr = np.trace(G, axis1=2, axis2=3), G.shape[-1]
    if ridge_extra is not None:
        tr, n_tr = tr + ridge_extra[0], n_tr + ridge_extra[1]
    ridge = 1e-9 * tr[..., None, None] / n_tr + 1e-12
    G += ridge * np.eye(nu + K)
    if prec is not None:
        idx = np.arange(nu, nu + K)
        G[..., idx, idx] += prec
    return G
