"""Held-out scoring of the base model and of augmented models on rotating windows (k-fold).

The flight is cut into windows of ``window_s``; window i belongs to fold ``i % folds``, so every
excitation of the flight-test card is in some training fold. A model variant (inputs transformed,
outputs delayed, extra forcing ...) is simulated once at the base parameters ``theta0``; the base
parameters are then re-fitted on the training folds by one regularised Gauss-Newton step with the
Jacobian of the base model (computed once, batched finite differences, each subsystem's parameters on
that subsystem alone), together with the variant's
linear parameters (extra columns), and the re-fitted variant is scored on the held-out fold.
The base model goes through the same step, so base and variants are compared on equal terms.

Residuals are weighted per channel by 1/scale (channel standard deviation), i.e. the paper's
eq.-11 normalisation; samples before ``start_s`` in each window (initial transient) are ignored.

Array conventions: windows (W, L, ...) as in :mod:`groundstation.gap.linsim`; held-out costs (W, 8).
Pure numpy; no IO.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from groundstation.errors import GapError
from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.linsim import HORIZONTAL, PARAM_BLOCKS, VERTICAL, simulate
from groundstation.sysid.model import N_PARAMS


@dataclass(frozen=True)
class SegmentArrays:
    """One uniformly sampled in-air segment (the fields of ``dsp.prepare.Segment`` the diagnosis uses).

    Attributes: ``t_s (n,)``, ``inputs (n, 4)``, ``outputs (n, 8)`` smoothed, ``outputs_raw (n, 8)``,
    ``alt_m (n,)`` (NaN if unknown), ``flight`` index, ``measured (n, 8)`` bool (False in holes of
    the link, where the values are bridged; None: all measured), ``bridged (n,)`` bool (True where
    the inputs are a straight line over a hole; None: none).
    """

    t_s: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray
    outputs_raw: np.ndarray
    alt_m: np.ndarray
    flight: int = 0
    measured: np.ndarray | None = None
    bridged: np.ndarray | None = None

    def raw_measured(self) -> np.ndarray:
        """``outputs_raw`` with NaN in the holes of the link (for noise estimates)."""
        return self.measured_only(self.outputs_raw)

    def measured_only(self, x: np.ndarray) -> np.ndarray:
        """``x`` (n, k) with NaN at the samples in holes: per channel for outputs (k = 8), any hole for inputs."""
        if self.measured is None:
            return x
        m = self.measured if x.shape[1] == 8 else self.measured.all(axis=1, keepdims=True)
        return np.where(m, x, np.nan)


def window_starts(segments: list[SegmentArrays], length: int) -> list[tuple[int, int]]:
    """(segment index, first sample) of every whole window of ``length`` samples."""
    out = []
    for si, seg in enumerate(segments):
        n = seg.t_s.shape[0]
        for i0 in range(0, n - length + 1, length):
            out.append((si, i0))
    return out


def cut(arrays: list[np.ndarray], starts: list[tuple[int, int]], length: int) -> np.ndarray:
    """Stack windows: arrays per segment (n, ...) -> (W, length, ...)."""
    return np.stack([arrays[si][i0:i0 + length] for si, i0 in starts])


class JacobianMemo:
    """The last ``size`` base states of a family of evaluators (the residual ``r0``, the column norms, the
    column-normalised Jacobian and its normal matrices), by everything :meth:`Evaluator.set_theta` reads:
    the parameters, the windowed inputs and outputs, weights, masks and nuisance columns. Evaluators built
    from one another for the same data and parameters (a re-fit's end point, then a context built on it)
    then form the Jacobian once; a state is the same arrays, never recomputed differently. Bounded, and
    :meth:`clear` drops the states when the diagnosis is done; a copy in another process starts empty."""

    #: refinements remembered (end point and cost, a few hundred bytes each)
    REFINED = 16

    def __init__(self, size: int = 2):
        self.size = int(size)
        self._states: OrderedDict[bytes, tuple[np.ndarray, ...]] = OrderedDict()
        self._refined: OrderedDict[bytes, tuple[np.ndarray, float]] = OrderedDict()

    def get(self, key: bytes) -> tuple[np.ndarray, ...] | None:
        state = self._states.get(key)
        if state is not None:
            self._states.move_to_end(key)
        return state

    def put(self, key: bytes, state: tuple[np.ndarray, ...]) -> None:
        self._states[key] = state
        self._states.move_to_end(key)
        while len(self._states) > self.size:
            self._states.popitem(last=False)

    def refined(self, key: bytes) -> tuple[np.ndarray, float] | None:
        """The end point and cost of a refinement already run from the state ``key`` (see
        :meth:`Evaluator.refine`), or None."""
        return self._refined.get(key)

    def put_refined(self, key: bytes, theta: np.ndarray, cost: float) -> None:
        self._refined[key] = (theta.copy(), cost)
        while len(self._refined) > self.REFINED:
            self._refined.popitem(last=False)

    def clear(self) -> None:
        self._states.clear()
        self._refined.clear()

    def __getstate__(self) -> dict:
        # a copy sent to a worker process starts empty: the states are large and only save work here
        return {"size": self.size}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["size"])  # type: ignore[misc]


class Evaluator:
    """Windows of a flight, the base model, its Jacobian and k-fold held-out scoring.

    Parameters
    ----------
    segments : list of SegmentArrays
    dt_s : float, sample period (s)
    theta0 : array (31,), base parameters
    available : array (8,) bool, measured output channels
    window_s, folds, start_s : windowing (s), number of folds, ignored start of each window (s)
    memo : JacobianMemo or None, base states shared with the evaluators built from this one (None: none)
    """

    def __init__(self, segments: list[SegmentArrays], dt_s: float, theta0: np.ndarray,
                 available: np.ndarray, *, window_s: float = DiagnoseConfig.window_s,
                 folds: int = DiagnoseConfig.folds, start_s: float = DiagnoseConfig.window_start_s,
                 ridge: float = DiagnoseConfig.ridge, memo: JacobianMemo | None = None):
        self.segments = segments
        self.memo = memo
        self.dt_s = float(dt_s)
        self.theta0 = np.asarray(theta0, float).copy()
        self.ridge = float(ridge)
        self.start_s = float(start_s)   # as given (the evaluators built from this one copy it)
        # optional per-window nuisance columns (W, L, 8, K) fitted with the initial states, with a
        # prior precision (K,): used to re-identify the base model under a disturbance hypothesis
        self.nuisance: np.ndarray | None = None
        self.nuisance_prec: np.ndarray | None = None
        self.available = np.asarray(available, bool)
        self.L = max(int(round(window_s / dt_s)), 20)
        self.starts = window_starts(segments, self.L)
        if len(self.starts) < 2 * folds:
            raise GapError(f"too little in-air data for diagnosis: {len(self.starts)} windows of "
                             f"{window_s:g} s (need at least {2 * folds})")
        self.W = len(self.starts)
        self.folds = folds
        self.fold = np.arange(self.W) % folds
        self.start = min(int(round(start_s / dt_s)), self.L // 4)
        self.U = self.cut([s.inputs for s in segments])
        self.Y = self.cut([s.outputs for s in segments])
        self.Yraw = self.cut([s.outputs_raw for s in segments])
        self.T = self.cut([s.t_s for s in segments])
        # samples measured (False in holes of the link): residuals and sensitivities count only those
        self.holes = any(s.measured is not None for s in segments)
        self.M = (self.cut([np.ones((s.t_s.shape[0], 8), bool) if s.measured is None else s.measured
                            for s in segments]) if self.holes else None)
        self.flight = np.array([segments[si].flight for si, _ in self.starts])
        yv = self.Y[:, self.start:, :].reshape(-1, 8)
        sc = yv.std(axis=0)
        sc = np.where(self.available & (sc > 0), sc, 1.0)
        self.scale = sc
        self.w8 = np.where(self.available, 1.0 / sc, 0.0)
        # blocks of ~0.5 s inside windows: the resampling unit of the significance tests
        self.block = max(int(round(0.5 / dt_s)), 5)
        self.n_blocks = self.L // self.block
        self.last_blocks = np.zeros((self.W, self.n_blocks))
        self.mask = np.zeros(self.L, bool)
        self.mask[self.start:] = True
        #: weights of the residuals: the window's start ignored, holes of the link ignored; (L, 1) or (W, L, 8)
        self.wmask = self.mask[:, None] if self.M is None else (self.mask[None, :, None] & self.M).astype(float)
        #: samples scored: (L,) or, with holes, (W, L, 8) bool
        self.score_mask = self.mask if self.M is None else self.mask[None, :, None] & self.M
        # per-window, per-channel energy of the (weighted) target about the overall mean, over the
        # samples the residuals count (measured ones: a ratio of the two then reads the same with holes)
        yc = (self.Y - self.Y[:, self.start:].reshape(-1, 8).mean(0)) * self.w8 * self.wmask
        self.energy = (yc[:, self.start:] ** 2).sum(axis=1)  # (W, 8)
        self.set_theta(self.theta0)

    # ---------------------------------------------------------------------------------------
    def cut(self, arrays: list[np.ndarray]) -> np.ndarray:
        return cut(arrays, self.starts, self.L)

    def simulate(self, theta: np.ndarray, U: np.ndarray | None = None, Y: np.ndarray | None = None,
                 F: np.ndarray | None = None, nuisance: np.ndarray | None = None,
                 stop: int | None = None) -> np.ndarray:
        """yhat (C, W, L, 8) of ``theta`` (C, 31) on the windows (optionally modified U, Y, forcing F).

        ``stop``: initial states (and nuisance) are fitted on samples ``start:stop`` only.
        """
        if nuisance is None and self.nuisance is not None:
            nuisance = self.nuisance
        out = simulate(theta, self.U if U is None else U, self.Y if Y is None else Y, self.dt_s,
                       forcing=F, weights=self.w8, available=self.available, nuisance=nuisance,
                       start=self.start, stop=stop, nuisance_prec=self.nuisance_prec)
        assert isinstance(out, np.ndarray)
        return out

    def residual(self, yhat: np.ndarray, Y: np.ndarray | None = None) -> np.ndarray:
        """Weighted, masked residual (..., W, L, 8) of a simulation against Y (default: measured)."""
        Yt = self.Y if Y is None else Y
        r = (Yt - yhat) * self.w8
        return r * self.wmask

    def set_theta(self, theta: np.ndarray) -> None:
        """Set the base parameters. The base state at them (residual and Jacobian, batched finite
        differences; or :attr:`memo`'s when an evaluator of the family had this state) is formed on
        first use: an evaluator whose parameters or data are set again before it is used (built, then
        given nuisance columns or a changed target) never forms the one in between."""
        self.theta0 = np.asarray(theta, float).copy()
        self._state: tuple[np.ndarray, ...] | None = None

    @property
    def r0(self) -> np.ndarray:
        """Weighted, masked residual (W, L, 8) of the base parameters."""
        return self._base()[0]

    @property
    def col(self) -> np.ndarray:
        """Column norms (31,) of the base Jacobian."""
        return self._base()[1]

    @property
    def Jn(self) -> np.ndarray:
        """Column-normalised base Jacobian per window (W, L 8, 31), formed once for every held-out re-fit."""
        return self._base()[2]

    @property
    def JtJ(self) -> np.ndarray:
        """Its normal matrix per window (W, 31, 31)."""
        return self._base()[3]

    def _base(self) -> tuple[np.ndarray, ...]:
        if self._state is None:
            key = self._state_key() if self.memo is not None else b""
            state = self.memo.get(key) if self.memo is not None else None
            if state is None:
                state = self._base_state()
                if self.memo is not None:
                    self.memo.put(key, state)
            self._state = state
        return self._state

    def _state_key(self) -> bytes:
        """Digest of everything the base state depends on (see :class:`JacobianMemo`)."""
        h = hashlib.blake2b(digest_size=20)
        h.update(np.array([self.dt_s, self.start, self.W, self.L], float).tobytes())
        for a in (self.theta0, self.U, self.Y, self.w8, self.wmask, self.available, self.nuisance, self.nuisance_prec):
            if a is None:
                h.update(b"none")
            else:
                h.update(str((a.dtype, a.shape)).encode())
                h.update(a.tobytes())
        return h.digest()

    def _base_state(self) -> tuple[np.ndarray, ...]:
        """(``r0``, ``col``, ``Jn``, ``JtJ``): the base residual and the Jacobian at ``theta0`` (batched
        finite differences)."""
        h = 1e-4 * np.maximum(np.abs(self.theta0), 1e-2)
        nuisance_blocks = self._nuisance_blocks()
        if nuisance_blocks is None:  # columns fitted across both subsystems: one joint batch
            batch = np.vstack([self.theta0[None], self.theta0[None] + np.diag(h)])
            r = self.residual(self.simulate(batch))
            # d residual / d theta ; column-normalised for conditioning
            J = (r[1:] - r[0][None]) / h[:, None, None, None]  # (31, W, L, 8)
            # C order: a worker process gets this array unpickled in C order, and products of another
            # layout round differently (the report must not depend on --jobs)
            return (r[0], *self._prepare_folds([(np.arange(N_PARAMS), np.arange(8),
                                                 np.ascontiguousarray(np.moveaxis(J, 0, -1)))]))
        gram: dict = {}
        y0 = simulate(self.theta0, self.U, self.Y, self.dt_s, weights=self.w8, available=self.available,
                      start=self.start, gram=gram, nuisance=self.nuisance, nuisance_prec=self.nuisance_prec)
        assert isinstance(y0, np.ndarray)
        return (self.residual(y0)[0], *self._prepare_folds(self._block_jacobian(h, gram, nuisance_blocks)))

    def _nuisance_blocks(self) -> tuple[bool, bool] | None:
        """Which subsystems' outputs the nuisance columns reach ((False, False) without any); None when
        they are per window and reach both (the Jacobian is then simulated in one joint batch)."""
        if self.nuisance is None:
            return False, False
        reach = tuple(bool(self.nuisance[..., list(b.outputs), :].any()) for b in (HORIZONTAL, VERTICAL))
        return None if self.nuisance.shape[0] != 1 or all(reach) else (reach[0], reach[1])

    def _block_jacobian(self, h: np.ndarray, gram: dict,
                        nuisance_blocks: tuple[bool, bool]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """d residual / d theta by finite differences ``h`` (31,), each subsystem's parameters simulated
        on that subsystem alone (the other's outputs do not depend on them: zero there), the initial
        states' ridge that of both (``gram``: the base simulation's, see
        :func:`groundstation.gap.linsim.simulate`): the same numbers as one simulation of both to
        round-off. Per block: (parameter indices (k,), output channels (ny,), d residual (W, L, ny, k))."""
        pieces = []
        blocks = ((HORIZONTAL, VERTICAL, PARAM_BLOCKS[0], nuisance_blocks[0]),
                  (VERTICAL, HORIZONTAL, PARAM_BLOCKS[1], nuisance_blocks[1]))
        for block, other, idx, with_nuisance in blocks:
            oc = np.array(block.outputs)
            theirs = [j for j, st in enumerate(gram["unknown"]) if st in other.states]
            extra = (float(gram["diag"][0, theirs].sum()), len(theirs))
            if self.nuisance is not None and not with_nuisance:  # the other block's unknowns
                extra = (extra[0] + float(gram["nuisance_diag"].sum()), extra[1] + self.nuisance.shape[-1])
            batch = np.vstack([self.theta0[None], self.theta0[None] + np.diag(h)[idx]])
            yh = simulate(batch, self.U, self.Y, self.dt_s, weights=self.w8, available=self.available,
                          start=self.start, block=block, ridge_extra=extra,
                          nuisance=self.nuisance if with_nuisance else None,
                          nuisance_prec=self.nuisance_prec if with_nuisance else None)
            wm = self.wmask if self.wmask.shape[-1] == 1 else self.wmask[..., oc]
            r = (self.Y[..., oc] - yh) * self.w8[oc] * wm
            r[1:] -= r[0]
            r[1:] /= h[idx, None, None, None]
            pieces.append((idx, oc, np.ascontiguousarray(np.moveaxis(r[1:], 0, -1))))
        return pieces

    def _prepare_folds(self, pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(``col``, ``Jn``, ``JtJ``): column norms, the column-normalised Jacobian per window (W, L 8, 31)
        and its normal matrix per window (W, 31, 31) from the Jacobian's non-zero blocks ``pieces``
        (parameter indices, output channels, d residual (W, L, ny, k)); zero elsewhere."""
        W = self.W
        col = np.empty(N_PARAMS)
        Jn = np.zeros((W, self.L, 8, N_PARAMS)) if len(pieces) > 1 else None
        JtJ = np.zeros((W, N_PARAMS, N_PARAMS))
        for idx, oc, P in pieces:
            Pf = P.reshape(W, -1, len(idx))
            col[idx] = np.sqrt((Pf ** 2).sum(axis=(0, 1))) + 1e-30
            Pn = Pf / col[idx]
            JtJ[:, idx[:, None], idx[None, :]] = np.matmul(np.swapaxes(Pn, 1, 2), Pn)
            if Jn is None:
                Jn = Pn.reshape(W, self.L, 8, N_PARAMS)
            else:
                Jn[:, :, oc[:, None], idx[None, :]] = Pn.reshape(P.shape)
        assert Jn is not None
        return col, Jn.reshape(W, -1, N_PARAMS), JtJ

    # ---------------------------------------------------------------------------------------
    def heldout(self, r: np.ndarray, X: np.ndarray | None = None,
                ridge: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Held-out costs of a variant after the k-fold re-fit.

        Parameters
        ----------
        r : array (W, L, 8), weighted residual of the variant at theta0
        X : array (W, L, 8, K) or None, weighted sensitivities d yhat / d b of the variant's linear
            parameters b (the re-fit solves r ~ -J d_theta + X b)
        ridge : Levenberg damping relative to the mean diagonal of the normal matrix (default: self.ridge)

        Returns
        -------
        sse : array (W, 8), held-out sum of squared weighted residuals per window and channel
        train : array (folds,), training cost of each fold's re-fit
        coef : array (folds, K), the fitted linear parameters per fold (K = 0 if X is None)
        """
        ridge = self.ridge if ridge is None else ridge
        W = self.W
        rf = r.reshape(W, -1)
        Jn = self.Jn
        K = 0 if X is None else X.shape[-1]
        # normal matrices per window in blocks: J^T J is the base model's (formed once), only the
        # variant's own columns X are new
        JtT = np.swapaxes(Jn, 1, 2)
        Mtr = np.matmul(JtT, rf[..., None])[..., 0]  # (W, 31)
        if K:
            assert X is not None
            Xf = X.reshape(W, -1, K)
            xs = np.sqrt((Xf ** 2).sum(axis=(0, 1))) + 1e-30
            Xn = Xf / xs
            XtT = np.swapaxes(Xn, 1, 2)
            JtX = np.matmul(JtT, Xn)  # (W, 31, K)
            MtM = np.empty((W, N_PARAMS + K, N_PARAMS + K))
            MtM[:, :N_PARAMS, :N_PARAMS] = self.JtJ
            MtM[:, :N_PARAMS, N_PARAMS:] = JtX
            MtM[:, N_PARAMS:, :N_PARAMS] = np.swapaxes(JtX, 1, 2)
            MtM[:, N_PARAMS:, N_PARAMS:] = np.matmul(XtT, Xn)
            Mtr = np.concatenate([Mtr, np.matmul(XtT, rf[..., None])[..., 0]], axis=1)
        else:
            xs = np.ones(0)
            MtM = self.JtJ
        P = N_PARAMS + K
        rr = (rf ** 2).sum(axis=1)
        train = np.empty(self.folds)
        coef = np.zeros((self.folds, K))
        D = np.empty((P, self.folds))
        for f in range(self.folds):
            tr = self.fold != f
            G = MtM[tr].sum(0)
            b = Mtr[tr].sum(0)
            lam = ridge * np.trace(G) / P
            d = np.linalg.solve(G + lam * np.eye(P), b)
            train[f] = rr[tr].sum() - 2 * d @ b + d @ G @ d
            D[:, f] = d
            if K:
                coef[f] = d[N_PARAMS:] / xs
        # every window's prediction under every fold's step in one product; each window keeps its own fold's
        fit = np.matmul(Jn, D[:N_PARAMS])  # (W, n, folds)
        if K:
            fit += np.matmul(Xn, D[N_PARAMS:])
        e = rf - np.take_along_axis(fit, self.fold[:, None, None], axis=2)[..., 0]
        e2 = e.reshape(W, self.L, 8) ** 2
        sse = e2.sum(axis=1)
        blocks = self.to_blocks(e2.sum(axis=2))
        self.last_blocks = blocks
        return sse, train, coef

    def heldout_many(self, rs: np.ndarray, ridge: float | None = None,
                     chunk_bytes: float = 8e6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`heldout` (no linear columns) of V variants at once: ``rs`` (V, W, L, 8).

        The re-fit's normal matrix is the base model's for every variant, so each fold is factored
        once and the variants are its right-hand sides; the Jacobian is read once per chunk of
        variants, not twice per variant. Returns ``sse`` (V, W, 8), ``train`` (V, folds) and the
        held-out cost per block (V, W, n_blocks), the same numbers as V calls of :meth:`heldout`
        to round-off.
        """
        ridge = self.ridge if ridge is None else ridge
        V, W = rs.shape[0], self.W
        Jn = self.Jn
        JtT = np.swapaxes(Jn, 1, 2)
        P = N_PARAMS
        Gf, lams = [], []
        for f in range(self.folds):
            G = self.JtJ[self.fold != f].sum(0)
            lams.append(ridge * np.trace(G) / P)
            Gf.append(G)
        sse = np.empty((V, W, 8))
        blocks = np.empty((V, W, self.n_blocks))
        train = np.empty((V, self.folds))
        vc = max(1, int(chunk_bytes // max(rs[0].nbytes, 1)))
        for v0 in range(0, V, vc):
            v1 = min(V, v0 + vc)
            R = rs[v0:v1].reshape(v1 - v0, W, -1)
            Rt = np.moveaxis(R, 0, 2).copy(order="C")  # (W, n, Vc), a copy: corrected in place below
            Mtr = np.matmul(JtT, Rt)  # (W, 31, Vc)
            rr = (R ** 2).sum(axis=2)  # (Vc, W)
            Dw = np.empty((W, P, v1 - v0))
            for f in range(self.folds):
                tr = self.fold != f
                G = Gf[f]
                b = Mtr[tr].sum(0)  # (31, Vc)
                d = np.linalg.solve(G + lams[f] * np.eye(P), b)
                train[v0:v1, f] = rr[:, tr].sum(axis=1) - 2 * (d * b).sum(0) + (d * (G @ d)).sum(0)
                Dw[~tr] = d
            Rt -= np.matmul(Jn, Dw)  # held-out residual of every window under its own fold's re-fit
            e2 = np.moveaxis(Rt, 2, 0).reshape(v1 - v0, W, self.L, 8) ** 2
            sse[v0:v1] = e2.sum(axis=2)
            blocks[v0:v1] = self.to_blocks(e2.sum(axis=3).reshape(-1, self.L)).reshape(v1 - v0, W, -1)
        return sse, train, blocks

    def to_blocks(self, e2: np.ndarray) -> np.ndarray:
        """Sum (W, L) squared residuals over blocks of ``block`` samples: (W, n_blocks)."""
        Wn = e2.shape[0]
        return e2[:, : self.n_blocks * self.block].reshape(Wn, self.n_blocks, self.block).sum(axis=2)

    def heldout_residual(self, r: np.ndarray, ridge: float | None = None) -> np.ndarray:
        """Weighted held-out residual (W, L, 8) of the base-model k-fold re-fit (for locating the gap)."""
        ridge = self.ridge if ridge is None else ridge
        W = self.W
        rf = r.reshape(W, -1)
        Jn = self.Jn
        Mtr = np.matmul(np.swapaxes(Jn, 1, 2), rf[..., None])[..., 0]
        out = np.empty_like(rf)
        for f in range(self.folds):
            tr = self.fold != f
            te = ~tr
            G = self.JtJ[tr].sum(0)
            b = Mtr[tr].sum(0)
            lam = ridge * np.trace(G) / N_PARAMS
            d = np.linalg.solve(G + lam * np.eye(N_PARAMS), b)
            out[te] = rf[te] - np.einsum("wni,i->wn", Jn[te], d)
        return out.reshape(r.shape)

    def fit_all(self, r: np.ndarray, X: np.ndarray | None = None,
                ridge: float = DiagnoseConfig.refine_ridge) -> tuple[np.ndarray, np.ndarray]:
        """One Gauss-Newton step on all windows: returns (d_theta (31,), linear params (K,))."""
        W = self.W
        rf = r.reshape(W, -1)
        Jn = self.Jn
        K = 0 if X is None else X.shape[-1]
        if X is not None and K:
            Xf = X.reshape(W, -1, K)
            xs = np.sqrt((Xf ** 2).sum(axis=(0, 1))) + 1e-30
            M = np.concatenate([Jn, Xf / xs], axis=2)
        else:
            xs = np.ones(0)
            M = Jn
        Mf = M.reshape(-1, M.shape[2])
        G = self.JtJ.sum(0) if not K else Mf.T @ Mf  # the base model's: the per-window ones summed
        b = Mf.T @ rf.ravel()
        lam = ridge * np.trace(G) / M.shape[2]
        d = np.linalg.solve(G + lam * np.eye(M.shape[2]), b)
        # residual r = y - yhat; r ~ M d  =>  yhat_new = yhat + M d  => theta_new = theta0 - d/col
        return -d[:N_PARAMS] / self.col, d[N_PARAMS:] / xs

    def refine(self, iterations: int, ridge: float = DiagnoseConfig.refine_ridge) -> float:
        """Levenberg-Marquardt refinement of theta0 on all windows (``ridge``: the starting damping,
        ``[diagnose] refine_ridge``); returns the final total cost.

        A refinement is a function of the state it starts from (:meth:`_state_key`), the iterations
        and the damping: with a :attr:`memo`, one already run in the family (the same effect applied
        to the same data from the same parameters, by two stages) is not run again; its end point is
        set (its base state formed once, or taken from the memo)."""
        if self.memo is None:
            return self._refine(iterations, ridge)
        key = self._state_key() + np.array([iterations, ridge], float).tobytes()
        done = self.memo.refined(key)
        if done is not None:
            theta, cost = done
            if not np.array_equal(theta, self.theta0):
                self.set_theta(theta)
            return cost
        cost = self._refine(iterations, ridge)
        self.memo.put_refined(key, self.theta0, cost)
        return cost

    def _refine(self, iterations: int, ridge: float) -> float:
        cost = float((self.r0 ** 2).sum())
        lam = ridge
        for _ in range(iterations):
            dth, _ = self.fit_all(self.r0, None, ridge=lam)
            cand = self.theta0 + dth
            rc = self.residual(self.simulate(cand))[0]
            c = float((rc ** 2).sum())
            if np.isfinite(c) and c < cost:
                self.set_theta(cand)
                if cost - c < 1e-4 * cost:
                    cost = c
                    break
                cost = c
                lam = max(lam / 3, 1e-6)
            else:
                lam *= 10
        return cost
