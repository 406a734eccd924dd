"""How far the verdict sits from the edges of the tests that decided it: the report's ``verdict_margin``.

A verdict is decided by tests with thresholds: a candidate is named when the paired bootstrap of its
held-out gain gives a p-value below the Bonferroni level, and the named effects must remove enough of
the gap above the noise (the share rule). The same flight cut into windows half a second later has
other windows, other folds and other bootstrap draws, and each statistic moves by a fraction of its
own standard error; a verdict whose statistic lies that close to its threshold can come out either
way, with or without any loss of the link. This module measures, for each test that decided the
verdict, the signed distance from its threshold in the statistic's own standard errors, and calls the
verdict ``borderline`` when the closest edge is within ``DiagnoseConfig.borderline_se`` of them; the
report then names the verdict on the other side of that edge. The verdict itself is not changed.

* significance (a candidate's paired bootstrap): the margin is the ``level`` quantile of the
  bootstrap distribution of the total held-out gain over its standard deviation (the test passes
  exactly when that quantile is above zero; for a normal sum it is ``z - z_level``). The same
  resampling units as the test (blocks when the whole-window check passes, else the weaker of
  blocks and windows; the air mass also on the attitude angles), with draws of their own.
* an input effect against an air mass (the encompassing test: what it adds once an air-mass motion
  is allowed, a window bootstrap): the same quantile margin of the windows' gains;
* the share rule: the upper end of the share's 5-95 % interval against ``explained_share_min_pct``,
  in the share's standard error ((95 % end - 5 % end) / 3.29).

Pure numpy; the draws derive from the diagnosis seed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from groundstation.gap import attribute, candidates, hypotheses
from groundstation.gap.config import DiagnoseConfig

#: the 5-95 % interval spans this many standard deviations of a normal statistic
_INTERVAL_SD = 3.29
#: resampled sums per quantile (the level quantile of a ~0.001 level rests on ~8 of them)
_DRAWS = 8000


@dataclass(frozen=True)
class Edge:
    """One test that decided the verdict: its statistic's distance from the threshold."""

    test: str  # "significance", "air_mass" or "share"
    subject: str  # the effect (and channel) tested
    margin_se: float  # signed: positive where the test passed
    passed: bool
    alternative: str  # the verdict had the test gone the other way
    detail: str


def quantile_margin(d: np.ndarray, level: float, rng: np.random.Generator, draws: int = _DRAWS) -> float:
    """The ``level`` quantile of the bootstrap sums of ``d`` (n,) over their standard deviation
    (positive: a paired bootstrap at ``level`` finds the total gain above zero)."""
    d = np.asarray(d, float).ravel()
    d = d[np.isfinite(d)]
    if d.size < 2:
        return float("-inf")
    sums = np.empty(draws)
    chunk = max(1, 2_000_000 // d.size)  # bounded memory: indices of about 2 M draws at a time
    for i in range(0, draws, chunk):
        k = min(chunk, draws - i)
        sums[i:i + k] = d[rng.integers(0, d.size, (k, d.size))].sum(axis=1)
    sd = float(sums.std())
    q = float(np.quantile(sums, level))
    return q / sd if sd > 0 else (float("inf") if q > 0 else float("-inf"))


def significance_margin(c: attribute.Candidate, ctx: hypotheses.Context, level: float, cfg: DiagnoseConfig,
                        rng: np.random.Generator) -> float | None:
    """The margin (standard errors) of candidate ``c``'s held-out gain test at ``level`` (see the module
    docstring); None for a candidate without per-window costs (a spectral line)."""
    h = c.hyp
    if h.sse is None:
        return None
    base = np.asarray(h.extra.get("base_sse", ctx.base_sse), float)
    d_win = base.sum(1) - np.asarray(h.sse, float).sum(1)
    m_win = quantile_margin(d_win, level, rng)
    blocks = h.extra.get("blocks_scored", ctx.blocks.get(h.effect))
    if blocks is None or ctx.base_blocks is None:
        m = m_win
    else:
        m_blk = quantile_margin(np.asarray(ctx.base_blocks) - np.asarray(blocks), level, rng)
        gate = quantile_margin(d_win, cfg.window_alpha, rng) > 0  # the whole-window check of combined_p
        m = m_blk if gate else min(m_blk, m_win)
    if h.effect == "wind_gust":
        att = [6, 7]
        m = min(m, quantile_margin(base[:, att].sum(1) - np.asarray(h.sse, float)[:, att].sum(1), level, rng))
    return m


def _top_gain(named: Sequence[attribute.Candidate], partial: Sequence[attribute.Candidate]) -> float:
    """The held-out gain a candidate must beat to change the verdict: the first named effect's, else the
    first partial finding's (which the share rule or the halves set aside), else none."""
    first = (list(named) or list(partial))[:1]
    return first[0].score.score_pct if first else -np.inf


def _label(c: attribute.Candidate) -> str:
    ch = c.hyp.input or c.hyp.output
    return c.hyp.effect + (f" {ch}" if ch else "")


def significance_edges(named: list[attribute.Candidate], others: list[attribute.Candidate], verdict: str,
                       fallback: str, ctx: hypotheses.Context, crit: float, cfg: DiagnoseConfig,
                       rng: np.random.Generator, partial: Sequence[attribute.Candidate] = ()) -> list[Edge]:
    """The significance edges of the verdict: the first named effect's own test, and every candidate
    that failed on its p-value alone (practically significant and physical) whose naming would change
    the verdict (a larger held-out gain than the first named effect or partial finding, or nothing
    found at all). ``fallback``: the verdict without the first named effect."""
    edges = []
    if named:
        m = significance_margin(named[0], ctx, crit, cfg, rng)
        if m is not None:
            edges.append(Edge("significance", _label(named[0]), round(m, 2), True,
                              named[1].hyp.effect if len(named) > 1 else fallback,
                              f"held-out gain {named[0].score.score_pct:+.1f} %, p={named[0].score.p_value:.2g} "
                              f"against {crit:.2g}"))
    top = _top_gain(named, partial)
    for c in others:
        if c.score.p_value < crit or not (candidates.gain_ok(c.score, cfg) and candidates.physical(c.hyp, cfg)):
            continue
        if c.score.score_pct <= top:
            continue
        m = significance_margin(c, ctx, crit, cfg, rng)
        if m is not None:
            edges.append(Edge("significance", _label(c), round(m, 2), False, c.hyp.effect,
                              f"held-out gain {c.score.score_pct:+.1f} %, p={c.score.p_value:.2g} against {crit:.2g}"))
    return edges


def air_mass_edges(named: list[attribute.Candidate], others: list[attribute.Candidate], fallback: str, crit: float,
                   cfg: DiagnoseConfig, rng: np.random.Generator, partial: Sequence[attribute.Candidate] = ()) -> list[Edge]:
    """The encompassing test of an input effect against an air mass (does it still lower the held-out cost
    once an air-mass motion is allowed? a window bootstrap at ``crit``) where it decided the verdict: the
    first named effect passed it, or a candidate that passed its own test and failed this one would have
    been named first. An input effect the air mass explained as well, kept because the air mass added
    nothing to it, was not decided by this test."""
    edges = []
    top = _top_gain(named, partial)
    for c in named[:1] + others:
        d = c.hyp.extra.get("gain_given_air_mass")
        if c.hyp.extra.get("air_mass_adds_nothing_p") is not None:
            continue
        first = bool(named) and c is named[0]
        p = float(c.hyp.extra.get("p_given_air_mass", np.nan))
        failed_here = c.score.p_value < crit and not p < crit  # passed its own test, not this one
        if d is None or not (first or (failed_here and c.score.score_pct > top
                                       and candidates.gain_ok(c.score, cfg) and candidates.physical(c.hyp, cfg))):
            continue
        alt = (named[1].hyp.effect if len(named) > 1 else fallback) if first else c.hyp.effect
        edges.append(Edge("air_mass", _label(c), round(quantile_margin(np.asarray(d), crit, rng), 2), first, alt,
                          f"what it adds once an air-mass motion is allowed, p={p:.2g} against {crit:.2g}"))
    return edges


def share_edge(interval: tuple[float, float] | None, verdict: str, partial: list[attribute.Candidate],
               named: list[attribute.Candidate], cfg: DiagnoseConfig) -> Edge | None:
    """The share rule's edge: None when the rule did not decide (no significant gap, or no interval)."""
    if interval is None or not (named or partial):
        return None
    lo, hi = interval
    se = (hi - lo) / _INTERVAL_SD
    if not se > 0:
        return None
    first = (named or partial)[0]
    passed = bool(named)
    return Edge("share", _label(first), round((hi - cfg.explained_share_min_pct) / se, 2), passed,
                "unexplained" if passed else first.hyp.effect,
                f"the named effects remove up to {hi:.1f} % of the gap above noise (5-95 % interval "
                f"{lo:.1f} to {hi:.1f} %), against {cfg.explained_share_min_pct:g} %")


def summary(edges: list[Edge], verdict: str, cfg: DiagnoseConfig) -> dict[str, Any]:
    """The report's ``verdict_margin``: every deciding edge, the closest, whether the verdict is borderline, and
    the verdicts across the edges within the band (closest first)."""
    if not edges:
        return {"borderline": False, "alternative": None, "alternatives": [], "closest": None, "edges": [],
                "band_se": cfg.borderline_se}
    inside = sorted((e for e in edges if abs(e.margin_se) < cfg.borderline_se and e.alternative != verdict),
                    key=lambda e: abs(e.margin_se))
    closest = inside[0] if inside else min(edges, key=lambda e: abs(e.margin_se))
    near = bool(inside)
    out = {"borderline": near, "alternative": closest.alternative if near else None,
           "alternatives": list(dict.fromkeys(e.alternative for e in inside)),
           "closest": asdict(closest), "edges": [asdict(e) for e in edges], "band_se": cfg.borderline_se}
    if near:
        out["note"] = (f"the verdict is borderline: the {closest.test} test of the {closest.subject.replace('_', ' ')} "
                       f"is {closest.margin_se:+.2f} standard errors from its threshold ({closest.detail}); "
                       f"another cut of the same flight into windows can give {closest.alternative}")
    return out
