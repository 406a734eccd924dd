"""Frequency-domain identification: the eq.-8 parameters (optionally one delay per input) fitted by
minimising Tischler's J averaged over the input-output pairs with a response.

``identify_frequency(responses, prepared=None, algorithm="cabc", seed=0, bounds=None, config=None)``

1. the two decoupled subsystems (horizontal 22 parameters: lat/lon pairs of u v p q theta phi;
   vertical/yaw 9: col/ped pairs of w r) one after the other, as the time-domain fit does: J_avg is a
   mean over pairs, and the pairs of one subsystem depend only on its parameters;
2. a parameter is fixed at 0 when its input never moves or its subsystem has no pair with a
   response (reported in ``fit["fixed"]``); input delays (``fit_delays``) are searched in
   ``[0, max_delay_s]`` for the inputs with a response;
3. the global search with one of the registered optimisers
   (:data:`groundstation.sysid.optimizers.ALGORITHMS`: CABC by default, ABC, GA, DE) on the
   batched cost (``searches`` independent runs), then a least-squares refinement (scipy
   ``least_squares``, trust region) of the J residuals from the ``refine_starts`` best distinct
   points each search evaluated; the lowest refined J wins;
   The cost is Tischler's J_avg by default (``weighting="coherence"``); ``weighting="random_error"``
   weights every coherent point by its composite random error instead (residuals in standard
   deviations of the estimate, all pairs summed: the maximum-likelihood form, in which points the
   leakage-bias estimate marks as unreliable count little); J is reported either way;
4. standard errors: ``s^2 (R^T R)^-1`` with ``R`` the Jacobian of the J residuals and ``s^2`` their
   mean square per degree of freedom (Tischler's Cramér-Rao form); neighbouring frequency points
   are not independent estimates, so the figure is a lower bound - read it together with the
   insensitive/correlated parameters it exposes, not as a confidence interval.

Pure numpy/scipy; the model file and the timing are the caller's.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from groundstation.freq import FreqError
from groundstation.freq.cost import coherence_weight, error_residuals, pair_residuals
from groundstation.freq.fdoe import FdoeCost
from groundstation.freq.model_response import has_path, model_response
from groundstation.freq.settings import FreqIdentifyConfig
from groundstation.freq.spectra import ResponseSet
from groundstation.sysid.fit_section import ModelFit
from groundstation.sysid.model import (
    HOR_PARAMS,
    INPUTS,
    N_PARAMS,
    OUTPUTS,
    PARAM_INDEX,
    PARAM_NAMES,
    VER_PARAMS,
    HoverModel,
    bounds_array,
    build_matrices,
    discretize,
)
from groundstation.sysid.optimizers import ALGORITHMS

#: B-matrix parameters of each input (fixed at 0 when the input never moves).
INPUT_PARAMS: dict[str, tuple[str, ...]] = {
    "lat": ("X_lat", "M_lat", "L_lat", "A_lat"), "lon": ("Y_lon", "M_lon", "L_lon", "B_lon"),
    "col": ("Z_col", "N_col"), "ped": ("Z_ped", "N_ped"),
}
_SUBSYSTEMS = (("horizontal", HOR_PARAMS, ("lat", "lon")), ("vertical", VER_PARAMS, ("col", "ped")))


class _SubCost:
    """J_avg of one subsystem's pairs as a function of its free parameters (and delays), batched."""

    def __init__(self, rs: ResponseSet, pairs: list[Any], free_idx: np.ndarray, delay_inputs: list[int],
                 theta0: np.ndarray, weighting: str = "coherence") -> None:
        self.rs, self.pairs, self.free_idx, self.delay_inputs, self.theta0 = rs, pairs, free_idx, delay_inputs, theta0
        self.weighting = weighting
        self.cols = [(OUTPUTS.index(p.output), INPUTS.index(p.input)) for p in pairs]
        self.nfev = 0

    def unpack(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        X = np.atleast_2d(X)
        th = np.repeat(self.theta0[None], X.shape[0], axis=0)
        th[:, self.free_idx] = X[:, : self.free_idx.size]
        d = np.zeros((X.shape[0], 4))
        d[:, self.delay_inputs] = X[:, self.free_idx.size:]
        return th, d

    def residuals(self, X: np.ndarray, weighting: str | None = None) -> np.ndarray:
        """(C, n_res) residuals whose sum of squares is the cost (J_avg with ``coherence`` weighting)."""
        th, d = self.unpack(X)
        G = model_response(th, self.rs.f_hz, dt_s=self.rs.dt_s, delays_s=d)
        self.nfev += th.shape[0]
        if (weighting or self.weighting) == "random_error":
            return np.concatenate([error_residuals(G[:, :, j, i], p.response, p.random_error, p.coherent)
                                   for p, (j, i) in zip(self.pairs, self.cols, strict=True)], axis=1)
        k = np.sqrt(1.0 / len(self.pairs))
        return np.concatenate([k * pair_residuals(G[:, :, j, i], p.response, p.coherence, p.coherent)
                               for p, (j, i) in zip(self.pairs, self.cols, strict=True)], axis=1)

    def __call__(self, X: np.ndarray, weighting: str | None = None) -> np.ndarray:
        r = self.residuals(X, weighting)
        with np.errstate(over="ignore", invalid="ignore"):
            f = np.sum(r ** 2, axis=1)
        return np.where(np.isfinite(f), f, np.inf)

    def j_avg(self, x: np.ndarray) -> float:
        """Tischler's J_avg of these pairs at one point, whatever the fit's weighting."""
        return float(self(x[None], "coherence")[0])


#: horizontal B-matrix parameters and the state row each enters (B_hor of eq. 8): lat, then lon.
_HOR_B_ROWS = {0: (("X_lat", 0), ("M_lat", 4), ("L_lat", 5), ("A_lat", 6)),
               1: (("Y_lon", 1), ("M_lon", 4), ("L_lon", 5), ("B_lon", 7))}
_HOR_STATE_OF_OUTPUT = {0: 0, 1: 1, 3: 5, 4: 4, 6: 2, 7: 3}


class _VarProCost:
    """The horizontal search with the input gains (B) solved inside the cost (variable projection).

    For given A (and delays) every response is linear in B: ``G(z) = C (zI - Ad)^-1 Gamma B`` with
    ``Gamma`` the zero-order-hold input integral. The gains minimise the coherence-weighted relative
    error ``sum 20/n W_g |G/T - 1|^2`` (J's first-order form: 1 dB ~ 0.115, 7.6 deg ~ 0.13) by linear
    least squares, so the search runs over A alone and cannot stall on a gain's sign or scale; J is
    then evaluated exactly. :meth:`complete` gives the full vector for the refinement.
    """

    def __init__(self, base: _SubCost, b_lo: np.ndarray, b_hi: np.ndarray) -> None:
        self.base = base
        free = list(base.free_idx)
        self.b_pos = {i: [(free.index(PARAM_INDEX[n]), row) for n, row in rows if PARAM_INDEX[n] in free]
                      for i, rows in _HOR_B_ROWS.items()}
        b_set = {k for v in self.b_pos.values() for k, _ in v}
        self.a_pos = [k for k in range(len(free)) if k not in b_set]
        self.n_x = len(free) + len(base.delay_inputs)
        self.b_lo, self.b_hi = b_lo, b_hi
        w = 2.0 * np.pi * base.rs.f_hz
        self.z = np.exp(1j * w * base.rs.dt_s)
        self.w = w

    def search_dims(self) -> list[int]:
        """Positions (in the full search vector) the variable-projection search runs over."""
        return self.a_pos + list(range(len(self.base.free_idx), self.n_x))

    def complete(self, Xs: np.ndarray) -> np.ndarray:
        Xs = np.atleast_2d(Xs)
        X = np.zeros((Xs.shape[0], self.n_x))
        X[:, self.search_dims()] = Xs
        th, d = self.base.unpack(X)
        Ah = build_matrices(th)[0]
        Ad, Gam = discretize(Ah, np.broadcast_to(np.eye(8), Ah.shape), self.base.rs.dt_s)
        with np.errstate(all="ignore"):
            M = np.linalg.solve(self.z[:, None, None] * np.eye(8) - Ad[:, None], Gam[:, None])  # (C, nf, 8, 8)
        for i, pos in self.b_pos.items():
            if not pos:
                continue
            rows_a, rhs = [], []
            for p, (j, ii) in zip(self.base.pairs, self.base.cols, strict=True):
                if ii != i:
                    continue
                m = p.coherent
                sw = np.sqrt(20.0 / m.sum() * coherence_weight(p.coherence[m]))
                ph = np.exp(-1j * self.w[m][None, :] * d[:, i:i + 1])
                cols = [M[:, m, _HOR_STATE_OF_OUTPUT[j], r] * ph / p.response[m] * sw for _, r in pos]
                rows_a.append(np.stack(cols, axis=-1))
                rhs.append(np.broadcast_to(sw, (Xs.shape[0], sw.size)).astype(complex))
            if not rows_a:
                continue
            A = np.concatenate(rows_a, axis=1)
            b = np.concatenate(rhs, axis=1)
            A = np.concatenate([A.real, A.imag], axis=1)
            b = np.concatenate([b.real, b.imag], axis=1)
            with np.errstate(all="ignore"):
                AtA = np.einsum("cnk,cnl->ckl", A, A)
                Atb = np.einsum("cnk,cn->ck", A, b)
                ridge = 1e-9 * np.trace(AtA, axis1=1, axis2=2)[:, None, None] * np.eye(len(pos))
                try:
                    beta = np.linalg.solve(AtA + ridge, Atb[..., None])[..., 0]
                except np.linalg.LinAlgError:
                    beta = np.zeros((Xs.shape[0], len(pos)))
            k = [q for q, _ in pos]
            X[:, k] = np.clip(np.nan_to_num(beta), self.b_lo[k], self.b_hi[k])
        return X

    def __call__(self, Xs: np.ndarray) -> np.ndarray:
        return self.base(self.complete(Xs))


class _Partial:
    """``cost`` over its first ``k`` variables, the others held at ``x_full``'s (residuals only)."""

    def __init__(self, cost: Any, x_full: np.ndarray, k: int) -> None:
        self.cost, self.x_full, self.k = cost, np.asarray(x_full, float), k

    def residuals(self, X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(X)
        full = np.repeat(self.x_full[None], X.shape[0], axis=0)
        full[:, : self.k] = X
        return self.cost.residuals(full)


def _distinct_best(opt: Any, k: int, span: np.ndarray, min_dist: float = 0.2) -> list[np.ndarray]:
    X, f = getattr(opt, "archive_x", None), getattr(opt, "archive_f", None)
    if X is None or f is None:
        return [np.asarray(opt.x, float)]
    out: list[np.ndarray] = []
    for i in np.argsort(f):
        if len(out) >= k or not np.isfinite(f[i]):
            break
        if all(np.linalg.norm((X[i] - o) / span) / np.sqrt(span.size) >= min_dist for o in out):
            out.append(np.asarray(X[i], float))
    return out or [np.asarray(opt.x, float)]


def _refine(cost: Any, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_nfev: int) -> Any:
    from scipy.optimize import least_squares  # here: the time-domain identify loads no scipy

    span = hi - lo
    x0 = np.clip(x0, lo + 1e-9 * span, hi - 1e-9 * span)

    def fun(x: np.ndarray) -> np.ndarray:
        r = cost.residuals(x[None])[0]
        return np.where(np.isfinite(r), r, 1e6)

    def jac(x: np.ndarray) -> np.ndarray:
        h = 1e-6 * np.maximum(np.abs(x), 1e-2 * span)
        h = np.where(x + h > hi, -h, h)
        R = cost.residuals(np.vstack([x[None], x[None] + np.diag(h)]))
        R = np.where(np.isfinite(R), R, 1e6)
        return ((R[1:] - R[0]) / h[:, None]).T

    return least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac", max_nfev=max_nfev)


def _std(res: Any, n_params: int) -> np.ndarray:
    J = res.jac
    dof = max(res.fun.size - n_params, 1)
    s2 = float(np.sum(res.fun ** 2)) / dof
    cov = s2 * np.linalg.pinv(J.T @ J)
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def _global_search(cost: _SubCost, lo: np.ndarray, hi: np.ndarray, name: str, cfg: FreqIdentifyConfig,
                   algorithm: str, rng: np.random.Generator, callback: Callable[[dict], Any] | None,
                   search_options: Mapping[str, Any]) -> tuple[list[np.ndarray], np.ndarray, float, list[float]]:
    """The optimiser's search of one subsystem: (refinement starts, best point, its cost, history)."""

    def cb(res: Any) -> bool:
        if callback is not None:
            return bool(callback({"stage": f"search {name} (frequency)", "nit": res.nit, "maxiter": cfg.maxiter,
                                  "fun": float(res.fun), "nfev": res.nfev}))
        return False

    search: Any = cost
    dims = list(range(lo.size))
    if name == "horizontal" and cfg.varpro:
        search = _VarProCost(cost, lo, hi)
        dims = search.search_dims()
    opt = ALGORITHMS[algorithm](search, np.stack([lo[dims], hi[dims]], axis=1), rng=rng, maxiter=cfg.maxiter,
                                callback=cb, **search_options)
    starts = _distinct_best(opt, cfg.refine_starts, hi[dims] - lo[dims])
    if search is not cost:
        starts = list(search.complete(np.array(starts)))
        opt.x = starts[0]
    return starts, np.asarray(opt.x, float), float(opt.fun), list(opt.history)


def identify_frequency(responses: ResponseSet, prepared: Any = None, *, algorithm: str = "cabc", seed: int = 0,
                       bounds: dict[str, tuple[float, float]] | None = None, config: FreqIdentifyConfig | None = None,
                       callback: Callable[[dict], Any] | None = None, start: np.ndarray | None = None,
                       search_options: Mapping[str, Any] | None = None) -> HoverModel:
    """Fit the hover model to ``responses``; trims and sources come from ``prepared`` when given.

    ``search_options``: the optimiser's hyper-parameters (colony size, population, ...), as the
    time-domain identification takes them from ``[identify]``
    (:meth:`groundstation.sysid.settings.IdentifyConfig.search_options`); None: the optimiser's defaults.

    ``start`` (31,): no global search; the refinement runs from this parameter vector only (the
    J minimum nearest a given model, e.g. a time-domain fit's or, on simulated data, the truth's).
    """
    cfg = config or FreqIdentifyConfig()
    if cfg.weighting == "output_error" and prepared is None:   # responses only: Tischler's J
        cfg = replace(cfg, weighting="coherence")
    if algorithm not in ALGORITHMS:
        raise FreqError(f"unknown algorithm {algorithm!r}; choose one of {sorted(ALGORITHMS)}")
    rs = responses
    b_all = bounds_array(bounds)
    rng = np.random.default_rng(seed)
    theta = np.clip(np.zeros(N_PARAMS), b_all[:, 0], b_all[:, 1])
    std = np.full(N_PARAMS, np.nan)
    delays = np.zeros(4)
    fixed: list[str] = []
    reasons: list[str] = []
    fit: dict[str, Any] = {"algorithm": algorithm if start is None else "refinement from a given start",
                           "domain": "frequency", "evaluations": 0, "history": {}, "search_cost": {}, "J_by_subsystem": {},
                           "cost_by_subsystem": {}, "weighting": cfg.weighting}
    active = set(rs.conditioned_on)
    for name, params, inputs in _SUBSYSTEMS:
        pairs = [p for p in rs.with_response if p.input in inputs and has_path(p.input, p.output)]
        idx = [PARAM_INDEX[n] for n in params]
        if not pairs:
            fixed += list(params)
            reasons.append(f"{name} subsystem: no input-output pair with a coherent response; parameters fixed at 0")
            continue
        drop = {PARAM_INDEX[n] for i in inputs if i not in active for n in INPUT_PARAMS[i]}
        for i in inputs:
            if i not in active:
                fixed += list(INPUT_PARAMS[i])
                reasons.append(f"input {i} never moves: {', '.join(INPUT_PARAMS[i])} fixed at 0")
        free_idx = np.array([k for k in idx if k not in drop])
        d_in = [INPUTS.index(i) for i in inputs if cfg.fit_delays and any(p.input == i for p in pairs)]
        jcost = _SubCost(rs, pairs, free_idx, d_in, theta, "coherence" if cfg.weighting == "output_error" else cfg.weighting)
        cost: Any = jcost
        if cfg.weighting == "output_error":
            sub = 0 if name == "horizontal" else 1
            cost = FdoeCost(prepared.segments, prepared.dt_s, sub, jcost.unpack, f_min_hz=cfg.oe_band_hz[0],
                            f_max_hz=cfg.oe_band_hz[1], n_freq=cfg.oe_n_freq, window_s=cfg.oe_window_s)
        lo = np.concatenate([b_all[free_idx, 0], np.zeros(len(d_in))])
        hi = np.concatenate([b_all[free_idx, 1], np.full(len(d_in), cfg.max_delay_s)])

        if start is None:   # output error: the search (and first refinement) on J, then the output error from there
            runs = [_global_search(jcost, lo, hi, name, cfg, algorithm, rng, callback, search_options or {})
                    for _ in range(cfg.searches)]
            starts = [x for r in runs for x in r[0]]
            _, x_s, f_s, history = min(runs, key=lambda r: r[2])
        else:  # refine the given model only
            x_s = np.clip(np.concatenate([np.asarray(start, float)[free_idx], np.zeros(len(d_in))]), lo, hi)
            starts, f_s, history = [x_s], float(cost(x_s[None])[0]), []
        best_x, best_f, best_res = np.asarray(x_s, float), f_s, None
        if cfg.refine:
            best_f = np.inf
            for x0 in starts:
                res = _refine(jcost, x0, lo, hi, cfg.refine_max_nfev)
                f = float(jcost(res.x[None])[0])
                if f < best_f:
                    best_x, best_f, best_res = res.x, f, res
        if cfg.refine and cost is not jcost:   # channels weighted by their residual at the J fit, then refined
            cost.set_noise_weights(best_x)
            k = free_idx.size   # the delays stay at the J fit's (a phase slope J measures well; windows cut a delay)
            best_res = _refine(_Partial(cost, best_x, k), best_x[:k], lo[:k], hi[:k], cfg.refine_max_nfev)
            best_x = np.concatenate([best_res.x, best_x[k:]])
            best_f = float(cost(best_x[None])[0])
        th, d = cost.unpack(best_x[None])
        theta = th[0]
        delays[d_in] = d[0, d_in]
        if best_res is not None:
            s = _std(best_res, best_x.size)
            std[free_idx] = s[: free_idx.size]
        fit["evaluations"] += cost.nfev + (jcost.nfev if cost is not jcost else 0)
        fit["history"][name] = [float(h) for h in history]
        fit["search_cost"][name] = f_s
        fit["cost_by_subsystem"][name] = best_f
        fit["J_by_subsystem"][name] = jcost.j_avg(best_x)
    return _model(theta, std, delays, cfg, fit, fixed, reasons, rs, prepared, b_all)


def _model(theta: np.ndarray, std: np.ndarray, delays: np.ndarray, cfg: FreqIdentifyConfig, fit: dict[str, Any],
           fixed: list[str], reasons: list[str], rs: ResponseSet, prepared: Any, b_all: np.ndarray) -> HoverModel:
    span = b_all[:, 1] - b_all[:, 0]
    pinned = [n for k, n in enumerate(PARAM_NAMES)
              if n not in fixed and min(theta[k] - b_all[k, 0], b_all[k, 1] - theta[k]) < 1e-3 * span[k]]
    fit.update({"fixed": fixed, "fixed_reasons": reasons, "windows_s": list(rs.windows_s),
                "frequency_hz": [float(rs.f_hz[0]), float(rs.f_hz[-1])], "sample_interval_s": rs.dt_s,
                "cost": float(sum(fit["cost_by_subsystem"].values())), "fitness": 0.0})
    fit["fitness"] = 1.0 / (1.0 + fit["cost"])
    augment = [{"name": "input_delay", "input": INPUTS[i], "delay_s": float(delays[i])}
               for i in range(4) if cfg.fit_delays and delays[i] > 0]
    kw: dict[str, Any] = {}
    if prepared is not None:
        kw = {"input_trim_pwm": dict(prepared.input_trim_pwm), "pwm_per_unit": float(prepared.pwm_per_unit),
              "output_trim": dict(prepared.output_trim),
              "source": {"logs": sorted({s.source for s in prepared.segments})}}
    return HoverModel(params={n: float(v) for n, v in zip(PARAM_NAMES, theta, strict=True)},
                      sample_rate_hz=float(1.0 / rs.dt_s),
                      parameter_std={n: (None if n in fixed or not np.isfinite(s) else float(s))
                                     for n, s in zip(PARAM_NAMES, std, strict=True)},
                      augmentations=augment, fit=ModelFit.make(**fit), pinned=pinned, **kw)
