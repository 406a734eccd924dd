"""``diagnose(model, prepared)``: locate the gap, attribute it to a catalogue effect, decide, report.

Three stages on the prepared in-air segments, cut into windows rotating through k folds, each with
a typed result:

1. :func:`base_stage` -> :class:`Base`: the given model (or ``groundstation.sysid.identify.identify``
   when None), refined by Levenberg-Marquardt on the windows, every initial state fitted per window;
2. :func:`locate_stage` -> :class:`Located`: k-fold held-out residual of the base model per
   channel / window / band / condition (:mod:`groundstation.gap.locate`), noise floors from the raw
   data (:mod:`groundstation.gap.noise`, calibrated per channel for streams slower than the grid),
   what the flight excited;
3. :func:`attribute_stage` -> :class:`Attributed`: every hypothesis of
   :mod:`groundstation.gap.hypotheses` scored on held-out windows (nested selection, paired
   bootstrap, Bonferroni), plus the model-free fingerprints of :mod:`groundstation.gap.fingerprints`
   (spectral lines for rotor vibration, Euler kinematics for gyro bias); physical plausibility,
   practical significance, the outer re-fit of input effects and the encompassing tests
   (:mod:`groundstation.gap.candidates`);
4. :func:`decide_stage` -> :class:`Decision`: the verdict: the significant candidate with the
   largest held-out cost reduction; ``unexplained`` when none is significant while the held-out
   residual is well above its noise floor and most of the excess sits in flagged windows; else
   ``none``;

then the ``heli-gap-report/1`` dict (docs/gap-report.md) (:mod:`groundstation.gap.report`). Every threshold
is a documented field of :class:`DiagnoseConfig`; every random draw derives from ``seed``.

What it leaves to others: reading logs and preparing data (``dsp.prepare``), identification
(``sysid.identify``), files, plots and printing (the ``diagnose`` command). Pure: no IO.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np
from scipy import stats

from groundstation.dsp.velocity_check import check_horizontal
from groundstation.errors import GapError
from groundstation.freq.model_response import model_response
from groundstation.gap import (
    attribute,
    bridging,
    candidates,
    compat,
    controller,
    drift,
    fingerprints,
    hypotheses,
    locate,
    margins,
    noise,
    rebase,
    shares,
    structure,
)
from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.evaluate import Evaluator, JacobianMemo, SegmentArrays
from groundstation.gap.report import _effect_entry, build_report
from groundstation.parallel import Map, serial_map
from groundstation.sysid.identify import IdentifyConfig, identify
from groundstation.sysid.model import INPUTS, OUTPUTS, HoverModel

__all__ = ["CATALOGUE", "VERDICTS", "DiagnoseConfig", "Diagnosis", "diagnose", "run_diagnosis", "segments_from_prepared"]

CATALOGUE = ("input_delay", "rate_limit", "deadband", "ground_effect", "wind_gust", "quadratic_drag",
             "gyro_bias", "rotor_vibration", "velocity_latency")
#: every verdict a report can carry
VERDICTS = (*CATALOGUE, "stabilising_controller", "sensor_error", "unexplained", "none")


@dataclass
class Diagnosis:
    """The report plus the arrays the command plots."""

    report: dict[str, Any]
    arrays: dict[str, Any] = field(default_factory=dict)


def segments_from_prepared(prepared: Any, share_min: float = DiagnoseConfig.channel_share_min) -> tuple[list[SegmentArrays], np.ndarray]:
    """SegmentArrays of a ``dsp.prepare.PreparedData`` and the channels available in all of them
    (measured in at least ``share_min`` of the in-air time)."""
    segs, avails = [], []
    for s in prepared.segments:
        n = np.asarray(s.t_s).shape[0]
        alt = getattr(s, "alt_m", None)
        alt = np.full(n, np.nan) if alt is None else np.asarray(alt, float)
        raw = getattr(s, "outputs_raw", None)
        out = np.asarray(s.outputs, float)
        meas = s.measured_mask() if getattr(s, "measured", None) is not None else None
        br = getattr(s, "inputs_bridged", None)
        segs.append(SegmentArrays(t_s=np.asarray(s.t_s, float), inputs=np.asarray(s.inputs, float),
                                  outputs=out, outputs_raw=out if raw is None else np.asarray(raw, float),
                                  alt_m=alt, flight=int(getattr(s, "flight", 0)), measured=meas,
                                  bridged=None if br is None else np.asarray(br, bool)))
        a = getattr(s, "available", None)
        avails.append(np.isfinite(out).all(axis=0) if a is None else np.asarray(a, bool))
    # channels measured in most of the data are kept; segments lacking one of them are left out
    if segs:
        dur = np.array([s.t_s.shape[0] for s in segs], float)
        share = (np.array(avails, float) * dur[:, None]).sum(axis=0) / dur.sum()
        avail = share >= share_min
        keep = [i for i, a in enumerate(avails) if a[avail].all()]
        segs = [segs[i] for i in keep]
    else:
        avail = np.zeros(8, bool)
    # a channel that is all-NaN or constant is not available either
    for c in range(8):
        y = np.concatenate([s.outputs[:, c] for s in segs]) if segs else np.zeros(0)
        if y.size == 0 or not np.isfinite(y).all() or np.nanstd(y) == 0:
            avail[c] = False
    cleaned = []
    for s in segs:
        cleaned.append(SegmentArrays(t_s=s.t_s, inputs=np.nan_to_num(s.inputs),
                                     outputs=np.where(avail, np.nan_to_num(s.outputs), 0.0),
                                     outputs_raw=np.where(avail, np.nan_to_num(s.outputs_raw), 0.0),
                                     alt_m=s.alt_m, flight=s.flight,
                                     measured=None if s.measured is None else s.measured | ~avail,
                                     bridged=s.bridged))
    return cleaned, avail


def _grid_offsets(segs: list[SegmentArrays], dt_s: float) -> list[int]:
    """Each segment's first grid index on its flight's grid (noise estimates read one phase of a
    slower stream the same way in every segment, wherever holes of the link split them)."""
    return noise.grid_offsets([float(s.t_s[0]) for s in segs], [s.flight for s in segs], dt_s)


def _trims(prepared: Any) -> np.ndarray:
    tr = getattr(prepared, "output_trim", None)
    if tr is None:
        return np.zeros(8)
    if isinstance(tr, dict):
        return np.array([float(tr.get(k, 0.0) or 0.0) for k in OUTPUTS])
    arr = np.asarray(tr, float).ravel()
    return arr if arr.shape == (8,) else np.zeros(8)


@dataclass(frozen=True)
class Base:
    """Stage 1: the windows and the refined base model on them."""

    ev: Evaluator
    segs: list[SegmentArrays]
    avail: np.ndarray  # (8,) output channels measured
    dt_s: float
    notes: list[str]
    given_metrics: dict | None  # the model as given (before the polish), None when identified here


@dataclass(frozen=True)
class Located:
    """Stage 2: where the base model departs, and what the flight excited."""

    nf: dict[str, np.ndarray]  # noise floors (:func:`groundstation.gap.noise.noise_floor`)
    out_excited: np.ndarray  # (8,)
    in_excited: np.ndarray  # (4,)
    yhat_ho: np.ndarray  # held-out prediction (W, L, 8)
    chan: dict  # per-channel match / Theil
    energy_w: np.ndarray  # (W,) held-out residual energy per window
    flag: np.ndarray  # (W,) flagged windows
    nominal: float  # nominal window energy
    windows_s: list
    band: dict
    cond: dict
    gap_ratio: np.ndarray  # (8,) held-out NRMSE over noise floor
    worst: list[str]
    gap_significant: bool
    flagged_share: float  # share of the excess residual energy in flagged windows
    out_stride: np.ndarray | None  # (8,) grid steps between samples of each output's own stream
    lines: list[fingerprints.Line] = field(default_factory=list)  # rotor lines of the raw residual
    spectra: dict = field(default_factory=dict)  # their spectra (spectral_lines)


@dataclass(frozen=True)
class Attributed:
    """Stage 3: every candidate, scored and tested."""

    ctx: hypotheses.Context
    hyps: list[hypotheses.Hypothesis]
    candidates: list[attribute.Candidate]
    kin: dict
    lines: list[fingerprints.Line]
    spectra: Any
    crit: float  # per-test significance level (Bonferroni)


@dataclass(frozen=True)
class Decision:
    """Stage 4: the verdict and the named effects."""

    verdict: str
    ranked: list[attribute.Candidate]  # named, best first
    others: list[attribute.Candidate]  # scored, not named
    untestable: dict[str, str]
    excitation: dict
    unexplained: dict | None  # evidence when the verdict is "unexplained" (else None)


def diagnose(model: HoverModel | None, prepared: Any, *, seed: int = 0,
             config: DiagnoseConfig | None = None) -> dict[str, Any]:
    """The ``heli-gap-report/1`` gap report of ``model`` on ``prepared`` (see module docstring)."""
    return run_diagnosis(model, prepared, seed=seed, config=config).report


def run_diagnosis(model: HoverModel | None, prepared: Any, *, seed: int = 0,
                  config: DiagnoseConfig | None = None, pmap: Map = serial_map) -> Diagnosis:
    """Like :func:`diagnose` but also returns the arrays behind the report (for plots). ``pmap``: a
    map over worker processes (:func:`groundstation.parallel.worker_map`) for the base model's
    identification and the catalogue scans; the report is the same with any map."""
    cfg = config or DiagnoseConfig()
    rng = np.random.default_rng(seed)
    comp, prepared = compat_stage(prepared, cfg)
    base = base_stage(model, prepared, cfg, seed, pmap)
    loc = locate_stage(base, prepared, cfg)
    att = attribute_stage(base, loc, prepared, cfg, rng, seed, pmap)
    again = _base_searched_again(base, att, prepared, cfg, seed, pmap)
    if again is not None:
        base, rng = again, np.random.default_rng(seed)
        loc = locate_stage(base, prepared, cfg)
        att = attribute_stage(base, loc, prepared, cfg, rng, seed, pmap)
    tests = structure_stage(base, loc, att, cfg, rng)
    dec = decide_stage(base, loc, att, comp, tests, cfg)
    dec, verdict_info = verdict_stage(base, loc, att, dec, tests, cfg, np.random.default_rng((seed, 26)))
    ev = base.ev
    report = build_report(
        verdict=dec.verdict, channels=loc.chan, worst=loc.worst, windows_s=loc.windows_s, band=loc.band,
        cond=loc.cond, ranked=dec.ranked, others=dec.others, untestable=dec.untestable, noise=loc.nf,
        gap_ratio=loc.gap_ratio, excitation=dec.excitation, notes=base.notes, given_metrics=base.given_metrics,
        base_params=ev.theta0, kinematic=att.kin, lines=att.lines, nominal=loc.nominal, n_windows=ev.W,
        window_s=cfg.window_s, folds=cfg.folds, alpha=cfg.alpha, gap_significant=loc.gap_significant,
    )
    report["tested"] = sorted(h.effect for h in att.hyps if h.testable and h.effect not in dec.untestable) + (
        ["rotor_vibration"] if any(base.avail[3:]) else [])
    report["data_compatibility"] = compat_section(comp)
    report["unexplained"] = dec.unexplained
    report["link_quality"] = {**dict(getattr(prepared, "link_quality", {}) or {}), "windows": int(ev.W),
                              "windows_with_holes": 0 if ev.M is None else int((~ev.M.all(axis=(1, 2))).sum())}
    # where and how the model departs, whatever the verdict, when the departure is above the noise
    report["departure"] = (dec.unexplained or _unexplained_evidence(base, loc, tests, cfg)) \
        if loc.gap_significant else None
    info = dict(verdict_info["report"])
    report["notes"] = list(report.get("notes", [])) + info.pop("notes_add")
    report.update(info)
    for e, c in zip(report["effects"], dec.ranked, strict=True):
        e.update(verdict_info["per_effect"].get(id(c), {}))
    if model is not None and controller.may_be_commands(model):
        _controller_finding(report, prepared, model, loc, cfg, seed, pmap)
    report["verdict_margin"] = margin_stage(att, loc, dec, verdict_info["rule"], cfg, seed)
    if report["verdict_margin"]["borderline"]:
        report["notes"].append(report["verdict_margin"]["note"])
    report["structure_tests"] = [{**dataclasses.asdict(t), "effect_to_noise": round(t.effect_to_noise, 2)
                                  if np.isfinite(t.effect_to_noise) else None} for t in tests]
    arrays = {"t_s": ev.T, "Y": ev.Y, "Yraw": ev.Yraw, "yhat": loc.yhat_ho, "mask": ev.mask, "flag": loc.flag,
              "spectra": att.spectra, "band": loc.band, "candidates": att.candidates, "evaluator": ev,
              "ctx": att.ctx}
    if ev.memo is not None:
        ev.memo.clear()  # the Jacobians shared between the stages: not kept with the report
    return Diagnosis(report=report, arrays=arrays)


def _base_searched_again(base: Base, att: Attributed, prepared: Any, cfg: DiagnoseConfig, seed: int,
                         pmap: Map) -> Base | None:
    """The base searched for again without the first named effect's velocity latency, when the
    diagnosis identified the base and that search lowers its cost (:mod:`groundstation.gap.rebase`);
    None otherwise."""
    ranked = rank_named(att.candidates)
    if base.given_metrics is not None or not ranked or ranked[0].hyp.effect != "velocity_latency":
        return None
    latency_s = float(ranked[0].hyp.estimate["latency_s"])
    ev2, cost2, cost = rebase.searched_again(base.ev, base.segs, latency_s, prepared, cfg, seed, pmap)
    if not rebase.lower(cost2, cost, cfg):
        return None
    note = (f"base model searched for again with the {1000 * latency_s:.0f} ms velocity latency taken off the "
            f"velocities: its cost on this flight is {100 * (1 - cost2 / cost):.0f} % lower than the first "
            "search's; the diagnosis is against it")
    return dataclasses.replace(base, ev=ev2, notes=[*base.notes, note])


def _controller_finding(report: dict[str, Any], prepared: Any, model: HoverModel, loc: Located, cfg: DiagnoseConfig,
                        seed: int, pmap: Map) -> None:
    """"A stabilising controller in the loop" as a finding of the report, with its share
    (:mod:`groundstation.gap.controller`), looked for only when the model's inputs may be commands.

    Named when the inputs follow the model's output error and the command-response structure removes
    a share of the held-out gap above noise whose interval (over contiguous folds) is above zero. It
    is ranked with the named effects by its share; it is the verdict when it is first and the share
    rule holds for it (not clearly below ``explained_share_min_pct``), or when nothing else is named
    (the verdict was ``none`` or ``unexplained``). Changes ``report`` in place."""
    kind = "attitude_command" if (getattr(model, "command", None) or {}).get("kind") == "attitude_command" \
        else "rate_command"
    try:
        f = controller.stabilising_controller(prepared, model, sigma=loc.nf["sigma_smoothed"], k=cfg.folds, kind=kind,
                                              pmap=pmap, n_boot=cfg.share_n_boot, seed=seed, config=cfg)
    except (ValueError, ArithmeticError) as exc:
        report["notes"] = list(report.get("notes", [])) + [f"a stabilising controller in the loop not checked: {exc}"]
        return
    report["controller"] = None if f is None else {k: v for k, v in f.items() if k != "describe"}
    if f is None or not f["named"]:
        return
    entry = {k: f[k] for k in ("effect", "input", "output", "estimate", "gap_before", "gap_after", "shrink_pct",
                               "score", "evidence", "share_pct", "share_interval_pct")}
    entry["consistency"] = {"status": "not_checked", "why": f"checked over {f['folds']} contiguous folds of the flight"}
    sh = report["shares"]
    lo, hi = f["share_interval_pct"]
    rule_ok = hi >= cfg.explained_share_min_pct or not loc.gap_significant
    others = sh.get("explained_pct") if report["effects"] else None
    first = rule_ok and (others is None or f["share_pct"] > others)
    x = min(max(f["share_pct"], 0.0), 100.0)
    text = (f"{x:.0f} % of the gap above noise is explained by a stabilising controller in the loop (interval "
            f"{min(max(lo, 0.0), 100.0):.0f} to {min(max(hi, 0.0), 100.0):.0f} % over {f['folds']} contiguous folds): "
            f"the inputs are commands to a stabilised aircraft, identify it with the command-response structure")
    if first:
        report["effects"] = [entry] + list(report["effects"])
        if report["verdict"] == "unexplained" and report.get("partial_findings"):
            report["effects"] += list(report["partial_findings"])
            report["partial_findings"] = []
        names = ", ".join(e["effect"].replace("_", " ") + (f" {e['input'] or e['output']}" if e["input"] or e["output"]
                                                           else "") for e in report["effects"][1:])
        report["verdict"] = controller.EFFECT
        report["unexplained"] = None
        # the named finding's share (its own protocol: contiguous folds) is the report's explained share
        sh.update(explained_pct=round(f["share_pct"], 1), interval_pct=[round(lo, 1), round(hi, 1)],
                  unexplained_pct=round(100.0 - x, 1), partial_explained_pct=None,
                  per_effect=[{"effect": "stabilising controller", "share_pct": entry["share_pct"],
                               "interval_pct": entry["share_interval_pct"]}] + list(sh.get("per_effect") or []))
        sh["headline"] = text + (f"; beside it: {names}" if names else "")
    elif report["verdict"] == "unexplained":
        report["partial_findings"] = list(report.get("partial_findings", [])) + [entry]
        sh["headline"] += f"; {text.replace(' is explained by', ' is removed by')}, below the share needed to name it"
    else:
        report["effects"] = list(report["effects"]) + [entry]
        sh["headline"] += f"; and {x:.0f} % by a stabilising controller in the loop"


def compat_stage(prepared: Any, cfg: DiagnoseConfig) -> tuple[compat.Compatibility, Any]:
    """Data compatibility before blame: the kinematic checks, and the data with found scale errors undone."""
    segs, avail = segments_from_prepared(prepared, cfg.channel_share_min)
    stride = getattr(prepared, "native_stride", None)
    sigma = noise.raw_noise_std([s.raw_measured() for s in segs], stride(OUTPUTS) if stride is not None else None,
                                cfg.noise_calibration_seed, _grid_offsets(segs, float(prepared.dt_s))) \
        if segs else np.full(8, np.nan)
    comp = compat.check(segs, avail, float(prepared.dt_s), sigma, _trims(prepared), window_s=cfg.compat_window_s,
                        alpha=cfg.alpha, min_windows=cfg.min_windows,
                        min_effect_to_noise=cfg.compat_min_effect_to_noise, z_agree=cfg.compat_z_agree,
                        max_slope=cfg.compat_max_slope,
                        horizontal=_horizontal_checks(prepared, cfg))
    fac = comp.scale_corrections()
    if not fac:
        return comp, prepared
    cols = np.ones(8)
    for c, f in fac.items():
        cols[c] = f
    new_segs = []
    for s in prepared.segments:
        s2 = copy.copy(s)
        for name in ("outputs", "outputs_raw"):
            if getattr(s, name, None) is not None:
                object.__setattr__(s2, name, np.asarray(getattr(s, name), float) * cols)
        new_segs.append(s2)
    p2 = copy.copy(prepared)
    object.__setattr__(p2, "segments", new_segs)
    notes = list(getattr(prepared, "notes", []) or [])
    notes.append("sensor scale errors found by data compatibility were undone before the diagnosis: "
                 + "; ".join(f"{f.kind} on {f.channel} {100 * f.estimate:+.1f}%" for f in comp.findings))
    object.__setattr__(p2, "notes", notes)
    return comp, p2


def _horizontal_checks(prepared: Any, cfg: DiagnoseConfig) -> list:
    """The horizontal velocities against the attitude (:mod:`groundstation.dsp.velocity_check`) on the
    prepared segments; empty when they do not carry what the check needs."""
    segs = [s for s in prepared.segments if hasattr(s, "available") and hasattr(s, "n")]
    if not segs or len(segs) < len(prepared.segments):
        return []
    return [c for c in check_horizontal(segs, float(prepared.dt_s), window_s=cfg.compat_window_s)
            if c.channel in ("u", "v")]


def compat_section(comp: compat.Compatibility) -> dict[str, Any]:
    """The ``data_compatibility`` block of the report."""
    return {
        "estimates": [{"sensor": e.sensor, "parameter": e.parameter, "value": round(e.value, 6), "se": round(e.se, 6),
                       "p_value": float(f"{e.p_value:.3g}")} for e in comp.estimates],
        "findings": [{"kind": f.kind, "channel": f.channel, "estimate": round(f.estimate, 4), "se": round(f.se, 4),
                      "p_value": float(f"{f.p_value:.3g}"), "effect_to_noise": round(f.effect_to_noise, 2),
                      "significant": True, "evidence": f.evidence} for f in comp.findings],
        "untestable": comp.untestable,
    }


def base_stage(model: HoverModel | None, prepared: Any, cfg: DiagnoseConfig, seed: int,
               pmap: Map = serial_map) -> Base:
    """Windows of the in-air data and the base model refined on them (identified when ``model`` is None)."""
    segs, avail = segments_from_prepared(prepared, cfg.channel_share_min)
    dt = float(prepared.dt_s)
    L = int(round(cfg.window_s / dt))
    segs = [s for s in segs if s.t_s.shape[0] >= L]
    if not segs:
        raise GapError(f"diagnose.window_s = {cfg.window_s:g}: no in-air segment is that long, nothing to diagnose")
    if avail.sum() < 2:
        raise GapError(f"too few measured output channels to diagnose: {[OUTPUTS[c] for c in np.flatnonzero(avail)]}")
    notes: list[str] = list(getattr(prepared, "notes", []) or [])
    identified_here = model is None
    if model is None:
        # the diagnosis blames whatever the base model gets wrong: a search stuck in a wrong basin
        # would be reported as an effect, so it pays for independent searches here. The base model keeps
        # one configuration (no held-out choice between settings): the scans score the effects against
        # the model the diagnosis's own windows are built for
        model = identify(prepared, seed=seed, config=IdentifyConfig(search_restarts=cfg.identify_restarts,
                                                                    select_candidates=""), pmap=pmap)
        notes.append("base model identified on the same data; hold-out by k-fold re-fit over windows")
    theta_given = model.theta
    ev = Evaluator(segs, dt, theta_given, avail, window_s=cfg.window_s, folds=cfg.folds, ridge=cfg.ridge,
                   start_s=cfg.window_start_s, memo=JacobianMemo())
    if ev.W < cfg.min_windows:
        raise GapError(f"diagnose.window_s = {cfg.window_s:g}: too little in-air data, {ev.W} windows "
                       f"(diagnose.min_windows = {cfg.min_windows})")
    given_metrics = None
    if not identified_here:
        yg = ev.simulate(theta_given)[0]
        given_metrics = locate.channel_metrics(ev.Y, yg, ev.score_mask, avail)
    ev.refine(cfg.refine_iterations, cfg.refine_ridge)
    return Base(ev=ev, segs=segs, avail=avail, dt_s=dt, notes=notes, given_metrics=given_metrics)


def locate_stage(base: Base, prepared: Any, cfg: DiagnoseConfig) -> Located:
    """Noise floors and excitation, then the held-out gap per channel, window, band and condition."""
    ev, segs, avail, dt = base.ev, base.segs, base.avail, base.dt_s
    # channels sent slower than the grid are interpolated: their noise floors are calibrated for it
    stride = getattr(prepared, "native_stride", None)
    out_stride = stride(OUTPUTS) if stride is not None else None
    in_stride = stride(INPUTS) if stride is not None else None
    # noise from measured samples only: a straight line bridged across a hole of the link has none;
    # and without the rotor lines, which are signal (a vibration), not sensor noise
    offs = _grid_offsets(segs, dt)
    lines, spectra = _rotor_lines(base, out_stride, cfg)
    chunk = int(round(cfg.window_s / dt))
    nf = noise.noise_floor([fingerprints.without_lines(s.raw_measured(), dt, lines, chunk) for s in segs],
                           [fingerprints.without_lines(s.measured_only(s.outputs), dt, lines, chunk) for s in segs],
                           out_stride, cfg.noise_calibration_seed, offs)
    out_excited = avail & (nf["signal_std"] > cfg.excitation_snr * nf["sigma_smoothed"])
    u_all = np.concatenate([s.inputs for s in segs])
    u_noise = noise.raw_noise_std([s.measured_only(s.inputs) for s in segs], in_stride, cfg.noise_calibration_seed,
                                  offs)
    u_std = u_all.std(axis=0)
    in_excited = (u_std > cfg.excitation_snr * np.maximum(u_noise, 1e-12)) & (u_std > cfg.input_std_min)

    # the straight lines over holes of the link drive the model wrong: a perfect model shows that error too
    bridge = bridging.bridge_error_nrmse(ev, segs, ev.theta0, np.random.default_rng(cfg.noise_calibration_seed))
    nf = {**nf, "nrmse_sensor": nf["nrmse_floor"], "bridge_nrmse": bridge,
          "nrmse_floor": np.sqrt(nf["nrmse_floor"] ** 2 + bridge ** 2)}
    e_w = ev.heldout_residual(ev.r0)  # weighted
    e = e_w / np.where(ev.w8 > 0, ev.w8, 1.0)
    chan = locate.channel_metrics(ev.Y, ev.Y - e, ev.score_mask, avail)
    energy_w = (e_w ** 2).sum(axis=(1, 2))
    flag, nominal = locate.flag_windows(energy_w)
    windows_s = locate.merge_intervals([(float(ev.T[i, 0]), float(ev.T[i, -1] + dt)) for i in np.flatnonzero(flag)])
    noise_psd = 2 * dt * nf["sigma_smoothed"] ** 2
    band = locate.worst_band(e[:, ev.start:], ev.U[:, ev.start:], dt, noise_psd, ev.w8)
    cond = locate.conditions(energy_w, _window_features(ev), alpha=cfg.conditions_alpha)
    ho_nrmse = np.array([np.sqrt((e_w[:, ev.start:, c] ** 2).sum() / ev.energy[:, c].sum())
                         if ev.energy[:, c].sum() > 0 else np.nan for c in range(8)])
    gap_ratio = ho_nrmse / np.where(nf["nrmse_floor"] > 0, nf["nrmse_floor"], np.nan)
    order = np.argsort(-np.nan_to_num(gap_ratio, nan=-1))
    worst = [OUTPUTS[c] for c in order[:2] if avail[c]]
    excess = np.maximum(energy_w - nominal, 0.0)
    flagged_share = float(excess[flag].sum() / excess.sum()) if excess.sum() > 0 else 0.0
    return Located(nf=nf, out_excited=out_excited, in_excited=in_excited, yhat_ho=ev.Y - e, chan=chan,
                   energy_w=energy_w, flag=flag, nominal=nominal, windows_s=windows_s, band=band, cond=cond,
                   gap_ratio=gap_ratio, worst=worst, gap_significant=_gap_significant(gap_ratio, out_excited, cfg),
                   flagged_share=flagged_share,
                   out_stride=None if out_stride is None else np.asarray(out_stride, float), lines=lines, spectra=spectra)


def _rotor_lines(base: Base, out_stride: Any, cfg: DiagnoseConfig) -> tuple[list[fingerprints.Line], dict]:
    """Narrow lines in the base model's raw residual (:func:`groundstation.gap.fingerprints.spectral_lines`),
    looked for in the body rates and attitude only: the velocities come from a slower position estimate
    resampled to the grid, whose interpolation images are not vibration. A line above the Nyquist
    frequency of the stream a channel was sent at is an interpolation image and is dropped."""
    ev, dt = base.ev, base.dt_s
    resid_raw = (ev.Yraw - ev.simulate(ev.theta0)[0])[:, ev.start:]
    line_ch = base.avail & (np.arange(8) >= 3)
    lines, spectra = fingerprints.spectral_lines(resid_raw, ev.U[:, ev.start:], dt, line_ch, alpha=cfg.alpha,
                                                 response=_response(ev.theta0, dt),
                                                 reach_factor=cfg.line_stick_reach_factor)
    stride = None if out_stride is None else np.asarray(out_stride, float)
    return fingerprints.resolvable_lines(lines, stride, dt), spectra


_INPUT_SCANS = ("input_delay", "rate_limit", "deadband")
_OTHER_SCANS = ("velocity_latency", "gyro_bias", "quadratic_drag", "ground_effect", "wind_gust")


def _scan_one(ctx: hypotheses.Context, in_ch: list[int], name: str) -> tuple[hypotheses.Hypothesis, dict, dict]:
    """One catalogue scan (``hypotheses.scan_<name>``) and what it cached on ``ctx`` (module-level, so
    worker processes can run it on their copy of ``ctx``)."""
    fn = getattr(hypotheses, f"scan_{name}")
    h = fn(ctx, in_ch) if name in _INPUT_SCANS else fn(ctx)
    return h, dict(ctx.change), dict(ctx.blocks)


def _scan_all(ctx: hypotheses.Context, in_excited: np.ndarray, pmap: Map = serial_map) -> list[hypotheses.Hypothesis]:
    """Every catalogue hypothesis scanned on the base windows (input effects only on excited inputs).
    The scans are independent and deterministic: ``pmap`` may run them in worker processes; what
    each cached on its copy of ``ctx`` comes back into ``ctx``."""
    in_ch = [c for c in range(4) if in_excited[c]]
    hyps: list[hypotheses.Hypothesis] = []
    if not in_ch:
        for name in _INPUT_SCANS:
            hyps.append(hypotheses.Hypothesis(name, testable=False, reason="no excited input channel"))
    names = (_INPUT_SCANS if in_ch else ()) + _OTHER_SCANS
    for h, change, blocks in pmap(partial(_scan_one, ctx, in_ch), names):
        ctx.change.update(change)
        ctx.blocks.update(blocks)
        hyps.append(h)
    return hyps


def attribute_stage(base: Base, loc: Located, prepared: Any, cfg: DiagnoseConfig, rng: np.random.Generator,
                    seed: int, pmap: Map = serial_map) -> Attributed:
    """Scan, score and test every catalogue hypothesis; the fingerprints; plausibility; encompassing."""
    ev, segs, avail, dt, nf = base.ev, base.segs, base.avail, base.dt_s, loc.nf
    ctx = hypotheses.Context(ev, segs, cfg=cfg)
    ctx.pwm_per_unit = float(getattr(prepared, "pwm_per_unit", 500.0))
    ctx.noise_unit = hypotheses.noise_unit(ev, nf["sigma_smoothed"])
    hyps = _scan_all(ctx, loc.in_excited, pmap)

    # model-free fingerprints
    yfit = ev.simulate(ev.theta0)[0]
    resid_raw = (ev.Yraw - yfit)[:, ev.start:]
    lines, spectra = loc.lines, loc.spectra
    kin = fingerprints.kinematic_rate_offsets(ev.Y, dt, avail, trims=_trims(prepared))

    for h in hyps:
        if h.effect == "wind_gust" and h.testable:
            # horizontal air speed the velocity sensors resolve: excitation_snr x their white noise
            # and no less than calm air's upper bound: a smaller fitted air velocity is slow model error
            h.extra["resolvable_m_s"] = max(float(cfg.excitation_snr * np.hypot(nf["sigma_raw"][0], nf["sigma_raw"][1])),
                                            cfg.gust_min_rms_m_s)
    crit = cfg.alpha / (sum(h.testable for h in hyps) + 1)
    results = []
    for h in hyps:
        if not h.testable or h.sse is None:
            continue
        b = h.extra.get("base_sse", ctx.base_sse)
        s = attribute.score(b, h.sse, ev.energy, h.channels, rng, n_boot=min(cfg.n_boot, cfg.score_n_boot), test_n_boot=cfg.n_boot)
        s.p_value = candidates.p_value(h, ctx, b, rng, cfg)
        results.append((h, s))
    if lines:  # rotor vibration: scored on the raw residual of the line channels
        results.append(candidates.vibration_candidate(lines, resid_raw, ev, dt, np.random.default_rng((seed, 1)), cfg))
    cands = _significance(results, kin, lines, crit, cfg)
    for c in cands:
        if c.significant and c.hyp.effect in hypotheses.INPUT_EFFECTS:
            for _ in range(cfg.outer_iterations):
                before = dict(c.hyp.extra["label"])
                candidates.refit_input_effect(c, ctx, segs, rng, cfg, crit)
                if c.hyp.extra["label"] == before or not c.significant:
                    break
            c.evidence = candidates.evidence(c.hyp, c.score, kin, lines)
    candidates.encompass(cands, ctx, segs, rng, cfg, crit)
    ranked = rank_named(cands)
    kin_sig = {k for k, v in kin.items() if v.log10_p < np.log10(crit)}
    candidates.conditional_names(ranked, cands, ctx, segs, [c for c in range(4) if loc.in_excited[c]], kin_sig,
                                 rng, cfg, crit, np.asarray(nf["nrmse_floor"], float), pmap)
    return Attributed(ctx=ctx, hyps=hyps, candidates=cands, kin=kin, lines=lines, spectra=spectra, crit=crit)


def _response(theta: np.ndarray, dt_s: float) -> Any:
    """``f_hz -> (F, 8, 4)`` the base model's discrete frequency response (for the spectral-line test)."""
    return partial(model_response, np.asarray(theta, float), dt_s=dt_s)


def rank_named(cands: list[attribute.Candidate]) -> list[attribute.Candidate]:
    """The named candidates, best first: by held-out gain, an effect named as a second one (given a
    first, see :func:`groundstation.gap.candidates.conditional_names`) after the others."""
    return sorted((c for c in cands if c.significant),
                  key=lambda c: (bool(c.hyp.extra.get("second_to")), -c.score.score_pct))


def _significance(results: list, kin: dict, lines: list, crit: float, cfg: DiagnoseConfig) -> list[attribute.Candidate]:
    """Candidates with their first significance call (p below ``crit``, practical gain, physics)."""
    # gyro bias: the kinematic evidence decides p and q (model-free); r relies on the model scan
    kin_sig = {k: v for k, v in kin.items() if v.log10_p < np.log10(crit)}
    cands: list[attribute.Candidate] = []
    for h, s in results:
        is_sig = s.p_value < crit and candidates.gain_ok(s, cfg) and candidates.physical(h, cfg)
        if h.effect == "gyro_bias" and h.output in ("p", "q"):
            is_sig = h.output in kin_sig and is_sig
        cands.append(attribute.Candidate(h, s, bool(is_sig), candidates.evidence(h, s, kin, lines)))
    # a significant kinematic offset on a channel the model scan did not pick still counts
    if kin_sig:
        best_k = min(kin_sig.values(), key=lambda r: r.log10_p)
        gb = next((c for c in cands if c.hyp.effect == "gyro_bias"), None)
        if gb is not None and gb.hyp.output != best_k.channel:
            gb.hyp.output = best_k.channel
            gb.hyp.estimate = {"bias_rad_s": best_k.offset_rad_s}
            gb.significant = candidates.gain_ok(gb.score, cfg)
            gb.evidence = candidates.evidence(gb.hyp, gb.score, kin, lines)
    return cands


def structure_stage(base: Base, loc: Located, att: Attributed, cfg: DiagnoseConfig,
                    rng: np.random.Generator) -> list[structure.StructureTest]:
    """Held-out tests of structure the linear model cannot have (input asymmetry, amplitude dependence),
    then, when both a structure and catalogue effects are significant, which of them explains the other
    (:func:`_structure_against_named`)."""
    floor = np.asarray(loc.nf["nrmse_floor"], float)
    tests = structure.nonlinear_input_tests(att.ctx, loc.in_excited, rng, cfg, floor)
    if any(t.significant for t in tests) and any(c.significant for c in att.candidates):
        _structure_against_named(base, att, tests, structure.structure_crit(loc.in_excited, cfg), cfg, rng, floor)
    return tests


def _structure_context(t: structure.StructureTest, base: Base, att: Attributed, cfg: DiagnoseConfig,
                       rng: np.random.Generator) -> hypotheses.Context:
    """A context whose base model has structure ``t`` in its input, re-identified around it.

    Like an input effect's outer re-fit: the base was identified without the structure and absorbed
    part of it, so the coefficient found around it is biased towards none; the base is re-fitted
    (Levenberg-Marquardt) with the structure in place and the coefficient estimated again on it,
    up to ``outer_iterations`` times.
    """
    ev = base.ev
    coef = t.coefficient
    for it in range(cfg.outer_iterations + 1):
        segs_s = structure.apply_structure(dataclasses.replace(t, coefficient=coef), base.segs, ev)
        ev_s = Evaluator(segs_s, ev.dt_s, ev.theta0, ev.available, window_s=ev.L * ev.dt_s, folds=ev.folds,
                         ridge=ev.ridge, start_s=ev.start_s)
        ev_s.refine(cfg.refit_iterations, cfg.refine_ridge)
        ctx_s = hypotheses.Context(ev_s, segs_s, cfg=cfg)
        ctx_s.pwm_per_unit = att.ctx.pwm_per_unit
        ctx_s.noise_unit = att.ctx.noise_unit
        if it == cfg.outer_iterations:
            break
        more = structure.retest(ctx_s, [t], rng, cfg, 1.0)[0]
        if not more.score_pct > 0 or abs(more.coefficient) < 0.1 * abs(coef):
            break
        coef += more.coefficient
    return ctx_s


def _effect_given_structure(c: attribute.Candidate, t: structure.StructureTest, base: Base, att: Attributed,
                            cfg: DiagnoseConfig, rng: np.random.Generator) -> tuple[bool, float, str]:
    """Is catalogue effect ``c`` still significant once structure ``t`` is in the model (base re-fitted)?"""
    ctx_s = _structure_context(t, base, att, cfg, rng)
    h = candidates.rescan(c, ctx_s)
    if h is None or h.sse is None or not h.testable:
        return True, float("inf"), "cannot be re-tested with the structure in the model"
    h.extra = {**c.hyp.extra, **h.extra}
    b = h.extra.get("base_sse", ctx_s.base_sse) if h.effect == "wind_gust" else ctx_s.base_sse
    s = attribute.score(b, h.sse, ctx_s.ev.energy, h.channels, rng, n_boot=min(cfg.n_boot, cfg.score_n_boot), test_n_boot=cfg.n_boot)
    s.p_value = candidates.p_value(h, ctx_s, b, rng, cfg)
    ok = bool(s.p_value < att.crit and candidates.gain_ok(s, cfg) and candidates.physical(h, cfg))
    return ok, float(s.score_pct), f"{s.score_pct:+.1f}% held-out (p={s.p_value:.2g}) with the {t.input} {t.kind.replace('_', ' ')} in"


def _structure_against_named(base: Base, att: Attributed, tests: list[structure.StructureTest], crit_s: float,
                             cfg: DiagnoseConfig, rng: np.random.Generator, floor: np.ndarray | None = None) -> None:
    """Encompassing tests between the significant structures and the best named catalogue effect.

    A structure the linear model cannot have (an asymmetric or amplitude-dependent input gain) and a
    catalogue effect can mimic each other (a deadband is an amplitude-dependent gain; a per-window air
    velocity soaks up an asymmetric response). Both ways round, on held-out data: the structure tests
    again with the effect in the model (does the effect remove the structure?), and the effect's scan
    again with the structure in the model and the base re-fitted (does the effect add anything?).
    The effect stays named when it removes the structure; when the structure stays it is withheld
    (the structure is left unexplained) unless it adds to the structure more than the structure adds
    to it. An air mass (its own within-window protocol) and a rotor line (a raw-residual fingerprint)
    cannot be put into the model the structure is tested in: for them the larger held-out gain decides.
    Changes the candidates in place (``significant``, ``evidence``).
    """
    ranked = rank_named(att.candidates)
    sig = sorted((t for t in tests if t.significant), key=lambda t: -t.score_pct)
    top = ranked[0]
    if top.hyp.effect == "rotor_vibration":
        keep = top.score.score_pct >= sig[0].score_pct
        why = f"the structure explains more of the held-out cost ({sig[0].score_pct:+.1f}% vs {top.score.score_pct:+.1f}%)"
    else:
        cctx = candidates.conditioned_context(top, att.ctx, base.segs)
        if top.hyp.effect == "wind_gust":
            keep, why = _air_mass_against_structure(top, sig[0], base, att, cfg, rng)
        elif cctx is None:
            keep = top.score.score_pct >= sig[0].score_pct
            why = (f"the {sig[0].input} {sig[0].kind.replace('_', ' ')} (outside the catalogue) explains "
                   f"{sig[0].score_pct:+.1f}% of the held-out cost, the {top.hyp.effect} {top.score.score_pct:+.1f}%")
        else:
            left = [t for t in structure.retest(cctx, sig, rng, cfg, crit_s, floor) if t.significant]
            if not left:
                keep, why = True, f"it removes the {sig[0].input} {sig[0].kind.replace('_', ' ')} (outside the catalogue)"
            else:
                # the structure stays: the effect is named only if both are there and it explains more
                c_adds, c_score, c_txt = _effect_given_structure(top, left[0], base, att, cfg, rng)
                keep = c_adds and c_score >= left[0].score_pct
                why = (f"the {left[0].input} {left[0].kind.replace('_', ' ')} (outside the catalogue) stays with "
                       f"the {top.hyp.effect} in the model ({left[0].score_pct:+.1f}% held-out), and the "
                       f"{top.hyp.effect} adds {c_txt}")
    if keep:
        top.evidence += f"; kept beside a structure outside the catalogue: {why}"
        return
    if top.hyp.effect == "wind_gust":
        # the air mass was the structure's own drift: the effects named beside it on their own
        # evidence face the same test with the next one on top (none was named given the air mass)
        top.significant = False
        top.evidence += f"; not named: {why}"
        if any(c.significant for c in att.candidates):
            _structure_against_named(base, att, tests, crit_s, cfg, rng, floor)
        return
    for c in ranked:
        c.significant = False
        c.evidence += f"; not named: {why}"


def _air_mass_against_structure(gust: attribute.Candidate, t: structure.StructureTest, base: Base, att: Attributed,
                                cfg: DiagnoseConfig, rng: np.random.Generator) -> tuple[bool, str]:
    """Is the air mass still there once the input structure ``t`` is in the model, and the other way round?

    An input asymmetry is a response that depends on the sign of the stick; an air mass moves the
    aircraft whatever the stick does. A per-window air velocity can soak up the slow drift an
    asymmetric (or amplitude-dependent) gain leaves, so the larger gain alone does not tell them
    apart. The four models of the air-mass protocol (within-window chunk cross-validation) decide:
    base, + air mass, + structure (base re-identified around it), + both. The air mass is kept when
    it still lowers the cost significantly with the structure in the model (``crit``, and physically
    resolvable); it is withheld when it adds nothing once the stick-sign dependence is modelled.
    """
    ctx_s = _structure_context(t, base, att, cfg, rng)
    hg = hypotheses.scan_wind_gust(ctx_s)
    if hg.sse is None or not hg.testable or gust.hyp.sse is None:
        return True, "the air mass cannot be re-tested with the structure in the model"
    hg.extra["resolvable_m_s"] = gust.hyp.extra.get("resolvable_m_s", 0.0)
    m_s, m_sg, m_g = hg.extra["base_sse"], hg.sse, gust.hyp.sse
    p_g = candidates.p_value(hg, None, m_s, rng, cfg)
    p_s = attribute.paired_bootstrap(m_g.sum(1), m_sg.sum(1), rng, cfg.n_boot)
    gain_g = 100.0 * float((m_s - m_sg).sum() / max(m_s.sum(), 1e-300))
    gain_s = 100.0 * float((m_g - m_sg).sum() / max(m_g.sum(), 1e-300))
    ev = base.ev
    p_sign, share = structure.air_mass_sign_dependence(gust.hyp.extra["air_knots"], ev.U[:, :, INPUTS.index(t.input)])
    gust.hyp.extra.update(p_given_structure=p_g, score_given_structure=gain_g, p_stick_sign=p_sign)
    follows = p_sign < structure.structure_crit(np.ones(4, bool), cfg)
    g_ok = p_g < att.crit and gain_g > cfg.min_score_pct and candidates.physical(hg, cfg) and not follows
    name = f"{t.input} {t.kind.replace('_', ' ')} (outside the catalogue)"
    why = (f"with the {name} in the model the air mass adds {gain_g:+.1f}% (p={p_g:.2g}); with the air mass in, "
           f"the {name} adds {gain_s:+.1f}% (p={p_s:.2g}), air-mass protocol; the fitted air velocity "
           f"{'follows' if follows else 'does not follow'} the sign-even part of the {t.input} stick "
           f"(p={p_sign:.2g}, {100 * share:.0f} % of its variance): an air mass does not know the stick's sign")
    return bool(g_ok), why


def _unexplained_evidence(base: Base, loc: Located, tests: list[structure.StructureTest],
                          cfg: DiagnoseConfig) -> dict[str, Any]:
    """Where the departure is and what it looks like, for an ``unexplained`` verdict."""
    ev = base.ev
    e = ev.Y - loc.yhat_ho
    xc = structure.input_cross_correlation(e[:, ev.start:], ev.U[:, ev.start:], base.dt_s, loc.out_excited,
                                           loc.in_excited, cfg.xcorr_max_lag_s)
    ratio = {OUTPUTS[c]: round(float(loc.gap_ratio[c]), 2) for c in range(8)
             if np.isfinite(loc.gap_ratio[c]) and loc.gap_ratio[c] > cfg.gap_ratio_significant}
    sig = [t for t in tests if t.significant]
    looks = [t.description for t in sig]
    whiteness = structure.ljung_box((ev.Yraw - loc.yhat_ho)[:, ev.start:], loc.out_stride, loc.out_excited,
                                    base.dt_s, cfg.xcorr_max_lag_s, cfg.alpha)
    coloured = [w["output"] for w in whiteness if not w["white"]]
    if coloured:
        looks.append(f"held-out residual not white (Ljung-Box, lags up to {cfg.xcorr_max_lag_s:g} s) on "
                     + ", ".join(coloured))
    if loc.cond.get("label", "none") != "none":
        looks.append(f"the residual grows with {loc.cond['label']}")
    return {"channels_above_noise": ratio, "band_hz": loc.band.get("band_hz"),
            "band_input_coherence": round(float(loc.band.get("input_coherence", 0.0)), 3),
            "condition": loc.cond.get("label", "none"), "windows_s": loc.windows_s[:10],
            "what_it_looks_like": looks, "residual_input_correlation": xc, "whiteness": whiteness}


def decide_stage(base: Base, loc: Located, att: Attributed, comp: compat.Compatibility,
                 tests: list[structure.StructureTest], cfg: DiagnoseConfig) -> Decision:
    """The verdict, the named effects, what the log cannot test and what the flight excited.

    Order of verdicts: a named catalogue effect; else a sensor error found by data compatibility
    (``sensor_error``: it explains the gap, the data were corrected before the rest); else
    ``unexplained`` when a structure the linear model cannot have is significant, or the gap is
    significant and localised in flagged windows; else ``none``.
    """
    ranked = rank_named(att.candidates)
    unexplained = None
    if ranked:
        verdict = ranked[0].hyp.effect
    elif comp.findings:
        verdict = "sensor_error"
    elif any(t.significant for t in tests) or (loc.gap_significant
                                                and loc.flagged_share > cfg.unexplained_flagged_share):
        verdict = "unexplained"
        unexplained = _unexplained_evidence(base, loc, tests, cfg)
    else:
        verdict = "none"
    untestable = {h.effect: h.reason for h in att.hyps if not h.testable}
    if "ground_effect" not in untestable:
        ge = next(h for h in att.hyps if h.effect == "ground_effect")
        if ge.extra.get("height_span_m", 1.0) < cfg.ground_effect_min_height_span_m:
            untestable["ground_effect"] = "height barely varies: ground effect not excited"
    avail = base.avail
    excitation = {"inputs": {INPUTS[c]: ("ok" if loc.in_excited[c] else "too little excitation") for c in range(4)},
                  "outputs": {OUTPUTS[c]: ("ok" if loc.out_excited[c] else
                                           ("not measured" if not avail[c] else "too little excitation"))
                              for c in range(8)}}
    return Decision(verdict=verdict, ranked=ranked, others=[c for c in att.candidates if not c.significant],
                    untestable=untestable, excitation=excitation, unexplained=unexplained)


def _effect_label(c: attribute.Candidate) -> str:
    ch = c.hyp.input or c.hyp.output
    return c.hyp.effect.replace("_", " ") + (f" {ch}" if ch else "")


def verdict_stage(base: Base, loc: Located, att: Attributed, dec: Decision, tests: list[structure.StructureTest],
                  cfg: DiagnoseConfig, rng: np.random.Generator) -> tuple[Decision, dict[str, Any]]:
    """The named effects' shares of the gap above the noise, and whether each holds through the flight.

    Each named effect is estimated again in the first and the second half of the flight
    (:func:`groundstation.gap.shares.consistency`); one whose halves disagree is not named as a
    constant effect: the change through the flight is a finding of its own. The effects left are
    named only when together they remove at least ``explained_share_min_pct`` of the held-out gap
    above the noise floor; otherwise the verdict is ``unexplained``, they are listed as partial
    findings with their shares, and the report says where the rest lies and what it looks like.
    A flight too short to split in halves says so in a note; its effects are marked not checked.
    """
    ev, ctx = base.ev, att.ctx
    base_sse = ctx.base_sse
    noise_sse = shares.noise_cost(ev, loc.nf["sigma_smoothed"])
    avail = base.avail & loc.out_excited
    ranked = list(dec.ranked)
    notes: list[str] = []
    cons: dict[int, dict[str, Any]] = {}
    min_w = max(cfg.min_windows, 2 * cfg.folds)
    if ranked:
        if ev.W < 2 * min_w:
            notes.append(f"flight too short to split in halves ({ev.W} windows of {cfg.window_s:g} s, "
                         f"{2 * min_w} needed): the named effects are not checked for consistency through the flight")
            cons = {id(c): {"status": "not_checked", "why": "flight too short to split in halves"} for c in ranked}
        else:
            segs_h = shares.split_segments(base.segs, ev)
            level = cfg.alpha / (2 * len(ranked))
            arrays = None
            if any(c.hyp.effect == "rotor_vibration" for c in ranked):
                yfit = ev.simulate(ev.theta0)[0]
                arrays = {"resid_raw": (ev.Yraw - yfit)[:, ev.start:], "U": ev.U[:, ev.start:],
                          "response": _response(ev.theta0, ev.dt_s),
                          "line_channels": base.avail & (np.arange(8) >= 3), "stride": loc.out_stride,
                          "reach_factor": cfg.line_stick_reach_factor}
            for c in ranked:
                cons[id(c)] = shares.consistency(
                    c, segs_h, ev, np.asarray(c.hyp.extra.get("theta_refit", ev.theta0)), level,
                    cfg.consistency_min_loss, min_w, rng, cfg.n_boot, cfg.window_alpha, arrays)
            _drift_checks(ranked, cons, ctx, level, cfg, arrays)
    ranked, dec = _drop_unresolved_lines(ranked, cons, dec, loc, tests, cfg, notes)
    changing = [c for c in ranked if cons.get(id(c), {}).get("status") == "changes"]
    # effects named beside the first were found given it: when it changes, none is named
    kept = [] if ranked and ranked[0] in changing else [c for c in ranked if c not in changing]
    # what each effect removes: the first on its own, later ones given the first (no double count)
    rem = {id(c): shares.removal(c, base_sse, first=(i == 0)) for i, c in enumerate(ranked)}
    if kept and kept[0] is not ranked[0]:
        rem[id(kept[0])] = shares.removal(kept[0], base_sse, first=True)
    kept, unconfirmed = _confirm_beside_first(kept, rem, cons, base_sse, noise_sse, avail, rng, cfg, att.crit,
                                              lambda c, first: _line_given_first(c, first, base=base, loc=loc,
                                                                                 att=att, cfg=cfg))
    if unconfirmed:
        ranked = [c for c in ranked if c not in unconfirmed]
    sh_all = shares.compute_shares([(_effect_label(c), rem[id(c)]) for c in ranked], base_sse, noise_sse, avail,
                                   rng, cfg.share_n_boot, cfg.share_min_gap_ratio)
    sh = shares.compute_shares([(_effect_label(c), rem[id(c)]) for c in kept], base_sse, noise_sse, avail,
                               rng, cfg.share_n_boot, cfg.share_min_gap_ratio)
    if any(c.hyp.effect == "wind_gust" for c in kept):
        # the air-mass protocol scores the outputs of the horizontal block only (a horizontal air
        # velocity leaves w and r as they are): it cannot say how much of the other channels' gap
        # the air mass is, so the rule is decided on the channels it is scored on
        gust_ch = np.zeros(8, bool)
        gust_ch[list(hypotheses.GUST_CHANNELS)] = True
        sh_rule = shares.compute_shares([(_effect_label(c), rem[id(c)]) for c in kept], base_sse, noise_sse,
                                        avail & gust_ch, rng, cfg.share_n_boot, cfg.share_min_gap_ratio)
        names = ", ".join(OUTPUTS[k] for k in hypotheses.GUST_CHANNELS)
        notes.append("an air mass is named: the share rule is decided on the channels the air-mass protocol "
                     f"scores ({names}): {sh_rule.explained_pct or 0.0:.0f} % of their gap above noise")
    else:
        sh_rule = sh
    per_effect: dict[int, dict[str, Any]] = {}
    for c, pe in zip(ranked, sh_all.per_effect, strict=False):
        per_effect[id(c)] = {"share_pct": pe["share_pct"], "share_interval_pct": pe["interval_pct"],
                             "consistency": cons.get(id(c), {"status": "not_checked", "why": ""})}
    for c in ranked:
        per_effect.setdefault(id(c), {"share_pct": None, "share_interval_pct": None,
                                      "consistency": cons.get(id(c), {"status": "not_checked", "why": ""})})
    # "most of the gap": refuted only when the share's whole 5-95 % interval lies below the level
    # (the windows' own spread decides, not the point estimate alone), and only where there is a
    # gap to share: a gap within a few times the noise (not significant, section 1) is a small
    # difference of two large numbers, and the noise floor itself is an estimate
    explained = sh_rule.interval_pct[1] if sh_rule.interval_pct is not None else sh_rule.explained_pct
    # "unexplained" is a significant departure no named effect is: the excess over the white noise
    # also holds the model's own small misfit, there on a flight without any effect (the model is
    # linear, the aircraft is not). So where the named effects fall short of the share over all
    # channels, the departure is judged channel by channel as the gap's significance is: named when
    # fewer than ``gap_channels_min`` channels above ``gap_ratio_significant`` x their noise are left
    # without most of their excess clearly explained. Not when an effect changes through the flight:
    # that change is a departure the data show, left in the rest
    open_ch = _departures_left(sh_rule, loc, cfg) if kept and loc.gap_significant else []
    rest_small = (bool(kept) and not changing and loc.gap_significant and explained is not None
                  and explained < cfg.explained_share_min_pct and len(open_ch) < cfg.gap_channels_min)
    named_ok = bool(kept) and (not loc.gap_significant or explained is None
                               or explained >= cfg.explained_share_min_pct or rest_small)
    verdict, unexplained = dec.verdict, dec.unexplained
    partial = []
    if ranked and not named_ok:
        partial = ranked
        kept = []
        verdict = "unexplained"
    elif changing:
        partial = changing
    if verdict == "sensor_error" and loc.gap_significant:
        # the sensor error was undone before the diagnosis: a significant gap left after it is not explained by it
        verdict = "unexplained"
        notes.append("a sensor scale error was found and undone, but the held-out gap left is significant: "
                     "the sensor error does not explain it")
    if verdict == "none" and loc.gap_significant:
        # the share rule with nothing named: 0 % of a significant gap above noise is explained (a gap
        # spread evenly over the flight is still a gap: a parameter drifting slowly spreads its own)
        verdict = "unexplained"
        notes.append("nothing is named and the held-out gap is significant: 0 % of the gap above noise is explained")
    if verdict == "unexplained" and unexplained is None:
        unexplained = _unexplained_evidence(base, loc, tests, cfg)
    cols = [OUTPUTS.index(n) for n in sh.channels]
    removed = sum((rem[id(c)] for c in (kept or ranked)), np.zeros_like(base_sse))
    over_time = shares.gap_over_time(ev, base_sse, noise_sse, removed, cols)
    changes = [{"effect": c.hyp.effect, "channel": c.hyp.input or c.hyp.output, **cons[id(c)]} for c in changing]
    rest = _rest_of_gap(sh, loc, over_time, unexplained)
    if rest_small:
        rest["departures_left"] = {ch: round(float(loc.gap_ratio[OUTPUTS.index(ch)]), 2) for ch in open_ch}
    headline = _headline(kept, partial, sh if kept else sh_all, changes, rest, cfg, loc.gap_significant, rest_small)
    if unexplained is not None:
        unexplained = dict(unexplained)
        unexplained["what_it_looks_like"] = list(unexplained.get("what_it_looks_like", []))
        for ch in changes:
            unexplained["what_it_looks_like"].insert(0, f"the {ch['effect'].replace('_', ' ')} "
                                                        f"{ch['channel'] or ''} changes through the flight: {ch['why']}")
        unexplained["explained_pct"] = None if sh_all.explained_pct is None else round(sh_all.explained_pct, 1)
    share_block = {
        "explained_pct": None if sh.explained_pct is None else round(sh.explained_pct, 1),
        "interval_pct": None if sh.interval_pct is None else [round(v, 1) for v in sh.interval_pct],
        "unexplained_pct": None if sh.explained_pct is None else round(100.0 - min(max(sh.explained_pct, 0.0), 100.0), 1),
        "partial_explained_pct": None if not partial or sh_all.explained_pct is None else round(sh_all.explained_pct, 1),
        "excess_pct_of_cost": round(sh.excess_pct_of_cost, 1),
        "gap_significant": bool(loc.gap_significant),
        "channels": sh.channels,
        "per_channel": sh.per_channel if kept else sh_all.per_channel,
        "per_effect": sh.per_effect if kept else sh_all.per_effect,
        "rule": (f"effects are named unless together they remove less than {cfg.explained_share_min_pct:g} % of the "
                 f"held-out gap above the noise floor with the whole 5-95 % interval (bootstrap over held-out "
                 f"windows) below it, on a significant gap (at least {cfg.gap_channels_min} excited channels above "
                 f"{cfg.gap_ratio_significant:g}x their noise), unless fewer than {cfg.gap_channels_min} of those "
                 f"channels are left without most of their excess clearly explained (interval wholly above "
                 f"{cfg.explained_share_min_pct:g} %); and each holds through the flight (the halves' estimates "
                 f"agree)"),
        "rest": rest,
        "headline": headline,
    }

    partial_entries = []
    for c in partial:
        e = _effect_entry(c)
        e.update(per_effect[id(c)])
        partial_entries.append(e)
    rep: dict[str, Any] = {"shares": share_block, "partial_findings": partial_entries,
           "through_flight": {"checked": bool(cons) and not any(v.get("why") == "flight too short to split in halves"
                                                               for v in cons.values()),
                              **over_time, "changes": changes},
           "verdict": verdict, "unexplained": unexplained}
    new = dataclasses.replace(dec, verdict=verdict, ranked=kept, unexplained=unexplained,
                              others=list(dec.others) + unconfirmed)
    rep["notes_add"] = notes
    # what decided between naming and "unexplained" (for the verdict's margin): the share rule's interval,
    # unless a significant gap did not reach it or the channels left decided (rest_small)
    rule = {"interval": sh_rule.interval_pct if ranked and loc.gap_significant and not rest_small else None,
            "partial": partial}
    return new, {"report": rep, "per_effect": per_effect, "rule": rule}


def margin_stage(att: Attributed, loc: Located, dec: Decision, rule: dict[str, Any], cfg: DiagnoseConfig,
                 seed: int) -> dict[str, Any]:
    """How far the verdict sits from the edges of the tests that decided it (:mod:`groundstation.gap.margins`):
    the significance of the first named effect and of any candidate that failed on its p-value alone and
    would have changed the verdict, the input effects' encompassing test against an air mass, and the share rule."""
    rng = np.random.default_rng((seed, 25))
    fallback = "unexplained" if loc.gap_significant else "none"
    partial = rule["partial"]
    edges = margins.significance_edges(dec.ranked, dec.others, dec.verdict, fallback, att.ctx, att.crit, cfg, rng,
                                       partial)
    edges += margins.air_mass_edges(dec.ranked, dec.others, fallback, att.crit, cfg, rng, partial)
    share = margins.share_edge(rule["interval"], dec.verdict, partial, dec.ranked, cfg)
    return margins.summary(edges + ([share] if share is not None else []), dec.verdict, cfg)


def _drop_unresolved_lines(ranked: list[attribute.Candidate], cons: dict[int, dict[str, Any]], dec: Decision,
                           loc: Located, tests: list[structure.StructureTest], cfg: DiagnoseConfig,
                           notes: list[str]) -> tuple[list[attribute.Candidate], Decision]:
    """A rotor line one half of the flight does not show (``not_resolved``) and the whole-flight
    drift test does not find growing (:func:`_drift_checks`) is not named: it goes to the notes and
    the unnamed candidates. When it led, the verdict is chosen again from what is left
    as :func:`decide_stage` chooses it (a sensor error found first is not the verdict here: it led
    over no line)."""
    gone = [c for c in ranked if cons.get(id(c), {}).get("status") == "not_resolved"]
    if not gone:
        return ranked, dec
    for c in gone:
        notes.append(f"rotor vibration not named ({c.evidence.split(';')[0]}): {cons[id(c)]['why']}")
    left = [c for c in ranked if c not in gone]
    verdict = dec.verdict
    if ranked[0] in gone:
        if left:
            verdict = left[0].hyp.effect
        elif any(t.significant for t in tests) or (loc.gap_significant
                                                    and loc.flagged_share > cfg.unexplained_flagged_share):
            verdict = "unexplained"
        else:
            verdict = "none"
    return left, dataclasses.replace(dec, verdict=verdict, ranked=left, others=list(dec.others) + gone)


def _drift_checks(ranked: list[attribute.Candidate], cons: dict[int, dict[str, Any]], ctx: hypotheses.Context,
                  level: float, cfg: DiagnoseConfig, arrays: dict[str, Any] | None) -> None:
    """The whole-flight drift test (:func:`groundstation.gap.drift.drift`) of each named effect: a
    half that does not resolve the effect on its own cannot see a drift, a ramp through the whole
    flight can. An effect that drifts is marked ``changes`` with the ramp it follows; the halves'
    verdict stays in the entry. An input effect or gyro bias the halves find changing is tested
    too (:func:`_halves_change_in_time`). A rotor line is tested only where the halves did not find
    it changing."""
    rng = np.random.default_rng(26)  # its own stream: the shares' bootstrap draws stay as they were
    for c in ranked:
        con = cons.get(id(c))
        if con is None:
            continue
        if c.hyp.effect == "rotor_vibration":
            if con.get("status") == "changes":
                continue
            d = drift.line_drift(c, ctx.ev, arrays["resid_raw"], level) if arrays else None
        else:
            # the halves' changes draw from a stream of their own: the other effects' draws stay as they were
            r = np.random.default_rng(26) if con["status"] == "changes" else rng
            d = drift.drift(c, ctx, ctx.base_sse, level, r, cfg.n_boot, cfg.window_alpha)
        if d is None:
            continue
        con["drift"] = d
        if con["status"] == "changes":
            _halves_change_in_time(con, d)
        elif d["drifts"]:
            con["halves"] = {"status": con["status"], "why": con["why"]}
            con["status"], con["why"] = "changes", d["why"]


def _halves_change_in_time(con: dict[str, Any], d: dict[str, Any]) -> None:
    """A change the halves found is a change in time only when a parameter following the flight's
    progress predicts the held-out windows better than a constant one. Each half's value is
    estimated on that half's own stick excursions; where the catalogue effect only approximates the
    aircraft's physics (a symmetric deadzone for an asymmetric one), its best value depends on how
    far each side of the stick was flown, and halves flown differently reject each other's value
    though nothing changed. When the ramp removes no held-out cost at all beyond the constant (the
    same windows, chosen inside each training fold), the effect holds; the halves' verdict stays in
    the entry."""
    if d["drifts"] or d["ramp_gains"]:
        return
    con["halves"] = {"status": con["status"], "why": con["why"]}
    con["status"] = "holds"
    con["why"] = (f"{con['why']}, but a value ramping through the flight predicts the held-out windows no "
                  f"better than a constant one (p={d['p']:.2g}): the halves differ in how the aircraft was "
                  f"flown, not in time")


def _confirm_beside_first(kept: list[attribute.Candidate], rem: dict[int, np.ndarray], cons: dict[int, dict[str, Any]],
                          base_sse: np.ndarray, noise_sse: np.ndarray, avail: np.ndarray, rng: np.random.Generator,
                          cfg: DiagnoseConfig, crit: float, line_test: Any = None
                          ) -> tuple[list[attribute.Candidate], list[attribute.Candidate]]:
    """Effects named beside the first, confirmed with the dependence of their evidence measured.

    Each must remove, once the first effect is in, held-out cost beyond chance by
    :func:`_beside_first_p` (the conditional test's paired tests over the held-out blocks, each
    counted as ``1 / design effect`` of an independent one; beside an air mass the windows'
    signed ranks), with a share whose 5-95 % interval (bootstrap over windows) lies above zero.

    Why: the first effect named is often an approximation of the aircraft's physics (a first-order
    servo lag read as a delay, backlash as a deadband, turbulence as a smooth air mass), and what it
    leaves is systematic and input-linked: the pilot's corrective inputs follow every disturbance the
    model misses. A second catalogue effect can soak up a sliver of that remainder and pass the
    conditional test, whose ~0.5 s blocks are counted as independent pieces of evidence; the
    remainder is not noise, so neighbouring blocks of a window agree and the evidence is overcounted.
    The design effect measured on the blocks' differences says by how much: a sliver moving whole
    windows together keeps about one unit per window, a real effect at the sharpest inputs (a few
    blocks of the few windows where its stick was swept) keeps most of its blocks. A spectral line (a fingerprint of the raw residual,
    which the smoothed held-out gap barely shows) is confirmed instead by ``line_test``: the line must
    still be in the raw residual of the model with the first effect in (:func:`_line_given_first`).
    Effects failing are not named: they stay among the scored candidates with the reason. Returns
    (named, not confirmed)."""
    if len(kept) < 2:
        return kept, []
    named = [kept[0]]
    out = []
    for c in kept[1:]:
        if c.hyp.effect == "rotor_vibration":
            ok, why_line = line_test(c, kept[0]) if line_test is not None else (True, "")
            if ok:
                named.append(c)
            else:
                c.significant = False
                c.evidence += f"; not named beside the {kept[0].hyp.effect}: {why_line}"
                out.append(c)
            continue
        sh = shares.compute_shares([(_effect_label(c), rem[id(c)])], base_sse, noise_sse, avail, rng,
                                   cfg.share_n_boot, cfg.share_min_gap_ratio)
        pe = sh.per_effect[0] if sh.per_effect else None
        p, level, test = _beside_first_p(c, rem[id(c)], base_sse, noise_sse, avail, crit)
        c.hyp.extra["p_windows_beside_first"] = p
        why = []
        if pe is None or not pe["interval_pct"][0] > 0:
            iv = "no gap above noise to share" if pe is None else \
                f"{pe['share_pct']:.1f} % of the gap above noise, interval {pe['interval_pct'][0]:.1f} to {pe['interval_pct'][1]:.1f} %"
            why.append(f"its share once the {kept[0].hyp.effect} is in does not exclude zero ({iv})")
        if not p < level:
            why.append(f"what it removes once the {kept[0].hyp.effect} is in is not positive beyond chance "
                       f"({test}, p={p:.2g} against {level:.2g})")
        if why:
            c.significant = False
            c.evidence += f"; not named beside the {kept[0].hyp.effect}: " + "; ".join(why)
            out.append(c)
        else:
            c.evidence += (f"; confirmed beside the {kept[0].hyp.effect} ({test}, p={p:.2g}, "
                           f"share {pe['share_pct']:.1f} %)" if pe else "")
            named.append(c)
    return named, out


def _beside_first_p(c: attribute.Candidate, removed: np.ndarray, base_sse: np.ndarray, noise_sse: np.ndarray,
                    avail: np.ndarray, crit: float) -> tuple[float, float, str]:
    """The confirmation test of a second effect: (p, its level, what it is).

    With the held-out blocks of its conditional test: the same paired tests over the ~0.5 s blocks,
    each block counted as ``1 / design effect`` of an independent one, the design effect measured on
    the blocks' own differences (:func:`attribute.clustered_paired_p`), at the level it was named at
    (Holm's second step). Without blocks (beside an air mass): a one-sided Wilcoxon signed-rank test
    over the held-out windows' removals in noise units, at ``crit``."""
    bb, ab = c.hyp.extra.get("blocks_given") or (None, None)
    if bb is not None and ab is not None:
        deff = attribute.design_effect(np.asarray(bb) - np.asarray(ab))
        return (attribute.clustered_paired_p(bb, ab), float(c.hyp.extra.get("level_given", crit)),
                f"paired tests over {np.size(bb)} held-out blocks counted as {np.size(bb) / deff:.0f} "
                f"independent ones (design effect {deff:.1f})")
    num = shares.window_removal(removed, base_sse, noise_sse, avail)
    try:
        p = float(stats.wilcoxon(num, alternative="greater").pvalue) if np.any(num != 0) else 1.0
    except ValueError:
        p = 1.0
    return p, crit, f"Wilcoxon signed-rank over {num.size} held-out windows"


def _line_given_first(c: attribute.Candidate, first: attribute.Candidate, *, base: Base, loc: Located,
                      att: Attributed, cfg: DiagnoseConfig) -> tuple[bool, str]:
    """Is rotor line ``c`` still in the raw residual once ``first`` is in the model? (the conditional
    test of a line: a first effect that only approximates the physics, e.g. a delay standing for a
    servo lag, leaves its misfit where its input has power, which can stand out as a peak of the base
    model's residual; a rotor line does not care what the model of the stick is). Same test as the
    first (:func:`groundstation.gap.fingerprints.spectral_lines`, resolvable lines only), a line within
    two bins (or 0.3 Hz) of ``c``'s frequency. A first effect that cannot be put in the model (the air
    mass) leaves the line as it was named."""
    cctx = candidates.conditioned_context(first, att.ctx, base.segs)
    if cctx is None or cctx.given is not None:
        return True, ""
    ev = cctx.ev
    resid = (ev.Yraw - ev.simulate(ev.theta0)[0])[:, ev.start:]
    line_ch = base.avail & (np.arange(8) >= 3)
    lines, sp = fingerprints.spectral_lines(resid, ev.U[:, ev.start:], base.dt_s, line_ch, alpha=cfg.alpha,
                                            response=_response(ev.theta0, base.dt_s),
                                            reach_factor=cfg.line_stick_reach_factor)
    lines = fingerprints.resolvable_lines(lines, loc.out_stride, base.dt_s)
    f0 = float(c.hyp.estimate.get("frequency_hz", np.nan))
    f = sp.get("f_hz")
    tol = max(0.3, 2.0 * float(f[1] - f[0])) if f is not None and len(f) > 1 else 0.3
    if any(abs(ln.frequency_hz - f0) <= tol for ln in lines):
        return True, ""
    return False, (f"the line at {f0:.2f} Hz is not in the raw residual once the {first.hyp.effect} is in the model "
                   f"(the first effect's misfit stood out there)")


def _departures_left(sh: shares.Shares, loc: Located, cfg: DiagnoseConfig) -> list[str]:
    """The excited channels whose held-out gap is significant (above ``gap_ratio_significant`` x their
    noise) and whose excess the named effects do not clearly explain for the most part (the channel's
    share interval not wholly above ``explained_share_min_pct``)."""
    out = []
    for c in range(8):
        if not loc.out_excited[c] or not np.nan_to_num(loc.gap_ratio[c]) > cfg.gap_ratio_significant:
            continue
        v = sh.per_channel.get(OUTPUTS[c], {})
        iv = v.get("interval_pct")
        lo = iv[0] if iv is not None else v.get("explained_pct")
        if lo is None or lo < cfg.explained_share_min_pct:
            out.append(OUTPUTS[c])
    return out


def _gap_significant(gap_ratio: np.ndarray, excited: np.ndarray, cfg: DiagnoseConfig) -> bool:
    """The locate stage's rule: at least ``gap_channels_min`` excited channels above ``gap_ratio_significant``."""
    r = np.nan_to_num(np.where(excited, gap_ratio, 0.0))
    return bool(np.sum(r > cfg.gap_ratio_significant) >= cfg.gap_channels_min)


def _rest_of_gap(sh: shares.Shares, loc: Located, over_time: dict, unexplained: dict | None) -> dict[str, Any]:
    """Where the part of the gap the named effects leave lies: channels, band, time and condition."""
    chans = {k: v for k, v in sh.per_channel.items() if v.get("excess_share_pct")}

    def left(v: dict) -> float:  # the channel's part of the gap above noise the named effects leave
        x = v.get("explained_pct")
        return float(v.get("excess_share_pct") or 0.0) * (1.0 - (0.0 if x is None else min(max(x, 0.0), 100.0)) / 100.0)

    top = sorted(chans.items(), key=lambda kv: -left(kv[1]))[:3]
    halves = over_time.get("halves", [])
    return {"channels": [{"channel": k, "excess_share_pct": v["excess_share_pct"], "gap_to_noise": v["gap_to_noise"],
                          "explained_pct": v.get("explained_pct")} for k, v in top],
            "band_hz": loc.band.get("band_hz"), "condition": loc.cond.get("label", "none"),
            "halves_excess_share_pct": [h.get("excess_share_pct") for h in halves],
            "trend": over_time.get("trend"),
            "what_it_looks_like": list((unexplained or {}).get("what_it_looks_like", []))[:4]}


def _headline(kept: list[attribute.Candidate], partial: list[attribute.Candidate], sh: shares.Shares,
              changes: list[dict], rest: dict[str, Any], cfg: DiagnoseConfig, significant: bool = True,
              rest_small: bool = False) -> str:
    """One sentence a user reads first: how much of the gap above noise the named effects explain."""
    if sh.explained_pct is None:
        if kept:
            return ("the held-out gap is at the noise floor on every channel; named on its own tests: "
                    + ", ".join(_effect_label(c) for c in kept))
        return "the held-out gap is at the noise floor: nothing to explain"
    x = min(max(sh.explained_pct, 0.0), 100.0)
    lo, hi = sh.interval_pct or (float("nan"), float("nan"))
    iv = f"interval {min(max(lo, 0.0), 100.0):.0f} to {min(max(hi, 0.0), 100.0):.0f} %"
    where = ", ".join(f"{c['channel']} ({c['gap_to_noise']:g}x noise)" for c in rest["channels"])
    extra = []
    if rest.get("band_hz"):
        extra.append(f"{rest['band_hz'][0]:g}-{rest['band_hz'][1]:g} Hz")
    if rest.get("condition") not in (None, "none"):
        extra.append(f"grows with {rest['condition']}")
    hs = rest.get("halves_excess_share_pct") or []
    if len(hs) == 2 and all(v is not None and 0.0 <= v <= 100.0 for v in hs):
        extra.append(f"{hs[0]:.0f} % of it in the first half, {hs[1]:.0f} % in the second")
    tail = f": it lies in {where}" + (f"; {', '.join(extra)}" if extra else "") if where else ""
    if kept:
        names = " and ".join(_effect_label(c) for c in kept)
        small = ("" if significant else
                 f" (the gap is small: fewer than {cfg.gap_channels_min} channels above {cfg.gap_ratio_significant:g}x "
                 f"their noise, so the share is indicative and the effect is named on its own tests)")
        if rest_small:
            left = rest.get("departures_left", {})
            where = ("no channel above " if not left else
                     "only " + ", ".join(f"{k} ({v:g}x noise)" for k, v in left.items()) + " of the channels above ")
            return (f"{x:.0f} % of the gap above noise is explained by {names} ({iv}); the rest is no significant "
                    f"departure: {where}{cfg.gap_ratio_significant:g}x their noise is not mostly explained by "
                    + ("it" if len(kept) == 1 else "them"))
        return (f"{x:.0f} % of the gap above noise is explained by {names} ({iv}); "
                f"{100 - x:.0f} % is not" + (tail if 100 - x >= 20 and significant else "") + small)
    if partial:
        names = " and ".join(_effect_label(c) for c in partial)
        verb = "explains" if len(partial) == 1 else "explain"
        if changes:
            what = "; ".join(f"the {ch['effect'].replace('_', ' ')} changes through the flight" for ch in changes)
            return (f"unexplained: {names} {verb} {x:.0f} % of the gap above noise ({iv}) but no constant effect "
                    f"does: {what}; {100 - x:.0f} % is not explained" + tail)
        return (f"unexplained: {names} {verb} only {x:.0f} % of the gap above noise ({iv}), clearly below the "
                f"{cfg.explained_share_min_pct:g} % needed to name them; {100 - x:.0f} % is not explained" + tail)
    if not significant:
        return (f"no catalogue effect is named; the gap is small (fewer than {cfg.gap_channels_min} channels above "
                f"{cfg.gap_ratio_significant:g}x their noise)" + tail)
    return "no catalogue effect explains the gap above noise (0 % explained)" + tail


def _window_features(ev: Evaluator) -> dict[str, np.ndarray]:
    alt = ev.cut([s.alt_m for s in ev.segments])
    feats = {
        "input_amplitude": np.sqrt((ev.U[:, ev.start:] ** 2).mean(axis=(1, 2))),
        "input_rate": np.sqrt((np.diff(ev.U[:, ev.start:], axis=1) ** 2).mean(axis=(1, 2))) / ev.dt_s,
    }
    if np.isfinite(alt).mean() > 0.5:
        feats["height_m"] = np.nanmean(alt, axis=1)
    if ev.available[0] and ev.available[1]:
        feats["speed_m_s"] = np.sqrt((ev.Y[:, :, 0] ** 2 + ev.Y[:, :, 1] ** 2).mean(axis=1))
    return feats


