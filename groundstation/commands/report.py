"""``groundstation report LOG... [--aircraft FILE] [--model M] [--gap G] [--campaign-db DB] --out flight.html``.

Runs what the page needs and was not given (identification with its held-out check unless ``--model``,
the frequency check, the diagnosis unless ``--gap``) through the same chain and configuration as
``identify`` and ``diagnose`` (:mod:`groundstation.report.collect`), and writes one self-contained HTML
page (:mod:`groundstation.report.render`; docs/report.md). A log the analysis cannot use still gets a
page: its data quality and one line per section that could not be made. ``--json-out`` also writes the
model and gap report the page was made from.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rich.console import Console

from groundstation.commands.identify import config_from_args
from groundstation.parallel import spare_core_jobs, worker_map
from groundstation.pipeline import about_logs
from groundstation.report import one_line_summary, render_report, write_html
from groundstation.report.collect import collect


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", type=Path, help=".tlog / .bin / .px4log / .ulg flight logs")
    parser.add_argument("--out", type=Path, required=True, help="HTML page to write")
    parser.add_argument("--aircraft", type=Path, default=None,
                        help="aircraft TOML: input source and channel map, measured outputs, prior model")
    parser.add_argument("--model", type=Path, default=None, help="heli-hover-model/1 JSON (default: identify)")
    parser.add_argument("--gap", type=Path, default=None, help="heli-gap-report/1 JSON (default: diagnose)")
    parser.add_argument("--campaign-db", type=Path, default=None,
                        help="campaign table (groundstation campaign --db): the aircraft's earlier flights and trends")
    parser.add_argument("--config", type=Path, default=None, help="configuration TOML (as for identify/diagnose)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: [identification] seed, 0)")
    parser.add_argument("--folds", type=int, default=5, help="held-out folds (default 5; 0 = skip)")
    parser.add_argument("--segments", choices=("flights", "sysid"), default="flights",
                        help="'flights' (every in-air interval, default) or 'sysid' (only the SYSID chirps)")
    parser.add_argument("--title", default=None, help="page title (default: the log names)")
    parser.add_argument("--jobs", type=int, default=None,
                        help="worker processes (default: all cores but one; the page is the same for any number)")
    parser.add_argument("--json-out", type=Path, default=None,
                        help="also write the model and gap report used: DIR/model.json, DIR/gap.json")
    parser.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    with about_logs(args.logs), worker_map(spare_core_jobs() if args.jobs is None else args.jobs) as pmap:
        return _run(args, pmap)


def _run(args: argparse.Namespace, pmap) -> int:
    con = Console(stderr=True, quiet=args.quiet)
    cfg = config_from_args(args)
    with con.status("report") as status:
        data = collect(args.logs, config=cfg, aircraft_path=args.aircraft, model_path=args.model, gap_path=args.gap,
                       folds=args.folds, history_db=args.campaign_db, title=args.title, segments=args.segments,
                       pmap=pmap, progress=lambda msg: status.update(msg))
        status.update("drawing the page")
        html = render_report(data)
    write_html(args.out, html)
    if args.json_out is not None:
        args.json_out.mkdir(parents=True, exist_ok=True)
        if data.model is not None:
            (args.json_out / "model.json").write_text(json.dumps(data.model.to_json(), indent=1, default=float))
        if data.gap is not None:
            (args.json_out / "gap.json").write_text(json.dumps(data.gap, indent=1, default=float))
    con.print(f"wrote {args.out} ({len(html.encode()) / 1e6:.2f} MB): {one_line_summary(data)}")
    for part, why in data.errors.items():
        con.print(f"[yellow]not made[/] {part}: {why}")
    return 0
