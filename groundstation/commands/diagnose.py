"""``groundstation diagnose LOG... [--model model.json] --out report.json [--plots DIR] [--seed N] [--config FILE.toml]``.

Reads and prepares the logs as ``groundstation identify`` does and diagnoses the gap through
:func:`groundstation.analysis.analyse` (``[prepare]`` of the configuration file and the aircraft
file), with the model file if given (else the diagnosis identifies one first); writes the gap-report
JSON, prints a summary table and optionally PNG plots and a Rerun .rrd recording of the residuals.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from groundstation.analysis import analyse, native_vibration, unfold_rotor_line  # noqa: F401 - their home is the analysis
from groundstation.config import load_config
from groundstation.gap.report import frequency_rows, summary_rows, through_flight_lines
from groundstation.jsonio import write_atomic
from groundstation.parallel import spare_core_jobs, worker_map
from groundstation.pipeline import about_logs
from groundstation.sysid.model import OUTPUTS


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
    parser.add_argument("--aircraft", type=Path, default=None,
                        help="aircraft TOML: input source and channel map, measured outputs (and the prior model "
                             "when the diagnosis identifies its base model)")
    parser.add_argument("--quiet", action="store_true", help="no terminal table")
    parser.add_argument("--jobs", type=int, default=None,
                        help="worker processes for reading the logs, the base model's identification and the "
                             "catalogue scans (default: all cores but one; the report is the same for any number)")


def run(args: argparse.Namespace) -> int:
    with about_logs(args.logs), worker_map(spare_core_jobs() if args.jobs is None else args.jobs) as pmap:
        return _run(args, pmap)


def _run(args: argparse.Namespace, pmap) -> int:
    cfg = load_config(args.config)
    if args.window_s is not None:
        cfg = cfg.replace("diagnose", window_s=args.window_s)
    if args.seed is not None:
        cfg = cfg.replace("identification", seed=args.seed)
    res = analyse(args.logs, args.aircraft, cfg, steps=("freq", "diagnose"), model=args.model,
                  segments=args.segments, pmap=pmap)
    assert res.gap is not None   # the diagnosis step ran (analyse raises where it cannot)
    report = res.gap.report

    write_atomic(args.out, report)
    if args.plots:
        from groundstation.gap.plots import write_all  # matplotlib only when plotting

        write_all(res.gap.arrays, report, args.plots)
    if args.rrd:
        write_rrd(res.gap.arrays, report, args.rrd)
    if not args.quiet:
        print_summary(report)
    return 0


def print_summary(report: dict) -> None:
    rows = summary_rows(report)
    con = Console(width=max(Console().width, 160))
    t = Table(title=f"gap per channel (held-out) — verdict: [bold]{report['verdict']}[/bold]")
    for col in ("channel", "match %", "Theil U", "gap / noise floor"):
        t.add_column(col)
    for r in rows["channels"]:
        t.add_row(*r)
    con.print(t)
    sh = report.get("shares") or {}
    if sh.get("headline"):
        con.print(f"[bold]{sh['headline']}[/bold]")
    t2 = Table(title="effects (ranked), partial findings and best rejected candidates")
    for col in ("effect", "channel", "named", "share of gap above noise", "score %", "gap before -> after",
                "shrink %", "through the flight", "evidence"):
        t2.add_column(col)
    for r in rows["effects"]:
        t2.add_row(*r)
    con.print(t2)

    for line in through_flight_lines(report):
        con.print(line)
    nat = report.get("vibration_native")
    if nat:
        lines = ", ".join(f"{ln['frequency_hz']:.2f} Hz ({'/'.join(ln['channels'])})" for ln in nat["lines"]) or "none"
        rot = f"; logged rotor speed {nat['rotor_speed_hz']:.2f} Hz" if nat.get("rotor_speed_hz") else ""
        con.print(f"vibration lines in {nat['source']}: {lines}{rot}")
    g = report["gap"]
    con.print(f"worst channels {g['worst_channels']}, band {g['band_hz']} Hz, condition: {g['conditions']}, "
              f"flagged windows {g['windows_s'][:6]}")
    if report.get("tested"):
        con.print(f"tested on this log: {', '.join(report['tested'])}")
    if report.get("untestable"):
        con.print(f"not testable on this log: {report['untestable']}")
    dc = report.get("data_compatibility") or {}
    for f in dc.get("findings", []):
        con.print(f"[bold]sensor error[/bold] ({f['kind']} on {f['channel']}): {f['evidence']}")
    ux = report.get("unexplained")
    if ux:
        con.print(f"[bold]unexplained[/bold]: channels above noise {ux['channels_above_noise']}, band {ux['band_hz']} Hz, "
                  f"condition {ux['condition']}")
        for line in ux["what_it_looks_like"]:
            con.print(f"  - {line}")
    print_frequency(report.get("frequency") or {}, con)


def print_frequency(fr: dict, con) -> None:
    if "error" in fr:
        con.print(f"frequency section: {fr['error']}")
        return
    ja = fr.get("J_avg")
    con.print(f"frequency: Tischler J_avg {'-' if ja is None else f'{ja:.1f}'} over {len(fr.get('pairs', []))} pairs "
              f"({'good' if fr.get('J_avg_good') else 'not good'}); "
              + ", ".join(f"{p['input']}->{p['output']} {p['J']:.0f}{'' if p['pass'] else ' FAIL'}"
                          for p in fr.get("pairs", [])))
    rows = frequency_rows(fr)
    if rows:
        t = Table(title="where in frequency the model leaves the flight's 95 % random-error bound (worst first)")
        for col in ("pair", "band", "model - data dB", "deg", "departure / bound"):
            t.add_column(col)
        for r in rows:
            t.add_row(*r)
        con.print(t)
    for u in fr.get("unmodelled", []):
        con.print(f"{u['input']}->{u['output']}: coherent in the flight ({u['coherent_points']} points), no path in the model")


def write_rrd(arrays: dict, report: dict, path: Path) -> None:
    """Residuals per channel on the fc_time timeline, saved as a Rerun recording."""
    import rerun as rr

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
    sh = report.get("shares") or {}
    rec.log("/gap/verdict", rr.TextDocument(json.dumps({"verdict": report["verdict"], "headline": sh.get("headline"),
                                                        "explained_pct": sh.get("explained_pct"),
                                                        "interval_pct": sh.get("interval_pct"),
                                                        "effects": report["effects"][:3],
                                                        "partial_findings": (report.get("partial_findings") or [])[:3],
                                                        "through_flight": report.get("through_flight")},
                                                       indent=1, default=str)), static=True)
    rec.flush()
