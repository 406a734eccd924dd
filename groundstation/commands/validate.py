"""``groundstation validate model.json LOG... [--json] [--plot PNG] [--window-s S] [--config FILE.toml] [--freq [--bode PNG] [--rerun save RRD]]``.

Scores a model file on flight logs (validation segments or another flight): per-channel match
degree (eq. 19), NRMSE fit, Theil inequality coefficient and Pearson correlation, as a table or
JSON on stdout. With ``--freq``: the frequency-domain check instead (flight-data frequency
responses with coherence and random error, Tischler's J per input-output pair with pass/fail,
phase-slope delay, ADS-33 bandwidth; :mod:`groundstation.freq`), Bode plots to PNG and Rerun.
The logs are prepared as ``groundstation identify`` prepares them (``[prepare]`` of the
configuration file).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from groundstation.commands.freq_support import (
    add_freq_arguments,
    load_freq_config,
    print_verification,
    verification_json,
    write_rerun,
)
from groundstation.config import load_config
from groundstation.freq.model_response import delays_from_augmentations
from groundstation.freq.spectra import estimate_responses
from groundstation.freq.verify import verify
from groundstation.jsonio import dumps
from groundstation.pipeline import (
    about_logs,
    load_aircraft,
    load_logs,
    prepare_logs,
    prepare_native,
    with_aircraft,
)
from groundstation.pipeline import load_model as _load
from groundstation.sinks.bode import plot_bode
from groundstation.sysid.model import OUTPUTS
from groundstation.sysid.plots import plot_fit
from groundstation.sysid.validate import validate


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", type=Path, help="heli-hover-model/1 JSON")
    parser.add_argument("logs", nargs="+", type=Path, help=".tlog / .bin / .px4log / .ulg flight logs")
    parser.add_argument("--segments", choices=("flights", "sysid"), default="flights",
                        help="'flights' (every in-air interval, default) or 'sysid' (only the SYSID chirps)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--plot", type=Path, default=None, help="write measured vs model PNG here")
    parser.add_argument("--window-s", type=float, default=None, help="window length (default: the model's)")
    parser.add_argument("--config", type=Path, default=None, help="configuration TOML (its [prepare] channel map and trims are used)")
    parser.add_argument("--rrd", type=Path, default=None, help="write measured vs model to a Rerun .rrd file")
    parser.add_argument("--aircraft", type=Path, default=None, help="aircraft TOML (input source, channel map, outputs)")
    parser.add_argument("--freq", action="store_true",
                        help="frequency-domain check: J per input-output pair (JSON with --json: J_avg and pairs)")
    parser.add_argument("--bode", type=Path, default=None, help="with --freq: Bode PNGs, one per input (PATH_<input>.png)")
    parser.add_argument("--rerun", nargs="+", metavar="MODE", default=None,
                        help="with --freq: 'save FILE.rrd' writes the Bode data to a Rerun recording")

    add_freq_arguments(parser)


def load_model(path: Path):
    """The model file as a HoverModel (:func:`groundstation.pipeline.load_model`)."""
    return _load(path)


def run(args: argparse.Namespace) -> int:
    with about_logs(args.logs):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    aircraft = load_aircraft(args.aircraft)
    cfg = with_aircraft(load_config(args.config), aircraft)
    model = load_model(args.model)
    if args.freq:
        return run_freq(args, model, cfg)
    if args.bode is not None or args.rerun is not None:
        raise ValueError("--bode and --rerun need --freq")
    prepared = prepare_logs(args.logs, cfg, args.segments)
    want_series = args.plot is not None or args.rrd is not None
    v = validate(model, prepared, window_s=args.window_s, return_series=want_series)
    series, res = (None if v.series is None else dict(v.series)), v.to_json()
    res["model"] = str(args.model)
    res["logs"] = [str(p) for p in args.logs]
    res["notes"] = list(prepared.notes)
    res["link_quality"] = dict(prepared.link_quality)
    if args.plot is not None and series is not None:
        plot_fit(series, res["channels"], args.plot, title=f"{args.model.name} on {', '.join(p.name for p in args.logs)}")
    if args.rrd is not None and series is not None:
        write_rrd(series, res["channels"], args.rrd, "groundstation-validate")
    if args.json:
        print(dumps(res, indent=1))
        return 0

    t = Table(title=f"{args.model.name} on {', '.join(p.name for p in args.logs)} "
                    f"({res['windows']} windows of {res['window_s']:g} s)")
    for c in ("channel", "match %", "fit %", "Theil U", "corr"):
        t.add_column(c, justify="right")
    for ch, m in res["channels"].items():
        t.add_row(ch, f"{m['match']:.1f}", f"{m['fit']:.1f}", f"{m['tic']:.3f}", f"{m['corr']:.2f}")
    t.add_row("mean", f"{res['mean_match']:.1f}", f"{res['mean_fit']:.1f}", "")
    con = Console()
    con.print(t)
    for n in prepared.notes:
        con.print(f"note: {n}")
    return 0


def run_freq(args: argparse.Namespace, model, cfg) -> int:
    """``validate --freq``: the J table (or one JSON object), Bode PNGs and Rerun recording."""
    fcfg = load_freq_config(args.freq_config, cfg)
    prepared = prepare_native(load_logs(args.logs, args.segments), cfg.prepare, grid_only=args.grid_rate)
    v = verify(model.theta, estimate_responses(prepared, fcfg), delays_from_augmentations(model.augmentations))
    names = ", ".join(p.name for p in args.logs)
    if args.bode is not None:
        plot_bode(v, args.bode, title=f"{args.model.name} on {names}")
    if args.rerun is not None:
        write_rerun(v, args.rerun, "groundstation-validate-freq")
    if args.json:
        print(verification_json(v, model=str(args.model), logs=[str(p) for p in args.logs],
                                prepare_notes=list(prepared.notes)))
        return 0

    con = Console()
    print_verification(v, f"Tischler's J of {args.model.name} on {names} "
                          f"({1 / prepared.dt_s:.0f} Hz, windows {', '.join(f'{w:g}' for w in v.responses.windows_s)} s)",
                       con)
    for n in prepared.notes:
        con.print(f"note: {n}")
    return 0


def write_rrd(series: dict, channels: dict, path: Path, app: str) -> None:
    """Measured and model outputs per channel on the ``fc_time`` timeline, saved as a Rerun recording."""
    import rerun as rr

    path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(app)
    rec.save(str(path))
    t = series["t_s"].ravel()
    order = np.argsort(t)
    for c, name in enumerate(OUTPUTS):
        if name not in channels:
            continue
        for kind, data in (("measured", series["y"][..., c]), ("model", series["yhat"][..., c])):
            rec.send_columns(f"/sysid/outputs/{name}/{kind}", indexes=[rr.TimeColumn("fc_time", duration=t[order])],
                             columns=rr.Scalars.columns(scalars=data.ravel()[order]))
    rec.log("/sysid/match", rr.TextDocument(json.dumps({k: v["match"] for k, v in channels.items()}, indent=1)),
            static=True)
    rec.flush()
