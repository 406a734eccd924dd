"""``groundstation bench diagnose --cases N --seed S [--combined M]``: blind test of the diagnosis.

Generates N simulated flights with ``hil_replay.sim.write_tlog`` (the independent simulator),
each with one random catalogue effect (``hil_replay.sim.effects.random_effect``: random channel
and magnitude) or none, classes taken in turn; hides the label; reads the .tlog back through the
ordinary reader, prepares it and diagnoses it (identifying the model first unless
``--model-source truth``). Prints the confusion matrix, top-1 accuracy, false-alarm rate on
effect-free flights, channel accuracy, the error of the estimated effect parameter, predicted shrink
and (``--fresh``) the shrink of the same effect measured on a fresh flight, wall time per case,
and M combined cases with two effects at once (are both found?). Cases run in a process pool.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

HELP = "blind test of the gap diagnosis on simulated flights with hidden random effects"

CLASSES = ("none", "input_delay", "rate_limit", "deadband", "ground_effect", "wind_gust", "quadratic_drag",
           "gyro_bias", "rotor_vibration", "velocity_latency")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cases", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--combined", type=int, default=0, help="extra cases with two effects at once")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--classes", default=",".join(CLASSES), help="comma-separated classes to draw from")
    parser.add_argument("--model-source", choices=("identify", "truth"), default="identify",
                        help="base model: identified from the flight (blind) or the simulator's truth parameters")
    parser.add_argument("--fresh", action="store_true", help="also measure the shrink on a fresh flight")
    parser.add_argument("--aircraft", default=None, help="simulator aircraft name (default: the simulator's)")
    parser.add_argument("--rates", default=None,
                        help="telemetry rates of the simulated autopilot, e.g. ATTITUDE=25,LOCAL_POSITION_NED=10 "
                             "(default: the simulator's); a robustness check against other stream set-ups")
    parser.add_argument("--pilot", choices=tuple(PILOTS), default="default",
                        help="synthetic pilot: tight (stiffer loops, less input left on the excited axis), "
                             "loose, or the simulator's default; a robustness check against other pilots")
    parser.add_argument("--excitation", type=float, default=1.0,
                        help="scale of the card's sweep and doublet amplitudes (e.g. 0.5: a cautious pilot)")
    parser.add_argument("--json", type=Path, default=None, help="write every case result to this JSON file")


#: Pilot variants for robustness runs: Bryson allowed deviations scaled (smaller = stiffer loops).
PILOTS: dict[str, dict[str, float]] = {"default": {}, "tight": {"scale": 0.5, "excited_axis_gain": 0.6},
                                       "loose": {"scale": 1.6, "excited_axis_gain": 0.15}}


def pilot_config(name: str) -> Any:
    """The :class:`hil_replay.sim.pilot.PilotConfig` of a named variant (None for the default)."""
    from dataclasses import replace

    from hil_replay.sim.pilot import PilotConfig

    v = PILOTS[name]
    if not v:
        return None
    c = PilotConfig()
    k = v["scale"]
    return replace(c, vel_m_s=c.vel_m_s * k, att_rad=c.att_rad * k, rate_rad_s=c.rate_rad_s * k,
                   pos_m=c.pos_m * k, w_m_s=c.w_m_s * k, r_rad_s=c.r_rad_s * k, height_m=c.height_m * k,
                   heading_rad=c.heading_rad * k, excited_axis_gain=v["excited_axis_gain"])


def parse_rates(text: str | None) -> dict[str, float] | None:
    """``NAME=HZ,...`` -> {NAME: HZ}; None for no text. ValueError names the bad item."""
    if not text:
        return None
    out: dict[str, float] = {}
    for item in text.split(","):
        name, sep, value = item.strip().partition("=")
        try:
            if not sep:
                raise ValueError
            out[name.strip().upper()] = float(value)
        except ValueError:
            raise ValueError(f"--rates: {item.strip()!r} is not NAME=HZ") from None
    return out


def _effect_channel(e: dict[str, Any]) -> str | None:
    return e.get("input") or e.get("output")


def _main_param(name: str, params: dict[str, float]) -> tuple | None:
    """The truth effect parameter comparable with our estimate: (label, value in our units)."""
    p = {k: float(v) for k, v in params.items() if isinstance(v, (int, float))}
    if name == "rotor_vibration" and "rpm" in p:
        from hil_replay.sim.effects import aliased_hz

        # two-bladed rotor: the 2/rev line usually dominates; report the harmonic nearest the estimate
        return "aliased 1/rev or 2/rev line Hz", aliased_hz(p["rpm"] / 60.0, 50.0), aliased_hz(2 * p["rpm"] / 60.0, 50.0)  # type: ignore[return-value]
    if name == "wind_gust" and "sigma_m_s" in p:
        return "3-axis rms m/s", p["sigma_m_s"] * 1.5  # horizontal sigma, vertical at half
    keys = {"input_delay": "delay_s", "velocity_latency": "latency_s", "gyro_bias": "bias_rad_s",
            "rate_limit": "rate_per_s", "deadband": "half_width", "quadratic_drag": "c_per_m"}
    k = keys.get(name)
    return (k, p[k]) if k in p else None


def _estimate_for(name: str, est: dict[str, float]) -> float | None:
    if name == "quadratic_drag":
        v = [float(x) for k, x in est.items() if k.startswith("drag_") and x is not None]
        return float(np.mean(v)) if v else None
    keys = {"input_delay": "delay_s", "velocity_latency": "latency_s", "gyro_bias": "bias_rad_s",
            "rotor_vibration": "frequency_hz", "rate_limit": "rate_limit_per_s", "deadband": "deadband",
            "wind_gust": "air_velocity_rms_m_s"}
    k = keys.get(name)
    return None if k is None or est.get(k) is None else float(est[k])


def run_case(job: dict[str, Any]) -> dict[str, Any]:
    """Simulate, read back, prepare, diagnose one case (runs in a worker process)."""
    from firmware_interface.readers import load_log
    from groundstation.dsp.prepare import prepare
    from groundstation.gap.diagnose import run_diagnosis
    from groundstation.sysid.model import HoverModel
    from hil_replay.sim import write_tlog
    from hil_replay.sim.effects import random_effect

    rng = np.random.default_rng(job["seed"])
    effects = [random_effect(n, rng) for n in job["effects"]]
    out: dict[str, Any] = {"case": job["case"], "truth_effects": job["effects"]}
    with tempfile.TemporaryDirectory() as td:
        path = Path(td) / f"case{job['case']}.tlog"
        kw: dict[str, Any] = {} if job.get("aircraft") is None else {"aircraft": job["aircraft"]}
        if job.get("rates"):
            kw["rates_hz"] = job["rates"]
        if job.get("pilot", "default") != "default":
            kw["pilot"] = pilot_config(job["pilot"])
        if job.get("excitation", 1.0) != 1.0:
            kw["excitation_scale"] = job["excitation"]
        truth = write_tlog(path, seed=job["seed"], flights=1, effects=effects, **kw)
        out["truth"] = truth.get("effects", [])
        t0 = time.perf_counter()
        prepared = prepare([load_log(path)])
        model = None
        if job["model_source"] == "truth":
            model = HoverModel(params=dict(truth["parameters"]))
        diag = run_diagnosis(model, prepared, seed=job["seed"])
        out["seconds"] = time.perf_counter() - t0
        out["flight_s"] = float(sum(s.t_s[-1] - s.t_s[0] for s in prepared.segments))
        rep = diag.report
        out["verdict"] = rep["verdict"]
        out["effects"] = [{k: e[k] for k in ("effect", "input", "output", "estimate", "shrink_pct", "score")}
                          for e in rep["effects"]]
        # every scored hypothesis (significant or not), for inspecting why a case went wrong
        out["candidates"] = [{k: e.get(k) for k in ("effect", "input", "output", "estimate", "score", "p_value",
                                                    "shrink_pct")} for e in rep["effects"] + rep["candidates"]]
        out["gap_to_noise_ratio"] = rep["gap"].get("gap_to_noise_ratio")
        if job.get("fresh") and job["effects"]:
            path2 = Path(td) / "fresh.tlog"
            rng2 = np.random.default_rng(job["seed"])
            eff2 = [random_effect(n, rng2) for n in job["effects"]]  # same draw: same effect and magnitude
            write_tlog(path2, seed=job["seed"] + 100000, flights=1, effects=eff2, **kw)
            d2 = run_diagnosis(model, prepare([load_log(path2)]), seed=job["seed"])
            allc = d2.report["effects"] + d2.report["candidates"]
            same = [e for e in allc if e["effect"] == job["effects"][0]]
            out["fresh_shrink_pct"] = same[0]["shrink_pct"] if same else None
    return out


def run(args: argparse.Namespace) -> int:
    classes = [c.strip() for c in args.classes.split(",") if c.strip()]
    unknown = set(classes) - set(CLASSES)
    if unknown:
        raise ValueError(f"--classes: unknown effect name(s) {sorted(unknown)}; allowed {CLASSES}")
    rates = parse_rates(args.rates)
    rng = np.random.default_rng(args.seed)
    jobs = []
    for i in range(args.cases):
        name = classes[i % len(classes)]
        jobs.append({"case": i, "seed": int(args.seed * 1000 + i), "effects": [] if name == "none" else [name],
                     "model_source": args.model_source, "fresh": args.fresh, "aircraft": args.aircraft,
                     "rates": rates, "pilot": args.pilot, "excitation": args.excitation})
    real = [c for c in CLASSES if c != "none"]
    for j in range(args.combined):
        pair = [str(x) for x in rng.choice(real, 2, replace=False)]
        jobs.append({"case": args.cases + j, "seed": int(args.seed * 1000 + 500 + j), "effects": pair,
                     "model_source": args.model_source, "fresh": False, "aircraft": args.aircraft,
                     "rates": rates, "pilot": args.pilot, "excitation": args.excitation, "combined": True})
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        results = list(pool.map(run_case, jobs))
    wall = time.perf_counter() - t0
    singles = [r for r, j in zip(results, jobs, strict=True) if not j.get("combined")]
    combos = [r for r, j in zip(results, jobs, strict=True) if j.get("combined")]
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    print_summary(singles, combos, classes, wall)
    return 0


def print_summary(singles: list[dict], combos: list[dict], classes: list[str], wall: float) -> None:
    labels = list(classes) + [c for c in ("unexplained",) if c not in classes]
    idx = {c: i for i, c in enumerate(labels)}
    cm = np.zeros((len(classes), len(labels)), int)
    chan_ok = chan_n = 0
    param_err: list[str] = []
    shrinks: list[str] = []
    for r in singles:
        truth = r["truth_effects"][0] if r["truth_effects"] else "none"
        pred = r["verdict"]
        cm[classes.index(truth), idx.get(pred, idx["unexplained"])] += 1
        if truth != "none" and pred == truth and r["truth"]:
            t = r["truth"][0]
            ch = _effect_channel(t)
            if ch is not None:
                chan_n += 1
                chan_ok += int(ch in (r["effects"][0]["input"], r["effects"][0]["output"]))
            tp = _main_param(truth, t.get("params", {}))
            ev = _estimate_for(truth, r["effects"][0]["estimate"])
            if tp is not None and ev is not None:
                tv = min(tp[1:], key=lambda v: abs(v - ev))
                param_err.append(f"{truth}: est {ev:.4g} vs true {tv:.4g} ({tp[0]})")
            shrinks.append(f"{truth}: predicted {r['effects'][0]['shrink_pct']}% fresh {r.get('fresh_shrink_pct')}%")
    for r in singles + combos:
        got = [(e["effect"], e["input"] or e["output"]) for e in r["effects"][:3]]
        tr = [(t["effect"], t.get("input") or t.get("output")) for t in r.get("truth", [])]
        print(f"  case {r['case']:3d} truth {tr} -> {r['verdict']} {got} ({r['seconds']:.0f} s)")
    n = len(singles)
    correct = int(sum(cm[i, idx[c]] for i, c in enumerate(classes)))
    print("confusion matrix (rows truth, columns verdict):")
    w = max(len(c) for c in labels) + 1
    print(" " * w + " ".join(f"{c[:7]:>7}" for c in labels))
    for i, c in enumerate(classes):
        print(f"{c:<{w}}" + " ".join(f"{v:>7d}" for v in cm[i]))
    print(f"top-1 accuracy: {correct}/{n} = {100.0 * correct / max(n, 1):.1f}%")
    if "none" in classes:
        nn = int(cm[classes.index("none")].sum())
        fa = nn - int(cm[classes.index("none"), idx["none"]])
        print(f"false alarms on effect-free flights: {fa}/{nn}")
    print(f"channel accuracy (correct verdicts with a channel): {chan_ok}/{chan_n}")
    for s in param_err:
        print("  parameter " + s)
    for s in shrinks:
        print("  shrink " + s)
    if combos:
        both = 0
        for r in combos:
            found = {e["effect"] for e in r["effects"]}
            ok = all(t in found for t in r["truth_effects"])
            both += int(ok)
            print(f"  combined {r['truth_effects']} -> found {[e['effect'] for e in r['effects']]}")
        print(f"combined cases with both effects found: {both}/{len(combos)}")
    secs = [r["seconds"] for r in singles + combos]
    fl = [r["flight_s"] for r in singles + combos]
    if secs:
        print(f"diagnosis wall per case: median {np.median(secs):.1f} s (max {np.max(secs):.1f} s) for median "
              f"{np.median(fl):.0f} s of in-air data; total bench wall {wall:.0f} s")
