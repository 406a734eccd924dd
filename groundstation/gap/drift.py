"""Does a named effect's parameter drift through the flight? A test on the whole flight.

The halves test (:func:`groundstation.gap.shares.consistency`) estimates the effect again in each
half and asks whether each half's data reject the other half's value. It cannot see a drift when
one half does not resolve the effect on its own: a delay growing from nothing at take-off is not
significant in the first half, whatever it is in the second.

This test needs no half to resolve anything. It compares two families of the same effect on the
same held-out windows, both selected inside each training fold (the scan's nested selection, base
parameters re-fitted there, scored on windows the selection never saw):

* **constant**: the parameter at a few multiples of its whole-flight estimate;
* **ramp**: the same multiples, each also ramping linearly through the flight (the value at the
  flight's middle stays the multiple; at take-off and at the end it moves by ``±a`` of it), the
  constant among them.

The effect *drifts* when the ramp family lowers the held-out cost beyond chance against the
constant one (the conditional step's paired tests over the held-out blocks, a window's correlated
blocks counted as fewer independent ones). No cost floor beside the test: the gentlest ramp of the
family already changes the parameter threefold from take-off to the end (a swing of ±50 % of its
mid-flight value), a change an engineer must hear of however small its part of the cost. A ramp is
the simplest change through a flight; a parameter that changes any other way but steadily (a
battery's sag, a warming servo) projects onto it.

Effects it tests: the input effects (delay, deadband, rate limit: the value along the flight applied
to the input) and a gyro bias (a bias and a bias growing through the flight as two linear columns).
A rotor line is tested for a steady size instead (:func:`line_drift`). Other effects return None
(the halves test stands alone for them).

Pure numpy.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import stats

from groundstation.gap import attribute, fingerprints, hypotheses
from groundstation.gap.evaluate import Evaluator, SegmentArrays

#: multiples of the whole-flight estimate (both families) and the ramps' half-swings (ramp family)
SCALES = (0.6, 0.8, 1.0, 1.25, 1.6)
SWINGS = (-1.0, -0.5, 0.0, 0.5, 1.0)
#: a rotor line drifts when its amplitude in the flight's last third differs from its first third's
#: by more than this factor (besides the trend test)
LINE_RATIO = 1.5


def progress(segs: list[SegmentArrays]) -> list[np.ndarray]:
    """Per segment, each sample's place in the flight from -1 (first sample) to +1 (last)."""
    t0 = min(float(s.t_s[0]) for s in segs)
    t1 = max(float(s.t_s[-1]) for s in segs)
    span = max(t1 - t0, 1e-9)
    return [2.0 * (s.t_s - t0) / span - 1.0 for s in segs]


def _rate_limit(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """:func:`hypotheses.rate_limit` with a largest step per sample."""
    y, col = float(x[0]), []
    for xk, mk in zip(x.tolist(), m.tolist(), strict=True):
        y += min(max(xk - y, -mk), mk)
        col.append(y)
    return np.array(col, dtype=float)


def _input_variant(effect: str, lab: dict[str, Any], x: np.ndarray, scale: np.ndarray, dt_s: float) -> np.ndarray:
    """One input channel ``x`` (n,) through ``effect`` with its parameter ``lab``'s value times ``scale`` (n,)."""
    if effect == "input_delay":
        return hypotheses.shift(x, lab["delay_s"] * scale / dt_s)
    if effect == "rate_limit":
        return _rate_limit(x, float(lab["rate_per_s"]) * dt_s * scale)
    b = float(lab["width"]) * scale
    if lab["kind"] == "deadzone":  # hypotheses.deadzone with a width (and centre) per sample
        d = x - float(lab.get("centre", 0.0)) * scale
        return np.sign(d) * np.maximum(np.abs(d) - b, 0.0)
    return hypotheses.backlash(x, b)


Family = tuple[np.ndarray, np.ndarray, np.ndarray]  # held-out cost (W, 8), blocks, chosen parameters


def _input_families(c: attribute.Candidate, ctx: hypotheses.Context) -> tuple[Family, Family]:
    """(held-out cost (W, 8), blocks, chosen (scale, swing)) of the constant and of the ramp family."""
    ev, segs, lab = ctx.ev, ctx.segments, c.hyp.extra["label"]
    ch = int(lab["channel"])
    prog = progress(segs)
    combos = [(m, a) for a in SWINGS for m in SCALES]
    U = np.stack([ev.cut([_input_variant(c.hyp.effect, lab, s.inputs[:, ch], m * (1.0 + a * p), ev.dt_s)
                          for s, p in zip(segs, prog, strict=True)]) for m, a in combos])
    const = [i for i, (_, a) in enumerate(combos) if a == 0.0]
    out = []
    for key, idx in (("drift_constant", const), ("drift_ramp", list(range(len(combos))))):
        sse, best, _ = ctx.nested_inputs(key, [(ch, U[idx])])
        out.append((sse, ctx.blocks[key], np.array(combos[idx[best]])))
    return out[0], out[1]


def _bias_families(c: attribute.Candidate, ctx: hypotheses.Context) -> tuple[Family, Family] | None:
    """The constant gyro bias (one column) against a bias plus a bias growing through the flight."""
    ev = ctx.ev
    ch = hypotheses.RATE_CH.get(c.hyp.output or "")
    if ch is None:
        return None
    b = 0.01
    Y2 = ev.Y.copy()
    Y2[:, :, ch] -= b
    yh = ev.simulate(ev.theta0, Y=Y2)[0]
    yh[:, :, ch] += b
    X = hypotheses._mask_w(ev, (yh - ev.simulate(ev.theta0)[0]) / b)[..., None]
    p = ev.cut(progress(ev.segments))
    # the ramp's column: the bias's own response times the flight's progress (a bias changing
    # slowly against a window's length enters each window as its value there)
    Xr = np.concatenate([X, X * p[:, :, None, None]], axis=-1)
    out = []
    for XX in (X, Xr):
        sse, _, coef = ev.heldout(ev.r0, XX)
        out.append((sse, ev.last_blocks.copy(), coef.mean(axis=0)))
    return out[0], out[1]


def drift(c: attribute.Candidate, ctx: hypotheses.Context, base_sse: np.ndarray, level: float,
          rng: np.random.Generator, n_boot: int, window_alpha: float) -> dict[str, Any] | None:
    """The ramp test of named effect ``c`` on the base context ``ctx`` (see the module docstring).

    Returns None for an effect it does not test, else ``{"drifts", "p", "gain_pct", "cost_pct",
    "ramp_gains", "ramp", "why"}``: ``gain_pct`` what the ramp removes beyond the constant, in % of
    what the constant removes from the base (``base_sse`` (W, 8)), ``cost_pct`` in % of the base's
    held-out cost; ``ramp_gains`` whether the ramp removes any held-out cost beyond the constant;
    ``ramp`` the chosen value at take-off and at the end of the flight."""
    e = c.hyp.effect
    fams: tuple[Family, Family] | None
    if e in hypotheses.INPUT_EFFECTS and "label" in c.hyp.extra:
        fams = _input_families(c, ctx)
    elif e == "gyro_bias":
        fams = _bias_families(c, ctx)
    else:
        return None
    if fams is None:
        return None
    (s0, b0, v0), (s1, b1, v1) = fams
    eff_gain = float(base_sse.sum() - s0.sum())
    more = float(s0.sum() - s1.sum())
    p = attribute.conditional_p(s0.sum(1), s1.sum(1), rng, n_boot, window_alpha, b0, b1, clustered=True)
    ends = _ends(c, v1)
    drifts = bool(p < level and eff_gain > 0 and more > 0)
    gain_pct = 100.0 * more / eff_gain if eff_gain > 0 else float("nan")
    par = {"input_delay": "delay", "deadband": "width", "rate_limit": "rate limit", "gyro_bias": "bias"}[e]
    why = (f"a {par} ramping through the flight ({ends[0]:.3g} at take-off, {ends[1]:.3g} at the end) "
           f"removes {gain_pct:.0f} % more held-out cost than a constant one (paired tests over held-out "
           f"blocks, p={p:.2g} against {level:.2g})")
    return {"drifts": drifts, "p": float(f"{p:.3g}"), "gain_pct": round(gain_pct, 1),
            "cost_pct": round(100.0 * more / float(base_sse.sum()), 2), "ramp_gains": bool(more > 0),
            "ramp": [round(float(x), 6) for x in ends], "why": why}


def _ends(c: attribute.Candidate, v: np.ndarray) -> tuple[float, float]:
    """The ramp family's chosen parameter at the flight's start and end."""
    e = c.hyp.effect
    if e == "gyro_bias":
        return float(v[0] - v[1]), float(v[0] + v[1])
    lab = c.hyp.extra["label"]
    val = float(lab[{"input_delay": "delay_s", "rate_limit": "rate_per_s"}.get(e, "width")])
    m, a = float(v[0]), float(v[1])
    return val * m * (1.0 - a), val * m * (1.0 + a)


def line_drift(c: attribute.Candidate, ev: Evaluator, resid_raw: np.ndarray, level: float) -> dict[str, Any] | None:
    """Does a named rotor line keep its size through the flight?

    A rotor turning at a steady speed shakes the airframe by the same amount all flight. A line
    whose amplitude grows or falls steadily through the flight is something else at that frequency
    (an oscillation growing with a lag that grows, a loop losing its margin). Per held-out window,
    the line's sinusoid fitted on the raw residual of its channels (each in its channel's weight):
    its energy's rank correlation with the window's time (Spearman) against ``level``, and an
    amplitude in the flight's last third more than :data:`LINE_RATIO` times the first third's (or
    less than its inverse). The scatter of the windows' energies about their trend is the test's
    own noise. None without a line."""
    lines = c.hyp.extra.get("lines") or []
    chans = list(c.hyp.channels)
    if not lines or not chans or resid_raw.shape[0] < 8:
        return None
    energy = np.zeros(resid_raw.shape[0])
    for ln in lines:
        for ch in chans:
            x = np.nan_to_num(resid_raw[..., ch])
            energy += (fingerprints.sinusoid_fit(x, ev.dt_s, ln.frequency_hz) ** 2).mean(axis=1) * ev.w8[ch] ** 2
    rho, p = stats.spearmanr(ev.T[:, 0], energy)
    rho, p = float(rho), float(p)
    k = max(resid_raw.shape[0] // 3, 1)
    ratio = float(np.sqrt(energy[-k:].mean() / max(energy[:k].mean(), 1e-30)))
    drifts = bool(p < level and max(ratio, 1.0 / max(ratio, 1e-9)) > LINE_RATIO)
    why = (f"the line's amplitude {'grows' if rho > 0 else 'falls'} through the flight (last third "
           f"{ratio:.2g}x the first; rank correlation with time {rho:.2f}, p={p:.2g} against {level:.2g}): "
           f"a rotor at a steady speed shakes the same all flight")
    return {"drifts": drifts, "p": float(f"{p:.3g}"), "rho": round(rho, 3), "ratio": round(ratio, 3), "why": why}
