"""``groundstation bench identify [--seeds 20] [--budget N] [--duration-s 150] [--source auto|sim|linear]``.

The paper's comparison and the identification targets on simulated flights with known truth:

1. colony cost-evaluation speed (state updates per second, median of repeats);
2. default identification (CABC + refinement) of one flight: wall time, parameter errors relative
   to truth, z-scores against the reported standard errors, and the match of the identified vs the
   TRUE model on a DIFFERENT flight of the same aircraft (scored the same way);
3. GA, ABC, CABC and DE with equal evaluation budgets over ``--seeds`` seeds (search only, no
   refinement, so the optimisers are compared and not the local polish): a Table-6-style match
   table, final costs, wall time, evaluations, and a Figure-11-style convergence PNG.

Flights come from the nonlinear simulator (``hil_replay.sim.write_tlog``, read back
through the ordinary .tlog reader) when available, else from the linear model itself
(``benchkit.synthetic``; that only checks the estimator against its own model).
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table
from threadpoolctl import threadpool_limits

from benchkit.synthetic import EXAMPLE_TRUTH, simulate_flight
from firmware_interface.readers import load_log
from groundstation.cli import build_parser
from groundstation.dsp.prepare import PrepConfig, prepare, prepared_from_arrays
from groundstation.sysid.cost import WindowedCost, make_windows, subset_windows
from groundstation.sysid.fit_section import Selection
from groundstation.sysid.identify import IdentifyConfig, identify
from groundstation.sysid.model import (
    HOR_PARAMS,
    N_PARAMS,
    PARAM_INDEX,
    PARAM_NAMES,
    HoverModel,
    bounds_array,
    theta_from_dict,
)
from groundstation.sysid.plots import plot_convergence
from groundstation.sysid.validate import validate
from hil_replay.sim import write_tlog

HELP = "identification benchmark: speed, accuracy vs truth, and GA/ABC/CABC/DE at equal budgets"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=20, help="runs per algorithm in the comparison")
    parser.add_argument("--budget", type=int, default=3000, help="cost evaluations per subsystem per run")
    parser.add_argument("--duration-s", type=float, default=150.0, help="simulated flight length")
    parser.add_argument("--source", choices=("auto", "sim", "linear"), default="auto")
    parser.add_argument("--sim-seed", type=int, default=1, help="seed of the training flight (validation: +1)")
    parser.add_argument("--passes", type=int, default=None, help="eq. 18 smoothing passes (default PrepConfig)")
    parser.add_argument("--algorithms", default="ga,abc,cabc,de")
    parser.add_argument("--out-dir", type=Path, default=Path("bench_identify"), help="PNG and JSON output")
    parser.add_argument("--skip-compare", action="store_true", help="only speed and accuracy")
    parser.add_argument("--profile", action="store_true",
                        help="only the CPU per stage of `groundstation identify FLIGHT --out m.json` (the default "
                             "command, one process) on the simulated training flight, or on --log")
    parser.add_argument("--log", type=Path, default=None, help="--profile: this flight log instead of a simulated one")
    parser.add_argument("--aircraft", type=Path, default=None, help="--profile: aircraft file for --log")
    parser.add_argument("--whole-runs", type=int, default=1,
                        help="--profile: also run the whole command this many times in fresh processes, "
                             "with --jobs 1 and with its default workers in turn, and print the median CPU of "
                             "every process each run started (0 = skip)")


def _flights(args, tmp: Path) -> tuple[Any, Any, dict[str, float], str]:
    """(train PreparedData, validation PreparedData, truth parameters, description)."""
    cfg = PrepConfig() if args.passes is None else PrepConfig(smooth_passes=args.passes)
    if args.source in ("auto", "sim"):
        preps, truth = [], None
        for k in range(2):
            path = tmp / f"flight{k}.tlog"
            truth = write_tlog(path, seed=args.sim_seed + k, flights=1, effects=(), aircraft=None,
                               flight_duration_s=args.duration_s)
            if truth is None:
                truth = json.loads(path.with_suffix(".truth.json").read_text())
            preps.append(prepare([load_log(path)], cfg))
        assert truth is not None
        return preps[0], preps[1], dict(truth["parameters"]), f"hil_replay.sim nonlinear flights (seeds {args.sim_seed}, {args.sim_seed + 1})"

    th = theta_from_dict(EXAMPLE_TRUTH)
    preps = []
    for k in range(2):
        u, _, ym = simulate_flight(th, args.duration_s, 0.02, seed=args.sim_seed + k)
        preps.append(prepared_from_arrays(u, ym, 0.02, smooth_passes=cfg.smooth_passes, source=f"linear{k}"))
    return preps[0], preps[1], dict(EXAMPLE_TRUTH), "linear eq.-8 model flights (benchkit.synthetic)"


def _speed(prepared, repeats: int = 7) -> dict[str, float]:
    """Colony cost evaluation rate: state updates (one x[k+1] = A x[k] + B u[k] for one candidate) per
    second, the median of ``repeats`` calls, per wall second and per CPU second of this process, with
    BLAS held to one thread. The colony is random over the default bounds (most candidates unstable),
    the cost as the bench's accuracy run scores it: 3-s windows, all 31 parameters, every initial
    state estimated. Also the identification search cost (1-s windows, B by variable projection)."""

    win = make_windows(prepared.segments, prepared.dt_s, 3.0)
    b = bounds_array()
    rng = np.random.default_rng(0)
    out: dict[str, float] = {"repeats": float(repeats), "load_average_1min": os.getloadavg()[0]}

    def rate(cost, X, updates):
        cost(X)
        ts, cs = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            cost(X)
            ts.append(time.perf_counter() - t0)
            cs.append(time.process_time() - c0)
        return updates / float(np.median(ts)), updates / max(float(np.median(cs)), 1e-9)

    with threadpool_limits(1):
        for C in (20, 64):
            cost = WindowedCost(win, np.ones(N_PARAMS, bool), np.zeros(N_PARAMS), estimate_all_initial=True)
            X = b[:, 0] + rng.random((C, N_PARAMS)) * (b[:, 1] - b[:, 0])
            out[f"colony_{C}"], out[f"colony_{C}_cpu"] = rate(cost, X, C * win.count * win.length)
        # the search as identify() runs it (horizontal subsystem, the larger one)
        ws = make_windows(prepared.segments, prepared.dt_s, 1.0)
        ws = subset_windows(ws, np.arange(0, ws.count, 3))
        free = np.zeros(N_PARAMS, dtype=bool)
        free[[PARAM_INDEX[p] for p in HOR_PARAMS]] = True
        cv = WindowedCost(ws, free, np.zeros(N_PARAMS), estimate_all_initial=True, subsystems=(0,), varpro=True)
        bv = b[cv.free]
        X = bv[:, 0] + rng.random((20, int(cv.free.sum()))) * (bv[:, 1] - bv[:, 0])
        out["search_20"], out["search_20_cpu"] = rate(cv, X, 20 * ws.count * ws.length)
    out["load_average_1min_after"] = os.getloadavg()[0]
    return out


def run(args: argparse.Namespace) -> int:
    con = Console()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    if args.profile:
        return _run_profile(args, con)
    with tempfile.TemporaryDirectory() as td:
        train, val, truth, desc = _flights(args, Path(td))
    con.print(f"[bold]flights[/]: {desc}; training {train.duration_s:.0f} s, validation {val.duration_s:.0f} s")

    sp = _speed(train)
    con.print(f"colony cost evaluation (BLAS 1 thread, median of {int(sp['repeats'])} calls, 1-min load average "
              f"{sp['load_average_1min']:.1f} on {os.cpu_count()} cores): {sp['colony_20']:.3g} state updates per wall "
              f"second ({sp['colony_20_cpu']:.3g} per CPU second) with 20 candidates, {sp['colony_64']:.3g} wall "
              f"({sp['colony_64_cpu']:.3g} CPU) with 64 (target >= 1e7)")
    con.print(f"identification search cost (1-s windows, horizontal, B by variable projection, 20 candidates): "
              f"{sp['search_20']:.3g} updates per wall second ({sp['search_20_cpu']:.3g} per CPU second)")

    t0, c0 = time.perf_counter(), time.process_time()
    model = identify(train, seed=0)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    con.print(f"default identification (CABC + refinement + held-out selection of the configuration): {wall:.2f} s wall "
              f"({cpu:.2f} s CPU), {model.fit.evaluations} evaluations, cost {model.fit.cost:.4f}")
    wall, cpu, wall0, cpu0 = _selection_cost(train, identify, IdentifyConfig, wall, cpu)
    sel = model.fit.selection or Selection()
    scores = ", ".join(f"{r.name} {r.mean_match:.1f} %" for r in sel.candidates)
    con.print(f"held-out selection over {sel.k} folds chose: {sel.chosen} ({scores}); medians of two "
              f"runs each, alternating: {wall:.2f} s wall ({cpu:.2f} s CPU) with it, {wall0:.2f} s wall ({cpu0:.2f} s CPU) "
              f"without: {wall / wall0:.2f}x wall, {cpu / cpu0:.2f}x CPU (target <= 1.5x)")
    t = Table(title="identified vs truth")
    for c in ("param", "truth", "estimate", "err %", "std", "z"):
        t.add_column(c, justify="right")
    z_all = []
    for n in PARAM_NAMES:
        true_v, est_v, s = truth[n], model.params[n], model.parameter_std.get(n)
        err = 100 * (est_v - true_v) / abs(true_v) if true_v != 0 else float("nan")
        z = (est_v - true_v) / s if s else float("nan")
        z_all.append(z)
        t.add_row(n, f"{true_v:.4g}", f"{est_v:.4g}", f"{err:.1f}", "-" if s is None else f"{s:.3g}", f"{z:.2f}")
    con.print(t)
    key = ("M_a", "L_b", "inv_tau_s", "A_lat", "B_lon", "Z_col", "N_ped", "N_r")
    key_err = {k: abs(model.params[k] - truth[k]) / abs(truth[k]) * 100 for k in key}
    za = np.abs(np.array(z_all, dtype=float))
    worst_key = max(key_err, key=lambda k: key_err[k])
    con.print(f"key parameters within 10%: {sum(v <= 10 for v in key_err.values())}/{len(key)} "
              f"(worst {worst_key} {key_err[worst_key]:.1f}%); "
              f"|z| <= 3: {int(np.sum(za <= 3))}/{int(np.isfinite(za).sum())} (max {np.nanmax(za):.2f})")
    true_model = HoverModel(params=dict(truth))
    v_id, v_true = validate(model, val).to_json(), validate(true_model, val).to_json()
    ratio = v_id["mean_match"] / v_true["mean_match"] * 100
    tv = Table(title="match degree on a DIFFERENT flight (%), identified vs true model")
    tv.add_column("model")
    for ch in v_true["channels"]:
        tv.add_column(ch, justify="right")
    tv.add_column("mean", justify="right")
    for name, v in (("identified", v_id), ("true", v_true)):
        tv.add_row(name, *[f"{v['channels'][c]['match']:.2f}" for c in v_true["channels"]], f"{v['mean_match']:.2f}")
    con.print(tv)
    con.print(f"identified / true mean match on the other flight: {ratio:.2f}% (target >= 99%)")
    summary: dict[str, Any] = {"flights": desc, "speed_updates_per_s": sp, "default_wall_s": wall, "default_cpu_s": cpu,
                               "no_selection_wall_s": wall0, "no_selection_cpu_s": cpu0, "selection": sel.chosen,
                               "key_err_pct": key_err, "z": dict(zip(PARAM_NAMES, [float(z) for z in z_all], strict=True)),
                               "match_ratio_pct": ratio, "match_identified": v_id["channels"], "match_true": v_true["channels"]}
    if not args.skip_compare:
        summary["comparison"] = _compare(args, train, con, identify, IdentifyConfig, plot_convergence)
    (args.out_dir / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    con.print(f"wrote {args.out_dir / 'summary.json'}")
    return 0


def _selection_cost(train, identify, IdentifyConfig, wall: float, cpu: float) -> tuple[float, float, float, float]:
    """Wall and CPU s of the default identification with and without the held-out selection of the
    configuration: medians of two runs each, alternating (without, with, without) after the first
    run with it (``wall``, ``cpu``), so load changes on a shared machine hit both alike."""
    runs: dict[bool, list[tuple[float, float]]] = {True: [(wall, cpu)], False: []}
    for with_sel in (False, True, False):
        t0, c0 = time.perf_counter(), time.process_time()
        identify(train, seed=0, config=IdentifyConfig() if with_sel else IdentifyConfig(select_candidates=""))
        runs[with_sel].append((time.perf_counter() - t0, time.process_time() - c0))
    med = {k: np.median(np.array(v), axis=0) for k, v in runs.items()}
    return float(med[True][0]), float(med[True][1]), float(med[False][0]), float(med[False][1])


def _compare(args, train, con, identify, IdentifyConfig, plot_convergence) -> dict[str, Any]:
    algs = [a.strip() for a in args.algorithms.split(",") if a.strip()]
    cfg = IdentifyConfig(maxfev=args.budget)
    res: dict[str, dict[str, Any]] = {a: {"cost": [], "match": [], "wall": [], "nfev": [], "curves": []} for a in algs}
    for a in algs:
        for s in range(args.seeds):
            t0 = time.perf_counter()
            m = identify(train, algorithm=a, seed=s, refine=False, maxiter=10**6, config=cfg)
            res[a]["wall"].append(time.perf_counter() - t0)
            res[a]["cost"].append(m.fit.cost)
            res[a]["match"].append(m.fit.match_degree)
            res[a]["nfev"].append(m.fit.evaluations)
            h, hn = m.fit.history, m.fit.history_nfev
            grid = np.linspace(min(100, args.budget), args.budget, 100)
            tot = np.zeros_like(grid)
            for sub in h:
                tot += np.interp(grid, hn[sub], h[sub], left=np.nan)
            res[a]["curves"].append((grid, tot))
        con.print(f"  {a}: {args.seeds} runs done, median cost {np.median(res[a]['cost']):.4f}")
    chans = list(res[algs[0]]["match"][0])
    t = Table(title=f"Table-6 style: mean match degree % over {args.seeds} seeds, {args.budget} evaluations per subsystem (search only)")
    t.add_column("channel")
    for a in algs:
        t.add_column(a.upper(), justify="right")
    for ch in chans:
        t.add_row(ch, *[f"{np.mean([mm[ch] for mm in res[a]['match']]):.2f}" for a in algs])
    t.add_row("final cost F (median)", *[f"{np.median(res[a]['cost']):.4f}" for a in algs])
    t.add_row("final cost F (best/worst)", *[f"{np.min(res[a]['cost']):.3f}/{np.max(res[a]['cost']):.3f}" for a in algs])
    t.add_row("wall s (median)", *[f"{np.median(res[a]['wall']):.2f}" for a in algs])
    t.add_row("evaluations (median)", *[f"{int(np.median(res[a]['nfev']))}" for a in algs])
    con.print(t)
    pairs = [("cabc", "abc"), ("abc", "ga"), ("cabc", "ga"), ("cabc", "de")]
    wins = {}
    for x, y in pairs:
        if x in res and y in res:
            w = float(np.mean(np.array(res[x]["cost"]) < np.array(res[y]["cost"])) * 100)
            wins[f"{x}<{y}"] = w
            con.print(f"{x.upper()} lower final cost than {y.upper()} (same seed): {w:.0f}% of seeds")
    png = plot_convergence({a: res[a]["curves"] for a in algs}, args.out_dir / "convergence.png",
                           title=f"Fitness 1/(1+F) vs evaluations per subsystem ({args.seeds} seeds; median, range)")
    con.print(f"wrote {png}")
    return {a: {"cost": res[a]["cost"], "wall": res[a]["wall"], "nfev": res[a]["nfev"],
                "match_mean": {ch: float(np.mean([mm[ch] for mm in res[a]["match"]])) for ch in chans}} for a in algs} | {"wins_pct": wins}


# --- per-stage CPU of the default ``identify`` command (``--profile``) ------------------------------

#: stages of ``groundstation identify`` and the functions whose CPU they are (module, function[, the
#: stages under which it counts]). Time goes to the innermost stage running, so a stage's figure
#: excludes the stages it calls (the held-out folds of the selection are "held-out folds", not
#: "selection"); a function with a list of stages counts only under those (the refinements of the
#: search's starts stay "screening refinements", those of the selection's candidates "selection").
STAGES: tuple[tuple[str, ...], ...] = (
    ("read + prepare", "groundstation.pipeline", "prepare_logs"),
    ("read + prepare", "groundstation.pipeline", "load_logs"),
    ("read + prepare", "groundstation.dsp.prepare", "prepare"),
    ("search", "groundstation.sysid.optimizers", "minimize_cabc"),
    ("search", "groundstation.sysid.optimizers", "minimize_abc"),
    ("search", "groundstation.sysid.optimizers", "minimize_ga"),
    ("search", "groundstation.sysid.optimizers", "minimize_de"),
    ("screening refinements", "groundstation.sysid.identify", "_screen_refine"),
    ("identify: windows, costs, in-sample match", "groundstation.sysid.identify", "identify"),
    ("refinements", "groundstation.sysid.refine", "refine", "identify: windows, costs, in-sample match"),
    ("selection", "groundstation.sysid.select", "select_config"),
    ("held-out folds", "groundstation.sysid.heldout", "crossvalidate"),
    ("closed-loop evidence", "groundstation.sysid.heldout", "feedback_evidence"),
    ("validation", "groundstation.sysid.validate", "validate"),
    ("plots", "groundstation.sysid.plots", "plot_fit"),
    ("plots", "groundstation.sysid.plots", "plot_convergence"),
    ("frequency check", "groundstation.freq.spectra", "estimate_responses"),
    ("frequency check", "groundstation.freq.verify", "verify"),
)


class StageTimer:
    """CPU seconds (``time.process_time``: this process, every thread) per stage of :data:`STAGES`.

    While active, the stage functions are wrapped wherever the ``groundstation`` modules hold them
    (module attributes and module-level dicts such as the optimiser registry); CPU between two
    stage boundaries goes to the innermost stage running, the rest to "other" (imports, argument
    parsing, writing the model). Only the calling process is measured: run with one job.
    """

    def __init__(self) -> None:
        self.cpu_s: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._stack: list[str] = []
        self._t = 0.0
        self._undo: list[tuple[Any, Any, Any]] = []

    def _switch(self) -> None:
        t = time.process_time()
        top = self._stack[-1] if self._stack else "other"
        self.cpu_s[top] = self.cpu_s.get(top, 0.0) + t - self._t
        self._t = t

    def _wrap(self, stage: str, fn: Any, under: tuple[str, ...] = ()) -> Any:
        @functools.wraps(fn)
        def wrapped(*a: Any, **kw: Any) -> Any:
            if under and (not self._stack or self._stack[-1] not in under):
                return fn(*a, **kw)
            self._switch()
            self._stack.append(stage)
            self.calls[stage] = self.calls.get(stage, 0) + 1
            try:
                return fn(*a, **kw)
            finally:
                self._switch()
                self._stack.pop()
        return wrapped

    def __enter__(self) -> StageTimer:
        for stage, mod, name, *under in STAGES:
            try:
                fn = getattr(importlib.import_module(mod), name)
            except (ImportError, AttributeError):
                continue   # moved or not installed: that stage reads 0
            w = self._wrap(stage, fn, tuple(under))
            for m in [m for k, m in list(sys.modules.items()) if k.startswith("groundstation") and m is not None]:
                for attr, val in list(vars(m).items()):
                    if val is fn:
                        self._undo.append((m, attr, fn))
                        setattr(m, attr, w)
                    elif isinstance(val, dict):
                        for key, v in list(val.items()):
                            if v is fn:
                                self._undo.append((val, key, fn))
                                val[key] = w
        self._t = time.process_time()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._switch()
        for obj, key, fn in reversed(self._undo):
            if isinstance(obj, dict):
                obj[key] = fn
            else:
                setattr(obj, key, fn)
        self._undo.clear()

    def table(self) -> list[tuple[str, float, int]]:
        order = list(dict.fromkeys([s[0] for s in STAGES] + ["other"]))
        return [(s, self.cpu_s.get(s, 0.0), self.calls.get(s, 0)) for s in order if s in self.cpu_s]


def profile_identify(log: Path, out: Path, *, aircraft: Path | None = None, extra: tuple[str, ...] = ()) -> tuple[StageTimer, float, float]:
    """Run ``groundstation identify LOG --out OUT [--aircraft A] --jobs 1`` in this process under a
    :class:`StageTimer`; returns it, the wall and the CPU seconds of the command."""
    argv = ["identify", str(log), "--out", str(out), "--quiet", "--jobs", "1", *extra]
    if aircraft is not None:
        argv += ["--aircraft", str(aircraft)]
    args = build_parser(["identify"]).parse_args(argv)
    t0, c0 = time.perf_counter(), time.process_time()
    with StageTimer() as st:
        args._module.run(args)
    return st, time.perf_counter() - t0, time.process_time() - c0


#: run in a fresh process by :func:`command_cpu` (argv: the command as JSON, the reaping timeout):
#: it becomes the reaper of its orphaned descendants (Linux ``PR_SET_CHILD_SUBREAPER``), so a fork
#: server and the processes it forked come back to it when the command that started them exits, and
#: their CPU counts in its ``RUSAGE_CHILDREN`` once reaped; its only children are the command's
_MEASURE = """
import ctypes, json, os, resource, subprocess, sys, time
argv, timeout_s = json.loads(sys.argv[1]), float(sys.argv[2])
if sys.platform == "linux":
    ctypes.CDLL(None).prctl(36, 1, 0, 0, 0)
t0 = time.perf_counter()
rc = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False).returncode
wall = time.perf_counter() - t0
deadline = time.monotonic() + timeout_s
while time.monotonic() < deadline:   # the orphans exit once the command's pipes to them close
    try:
        pid, _ = os.waitpid(-1, os.WNOHANG)
    except ChildProcessError:
        break
    if pid == 0:
        time.sleep(0.01)
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps([wall, ru.ru_utime + ru.ru_stime, rc]))
"""


def command_cpu(argv: list[str], *, reap_timeout_s: float = 30.0) -> tuple[float, float, int]:
    """Run ``argv`` in a fresh process; returns its wall seconds, the CPU seconds (user+sys) of it and
    of every process it started however deep (worker processes, a fork server and its workers; off
    Linux only those its own process waited for), and its exit code: :data:`_MEASURE`. Unlike
    ``/usr/bin/time`` it counts a fork server's workers, and unlike the machine-wide CPU it holds
    on a busy machine."""
    out = subprocess.run([sys.executable, "-c", _MEASURE, json.dumps(argv), str(reap_timeout_s)],
                         capture_output=True, text=True, check=True).stdout
    wall, cpu, rc = json.loads(out.splitlines()[-1])
    return float(wall), float(cpu), int(rc)


def whole_command(log: Path, out: Path, runs: int, aircraft: Path | None = None) -> dict[str, list[tuple[float, float]]]:
    """``groundstation identify LOG --out OUT --quiet`` with ``--jobs 1`` and with its default workers,
    in turn, ``runs`` times each: (wall, CPU of every process) per run (:func:`command_cpu`)."""
    base = [sys.executable, "-m", "groundstation", "identify", str(log), "--out", str(out), "--quiet"]
    base += [] if aircraft is None else ["--aircraft", str(aircraft)]
    res: dict[str, list[tuple[float, float]]] = {"--jobs 1": [], "default": []}
    for _ in range(runs):
        for label, extra in (("--jobs 1", ["--jobs", "1"]), ("default", [])):
            wall, cpu, rc = command_cpu(base + extra)
            if rc != 0:
                raise RuntimeError(f"{' '.join(base + extra)}: exit code {rc}")
            res[label].append((wall, cpu))
    return res


def _run_profile(args: argparse.Namespace, con: Any) -> int:
    """``--profile``: the stage table of one identify command, and the whole command's CPU."""
    with tempfile.TemporaryDirectory() as td:
        log = args.log
        if log is None:
            log = Path(td) / "flight.tlog"
            write_tlog(log, seed=args.sim_seed, flights=1, effects=(), aircraft=None, flight_duration_s=args.duration_s)
        st, wall, cpu = profile_identify(log, args.out_dir / "profile_model.json", aircraft=args.aircraft)
        whole = whole_command(log, args.out_dir / "whole_model.json", args.whole_runs, args.aircraft)
    load = os.getloadavg()
    t = Table(title=f"groundstation identify {log.name if args.log else f'(simulated {args.duration_s:g} s flight)'}"
                    f" --jobs 1: CPU per stage")
    for c in ("stage", "CPU s", "share", "calls"):
        t.add_column(c, justify="right" if c != "stage" else "left")
    for name, s, n in st.table():
        t.add_row(name, f"{s:.2f}", f"{100 * s / max(cpu, 1e-9):.0f} %", str(n) if n else "")
    con.print(t)
    con.print(f"total {cpu:.2f} s CPU (this process), {wall:.2f} s wall; load average {load[0]:.2f} {load[1]:.2f} "
              f"{load[2]:.2f} on {os.cpu_count()} cores (wall is only a measurement on an otherwise idle machine)")
    for label, rows in whole.items():
        if rows:
            c, w = np.median([r[1] for r in rows]), np.median([r[0] for r in rows])
            con.print(f"whole command {label}, fresh process, median of {len(rows)}: {c:.2f} s CPU of every process "
                      f"it started (CPU {', '.join(f'{r[1]:.2f}' for r in rows)}), {w:.2f} s wall")
    (args.out_dir / "profile.json").write_text(json.dumps(
        {"log": str(args.log or f"simulated {args.duration_s} s seed {args.sim_seed}"), "cpu_s": cpu, "wall_s": wall,
         "load_average": load, "stages_cpu_s": {n: s for n, s, _ in st.table()},
         "whole_command": {k: [{"wall_s": w, "cpu_s": c} for w, c in v] for k, v in whole.items()}}, indent=1))
    return 0
