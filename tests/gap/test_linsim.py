"""The windowed simulator reproduces the exact discrete model and its initial-state fit is right."""

import numpy as np

from groundstation.gap.evaluate import Evaluator, SegmentArrays
from groundstation.gap.linsim import OUT_STATE, full_matrices, simulate
from groundstation.sysid.model import PARAM_NAMES, discretize


def _noise_free(paper_theta, n=300, dt=0.02, seed=1):
    rng = np.random.default_rng(seed)
    A, B = full_matrices(paper_theta)
    Ad, Bd = discretize(A, B, dt)
    u = 0.05 * rng.standard_normal((n, 4))
    x = 0.01 * rng.standard_normal(11)
    y = np.zeros((n, 8))
    for k in range(n):
        y[k] = x[OUT_STATE]
        x = Ad[0] @ x + Bd[0][:, :4] @ u[k]
    return u, y


def test_simulation_recovers_noise_free_trajectory_including_unmeasured_states(paper_theta):
    u, y = _noise_free(paper_theta)
    yhat = simulate(paper_theta, u[None], y[None], 0.02, all_initial=False)
    assert yhat.shape == (1, 1, 300, 8)
    # a_s, b_s, r_fb start non-zero and are recovered by the least squares
    np.testing.assert_allclose(yhat[0, 0], y, atol=1e-6 * np.abs(y).max())


def test_wrong_parameters_do_not_fit(paper_theta):
    u, y = _noise_free(paper_theta)
    th = paper_theta.copy()
    th[0] += 0.5
    yhat = simulate(th, u[None], y[None], 0.02)
    assert np.abs(yhat[0, 0] - y).max() > 1e-3


def test_heldout_scoring_and_refine(paper_theta, flight_factory):
    prep = flight_factory(T_s=60.0, seed=2)
    s = prep.segments[0]
    seg = SegmentArrays(s.t_s, s.inputs, s.outputs, s.outputs_raw, s.alt_m)
    ev = Evaluator([seg], 0.02, paper_theta, np.ones(8, bool))
    sse, train, coef = ev.heldout(ev.r0)
    assert sse.shape == (ev.W, 8) and coef.shape == (3, 0)
    # the batched re-fit of several variants is the one-by-one re-fit
    rs = ev.r0[None] * np.array([1.0, 0.5, 2.0])[:, None, None, None] + 0.01 * np.arange(3)[:, None, None, None]
    s_all, t_all, b_all = ev.heldout_many(rs, chunk_bytes=2 * rs[0].nbytes)
    for v in range(3):
        s1, t1, _ = ev.heldout(rs[v])
        np.testing.assert_allclose(s_all[v], s1, rtol=1e-9)
        np.testing.assert_allclose(t_all[v], t1, rtol=1e-9)
        np.testing.assert_allclose(b_all[v], ev.last_blocks, rtol=1e-9)
    # a model 20 % off in every parameter is clearly worse than the truth ...
    ev2 = Evaluator([seg], 0.02, paper_theta * 1.2, np.ones(8, bool))
    assert (ev2.r0 ** 2).sum() > 1.5 * (ev.r0 ** 2).sum()
    # ... and the Levenberg-Marquardt polish brings it back to the truth's cost
    ev2.refine(10)
    assert (ev2.r0 ** 2).sum() < 1.05 * (ev.r0 ** 2).sum()


def _stepped(theta, inputs, outputs, dt, forcing=None, weights=None, available=None, nuisance=None,
             start=0, fit_initial=True, nuisance_prec=None):
    """The plain reference: step x[k+1] = Ad x[k] + Bd u[k] sample by sample, then the same
    per-window weighted least squares of the initial states (and nuisance), one solve per window."""
    th = np.atleast_2d(theta)
    C, (W, L, _) = th.shape[0], inputs.shape
    avail = np.ones(8, bool) if available is None else available
    w8 = np.where(avail, np.ones(8) if weights is None else weights, 0.0)
    A, B = full_matrices(th)
    Ad, Bd = discretize(A, B, dt)
    u = inputs if forcing is None else np.concatenate([inputs, forcing], axis=2)
    unknown = [6, 7, 10] + [int(OUT_STATE[c]) for c in range(8)]
    x = np.zeros((C, W, 11))
    x[:, :, OUT_STATE[avail]] = outputs[None, :, 0, avail]
    e = np.zeros((C, len(unknown), 11))
    e[:, np.arange(len(unknown)), unknown] = 1.0
    ys, fs = np.empty((C, W, L, 11)), np.empty((C, len(unknown), L, 11))
    with np.errstate(all="ignore"):
        for k in range(L):
            ys[:, :, k], fs[:, :, k] = x, e
            x = np.einsum("cij,cwj->cwi", Ad, x) + np.einsum("cij,wj->cwi", Bd[:, :, :u.shape[2]], u[:, k])
            e = np.einsum("cij,cuj->cui", Ad, e)
        bad = ~(np.isfinite(ys).all(axis=(1, 2, 3)) & np.isfinite(fs).all(axis=(1, 2, 3))
                & (np.abs(ys).max(axis=(1, 2, 3)) < 1e150))
    ys[bad], fs[bad] = 0.0, 0.0
    yhat = ys[..., OUT_STATE]
    if fit_initial:
        S = fs[..., OUT_STATE]  # (C, nu, L, 8)
        K = 0 if nuisance is None else nuisance.shape[-1]
        for c in range(C):
            for w in range(W):
                cols = [S[c, j, start:] for j in range(len(unknown))]
                cols += [nuisance[w, start:, :, j] for j in range(K)]
                M = np.stack([(col * w8).ravel() for col in cols], axis=1)
                r = ((outputs[w] - yhat[c, w])[start:] * w8).ravel()
                G = M.T @ M
                G += (1e-9 * np.trace(G) / G.shape[0] + 1e-12) * np.eye(G.shape[0])
                if K and nuisance_prec is not None:
                    G[len(unknown):, len(unknown):] += np.diag(nuisance_prec)
                a = np.linalg.solve(G, M.T @ r)
                yhat[c, w] += np.einsum("i,ilk->lk", a[:len(unknown)], S[c])
                if K:
                    yhat[c, w] += nuisance[w] @ a[len(unknown):]
    yhat[bad] = np.nan
    return yhat


def test_lifted_simulation_is_the_stepped_one_stable_and_unstable(paper_theta):
    """The lifted, window-chunked simulation gives the sample-by-sample numbers to round-off, for
    stable and unstable parameter vectors, with forcing, nuisance columns and unavailable channels;
    a candidate that runs away is NaN, without overflow warnings."""
    import warnings

    from groundstation.gap import linsim

    rng = np.random.default_rng(7)
    W, L = 7, 37  # L not a multiple of the lifting block
    th = paper_theta[None] * (1 + 0.3 * rng.standard_normal((5, paper_theta.size)))
    th[1] = paper_theta
    names = list(PARAM_NAMES)
    th[2, [names.index("X_u"), names.index("Z_w")]] = 3.0  # unstable: grows, stays finite
    th[3] = paper_theta
    th[3, names.index("X_u")] = 3e3  # violently unstable: overflows within the window
    inputs = 0.05 * rng.standard_normal((W, L, 4))
    outputs = 0.1 * rng.standard_normal((W, L, 8))
    avail = np.array([1, 1, 1, 1, 1, 0, 1, 1], bool)
    forcing = 0.01 * rng.standard_normal((W, L, 11))
    nuis = rng.standard_normal((W, L, 8, 2))
    cases = [dict(), dict(available=avail, weights=rng.uniform(0.5, 2.0, 8), start=5),
             dict(forcing=forcing), dict(nuisance=nuis, nuisance_prec=np.array([0.1, 1.0])),
             dict(forcing=forcing, fit_initial=False)]
    old = linsim.CHUNK_BYTES
    try:
        for chunk in (old, 8 * 5 * L * 8 * 3):  # one chunk of windows, and chunks of 3 windows
            linsim.CHUNK_BYTES = chunk
            for kw in cases:
                with warnings.catch_warnings():
                    warnings.simplefilter("error")
                    got = simulate(th, inputs, outputs, 0.02, **kw)
                want = _stepped(th, inputs, outputs, 0.02, **kw)
                assert np.isnan(got[3]).all() and np.isfinite(np.delete(got, 3, axis=0)).all()
                np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
                ok = np.isfinite(want)
                scale = np.abs(want[ok]).max()
                np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-9 * scale)
        # input variants of the same windows: the outputs given once stand for every repetition
        u2 = np.concatenate([inputs, 1.5 * inputs])
        np.testing.assert_array_equal(simulate(th, u2, outputs, 0.02),
                                      simulate(th, u2, np.concatenate([outputs, outputs]), 0.02))
        # nuisance columns the same in every window, given once: the per-window fit's numbers, also
        # when the initial states are fitted on a mask of samples
        ok = np.arange(5) != 3
        mask = (np.arange(L) // 4) % 2 == 0
        for kw in (dict(), dict(fit_mask=mask)):
            one = simulate(th, inputs, outputs, 0.02, nuisance=nuis[:1], nuisance_prec=np.array([0.1, 1.0]),
                           return_coef=True, **kw)
            every = simulate(th, inputs, outputs, 0.02, nuisance=np.repeat(nuis[:1], W, axis=0),
                             nuisance_prec=np.array([0.1, 1.0]), return_coef=True, **kw)
            for a, b in zip(one, every, strict=True):
                np.testing.assert_allclose(a[ok], b[ok], rtol=0, atol=1e-10 * np.abs(b[ok]).max())
    finally:
        linsim.CHUNK_BYTES = old


def test_a_block_is_its_subsystem_of_the_joint_simulation_and_the_jacobian_by_blocks_the_joint_one(
        paper_theta, flight_factory):
    """Each subsystem simulated alone gives the joint simulation's outputs of that subsystem (its
    initial states' ridge taken relative to both blocks: to round-off); the evaluator's Jacobian,
    simulated block by block, is the finite-difference Jacobian of one joint batch to its round-off
    (the other block's entries exactly zero)."""
    from groundstation.gap.linsim import HORIZONTAL, PARAM_BLOCKS, VERTICAL

    rng = np.random.default_rng(3)
    W, L = 5, 43
    th = paper_theta[None] * (1 + 0.1 * rng.standard_normal((3, paper_theta.size)))
    inputs, outputs = 0.05 * rng.standard_normal((W, L, 4)), 0.1 * rng.standard_normal((W, L, 8))
    avail = np.array([1, 1, 1, 1, 1, 0, 1, 1], bool)
    for kw in (dict(), dict(available=avail, weights=rng.uniform(0.5, 2.0, 8), start=5)):
        gram: dict = {}
        joint = simulate(th, inputs, outputs, 0.02, gram=gram, **kw)
        for block, other in ((HORIZONTAL, VERTICAL), (VERTICAL, HORIZONTAL)):
            theirs = [j for j, st in enumerate(gram["unknown"]) if st in other.states]
            for c in range(3):
                got = simulate(th[c], inputs, outputs, 0.02, block=block,
                               ridge_extra=(float(gram["diag"][c, theirs].sum()), len(theirs)), **kw)
                want = joint[c:c + 1][..., list(block.outputs)]
                np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
    assert sorted(np.concatenate(PARAM_BLOCKS).tolist()) == list(range(paper_theta.size))

    prep = flight_factory(T_s=60.0, seed=2)
    s = prep.segments[0]
    ev = Evaluator([SegmentArrays(s.t_s, s.inputs, s.outputs, s.outputs_raw, s.alt_m)], 0.02, paper_theta * 1.05,
                   np.ones(8, bool))
    h = 1e-4 * np.maximum(np.abs(ev.theta0), 1e-2)
    r = ev.residual(ev.simulate(np.vstack([ev.theta0[None], ev.theta0[None] + np.diag(h)])))
    J = np.moveaxis((r[1:] - r[0]) / h[:, None, None, None], 0, -1)
    # one candidate or a batch of 32: the batched products round differently, through the initial-state fit
    np.testing.assert_allclose(ev.r0, r[0], rtol=0, atol=1e-8 * np.abs(r[0]).max())
    # the differences of two simulations 1e-4 apart carry their round-off amplified 1e4 times (and
    # more through the initial-state fit): two batch sizes of the joint simulation differ by up to 1e-5
    scale = np.abs(J).max(axis=(0, 1, 2))
    got = ev.Jn.reshape(J.shape) * ev.col
    assert (np.abs(got - J).max(axis=(0, 1, 2)) < 1e-3 * scale).all()
    hor = list(HORIZONTAL.outputs)
    assert not got[:, :, hor][..., PARAM_BLOCKS[1]].any()
    # the normal matrices formed from the blocks are those of the whole Jacobian
    Jf = got.reshape(ev.W, -1, paper_theta.size)
    np.testing.assert_allclose(ev.col, np.sqrt((Jf ** 2).sum(axis=(0, 1))), rtol=1e-12)
    np.testing.assert_allclose(ev.JtJ, np.matmul(np.swapaxes(ev.Jn, 1, 2), ev.Jn), rtol=0, atol=1e-12)
    # nuisance columns the same in every window on the horizontal outputs only (the air-mass scan's):
    # the vertical block is simulated without them, its ridge relative to them too
    nuis = rng.standard_normal((1, ev.L, 8, 2))
    nuis[..., list(VERTICAL.outputs), :] = 0.0
    ev.nuisance, ev.nuisance_prec = nuis, np.array([0.1, 1.0])
    ev.set_theta(ev.theta0)
    r = ev.residual(ev.simulate(np.vstack([ev.theta0[None], ev.theta0[None] + np.diag(h)])))
    J = np.moveaxis((r[1:] - r[0]) / h[:, None, None, None], 0, -1)
    np.testing.assert_allclose(ev.r0, r[0], rtol=0, atol=1e-8 * np.abs(r[0]).max())
    scale = np.abs(J).max(axis=(0, 1, 2))
    got = ev.Jn.reshape(J.shape) * ev.col
    assert (np.abs(got - J).max(axis=(0, 1, 2)) < 1e-3 * scale).all()
    assert not got[:, :, hor][..., PARAM_BLOCKS[1]].any()
