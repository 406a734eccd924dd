"""One interface for CABC, ABC, GA and DE; the logistic map avoids its fixed points."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.sysid.optimizers import (
    ALGORITHMS,
    LOGISTIC_BAD_POINTS,
    logistic_step,
    minimize_abc,
    minimize_cabc,
)

TARGET = np.array([0.7, -1.3, 2.1, 0.2])
BOUNDS = np.array([[-5.0, 5.0]] * 4)


def sphere(X):
    X = np.atleast_2d(X)
    return ((X - TARGET) ** 2).sum(axis=1)


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_each_optimizer_finds_the_minimum_with_one_interface(name):
    calls = []
    res = ALGORITHMS[name](sphere, BOUNDS, rng=np.random.default_rng(1), maxiter=400, maxfev=8000,
                           callback=lambda r: calls.append(r.fun) and False)
    assert res.fun < 0.05, (name, res.fun, res.x)
    assert np.all(np.abs(res.x - TARGET) < 0.25)
    assert res.nfev <= 8000 + 40
    assert res.nit == len(res.history) == len(calls) == len(res.history_nfev)
    assert np.all(np.diff(res.history) <= 1e-15)  # best-so-far never worsens
    assert np.all((res.x >= BOUNDS[:, 0]) & (res.x <= BOUNDS[:, 1]))


def test_budget_is_respected_and_callback_can_stop():
    res = minimize_cabc(sphere, BOUNDS, rng=0, maxiter=10_000, maxfev=500)
    assert 480 <= res.nfev <= 520
    stop = minimize_abc(sphere, BOUNDS, rng=0, maxiter=10_000, callback=lambda r: r.nit >= 3)
    assert stop.nit == 3


def test_logistic_map_never_sits_on_fixed_points():
    rng = np.random.default_rng(0)
    c = np.array(list(LOGISTIC_BAD_POINTS) + [0.3, 0.9])
    seen = []
    for _ in range(2000):
        c = logistic_step(c, rng)
        seen.append(c.copy())
    s = np.array(seen)
    for p in LOGISTIC_BAD_POINTS:
        assert np.min(np.abs(s - p)) > 0
    assert np.all((s > 0) & (s < 1))
    # still chaotic: the values spread over (0, 1) rather than collapse onto a cycle
    assert np.unique(np.round(s[-200:], 6)).size > 150


def test_chaotic_search_helps_on_a_narrow_valley():
    """Rosenbrock in 6-D: CABC gets at least as low as ABC on average at equal budgets."""
    def rosen(X):
        X = np.atleast_2d(X)
        return (100 * (X[:, 1:] - X[:, :-1] ** 2) ** 2 + (1 - X[:, :-1]) ** 2).sum(axis=1)
    b = np.array([[-2.0, 2.0]] * 6)
    fc = [minimize_cabc(rosen, b, rng=s, maxfev=6000, maxiter=10_000).fun for s in range(5)]
    fa = [minimize_abc(rosen, b, rng=s, maxfev=6000, maxiter=10_000).fun for s in range(5)]
    assert np.median(fc) < np.median(fa)


def test_chaotic_radius_schedule():
    """The chaotic radius shrinks from radius0 to radius_end over the iterations; over an evaluation
    budget only with shrink_over_budget (a budgeted run with maxiter=10**6 keeps ~radius0 otherwise)."""
    kw = dict(rng=0, radius0=0.05, radius_end=1e-4)
    res = minimize_cabc(sphere, BOUNDS, maxiter=10**6, maxfev=1500, shrink_over_budget=True, **kw)
    assert res.chaos_radius < 2e-4
    plain = minimize_cabc(sphere, BOUNDS, maxiter=10**6, maxfev=1500, **kw)
    assert plain.chaos_radius > 0.049
    half = minimize_cabc(sphere, BOUNDS, maxiter=20, callback=lambda r: r.nit >= 10, **kw)
    assert 1e-3 < half.chaos_radius < 5e-3  # half way in iterations: geometric mean ~2.2e-3
    assert minimize_abc(sphere, BOUNDS, rng=0, maxiter=5).chaos_radius == 0.0


@pytest.mark.parametrize("popsize, D, stop", [(1, 22, None), (1, 3, None), (2, 9, 7)])
def test_de_keeps_every_evaluation_of_scipys_search(popsize, D, stop):
    """DE is scipy's: every candidate scipy evaluates is in the archive (inside the bounds, failures as
    inf), one callback per generation, the callback's stop and the iteration budget are scipy's."""
    from groundstation.sysid.optimizers import minimize_de

    lo = -np.linspace(1.0, 3.0, D)
    bounds = np.stack([lo, np.linspace(0.5, 4.0, D)], axis=1)
    centre = np.linspace(-0.5, 0.5, D)

    def rugged(X):
        X = np.atleast_2d(X)
        f = ((X - centre) ** 2).sum(axis=1) + 0.3 * np.sin(7 * X).sum(axis=1)
        return np.where(X[:, 0] > 0.2, np.nan, f)   # a region that fails to simulate

    seen = []
    res = minimize_de(rugged, bounds, rng=np.random.default_rng(3), maxiter=40, popsize=popsize,
                      callback=lambda r: seen.append(r.nfev) or (stop is not None and r.nit >= stop))
    n = max(5, popsize * D)
    assert res.nit == len(seen) == (stop or 40)
    assert res.nfev == n * (res.nit + 1) == res.archive_x.shape[0] == seen[-1]
    assert np.all((res.archive_x >= bounds[:, 0]) & (res.archive_x <= bounds[:, 1]))
    failed = res.archive_x[:, 0] > 0.2
    assert failed.any() and np.all(np.isinf(res.archive_f[failed])) and np.all(np.isfinite(res.archive_f[~failed]))
    assert res.fun == res.archive_f.min() == res.history[-1]
    np.testing.assert_array_equal(res.x, res.archive_x[np.argmin(res.archive_f)])
    assert ("callback" in res.message) == (stop is not None)


def test_de_tolerance_stops_a_converged_population():
    """``tol`` (scipy's) ends the search once the population's costs agree; without it every generation runs."""
    from groundstation.sysid.optimizers import minimize_de

    bounds = np.array([[-5.0, 5.0]] * 4)
    full = minimize_de(lambda X: 1.0 + sphere(X), bounds, rng=np.random.default_rng(2), maxiter=60, popsize=5)
    short = minimize_de(lambda X: 1.0 + sphere(X), bounds, rng=np.random.default_rng(2), maxiter=60, popsize=5,
                        tol=1e-3)
    assert full.nit == 60 and 20 < short.nit < 60, (full.nit, short.nit)
    pop = short.archive_f[-20:]
    assert pop.std() <= 1e-3 * pop.mean() * 1.5 and short.fun < 1.0 + 1e-2
