"""The report pages as HTML text: :func:`render_report` (one flight) and :func:`render_campaign` (one
campaign), from Jinja2 templates in ``templates/`` with the figures of :mod:`groundstation.report.figures`
embedded (inline SVG or base64 PNG): one self-contained file, no script, no network, printable.

This module turns analysis results into words and tables (``*_view`` functions return plain dicts the
templates lay out); it computes nothing the analysis has not. A part that is missing renders as one
line saying why (``FlightReportData.errors``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape

from groundstation.report import figures as F
from groundstation.report.data import SECTIONS, FlightReportData
from groundstation.sysid.fit_section import HeldOut, PriorReport
from groundstation.sysid.model import OUTPUT_UNITS, OUTPUTS, PARAM_NAMES

#: what to do next, per verdict (the gap section's last paragraph)
NEXT_STEPS: dict[str, str] = {
    "input_delay": "add the estimated delay to the simulator's input path for that channel; check servo and "
                   "receiver latency on the bench",
    "rate_limit": "model the servo slew-rate limit in the simulator; check the servo's rated speed against the "
                  "sharpest inputs flown",
    "deadband": "measure the linkage play on the ground and add the deadband to the simulator's input path",
    "ground_effect": "identify from data flown well above one rotor diameter, or add a ground-effect term",
    "wind_gust": "fly in calmer air or log air data; treat velocity channels as disturbed",
    "quadratic_drag": "add fuselage drag growing with speed squared; fly faster translations to determine it",
    "gyro_bias": "recalibrate the gyro or estimate its bias before identification",
    "rotor_vibration": "check rotor balance and the autopilot's notch filter; filter the rates before identification",
    "velocity_latency": "shift the velocity stream by the estimated latency or use a velocity source without lag",
    "sensor_error": "recalibrate the named sensor; the data were corrected for the scale error before the rest",
    "unexplained": "the base model structure misses something the catalogue does not name: fly dedicated "
                   "frequency sweeps on the worst channel, or model the stabiliser / flight-controller loop",
    "none": "nothing to correct: the model is at the flight's noise floor on held-out data",
}


def _f(x: Any, fmt: str = ".3g", none: str = "–") -> str:
    if x is None:
        return none
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    return none if not math.isfinite(v) else format(v, fmt)


def _env() -> Any:
    env = Environment(loader=PackageLoader("groundstation.report", "templates"),
                      autoescape=select_autoescape(["html", "j2"]), undefined=StrictUndefined,
                      trim_blocks=True, lstrip_blocks=True)
    env.filters["num"] = _f
    env.filters["basename"] = lambda p: str(p).replace("\\", "/").rsplit("/", 1)[-1]
    return env


# ------------------------------------------------------------------ section views

def flight_view(d: FlightReportData) -> dict[str, Any]:
    rows = []
    for info in d.log_info:
        fl = info["flights"]
        pl = info["packet_loss"]
        rows.append({"source": info["source"].rsplit("/", 1)[-1],
                     "flights": len(fl), "armed_s": sum(f["duration_s"] or 0 for f in fl),
                     "in_air_s": sum(f["in_air_s"] or 0 for f in fl), "gaps": info["gaps_total"],
                     "corrupt": info["corrupt_bytes"], "lost": pl["lost"], "truncated": info["truncated_tail_bytes"],
                     "reboots": info["fc_reboots"], "chirps": len(info["chirps"]), "dropouts": len(info["dropouts"]),
                     "ground": [f"flight {f['index']}: {f['on_ground_evidence']}" for f in fl
                                if f.get("on_ground_evidence")],
                     "notes": info["notes"]})
    figs = [F.timeline_figure(d.timelines), F.rates_figure(d.log_info), F.gaps_figure(d.log_info, d.timelines),
            F.excitation_figure(d.prepared)]
    exc = []
    if d.prepared is not None:
        active = d.prepared.input_active
        for j, name in enumerate(("lat", "lon", "col", "ped")):
            x = np.concatenate([s.inputs[:, j] for s in d.prepared.segments])
            exc.append({"input": name, "rms": _f(np.nanstd(x), ".3f"), "moved": bool(active[j])})
    missing = [] if d.prepared is None else [c for c, a in zip(OUTPUTS, d.prepared.available, strict=True) if not a]
    return {"logs": rows, "figures": [f for f in figs if f is not None], "excitation": exc,
            "missing_outputs": missing, "notes": list(d.notes),
            "unusable": d.errors.get("logs") or d.errors.get("prepare"),
            "in_air_s": None if d.prepared is None else d.prepared.duration_s,
            "rate_hz": None if d.prepared is None else 1.0 / d.prepared.dt_s}


def model_view(d: FlightReportData) -> dict[str, Any]:
    m = d.model
    if m is None:
        return {"error": d.errors.get("model") or "no model"}
    fit = m.fit
    prior = fit.prior or PriorReport()
    share = prior.prior_share
    fixed = set(fit.fixed) | set(prior.fixed_at_prior)
    params = []
    for n in PARAM_NAMES:
        s = m.parameter_std.get(n)
        if n in fixed:
            status = "fixed (not identifiable)"
        elif n in m.pinned:
            status = "on a search bound: not an estimate"
        elif share.get(n, 0.0) > 0.5:
            status = "kept near the prior"
        elif prior.to_json():
            status = "determined by the flight"
        else:
            status = "estimated" if s is not None else "no std error"
        params.append({"name": n, "value": _f(m.params[n], ".4g"), "std": _f(s, ".2g"),
                       "prior": (f"{_f(prior.nominal.get(n), '.3g')} ± {_f(prior.std.get(n), '.2g')}"
                                 if prior.nominal else "–"),
                       "share": _f(100 * share[n], ".0f") + " %" if n in share else "–", "status": status,
                       "flag": status not in ("determined by the flight", "estimated")})
    ho = fit.heldout or HeldOut()
    lines: list[str] = []
    if ho.has("channel_mean") and not ho.channel_mean:
        lines.append(f"Held-out check over {ho.k} folds: no fold held a window the model could be scored on.")
    elif ho.has("channel_mean"):
        lines.append(f"Held-out match over {ho.k} contiguous folds: mean {ho.mean_match:.1f} % ("
                     + ", ".join(f"{c} {v:.1f}" for c, v in ho.channel_mean.items()) + ").")
        lines.append(f"The model predicts: {', '.join(ho.predicted) or 'no channel'}; it does not predict: "
                     f"{', '.join(ho.not_predicted) or 'none'}.")
    elif ho.has("skipped"):
        lines.append(f"Held-out check not made: {ho.skipped}")
    elif d.errors.get("heldout"):
        lines.append(f"Held-out check not made: {d.errors['heldout']}")
    else:
        lines.append("No k-fold held-out check with this model (the gap section's per-channel match is held out).")
    src = [str(x).replace("\\", "/").rsplit("/", 1)[-1] for x in (m.source or {}).get("logs", [])]
    here = [str(x).replace("\\", "/").rsplit("/", 1)[-1] for x in d.logs]
    if src and sorted(src) != sorted(here):
        lines.append(f"This model was identified on {', '.join(src)}: its held-out figures are of those logs; "
                     f"on {', '.join(here)} see the measured-vs-model figure and the gap section.")
    warnings: list[str] = []
    for sub in ho.unusable_subsystems:
        runs = "; ".join(f"{f}: " + ", ".join(c) for f, c in ho.runaway.items())
        warnings.append(f"The {sub} subsystem's held-out prediction runs away ({runs}): not a model of the aircraft.")
    for u in fit.unstable_modes:
        warnings.append(u[0].upper() + u[1:] + ".")
    if prior.prior_dominated:
        warnings.append(f"Not determined by this flight, kept near the prior ({prior.source}): "
                        f"{', '.join(prior.prior_dominated)}.")
    for name, why in fit.pinned_reasons.items():
        warnings.append(f"{name} {why}.")
    notes = list(fit.fixed_reasons) + list(fit.notes) + list(fit.closed_loop)
    figs = [F.parameters_figure(m), F.modes_figure(m), F.fit_figure(d.validation), F.heldout_figure(ho)]
    train = d.validation.channels if d.validation is not None else {}
    head = (f"{str(fit.algorithm or '?').upper()} fit, cost F = {_f(fit.cost, '.4f')}, "
            f"{'?' if fit.evaluations is None else fit.evaluations} evaluations; {len(m.augmentations)} augmentation(s)")
    return {"error": None, "head": head, "lines": lines, "warnings": warnings, "notes": notes, "params": params,
            "train": [{"channel": c, "match": _f(v.match, ".1f"), "unit": OUTPUT_UNITS[c]}
                      for c, v in train.items()],
            "figures": [f for f in figs if f is not None],
            "validation_error": d.errors.get("validation")}


def freq_view(d: FlightReportData) -> dict[str, Any]:
    v = d.freq
    if v is None:
        return {"error": d.errors.get("freq") or "no frequency check"}
    pairs = [{"pair": f"{p.input}→{p.output}", "J": _f(p.J, ".1f"), "pass": p.passed, "points": p.coherent_points,
              "band": f"{p.f_lo_hz:.2g}–{p.f_hi_hz:.2g}", "delay": _f(None if p.delay_s is None else 1000 * p.delay_s,
                                                                         "+.0f")} for p in v.pairs]
    delays = [f"{k}: {d_.delay_s * 1000:+.0f} ms ± {d_.std_s * 1000:.0f} ms ({d_.points} points)"
              for k, d_ in v.input_delays.items()]
    ja = v.J_avg
    head = (f"J_avg = {_f(ja, '.1f')} over {len(v.pairs)} pairs: {'good (≤ 100)' if v.good else 'not good (> 100)'}."
            if ja is not None else "No input-output pair has a coherent response: the flight says nothing in frequency.")
    figs = [*F.bode_figures(v), F.j_figure(v)]
    return {"error": None, "head": head, "pairs": pairs, "delays": delays,
            "no_response": [f"{i}→{o}: {r}" for i, o, r in v.no_response],
            "unmodelled": [f"{i}→{o}: coherent in the flight ({n} points), no path in the model" for i, o, n in v.unmodelled],
            "notes": list(v.responses.notes), "figures": [f for f in figs if f is not None]}


def verdict_sentence(gap: dict[str, Any]) -> str:
    """The gap report's verdict in one sentence."""
    v = gap.get("verdict", "?")
    g = gap.get("gap", {})
    eff = (gap.get("effects") or [None])[0]
    if v == "none":
        return "The model is at the flight's noise floor on held-out data: no effect beats the base model."
    if v == "unexplained":
        ux = gap.get("unexplained") or {}
        ch = ", ".join(ux.get("channels_above_noise") or g.get("worst_channels") or []) or "some channels"
        return (f"A significant gap remains on {ch} that no effect in the catalogue explains"
                + (f" (band {_band(ux.get('band_hz'))}, {ux.get('condition')})" if ux.get("band_hz") else "") + ".")
    if v == "sensor_error":
        f = ((gap.get("data_compatibility") or {}).get("findings") or [{}])[0]
        return f"A sensor error: {f.get('kind', 'scale error')} on {f.get('channel', '?')} ({f.get('evidence', '')})."
    if eff:
        where = eff.get("input") or eff.get("output")
        est = ", ".join(f"{k} = {_f(x, '.3g')}" for k, x in (eff.get("estimate") or {}).items())
        return (f"The gap is best explained by {v.replace('_', ' ')}" + (f" on {where}" if where else "")
                + (f" ({est})" if est else "") + f": it shrinks the held-out gap by {_f(eff.get('shrink_pct'), '.0f')} %.")
    return f"Verdict: {v}."


def _band(b: Any) -> str:
    return f"{_f(b[0], '.2g')}–{_f(b[1], '.2g')} Hz" if isinstance(b, list | tuple) and len(b) == 2 else "–"


def gap_view(d: FlightReportData) -> dict[str, Any]:
    gap = d.gap
    if gap is None:
        return {"error": d.errors.get("gap") or "no diagnosis"}
    g = gap.get("gap", {})
    ratio = g.get("gap_to_noise_ratio", {})
    channels = [{"channel": c, "match": _f(x.get("match"), ".1f"), "tic": _f(x.get("tic"), ".3f"),
                 "ratio": _f(ratio.get(c), ".2f")} for c, x in g.get("channels", {}).items()]
    def share(e: dict[str, Any]) -> str:
        iv = e.get("share_interval_pct")
        return _f(e.get("share_pct"), ".0f") + (f" ({_f(iv[0], '.0f')}–{_f(iv[1], '.0f')})" if iv else "")

    effects = [{"effect": e["effect"], "where": e.get("input") or e.get("output") or "–", "named": True,
                "share": share(e),
                "estimate": ", ".join(f"{k} {_f(x, '.3g')}" for k, x in (e.get("estimate") or {}).items()),
                "before_after": f"{_f(e.get('gap_before'), '.3f')} → {_f(e.get('gap_after'), '.3f')}",
                "shrink": _f(e.get("shrink_pct"), ".1f"), "p": _f(e.get("p_value"), ".2g"),
                "evidence": e.get("evidence", "")}
               for e in gap.get("effects", [])]
    effects += [{**x, "named": False} for x in
                [{"effect": e["effect"] + (" (partial finding)" if e in gap.get("partial_findings", []) else ""),
                  "where": e.get("input") or e.get("output") or "–", "share": share(e),
                  "estimate": ", ".join(f"{k} {_f(v, '.3g')}" for k, v in (e.get("estimate") or {}).items()),
                  "before_after": f"{_f(e.get('gap_before'), '.3f')} → {_f(e.get('gap_after'), '.3f')}",
                  "shrink": _f(e.get("shrink_pct"), ".1f"), "p": _f(e.get("p_value"), ".2g"),
                  "evidence": e.get("evidence", "")}
                 for e in list(gap.get("partial_findings", [])) + list(gap.get("candidates", []))[:4]]]
    wins = [w for w in g.get("windows_s", []) if w and w[0] is not None]
    where = [f"Channels: worst {', '.join(g.get('worst_channels', [])) or '–'}"
             f" (gap {'significant' if g.get('significant') else 'not significant'} against the noise floor).",
             f"Band: {_band(g.get('band_hz'))}.",
             f"Time: {len(wins)} flagged window(s)" + (": " + ", ".join(f"{a:.1f}–{b:.1f} s" for a, b in wins[:8])
                                                      + (" …" if len(wins) > 8 else "") if wins else "") + ".",
             f"Condition: {g.get('conditions') or '–'}."]
    findings = [f"Sensor error ({f['kind']} on {f['channel']}): {f['evidence']}"
                for f in (gap.get("data_compatibility") or {}).get("findings", [])]
    ux = gap.get("unexplained") or gap.get("departure") or {}
    looks = list(ux.get("what_it_looks_like", [])) if ux else []
    untestable = gap.get("untestable") or {}
    untest = ([f"{k}: {v}" for k, v in untestable.items()] if isinstance(untestable, dict)
              else [str(x) for x in untestable])
    nxt = [NEXT_STEPS.get(gap.get("verdict", ""), "")]
    if untest:
        nxt.append("to test what this flight could not: " + "; ".join(untest[:3]))
    fr = gap.get("frequency") or {}
    deps = [f"{x['input']}→{x['output']} {_band([x['f_lo_hz'], x['f_hi_hz']])}: {_f(x['magnitude_db'], '+.1f')} dB, "
            f"{_f(x['phase_deg'], '+.0f')} deg ({_f(x['max_ratio'], '.1f')}× the bound)"
            for x in fr.get("departures", [])[:6]]
    pic = d.pictures
    figs = [F.shares_figure(gap), F.residual_figure(pic), F.spectrum_figure(pic), F.effects_figure(pic)]
    no_pics = None if pic is not None else "Before/after pictures need the diagnosis arrays (made when the report " \
                                           "runs the diagnosis itself, not from a gap report file)."
    sh: dict[str, Any] = gap["shares"] if isinstance(gap.get("shares"), dict) else {}
    rest = sh.get("rest") or {}
    rest_lines = []
    if rest:
        if rest.get("channels"):
            chs = [c if isinstance(c, str) else f"{c.get('channel')} ({_f(c.get('excess_share_pct'), '.0f')} % of the "
                   f"gap, {_f(c.get('explained_pct'), '.0f')} % of it explained)" for c in rest["channels"]]
            rest_lines.append(f"The part not explained lies on {', '.join(chs)}"
                              + (f", band {_band(rest.get('band_hz'))}" if rest.get("band_hz") else "")
                              + (f", {rest['condition']}" if rest.get("condition") else "") + ".")
        rest_lines += [str(x) for x in rest.get("what_it_looks_like", [])]
    tf = gap.get("through_flight") or {}
    for k, h in enumerate(tf.get("halves") or []):
        span = h.get("t_s") or [None, None]
        rest_lines.append(f"{'First' if k == 0 else 'Second'} half ({_f(span[0], '.0f')}–{_f(span[1], '.0f')} s): "
                          f"{_f(h.get('excess_share_pct'), '.0f')} % of the gap above noise, "
                          f"{_f(h.get('explained_pct'), '.0f')} % of it explained by the named effects.")
    changes = [f"{c['effect']} {c.get('channel') or ''}: {c.get('why', '')}" for c in tf.get("changes", [])]
    shares = {"headline": sh.get("headline"), "rule": sh.get("rule"), "rest": rest_lines, "changes": changes,
              "explained": sh.get("explained_pct"), "checked": tf.get("checked")} if sh else None
    return {"error": None, "verdict": gap.get("verdict"), "sentence": verdict_sentence(gap), "channels": channels,
            "effects": effects, "where": where, "findings": findings, "looks": looks, "untestable": untest,
            "tested": gap.get("tested", []), "next": [n for n in nxt if n], "departures": deps,
            "shares": shares, "notes": gap.get("notes", []), "no_pictures": no_pics,
            "figures": [f for f in figs if f is not None]}


def across_view(d: FlightReportData) -> dict[str, Any]:
    cross = d.model.fit.cross_flight if d.model is not None else {}
    lines = []
    if cross.get("new_model_on_previous_flight"):
        lines.append(f"This model on flight {cross['previous_flight']}: held-out mean match "
                     f"{cross['new_model_on_previous_flight']['mean_match']:.1f} %.")
    if cross.get("previous_model_on_new_flight"):
        lines.append(f"Flight {cross['previous_flight']}'s model on this flight: mean match "
                     f"{cross['previous_model_on_new_flight']['mean_match']:.1f} %.")
    if cross.get("error"):
        lines.append(f"Cross-flight check not made: {cross['error']}")
    rows = [{"label": f"{r['log_name']}#{int(r['flight_index'])}", "date": r.get("date_utc") or "–",
             "in_air": _f(r.get("in_air_s"), ".0f"), "heldout": _f(r.get("heldout_match_pct"), ".1f"),
             "cross": _f(r.get("cross_match_pct"), ".1f"), "verdict": r.get("verdict") or "–",
             "current": any(r.get("log_name") == p.rsplit("/", 1)[-1] for p in d.logs)}
            for r in d.history]
    cur = next((str(x["label"]) for x in rows if x["current"]), None)
    fig = F.trends_figure(list(d.history), cur)
    empty = None
    if not rows and not lines:
        empty = (d.errors.get("history") or "No earlier flight of this aircraft is known: give the campaign table "
                 "(--campaign-db) or fly again with the service's campaign table on.")
    return {"lines": lines, "rows": rows, "aircraft": d.history_label, "figures": [fig] if fig else [], "empty": empty}


def unsupported(d: FlightReportData) -> list[str]:
    """What the data do not support, one plain sentence each (the page's first box; the terminal's
    warnings in one place)."""
    out: list[str] = []
    names = {"logs": "the logs", "prepare": "the in-air data", "model": "the model", "heldout": "the held-out check",
             "validation": "measured vs model", "freq": "the frequency check", "gap": "the diagnosis",
             "history": "the earlier flights"}
    for part, why in d.errors.items():
        out.append(f"No {names.get(part, part)}: {why}")
    p = d.prepared
    if p is not None:
        still = [n for n, a in zip(("lat", "lon", "col", "ped"), p.input_active, strict=True) if not a]
        if still:
            out.append(f"Input{'s' if len(still) > 1 else ''} never moved: {', '.join(still)}: nothing about "
                       f"{'them' if len(still) > 1 else 'it'} can be identified.")
        gone = [c for c, a in zip(OUTPUTS, p.available, strict=True) if not a]
        if gone:
            out.append(f"Outputs not measured or left out: {', '.join(gone)}.")
    m = d.model
    if m is not None:
        fit = m.fit
        ho = fit.heldout or HeldOut()
        for sub in ho.unusable_subsystems:
            out.append(f"The {sub} subsystem is not a model of the aircraft: its held-out prediction runs away.")
        if ho.not_predicted:
            out.append(f"The model does not predict {', '.join(ho.not_predicted)} on held-out data.")
        if ho.mean_match is not None and math.isfinite(ho.mean_match) and ho.mean_match < 50:
            out.append(f"The model predicts only {ho.mean_match:.0f} % of held-out data (mean match).")
        if fit.fixed:
            out.append(f"{len(fit.fixed)} parameters cannot be identified from this flight and stay fixed: "
                       f"{', '.join(fit.fixed)}.")
        if m.pinned:
            out.append(f"On a search bound, not estimates: {', '.join(m.pinned)}.")
        for c in fit.closed_loop[:1]:
            out.append(f"Closed loop: {c}")
        pr = fit.prior
        if pr is not None and pr.prior_dominated:
            out.append(f"Kept near the prior, not determined by this flight: {', '.join(pr.prior_dominated)}.")
    v = d.freq
    if v is not None:
        if v.J_avg is not None and not v.good:
            bad = [f"{x.input}→{x.output}" for x in v.pairs if not x.passed]
            out.append(f"In frequency the model misses the flight: J_avg {v.J_avg:.0f} > 100"
                       + (f" (failing: {', '.join(bad)})" if bad else "") + ".")
        if v.unmodelled:
            out.append("Coherent in the flight but absent from the model: "
                       + ", ".join(f"{i}→{o}" for i, o, _ in v.unmodelled) + ".")
    g = d.gap
    if g is not None:
        sh: dict[str, Any] = g["shares"] if isinstance(g.get("shares"), dict) else {}
        if g.get("verdict") == "unexplained":
            out.append("A significant gap remains that no effect in the catalogue explains"
                       + (f" ({sh['headline']})" if sh.get("headline") else "") + ".")
        elif (sh.get("unexplained_pct") or 0) >= 50 and g.get("verdict") != "none":
            out.append(f"{sh['unexplained_pct']:.0f} % of the gap above noise is not explained by the named effects.")
        ut = g.get("untestable") or {}
        if ut:
            out.append(f"Effects this flight cannot test: {', '.join(ut) if isinstance(ut, dict) else ut}.")
    return out


def render_report(d: FlightReportData) -> str:
    """The flight page (one self-contained HTML document) of ``d``."""
    views = {"flight": flight_view(d), "model": model_view(d), "frequency": freq_view(d), "gap": gap_view(d),
             "across": across_view(d)}
    summary = one_line_summary(d)
    n_figs = sum(len(v.get("figures", [])) for v in views.values())
    return _env().get_template("flight.html.j2").render(d=d, v=views, sections=SECTIONS, summary=summary,
                                                        n_figures=n_figs, unsupported=unsupported(d))


def one_line_summary(d: FlightReportData) -> str:
    """What the page says, in one line (the service publishes it)."""
    parts = []
    if d.prepared is not None:
        parts.append(f"{d.prepared.duration_s:.0f} s in air")
    elif d.errors.get("logs") or d.errors.get("prepare"):
        return f"not analysed: {d.errors.get('logs') or d.errors.get('prepare')}"
    if d.model is not None:
        ho = d.model.fit.heldout or HeldOut()
        if ho.mean_match is not None and math.isfinite(ho.mean_match):
            parts.append(f"held-out match {ho.mean_match:.1f} %")
        if ho.unusable_subsystems:
            parts.append(f"unusable: {', '.join(ho.unusable_subsystems)}")
    if d.freq is not None and d.freq.J_avg is not None:
        parts.append(f"J_avg {d.freq.J_avg:.1f}")
    if d.gap is not None:
        parts.append(f"verdict {d.gap.get('verdict')}")
    return "; ".join(parts) or "nothing analysed"


# ------------------------------------------------------------------ campaign

def render_campaign(aircraft: str, rows: list[dict[str, Any]], summary: dict[str, Any] | None,
                    links: dict[str, str] | None = None, title: str | None = None) -> str:
    """The campaign page: the table of flights (linked to their pages by ``links[log_name]``), the
    trend test's changes and the trend figures."""
    links = links or {}
    table = [{"label": f"{r['log_name']}#{int(r['flight_index'] or 0)}", "date": r.get("date_utc") or "–",
              "in_air": _f(r.get("in_air_s"), ".0f"), "train": _f(r.get("train_match_pct"), ".1f"),
              "heldout": _f(r.get("heldout_match_pct"), ".1f"), "cross": _f(r.get("cross_match_pct"), ".1f"),
              "verdict": r.get("verdict") or "–", "error": r.get("error"),
              "link": links.get(f"{r['log_name']}#{int(r['flight_index'] or 0)}")} for r in rows]
    changed = []
    for c in (summary or {}).get("changed", []):
        at = (summary or {}).get("flights", [])
        changed.append(f"{c['name']} ({c['kind']}, {'up' if c['direction'] > 0 else 'down'}) at "
                       f"{at[c['changed_at']] if c['changed_at'] < len(at) else c['changed_at']}: "
                       f"{_f(c['first'], '.4g')} → {_f(c['latest'], '.4g')}")
    ok = [r for r in rows if not r.get("error")]
    fig = F.trends_figure(ok)
    return _env().get_template("campaign.html.j2").render(
        aircraft=aircraft, title=title or f"Campaign report: {aircraft}", rows=table, changed=changed,
        figures=[fig] if fig else [], n_flights=len(rows), n_errors=len(rows) - len(ok))
