"""How much of the gap the named effects explain, and whether each holds through the flight.

Two questions a flight-test engineer asks before acting on a name:

* **Share.** The held-out gap *above the noise floor*: per window and channel, the base model's
  held-out cost less what a perfect model would still show there (the white noise measured on the
  raw data, after the smoothing: ``noise.noise_floor``'s ``sigma_smoothed``, in the cost's own
  weights). Each named effect removes part of the base cost (its held-out cost against the base
  model's on the same windows; a second effect given the first, on the model with the first in);
  its *share* is what it removes over the excess above the noise, in total (over the channels
  above their floor) and per channel. The interval is a bootstrap over the held-out windows
  (whole 3 s windows, so the residual's dependence inside a window stays in each draw).
* **Through the flight.** The windows are cut into a first and a second half (in time order). In
  each half, the named effect's parameter is estimated again (the same scan, base parameters
  re-fitted inside each fold) and both values are scored on each half's held-out blocks (the own
  value as chosen inside each fold, never on the windows it is scored on): the effect *holds*
  when a half's data do not reject the other half's value (paired tests over the ~0.5 s blocks,
  the analytic tests of the conditional step with a window's correlated blocks counted as fewer
  independent ones, Bonferroni over the halves and the effects tested, and a practical loss: the
  other value gives up more than
  ``consistency_min_loss`` of the effect's gain in that half); it *changes* when both do (a half
  whose data accept the other half's value holds the two estimates within its uncertainty); it is
  *not checked* when a half is too short for the windows and folds, or the effect does not lower
  that half's held-out cost significantly (its input barely moved there). An effect whose size
  depends on the flight condition (ground effect: height; drag: speed along u and v) is compared
  only over the windows of each half inside the range both halves flew (:func:`condition`): an
  estimate says nothing about conditions its half did not reach. The gap itself over time (its
  excess above the noise per half) is reported with it.

Units. Each channel's excess and removal are counted in multiples of that channel's own noise
(held-out cost over the noise cost), the scale of the report's gap-to-noise ratios: a channel
with a departure of k noise variances weighs the same whatever its signal's size (in the cost's
own weights, 1 / the signal's spread, a channel whose noise is large against its signal would
weigh most).

Pure numpy; the scans come from :mod:`groundstation.gap.hypotheses`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from groundstation.gap import attribute, fingerprints, hypotheses
from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.evaluate import Evaluator, SegmentArrays
from groundstation.sysid.model import INPUTS, OUTPUTS

#: the estimate of each effect compared between the halves (key of ``Hypothesis.estimate``)
PARAMETER = {"input_delay": "delay_s", "rate_limit": "rate_limit_per_s", "deadband": "deadband",
             "velocity_latency": "latency_s", "gyro_bias": "bias_rad_s", "ground_effect": "accel_m_s2",
             "quadratic_drag": None, "wind_gust": "air_velocity_rms_m_s", "rotor_vibration": "frequency_hz"}


#: an amplitude (air velocity rms, a line's amplitude) differing between the halves beyond chance
#: changes through the flight only when it differs by more than this factor
CHANGE_FACTOR = 1.5


# ----------------------------------------------------------------------------------------------
# shares
# ----------------------------------------------------------------------------------------------
def noise_cost(ev: Evaluator, sigma_smoothed: np.ndarray) -> np.ndarray:
    """(W, 8) held-out cost a perfect model would still show: the measured noise in the cost's weights."""
    s = np.nan_to_num(np.asarray(sigma_smoothed, float))
    if ev.M is None:
        return np.broadcast_to(float(ev.mask.sum()) * (s * ev.w8) ** 2, (ev.W, 8)).copy()
    return ev.score_mask.sum(axis=1) * (s * ev.w8) ** 2   # per window: its measured samples only


def removal(c: attribute.Candidate, base_sse: np.ndarray, first: bool = True) -> np.ndarray:
    """(W, 8) held-out cost a named effect removes, in the units of ``base_sse`` (the base model's).

    An effect named given a first one: what it removes from the model with the first in
    (``extra['sse_given']``/``['base_given']``); an effect scored in its own protocol (the air mass):
    its removal there, rescaled per channel to the base cost; the rotor line (a fingerprint of the
    raw residual): its per-channel share of the raw cost applied to the base cost."""
    h, s = c.hyp, c.score
    ex = h.extra
    if not first and ex.get("sse_given") is not None and ex.get("base_given") is not None:
        R = np.asarray(ex["base_given"], float) - np.asarray(ex["sse_given"], float)
        ref = ex.get("share_ref")
    elif h.effect == "rotor_vibration" or h.sse is None:
        f = np.zeros(8)
        for k, v in s.per_channel_shrink.items():
            f[int(k)] = 1.0 - (1.0 - max(min(float(v), 100.0), -100.0) / 100.0) ** 2
        return base_sse * f[None, :]
    elif ex.get("base_sse") is not None and h.sse is not None:
        R = np.asarray(ex["base_sse"], float) - np.asarray(h.sse, float)
        ref = ex["base_sse"]
    else:
        return base_sse - np.asarray(h.sse, float)
    if ref is not None:
        ref_t = np.asarray(ref, float).sum(axis=0)
        R = R * np.where(ref_t > 0, base_sse.sum(axis=0) / np.where(ref_t > 0, ref_t, 1.0), 0.0)[None, :]
    return R


def window_removal(removed: np.ndarray, base_sse: np.ndarray, noise_sse: np.ndarray, available: np.ndarray) -> np.ndarray:
    """(W,) what ``removed`` (W, 8) takes off each held-out window, in multiples of each channel's noise,
    over the channels whose gap is above their noise (those :func:`compute_shares` totals)."""
    unit = np.where(noise_sse > 0, 1.0 / np.where(noise_sse > 0, noise_sse, 1.0), 0.0)
    E = ((base_sse - noise_sse) * unit).sum(axis=0)
    cols = [c for c in range(8) if available[c] and E[c] > 0]
    return (removed * unit)[:, cols].sum(axis=1) if cols else np.zeros(base_sse.shape[0])


@dataclass
class Shares:
    """Shares of the held-out gap above the noise (percent); None where there is no gap to share."""

    explained_pct: float | None
    interval_pct: tuple[float, float] | None
    per_channel: dict[str, dict[str, Any]]
    per_effect: list[dict[str, Any]]
    excess_pct_of_cost: float  # the gap above noise, in percent of the base held-out cost
    channels: list[str] = field(default_factory=list)


def _ratio_interval(num: np.ndarray, den: np.ndarray, idx: np.ndarray) -> tuple[float, float]:
    b = num[idx].sum(axis=1) / np.maximum(den[idx].sum(axis=1), 1e-300)
    lo, hi = np.percentile(100.0 * b, [5, 95])
    return float(lo), float(hi)


def compute_shares(named: list[tuple[str, np.ndarray]], base_sse: np.ndarray, noise_sse: np.ndarray,
                   available: np.ndarray, rng: np.random.Generator, n_boot: int = DiagnoseConfig.share_n_boot,
                   min_gap_ratio: float = DiagnoseConfig.share_min_gap_ratio) -> Shares:
    """Shares of the gap above the noise removed by ``named`` ((label, removal (W, 8)) in order).

    Channels enter the total where their held-out cost is above their noise cost; a channel's own
    share is given where its gap-to-noise ratio (RMS) is at least ``min_gap_ratio`` (below, the
    excess is a small difference of two large numbers). Interval: 5-95 % bootstrap over windows."""
    W = base_sse.shape[0]
    cost = float(base_sse[:, available].sum())
    excess0 = float(np.maximum((base_sse - noise_sse).sum(axis=0), 0.0)[available].sum())
    # in multiples of each channel's noise (see the module docstring)
    unit = np.where(noise_sse > 0, 1.0 / np.where(noise_sse > 0, noise_sse, 1.0), 0.0)
    base_sse, noise_sse = base_sse * unit, noise_sse * unit
    named = [(label, Rk * unit) for label, Rk in named]
    E = base_sse - noise_sse
    tot_c = E.sum(axis=0)
    cols = [c for c in range(8) if available[c] and tot_c[c] > 0]
    idx = rng.integers(0, W, (n_boot, W))
    R = np.zeros_like(base_sse)
    per_effect = []
    for label, Rk in named:
        R = R + Rk
        if cols:
            num = Rk[:, cols].sum(axis=1)
            den = E[:, cols].sum(axis=1)
            per_effect.append({"effect": label, "share_pct": round(100.0 * float(num.sum() / den.sum()), 1),
                               "interval_pct": [round(v, 1) for v in _ratio_interval(num, den, idx)]})
    excess = float(E[:, cols].sum()) if cols else 0.0
    per_channel: dict[str, dict[str, Any]] = {}
    for c in range(8):
        if not available[c] or base_sse[:, c].sum() <= 0:
            continue
        ratio = float(np.sqrt(base_sse[:, c].sum() / max(noise_sse[:, c].sum(), 1e-300)))
        d: dict[str, Any] = {"gap_to_noise": round(ratio, 2),
                             "excess_share_pct": round(100.0 * float(max(tot_c[c], 0.0)) / excess, 1)
                             if excess > 0 else 0.0}
        if ratio >= min_gap_ratio and tot_c[c] > 0:
            d["explained_pct"] = round(100.0 * float(R[:, c].sum() / tot_c[c]), 1)
            d["interval_pct"] = [round(v, 1) for v in _ratio_interval(R[:, c], E[:, c], idx)]
        per_channel[OUTPUTS[c]] = d
    if not cols or excess <= 0:
        return Shares(None, None, per_channel, per_effect, 0.0, [])
    num = R[:, cols].sum(axis=1)
    den = E[:, cols].sum(axis=1)
    return Shares(explained_pct=100.0 * float(num.sum() / den.sum()), interval_pct=_ratio_interval(num, den, idx),
                  per_channel=per_channel, per_effect=per_effect,
                  excess_pct_of_cost=100.0 * excess0 / max(cost, 1e-300), channels=[OUTPUTS[c] for c in cols])


# ----------------------------------------------------------------------------------------------
# through the flight
# ----------------------------------------------------------------------------------------------
def halves(ev: Evaluator) -> np.ndarray:
    """(W,) index of the half (0 first, 1 second) of each window, in the windows' time order."""
    h = np.zeros(ev.W, int)
    h[ev.W // 2:] = 1
    return h


def split_segments(segs: list[SegmentArrays], ev: Evaluator) -> tuple[list[SegmentArrays], list[SegmentArrays]]:
    """The segments cut where the second half of the windows begins."""
    si, st = ev.starts[ev.W // 2]

    def piece(s: SegmentArrays, a: int, b: int) -> SegmentArrays:
        return SegmentArrays(t_s=s.t_s[a:b], inputs=s.inputs[a:b], outputs=s.outputs[a:b],
                             outputs_raw=s.outputs_raw[a:b], alt_m=s.alt_m[a:b], flight=s.flight)

    first = list(segs[:si]) + [piece(segs[si], 0, st)]
    second = [piece(segs[si], st, segs[si].t_s.shape[0])] + list(segs[si + 1:])
    keep = [s for s in first if s.t_s.shape[0] >= ev.L], [s for s in second if s.t_s.shape[0] >= ev.L]
    return keep


@dataclass
class HalfFit:
    """One half: its evaluator, the effect's own estimate there, the variant builder, and the held-out
    cost of the effect estimated inside each fold of the half (``own_sse`` (W, 8), ``own_blocks``
    (W, n_blocks)): the half's own value chosen on the very windows it is scored on would be an
    in-sample fit, which any other value loses to."""

    ev: Evaluator
    segs: list[SegmentArrays]
    value: Any  # the half's own estimate (label dict for input effects, float/array else)
    shown: float | None  # the value as reported
    own_sse: np.ndarray
    own_blocks: np.ndarray
    X: np.ndarray | None = None


def _input_residual(ev: Evaluator, segs: list[SegmentArrays], effect: str, lab: dict) -> np.ndarray:
    h = hypotheses.Hypothesis(effect, extra={"label": lab})
    U = ev.cut([s.inputs for s in hypotheses.apply_input_effect(h, segs, ev.dt_s)])
    return ev.residual(ev.simulate(ev.theta0, U=U))[0]


def _latency_residual(ev: Evaluator, segs: list[SegmentArrays], lat_s: float) -> np.ndarray:
    d = lat_s / ev.dt_s
    Ys = [s.outputs.copy() for s in segs]
    for y in Ys:
        y[:, :3] = hypotheses.shift(y[:, :3], -d)
    y = ev.simulate(ev.theta0, Y=ev.cut(Ys))[0]
    y[:, :, :3] = np.moveaxis(hypotheses.shift(np.moveaxis(y[:, :, :3], 1, 0), d), 0, 1)
    return ev.residual(y)


def _fit_half(c: attribute.Candidate, ev: Evaluator, segs: list[SegmentArrays]) -> HalfFit | None:
    """The effect's own estimate in one half (its scan on that half, on its channel), with the held-out
    cost of the effect estimated inside each fold (the scan's nested selection; a linear coefficient
    re-fitted per fold)."""
    h = c.hyp
    ctx = hypotheses.Context(ev, segs)
    e = h.effect
    if e in hypotheses.INPUT_EFFECTS or e == "velocity_latency":
        hh = hypotheses.rescan_input_effect(ctx, h) if e != "velocity_latency" else hypotheses.scan_velocity_latency(ctx)
        if not hh.testable or hh.sse is None:
            return None
        own = (hh.sse, ctx.blocks[e])
        if e == "velocity_latency":
            return HalfFit(ev, segs, float(hh.estimate["latency_s"]), float(hh.estimate["latency_s"]), *own)
        return HalfFit(ev, segs, dict(hh.extra["label"]), float(hh.estimate[str(PARAMETER[e])]), *own)
    X = _half_columns(c, ev, segs, ctx)
    if X is None:
        return None
    sse, _, coef = ev.heldout(ev.r0, X)
    v = coef.mean(axis=0)
    shown = {"gyro_bias": float(v[0]), "ground_effect": -float(np.mean(v))}.get(e, float(np.mean(v)))
    return HalfFit(ev, segs, float(v[0]) if e == "gyro_bias" else v, shown, sse, ev.last_blocks.copy(), X)


def _half_columns(c: attribute.Candidate, ev: Evaluator, segs: list[SegmentArrays],
                  ctx: hypotheses.Context) -> np.ndarray | None:
    """The linear columns (W, L, 8, K) of an effect entering as a coefficient (gyro bias, ground
    effect, drag) on one half; None for other effects or when it cannot be built there."""
    h, e = c.hyp, c.hyp.effect
    if e == "gyro_bias" and h.output in hypotheses.RATE_CH:
        ch = hypotheses.RATE_CH[h.output]
        b = 0.01
        Y2 = ev.Y.copy()
        Y2[:, :, ch] -= b
        yh = ev.simulate(ev.theta0, Y=Y2)[0]
        yh[:, :, ch] += b
        return hypotheses._mask_w(ev, (yh - ev.simulate(ev.theta0)[0]) / b)[..., None]
    if e == "ground_effect":
        # the whole flight's shape of height in both halves: only its amplitude is estimated again
        shape, hgt = h.extra.get("shape"), hypotheses.heights(ev, segs)
        if shape is None or hgt is None:
            return None
        return hypotheses.ground_effect_columns(ctx, hgt, float(shape["h0"]), str(shape["kind"]), float(shape["hmin"]))
    if e == "quadratic_drag":
        hh = hypotheses.scan_quadratic_drag(ctx)
        Xf = hh.extra.get("X")
        return None if not hh.testable or Xf is None else np.asarray(Xf)
    return None


def condition(c: attribute.Candidate, ev: Evaluator) -> tuple[str, np.ndarray] | None:
    """The flight condition an effect's size grows with, per window ((W, k) and its name): for ground
    effect the window's lowest height, negated (the effect grows as the height falls); for drag its
    largest speed along u and v. None for effects whose size does not depend on where the aircraft flies."""
    if c.hyp.effect == "ground_effect":
        hgt = hypotheses.heights(ev, ev.segments)
        return None if hgt is None else ("height", -hgt[:, ev.start:].min(axis=1)[:, None])
    if c.hyp.effect == "quadratic_drag":
        ax = [j for j in (0, 1) if ev.available[j]]
        return ("speed", np.abs(ev.Y[:, ev.start:, ax]).max(axis=1)) if ax else None
    return None


def _residual(c: attribute.Candidate, hf: HalfFit, value: Any) -> np.ndarray:
    """The weighted residual (W, L, 8) of the effect with parameter ``value`` fixed, in half ``hf``."""
    e = c.hyp.effect
    ev = hf.ev
    if e in hypotheses.INPUT_EFFECTS:
        return _input_residual(ev, hf.segs, e, value)
    if e == "velocity_latency":
        return _latency_residual(ev, hf.segs, float(value))
    assert hf.X is not None
    v = np.atleast_1d(np.asarray(value, float))
    X = hf.X
    if X.shape[-1] != v.size:
        v = np.resize(v, X.shape[-1])
    # the fitted coefficients are in the columns' own (un-normalised) units: r ~ -J d + X b
    return ev.r0 - np.einsum("wlck,k->wlc", X, v)


def consistency(c: attribute.Candidate, segs_h: tuple[list[SegmentArrays], list[SegmentArrays]], ev: Evaluator,
                theta: np.ndarray, level: float, min_loss: float, min_windows: int,
                rng: np.random.Generator, n_boot: int, window_alpha: float,
                arrays: dict[str, Any] | None = None) -> dict[str, Any]:
    """Does named effect ``c`` hold through the flight? (see the module docstring)

    Returns ``{"status": "holds" | "changes" | "not_checked" | "not_resolved" (a rotor line one half
    does not show), "parameter", "first", "second",
    "p_values", "why"}``."""
    e = c.hyp.effect
    par = PARAMETER.get(e)
    out: dict[str, Any] = {"status": "not_checked", "parameter": par, "first": None, "second": None,
                           "p_values": None, "why": ""}
    if e == "wind_gust":
        return _gust_consistency(c, ev, level, out)
    if e == "rotor_vibration":
        return _line_consistency(c, ev, arrays, level, out)
    e1, e2 = (_evaluator(s, ev, theta, min_windows) for s in segs_h)
    if e1 is None or e2 is None:
        out["why"] = "a half of the flight is too short to estimate the effect on its own"
        return out
    halves_ev, common = _where_both_flew(c, (e1, e2), ev, theta, min_windows)
    if halves_ev is None:
        out["why"] = common
        return out
    evs, segs_h = halves_ev, (halves_ev[0].segments, halves_ev[1].segments)
    fits = [_fit_half(c, eh, s) for eh, s in zip(evs, segs_h, strict=True)]
    if fits[0] is None or fits[1] is None:
        out["why"] = "the effect cannot be estimated again on a half of the flight"
        return out
    out["first"], out["second"] = _round(fits[0].shown), _round(fits[1].shown)
    resolved, rejected, out["p_values"] = _compare(c, fits[0], fits[1], level, min_loss, rng, n_boot, window_alpha)
    if not all(resolved):
        half = "first" if not resolved[0] else "second"
        where = f" (the {c.hyp.input} inputs there do not determine it)" if c.hyp.input else ""
        out["why"] = f"the effect does not lower the held-out cost of the {half} half{common} significantly{where}"
        return out
    if all(rejected):
        # each half's data reject the other half's value: the estimates disagree beyond both
        # halves' uncertainty. One half alone rejecting the other's value is a half that
        # determines the effect poorly (its data accept the other value: they agree within it)
        out["status"] = "changes"
        out["why"] = (f"{par} {out['first']} in the first half, {out['second']} in the second{common}: each half's "
                      f"data reject the other half's value")
    else:
        out["status"] = "holds"
        accepts = ("neither half rejects the other's value" if not any(rejected) else
                   f"the {('first', 'second')[rejected.index(False)]} half's data accept the other half's value")
        out["why"] = f"{par} {out['first']} and {out['second']} in the two halves{common}: {accepts}"
    return out


def _where_both_flew(c: attribute.Candidate, evs: tuple[Evaluator, Evaluator], ev: Evaluator, theta: np.ndarray,
                     min_windows: int) -> tuple[tuple[Evaluator, Evaluator] | None, str]:
    """The halves to compare, and the text naming the range compared (or why there is none).

    An effect whose size depends on where the aircraft flies (height, speed) is compared only where
    both halves flew: an estimate says nothing about conditions its half did not reach (a drag
    coefficient along an axis a half never flew fast on). Along each of the condition's axes both
    halves flew up to the smaller of their two extremes (the effect vanishes at the other end: low
    speed, large height). Other effects: the halves as they are."""
    c1, c2 = (condition(c, eh) for eh in evs)
    if c1 is None or c2 is None:
        return evs, ""
    cond = (c1[1], c2[1])
    top = np.minimum(cond[0].max(axis=0), cond[1].max(axis=0))
    name, unit, sign = {"height": ("height", "m", -1.0), "speed": ("speed", "m/s", 1.0)}[c1[0]]
    common = f" where both halves flew ({name} {'down to' if sign < 0 else 'up to'} {_span(sign * top)} {unit})"
    e1, e2 = (_evaluator(_window_segments(eh, np.all(x <= top, axis=1)), ev, theta, min_windows)
              for eh, x in zip(evs, cond, strict=True))
    if e1 is None or e2 is None:
        return None, (f"the halves flew to different {name}s (first {_span(sign * cond[0].max(axis=0))} {unit}, "
                      f"second {_span(sign * cond[1].max(axis=0))} {unit}): too few windows where both flew to "
                      f"compare them")
    return (e1, e2), common


def _evaluator(segs: list[SegmentArrays], ev: Evaluator, theta: np.ndarray, min_windows: int) -> Evaluator | None:
    """An evaluator like ``ev`` on ``segs``; None when they hold fewer than ``min_windows`` windows."""
    try:
        eh = Evaluator(segs, ev.dt_s, theta, ev.available, window_s=ev.L * ev.dt_s, folds=ev.folds, ridge=ev.ridge, start_s=ev.start_s)
    except Exception:  # too few windows for the folds
        return None
    return eh if eh.W >= min_windows else None


def _window_segments(ev: Evaluator, keep: np.ndarray) -> list[SegmentArrays]:
    """The windows ``keep`` (W,) of ``ev`` as segments of one window each."""
    out = []
    for (si, i0), k in zip(ev.starts, keep, strict=True):
        if k:
            s, sl = ev.segments[si], slice(i0, i0 + ev.L)
            out.append(SegmentArrays(t_s=s.t_s[sl], inputs=s.inputs[sl], outputs=s.outputs[sl],
                                     outputs_raw=s.outputs_raw[sl], alt_m=s.alt_m[sl], flight=s.flight,
                                     measured=None if s.measured is None else s.measured[sl]))
    return out


def _compare(c: attribute.Candidate, h1: HalfFit, h2: HalfFit, level: float, min_loss: float,
             rng: np.random.Generator, n_boot: int, window_alpha: float) -> tuple[list[bool], list[bool], dict[str, float]]:
    """Per half: does the effect lower its held-out cost (resolved), and do its data reject the other
    half's value (paired tests on the held-out blocks, and a loss above ``min_loss`` of the gain)."""
    pv: dict[str, float] = {}
    resolved, rejected = [], []
    for k, (hf, other) in enumerate(((h1, h2), (h2, h1))):
        ev_h = hf.ev
        base, _, _ = ev_h.heldout(ev_h.r0)
        bb = ev_h.last_blocks.copy()
        own, ob = hf.own_sse, hf.own_blocks
        oth, _, _ = ev_h.heldout(_residual(c, hf, _other_value(c, other.value, hf.value)))
        tb = ev_h.last_blocks.copy()
        p_res = attribute.conditional_p(base.sum(1), own.sum(1), rng, n_boot, window_alpha, bb, ob)
        p_rej = attribute.conditional_p(oth.sum(1), own.sum(1), rng, n_boot, window_alpha, tb, ob, clustered=True)
        gain = float(base.sum() - own.sum())
        loss = float(oth.sum() - own.sum())
        name = ("first", "second")[k]
        pv[f"{name}_effect"] = float(f"{p_res:.3g}")
        pv[f"{name}_rejects_other"] = float(f"{p_rej:.3g}")
        resolved.append(p_res < level and gain > 0)
        rejected.append(p_rej < level and gain > 0 and loss > min_loss * gain)
    return resolved, rejected, pv


def _span(x: np.ndarray) -> str:
    return ", ".join(f"{v:.2g}" for v in np.atleast_1d(x))


def _other_value(c: attribute.Candidate, other: Any, own: Any) -> Any:
    if c.hyp.effect in hypotheses.INPUT_EFFECTS:
        lab = dict(own)
        key = {"input_delay": "delay_s", "rate_limit": "rate_per_s", "deadband": "width"}[c.hyp.effect]
        lab[key] = other[key]
        if c.hyp.effect == "deadband":
            lab["kind"], lab["centre"] = other.get("kind", lab.get("kind")), other.get("centre", lab.get("centre"))
        return lab
    return other


def _round(v: Any) -> Any:
    if v is None:
        return None
    if isinstance(v, (list, tuple, np.ndarray)):
        return [round(float(x), 6) for x in np.ravel(v)]
    return round(float(v), 6)


def _gust_consistency(c: attribute.Candidate, ev: Evaluator, level: float, out: dict[str, Any]) -> dict[str, Any]:
    """An air mass holds when the fitted air velocity's rms per window is the same in both halves
    (Welch t-test on the log of the per-window rms, level ``level``, and a factor above
    :data:`CHANGE_FACTOR`)."""
    air = c.hyp.extra.get("air_knots")
    if air is None:
        out["why"] = "no per-window air velocity to compare"
        return out

    rms = np.sqrt((np.asarray(air) ** 2).sum(axis=1).mean(axis=1)) + 1e-9
    hv = halves(ev)
    a, b = np.log(rms[hv == 0]), np.log(rms[hv == 1])
    if a.size < 3 or b.size < 3:
        out["why"] = "a half of the flight is too short"
        return out
    p = float(stats.ttest_ind(a, b, equal_var=False).pvalue)
    r1, r2 = float(np.exp(a.mean())), float(np.exp(b.mean()))
    out.update(first=round(r1, 4), second=round(r2, 4), p_values={"halves_differ": float(f"{p:.3g}")})
    if p < level and max(r1, r2) / min(r1, r2) > CHANGE_FACTOR:
        out["status"], out["why"] = "changes", f"air velocity rms {r1:.2f} m/s in the first half, {r2:.2f} m/s in the second"
    else:
        out["status"], out["why"] = "holds", f"air velocity rms {r1:.2f} and {r2:.2f} m/s in the two halves"
    return out


def _line_consistency(c: attribute.Candidate, ev: Evaluator, arrays: dict[str, Any] | None, level: float,
                      out: dict[str, Any]) -> dict[str, Any]:
    """A rotor line holds when each half's raw residual shows a line at its frequency (within two
    bins of the averaged periodogram, or 0.3 Hz) at the same strength; ``not_resolved`` when a half
    does not show it (the line is then not named). A rotor spinning through the whole flight shakes
    the aircraft as hard in the second half as in the first; a line that grows or fades (a loop
    ringing as a delay grows) changes (:func:`_line_strength`)."""
    if arrays is None or arrays.get("resid_raw") is None:
        out["why"] = "no raw residual to look at"
        return out
    resid, U, ch, dt = arrays["resid_raw"], arrays["U"], arrays["line_channels"], ev.dt_s
    f0 = float(c.hyp.estimate.get("frequency_hz", np.nan))
    hv = halves(ev)
    found = []
    for k in (0, 1):
        sel = hv == k
        if sel.sum() < 3:
            out["why"] = "a half of the flight is too short"
            return out
        lines, sp = fingerprints.spectral_lines(resid[sel], U[sel], dt, ch, alpha=level, response=arrays.get("response"),
                                                reach_factor=arrays.get("reach_factor", DiagnoseConfig.line_stick_reach_factor))
        lines = fingerprints.resolvable_lines(lines, arrays.get("stride"), dt)
        f = sp["f_hz"] if isinstance(sp, dict) and "f_hz" in sp else None
        tol = max(0.3, 2.0 * float(f[1] - f[0])) if f is not None and len(f) > 1 else 0.3
        near = [ln.frequency_hz for ln in lines if abs(ln.frequency_hz - f0) <= tol]
        found.append(near[0] if near else None)
    out["first"], out["second"] = _round(found[0]), _round(found[1])
    if all(v is not None for v in found):
        lines = c.hyp.extra.get("lines") or []
        chans = lines[0].channels if lines else [OUTPUTS[k] for k in c.hyp.channels]
        return _line_strength(resid, dt, f0, tol, chans, hv, level, found, out)
    # a rotor spins through the whole flight: a line one half of the residual does not show above its
    # own local background is not shown to hold through it
    where = ("is not resolved in the second half" if found[0] is not None else
             "is not resolved in the first half" if found[1] is not None else "is resolved in neither half")
    out["status"] = "not_resolved"
    out["why"] = f"the line at {f0:.2f} Hz {where}: a rotor shakes the aircraft through the whole flight"
    return out


def _line_strength(resid: np.ndarray, dt: float, f0: float, tol: float, chans: list[str], hv: np.ndarray,
                   level: float, found: list, out: dict[str, Any]) -> dict[str, Any]:
    """A line found in both halves changes when its per-window power differs between the halves
    (Welch t-test on its log, level ``level``) by more than :data:`CHANGE_FACTOR` in amplitude: the
    air mass's rule, on the line's own power referred to its median over the flight."""
    pw = np.log(fingerprints.line_power_per_window(resid, dt, f0, tol, chans) + 1e-300)
    a, b = pw[hv == 0], pw[hv == 1]
    p = float(stats.ttest_ind(a, b, equal_var=False).pvalue)
    ratio = float(np.exp(0.5 * (b.mean() - a.mean())))  # amplitude, second half over first
    out["p_values"] = {"strength_differs": float(f"{p:.3g}")}
    out["amplitude_ratio"] = round(ratio, 3)
    if p < level and max(ratio, 1.0 / ratio) > CHANGE_FACTOR:
        out["status"] = "changes"
        out["why"] = (f"the line ({found[0]:.2f} and {found[1]:.2f} Hz) is {ratio:.2f}x as strong in the second half "
                      f"as in the first (p={p:.2g}): a rotor shakes the aircraft alike all flight")
    else:
        out["status"] = "holds"
        out["why"] = (f"the line is in both halves ({found[0]:.2f} and {found[1]:.2f} Hz), at {ratio:.2f}x the "
                      f"first half's amplitude in the second")
    return out


def gap_over_time(ev: Evaluator, base_sse: np.ndarray, noise_sse: np.ndarray, removed: np.ndarray,
                  cols: list[int]) -> dict[str, Any]:
    """The gap above the noise per half of the flight, what the named effects remove there, and the
    rank correlation of the windows' excess with time."""
    hv = halves(ev)
    unit = np.where(noise_sse > 0, 1.0 / np.where(noise_sse > 0, noise_sse, 1.0), 0.0)
    E = ((base_sse - noise_sse) * unit)[:, cols].sum(axis=1) if cols else np.zeros(ev.W)
    Rm = (removed * unit)[:, cols].sum(axis=1) if cols else np.zeros(ev.W)
    tot = float(E.sum())
    out = []
    for k in (0, 1):
        sel = hv == k
        t = ev.T[sel]
        e = float(E[sel].sum())
        ratio = {OUTPUTS[c]: round(float(np.sqrt(base_sse[sel, c].sum() / max(noise_sse[sel, c].sum(), 1e-300))), 2)
                 for c in cols}
        out.append({"t_s": [round(float(t[:, 0].min()), 2), round(float(t[:, -1].max()), 2)],
                    "excess_share_pct": round(100.0 * e / tot, 1) if tot > 0 else None,
                    "explained_pct": round(100.0 * float(Rm[sel].sum()) / e, 1) if e > 0 else None,
                    "gap_to_noise": ratio})
    rho, p = (stats.spearmanr(np.arange(ev.W), E) if ev.W >= 6 and np.ptp(E) > 0 else (0.0, 1.0))
    return {"halves": out, "trend": {"rho": round(float(rho), 3), "p": float(f"{float(p):.3g}")}}


def describe_inputs(name: str | None) -> str:
    return name if name in INPUTS else ""
