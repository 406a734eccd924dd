"""Attribute stage helpers: p-values, outer re-fits, encompassing tests, plausibility, evidence text.

Used by :mod:`groundstation.gap.diagnose` on the scanned hypotheses of
:mod:`groundstation.gap.hypotheses`. Every threshold comes from
:class:`groundstation.gap.config.DiagnoseConfig`; every random draw from the caller's generator;
every p-value of a held-out comparison from :func:`groundstation.gap.attribute.combined_p`.
Pure numpy.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from groundstation.gap import attribute, fingerprints, hypotheses, structure
from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.evaluate import Evaluator, SegmentArrays
from groundstation.parallel import Map, serial_map
from groundstation.sysid.model import OUTPUTS


def p_value(h: hypotheses.Hypothesis, ctx: hypotheses.Context | None, base: np.ndarray, rng: np.random.Generator,
            cfg: DiagnoseConfig, conditional: bool = False) -> float:
    """One-sided p-value that hypothesis ``h`` (scanned in ``ctx``) does not lower the held-out cost.

    ``conditional``: the test of a second effect given a first (analytic paired tests, :func:`attribute.conditional_p`)
    instead of the bootstrap of the first step."""
    assert h.sse is not None
    if h.effect == "wind_gust":
        return _air_mass_p(h, base, rng, cfg, conditional)
    blocks = ctx is not None and h.effect in ctx.blocks
    bb = ctx.base_blocks if blocks and ctx else None
    ab = ctx.blocks[h.effect] if blocks and ctx else None
    if conditional:
        return attribute.conditional_p(base.sum(1), h.sse.sum(1), rng, cfg.n_boot, cfg.window_alpha, bb, ab)
    return attribute.combined_p(base.sum(1), h.sse.sum(1), rng, cfg.n_boot, cfg.window_alpha, bb, ab)


def _air_mass_p(h: hypotheses.Hypothesis, base: np.ndarray, rng: np.random.Generator, cfg: DiagnoseConfig,
                conditional: bool) -> float:
    """:func:`p_value` of the air mass (its own protocol, no blocks): over the windows, in multiples of
    each channel's noise (``extra['unit']``, the units its variant was chosen in and the gap's shares'
    units; in the cost's weights the noisy body rates would drown the attitude's gain). An air-mass
    motion moves the attitude too (speed-stability moments): the same is demanded of the attitude
    angles alone, which integrate those moments (``extra['p_attitude']``); the larger p counts."""
    assert h.sse is not None
    unit = np.asarray(h.extra.get("unit", np.ones(8)), float)

    def test(cb: np.ndarray, ca: np.ndarray) -> float:
        return attribute.paired_t_p(cb, ca) if conditional else attribute.paired_bootstrap(cb, ca, rng, cfg.n_boot)

    p = test((base * unit).sum(1), (h.sse * unit).sum(1))
    att = [6, 7]
    p_att = test(base[:, att].sum(1), h.sse[:, att].sum(1))
    h.extra["p_attitude"] = p_att
    return max(p, p_att)


def p_pair(base: np.ndarray, base_blocks: np.ndarray, alt: np.ndarray, alt_blocks: np.ndarray,
           rng: np.random.Generator, cfg: DiagnoseConfig) -> float:
    """The conditional block/window p-value of :func:`p_value` for two held-out costs (W, 8) and blocks (W, n)."""
    return attribute.conditional_p(base.sum(1), alt.sum(1), rng, cfg.n_boot, cfg.window_alpha, base_blocks, alt_blocks)


def refit_input_effect(c: attribute.Candidate, ctx: hypotheses.Context, segs: list[SegmentArrays],
                       rng: np.random.Generator, cfg: DiagnoseConfig, crit: float) -> None:
    """One more outer iteration of the augmented fit of a significant input effect.

    The base model was identified without the effect and has absorbed part of it (a delay as a
    slower response, a slew limit as a smaller gain), and one Gauss-Newton step of the base
    parameters cannot undo that, so the grid value picked around the base is biased towards no
    effect. The base is re-identified with the selected variant in place (Levenberg-Marquardt on
    all windows, as the base itself was), and the effect's channel is scanned again around it:
    same grid, same nested k-fold selection and held-out scoring against the same base cost.
    Changes ``c`` in place; the refitted base is kept in ``hyp.extra['theta_refit']``.
    """
    ev = ctx.ev
    h = c.hyp
    segs_a = hypotheses.apply_input_effect(h, segs, ev.dt_s)
    ev_a = Evaluator(segs_a, ev.dt_s, ev.theta0, ev.available, window_s=ev.L * ev.dt_s,
                     folds=ev.folds, ridge=ev.ridge, start_s=ev.start_s, memo=ev.memo)
    ev_a.refine(cfg.refit_iterations, cfg.refine_ridge)
    h.extra["theta_refit"] = ev_a.theta0
    ev_r = Evaluator(segs, ev.dt_s, ev_a.theta0, ev.available, window_s=ev.L * ev.dt_s,
                     folds=ev.folds, ridge=ev.ridge, start_s=ev.start_s, memo=ev.memo)
    ctx_r = hypotheses.Context(ev_r, segs, cfg=cfg)
    h2 = hypotheses.rescan_input_effect(ctx_r, h)
    assert h2.sse is not None
    s2 = attribute.score(ctx.base_sse, h2.sse, ev.energy, h2.channels, rng, n_boot=min(cfg.n_boot, cfg.score_n_boot), test_n_boot=cfg.n_boot)
    s2.p_value = attribute.combined_p(ctx.base_sse.sum(1), h2.sse.sum(1), rng, cfg.n_boot, cfg.window_alpha,
                                      ctx.base_blocks, ctx_r.blocks[h.effect])
    h2.extra["first_pass"] = h.extra.get("first_pass") or {"estimate": dict(h.estimate),
                                                            "score_pct": c.score.score_pct}
    h.estimate, h.sse, h.extra = h2.estimate, h2.sse, {**h.extra, **h2.extra}
    h.extra["blocks_scored"] = ctx_r.blocks[h.effect]  # the blocks its test used (the verdict's margin)
    c.score = s2
    c.significant = bool(s2.p_value < crit and gain_ok(s2, cfg) and physical(h, cfg))


def encompass(cands: list[attribute.Candidate], ctx: hypotheses.Context, segs: list[SegmentArrays],
               rng: np.random.Generator, cfg: DiagnoseConfig, crit: float) -> None:
    """Encompassing tests between an input effect and the effects a closed loop makes look input-linked.

    The pilot's corrective inputs answer the disturbances: an unmeasured air mass (or the ground's
    extra lift, or drag) is partly cancelled by small inputs, so removing or delaying those inputs
    in the model (deadband, delay, slew limit) mimics the disturbance, and a per-window air velocity
    can in turn soak up part of an input effect's error. Each pair is decided by conditional tests,
    both on held-out data: does the input effect still lower the cost once the other effect is in
    the model (same channel, same grid, nested selection), and does the other effect still lower it
    once the input effect is in? (the analytic tests of the conditional step,
    :func:`attribute.conditional_p`). An effect that adds nothing given the other is not significant.
    When both stay (each adds to the other), both are reported, ranked by their own held-out score.
    Changes ``cands`` in place (``significant``, ``evidence``, ``hyp.extra``: conditional p-values
    and the share of each gain retained given the other).
    """
    ev = ctx.ev
    by = {c.hyp.effect: c for c in cands}
    gust = by.get("wind_gust")
    gust_explained = False  # the air mass adds nothing once a (larger) input effect is in
    for a in sorted((c for c in cands if c.hyp.effect in hypotheses.INPUT_EFFECTS and c.significant),
                    key=lambda c: -c.score.score_pct):
        # --- air mass: the four models (base, +A, +air mass, +both) in the air-mass protocol
        # (within-window chunk cross-validation). Input effects go largest first: an air mass that
        # one of them explains cannot set aside the next (it is that input effect)
        if (gust is not None and not gust_explained and gust.score.score_pct > 0 and "base_sse" in gust.hyp.extra
                and physical(gust.hyp, cfg)):
            segs_a = hypotheses.apply_input_effect(a.hyp, segs, ev.dt_s)
            ev_a = Evaluator(segs_a, ev.dt_s, ev.theta0, ev.available, window_s=ev.L * ev.dt_s,
                             folds=ev.folds, ridge=ev.ridge, start_s=ev.start_s, memo=ev.memo)
            ev_a.refine(cfg.refit_iterations, cfg.refine_ridge)   # refit_input_effect's, when it ran
            hg = hypotheses.scan_wind_gust(hypotheses.Context(ev_a, segs_a, cfg=cfg, noise_unit=ctx.noise_unit))
            assert hg.sse is not None and gust.hyp.sse is not None
            m0, mg = gust.hyp.extra["base_sse"], gust.hyp.sse
            ma, mag = hg.extra["base_sse"], hg.sse
            # the input effect given the air mass: its gain sits in the few windows of its sharpest
            # inputs, where the window bootstrap is the better test (a mean test over windows is
            # conservative for gains that skewed); the air mass given the input effect: a gain spread
            # over every window, the analytic test of the conditional step (no resampling floor)
            p_a = attribute.paired_bootstrap(mg.sum(1), mag.sum(1), rng, cfg.n_boot)
            p_g = p_value(hg, None, ma, rng, cfg, conditional=True)
            ret_a = float((mg - mag).sum() / max((m0 - ma).sum(), 1e-300))
            ret_g = float((ma - mag).sum() / max((m0 - mg).sum(), 1e-300))
            a.hyp.extra.update(p_given_air_mass=p_a, retained_given_air_mass=ret_a,
                               gain_given_air_mass=mg.sum(1) - mag.sum(1))  # per window (the verdict's margin)
            gust.hyp.extra.update({f"p_given_{a.hyp.effect}": p_g, f"retained_given_{a.hyp.effect}": ret_g})
            a_ok = p_a < crit and float((mg - mag).sum()) > 0
            g_ok = p_g < crit and float((ma - mag).sum()) > 0
            if not a_ok and g_ok:
                a.significant = False
                a.evidence += f"; adds nothing once an air-mass motion is allowed (p={p_a:.2g})"
                continue
            if not a_ok:
                # neither adds to the other: the same departure, explained by one parameter of the stick
                # or by a free air velocity in every window; the input effect is the one kept
                a.evidence += (f"; an air-mass motion explains it as well (p={p_a:.2g} for it given the air mass), "
                               f"but adds nothing to it (p={p_g:.2g})")
                a.hyp.extra["air_mass_adds_nothing_p"] = p_g   # kept by the air mass's test, not its own
            if gust.significant and not g_ok:
                gust.significant, gust_explained = False, True
                gust.evidence += f"; adds nothing once the {a.hyp.input} {a.hyp.effect} is in the model (p={p_g:.2g})"
        # --- effects entering as forcing columns (ground effect, drag)
        for b in cands:
            if b.hyp.effect not in ("ground_effect", "quadratic_drag") or not b.significant or not a.significant:
                continue
            Xb = b.hyp.extra.get("X")
            if Xb is None:
                continue
            ctx_b = hypotheses.Context(ev, segs, given=Xb, cfg=cfg)
            ha = hypotheses.rescan_input_effect(ctx_b, a.hyp)
            assert ha.sse is not None
            p = p_value(ha, ctx_b, ctx_b.base_sse, rng, cfg, conditional=True)
            a.hyp.extra[f"p_given_{b.hyp.effect}"] = p
            ra = a.hyp.extra["r_best"]
            s0, _, _ = ev.heldout(ra)
            b0 = ev.last_blocks.copy()
            s1, _, _ = ev.heldout(ra, Xb)
            pb = p_pair(s0, b0, s1, ev.last_blocks, rng, cfg)
            b.hyp.extra[f"p_given_{a.hyp.effect}"] = pb
            a_ok = p < crit and float(ctx_b.base_sse.sum() - ha.sse.sum()) > 0
            b_ok = pb < crit and float(s0.sum() - s1.sum()) > 0
            if not a_ok and b_ok:
                a.significant = False
                a.evidence += f"; adds nothing once {b.hyp.effect} is in the model (p={p:.2g})"
            elif a_ok and not b_ok:
                b.significant = False
                b.evidence += f"; adds nothing once the {a.hyp.input} {a.hyp.effect} is in the model (p={pb:.2g})"


def physical(h: hypotheses.Hypothesis, cfg: DiagnoseConfig) -> bool:
    """Physical plausibility: drag opposes motion (on every axis), ground effect adds lift, a deadband
    is wider than the input resolution, an air mass moves more than the velocity sensors resolve."""
    if h.effect == "quadratic_drag":
        # drag opposes the motion along every axis it is estimated on (a term of either sign on
        # one axis is model-structure error, e.g. the rigid body's velocity-rate products)
        vals = [float(v) for v in h.estimate.values()]
        return bool(vals) and all(v > 0 for v in vals)
    if h.effect == "ground_effect":
        return float(h.estimate.get("accel_m_s2", 0.0)) > 0
    if h.effect == "deadband":
        # wider than a few steps of the recorded input's resolution, else it is quantisation
        return float(h.estimate.get("deadband", 0.0)) > cfg.deadband_min_quanta * float(h.extra.get("quantum", 0.0))
    if h.effect == "wind_gust":
        # a low-frequency air mass carries the aircraft along: one moving less than the velocity
        # sensors resolve cannot be what the gap is (the fitted air velocity is then soaking up
        # slow model-structure error)
        return float(h.estimate.get("air_velocity_rms_m_s", 0.0)) > float(h.extra.get("resolvable_m_s", 0.0))
    return True


def gain_ok(s: attribute.Score, cfg: DiagnoseConfig) -> bool:
    """Practically significant: held-out cost down by more than ``min_score_pct`` and the gap on the
    effect's own channels smaller (see :class:`DiagnoseConfig`)."""
    return bool(s.score_pct > cfg.min_score_pct and s.shrink_pct > 0)


def vibration_candidate(lines: list[fingerprints.Line], resid_raw: np.ndarray, ev: Evaluator,
                        dt: float, rng: np.random.Generator, cfg: DiagnoseConfig) -> tuple[hypotheses.Hypothesis, attribute.Score]:
    """Rotor vibration: per-window sinusoid at each line removed from the raw residual (held-out not
    needed: two parameters per window and line, whose chance share of the energy is subtracted)."""
    chans = sorted({OUTPUTS.index(c) for ln in lines for c in ln.channels})
    base = (resid_raw * ev.w8) ** 2
    after = resid_raw.copy()
    for ln in lines:
        for c in chans:
            after[..., c] -= fingerprints.sinusoid_fit(after[..., c], dt, ln.frequency_hz)
    alt = (after * ev.w8) ** 2
    Lw = resid_raw.shape[1]
    chance = 1.0 - 2.0 * len(lines) / Lw  # expected share left if the "line" were white noise
    sse_b = base.sum(axis=1)
    sse_a = alt.sum(axis=1)
    sse_a[:, chans] /= max(chance, cfg.vibration_chance_floor)  # only where sinusoids were fitted: the others are unchanged
    energy = ((ev.Yraw[:, ev.start:] - ev.Yraw[:, ev.start:].reshape(-1, 8).mean(0)) * ev.w8) ** 2
    sc = attribute.score(sse_b, np.minimum(sse_a, sse_b * cfg.vibration_cost_cap), energy.sum(axis=1), tuple(chans),
                         rng, n_boot=cfg.vibration_n_boot, test_n_boot=cfg.n_boot)
    sc.p_value = 10 ** max(min(ln.log10_p for ln in lines), -300)
    top = lines[0]
    h = hypotheses.Hypothesis("rotor_vibration", estimate={"frequency_hz": round(top.frequency_hz, 3),
                                                            **{f"amplitude_{k}": v for k, v in top.amplitude.items()}},
                              sse=None, channels=tuple(chans), extra={"lines": lines})
    return h, sc


def evidence(h: hypotheses.Hypothesis, s: attribute.Score, kin: dict, lines: list) -> str:
    base = f"held-out cost {s.score_pct:+.1f}% (p={s.p_value:.2g})"
    e = h.effect
    if e == "input_delay":
        return f"{h.input} delayed {1000 * h.estimate['delay_s']:.0f} ms fits best; {base}"
    if e == "rate_limit":
        return f"{h.input} slew-limited at {h.estimate['rate_limit_per_s']:.2f} /s fits best; {base}"
    if e == "deadband":
        return f"{h.input} {h.extra.get('kind', 'deadband')} of +-{h.estimate['deadband']:.4f} fits best; {base}"
    if e == "velocity_latency":
        return f"velocities lag attitude by {1000 * h.estimate['latency_s']:.0f} ms; {base}"
    if e == "gyro_bias":
        k = kin.get(h.output or "")
        kt = f"; Euler-kinematics offset {1000 * k.offset_rad_s:.2f} mrad/s (t={k.t_stat:.1f})" if k else ""
        return f"constant offset on {h.output} of {1000 * h.estimate['bias_rad_s']:.2f} mrad/s{kt}; {base}"
    if e == "quadratic_drag":
        terms = ", ".join(f"{k.removesuffix('_per_m')} {v:.2g} /m" for k, v in h.estimate.items())
        return f"-|v|v drag terms {terms}; {base}"
    if e == "ground_effect":
        return f"w force decaying with height ({h.estimate.get('decay_height_m')} m); {base}"
    if e == "wind_gust":
        return (f"a smooth air velocity (rms {h.estimate.get('air_velocity_rms_m_s', 0):.2f} m/s) fitted on alternate "
                f"0.5 s chunks predicts the chunks between them, attitude included; {base}")
    if e == "rotor_vibration":
        ln = lines[0]
        return (f"narrow line at {ln.frequency_hz:.2f} Hz in {','.join(ln.channels)} "
                f"({ln.ratio:.1f}x local median, log10 p={ln.log10_p:.1f})")
    return base


def conditioned_context(a: attribute.Candidate, ctx: hypotheses.Context, segs: list[SegmentArrays]
                         ) -> hypotheses.Context | None:
    """A context whose base model already contains effect ``a`` (None when it cannot be put in)."""
    ev, h = ctx.ev, a.hyp
    if h.effect in ("ground_effect", "quadratic_drag") and h.extra.get("X") is not None:
        return hypotheses.Context(ev, segs, given=h.extra["X"], cfg=ctx.cfg, noise_unit=ctx.noise_unit)
    segs_a = applied(h, segs, ev.dt_s)
    if segs_a is None:
        return None  # rotor vibration (raw residual only), air mass (its own protocol, see encompass)
    theta = h.extra.get("theta_refit", ev.theta0) if h.effect in hypotheses.INPUT_EFFECTS else ev.theta0
    return _context_on(ctx, segs_a, theta)


def _context_on(ctx: hypotheses.Context, segs: list[SegmentArrays], theta: np.ndarray) -> hypotheses.Context:
    """A context like ``ctx`` on other segments and base parameters."""
    ev = ctx.ev
    ev_x = Evaluator(segs, ev.dt_s, theta, ev.available, window_s=ev.L * ev.dt_s, folds=ev.folds,
                     ridge=ev.ridge, start_s=ev.start_s, memo=ev.memo)
    out = hypotheses.Context(ev_x, segs, cfg=ctx.cfg, noise_unit=ctx.noise_unit)
    out.pwm_per_unit = ctx.pwm_per_unit
    return out


def applied(h: hypotheses.Hypothesis, segs: list[SegmentArrays], dt_s: float) -> list[SegmentArrays] | None:
    """The segments with effect ``h`` put into the data the model is fitted to: an input effect on its
    input, a gyro bias taken off its rate, a velocity latency taken off the velocities; None for an
    effect that enters otherwise (forcing columns, the air mass, a spectral line)."""
    if h.effect in hypotheses.INPUT_EFFECTS:
        return hypotheses.apply_input_effect(h, segs, dt_s)
    if h.effect not in ("gyro_bias", "velocity_latency") or (h.effect == "gyro_bias" and not h.output):
        return None
    out = []
    for s in segs:
        y, yr = s.outputs.copy(), s.outputs_raw.copy()
        if h.effect == "gyro_bias":
            c = OUTPUTS.index(str(h.output))
            b = float(h.estimate.get("bias_rad_s", 0.0))
            y[:, c] -= b
            yr[:, c] -= b
        else:
            d = float(h.estimate.get("latency_s", 0.0)) / dt_s
            y[:, :3] = hypotheses.shift(y[:, :3], -d)
            yr[:, :3] = hypotheses.shift(yr[:, :3], -d)
        out.append(SegmentArrays(t_s=s.t_s, inputs=s.inputs, outputs=y, outputs_raw=yr, alt_m=s.alt_m,
                                 flight=s.flight, measured=s.measured))
    return out


def rescan(b: attribute.Candidate, ctx: hypotheses.Context, channels: list[int] | None = None
           ) -> hypotheses.Hypothesis | None:
    """``b``'s scan again in another context: an input effect on its selected channel, or on every
    channel in ``channels`` when given (the channel may change once another effect is in the model)."""
    e = b.hyp.effect
    if e in hypotheses.INPUT_EFFECTS:
        if channels:
            scan = {"input_delay": hypotheses.scan_input_delay, "rate_limit": hypotheses.scan_rate_limit,
                    "deadband": hypotheses.scan_deadband}[e]
            return scan(ctx, channels)
        return hypotheses.rescan_input_effect(ctx, b.hyp)
    scans = {"velocity_latency": hypotheses.scan_velocity_latency, "gyro_bias": hypotheses.scan_gyro_bias,
             "quadratic_drag": hypotheses.scan_quadratic_drag, "ground_effect": hypotheses.scan_ground_effect,
             "wind_gust": hypotheses.scan_wind_gust}
    return scans[e](ctx) if e in scans else None


def rescan_one(cctx: hypotheses.Context, channels: list[int], b: attribute.Candidate
               ) -> tuple[hypotheses.Hypothesis | None, dict, dict]:
    """:func:`rescan` of ``b`` in ``cctx`` (input effects over ``channels``) and what it cached on
    ``cctx`` (module-level, so worker processes can run it on their copy of ``cctx``)."""
    hb = rescan(b, cctx, channels if b.hyp.effect in hypotheses.INPUT_EFFECTS else None)
    return hb, dict(cctx.change), dict(cctx.blocks)


def _conditional_score(b: attribute.Candidate, hb: hypotheses.Hypothesis | None, cctx: hypotheses.Context,
                       rng: np.random.Generator, cfg: DiagnoseConfig, floor: np.ndarray | None
                       ) -> tuple[hypotheses.Hypothesis, attribute.Score, float] | None:
    """``b`` scanned again in the conditioned context (``hb``) and scored against that context's base
    cost; with the RMS of the residual part it explains there over the noise floor (largest over outputs)."""
    if hb is None or hb.sse is None or not hb.testable:
        return None
    hb.extra = {**{k: v for k, v in b.hyp.extra.items() if k not in hb.extra}, **hb.extra}
    base = hb.extra.get("base_sse", cctx.base_sse) if hb.effect == "wind_gust" else cctx.base_sse
    s = attribute.score(base, hb.sse, cctx.ev.energy, hb.channels, rng, n_boot=min(cfg.n_boot, cfg.score_n_boot), test_n_boot=cfg.n_boot)
    s.p_value = p_value(hb, cctx, base, rng, cfg, conditional=True)
    return hb, s, structure.effect_to_noise(base, hb.sse, cctx.ev.energy, floor)


def conditional_names(ranked: list[attribute.Candidate], cands: list[attribute.Candidate], ctx: hypotheses.Context,
                      segs: list[SegmentArrays], in_channels: list[int], kin_significant: set[str],
                      rng: np.random.Generator, cfg: DiagnoseConfig, crit: float,
                      floor: np.ndarray | None = None, pmap: Map = serial_map) -> None:
    """A second effect is named only if it adds to the first one (held-out, conditional).

    With the top effect in the base model, every other catalogue effect is scanned again (input
    effects over every excited input: the channel may change once the first effect is in) and must
    lower the held-out cost of that model significantly (at Holm's second step-down level: the
    family-wise ``alpha`` over the candidates that enter this test, :func:`second_level`), by more than
    ``min_score_pct`` of *that* model's cost, and shrink the gap on its own channels (the RMS of the
    residual part it explains over the noise floor is reported with it):

    * an effect named on its own that fails this is withheld, with the conditional p-value;
    * when no other effect is named beside the first, the one step of a forward selection: of the
      physically plausible effects, the one with the largest conditional gain is named if it passes (the first effect's share of
      the residual diluted its gain: alone it explained too small a share of the base cost), and
      nothing is named if it does not (a smaller one would be soaking up part of the larger one's
      residual). Effects that an encompassing test set aside, that are physically implausible or
      whose kinematic evidence is missing (a roll or pitch gyro bias) are not brought back.

    Effects that cannot be put into a model (the spectral line, the air mass as first effect) keep
    their own tests. The conditional scans are independent: ``pmap`` may run them in worker
    processes. Changes the candidates in place.
    """
    if not ranked:
        return
    top = ranked[0]
    if top.hyp.effect == "wind_gust":
        second_given_air_mass(top, cands, ctx, segs, rng, cfg, crit, pmap)
        return
    cctx = conditioned_context(top, ctx, segs)
    if cctx is None:
        return
    # set aside by an encompassing test: not brought back here
    todo = [b for b in cands if b is not top and b.hyp.effect != "rotor_vibration" and b.hyp.testable
            and (b.significant or ("adds nothing" not in b.evidence and "not named" not in b.evidence))]
    scans = pmap(partial(rescan_one, cctx, in_channels), todo)
    for _hb, change, blocks in scans:
        cctx.change.update(change)
        cctx.blocks.update(blocks)
    entries = []
    ref = joint_reference(top, ctx, segs, cfg)
    for b, (hb, _, _) in zip(todo, scans, strict=True):
        res = _conditional_score(b, hb, cctx, rng, cfg, floor)
        if res is None:
            continue
        hb, s, etn = res
        given_base = hb.extra.get("base_sse", cctx.base_sse) if hb.effect == "wind_gust" else cctx.base_sse
        if ref is not None and hb.effect != "wind_gust" and s.score_pct > 0:
            joint = joint_score(top, b, hb, ctx, segs, ref, in_channels, rng, cfg, floor)
            if joint is not None:
                hb, s, etn = joint
                given_base = ref.base_sse
        # what it removes once the first is in (the shares of the named effects: no double count)
        change = hb.extra.get("change_given", cctx.change.get(hb.effect))
        blocks = hb.extra.get("blocks_given", (cctx.base_blocks, cctx.blocks.get(hb.effect)))
        for ex in (b.hyp.extra, hb.extra):
            ex["sse_given"], ex["base_given"], ex["change_given"] = hb.sse, given_base, change
            ex["blocks_given"] = blocks
            if hb.effect == "wind_gust":
                ex["share_ref"] = given_base
        b.hyp.extra[f"p_given_{top.hyp.effect}"] = s.p_value
        b.hyp.extra[f"score_given_{top.hyp.effect}"] = s.score_pct
        b.hyp.extra[f"effect_to_noise_given_{top.hyp.effect}"] = etn
        plausible = physical(hb, cfg) and not (hb.effect == "gyro_bias" and hb.output in ("p", "q")
                                               and hb.output not in kin_significant)
        entries.append((b, hb, s, etn, plausible))
    crit2 = second_level(crit, sum(e[4] for e in entries), cfg)
    tried = []
    for b, hb, s, etn, plausible in entries:
        ok = bool(s.p_value < crit2 and gain_ok(s, cfg) and plausible)
        b.hyp.extra["level_given"] = hb.extra["level_given"] = crit2
        joint = hb.extra.get("joint_first")
        how = (f"once the {top.hyp.effect} is in the model" if joint is None else
               f"in a joint fit with the {top.hyp.effect} (base re-identified"
               + (f" with both, the {top.hyp.effect} re-estimated: {joint})" if joint else " around it)"))
        given = (f"adds {s.score_pct:+.1f}% held-out (p={s.p_value:.2g} against {crit2:.2g}, gap on its channels "
                 f"{s.shrink_pct:+.1f}%, {etn:.1f}x the noise) {how}")
        if b.significant and not ok:
            b.significant = False
            b.evidence += f"; not named: {given}"
        elif not b.significant and not plausible:
            why = ("no Euler-kinematics offset on " + str(hb.output) if hb.effect == "gyro_bias"
                   and physical(hb, cfg) else "not physically plausible")
            b.evidence += f"; given the {top.hyp.effect}: {given}, {why}"
        elif not b.significant:
            tried.append((b, hb, s, ok, given))
    _name_second(top, tried, cands, cctx, ctx)


def joint_reference(top: attribute.Candidate, ctx: hypotheses.Context, segs: list[SegmentArrays],
                    cfg: DiagnoseConfig) -> hypotheses.Context | None:
    """The model a second effect is tested against: the first effect alone, the base re-identified
    around it (Levenberg-Marquardt from the first effect's own re-fit, as many iterations as the joint
    fit gets, so that a second effect is not credited with the convergence of the first's fit). None
    when the first effect cannot be put into the data (forcing columns, air mass, spectral line)."""
    ev = ctx.ev
    segs_a = applied(top.hyp, segs, ev.dt_s)
    if segs_a is None:
        return None
    ev_a = Evaluator(segs_a, ev.dt_s, np.asarray(top.hyp.extra.get("theta_refit", ev.theta0)), ev.available,
                     window_s=ev.L * ev.dt_s, folds=ev.folds, ridge=ev.ridge, start_s=ev.start_s,
                     memo=ev.memo)
    ev_a.refine(cfg.refit_iterations, cfg.refine_ridge)
    return _context_on(ctx, segs_a, ev_a.theta0)


def joint_score(top: attribute.Candidate, b: attribute.Candidate, hb: hypotheses.Hypothesis,
                ctx: hypotheses.Context, segs: list[SegmentArrays], ref: hypotheses.Context,
                in_channels: list[int], rng: np.random.Generator, cfg: DiagnoseConfig, floor: np.ndarray | None
                ) -> tuple[hypotheses.Hypothesis, attribute.Score, float] | None:
    """Second effect ``b`` (its conditional scan ``hb``) tested in a joint fit with the first effect.

    Both effects are put into the data and the base is re-identified with both (Levenberg-Marquardt,
    from the first effect's re-fit); the first effect is scanned again there with the second in (its
    estimate free: a first effect fitted alone absorbs part of the second), and the second is scanned
    again with that first effect in. Its held-out cost is scored against :func:`joint_reference` (the
    first alone, re-identified the same way) by the paired tests of the conditional step on the
    held-out blocks, whose spread is measured on the data. An effect entering as forcing columns is
    scanned on the reference's base. None when the scan cannot run."""
    ev = ctx.ev
    segs_b = applied(hb, segs, ev.dt_s)
    first = None
    if segs_b is None:
        ctx_j = _context_on(ref, ref.segments, ref.ev.theta0)
    else:
        segs_ab = applied(top.hyp, segs_b, ev.dt_s)
        assert segs_ab is not None  # the reference exists: the first effect can be put into the data
        ev_ab = Evaluator(segs_ab, ev.dt_s, np.asarray(top.hyp.extra.get("theta_refit", ev.theta0)), ev.available,
                          window_s=ev.L * ev.dt_s, folds=ev.folds, ridge=ev.ridge, start_s=ev.start_s)
        ev_ab.refine(cfg.refit_iterations, cfg.refine_ridge)
        ha = rescan(top, _context_on(ctx, segs_b, ev_ab.theta0))
        ha = ha if ha is not None and ha.testable and ha.sse is not None else top.hyp
        first = dict(ha.estimate)
        segs_a2 = applied(ha, segs, ev.dt_s)
        ctx_j = _context_on(ctx, segs_ab if segs_a2 is None else segs_a2, ev_ab.theta0)
    h2 = rescan(b, ctx_j, in_channels if b.hyp.effect in hypotheses.INPUT_EFFECTS else None)
    if h2 is None or h2.sse is None or not h2.testable:
        return None
    h2.extra = {**{k: v for k, v in hb.extra.items() if k not in h2.extra}, **h2.extra,
                "joint_first": first if first is not None else {}, "change_given": ctx_j.change.get(h2.effect),
                "blocks_given": (ref.base_blocks, ctx_j.blocks.get(h2.effect))}
    base = ref.base_sse
    s = attribute.score(base, h2.sse, ref.ev.energy, h2.channels, rng, n_boot=min(cfg.n_boot, cfg.score_n_boot),
                        test_n_boot=cfg.n_boot)
    blocks = ctx_j.blocks.get(h2.effect)
    s.p_value = attribute.conditional_p(base.sum(1), h2.sse.sum(1), rng, cfg.n_boot, cfg.window_alpha,
                                        ref.base_blocks if blocks is not None else None, blocks)
    return h2, s, structure.effect_to_noise(base, h2.sse, ref.ev.energy, floor)


def second_level(crit: float, n_remaining: int, cfg: DiagnoseConfig) -> float:
    """Per-test level of the conditional step (Holm's step-down): the first effect was named at the
    Bonferroni level over every candidate; given it, the ``n_remaining`` candidates that enter the
    conditional test (physically plausible, not set aside by an encompassing test: a screening
    that does not look at the held-out gain) share the family-wise ``alpha``. Never stricter than
    ``crit``."""
    return max(crit, cfg.alpha / max(n_remaining, 1))


def _name_second(top: attribute.Candidate, tried: list, cands: list[attribute.Candidate],
                 cctx: hypotheses.Context, ctx: hypotheses.Context) -> None:
    """The forward-selection step of :func:`conditional_names`: of the candidates not named on their
    own, the one with the largest conditional gain is named when it passes."""
    if any(c.significant for c in cands if c is not top and c.hyp.effect != "rotor_vibration") or not tried:
        for b, _, _, _, given in tried:
            b.evidence += f"; given the {top.hyp.effect}: {given}"
        return
    best = max(tried, key=lambda t: t[2].score_pct)
    for b, hb, s, ok, given in tried:
        if b is not best[0] or not ok:
            why = "" if b is best[0] else f" (the {best[0].hyp.effect} adds more)"
            b.evidence += f"; given the {top.hyp.effect}: {given}{why}"
            continue
        b.hyp.input, b.hyp.output, b.hyp.estimate = hb.input, hb.output, hb.estimate
        b.hyp.sse, b.hyp.channels, b.hyp.extra = hb.sse, hb.channels, hb.extra
        b.evidence = f"{evidence(b.hyp, s, {}, [])}; named as a second effect: it {given}"
        # ranked beside the first effect by its share of the *base* model's cost (the conditional
        # percentage is of a smaller cost and would put it above the effect it was tested after)
        s.score_pct *= float(cctx.base_sse.sum() / max(ctx.base_sse.sum(), 1e-300))
        b.score, b.significant = s, True
        b.hyp.extra["second_to"] = top.hyp.effect  # ranked after the effect it was tested given


def _with_effect_removed(b: attribute.Candidate, ctx: hypotheses.Context, segs: list[SegmentArrays]
                         ) -> hypotheses.Context | None:
    """A context whose data have effect ``b`` taken out (its segments changed, or, for an effect entering
    as forcing columns, its fitted response subtracted from the windows' outputs); None when it cannot be."""
    h = b.hyp
    if h.effect in ("ground_effect", "quadratic_drag"):
        X = h.extra.get("X")
        if X is None:
            return None
        c = (np.array([-float(h.estimate.get("accel_m_s2", 0.0))]) if h.effect == "ground_effect"
             else np.array([float(v) for v in h.estimate.values()]))
        if X.shape[-1] != c.size:
            return None
        ev = ctx.ev
        ev_b = Evaluator(segs, ev.dt_s, ev.theta0, ev.available, window_s=ev.L * ev.dt_s, folds=ev.folds,
                         ridge=ev.ridge, start_s=ev.start_s)
        w = np.where(ev.w8 > 0, ev.w8, 1.0)
        ev_b.Y = ev.Y - np.einsum("wlck,k->wlc", X, c) / w
        ev_b.set_theta(ev.theta0)
        return hypotheses.Context(ev_b, segs, cfg=ctx.cfg, noise_unit=ctx.noise_unit)
    return conditioned_context(b, ctx, segs)


def _air_mass_given(b: attribute.Candidate, ctx: hypotheses.Context, segs: list[SegmentArrays]
                    ) -> hypotheses.Hypothesis | None:
    """The air-mass scan on the data with ``b`` taken out (module-level: runs in worker processes)."""
    cb = _with_effect_removed(b, ctx, segs)
    return None if cb is None else hypotheses.scan_wind_gust(cb)


def second_given_air_mass(top: attribute.Candidate, cands: list[attribute.Candidate], ctx: hypotheses.Context,
                          segs: list[SegmentArrays], rng: np.random.Generator, cfg: DiagnoseConfig, crit: float,
                          pmap: Map = serial_map) -> None:
    """The conditional step when the first effect is an air mass (which has its own protocol).

    An air mass cannot be put into the base model of the ordinary held-out scans, so the other way
    round: each candidate with a positive gain of its own and physically plausible is taken out of
    the data (its segments changed, or its fitted response subtracted) and the air-mass scan is run
    again there. In the air-mass protocol (within-window chunk cross-validation) that gives the
    models "air mass" (``top``) and "air mass + candidate"; the candidate adds to the air mass when
    the second lowers the cost significantly at Holm's second level (:func:`second_level` over the
    candidates that enter), by more than ``min_score_pct``, and shrinks the gap on its own channels.
    The best one passing is named second. Changes the candidates in place.
    """
    todo = [b for b in cands if b is not top and b.hyp.effect != "rotor_vibration" and b.hyp.testable
            and b.hyp.sse is not None and b.score.score_pct > 0 and physical(b.hyp, cfg)
            and "adds nothing" not in b.evidence and "not named" not in b.evidence]
    m_g = top.hyp.sse
    if not todo or m_g is None:
        return
    crit2 = second_level(crit, len(todo), cfg)
    scans = pmap(partial(_air_mass_given, ctx=ctx, segs=segs), todo)
    tried = []
    for b, hg in zip(todo, scans, strict=True):
        if hg is None or hg.sse is None:
            continue
        s = attribute.score(m_g, hg.sse, ctx.ev.energy, b.hyp.channels, rng, n_boot=min(cfg.n_boot, cfg.score_n_boot), test_n_boot=cfg.n_boot)
        s.p_value = attribute.paired_bootstrap(m_g.sum(1), hg.sse.sum(1), rng, cfg.n_boot)
        b.hyp.extra["p_given_wind_gust"] = s.p_value
        b.hyp.extra.update(sse_given=hg.sse, base_given=m_g, share_ref=top.hyp.extra.get("base_sse"))
        b.hyp.extra["score_given_wind_gust"] = s.score_pct
        ok = bool(s.p_value < crit2 and gain_ok(s, cfg))
        given = (f"adds {s.score_pct:+.1f}% (p={s.p_value:.2g} against {crit2:.2g}, gap on its channels "
                 f"{s.shrink_pct:+.1f}%) to the air mass, air-mass protocol with the {b.hyp.effect} taken out of the data")
        if b.significant and not ok:
            b.significant = False
            b.evidence += f"; not named: {given}"
        elif not b.significant:
            tried.append((b, s, ok, given))
    if any(c.significant for c in cands if c is not top and c.hyp.effect != "rotor_vibration") or not tried:
        for b, _, _, given in tried:
            b.evidence += f"; given the wind_gust: {given}"
        return
    best = max(tried, key=lambda t: t[1].score_pct)
    for b, _s, ok, given in tried:
        if b is not best[0] or not ok:
            b.evidence += f"; given the wind_gust: {given}" + ("" if b is best[0] else f" (the {best[0].hyp.effect} adds more)")
            continue
        b.evidence = f"{evidence(b.hyp, b.score, {}, [])}; named as a second effect: it {given}"
        b.significant = True
        b.hyp.extra["second_to"] = "wind_gust"
