"""Population optimisers with one interface: CABC (the paper), plain ABC, a real-coded GA, and DE;
and a multi-start least-squares minimiser (:func:`minimize_lsq`, the same shape plus a residual
function: the plain output-error reference fit of the held-out benchmark) and a grid-then-free
least-squares minimiser for a delay-like coordinate (:func:`minimize_grid_lsq`: the equivalent
time delays of the command-response structure, :mod:`groundstation.sysid.structure`).

``minimize_X(fun, bounds, *, rng, maxiter, maxfev=None, callback=None, **opts) -> OptimizeResult``

* ``fun`` takes a batch ``(C, D)`` and returns costs ``(C,)`` (the whole colony is evaluated at once);
* ``bounds`` is ``(D, 2)``; candidates are kept inside;
* ``rng`` is a ``numpy.random.Generator`` (or a seed); ``maxiter`` iterations or ``maxfev`` cost
  evaluations (candidates), whichever comes first - the comparison uses equal ``maxfev``;
* ``callback(res)`` gets an OptimizeResult with ``x, fun, nit, nfev`` after each iteration; returning
  True stops the run;
* the result has ``x, fun, nfev, nit, success, message`` and ``history`` (best cost after each
  iteration), ``history_nfev`` (evaluations spent at that point), the final ``population`` /
  ``population_fun`` and every evaluated point (``archive_x``, ``archive_f``) so that a local
  refinement can start from several distinct good points.

CABC follows the paper's steps 1-8: N_s = 20 = 2 N_e food sources ranked, employed bees (eq. 13,
greedy eq. 14), onlookers by fitness ``p_i = fit_i / sum fit`` (eq. 15), scouts after ``limit``
failed trials (eq. 16), and a chaotic search around the best with the logistic map (mu = 4, eq. 9)
that avoids the fixed/periodic points 0, 0.25, 0.5, 0.75, 1, candidates ``x_best + R (2 c - 1)``
(eq. 17) with a radius R shrinking geometrically over the run; the best chaotic candidate replaces
a random employed bee (never the best one). Onlookers are generated together from the sources
as they stand after the employed phase and applied greedily in turn (a batched colony).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

Fun = Callable[[np.ndarray], np.ndarray]


class OptimizeResult(dict):
    """A dict whose keys read as attributes (the shape of ``scipy.optimize.OptimizeResult``): the bee
    colonies and the GA return it without importing scipy.optimize (about 0.3 s of CPU), which only DE
    and the least-squares fits load. A missing key raises AttributeError, so ``getattr(res, k, None)``
    works as with scipy's."""

    def __getattr__(self, name: str) -> Any:
        try:
            return self[name]
        except KeyError as exc:
            raise AttributeError(name) from exc

    def __setattr__(self, name: str, value: Any) -> None:
        self[name] = value

    def __delattr__(self, name: str) -> None:
        del self[name]

    def __dir__(self) -> list[str]:
        return list(self.keys())

#: Points where the mu = 4 logistic map loses its chaos (fixed points and short cycles).
LOGISTIC_BAD_POINTS = (0.0, 0.25, 0.5, 0.75, 1.0)


def _rng(rng) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def logistic_step(c: np.ndarray, rng: np.random.Generator, mu: float = 4.0, eps: float = 1e-6) -> np.ndarray:
    """One step of the logistic map ``mu c (1 - c)``; values that land on (or next to) a point
    of :data:`LOGISTIC_BAD_POINTS` are re-drawn uniformly so the sequence stays chaotic."""
    out = mu * c * (1.0 - c)
    return _avoid_bad(out, rng, eps)


def _avoid_bad(c: np.ndarray, rng: np.random.Generator, eps: float = 1e-6) -> np.ndarray:
    c = np.asarray(c, dtype=float).copy()
    points = np.array(LOGISTIC_BAD_POINTS)
    for _ in range(10):
        bad = (np.abs(c[..., None] - points) < eps).any(axis=-1) | ~np.isfinite(c)
        if not bad.any():
            break
        c[bad] = rng.uniform(eps, 1 - eps, size=int(bad.sum()))
    return c


class _Tracker:
    """Counts evaluations, keeps the best, history, stopping and the callback."""

    def __init__(self, fun: Fun, maxfev: int | None, callback) -> None:
        self.fun = fun
        self.maxfev = maxfev
        self.callback = callback
        self.nfev = 0
        self.best_x: np.ndarray | None = None
        self.best_f = np.inf
        self.history: list[float] = []
        self.history_nfev: list[int] = []
        self.nit = 0
        self.stopped = False
        self.archive_x: list[np.ndarray] = []
        self.archive_f: list[np.ndarray] = []

    def budget_left(self) -> int:
        return np.iinfo(np.int64).max if self.maxfev is None else self.maxfev - self.nfev

    def __call__(self, X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(X)
        f = np.asarray(self.fun(X), dtype=float).reshape(-1)
        f = np.where(np.isfinite(f), f, np.inf)
        self.nfev += X.shape[0]
        self.archive_x.append(X.copy())
        self.archive_f.append(f.copy())
        i = int(np.argmin(f))
        if f[i] < self.best_f:
            self.best_f = float(f[i])
            self.best_x = X[i].copy()
        return f

    def end_iteration(self) -> bool:
        self.nit += 1
        self.history.append(self.best_f)
        self.history_nfev.append(self.nfev)
        if self.callback is not None:
            if self.callback(OptimizeResult(x=self.best_x, fun=self.best_f, nit=self.nit, nfev=self.nfev)):
                self.stopped = True
        return self.stopped or self.budget_left() <= 0

    def result(self, message: str, population: np.ndarray | None = None,
               population_fun: np.ndarray | None = None) -> OptimizeResult:
        return OptimizeResult(x=self.best_x, fun=self.best_f, nfev=self.nfev, nit=self.nit, success=True,
                              message=message, history=np.array(self.history),
                              history_nfev=np.array(self.history_nfev), population=population,
                              population_fun=population_fun,
                              archive_x=np.concatenate(self.archive_x) if self.archive_x else None,
                              archive_f=np.concatenate(self.archive_f) if self.archive_f else None)


def _neighbour(X: np.ndarray, i: np.ndarray, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Eq. 13 for sources ``i``: change one random dimension j towards/away from a random k != i."""
    n, D = X.shape
    V = X[i].copy()
    j = rng.integers(0, D, size=i.size)
    k = rng.integers(0, n - 1, size=i.size)
    k = np.where(k >= i, k + 1, k)
    phi = rng.uniform(-1.0, 1.0, size=i.size)
    rows = np.arange(i.size)
    V[rows, j] = X[i, j] + phi * (X[i, j] - X[k, j])
    V[rows, j] = np.clip(V[rows, j], lo[j], hi[j])
    return V


def _bee_colony(fun: Fun, bounds, *, rng, maxiter: int, maxfev: int | None, callback, colony_size: int,
                limit: int, chaos: bool, chaos_points: int, radius0: float, radius_end: float,
                shrink_over_budget: bool = False) -> OptimizeResult:
    rng = _rng(rng)
    b = np.asarray(bounds, dtype=float)
    lo, hi = b[:, 0], b[:, 1]
    span = hi - lo
    D = b.shape[0]
    ne = max(2, colony_size // 2)
    tr = _Tracker(fun, maxfev, callback)
    # step 1-2: N_s random solutions, the best N_e become the employed bees' food sources
    X0 = lo + rng.random((colony_size, D)) * span
    f0 = tr(X0)
    order = np.argsort(f0)[:ne]
    X, f = X0[order].copy(), f0[order].copy()
    trial = np.zeros(ne, dtype=int)
    cmap = _avoid_bad(rng.random(D), rng)
    R_last = 0.0
    for it in range(maxiter):
        if tr.budget_left() <= 0:
            break
        # step 3: employed bees
        idx = np.arange(ne)
        if tr.budget_left() < ne:
            idx = idx[: tr.budget_left()]
        V = _neighbour(X, idx, rng, lo, hi)
        fv = tr(V)
        better = fv < f[idx]
        X[idx[better]], f[idx[better]] = V[better], fv[better]
        trial[idx] = np.where(better, 0, trial[idx] + 1)
        # steps 4-5: onlookers choose sources by fitness
        n_on = min(ne, tr.budget_left())
        if n_on > 0:
            fit = 1.0 / (1.0 + np.maximum(f, 0.0))
            p = fit / fit.sum()
            pick = rng.choice(ne, size=n_on, p=p)
            V = _neighbour(X, pick, rng, lo, hi)
            fv = tr(V)
            for v, fvv, i in zip(V, fv, pick, strict=True):
                if fvv < f[i]:
                    X[i], f[i], trial[i] = v, fvv, 0
                else:
                    trial[i] += 1
        # step 6: scout for the most exhausted source
        i = int(np.argmax(trial))
        if trial[i] > limit and i != int(np.argmin(f)) and tr.budget_left() > 0:
            X[i] = lo + rng.random(D) * span
            f[i] = tr(X[i:i + 1])[0]
            trial[i] = 0
        # step 7: chaotic search around the best
        if chaos and tr.budget_left() > 0:
            # progress through the run in iterations; with shrink_over_budget also in evaluations, which
            # binds in budgeted runs with maxiter=10**6 (there the radius otherwise stays ~radius0)
            frac = it / max(maxiter - 1, 1)
            if shrink_over_budget and maxfev is not None:
                frac = min(1.0, max(frac, tr.nfev / maxfev))
            R_last = radius0 * (radius_end / radius0) ** frac
            R = span * R_last
            m = min(chaos_points, tr.budget_left())
            cands = np.empty((m, D))
            best = X[int(np.argmin(f))]
            for q in range(m):
                cmap = logistic_step(cmap, rng)
                cands[q] = np.clip(best + R * (2.0 * cmap - 1.0), lo, hi)
            fc = tr(cands)
            q = int(np.argmin(fc))
            ib = int(np.argmin(f))
            others = [r for r in range(ne) if r != ib]
            r = int(rng.choice(others))
            X[r], f[r], trial[r] = cands[q], fc[q], 0
        if tr.end_iteration():
            break
    out = tr.result("stopped by callback" if tr.stopped else "iteration or evaluation budget reached", X, f)
    out.chaos_radius = float(R_last)  # last chaotic-search radius as a fraction of the range (0 without chaos)
    return out


def minimize_cabc(fun: Fun, bounds, *, rng=None, maxiter: int = 100, maxfev: int | None = None, callback=None,
                  colony_size: int = 20, limit: int = 5, chaos_points: int = 10, radius0: float = 0.05,
                  radius_end: float = 1e-4, shrink_over_budget: bool = False) -> OptimizeResult:
    """Chaotic artificial bee colony (paper section 3.2, steps 1-8).

    The chaotic radius shrinks geometrically from ``radius0`` to ``radius_end`` (fractions of the range)
    over ``maxiter`` iterations; ``shrink_over_budget`` also over ``maxfev`` evaluations. Off by
    default: in the bench's equal-budget comparison (maxiter=10**6) shrinking over the budget made
    CABC clearly worse (median search cost 1.25 vs 1.07 over 20 seeds: the chaotic winner replaces an
    employed bee every iteration and the colony collapses onto the best), see ``chaos_radius``.
    """
    return _bee_colony(fun, bounds, rng=rng, maxiter=maxiter, maxfev=maxfev, callback=callback,
                       colony_size=colony_size, limit=limit, chaos=True, chaos_points=chaos_points,
                       radius0=radius0, radius_end=radius_end, shrink_over_budget=shrink_over_budget)


def minimize_abc(fun: Fun, bounds, *, rng=None, maxiter: int = 100, maxfev: int | None = None, callback=None,
                 colony_size: int = 20, limit: int = 5) -> OptimizeResult:
    """Plain artificial bee colony (CABC without step 7)."""
    return _bee_colony(fun, bounds, rng=rng, maxiter=maxiter, maxfev=maxfev, callback=callback,
                       colony_size=colony_size, limit=limit, chaos=False, chaos_points=0, radius0=0.0, radius_end=0.0)


def _tournament(P: np.ndarray, f: np.ndarray, n: int, size: int, rng: np.random.Generator) -> np.ndarray:
    c = rng.integers(0, P.shape[0], size=(n, size))
    return P[c[np.arange(n), np.argmin(f[c], axis=1)]]


def minimize_ga(fun: Fun, bounds, *, rng=None, maxiter: int = 100, maxfev: int | None = None, callback=None,
                population: int = 20, crossover: float = 0.8, mutation: float = 0.2, elite: int = 2,
                tournament: int = 2, mutation_scale: float = 0.1) -> OptimizeResult:
    """Real-coded GA: tournament selection, arithmetic (blend) crossover with probability
    ``crossover``, Gaussian mutation (sigma = ``mutation_scale`` x range) of each child with
    probability ``mutation`` on one random gene, and ``elite`` best kept unchanged."""
    rng = _rng(rng)
    b = np.asarray(bounds, dtype=float)
    lo, hi = b[:, 0], b[:, 1]
    span = hi - lo
    D = b.shape[0]
    tr = _Tracker(fun, maxfev, callback)
    P = lo + rng.random((population, D)) * span
    f = tr(P)
    for _ in range(maxiter):
        n_child = min(population - elite, tr.budget_left())
        if n_child <= 0:
            break
        order = np.argsort(f)
        elites, f_el = P[order[:elite]], f[order[:elite]]
        pa = _tournament(P, f, n_child, tournament, rng)
        pb = _tournament(P, f, n_child, tournament, rng)
        do_x = rng.random(n_child) < crossover
        alpha = rng.uniform(-0.25, 1.25, size=(n_child, D))
        kids = np.where(do_x[:, None], pa + alpha * (pb - pa), pa)
        do_m = rng.random(n_child) < mutation
        j = rng.integers(0, D, size=n_child)
        rows = np.flatnonzero(do_m)
        kids[rows, j[rows]] += rng.normal(0.0, mutation_scale, size=rows.size) * span[j[rows]]
        kids = np.clip(kids, lo, hi)
        fk = tr(kids)
        P = np.concatenate([elites, kids])
        f = np.concatenate([f_el, fk])
        if tr.end_iteration():
            break
    return tr.result("stopped by callback" if tr.stopped else "iteration or evaluation budget reached", P, f)


def minimize_de(fun: Fun, bounds, *, rng=None, maxiter: int = 100, maxfev: int | None = None, callback=None,
                popsize: int = 1, tol: float = 0.0) -> OptimizeResult:
    """scipy's ``differential_evolution`` under the same interface: ``best1bin``, a Latin-hypercube
    start, the whole population evaluated in one call (``vectorized=True``, ``updating="deferred"``),
    no polishing; the callback sees every generation.

    Population = ``popsize * D`` (scipy's convention, at least 5); ``maxfev`` is turned into iterations.
    ``tol`` is scipy's relative convergence tolerance: the search stops once the spread (standard
    deviation) of the population's costs is at most ``tol`` times their mean magnitude (0 = never).
    """
    from scipy.optimize import differential_evolution

    rng = _rng(rng)
    b = np.asarray(bounds, dtype=float)
    npop = max(5, popsize * b.shape[0])
    tr = _Tracker(fun, maxfev, callback)
    if maxfev is not None:
        maxiter = min(maxiter, max(1, maxfev // npop - 1))

    def batch(x: np.ndarray) -> np.ndarray:   # scipy passes the population as (D, S)
        return tr(np.asarray(x).T)

    def generation(intermediate_result: Any) -> bool:
        return tr.end_iteration()

    res = differential_evolution(batch, b, maxiter=maxiter, popsize=popsize, rng=rng, callback=generation,
                                 vectorized=True, updating="deferred", polish=False, tol=tol)
    out = tr.result(str(res.message))
    out.x = tr.best_x if tr.best_x is not None else res.x
    return out


def minimize_lsq(fun: Fun, bounds, *, rng=None, maxiter: int = 100, maxfev: int | None = None, callback=None,
                 residuals: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], np.ndarray] | None = None,
                 x0: list[np.ndarray] | None = None, starts: int = 4, start_scale: float = 0.1) -> OptimizeResult:
    """Multi-start trust-region least squares (scipy ``least_squares``, ``trf``) under the same interface.

    ``residuals(x (D,)) -> (n,)`` is minimised from each start: the given ``x0`` points, then random
    points uniform in the box of ``start_scale`` times the bounds around their centre, ``starts`` in
    all; ``jac(x) -> (n, D)`` if given (else 2-point differences). ``maxiter`` bounds the residual
    evaluations of each start. ``fun`` scores the final point of each start (batch (C, D) -> (C,));
    the lowest wins. ``history`` is the winner's score after each start.
    """
    from scipy.optimize import least_squares

    rng = _rng(rng)
    b = np.asarray(bounds, dtype=float)
    lo, hi = b[:, 0], b[:, 1]
    span = hi - lo
    pts = [np.asarray(x, dtype=float) for x in (x0 or [])]
    centre = (lo + hi) / 2
    while len(pts) < starts:
        pts.append(centre + (rng.random(lo.size) - 0.5) * span * start_scale)
    tr = _Tracker(fun, maxfev, callback)
    for x in pts[:max(starts, len(pts))]:
        x = np.clip(x, lo + 1e-9 * span, hi - 1e-9 * span)
        res = least_squares(residuals, x, jac=jac if jac is not None else "2-point", bounds=(lo, hi), method="trf",
                            x_scale="jac", max_nfev=maxiter)
        tr(res.x[None])
        if tr.end_iteration():
            break
    return tr.result("stopped by callback" if tr.stopped else "all starts refined")


def minimize_grid_lsq(fun: Fun, bounds, *, rng=None, maxiter: int = 100, maxfev: int | None = None, callback=None,
                      residuals: Callable[[np.ndarray], np.ndarray], grid_index: int, grid: np.ndarray,
                      x0: list[np.ndarray] | None = None) -> OptimizeResult:
    """Least squares over a grid of one coordinate, then with every coordinate free (the same interface).

    For a parameter whose cost has many local minima along it and smooth ones across it (an
    equivalent time delay: the residual of a delayed response is piecewise linear in the delay, with a
    minimum near every multiple of the period of whatever oscillates): ``residuals(x (D,)) -> (n,)`` is
    minimised with coordinate ``grid_index`` held at each value of ``grid`` (from the first ``x0``, or
    the centre of the bounds, each grid fit at most ``maxiter // 2`` evaluations), then from the best of
    those with it free (at most ``maxiter``). ``fun`` scores each fit's end point (batch (C, D) -> (C,)),
    the lowest wins. The result also holds ``jac`` (n, D), the final fit's Jacobian (for standard errors).
    """
    from scipy.optimize import least_squares

    b = np.asarray(bounds, dtype=float)
    lo, hi = b[:, 0], b[:, 1]
    span = hi - lo
    start = np.asarray(x0[0], dtype=float) if x0 else (lo + hi) / 2
    free = np.ones(lo.size, dtype=bool)
    free[grid_index] = False
    tr = _Tracker(fun, maxfev, callback)

    def sub(g: float):
        def r(z: np.ndarray) -> np.ndarray:
            x = start.copy()
            x[free], x[grid_index] = z, g
            return residuals(x)
        return r

    best: tuple[float, np.ndarray] | None = None
    for g in np.clip(np.asarray(grid, dtype=float), lo[grid_index], hi[grid_index]):
        z0 = np.clip(start[free], lo[free] + 1e-9 * span[free], hi[free] - 1e-9 * span[free])
        res = least_squares(sub(float(g)), z0, bounds=(lo[free], hi[free]), method="trf", x_scale="jac",
                            max_nfev=max(2, maxiter // 2))
        x = start.copy()
        x[free], x[grid_index] = res.x, g
        f = float(tr(x[None])[0])
        if best is None or f < best[0]:
            best = (f, x)
        if tr.end_iteration():
            break
    assert best is not None
    x = np.clip(best[1], lo + 1e-9 * span, hi - 1e-9 * span)
    res = least_squares(residuals, x, bounds=(lo, hi), method="trf", x_scale="jac", max_nfev=maxiter)
    tr(res.x[None])
    tr.end_iteration()
    out = tr.result("grid, then every coordinate free")
    out.jac = res.jac if float(np.sum(res.fun ** 2)) <= out.fun * (1 + 1e-9) else None
    return out


ALGORITHMS: dict[str, Callable[..., OptimizeResult]] = {
    "cabc": minimize_cabc, "abc": minimize_abc, "ga": minimize_ga, "de": minimize_de,
}
