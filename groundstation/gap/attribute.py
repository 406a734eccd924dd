"""Scoring, significance and verdict over the hypothesis library; shrink with bootstrap intervals.

A hypothesis is scored by its held-out cost against the base model's on the same windows
(``Hypothesis.sse`` vs the base ``sse``, both (W, 8)):

* ``score`` = held-out cost reduction in percent of the base cost (all channels, eq.-11 weights);
* significance by a paired bootstrap: over ~0.5 s blocks of the held-out residual (an effect at
  the sharpest inputs or near the ground lives in a handful of windows but many blocks),
  accompanied by a coarse whole-window bootstrap; Bonferroni over the tested hypotheses
  (see ``diagnose.py``);
* significance of a second effect given a first (the conditional step, Holm's second level):
  analytic tests of the same paired differences (:func:`conditional_p`), whose p-values are not
  floored by a resampling count, over the ~0.5 s blocks once a coarse whole-window bootstrap
  passes: a Wilcoxon signed-rank test (a gain in most blocks, robust to a few large losses that
  give a resampled sum heavy tails) and a studentised paired t-test (a large gain in a few
  blocks), the smaller p doubled (Bonferroni over the two); over windows alone (no blocks) the
  t-test;
* gap before/after = normalised RMS residual (held-out) over the channels the effect acts on;
  shrink = relative reduction, with a bootstrap percentile interval over windows.

The verdict rules (physical sign constraints, ``none``/``unexplained``) live in ``diagnose.py``.
Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from groundstation.gap.config import DiagnoseConfig


@dataclass
class Candidate:
    """A scored hypothesis (``hyp`` is a :class:`groundstation.gap.hypotheses.Hypothesis`)."""

    hyp: Any
    score: Score
    significant: bool
    evidence: str


@dataclass
class Score:
    score_pct: float
    p_value: float
    gap_before: float
    gap_after: float
    shrink_pct: float
    shrink_interval: tuple[float, float]
    per_channel_shrink: dict[int, float]


def paired_bootstrap(base: np.ndarray, alt: np.ndarray, rng: np.random.Generator, n_boot: int = DiagnoseConfig.n_boot,
                     groups: np.ndarray | None = None) -> float:
    """One-sided p-value that ``alt`` (W,) does not reduce the total of ``base`` (W,).

    ``groups`` (W,) optional block labels (e.g. segment) — resampled as wholes when given.
    """
    d = base - alt
    W = d.shape[0]
    if groups is not None and len(np.unique(groups)) >= 6:
        ug = np.unique(groups)
        sums = np.array([d[groups == g].sum() for g in ug])
        idx = rng.integers(0, len(ug), (n_boot, len(ug)))
        m = sums[idx].sum(axis=1)
    else:
        idx = rng.integers(0, W, (n_boot, W))
        m = d[idx].sum(axis=1)
    return float((np.sum(m <= 0) + 1) / (n_boot + 1))


def nrmse(sse: np.ndarray, energy: np.ndarray, channels: tuple[int, ...] | list[int]) -> float:
    """Mean over channels of sqrt(sum sse / sum energy) (held-out normalised RMS residual)."""
    vals = []
    for c in channels:
        e = energy[:, c].sum()
        if e > 0:
            vals.append(np.sqrt(sse[:, c].sum() / e))
    return float(np.mean(vals)) if vals else float("nan")


def _boot_shrink(base: np.ndarray, alt: np.ndarray, energy: np.ndarray, chans: tuple[int, ...],
                 idx: np.ndarray) -> np.ndarray:
    """Shrink (%) of :func:`nrmse` over the channels for every bootstrap resample of the windows
    (rows of ``idx`` (n_boot, W)), all at once: each resample's sums are its window counts times
    the per-window costs (0 where the base is not positive, as in :func:`score`)."""
    n_boot, W = idx.shape
    ch = list(chans)
    counts = np.bincount((idx + W * np.arange(n_boot)[:, None]).ravel(),
                         minlength=n_boot * W).reshape(n_boot, W).astype(float)
    e = counts @ energy[:, ch]  # (n_boot, nch)
    ok = e > 0
    n_ok = ok.sum(axis=1)
    e_safe = np.where(ok, e, 1.0)

    def _nrmse(sse: np.ndarray) -> np.ndarray:
        v = np.where(ok, np.sqrt(np.maximum(counts @ sse[:, ch], 0.0) / e_safe), 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(n_ok > 0, v.sum(axis=1) / n_ok, np.nan)

    b, a = _nrmse(base), _nrmse(alt)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(b > 0, 100.0 * (b - a) / np.where(b > 0, b, 1.0), 0.0)


def score(base: np.ndarray, alt: np.ndarray, energy: np.ndarray, channels: tuple[int, ...],
          rng: np.random.Generator, n_boot: int = DiagnoseConfig.score_n_boot,
          test_n_boot: int = DiagnoseConfig.n_boot) -> Score:
    """Score a hypothesis: base/alt held-out costs (W, 8), target energy (W, 8), effect channels.

    ``n_boot`` resamples for the shrink interval, ``test_n_boot`` for the paired test's p-value
    (``DiagnoseConfig.score_n_boot`` and ``n_boot``)."""
    tb, ta = base.sum(axis=1), alt.sum(axis=1)
    sc = 100.0 * (tb.sum() - ta.sum()) / max(tb.sum(), 1e-300)
    p = paired_bootstrap(tb, ta, rng, test_n_boot)
    chans = tuple(c for c in channels if energy[:, c].sum() > 0)
    gb = nrmse(base, energy, chans)
    ga = nrmse(alt, energy, chans)
    sh = 100.0 * (gb - ga) / gb if gb > 0 else 0.0
    W = base.shape[0]
    idx = rng.integers(0, W, (n_boot, W))
    boots = _boot_shrink(base, alt, energy, chans, idx)
    lo, hi = np.percentile(boots, [5, 95])
    per = {}
    for c in range(8):
        e = energy[:, c].sum()
        if e > 0 and base[:, c].sum() > 0:
            b1 = np.sqrt(base[:, c].sum() / e)
            a1 = np.sqrt(alt[:, c].sum() / e)
            per[c] = float(100.0 * (b1 - a1) / b1)
    return Score(float(sc), p, gb, ga, float(sh), (float(lo), float(hi)), per)


def combined_p(base: np.ndarray, alt: np.ndarray, rng: np.random.Generator, n_boot: int, window_alpha: float,
               base_blocks: np.ndarray | None = None, alt_blocks: np.ndarray | None = None) -> float:
    """The one p-value combination of the diagnosis: does ``alt`` lower the held-out cost of ``base``?

    ``base``/``alt`` (W,) held-out cost per window; ``base_blocks``/``alt_blocks`` (W, n) the same
    per ~0.5 s block when the hypothesis has them. Two resampling units: blocks (an effect at the
    sharpest inputs or near the ground lives in a handful of windows but in many blocks) and whole
    windows (a coarse check that the gain is not the within-window dependence of the blocks). When
    the window-level p is below ``window_alpha`` the block-level p decides, else the larger of the
    two. Without blocks the window-level p.
    """
    p_win = paired_bootstrap(base, alt, rng, n_boot)
    if base_blocks is None or alt_blocks is None:
        return p_win
    p_blk = paired_bootstrap(base_blocks.ravel(), alt_blocks.ravel(), rng, n_boot)
    return p_blk if p_win < window_alpha else max(p_blk, p_win)


def signed_rank_p(base: np.ndarray, alt: np.ndarray) -> float:
    """One-sided Wilcoxon signed-rank p-value that ``alt`` (n,) does not lower ``base`` (n,) unit by unit.

    Paired units (windows or blocks of the held-out cost); under the null the differences are
    symmetric about zero (the variant is as likely to raise a unit's cost as to lower it by the same
    amount), referred to the differences' own spread through their ranks, so a few large gains do
    not make the statistic heavy-tailed and no constant of the data enters. Units the variant leaves
    exactly unchanged carry no evidence and are dropped. Exact distribution up to 50 units (ties
    and zeros aside), normal approximation with tie correction beyond. 1 with fewer than two units.
    """
    d = np.asarray(base, float) - np.asarray(alt, float)
    d = d[np.isfinite(d) & (d != 0)]
    if d.size < 2:
        return 1.0
    return float(stats.wilcoxon(d, alternative="greater", zero_method="wilcox").pvalue)


def paired_t_p(base: np.ndarray, alt: np.ndarray) -> float:
    """One-sided studentised paired t-test p-value that ``alt`` (n,) does not lower ``base`` (n,) on average.

    The mean difference over its standard error, both measured on the units themselves (Student's
    t with n - 1 degrees of freedom). 1 with fewer than two units.
    """
    d = np.asarray(base, float) - np.asarray(alt, float)
    d = d[np.isfinite(d)]
    if d.size < 2:
        return 1.0
    sd = float(d.std(ddof=1))
    if sd == 0.0:
        return 0.0 if d.mean() > 0 else 1.0
    return float(stats.t.sf(d.mean() / (sd / np.sqrt(d.size)), d.size - 1))


def paired_p(base: np.ndarray, alt: np.ndarray) -> float:
    """Two analytic paired tests, the smaller p doubled (Bonferroni): :func:`signed_rank_p` (a gain
    in most units) and :func:`paired_t_p` (a large gain in a few)."""
    return min(1.0, 2.0 * min(signed_rank_p(base, alt), paired_t_p(base, alt)))


def design_effect(d: np.ndarray) -> float:
    """How many times the variance of a mean over the blocks (W, m) exceeds what independent blocks
    would give: ``1 + (m - 1) rho``, ``rho`` the correlation of blocks within a window measured on
    ``d`` itself (one-way analysis of variance over the windows, clipped to 0..1). 1 for one block
    per window or fewer than two windows."""
    d = np.asarray(d, float)
    W, m = d.shape
    if m < 2 or W < 2:
        return 1.0
    msb = m * float(d.mean(axis=1).var(ddof=1))
    msw = float(((d - d.mean(axis=1, keepdims=True)) ** 2).sum()) / (W * (m - 1))
    den = msb + (m - 1) * msw
    rho = min(max((msb - msw) / den, 0.0), 1.0) if den > 0 else 0.0
    return 1.0 + (m - 1) * rho


def clustered_paired_p(base_blocks: np.ndarray, alt_blocks: np.ndarray) -> float:
    """:func:`paired_p` over the blocks (W, m) of the held-out windows, each test's evidence counted as
    that of ``n / design_effect`` independent blocks (its one-sided z-score divided by the square root
    of :func:`design_effect` of the differences): neighbouring blocks of a window share the residual's
    slow part, so ``n`` correlated blocks say less than ``n`` independent ones."""
    b, a = np.asarray(base_blocks, float), np.asarray(alt_blocks, float)
    deff = design_effect(b - a)
    ps = [signed_rank_p(b.ravel(), a.ravel()), paired_t_p(b.ravel(), a.ravel())]
    ps = [float(stats.norm.sf(stats.norm.isf(min(max(p, 1e-300), 1.0)) / np.sqrt(deff))) for p in ps]
    return min(1.0, 2.0 * min(ps))


def conditional_p(base: np.ndarray, alt: np.ndarray, rng: np.random.Generator, n_boot: int, window_alpha: float,
                  base_blocks: np.ndarray | None = None, alt_blocks: np.ndarray | None = None,
                  clustered: bool = False) -> float:
    """:func:`combined_p` with the analytic tests of :func:`paired_p` deciding in place of the bootstrap.

    The test of a second effect given a first. With blocks: the coarse whole-window check stays the
    window bootstrap (its level ``window_alpha`` is far above its floor, and a large gain in a few
    of a few windows passes it where a test of the windows' ranks or mean would not); when it passes
    the ~0.5 s blocks decide by :func:`paired_p`, else the larger of the two. Without blocks the
    studentised t-test over the windows (:func:`paired_t_p`): over a few dozen windows a
    signed-rank test finds a consistent small shift whose total gain is not significant (measured:
    a 20 ms delay beside an air mass, signed-rank p 0.0004, mean p 0.09). ``clustered``: the block
    tests count correlated blocks as fewer independent ones (:func:`clustered_paired_p`).
    """
    if base_blocks is None or alt_blocks is None:
        return paired_t_p(base, alt)
    p_win = paired_bootstrap(base, alt, rng, n_boot)
    p_blk = (clustered_paired_p(base_blocks, alt_blocks) if clustered
             else paired_p(base_blocks.ravel(), alt_blocks.ravel()))
    return p_blk if p_win < window_alpha else max(p_blk, p_win)
