"""``groundstation demo`` (``make demo``): the whole mission on the built-in simulated helicopter.

Two flights at accelerated time; the service records them, smooths and windows live, identifies
the hover model between and after the flights in a worker process, diagnoses the gap, publishes on
zenoh (a demo subscriber in this process prints what it receives and, at the end, asks the
``model/latest`` queryable as a late subscriber would), saves a Rerun .rrd, and prints where
everything went and the match table. Output goes to ``demo_out/`` (gitignored).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shutil
import time
from pathlib import Path
from typing import Any

from groundstation.commands.run import add_common, config_from_args, print_report, sim_options
from groundstation.config import load_config
from groundstation.service import Service
from groundstation.sinks.zenoh_sink import loopback_peer_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="demo_out", metavar="DIR", help="output directory (default demo_out)")
    add_common(parser)
    parser.set_defaults(speed=None, flights=None)


class DemoSubscriber:
    """A separate zenoh session (peer on loopback) printing what the service publishes."""

    def __init__(self, endpoint: str, vehicle: str, loop: asyncio.AbstractEventLoop, out=print) -> None:
        import zenoh

        port = int(endpoint.rsplit(":", 1)[1])
        self.zenoh = zenoh
        self.session = zenoh.open(zenoh.Config.from_json5(loopback_peer_config(connect_ports=(port,))))
        self.vehicle = vehicle
        self.loop = loop
        self.out = out
        self.counts: dict[str, int] = {}
        self._last_status_print = 0.0
        self._last_state: tuple[Any, ...] = ()
        self._late_done = False
        self.late_task: asyncio.Task[None] | None = None
        self._port = port
        # zenoh calls back on its own thread: hand each sample to the event loop
        self.sub = self.session.declare_subscriber(
            f"heli/{vehicle}/**",
            lambda s: loop.call_soon_threadsafe(self._on, str(s.key_expr), s.payload.to_string()))

    def _on(self, key: str, payload: str) -> None:
        kind = key.split("/", 2)[2]
        short = "window" if kind.endswith("telemetry/window") else kind
        self.counts[short] = self.counts.get(short, 0) + 1
        doc: dict[str, Any] = json.loads(payload)
        if short == "status":
            now = time.monotonic()
            state = (doc["link"]["up"], doc["armed"], doc["in_air"], doc["flights_completed"],
                     doc["identification"]["state"])
            if state != self._last_state or now - self._last_status_print >= 15.0:
                self._last_status_print = now
                self._last_state = state
                link = doc["link"]
                self.out(f"[zenoh] {key}: link {'up' if link['up'] else 'DOWN'} packets {link['packets']} "
                         f"loss {link['loss_pct']:.2f}% armed {doc['armed']} in_air {doc['in_air']} "
                         f"flights {doc['flights_completed']} ident {doc['identification']['state']} "
                         f"windows {self.counts.get('window', 0)}")
        elif kind.endswith("/model"):
            if not self._late_done:
                self._late_done = True
                self.late_task = self.loop.create_task(asyncio.to_thread(self._late_query))
            md = doc.get("fit", {}).get("match_degree", {})
            self.out(f"[zenoh] {key}: model received ({len(doc.get('parameters', {}))} parameters, "
                     f"fitness {doc.get('fit', {}).get('fitness')}, {len(md)} match degrees)")
        elif kind.endswith("/gap"):
            self.out(f"[zenoh] {key}: gap report received, verdict {doc.get('verdict')}")

    def _late_query(self) -> None:
        """A new session joining late asks the queryable for the latest model (zenoh thread)."""
        late = self.zenoh.open(self.zenoh.Config.from_json5(loopback_peer_config(connect_ports=(self._port,))))
        try:
            time.sleep(0.2)
            for r in late.get(f"heli/{self.vehicle}/model/latest", timeout=3):
                if r.ok is not None:
                    doc = json.loads(r.ok.payload.to_string())
                    self.loop.call_soon_threadsafe(
                        self.out, f"[zenoh] late subscriber: heli/{self.vehicle}/model/latest answered "
                                  f"(schema {doc.get('schema')})")
        finally:
            late.close()

    def close(self) -> None:
        self.session.close()


async def _main(cfg: Any, out_dir: Path, options: dict[str, Any] | None
                ) -> tuple[Any, dict[str, int], dict[str, Any]]:
    service = Service(cfg, sim_options=options)
    task = asyncio.create_task(service.run())
    ready = asyncio.create_task(service.ready.wait())
    await asyncio.wait({task, ready}, return_when=asyncio.FIRST_COMPLETED)
    sub = None
    if service.ready.is_set() and service.zenoh is not None and service.zenoh.endpoint:
        sub = DemoSubscriber(service.zenoh.endpoint, service.vehicle, asyncio.get_running_loop())
    try:
        report = await task
        late: dict[str, Any] = {}
        counts: dict[str, int] = {}
        if sub is not None:
            if sub.late_task is not None:
                await sub.late_task
            counts = dict(sub.counts)
        return report, counts, late
    finally:
        ready.cancel()
        if sub is not None:
            sub.close()


def run(args: argparse.Namespace) -> int:
    t0 = time.monotonic()
    out_dir = Path(args.out)
    if out_dir.exists():
        shutil.rmtree(out_dir / "recordings", ignore_errors=True)
    base = load_config(args.config)
    base = base.replace("service", record_dir=str(out_dir / "recordings"), exit_after_flights=2)
    base = base.replace("sim", speed=10.0, flights=2)
    base = base.replace("rerun", mode="save", target=str(out_dir / "demo.rrd"))
    cfg = config_from_args(args, base)
    print(f"demo: {cfg.sim.flights} simulated flight(s) at {cfg.sim.speed:g}x; output in {out_dir}/")
    report, counts, _ = asyncio.run(_main(cfg, out_dir, sim_options(args)))
    print_report(report)
    if counts:
        print("zenoh demo subscriber received: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    print(f"demo finished in {time.monotonic() - t0:.0f} s")
    return 0
