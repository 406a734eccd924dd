"""The hypothesis library: one augmented model per effect of the catalogue (docs/gap-report.md).

Each ``scan_*`` function builds the variants of one effect (the base model plus the effect, for
every candidate channel and every value of the effect's nonlinear parameter on a grid referred to
the data: delays in seconds, slew limits and deadband widths as quantiles of the channel's own
input rate / amplitude), scores each variant on held-out windows after the k-fold re-fit of the
base parameters and of the effect's linear parameters (:meth:`Evaluator.heldout`), and selects
channel and grid value *inside each fold on the training cost* (nested selection), so the held-out
cost of the hypothesis carries the penalty for what it adds.

A :class:`Context` built with ``given`` columns (another effect's linear columns) runs the same
scans conditionally on that effect (encompassing tests); :func:`apply_input_effect` re-applies the
selected variant of an input effect to the data, :func:`rescan_input_effect` scans its channel
again in another context (around a re-identified base, or given another effect).

``rotor_vibration`` is not a model change at the sample rate of the cost: it is tested by
:mod:`groundstation.gap.fingerprints` on the raw residual spectrum. Pure numpy; no IO.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from groundstation.errors import GapError
from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.evaluate import Evaluator, SegmentArrays
from groundstation.gap.linsim import free_responses, full_matrices
from groundstation.gap.linsim import simulate as lsim
from groundstation.sysid.model import INPUTS

#: Candidate delays / latencies (s); the grid is physical time, not samples.
DELAY_GRID_S = (0.02, 0.04, 0.06, 0.08, 0.10, 0.13, 0.16, 0.20, 0.25)
#: Slew limits as quantiles of the channel's own |input rate| ...
RATE_QUANTILES = (0.6, 0.75, 0.85, 0.92, 0.96, 0.98, 0.99, 0.995, 0.998)
#: ... and as fractions of its largest |input rate|: on a card of steps (multisteps, no sweeps) the
#: quantiles are set by the small corrections between the steps (a few input quanta per sample)
#: and a slew limit acts only on the step edges, far above every quantile. Successive fractions are
#: no more than about 1.4x apart, the delay grid's own resolution (0.04 -> 0.06 s is 1.5x): a slew
#: limit between two values twice apart fits worse than the delay that mimics it, and is read as one
RATE_OF_MAX = (0.05, 0.07, 0.1, 0.14, 0.2, 0.27, 0.35, 0.5, 0.7)
#: Deadband half-widths as quantiles of the channel's own |input|.
DEADBAND_QUANTILES = (0.1, 0.2, 0.35, 0.5, 0.7, 0.85)
#: ... and as multiples of the channel's input standard deviation.
DEADBAND_STD = (0.1, 0.25, 0.5, 0.75, 1.0)
#: Deadzone centres relative to the input trim, as fractions of the half-width: the trim is the
#: median input in the air, and inside a wide band the pilot's stick rests anywhere (nothing
#: answers it there), so the median need not be the band's centre
DEADBAND_CENTRE = (-0.5, 0.0, 0.5)
#: Ground-effect decay heights relative to the smallest height flown (m, added to it).
GROUND_DECAY_M = (0.25, 0.5, 1.0, 2.0)

VEL = (0, 1, 2)
#: channels on which an air-mass motion is scored: the outputs of the horizontal block (u v p q theta
#: phi); a horizontal air velocity leaves w and r as they are
GUST_CHANNELS = (0, 1, 3, 4, 6, 7)
#: grid (s) of the per-window air velocity (linear between the grid times)
GUST_GRID_S = 0.1
#: time scales (s) of the air velocity's Gauss-Markov prior the data choose from
GUST_TAU_S = (0.3, 1.0, 3.0)
#: its intensities, in multiples of the measured horizontal speed
GUST_SIGMA = (0.25, 0.5, 1.0, 2.0)
RATE_CH = {"p": 3, "q": 4, "r": 5}


@dataclass
class Hypothesis:
    """Result of one effect's scan."""

    effect: str
    input: str | None = None
    output: str | None = None
    estimate: dict[str, float] = field(default_factory=dict)
    sse: np.ndarray | None = None  # (W, 8) nested held-out cost
    channels: tuple[int, ...] = ()  # outputs the effect acts on most
    evidence: str = ""
    testable: bool = True
    reason: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# signal transforms (segment level, (n,) arrays)
# ---------------------------------------------------------------------------------------------
def shift(x: np.ndarray, d: float) -> np.ndarray:
    """x(t - d) for a (n, ...) array sampled at unit steps, d in samples (may be fractional/negative)."""
    n = x.shape[0]
    src = np.clip(np.arange(n) - d, 0, n - 1)
    i0 = np.floor(src).astype(int)
    i1 = np.minimum(i0 + 1, n - 1)
    a = (src - i0).reshape((n,) + (1,) * (x.ndim - 1))
    return (1 - a) * x[i0] + a * x[i1]


def rate_limit(x: np.ndarray, max_step: np.ndarray) -> np.ndarray:
    """Slew-limit x (n,) with per-variant maximum step per sample (V,) -> (n, V)."""
    xs = x.tolist()  # Python floats: a scalar loop over numpy scalars or a ufunc call per sample costs more
    out = np.empty((x.shape[0], max_step.shape[0]))
    for j, m in enumerate(max_step.tolist()):
        lo, y, col = -m, xs[0], []
        for xk in xs:
            d = xk - y
            y = y + (lo if d < lo else (m if d > m else d))  # y + clip(x - y, -m, m)
            col.append(y)
        out[:, j] = col
    return out


def deadzone(x: np.ndarray, b: float, centre: float = 0.0) -> np.ndarray:
    """No output within ``b`` of ``centre``; outside, the input less ``b`` (zero at zero input when
    ``|centre| < b``: the trim stays the trim)."""
    d = x - centre
    return np.sign(d) * np.maximum(np.abs(d) - b, 0.0)


def backlash(x: np.ndarray, b: float | np.ndarray) -> np.ndarray:
    """Mechanical play of total width 2b: the output follows only when pushed past +-b (``b`` one
    width, or one per sample of ``x``)."""
    xs = x.tolist()  # Python floats: the same arithmetic as numpy's scalars, half the time
    bs = np.broadcast_to(np.asarray(b, dtype=float), x.shape).tolist()
    y, col = xs[0], []
    for xk, bk in zip(xs, bs, strict=True):
        if xk > y + bk:
            y = xk - bk
        elif xk < y - bk:
            y = xk + bk
        col.append(y)
    return np.array(col, dtype=float)


# ---------------------------------------------------------------------------------------------
class Context:
    """Base-model windows plus the cached base held-out cost, shared by every scan."""

    def __init__(self, ev: Evaluator, segments: list[SegmentArrays], given: np.ndarray | None = None,
                 cfg: DiagnoseConfig | None = None, noise_unit: np.ndarray | None = None):
        self.ev = ev
        self.cfg = cfg or DiagnoseConfig()  # the scans' own settings (the air-mass scan's chunks and knots)
        self.segments = segments
        # ``given`` (W, L, 8, K): linear columns of another effect already in the model (conditional
        # scans: does this effect still add anything once the other one is in?)
        self.given = given
        self.base_sse, self.base_train, _ = ev.heldout(ev.r0, given)
        self.dt_s = ev.dt_s
        self.change: dict[str, np.ndarray] = {}  # effect -> (W,) prediction change of its variant
        self.blocks: dict[str, np.ndarray] = {}  # effect -> (W, n_blocks) nested held-out cost
        self.base_blocks = ev.last_blocks.copy()
        self.pwm_per_unit = 500.0
        # (8,) multiples of each channel's noise per unit of held-out cost (the gap shares' units),
        # when the flight's noise floor is known; the air-mass scan chooses its variant in them
        self.noise_unit = noise_unit
        # input_variants' caches: theta0 they were made for, the context's windowed inputs and
        # residual at theta0, the weighted response of the fitted simulation per input channel
        self._linear: tuple[bytes, np.ndarray, np.ndarray] | None = None
        self._response: dict[int, np.ndarray] = {}
        self._quadratic: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def variants_residual(self, U_list: list[np.ndarray] | None = None,
                          Y_list: list[np.ndarray] | None = None) -> np.ndarray:
        """Residuals (V, W, L, 8) at theta0 of V input (or initial-state) variants, simulated in one batch."""
        ev = self.ev
        V = len(U_list) if U_list is not None else len(Y_list or [])
        U = np.concatenate(U_list) if U_list is not None else np.tile(ev.U, (V, 1, 1))
        Y = np.concatenate(Y_list) if Y_list is not None else ev.Y  # the simulation repeats it per variant
        yh = lsim(ev.theta0, U, Y, ev.dt_s, weights=ev.w8, available=ev.available, start=ev.start)[0]
        yh = yh.reshape(V, ev.W, ev.L, 8)
        return yh

    def _base_residual(self) -> tuple[np.ndarray, np.ndarray]:
        """(windowed inputs (W, L, 4) of the context's segments, weighted residual (W, L, 8) of their
        simulation at theta0), computed once per theta0."""
        ev = self.ev
        key = ev.theta0.tobytes()
        if self._linear is None or self._linear[0] != key:
            U = ev.cut([s.inputs for s in self.segments])
            yh = lsim(ev.theta0, U, ev.Y, ev.dt_s, weights=ev.w8, available=ev.available, start=ev.start)[0]
            self._linear = (key, U, ev.residual(yh))
            self._response = {}
            self._quadratic = {}
        return self._linear[1], self._linear[2]

    def response(self, c: int) -> np.ndarray:
        """(L, L 8): the weighted change of a window's fitted simulation at theta0 (initial states
        re-fitted as :func:`groundstation.gap.linsim.simulate` fits them) per unit change at each of
        its samples of input ``c`` (0-3: lat lon col ped; 4-14: the forcing of state ``c - 4``). The
        model and the initial-state fit are linear, so this matrix is the same for every window, and
        a variant of one input (or a forcing) changes the base simulation by its product with it:
        one product instead of a simulation."""
        self._base_residual()
        if c not in self._response:
            ev, L = self.ev, self.ev.L
            E = np.zeros((L, L, 4 + 11))
            E[np.arange(L), np.arange(L), c] = 1.0  # window l: a unit on column c at sample l
            M = lsim(ev.theta0, E[..., :4], np.zeros((1, L, 8)), ev.dt_s, weights=ev.w8, available=ev.available,
                     start=ev.start, forcing=E[..., 4:] if c >= 4 else None)[0]
            self._response[c] = np.ascontiguousarray((M * ev.w8).reshape(L, L * 8))
        return self._response[c]

    def input_variants(self, groups: Sequence[tuple[int, np.ndarray]]) -> np.ndarray:
        """Weighted residuals (V, W, L, 8) at theta0 of V variants of single inputs, the same numbers
        as simulating each variant's inputs (to round-off): ``groups`` of (input channel ``c``, that
        channel's windows in each variant (Vc, W, L)); every other input as in the context's segments."""
        ev = self.ev
        U, r0 = self._base_residual()
        V = sum(u.shape[0] for _, u in groups)
        out = np.empty((V, ev.W, ev.L, 8))
        v0 = 0
        for c, u in groups:
            v1 = v0 + u.shape[0]
            d = out[v0:v1]
            with np.errstate(over="ignore", invalid="ignore"):
                np.matmul((u - U[None, :, :, c]).reshape(-1, ev.L), self.response(c),
                          out=d.reshape(-1, ev.L * 8))
            d *= ev.wmask
            np.subtract(r0, d, out=d)
            v0 = v1
        return out

    def quadratic(self, c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the re-fit's training cost of a variant of input ``c`` needs from the variant's change
        ``d`` (W, L) of that input alone (windows without holes): with ``R`` the masked :meth:`response`,
        the variant's residual is ``r0 - d R``, so its squared norm per window is
        ``|r0|^2 - 2 d.g + d Q d`` and its product with the Jacobian ``Jn^T r0 - Ht d``.
        Returns ``Q`` (L, L) = R R^T, ``g`` (W, L) = R r0 and ``Ht`` (W, 31, L) = (R Jn)^T per window."""
        _, r0 = self._base_residual()
        if c not in self._quadratic:
            ev = self.ev
            R = self.response(c) * np.repeat(ev.wmask[:, 0], 8)[None, :]
            # every window's Jacobian in one product (a stack of small ones is several times slower)
            Ht = (np.swapaxes(ev.Jn, 1, 2).reshape(-1, R.shape[1]) @ R.T).reshape(ev.W, -1, ev.L)
            self._quadratic[c] = (R @ R.T, r0.reshape(ev.W, -1) @ R.T, Ht)
        return self._quadratic[c]

    def input_train(self, groups: Sequence[tuple[int, np.ndarray]]) -> np.ndarray:
        """The training cost (V, folds) of every fold's re-fit of V variants of single inputs (``groups``
        as :meth:`input_variants` takes them), the numbers :meth:`Evaluator.heldout_many` gives for
        their residuals to round-off, from :meth:`quadratic` (no variant's residual formed). Windows
        without holes only (``ev.wmask`` per sample)."""
        ev = self.ev
        U, r0 = self._base_residual()
        rf0 = r0.reshape(ev.W, -1)
        rr0 = (rf0 ** 2).sum(axis=1)
        mtr0 = np.matmul(np.swapaxes(ev.Jn, 1, 2), rf0[..., None])[..., 0]  # (W, 31)
        rr, mtr = [], []
        for c, u in groups:
            Q, g, Ht = self.quadratic(c)
            d = u - U[None, :, :, c]  # (Vc, W, L)
            dQ = (d.reshape(-1, ev.L) @ Q).reshape(d.shape)
            rr.append(rr0 - 2 * (d * g).sum(axis=2) + (dQ * d).sum(axis=2))  # (Vc, W)
            Hd = np.matmul(Ht, np.ascontiguousarray(np.moveaxis(d, 0, 2)))  # (W, 31, Vc)
            mtr.append(mtr0 - np.moveaxis(Hd, 2, 0))  # (Vc, W, 31)
        rr_all, m_all = np.concatenate(rr), np.concatenate(mtr)
        train = np.empty((rr_all.shape[0], ev.folds))
        for f in range(ev.folds):
            tr = ev.fold != f
            G = ev.JtJ[tr].sum(0)
            b = m_all[:, tr].sum(axis=1).T  # (31, V)
            dd = np.linalg.solve(G + ev.ridge * np.trace(G) / G.shape[0] * np.eye(G.shape[0]), b)
            train[:, f] = rr_all[:, tr].sum(axis=1) - 2 * (dd * b).sum(0) + (dd * (G @ dd)).sum(0)
        return train

    def nested_inputs(self, effect: str, groups: Sequence[tuple[int, np.ndarray]]) -> tuple[np.ndarray, int, np.ndarray]:
        """:meth:`nested` over the variants of single inputs ``groups`` (as :meth:`input_variants` takes
        them): every variant's training costs from :meth:`input_train`, and the residuals and held-out
        costs of the variants the selection picks only. The same selection as stacking every variant's
        residual (training costs to round-off). Returns the nested held-out cost (W, 8), the index of the
        variant with the lowest total training cost and its residual (W, L, 8)."""
        ev = self.ev
        V = sum(u.shape[0] for _, u in groups)
        if self.given is not None or ev.wmask.ndim != 2 or V < 2:
            rs = self.input_variants(groups)
            sse, best, _ = self.nested(effect, [({}, r, None) for r in rs], rs)
            return sse, best, rs[best].copy()
        T = self.input_train(groups)
        keep = sorted({int(np.argmin(T[:, f])) for f in range(ev.folds)} | {int(np.argmin(T.sum(axis=1))), V - 1})
        sub, v0 = [], 0
        for c, u in groups:
            mine = [k - v0 for k in keep if v0 <= k < v0 + u.shape[0]]
            if mine:
                sub.append((c, u[mine]))
            v0 += u.shape[0]
        rs = self.input_variants(sub)
        s_k, _, b_k = ev.heldout_many(rs)
        ev.last_blocks = b_k[-1].copy()
        at = {k: i for i, k in enumerate(keep)}
        sse, best = self._select(effect, T, lambda v: (s_k[at[v]], b_k[at[v]], rs[at[v]], None))
        return sse, best, rs[at[best]].copy()

    def nested(self, effect: str, variants: Sequence[tuple[dict[str, Any], np.ndarray, np.ndarray | None]],
               rs: np.ndarray | None = None) -> tuple[np.ndarray, int, list[np.ndarray]]:
        """Nested selection over variants (label, r (W,L,8), X or None); ``rs`` (V, W, L, 8): the
        variants' residuals already stacked (input variants), else they are stacked here.

        Returns the nested held-out cost (W, 8), the index of the variant with the lowest total
        training cost, and the per-variant linear-parameter estimates (folds, K).
        """
        ev = self.ev
        sses, trains, coefs, blks = [], [], [], []
        if self.given is None and len(variants) > 1 and all(X is None for _, _, X in variants):
            # input variants: one batched re-fit (the normal matrix is the base model's for all)
            s_all, T, b_all = ev.heldout_many(np.stack([r for _, r, _ in variants]) if rs is None else rs)
            sses, blks = list(s_all), list(b_all)
            ev.last_blocks = b_all[-1].copy()
            coefs = [np.zeros((ev.folds, 0))] * len(variants)
        else:
            for _, r, X in variants:
                k_own = 0 if X is None else X.shape[-1]
                if self.given is not None:
                    X = self.given if X is None else np.concatenate([X, self.given], axis=-1)
                s, t, c = ev.heldout(r, X)
                sses.append(s)
                trains.append(t)
                coefs.append(c[:, :k_own])
                blks.append(ev.last_blocks.copy())
            T = np.array(trains)  # (V, folds)
        out, best = self._select(effect, T, lambda v: (sses[v], blks[v], variants[v][1],
                                                       None if variants[v][2] is None else (variants[v][2], coefs[v])))
        return out, best, coefs

    def _select(self, effect: str, T: np.ndarray, of: Any) -> tuple[np.ndarray, int]:
        """The nested selection from the training costs ``T`` (V, folds): per fold the variant with the
        lowest, scored on that fold; ``of(v)``: variant v's held-out cost (W, 8), blocks (W, n_blocks),
        residual (W, L, 8) and (X, per-fold coefficients) or None. Records its blocks and prediction
        change; returns the nested held-out cost (W, 8) and the variant with the lowest total."""
        ev = self.ev
        out = np.empty((ev.W, 8))
        out_b = np.empty((ev.W, ev.n_blocks))
        # how much the selected variant changes each window's prediction (at theta0): windows it
        # leaves untouched carry no evidence either way
        change = np.zeros(ev.W)
        for f in range(ev.folds):
            v = int(np.argmin(T[:, f]))
            te = ev.fold == f
            sse_v, blk_v, r_b, lin = of(v)
            out[te] = sse_v[te]
            out_b[te] = blk_v[te]
            d = r_b[te] - ev.r0[te]
            if lin is not None:
                d = d - np.einsum("wlck,k->wlc", lin[0][te], lin[1][f])
            change[te] = (d ** 2).sum(axis=(1, 2))
        self.blocks[effect] = out_b
        self.change[effect] = change
        return out, int(np.argmin(T.sum(axis=1)))


def _mask_w(ev: Evaluator, yh: np.ndarray) -> np.ndarray:
    return (yh * ev.w8) * ev.wmask


# ---------------------------------------------------------------------------------------------
def input_excitation(segments: list[SegmentArrays]) -> np.ndarray:
    """Per input channel: standard deviation of the input (normalised units), (4,)."""
    u = np.concatenate([s.inputs for s in segments])
    return u.std(axis=0)


def scan_input_delay(ctx: Context, channels: list[int]) -> Hypothesis:
    ev, segs = ctx.ev, ctx.segments
    groups = []
    labels: list[dict[str, Any]] = []
    for c in channels:
        groups.append((c, np.stack([ev.cut([shift(s.inputs[:, c], d_s / ev.dt_s) for s in segs])
                                    for d_s in DELAY_GRID_S])))
        labels += [{"channel": c, "delay_s": d_s} for d_s in DELAY_GRID_S]
    sse, best, r_best = ctx.nested_inputs("input_delay", groups)
    lab = labels[best]
    return Hypothesis("input_delay", input=INPUTS[lab["channel"]], estimate={"delay_s": lab["delay_s"]},
                      sse=sse, channels=(3, 4, 5, 6, 7),
                      extra={"variants": len(labels), "label": lab, "r_best": r_best})


def slew_grid(du: np.ndarray) -> np.ndarray:
    """Candidate slew limits (input units per grid step) from one channel's |input steps| ``du``:
    :data:`RATE_QUANTILES` of them and :data:`RATE_OF_MAX` fractions of the largest, ascending."""
    steps = np.unique(np.concatenate([np.quantile(du, RATE_QUANTILES), du.max() * np.array(RATE_OF_MAX)]))
    return np.maximum(steps, 1e-9)


def scan_rate_limit(ctx: Context, channels: list[int]) -> Hypothesis:
    ev, segs = ctx.ev, ctx.segments
    groups = []
    labels: list[dict[str, Any]] = []
    for c in channels:
        du = np.concatenate([np.abs(np.diff(s.inputs[:, c])) for s in segs])
        steps = slew_grid(du)
        groups.append((c, np.moveaxis(ev.cut([rate_limit(s.inputs[:, c], steps) for s in segs]), 2, 0)))
        labels += [{"channel": c, "rate_per_s": float(st / ev.dt_s), "quantile": float(np.mean(du <= st))}
                   for st in steps]
    sse, best, r_best = ctx.nested_inputs("rate_limit", groups)
    lab = labels[best]
    return Hypothesis("rate_limit", input=INPUTS[lab["channel"]],
                      estimate={"rate_limit_per_s": lab["rate_per_s"],
                                "rate_limit_pwm_us_per_s": lab["rate_per_s"] * ctx_pwm(ctx)},
                      sse=sse, channels=(3, 4, 5, 6, 7), extra={"label": lab, "r_best": r_best})


def ctx_pwm(ctx: Context) -> float:
    return float(ctx.pwm_per_unit)


def scan_deadband(ctx: Context, channels: list[int]) -> Hypothesis:
    ev, segs = ctx.ev, ctx.segments
    groups = []
    labels: list[dict[str, Any]] = []
    for c in channels:
        au = np.concatenate([np.abs(s.inputs[:, c]) for s in segs])
        widths = np.unique(np.round(np.concatenate([np.quantile(au, DEADBAND_QUANTILES),
                                                    np.array(DEADBAND_STD) * au.std()]), 6))
        labs: list[dict[str, Any]] = [{"channel": c, "width": float(b), "kind": kind, "centre": float(off * b)}
                                      for b in widths
                                      for kind, off in [("deadzone", f) for f in DEADBAND_CENTRE] + [("backlash", 0.0)]]
        groups.append((c, np.stack([ev.cut([deadband_input(s.inputs[:, c], lab) for s in segs]) for lab in labs])))
        labels += labs
    sse, best, r_best = ctx.nested_inputs("deadband", groups)
    lab = labels[best]
    # resolution of the recorded input: MAVLink servo/RC values are whole microseconds, so a
    # "deadband" of a few quanta is indistinguishable from quantisation
    quantum = 1.0 / ctx_pwm(ctx)
    return Hypothesis("deadband", input=INPUTS[lab["channel"]],
                      estimate={"deadband": lab["width"], "deadband_pwm_us": lab["width"] * ctx_pwm(ctx)},
                      sse=sse, channels=(3, 4, 5, 6, 7),
                      extra={"kind": lab["kind"], "quantum": quantum, "label": lab, "r_best": r_best})


INPUT_EFFECTS = ("input_delay", "rate_limit", "deadband")


def apply_input_effect(h: Hypothesis, segments: list[SegmentArrays], dt_s: float) -> list[SegmentArrays]:
    """The segments with the selected variant of an input-effect hypothesis applied to its input."""
    lab = h.extra["label"]
    c = int(lab["channel"])
    out = []
    for s in segments:
        u = s.inputs.copy()
        if h.effect == "input_delay":
            u[:, c] = shift(u[:, c], lab["delay_s"] / dt_s)
        elif h.effect == "rate_limit":
            u[:, c] = rate_limit(u[:, c], np.array([lab["rate_per_s"] * dt_s]))[:, 0]
        elif h.effect == "deadband":
            u = apply_deadband([s], lab)[0]
        else:
            raise GapError(f"not an input effect: {h.effect}")
        out.append(SegmentArrays(t_s=s.t_s, inputs=u, outputs=s.outputs, outputs_raw=s.outputs_raw,
                                 alt_m=s.alt_m, flight=s.flight, measured=s.measured))
    return out


def apply_deadband(segments: Sequence[SegmentArrays], lab: dict[str, Any]) -> list[np.ndarray]:
    """Each segment's inputs with the deadband variant ``lab`` (channel, width, kind, centre) applied."""
    c = int(lab["channel"])
    out = []
    for s in segments:
        u = s.inputs.copy()
        u[:, c] = deadband_input(u[:, c], lab)
        out.append(u)
    return out


def deadband_input(x: np.ndarray, lab: dict[str, Any]) -> np.ndarray:
    """One input channel's samples (n,) through the deadband variant ``lab`` (width, kind, centre)."""
    b = float(lab["width"])
    if lab["kind"] == "deadzone":
        return deadzone(x, b, float(lab.get("centre", 0.0)))
    return backlash(x, b)


def rescan_input_effect(ctx: Context, h: Hypothesis) -> Hypothesis:
    """The scan of ``h``'s effect on its selected channel only, in another (conditional) context."""
    scan = {"input_delay": scan_input_delay, "rate_limit": scan_rate_limit, "deadband": scan_deadband}[h.effect]
    return scan(ctx, [int(h.extra["label"]["channel"])])


def scan_velocity_latency(ctx: Context) -> Hypothesis:
    ev, segs = ctx.ev, ctx.segments
    if not ev.available[list(VEL)].any():
        return Hypothesis("velocity_latency", testable=False, reason="no velocity measurements")
    Y_list: list[np.ndarray] = []
    labels: list[dict[str, Any]] = []
    for d_s in DELAY_GRID_S:
        d = d_s / ev.dt_s
        Ys = [s.outputs.copy() for s in segs]
        for y in Ys:
            y[:, :3] = shift(y[:, :3], -d)  # true-time velocity = measurement d later
        Y_list.append(ev.cut(Ys))
        labels.append({"latency_s": d_s})
    yh = ctx.variants_residual(Y_list=Y_list)
    variants = []
    for lab, y in zip(labels, yh, strict=True):
        y2 = y.copy()
        d = lab["latency_s"] / ev.dt_s
        y2[:, :, :3] = np.moveaxis(shift(np.moveaxis(y[:, :, :3], 1, 0), d), 0, 1)
        variants.append((lab, ev.residual(y2), None))
    sse, best, _ = ctx.nested("velocity_latency", variants)
    return Hypothesis("velocity_latency", estimate={"latency_s": labels[best]["latency_s"]}, sse=sse,
                      channels=VEL)


def scan_gyro_bias(ctx: Context) -> Hypothesis:
    ev = ctx.ev
    b = 0.01
    variants, labels = [], []
    for name, c in RATE_CH.items():
        if not ev.available[c]:
            continue
        Y2 = ev.Y.copy()
        Y2[:, :, c] -= b
        yh = ev.simulate(ev.theta0, Y=Y2)[0]
        yh[:, :, c] += b
        base = ev.simulate(ev.theta0)[0]
        X = _mask_w(ev, (yh - base) / b)[..., None]
        variants.append(({"output": name}, ev.r0, X))
        labels.append(name)
    if not variants:
        return Hypothesis("gyro_bias", testable=False, reason="no body-rate measurements")
    sse, best, coefs = ctx.nested("gyro_bias", variants)
    est = float(np.mean(coefs[best][:, 0]))
    return Hypothesis("gyro_bias", output=labels[best], estimate={"bias_rad_s": est}, sse=sse,
                      channels=(RATE_CH[labels[best]],))


def _forcing_columns(ctx: Context, F_list: list[np.ndarray]) -> np.ndarray:
    """Weighted sensitivities (W, L, 8, K) of the outputs to K forcing patterns (W, L, 11) each: each
    forced state's samples times its response (:meth:`Context.response`; the model is linear in the
    forcing, so this is the simulation with the forcing less the one without, to round-off)."""
    ev = ctx.ev
    X = np.zeros((len(F_list), ev.W, ev.L * 8))
    for k, F in enumerate(F_list):
        for j in np.flatnonzero(np.abs(F).sum(axis=(0, 1))):
            X[k] += np.matmul(F[:, :, j], ctx.response(4 + int(j)))
    return np.moveaxis(X.reshape(len(F_list), ev.W, ev.L, 8) * ev.wmask, 0, -1)


def scan_quadratic_drag(ctx: Context) -> Hypothesis:
    ev = ctx.ev
    if not ev.available[list(VEL)].any():
        return Hypothesis("quadratic_drag", testable=False, reason="no velocity measurements")
    F_list = []
    rows = (0, 1)  # horizontal: a vertical column would also soak up any heave-model error
    used = []
    # the drag acts on the model's own velocity (output error): using the measured velocity here
    # would feed measurements into the simulation and reward any term that does so
    ysim = ev.simulate(ev.theta0)[0]
    for j, row in enumerate(rows):
        if not ev.available[j]:
            continue
        v = ysim[:, :, j]
        F = np.zeros((ev.W, ev.L, 11))
        F[:, :, row] = -np.abs(v) * v
        F_list.append(F)
        used.append("uvw"[j])
    X = _forcing_columns(ctx, F_list)
    sse, best, coefs = ctx.nested("quadratic_drag", [({}, ev.r0, X)])
    c = coefs[0].mean(axis=0)
    est = {f"drag_{n}_per_m": float(v) for n, v in zip(used, c, strict=True)}
    return Hypothesis("quadratic_drag", estimate=est, sse=sse, channels=(0, 1), extra={"X": X})


def heights(ev: Evaluator, segments: list[SegmentArrays]) -> np.ndarray | None:
    """(W, L) height above ground of each window's samples (m, >= 0), None without altitude."""
    alt = np.concatenate([s.alt_m for s in segments])
    if np.isfinite(alt).mean() < 0.5:
        return None
    A = ev.cut([np.nan_to_num(s.alt_m, nan=np.nanmedian(alt)) for s in segments])
    return np.maximum(A, 0.0)


def ground_effect_columns(ctx: Context, h: np.ndarray, h0: float, kind: str, hmin: float) -> np.ndarray:
    """Sensitivities (W, L, 8, 1) to a w force of shape ``kind`` ("exp" or "inv_square") decaying over
    ``h0`` (m) from the reference height ``hmin`` (m), heights ``h`` (W, L)."""
    shape = np.exp(-(h - hmin) / h0) if kind == "exp" else (h0 / (h - hmin + h0)) ** 2
    F = np.zeros((ctx.ev.W, ctx.ev.L, 11))
    F[:, :, 8] = shape
    return _forcing_columns(ctx, [F])


def scan_ground_effect(ctx: Context) -> Hypothesis:
    ev = ctx.ev
    h = heights(ev, ctx.segments)
    if h is None:
        return Hypothesis("ground_effect", testable=False, reason="no altitude in the log")
    hmin = float(np.quantile(h, 0.02))
    variants, labels = [], []
    for h0 in GROUND_DECAY_M:
        # two shapes: exponential decay and the Cheeseman-Bennett-like inverse square
        for kind in ("exp", "inv_square"):
            variants.append(({"h0": h0, "kind": kind}, ev.r0, ground_effect_columns(ctx, h, h0, kind, hmin)))
            labels.append(h0)
    sse, best, coefs = ctx.nested("ground_effect", variants)
    span = float(np.quantile(h, 0.98) - hmin)
    # the shape (decay, kind, reference height) is kept: an estimate on part of the flight (a half) is
    # comparable with another part's only as the amplitude of the same function of height
    return Hypothesis("ground_effect", estimate={"accel_m_s2": float(-coefs[best].mean()),
                                                  "decay_height_m": labels[best]},
                      sse=sse, channels=(2,), extra={"height_span_m": span, "min_height_m": hmin,
                                                     "shape": dict(variants[best][0], hmin=hmin),
                                                     "X": variants[best][2]})


def _air_columns(ev: Evaluator, theta: np.ndarray, n_knots: int = 3) -> np.ndarray:
    """Responses (1, L, 8, 2 n_knots) to a piecewise-linear horizontal air velocity, the same in every
    window (zero initial state, no input: :func:`groundstation.gap.linsim.simulate` takes them as
    shared by every window)."""
    A, _ = full_matrices(theta)
    # horizontal air velocity only: a vertical one would also soak up any heave-model error
    Fdir = np.stack([-A[0, :, s_idx] for s_idx in (0, 1)])  # (2, 11) per unit air velocity
    L = ev.L
    tt = np.linspace(0.0, 1.0, L)
    knots = np.linspace(0.0, 1.0, n_knots)
    hats = [np.maximum(0.0, 1.0 - np.abs(tt - c) * (n_knots - 1)) for c in knots]
    F = np.stack([hat[:, None] * Fdir[comp][None, :] for comp in range(Fdir.shape[0]) for hat in hats])
    K = F.shape[0]  # one "window" per column
    cols = np.asarray(lsim(theta, np.zeros((K, L, 4)), np.zeros((1, L, 8)), ev.dt_s, forcing=F,
                           fit_initial=False))[0]  # (K, L, 8)
    return np.moveaxis(cols, 0, -1)[None] * ev.available[None, None, :, None]


def gauss_markov_factor(n: int, span_s: float, tau_s: float) -> np.ndarray:
    """(n, n) lower Cholesky factor of a first-order Gauss-Markov process's correlation
    ``exp(-|t_i - t_j| / tau_s)`` at ``n`` evenly spaced times over ``span_s`` seconds: unit white
    coefficients times it are a sample of the process (the whitened basis of the air velocity)."""
    t = np.linspace(0.0, span_s, n)
    return np.linalg.cholesky(np.exp(-np.abs(t[:, None] - t[None]) / tau_s) + 1e-9 * np.eye(n))


class _ChunkFit:
    """The air-mass protocol's least squares for one parameter set: every window's initial states (and
    shared columns, with a prior) fitted on alternate chunks of ``chunk_s``, scored on the chunks
    between them, both ways round. The free responses of the initial states and the columns are the
    same in every window, so one normal matrix per protocol half serves every window and each prior
    costs one small solve: the same numbers as :func:`groundstation.gap.linsim.simulate` with the
    columns as shared nuisance (to round-off), without simulating the windows again."""

    def __init__(self, ev: Evaluator, theta: np.ndarray, chunk_s: float):
        self.ev, self.theta = ev, theta
        self.wf = np.where(ev.available, ev.w8, 0.0)  # the least squares' weights
        y0 = lsim(theta, ev.U, ev.Y, ev.dt_s, weights=ev.w8, available=ev.available, fit_initial=False)[0]
        self.r = ev.Y - y0  # (W, L, 8): what the fitted columns are to explain
        self.S = free_responses(theta, ev.L, ev.dt_s, ev.available)  # (nu, L, 8)
        chunk = max(int(round(chunk_s / ev.dt_s)), 2)
        k = np.arange(ev.L) // chunk
        self.halves = [(np.flatnonzero((k % 2 == p) & ev.mask), np.flatnonzero((k % 2 != p) & ev.mask)) for p in (0, 1)]

    def cv(self, cols: np.ndarray | None = None, precs: Sequence[float] = (0.0,)) -> tuple[np.ndarray, np.ndarray]:
        """Held-out costs (V, W, 8) with the shared columns ``cols`` (K, L, 8) (None: the initial states
        alone) under each of the V prior precisions ``precs`` of their coefficients, and the
        coefficients (V, W, K) of the second fit."""
        ev = self.ev
        D = self.S if cols is None else np.concatenate([self.S, cols])
        P, nu = D.shape[0], self.S.shape[0]
        V = len(precs)
        sse = np.zeros((V, ev.W, 8))
        a = np.zeros((V, ev.W, P))
        for fit, score in self.halves:
            Df = (D[:, fit] * self.wf).reshape(P, -1)
            G = np.tile(Df @ Df.T, (V, 1, 1))
            G += (1e-9 * np.trace(G[0]) / P + 1e-12) * np.eye(P)
            G[:, np.arange(nu, P), np.arange(nu, P)] += np.asarray(precs, float)[:, None]
            h = Df @ (self.r[:, fit] * self.wf).reshape(ev.W, -1).T  # (P, W)
            a = np.swapaxes(np.linalg.solve(G, np.broadcast_to(h, (V, P, ev.W))), 1, 2)  # (V, W, P)
            e = self.r[None, :, score] - (a @ D[:, score].reshape(P, -1)).reshape(V, ev.W, score.size, 8)
            e2 = (e * ev.w8) ** 2
            sse += (e2 if ev.M is None else e2 * ev.M[None, :, score]).sum(axis=2)   # holes of the link not scored
        return sse, a[..., nu:]


def _refined_theta(ctx: Context, knot_s: float, prec_scale: float, iterations: int) -> np.ndarray:
    """The base re-identified (Levenberg-Marquardt) under a per-window piecewise-linear air velocity
    with knots every ``knot_s``: an unmodelled air mass distorts the identified parameters."""
    ev = ctx.ev
    n_knots = max(int(round(ev.L * ev.dt_s / knot_s)) + 1, 2)
    if ctx.segments is ev.segments:  # the context's evaluator as it is: its Jacobian is recomputed below
        evg = copy.copy(ev)
    else:
        evg = Evaluator(ctx.segments, ev.dt_s, ev.theta0, ev.available, window_s=ev.L * ev.dt_s,
                        folds=ev.folds, ridge=ev.ridge, start_s=ev.start_s)
    evg.nuisance = _air_columns(evg, ev.theta0, n_knots)
    evg.nuisance_prec = np.full(2 * n_knots, prec_scale)
    evg.set_theta(ev.theta0)
    evg.refine(iterations, ctx.cfg.refine_ridge)
    return evg.theta0


def scan_wind_gust(ctx: Context, chunk_s: float | None = None, refine_iterations: int | None = None,
                   knot_s: float | None = None) -> Hypothesis:
    """Air-mass motion: a horizontal air velocity entering wherever the body velocity does.

    In each window each horizontal component of the air velocity is a first-order Gauss-Markov
    process on a grid of :data:`GUST_GRID_S` (linear between the grid times), entering the model
    through the columns of A for u and v (drag and the speed-stability moments act on airspeed;
    GPS measures ground speed). It is fitted in its whitened basis (the model's responses to the
    Cholesky factor of the process's covariance) by the same regularised least squares as the
    initial states: the posterior mean of a smoother with the air velocity as a Gauss-Markov state.
    Its time scale (:data:`GUST_TAU_S`) and intensity (:data:`GUST_SIGMA` x the measured horizontal
    speed) are chosen by the data, and so is the parameter set: the base as it is, or re-identified
    under a smooth air velocity (knots every ``knot_s``; an unmodelled air mass distorts the
    identified parameters, and the re-identification can also over-fit them).
    Scoring is *within-window* cross-validation: initial states and the air velocity are fitted on
    alternate chunks of ``chunk_s`` and the residual is scored on the other chunks, both ways
    round; the base model goes through the same protocol. An air-mass motion fitted on some chunks
    predicts the chunks between them as far as its time scale carries; parameters fitted to noise
    (correlated over a few samples only) do not. The variant (time scale, intensity, parameter set)
    is chosen per fold on the other folds' windows, by their held-out cost in multiples of each
    channel's noise (``ctx.noise_unit``; without it, of the base model's cost in each channel), the
    units of the gap's shares: in the cost's own weights a channel whose signal is small against
    its noise (v) could be wrecked unseen. Scored on :data:`GUST_CHANNELS`, the outputs of the
    horizontal block (w and r see no horizontal air). ``chunk_s``, ``refine_iterations`` and
    ``knot_s`` default to the context's ``gust_chunk_s``, ``gust_refine_iterations`` and
    ``gust_knot_s``.
    """
    chunk_s = ctx.cfg.gust_chunk_s if chunk_s is None else chunk_s
    knot_s = ctx.cfg.gust_knot_s if knot_s is None else knot_s
    refine_iterations = ctx.cfg.gust_refine_iterations if refine_iterations is None else refine_iterations
    if not ctx.ev.available[[0, 1]].all():
        return Hypothesis("wind_gust", testable=False, reason="no horizontal velocity measurements")
    # small products, many of them: one thread (a pool's threads spinning cost more than they do)
    with threadpool_limits(1):
        return _air_mass(ctx, chunk_s, knot_s, refine_iterations)


def _air_mass(ctx: Context, chunk_s: float, knot_s: float, refine_iterations: int) -> Hypothesis:
    """:func:`scan_wind_gust`'s work, its settings resolved."""
    ev = ctx.ev
    # prior: air velocity of the order of the measured horizontal speed (weighted-residual units)
    s_air = float(np.sqrt((ev.Y[:, :, :2] ** 2).mean())) + 1e-6
    n_scored = ev.mask.sum() * ev.W * ev.available.sum() if ev.M is None else (ev.score_mask & ev.available).sum()
    sig2 = float((ev.r0 ** 2).sum() / max(n_scored, 1))
    fits = [_ChunkFit(ev, ev.theta0, chunk_s)]
    sse_b = fits[0].cv()[0][0]
    unit = _cost_unit(ctx, sse_b)
    if refine_iterations > 0:
        fits.append(_ChunkFit(ev, _refined_theta(ctx, knot_s, sig2 / s_air ** 2, refine_iterations), chunk_s))
    span_s = (ev.L - 1) * ev.dt_s
    n = max(int(round(span_s / GUST_GRID_S)) + 1, 2)
    factors = {tau: gauss_markov_factor(n, span_s, tau) for tau in GUST_TAU_S}
    variants = []
    for i, fit in enumerate(fits):
        grid = np.moveaxis(_air_columns(ev, fit.theta, n)[0], -1, 0)  # (2 n, L, 8)
        for tau, fac in factors.items():
            cols = np.concatenate([np.einsum("klc,kj->jlc", grid[c * n:(c + 1) * n], fac) for c in range(2)])
            sse, coef = fit.cv(cols, [sig2 / (s * s_air) ** 2 for s in GUST_SIGMA])
            variants += [((i, tau, s), sse[j], coef[j]) for j, s in enumerate(GUST_SIGMA)]
    cost = np.stack([(v[1] * unit).sum(axis=1) for v in variants])  # (V, W) in noise units
    sse_g = np.empty((ev.W, 8))
    picks = []
    for f in range(ev.folds):
        tr, te = ev.fold != f, ev.fold == f
        k = int(np.argmin(cost[:, tr].sum(axis=1)))
        picks.append(variants[k][0])
        sse_g[te] = variants[k][1][te]
    (i, tau, s), _, coef = variants[int(np.argmin(cost.sum(axis=1)))]
    off = [c for c in range(8) if c not in GUST_CHANNELS]  # untouched by a horizontal air velocity
    sse_g[:, off] = sse_b[:, off]
    air = coef.reshape(ev.W, 2, n) @ factors[tau].T  # (W, 2, n) m/s at the grid times
    rms = float(np.sqrt((air ** 2).sum(axis=1).mean()))
    return Hypothesis("wind_gust", estimate={"air_velocity_rms_m_s": rms}, sse=sse_g,
                      channels=GUST_CHANNELS,
                      extra={"base_sse": sse_b, "theta": fits[i].theta, "n_knots": n, "air_knots": air,
                             "tau_s": tau, "sigma_factor": s, "unit": unit,
                             "reidentified": [bool(p[0]) for p in picks],
                             "variants": [[float(p[1]), float(p[2])] for p in picks]})


def _cost_unit(ctx: Context, base_sse: np.ndarray) -> np.ndarray:
    """(8,) weights turning a held-out cost per channel into multiples of the channel's noise: the
    context's ``noise_unit`` when it has one, else the base model's own cost in the channel (0 for
    a channel without one)."""
    if ctx.noise_unit is not None:
        return np.asarray(ctx.noise_unit, float)
    tot = base_sse.sum(axis=0)
    return np.where(tot > 0, 1.0 / np.where(tot > 0, tot, 1.0), 0.0)


def noise_unit(ev: Evaluator, sigma_smoothed: np.ndarray) -> np.ndarray:
    """(8,) per-sample weights turning the held-out cost of each channel into multiples of its noise
    (``sigma_smoothed`` (8,) the flight's measured white noise after the smoothing, in the channel's
    units); 0 for a channel without a noise figure or weight."""
    s = np.nan_to_num(np.asarray(sigma_smoothed, float)) * ev.w8
    return np.where(s > 0, 1.0 / np.where(s > 0, s, 1.0) ** 2, 0.0)
