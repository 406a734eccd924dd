"""Identification of the eq.-8 hover model from prepared data: global search (CABC by default) + refinement.

``identify(prepared, algorithm="cabc", seed=0, refine=True, maxiter=None, callback=None, bounds=None, prior=None)``

1. cut the segments into windows (:func:`groundstation.sysid.cost.make_windows`);
2. decide which parameters the data can support: parameters of an input that never moves, or that
   only act on/through an unmeasured velocity channel, are fixed at 0 and reported in
   ``fit["fixed"]`` (std ``None``) - e.g. the real TREX 550 log has no lateral cyclic and no
   usable velocities after 215 s;
3. search the free parameters inside ``bounds`` with the chosen optimiser on the paper's eq. 11
   cost (vectorised over the colony) on short windows (``search_window_s``, every
   ``search_stride``-th), with the B-matrix parameters solved by least squares inside the cost
   (variable projection: for a given A the output is linear in B and the initial states), which
   removes the sign/scale local minima of the input gains from the search; the two decoupled subsystems (horizontal 22 parameters,
   vertical/yaw 9) one after the other as in the paper - eq. 11 is a sum over channels, so the
   cost separates exactly and each search is in fewer dimensions;
4. ``search_restarts`` independent searches per subsystem (after the first with
   ``restart_algorithm``, DE by default), each screened and refined; the lowest refined cost wins
   (the search cost does not tell a wrong basin from the right one); a search that screened down to
   an earlier search's start (``refine_start_min_dist``, the scores within their sampling spread)
   shares that start's refinement instead of repeating it; the searches draw the random
   numbers, the screening and refinements none, so with worker processes a subsystem is screened and
   refined on them while this process searches the next one (the same model);
   refine with least squares from the best solution (:mod:`groundstation.sysid.refine`) and
   compute the standard errors; parameters within 0.1 % of a bound are ``pinned``. The refinement
   cost also solves one input trim offset per input (``estimate_trim``; the model file's
   ``input_trim_pwm`` carries it) and takes the measured heave kinematics
   ``q u - p v + g (cos phi cos theta - 1)`` as a known forcing on w (``kinematic_forcing``): eq. 8
   drops them, and with a pilot closing the loop they bias Z_col low (simulated trex600 flights:
   7-12 % low without, under 1 % with).

5. with a ``prior`` (the aircraft file's prior model) the refinement is output error with a priori
   weighting (MAP, :func:`groundstation.sysid.refine.refine`): ``fit["prior"]`` says which parameters the
   flight determines and which stay near the prior; ``extra_starts`` adds refinements from the prior and
   from zero; restarts and starts are compared by the MAP objective at fixed channel scales;
6. the report: parameters on a bound with why (``fit["pinned_reasons"]``), unstable modes with their
   time constants (``fit["unstable_modes"]``). :func:`refit` refines a model on other data without a
   search (the folds of the held-out check, :mod:`groundstation.sysid.heldout`).

No timing and no IO here (the CLI measures wall time and writes files). BLAS is held to one thread
while identifying: the batched products are small and threads only contend on a shared machine.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from groundstation.errors import SysidError
from groundstation.parallel import Map, serial_map
from groundstation.sysid.cost import WindowedCost, make_windows, subset_windows
from groundstation.sysid.fit_section import ModelFit
from groundstation.sysid.heldout import unstable_modes
from groundstation.sysid.hole_inputs import estimate_hole_inputs, window_holes
from groundstation.sysid.holes import has_bridged_inputs, restart_windows
from groundstation.sysid.model import (
    HOR_PARAMS,
    N_PARAMS,
    OUTPUTS,
    PARAM_INDEX,
    PARAM_NAMES,
    VER_PARAMS,
    HoverModel,
    bounds_array,
)
from groundstation.sysid.optimizers import ALGORITHMS
from groundstation.sysid.refine import _sigma as noise_scales
from groundstation.sysid.refine import map_objective, with_standard_errors
from groundstation.sysid.refine import refine as refine_ls
from groundstation.sysid.select import best_refinement, select_config
from groundstation.sysid.settings import IdentifyConfig
from groundstation.sysid.simulate import kinematic_forcing
from groundstation.sysid.structure_choice import attach_command_structure

#: Parameters that need each input to move.
INPUT_PARAMS: dict[str, tuple[str, ...]] = {
    "lat": ("X_lat", "M_lat", "L_lat", "A_lat"),
    "lon": ("Y_lon", "M_lon", "L_lon", "B_lon"),
    "col": ("Z_col", "N_col"),
    "ped": ("Z_ped", "N_ped"),
}
#: Parameters that need each velocity channel measured.
VELOCITY_PARAMS: dict[str, tuple[str, ...]] = {
    "u": ("X_u", "M_u", "L_u", "X_lat"),
    "v": ("Y_v", "M_v", "L_v", "Y_lon"),
    "w": ("Z_w", "Z_r", "N_w", "Z_col", "Z_ped"),
}


#: Input channels (indices into lat lon col ped) of each subsystem.
_SUBS_INPUTS = ((0, 1), (2, 3))

DEFAULT_MAXITER = {"cabc": 50, "abc": 75, "ga": 75, "de": 50}


def free_mask(prepared: Any) -> tuple[np.ndarray, list[str]]:
    """(31,) bool of identifiable parameters and the reasons for the fixed ones."""
    free = np.ones(N_PARAMS, dtype=bool)
    reasons: list[str] = []
    active = prepared.input_active
    for k, name in enumerate(("lat", "lon", "col", "ped")):
        if not active[k]:
            for p in INPUT_PARAMS[name]:
                free[PARAM_INDEX[p]] = False
            reasons.append(f"input {name} never moves: {', '.join(INPUT_PARAMS[name])} fixed at 0")
    avail = prepared.available
    for name, params in VELOCITY_PARAMS.items():
        if not avail[OUTPUTS.index(name)]:
            for p in params:
                free[PARAM_INDEX[p]] = False
            reasons.append(f"output {name} not measured: {', '.join(params)} fixed at 0")
    return free, reasons


def _starts(opt: Any, k: int, span: np.ndarray, min_dist: float = IdentifyConfig.refine_start_min_dist) -> list[np.ndarray]:
    """Up to k good and mutually distinct points of everything the search evaluated, best first.

    Distinct: normalised distance ``||(x - y) / span|| / sqrt(D)`` of at least ``min_dist``. Each
    point taken rules out the archive near it in one vectorised step (the archive holds thousands of
    points, often many close to the best)."""
    X = getattr(opt, "archive_x", None)
    if X is None:
        return [np.asarray(opt.x, dtype=float)]
    f = opt.archive_f
    order = np.argsort(f)
    bad = np.flatnonzero(~np.isfinite(f[order]))
    order = order[:bad[0]] if bad.size else order
    far = np.ones(order.size, dtype=bool)
    out: list[np.ndarray] = []
    while len(out) < k and far.any():
        x = np.asarray(X[order[int(np.argmax(far))]], dtype=float)
        out.append(x)
        far &= np.linalg.norm((X[order] - x) / span, axis=1) / np.sqrt(X.shape[1]) >= min_dist
    return out or [np.asarray(opt.x, dtype=float)]


@dataclass
class _Run:
    """What the subsystem identifications accumulate (internal)."""

    theta: np.ndarray
    std: np.ndarray = field(default_factory=lambda: np.full(N_PARAMS, np.nan))
    share: np.ndarray = field(default_factory=lambda: np.full(N_PARAMS, np.nan))
    sigma: np.ndarray = field(default_factory=lambda: np.full(8, np.nan))
    delta: np.ndarray = field(default_factory=lambda: np.zeros(4))  # input trim corrections, lat lon col ped
    F_total: float = 0.0
    F_search: float = 0.0
    nfev: int = 0
    nit: int = 0
    histories: dict[str, list[float]] = field(default_factory=dict)
    histories_nfev: dict[str, list[int]] = field(default_factory=dict)
    search_by_sub: dict[str, float] = field(default_factory=dict)
    search_alg: dict[str, str] = field(default_factory=dict)
    #: parameter index -> (index of the parameter its estimate trades off with most, correlation)
    partner: dict[int, tuple[int, float]] = field(default_factory=dict)


def record_tradeoffs(run: _Run, sub_free: np.ndarray, ref: Any, prior_std: np.ndarray | None) -> None:
    """Into ``run.partner``: for each free parameter of a refinement, the one its estimate is most
    correlated with (the data's information ``J^T J`` plus the prior's, inverted), when ``ref`` has a
    Jacobian. A parameter that ends on a bound is reported with it: the pair, not each alone, is
    what the flight determines."""
    J = getattr(ref, "jac", None)
    if J is None or J.shape[1] < 2:
        return
    H = J.T @ J
    if prior_std is not None:
        H = H + np.diag(1.0 / np.asarray(prior_std, dtype=float) ** 2)
    cov = np.linalg.pinv(H)
    d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    corr = cov / np.outer(d, d)
    np.fill_diagonal(corr, 0.0)
    idx = np.flatnonzero(sub_free)
    for a in range(idx.size):
        b = int(np.argmax(np.abs(corr[a])))
        run.partner[int(idx[a])] = (int(idx[b]), float(corr[a, b]))


@dataclass(frozen=True, eq=False)
class _Plan:
    """Windows, forcing, free parameters, bounds and prior of one identification (internal)."""

    win: Any
    win_s: Any
    forcing: np.ndarray | None
    forcing_s: np.ndarray | None
    free: np.ndarray
    reasons: list[str]
    bounds: np.ndarray
    prior: tuple[np.ndarray, np.ndarray] | None
    kf: list[str]
    pmap: Callable[[Callable[[Any], Any], Any], list[Any]] = field(default=serial_map)
    #: where the link's holes lie in ``win`` when their inputs are estimated (for the standard errors)
    holes: Any = None
    #: the holes whose inputs keep the straight line, with its error measured per shape (for the
    #: standard errors: :meth:`~groundstation.sysid.hole_inputs.WindowHoles.line_covariance`)
    lines: Any = None


def _check(cfg: IdentifyConfig, algorithm: str, prepared: Any) -> None:
    if algorithm not in ALGORITHMS:
        raise SysidError(f"unknown algorithm {algorithm!r}; choose one of {sorted(ALGORITHMS)}")
    if cfg.restart_algorithm and cfg.restart_algorithm not in ALGORITHMS:
        raise SysidError(f"identify.restart_algorithm: unknown {cfg.restart_algorithm!r}; choose one of {sorted(ALGORITHMS)}")
    if cfg.search_restarts < 1:
        raise SysidError(f"identify.search_restarts = {cfg.search_restarts}: must be >= 1")
    if cfg.window_step_s < 0:
        raise SysidError(f"identify.window_step_s = {cfg.window_step_s}: must be >= 0 (0 = non-overlapping windows)")
    if not cfg.prior_scale > 0:
        raise SysidError(f"identify.prior_scale = {cfg.prior_scale}: must be > 0")
    if cfg.prior_weighting not in ("logged", "effective"):
        raise SysidError(f"identify.prior_weighting = {cfg.prior_weighting!r}: choose logged or effective")
    if cfg.input_kind not in ("blade", "rate_command", "attitude_command", "unknown"):
        raise SysidError(f"identify.input_kind = {cfg.input_kind!r}: choose blade, rate_command, attitude_command or unknown")
    if not prepared.segments:
        raise SysidError("no in-air segments to identify from")


def _prior_arrays(prior: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """(nominal (31,), std (31,)) of a prior (an object with ``mean_array``/``std_array``, or a pair)."""
    if prior is None:
        return None
    if hasattr(prior, "mean_array"):
        return np.asarray(prior.mean_array, dtype=float), np.asarray(prior.std_array, dtype=float)
    m, sd = prior
    return np.asarray(m, dtype=float), np.asarray(sd, dtype=float)


def _plan(prepared: Any, cfg: IdentifyConfig, refine: bool, bounds: dict | None, prior: Any,
          pmap: Map = serial_map, search: bool = True) -> _Plan:
    """``search=False``: no search windows (a refit from a model: :func:`refit`, the selection's fits)."""
    cut = restart_windows if cfg.restart_after_holes else make_windows   # no hole: the same windows
    win = cut(prepared.segments, prepared.dt_s, cfg.window_s, key="identify.window_s", step_s=cfg.window_step_s)
    win_s = None
    if search:
        win_s = cut(prepared.segments, prepared.dt_s, cfg.search_window_s, key="identify.search_window_s")
        if cfg.search_stride > 1 and win_s.count >= 2 * cfg.search_stride:
            win_s = subset_windows(win_s, np.arange(0, win_s.count, cfg.search_stride))
    free, reasons = free_mask(prepared)
    kf = [c.strip() for c in cfg.kinematic_forcing.split(",") if c.strip()]
    if any(c not in ("u", "v", "w") for c in kf):
        raise SysidError(f"identify.kinematic_forcing: channels must be among u, v, w, got {cfg.kinematic_forcing!r}")
    forcing = forcing_s = None
    if kf and refine:
        trim_vec = np.array([float(prepared.output_trim.get(c, 0.0)) for c in OUTPUTS])
        off = [j for j, c in enumerate(("u", "v", "w")) if c not in kf]
        forcing = kinematic_forcing(win.outputs, trim_vec)
        forcing[..., off] = 0.0
        if win_s is not None:
            forcing_s = kinematic_forcing(win_s.outputs, trim_vec)
            forcing_s[..., off] = 0.0
    pr = _prior_arrays(prior)
    if pr is not None and cfg.prior_scale != 1.0:
        pr = (pr[0], pr[1] * float(cfg.prior_scale))
    estimated = _hole_subsystems(cfg) if estimates_hole_inputs(prepared, cfg) else ()
    holes = window_holes(prepared.segments, win, cfg.hole_input_band, estimated, cfg.hole_input_prior_s) \
        if estimated else None
    return _Plan(win, win_s, forcing, forcing_s, free, reasons, bounds_array(bounds), pr,
                 kf if refine else [], pmap, holes, _line_holes(prepared, win, cfg, estimated))


def _line_holes(prepared: Any, win: Any, cfg: IdentifyConfig, estimated: tuple[int, ...]) -> Any:
    """The holes of ``win`` whose inputs keep the straight line (the subsystems not in ``estimated``),
    their line error measured per shape; None when there are none or ``line_error_in_std`` is off."""
    subs = tuple(s for s in (0, 1) if s not in estimated)
    if not (cfg.line_error_in_std and subs and has_bridged_inputs(prepared.segments)):
        return None
    return window_holes(prepared.segments, win, cfg.hole_input_band, subs, cfg.hole_input_prior_s, shapes=True)


def _costs(plan: _Plan, cfg: IdentifyConfig, sub: int, sub_free: np.ndarray, theta: np.ndarray,
           trim: bool) -> tuple[WindowedCost, WindowedCost, WindowedCost]:
    """(refinement cost, screening cost, search cost with B by variable projection) of one subsystem."""
    kw = dict(estimate_all_initial=cfg.estimate_all_initial, subsystems=(sub,))
    cost = _refine_cost(plan, cfg, sub, sub_free, theta, trim)
    cost_s = WindowedCost(plan.win_s, sub_free, theta, forcing=plan.forcing_s, **_offsets(cfg, trim), **kw)  # type: ignore[arg-type]
    cost_v = WindowedCost(plan.win_s, sub_free, theta, varpro=cfg.varpro, **kw)  # type: ignore[arg-type]
    return cost, cost_s, cost_v


def _refine_cost(plan: _Plan, cfg: IdentifyConfig, sub: int, sub_free: np.ndarray, theta: np.ndarray,
                 trim: bool) -> WindowedCost:
    """The refinement cost of one subsystem alone (a refit needs no search or screening cost)."""
    cost = WindowedCost(plan.win, sub_free, theta, forcing=plan.forcing, **_offsets(cfg, trim),
                        estimate_all_initial=cfg.estimate_all_initial, subsystems=(sub,))
    cost.input_holes = plan.holes   # type: ignore[attr-defined]
    cost.line_holes = plan.lines    # type: ignore[attr-defined]
    return cost


def _offsets(cfg: IdentifyConfig, on: bool) -> dict[str, Any]:
    """WindowedCost keywords of the input offsets: one per flight (``estimate_trim``, the trim), one per
    window (``window_input_offsets``), or none (``on`` False)."""
    if not on:
        return {}
    return {"window_offsets": True} if cfg.window_input_offsets else {"estimate_trim": True}


def _progress(callback: Callable[[dict], Any] | None, stage: str, fun: float, nfev: int) -> None:
    if callback is not None:
        callback({"stage": stage, "nit": 0, "maxiter": 1, "fun": fun, "nfev": nfev})


def _score(cost: WindowedCost, r: Any, sig_eff: np.ndarray, prior: tuple[np.ndarray, np.ndarray] | None) -> float:
    """Comparable score of a refinement: eq. 11 cost without a prior, else the MAP objective at fixed scales."""
    return float(r.fun) if prior is None else map_objective(cost, r.x, sig_eff, prior)


def _search_once(alg: str, it: int, costs: tuple, plan: _Plan, cfg: IdentifyConfig, sub_free: np.ndarray,
                 refine: bool, rng: np.random.Generator, cb: Callable) -> tuple[float, list[np.ndarray], Any]:
    """One search: (F, starts, opt). With ``refine`` the starts of its screening (:func:`_screen`): its best
    distinct points and the prior's nominal, F nan; without, the search's best point and its cost."""
    cost, _, cost_v = costs
    bfree = plan.bounds[sub_free]
    prior = None if plan.prior is None else (plan.prior[0][sub_free], plan.prior[1][sub_free])

    def to_free(xv: np.ndarray) -> np.ndarray:
        th = cost_v.complete(np.asarray(xv, dtype=float)[None])[0]
        return np.clip(th[sub_free], bfree[:, 0], bfree[:, 1])

    opt = ALGORITHMS[alg](cost_v, plan.bounds[cost_v.free], rng=rng, maxiter=it, maxfev=cfg.maxfev, callback=cb,
                          **cfg.search_options(alg))
    if not refine:
        xr = to_free(opt.x)
        return float(cost(xr[None])[0]), [xr], opt
    vb = plan.bounds[cost_v.free]
    starts = [to_free(xv) for xv in _starts(opt, cfg.refine_starts, vb[:, 1] - vb[:, 0], cfg.refine_start_min_dist)]
    if prior is not None:
        span = bfree[:, 1] - bfree[:, 0]
        starts.append(np.clip(prior[0], bfree[:, 0] + 1e-6 * span, bfree[:, 1] - 1e-6 * span))
    return float("nan"), starts, opt


def _screen(starts: list[np.ndarray], opt: Any, label: str, costs: tuple, plan: _Plan, cfg: IdentifyConfig,
            sub_free: np.ndarray, callback: Callable | None, sub_name: str) -> tuple[np.ndarray, float]:
    """Successive-halving screening of a search's ``starts`` on the search windows: short refinements of
    many, longer ones of the best few; returns the winner, the start of the full refinement
    (:func:`_full_refine`), and its screened score (nan for a single start). Draws no random numbers."""
    cost, cost_s, _ = costs
    bfree = plan.bounds[sub_free]
    prior = None if plan.prior is None else (plan.prior[0][sub_free], plan.prior[1][sub_free])
    nfev_round = cfg.screen_max_nfev
    screen_f = float("nan")
    while len(starts) > 1:   # short refinements of many starts, longer ones of the best few
        _progress(callback, f"screen {sub_name} ({len(starts)} starts)", float(opt.fun), cost_s.nfev + cost.nfev)
        nfev0 = cost_s.nfev
        rs = plan.pmap(partial(_screen_refine, cost_s, bfree, nfev_round, prior, cfg.channel_weighting,
                               cfg.prior_weighting == "effective"), starts)
        cost_s.nfev = nfev0 + sum(int(r.nfev) for r in rs)   # also those refined on copies, in worker processes
        scored = sorted(((_score(cost_s, r, rs[0].sig_eff, prior), r.x) for r in rs), key=lambda t: t[0])
        starts = [sx for _, sx in scored[: max(1, len(scored) // 3)]]
        screen_f = scored[0][0]
        nfev_round *= 2
    _progress(callback, f"screened {sub_name}{label}", screen_f, cost_s.nfev + cost.nfev)
    return starts[0], screen_f


def _relative_spread(cost: WindowedCost) -> float:
    """``sqrt(2 / N)``: the relative sampling spread of a sum of N squared residuals, N the cost's residual
    samples (coloured residuals carry fewer independent samples and spread more: this is the strict side)."""
    w = cost.windows
    n = w.measured[..., cost.used].sum() if w.measured is not None else w.available[:, cost.used].sum() * w.length
    return float(np.sqrt(2.0 / max(int(n), 1)))


def _same_winners(winners: list[tuple[np.ndarray, float]], span: np.ndarray, min_dist: float,
                  spread: float) -> list[int]:
    """For each search's screened winner (start, score), the first earlier winner it repeats, else itself.

    A later search that screened down to the same start is not refined again: the same start by
    ``refine_start_min_dist`` (RMS over the parameters of the difference as a fraction of each search
    range, as the starts of one search), with screened scores within their sampling spread of each other
    (a wrong basin shows as a score far beyond it, and is refined)."""
    rep: list[int] = []
    for i, (x, f) in enumerate(winners):
        near = [j for j in set(rep) if np.linalg.norm((x - winners[j][0]) / span) / np.sqrt(x.size) < min_dist
                and abs(f - winners[j][1]) <= spread * min(abs(f), abs(winners[j][1]))]
        rep.append(min(near) if near else i)
    return rep


def _full_refine(cost: WindowedCost, bfree: np.ndarray, cfg: IdentifyConfig,
                 prior: tuple[np.ndarray, np.ndarray] | None, x0: np.ndarray) -> Any:
    """The full refinement of one start (a search's screened winner or an extra start), without
    standard errors; module-level so that worker processes can run the starts side by side."""
    with threadpool_limits(1):
        return refine_ls(cost, x0, bfree, passes=cfg.refine_passes, max_nfev=cfg.refine_max_nfev, prior=prior,
                         weighting=cfg.channel_weighting, with_std=False,
                         prior_colour=cfg.prior_weighting == "effective")


def _screen_refine(cost: WindowedCost, bfree: np.ndarray, max_nfev: int, prior: tuple[np.ndarray, np.ndarray] | None,
                   weighting: str, prior_colour: bool, x0: np.ndarray) -> Any:
    """A short refinement of one start (the screening; module-level so worker processes can run it)."""
    with threadpool_limits(1):
        return refine_ls(cost, x0, bfree, passes=1, max_nfev=max_nfev, with_std=False, prior=prior,
                         weighting=weighting, prior_colour=prior_colour)


def _extra_start_points(plan: _Plan, cfg: IdentifyConfig, sub_free: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """(name, start) of each of ``cfg.extra_starts`` that applies (the prior's nominal, zero), inside the bounds."""
    names = [n.strip() for n in cfg.extra_starts.split(",") if n.strip()]
    bad = [n for n in names if n not in ("prior", "zero")]
    if bad:
        raise SysidError(f"identify.extra_starts: unknown start(s) {bad} (allowed: prior, zero)")
    bfree = plan.bounds[sub_free]
    span = bfree[:, 1] - bfree[:, 0]
    prior = None if plan.prior is None else (plan.prior[0][sub_free], plan.prior[1][sub_free])
    out = []
    for n in names:
        if n == "prior" and prior is None:
            continue
        x0 = prior[0] if n == "prior" and prior is not None else np.zeros(int(sub_free.sum()))
        out.append((n, np.clip(x0, bfree[:, 0] + 1e-6 * span, bfree[:, 1] - 1e-6 * span)))
    return out


@dataclass(eq=False)
class _SubSearch:
    """One subsystem's searches, before their screening and refinement (internal)."""

    sub: int
    name: str
    free: np.ndarray
    costs: tuple
    #: per search: (F, its best point without refinement, OptimizeResult, algorithm, the screening's winner
    #: and its screened score: a call that returns them, with refinement)
    found: list[tuple[float, np.ndarray, Any, str, Callable[[], tuple[np.ndarray, float]] | None]]


#: ``later(fn)``: a call that returns ``fn()``, which runs on a background thread (with worker processes)
#: or when first called (with the serial map)
Later = Callable[[Callable[[], Any]], Callable[[], Any]]


def _search_subsystem(sub: int, sub_name: str, sub_params: tuple[str, ...], plan: _Plan, cfg: IdentifyConfig,
                      run: _Run, *, algorithm: str, iters: int, maxiter: int | None, refine: bool,
                      rng: np.random.Generator, callback: Callable[[dict], Any] | None, later: Later) -> _SubSearch | None:
    """The searches of one subsystem (the only part that draws random numbers), each search's screening
    handed to ``later`` as soon as it ends; None without a measured output. The costs are built at
    ``run.theta`` as it stands: the subsystem's simulation reads only its own parameters."""
    idx = np.array([PARAM_INDEX[p] for p in sub_params])
    sub_free = np.zeros(N_PARAMS, dtype=bool)
    sub_free[idx] = plan.free[idx]
    costs = _costs(plan, cfg, sub, sub_free, run.theta, cfg.input_offsets and refine)
    if not costs[0].used.any():
        plan.reasons.append(f"{sub_name} subsystem: no measured output, not identified")
        return None

    def cb(res: Any) -> bool:
        if callback is not None:
            return bool(callback({"stage": f"search {sub_name}", "nit": res.nit, "maxiter": iters,
                                  "fun": float(res.fun), "nfev": res.nfev}))
        return False

    # the vertical/yaw search's iterations relative to the horizontal one's (cfg.vertical_iter_factor)
    sub_iters = iters if sub == 0 else int(iters * cfg.vertical_iter_factor)
    found = []
    for restart in range(max(1, cfg.search_restarts if refine else 1)):
        alg = algorithm if restart == 0 or not cfg.restart_algorithm else cfg.restart_algorithm
        it = sub_iters
        if alg != algorithm and not (maxiter or cfg.maxiter):
            it = DEFAULT_MAXITER[alg] if sub == 0 else int(DEFAULT_MAXITER[alg] * cfg.vertical_iter_factor)
        F, starts, opt = _search_once(alg, it, costs, plan, cfg, sub_free, refine, rng, cb)
        run.nit += int(opt.nit)
        label = f" (search {restart + 1})" if restart else ""
        screened = later(partial(_screen, starts, opt, label, costs, plan, cfg, sub_free, callback, sub_name)) \
            if refine else None
        found.append((F, starts[0], opt, alg, screened))
    return _SubSearch(sub, sub_name, sub_free, costs, found)


def _refine_subsystem(s: _SubSearch, plan: _Plan, cfg: IdentifyConfig,
                      callback: Callable | None) -> tuple[float, np.ndarray, Any, Any, str]:
    """The full refinements of every search's screened winner and of the extra starts (independent,
    drawing no random numbers: side by side in the worker processes), and the lowest refined (MAP)
    cost of them with its standard errors: (F, x, the search's result, the refinement, algorithm)."""
    cost = s.costs[0]
    pr = None if plan.prior is None else (plan.prior[0][s.free], plan.prior[1][s.free])
    extra = _extra_start_points(plan, cfg, s.free)
    winners = [screened() for *_, screened in s.found if screened is not None]
    bfree = plan.bounds[s.free]
    rep = _same_winners(winners, bfree[:, 1] - bfree[:, 0], cfg.refine_start_min_dist, _relative_spread(s.costs[1]))
    own = sorted(set(rep))
    x0s = [winners[i][0] for i in own] + [x0 for _, x0 in extra]
    _progress(callback, f"refine {s.name} ({len(x0s)} start{'s' if len(x0s) > 1 else ''})",
              float(s.found[0][2].fun), sum(c.nfev for c in s.costs))
    nfev0 = cost.nfev
    refs = plan.pmap(partial(_full_refine, cost, bfree, cfg, pr), x0s)
    cost.nfev = nfev0 + sum(int(r.nfev) for r in refs)   # also those refined on copies, in worker processes
    found_refs = [refs[own.index(k)] for k in rep]   # a repeated winner shares its first refinement (never wins)
    refs = found_refs + refs[len(own):]
    best: tuple[float, np.ndarray, Any, Any, str] | None = None
    sig_ref = None   # with a prior, restarts are compared by the MAP objective at the first one's scales
    for (_, _, opt, alg, _), r in zip(s.found, refs[:len(s.found)], strict=True):
        F = float(r.fun)
        if pr is not None:
            sig_ref = r.sig_eff if sig_ref is None else sig_ref
            F = map_objective(cost, r.x, sig_ref, pr)
        if best is None or F < best[0]:
            best = (F, r.x, opt, r, alg)
    assert best is not None
    for (n, _), r in zip(extra, refs[len(s.found):], strict=True):
        F = float(r.fun) if pr is None or sig_ref is None else map_objective(cost, r.x, sig_ref, pr)
        if F < best[0]:
            best = (F, r.x, best[2], r, f"{best[4]}+{n} start")
    # the standard errors of the winner only (each restart's refinement skips them)
    return best[:3] + (with_standard_errors(cost, best[3], plan.bounds[s.free], pr), best[4])


def _record_subsystem(s: _SubSearch, best: tuple[float, np.ndarray, Any, Any, str] | None, plan: _Plan,
                      cfg: IdentifyConfig, run: _Run) -> None:
    """One subsystem's winner into ``run``: ``best`` from :func:`_refine_subsystem`; None without
    refinement: the search of the lowest search cost."""
    sub, sub_name, sub_free, costs = s.sub, s.name, s.free, s.costs
    cost = costs[0]
    if best is None:
        for F, xr, opt, alg, _ in s.found:
            if best is None or F < best[0]:
                best = (F, xr, opt, None, alg)
    assert best is not None
    _, x, opt, ref, won = best
    run.search_alg[sub_name] = won
    run.F_search += float(opt.fun)
    run.search_by_sub[sub_name] = float(opt.fun)
    run.histories[sub_name] = [float(h) for h in opt.history]
    run.histories_nfev[sub_name] = [int(h) for h in opt.history_nfev]
    if ref is not None:
        pr_std = None if plan.prior is None else plan.prior[1][sub_free]
        record_tradeoffs(run, sub_free, ref, pr_std)
        run.std[np.flatnonzero(sub_free)] = ref.std
        run.share[np.flatnonzero(sub_free)] = ref.prior_share if plan.prior is not None else 0.0
        run.sigma[cost.used] = ref.sigma[cost.used]
    run.theta = run.theta.copy()
    run.theta[sub_free] = x   # the cost's own full(x) would also reset what earlier subsystems left
    if cfg.flight_trim and ref is not None:
        run.delta[list(_SUBS_INPUTS[sub])] = cost.sim.solve_trim(run.theta[None])[sub][0]
    run.F_total += float(cost(x[None])[0])
    run.nfev += sum(c.nfev for c in costs)


def _identify_subsystems(plan: _Plan, cfg: IdentifyConfig, run: _Run, *, refine: bool,
                         callback: Callable[[dict], Any] | None, **search: Any) -> None:
    """Search, screen and refine both subsystems into ``run``. The searches run one after the other in
    this process (they share the random number generator). The screening of each search's starts draws
    no random numbers: with worker processes a background thread hands it to the workers as soon as its
    search ends, while this process runs the next search. The full refinements this process runs once
    the searches are done (it would only wait), sharing their starts with the workers; with the serial
    map the screening too runs after the searches. The same model either way."""
    subs = ((0, "horizontal", HOR_PARAMS), (1, "vertical", VER_PARAMS))
    parallel = plan.pmap is not serial_map and refine
    with ThreadPoolExecutor(max_workers=1) as bg:   # one thread: the jobs run in the order handed over

        def later(fn: Callable[[], Any]) -> Callable[[], Any]:
            return bg.submit(fn).result if parallel else fn

        pending = []
        for sub, sub_name, sub_params in subs:
            s = _search_subsystem(sub, sub_name, sub_params, plan, cfg, run, refine=refine, callback=callback,
                                  later=later, **search)
            if s is not None:
                pending.append((s, partial(_refine_subsystem, s, plan, cfg, callback) if refine else None))
        for s, best in pending:   # recorded in order: the totals add up as before
            _record_subsystem(s, None if best is None else best(), plan, cfg, run)


def _in_sample_match(plan: _Plan, cfg: IdentifyConfig, theta: np.ndarray, trim: bool) -> tuple[dict[str, float], np.ndarray]:
    """Eq. 19 match per used channel on the training windows, and the used-channel mask (8,)."""
    full_cost = WindowedCost(plan.win, np.zeros(N_PARAMS, dtype=bool), theta, estimate_all_initial=cfg.estimate_all_initial,
                             forcing=plan.forcing, **_offsets(cfg, trim))
    errs = full_cost.sim.errors(theta[None])[0]
    y = full_cost.sim.outputs
    match = {}
    for j, ch in enumerate(OUTPUTS):
        if full_cost.used[j]:
            m = full_cost.sim.smask[:, :, j]  # measured samples only
            num = np.sqrt((errs[:, :, j][m] ** 2).sum())
            den = np.sqrt((y[:, :, j][m] ** 2).sum())
            match[ch] = float((1 - num / den) * 100) if den > 0 else float("nan")
    return match, full_cost.used


def _pinned(theta: np.ndarray, free: np.ndarray, b: np.ndarray,
            partner: dict[int, tuple[int, float]] | None = None) -> dict[str, str]:
    """Free parameters within 0.1 % of a search bound, with the reason the report gives: the data pull
    it past the bound, and the parameter it trades off with most (``partner``, when known)."""
    span = b[:, 1] - b[:, 0]
    out = {}
    for i in range(N_PARAMS):
        for side, edge in (("lower", 0), ("upper", 1)):
            if free[i] and abs(theta[i] - b[i, edge]) < 1e-3 * span[i]:
                j, r = (partner or {}).get(i, (-1, 0.0))
                pair = (f"its estimate trades off with {PARAM_NAMES[j]} (correlation {r:+.2f}): the flight determines "
                        f"the two together, not each alone, and " if j >= 0 and abs(r) >= 0.5 else "")
                out[PARAM_NAMES[i]] = (f"ended on its {side} search bound {b[i, edge]:g}: the data pull it further than "
                                       f"the bounds allow; {pair}a model-structure error (what eq. 8 cannot explain, "
                                       f"e.g. a flight controller's loop) is taken up by it; the value is not an estimate")
    return out


def _prior_report(plan: _Plan, run: _Run, prior: Any, pinned: dict[str, str] | None = None) -> dict[str, Any]:
    """Which free parameters the flight determines and which stay at their prior (share > 0.5); the
    parameters the data cannot move at all (``fixed_at_prior``) keep the prior's value and std. A
    parameter on a search bound (``pinned``) is in neither list: the data pulled it away from the
    prior as far as the bounds allow, and its value is not an estimate (``on_bound``)."""
    if plan.prior is None:
        return {}
    det: list[str] = []
    undet: list[str] = []
    for i, n in enumerate(PARAM_NAMES):
        if plan.free[i] and np.isfinite(run.share[i]) and n not in (pinned or {}):
            (undet if run.share[i] > 0.5 else det).append(n)
    return {"source": str(getattr(prior, "source", "given")), "determined": det, "prior_dominated": undet,
            "on_bound": sorted(pinned or {}),
            "fixed_at_prior": [n for i, n in enumerate(PARAM_NAMES) if not plan.free[i]],
            "prior_share": {n: float(run.share[i]) for i, n in enumerate(PARAM_NAMES) if np.isfinite(run.share[i])},
            "nominal": {n: float(plan.prior[0][i]) for i, n in enumerate(PARAM_NAMES)},
            "std": {n: float(plan.prior[1][i]) for i, n in enumerate(PARAM_NAMES)}}


def identify(prepared: Any, *, algorithm: str = "cabc", seed: int = 0, refine: bool = True,
             maxiter: int | None = None, callback: Callable[[dict], Any] | None = None,
             bounds: dict[str, tuple[float, float]] | None = None,
             config: IdentifyConfig | None = None, prior: Any = None, pmap: Map = serial_map) -> HoverModel:
    """Identify the hover model; see the module docstring. Raises SysidError (a ValueError) for unusable data.

    ``prior``: a prior model (:class:`groundstation.aircraft.Prior` or ``(nominal (31,), std (31,))``)
    for output error with a priori weighting; None = plain output error. ``pmap``: a map over worker
    processes (:func:`groundstation.parallel.worker_map`) for the screening refinements of each
    search's starts; the model is the same with any map.
    """
    cfg = config or IdentifyConfig()
    _check(cfg, algorithm, prepared)
    iters = maxiter or cfg.maxiter or DEFAULT_MAXITER[algorithm]
    rng = np.random.default_rng(seed)
    trim = cfg.input_offsets and refine
    with threadpool_limits(1):
        plan = _plan(prepared, cfg, refine, bounds, prior, pmap)
        run = _Run(theta=np.clip(_fixed_values(plan), plan.bounds[:, 0], plan.bounds[:, 1]))
        _identify_subsystems(plan, cfg, run, refine=refine, callback=callback, algorithm=algorithm, iters=iters,
                             maxiter=maxiter, rng=rng)
        match, used = _in_sample_match(plan, cfg, run.theta, trim)
    model = _model(prepared, plan, cfg, run, match, used, algorithm=algorithm, seed=seed, refine=refine, prior=prior)
    if refine and estimates_hole_inputs(prepared, cfg):
        prepared, model = refit_hole_inputs(prepared, model, cfg, prior=prior, bounds=bounds, pmap=pmap)
    if refine and cfg.select_candidates.strip() and cfg.select_folds >= 2:
        model = select_config(prepared, model, cfg, prior=prior, bounds=bounds, pmap=pmap, fit=fit_candidate, refit=refit)
    if refine and cfg.input_kind != "blade":
        model = attach_command_structure(prepared, model, cfg, pmap=pmap, refit=refit)
    return model


def estimates_hole_inputs(prepared: Any, cfg: IdentifyConfig) -> bool:
    """Whether the identification estimates the inputs in the link's holes: passes asked for, bridged
    inputs, and lat and lon streamed at least every ``hole_input_max_stride`` grid steps."""
    if cfg.hole_input_passes <= 0 or not has_bridged_inputs(prepared.segments):
        return False
    stride = prepared.native_stride(("lat", "lon")) if hasattr(prepared, "native_stride") else np.ones(2)
    return bool(np.all(stride <= cfg.hole_input_max_stride))


def refit_hole_inputs(prepared: Any, model: HoverModel, cfg: IdentifyConfig, *, prior: Any = None,
                      bounds: dict | None = None, pmap: Map = serial_map) -> tuple[Any, HoverModel]:
    """``cfg.hole_input_passes`` times: the inputs in the link's holes estimated with the model, always
    from the prepared data's own bridges (:func:`solve_hole_inputs`), then the model refined on them
    (:func:`fit_candidate`); with ``hole_input_count_settling`` both count the outputs right after the
    holes (:func:`count_settling`). Returns the data with the last estimate and the model refined on it."""
    base = count_settling(prepared) if cfg.hole_input_count_settling else prepared
    filled = base
    for _ in range(cfg.hole_input_passes):
        filled = solve_hole_inputs(base, model, cfg, bounds=bounds, prior=prior)
        model = fit_candidate(filled, model, cfg, prior=prior, bounds=bounds, pmap=pmap)
    return filled, model


def count_settling(prepared: Any) -> Any:
    """``prepared`` with the output samples that data preparation left out while the rotor settles after
    a bridged input (``settle_after_bridge_tau``: the straight line's error still moves the rotor there)
    counted again: once the inputs in the holes are estimated, they are the outputs that show what the
    inputs did."""
    segs, counted = [], 0
    for s in prepared.segments:
        st = getattr(s, "settling", None)
        if st is None or s.measured is None:
            segs.append(s)
            continue
        m = s.measured | st
        counted += int(st[:, s.available].sum())
        segs.append(replace(s, measured=None if m[:, s.available].all() else m, settling=None))
    if not counted:
        return prepared
    lq = dict(getattr(prepared, "link_quality", {}) or {})
    lq["settling_samples_counted"] = counted      # output samples (channel by channel) counted again
    return replace(prepared, segments=segs, link_quality=lq)


def solve_hole_inputs(prepared: Any, model: HoverModel, cfg: IdentifyConfig, *, bounds: dict | None = None,
                      prior: Any = None) -> Any:
    """``prepared`` with the inputs in its bridged holes estimated with ``model``: by default
    (``hole_input_solve = "windows"``) the coefficients that minimise the refinement's own cost at the
    model's parameters and noise scales (:meth:`~groundstation.sysid.hole_inputs.WindowHoles.solve`),
    so that refit and estimate alternate on one cost and meet at its joint minimum; "stretch":
    :func:`~groundstation.sysid.hole_inputs.estimate_hole_inputs`."""
    subs = _hole_subsystems(cfg)
    if cfg.hole_input_solve == "stretch":
        kf = tuple(c.strip() for c in cfg.kinematic_forcing.split(",") if c.strip())
        return estimate_hole_inputs(prepared, model, horizon_s=cfg.hole_input_horizon_s,
                                    band_factor=cfg.hole_input_band, forcing_channels=kf, subsystems=subs,
                                    prior_s=cfg.hole_input_prior_s)
    if cfg.hole_input_solve != "windows":
        raise SysidError(f"identify.hole_input_solve: {cfg.hole_input_solve!r}; allowed windows, stretch")
    plan = _plan(prepared, cfg, True, bounds, prior, search=False)
    if plan.holes is None:
        return prepared
    theta = model.theta
    ns = dict(getattr(model.fit, "noise_sigma", {}) or {})
    coeffs: dict = {}
    for sub, sub_params in ((0, HOR_PARAMS), (1, VER_PARAMS)):
        if sub not in subs:
            continue
        sub_free = np.zeros(N_PARAMS, dtype=bool)
        sub_free[[PARAM_INDEX[p] for p in sub_params]] = True
        cost = _refine_cost(plan, cfg, sub, sub_free, theta, cfg.input_offsets)
        if cost.used.any():   # the model's noise scales, else the residual's on these windows
            x = theta[sub_free]
            sigma = np.array([float(ns.get(c, s)) for c, s in zip(OUTPUTS, noise_scales(cost, x), strict=True)])
            coeffs.update(plan.holes.solve(cost, x, sigma))
    lq = dict(getattr(prepared, "link_quality", {}) or {})
    band = cfg.hole_input_band * abs(float(model.params["inv_tau_s"])) / (2.0 * np.pi)
    lq["inputs_in_holes"] = {"estimated_holes": len({h for h, _ in coeffs}), "band_hz": round(band, 3),
                             "solve": "windows"}
    return replace(prepared, segments=plan.holes.fill(prepared.segments, coeffs), link_quality=lq)


def _hole_subsystems(cfg: IdentifyConfig) -> tuple[int, ...]:
    """The subsystems of ``identify.hole_input_subsystems`` (0 horizontal, 1 vertical)."""
    names = [n.strip() for n in cfg.hole_input_subsystems.split(",") if n.strip()]
    bad = [n for n in names if n not in ("horizontal", "vertical")]
    if bad:
        raise SysidError(f"identify.hole_input_subsystems: unknown {bad}; allowed horizontal, vertical")
    return tuple(i for i, n in enumerate(("horizontal", "vertical")) if n in names)


def _subsystem_costs(plan: Any, cfg: Any, run: Any) -> Iterator[tuple[int, np.ndarray, Any]]:
    """(subsystem, its free-parameter mask, its refinement cost) for each subsystem with measured data,
    each cost built at ``run.theta`` as the previous subsystem's refinement left it."""
    for sub, sub_params in ((0, HOR_PARAMS), (1, VER_PARAMS)):
        idx = np.array([PARAM_INDEX[p] for p in sub_params])
        sub_free = np.zeros(N_PARAMS, dtype=bool)
        sub_free[idx] = plan.free[idx]
        cost = _refine_cost(plan, cfg, sub, sub_free, run.theta, cfg.input_offsets)
        if cost.used.any():
            yield sub, sub_free, cost


def _take(run: Any, cost: Any, x: np.ndarray, sub: int, cfg: Any) -> None:
    """``run`` moved to the subsystem's refined parameters ``x`` (and its trims, where estimated)."""
    run.theta = cost.full(x)[0]
    if cfg.flight_trim:
        run.delta[list(_SUBS_INPUTS[sub])] = cost.sim.solve_trim(run.theta[None])[sub][0]


def fit_candidate(prepared: Any, model0: HoverModel, cfg: Any, *, prior: Any = None,
                  bounds: dict | None = None, quick: bool = False, pmap: Map = serial_map) -> HoverModel:
    """``cfg``'s model of ``prepared``: refinements from ``model0``'s parameters and ``cfg.extra_starts``,
    the lowest refined (MAP) objective per subsystem; standard errors and report as :func:`identify`'s.
    ``quick``: one refinement pass from ``model0``'s parameters only (the selection's screening fit)."""
    with threadpool_limits(1):
        plan = _plan(prepared, cfg, True, bounds, prior, search=False)
        run = _Run(theta=np.clip(model0.theta, plan.bounds[:, 0], plan.bounds[:, 1]))
        for sub, sub_free, cost in _subsystem_costs(plan, cfg, run):
            x, ref = best_refinement(cost, run.theta[sub_free], plan, cfg, sub_free, quick, pmap)
            record_tradeoffs(run, sub_free, ref, None if plan.prior is None else plan.prior[1][sub_free])
            run.std[np.flatnonzero(sub_free)] = ref.std
            run.share[np.flatnonzero(sub_free)] = ref.prior_share if plan.prior is not None else 0.0
            run.sigma[cost.used] = ref.sigma[cost.used]
            _take(run, cost, x, sub, cfg)
            run.F_total += float(cost(x[None])[0])
            run.nfev += cost.nfev
        match, used = _in_sample_match(plan, cfg, run.theta, cfg.input_offsets)
    f0 = model0.fit
    run.F_search = float(np.nan if f0.search_cost is None else f0.search_cost)  # type: ignore[arg-type]
    run.nit = int(f0.iterations or 0)
    run.nfev += int(f0.evaluations or 0)
    run.histories, run.histories_nfev = dict(f0.history), dict(f0.history_nfev)
    run.search_by_sub = dict(f0.search_cost_by_subsystem)
    run.search_alg = dict(f0.search_algorithm_by_subsystem)
    return _model(prepared, plan, cfg, run, match, used, algorithm=str(f0.algorithm or "cabc"),
                  seed=int(f0.seed or 0), refine=True, prior=prior)


def _fixed_values(plan: _Plan) -> np.ndarray:
    """(31,) start vector whose fixed entries are what is published for them: 0 without a prior, the
    prior's nominal with one (a parameter the flight cannot move stays at the prior, not at 0)."""
    theta = np.zeros(N_PARAMS)
    if plan.prior is not None:
        theta[~plan.free] = plan.prior[0][~plan.free]
    return theta


def _model(prepared: Any, plan: _Plan, cfg: IdentifyConfig, run: _Run, match: dict[str, float], used: np.ndarray, *,
           algorithm: str, seed: int, refine: bool, prior: Any) -> HoverModel:
    theta = run.theta
    pinned = _pinned(theta, plan.free, plan.bounds, run.partner)
    std: dict[str, float | None] = {n: (float(run.std[i]) if np.isfinite(run.std[i]) else None)
                                    for i, n in enumerate(PARAM_NAMES)}
    if plan.prior is not None:  # fixed at the prior: published with the prior's uncertainty
        std.update({PARAM_NAMES[i]: float(plan.prior[1][i]) for i in np.flatnonzero(~plan.free)})
    segs = prepared.segments
    fit = ModelFit.make(
        algorithm=algorithm, seed=int(seed), fitness=float(1.0 / (1.0 + run.F_total)), cost=float(run.F_total),
        search_cost=float(run.F_search), search_window_s=float(cfg.search_window_s),
        search_cost_by_subsystem=run.search_by_sub, search_restarts=int(cfg.search_restarts if refine else 1),
        search_algorithm_by_subsystem=run.search_alg, refined=bool(refine), match_degree=match,
        evaluations=int(run.nfev), iterations=int(run.nit), seconds=None,
        window_s=float(cfg.window_s), window_step_s=float(cfg.window_step_s), windows=int(plan.win.count),
        estimate_all_initial=cfg.estimate_all_initial,
        channels=[OUTPUTS[j] for j in range(8) if used[j]],
        fixed=[PARAM_NAMES[i] for i in range(N_PARAMS) if not plan.free[i]],
        fixed_reasons=[r.replace(" fixed at 0", " fixed at the prior's value") if plan.prior is not None else r
                       for r in plan.reasons],
        noise_sigma={OUTPUTS[j]: float(run.sigma[j]) for j in range(8) if np.isfinite(run.sigma[j])},
        history=run.histories, history_nfev=run.histories_nfev, notes=list(prepared.notes),
        trim_estimated=bool(cfg.flight_trim and refine), kinematic_forcing=plan.kf,
        input_trim_correction_pwm={k: float(run.delta[j]) * float(prepared.pwm_per_unit)
                                   for j, k in enumerate(prepared.input_trim_pwm)},
        pinned_reasons=pinned,
        unstable_modes=[m.describe() for m in unstable_modes(theta)],
        prior=_prior_report(plan, run, prior, pinned),
    )
    return HoverModel(
        params={n: float(v) for n, v in zip(PARAM_NAMES, theta, strict=True)},
        sample_rate_hz=float(1.0 / prepared.dt_s),
        input_trim_pwm={k: float(v) + float(run.delta[j]) * float(prepared.pwm_per_unit)
                        for j, (k, v) in enumerate(prepared.input_trim_pwm.items())},
        pwm_per_unit=float(prepared.pwm_per_unit), output_trim=dict(prepared.output_trim), parameter_std=std, fit=fit,
        source={"logs": sorted({s.source for s in segs}),
                "window_s": [float(min(s.t_s[0] for s in segs)), float(max(s.t_s[-1] for s in segs))],
                "segments": [[s.source, int(s.flight), float(s.t_s[0]), float(s.t_s[-1])] for s in segs],
                "link_quality": _link_report(prepared, plan.win)},
        pinned=list(pinned), window_input_offsets=cfg.window_input_offsets,
    )


def _link_report(prepared: Any, win: Any) -> dict[str, Any]:
    """The link figures of data preparation and what they did to the fit: windows used, and how many
    of them have holes (samples bridged, not counted in the cost)."""
    lq = dict(getattr(prepared, "link_quality", {}) or {})
    meas = getattr(win, "measured", None)
    holed = 0 if meas is None else int((~meas.all(axis=(1, 2))).sum())
    lq.update(windows=int(win.count), windows_with_holes=holed)
    return lq


def refit(prepared: Any, model: HoverModel, *, config: IdentifyConfig | None = None, prior: Any = None) -> HoverModel:
    """The model refined on ``prepared`` from ``model``'s parameters (no search): the cheap refit of
    a cross-validation fold (one pass, stopped at ``fold_refit_ftol``). Same windows, trims, forcing,
    weighting and prior as :func:`identify`."""
    cfg = config or IdentifyConfig()
    _check(cfg, "cabc", prepared)
    with threadpool_limits(1):
        plan = _plan(prepared, cfg, True, None, prior, search=False)
        run = _Run(theta=np.clip(model.theta, plan.bounds[:, 0], plan.bounds[:, 1]))
        for sub, sub_free, cost in _subsystem_costs(plan, cfg, run):
            pr = None if plan.prior is None else (plan.prior[0][sub_free], plan.prior[1][sub_free])
            ref = refine_ls(cost, run.theta[sub_free], plan.bounds[sub_free], passes=1, max_nfev=cfg.refine_max_nfev,
                            with_std=False, prior=pr, weighting=cfg.channel_weighting,
                            prior_colour=cfg.prior_weighting == "effective", ftol=cfg.fold_refit_ftol)
            _take(run, cost, ref.x, sub, cfg)
    return HoverModel(params={n: float(v) for n, v in zip(PARAM_NAMES, run.theta, strict=True)},
                      sample_rate_hz=float(1.0 / prepared.dt_s),
                      input_trim_pwm={k: float(v) + float(run.delta[j]) * float(prepared.pwm_per_unit)
                                      for j, (k, v) in enumerate(prepared.input_trim_pwm.items())},
                      pwm_per_unit=float(prepared.pwm_per_unit), output_trim=dict(prepared.output_trim),
                      fit=ModelFit.make(window_s=cfg.window_s, estimate_all_initial=cfg.estimate_all_initial),
                      window_input_offsets=cfg.window_input_offsets)
