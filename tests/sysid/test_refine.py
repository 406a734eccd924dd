"""The refinement's Levenberg-Marquardt against scipy's least squares on the same windowed cost."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from benchkit.synthetic import EXAMPLE_TRUTH, simulate_flight
from groundstation.sysid.cost import WindowedCost, Windows
from groundstation.sysid.model import PARAM_INDEX, VER_PARAMS, bounds_array, theta_from_dict
from groundstation.sysid.refine import levenberg_marquardt, refine


def _cost():
    th = theta_from_dict(EXAMPLE_TRUTH)
    u, _, ym = simulate_flight(th, 40.0, 0.02, seed=4)
    L = 150
    W = u.shape[0] // L
    win = Windows(u[: W * L].reshape(W, L, 4), ym[: W * L].reshape(W, L, 8), np.ones((W, 8), dtype=bool),
                  np.zeros(W, dtype=int), np.arange(W) * 3.0, 0.02)
    free = np.zeros(31, dtype=bool)
    free[[PARAM_INDEX[p] for p in VER_PARAMS]] = True
    return WindowedCost(win, free, th, subsystems=(1,)), th, free


def test_levenberg_marquardt_reaches_the_least_squares_optimum():
    cost, th, free = _cost()
    b = bounds_array()[free]
    x0 = np.clip(th[free] * 1.3, b[:, 0], b[:, 1])
    sig = np.ones(8)
    lm = levenberg_marquardt(cost, x0, b[:, 0], b[:, 1], sig, max_nfev=100)
    ref = least_squares(lambda x: cost.residuals(x[None], sig).ravel(), x0, bounds=(b[:, 0], b[:, 1]),
                        method="trf", x_scale="jac", ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=200)
    assert lm.cost <= ref.cost * (1 + 1e-9)
    assert np.allclose(lm.x, ref.x, rtol=1e-4, atol=1e-8)


def test_a_parameter_held_by_its_bound_stays_on_it():
    cost, th, free = _cost()
    b = bounds_array()[free].copy()
    i = VER_PARAMS.index("N_r")
    b[i] = (0.5 * th[PARAM_INDEX["N_r"]], 0.4 * th[PARAM_INDEX["N_r"]])  # N_r < 0: a range that excludes the truth
    b[i] = np.sort(b[i])
    x0 = np.clip(th[free], b[:, 0], b[:, 1])
    res = refine(cost, x0, b, passes=1, max_nfev=40, with_std=False)
    assert b[i, 0] <= res.x[i] <= b[i, 1]
    assert min(abs(res.x[i] - b[i, 0]), abs(res.x[i] - b[i, 1])) < 1e-9 * abs(b[i, 1] - b[i, 0]) + 1e-12


def test_the_refined_cost_and_scales_are_those_of_the_solution():
    """``fun`` and ``sigma`` come from one simulation at the solution: the eq. 11 cost exactly as the
    cost function gives it there, and the residual RMS per channel."""
    cost, th, free = _cost()
    b = bounds_array()[free]
    res = refine(cost, np.clip(th[free] * 1.2, b[:, 0], b[:, 1]), b, passes=2, max_nfev=20, with_std=False)
    assert res.fun == float(cost(res.x[None])[0])
    e = cost.residuals(res.x[None], np.ones(8))[0]
    used = np.flatnonzero(cost.used)
    np.testing.assert_allclose(res.sigma[used], np.sqrt((e ** 2).mean(axis=(0, 1))), rtol=1e-12)


def test_a_refinement_simulates_each_of_its_points_once():
    """The start's channel scales and residuals, each pass's next start and the solution's scales come
    from the simulations the refinement counts as evaluations: no single point is simulated twice."""
    cost, th, free = _cost()
    b = bounds_array()[free]
    run, singles = cost.sim._run, []

    def counting_run(theta, **kw):
        if np.atleast_2d(theta).shape[0] == 1:
            singles.append(np.array(theta, dtype=float).tobytes())
        return run(theta, **kw)

    cost.sim._run = counting_run
    nfev0 = cost.nfev
    res = refine(cost, np.clip(th[free] * 1.2, b[:, 0], b[:, 1]), b, passes=2, max_nfev=20, with_std=False)
    assert len(singles) == len(set(singles))
    jacobians = (cost.nfev - nfev0 - len(singles)) / free.sum()
    assert jacobians >= 2 and jacobians == int(jacobians)   # every other evaluation is in a Jacobian's batch
    assert res.fun == float(cost(res.x[None])[0])


def test_a_fold_refit_tolerance_stops_a_start_near_the_optimum_only():
    cost, th, free = _cost()
    b = bounds_array()[free]
    kw = dict(passes=1, max_nfev=6, with_std=False)
    full = refine(cost, th[free], b, **kw, ftol=1e-10)
    opt = full.x
    near = np.clip(opt * 1.001, b[:, 0], b[:, 1])
    loose, tight = refine(cost, near, b, **kw, ftol=1e-4), refine(cost, near, b, **kw, ftol=1e-10)
    assert loose.nfev < tight.nfev and loose.message == "cost decrease below ftol"
    assert abs(loose.fun - tight.fun) <= 1e-4 * tight.fun
    far = np.clip(th[free] * 1.3, b[:, 0], b[:, 1])   # every step gains more than the tolerance: the same run
    np.testing.assert_array_equal(refine(cost, far, b, **kw, ftol=1e-4).x, refine(cost, far, b, **kw, ftol=1e-10).x)


def test_stage_timer_charges_the_innermost_stage_and_restores_the_functions(monkeypatch):
    """``bench identify --profile``: CPU goes to the stage running, every reference is put back."""
    import groundstation.bench.identify as bench
    import groundstation.parallel as parallel
    import groundstation.sysid.identify as ident

    original = parallel.serial_map
    monkeypatch.setattr(bench, "STAGES", (("mapping", "groundstation.parallel", "serial_map"),))

    def busy(n):
        return float(np.linalg.norm(np.random.default_rng(n).normal(size=(200, 200)) @ np.ones(200)))

    with bench.StageTimer() as st:
        assert ident.serial_map is not original   # wrapped where identify holds it too
        out = ident.serial_map(busy, range(20))
    assert len(out) == 20
    assert parallel.serial_map is original and ident.serial_map is original
    table = {name: (cpu, calls) for name, cpu, calls in st.table()}
    assert table["mapping"][1] == 1 and table["mapping"][0] > 0


_ORPHAN = """
import subprocess, sys
busy = "import time\\nwhile time.process_time() < 0.4: pass"
subprocess.Popen([sys.executable, "-c", busy])   # not waited for: an orphan once this process exits
"""


def test_command_cpu_counts_the_processes_the_command_leaves_behind():
    """``bench identify --profile``'s whole-command CPU: a process the command started and did not wait
    for (as a fork server's workers) still counts, on Linux, where it is adopted and reaped; this
    process's own children (a fork server of earlier tests) neither count nor hold it up."""
    import sys

    from groundstation.bench.identify import command_cpu

    wall, cpu, rc = command_cpu([sys.executable, "-c", _ORPHAN])
    assert rc == 0 and wall > 0
    if sys.platform == "linux":
        assert cpu >= 0.4


def test_lagged_products_by_fft_are_the_sum_over_lags():
    """The colour-corrected sandwich's lagged Jacobian products, all lags at once by FFT, against the
    plain sum over lags (windows of a length that is no power of two; coloured columns)."""
    from groundstation.sysid.refine import lagged_products

    rng = np.random.default_rng(3)
    D, W, L, nch, K = 4, 5, 37, 3, 20
    Jt4 = np.cumsum(rng.standard_normal((D, W, L, nch)), axis=2)
    wts = rng.standard_normal((K + 1, nch))
    M = np.zeros((D, D))
    for k in range(K + 1):
        P = np.einsum("dwtc,ewtc,c->de", Jt4[:, :, : L - k], Jt4[:, :, k:], wts[k])
        M += P if k == 0 else P + P.T
    got = lagged_products(Jt4, wts)
    assert np.allclose(got, M, rtol=1e-12, atol=1e-12 * np.abs(M).max())
    assert np.allclose(got, got.T)


def test_standard_errors_with_holes_count_only_the_measured_pairs():
    """White residuals of unit variance with a quarter of the samples lost in bursts: the colour-corrected
    standard errors match the least-squares ones, sqrt(diag((J^T J)^-1)). Averaging the residual
    autocovariance over every sample, lost ones as zeros, made them sqrt(1 - share lost) too small."""
    from groundstation.sysid.refine import _sandwiches

    rng = np.random.default_rng(3)
    W, L, D = 60, 150, 3
    t = np.arange(L) * 0.02
    J = np.stack([np.sin(2 * np.pi * f * t + rng.uniform(0, 6, (W, 1))) for f in (0.4, 1.1, 2.3)], axis=-1)
    r = rng.standard_normal((W, L))
    lost = np.zeros((W, L), dtype=bool)
    for w in range(W):          # bursts of 5-15 samples, about a quarter of each window
        for s0 in rng.choice(L - 15, 4, replace=False):
            lost[w, s0:s0 + int(rng.integers(5, 16))] = True
    J[lost], r[lost] = 0.0, 0.0
    ref = np.sqrt(np.diag(np.linalg.inv(J.reshape(-1, D).T @ J.reshape(-1, D))))
    counted = ~lost[..., None]
    with_mask = _sandwiches(J.reshape(-1, D), r[..., None], counted=counted)[1] / ref
    without = _sandwiches(J.reshape(-1, D), r[..., None])[1] / ref
    share = lost.mean()
    assert share > 0.2
    assert np.all(np.abs(with_mask - 1.0) < 0.08), with_mask
    assert np.all(np.abs(without - np.sqrt(1.0 - share)) < 0.05) and np.all(without < 0.9), (without, share)


def test_the_cost_tells_the_standard_errors_which_samples_it_counts():
    from groundstation.sysid.refine import _counted

    cost, th, free = _cost()
    assert _counted(cost) is None
    win = cost.windows
    measured = np.ones(win.outputs.shape, dtype=bool)
    measured[:, 40:55] = False
    holed = WindowedCost(Windows(win.inputs, win.outputs, win.available, win.segment, win.t0_s, win.dt_s,
                                 measured=measured), free, th, subsystems=(1,))
    c = _counted(holed)
    assert c is not None and c.shape == (win.outputs.shape[0], win.outputs.shape[1], int(holed.used.sum()))
    assert not c[:, 40:55].any() and c[:, :40].all()


def test_window_clustered_errors_correct_each_windows_leverage():
    """Independent unit errors, least squares over 8 windows, one parameter excited in only 2 of them:
    the leverage-corrected clustered variance (CR2) is unbiased for every parameter (mean over 2000
    noise draws against sigma^2 (J^T J)^-1), where the plain clustered form finds barely half the
    variance of the parameter the few windows carry (their own residuals absorb their errors)."""
    from groundstation.sysid.refine import clustered_cov

    rng = np.random.default_rng(5)
    D, W, n, reps = 3, 8, 20, 2000
    J = rng.standard_normal((W, n, D))
    J[:, :, 2] *= 0.05
    J[:2, :, 2] = rng.standard_normal((2, n))
    Jf = J.reshape(-1, D)
    Hi = np.linalg.inv(Jf.T @ Jf)
    Jw = np.ascontiguousarray(J.transpose(2, 0, 1))
    cr2, plain = np.zeros(D), np.zeros(D)
    for _ in range(reps):
        y = rng.standard_normal(W * n)
        r = (y - Jf @ (Hi @ (Jf.T @ y))).reshape(W, n)
        cr2 += np.diag(clustered_cov(Jw, r)) / reps
        g = np.einsum("dwk,wk->wd", Jw, r)
        plain += np.diag(Hi @ (g.T @ g) @ Hi) * W / (W - 1) / reps
    assert np.all(np.abs(cr2 / np.diag(Hi) - 1.0) < 0.06), cr2 / np.diag(Hi)
    assert plain[2] / Hi[2, 2] < 0.7, plain / np.diag(Hi)


def test_a_direction_one_window_alone_determines_keeps_the_colour_corrected_error():
    """One window (every direction its alone), the optimiser stopped a little short of the optimum: the
    clustered sandwich has nothing to say and gives 0, so the reported error is the colour-corrected
    one, not the leftover gradient blown up by the leverage correction."""
    from groundstation.sysid.refine import _sandwiches, clustered_cov

    rng = np.random.default_rng(2)
    L, D = 200, 2
    J = rng.standard_normal((L, D))
    y = rng.standard_normal(L)
    r = y - J @ np.linalg.lstsq(J, y, rcond=None)[0] + 1e-3 * rng.standard_normal(L)
    assert np.allclose(clustered_cov(np.ascontiguousarray(J.T[:, None, :]), r[None]), 0.0)
    _, s_col, s_max = _sandwiches(J, r.reshape(1, L, 1))
    assert np.all(s_col > 0) and np.array_equal(s_max, s_col)
