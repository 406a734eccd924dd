"""``groundstation campaign DIR_OR_LOG... --db campaign.sqlite [--parquet DIR] [--jobs N] [--scheduler local|tcp://host:8786]``.

Finds every log (.tlog, .bin, .ulg, .px4log) under the given directories, skips those already in
the table with the same content hash and settings, identifies and diagnoses the others - one task
per log on a local process pool (``--jobs``, default every core) or on a Dask cluster
(``--scheduler``) - stores one row per flight in the aircraft's table, then runs the trend test over
all of the aircraft's flights and writes ``trends.json``, ``trends.png`` and ``trends.rrd`` next to
the table (or where ``--trends-dir`` says).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from groundstation.campaign import runner
from groundstation.campaign.job import FlightJob, Settings, file_sha256, find_logs, log_date_utc, page_name
from groundstation.campaign.plots import load_plotting, plot_trends, write_trends_rrd
from groundstation.campaign.store import CampaignStore, series
from groundstation.commands.identify import config_from_args
from groundstation.pipeline import load_aircraft
from groundstation.report import render_campaign, write_html
from groundstation.trends.change import TrendConfig, assess_all, campaign_summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("paths", nargs="+", type=Path, help="directories (searched recursively) or log files")
    parser.add_argument("--db", type=Path, default=Path("campaign.sqlite"), help="SQLite file of the table(s)")
    parser.add_argument("--parquet", type=Path, default=None, help="also write DIR/<aircraft>.parquet")
    parser.add_argument("--aircraft", type=Path, default=None,
                        help="aircraft TOML: channel map, measured outputs, prior model; its name keys the table")
    parser.add_argument("--vehicle", default=None, help="aircraft name for the table (default: from --aircraft)")
    parser.add_argument("--config", type=Path, default=None,
                        help="configuration TOML ([prepare], [identify], [bounds], [identification], [diagnose])")
    parser.add_argument("--jobs", type=int, default=None, help="worker processes (default: every core)")
    parser.add_argument("--scheduler", default=None,
                        help="run on Dask distributed: tcp://host:8786, or 'local' for a LocalCluster on loopback")
    parser.add_argument("--algorithm", choices=("cabc", "abc", "ga", "de"), default=None,
                        help="search algorithm (default: [identification] algorithm, cabc)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: [identification] seed, 0)")
    parser.add_argument("--maxiter", type=int, default=None, help="search iterations per subsystem")
    parser.add_argument("--restarts", type=int, default=None, help="independent searches per subsystem")
    parser.add_argument("--no-diagnose", action="store_true", help="identify only (no gap verdicts or effects)")
    parser.add_argument("--no-cross", action="store_true", help="do not score each model on the previous flight")
    parser.add_argument("--trends-dir", type=Path, default=None, help="where trends.json/png/rrd go (default: --db's dir)")
    parser.add_argument("--report-dir", type=Path, default=None,
                        help="write an HTML page per analysed flight and DIR/campaign.html (table, trends, links)")
    parser.add_argument("--alpha", type=float, default=None,
                        help="family-wise false-alarm level of the trend test (default: [trends] alpha, 0.05)")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True, help="progress bar")
    parser.add_argument("--quiet", action="store_true")


def _aircraft(args: argparse.Namespace) -> tuple[str, str, Any]:
    """(name, file text, loaded aircraft file or None)."""
    if args.aircraft is None:
        return args.vehicle or "aircraft", "", None

    aircraft = load_aircraft(args.aircraft)
    name = args.vehicle or (aircraft.name if aircraft.name != "aircraft" else args.aircraft.stem)
    return str(name), args.aircraft.read_text(), aircraft


def build_jobs(args: argparse.Namespace, store: Any) -> tuple[list, list[Path], Any]:
    """(jobs to run, logs skipped as done, settings)."""
    name, text, aircraft = _aircraft(args)
    s = Settings(config=config_from_args(args), diagnose=not args.no_diagnose, aircraft_text=text, aircraft=aircraft)
    logs = find_logs(args.paths)
    if not logs:
        raise ValueError(f"no .tlog/.bin/.ulg/.px4log file in {', '.join(map(str, args.paths))}")
    logs.sort(key=lambda p: (log_date_utc(p)[0], p.name))
    jobs, skipped = [], []
    key = s.key()
    for k, p in enumerate(logs):
        h = file_sha256(p)
        if store.done(name, h, key):
            skipped.append(p)
            continue
        ref = None if args.no_cross or k == 0 else str(logs[k - 1])
        jobs.append(FlightJob(str(p), h, name, s, ref,
                              str(args.report_dir) if getattr(args, "report_dir", None) is not None else None))
    return jobs, skipped, s


def run(args: argparse.Namespace) -> int:
    con = Console(stderr=True, quiet=args.quiet)
    workers = args.jobs if args.jobs is not None else runner.default_workers()
    if workers < 1:
        raise ValueError(f"--jobs: {workers} must be >= 1")
    store = CampaignStore(args.db)
    try:
        jobs, skipped, settings = build_jobs(args, store)
        name = jobs[0].aircraft if jobs else _aircraft(args)[0]
        con.print(f"{len(jobs) + len(skipped)} log(s): {len(skipped)} already done, {len(jobs)} to analyse on "
                  f"{'Dask ' + args.scheduler if args.scheduler else f'{workers} process(es)'}"
                  f"{'' if args.scheduler or args.jobs is not None else f' (every core of {os.cpu_count()}; --jobs to change)'}")
        t0 = time.perf_counter()
        # the workers first: forked from this process before the progress bar's thread starts
        with runner.open_for(jobs, workers, args.scheduler) as ex, \
                Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                         TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=con, transient=True,
                         disable=not args.progress) as prog:
            task = prog.add_task("campaign", total=len(jobs), info="")

            def on_result(job, rows) -> None:
                store.put(rows)
                last = rows[-1]
                info = last["error"] or f"verdict {last.get('verdict')}, held-out {_fmt(last.get('heldout_match_pct'))} %"
                prog.update(task, advance=1, info=f"{last['log_name']}: {info}"[:80])

            # the trends' plotting libraries are imported on the core the first worker without a flight
            # left leaves idle, not after the run nor on a core the workers need
            runner.run(jobs, on_result=on_result, executor=ex, meanwhile=load_plotting)
        wall = time.perf_counter() - t0
        for e in store.errors(name):
            con.print(f"[red]error[/]: {e['error']}")
        if args.parquet is not None:
            out = store.write_parquet(name, args.parquet / f"{name}.parquet")
            con.print(f"wrote {out}")
        summary = write_trends(store, name, settings.key(), args, settings.service_config().trends)
        if args.report_dir is not None:
            page = write_campaign_page(store, name, settings.key(), summary, args.report_dir)
            con.print(f"wrote {page}")
        if not args.quiet:
            _print(store.rows(name, settings.key()), summary, con)
        con.print(f"{len(jobs)} log(s) analysed in {wall:.1f} s; table {args.db} ({name})")
    finally:
        store.close()
    return 0


def _fmt(v: Any) -> str:
    return "-" if v is None else f"{float(v):.1f}"


def write_trends(store: Any, aircraft: str, settings_key: str, args: argparse.Namespace, trend_cfg: Any = None) -> dict:
    """Trend test over the aircraft's flights (``[trends]`` of the configuration, ``--alpha`` over it);
    trends.json / .png / .rrd; returns the summary."""
    rows = store.rows(aircraft, settings_key)
    out_dir = args.trends_dir or args.db.parent
    labels = [f"{r['log_name']}#{int(r['flight_index'])}" for r in rows]
    tc = trend_cfg if trend_cfg is not None else TrendConfig()
    if args.alpha is not None:
        tc = dataclasses.replace(tc, alpha=args.alpha)
    trends = assess_all(series(rows), tc)
    summary = campaign_summary(aircraft, labels, trends)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "trends.json").write_text(json.dumps(summary, indent=1, allow_nan=False))
    if len(rows) >= 2:
        plot_trends(trends, labels, out_dir / "trends.png", title=f"{aircraft}: trends over {len(rows)} flights")
        write_trends_rrd(trends, labels, out_dir / "trends.rrd")
    return summary


def write_campaign_page(store: Any, aircraft: str, settings_key: str, summary: dict, report_dir: Path) -> Path:
    """``report_dir/campaign.html``: the aircraft's flights (every row, errors included) linked to the flight
    pages that exist in ``report_dir``, the trend test's changes and figure."""
    rows = store.rows(aircraft, settings_key) + [{**e, "flight_index": 0} for e in store.errors(aircraft)]
    links = {}
    for r in rows:
        name = page_name(r["log_name"], int(r.get("flight_index") or 0))
        if (report_dir / name).exists():
            links[f"{r['log_name']}#{int(r.get('flight_index') or 0)}"] = name
    return write_html(report_dir / "campaign.html", render_campaign(aircraft, rows, summary, links))


def _print(rows: list[dict], summary: dict, con: Any) -> None:
    t = Table(title=f"{summary['aircraft']}: {len(rows)} flight(s)")
    for c in ("flight", "date (UTC)", "in air s", "held-out %", "cross %", "verdict", "s"):
        t.add_column(c)
    for r in rows:
        t.add_row(f"{r['log_name']}#{int(r['flight_index'])}", r["date_utc"], _fmt(r.get("in_air_s")),
                  _fmt(r.get("heldout_match_pct")), _fmt(r.get("cross_match_pct")), str(r.get("verdict")),
                  _fmt(r.get("seconds")))
    con.print(t)
    if summary["changed"]:
        for c in summary["changed"]:
            con.print(f"[bold]changed[/]: {c['name']} ({c['kind']}, {'up' if c['direction'] > 0 else 'down'}) "
                      f"at {summary['flights'][c['changed_at']]}: {c['first']:.4g} -> {c['latest']:.4g}")
    else:
        con.print("no parameter or effect moved beyond its uncertainty")
