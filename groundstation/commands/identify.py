"""``groundstation identify LOG... --out model.json [--algorithm cabc|abc|ga|de] [--seed N] [--no-refine] [--config FILE.toml]``.

Reads and prepares the logs and identifies the hover model through :mod:`groundstation.pipeline`
(the same chain the service's worker runs) with a rich progress bar, writes the model file
(docs/model-file.md; atomically) and a PNG of measured vs model next to it (``model.png``), and prints
a summary. Options override the configuration file (``[prepare]``, ``[identify]``, ``[bounds]``,
``[identification]``; see docs/configuration.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import time
from pathlib import Path

import numpy as np

HELP = "identify the hover model (paper eq. 8) from flight logs with CABC and write the model JSON"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", type=Path, help=".tlog / .bin / .px4log / .ulg flight logs")
    parser.add_argument("--out", type=Path, required=True, help="model JSON to write")
    parser.add_argument("--algorithm", choices=("cabc", "abc", "ga", "de"), default=None,
                        help="search algorithm (default: [identification] algorithm, cabc)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: [identification] seed, 0)")
    parser.add_argument("--no-refine", action="store_true", help="skip the least-squares refinement (no std errors)")
    parser.add_argument("--maxiter", type=int, default=None, help="search iterations per subsystem")
    parser.add_argument("--restarts", type=int, default=None,
                        help="independent searches per subsystem (the second and later by differential evolution), "
                             "lowest refined cost wins (default: [identify] search_restarts, 2)")
    parser.add_argument("--config", type=Path, default=None,
                        help="configuration TOML ([prepare] channel map and trims, [identify], [bounds], ...)")
    parser.add_argument("--aircraft", type=Path, default=None,
                        help="aircraft TOML: input source and channel map, measured outputs, prior model")
    parser.add_argument("--folds", type=int, default=5,
                        help="held-out check: refit on k-1 contiguous blocks of the in-air time and predict the "
                             "left-out one, for each block (default 5; 0 = skip)")
    parser.add_argument("--no-plot", action="store_true", help="do not write the PNG")
    parser.add_argument("--rrd", type=Path, default=None, help="also write measured vs model to a Rerun .rrd file")
    parser.add_argument("--segments", choices=("flights", "sysid"), default="flights", help=SEGMENTS_HELP)
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--jobs", type=int, default=None,
                        help="worker processes for reading the logs, the searches' screening refinements and the "
                             "held-out folds (default: all cores but one; the model is the same for any number)")
    parser.add_argument("--domain", choices=("time", "frequency", "both"), default="time",
                        help="time: the paper's output-error fit (default); frequency: minimise Tischler's J over the "
                             "flight's frequency responses; both: the time fit, then the frequency cost as a "
                             "refinement started from it; each scored both ways")
    parser.add_argument("--fit-delays", action="store_true", help="frequency domain: also fit one delay per input")
    parser.add_argument("--freq-weighting", choices=("output_error", "coherence", "random_error"), default="output_error",
                        help="frequency-domain cost: output_error = the Fourier transforms of 3-s windows of the "
                             "flight against the model's, from the J fit (default); coherence = Tischler's J only; "
                             "random_error = each coherent point weighted by its random error")
    from groundstation.commands.freq_support import add_freq_arguments

    add_freq_arguments(parser)


def config_from_args(args: argparse.Namespace):
    """The configuration file (``--config``) with this command's options applied."""
    from groundstation.config import load_config

    cfg = load_config(args.config)
    ident: dict = {}
    if getattr(args, "algorithm", None) is not None:
        ident["algorithm"] = args.algorithm
    if getattr(args, "seed", None) is not None:
        ident["seed"] = args.seed
    if getattr(args, "no_refine", False):
        ident["refine"] = False
    if ident:
        cfg = cfg.replace("identification", **ident)
    if getattr(args, "restarts", None) is not None:
        if args.restarts < 1:
            raise ValueError(f"--restarts: {args.restarts} must be >= 1")
        cfg = cfg.replace("identify", search_restarts=args.restarts)
    if getattr(args, "maxiter", None) is not None:
        if args.maxiter < 1:
            raise ValueError(f"--maxiter: {args.maxiter} must be >= 1")
        cfg = cfg.replace("identify", maxiter=args.maxiter)
    return cfg


SEGMENTS_HELP = ("which data to use: 'flights' (every in-air interval, default) or 'sysid' (only the "
                 "system-identification chirps of ArduPilot SYSID-mode dataflash logs)")


def write_json(path: Path, doc: dict) -> None:
    from groundstation.jsonio import write_atomic

    write_atomic(path, doc)


def run(args: argparse.Namespace) -> int:
    from groundstation.parallel import worker_map
    from groundstation.pipeline import about_logs

    with about_logs(args.logs), worker_map(args.jobs) as pmap:
        return _run(args, pmap)


def _run(args: argparse.Namespace, pmap) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from groundstation.pipeline import identify_prepared, load_aircraft, prepare_logs, with_aircraft

    cfg = config_from_args(args)
    algorithm = cfg.identification.algorithm
    aircraft = load_aircraft(args.aircraft)
    cfg = with_aircraft(cfg, aircraft)
    if args.domain != "time":
        from groundstation.commands.freq_support import identify_domain
        from groundstation.pipeline import load_logs

        return identify_domain(args, load_logs(args.logs, args.segments, pmap), cfg)
    prepared = prepare_logs(args.logs, cfg, args.segments, aircraft, pmap)
    con = Console(stderr=True, quiet=args.quiet)
    t0 = time.perf_counter()
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[info]}"),
                  TimeElapsedColumn(), console=con, transient=True) as prog:
        task = prog.add_task("identify", total=1.0, info="")

        def cb(info: dict) -> bool:
            frac = info["nit"] / max(info["maxiter"], 1)
            prog.update(task, completed=min(frac, 1.0), description=info["stage"],
                        info=f"F={info['fun']:.4g} evals={info['nfev']}")
            return False

        model = identify_prepared(prepared, cfg, callback=cb, aircraft=aircraft, pmap=pmap)
    model.fit["seconds"] = round(time.perf_counter() - t0, 3)
    if args.folds >= 2:
        held_out(model, prepared, cfg, aircraft, args.folds, con, pmap)
    model.source["logs"] = [str(p) for p in args.logs]
    write_json(args.out, model.to_json())
    if not args.no_plot or args.rrd is not None:
        from groundstation.sysid.validate import validate

        v = validate(model, prepared, return_series=True)
        if not args.no_plot:
            from groundstation.sysid.plots import plot_convergence, plot_fit

            plot_fit(v["series"], v["channels"], args.out.with_suffix(".png"),
                     title=f"{algorithm.upper()} model on its training data ({', '.join(p.name for p in args.logs)})")
            curves = {f"{algorithm} {sub}": [(np.asarray(model.fit["history_nfev"][sub], dtype=float),
                                                   np.asarray(h, dtype=float))]
                      for sub, h in model.fit["history"].items() if len(h) > 1}
            if curves:
                plot_convergence(curves, args.out.with_name(args.out.stem + "_convergence.png"),
                                 title="search convergence per subsystem: fitness 1/(1+F) vs evaluations")
        if args.rrd is not None:
            from groundstation.commands.validate import write_rrd

            write_rrd(v["series"], v["channels"], args.rrd, "groundstation-identify")
    if not args.quiet:
        print_model(model, con)
    return 0


def held_out(model, prepared, cfg, aircraft, k: int, con, pmap=None) -> None:
    """Cross-validate ``model`` (refinement from its parameters on k-1 blocks, prediction of the k-th)
    and record the verdicts in ``model.fit``: ``heldout`` (per channel and fold), ``usable`` (False
    when a subsystem's prediction runs away in some fold) and the closed-loop evidence."""
    from groundstation.sysid.heldout import crossvalidate
    from groundstation.sysid.identify import refit

    prior = aircraft.prior if aircraft is not None else None
    done = model.fit.get("heldout") or {}
    if done.get("k") != k:   # not already checked by the configuration's held-out selection
        con.print(f"held-out check: {k} contiguous folds ...")
        try:
            chosen = (model.fit.get("selection") or {}).get("overrides", {})
            icfg = dataclasses.replace(cfg.identify, **chosen)
            cv = crossvalidate(prepared, functools.partial(refit, model=model, config=icfg, prior=prior), k=k,
                               **({} if pmap is None else {"pmap": pmap}))
        except ValueError as exc:
            model.fit["heldout"] = {"skipped": str(exc)}
            return
        done = cv.to_json()
    model.fit["heldout"] = done
    model.fit["unusable_subsystems"] = list(done["unusable_subsystems"])
    model.fit["usable"] = not done["unusable_subsystems"]
    model.fit["closed_loop"] = closed_loop_notes(model, prepared, cfg)


def closed_loop_notes(model, prepared, cfg) -> list[str]:
    """What the closed loop means for this model: inputs that follow the output error, stick inputs."""
    from groundstation.sysid.heldout import feedback_evidence

    notes = feedback_evidence(model, prepared)
    if notes:
        notes.append("with the loop closed the inputs correlate with the disturbances the model does not see: "
                     "output error stays consistent only where the feedback acts on measured outputs; expect damping "
                     "and input gains biased towards what the controller makes of them, and judge the model by "
                     "the held-out match, not by its standard errors")
    if cfg.prepare.input_source == "RC_CHANNELS":
        notes.append("the inputs are the pilot's sticks (RC), commands to a stabilised aircraft: the model is that "
                     "of the aircraft with its stabiliser, not of the bare rotor (rotor terms such as M_a, L_b and "
                     "1/tau_s describe the closed loop)")
    return notes


def print_model(model, con=None) -> None:
    from rich.console import Console
    from rich.table import Table

    from groundstation.sysid.model import PARAM_NAMES

    con = con or Console()
    fit = model.fit
    con.print(f"[bold]{fit['algorithm'].upper()}[/]: cost F={fit['cost']:.4f} (search {fit['search_cost']:.4f}), "
              f"fitness {fit['fitness']:.4f}, {fit['evaluations']} evaluations, {fit['seconds']} s")
    t = Table(title="match degree (eq. 19) on the training windows, %")
    for ch in fit["match_degree"]:
        t.add_column(ch, justify="right")
    t.add_row(*[f"{v:.1f}" for v in fit["match_degree"].values()])
    con.print(t)
    p = Table(title="parameters")
    p.add_column("name")
    p.add_column("value", justify="right")
    p.add_column("std error", justify="right")
    p.add_column("note")
    for n in PARAM_NAMES:
        s = model.parameter_std.get(n)
        note = "fixed (not identifiable)" if n in fit.get("fixed", []) else ("PINNED at bound" if n in model.pinned else "")
        p.add_row(n, f"{model.params[n]:.4g}", "-" if s is None else f"{s:.3g}", note)
    con.print(p)
    from rich.markup import escape

    for r in fit.get("fixed_reasons", []) + fit.get("notes", []):
        con.print(f"note: {escape(r)}")
    print_verdicts(model, con)


def print_verdicts(model, con) -> None:
    """Held-out match, channels predicted or not, unusable subsystems, bounds, instability, prior."""
    fit = model.fit
    for name, why in fit.get("pinned_reasons", {}).items():
        con.print(f"[yellow]bound[/]: {name} {why}")
    for u in fit.get("unstable_modes", []):
        con.print(f"[yellow]unstable[/]: {u}")
    pr = fit.get("prior") or {}
    if pr.get("prior_dominated"):
        con.print(f"prior ({pr.get('source')}): not determined by this flight, kept near the prior with its "
                  f"uncertainty: {', '.join(pr['prior_dominated'])}")
    for line in selection_lines(fit.get("selection") or {}):
        con.print(line)
    ho = fit.get("heldout") or {}
    if "channel_mean" in ho:
        chans = ", ".join(f"{c} {v:.1f}" for c, v in ho["channel_mean"].items())
        con.print(f"held-out match over {ho['k']} contiguous folds ({ho['window_s']:g}-s windows from the measured "
                  f"states): mean {ho['mean_match']:.1f} % ({chans})")
        con.print(f"the model predicts: {', '.join(ho['predicted']) or 'no channel'}; "
                  f"it does not predict: {', '.join(ho['not_predicted']) or 'none'}")
        for sub in ho.get("unusable_subsystems", []):
            con.print(f"[red]unusable[/]: the {sub} subsystem's held-out prediction runs away "
                      f"({'; '.join(f'{f}: {chs}' for f, chs in ho['runaway'].items())}): not a model of the aircraft")
    for c in fit.get("closed_loop", []):
        con.print(f"closed loop: {c}")
    if fit.get("structure_choice"):
        ch = fit["structure_choice"]
        con.print(f"structure: {ch['chosen']} ({ch['reason']})", markup=False)
    for c in fit.get("command_response", []):
        con.print(f"stabilised aircraft: {c}", markup=False)


def selection_lines(sel: dict) -> list[str]:
    """What the held-out selection of the configuration compared and chose, one line per candidate."""
    if "skipped" in sel:
        return [f"configuration not compared by held-out prediction: {sel['skipped']}"]
    rows = sel.get("candidates") or []
    if len(rows) < 2:
        return []
    out = [f"configuration chosen by held-out prediction over {sel['k']} folds: {sel['chosen']} ({sel['rule']})"]
    for r in rows:
        gain = "" if "gain" not in r else f", gain {r['gain']:+.1f} +- {r['gain_se']:.1f} points per fold"
        if "gain_folds" in r:
            gain += f" (better on {r['gain_folds']} of {len(r['fold_score'])} folds)"
        why = f"; {r['reason']}" if r.get("reason") else ""
        ran = "" if not r.get("runaway") or r.get("reason") else "; runs away on " + ", ".join(r["runaway"])
        out.append(f"  {r['name']}: held-out mean {r['mean_match']:.1f} %{gain}{why}{ran}")
    return out
