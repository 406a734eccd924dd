"""Choose the identification's configuration by held-out prediction.

No single setting of the output-error fit serves every flight: on a simulated flight with accurate
measured states, estimating every initial state over short (3-s) windows identifies the parameters
best; on a real flight, where the pilot closes the loop and the model misses part of the dynamics,
that lets each window absorb what the dynamics miss, and 5-s windows started from the *measured*
states predict the aircraft far better. So ``identify`` compares its configuration with a few
candidates (``IdentifyConfig.select_candidates``) by what a model is for, predicting data it was not
fitted to:

1. each candidate configuration is refined on the whole flight from the configuration's model (one
   pass: a screening fit, cheap);
2. each (the configuration's model too) is cross-validated over ``select_folds`` contiguous blocks
   (refit on k-1 blocks from the whole-flight fit, at most ``select_refit_nfev`` Jacobians, then
   predict the left-out one from the measured states:
   :func:`groundstation.sysid.heldout.crossvalidate`); a fold's score is the mean over channels of
   the eq.-19 match, each channel's floored at -100 % (a prediction that runs away counts as one
   twice as bad as predicting no motion, so one fold cannot swamp the others);
3. a configuration whose held-out prediction runs away on any fold (a channel's error more than
   three times the signal: :func:`groundstation.sysid.heldout.runaway_channels`) never wins over one
   that does not: a runaway model is not a usable model however well it predicts the other folds.
   Between two that both run away or both do not, a candidate replaces the configuration when its
   paired gain over the folds is positive by more than one standard error of that gain (the
   one-standard-error rule of cross-validated model choice; the error is the folds' own spread: a
   difference inside the noise of the held-out data keeps the configuration as given), or when it
   gains on every fold (a sign test: 5 of 5 folds has a chance of 1/32 under no difference; this
   keeps one catastrophic fold of the configuration, whose floored score swells the spread, from
   hiding a candidate that is better everywhere); among several such, the largest
   mean gain wins, and only the winner is refined in full (from the configuration's model and its
   own ``extra_starts``, the lowest refined (MAP) objective per subsystem), then cross-validated
   again for the report.

On a 150-s simulated flight the selection adds about 0.4 of the identification's time (one
candidate); on the simulated flights it keeps the configuration as given (its parameters are
within a few per cent of the truth), on the real TREX 550 log it switches to ``predictive``.

``select_candidates`` may hold rounds separated by ``|``: a round compares its candidates with the
winner of the round before and runs only when that round switched (the default tries overlapping
windows only once the ``predictive`` setting has won, so a simulated flight pays for one candidate).

``fit["selection"]`` reports every candidate's overrides, per-fold scores, gain and standard
error, and the choice; ``fit["heldout"]`` holds the chosen model's cross-validation.
Pure numpy on prepared data; no IO.
"""

from __future__ import annotations

import dataclasses
import json
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from groundstation.errors import SysidError
from groundstation.parallel import Map, serial_map
from groundstation.sysid.heldout import crossvalidate
from groundstation.sysid.model import HoverModel
from groundstation.sysid.refine import map_objective, with_standard_errors
from groundstation.sysid.refine import refine as refine_ls
from groundstation.sysid.settings import IdentifyConfig

#: named candidate configurations (overrides of IdentifyConfig fields)
PRESETS: dict[str, dict[str, Any]] = {
    # fit what the model is asked to do on a real flight: 5-s windows from the measured states,
    # channels weighted by their residual (the real TREX 550 log: 5-fold held-out 32.4 % against 31.0 %
    # weighting by the signal, eq. 11; roll rate no longer below zero in any fold), no trim or
    # heave-kinematics terms, refinements also started from the prior and from zero
    "predictive": {"window_s": 5.0, "window_step_s": 0.0, "estimate_all_initial": False, "channel_weighting": "noise",
                   "kinematic_forcing": "", "estimate_trim": False, "extra_starts": "prior,zero"},
    # the simulator's setting: 3-s windows, every initial state estimated, residual weighting
    "all_initial": {"window_s": 3.0, "window_step_s": 0.0, "estimate_all_initial": True, "channel_weighting": "noise",
                    "kinematic_forcing": "w", "estimate_trim": True, "extra_starts": ""},
}


def parse_candidates(spec: str) -> list[tuple[str, dict[str, Any]]]:
    """``"predictive; prior_scale=10"`` -> [(name, overrides)]; SysidError naming the bad entry."""
    fields = {f.name for f in dataclasses.fields(IdentifyConfig) if not f.name.startswith("select_")}
    out = []
    for item in (s.strip() for s in spec.replace("|", ";").split(";")):
        if not item:
            continue
        if "=" not in item:
            if item not in PRESETS:
                raise SysidError(f"identify.select_candidates: unknown preset {item!r} (presets: {', '.join(PRESETS)}; "
                                 f"or key=value,key=value)")
            out.append((item, dict(PRESETS[item])))
            continue
        kw: dict[str, Any] = {}
        for pair in item.split(","):
            k, _, v = (x.strip() for x in pair.partition("="))
            if k not in fields:
                raise SysidError(f"identify.select_candidates: unknown field {k!r} in {item!r}")
            try:
                kw[k] = json.loads(v)
            except json.JSONDecodeError:
                kw[k] = v
        out.append((item, kw))
    return out


def _refine_start(cost: Any, bfree: np.ndarray, kw: dict[str, Any], x0: np.ndarray) -> Any:
    """One refinement of :func:`best_refinement` (module-level: worker processes run the starts)."""

    with threadpool_limits(1):
        return refine_ls(cost, x0, bfree, **kw)


def best_refinement(cost: Any, x_model: np.ndarray, plan: Any, cfg: Any, sub_free: np.ndarray,
                    quick: bool, pmap: Map = serial_map) -> tuple[np.ndarray, Any]:
    """The refinement of the lowest (MAP) objective from the model's point and ``cfg.extra_starts``
    (the starts' refinements are independent: ``pmap`` may run them side by side)."""
    bfree = plan.bounds[sub_free]
    span = bfree[:, 1] - bfree[:, 0]
    prior = None if plan.prior is None else (plan.prior[0][sub_free], plan.prior[1][sub_free])
    starts = [x_model]
    names = [] if quick else [n.strip() for n in cfg.extra_starts.split(",") if n.strip()]
    if "prior" in names and prior is not None:
        starts.append(prior[0])
    if "zero" in names:
        starts.append(np.zeros(int(sub_free.sum())))
    best: tuple[float, np.ndarray, Any] | None = None
    sig_ref = None
    kw = dict(passes=1 if quick else cfg.refine_passes, prior=prior,
              max_nfev=min(int(cfg.refine_max_nfev), int(cfg.select_refit_nfev)) if quick else cfg.refine_max_nfev,
              weighting=cfg.channel_weighting, prior_colour=cfg.prior_weighting == "effective", with_std=False)
    x0s = [np.clip(x0, bfree[:, 0] + 1e-6 * span, bfree[:, 1] - 1e-6 * span) for x0 in starts]
    nfev0 = cost.nfev
    refs = pmap(partial(_refine_start, cost, bfree, kw), x0s)
    cost.nfev = nfev0 + sum(int(r.nfev) for r in refs)   # also those refined on copies, in worker processes
    for ref in refs:
        if prior is not None:
            sig_ref = ref.sig_eff if sig_ref is None else sig_ref
            F = map_objective(cost, ref.x, sig_ref, prior)
        else:
            F = float(ref.fun)
        if best is None or F < best[0]:
            best = (F, ref.x, ref)
    assert best is not None
    if not quick:   # standard errors of the winner only; the screening fit's model is only cross-validated

        with_standard_errors(cost, best[2], bfree, prior)
    return best[1], best[2]


def fold_scores(cv: Any, floor_pct: float = IdentifyConfig.select_match_floor_pct) -> np.ndarray:
    """(folds,) mean over channels of each fold's held-out match, each channel floored at ``floor_pct``
    (``[identify] select_match_floor_pct``, -100 %)."""
    return np.array([float(np.mean([max(v, floor_pct) for v in p.match.values()])) for p in cv.folds])


def _gain(s: np.ndarray, s0: np.ndarray) -> tuple[float, float]:
    """Mean paired gain over the folds and its standard error (inf when it cannot be estimated)."""
    if s.size != s0.size or s.size < 2:
        return float(np.mean(s) - np.mean(s0)) if s.size and s0.size else float("nan"), float("inf")
    g = s - s0
    return float(g.mean()), float(g.std(ddof=1) / np.sqrt(g.size))


def _crossvalidate(prepared: Any, model: HoverModel, cfg: Any, prior: Any, pmap: Map, refit: Any) -> Any:
    c = dataclasses.replace(cfg, refine_max_nfev=min(int(cfg.refine_max_nfev), int(cfg.select_refit_nfev)))
    return crossvalidate(prepared, partial(refit, model=model, config=c, prior=prior), k=int(cfg.select_folds),
                         window_s=float(cfg.heldout_window_s), runaway_factor=float(cfg.runaway_factor), pmap=pmap)


def _row(name: str, c_cfg: Any, cfg: Any, cv: Any) -> dict[str, Any]:
    return {"name": name, "overrides": {f.name: getattr(c_cfg, f.name) for f in dataclasses.fields(cfg)
                                        if getattr(c_cfg, f.name) != getattr(cfg, f.name)},
            "fold_score": fold_scores(cv, cfg.select_match_floor_pct).tolist(), "mean_match": cv.mean_match,
            "channel_mean": cv.channel_mean,
            "runaway": {k: list(v) for k, v in cv.runaway.items()}}


def _now(fn: Any) -> Any:
    """``fn()`` computed now, handed back as a call (the serial counterpart of a background job's result)."""
    out = fn()
    return lambda: out


def _candidates(prepared: Any, cfg: Any, model0: HoverModel, cands: list[tuple[str, dict[str, Any]]], prior: Any,
                bounds: dict | None, pmap: Map, fit: Any, refit: Any, later: Any = _now) -> list[tuple]:
    """The candidates applied to ``cfg`` (each configuration once, none equal to ``cfg``): each fitted from
    ``model0`` (a screening fit), its cross-validation handed to ``later``: (name, config, model, call
    returning the cross-validation)."""
    out: list[tuple] = []
    for name, kw in cands:
        c_cfg = dataclasses.replace(cfg, **kw)
        if c_cfg != cfg and all(c_cfg != e[1] for e in out):
            m = fit(prepared, model0, c_cfg, prior=prior, bounds=bounds, quick=True)
            out.append((name, c_cfg, m, later(partial(_crossvalidate, prepared, m, c_cfg, prior, pmap, refit))))
    return out


def _round(prepared: Any, base: tuple[str, Any, HoverModel, Any], cands: list[tuple[str, dict[str, Any]]],
           cfg0: Any, prior: Any, bounds: dict | None, pmap: Map, fit: Any, refit: Any,
           pending: list[tuple] | None = None) -> tuple[int, list[tuple], list[dict[str, Any]]]:
    """One comparison: the base (name, config, model, its cross-validation) and the candidates applied
    to its config (``pending``: already started by :func:`_candidates`). Returns the winner's index
    (0 = the base), the entries and their report rows."""
    if pending is None:
        pending = _candidates(prepared, base[1], base[2], cands, prior, bounds, pmap, fit, refit)
    entries = [base] + [(n, c, m, cv()) for n, c, m, cv in pending]
    rows = [_row(n, c, cfg0, cv) for n, c, _, cv in entries]
    return choose(rows, cfg0.select_gain_z), entries, rows


def choose(rows: list[dict[str, Any]], gain_z: float = IdentifyConfig.select_gain_z) -> int:
    """Index of the winning row (0 = the base, ``rows[0]``) by the rule of the module docstring (a gain
    beyond ``gain_z`` standard errors, ``[identify] select_gain_z``); fills
    each candidate row's ``gain``, ``gain_se``, ``gain_folds`` (folds it gains on) and ``significant``."""
    s0 = np.asarray(rows[0]["fold_score"])
    ran0 = bool(rows[0].get("runaway"))
    best = 0
    for i, r in enumerate(rows[1:], start=1):
        s = np.asarray(r["fold_score"])
        g, se = _gain(s, s0)
        wins = int(np.sum(s > s0)) if s.size == s0.size else 0
        r["gain"], r["gain_se"], r["gain_folds"] = g, se, wins
        ran = bool(r.get("runaway"))
        if ran != ran0:   # a prediction that runs away never beats one that does not
            r["significant"] = ran0
            r["reason"] = ("the configuration's prediction runs away on " if ran0 else "runs away on ") + \
                ", ".join(f"{k} ({', '.join(v)})" for k, v in (rows[0] if ran0 else r)["runaway"].items())
        else:
            r["significant"] = bool(np.isfinite(g) and g > 0 and (g > gain_z * se or (s.size >= 3 and wins == s.size)))
        if not r["significant"]:
            continue
        if best == 0:
            best = i
            continue
        # among winners: one that does not run away first, then the larger mean gain
        key = (not ran, g)
        if key > (not bool(rows[best].get("runaway")), rows[best]["gain"]):
            best = i
    return best


def select_config(prepared: Any, model0: HoverModel, cfg: Any, *, prior: Any = None, bounds: dict | None = None,
                  pmap: Map = serial_map, fit: Any, refit: Any) -> HoverModel:
    """The model of the configuration that predicts held-out data best (see the module docstring).

    ``fit(prepared, model0, cfg, *, prior, bounds, quick[, pmap])`` fits one candidate configuration from
    ``model0``'s parameters and ``refit(prepared, *, model, config, prior)`` refits a model on a fold
    (:func:`groundstation.sysid.identify.fit_candidate` and :func:`~groundstation.sysid.identify.refit`:
    given by the identification, so this module does not import it back)."""
    rounds = [parse_candidates(r) for r in cfg.select_candidates.split("|")]
    with ThreadPoolExecutor(max_workers=2) as bg:
        return _select(prepared, model0, cfg, rounds, prior, bounds, pmap, fit, refit, bg)


def _skipped(model0: HoverModel, exc: BaseException | None) -> HoverModel:
    """``model0`` as configured: too little data for the selection's folds."""
    model0.fit = model0.fit.set(selection={"skipped": str(exc)})
    return model0


def _select(prepared: Any, model0: HoverModel, cfg: Any, rounds: list, prior: Any, bounds: dict | None, pmap: Map,
            fit: Any, refit: Any, bg: ThreadPoolExecutor) -> HoverModel:
    """:func:`select_config`. With worker processes the configuration's cross-validation runs (from a
    background thread ``bg``) while this process fits the first round's candidates, whose folds then
    queue behind it on the same workers; with the serial map one after the other. The same choice
    either way (nothing here draws random numbers)."""
    job = partial(_crossvalidate, prepared, model0, cfg, prior, pmap, refit)
    first = None
    if pmap is serial_map:
        try:
            cv = job()
        except ValueError as exc:   # too little data for k folds: keep the configuration as given
            return _skipped(model0, exc)
    else:
        fut = bg.submit(job)
        try:
            first = _candidates(prepared, cfg, model0, rounds[0], prior, bounds, pmap, fit, refit,
                                lambda fn: bg.submit(fn).result)
        except ValueError:
            if isinstance(fut.exception(), ValueError):   # the configuration's own folds fail first
                return _skipped(model0, fut.exception())
            raise
        if isinstance(fut.exception(), ValueError):
            return _skipped(model0, fut.exception())
        cv = fut.result()
    cur = ("as configured", cfg, model0, cv)
    report: list[dict[str, Any]] = []
    for k, cands in enumerate(rounds):
        best, entries, rows = _round(prepared, cur, cands, cfg, prior, bounds, pmap, fit, refit, first if k == 0 else None)
        for r in rows[int(k > 0):]:
            report.append(r | {"round": k + 1})
        if not best:
            break   # a later round refines a switch; with none it has nothing to refine
        name, c_cfg, _, _ = entries[best]
        model = fit(prepared, cur[2], c_cfg, prior=prior, bounds=bounds, pmap=pmap)
        cv = _crossvalidate(prepared, model, c_cfg, prior, pmap, refit)
        report[-len(rows) + best]["final"] = _row(name, c_cfg, cfg, cv)
        cur = (name if k == 0 else f"{cur[0]}, {name}", c_cfg, model, cv)
    name, c_cfg, model, cv = cur
    over = {f.name: getattr(c_cfg, f.name) for f in dataclasses.fields(cfg) if getattr(c_cfg, f.name) != getattr(cfg, f.name)}
    rule = (f"a prediction that runs away on some fold never wins over one that does not; otherwise a candidate "
            f"replaces the configuration when its mean held-out gain over the folds exceeds {cfg.select_gain_z:g} standard "
            f"error(s) of that gain or it gains on every fold")
    model.fit = model.fit.set(selection={"k": int(cfg.select_folds), "chosen": name, "candidates": report,
                                         "overrides": over, "rule": rule}, heldout=cv.to_json())
    return model
