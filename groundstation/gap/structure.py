"""What the base model leaves in its held-out residual that no catalogue effect names: ``unexplained``.

When no catalogue effect is named, the residual can still hold structure the linear hover model
cannot have. Tests, each on held-out windows against the base model's own held-out cost (the same
k-fold re-fit, so the model gets every chance to absorb the structure linearly first):

* **input asymmetry** per excited input: an extra input column ``|u| - mean|u|`` entering through the
  input's own control derivatives (a gain that differs for deflections above and below trim);
* **amplitude dependence** per excited input: an extra column ``u |u| / std(u)`` (a gain growing or
  shrinking with deflection);
* **residual-input cross-correlation**: the largest normalised cross-correlation between the
  held-out residual of each excited output and each excited input at lags 0-1 s (input leading),
  against its white-noise null ``N(0, 1/n_eff)`` with ``n_eff`` from the residual's own
  autocorrelation (Bartlett), reported as evidence.

* **whiteness** (Ljung-Box, reported as evidence): the held-out residual against the *raw* outputs
  (not the smoothed ones), read at each channel's own stream interval (a channel sent slower than
  the grid is interpolated onto it, which correlates neighbouring grid samples), pooled over
  windows, lags up to ``max_lag_s``; the statistic against chi-square with as many degrees of freedom
  as lags. It does not decide a verdict on its own: in closed-loop flight the disturbances the pilot
  answers colour even a perfect model's residual; the held-out gap-to-noise ratio of the locate
  stage (residual against the noise floor measured in the data) decides whether there is a gap.

A structure test counts when it is significant (Bonferroni over the structure tests at the
configured family-wise alpha) and practically significant (held-out cost down by more than
``min_score_pct`` and the gap on the outputs smaller), exactly as a catalogue effect must be, and
when the part of the residual it explains stands out of the noise: on at least one output its RMS
(from the held-out cost it removes) exceeds ``structure_min_effect_to_noise`` times that channel's
noise floor measured in the data (:mod:`groundstation.gap.noise`). On a long flight a structure a
fraction of the noise in size is significant and still no departure anyone could act on.
Pure numpy/scipy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from groundstation.gap import attribute, hypotheses
from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.evaluate import SegmentArrays
from groundstation.sysid.model import INPUTS, OUTPUTS


@dataclass(frozen=True)
class StructureTest:
    """One held-out test of a structure the linear model cannot have."""

    kind: str  # "input_asymmetry" | "amplitude_dependence"
    input: str
    coefficient: float  # relative gain change: asymmetry a (gain 1 +- a) or per std of the input
    score_pct: float
    shrink_pct: float
    p_value: float
    significant: bool
    description: str
    #: largest over the outputs of the RMS of the residual part it explains over the channel's noise floor
    effect_to_noise: float = float("inf")


def _feature(u: np.ndarray, kind: str, mean_abs: float, sd: float) -> np.ndarray:
    """The extra input signal of a structure on input samples ``u`` (any shape)."""
    if kind == "input_asymmetry":
        return np.abs(u) - mean_abs
    return u * np.abs(u) / sd


def _feature_columns(ctx: hypotheses.Context, c: int, kind: str) -> tuple[np.ndarray, float]:
    """Weighted output sensitivities (W, L, 8, 1) to an extra input signal on channel ``c``."""
    ev = ctx.ev
    u = ev.U[:, :, c]
    sd = float(u.std()) or 1.0
    g = _feature(u, kind, float(np.abs(u).mean()), sd)
    # the model is linear in its inputs: the extra signal's response is its product with the input's
    # response matrix (what simulating the inputs with and without it and subtracting gives, to round-off)
    X = np.matmul(g.reshape(-1, ev.L), ctx.response(c)).reshape(ev.W, ev.L, 8) * ev.wmask
    return X[..., None], (1.0 if kind == "input_asymmetry" else sd)


def effect_to_noise(base_sse: np.ndarray, sse: np.ndarray, energy: np.ndarray, floor: np.ndarray | None) -> float:
    """Largest over the outputs of the RMS of the residual part a change explains (held-out cost
    removed, ``base_sse - sse`` (W, 8)) over the channel's noise floor (normalised RMS, as
    ``floor`` (8,) of :func:`groundstation.gap.noise.noise_floor`); inf without a floor."""
    if floor is None:
        return float("inf")
    gain = np.maximum(base_sse.sum(axis=0) - sse.sum(axis=0), 0.0)
    e = energy.sum(axis=0)
    ok = (e > 0) & np.isfinite(floor) & (floor > 0)
    if not ok.any():
        return float("inf")
    return float(np.max(np.sqrt(gain[ok] / e[ok]) / floor[ok]))


def _one_test(ctx: hypotheses.Context, c: int, kind: str, rng: np.random.Generator, cfg: DiagnoseConfig,
              crit: float, floor: np.ndarray | None = None) -> StructureTest:
    """One held-out structure test on input ``c`` against ``ctx``'s base model (``floor``: the outputs'
    noise floors, the effect-size gate; None: no gate)."""
    ev = ctx.ev
    out_ch = tuple(int(k) for k in np.flatnonzero(ev.available))
    X, _ = _feature_columns(ctx, c, kind)
    sse, _, coefs = ctx.nested(f"{kind}_{c}", [({}, ev.r0, X)])
    s = attribute.score(ctx.base_sse, sse, ev.energy, out_ch, rng, n_boot=min(cfg.n_boot, cfg.score_n_boot), test_n_boot=cfg.n_boot)
    s.p_value = attribute.combined_p(ctx.base_sse.sum(1), sse.sum(1), rng, cfg.n_boot, cfg.window_alpha,
                                     ctx.base_blocks, ctx.blocks[f"{kind}_{c}"])
    coef = float(np.mean(coefs[0][:, 0]))
    etn = effect_to_noise(ctx.base_sse, sse, ev.energy, floor)
    sig = bool(s.p_value < crit and s.score_pct > cfg.min_score_pct and s.shrink_pct > 0
               and etn > cfg.structure_min_effect_to_noise)
    if kind == "input_asymmetry":
        what = (f"{INPUTS[c]} response asymmetric: gain {100 * coef:+.0f} % for deflections above trim, "
                f"{-100 * coef:+.0f} % below")
    else:
        what = f"{INPUTS[c]} gain changes with deflection: {100 * coef:+.0f} % per input std"
    size = f", {etn:.1f}x the noise" if np.isfinite(etn) else ""
    return StructureTest(kind, INPUTS[c], coef, float(s.score_pct), float(s.shrink_pct), float(s.p_value), sig,
                         f"{what}; held-out cost {s.score_pct:+.1f}% (p={s.p_value:.2g}{size})", etn)


def structure_crit(in_excited: np.ndarray, cfg: DiagnoseConfig) -> float:
    """Per-test level of the structure tests (Bonferroni over two tests per excited input)."""
    return cfg.alpha / max(2 * int(np.sum(in_excited[:4])), 1)


def nonlinear_input_tests(ctx: hypotheses.Context, in_excited: np.ndarray, rng: np.random.Generator,
                          cfg: DiagnoseConfig, floor: np.ndarray | None = None) -> list[StructureTest]:
    """Asymmetry and amplitude-dependence tests on every excited input (see the module docstring);
    ``floor`` (8,): the outputs' noise floors (normalised RMS) of the effect-size gate."""
    crit = structure_crit(in_excited, cfg)
    return [_one_test(ctx, c, kind, rng, cfg, crit, floor) for c in range(4) if in_excited[c]
            for kind in ("input_asymmetry", "amplitude_dependence")]


def retest(ctx: hypotheses.Context, tests: list[StructureTest], rng: np.random.Generator, cfg: DiagnoseConfig,
           crit: float, floor: np.ndarray | None = None) -> list[StructureTest]:
    """The same structure tests against another base model (one with a catalogue effect in it):
    does the structure survive once that effect is in the model?"""
    return [_one_test(ctx, INPUTS.index(t.input), t.kind, rng, cfg, crit, floor) for t in tests]


def apply_structure(t: StructureTest, segments: list[SegmentArrays], ev: Any) -> list[SegmentArrays]:
    """The segments with the fitted structure put into their input (``u + coefficient x feature(u)``)."""
    c = INPUTS.index(t.input)
    u_w = ev.U[:, :, c]
    mean_abs, sd = float(np.abs(u_w).mean()), float(u_w.std()) or 1.0
    out = []
    for s in segments:
        u = s.inputs.copy()
        u[:, c] = u[:, c] + t.coefficient * _feature(u[:, c], t.kind, mean_abs, sd)
        out.append(SegmentArrays(t_s=s.t_s, inputs=u, outputs=s.outputs, outputs_raw=s.outputs_raw,
                                 alt_m=s.alt_m, flight=s.flight, measured=s.measured))
    return out


def air_mass_sign_dependence(air: np.ndarray, u: np.ndarray) -> tuple[float, float]:
    """Does a fitted air velocity follow the sign-even part of one stick's deflection?

    ``air`` (W, 2, K): the per-window air-velocity knots of the air-mass fit (m/s, piecewise linear
    over the window); ``u`` (W, L): the input over the same windows. An air mass moves the aircraft
    whatever the stick does; the pilot's answers to it are odd in the stick (a push one way for a gust
    one way) and so are uncorrelated with the even part ``|u| - mean|u|``. A response that differs
    for deflections above and below trim soaks a fitted air velocity that follows that even part.
    Each knot's air velocity is regressed on the even and the odd part of the input averaged under
    the knot's hat function (intercept per component); the even coefficients of both components are
    tested together (Wald, chi-square with 2 degrees of freedom) with a cluster-robust covariance over
    windows, so the noise of the air-velocity estimates is the data's own.
    Returns (p-value, the even part's share of the air velocity's variance).
    """
    W, _, K = air.shape
    L = u.shape[1]
    tt = np.linspace(0.0, 1.0, L)
    hats = np.stack([np.maximum(0.0, 1.0 - np.abs(tt - c) * (K - 1)) for c in np.linspace(0.0, 1.0, K)])
    hats /= hats.sum(axis=1, keepdims=True)
    even = (np.abs(u) - np.abs(u).mean()) @ hats.T  # (W, K)
    odd = (u - u.mean()) @ hats.T
    X1 = np.column_stack([np.ones(W * K), even.ravel(), odd.ravel()])
    # both components stacked, each with its own three coefficients
    X = np.zeros((2 * W * K, 6))
    X[: W * K, :3] = X1
    X[W * K:, 3:] = X1
    y = np.concatenate([air[:, 0].ravel(), air[:, 1].ravel()])
    cl = np.concatenate([np.repeat(np.arange(W), K)] * 2)
    XtX_inv = np.linalg.pinv(X.T @ X)
    beta = XtX_inv @ X.T @ y
    e = y - X @ beta
    meat = np.zeros((6, 6))
    for w in range(W):
        g = X[cl == w].T @ e[cl == w]
        meat += np.outer(g, g)
    cov = XtX_inv @ meat @ XtX_inv * W / max(W - 1, 1)
    idx = [1, 4]
    b = beta[idx]
    stat = float(b @ np.linalg.pinv(cov[np.ix_(idx, idx)]) @ b)
    fitted = X[:, idx] @ b
    share = float(fitted.var() / max(y.var(), 1e-300))
    return float(stats.chi2.sf(stat, 2)), share


def _n_eff(x: np.ndarray, max_lag: int) -> float:
    """Effective sample size of a series from its autocorrelation (Bartlett)."""
    x = x - x.mean()
    v = float(x @ x)
    if v <= 0:
        return float(x.size)
    rho = [float(x[:-k] @ x[k:]) / v for k in range(1, max_lag)]
    return float(x.size / max(1.0 + 2.0 * sum(r for r in rho if r > 0), 1.0))


def input_cross_correlation(e: np.ndarray, U: np.ndarray, dt_s: float, out_excited: np.ndarray,
                            in_excited: np.ndarray, max_lag_s: float = DiagnoseConfig.xcorr_max_lag_s) -> list[dict]:
    """Largest residual-input cross-correlation (input leading by 0..max_lag_s) per output/input pair,
    with its z-score against the white-noise null using the residual's effective sample size."""
    res: list[dict[str, Any]] = []
    n_lag = max(int(round(max_lag_s / dt_s)), 1)
    for c in np.flatnonzero(out_excited):
        r = e[:, :, c].ravel()
        r = r - r.mean()
        ne = _n_eff(r, n_lag)
        for i in np.flatnonzero(in_excited):
            u = U[:, :, i].ravel()
            u = u - u.mean()
            den = np.sqrt((r @ r) * (u @ u))
            if den <= 0:
                continue
            cc = np.array([float(r[k:] @ u[: u.size - k]) / den for k in range(0, n_lag, max(n_lag // 10, 1))])
            k = int(np.argmax(np.abs(cc)))
            z = float(abs(cc[k]) * np.sqrt(ne))
            res.append({"output": OUTPUTS[c], "input": INPUTS[i], "corr": round(float(cc[k]), 3),
                        "lag_s": round(k * max(n_lag // 10, 1) * dt_s, 2), "z": round(z, 1),
                        "log10_p": round(float(stats.norm.logsf(z) / np.log(10) + np.log10(2)), 1)})
    return sorted(res, key=lambda d: -float(d["z"]))[:4]


def ljung_box(e_raw: np.ndarray, stride: np.ndarray | None, channels: np.ndarray, dt_s: float,
              max_lag_s: float = DiagnoseConfig.xcorr_max_lag_s, alpha: float = DiagnoseConfig.alpha) -> list[dict]:
    """Ljung-Box (portmanteau) whiteness of the held-out raw residual ``e_raw`` (W, L, 8) per channel in
    ``channels``: ``Q = sum_h n_h rho_h^2`` with ``n_h`` the lag-``h`` products pooled over windows.

    Each channel is read every ``stride[c]`` grid steps (its own stream interval), windows pooled
    (lag products within windows only); Bonferroni over the channels tested.
    """
    res: list[dict[str, Any]] = []
    chans = [int(c) for c in np.flatnonzero(channels)]
    for c in chans:
        k = 1 if stride is None else max(int(round(float(stride[c]))), 1)
        x = e_raw[:, ::k, c]
        x = x - x.mean()
        n_w = x.shape[1]
        H = min(max(int(round(max_lag_s / (k * dt_s))), 1), max(n_w // 4, 1))
        den = float((x ** 2).sum()) / x.size
        if den <= 0 or n_w <= H + 1:
            continue
        rho = np.array([float((x[:, h:] * x[:, :-h]).sum()) / (x.shape[0] * (n_w - h)) / den for h in range(1, H + 1)])
        n_h = x.shape[0] * (n_w - np.arange(1, H + 1))
        q = float(np.sum(n_h * rho ** 2))  # pooled over windows: var(rho_h) = 1 / n_h under whiteness
        log10_p = max(float(stats.chi2.logsf(q, H) / np.log(10)), -300.0)  # finite for the JSON report
        res.append({"output": OUTPUTS[c], "q": round(q, 1), "lags": H, "lag_step_s": round(k * dt_s, 3),
                    "lag1_autocorrelation": round(float(rho[0]), 3), "log10_p": round(log10_p, 1),
                    "white": bool(log10_p > np.log10(alpha / max(len(chans), 1)))})
    return res
