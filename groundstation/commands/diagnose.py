"""``groundstation diagnose LOG... [--model model.json] --out report.json [--plots DIR] [--seed N] [--config FILE.toml]``.

Reads and prepares the logs as ``groundstation identify`` does (:mod:`groundstation.pipeline`,
``[prepare]`` of the configuration file), loads the model file if given (else the diagnosis
identifies one first), runs
:func:`groundstation.gap.diagnose.run_diagnosis`, writes the gap-report JSON, prints a summary
table and optionally PNG plots and a Rerun .rrd recording of the residuals.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = "diagnose where and why the hover model departs from flight data (gap report JSON)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", type=Path, help=".tlog / .bin / .px4log / .ulg flight logs")
    parser.add_argument("--segments", choices=("flights", "sysid"), default="flights",
                        help="'flights' (every in-air interval, default) or 'sysid' (only the SYSID chirps)")
    parser.add_argument("--model", type=Path, default=None, help="heli-hover-model/1 JSON (default: identify first)")
    parser.add_argument("--out", type=Path, required=True, help="gap report JSON to write")
    parser.add_argument("--plots", type=Path, default=None, help="directory for PNG plots")
    parser.add_argument("--rrd", type=Path, default=None, help="write the residuals to a Rerun .rrd file")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: [identification] seed, 0)")
    parser.add_argument("--window-s", type=float, default=None,
                        help="scoring window length (s) (default: [diagnose] window_s, 3)")
    parser.add_argument("--config", type=Path, default=None,
                        help="configuration TOML ([prepare] channel map and trims, [diagnose], ...)")
    parser.add_argument("--quiet", action="store_true", help="no terminal table")


def run(args: argparse.Namespace) -> int:
    from groundstation.commands.validate import load_model
    from groundstation.config import load_config
    from groundstation.gap.diagnose import run_diagnosis
    from groundstation.pipeline import prepare_logs

    cfg = load_config(args.config)
    if args.window_s is not None:
        cfg = cfg.replace("diagnose", window_s=args.window_s)
    seed = cfg.identification.seed if args.seed is None else args.seed
    model = load_model(args.model) if args.model else None
    prepared = prepare_logs(args.logs, cfg, args.segments)
    diag = run_diagnosis(model, prepared, seed=seed, config=cfg.diagnose)
    report = diag.report
    report["source"] = {"logs": [str(p) for p in args.logs], "model": str(args.model) if args.model else None}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(args.out.suffix + ".tmp")
    tmp.write_text(json.dumps(report, indent=1, allow_nan=False))
    tmp.replace(args.out)
    if args.plots:
        from groundstation.gap.plots import write_all

        write_all(diag.arrays, report, args.plots)
    if args.rrd:
        write_rrd(diag.arrays, report, args.rrd)
    if not args.quiet:
        print_summary(report)
    return 0


def print_summary(report: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    from groundstation.gap.report import summary_rows

    rows = summary_rows(report)
    con = Console(width=max(Console().width, 160))
    t = Table(title=f"gap per channel (held-out) — verdict: [bold]{report['verdict']}[/bold]")
    for col in ("channel", "match %", "Theil U", "gap / noise floor"):
        t.add_column(col)
    for r in rows["channels"]:
        t.add_row(*r)
    con.print(t)
    t2 = Table(title="effects (ranked) and best rejected candidates")
    for col in ("effect", "channel", "significant", "score %", "gap before -> after", "shrink %", "evidence"):
        t2.add_column(col)
    for r in rows["effects"]:
        t2.add_row(*r)
    con.print(t2)
    g = report["gap"]
    con.print(f"worst channels {g['worst_channels']}, band {g['band_hz']} Hz, condition: {g['conditions']}, "
              f"flagged windows {g['windows_s'][:6]}")
    if report.get("untestable"):
        con.print(f"untestable: {report['untestable']}")


def write_rrd(arrays: dict, report: dict, path: Path) -> None:
    """Residuals per channel on the fc_time timeline, saved as a Rerun recording."""
    import numpy as np
    import rerun as rr

    from groundstation.sysid.model import OUTPUTS

    rec = rr.RecordingStream("groundstation-diagnose")
    rec.save(str(path))
    T, Y, yh, mask = arrays["t_s"], arrays["Y"], arrays["yhat"], arrays["mask"]
    t = T[:, mask].ravel()
    order = np.argsort(t)
    for c, name in enumerate(OUTPUTS):
        if name not in report["gap"]["channels"]:
            continue
        for kind, data in (("measured", Y[:, mask, c]), ("model", yh[:, mask, c]),
                           ("residual", Y[:, mask, c] - yh[:, mask, c])):
            rec.send_columns(f"/gap/{name}/{kind}", indexes=[rr.TimeColumn("fc_time", duration=t[order])],
                             columns=rr.Scalars.columns(scalars=data.ravel()[order]))
    rec.log("/gap/verdict", rr.TextDocument(json.dumps({"verdict": report["verdict"],
                                                        "effects": report["effects"][:3]}, indent=1)), static=True)
    rec.flush()
