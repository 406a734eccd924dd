"""Local refinement on the windowed output error (scipy least_squares) and Cramér-Rao standard errors.

The residual vector is ``(yhat - y) / sigma_ch`` over all windows (``sigma_ch`` the per-channel
noise scale, re-estimated from the residuals so the weighting approximates maximum likelihood);
the unmeasured initial states are nuisance parameters eliminated inside every evaluation by the
per-window least squares of :mod:`groundstation.sysid.simulate` (variable projection), so the
Jacobian already accounts for them. The Jacobian is a forward difference computed as one batched
simulation of D + 1 candidates.

Standard errors: ``cov = H^-1 M H^-1`` with ``H = J^T J`` and ``M`` the residual-colour correction of
Morelli & Klein (``sum_k R_ch(k) sum_i J_i^T J_{i+k}`` within windows, Bartlett-tapered lags), which
reduces to ``s^2 H^-1`` for white residuals. Smoothed data and model error make residuals coloured;
without the correction standard errors come out several times too small. Each parameter's reported
error is the larger of that and the window-clustered sandwich (``M = sum_w g_w g_w^T``, scores
``g_w = J_w^T r_w``, each window's corrected for its leverage: :func:`clustered_cov`): model error
that changes with flight condition (fast legs, near-ground hover) makes windows disagree, which only
the clustered form sees. On a simulated nonlinear flight this
took the worst |estimate - truth| / std from 5.0 to 3.2 (X_u, Y_v, Z_col were the ones hit).
On a lossy link, inputs left straight lines over the holes add their error's covariance to the
colour-corrected sandwich (:func:`coloured_cov`).
"""

from __future__ import annotations

import numpy as np

from groundstation.sysid.cost import WindowedCost
from groundstation.sysid.optimizers import OptimizeResult
from groundstation.sysid.settings import IdentifyConfig
from groundstation.sysid.simulate import objective_of_sse

#: residual bytes simulated per batch of perturbed candidates in the finite-difference Jacobians.
#: Small on purpose: the simulation's temporaries are a few times this, and temporaries of tens of
#: MB are fresh pages from the kernel at every Jacobian (on 4 simulated flights 16 MB batches made
#: 465 000 page faults and 1.9 s of system time in the Jacobians, 1 MB batches 40 000 and 0.1 s,
#: with less user time too: the batch stays in cache). The numbers do not depend on it.
JAC_CHUNK_BYTES = 1e6
#: the same for the refinement's normal equations (:func:`levenberg_marquardt`): without the transposed
#: 8-channel error arrays their temporaries are a fraction of these bytes, and with freed memory kept
#: for reuse (:func:`groundstation.parallel.keep_freed_memory`) batches of 4 MB made no page faults and
#: were 20-25 % faster than 1 MB (fewer, larger batched products; simulated and real TREX 550 flights)
NORMAL_CHUNK_BYTES = 4e6


def _fd_step(x: np.ndarray, span: np.ndarray) -> np.ndarray:
    return 1e-6 * np.maximum(np.abs(x), 1e-2 * span)


def refine(cost: WindowedCost, x0: np.ndarray, bounds: np.ndarray, *, passes: int = IdentifyConfig.refine_passes,
           max_nfev: int = IdentifyConfig.refine_max_nfev,
           with_std: bool = True, prior: tuple[np.ndarray, np.ndarray] | None = None,
           weighting: str = "noise", prior_colour: bool = False, ftol: float = 1e-10) -> OptimizeResult:
    """Levenberg-Marquardt-like trust-region refinement from ``x0`` (free parameters, (D,)).

    ``prior`` = (nominal (D,), std (D,)): output error with a priori weighting (Morelli & Klein
    ch. 7, a MAP fit): the residual vector gains the rows ``(x - nominal) / std``. The data rows
    count every logged sample (``prior_colour=False``): the prior holds the directions the flight
    carries no information on, and does not pull the ones it does. With ``prior_colour=True`` each
    channel's rows are weighted by its residual colour too (``sigma_ch sqrt(tau_ch)``, ``tau_ch``
    the integrated autocorrelation of the residual in samples), so a flight counts as the
    independent samples it holds; on real flights the residual colour is mostly model error, and
    that weighting let the prior pull parameters the flight does determine (the real TREX 550,
    5 contiguous folds: held-out mean 24 % against 28 % counting every sample). Either way the
    reported ``std`` is the posterior one, ``(I_data + diag(1/std^2))^-1`` with ``I_data`` the
    inverse of the colour-corrected data covariance, and ``prior_share`` (D,) how much of the
    parameter's information is the prior's.

    ``weighting``: "noise" weights each channel by its residual RMS (maximum likelihood when the residual
    is measurement noise); "signal" by the spread of the measured signal (the paper's eq. 11), with one
    common level from the residuals: when model error, not noise, makes the residual, ML weighting
    gives up the channels the model fits worst, and those are then not predicted at all.

    ``ftol``: each pass stops once an accepted step lowers its cost by less than this fraction
    (:func:`levenberg_marquardt`).

    Returns an OptimizeResult with ``x``, ``fun`` (eq. 11 cost), ``sigma`` (8,) channel noise
    scales, ``std`` (D,) standard errors, ``nfev`` (candidate evaluations) and ``jac`` (n_res, D).
    """
    b = np.asarray(bounds, dtype=float)
    lo, hi = b[:, 0], b[:, 1]
    span = hi - lo
    x = np.clip(np.asarray(x0, dtype=float), lo + 1e-9 * span, hi - 1e-9 * span)
    nfev0 = cost.nfev
    # one simulation gives each pass's start both its channel scales and its residuals
    errors, sse = cost.native_errors_and_sse(x[None])
    sse = sse[0]
    sigma = _sigma(cost, x, weighting, sse)
    pm, ps = (None, None) if prior is None else (np.asarray(prior[0], dtype=float), np.asarray(prior[1], dtype=float))
    res = None
    for _ in range(passes):
        sig = sigma
        if prior is not None and prior_colour:
            sig = sigma * np.sqrt(residual_tau(cost.residuals(x[None], sigma)[0], cost.used))

        res = levenberg_marquardt(cost, x, lo, hi, sig, max_nfev=max_nfev, prior=prior, ftol=ftol, start=(errors, sse))
        x, errors, sse = res.x, res.errors, res.sse
        sigma = _sigma(cost, x, weighting, sse)
    assert res is not None
    J = None
    std = np.full(x.size, np.nan)
    share = np.zeros(x.size)
    if with_std:
        J, std, share = standard_errors(cost, x, sigma, b, ps)
    F = float(objective_of_sse(cost.sim, sse[None])[0])   # eq. 11 from the scales' simulation: no second one
    map_cost = float(res.cost)
    nit = int(res.nfev)
    return OptimizeResult(x=x, fun=F, sigma=sigma, std=std, nfev=cost.nfev - nfev0, jac=J, success=bool(res.success),
                          message=str(res.message), nit=nit, prior_share=share, map_cost=map_cost,
                          sig_eff=sig)


def levenberg_marquardt(cost: WindowedCost, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, sig: np.ndarray, *,
                        max_nfev: int = IdentifyConfig.refine_max_nfev,
                        prior: tuple[np.ndarray, np.ndarray] | None = None,
                        ftol: float = 1e-10, xtol: float = 1e-10, gtol: float = 1e-10,
                        start: tuple[dict[int, np.ndarray], np.ndarray] | None = None) -> OptimizeResult:
    """Bounded Levenberg-Marquardt on the normal equations (as SIDPAC's ``oe.m``): minimises
    ``0.5 ||r(x)||^2`` with ``r`` the residuals ``(yhat - y) / sig_ch`` (plus the prior rows
    ``(x - nominal) / std``) from ``x0`` inside ``[lo, hi]``.

    Each iteration takes one forward-difference Jacobian (D + 1 candidates simulated as batches, in
    the simulator's own row order: only ``J^T J`` (D, D) and ``J^T r`` are formed, never an SVD of
    the tall Jacobian) and solves ``(J^T J + mu diag(J^T J)) dx = -J^T r`` on the parameters not held
    by a bound (Marquardt's scaling; ``mu`` by Nielsen's rule from the gain ratio). Trial points are
    clipped into the bounds; a parameter on its bound whose gradient pushes it outwards is held there
    for the step. ``max_nfev`` counts trial points (function evaluations, as scipy's
    ``least_squares``); stops when the relative decrease of the cost is below ``ftol``, the step
    below ``xtol`` relative to ``x`` or the scaled gradient below ``gtol``.
    ``start``: the unweighted output errors and per-channel sums of squared errors (8,) at ``x0``
    (:meth:`WindowedCost.native_errors_and_sse`), when already simulated.
    Returns an OptimizeResult with ``x``, ``cost`` (``0.5 ||r||^2``), ``nfev``, ``njev``, ``success``, and
    from the simulation of ``x``: ``errors`` (as ``start``) and ``sse`` (8,) (as :func:`_sse`).
    """
    span = hi - lo
    x = np.clip(np.asarray(x0, dtype=float), lo, hi)
    D = x.size
    pm = np.zeros(D) if prior is None else np.asarray(prior[0], dtype=float)
    pinfo = np.zeros(D) if prior is None else 1.0 / np.asarray(prior[1], dtype=float) ** 2  # prior information

    def objective(r: np.ndarray, xx: np.ndarray) -> float:
        d = xx - pm
        return 0.5 * (float(r @ r) + float(d @ (pinfo * d)))

    errors, sse = start if start is not None else cost.native_errors_and_sse(x[None])
    sse = np.asarray(sse).reshape(-1)
    r = cost.sim.weigh_native(errors, sig)[0]
    f = objective(r, x)
    nfev, njev, mu, nu = 1, 0, 1e-3, 2.0
    message, success = "maximum number of function evaluations reached", False
    A, g, dA = np.zeros((D, D)), np.zeros(D), np.ones(D)
    need_jac = True
    while nfev < max_nfev:
        if need_jac:
            h = _fd_step(x, span)
            h = np.where(x + h > hi, -h, h)  # step away from the bound we are close to
            A, g = _normal_equations(cost, x, h, sig, r)
            njev += 1
            need_jac = False
            A += np.diag(pinfo)
            g += pinfo * (x - pm)
            dA = np.maximum(np.diag(A).copy(), 1e-300)
            if np.max(np.abs(g) / np.sqrt(dA)) < gtol * max(np.sqrt(2 * f), 1e-300):
                message, success = "gradient below gtol", True
                break
        held = ((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0))
        fr = ~held
        step = np.zeros_like(x)
        if fr.any():
            Af = A[np.ix_(fr, fr)] + mu * np.diag(dA[fr])
            try:
                step[fr] = -np.linalg.solve(Af, g[fr])
            except np.linalg.LinAlgError:
                step[fr] = -g[fr] / (dA[fr] * (1.0 + mu))
        xn = np.clip(x + step, lo, hi)
        step = xn - x
        pred = -(g @ step + 0.5 * step @ A @ step)
        if not np.any(step) or np.linalg.norm(step) <= xtol * (xtol + np.linalg.norm(x)):
            message, success = "step below xtol", True
            break
        en, ssen = cost.native_errors_and_sse(xn[None])
        rn = cost.sim.weigh_native(en, sig)[0]
        nfev += 1
        fn = objective(rn, xn)
        rho = (f - fn) / pred if pred > 0 else -1.0
        if np.isfinite(fn) and fn < f:
            x, r, df, f, errors, sse = xn, rn, f - fn, fn, en, ssen[0]
            need_jac = True
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * min(rho, 1.0) - 1.0) ** 3)
            nu = 2.0
            if df <= ftol * f and rho > 0.25:
                message, success = "cost decrease below ftol", True
                break
        else:
            mu *= nu
            nu *= 2.0
            if mu > 1e16:
                message, success = "no decrease in any step", True
                break
    return OptimizeResult(x=x, cost=f, nfev=nfev, njev=njev, success=success, message=message, errors=errors, sse=sse)


def _normal_equations(cost: WindowedCost, x: np.ndarray, h: np.ndarray, sigma: np.ndarray,
                      r0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(J^T J (D, D), J^T r (D,))`` of the forward-difference Jacobian at ``x`` (steps ``h``, residuals
    ``r0`` at ``x``), the perturbed candidates simulated a few at a time (about :data:`NORMAL_CHUNK_BYTES`
    of residuals per batch) in the simulator's own row order, into the array kept on ``cost``."""
    D = x.size
    n_res = r0.size
    step = max(1, int(NORMAL_CHUNK_BYTES // (8 * n_res)))
    J = _jacobian_buffer(cost, D, n_res)
    for d0 in range(0, D, step):
        d1 = min(D, d0 + step)
        Rp = cost.residuals_native(x[None] + np.diag(h)[d0:d1], sigma)
        Jc = J[d0:d1]
        np.subtract(Rp, r0[None], out=Jc)   # straight into the kept array: no copy of the batch
        Jc /= h[d0:d1, None]
    return J @ J.T, J @ r0


def standard_errors(cost: WindowedCost, x: np.ndarray, sigma: np.ndarray, bounds: np.ndarray,
                    prior_std: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Jacobian (n_res, D), standard errors (D,), prior share (D,)) at a refinement's solution ``x``
    with its channel scales ``sigma`` (see the module docstring; posterior ones with ``prior_std``)."""
    b = np.asarray(bounds, dtype=float)
    J = jac_final(cost, x, sigma, b[:, 1] - b[:, 0], b[:, 1])
    holes = getattr(cost, "input_holes", None)   # inputs estimated in the link's holes: their share projected out
    if holes is not None:
        J = holes.marginal_jacobian(cost, x, sigma, J)
    r = cost.residuals(x[None], sigma)[0]
    counted = _counted(cost)
    lines = getattr(cost, "line_holes", None)    # inputs left straight lines in the link's holes
    extra = None if lines is None else lines.line_covariance(cost, x, sigma, J, np.linalg.pinv(J.T @ J))
    if prior_std is None and extra is None:
        return J, coloured_std(J, r, counted=counted), np.zeros(x.size)
    cov = coloured_cov(J, r, counted=counted, lines=extra)
    if prior_std is None:
        return J, np.sqrt(np.maximum(np.diag(cov), 0.0)), np.zeros(x.size)
    std, share = posterior_std(cov, np.asarray(prior_std, dtype=float))
    return J, std, share


def _counted(cost: WindowedCost) -> np.ndarray | None:
    """(W, L, n_used) samples the residuals count, where the link left holes (None: every sample)."""
    sim = getattr(cost, "sim", None)
    if sim is None or not getattr(sim, "holes", False):
        return None
    return np.asarray(sim.smask[..., cost.used], dtype=bool)


def with_standard_errors(cost: WindowedCost, res: OptimizeResult, bounds: np.ndarray,
                         prior: tuple[np.ndarray, np.ndarray] | None = None) -> OptimizeResult:
    """``res`` (a :func:`refine` run with ``with_std=False``) with ``jac``, ``std`` and ``prior_share``
    filled in: the standard errors of only the refinement that wins, not of every one compared."""
    if res.jac is None:
        res.jac, res.std, res.prior_share = standard_errors(cost, res.x, res.sigma, bounds,
                                                            None if prior is None else prior[1])
    return res


def map_objective(cost: WindowedCost, x: np.ndarray, sig_eff: np.ndarray,
                  prior: tuple[np.ndarray, np.ndarray] | None) -> float:
    """``0.5 ||r||^2`` of the a-priori-weighted residual at ``x`` with FIXED channel scales ``sig_eff``
    (8,): comparable between starts, unlike each refinement's own cost (whose scales follow its misfit)."""
    r = cost.residuals(np.asarray(x, dtype=float)[None], sig_eff)[0].ravel()
    J = float(r @ r)
    if prior is not None:
        d = (np.asarray(x, dtype=float) - prior[0]) / prior[1]
        J += float(d @ d)
    return 0.5 * J


def residual_tau(r: np.ndarray, used: np.ndarray, max_lag: int = 60) -> np.ndarray:
    """Integrated autocorrelation time (samples, >= 1) of each channel's residual within windows, (8,).

    r (W, L, n_used) residuals; channels not used get 1. Bartlett-tapered sum of the
    autocorrelation over lags 1..max_lag: the number of logged samples one independent sample is worth.
    """
    W, L, nch = r.shape
    K = min(max_lag, L - 1)
    r0 = (r * r).sum(axis=(0, 1))
    acc = np.zeros(nch)
    for k in range(1, K + 1):
        acc += (1.0 - k / (K + 1)) * (r[:, : L - k] * r[:, k:]).sum(axis=(0, 1))
    tau_used = np.clip(1.0 + 2.0 * acc / np.maximum(r0, 1e-300), 1.0, float(L))
    tau = np.ones(8)
    tau[np.flatnonzero(used)] = tau_used
    return tau


def posterior_std(cov_data: np.ndarray, prior_std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Posterior standard errors and the prior's share of the information per parameter.

    ``cov_data`` (D, D) the data-only covariance, ``prior_std`` (D,). Share = prior information /
    posterior information on the diagonal (0: the flight determines it, 1: only the prior does).
    """
    info_data = np.linalg.pinv(cov_data)
    info_prior = np.diag(1.0 / np.asarray(prior_std, dtype=float) ** 2)
    cov = np.linalg.pinv(info_data + info_prior)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    share = np.clip(std ** 2 / np.asarray(prior_std, dtype=float) ** 2, 0.0, 1.0)
    return std, share


def _sse(cost: WindowedCost, x: np.ndarray) -> np.ndarray:
    """Per-channel sum of squared output errors (8,) at ``x`` (one simulation)."""
    return cost.sim.sse(cost.full(x[None]))[0]


def _sigma(cost: WindowedCost, x: np.ndarray, weighting: str = "noise", sse: np.ndarray | None = None) -> np.ndarray:
    """Per-channel residual scale (8,); unused channels 1. "noise": the RMS of the output error over
    used samples; "signal": the channel's signal spread (eq. 11) times one common factor that makes
    the weighted residual RMS one. ``sse``: :func:`_sse` at ``x`` when already simulated."""
    sse = _sse(cost, x) if sse is None else sse
    n = cost.sim.smask.sum(axis=(0, 1))
    ok = n > 0
    if weighting == "signal":
        rel = cost.sim.scales / np.sqrt(np.maximum(n, 1))  # RMS of each channel's signal about its mean
        level = np.sqrt(np.sum(sse[ok] / rel[ok] ** 2) / max(float(n[ok].sum()), 1.0)) if ok.any() else 1.0
        s = rel * level
    else:
        s = np.sqrt(sse / np.maximum(n, 1))
    return np.where(ok & (s > 0), s, 1.0)


def jac_final(cost: WindowedCost, x: np.ndarray, sigma: np.ndarray, span: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Central-difference Jacobian (n_res, D) of the weighted residuals at ``x``."""
    return _fd_jacobian(cost, x, _fd_step(x, span) * 10.0, sigma, central=True)


def _fd_jacobian(cost: WindowedCost, x: np.ndarray, h: np.ndarray, sigma: np.ndarray, *,
                 central: bool, reuse: bool = False) -> np.ndarray:
    """Finite-difference Jacobian (n_res, D) of the weighted residuals, steps ``h`` (D,).

    The perturbed candidates are simulated a few at a time (about :data:`JAC_CHUNK_BYTES` of
    residuals per batch), so the temporaries of the simulation stay bounded however many windows
    the data hold: only the Jacobian itself grows with the data. Rows in the order of
    :meth:`WindowedCost.residuals` (window, sample, channel); the same numbers as one batch.
    ``reuse``: write into the array kept on ``cost`` (:func:`_jacobian_buffer`), overwritten by the
    next such call; for the Jacobians of the iterations, not for one that is kept.
    """
    D = x.size
    r0 = None if central else cost.residuals(x[None], sigma).reshape(-1)
    n_res = cost.sim.W * cost.sim.L * int(cost.used.sum())
    J = _jacobian_buffer(cost, D, n_res) if reuse else np.empty((D, n_res))
    step = max(1, int(JAC_CHUNK_BYTES // (8 * n_res * (2 if central else 1))))
    for d0 in range(0, D, step):
        d1 = min(D, d0 + step)
        Xp = x[None] + np.diag(h)[d0:d1]
        if central:
            X = np.vstack([Xp, x[None] - np.diag(h)[d0:d1]])
            R = cost.residuals(X, sigma).reshape(X.shape[0], -1)
            J[d0:d1] = (R[: d1 - d0] - R[d1 - d0:]) / (2 * h[d0:d1, None])
        else:
            R = cost.residuals(Xp, sigma).reshape(d1 - d0, -1)
            J[d0:d1] = (R - r0) / h[d0:d1, None]
    return J.T


def _jacobian_buffer(cost: WindowedCost, D: int, n_res: int) -> np.ndarray:
    """A (D, n_res) array kept on ``cost`` and reused by every Jacobian of the same shape.

    A refinement takes a Jacobian per iteration; with many windows it is tens of MB, and a fresh
    array each time is fresh pages from the kernel (page faults: system time that grew with the
    data). scipy's least_squares is done with a Jacobian when it asks for the next one; the Jacobian
    that is kept (:func:`jac_final`, the standard errors) gets its own array.
    """
    buf = getattr(cost, "_jac_buffer", None)
    if buf is None or buf.shape != (D, n_res):
        buf = np.empty((D, n_res))
        cost._jac_buffer = buf  # type: ignore[attr-defined]
    return buf


def coloured_cov(J: np.ndarray, r: np.ndarray, max_lag: int = 60, counted: np.ndarray | None = None,
                 lines: np.ndarray | None = None) -> np.ndarray:
    """Data covariance (D, D): the residual-colour-corrected sandwich with its diagonal raised to the
    window-clustered one where that is larger (the standard errors of :func:`coloured_std`).

    ``lines`` (D, D): what the straight lines over the link's holes add
    (:meth:`~groundstation.sysid.hole_inputs.WindowHoles.line_covariance`), added to the colour-corrected
    sandwich, which models the residual as stationary noise and so leaves it out. Not to the clustered
    one: its window scores already hold the part of the lines' error that shows in the residuals."""
    cov, s_col, s_max = _sandwiches(J, r, max_lag, counted)
    if lines is not None:
        cov = cov + lines
        s_col = np.sqrt(np.maximum(np.diag(cov), 0.0))
        s_max = np.maximum(s_max, s_col)
    scale = np.where(s_col > 0, s_max / np.maximum(s_col, 1e-300), 1.0)
    return cov * scale[:, None] * scale[None, :]


def coloured_std(J: np.ndarray, r: np.ndarray, max_lag: int = 60, counted: np.ndarray | None = None) -> np.ndarray:
    """Standard errors: max of the residual-colour-corrected and the window-clustered sandwich."""
    return _sandwiches(J, r, max_lag, counted)[2]


def lagged_products(Jt4: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``sum_k sum_c weights[k, c] (C_ck + C_ck^T)`` (lag 0 once), ``C_ck[d, e] = sum_w sum_t
    Jt4[d, w, t, c] Jt4[e, w, t + k, c]``: the lagged products of the Jacobian within windows (D, D).

    By FFT along time (zero-padded past ``L + K``, so no lag wraps round): every lag at once,
    where one product per lag cost ~0.25 s per horizontal refinement. Parameters: ``Jt4`` (D, W,
    L, nch); ``weights`` (K + 1, nch).
    """
    D, W, L, nch = Jt4.shape
    K = weights.shape[0] - 1
    n = 1 << int(np.ceil(np.log2(L + K)))
    S = np.zeros((nch, n // 2 + 1, D, D), dtype=complex)
    # windows in chunks of about 2 MB of spectra: ~16 MB of temporaries on a 150-s flight's
    # horizontal refinement (40 MB with 16-MB chunks), and no slower
    wstep = max(1, int(2e6 // (16 * (n // 2 + 1) * nch * D)))
    for w0 in range(0, W, wstep):
        F = np.fft.rfft(Jt4[:, w0:w0 + wstep], n=n, axis=2).transpose(3, 2, 0, 1)  # (nch, nf, D, Wc)
        S += np.conj(F) @ F.transpose(0, 1, 3, 2)
    C = np.fft.irfft(S, n=n, axis=1)[:, : K + 1]   # (nch, K + 1, D, D)
    T = np.einsum("kc,ckde->de", weights, C)
    return T + T.T - np.einsum("c,cde->de", weights[0], C[:, 0])


def _sandwiches(J: np.ndarray, r: np.ndarray, max_lag: int = 60,
                counted: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(colour-corrected covariance, its standard errors, max of those and the clustered ones).

    Parameters
    ----------
    J : (W*L*nch, D) Jacobian of the residuals, rows ordered (window, sample, channel)
    r : (W, L, nch) residuals at the solution (zero where not counted)
    counted : (W, L, nch) bool, samples counted (None: all): with holes of the link the residuals'
        autocovariance at each lag is the mean over the pairs of counted samples, not over all
        pairs (the lost samples' zeros would shrink it by the share lost, and the errors with it)
    """
    W, L, nch = r.shape
    D = J.shape[1]
    Jt = np.ascontiguousarray(J.T)  # (D, n_res): a view when J came from _fd_jacobian
    Jt4 = Jt.reshape(D, W, L, nch)
    H = Jt @ Jt.T
    Hinv = np.linalg.pinv(H)
    K = min(max_lag, L - 1)
    # per-channel autocovariance of residuals within windows, lags 0..K
    R = np.zeros((K + 1, nch))
    for k in range(K + 1):
        R[k] = (r[:, : L - k] * r[:, k:]).sum(axis=(0, 1)) / (W * L)
    if counted is not None:   # per lag: the mean over counted pairs, with the taper of the all-pairs mean
        m = counted.astype(float)
        pairs = np.array([(m[:, : L - k] * m[:, k:]).sum(axis=(0, 1)) for k in range(K + 1)])
        R *= np.where(pairs > 0, W * (L - np.arange(K + 1))[:, None] / np.maximum(pairs, 1.0), 0.0)
    M = lagged_products(Jt4, R * (1.0 - np.arange(K + 1) / (K + 1))[:, None])  # Bartlett taper: M stays PSD
    cov = Hinv @ M @ Hinv
    s_coloured = np.sqrt(np.maximum(np.diag(cov), 0.0))
    # window-clustered sandwich: windows that disagree (model error that differs between flight
    # conditions) widen it where the stationary colour model cannot
    s_cluster = np.sqrt(np.maximum(np.diag(clustered_cov(Jt.reshape(D, W, L * nch), r.reshape(W, L * nch))), 0.0))
    return cov, s_coloured, np.maximum(s_coloured, s_cluster)


def clustered_cov(Jw: np.ndarray, rw: np.ndarray) -> np.ndarray:
    """Window-clustered sandwich covariance (D, D) with each window's leverage corrected (CR2).

    Per-window scores ``g_w = J_w^T r_w``; the fit bends towards each window by its leverage, so a
    window's own residuals understate its errors, most where a few windows carry a parameter (one
    channel's doublets in a few windows). CR2 (Bell & McCaffrey 2002) scores each window with
    ``(I - J_w H^-1 J_w^T)^(-1/2) r_w``, which makes the sandwich unbiased for independent errors,
    ``H^-1 sum_w g~_w g~_w^T H^-1``. In D x D terms, ``g~_w = H^(1/2) (I - P_w)^(-1/2) H^(-1/2) g_w``
    with ``P_w = H^(-1/2) J_w^T J_w H^(-1/2)``. The plain form (``W / (W - 1) sum g_w g_w^T``) left
    the 25-Hz radio flight's key-parameter errors at 1.24 of their standard errors (rms over 8
    flights, 6 window layouts each); with the correction 1.06.

    Parameters
    ----------
    Jw : (D, W, n) Jacobian rows of each window
    rw : (W, n) residuals of each window
    """
    D, W, _ = Jw.shape
    g = np.einsum("dwk,wk->wd", Jw, rw)
    Hw = np.einsum("dwk,ewk->wde", Jw, Jw)
    ev, V = np.linalg.eigh(Hw.sum(axis=0))
    ok = ev > ev.max(initial=0.0) * 1e-12
    root = np.where(ok, np.sqrt(np.where(ok, ev, 1.0)), 0.0)
    Hh = (V * root) @ V.T                                        # H^(1/2)
    Hmh = (V * np.where(ok, 1.0 / np.where(ok, root, 1.0), 0.0)) @ V.T   # H^(-1/2), pseudo-inverse
    P = Hmh @ Hw @ Hmh                                           # (W, D, D) each window's leverage
    lev, U = np.linalg.eigh(P)
    # a direction one window alone determines (leverage 1: a single window, or a parameter only it
    # excites) leaves that window's residual nothing to show: no clustered information there (the
    # colour-corrected errors stand), rather than the optimiser's leftover gradient blown up
    alone = lev > 1.0 - 1e-6
    f = np.where(alone, 0.0, 1.0 / np.sqrt(1.0 - np.where(alone, 0.0, np.clip(lev, 0.0, 1.0))))
    adj = np.einsum("wde,we,wfe->wdf", U, f, U)                  # (I - P_w)^(-1/2)
    gt = np.einsum("wde,we->wd", adj, g @ Hmh) @ Hh
    Hinv = Hmh @ Hmh
    return Hinv @ (gt.T @ gt) @ Hinv
