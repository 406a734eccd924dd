"""``groundstation bench service``: live-path latency and CPU, max-speed throughput, latency under load.

Three measurements of the real service (:class:`groundstation.service.Service`: pty -> serial
transport -> session -> recorder -> live DSP -> zenoh), the flight side always in a *separate process*
so its CPU is not counted:

1. **real time** -- the simulated FC (``hil_replay.fc`` + ``hil_replay.sim``) at speed 1 for
   ``--realtime-s``. A zenoh subscriber (another session on loopback, in this process) takes the
   latency of each window as its receive time minus ``t_host_last_s``, the host receive time of the
   packet that completed the window's newest row (arrival -> the zenoh window that contains it).
   CPU = this process's user+sys time (``resource.getrusage``) over wall time, in % of one core.
   Targets: p99 <= 50 ms, CPU <= 15 %.
2. **max speed** -- a simulated flight .tlog replayed by :class:`hil_replay.player.TlogPlayer` at
   maximum speed (``speed=0``: as fast as the service drains the pty); real-time factor = FC seconds
   of the log over wall seconds between the first and last packet received; packets lost = packets
   the player sent intact minus packets the service's recorder wrote. Targets: >= 20x, 0 lost.
3. **under load** -- as 1, then an identification (+ diagnosis) of a simulated flight is submitted
   to the service's worker process; p99 latency during the job minus p99 before. Target <= 10 ms.

Prints medians and p99 with the numbers of samples. Nothing here is tuned: it only measures.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import resource
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from firmware_interface.readers import load_log
from groundstation.config import ServiceConfig
from groundstation.service import Service
from groundstation.sinks.zenoh_sink import free_tcp_port, loopback_peer_config
from groundstation.worker import IdentifyJob
from hil_replay.fc import SimulatedFCThread
from hil_replay.player import TlogPlayer
from hil_replay.pty import VirtualSerialPort
from hil_replay.sim import write_tlog

HELP = "service: p99 arrival->zenoh window latency and CPU at real time, max-speed RTF, latency under load"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--realtime-s", type=float, default=30.0, help="seconds at real time (phase 1)")
    parser.add_argument("--replay-flight-s", type=float, default=120.0,
                        help="flight length of the max-speed replay log (phase 2)")
    parser.add_argument("--skip", action="append", default=[], choices=("realtime", "maxspeed", "load"),
                        help="skip a phase (repeatable)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="also write the figures as JSON here")
    parser.add_argument("--idle-after-s", type=float, default=60.0,
                        help="after the job, measure the idle service for as long as the job took, up to this "
                             "(the load the machine's other work causes over a period of that length; 0: skip)")
    parser.add_argument("--rerun", action="store_true",
                        help="also save a Rerun .rrd (rerun.mode = save) so its cost is in the figures")


# ------------------------------------------------------------------ child processes (flight side)


def _fc_child(conn: Any, speed: float, seed: int, sim_options: dict[str, Any]) -> None:
    fc = SimulatedFCThread(speed=speed, seed=seed, flights=1, sim_options=sim_options)
    fc.start()
    conn.send(fc.port_path)
    conn.recv()
    fc.stop(2.0)


def _player_child(conn: Any, tlog: str) -> None:
    port = VirtualSerialPort(None)
    player = TlogPlayer(tlog, port, speed=0.0, reader_timeout_s=30.0)
    conn.send(port.path)
    rep = player.run()
    conn.send({"n_packets": rep.n_packets, "intact": len(rep.intact)})
    conn.recv()
    port.close()


class _Child:
    def __init__(self, target: Any, *args: Any) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=target, args=(child, *args), daemon=True)
        self.proc.start()
        if not self.conn.poll(60):
            raise TimeoutError("flight-side process did not start")
        self.port_path: str = self.conn.recv()

    def stop(self) -> None:
        try:
            self.conn.send("stop")
        except (BrokenPipeError, OSError):
            pass
        self.proc.join(5)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(2)


# ------------------------------------------------------------------ measurement helpers


class _WindowLatency:
    """A zenoh subscriber (own session, loopback) timing every window on arrival."""

    def __init__(self, port: int, vehicle: str) -> None:
        import zenoh

        self.session = zenoh.open(zenoh.Config.from_json5(loopback_peer_config(connect_ports=(port,))))
        self.samples: list[tuple[float, float]] = []      # (receive time, latency s)
        self._lock = threading.Lock()
        self.sub = self.session.declare_subscriber(f"heli/{vehicle}/telemetry/window", self._on)

    def _on(self, sample: Any) -> None:
        now = time.time()
        t_host = json.loads(sample.payload.to_string()).get("t_host_last_s")
        if isinstance(t_host, float):
            with self._lock:
                self.samples.append((now, now - t_host))

    def worst(self, t0: float, t1: float, k: int = 5) -> list[tuple[float, float]]:
        """The k largest latencies in [t0, t1) as (seconds after t0, ms)."""
        with self._lock:
            sel = sorted(((lat, t) for t, lat in self.samples if t0 <= t < t1), reverse=True)[:k]
        return [(round(t - t0, 2), round(1000 * lat, 1)) for lat, t in sel]

    def between(self, t0: float, t1: float) -> np.ndarray:
        with self._lock:
            return np.array([lat for t, lat in self.samples if t0 <= t < t1])

    def close(self) -> None:
        self.session.close()


def _stats_ms(lat_s: np.ndarray) -> dict[str, float]:
    if len(lat_s) == 0:
        return {"n": 0, "median_ms": float("nan"), "p99_ms": float("nan"), "max_ms": float("nan")}
    ms = 1000.0 * lat_s
    return {"n": int(len(ms)), "median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max())}


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _config(tmp: Path, link_url: str, *, identify: bool, hop_s: float = 0.25, rerun: bool = False) -> Any:
    cfg = ServiceConfig()
    cfg = cfg.replace("service", record_dir=str(tmp / "rec"), vehicle="bench")
    cfg = cfg.replace("link", url=link_url)
    cfg = cfg.replace("zenoh", listen_port=free_tcp_port())
    cfg = cfg.replace("live", hop_s=hop_s)
    if rerun:
        cfg = cfg.replace("rerun", mode="save", target=str(tmp / "bench.rrd"))
    return cfg.replace("identification", enabled=identify)


# ------------------------------------------------------------------ phases


async def _realtime_and_load(tmp: Path, seconds: float, seed: int, load: bool, realtime: bool,
                             job_tlog: str | None, rerun: bool = False, idle_after_s: float = 0.0) -> dict[str, Any]:
    out: dict[str, Any] = {}
    fc = await asyncio.to_thread(_Child, _fc_child, 1.0, seed, {"pause_s": 2.0})
    service = Service(_config(tmp, f"serial://{fc.port_path}:115200", identify=load, rerun=rerun), log=lambda m: None)
    task = asyncio.create_task(service.run())
    sub = None
    try:
        await asyncio.wait_for(service.ready.wait(), 30)
        sub = _WindowLatency(service.config.zenoh.listen_port, service.vehicle)
        await asyncio.sleep(3.0)                      # stream setup and grid warm-up
        t0, c0 = time.time(), _cpu_s()
        await asyncio.sleep(seconds if realtime else min(seconds, 10.0))
        t1, c1 = time.time(), _cpu_s()
        base = _stats_ms(sub.between(t0, t1))
        out["realtime"] = {**base, "seconds": t1 - t0, "cpu_pct_one_core": 100.0 * (c1 - c0) / (t1 - t0),
                           "windows_dropped": service.zenoh.windows_dropped if service.zenoh else None}
        if load and job_tlog is not None:
            job = IdentifyJob(flight=99, tlogs=(job_tlog,), out_dir=str(tmp / "rec"),
                              config=service.config.replace("identification", plots=False))
            t2 = time.time()
            fut = service.submit_identification(job)
            res = await asyncio.wait_for(fut, 600)
            t3 = time.time()
            during = _stats_ms(sub.between(t2 + 1.0, t3))   # skip the worker's spawn second
            # the same service, idle, for as long again (up to --idle-after-s): what the machine's
            # other load does to the p99 over a period of that length, right after the job
            idle_s = min(t3 - t2, idle_after_s)
            await asyncio.sleep(1.0 + idle_s)
            idle = _stats_ms(sub.between(t3 + 1.0, t3 + 1.0 + idle_s))
            out["load"] = {**during, "job_s": t3 - t2, "job_error": res.error,
                           "identify_s": res.identify_s,
                           "worst_s_ms": sub.worst(t2, t3 + 1.0),
                           "p99_growth_ms": during["p99_ms"] - base["p99_ms"],
                           "idle_after": {**idle, "seconds": idle_s, "worst_s_ms": sub.worst(t3 + 1.0, t3 + 1.0 + idle_s)},
                           "p99_vs_idle_after_ms": during["p99_ms"] - idle["p99_ms"]}
    finally:
        service.request_stop("bench done")
        await asyncio.wait_for(task, 30)
        if sub is not None:
            sub.close()
        await asyncio.to_thread(fc.stop)
    return out


async def _maxspeed(tmp: Path, tlog: str, rerun: bool = False) -> dict[str, Any]:
    log = load_log(tlog)
    att = log.series["ATTITUDE"].t_fc_s
    fc_span_s = float(att[-1] - att[0])
    player = await asyncio.to_thread(_Child, _player_child, tlog)
    service = Service(_config(tmp, f"serial://{player.port_path}:115200", identify=False, rerun=rerun), log=lambda m: None)
    task = asyncio.create_task(service.run())
    first: float | None = None
    last_change = time.monotonic()
    last_count = 0
    try:
        await asyncio.wait_for(service.ready.wait(), 30)
        while True:
            await asyncio.sleep(0.02)
            n = service.packets
            if n and first is None:
                first = time.monotonic()
            if n != last_count:
                last_count, last_change = n, time.monotonic()
            elif first is not None and time.monotonic() - last_change > 2.0 and player.conn.poll():
                break
            if time.monotonic() - last_change > 60:
                raise TimeoutError("max-speed replay stalled")
        wall_s = last_change - (first or last_change)
        rep = player.conn.recv()
        recorded = service.recorder.packets
    finally:
        service.request_stop("bench done")
        await asyncio.wait_for(task, 30)
        await asyncio.to_thread(player.stop)
    # The ground station's own requests are not in the source log; the recorder counts only received packets.
    return {"fc_seconds": fc_span_s, "wall_s": wall_s, "rtf": fc_span_s / wall_s if wall_s > 0 else float("inf"),
            "packets_source": rep["n_packets"], "packets_sent_intact": rep["intact"],
            "packets_recorded": recorded, "packets_lost": rep["intact"] - recorded,
            "seq_gaps_seen": service.report.packets_lost}


def run(args: argparse.Namespace) -> int:
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="bench-service-") as d:
        tmp = Path(d)
        need_log = "maxspeed" not in args.skip or "load" not in args.skip
        tlog = None
        if need_log:
            tlog = str(tmp / "flight.tlog")
            write_tlog(tlog, seed=args.seed, flights=1, effects=(), aircraft=None,
                       **({"flight_duration_s": args.replay_flight_s} if args.replay_flight_s else {}))
        if "realtime" not in args.skip or "load" not in args.skip:
            results.update(asyncio.run(_realtime_and_load(
                tmp / "rt", args.realtime_s, args.seed, "load" not in args.skip, "realtime" not in args.skip, tlog,
                args.rerun, args.idle_after_s)))
        if "maxspeed" not in args.skip and tlog is not None:
            results["maxspeed"] = asyncio.run(_maxspeed(tmp / "max", tlog, args.rerun))

    rt = results.get("realtime")
    if rt:
        print(f"real time ({rt['seconds']:.0f} s, {rt['n']} windows): arrival->zenoh window latency "
              f"median {rt['median_ms']:.1f} ms, p99 {rt['p99_ms']:.1f} ms, max {rt['max_ms']:.1f} ms "
              f"(target p99 <= 50); CPU {rt['cpu_pct_one_core']:.1f}% of one core (target <= 15); "
              f"windows dropped {rt['windows_dropped']}")
    ms = results.get("maxspeed")
    if ms:
        print(f"max speed: {ms['fc_seconds']:.0f} FC s in {ms['wall_s']:.1f} wall s = {ms['rtf']:.1f}x real time "
              f"(target >= 20); packets sent {ms['packets_sent_intact']}, recorded {ms['packets_recorded']}, "
              f"lost {ms['packets_lost']} (target 0)")
    ld = results.get("load")
    if ld:
        print(f"under load (identification {ld['job_s']:.0f} s{', error ' + ld['job_error'] if ld['job_error'] else ''}; "
              f"{ld['n']} windows): latency median {ld['median_ms']:.1f} ms, p99 {ld['p99_ms']:.1f} ms; "
              f"p99 growth {ld['p99_growth_ms']:+.1f} ms (target <= 10)")
        ia = ld.get("idle_after") or {}
        if ia.get("n"):
            print(f"idle right after the job ({ia['seconds']:.0f} s, {ia['n']} windows): p99 {ia['p99_ms']:.1f} ms; "
                  f"during the job minus idle after: {ld['p99_vs_idle_after_ms']:+.1f} ms; worst windows "
                  f"(s after submit, ms) during {ld['worst_s_ms'][:3]} (identification ended at "
                  f"{ld['identify_s'] or float('nan'):.0f} s), idle {ia['worst_s_ms'][:3]}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0
