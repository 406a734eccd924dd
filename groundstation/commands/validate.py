"""``groundstation validate model.json LOG... [--json] [--plot PNG] [--window-s S]``.

Scores a model file on flight logs (validation segments or another flight): per-channel match
degree (eq. 19), NRMSE fit, Theil inequality coefficient and Pearson correlation, as a table or
JSON on stdout.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = "score a hover model file on flight logs (match degree, NRMSE fit, Theil U, correlation per channel)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", type=Path, help="heli-hover-model/1 JSON")
    parser.add_argument("logs", nargs="+", type=Path, help=".tlog / .bin / .px4log / .ulg flight logs")
    parser.add_argument("--segments", choices=("flights", "sysid"), default="flights",
                        help="'flights' (every in-air interval, default) or 'sysid' (only the SYSID chirps)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--plot", type=Path, default=None, help="write measured vs model PNG here")
    parser.add_argument("--window-s", type=float, default=None, help="window length (default: the model's)")
    parser.add_argument("--config", type=Path, default=None, help="TOML with a [prepare] table")
    parser.add_argument("--rrd", type=Path, default=None, help="write measured vs model to a Rerun .rrd file")


def load_model(path: Path):
    from groundstation.sysid.model import HoverModel

    if not path.exists():
        raise OSError(f"{path}: no such model file")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    try:
        return HoverModel.from_json(doc)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def run(args: argparse.Namespace) -> int:
    from groundstation.commands.identify import load_configs, load_logs
    from groundstation.dsp.prepare import prepare
    from groundstation.sysid.validate import validate

    model = load_model(args.model)
    prep_cfg, _, _ = load_configs(args.config)
    prepared = prepare(load_logs(args.logs, args.segments), prep_cfg)
    want_series = args.plot is not None or args.rrd is not None
    res = validate(model, prepared, window_s=args.window_s, return_series=want_series)
    series = res.pop("series", None)
    res["model"] = str(args.model)
    res["logs"] = [str(p) for p in args.logs]
    res["notes"] = list(prepared.notes)
    if args.plot is not None and series is not None:
        from groundstation.sysid.plots import plot_fit

        plot_fit(series, res["channels"], args.plot, title=f"{args.model.name} on {', '.join(p.name for p in args.logs)}")
    if args.rrd is not None and series is not None:
        write_rrd(series, res["channels"], args.rrd, "groundstation-validate")
    if args.json:
        print(json.dumps(res, indent=1, allow_nan=False))
        return 0
    from rich.console import Console
    from rich.table import Table

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


def write_rrd(series: dict, channels: dict, path: Path, app: str) -> None:
    """Measured and model outputs per channel on the ``fc_time`` timeline, saved as a Rerun recording."""
    import numpy as np
    import rerun as rr

    from groundstation.sysid.model import OUTPUTS

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
