"""``groundstation bench diagnose --cases N --seed S [--out-of-catalogue K] [--combined M]``: blind test.

Generates simulated flights (the scenario sets of :mod:`hil_replay.scenarios`, written with
``hil_replay.sim.write_tlog``, the independent simulator), each
with one random catalogue effect (``hil_replay.sim.effects.random_effect``: random channel and
magnitude) or none, classes taken in turn; K flights with an effect OUTSIDE the catalogue
(``hil_replay.sim.effects.OUT_OF_CATALOGUE``: gyro scale factor, velocity-sensor scale, rotor speed
sagging with collective, asymmetric input gain) whose right answer is ``unexplained`` or the sensor
error found by data compatibility; and M flights with two catalogue effects at once. Unless
``--plain``, every flight is drawn from a varied simulator: aircraft (TREX-600 or R-50) with every
eq.-8 parameter scattered (log-normal, ``--scatter``), stiff / default / loose pilot, sweep-free
cards (3-2-1-1 multisteps only) on half the flights, attitude and velocity streams at 10-50 Hz,
excitation amplitude 0.6-1.3x, nonlinear kinematics on or off (the rigid body linearised about
hover) on half the flights each. ``--kinds`` runs only some kinds of case (the others are drawn
and skipped, so each case is the same flight as in the full run). Hides the label; reads the .tlog back through the ordinary reader,
prepares it and diagnoses it (identifying the model first unless ``--model-source truth``).

``--held-back N`` adds N flights of a set held back from every tuning of the diagnosis
(``hil_replay.sim.effects.HELD_BACK``: physics a catalogue entry only approximates, whose right
answer is that entry, and parameters that drift through the flight, whose right answer is
``unexplained``; effect-free flights and catalogue effects at other noise levels), with their own
random draws and seeds (``1000 S + 700 + j``), reported separately.

Prints the confusion matrix, top-1 accuracy, false alarms on effect-free flights, invented second
effects (a named effect that is not in the flight, beside a right one), the out-of-catalogue
outcome (``unexplained`` or the right sensor finding; catalogue names with a shrink above 10 %),
both-found rate on two-effect flights, channel accuracy, parameter errors, wall time per case.
Cases run in a process pool.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.analysis import analyse
from groundstation.config import ServiceConfig
from groundstation.parallel import serial_map, worker_map
from groundstation.sysid.model import HoverModel
from hil_replay import scenarios
from hil_replay.sim.effects import aliased_hz

HELP = "blind test of the gap diagnosis on simulated flights with hidden random effects"

#: kinds of case (``--kinds``) and classes (``--classes``): see :mod:`hil_replay.scenarios`
CLASSES = scenarios.CLASSES
KINDS = scenarios.KINDS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cases", type=int, default=20, help="flights with one catalogue effect or none")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out-of-catalogue", type=int, default=0, dest="out_of_catalogue",
                        help="extra flights with an effect outside the catalogue")
    parser.add_argument("--combined", type=int, default=0, help="extra cases with two effects at once")
    parser.add_argument("--held-back", type=int, default=0, dest="held_back",
                        help="extra flights from the set held back from tuning (other physics, drifting "
                             "parameters, other noise levels), reported separately")
    parser.add_argument("--workers", type=int, default=2, help="flights diagnosed at once (processes)")
    parser.add_argument("--jobs", type=int, default=1,
                        help="worker processes inside each diagnosis (its independent scans); with --workers 1 "
                             "the flights run one after the other, each on --jobs cores: the wall time per "
                             "flight a user with that many cores sees")
    parser.add_argument("--classes", default=",".join(CLASSES), help="comma-separated classes to draw from")
    parser.add_argument("--model-source", choices=("identify", "truth"), default="identify",
                        help="base model: identified from the flight (blind) or the simulator's truth parameters")
    parser.add_argument("--fresh", action="store_true", help="also measure the shrink on a fresh flight")
    parser.add_argument("--plain", action="store_true",
                        help="the simulator's default flights (no random aircraft, pilot, card, rates)")
    parser.add_argument("--scatter", type=float, default=0.25,
                        help="log-normal sigma of the aircraft parameter scatter on varied flights")
    parser.add_argument("--aircraft", default=None, help="simulator aircraft name (default: drawn, or the simulator's)")
    parser.add_argument("--rates", default=None,
                        help="telemetry rates of the simulated autopilot, e.g. ATTITUDE=25,LOCAL_POSITION_NED=10 "
                             "(default: drawn, or the simulator's); a robustness check against other stream set-ups")
    parser.add_argument("--pilot", choices=tuple(scenarios.PILOTS), default=None,
                        help="synthetic pilot: tight (stiffer loops, less input left on the excited axis), "
                             "loose, or the simulator's default (default: drawn)")
    parser.add_argument("--kinematics", choices=("nonlinear", "linear"), default=None,
                        help="simulator rigid body: full nonlinear equations, or linearised about hover "
                             "(nonlinear kinematics off) (default: drawn, on or off with equal odds; "
                             "nonlinear with --plain)")
    parser.add_argument("--excitation", type=float, default=None,
                        help="scale of the card's sweep and doublet amplitudes (e.g. 0.5: a cautious pilot)")
    parser.add_argument("--kinds", default="single,outside,combined,held_back",
                        help="comma-separated kinds of case to run (single, outside, combined): the others are "
                             "drawn but not run, so each case is the same flight as in a full run of these options")
    parser.add_argument("--json", type=Path, default=None,
                        help="write every case result to this JSON file (rewritten as each case finishes)")
    parser.add_argument("--from-json", type=Path, default=None, dest="from_json",
                        help="print the summary of a JSON file written by --json (a whole or a stopped run) "
                             "without running anything")


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


def tree_cpu_s() -> float:
    """CPU time (s) of this process and of its live descendants (the worker processes of a
    diagnosis's ``--jobs``, which a fork server forks: grandchildren), read from /proc where there is
    one; this process alone elsewhere."""
    t = time.process_time()
    try:
        tick = os.sysconf("SC_CLK_TCK")
        todo, seen = _child_pids("self"), set()
    except (OSError, ValueError):
        return t
    while todo:
        pid = todo.pop()
        if pid in seen:
            continue
        seen.add(pid)
        try:
            f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            t += (int(f[11]) + int(f[12])) / tick  # utime, stime
            todo.extend(_child_pids(pid))
        except (OSError, ValueError, IndexError):  # exited between the listing and the reading
            continue
    return t


def _child_pids(pid: str) -> list[str]:
    """The child process ids of ``pid`` ("self" for this process), from /proc."""
    out: list[str] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        out.extend((task / "children").read_text().split())
    return out


def run_case(job: dict[str, Any], pmap: Any = None) -> dict[str, Any]:
    """Simulate, read back, prepare, diagnose one case (runs in a worker process; ``pmap``: a map over
    worker processes for the diagnosis's independent pieces, None: serial)."""
    out: dict[str, Any] = {"case": job["case"], "kind": job["kind"], "truth_effects": job["effects"],
                           "flight": job["flight"], "expect": job.get("expect")}
    with tempfile.TemporaryDirectory() as td:
        path = Path(td) / f"case{job['case']}.tlog"
        truth = scenarios.write_case(path, job)
        out["truth"] = truth.get("effects", [])
        t0 = time.perf_counter()
        c0 = tree_cpu_s()
        model = None
        if job["model_source"] == "truth":
            model = HoverModel(params=dict(truth["parameters"]))
        cfg = ServiceConfig().replace("identification", seed=job["seed"])
        try:   # the product's analysis, the diagnosis step only (the model given, or identified by the diagnosis)
            res = analyse([path], config=cfg, steps=("diagnose",), model=model, pmap=pmap or serial_map)
            assert res.gap is not None   # the diagnosis step ran
            prepared, diag = res.prepared, res.gap.diagnosis
        except ValueError as exc:  # a flight the diagnosis refuses (too little data): counted, not hidden
            out.update(seconds=time.perf_counter() - t0, cpu_s=tree_cpu_s() - c0, flight_s=0.0, verdict="refused", effects=[], sensor_errors=[],
                       candidates=[], error=str(exc))
            return out
        out["seconds"] = time.perf_counter() - t0
        out["cpu_s"] = tree_cpu_s() - c0
        out["load_1min"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
        out["flight_s"] = float(sum(s.t_s[-1] - s.t_s[0] for s in prepared.segments))
        rep = diag.report
        out["verdict"] = rep["verdict"]
        out["effects"] = [{k: e[k] for k in ("effect", "input", "output", "estimate", "shrink_pct", "score")}
                          for e in rep["effects"]]
        out["sensor_errors"] = [{k: e.get(k) for k in ("kind", "channel", "estimate", "se", "significant")}
                                for e in rep.get("data_compatibility", {}).get("findings", [])
                                if e.get("significant")]
        # every scored hypothesis (significant or not), for inspecting why a case went wrong
        out["candidates"] = [{k: e.get(k) for k in ("effect", "input", "output", "estimate", "score", "p_value",
                                                    "shrink_pct", "evidence")} for e in rep["effects"] + rep["candidates"]]
        out["unexplained"] = rep.get("unexplained")
        out["structure_tests"] = [{k: t.get(k) for k in ("kind", "input", "coefficient", "score_pct", "p_value",
                                                     "significant", "effect_to_noise")} for t in rep.get("structure_tests", [])]
        out["gap_to_noise_ratio"] = rep["gap"].get("gap_to_noise_ratio")
        out["gap_significant"] = rep["gap"].get("significant")
        sh = rep.get("shares") or {}
        out["explained_pct"] = sh.get("explained_pct")
        out["partial_explained_pct"] = sh.get("partial_explained_pct")
        out["headline"] = sh.get("headline")
        out["partial_findings"] = [{k: e.get(k) for k in ("effect", "input", "output", "share_pct", "consistency")}
                                   for e in rep.get("partial_findings", [])]
        out["consistency"] = [{k: e.get("consistency", {}).get(k) for k in ("status", "parameter", "first", "second")}
                              for e in rep["effects"]]
        if job.get("fresh") and job["effects"]:
            path2 = Path(td) / "fresh.tlog"
            # the same effect and magnitude, another flight
            scenarios.write_case(path2, job, flight_seed=job["seed"] + 100000)
            d2 = analyse([path2], config=cfg, steps=("diagnose",), model=model).gap
            assert d2 is not None
            allc = d2.report["effects"] + d2.report["candidates"]
            same = [e for e in allc if e["effect"] == job["effects"][0]]
            out["fresh_shrink_pct"] = same[0]["shrink_pct"] if same else None
    return out


def scenario_set(args: argparse.Namespace) -> scenarios.ScenarioSet:
    """The scenario set of the command line (ValueError naming the option on a bad value)."""
    classes = tuple(c.strip() for c in args.classes.split(",") if c.strip())
    unknown = set(classes) - set(CLASSES)
    if unknown:
        raise ValueError(f"--classes: unknown effect name(s) {sorted(unknown)}; allowed {CLASSES}")
    kinds = tuple(k.strip() for k in args.kinds.split(",") if k.strip())
    if not kinds or set(kinds) - set(KINDS):
        raise ValueError(f"--kinds: {args.kinds!r}: allowed {', '.join(KINDS)}")
    return scenarios.ScenarioSet(
        cases=args.cases, seed=args.seed, out_of_catalogue=args.out_of_catalogue, combined=args.combined,
        held_back=args.held_back, classes=classes, kinds=kinds, model_source=args.model_source, fresh=args.fresh,
        plain=args.plain, scatter=args.scatter, aircraft=args.aircraft, rates_hz=parse_rates(args.rates),
        pilot=args.pilot, kinematics=args.kinematics, excitation=args.excitation)


def run(args: argparse.Namespace) -> int:
    classes = [c.strip() for c in args.classes.split(",") if c.strip()]
    unknown = set(classes) - set(CLASSES)
    if unknown:
        raise ValueError(f"--classes: unknown effect name(s) {sorted(unknown)}; allowed {CLASSES}")
    if args.from_json is not None:
        try:
            saved = json.loads(args.from_json.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"--from-json {args.from_json}: {exc}") from None
        print(f"{len(saved)} cases from {args.from_json}")
        print_summary(sorted(saved, key=lambda r: r["case"]), classes, float("nan"))
        return 0
    spec = scenario_set(args)  # a bad --rates or --kinds is reported before any flight is simulated
    jobs = scenarios.interleave(scenarios.select_jobs(spec))
    t0 = time.perf_counter()
    results: list[dict[str, Any]] = []
    for r in _run_jobs(jobs, args.workers, args.jobs):
        results.append(r)
        if args.json:  # written as cases finish: a bench stopped early keeps what it measured
            args.json.write_text(json.dumps(results, indent=1, default=str))
    wall = time.perf_counter() - t0
    print_summary(sorted(results, key=lambda r: r["case"]), classes, wall)
    return 0


def _run_jobs(jobs: list[dict[str, Any]], workers: int, n_jobs: int) -> Any:
    """The case results as they finish: ``workers`` flights at once in a process pool, or (one worker)
    one after the other in this process, each diagnosis on ``n_jobs`` worker processes."""
    if workers <= 1:
        with worker_map(max(1, n_jobs)) as pmap:
            for job in jobs:
                r = run_case(job, pmap if n_jobs > 1 else None)
                r["jobs"] = max(1, n_jobs)
                yield r
        return
    with ProcessPoolExecutor(max_workers=workers) as pool:
        yield from pool.map(run_case, jobs)


def _named(r: dict[str, Any]) -> list[str]:
    return [e["effect"] for e in r["effects"]]


def _sensor_right(r: dict[str, Any]) -> bool:
    """An out-of-catalogue sensor error found by data compatibility on the right channel."""
    t = r["truth"][0] if r.get("truth") else {}
    ch = t.get("output") or t.get("input")
    return any(f.get("kind") == t.get("effect") and (ch is None or f.get("channel") == ch)
               for f in r.get("sensor_errors", []))


def print_summary(results: list[dict], classes: list[str], wall: float) -> None:
    held = [r for r in results if r["kind"] == "held_back"]
    singles = [r for r in results if r["kind"] == "single"]
    outside = [r for r in results if r["kind"] == "outside"]
    combos = [r for r in results if r["kind"] == "combined"]
    for r in results:
        got = [(e["effect"], e["input"] or e["output"]) for e in r["effects"][:3]]
        sens = [(f["kind"], f["channel"]) for f in r.get("sensor_errors", [])]
        tr = [(t["effect"], t.get("input") or t.get("output")) for t in r.get("truth", [])]
        fl = r["flight"]
        setup = (f"{fl['aircraft']}/{fl['pilot']}/{'sweeps' if fl['sweeps'] else 'multisteps'}/"
                 f"{(fl.get('rates') or {}).get('ATTITUDE', 50):g}Hz/{fl.get('kinematics', 'nonlinear')[:3]}")
        print(f"  case {r['case']:3d} [{setup}] truth {tr} -> {r['verdict']} {got}"
              f"{' sensor ' + str(sens) if sens else ''} ({r['seconds']:.0f} s)")
    _print_singles(singles, classes)
    _print_invented(singles + combos)
    if outside:
        ok = sum(r["verdict"] == "unexplained" or _sensor_right(r) for r in outside)
        wrong = [r for r in outside if any((e.get("shrink_pct") or 0) > 10 for e in r["effects"])]
        print(f"out-of-catalogue flights: unexplained or the right sensor finding {ok}/{len(outside)}; "
              f"a catalogue name with shrink > 10 %: {len(wrong)}/{len(outside)}")
    if combos:
        both = sum(all(t in _named(r) for t in r["truth_effects"]) for r in combos)
        print(f"two-effect flights with both effects named: {both}/{len(combos)}")
    secs = [r["seconds"] for r in results]
    cpu = [r.get("cpu_s", np.nan) for r in results]
    fl = [r["flight_s"] for r in results]
    if secs:
        print(f"diagnosis wall per case: median {np.median(secs):.1f} s (max {np.max(secs):.1f} s) for median "
              f"{np.median(fl):.0f} s of in-air data; total bench wall {wall:.0f} s")
        print(f"diagnosis CPU time per case (all its processes; independent of other load on the machine): "
              f"median {np.median(cpu):.1f} s (max {np.max(cpu):.1f} s)")
        load = [r["load_1min"] for r in results if r.get("load_1min") is not None]
        if load:
            print(f"machine load (1-min average, runnable processes) at the end of each case: median "
                  f"{np.median(load):.1f} on {os.cpu_count()} cores")
        per150 = [r["seconds"] * 150.0 / r["flight_s"] for r in results if r.get("flight_s")]
        jobs = {r.get("jobs", 1) for r in results}
        if per150:
            print(f"diagnosis wall per 150 s of in-air data: median {np.median(per150):.1f} s (max "
                  f"{np.max(per150):.1f} s), {'one flight at a time on ' + str(max(jobs)) + ' worker process(es)' if 'jobs' in results[0] else 'flights diagnosed in parallel'}"
                  f"; wall includes whatever else loads the machine")
    if held:
        print_held_back(held)


def print_held_back(held: list[dict]) -> None:
    """The held-back set, on its own: top-1 on the flights with a catalogue answer (or none), the
    out-of-catalogue (drifting) flights, invented second effects per right report, false alarms."""
    drift = [r for r in held if r.get("expect") == "unexplained"]
    rest = [r for r in held if r.get("expect") != "unexplained"]
    right = [r for r in rest if r["verdict"] == r.get("expect")]
    nones = [r for r in rest if r.get("expect") == "none"]
    inv = sum(any(e != r.get("expect") for e in _named(r)) for r in right if r.get("expect") != "none")
    n_right_eff = sum(r.get("expect") != "none" for r in right)
    print("held-back set (never used for tuning):")
    for r in held:
        print(f"  case {r['case']:3d} {r['truth_effects'] or ['none']} noise x{r['flight'].get('noise_scale', 1.0):g}"
              f" expect {r.get('expect')} -> {r['verdict']} {_named(r)}"
              f"{' explained ' + str(r['explained_pct']) + '%' if r.get('explained_pct') is not None else ''}"
              f"{_gap_text(r)}")
    if rest:
        print(f"held-back top-1 accuracy: {len(right)}/{len(rest)} = {100.0 * len(right) / len(rest):.1f}%")
    if nones:
        print(f"held-back false alarms on effect-free flights: {sum(r['verdict'] != 'none' for r in nones)}/{len(nones)}")
    print(f"held-back reports with an invented second effect: {inv}/{n_right_eff} right reports")
    if drift:
        ok = sum(r["verdict"] == "unexplained" or _sensor_right(r) for r in drift)
        print(f"held-back drifting / out-of-catalogue flights: unexplained {ok}/{len(drift)}")
        # a departure no larger than the noise cannot be told from an effect-free flight by any test:
        # the drifting flights whose held-out gap is significant are the ones the figure can ask for
        sig = [r for r in drift if r.get("gap_significant")]
        if len(sig) < len(drift):
            ok_s = sum(r["verdict"] == "unexplained" or _sensor_right(r) for r in sig)
            print(f"  of them with a significant held-out gap: unexplained {ok_s}/{len(sig)}; the other "
                  f"{len(drift) - len(sig)} leave a gap at the noise floor (verdicts "
                  f"{', '.join(r['verdict'] for r in drift if not r.get('gap_significant'))})")


def _gap_text(r: dict) -> str:
    """`` gap max Nx noise (significant|at the noise floor)`` of a case, when the run recorded it."""
    g = r.get("gap_to_noise_ratio") or {}
    if not g or r.get("gap_significant") is None:
        return ""
    c = max(g, key=lambda k: g[k])
    return f" gap {c} {g[c]:g}x noise ({'significant' if r['gap_significant'] else 'not significant'})"


def _print_singles(singles: list[dict], classes: list[str]) -> None:
    labels = list(classes) + [c for c in ("unexplained", "sensor_error", "refused") if c not in classes]
    idx = {c: i for i, c in enumerate(labels)}
    cm = np.zeros((len(classes), len(labels)), int)
    chan_ok = chan_n = 0
    param_err: list[str] = []
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
    n = len(singles)
    if not n:
        return
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


def _print_invented(reports: list[dict]) -> None:
    """Reports naming an effect that is not in the flight, beside a right top verdict (or on none)."""
    inv = 0
    for r in reports:
        truth = set(r["truth_effects"])
        extra = [e for e in _named(r) if e not in truth]
        if truth and r["verdict"] in truth and extra:
            inv += 1
        elif not truth and len(extra) > 1:
            inv += 1
    print(f"reports with an invented second effect: {inv}/{len(reports)}")
