"""The plain output-error reference fit: the floor an identification must beat on held-out data.

``fit_reference(prepared, starts=4, seed=0, window_s=5.0)`` fits the same eq.-8 structure (every
parameter the data can move, see :func:`groundstation.sysid.identify.free_mask`) by nothing more
than multi-start least squares (:func:`groundstation.sysid.optimizers.minimize_lsq`) on the
windowed output error: windows of ``window_s`` started from the measured states, unmeasured
initial states by least squares, residuals normalised per channel as in the paper's eq. 11. No
search, no prior, no trims, no stability check: a baseline, not a product.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from groundstation.dsp.split import contiguous_kfold
from groundstation.dsp.timeskew import shift_inputs
from groundstation.sysid.cost import WindowedCost, make_windows
from groundstation.sysid.fit_section import ModelFit
from groundstation.sysid.heldout import predict
from groundstation.sysid.identify import free_mask
from groundstation.sysid.model import N_PARAMS, HoverModel, bounds_array, theta_to_dict
from groundstation.sysid.optimizers import minimize_lsq
from groundstation.sysid.refine import _fd_step


def fit_reference(prepared: Any, *, starts: int = 4, seed: int = 0, window_s: float = 5.0,
                  max_nfev: int = 60, theta0: np.ndarray | None = None) -> HoverModel:
    """Plain multi-start least-squares output-error fit (see the module docstring); ``theta0`` (all
    parameters) replaces the zero start."""
    free, _ = free_mask(prepared)
    b = bounds_array()[free]
    span = b[:, 1] - b[:, 0]
    with threadpool_limits(1):
        cost = WindowedCost(make_windows(prepared.segments, prepared.dt_s, window_s), free, np.zeros(N_PARAMS))

        def residuals(x: np.ndarray) -> np.ndarray:
            return cost.residuals(x[None])[0].ravel()

        def jac(x: np.ndarray) -> np.ndarray:
            h = _fd_step(x, span)
            h = np.where(x + h > b[:, 1], -h, h)
            R = cost.residuals(np.vstack([x[None], x[None] + np.diag(h)])).reshape(x.size + 1, -1)
            return ((R[1:] - R[0]) / h[:, None]).T

        zero = np.clip(np.zeros(int(free.sum())) if theta0 is None else np.asarray(theta0)[free], b[:, 0], b[:, 1])
        res = minimize_lsq(cost, b, rng=seed, maxiter=max_nfev, residuals=residuals, jac=jac, x0=[zero], starts=starts)
        theta = cost.full(res.x[None])[0]
    return HoverModel(params=theta_to_dict(theta), sample_rate_hz=1.0 / prepared.dt_s,
                      input_trim_pwm=dict(prepared.input_trim_pwm), pwm_per_unit=float(prepared.pwm_per_unit),
                      output_trim=dict(prepared.output_trim),
                      fit=ModelFit.make(algorithm="reference-lsq", cost=float(res.fun), starts=int(starts),
                                        window_s=float(window_s), estimate_all_initial=False))


def _cut(seg: Any, a_s: float, b_s: float) -> Any:
    """``seg`` restricted to the times a_s..b_s."""
    k = (seg.t_s >= a_s - 1e-9) & (seg.t_s <= b_s + 1e-9)
    m, br, st = seg.measured, seg.inputs_bridged, seg.settling
    return replace(seg, t_s=seg.t_s[k], inputs=seg.inputs[k], outputs=seg.outputs[k], outputs_raw=seg.outputs_raw[k],
                   alt_m=seg.alt_m[k], measured=None if m is None else m[k],
                   inputs_bridged=None if br is None else br[k], settling=None if st is None else st[k])


def shift_profile(prepared: Any, *, grid_s: tuple[float, ...] = tuple(np.round(np.arange(-0.08, 0.201, 0.04), 3)),
                  seed: int = 0, window_s: float = 5.0, folds: int = 3) -> dict[str, Any]:
    """The common input shift of ``grid_s`` (inputs advanced by it,
    :func:`groundstation.dsp.timeskew.shift_inputs`) under which the plain reference fit predicts
    ``folds`` contiguous held-out blocks of ``prepared`` best (mean eq.-19 match; every fit refined from
    the same point, the multi-start fit without a shift, so the profile is smooth). ``folds=0`` takes
    the lowest in-sample cost instead, every shift on the same samples: on a flight flown in closed loop
    it runs past the skew (the stick follows the motion, so inputs moved earlier keep explaining
    more of it in-sample) and predicts worse. A measurement for the bench: one single-start
    refinement per grid point and fold."""

    lo, hi = max(0.0, -min(grid_s)), max(0.0, max(grid_s))
    span = [(s.t_s[0] + lo, s.t_s[-1] - hi) for s in prepared.segments]
    theta0 = fit_reference(prepared, seed=seed, window_s=window_s).theta
    score = []
    for g in grid_s:
        one = [shift_inputs(replace(prepared, segments=[s]), g).segments for s in prepared.segments]
        data = replace(prepared, segments=[_cut(ss[0], a, b) for ss, (a, b) in zip(one, span, strict=True)
                                           if ss and b - a > window_s])
        if folds < 2:
            cost = fit_reference(data, starts=1, seed=seed, window_s=window_s, theta0=theta0).fit.cost
            score.append(float("nan") if cost is None else -float(cost))
            continue
        m = [predict(fit_reference(tr, starts=1, seed=seed, window_s=window_s, theta0=theta0), va,
                     window_s=window_s).mean_match for tr, va in contiguous_kfold(data, folds) if tr.segments and va.segments]
        score.append(float(np.mean(m)))
    i = int(np.nanargmax(score))
    best = float(grid_s[i])
    if 0 < i < len(score) - 1:
        den = score[i - 1] - 2 * score[i] + score[i + 1]
        if den < 0:
            best += 0.5 * (score[i - 1] - score[i + 1]) / den * (grid_s[i + 1] - grid_s[i])
    return {"shift_s": round(best, 4), "grid_s": [float(g) for g in grid_s], "folds": folds,
            "score": score, "score_is": "held-out mean match %" if folds >= 2 else "minus in-sample cost"}
