"""Batched windowed output-error simulation of the eq.-8 hover model and the paper's objective.

Array conventions
-----------------
* ``theta (C, 31)``: C candidate parameter vectors (a whole colony) in ``model.PARAM_NAMES`` order.
* ``inputs (W, L, 4)``: W data windows of L samples, normalised ``lat lon col ped``.
* ``outputs (W, L, 8)``: measured ``u v w p q r theta phi`` (trim removed); NaN / unavailable
  channels are ignored (``available (8,)`` or ``(W, 8)`` bool); ``measured (W, L, 8)`` bool marks
  the samples in holes of the link (False): they are not counted in the errors, the cost or the
  channel scales. The initial-state least squares still sees the bridged values there (a straight
  line across the hole): solving it per window without them would cost a Gram matrix per window.
* ``yhat (C, W, L, 8)``: simulated outputs.

Each window starts from an initial state: measured states (u v theta phi q p; w r) are taken from the
first sample of the window, the unmeasured ones (a_s b_s; r_fb, and any measured channel that is
unavailable in that window) are estimated per candidate per window by linear least squares - the
outputs are linear in the initial state (``y = Phi x0 + forced``), so this is a small solve with
the same channel weighting as the objective. Windows keep unstable hover modes from blowing up.
Discretisation is the exact zero-order hold (``model.discretize``). The horizontal (8 states) and
vertical (3 states) subsystems are stepped separately, all C*W systems per time step at once.

Pure numpy/scipy; which windows to cut from which segments is :mod:`groundstation.sysid.cost`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from groundstation.errors import SysidError
from groundstation.sysid.markov import markov_data, markov_sse
from groundstation.sysid.model import build_matrices, discretize

# (state index, output column) of the measured states per subsystem
_HOR_MEAS: tuple[tuple[int, int], ...] = ((0, 0), (1, 1), (5, 3), (4, 4), (2, 6), (3, 7))
_VER_MEAS: tuple[tuple[int, int], ...] = ((0, 2), (1, 5))


@dataclass(frozen=True)
class _Sub:
    n: int
    inputs: tuple[int, ...]
    meas: tuple[tuple[int, int], ...]


_SUBS = (_Sub(8, (0, 1), _HOR_MEAS), _Sub(3, (2, 3), _VER_MEAS))
#: per subsystem: (state, column of ``forcing``) of the known accelerations on u, v (horizontal) and w
_FORCED: tuple[tuple[tuple[int, int], ...], ...] = (((0, 0), (1, 1)), ((0, 2),))


def _avail_2d(available: np.ndarray | None, outputs: np.ndarray) -> np.ndarray:
    W = outputs.shape[0]
    finite = np.isfinite(outputs).all(axis=1)  # (W, 8)
    if available is None:
        return finite
    a = np.asarray(available, dtype=bool)
    if a.ndim == 1:
        a = np.broadcast_to(a, (W, 8))
    return a & finite


def channel_scales(outputs: np.ndarray, mask: np.ndarray, smask: np.ndarray | None = None) -> np.ndarray:
    """Per-channel ``||y - mean(y)||`` over all windows where the channel is used; shape (8,).

    outputs (W, L, 8); mask (W, 8); smask (W, L, 8) samples counted (default: all of the used
    channels). Unused channels get 1.
    """
    y = np.nan_to_num(outputs)
    m = np.broadcast_to(mask[:, None, :], y.shape) if smask is None else smask
    m = m.astype(float)
    cnt = m.sum(axis=(0, 1))
    mean = (y * m).sum(axis=(0, 1)) / np.maximum(cnt, 1)
    ss = (((y - mean) ** 2) * m).sum(axis=(0, 1))
    s = np.sqrt(ss)
    return np.where((cnt > 0) & (s > 0), s, 1.0)



def _window_gram(w_ch: np.ndarray, Hzz: np.ndarray, unk: np.ndarray, ridge: float) -> np.ndarray:
    """Per-window normal matrices of the initial states (k, W, n, n): ``sum_h w_h Hzz_h`` over the
    channels, restricted to the unknown states ``unk`` (W, n), with a relative ridge on their
    diagonal and the identity on the known ones (their solution is then zero)."""
    k, nch, n = Hzz.shape[0], Hzz.shape[1], Hzz.shape[-1]
    W = w_ch.shape[0]
    G = np.matmul(w_ch[None], np.ascontiguousarray(Hzz).reshape(k, nch, n * n)).reshape(k, W, n, n)
    G *= (unk[:, :, None] * unk[:, None, :])[None]
    scale = np.maximum(np.einsum("cwii->cwi", G).max(axis=-1, keepdims=True), 1e-300)
    G += np.where(unk[None] > 0, ridge * scale, 1.0)[..., :, None] * np.eye(n)
    return G


def _schur_solve(G: np.ndarray, E: np.ndarray, rhs: np.ndarray, FF: np.ndarray,
                 rb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Block least squares with per-window unknowns ``z`` (k, W, n) and shared ones ``beta`` (k, P):
    ``[[G_w, E_w], [E_w^T, FF]] [z_w; beta] = [rhs_w; rb]``, by the Schur complement over the windows
    (variable projection; a 1e-10 relative ridge keeps S solvable). ``G`` (k, n, n) instead of
    (k, W, n, n): the same matrix in every window (one factorisation for all). Returns ``(z, beta)``."""
    P = E.shape[-1]
    Bm = np.concatenate([E, rhs[..., None]], axis=-1)  # (k, W, n, P + 1)
    if G.ndim == 3:
        k, W, n, q = Bm.shape
        sol = np.linalg.solve(G, Bm.transpose(0, 2, 1, 3).reshape(k, n, W * q))
        sol = sol.reshape(k, n, W, q).transpose(0, 2, 1, 3)
    else:
        sol = np.linalg.solve(G, Bm)
    GiE, Gia = sol[..., :P], sol[..., P]
    S = FF - np.einsum("cwnp,cwnq->cpq", E, GiE)
    dS = np.einsum("cpp->cp", S)
    S += (1e-10 * np.maximum(dS.max(axis=-1), 1e-300))[:, None, None] * np.eye(P)
    beta = np.linalg.solve(S, (rb - np.einsum("cwnp,cwn->cp", E, Gia))[..., None])[..., 0]
    return Gia - np.einsum("cwnp,cp->cwn", GiE, beta), beta

def _schur_alike(G: np.ndarray, E: np.ndarray, rhs: np.ndarray, FF: np.ndarray,
                 rb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_schur_solve` when every window has the same normal matrix ``G`` (k, n, n) and coupling
    ``E`` (k, n, P): one solve for the coupling instead of one per window, and the Schur complement
    ``FF - W E^T G^-1 E``. ``rhs`` (k, W, n), ``rb`` (k, P). Returns ``(z (k, W, n), beta (k, P))``."""
    k, W, n = rhs.shape
    P = E.shape[-1]
    sol = np.linalg.solve(G, np.concatenate([E, np.swapaxes(rhs, 1, 2)], axis=-1))  # (k, n, P + W)
    GiE, Gia = sol[..., :P], sol[..., P:]
    S = FF - W * np.matmul(np.swapaxes(E, 1, 2), GiE)
    dS = np.einsum("cpp->cp", S)
    S += (1e-10 * np.maximum(dS.max(axis=-1), 1e-300))[:, None, None] * np.eye(P)
    beta = np.linalg.solve(S, (rb - np.matmul(np.swapaxes(E, 1, 2), Gia.sum(axis=-1, keepdims=True))[..., 0])[..., None])
    return np.swapaxes(Gia - np.matmul(GiE, beta), 1, 2), beta[..., 0]


class WindowSimulator:
    """Precomputed windows; ``simulate(theta)`` returns ``yhat (C, W, L, 8)``, ``sse(theta)`` (C, 8).

    Parameters
    ----------
    inputs : (W, L, 4)
    outputs : (W, L, 8), used for the initial states and the least-squares weights
    dt_s : sample interval, s
    available : (8,) or (W, 8) bool, channel measured
    estimate_all_initial : estimate every initial state by least squares (not only the unmeasured)
    ridge : relative Tikhonov weight that keeps unobservable initial states finite
    block : time-lifting block length (samples) for both subsystems (overrides ``lifted_block``)
    subsystems : which decoupled subsystems to simulate (0 horizontal, 1 vertical/yaw); the
        outputs of the others stay zero and their channels are not used
    linear : per subsystem, B-matrix entries ``(state, input)`` (input index within the subsystem)
        solved by least squares together with the initial states (variable projection: the output
        is linear in B for a given A); the values of those entries in ``theta`` are ignored and the
        estimates are returned by :meth:`solve_linear`
    lifted_block : block length per subsystem of the lifted simulation (see Notes)
    measured : (W, L, 8) bool or None, sample measured (False in a hole of the link: not counted)
    forcing : (W, L, 3) known accelerations (m/s^2) added to u_dot, v_dot, w_dot, e.g. the measured
        kinematic and gravity terms that eq. 8 linearises away (:func:`kinematic_forcing`)
    window_offsets : solve one constant offset per input in each window, with the window's unmeasured
        initial states (a stabiliser's integrator trim, or a stick held away from its logged value, that
        changes from window to window); excludes ``estimate_trim``
    scales : (8,) channel scales of the initial-state least squares' weights (default: the outputs' own,
        :func:`channel_scales`), e.g. another simulator's, so that responses computed on a few of its
        windows are weighted as there
    estimate_trim : also solve, per subsystem, one constant offset per input shared by all windows
        (the model sees ``u - delta``): the input trim, which the in-air median only approximates,
        is a nuisance of the perturbation model like the initial states (see :meth:`solve_trim`)

    Notes
    -----
    The forced response is computed by time lifting: with blocks of b samples,
    ``x_{i+1} = A^b x_i + Cb U_i`` and ``Y_i = Ob x_i + T U_i`` (``Ob`` the stacked ``C A^j``, ``T`` the
    block-Toeplitz Markov parameters, ``Cb`` the block controllability matrix) - exactly the same
    numbers as stepping ``x[k+1] = A x[k] + B u[k]`` sample by sample, but in a few large products:
    per candidate one ``[Ob | T] [x; U]`` product over all blocks of all windows, laid out channel-major
    (rows channel and in-block sample, columns block and window), so that the initial-state least
    squares needs only ``Phi_h^T r_h`` per channel and the per-channel SSE follows from the quadratic
    form without an error array (explicit where the form cancels). Candidates run in chunks of
    ``chunk_bytes`` of output so that product, subtraction and reductions stay in cache.
    """

    def __init__(self, inputs: np.ndarray, outputs: np.ndarray, dt_s: float, available: np.ndarray | None = None,
                 *, estimate_all_initial: bool = False, ridge: float = 1e-6, block: int | None = None,
                 subsystems: tuple[int, ...] = (0, 1),
                 linear: dict[int, tuple[tuple[int, int], ...]] | None = None,
                 lifted_block: tuple[int, int] = (5, 5), estimate_trim: bool = False,
                 forcing: np.ndarray | None = None, measured: np.ndarray | None = None,
                 window_offsets: bool = False, scales: np.ndarray | None = None) -> None:
        u = np.asarray(inputs, dtype=float)
        y = np.asarray(outputs, dtype=float)
        if u.ndim != 3 or u.shape[2] != 4 or y.ndim != 3 or y.shape[2] != 8 or u.shape[:2] != y.shape[:2]:
            raise SysidError(f"inputs must be (W, L, 4) and outputs (W, L, 8), got {u.shape} and {y.shape}")
        if not np.isfinite(u).all():
            raise SysidError("inputs contain NaN/inf")
        self.inputs = u
        self.dt_s = float(dt_s)
        self.subsystems = tuple(sorted(set(subsystems)))
        if not self.subsystems or any(i not in (0, 1) for i in self.subsystems):
            raise SysidError(f"subsystems must be a subset of (0, 1), got {subsystems}")
        keep = np.zeros(8, dtype=bool)
        for i in self.subsystems:
            keep[[o for _, o in _SUBS[i].meas]] = True
        self.mask = _avail_2d(available, y) & keep[None, :]  # (W, 8)
        self.outputs = np.where(self.mask[:, None, :], np.nan_to_num(y), 0.0)
        #: (W, L, 8) samples counted: channel used in the window and the sample measured
        self.smask = np.broadcast_to(self.mask[:, None, :], y.shape).copy()
        self.holes = measured is not None and not bool(np.asarray(measured, dtype=bool)[self.smask].all())
        if self.holes:
            assert measured is not None
            self.smask &= np.asarray(measured, dtype=bool)
        self.scales = channel_scales(self.outputs, self.mask, self.smask if self.holes else None) if scales is None \
            else np.asarray(scales, dtype=float)
        self.weights = self.mask / self.scales[None, :] ** 2  # (W, 8) LS weights, same as eq. 11 normalisation
        self.estimate_all_initial = estimate_all_initial
        self.ridge = ridge
        self.W, self.L = u.shape[0], u.shape[1]
        self.linear = {k: tuple(v) for k, v in (linear or {}).items() if v}
        self.lifted_block = (int(block), int(block)) if block is not None else tuple(int(v) for v in lifted_block)
        self.estimate_trim = bool(estimate_trim)
        self.window_offsets = bool(window_offsets)
        if (self.estimate_trim or self.window_offsets) and linear:
            raise SysidError("input offsets and linear (projected B entries) cannot be combined")
        if self.estimate_trim and self.window_offsets:
            raise SysidError("estimate_trim (one offset per flight) and window_offsets (one per window) exclude each other")
        self.forcing = None if forcing is None else np.nan_to_num(np.asarray(forcing, dtype=float))
        if self.forcing is not None:
            if self.forcing.shape != (u.shape[0], u.shape[1], 3):
                raise SysidError(f"forcing must be (W, L, 3) like the inputs, got {self.forcing.shape}")
            if linear:
                raise SysidError("forcing and linear (projected B entries) cannot be combined")
        self.chunk_bytes = 2e6  # candidates are processed in chunks of about this much lifted output
        self._prep: list[dict] = []
        for sub in _SUBS:
            if _SUBS.index(sub) not in self.subsystems:
                self._prep.append({})
                continue
            s_idx = np.array([s for s, _ in sub.meas])
            o_idx = np.array([o for _, o in sub.meas])
            nch = len(sub.meas)
            known = np.zeros((self.W, sub.n), dtype=bool)
            if not estimate_all_initial:
                known[:, s_idx] = self.mask[:, o_idx]
            xm = np.zeros((self.W, sub.n))
            xm[:, s_idx] = self.outputs[:, 0, o_idx]
            xm = np.where(known, xm, 0.0)
            yflat = self.outputs[:, :, o_idx].reshape(self.W, self.L * nch)
            w_ch = self.weights[:, o_idx]
            mflat = self.smask[:, :, o_idx].reshape(self.W, self.L * nch)
            lin = self.linear.get(_SUBS.index(sub), ())
            lb = self.lifted_block[_SUBS.index(sub)]
            self._prep.append(dict(s_idx=s_idx, o_idx=o_idx, nch=nch, xm=xm, yflat=yflat, lin=lin,
                                   mask_hw=np.ascontiguousarray(self.mask[:, o_idx].T).astype(float),
                                   w_ch=w_ch, mflat=mflat, unk=(~known).astype(float),
                                   full_mask=bool(self.smask[:, :, o_idx].all()),
                                   hole_lift=self._lift_mask(self.smask[:, :, o_idx], lb) if self.holes else None))
            u_sub = u[:, :, list(sub.inputs)]
            if self.forcing is not None:  # known accelerations enter as extra inputs with unit gain
                u_sub = np.concatenate([u_sub, self.forcing[:, :, [c for _, c in _FORCED[_SUBS.index(sub)]]]], axis=2)
            self._prep[-1].update(self._lifted_prep(sub, u_sub, self.outputs[:, :, o_idx], xm, known,
                                                    w_ch, lb))
            # the search's projected cost by Markov parameters (:mod:`groundstation.sysid.markov`)
            # (same channels in every window: a channel missing in all of them has weight 0 and its SSE is 0)
            markov = lin and self._prep[-1]["same_G"] and not self.holes
            self._prep[-1]["markov"] = markov_data(u_sub, self.outputs[:, :, o_idx], lin, w_ch[0], ridge, xm,
                                                   (~known[0]).astype(float)) if markov else None

    def _lift_mask(self, m: np.ndarray, block: int) -> np.ndarray:
        """Sample mask (W, L, nch) in the lifted layout of the errors (nch, Lp, W), as floats."""
        b = max(1, min(int(block), self.L))
        nb = -(-self.L // b)
        mp = np.zeros((self.W, nb * b, m.shape[2]))
        mp[:, :self.L] = m
        return np.ascontiguousarray(mp.reshape(self.W, nb, b, -1).transpose(3, 2, 1, 0).reshape(m.shape[2], nb * b, self.W))

    def _lifted_prep(self, sub: _Sub, u: np.ndarray, y: np.ndarray, xm: np.ndarray, known: np.ndarray,
                     w_ch: np.ndarray, block: int) -> dict:
        """Data in the lifted layout of :meth:`_lifted`: columns ``(block i, window w)``, rows ``(channel, j)``."""
        W = self.W
        b = max(1, min(int(block), self.L))
        nb = -(-self.L // b)
        m, nch = u.shape[2], len(sub.meas)  # inputs, then any known forcing channels
        Lp = nb * b
        up = np.zeros((W, Lp, m))
        up[:, :self.L] = u
        # Ut[(l, input), (i, w)] = u[w, i b + l, input]
        Ut = np.ascontiguousarray(up.reshape(W, nb, b, m).transpose(2, 3, 1, 0).reshape(b * m, nb * W))
        yp = np.zeros((W, Lp, nch))
        yp[:, :self.L] = y
        # yT[(h, j), (i, w)] = y[w, i b + j, h]
        yT = np.ascontiguousarray(yp.reshape(W, nb, b, nch).transpose(3, 2, 1, 0).reshape(nch * b, nb * W))
        # Toeplitz index: T[j, l] = C A^(j-1-l) B for l < j, else the zero block (index b)
        jj, ll = np.meshgrid(np.arange(b), np.arange(b), indexing="ij")
        qidx = np.where(ll < jj, jj - 1 - ll, b)
        jv = self.L - (nb - 1) * b  # valid j in the last block
        unk = ~known
        same = bool((unk == unk[:1]).all()) and bool((w_ch == w_ch[:1]).all())
        mi = len(sub.inputs)  # trims only for the real inputs
        Uones = np.broadcast_to(np.eye(m)[None, :, None, :mi], (b, m, nb, mi)).reshape(b * m, nb * mi)
        return dict(Ut=Ut, yT=yT, qidx=qidx, jv=jv, x0T=np.ascontiguousarray(xm.T), X={}, lb=b, lnb=nb, same_G=same,
                    Uones=Uones)

    def _xbuf(self, pre: dict, C: int, n: int) -> np.ndarray:
        """(C, n + b m, nb W) lifted state/input matrix; the input rows are filled once (kept for the
        largest colony seen: fresh multi-megabyte arrays every call cost page faults)."""
        X = pre["X"].get("X")
        if X is None or X.shape[0] < C:
            Ut = pre["Ut"]
            X = np.empty((C, n + Ut.shape[0], Ut.shape[1]))
            X[:, n:] = Ut[None]
            pre["X"]["X"] = X
        return X[:C]

    def _rbuf(self, pre: dict, cc: int, rows: int) -> np.ndarray:
        """(cc, rows, nb W) work buffer for one chunk of candidates, reused between calls."""
        R = pre["X"].get("R")
        if R is None or R.shape[0] < cc:
            R = np.empty((cc, rows, pre["Ut"].shape[1]))
            pre["X"]["R"] = R
        return R[:cc]

    def _lifted(self, sub: _Sub, pre: dict, Ad: np.ndarray, Bd: np.ndarray, *, explicit: bool | str):
        """Windowed simulation with per-window least-squares initial states, in the lifted layout.

        Blocks of b samples: the block-start states come from the recursion
        ``x_{i+1} = [A^b | Cb] [x_i; U_i]`` (Cb the block controllability matrix), and every output
        sample of every block from ONE product per candidate, ``Y = [Ob | T] [x; U]`` (``Ob`` rows
        ``C_h A^j``, ``T`` the block-Toeplitz Markov parameters), laid out channel-major so that the
        initial-state least squares needs only per-channel products ``Phi_h^T r_h``. ``explicit``:
        return the output errors ``e = yhat - y`` (C, W, L, nch) (``"native"``: in the lifted layout
        (C, nch, Lp, W), padding zero); else the per-channel sums of squared
        errors over windows, from the quadratic form ``||r||^2 - 2 z.g + z^T H z`` (no error
        array), recomputed explicitly for any candidate where that form loses more than ~8 digits.
        Returns ``(e or sse, x0)``.
        """
        C = Ad.shape[0]
        W, L, n = self.W, self.L, sub.n
        b, nb = pre["lb"], pre["lnb"]
        s_idx, nch, jv = pre["s_idx"], pre["nch"], pre["jv"]
        m = Bd.shape[-1]
        K = n + b * m
        Lp = nb * b
        pw = [np.broadcast_to(np.eye(n), (C, n, n)), Ad]
        for _ in range(b - 1):
            pw.append(np.matmul(Ad, pw[-1]))
        Apow = np.stack(pw, axis=1)  # (C, b+1, n, n)
        Ab = Apow[:, b]
        AB = np.matmul(Apow[:, :b], Bd[:, None])  # (C, b, n, m): A^q B
        CABz = np.concatenate([AB[:, :, s_idx, :], np.zeros((C, 1, nch, m))], axis=1)  # (C, b+1, nch, m)
        Tq = CABz[:, pre["qidx"]]  # (C, b(j), b(l), nch, m): C_h A^(j-1-l) B, zero for l >= j
        Obm = np.ascontiguousarray(Apow[:, :b][:, :, s_idx, :].transpose(0, 2, 1, 3))  # (C, nch, b(j), n): C_h A^j
        M = np.concatenate([Obm, Tq.transpose(0, 3, 1, 2, 4).reshape(C, nch, b, b * m)], axis=-1)
        M = M.reshape(C, nch * b, K)
        AbCb = np.concatenate([Ab, AB[:, ::-1].transpose(0, 2, 1, 3).reshape(C, n, b * m)], axis=-1)  # (C, n, K)
        X = self._xbuf(pre, C, n)
        X[:, :n, :W] = pre["x0T"][None]
        for i in range(nb - 1):
            np.matmul(AbCb, X[:, :, i * W:(i + 1) * W], out=X[:, :n, (i + 1) * W:(i + 2) * W])
        # free-response basis Phi[h, (j, i)] = C_h A^j (A^b)^i: one product with [I, Ab, Ab^2, ...]
        Abc = np.empty((C, n, nb * n))
        Abc[:, :, :n] = np.eye(n)
        Abk, k = Ab, 1  # doubling: [I .. Ab^(k-1)] -> [I .. Ab^(2k-1)] with one product by Ab^k
        while k < nb:
            kk = min(k, nb - k)
            np.matmul(Abk, Abc[:, :, :kk * n], out=Abc[:, :, k * n:(k + kk) * n])
            k += kk
            if k < nb:  # then kk was the old k, so the new k is twice it
                Abk = np.matmul(Abk, Abk)
        Phi = np.matmul(Obm.reshape(C, nch * b, n), Abc).reshape(C, nch, b, nb, n)
        if jv < b:
            Phi[:, :, jv:, nb - 1] = 0.0
        Phi = Phi.reshape(C, nch, Lp, n)
        nt = 0
        if self.estimate_trim or self.window_offsets:
            # response to a constant unit input on each channel from rest: the same in every window, so
            # one lifted "window" per input; appended to Phi as global least-squares columns
            mi = len(sub.inputs)
            Xo = np.zeros((C, K, nb * mi))
            Xo[:, n:] = pre["Uones"][None]
            for i in range(nb - 1):
                np.matmul(AbCb, Xo[:, :, i * mi:(i + 1) * mi], out=Xo[:, :n, (i + 1) * mi:(i + 2) * mi])
            Fo = np.matmul(M, Xo).reshape(C, nch, b, nb, mi)
            if jv < b:
                Fo[:, :, jv:, nb - 1] = 0.0
            Phi = np.concatenate([Phi, Fo.reshape(C, nch, Lp, mi)], axis=-1)
            nt = mi
        H = np.matmul(np.swapaxes(Phi, -1, -2), Phi)  # (C, nch, n+nt, n+nt), the same for every window
        # candidates in chunks of ~2 MB of output: the chunk stays in cache from product to reduction
        cc = max(1, min(C, int(self.chunk_bytes // (8 * nch * b * nb * W))))
        native = explicit in ("native", "native+sse")
        res = np.empty(((C, nch, Lp, W) if native else (C, W, L, nch)) if explicit else (C, nch))
        sse = np.empty((C, nch)) if explicit == "native+sse" else None
        z = np.empty((C, W, n))
        beta = np.zeros((C, nt))
        for c0 in range(0, C, cc):
            c1 = min(C, c0 + cc)
            z[c0:c1], beta[c0:c1], out = self._lifted_chunk(pre, M[c0:c1], X[c0:c1], Phi[c0:c1], H[c0:c1], explicit, n)
            if sse is None:
                res[c0:c1] = out
            else:
                res[c0:c1], sse[c0:c1] = out
        # input offsets: the model sees u - delta, e = ... - F delta
        return (res if sse is None else (res, sse)), pre["xm"][None] + z, -beta

    def _lifted_chunk(self, pre: dict, M: np.ndarray, X: np.ndarray, Phi: np.ndarray, H: np.ndarray, explicit: bool | str,
                      n: int):
        """Least squares and errors of one chunk of candidates.

        ``Phi`` (k, nch, Lp, n + nt): free-response basis, then ``nt`` global columns (constant-input
        responses) whose coefficients ``beta`` are shared by all windows. Returns ``(z (k, W, n),
        beta (k, nt), e (k, W, L, nch) or sse (k, nch))``.
        """
        k, nch, Lp, na = Phi.shape
        nt = na - n
        W, L, b, nb, jv = self.W, self.L, pre["lb"], pre["lnb"], pre["jv"]
        # r = y - forced - known free response; g = Phi_h^T r_h per window; rr = ||r_h||^2 per window
        R = self._rbuf(pre, k, nch * b)
        np.matmul(M, X, out=R)  # (k, nch b, nb W)
        np.subtract(pre["yT"][None], R, out=R)
        if jv < b:
            R.reshape(k, nch, b, nb, W)[:, :, jv:, nb - 1] = 0.0
        R4 = R.reshape(k, nch, Lp, W)
        g = np.matmul(np.swapaxes(R4, -1, -2), Phi)  # (k, nch, W, na)
        # normal equations per candidate per window: G = sum_h w_h H_h (+ ridge), rhs = sum_h w_h g_h
        unk = pre["unk"]
        w_ch = pre["w_ch"]  # (W, nch)
        rhs = np.einsum("wh,chwn->cwn", w_ch, g[..., :n])
        rhs *= unk[None]
        Hzz = H[:, :, :n, :n]
        same = pre["same_G"] and nt == 0
        if same:  # one G per candidate (same weights and unknowns in every window)
            G = np.matmul(w_ch[:1][None], Hzz.reshape(k, nch, n * n)).reshape(k, n, n)
            uk = unk[0]
            G *= uk[:, None] * uk[None, :]
            scale = np.maximum(np.einsum("cii->ci", G).max(axis=-1, keepdims=True), 1e-300)
            G += np.where(uk[None] > 0, self.ridge * scale, 1.0)[..., :, None] * np.eye(n)
            z = np.swapaxes(np.linalg.solve(G, np.swapaxes(rhs, 1, 2)), 1, 2)  # (k, W, n)
        else:
            # with global columns too: one G for every window when the windows are alike
            G = _window_gram(w_ch[:1], Hzz, unk[:1], self.ridge)[:, 0] if pre["same_G"] else \
                _window_gram(w_ch, Hzz, unk, self.ridge)
            if nt and self.window_offsets:
                # per-window columns: solved with the window's initial states
                unk_o = np.concatenate([unk, np.ones((W, nt))], axis=1)
                rhs_o = np.einsum("wh,chwn->cwn", w_ch, g) * unk_o[None]
                zo = np.linalg.solve(_window_gram(w_ch, H, unk_o, self.ridge), rhs_o[..., None])[..., 0]
                z, offsets = zo[..., :n], zo[..., n:]
            elif nt and pre["same_G"]:
                # global columns, every window alike: one coupling block E for all windows
                E1 = np.matmul(w_ch[0], np.ascontiguousarray(H[:, :, :n, n:]).reshape(k, nch, n * nt))
                E1 = E1.reshape(k, n, nt) * unk[0][None, :, None]
                FF = np.einsum("wh,chpq->cpq", w_ch, H[:, :, n:, n:])
                rb = np.einsum("wh,chwp->cp", w_ch, g[..., n:])
                z, beta = _schur_alike(G, E1, rhs, FF, rb)
            elif nt:
                # global columns: Schur complement over the windows (variable projection)
                E = np.matmul(w_ch[None], np.ascontiguousarray(H[:, :, :n, n:]).reshape(k, nch, n * nt))
                E = E.reshape(k, W, n, nt) * unk[None, :, :, None]
                FF = np.einsum("wh,chpq->cpq", w_ch, H[:, :, n:, n:])
                rb = np.einsum("wh,chwp->cp", w_ch, g[..., n:])
                z, beta = _schur_solve(G, E, rhs, FF, rb)
            else:
                z = np.linalg.solve(G, rhs[..., None])[..., 0]  # (k, W, n), zero on known dims
        if not nt or self.window_offsets:
            beta = np.zeros((k, nt))
        v = z if not nt else np.concatenate(
            [z, offsets if self.window_offsets else np.broadcast_to(beta[:, None, :], (k, W, nt))], axis=-1)  # (k, W, na)
        if explicit == "native+sse":   # the errors and, from the same simulation, what the sse mode returns
            e = np.matmul(Phi, np.swapaxes(v, 1, 2)[:, None])
            e -= R4
            if pre["hole_lift"] is None:
                return z, beta, (e, self._quadratic_sse(pre, Phi, v, R4, H, g))
            eh = e * pre["hole_lift"][None]
            return z, beta, (e, np.einsum("chkw,chkw->ch", eh, eh))
        if explicit or pre["hole_lift"] is not None:
            e = np.matmul(Phi, np.swapaxes(v, 1, 2)[:, None])  # (k, nch, Lp, W)
            e -= R4
            if not explicit:  # holes in the link: only the measured samples count
                e *= pre["hole_lift"][None]
                return z, beta, np.einsum("chkw,chkw->ch", e, e)
            if explicit == "native":
                return z, beta, e
            return z, beta, e.reshape(k, nch, b, nb, W).transpose(0, 4, 3, 2, 1).reshape(k, W, Lp, nch)[:, :, :L]
        return z, beta, self._quadratic_sse(pre, Phi, v, R4, H, g)

    @staticmethod
    def _quadratic_sse(pre: dict, Phi: np.ndarray, v: np.ndarray, R4: np.ndarray, H: np.ndarray,
                       g: np.ndarray) -> np.ndarray:
        """Per-channel sums of squared errors (k, nch) of one chunk from the quadratic form
        ``||r||^2 - 2 v.g + v^T H v`` (no error array), recomputed explicitly for any candidate where
        that form loses more than ~8 digits."""
        rr = np.einsum("chkw,chkw->chw", R4, R4)
        vHv = np.einsum("chwn,cwn->chw", np.matmul(v[:, None], H), v)
        vg = np.einsum("chwn,cwn->chw", g, v)
        q = rr - 2.0 * vg + vHv  # (k, nch, W)
        if not pre["full_mask"]:
            q *= pre["mask_hw"][None]
            rr *= pre["mask_hw"][None]
        sse = q.sum(axis=-1)  # (k, nch)
        # the quadratic form cancels: trust it to ~1e-8 of ||r||^2, else compute those errors explicitly
        rr_sum = rr.sum(axis=-1)
        bad = ~(sse > 1e-8 * rr_sum) & np.isfinite(rr_sum)
        for c in np.flatnonzero(bad.any(axis=1)):  # one candidate at a time: views, no fancy-index copies
            e = np.matmul(Phi[c], v[c].T)  # (nch, Lp, W)
            e -= R4[c]
            if not pre["full_mask"]:
                e *= pre["mask_hw"][:, None, :]
            sse[c] = np.einsum("hkw,hkw->h", e, e)
        return sse

    def _markov_vp(self, sub: _Sub, pre: dict, Ad: np.ndarray, Bd: np.ndarray, Gam: np.ndarray):
        """:meth:`_lifted_vp` by Markov parameters (:func:`~groundstation.sysid.markov.markov_sse`); the
        candidates whose free response grows too far over a window for those products to keep their
        digits (NaN rows) are simulated as the lifted path does."""
        z, beta, sse = markov_sse(pre["markov"], Ad, Gam, pre["s_idx"])
        sse, x0 = sse * pre["mask_hw"][:, 0], pre["xm"][None] + z
        wild = np.flatnonzero(np.isnan(sse).any(axis=1))
        if wild.size:
            sse[wild], x0[wild], beta[wild] = self._lifted_vp(sub, pre, Ad[wild], Bd[wild], Gam[wild], explicit=False,
                                                              markov=False)
        return sse, x0, beta

    def _lifted_vp(self, sub: _Sub, pre: dict, Ad: np.ndarray, Bd: np.ndarray, Gam: np.ndarray, *, explicit: bool | str,
                   markov: bool = True):
        """Lifted simulation with the ``linear`` B entries solved by least squares (variable projection).

        For a given A the output is linear in those entries: each has a unit response ``F_p`` (input
        ``inp_p`` through the ZOH column ``Gamma[:, st_p]``, from rest), simulated like the forced
        response, and the coefficients ``beta`` (global) and the initial states (per window) come from
        one least-squares solve (Schur complement over the windows). Returns ``(e or sse, x0, beta)``.
        """
        if markov and not explicit and pre["markov"] is not None and not Bd.any():
            return self._markov_vp(sub, pre, Ad, Bd, Gam)
        C = Ad.shape[0]
        W, L, n = self.W, self.L, sub.n
        b, nb = pre["lb"], pre["lnb"]
        s_idx, nch, jv = pre["s_idx"], pre["nch"], pre["jv"]
        lin = pre["lin"]
        P = len(lin)
        m = Bd.shape[-1]
        K = n + b * m
        Lp, N = nb * b, nb * W
        pw = [np.broadcast_to(np.eye(n), (C, n, n)), Ad]
        for _ in range(b - 1):
            pw.append(np.matmul(Ad, pw[-1]))
        Apow = np.stack(pw, axis=1)  # (C, b+1, n, n)
        Ab = Apow[:, b]
        Obm = np.ascontiguousarray(Apow[:, :b][:, :, s_idx, :].transpose(0, 2, 1, 3))  # (C, nch, b, n)
        # forced response of the fixed B entries, as in _lifted
        AB = np.matmul(Apow[:, :b], Bd[:, None])  # (C, b, n, m)
        CABz = np.concatenate([AB[:, :, s_idx, :], np.zeros((C, 1, nch, m))], axis=1)
        Tq = CABz[:, pre["qidx"]]
        M = np.concatenate([Obm, Tq.transpose(0, 3, 1, 2, 4).reshape(C, nch, b, b * m)], axis=-1).reshape(C, nch * b, K)
        AbCb = np.concatenate([Ab, AB[:, ::-1].transpose(0, 2, 1, 3).reshape(C, n, b * m)], axis=-1)
        X = self._xbuf(pre, C, n)
        X[:, :n, :W] = pre["x0T"][None]
        for i in range(nb - 1):
            np.matmul(AbCb, X[:, :, i * W:(i + 1) * W], out=X[:, :n, (i + 1) * W:(i + 2) * W])
        # unit responses: one single-input lifted system per projected entry
        G1 = Gam[:, :, [st for st, _ in lin]]  # (C, n, P)
        AG = np.matmul(Apow[:, :b], G1[:, None])  # (C, b, n, P): A^q Gamma e_st
        CAGz = np.concatenate([AG[:, :, s_idx, :], np.zeros((C, 1, nch, P))], axis=1)
        Tp = CAGz[:, pre["qidx"]]  # (C, b(j), b(l), nch, P)
        Mp = np.concatenate([np.broadcast_to(Obm[:, None], (C, P, nch, b, n)),
                             Tp.transpose(0, 4, 3, 1, 2)], axis=-1).reshape(C, P, nch * b, n + b)
        AbCp = np.concatenate([np.broadcast_to(Ab[:, None], (C, P, n, n)),
                               AG[:, ::-1].transpose(0, 3, 2, 1)], axis=-1)  # (C, P, n, n + b)
        Xp = pre["X"].get("Xp")
        if Xp is None or Xp.shape[0] < C:
            Xp = np.empty((C, P, n + b, N))
            for q, (_, inp) in enumerate(lin):
                Xp[:, q, n:] = pre["Ut"][inp::m][None]
            pre["X"]["Xp"] = Xp
        Xp = Xp[:C]
        Xp[:, :, :n, :W] = 0.0
        for i in range(nb - 1):
            np.matmul(AbCp, Xp[:, :, :, i * W:(i + 1) * W], out=Xp[:, :, :n, (i + 1) * W:(i + 2) * W])
        Abc = np.empty((C, n, nb * n))
        Abc[:, :, :n] = np.eye(n)
        Abk, k = Ab, 1
        while k < nb:
            kk = min(k, nb - k)
            np.matmul(Abk, Abc[:, :, :kk * n], out=Abc[:, :, k * n:(k + kk) * n])
            k += kk
            if k < nb:
                Abk = np.matmul(Abk, Abk)
        Phi = np.matmul(Obm.reshape(C, nch * b, n), Abc).reshape(C, nch, b, nb, n)
        if jv < b:
            Phi[:, :, jv:, nb - 1] = 0.0
        Phi = Phi.reshape(C, nch, Lp, n)
        H = np.matmul(np.swapaxes(Phi, -1, -2), Phi)
        cc = max(1, min(C, int(self.chunk_bytes // (8 * (P + 1) * nch * b * N))))
        res = np.empty(((C, nch, Lp, W) if explicit == "native" else (C, W, L, nch)) if explicit else (C, nch))
        z = np.empty((C, W, n))
        beta = np.empty((C, P))
        for c0 in range(0, C, cc):
            c1 = min(C, c0 + cc)
            z[c0:c1], beta[c0:c1], res[c0:c1] = self._vp_chunk(pre, M[c0:c1], X[c0:c1], Mp[c0:c1], Xp[c0:c1],
                                                               Phi[c0:c1], H[c0:c1], explicit)
        return res, pre["xm"][None] + z, beta

    def _vp_chunk(self, pre, M, X, Mp, Xp, Phi, H, explicit):
        k, nch, Lp, n = Phi.shape
        P = Mp.shape[1]
        W, L, b, nb, jv = self.W, self.L, pre["lb"], pre["lnb"], pre["jv"]
        R = self._rbuf(pre, k, nch * b)
        np.matmul(M, X, out=R)
        np.subtract(pre["yT"][None], R, out=R)
        F = np.matmul(Mp, Xp)  # (k, P, nch b, N)
        if jv < b:
            R.reshape(k, nch, b, nb, W)[:, :, jv:, nb - 1] = 0.0
            F.reshape(k, P, nch, b, nb, W)[:, :, :, jv:, nb - 1] = 0.0
        R4 = R.reshape(k, nch, Lp, W)
        F5 = F.reshape(k, P, nch, Lp, W)
        w_ch, unk = pre["w_ch"], pre["unk"]
        g = np.matmul(np.swapaxes(R4, -1, -2), Phi)  # (k, nch, W, n)
        gF = np.matmul(np.swapaxes(F5, -1, -2), Phi[:, None])  # (k, P, nch, W, n)
        rhs = np.einsum("wh,chwn->cwn", w_ch, g) * unk[None]
        E = np.einsum("wh,cphwn->cwnp", w_ch, gF) * unk[None, :, :, None]  # (k, W, n, P)
        Fw = F5 * w_ch.T[None, None, :, None, :]
        FF = np.matmul(F.reshape(k, P, -1), np.swapaxes(Fw.reshape(k, P, -1), 1, 2))  # (k, P, P)
        rb = np.matmul(Fw.reshape(k, P, -1), R.reshape(k, -1, 1))[..., 0]  # (k, P)
        # the same normal matrix in every window when every window has the same channels and unknowns
        G = _window_gram(w_ch[:1], H, unk[:1], self.ridge)[:, 0] if pre["same_G"] else _window_gram(w_ch, H, unk, self.ridge)
        z, beta = _schur_solve(G, E, rhs, FF, rb)
        # e = Phi z + F beta - r, explicitly (no cancellation to guard)
        e = np.matmul(beta[:, None, :], F.reshape(k, P, -1)).reshape(k, nch, Lp, W)
        e -= R4
        e += np.matmul(Phi, np.swapaxes(z, 1, 2)[:, None])
        if explicit == "native":
            return z, beta, e
        if explicit:
            return z, beta, e.reshape(k, nch, b, nb, W).transpose(0, 4, 3, 2, 1).reshape(k, W, Lp, nch)[:, :, :L]
        if pre["hole_lift"] is not None:
            e *= pre["hole_lift"][None]
        elif not pre["full_mask"]:
            e *= pre["mask_hw"][None, :, None, :]
        return z, beta, np.einsum("chkw,chkw->ch", e, e)

    @property
    def state_updates_per_call(self) -> int:
        """State updates (one x[k+1] = A x[k] + B u[k]) per candidate per call."""
        return self.W * self.L

    def _run(self, theta: np.ndarray, *, sse: bool = False, native: bool = False):
        """Per subsystem ``(i, (e, x0[, beta]))``; e (C, W, L*nch) output errors, or with ``sse`` and no
        projected B entries the per-channel sums of squared errors (C, nch) in place of e; with
        ``native`` the output errors in the simulation's own layout (C, nch, Lp, W) (see
        :meth:`residuals_native`); with both, both: ``((e native, sse), x0, ...)``, for the lifted path only."""
        mode: bool | str = ("native+sse" if sse else "native") if native else not sse
        th = np.atleast_2d(np.asarray(theta, dtype=float))
        Ah, Bh, Av, Bv = build_matrices(th)
        out = []
        with np.errstate(all="ignore"):
            for i in self.subsystems:
                A, B = ((Ah, Bh), (Av, Bv))[i]
                n = A.shape[-1]
                pre = self._prep[i]
                if pre["lin"]:
                    # Ad and Gamma = int_0^dt e^(A s) ds in one exponential; Bd = Gamma B (exact ZOH)
                    Ad, Gam = discretize(A, np.broadcast_to(np.eye(n), A.shape), self.dt_s)
                    Bd = np.matmul(Gam, B)
                    e, x0, beta = self._lifted_vp(_SUBS[i], pre, Ad, Bd, Gam, explicit=mode)
                    if not sse and not native:
                        e = e.reshape(e.shape[0], self.W, self.L * pre["nch"])
                    out.append((i, (e, x0, beta, None)))
                    continue
                if self.forcing is not None:  # unit forcing columns on the forced states (ZOH like the inputs)
                    E = np.zeros(B.shape[:-1] + (len(_FORCED[i]),))
                    for c, (st, _) in enumerate(_FORCED[i]):
                        E[..., st, c] = 1.0
                    B = np.concatenate([B, E], axis=-1)
                Ad, Bd = discretize(A, B, self.dt_s)
                e, x0, delta = self._lifted(_SUBS[i], pre, Ad, Bd, explicit=mode)
                if not sse and not native:
                    e = e.reshape(e.shape[0], self.W, self.L * pre["nch"])
                out.append((i, (e, x0, None, delta if self.estimate_trim else None)))
        return out

    def solve_linear(self, theta: np.ndarray) -> dict[int, np.ndarray]:
        """Least-squares values (C, P) of the ``linear`` B entries per subsystem for candidates ``theta``."""
        return {i: r[2] for i, r in self._run(theta) if r[2] is not None}

    def solve_trim(self, theta: np.ndarray) -> dict[int, np.ndarray]:
        """With ``estimate_trim``: least-squares input offsets (C, m) per subsystem (normalised units, the
        model sees ``u - delta``: add ``delta * pwm_per_unit`` to the input trim PWM)."""
        return {i: r[3] for i, r in self._run(theta, sse=True) if r[3] is not None}

    def simulate(self, theta: np.ndarray, *, return_x0: bool = False):
        """yhat (C, W, L, 8) (unavailable channels hold the simulation too; x0 per subsystem if asked)."""
        res = self._run(theta)
        C = res[0][1][0].shape[0]
        yhat = np.zeros((C, self.W, self.L, 8))
        for i, (e, *_rest) in res:
            pre = self._prep[i]
            yhat[:, :, :, pre["o_idx"]] = (e + pre["yflat"][None]).reshape(C, self.W, self.L, pre["nch"])
        yhat = np.where(np.isfinite(yhat), yhat, 1e6)
        if return_x0:
            return yhat, {i: r[1] for i, r in res}
        return yhat

    def sse(self, theta: np.ndarray) -> np.ndarray:
        """Sum of squared output errors per candidate and channel over used samples; shape (C, 8)."""
        res = self._run(theta, sse=True)
        C = res[0][1][0].shape[0]
        out = np.zeros((C, 8))
        for i, (e, *_rest) in res:
            pre = self._prep[i]
            if e.ndim == 2:  # already per channel (lifted path)
                out[:, pre["o_idx"]] = e
                continue
            if not pre["full_mask"]:
                e *= pre["mflat"][None]
            e *= e
            # sum windows first (contiguous rows), then samples: far faster than one strided reduction
            nch = pre["nch"]
            out[:, pre["o_idx"]] = e.reshape(C, self.W, self.L * nch).sum(axis=1).reshape(C, self.L, nch).sum(axis=1)
        return np.where(np.isfinite(out), out, 1e300)

    def residuals_native(self, theta: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """Weighted output errors ``(yhat - y) / sigma_ch`` of C candidates as flat vectors (C, N), in
        the simulation's own layout (per subsystem: channel, padded sample, window) instead of
        :meth:`errors`' (window, sample, channel): no transpose and no 8-channel array. Unused samples
        (unavailable channel, padding of the last lifted block, holes of the link) are zero. For what does not depend on
        the order of the rows (``J^T J``, ``J^T r``, ``||r||``: the refinement's normal equations)."""
        return self.weigh_native({i: e for i, (e, *_rest) in self._run(theta, native=True)}, sigma, in_place=True)

    def weigh_native(self, errors: dict[int, np.ndarray], sigma: np.ndarray, *, in_place: bool = False) -> np.ndarray:
        """:meth:`residuals_native` of output errors already simulated in the native layout (per subsystem,
        as :meth:`native_errors_and_sse` gives them): the same numbers, weighted by ``sigma`` (8,).
        ``in_place``: overwrite ``errors`` (else they stay as they are, to be weighted again)."""
        s = np.asarray(sigma, dtype=float)
        parts = []
        for i, e in errors.items():
            pre = self._prep[i]
            w = pre["mask_hw"] / s[pre["o_idx"]][:, None]  # (nch, W): mask and channel weight
            if in_place:
                e *= w[None, :, None, :]
            else:
                e = e * w[None, :, None, :]
            if pre["hole_lift"] is not None:  # holes of the link: unmeasured samples are not residuals
                e *= pre["hole_lift"][None]
            parts.append(e.reshape(e.shape[0], -1))
        out = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
        if not np.isfinite(out).all():
            out = np.where(np.isfinite(out), out, 1e6)
        return out

    def native_errors_and_sse(self, theta: np.ndarray) -> tuple[dict[int, np.ndarray], np.ndarray]:
        """(output errors in the native layout per subsystem, unweighted, for :meth:`weigh_native`; what
        :meth:`sse` returns) of the candidates ``theta``, from ONE simulation where every subsystem is
        simulated by the lifted path (else two): the same numbers as the two calls."""
        if any(self._prep[i]["lin"] for i in self.subsystems):
            return {i: e for i, (e, *_rest) in self._run(theta, native=True)}, self.sse(theta)
        res = self._run(theta, native=True, sse=True)
        out = np.zeros((res[0][1][0][0].shape[0], 8))
        for i, ((_, sse), *_rest) in res:
            out[:, self._prep[i]["o_idx"]] = sse
        return {i: e for i, ((e, _), *_rest) in res}, np.where(np.isfinite(out), out, 1e300)

    def errors(self, theta: np.ndarray) -> np.ndarray:
        """Output errors ``yhat - y`` (C, W, L, 8), zero where a channel is unused."""
        res = self._run(theta)
        C = res[0][1][0].shape[0]
        out = np.zeros((C, self.W, self.L, 8))
        for i, (e, *_rest) in res:
            pre = self._prep[i]
            out[:, :, :, pre["o_idx"]] = (e * pre["mflat"][None]).reshape(C, self.W, self.L, pre["nch"])
        return np.where(np.isfinite(out), out, 1e6)


def kinematic_forcing(outputs: np.ndarray, output_trim: np.ndarray | None = None, g: float = 9.81) -> np.ndarray:
    """Measured body-axis kinematic and gravity terms that the hover linearisation (eq. 8) drops.

    ``outputs (..., 8)`` u v w p q r theta phi with trims removed; ``output_trim (8,)`` adds them back
    (absolute attitude and velocities). Returns ``(..., 3)`` accelerations on u, v, w (m/s^2)::

        u: r v - q w - g (sin theta - sin theta0 - (theta - theta0))
        v: p w - r u + g (sin phi cos theta - sin phi0 cos theta0 - (phi - phi0))
        w: q u - p v + g (cos phi cos theta - cos phi0 cos theta0)

    i.e. the rigid-body terms ``omega x V`` and the gravity components beyond eq. 8's ``-g theta`` and
    ``g phi`` (perturbations from the trim attitude ``theta0 phi0``); NaN (unmeasured channel) gives 0. Rotor-flapping terms (T sin a_s ...) are not
    measured and stay in the residual.
    """
    y = np.asarray(outputs, dtype=float)
    t = np.zeros(8) if output_trim is None else np.asarray(output_trim, dtype=float)
    u, v, w, p, q, r, th, ph = (np.nan_to_num(y[..., j]) + t[j] for j in range(8))
    th0, ph0 = t[6], t[7]
    out = np.empty(y.shape[:-1] + (3,))
    out[..., 0] = r * v - q * w - g * (np.sin(th) - np.sin(th0) - (th - th0))
    out[..., 1] = p * w - r * u + g * (np.sin(ph) * np.cos(th) - np.sin(ph0) * np.cos(th0) - (ph - ph0))
    out[..., 2] = q * u - p * v + g * (np.cos(ph) * np.cos(th) - np.cos(ph0) * np.cos(th0))
    return out


def simulate_windows(theta: np.ndarray, inputs: np.ndarray, outputs: np.ndarray, dt_s: float,
                     available: np.ndarray | None = None, *, estimate_all_initial: bool = False) -> np.ndarray:
    """Windowed simulation of C candidates on W windows: returns ``yhat (C, W, L, 8)``.

    See the module docstring for the array shapes and the initial-state estimate.
    """
    sim = WindowSimulator(inputs, outputs, dt_s, available, estimate_all_initial=estimate_all_initial)
    return sim.simulate(theta)


def objective(yhat: np.ndarray, y: np.ndarray, available: np.ndarray | None = None) -> np.ndarray:
    """Paper eq. (11): ``F = sum_ch ||y - yhat|| / ||y - mean(y)||`` over all windows; shape (C,).

    yhat (C, W, L, 8); y (W, L, 8) (NaN or unavailable channels are skipped).
    """
    yy = np.asarray(y, dtype=float)
    mask = _avail_2d(available, yy)
    y0 = np.where(mask[:, None, :], np.nan_to_num(yy), 0.0)
    scales = channel_scales(y0, mask)
    used = mask.any(axis=0)
    err = (np.asarray(yhat) - y0[None]) * mask[None, :, None, :]
    num = np.sqrt((err ** 2).sum(axis=(1, 2)))  # (C, 8)
    F = (num / scales[None, :])[:, used].sum(axis=1)
    return np.where(np.isfinite(F), F, 1e12)


def objective_from_sse(sim: WindowSimulator, theta: np.ndarray) -> np.ndarray:
    """Eq. (11) for C candidates without assembling yhat; shape (C,)."""
    return objective_of_sse(sim, sim.sse(theta))


def objective_of_sse(sim: WindowSimulator, sse: np.ndarray) -> np.ndarray:
    """Eq. (11) of C candidates from their per-channel sums of squared errors (C, 8) (:meth:`WindowSimulator.sse`)."""
    used = sim.mask.any(axis=0)
    F = (np.sqrt(sse) / sim.scales[None, :])[:, used].sum(axis=1)
    return np.where(np.isfinite(F), F, 1e12)


def fitness(F: np.ndarray) -> np.ndarray:
    """Paper eq. (12): ``1 / (1 + F)``."""
    return 1.0 / (1.0 + np.asarray(F, dtype=float))
