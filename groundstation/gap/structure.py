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

Whiteness of the residual itself is not tested: the outputs are smoothed and some are interpolated
from slower streams, so even a perfect model leaves coloured noise; the held-out gap-to-noise ratio
of the locate stage (residual against the noise floor measured in the data) stands in for it.

A structure test counts when it is significant (Bonferroni over the structure tests at the
configured family-wise alpha) and practically significant (held-out cost down by more than
``min_score_pct`` and the gap on the outputs smaller), exactly as a catalogue effect must be.
Pure numpy/scipy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from groundstation.gap import attribute, hypotheses
from groundstation.gap.config import DiagnoseConfig
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


def _feature_columns(ctx: hypotheses.Context, c: int, kind: str) -> tuple[np.ndarray, float]:
    """Weighted output sensitivities (W, L, 8, 1) to an extra input signal on channel ``c``."""
    ev = ctx.ev
    u = ev.U[:, :, c]
    if kind == "input_asymmetry":
        g = np.abs(u) - np.abs(u).mean()
        scale = 1.0
    else:
        sd = float(u.std()) or 1.0
        g = u * np.abs(u) / sd
        scale = sd
    U2 = ev.U.copy()
    U2[:, :, c] = u + g
    yh = ctx.variants_residual(U_list=[ev.U, U2])
    X = ((yh[1] - yh[0]) * ev.w8) * ev.mask[:, None]
    return X[..., None], scale


def nonlinear_input_tests(ctx: hypotheses.Context, in_excited: np.ndarray, rng: np.random.Generator,
                          cfg: DiagnoseConfig) -> list[StructureTest]:
    """Asymmetry and amplitude-dependence tests on every excited input (see the module docstring)."""
    ev = ctx.ev
    chans = [c for c in range(4) if in_excited[c]]
    n_tests = max(2 * len(chans), 1)
    crit = cfg.alpha / n_tests
    out_ch = tuple(int(c) for c in np.flatnonzero(ev.available))
    tests = []
    for c in chans:
        for kind in ("input_asymmetry", "amplitude_dependence"):
            X, _ = _feature_columns(ctx, c, kind)
            sse, _, coefs = ctx.nested(f"{kind}_{c}", [({}, ev.r0, X)])
            s = attribute.score(ctx.base_sse, sse, ev.energy, out_ch, rng, n_boot=min(cfg.n_boot, cfg.score_n_boot))
            s.p_value = attribute.combined_p(ctx.base_sse.sum(1), sse.sum(1), rng, cfg.n_boot, cfg.window_alpha,
                                             ctx.base_blocks, ctx.blocks[f"{kind}_{c}"])
            coef = float(np.mean(coefs[0][:, 0]))
            sig = bool(s.p_value < crit and s.score_pct > cfg.min_score_pct and s.shrink_pct > 0)
            if kind == "input_asymmetry":
                what = (f"{INPUTS[c]} response asymmetric: gain {100 * coef:+.0f} % for deflections above trim, "
                        f"{-100 * coef:+.0f} % below")
            else:
                what = f"{INPUTS[c]} gain changes with deflection: {100 * coef:+.0f} % per input std"
            tests.append(StructureTest(kind, INPUTS[c], coef, float(s.score_pct), float(s.shrink_pct),
                                       float(s.p_value), sig,
                                       f"{what}; held-out cost {s.score_pct:+.1f}% (p={s.p_value:.2g})"))
    return tests


def _n_eff(x: np.ndarray, max_lag: int) -> float:
    """Effective sample size of a series from its autocorrelation (Bartlett)."""
    x = x - x.mean()
    v = float(x @ x)
    if v <= 0:
        return float(x.size)
    rho = [float(x[:-k] @ x[k:]) / v for k in range(1, max_lag)]
    return float(x.size / max(1.0 + 2.0 * sum(r for r in rho if r > 0), 1.0))


def input_cross_correlation(e: np.ndarray, U: np.ndarray, dt_s: float, out_excited: np.ndarray,
                            in_excited: np.ndarray, max_lag_s: float = 1.0) -> list[dict]:
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
