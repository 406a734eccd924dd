"""Hypothesis-library pieces the verdict relies on: input-effect variants re-applied exactly."""

import numpy as np
import pytest

from groundstation.gap.evaluate import SegmentArrays
from groundstation.gap.hypotheses import Hypothesis, apply_input_effect, backlash, deadzone, rate_limit, shift


def _segment(n=400, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.02
    u = np.cumsum(rng.standard_normal((n, 4)), axis=0) * 0.01
    return SegmentArrays(t_s=t, inputs=u, outputs=np.zeros((n, 8)), outputs_raw=np.zeros((n, 8)),
                         alt_m=np.full(n, np.nan))


@pytest.mark.parametrize("effect,label,fn", [
    ("input_delay", {"channel": 1, "delay_s": 0.06}, lambda x: shift(x, 3.0)),
    ("rate_limit", {"channel": 2, "rate_per_s": 0.5}, lambda x: rate_limit(x, np.array([0.01]))[:, 0]),
    ("deadband", {"channel": 0, "width": 0.02, "kind": "deadzone"}, lambda x: deadzone(x, 0.02)),
    ("deadband", {"channel": 3, "width": 0.02, "kind": "backlash"}, lambda x: backlash(x, 0.02)),
    ("deadband", {"channel": 2, "width": 0.03, "kind": "deadzone", "centre": -0.015},
     lambda x: deadzone(x, 0.03, -0.015)),
])
def test_apply_input_effect_transforms_only_its_channel(effect, label, fn):
    seg = _segment()
    h = Hypothesis(effect, extra={"label": label})
    out = apply_input_effect(h, [seg], 0.02)[0]
    c = label["channel"]
    np.testing.assert_allclose(out.inputs[:, c], fn(seg.inputs[:, c]))
    others = [k for k in range(4) if k != c]
    np.testing.assert_array_equal(out.inputs[:, others], seg.inputs[:, others])
    assert not np.allclose(out.inputs[:, c], seg.inputs[:, c])  # the transform did something


def test_deadzone_off_the_trim_is_silent_around_its_centre_and_keeps_the_trim():
    """A band centred off the input trim (the pilot rested inside it, so the median input is not its
    centre): nothing within the half-width of the centre, the input less the half-width outside,
    and zero input still gives zero."""
    x = np.linspace(-0.2, 0.2, 401)
    y = deadzone(x, 0.08, -0.05)
    inside = np.abs(x + 0.05) <= 0.08
    assert np.all(y[inside] == 0.0) and np.all(y[~inside] != 0.0)
    np.testing.assert_allclose(y[x > 0.03], x[x > 0.03] - 0.03)
    np.testing.assert_allclose(y[x < -0.13], x[x < -0.13] + 0.13)
    assert deadzone(np.array([0.0]), 0.08, -0.05)[0] == 0.0


def test_apply_input_effect_rejects_other_effects():
    with pytest.raises(ValueError, match="not an input effect"):
        apply_input_effect(Hypothesis("gyro_bias", extra={"label": {"channel": 0}}), [_segment()], 0.02)


def test_air_mass_predicts_velocities_between_its_chunks_and_leaves_w_and_r_alone(flight_factory, paper_theta):
    """An air velocity fitted on alternate 0.5 s chunks predicts the horizontal velocities of the
    chunks between them on a gusty flight; w and r keep the base cost (no horizontal air reaches them)."""
    from groundstation.gap.diagnose import segments_from_prepared
    from groundstation.gap.evaluate import Evaluator
    from groundstation.gap.hypotheses import GUST_CHANNELS, Context, scan_wind_gust

    prep = flight_factory(T_s=60.0, seed=21, effect=("wind_gust", 2.0, 1.5))
    segs, avail = segments_from_prepared(prep)
    ev = Evaluator(segs, prep.dt_s, paper_theta, avail, window_s=3.0, folds=3)
    h = scan_wind_gust(Context(ev, segs), refine_iterations=0)
    base, alt = h.extra["base_sse"], h.sse
    rough = [c for c in range(8) if c not in GUST_CHANNELS]
    np.testing.assert_array_equal(alt[:, rough], base[:, rough])
    gain = 1 - alt.sum(0) / base.sum(0)
    assert gain[0] > 0.5 and gain[1] > 0.5, gain  # u, v
    assert gain[6] > 0.5 and gain[7] > 0.5, gain  # the attitude angles follow (speed-stability moments)
    # and on the same flight without gust there is nothing for it to predict
    clean = flight_factory(T_s=60.0, seed=21)
    segs0, _ = segments_from_prepared(clean)
    ev0 = Evaluator(segs0, prep.dt_s, paper_theta, avail, window_s=3.0, folds=3)
    h0 = scan_wind_gust(Context(ev0, segs0), refine_iterations=0)
    assert h0.sse.sum() > 0.97 * h0.extra["base_sse"].sum()


def test_fast_air_mass_is_followed_on_its_own_time_scale_and_credited_in_the_rates(flight_factory, paper_theta):
    """A Gauss-Markov air velocity of 0.3 s time scale (faster than a 1.5 s spline follows): the scan
    chooses the short time scale in every fold, and the rates it drives count as explained between
    the fitting chunks (held out), as u, v and the attitude angles do; w and r are not scored."""
    from groundstation.gap.diagnose import segments_from_prepared
    from groundstation.gap.evaluate import Evaluator
    from groundstation.gap.hypotheses import Context, scan_wind_gust

    prep = flight_factory(T_s=60.0, seed=21, effect=("wind_gust", 0.3, 1.5))
    segs, avail = segments_from_prepared(prep)
    ev = Evaluator(segs, prep.dt_s, paper_theta, avail, window_s=3.0, folds=3)
    h = scan_wind_gust(Context(ev, segs), refine_iterations=0)
    assert [tau for tau, _ in h.extra["variants"]] == [0.3, 0.3, 0.3]
    gain = 1 - h.sse.sum(0) / h.extra["base_sse"].sum(0)
    assert min(gain[[0, 1, 3, 4, 6, 7]]) > 0.3, gain  # u v p q theta phi
    assert gain[2] == 0 and gain[5] == 0, gain
    assert h.extra["air_knots"].shape == (ev.W, 2, 31)  # the air velocity on the 0.1 s grid of each 3 s window


def test_air_mass_least_squares_is_the_simulation_with_shared_nuisance_columns(flight_factory, paper_theta):
    """The air-mass protocol's own least squares (one normal matrix for every window, every prior in one
    solve) gives the numbers of :func:`linsim.simulate` with the same columns as shared nuisance."""
    from groundstation.gap import hypotheses as H
    from groundstation.gap.diagnose import segments_from_prepared
    from groundstation.gap.evaluate import Evaluator
    from groundstation.gap.linsim import simulate

    prep = flight_factory(T_s=18.0, seed=21, effect=("wind_gust", 0.5, 1.5))
    segs, avail = segments_from_prepared(prep)
    ev = Evaluator(segs, prep.dt_s, paper_theta, avail, window_s=3.0, folds=3)
    n = 31
    cols = H._air_columns(ev, paper_theta, n) @ np.kron(np.eye(2), H.gauss_markov_factor(n, (ev.L - 1) * ev.dt_s, 0.3))
    fit = H._ChunkFit(ev, paper_theta, 0.5)
    sse, coef = fit.cv(np.moveaxis(cols[0], -1, 0), [0.5, 2.0])
    for j, prec in enumerate((0.5, 2.0)):
        ref = np.zeros((ev.W, 8))
        for fit_m, score_m in zip(*[[h[k] for h in fit.halves] for k in (0, 1)], strict=True):
            fm = np.zeros(ev.L, bool)
            fm[fit_m] = True
            y, c = simulate(paper_theta, ev.U, ev.Y, ev.dt_s, weights=ev.w8, available=ev.available, nuisance=cols,
                            fit_mask=fm, return_coef=True, nuisance_prec=np.full(2 * n, prec))
            ref += (((ev.Y - y[0]) * ev.w8)[:, score_m] ** 2).sum(axis=1)
        np.testing.assert_allclose(sse[j], ref, rtol=1e-9)
        np.testing.assert_allclose(coef[j], c[0][:, -2 * n:], rtol=1e-7, atol=1e-9 * np.abs(c).max())


def test_air_mass_scan_settings_come_from_the_diagnosis_configuration(flight_factory, paper_theta):
    """``[diagnose] gust_chunk_s / gust_knot_s / gust_refine_iterations`` reach the air-mass scan
    through its context (the same scan as with the values passed by hand, another one than the
    defaults)."""
    from groundstation.gap.config import DiagnoseConfig
    from groundstation.gap.diagnose import segments_from_prepared
    from groundstation.gap.evaluate import Evaluator
    from groundstation.gap.hypotheses import Context, scan_wind_gust

    prep = flight_factory(T_s=18.0, seed=21, effect=("wind_gust", 2.0, 1.5))
    segs, avail = segments_from_prepared(prep)
    ev = Evaluator(segs, prep.dt_s, paper_theta, avail, window_s=3.0, folds=3)
    cfg = DiagnoseConfig(gust_chunk_s=1.0, gust_knot_s=1.0, gust_refine_iterations=1)
    h_cfg = scan_wind_gust(Context(ev, segs, cfg=cfg))
    h_arg = scan_wind_gust(Context(ev, segs), chunk_s=1.0, knot_s=1.0, refine_iterations=1)
    np.testing.assert_array_equal(h_cfg.sse, h_arg.sse)
    h_def = scan_wind_gust(Context(ev, segs), refine_iterations=0)
    assert not np.array_equal(h_cfg.sse, h_def.sse)
    # the knots of the smooth air velocity the base is re-identified under
    h_knots = scan_wind_gust(Context(ev, segs), chunk_s=1.0, knot_s=1.5, refine_iterations=1)
    assert not np.array_equal(h_cfg.extra["theta"], h_knots.extra["theta"])


def test_score_takes_its_test_resamples_from_the_caller():
    from groundstation.gap.attribute import score

    rng = np.random.default_rng(0)
    base = rng.random((12, 8)) + 1.0
    energy = np.ones((12, 8))
    s = score(base, 0.5 * base, energy, (0, 1), np.random.default_rng(1), n_boot=20, test_n_boot=9)
    assert s.p_value == pytest.approx(1 / 10)   # (0 + 1) / (9 + 1): every resample favours the alternative


def test_air_mass_slower_than_the_velocity_sensors_resolve_is_not_physical():
    from groundstation.gap.candidates import physical
    from groundstation.gap.config import DiagnoseConfig

    def _physical(h):
        return physical(h, DiagnoseConfig())

    slow = Hypothesis("wind_gust", estimate={"air_velocity_rms_m_s": 0.06}, extra={"resolvable_m_s": 0.13})
    real = Hypothesis("wind_gust", estimate={"air_velocity_rms_m_s": 0.9}, extra={"resolvable_m_s": 0.13})
    assert not _physical(slow) and _physical(real)
    # drag must oppose the motion on every axis it is estimated on
    assert not _physical(Hypothesis("quadratic_drag", estimate={"drag_u_per_m": -0.0002, "drag_v_per_m": 0.0016}))
    assert _physical(Hypothesis("quadratic_drag", estimate={"drag_u_per_m": 0.03, "drag_v_per_m": 0.04}))


def test_slew_grid_reaches_a_limit_that_acts_only_on_step_edges():
    """A card of steps (no sweeps) with small quantised corrections between them: the |input step|
    quantiles sit at the input quantum, while a 2.4 /s slew limit acts on the step edges only."""
    from groundstation.gap.hypotheses import RATE_QUANTILES, slew_grid

    dt, quantum = 0.02, 1 / 500
    rng = np.random.default_rng(5)
    n = 7500
    steps = np.repeat(rng.choice([-0.15, 0.15], n // 750), 750)  # a multistep every 15 s
    corr = np.zeros(n)
    for k in range(1, n):  # the pilot's small corrections between the steps
        corr[k] = 0.98 * corr[k - 1] + 0.002 * rng.standard_normal()
    u = np.round((steps + corr) / quantum) * quantum
    du = np.abs(np.diff(u))
    limit = 2.4 * dt
    assert np.quantile(du, RATE_QUANTILES).max() < limit / 3  # the quantiles alone never get near it
    grid = slew_grid(du)
    assert np.all(np.diff(grid) > 0)
    assert np.min(np.abs(np.log(grid / limit))) < np.log(1.5)


def test_slew_grid_is_as_fine_as_the_delay_grid_over_the_fractions_of_the_largest_rate():
    """Every slew limit between 5 % and 70 % of the largest input rate lies within a factor 1.2 of a
    candidate: a limit halfway (in ratio) between two candidates twice apart fits worse than the
    delay that mimics it (delay candidates are at most 1.5x apart from 0.04 s on), and was read as one."""
    from groundstation.gap.hypotheses import DELAY_GRID_S, slew_grid

    du = np.r_[np.full(99, 1e-4), 1.0]  # the quantiles sit at the input quantum, far below the largest step
    grid = slew_grid(du)
    limits = np.geomspace(0.05, 0.7, 200)
    nearest = np.min(np.abs(np.log(grid[None, :] / limits[:, None])), axis=1)
    assert np.exp(nearest.max()) < 1.2
    delay_ratio = np.max(np.array(DELAY_GRID_S[1:])[1:] / np.array(DELAY_GRID_S[1:])[:-1])  # from 0.04 s on
    assert np.exp(2 * nearest.max()) <= delay_ratio + 1e-9  # candidate spacing no coarser than the delays'


def test_input_variants_are_the_simulated_variants(flight_factory, paper_theta):
    """The residual of a variant of one input from the linear response (one product) is the one of
    simulating the variant's inputs, on every channel and for a change of any shape."""
    from groundstation.gap.diagnose import segments_from_prepared
    from groundstation.gap.evaluate import Evaluator
    from groundstation.gap.hypotheses import Context, backlash, shift
    from groundstation.gap.linsim import simulate

    prep = flight_factory(T_s=18.0, seed=3)
    segs, avail = segments_from_prepared(prep)
    ev = Evaluator(segs, prep.dt_s, paper_theta * 1.05, avail, window_s=3.0, folds=3)
    ctx = Context(ev, segs)
    groups = [(c, np.stack([ev.cut([fn(s.inputs[:, c]) for s in segs]) for fn in
                            (lambda x: shift(x, 3.5), lambda x: backlash(x, 0.02), lambda x: 0.0 * x)]))
              for c in range(4)]
    got = ctx.input_variants(groups)
    assert got.shape == (12, ev.W, ev.L, 8)
    for v, (c, u) in enumerate((c, u) for c, us in groups for u in us):
        U = ev.U.copy()
        U[:, :, c] = u
        want = ev.residual(simulate(ev.theta0, U, ev.Y, ev.dt_s, weights=ev.w8, available=ev.available,
                                    start=ev.start)[0])
        np.testing.assert_allclose(got[v], want, rtol=0, atol=1e-10 * np.abs(want).max())
        assert np.abs(got[v] - ev.r0).max() > 1e-3 * np.abs(ev.r0).max()  # the change is seen
    # forcing columns (drag, ground effect): the simulation with the forcing less the one without
    from groundstation.gap.hypotheses import _forcing_columns

    F = np.zeros((ev.W, ev.L, 11))
    F[:, :, 0] = np.sin(ev.T)
    F[:, :, 8] = 0.3 * np.cos(2 * ev.T)
    yh = simulate(ev.theta0, np.concatenate([ev.U, ev.U]), ev.Y, ev.dt_s, forcing=np.concatenate([0 * F, F]),
                  weights=ev.w8, available=ev.available, start=ev.start)[0]
    want = (yh[ev.W:] - yh[:ev.W]) * ev.w8 * ev.wmask
    got = _forcing_columns(ctx, [F])[..., 0]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())


def test_drag_evidence_reads_as_a_sentence_with_units():
    from groundstation.gap.attribute import Score
    from groundstation.gap.candidates import evidence

    h = Hypothesis("quadratic_drag", estimate={"drag_u_per_m": 0.0012615798290600054, "drag_v_per_m": 0.0003196950510928297})
    s = Score(score_pct=-0.007, p_value=0.62, gap_before=0.0349, gap_after=0.0349, shrink_pct=-0.03,
              shrink_interval=(0.0, 0.0), per_channel_shrink={})
    text = evidence(h, s, {}, [])
    assert text.startswith("-|v|v drag terms drag_u 0.0013 /m, drag_v 0.00032 /m; held-out cost")
    assert "{" not in text


def test_input_scans_select_from_training_costs_without_forming_every_variant(flight_factory, paper_theta):
    """The training costs of input variants from each window's quadratic form equal those of their
    formed residuals (to round-off), and the nested selection over them gives the same held-out
    cost, choice, residual, blocks and prediction change as stacking every variant."""
    from groundstation.gap.diagnose import segments_from_prepared
    from groundstation.gap.evaluate import Evaluator
    from groundstation.gap.hypotheses import Context

    prep = flight_factory(T_s=30.0, seed=5, effect=("deadband", 1, 0.02))
    segs, avail = segments_from_prepared(prep)
    ev = Evaluator(segs, prep.dt_s, paper_theta * 1.02, avail, window_s=3.0, folds=3)
    groups = [(c, np.stack([ev.cut([deadzone(s.inputs[:, c], b) for s in segs]) for b in (0.0, 0.005, 0.01, 0.02, 0.03)]))
              for c in (0, 1)]
    fast, full = Context(ev, segs), Context(ev, segs)
    rs = full.input_variants(groups)
    _, T_formed, _ = ev.heldout_many(rs)
    np.testing.assert_allclose(fast.input_train(groups), T_formed, rtol=1e-10)
    sse, best, r_best = fast.nested_inputs("deadband", groups)
    sse_all, best_all, _ = full.nested("deadband", [({}, r, None) for r in rs], rs)
    assert best == best_all == 8  # lon, the band flown
    np.testing.assert_allclose(sse, sse_all, rtol=1e-10)
    np.testing.assert_array_equal(r_best, rs[best])
    np.testing.assert_allclose(fast.blocks["deadband"], full.blocks["deadband"], rtol=1e-10)
    np.testing.assert_allclose(fast.change["deadband"], full.change["deadband"], rtol=1e-10)
