"""The search's cost with projected B entries, from Markov parameters and per-flight data products.

:class:`~groundstation.sysid.simulate.WindowSimulator` solves the projected B entries (variable
projection) and every window's initial state by least squares inside each evaluation. When the B
entries that are not projected are zero (the horizontal search: all of its B entries are projected
or held at zero), every window has the same channels and weights and no sample is missing from the
link, the residual before that least squares is the measured output less the free response of the
window's measured initial states (if any are taken as measured), and the unit response of projected
entry ``p`` (state ``st_p``, input ``i_p``) on channel ``h`` in window ``w`` is a convolution of the
window's input with the entry's Markov parameters::

    F_phw[k] = sum_{j<k} m_ph[j] u_w[k-1-j],   m_ph[j] = C_h A^j Gamma e_st

so ``F_phw = T_w m_ph`` with ``T_w`` the window's (L, L) Toeplitz matrix of its input. Every product
the least squares and the per-channel SSE need then splits into products of the data alone (the
input Grams ``Q = sum_w T_w^T T_w'``, ``sum_w T_w^T y_hw``, ``||y_h||^2``: computed once per flight,
:func:`markov_data`) and small products with the candidate's Markov parameters and free-response
basis ``Phi_h[k] = C_h A^k``. The projections of the unit responses on the free responses,
``Phi_h^T F_phw = sum_l u_w[l] K_ph[l]``, use ``K_ph[l] = (sum_{j <= L-2-l} m_ph[j] Phi_h[j]) A^(l+1)``
(through partial observability Gramians, see :func:`_gramian_sum`). No unit response is simulated: about a fifth of the multiply-adds of the lifted simulation, in
arrays that stay in cache. The per-channel SSE ``||Phi_h z + F_h beta - y_h||^2`` is a quadratic form
of those products; where it keeps fewer than about eight digits (a fit close to the data) the errors
are computed explicitly, and a candidate whose free response grows more than :data:`GROWTH` over a
window (a runaway trial step) is left to the caller's lifted simulation.

Array conventions as in :mod:`groundstation.sysid.simulate`: C candidates, W windows of L samples,
nch measured channels of the subsystem, n states, P projected entries. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the quadratic-form SSE is trusted where it is at least this fraction of the size of its terms
TRUST = 1e-8
#: a candidate whose free response grows more than this over a window (``max |A^k|``, k < L) is left to
#: the lifted simulation: the products here then lose digits the trust test does not see (runaway trial
#: candidates of an unstable search, e.g. a real flight without its aircraft file)
GROWTH = 1e3


@dataclass(frozen=True, eq=False)
class MarkovData:
    """What the projected search cost needs of one subsystem's data (:func:`markov_data`)."""

    toeplitz: dict[int, np.ndarray]  # input -> (W L, L): row (w, k), column j holds u_w[k-1-j]
    gram: dict[tuple[int, int], np.ndarray]  # (input, input) -> (L, L) sum_w T_w^T T_w'
    y: np.ndarray  # (nch, W, L) outputs
    ty: np.ndarray  # (P, nch, L) sum_w T_w(i_p)^T y_hw
    yy: np.ndarray  # (nch,) ||y_h||^2
    u_p: np.ndarray  # (P, W, L-1) each entry's input (the last sample drives nothing)
    u_in: dict[int, np.ndarray]  # input -> (L-1, W)
    groups: tuple[tuple[int, np.ndarray], ...]  # (input, entries driven by it)
    states: np.ndarray  # (P,) state of each entry
    inputs: np.ndarray  # (P,) input of each entry
    w: np.ndarray  # (nch,) channel weights of the least squares
    ridge: float
    unknown: np.ndarray  # (n,) 1.0 for the initial states solved, 0.0 for the measured ones
    known: np.ndarray | None  # (W, n) the measured initial states (None: every state is solved)
    known_u: dict[int, np.ndarray]  # input -> (L-1, n) sum_w u_w[l] known_w


def markov_data(u: np.ndarray, y: np.ndarray, lin: tuple[tuple[int, int], ...], w: np.ndarray,
                ridge: float, known: np.ndarray, unknown: np.ndarray) -> MarkovData:
    """Data products of one subsystem: ``u (W, L, m)`` its inputs, ``y (W, L, nch)`` its measured
    outputs, ``lin`` the projected (state, input) entries, ``w (nch,)`` the channel weights, ``known
    (W, n)`` the measured initial states (zero where solved) and ``unknown (n,)`` which are solved."""
    W, L, _ = u.shape
    inputs = np.array([i for _, i in lin])
    used = sorted({int(i) for i in inputs})
    T = {}
    for i in used:
        t = np.zeros((W, L, L))
        for j in range(L - 1):
            t[:, j + 1:, j] = u[:, :L - 1 - j, i]
        T[i] = t.reshape(W * L, L)
    yf = y.reshape(W * L, -1)
    ty = {i: (T[i].T @ yf).T for i in used}  # (nch, L)
    return MarkovData(
        toeplitz=T, gram={(i, k): T[i].T @ T[k] for i in used for k in used},
        y=np.ascontiguousarray(y.transpose(2, 0, 1)), ty=np.stack([ty[i] for i in inputs]),
        yy=np.einsum("wkh,wkh->h", y, y), u_p=np.ascontiguousarray(np.stack([u[:, :L - 1, i] for i in inputs])),
        u_in={i: np.ascontiguousarray(u[:, :L - 1, i].T) for i in used},
        groups=tuple((i, np.flatnonzero(inputs == i)) for i in used),
        states=np.array([s for s, _ in lin]), inputs=inputs, w=np.asarray(w, dtype=float), ridge=float(ridge),
        unknown=np.asarray(unknown, dtype=float), known=np.asarray(known, dtype=float) if np.any(known) else None,
        known_u={i: np.ascontiguousarray(u[:, :L - 1, i].T) @ known for i in used} if np.any(known) else {})


def powers(A: np.ndarray, k: int) -> np.ndarray:
    """``A^0 .. A^(k-1)`` of C matrices (C, n, n): (C, k, n, n), by doubling."""
    C, n, _ = A.shape
    pw = np.empty((C, k, n, n))
    pw[:, 0] = np.eye(n)
    if k > 1:
        pw[:, 1] = A
    j = 2
    while j < k:
        jj = min(j, k - j)
        np.matmul(pw[:, :jj], np.matmul(pw[:, j - 1], A)[:, None], out=pw[:, j:j + jj])
        j += jj
    return pw


def markov_sse(d: MarkovData, Ad: np.ndarray, Gam: np.ndarray,
               s_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of the initial states (per window) and the projected entries (shared) for C
    candidates, ``Ad (C, n, n)`` and ``Gam (C, n, n)`` (the ZOH input matrix of unit columns), with
    the measured states ``s_idx`` (nch,). Returns ``(z (C, W, n), beta (C, P), sse (C, nch))``; ``sse`` is
    NaN for a candidate whose free response grows more than :data:`GROWTH` over a window."""
    nch, W, L = d.y.shape
    pw = powers(Ad, L)
    t = _terms(d, pw, Gam, s_idx)
    t["yy"] = np.broadcast_to(d.yy, (Ad.shape[0], nch))
    if d.known is not None:
        _subtract_known(d, t)
    z, beta = _solve(d, t)
    sse = _quadratic(d, t, z, beta)
    x0 = z if d.known is None else z + d.known
    wild = ~(np.abs(pw).max(axis=(1, 2, 3)) <= GROWTH)
    for c in np.flatnonzero(np.isnan(sse).any(axis=1) & ~wild):  # the form keeps too few digits here
        sse[c] = _explicit(d, t["obs"][c], t["m"][c], x0[c], beta[c])
    sse[wild] = np.nan  # the caller simulates these
    return z, beta, sse


def _subtract_known(d: MarkovData, t: dict[str, np.ndarray]) -> None:
    """The residual before the least squares is ``y_hw - Phi_h k_w``, ``k_w`` the window's measured
    initial states: ``yy``, ``gy`` and ``Fy`` of that residual into ``t`` (``Phi_h^T F_phw . k_w`` as in
    :func:`_cross`)."""
    H, gy, k = t["H"], t["gy"], d.known
    assert k is not None
    Hk = np.matmul(k, H)  # (C, nch, W, n); H is symmetric
    t["yy"] = t["yy"] - np.einsum("chwn,wn->ch", 2.0 * gy - Hk, k)
    t["gy"] = gy - Hk
    for i, gi in d.groups:
        t["Fy"][:, :, gi] -= np.matmul(_gramian_sum(t, d.known_u[i]), t["g"][:, :, gi])


def _terms(d: MarkovData, pw: np.ndarray, Gam: np.ndarray, s_idx: np.ndarray) -> dict[str, np.ndarray]:
    """The candidate's products with the data: free-response rows ``obs`` (C, L, nch, n) ``C_h A^k``
    and as ``Phi`` (C, nch, L, n), input columns ``g`` (C, n, P) ``Gamma e_st``, Markov parameters
    ``m`` (C, nch, P, L), ``H = Phi_h^T Phi_h``, ``gy = Phi_h^T y_hw`` (C, nch, W, n), ``E = sum_h w_h
    Phi_h^T F_phw`` (C, P, W, n), ``FF = F_h F_h^T`` (C, nch, P, P) and ``Fy = F_h y_h`` (C, nch, P).

    ``sum_h w_h K_ph[l] = g_p^T Wo[L-2-l] A^(l+1)`` with ``Wo[J] = sum_{j<=J} sum_h w_h obs_h[j]^T
    obs_h[j]`` (the weighted partial observability Gramians), so ``K`` itself is never formed."""
    C, L, n, _ = pw.shape
    obs = pw[:, :, s_idx, :]
    Phi = np.ascontiguousarray(obs.transpose(0, 2, 1, 3))
    g = np.ascontiguousarray(Gam[..., d.states])
    m = np.ascontiguousarray(np.matmul(pw, g[:, None])[:, :, s_idx, :].transpose(0, 2, 3, 1))
    Wo = np.cumsum(np.matmul(np.swapaxes(obs * d.w[:, None], -1, -2), obs), axis=1)  # (C, L, n, n)
    Kw = np.matmul(np.swapaxes(g, 1, 2)[:, None], np.matmul(Wo[:, L - 2::-1], pw[:, 1:]))  # (C, L-1, P, n)
    FF = np.empty((C, len(s_idx), len(d.states), len(d.states)))
    for i, gi in d.groups:
        for k, gk in d.groups:
            FF[:, :, gi[:, None], gk[None, :]] = np.matmul(np.matmul(m[:, :, gi], d.gram[(i, k)]),
                                                            np.swapaxes(m[:, :, gk], -1, -2))
    H = np.matmul(np.swapaxes(Phi, -1, -2), Phi)
    gy = np.matmul(d.y[None], Phi)
    E = np.matmul(d.u_p[None], Kw.transpose(0, 2, 1, 3))
    Fy = np.einsum("chpl,phl->chp", m, d.ty)
    return dict(pw=pw, obs=obs, g=g, m=m, H=H, gy=gy, E=E, FF=FF, Fy=Fy)


def _solve(d: MarkovData, t: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``z`` (C, W, n) and ``beta`` (C, P): the per-window normal equations eliminated by their Schur
    complement, with the relative ridges of the lifted path (1e-10 on the shared entries)."""
    w, uk = d.w, d.unknown
    E = t["E"] * uk
    C, P, W, n = E.shape
    G = np.einsum("h,chij->cij", w, t["H"]) * (uk[:, None] * uk[None, :])
    scale = np.maximum(np.einsum("cii->ci", G).max(axis=-1), 1e-300)
    G += np.where(uk > 0, d.ridge * scale[:, None], 1.0)[..., :, None] * np.eye(n)  # measured states: z = 0
    GiT = np.swapaxes(np.linalg.solve(G, np.broadcast_to(np.eye(n), G.shape)), -1, -2)
    GiE = np.matmul(E, GiT[:, None]).reshape(C, P, W * n)
    gia = np.matmul(np.einsum("h,chwn->cwn", w, t["gy"]) * uk, GiT).reshape(C, W * n, 1)
    E2 = E.reshape(C, P, W * n)
    S = np.einsum("h,chpq->cpq", w, t["FF"]) - np.matmul(E2, np.swapaxes(GiE, 1, 2))
    S += (1e-10 * np.maximum(np.einsum("cpp->cp", S).max(axis=-1), 1e-300))[:, None, None] * np.eye(P)
    rb = np.einsum("h,chp->cp", w, t["Fy"])[..., None] - np.matmul(E2, gia)
    beta = np.linalg.solve(S, rb)[..., 0]
    z = gia[..., 0] - np.matmul(beta[:, None, :], GiE)[:, 0]
    return z.reshape(C, W, n), beta


def _quadratic(d: MarkovData, t: dict[str, np.ndarray], z: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Per channel ``||Phi_h z + F_h beta - y_h||^2`` (C, nch) from the products; NaN where the form
    keeps fewer than about eight digits (each term's rounding is relative to the norms of its factors)."""
    H, FF = t["H"], t["FF"]
    zHz = np.einsum("chwn,cwn->ch", np.matmul(z[:, None], H), z)
    bFFb = np.einsum("chpq,cp,cq->ch", FF, beta, beta)
    sse = t["yy"] - 2.0 * (np.einsum("chwn,cwn->ch", t["gy"], z) + np.einsum("chp,cp->ch", t["Fy"], beta)
                              - _cross(d, t, z, beta)) + zHz + bFFb
    zz = np.einsum("cwn,cwn->c", z, z) + (0.0 if d.known is None else np.einsum("wn,wn->", d.known, d.known))
    size = d.yy[None] + zz[:, None] * np.einsum("chii->ch", H) \
        + np.einsum("cp,cp->c", beta, beta)[:, None] * np.einsum("chpp->ch", FF)
    return np.where((sse > TRUST * size) | ~np.isfinite(size), sse, np.nan)


def _cross(d: MarkovData, t: dict[str, np.ndarray], z: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """``sum_w (Phi_h z_w) . (F_hw beta)`` (C, nch): ``sum_{p of i} beta_p g_p^T b_hi`` over the inputs
    ``i``, ``b_hi`` from :func:`_gramian_sum` of ``sum_w u_w[l] z_w``."""
    out = np.zeros(t["yy"].shape)
    for i, gi in d.groups:
        b = _gramian_sum(t, np.matmul(d.u_in[i][None], z))
        out += np.matmul(b, np.matmul(t["g"][:, :, gi], beta[:, gi, None]))[..., 0]
    return out


def _gramian_sum(t: dict[str, np.ndarray], v: np.ndarray) -> np.ndarray:
    """``b_h = sum_l Wo_h[L-2-l] A^(l+1) v[l]`` (C, nch, n) for ``v`` ((C,) L-1, n), with ``Wo_h[J] =
    sum_{j<=J} obs_h[j]^T obs_h[j]``: with ``a[l] = A^(l+1) v[l]`` and ``S[j] = sum_{l <= L-2-j} a[l]``,
    ``b_h = sum_j obs_h[j]^T (obs_h[j] . S[j])`` (no Gramian is formed). ``sum_w z_w . Phi_h^T F_phw
    = g_p^T b_h`` for ``v[l] = sum_w u_w[l] z_w``, ``u`` the input of entry p."""
    pw, obs = t["pw"], t["obs"][:, :-1]
    a = np.matmul(pw[:, 1:], np.broadcast_to(v, obs.shape[:2] + v.shape[-1:])[..., None])[..., 0]  # (C, L-1, n)
    acc = np.cumsum(a, axis=1)[:, ::-1]
    return np.einsum("cjh,cjhn->chn", np.einsum("cjhn,cjn->cjh", obs, acc), obs)


def _explicit(d: MarkovData, obs: np.ndarray, m: np.ndarray, z: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Per channel SSE (nch,) of one candidate from its errors: ``obs`` (L, nch, n) the free-response
    basis, ``m`` (nch, P, L) the Markov parameters, ``z`` (W, n), ``beta`` (P,)."""
    nch, W, L = d.y.shape
    e = np.matmul(z, obs.reshape(L * nch, -1).T).reshape(W * L, nch)  # (w, k) rows
    for i, gi in d.groups:
        e += d.toeplitz[i] @ np.einsum("p,hpl->lh", beta[gi], m[:, gi])  # (W L, nch)
    e -= d.y.transpose(1, 2, 0).reshape(W * L, nch)
    return np.einsum("xh,xh->h", e, e)
