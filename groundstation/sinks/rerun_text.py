"""Readable text panels of a flight's results (markdown): fit per channel, and the gap verdict.

:func:`verdict_text` says what the diagnosis found, how sure it is and what to do next;
:func:`fit_table` and :func:`fit_text` show the in-sample fit beside the held-out fit and the
cross-flight check whenever the worker result carries them. Results may be mappings or frozen
dataclasses (:func:`field_of`). Pure text: no Rerun, no IO.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from groundstation.gap.report import through_flight_lines
from groundstation.sinks.rerun_layout import OUTPUTS, SYMBOL, UNITS

NEXT_STEP = {
    "input_delay": "add the estimated transport delay on the {input} channel to the model, or look for it in the "
                   "servo, receiver or flight-controller output path",
    "rate_limit": "check the {input} servo's slew rate (servo type, rate limits in the flight-controller mixer)",
    "deadband": "check the {input} linkage for play around centre (ball links, servo horn)",
    "ground_effect": "fly the identification test points higher than a rotor diameter, or add a ground-effect term",
    "wind_gust": "repeat in calmer air, or identify with the flight's air-mass motion as an input",
    "quadratic_drag": "add fuselage drag growing with speed squared to the model",
    "gyro_bias": "recalibrate the {output} gyro (or let the model carry a constant rate offset)",
    "rotor_vibration": "balance and track the rotor, or notch-filter the rates at the line's frequency",
    "velocity_latency": "check the GPS/velocity delay setting of the estimator",
    "unexplained": "inspect the flagged windows (times below): no catalogue effect explains them; check sensors, "
                   "events and the pilot's notes at those times, and fly more excitation in that condition",
    "none": "nothing to fix: the model explains this flight down to the measurement noise",
}


def field_of(obj: Any, key: str, default: Any = None) -> Any:
    """``obj[key]`` for a mapping, ``obj.key`` for a dataclass; ``default`` when absent."""
    if isinstance(obj, Mapping):
        return obj.get(key, default)
    return getattr(obj, key, default)


def _num(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _per_channel(d: Any) -> dict[str, float]:
    """``{channel: match %}`` from ``{"channels": {c: {"match": ..}}}``, ``{c: {"match": ..}}`` or ``{c: x}``."""
    if not isinstance(d, Mapping):
        return {}
    d = d.get("channels", d)
    out = {}
    for c in OUTPUTS:
        v = d.get(c) if isinstance(d, Mapping) else None
        v = v.get("match") if isinstance(v, Mapping) else v
        if _num(v) is not None:
            out[c] = float(v)  # type: ignore[arg-type]
    return out


def heldout_match(result: Any) -> dict[str, float]:
    """Held-out match % per channel, wherever the worker result (or its validation) carries it."""
    val = field_of(result, "validation") or {}
    for src in (result, val):
        for key in ("held_out", "heldout", "holdout", "held_out_fit", "heldout_fit"):
            got = _per_channel(field_of(src, key))
            if got:
                return got
    return {}


def _previous(result: Any) -> dict[str, Any]:
    """The cross-flight check the worker puts in the model's fit (``model.fit.cross_flight``)."""
    fit = (field_of(result, "model") or {}).get("fit") or {}
    return fit.get("cross_flight") or {}


def cross_flight(result: Any) -> dict[str, float]:
    """Match % per channel of the previous flight's model predicting this flight, when present."""
    got = _per_channel((_previous(result).get("previous_model_on_new_flight") or {}).get("match"))
    if got:
        return got
    val = field_of(result, "validation") or {}
    for src in (result, val):
        for key in ("cross_flight", "cross_flight_check", "crossflight"):
            got = _per_channel(field_of(src, key))
            if got:
                return got
    return {}


def fit_text(result: Any) -> dict[str, str]:
    """Short per-channel fit for view titles: ``fit 91% · held-out 88%``."""
    fit = _per_channel(field_of(result, "validation")) or _per_channel(field_of(result, "match_degree"))
    ho, xf = heldout_match(result), cross_flight(result)
    out = {}
    for c in OUTPUTS:
        parts = ([f"fit {fit[c]:.0f}%"] if c in fit else []) + ([f"held-out {ho[c]:.0f}%"] if c in ho else [])
        parts += [f"held-out {xf[c]:.0f}%"] if c in xf and c not in ho else []   # the previous flight's model
        if parts:
            out[c] = " · ".join(parts)
    return out


def fit_table(flight: int, result: Any) -> str:
    """Markdown table: match % of the model per channel, in-sample, held-out and on another flight."""
    fit = _per_channel(field_of(result, "validation")) or _per_channel(field_of(result, "match_degree"))
    ho, xf = heldout_match(result), cross_flight(result)
    prev = _previous(result).get("previous_flight", field_of(field_of(result, "cross_flight") or {}, "model_flight", "?"))
    xf_name = f"flight {prev}'s model %"
    cols = [("fit (this flight) %", fit)] + ([("held-out %", ho)] if ho else []) + ([(xf_name, xf)] if xf else [])
    lines = [f"### Flight {flight}: model match per channel", "",
             "| channel | " + " | ".join(n for n, _ in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for c in OUTPUTS:
        cells = [f"{d[c]:.1f}" if c in d else "–" for _, d in cols]
        lines.append(f"| {SYMBOL[c]} [{UNITS[c]}] | " + " | ".join(cells) + " |")
    if not ho and not xf:
        lines += ["", "No held-out score in this result: judge the model by held-out prediction before trusting it."]
    elif not ho:
        lines += ["", "Held out: the previous flight's model predicting this flight (a cross-flight check)."]
    secs = _num(field_of(result, "seconds"))
    if secs is not None:
        lines += ["", f"identified in {secs:.0f} s"]
    return "\n".join(lines)


def _effect_lines(e: Mapping[str, Any], alpha: Any) -> list[str]:
    where = e.get("input") or e.get("output") or ""
    est = ", ".join(f"{k} = {v:g}" for k, v in (e.get("estimate") or {}).items() if _num(v) is not None)
    lo, hi = (e.get("shrink_interval") or [None, None])[:2]
    sure = f"held-out cost down {e.get('score', 0) or 0:.1f} % (p = {e.get('p_value', float('nan')):.2g}"
    sure += f", family-wise α = {alpha})" if alpha is not None else ")"
    if _num(lo) is not None and _num(hi) is not None:
        sure += f"; gap on its channels shrinks {e.get('shrink_pct', 0) or 0:.0f} % (interval {lo:.0f}–{hi:.0f} %)"
    if _num(e.get("share_pct")) is not None:
        iv = e.get("share_interval_pct") or [None, None]
        sure += f"; removes {e['share_pct']:.0f} % of the gap above noise" + (
            f" (interval {iv[0]:.0f}–{iv[1]:.0f} %)" if _num(iv[0]) is not None and _num(iv[1]) is not None else "")
    cs = (e.get("consistency") or {}).get("status")
    if cs:
        sure += {"holds": "; holds through the flight", "changes": "; changes through the flight",
                 "not_checked": "; not checked through the flight"}.get(cs, "")
    step = NEXT_STEP.get(str(e.get("effect")), "").format(input=e.get("input") or "?", output=e.get("output") or "?")
    return [f"- **Found:** {str(e.get('effect', '')).replace('_', ' ')} {where}" + (f" ({est})" if est else ""),
            f"- *Evidence:* {e.get('evidence') or '–'}", f"- **How sure:** {sure}", f"- **Next:** {step}", ""]


def verdict_text(flight: int, gap: Mapping[str, Any]) -> str:
    """What the diagnosis of ``flight`` found, how sure it is and what to do next (markdown)."""
    verdict = str(gap.get("verdict", ""))
    g = gap.get("gap") or {}
    alpha = (gap.get("method") or {}).get("alpha")
    lines = [f"## Flight {flight}: verdict **{verdict.replace('_', ' ') or '–'}**", ""]
    sh = gap.get("shares") or {}
    if sh.get("headline"):
        lines += [f"**{sh['headline']}**", ""]
    for e in (gap.get("effects") or [])[:3]:
        lines += _effect_lines(e, alpha)
    for e in (gap.get("partial_findings") or [])[:3]:
        lines += ["*Partial finding (not named):*"] + _effect_lines(e, alpha)

    lines += [f"- {t}" for t in through_flight_lines(dict(gap))] + ([""] if gap.get("through_flight") else [])
    if verdict in ("none", "unexplained"):
        sig = "significant" if g.get("significant") else "not significant"
        found = ("the effects found explain too little of the gap, or change through the flight (partial findings above)"
                 if gap.get("partial_findings") else "no catalogue effect beats the base model on held-out data")
        lines += [f"- **Found:** {found}; the remaining gap is {sig}.",
                  f"- **Next:** {NEXT_STEP[verdict]}.", ""]
        best = (gap.get("candidates") or [])[:1]
        if best:
            b = best[0]
            lines += [f"- Best candidate, not significant: {b.get('effect')} {b.get('input') or b.get('output') or ''} "
                      f"(held-out cost down {b.get('score', 0) or 0:.1f} %, p = {b.get('p_value', float('nan')):.2g}).",
                      ""]
    ratio = g.get("gap_to_noise_ratio") or {}
    if ratio:
        lines += ["| channel | match % | residual / noise |", "|---|---|---|"]
        for c in OUTPUTS:
            m = (g.get("channels") or {}).get(c, {}).get("match")
            if c in ratio or m is not None:
                lines.append(f"| {SYMBOL[c]} | {m if m is not None else '–'} | {ratio.get(c, '–')} |")
        lines.append("")
    lines.append("")
    win = g.get("windows_s") or []
    if win:
        shown = ", ".join(f"{a:.1f}–{b:.1f} s" for a, b in win[:8] if a is not None and b is not None)
        lines.append(f"- **Flagged windows** (FC time, {g.get('conditions') or 'no common condition'}): {shown}"
                     + (f" and {len(win) - 8} more" if len(win) > 8 else ""))
    if g.get("band_hz"):
        lines.append(f"- Worst band: {g['band_hz'][0]:g}–{g['band_hz'][1]:g} Hz.")
    poor = [k for k, v in ((gap.get("excitation") or {}).get("inputs") or {}).items() if v != "ok"]
    if poor:
        lines.append(f"- Too little excitation on: {', '.join(poor)} (effects on these inputs cannot be tested).")
    for k, why in (gap.get("untestable") or {}).items():
        lines.append(f"- Untestable: {k.replace('_', ' ')}: {why}.")
    for n in (gap.get("notes") or [])[:5]:
        lines.append(f"- Note: {n}")
    return "\n".join(lines)
