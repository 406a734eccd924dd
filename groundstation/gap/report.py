"""The ``heli-gap-report/2`` document (docs/gap-report.md) and the rows of its terminal summary.

:func:`build_report` assembles plain JSON types only (floats rounded, no numpy); the command
renders :func:`summary_rows` with rich. Pure.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from groundstation.gap.attribute import Candidate
from groundstation.sysid.model import OUTPUTS, theta_to_dict

SCHEMA = "heli-gap-report/2"


def _r(x: float, nd: int = 4) -> float | None:
    x = float(x)
    return round(x, nd) if np.isfinite(x) else None


def _effect_entry(c: Candidate) -> dict[str, Any]:
    h, s = c.hyp, c.score
    return {
        "effect": h.effect,
        "input": h.input,
        "output": h.output,
        "estimate": {k: _r(v, 6) for k, v in h.estimate.items()},
        "gap_before": _r(s.gap_before),
        "gap_after": _r(s.gap_after),
        "shrink_pct": _r(s.shrink_pct, 2),
        "score": _r(s.score_pct, 3),
        "p_value": _r(s.p_value, 6),
        "shrink_interval": [_r(s.shrink_interval[0], 2), _r(s.shrink_interval[1], 2)],
        "per_channel_shrink": {OUTPUTS[k]: _r(v, 2) for k, v in s.per_channel_shrink.items()},
        "evidence": c.evidence,
    }


def build_report(*, verdict: str, channels: dict, worst: list[str], windows_s: list, band: dict,
                 cond: dict, ranked: list[Candidate], others: list[Candidate], untestable: dict[str, str],
                 noise: dict, gap_ratio: np.ndarray, excitation: dict, notes: list[str],
                 given_metrics: dict | None, base_params: np.ndarray, kinematic: dict, lines: list,
                 nominal: float, n_windows: int, window_s: float, folds: int, alpha: float,
                 gap_significant: bool) -> dict[str, Any]:
    effects = [_effect_entry(c) for c in ranked]
    top = effects[0] if effects else None
    rep: dict[str, Any] = {
        "schema": SCHEMA,
        "verdict": verdict,
        "gap": {
            "channels": channels,
            "worst_channels": worst,
            "windows_s": [[_r(a, 2), _r(b, 2)] for a, b in windows_s],
            "band_hz": band.get("band_hz"),
            "band_input_coherence": _r(band.get("input_coherence", 0.0), 3),
            "conditions": cond["label"],
            "condition_stats": {k: v for k, v in cond["features"].items()},
            "significant": gap_significant,
            "gap_to_noise_ratio": {OUTPUTS[c]: _r(gap_ratio[c], 2) for c in range(8) if np.isfinite(gap_ratio[c])},
            "nominal_window_cost": _r(nominal, 6),
        },
        "effects": effects,
        "candidates": [_effect_entry(c) for c in sorted(others, key=lambda c: -c.score.score_pct)],
        "untestable": untestable,
        "shrink_interval": top["shrink_interval"] if top else None,
        "per_channel_shrink": top["per_channel_shrink"] if top else {},
        "noise_floor": {OUTPUTS[c]: {"sigma_raw": _r(noise["sigma_raw"][c], 6),
                                     "sigma_smoothed": _r(noise["sigma_smoothed"][c], 6),
                                     "nrmse_floor": _r(noise["nrmse_floor"][c], 4),
                                     **({"bridge_nrmse": _r(noise["bridge_nrmse"][c], 4)}
                                        if "bridge_nrmse" in noise else {})} for c in range(8)},
        "excitation": excitation,
        "fingerprints": {
            "kinematic_rate_offsets": {k: {"offset_rad_s": _r(v.offset_rad_s, 6), "t": _r(v.t_stat, 2),
                                           "log10_p": _r(v.log10_p, 2)} for k, v in kinematic.items()},
            "spectral_lines": [{"frequency_hz": _r(ln.frequency_hz, 3), "channels": ln.channels,
                                "ratio": _r(ln.ratio, 2), "log10_p": _r(ln.log10_p, 2),
                                "amplitude": {k: _r(v, 6) for k, v in ln.amplitude.items()}} for ln in lines],
        },
        "method": {"windows": n_windows, "window_s": window_s, "folds": folds, "alpha": alpha,
                   "base_parameters": theta_to_dict(base_params)},
        "notes": notes,
    }
    if given_metrics is not None:
        rep["gap"]["channels_model_as_given"] = given_metrics
    return rep


def summary_rows(report: dict[str, Any]) -> dict[str, list[list[str]]]:
    """Tables (title -> rows of strings) summarising a report for the terminal."""
    ch = report["gap"]["channels"]
    ratio = report["gap"].get("gap_to_noise_ratio", {})
    chan_rows = [[k, f"{v['match']:.1f}", f"{v['tic']:.3f}", f"{ratio.get(k, float('nan'))}"] for k, v in ch.items()]
    eff_rows = []
    partial = report.get("partial_findings") or []
    for e in report["effects"] + partial + report.get("candidates", [])[:4]:
        sig = "yes" if e in report["effects"] else ("partial" if e in partial else "no")
        eff_rows.append([e["effect"], e["input"] or e["output"] or "-", sig, share_text(e), f"{e['score']}",
                         f"{e['gap_before']} -> {e['gap_after']}", f"{e['shrink_pct']}",
                         (e.get("consistency") or {}).get("status", "-"), e["evidence"]])
    return {"channels": chan_rows, "effects": eff_rows}


def share_text(e: dict[str, Any]) -> str:
    """An effect's share of the gap above noise with its interval, e.g. ``62 % (48-75)``; ``-`` when none."""
    sp, iv = e.get("share_pct"), e.get("share_interval_pct")
    if sp is None:
        return "-"
    return f"{sp:.0f} %" + (f" ({iv[0]:.0f}-{iv[1]:.0f})" if iv and None not in iv else "")


def through_flight_lines(report: dict[str, Any]) -> list[str]:
    """What the report says about the flight's first and second half, in sentences."""
    tf = report.get("through_flight") or {}
    out = []
    for ch in tf.get("changes") or []:
        out.append(f"changes through the flight: {ch['effect']} {ch.get('channel') or ''}: {ch.get('why', '')}")
    for e in report.get("effects") or []:
        c = e.get("consistency") or {}
        if c.get("status") == "not_checked":
            out.append(f"{e['effect']} {e.get('input') or e.get('output') or ''}: not checked for consistency "
                       f"through the flight ({c.get('why') or 'no reason given'})")
    hv = tf.get("halves") or []
    if len(hv) == 2 and all(h.get("excess_share_pct") is not None for h in hv):
        out.append(f"gap above noise: {hv[0]['excess_share_pct']:.0f} % in the first half "
                   f"({hv[0]['t_s'][0]:.0f}-{hv[0]['t_s'][1]:.0f} s), {hv[1]['excess_share_pct']:.0f} % in the second "
                   f"({hv[1]['t_s'][0]:.0f}-{hv[1]['t_s'][1]:.0f} s)")
    return out


def frequency_section(verification: Any) -> dict[str, Any]:
    """The report's ``frequency`` section from a :class:`groundstation.freq.verify.FreqVerification` of the
    base model: where in frequency the model departs from the flight.

    ``departures``: every band of adjacent coherent points where the model's response leaves the
    data's 95 % random-error bound, worst (largest departure over the bound) first, with the mean
    magnitude (dB) and phase (deg) of model minus data; ``pairs``: Tischler's J per input-output
    pair with pass/fail and the phase-slope delay; ``unmodelled``: coherent responses the model has no
    path for; ``no_response``: one reason per pair the flight says nothing about.
    """
    doc = verification.to_json()
    departures = [{"input": p.input, "output": p.output, "f_lo_hz": _r(b.f_lo_hz, 3), "f_hi_hz": _r(b.f_hi_hz, 3),
                   "points": b.points, "magnitude_db": _r(b.magnitude_db, 2), "phase_deg": _r(b.phase_deg, 1),
                   "max_ratio": _r(b.max_ratio, 2)}
                  for p in verification.pairs for b in p.deviations]
    departures.sort(key=lambda d: -(d["max_ratio"] or 0.0))
    return {
        "J_avg": doc["J_avg"], "J_avg_good": doc["J_avg_good"],
        "pairs": [{k: p[k] for k in ("input", "output", "J", "pass", "coherent_points", "band_hz", "delay_s")}
                  for p in doc["pairs"]],
        "departures": departures,
        "unmodelled": doc["unmodelled"],
        "no_response": doc["no_response"],
        "input_delays": doc["input_delays"],
        "frequency_hz": doc["frequency_hz"], "windows_s": doc["windows_s"],
        "sample_interval_s": doc["sample_interval_s"],
    }


def frequency_rows(section: dict[str, Any], limit: int = 8) -> list[list[str]]:
    """Terminal rows of the frequency section's departures (input->output, band, dB, deg, over the bound)."""
    return [[f"{d['input']}->{d['output']}", f"{d['f_lo_hz']:.2g}-{d['f_hi_hz']:.2g} Hz", f"{d['magnitude_db']:+.1f}",
             f"{d['phase_deg']:+.0f}", f"{d['max_ratio']:.1f}x"] for d in section.get("departures", [])[:limit]]
