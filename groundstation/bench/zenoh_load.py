"""``groundstation bench zenoh-load``: the live service on the secured field router under subscriber load.

Everything is real: certificates from ``scripts/make-field-certs`` in a temporary directory, a
Python zenoh session in router mode with the shipped router config (TLS, mTLS, usrpwd, ACL) on
loopback, the live service (:class:`groundstation.service.Service`, built-in simulated FC on a pty,
recorder, live DSP, :class:`~groundstation.sinks.zenoh_sink.ZenohSink` with the rendered
``groundstation.json5``) and viewer clients with the rendered ``viewer.json5``. Identification is
off; instead a thread hands the sink a model and a gap report every ``--model-period-s`` so the
reliable (BLOCK) path carries traffic too.

Phases (each ``--duration`` s of wall time, FC at real time):

1. ``baseline`` -- no subscribers;
2. ``loaded``   -- ``--subscribers`` viewers: most read promptly, ``--slow`` take ``--slow-s`` per
   sample in their callback, one never reads (a bounded FIFO it never drains);
3. ``restart``  -- as ``loaded``, and the router is closed and reopened on the same port halfway;
   measured: time from the router being back to the first window reaching a viewer again, and
   whether a model published during the outage is served by ``model/latest`` afterwards.

Printed per phase (after ``--warmup-s``: the first windows of a run wait for the live pipeline to
fill and are start-up, not load): live latency (window's last host-receive time -> ``put`` returned, from the
sink) p50/p99; end-to-end latency at the prompt viewers p50/p99; windows published/dropped;
packets decoded by the session vs records in the session .tlog (must be equal) and link losses;
models received by each prompt viewer (reliable: all of them).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from firmware_interface.tlogread import scan_tlog
from groundstation.config import ServiceConfig
from groundstation.service import Service
from groundstation.sinks.zenoh_sink import free_tcp_port

HELP = "zenoh load: live latency p99 and recording with 20 subscribers on the secured router; router restart"

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "make-field-certs"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration", type=float, default=20.0, help="wall seconds per phase (default 20)")
    p.add_argument("--subscribers", type=int, default=20, help="viewer sessions in the loaded phases")
    p.add_argument("--slow", type=int, default=5, help="how many of them are slow readers")
    p.add_argument("--slow-s", type=float, default=0.2, help="seconds a slow reader spends per sample")
    p.add_argument("--hop-s", type=float, default=0.1, help="live window hop (window rate = 1/hop)")
    p.add_argument("--model-period-s", type=float, default=1.0, help="model + gap report every ... s")
    p.add_argument("--warmup-s", type=float, default=2.0,
                   help="windows whose data arrived this soon after start-up are left out of the latency figures")
    p.add_argument("--router-block-close-ms", type=float, default=None,
                   help="override the router's congestion_control/block/wait_before_close (ms)")
    p.add_argument("--viewers-in-process", action="store_true",
                   help="run the viewers in the service's process (default: their own process)")
    p.add_argument("--repeat", type=int, default=1, help="run the phase list this many times (medians printed)")
    p.add_argument("--verbose", action="store_true", help="print the slowest windows of each phase")
    p.add_argument("--phases", default="baseline,loaded,restart", help="comma-separated subset")


def _pct(xs: list[float], q: float) -> float:
    if not xs:
        return float("nan")
    s = sorted(xs)
    return s[min(len(s) - 1, int(round(q / 100.0 * (len(s) - 1))))]


def _make_field(out: Path) -> Path:
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out)], capture_output=True, text=True)
    if proc.returncode != 0:
        raise OSError(f"{SCRIPT}: {proc.stderr.strip()}")
    return out


def _retarget(src: Path, dst: Path, port: int) -> Path:
    text = re.sub(r"tls/[^\"]+:\d+", f"tls/localhost:{port}", src.read_text())
    fd = os.open(dst, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    return dst


class Router:
    """The field router as a Python zenoh session (restartable on the same port)."""

    def __init__(self, config_path: Path, port: int, block_close_ms: float | None = None) -> None:
        self.config_path, self.port, self.block_close_ms = config_path, port, block_close_ms
        self.session: Any = None

    def open(self) -> None:
        import zenoh

        cfg = zenoh.Config.from_file(str(self.config_path))
        cfg.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{self.port}"]))
        if self.block_close_ms is not None:
            cfg.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close",
                             str(int(self.block_close_ms * 1000)))
        self.session = zenoh.open(cfg)

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None


class Viewer:
    """One viewer session: ``prompt`` records arrival times, ``slow`` sleeps per sample, ``stuck``
    never reads its bounded FIFO (until :meth:`close`)."""

    def __init__(self, config_path: Path, vehicle: str, kind: str, slow_s: float) -> None:
        import zenoh

        self.kind = kind
        self.closing = threading.Event()
        self.windows: list[tuple[float, float]] = []    # (t_received, t_host_last_s)
        self.models = 0
        cfg = zenoh.Config.from_file(str(config_path))
        if kind == "stuck":
            # a small socket receive buffer: the router's queue towards it fills within seconds,
            # not after the megabytes of a default loopback buffer
            cfg.insert_json5("transport/link/tls/so_rcvbuf", "4096")
        self.session = zenoh.open(cfg)
        key = f"heli/{vehicle}/**"
        if kind == "stuck":
            self.sub: Any = self.session.declare_subscriber(key, zenoh.handlers.FifoChannel(4))
        else:
            def cb(sample: Any) -> None:
                t = time.time()
                k = str(sample.key_expr)
                if k.endswith("/telemetry/window"):
                    if kind == "prompt":
                        doc = json.loads(sample.payload.to_bytes())
                        self.windows.append((t, float(doc.get("t_host_last_s") or "nan")))
                    else:
                        self.windows.append((t, float("nan")))
                elif k.endswith("/model"):
                    self.models += 1
                if kind == "slow" and not self.closing.is_set():
                    time.sleep(slow_s)

            self.sub = self.session.declare_subscriber(key, cb)

    def close(self) -> None:
        self.closing.set()     # a slow reader's backlog drains at once instead of slow_s per sample
        if self.kind == "stuck":
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:    # drain so zenoh's rx thread can finish
                if self.sub.try_recv() is None:
                    time.sleep(0.01)
                    if self.sub.try_recv() is None:
                        break
        try:
            self.sub.undeclare()
        finally:
            self.session.close()


@dataclass
class ViewerRecord:
    kind: str
    windows: list[tuple[float, float]]
    models: int


def _drain(viewers: list[Viewer]) -> list[ViewerRecord]:
    """Stop the slow readers' sleeping, wait until counts settle (reliable samples still in flight
    are counted rather than cut off by closing), and snapshot them."""
    for v in viewers:
        v.closing.set()
    last, stable_since, t_end = None, time.monotonic(), time.monotonic() + 10.0
    while time.monotonic() < t_end and time.monotonic() - stable_since < 1.0:
        now_counts = [(v.models, len(v.windows)) for v in viewers]
        if now_counts != last:
            last, stable_since = now_counts, time.monotonic()
        time.sleep(0.05)
    return [ViewerRecord(v.kind, list(v.windows), v.models) for v in viewers]


def _host_main(viewer_cfg: str, vehicle: str, kinds: list[str], slow_s: float, conn: Any) -> None:
    """Body of the viewer process: open the viewers, report ready, wait, drain, send the counts."""
    viewers = []
    try:
        viewers = [Viewer(Path(viewer_cfg), vehicle, k, slow_s) for k in kinds]
        conn.send("ready")
        conn.recv()
        conn.send([(r.kind, r.windows, r.models) for r in _drain(viewers)])
    finally:
        for v in viewers:
            v.close()


class ViewerHost:
    """The viewers in their own process, as on teammates' laptops: their callbacks (JSON parsing,
    sleeping) do not compete with the service for this process's interpreter."""

    def __init__(self, viewer_cfg: Path, vehicle: str, kinds: list[str], slow_s: float) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_host_main, args=(str(viewer_cfg), vehicle, kinds, slow_s, child),
                                 name="zenoh-load-viewers", daemon=True)
        self._proc.start()
        if not self._conn.poll(60) or self._conn.recv() != "ready":
            self.kill()
            raise OSError("zenoh-load: the viewer process did not start")

    def finish(self) -> list[ViewerRecord]:
        self._conn.send("drain")
        if not self._conn.poll(60):
            self.kill()
            raise OSError("zenoh-load: the viewer process did not report")
        recs = [ViewerRecord(k, w, m) for k, w, m in self._conn.recv()]
        self._proc.join(20)
        self.kill()
        return recs

    def kill(self) -> None:
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5)


def _service_config(record_dir: Path, gs_config: Path, hop_s: float):
    cfg = ServiceConfig()
    cfg = cfg.replace("service", record_dir=str(record_dir), vehicle="bench", status_rate_hz=1.0)
    cfg = cfg.replace("zenoh", config_file=str(gs_config), window_queue=8)
    cfg = cfg.replace("live", window_s=4.0, hop_s=hop_s)
    cfg = cfg.replace("identification", enabled=False)
    cfg = cfg.replace("sim", speed=1.0, flights=50)
    return cfg


def _count_records(path: str | None) -> int:
    if not path:
        return 0
    return sum(1 for _ in scan_tlog(Path(path).read_bytes()))


def _restart_router(args: argparse.Namespace, router: Router, prompt: list[Any], viewer_cfg: Path,
                    models_sent: list[int], restart_info: dict[str, Any]) -> None:
    """Halfway through the phase: close the router, publish a model while it is down, reopen it and
    time how long the prompt viewers take to get windows again; the late joiner asks the queryable."""
    time.sleep(args.duration / 2)
    t0 = time.time()
    router.close()
    t_closed = time.time()
    time.sleep(1.0)
    n_before = models_sent[0]
    # a model published while the router is down: lost for live subscribers, but the
    # queryable must serve it once the router is back
    while models_sent[0] == n_before and time.time() - t_closed < 5:
        time.sleep(0.05)
    outage_model = models_sent[0]
    router.open()
    t_back = time.time()
    first = None
    while time.time() - t_back < 15.0:
        arrivals = [t for v in prompt for t, _ in v.windows if t > t_back]
        if arrivals:
            first = min(arrivals)
            break
        time.sleep(0.01)
    served = None
    if first is not None:
        late = Viewer(viewer_cfg, "bench", "prompt", 0.0)
        try:
            served = [json.loads(r.ok.payload.to_bytes()).get("seq")
                      for r in late.session.get("heli/bench/model/latest", timeout=3.0) if r.ok]
        finally:
            late.close()
    restart_info.update(close_s=t_closed - t0, served_after_back=served, router_open_s=t_back - t_closed - 1.0,
                        resume_after_back_s=(first - t_back) if first else float("nan"),
                        resume_after_close_s=(first - t_closed) if first else float("nan"),
                        outage_model=outage_model)


def _phase_figures(name: str, args: argparse.Namespace, report: Any, records: list[Any], sink: Any,
                   t_steady: float, models_sent: int) -> dict[str, Any]:
    """Latencies (after the warm-up), delivery counts and recording completeness of one phase."""
    lat_seq = [(seq, (tp - th) * 1e3) for seq, th, tp in list(sink.window_latency) if th >= t_steady]
    if args.verbose:
        print(f"  [{name}] slowest windows (seq, ms): {sorted(lat_seq, key=lambda x: -x[1])[:5]}")
    lat = [x for _s, x in lat_seq]
    e2e = [(t - th) * 1e3 for v in records if v.kind == "prompt" for t, th in v.windows if th >= t_steady]
    prompt = [v for v in records if v.kind == "prompt"]
    return dict(
        live_p50_ms=_pct(lat, 50), live_p99_ms=_pct(lat, 99), windows_published=report.windows_published,
        windows_dropped=report.windows_dropped, e2e_p50_ms=_pct(e2e, 50), e2e_p99_ms=_pct(e2e, 99),
        session_packets=report.packets, recorded_packets=_count_records(report.session_tlog),
        link_packets_lost=report.packets_lost, models_sent=models_sent,
        models_received_min=min((v.models for v in prompt), default=0),
        models_received_max=max((v.models for v in prompt), default=0),
        slow_windows=[len(v.windows) for v in records if v.kind == "slow"],
        slow_models=[v.models for v in records if v.kind == "slow"],
        prompt_windows_median=statistics.median([len(v.windows) for v in prompt]) if prompt else 0,
        sink_error=sink.error,
    )


def run_phase(name: str, args: argparse.Namespace, work: Path, field: Path, router: Router,
              n_subs: int, restart: bool) -> dict[str, Any]:
    gs_cfg = _retarget(field / "groundstation.json5", work / f"{name}-gs.json5", router.port)
    viewer_cfg = _retarget(field / "viewer.json5", work / f"{name}-viewer.json5", router.port)
    viewers: list[Viewer] = []
    host: ViewerHost | None = None
    probe: Viewer | None = None
    out: dict[str, Any] = {"phase": name, "subscribers": n_subs}
    try:
        kinds = ["stuck" if i == n_subs - 1 else ("slow" if i < args.slow else "prompt") for i in range(n_subs)]
        if args.viewers_in_process:
            viewers = [Viewer(viewer_cfg, "bench", k, args.slow_s) for k in kinds]
        elif kinds:
            host = ViewerHost(viewer_cfg, "bench", kinds, args.slow_s)
        if restart:   # one more prompt viewer here, to time the resumption after the router restart
            probe = Viewer(viewer_cfg, "bench", "prompt", 0.0)
        service = Service(_service_config(work / name, gs_cfg, args.hop_s), log=lambda m: None)
        stop_models = threading.Event()
        models_sent = [0]
        model_doc = {"schema": "heli-hover-model/1", "parameters": {f"p{i}": 0.001 * i for i in range(31)},
                     "horizontal": {"A": [[0.0] * 8] * 8, "B": [[0.0] * 2] * 8}}
        gap_doc = {"schema": "heli-gap-report/1", "verdict": "none", "effects": []}

        def models() -> None:
            k = 0
            while not stop_models.wait(args.model_period_s):
                if service.zenoh is None:
                    continue
                k += 1
                service.zenoh.publish_model(k, {**model_doc, "seq": k})
                service.zenoh.publish_gap(k, gap_doc)
                models_sent[0] = k

        restart_info: dict[str, Any] = {}
        t_ready = [0.0]

        def restarter(loop: asyncio.AbstractEventLoop) -> None:
            prompt = [probe] if probe is not None else [v for v in viewers if v.kind == "prompt"]
            _restart_router(args, router, prompt, viewer_cfg, models_sent, restart_info)

        async def main() -> Any:
            loop = asyncio.get_running_loop()
            task = asyncio.create_task(service.run())
            await asyncio.wait_for(service.ready.wait(), 30)
            t_ready[0] = time.time()
            th = threading.Thread(target=models, daemon=True)
            th.start()
            rth = None
            if restart:
                rth = threading.Thread(target=restarter, args=(loop,), daemon=True)
                rth.start()
            t_end = time.monotonic() + args.duration
            while time.monotonic() < t_end and not task.done():
                await asyncio.sleep(0.1)
            if rth is not None:
                await asyncio.to_thread(rth.join, 30)
            stop_models.set()
            service.request_stop("bench")
            report = await task
            th.join(2)
            return report

        report = asyncio.run(main())
        records = host.finish() if host is not None else _drain(viewers)
        host = None
        out.update(_phase_figures(name, args, report, records, service.zenoh, t_ready[0] + args.warmup_s,
                                  models_sent[0]), **restart_info)
    finally:
        if host is not None:
            host.kill()
        for v in viewers + ([probe] if probe is not None else []):
            v.close()
    return out


def run(args: argparse.Namespace) -> int:
    phases = [p.strip() for p in args.phases.split(",") if p.strip()]
    bad = set(phases) - {"baseline", "loaded", "restart"}
    if bad:
        raise ValueError(f"--phases: unknown phase(s) {sorted(bad)}")
    if not 0 <= args.slow < args.subscribers:
        raise ValueError("--slow must be in [0, --subscribers)")

    results = []
    with tempfile.TemporaryDirectory(prefix="zenoh-load-") as tmp:
        work = Path(tmp)
        field = _make_field(work / "field")
        router = Router(field / "router.json5", free_tcp_port(), args.router_block_close_ms)
        router.open()
        try:
            for rep in range(args.repeat):
                for ph in phases:
                    n = 0 if ph == "baseline" else args.subscribers
                    res = run_phase(f"{ph}-{rep}" if args.repeat > 1 else ph, args, work, field, router, n,
                                    restart=(ph == "restart"))
                    res["kind"] = ph
                    results.append(res)
                    _print(res)
        finally:
            router.close()
    print(f"summary over {args.repeat} run(s) (medians):")
    med: dict[str, float] = {}
    for ph in phases:
        rs = [r for r in results if r["kind"] == ph]
        med[ph] = statistics.median(r["live_p99_ms"] for r in rs)
        lost = sum(r["session_packets"] - r["recorded_packets"] for r in rs)
        line = (f"  {ph:8s} live p50 {statistics.median(r['live_p50_ms'] for r in rs):6.2f} ms  "
                f"p99 {med[ph]:6.2f} ms  recorded packets lost {lost}")
        if ph != "baseline" and "baseline" in med:
            line += f"  p99 vs baseline {med[ph] - med['baseline']:+.2f} ms (issue budget +10 ms)"
        if ph == "restart":
            line += (f"  resume after router back {statistics.median(r['resume_after_back_s'] for r in rs):.2f} s"
                     f" (after close {statistics.median(r['resume_after_close_s'] for r in rs):.2f} s, budget 5 s)")
        print(line)
    return 0


def _print(r: dict[str, Any]) -> None:
    print(f"[{r['phase']}] subscribers={r['subscribers']}")
    print(f"  live latency (window last sample -> put returned): p50 {r['live_p50_ms']:.2f} ms, "
          f"p99 {r['live_p99_ms']:.2f} ms; windows published {r['windows_published']}, "
          f"dropped at the sink {r['windows_dropped']}")
    if r["subscribers"]:
        print(f"  end-to-end at prompt viewers: p50 {r['e2e_p50_ms']:.2f} ms, p99 {r['e2e_p99_ms']:.2f} ms; "
              f"windows per prompt viewer (median) {r['prompt_windows_median']}, per slow viewer "
              f"{r['slow_windows']}")
        print(f"  models (after the run, backlogs drained): sent {r['models_sent']}, received per prompt viewer "
              f"{r['models_received_min']}..{r['models_received_max']}, per slow viewer {r['slow_models']}")
    print(f"  recording: session decoded {r['session_packets']} packets, session .tlog holds "
          f"{r['recorded_packets']} (lost {r['session_packets'] - r['recorded_packets']}); "
          f"link seq losses {r['link_packets_lost']}")
    if "resume_after_back_s" in r:
        print(f"  router restart: down 1.0 s; reopen took {r['router_open_s']:.2f} s; first window at a "
              f"viewer {r['resume_after_back_s']:.2f} s after the router was back "
              f"({r['resume_after_close_s']:.2f} s after it closed); model #{r['outage_model']} published "
              f"during the outage; model/latest right after the restart serves {r.get('served_after_back')}")
    if r.get("sink_error"):
        print(f"  sink error: {r['sink_error']}")
