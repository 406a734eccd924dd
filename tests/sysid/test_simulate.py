"""Windowed batched simulation against a plain loop; LS initial-state recovery; eq. 11."""

from __future__ import annotations

import numpy as np
import pytest

from benchkit.synthetic import EXAMPLE_TRUTH
from groundstation.errors import SysidError
from groundstation.sysid.model import build_matrices, discretize, theta_from_dict
from groundstation.sysid.simulate import WindowSimulator, objective, simulate_windows

HOR_OUT = ((0, 0), (1, 1), (5, 3), (4, 4), (2, 6), (3, 7))
VER_OUT = ((0, 2), (1, 5))


def loop_sim(theta, u, x0h, x0v, dt):
    """Plain sample-by-sample simulation of one window: u (L, 4) -> y (L, 8)."""
    Ah, Bh, Av, Bv = build_matrices(theta)
    Adh, Bdh = discretize(Ah, Bh, dt)
    Adv, Bdv = discretize(Av, Bv, dt)
    L = u.shape[0]
    y = np.zeros((L, 8))
    xh, xv = x0h.copy(), x0v.copy()
    for k in range(L):
        for s, o in HOR_OUT:
            y[k, o] = xh[s]
        for s, o in VER_OUT:
            y[k, o] = xv[s]
        xh = Adh @ xh + Bdh @ u[k, :2]
        xv = Adv @ xv + Bdv @ u[k, 2:]
    return y


@pytest.fixture
def windows():
    rng = np.random.default_rng(3)
    th = theta_from_dict(EXAMPLE_TRUTH)
    W, L, dt = 6, 73, 0.02  # L not a multiple of the lifting block on purpose
    u = rng.normal(0, 0.1, (W, L, 4))
    x0h = rng.normal(0, 0.05, (W, 8))
    x0v = rng.normal(0, 0.05, (W, 3))
    y = np.stack([loop_sim(th, u[w], x0h[w], x0v[w], dt) for w in range(W)])
    return th, u, y, x0h, x0v, dt


def test_batched_equals_loop_from_the_estimated_initial_state(windows):
    th, u, y, _, _, dt = windows
    rng = np.random.default_rng(0)
    thetas = np.stack([th, th * (1 + 0.05 * rng.normal(size=th.size)), th * (1 + 0.05 * rng.normal(size=th.size))])
    sim = WindowSimulator(u, y + rng.normal(0, 0.01, y.shape), dt)
    yhat, x0 = sim.simulate(thetas, return_x0=True)
    assert yhat.shape == (3, 6, 73, 8)
    for c in range(3):
        for w in range(6):
            ref = loop_sim(thetas[c], u[w], x0[0][c, w], x0[1][c, w], dt)
            assert np.allclose(yhat[c, w], ref, atol=1e-10)


@pytest.mark.parametrize("all_initial", [False, True])
def test_least_squares_recovers_a_known_initial_state(windows, all_initial):
    th, u, y, x0h, x0v, dt = windows
    sim = WindowSimulator(u, y, dt, estimate_all_initial=all_initial, ridge=1e-12)
    yhat, x0 = sim.simulate(th[None], return_x0=True)
    assert np.allclose(x0[0][0], x0h, atol=1e-6)  # includes the unmeasured a_s, b_s
    assert np.allclose(x0[1][0], x0v, atol=1e-6)  # includes r_fb
    assert np.allclose(yhat[0], y, atol=1e-8)
    assert objective(yhat, y)[0] < 1e-6


def test_zero_start_of_unmeasured_states_would_be_worse(windows):
    """The LS estimate beats starting a_s b_s r_fb at zero (what the issue warns against)."""
    th, u, y, x0h, x0v, dt = windows
    y_zero = np.stack([loop_sim(th, u[w], np.r_[x0h[w, :6], 0, 0], np.r_[x0v[w, :2], 0], dt) for w in range(6)])
    yhat = simulate_windows(th[None], u, y, dt)
    assert objective(yhat, y)[0] < 0.01 * objective(y_zero[None], y)[0]


def test_unavailable_channels_are_ignored(windows):
    th, u, y, _, _, dt = windows
    y2 = y.copy()
    y2[..., 0:3] = np.nan  # no velocities
    avail = np.array([False, False, False, True, True, True, True, True])
    yhat = simulate_windows(th[None], u, y2, dt, available=avail)
    assert np.isfinite(yhat).all()
    F = objective(yhat, y2, avail)
    assert F.shape == (1,) and F[0] < 1e-3
    # a wrong candidate costs more
    F_bad = objective(simulate_windows((th * 1.3)[None], u, y2, dt, available=avail), y2, avail)
    assert F_bad[0] > 10 * F[0]


def test_objective_is_eq11():
    rng = np.random.default_rng(0)
    y = rng.normal(size=(2, 50, 8))
    yhat = y + 0.1
    F = objective(yhat[None], y)
    yy = y.reshape(-1, 8)
    expect = sum(np.linalg.norm(np.full(100, 0.1)) / np.linalg.norm(yy[:, j] - yy[:, j].mean()) for j in range(8))
    assert F[0] == pytest.approx(expect)


def test_variable_projection_recovers_the_input_matrix(windows):
    from groundstation.sysid.cost import LINEAR_B, WindowedCost, Windows
    from groundstation.sysid.model import PARAM_INDEX

    th, u, y, _, _, dt = windows
    win = Windows(u, y, np.ones((6, 8), bool), np.zeros(6, int), np.zeros(6), dt)
    free = np.ones(31, dtype=bool)
    cost = WindowedCost(win, free, th, estimate_all_initial=True, varpro=True)
    assert cost.dim == 31 - len(LINEAR_B)
    x_true = th[cost.free]
    full = cost.complete(x_true[None])[0]
    for name in LINEAR_B:
        assert full[PARAM_INDEX[name]] == pytest.approx(th[PARAM_INDEX[name]], rel=2e-3, abs=1e-6)
    assert cost(x_true[None])[0] < 1e-3


def test_expm_batched_matches_scipy():
    from scipy.linalg import expm

    from groundstation.sysid.model import expm_batched

    rng = np.random.default_rng(5)
    M = rng.normal(size=(40, 10, 10)) * np.logspace(-4, 1.5, 40)[:, None, None]  # norms from tiny to ~1e2
    E = expm_batched(M)
    for i in range(M.shape[0]):
        ref = expm(M[i])
        assert np.abs(E[i] - ref).max() <= 1e-12 * np.abs(ref).max()
    M[3, 0, 0] = np.nan
    E = expm_batched(M)
    assert not np.isfinite(E[3]).all() and np.isfinite(np.delete(E, 3, axis=0)).all()


@pytest.mark.parametrize("block", [(5, 5), (7, 4), (10, 10)])
def test_sse_equals_the_explicit_errors(windows, block):
    """The quadratic-form SSE (no error array) equals the sum of squared explicit errors, also for
    unstable candidates (where the form cancels and the explicit fallback runs), L not a multiple of
    the block, and a channel missing in some windows."""
    from groundstation.sysid.model import bounds_array

    th, u, y, _, _, dt = windows
    rng = np.random.default_rng(7)
    b = bounds_array()
    wild = b[:, 0] + rng.random((6, th.size)) * (b[:, 1] - b[:, 0])  # mostly unstable
    near = th * (1 + 0.05 * rng.normal(size=(4, th.size)))
    thetas = np.vstack([th, near, wild])
    avail = np.ones((6, 8), dtype=bool)
    avail[1, 0] = avail[4, 5] = False  # u missing in window 1, r in window 4
    for est in (False, True):
        sim = WindowSimulator(u, y + rng.normal(0, 0.01, y.shape), dt, avail, estimate_all_initial=est,
                              lifted_block=block)
        sse = sim.sse(thetas)
        e = sim.errors(thetas)
        ref = (e ** 2).sum(axis=(1, 2))
        ok = ref < 1e200
        assert ok[:5].all()
        assert np.allclose(sse[ok], ref[ok], rtol=1e-7, atol=0)
        assert np.allclose(sse[:5], ref[:5], rtol=1e-10, atol=0)


def test_input_trim_offsets_are_recovered(windows):
    """Inputs logged with a constant offset (a wrong trim): the offset is solved and the fit is exact."""
    th, u, y, _, _, dt = windows
    delta = np.array([0.02, -0.015, 0.03, 0.01])  # lat lon col ped
    sim = WindowSimulator(u + delta, y, dt, estimate_all_initial=True, ridge=1e-12, estimate_trim=True)
    trims = sim.solve_trim(th[None])
    assert np.allclose(trims[0][0], delta[:2], atol=1e-6)
    assert np.allclose(trims[1][0], delta[2:], atol=1e-6)
    assert sim.sse(th[None])[0].max() < 1e-12
    assert np.abs(sim.errors(th[None])).max() < 1e-6
    # without the trim the same data fit clearly worse
    plain = WindowSimulator(u + delta, y, dt, estimate_all_initial=True, ridge=1e-12)
    assert plain.sse(th[None])[0].sum() > 1e3 * sim.sse(th[None])[0].sum()


def test_input_offsets_per_window_are_solved_with_the_initial_states(windows):
    """Each window's inputs logged with its own constant offset (a stabiliser's integrator trim that
    changes from window to window): per-window offsets fit exactly, one offset per flight does not,
    and the two modes exclude each other."""
    th, u, y, _, _, dt = windows
    rng = np.random.default_rng(3)
    delta = rng.normal(0, 0.02, (u.shape[0], 1, 4))   # (W, 1, 4): one offset per window and input
    per_window = WindowSimulator(u + delta, y, dt, ridge=1e-12, window_offsets=True)
    assert per_window.sse(th[None])[0].max() < 1e-10
    assert np.abs(per_window.errors(th[None])).max() < 1e-5
    flight = WindowSimulator(u + delta, y, dt, ridge=1e-12, estimate_trim=True)
    assert flight.sse(th[None])[0].sum() > 1e3 * per_window.sse(th[None])[0].sum()
    with pytest.raises(SysidError, match="exclude each other"):
        WindowSimulator(u, y, dt, estimate_trim=True, window_offsets=True)


def test_known_forcing_enters_like_an_input(windows):
    """Accelerations added to u_dot, v_dot, w_dot (held over a sample, like the inputs) are simulated
    exactly; without them the same data do not fit."""
    th, u, _, x0h, x0v, dt = windows
    rng = np.random.default_rng(11)
    W, L = u.shape[:2]
    f = rng.normal(0, 0.3, (W, L, 3))
    Ah, Bh, Av, Bv = build_matrices(th)
    Eh = np.zeros((8, 2))
    Eh[0, 0] = Eh[1, 1] = 1.0
    Ev = np.zeros((3, 1))
    Ev[0, 0] = 1.0
    Adh, Bdh = discretize(Ah, np.hstack([Bh, Eh]), dt)
    Adv, Bdv = discretize(Av, np.hstack([Bv, Ev]), dt)
    y = np.zeros((W, L, 8))
    for w in range(W):
        xh, xv = x0h[w].copy(), x0v[w].copy()
        for k in range(L):
            for s, o in HOR_OUT:
                y[w, k, o] = xh[s]
            for s, o in VER_OUT:
                y[w, k, o] = xv[s]
            xh = Adh @ xh + Bdh @ np.r_[u[w, k, :2], f[w, k, :2]]
            xv = Adv @ xv + Bdv @ np.r_[u[w, k, 2:], f[w, k, 2]]
    sim = WindowSimulator(u, y, dt, estimate_all_initial=True, ridge=1e-12, forcing=f)
    assert sim.sse(th[None])[0].max() < 1e-12
    assert np.abs(sim.simulate(th[None])[0] - y).max() < 1e-7
    trim = WindowSimulator(u, y, dt, estimate_all_initial=True, ridge=1e-12, forcing=f, estimate_trim=True)
    assert np.abs(trim.solve_trim(th[None])[1]).max() < 1e-7  # no offset to find
    plain = WindowSimulator(u, y, dt, estimate_all_initial=True, ridge=1e-12)
    assert plain.sse(th[None])[0].sum() > 1e3 * max(sim.sse(th[None])[0].sum(), 1e-12)


def test_kinematic_forcing_terms():
    from groundstation.sysid.simulate import kinematic_forcing

    trim = np.array([0.1, -0.2, 0.05, 0.0, 0.0, 0.0, 0.03, -0.02])
    y = np.zeros((2, 8))
    assert np.allclose(kinematic_forcing(y, trim), 0.0)  # nothing at the trim point
    y[1] = [1.0, 0.5, 0.2, 0.1, -0.2, 0.3, 0.0, 0.0]  # perturbations; attitude at trim
    f = kinematic_forcing(y, trim)[1]
    u, v, w, p, q, r = y[1, :6] + trim[:6]
    assert f[0] == pytest.approx(r * v - q * w)
    assert f[1] == pytest.approx(p * w - r * u)
    assert f[2] == pytest.approx(q * u - p * v)
    y2 = np.zeros(8)
    y2[6] = 0.2  # pitch 0.2 rad above trim: only the gravity remainders beyond eq. 8's -g theta
    f2 = kinematic_forcing(y2, np.zeros(8))
    assert f2[0] == pytest.approx(-9.81 * (np.sin(0.2) - 0.2))
    assert f2[2] == pytest.approx(9.81 * (np.cos(0.2) - 1.0))


@pytest.mark.parametrize(("est_all", "missing"), [(False, True), (True, True), (False, False), (True, False)])
def test_variable_projection_cost_equals_the_plain_cost_at_the_solved_b(windows, est_all, missing):
    """The projected cost of x is the plain cost of the completed parameters (B entries = their LS values),
    L not a multiple of the block; with a channel missing in one window, and with every channel in every
    window (the search's batched products and quadratic-form SSE)."""
    from groundstation.sysid.cost import LINEAR_B, WindowedCost, Windows

    th, u, y, _, _, dt = windows
    rng = np.random.default_rng(4)
    avail = np.ones((6, 8), bool)
    avail[2, 1] = not missing
    win = Windows(u, y + rng.normal(0, 0.01, y.shape), avail, np.zeros(6, int), np.zeros(6), dt)
    free = np.ones(31, dtype=bool)
    cv = WindowedCost(win, free, th, estimate_all_initial=est_all, varpro=True)
    plain = WindowedCost(win, free, th, estimate_all_initial=est_all)
    X = th[cv.free][None] * (1 + 0.05 * rng.normal(size=(4, cv.dim)))
    full = cv.complete(X)
    assert np.allclose(cv(X), plain(full), rtol=1e-9, atol=0)
    # and the projected entries really minimise the least-squares criterion (channel SSE / scale^2;
    # not eq. 11 itself): nudging one raises it
    from groundstation.sysid.model import PARAM_INDEX

    def wsse(t):
        return (plain.sim.sse(t) / plain.sim.scales[None] ** 2).sum(axis=1)

    for name in ("Z_col", "L_lat"):
        nudged = full.copy()
        nudged[:, PARAM_INDEX[name]] *= 1.01
        assert (wsse(nudged) > wsse(full)).all()
    assert len(LINEAR_B) == 11


@pytest.mark.parametrize(("est_all", "no_v"), [(False, False), (True, False), (True, True)])
def test_projected_sse_is_the_sum_of_the_explicit_errors(windows, est_all, no_v):
    """The search's SSE with projected B entries (channel weights applied after the products, the SSE
    as a quadratic form) equals the sum of the squared explicit errors: near the truth, at the truth on
    noise-free data (the form cancels there and the errors are computed explicitly) and, to their
    magnitude, for wild, mostly unstable candidates; also with a channel (v) missing in every window."""
    from groundstation.sysid.cost import LINEAR_B
    from groundstation.sysid.model import PARAM_INDEX, bounds_array

    th, u, y, _, _, dt = windows
    rng = np.random.default_rng(9)
    b = bounds_array()
    wild = b[:, 0] + rng.random((6, th.size)) * (b[:, 1] - b[:, 0])
    near = th * (1 + 0.05 * rng.normal(size=(4, th.size)))
    thetas = np.vstack([th, near, wild])
    linear = {0: (), 1: ()}
    for name, (sub, st, inp) in LINEAR_B.items():
        linear[sub] = linear[sub] + ((st, inp),)
        thetas[:, PARAM_INDEX[name]] = 0.0
    for noise in (0.0, 0.01):
        avail = np.ones(8, dtype=bool)
        avail[1] = not no_v
        sim = WindowSimulator(u, y + rng.normal(0, noise, y.shape), dt, avail, estimate_all_initial=est_all,
                              linear=linear)
        sse = sim.sse(thetas)
        ref = (sim.errors(thetas) ** 2).sum(axis=(1, 2))
        assert not sse[:, ~sim.mask.any(axis=0)].any()  # a channel in no window has no error
        sse, ref = sse[:, sim.mask.any(axis=0)], ref[:, sim.mask.any(axis=0)]
        if noise == 0.0:  # the quadratic form would keep no digit of these
            assert sse[0].sum() < 1e-6 * (y ** 2).sum()
            assert np.allclose(sse[0], ref[0], rtol=1e-6, atol=0)
            continue
        assert np.allclose(sse[:5], ref[:5], rtol=1e-9, atol=0)
        ok = ref < 1e200
        # unstable candidates: the least squares is ill-conditioned and either computation keeps only
        # a few digits of it (differences of either sign); the same magnitude
        assert np.allclose(np.log10(sse[ok]), np.log10(ref[ok]), rtol=0, atol=0.5)


@pytest.mark.parametrize("trim", [False, True])
def test_native_residuals_are_the_residuals_in_another_order(windows, trim):
    """The refinement's normal equations use the simulator's own row order: the same numbers."""
    from groundstation.sysid.cost import WindowedCost, Windows

    th, u, y, _, _, dt = windows
    rng = np.random.default_rng(5)
    avail = np.ones((6, 8), dtype=bool)
    avail[2, 0] = False  # a channel missing in one window stays out of both
    win = Windows(u, y + rng.normal(0, 0.01, y.shape), avail, np.zeros(6, dtype=int), np.arange(6.0), dt)
    for sub in ((0,), (1,)):
        cost = WindowedCost(win, np.ones(31, dtype=bool), th, subsystems=sub, estimate_trim=trim)
        X = th[None] * (1 + 0.02 * rng.normal(size=(3, 31)))
        sig = np.linspace(0.5, 2.0, 8)
        a = cost.residuals(X, sig).reshape(3, -1)
        b = cost.residuals_native(X, sig)
        assert np.allclose(np.sort(np.abs(a), axis=1)[:, -a.shape[1]:], np.sort(np.abs(b), axis=1)[:, -a.shape[1]:],
                           atol=1e-12)
        assert np.allclose((b ** 2).sum(axis=1), (a ** 2).sum(axis=1), rtol=1e-12)


@pytest.mark.parametrize("trim,holes", [(False, False), (True, False), (True, True)])
def test_one_simulation_gives_the_native_residuals_and_the_sse_bit_for_bit(windows, trim, holes):
    """The refinement takes a point's channel scales (its SSE) and its residuals from one simulation:
    exactly the numbers of the two separate calls, the residuals weighted again with other scales too."""
    from groundstation.sysid.cost import WindowedCost, Windows

    th, u, y, _, _, dt = windows
    rng = np.random.default_rng(7)
    measured = None
    if holes:
        measured = np.ones(y.shape, dtype=bool)
        measured[1, 20:31] = False
    win = Windows(u, y + rng.normal(0, 0.01, y.shape), np.ones((6, 8), dtype=bool), np.zeros(6, dtype=int),
                  np.arange(6.0), dt, measured)
    cost = WindowedCost(win, np.ones(31, dtype=bool), th, estimate_trim=trim)
    assert cost.sim.holes == holes
    X = th[None] * (1 + 0.02 * rng.normal(size=(2, 31)))
    errors, sse = cost.native_errors_and_sse(X)
    assert np.array_equal(sse, cost.sim.sse(cost.full(X)))
    for sig in (np.linspace(0.5, 2.0, 8), np.linspace(2.0, 0.5, 8)):
        assert np.array_equal(cost.sim.weigh_native(errors, sig), cost.residuals_native(X, sig))


def test_the_markov_cost_of_a_runaway_candidate_is_the_simulated_one(windows):
    """Candidates whose free response runs away over a window (a search's trial steps on a real flight
    without its aircraft file) get the lifted simulation's SSE, not a product form that has lost its
    digits: the two paths agree to 1e-7 on wild candidates (a few per cent apart before)."""
    from groundstation.sysid.cost import LINEAR_B
    from groundstation.sysid.model import PARAM_INDEX, bounds_array

    th, u, y, _, _, dt = windows
    rng = np.random.default_rng(11)
    b = bounds_array()
    thetas = b[:, 0] + rng.random((40, th.size)) * (b[:, 1] - b[:, 0])
    linear = {0: (), 1: ()}
    for name, (sub, st, inp) in LINEAR_B.items():
        linear[sub] = linear[sub] + ((st, inp),)
        thetas[:, PARAM_INDEX[name]] = 0.0
    sim = WindowSimulator(u, y + rng.normal(0, 0.01, y.shape), dt, np.ones(8, dtype=bool), linear=linear)
    by_markov = sim.sse(thetas)
    assert any(p.get("markov") is not None for p in sim._prep)
    for p in sim._prep:
        p["markov"] = None
    simulated = sim.sse(thetas)
    ok = np.isfinite(simulated) & (simulated < 1e200)
    assert ok.sum() > 20
    assert np.allclose(by_markov[ok], simulated[ok], rtol=1e-7, atol=0)
