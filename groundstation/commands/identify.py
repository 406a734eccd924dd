"""``groundstation identify LOG... --out model.json [--algorithm cabc|abc|ga|de] [--seed N] [--no-refine] [--config FILE.toml]``.

Reads and prepares the logs, identifies the hover model and checks it on held-out data through
:func:`groundstation.analysis.analyse` (the same chain the service's worker runs) with a rich progress bar, writes the model file
(docs/model-file.md; atomically) and a PNG of measured vs model next to it (``model.png``), and prints
a summary. Options override the configuration file (``[prepare]``, ``[identify]``, ``[bounds]``,
``[identification]``; see docs/configuration.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from groundstation.analysis import analyse
from groundstation.analysis import held_out as _held_out
from groundstation.commands.freq_support import add_freq_arguments, identify_domain
from groundstation.commands.model_summary import (  # noqa: F401 - importable from here as before
    print_model,
    print_verdicts,
    selection_lines,
    write_json,
)
from groundstation.commands.validate import write_rrd
from groundstation.config import load_config
from groundstation.parallel import IDENTIFY_NO_PLOT_PRELOAD, IDENTIFY_PRELOAD, spare_core_jobs, worker_map
from groundstation.pipeline import about_logs, load_aircraft, load_logs, with_aircraft
from groundstation.sysid.plots import draw


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
    parser.add_argument("--folds", type=int, default=None,
                        help="held-out check: refit on k-1 contiguous blocks of the in-air time and predict the "
                             "left-out one, for each block (default: [identification] heldout_folds, 5; 0 = skip)")
    parser.add_argument("--no-plot", action="store_true", help="do not write the PNG")
    parser.add_argument("--rrd", type=Path, default=None, help="also write measured vs model to a Rerun .rrd file")
    parser.add_argument("--segments", choices=("flights", "sysid"), default="flights", help=SEGMENTS_HELP)
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--jobs", type=int, default=None,
                        help="processes for reading the logs, the searches' screening refinements, the held-out "
                             "folds and the figures: this command's own (which searches meanwhile) and N-1 workers "
                             "(default: all cores but one, as for diagnose: one stays free for the link; the model is the same "
                             "for any number)")
    parser.add_argument("--domain", choices=("time", "frequency", "both"), default="time",
                        help="time: the paper's output-error fit (default); frequency: minimise Tischler's J over the "
                             "flight's frequency responses; both: the time fit, then the frequency cost as a "
                             "refinement started from it; each scored both ways")
    parser.add_argument("--fit-delays", action="store_true", help="frequency domain: also fit one delay per input")
    parser.add_argument("--freq-weighting", choices=("output_error", "coherence", "random_error"), default=None,
                        help="frequency-domain cost: output_error = the Fourier transforms of 3-s windows of the "
                             "flight against the model's, from the J fit (default: [freq_identify] weighting); coherence = Tischler's J only; "
                             "random_error = each coherent point weighted by its random error")

    add_freq_arguments(parser)


def config_from_args(args: argparse.Namespace):
    """The configuration file (``--config``) with this command's options applied."""
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
    if getattr(args, "folds", None) is not None:
        if args.folds == 1 or args.folds < 0:
            raise ValueError(f"--folds: {args.folds} must be 0 (skip) or >= 2")
        cfg = cfg.replace("identification", heldout_folds=args.folds)
    return cfg


SEGMENTS_HELP = ("which data to use: 'flights' (every in-air interval, default) or 'sysid' (only the "
                 "system-identification chirps of ArduPilot SYSID-mode dataflash logs)")


def run(args: argparse.Namespace) -> int:
    preload = IDENTIFY_NO_PLOT_PRELOAD if args.no_plot else IDENTIFY_PRELOAD
    with about_logs(args.logs), worker_map(spare_core_jobs() if args.jobs is None else args.jobs, preload, fork_here=True,
                                                 caller_works=True) as pmap:
        return _run(args, pmap)


def _run(args: argparse.Namespace, pmap) -> int:
    cfg = config_from_args(args)
    algorithm = cfg.identification.algorithm
    aircraft = load_aircraft(args.aircraft)
    if args.domain != "time":
        return identify_domain(args, load_logs(args.logs, args.segments, pmap), with_aircraft(cfg, aircraft))
    con = Console(stderr=True, quiet=args.quiet)
    want_series = not args.no_plot or args.rrd is not None
    steps = ("identify", "heldout") + (("validate",) if want_series else ())
    if args.quiet:   # no progress bar to draw (its refresh thread and updates cost CPU even when silent)
        res = analyse(args.logs, aircraft, cfg, steps=steps, segments=args.segments, pmap=pmap)
    else:
        res = _analyse_with_progress(args, aircraft, cfg, steps, con, pmap)
    model = res.model
    write_json(args.out, model.to_json())
    if want_series:
        assert res.validation is not None and res.validation_series is not None   # the validate step ran
        series, channels = res.validation_series, res.validation.to_json()["channels"]
        if not args.no_plot:
            title = f"{algorithm.upper()} model on its training data ({', '.join(p.name for p in args.logs)})"
            figures: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = [
                ("plot_fit", (series, channels, args.out.with_suffix(".png")), {"title": title})]
            curves = {f"{algorithm} {sub}": [(np.asarray(model.fit.history_nfev[sub], dtype=float),
                                                   np.asarray(h, dtype=float))]
                      for sub, h in model.fit.history.items() if len(h) > 1}
            if curves:
                figures.append(("plot_convergence", (curves, args.out.with_name(args.out.stem + "_convergence.png")),
                                {"title": "search convergence per subsystem: fitness 1/(1+F) vs evaluations"}))
            pmap(draw, figures)   # side by side: on a worker and in this process (both imported matplotlib)
        if args.rrd is not None:
            write_rrd(series, channels, args.rrd, "groundstation-identify")
    if not args.quiet:
        print_model(model, con)
    return 0


def _analyse_with_progress(args: argparse.Namespace, aircraft, cfg, steps: tuple[str, ...], con: Console, pmap):
    """:func:`groundstation.analysis.analyse` with a rich progress bar on ``con``."""
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[info]}"),
                  TimeElapsedColumn(), console=con, transient=True) as prog:
        task = prog.add_task("identify", total=1.0, info="")

        def on(ev) -> None:
            if ev.step == "identify" and ev.state == "running":
                info = ev.info
                frac = info["nit"] / max(info["maxiter"], 1)
                prog.update(task, completed=min(frac, 1.0), description=info["stage"],
                            info=f"F={info['fun']:.4g} evals={info['nfev']}")
            elif ev.step == "heldout" and ev.state == "start":
                con.print(f"held-out check: {cfg.identification.heldout_folds} contiguous folds ...")

        return analyse(args.logs, aircraft, cfg, steps=steps, segments=args.segments, progress=on, pmap=pmap)


def held_out(model, prepared, cfg, aircraft, k: int, con=None, pmap=None) -> None:
    """The held-out check (:func:`groundstation.analysis.held_out`; ``con`` is not used any more)."""
    _held_out(model, prepared, cfg, aircraft, k, pmap)
