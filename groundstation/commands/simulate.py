"""``groundstation simulate``: write a simulated flight .tlog or onboard .bin (+ truth sidecar), or serve a simulated FC.

``--out FILE.tlog`` flies :class:`hil_replay.sim.SimulatedSession` and writes ``FILE.tlog`` and
``FILE.truth.json`` (via :func:`hil_replay.sim.write_tlog`), then prints what it wrote; ``--out
FILE.bin`` (or ``--bin``) writes the autopilot's onboard dataflash log instead
(:func:`hil_replay.dataflash.write_bin`). ``--serve``
starts the simulated flight controller (``hil_replay.fc.serve_simulated_fc``) on a
virtual serial port, prints the port path (one line, flushed) and serves until Ctrl-C.
Bad input (unknown effect, key or value out of range, malformed aircraft file) raises ``ValueError``
naming it; the CLI prints one line and exits 2.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
from pathlib import Path

from hil_replay.dataflash import write_bin
from hil_replay.fc import FcConfig, serve_simulated_fc
from hil_replay.sim import MESSAGE_NAMES, parse_effect, resolve_aircraft, write_tlog


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=None,
                        help="output .tlog, or .bin for the autopilot's onboard dataflash log (200 Hz IMU, ATT, "
                             "RATE, RCOU, HELI; the card's sweeps as SYSID chirps); truth goes to FILE.truth.json")
    parser.add_argument("--bin", action="store_true", help="write the onboard dataflash log (same as --out FILE.bin)")
    parser.add_argument("--no-sysid", action="store_true", help=".bin: do not log the sweeps as SYSID chirps")
    parser.add_argument("--serve", action="store_true", help="serve a simulated FC on a virtual serial port")
    parser.add_argument("--effect", action="append", default=[], metavar="NAME[:key=value,...]",
                        help="unmodelled effect to inject (repeatable), e.g. input_delay:input=lon,delay_s=0.1")
    parser.add_argument("--seed", type=int, default=0, help="random seed (same seed, same bytes)")
    parser.add_argument("--flights", type=int, default=None, help="number of flights (default 1; --serve: 2)")
    parser.add_argument("--aircraft", default=None, help="aircraft TOML file or name (default: trex600)")
    parser.add_argument("--duration-s", type=float, default=None, help="armed time per flight, approximate (default ~175 s; short cards keep whole manoeuvres, so 40 s gives ~45-50 s)")
    parser.add_argument("--pause-s", type=float, default=10.0, help="disarmed pause between flights (s)")
    parser.add_argument("--rate", action="append", default=[], metavar="MESSAGE=HZ",
                        help="--out: message rate in the .tlog, e.g. LOCAL_POSITION_NED=10 (0 = not written; "
                             "default: 50 Hz SERVO_OUTPUT_RAW/ATTITUDE/LOCAL_POSITION_NED, 10 Hz GLOBAL_POSITION_INT/"
                             "RAW_IMU, 5 Hz GPS/EXTENDED_SYS_STATE, 1 Hz HEARTBEAT/SYS_STATUS)")
    parser.add_argument("--packet-loss", type=float, default=0.002, metavar="P",
                        help="--out .tlog: share of packets the simulated link loses (default 0.002)")
    parser.add_argument("--loss-burst", type=float, default=1.0, metavar="N",
                        help="--out .tlog: mean length of a lost run, packets of every type alike, as a radio fade "
                             "(default 1: independent losses; 8 is a typical fade at range)")
    parser.add_argument("--speed", type=float, default=1.0, help="--serve: N times real time")
    parser.add_argument("--link-path", default=None, help="--serve: symlink path for the port")


def run(args: argparse.Namespace) -> int:
    effects = tuple(parse_effect(e) for e in args.effect)  # bad input fails before anything is written
    aircraft = resolve_aircraft(args.aircraft)
    if args.flights is None:
        args.flights = 2 if args.serve else 1
    if args.flights < 1:
        raise ValueError(f"--flights: {args.flights} must be >= 1")
    if args.duration_s is not None and args.duration_s < 30:
        raise ValueError(f"--duration-s: {args.duration_s:g} too short; allowed >= 30 s")
    if args.pause_s < 0:
        raise ValueError(f"--pause-s: {args.pause_s:g} must be >= 0")
    if args.serve == (args.out is not None):
        raise ValueError("give exactly one of --out FILE.tlog or --serve")
    if args.serve:
        return _serve(args, effects, aircraft)

    out: Path = args.out
    if args.bin or out.suffix.lower() == ".bin":
        return _write_bin(args, effects, aircraft)
    if out.suffix != ".tlog":
        raise ValueError(f"--out {out}: the file name must end in .tlog or .bin")
    rates: dict[str, float] = {}
    for item in args.rate:
        name, eq, hz = item.partition("=")
        try:
            rates[name.strip().upper()] = float(hz)
        except ValueError:
            raise ValueError(f"--rate {item!r}: expected MESSAGE=HZ, e.g. LOCAL_POSITION_NED=10") from None
        if not eq:
            raise ValueError(f"--rate {item!r}: expected MESSAGE=HZ, e.g. LOCAL_POSITION_NED=10")

    for name, hz in rates.items():
        if name not in MESSAGE_NAMES:
            raise ValueError(f"--rate: unknown message {name!r}; allowed: {list(MESSAGE_NAMES)}")
        if not 0.0 <= hz <= 50.0:
            raise ValueError(f"--rate {name}={hz:g}: allowed 0..50 Hz (the simulator's 50 Hz frames)")
    truth = write_tlog(out, seed=args.seed, flights=args.flights, effects=effects, aircraft=aircraft,
                       flight_duration_s=args.duration_s, pause_s=args.pause_s, rates_hz=rates or None,
                       packet_loss=args.packet_loss, loss_burst=args.loss_burst)
    fl = truth["flights"]
    total = fl[-1]["end_fc_s"] + 2.0
    print(f"wrote {out} ({out.stat().st_size} bytes, {truth['packets_written']} packets, "
          f"{truth['packets_lost']} lost on the simulated link)")
    print(f"wrote {out.with_suffix('.truth.json')}")
    print(f"aircraft {truth['aircraft']}, seed {truth['seed']}, {len(fl)} flight(s), {total:.1f} s of FC time")
    for f in fl:
        air = ", ".join(f"{a:.1f}-{b:.1f}" for a, b in f.get("in_air_fc_s", []) if b is not None)
        print(f"  flight {f['index']}: armed {f['start_fc_s']:.1f}-{f['end_fc_s']:.1f} s, in air {air or '-'} s, "
              f"{len(f['segments'])} card segments")
    if truth["effects"]:
        for e in truth["effects"]:
            ch = e["input"] or e["output"] or "-"
            params = ", ".join(f"{k}={v}" for k, v in e["params"].items())
            print(f"  effect {e['effect']} on {ch}: {params}")
    else:
        print("  effects: none (sensor noise, packet loss and timestamp jitter only)")
    return 0


def _write_bin(args: argparse.Namespace, effects: tuple, aircraft: object) -> int:
    out: Path = args.out
    if out.suffix.lower() != ".bin":
        raise ValueError(f"--out {out}: with --bin the file name must end in .bin")
    if args.rate:
        raise ValueError("--rate applies to .tlog output only (the .bin logs at the autopilot's own rates)")
    truth = write_bin(out, seed=args.seed, flights=args.flights, effects=effects, aircraft=aircraft,
                      flight_duration_s=args.duration_s, pause_s=args.pause_s, sysid=not args.no_sysid)
    df = truth["dataflash"]
    print(f"wrote {out} ({out.stat().st_size} bytes, {df['records']} records at {df['sample_rate_hz']:g} Hz, "
          f"{df['sysid_chirps']} SYSID chirps)")
    print(f"wrote {out.with_suffix('.truth.json')}")
    return 0


def _serve(args: argparse.Namespace, effects: tuple, aircraft: object) -> int:
    if not args.speed > 0:
        raise ValueError(f"--speed: {args.speed} must be > 0")
    flights = args.flights
    options = {"pause_s": args.pause_s}
    if args.duration_s is not None:
        options["flight_duration_s"] = args.duration_s

    def ready(path: str) -> None:
        print(path, flush=True)

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve_simulated_fc(args.link_path, speed=args.speed, seed=args.seed, flights=flights,
                                       effects=effects, aircraft=aircraft, on_ready=ready, sim_options=options,
                                       config=FcConfig(seed=args.seed, record_dataflash=True)))
    return 0
