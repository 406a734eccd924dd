"""``groundstation run``: the live service (link -> record -> smooth/window -> zenoh/Rerun -> identify).

With no ``--link`` it starts the built-in simulated flight controller on a pty and connects to it
through the ordinary ``serial://`` transport. Command-line options override the TOML config.
The service itself is :class:`groundstation.service.Service`; this module parses, runs, prints.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from typing import Any

from groundstation.config import ServiceConfig, load_config
from groundstation.service import Service


def add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE.toml", help="configuration TOML (see docs/configuration.md)")
    parser.add_argument("--record-dir", metavar="DIR", help="where recordings and results go")
    parser.add_argument("--zenoh", metavar="FILE.json5", help="zenoh session config (default: loopback peer)")
    parser.add_argument("--no-zenoh", action="store_true", help="do not publish on zenoh")
    parser.add_argument("--signing-key", metavar="FILE",
                        help="MAVLink 2 signing key file (chmod 600): sign outgoing, drop unsigned incoming")
    parser.add_argument("--rerun", nargs="+", metavar="MODE",
                        help="spawn | connect URL | save FILE.rrd | off")
    parser.add_argument("--vehicle", metavar="NAME", help="vehicle name (zenoh key chunk, Rerun root)")
    parser.add_argument("--speed", type=float, help="built-in simulator speed-up (default 1)")
    parser.add_argument("--flights", type=int, help="built-in simulator: number of flights")
    parser.add_argument("--seed", type=int, help="built-in simulator seed")
    parser.add_argument("--flight-s", type=float, metavar="S",
                        help="built-in simulator: armed time per flight (default: the test card's length)")
    parser.add_argument("--effect", action="append", default=None, metavar="NAME:K=V,...",
                        help="built-in simulator: unmodelled effect (repeatable)")
    parser.add_argument("--exit-after-flights", type=int, metavar="K",
                        help="stop after K flights (and their identification)")
    parser.add_argument("--scope", choices=("last", "all"), help="identify the last flight or all so far")
    parser.add_argument("--no-identify", action="store_true", help="do not identify between flights")
    parser.add_argument("--aircraft", metavar="FILE.toml",
                        help="aircraft file: channel map, measured outputs and prior model of the flights identified")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--link", metavar="URL",
                        help="serial:///dev/ttyUSB0:921600, udpin://0.0.0.0:14550, tcp://host:5760 ...")
    add_common(parser)


def config_from_args(args: argparse.Namespace, base: ServiceConfig | None = None) -> ServiceConfig:
    cfg = base if base is not None else load_config(args.config)
    if getattr(args, "link", None):
        cfg = cfg.replace("link", url=args.link)
    if args.record_dir:
        cfg = cfg.replace("service", record_dir=args.record_dir)
    if args.vehicle:
        cfg = cfg.replace("service", vehicle=args.vehicle)
    if args.exit_after_flights is not None:
        cfg = cfg.replace("service", exit_after_flights=args.exit_after_flights)
    if args.zenoh:
        cfg = cfg.replace("zenoh", config_file=args.zenoh, enabled=True)
    if args.no_zenoh:
        cfg = cfg.replace("zenoh", enabled=False)
    if getattr(args, "signing_key", None):
        cfg = cfg.replace("link", signing_key_file=args.signing_key)
    if args.rerun:
        mode, *rest = args.rerun
        if mode not in ("spawn", "connect", "save", "off") or len(rest) > 1:
            raise ValueError(f"--rerun {' '.join(args.rerun)}: expected spawn | connect [URL] | save FILE.rrd | off")
        if mode == "save" and not rest:
            raise ValueError("--rerun save: needs FILE.rrd")
        cfg = cfg.replace("rerun", mode=mode, target=rest[0] if rest else "")
    sim: dict[str, Any] = {}
    if args.speed is not None:
        sim["speed"] = args.speed
    if args.flights is not None:
        sim["flights"] = args.flights
    if args.seed is not None:
        sim["seed"] = args.seed
    if args.effect:
        sim["effects"] = tuple(args.effect)
    if sim:
        cfg = cfg.replace("sim", **sim)
    if args.scope:
        cfg = cfg.replace("identification", scope=args.scope)
    if args.no_identify:
        cfg = cfg.replace("identification", enabled=False)
    if getattr(args, "aircraft", None):
        cfg = cfg.replace("identification", aircraft=str(args.aircraft))
    return cfg


def print_report(report: Any, out=print) -> None:
    out("")
    out(f"stopped: {report.stopped_by or 'end'}; {report.flights} flight(s); packets {report.packets} "
        f"(lost {report.packets_lost}, bad CRC {report.bad_crc}); windows published {report.windows_published} "
        f"(dropped {report.windows_dropped})")
    out(f"recordings: {report.record_dir}")
    if report.session_tlog:
        out(f"  session  {report.session_tlog}")
    for p in report.flight_tlogs:
        out(f"  flight   {p}")
    for r in report.results:
        if r.error is not None:
            out(f"  flight {r.flight}: identification failed: {r.error}")
            continue
        out(f"  model    {r.model_path}")
        if r.gap_path:
            out(f"  gap      {r.gap_path} (verdict {(r.gap or {}).get('verdict')})")
        for png in r.png:
            out(f"  plot     {png}")
    if report.rrd:
        out(f"rerun: {report.rrd}")
    if report.zenoh_endpoint:
        out(f"zenoh: peer on {report.zenoh_endpoint}")
    rows = [r for r in report.results if r.error is None and r.match_degree]
    if rows:
        chans = list(rows[0].match_degree)
        out("")
        out("match degree (%)  " + " ".join(f"{c:>6}" for c in chans))
        for r in rows:
            md = r.match_degree
            out(f"flight {r.flight!s:<10} " + " ".join(
                f"{md[c]:6.1f}" if isinstance(md.get(c), int | float) else f"{'-':>6}" for c in chans))
    for w in report.warnings:
        out(f"warning: {w}")


def sim_options(args: argparse.Namespace) -> dict[str, Any] | None:
    if getattr(args, "flight_s", None) is None:
        return None
    if not args.flight_s > 0:
        raise ValueError(f"--flight-s {args.flight_s}: must be > 0")
    return {"flight_duration_s": args.flight_s}


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    service = Service(cfg, sim_options=sim_options(args))
    report = asyncio.run(service.run())
    print_report(report)
    sys.stdout.flush()
    return 0
