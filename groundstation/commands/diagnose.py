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
    parser.add_argument("--jobs", type=int, default=None,
                        help="worker processes for reading the logs, the base model's identification and the "
                             "catalogue scans (default: all cores but one; the report is the same for any number)")


def run(args: argparse.Namespace) -> int:
    from groundstation.parallel import worker_map
    from groundstation.pipeline import about_logs

    with about_logs(args.logs), worker_map(args.jobs) as pmap:
        return _run(args, pmap)


def _run(args: argparse.Namespace, pmap) -> int:
    from groundstation.commands.validate import load_model
    from groundstation.config import load_config
    from groundstation.dsp.prepare import prepare
    from groundstation.gap.diagnose import run_diagnosis
    from groundstation.pipeline import load_logs

    cfg = load_config(args.config)
    if args.window_s is not None:
        cfg = cfg.replace("diagnose", window_s=args.window_s)
    seed = cfg.identification.seed if args.seed is None else args.seed
    model = load_model(args.model) if args.model else None
    logs = load_logs(args.logs, args.segments, pmap)
    prepared = prepare(logs, cfg.prepare)
    diag = run_diagnosis(model, prepared, seed=seed, config=cfg.diagnose, pmap=pmap)
    report = diag.report
    native = native_vibration(logs, cfg.prepare.rate_hz)
    if native is not None:
        unfold_rotor_line(report, native, cfg.prepare.rate_hz)
    report["source"] = {"logs": [str(p) for p in args.logs], "model": str(args.model) if args.model else None}
    report["frequency"] = frequency_report(logs, cfg, model, report)
    from groundstation.jsonio import write_atomic

    write_atomic(args.out, report)
    if args.plots:
        from groundstation.gap.plots import write_all

        write_all(diag.arrays, report, args.plots)
    if args.rrd:
        write_rrd(diag.arrays, report, args.rrd)
    if not args.quiet:
        print_summary(report)
    return 0


def native_vibration(logs: list, grid_rate_hz: float) -> dict | None:
    """Vibration lines in the logs' own high-rate gyro (dataflash IMU/GYR faster than twice the grid),
    over the armed flights; None when no log has one. Adds the logged rotor speed when there is one."""
    import numpy as np

    from groundstation.gap.fingerprints import native_rate_lines

    for log in logs:
        for name in ("GYRO_FAST", "IMU"):
            s = log.series.get(name)
            if s is None or len(s) < 100:
                continue
            dt = float(np.median(np.diff(s.t_fc_s)))
            if not 0 < dt < 1.0 / (2.0 * grid_rate_hz):
                continue
            sel = np.zeros(len(s), bool)
            for fl in log.flights:
                sel |= (s.t_fc_s >= fl.start_fc_s) & (s.t_fc_s <= fl.end_fc_s)
            g = np.stack([s["gx_rad_s"], s["gy_rad_s"], s["gz_rad_s"]], axis=1)[sel]
            lines = native_rate_lines(g[np.isfinite(g).all(axis=1)], dt)
            rotor = log.series.get("ROTOR")
            rpm = None
            if rotor is not None and len(rotor):
                r = rotor["rotor_speed_rpm"][np.isfinite(rotor["rotor_speed_rpm"])]
                spinning = r[r > 0.8 * r.max()] if r.size and r.max() > 0 else r[:0]
                rpm = float(np.median(spinning)) if spinning.size else None
            return {"source": f"{name} at {1 / dt:.0f} Hz in {log.source}",
                    "lines": [{"frequency_hz": round(ln.frequency_hz, 3), "channels": ln.channels,
                               "log10_p": round(ln.log10_p, 1), "amplitude_rad_s": ln.amplitude} for ln in lines],
                    "rotor_speed_hz": None if rpm is None else round(rpm / 60.0, 3)}
    return None


def unfold_rotor_line(report: dict, native: dict, grid_rate_hz: float) -> None:
    """Put the native lines in the report; a rotor_vibration effect found on the grid gets the true
    frequency of the native line that folds onto its own (its grid frequency is kept beside it)."""
    report["vibration_native"] = native
    for eff in report.get("effects", []):
        if eff.get("effect") != "rotor_vibration":
            continue
        f_grid = float(eff["estimate"].get("frequency_hz", float("nan")))
        for ln in native["lines"]:
            f = ln["frequency_hz"] % grid_rate_hz
            if abs(min(f, grid_rate_hz - f) - f_grid) < 0.3:
                eff["estimate"]["frequency_hz_on_grid"] = f_grid
                eff["estimate"]["frequency_hz"] = ln["frequency_hz"]
                eff["evidence"] = (eff.get("evidence", "") + f"; at {ln['frequency_hz']:.2f} Hz in the "
                                   f"autopilot's own log ({native['source'].split(' in ')[0]})")
                break


def frequency_report(logs: list, cfg, model, report: dict) -> dict:
    """The gap report's frequency section: the base model checked against the flight's frequency
    responses (at the log's native rate), or ``{"error": ...}`` when the analysis cannot run."""
    from groundstation.commands.freq_support import prepare_native
    from groundstation.freq.model_response import delays_from_augmentations
    from groundstation.freq.spectra import estimate_responses
    from groundstation.freq.verify import verify
    from groundstation.gap.report import frequency_section
    from groundstation.sysid.model import theta_from_dict

    try:
        theta = theta_from_dict(report["method"]["base_parameters"])
        prepared = prepare_native(logs, cfg.prepare)
        v = verify(theta, estimate_responses(prepared, cfg.freq),
                   delays_from_augmentations(model.augmentations) if model is not None else None)
    except ValueError as exc:
        return {"error": str(exc)}
    return frequency_section(v)


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
    from groundstation.gap.report import through_flight_lines

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
    from rich.table import Table

    from groundstation.gap.report import frequency_rows

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
    sh = report.get("shares") or {}
    rec.log("/gap/verdict", rr.TextDocument(json.dumps({"verdict": report["verdict"], "headline": sh.get("headline"),
                                                        "explained_pct": sh.get("explained_pct"),
                                                        "interval_pct": sh.get("interval_pct"),
                                                        "effects": report["effects"][:3],
                                                        "partial_findings": (report.get("partial_findings") or [])[:3],
                                                        "through_flight": report.get("through_flight")},
                                                       indent=1, default=str)), static=True)
    rec.flush()
