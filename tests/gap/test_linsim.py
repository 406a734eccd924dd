"""The windowed simulator reproduces the exact discrete model and its initial-state fit is right."""

import numpy as np

from groundstation.gap.evaluate import Evaluator, SegmentArrays
from groundstation.gap.linsim import OUT_STATE, full_matrices, simulate
from groundstation.sysid.model import discretize


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
    # a model 20 % off in every parameter is clearly worse than the truth ...
    ev2 = Evaluator([seg], 0.02, paper_theta * 1.2, np.ones(8, bool))
    assert (ev2.r0 ** 2).sum() > 1.5 * (ev.r0 ** 2).sum()
    # ... and the Levenberg-Marquardt polish brings it back to the truth's cost
    ev2.refine(10)
    assert (ev2.r0 ** 2).sum() < 1.05 * (ev.r0 ** 2).sum()
