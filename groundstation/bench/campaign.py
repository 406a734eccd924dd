"""``groundstation bench campaign [--flights 16] [--duration-s 60] [--speedup-flights 8]``.

N simulated flights of one aircraft (``hil_replay.sim.write_tlog``, one log each, seeds 1..N). Every
flight carries a deadband on one input that widens linearly from ``--grow-from`` to ``--grow-to``
(normalised units; servo wear); nothing else changes from flight to flight except the weather of
the seed. Prints:

1. time per flight and peak memory against N (1, 2, 4, ... N) from one in-process campaign over all
   flights (identify + diagnose + cross-flight fit per flight; the cumulative time after N flights
   over N, and the process's peak RSS after N flights). Targets: time per flight constant within
   20 %, peak memory for 16 flights <= 2x one;
2. speed-up on ``--speedup-flights`` flights (identification only, to keep the bench short; the
   campaign's first flights, then as many more as needed with the last deadband width): one process, a process pool of every core, and a local Dask cluster of every core, each
   warm (workers started and their imports done before the clock; the one fork server that imports
   the analysis for every worker is timed once, apart). Prints the CPU of the whole process tree
   (the pool's overhead: pool CPU / one process CPU, target <= 1.10) and the wall speed-up (target
   >= 1.7x on two cores; a shared machine depresses it, the CPU ratio is immune), and Dask against
   the pool on both (target within 10 %);
3. the trend test over the campaign: whether the growing deadband is flagged by the flight where
   its estimate exceeds twice its first estimate, and whether anything else is flagged.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.campaign import runner
from groundstation.campaign.job import FlightJob, Settings, file_sha256
from groundstation.campaign.store import CampaignStore, series
from groundstation.config import ServiceConfig
from groundstation.trends.change import MIN_FLIGHTS_FOR_SCATTER, assess_all
from hil_replay.sim import parse_effect, write_tlog

HELP = "campaign of simulated flights: time per flight vs N, speed-up 1 core / all cores / Dask, trend test"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--flights", type=int, default=16, help="flights in the campaign")
    parser.add_argument("--duration-s", type=float, default=60.0, help="armed time per simulated flight (>= 30)")
    parser.add_argument("--speedup-flights", type=int, default=8, help="flights of the speed-up runs (0: skip)")
    parser.add_argument("--input", default="lon", choices=("lat", "lon", "col", "ped"), help="input with the deadband")
    # the simulator's typical range of servo play (0.01-0.05); wider than about a third of the card's
    # excitation on that input (0.1-0.15) the base model itself is not identifiable from these flights
    parser.add_argument("--grow-from", type=float, default=0.01, help="deadband half-width on the first flight")
    parser.add_argument("--grow-to", type=float, default=0.05, help="deadband half-width on the last flight")
    parser.add_argument("--restarts", type=int, default=1, help="identification searches per subsystem")
    parser.add_argument("--default-flights", type=int, default=4,
                        help="flights of the default campaign as a user runs it (default settings, --jobs default: "
                             "every core): wall and CPU per flight (0: skip)")
    parser.add_argument("--only-default", action="store_true", help="only the default campaign")
    parser.add_argument("--keep", type=Path, default=None,
                        help="keep the logs and the table (bench.sqlite, aircraft 'bench') in this directory")


def _simulate(d: Path, args: argparse.Namespace) -> tuple[list[Path], np.ndarray]:
    widths = np.linspace(args.grow_from, args.grow_to, args.flights)
    # flights beyond the campaign's (only for the speed-up runs) keep the last width
    extra = np.full(max(args.speedup_flights - args.flights, 0), args.grow_to)
    paths = []
    for k, hw in enumerate(np.r_[widths, extra]):
        p = d / f"flight{k + 1:02d}.tlog"
        if not p.exists():
            eff = parse_effect(f"deadband:input={args.input},half_width={hw:.5f}")
            write_tlog(p, seed=k + 1, flights=1, effects=(eff,), flight_duration_s=args.duration_s)
        paths.append(p)
    return paths, widths


def _jobs(paths: list[Path], settings: Any, cross: bool = True) -> list:
    return [FlightJob(str(p), file_sha256(p), "bench", settings, str(paths[k - 1]) if cross and k else None)
            for k, p in enumerate(paths)]


def _scaling(paths: list[Path], settings: Any) -> tuple[list[dict], list[dict]]:
    """One in-process campaign; (rows, per-N figures)."""
    runner.warm()  # imports (those a first log triggers too) are not a flight's cost

    marks: list[dict] = []
    rows: list[dict] = []
    t0, c0 = time.perf_counter(), time.process_time()

    def on_result(job, r) -> None:
        rows.extend(r)
        n = len(rows)
        marks.append({"n": n, "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                      "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3})
        print(f"  flight {n}: {r[-1].get('seconds', float('nan')):.1f} s, verdict {r[-1].get('verdict')}, "
              f"{r[-1].get('error') or ''}", flush=True)

    runner.run(_jobs(paths, settings), workers=1, on_result=on_result)
    return rows, marks


def _default_campaign(paths: list[Path]) -> dict[str, float]:
    """``groundstation campaign`` of ``paths`` with the default configuration and workers: wall and
    CPU (the whole process tree: this process and every worker) per flight, the workers'
    start included (a user's run pays it)."""
    workers = runner.default_workers()
    jobs = _jobs(paths, Settings(config=ServiceConfig(), diagnose=True))   # as the command, before its clock
    c0, t0, b0, m0 = _tree_cpu_s(), time.perf_counter(), _machine_busy_s(), time.monotonic()
    res = runner.run(jobs, workers=workers)
    wall, cpu, busy = time.perf_counter() - t0, _tree_cpu_s() - c0, _machine_busy_s() - b0
    m1 = time.monotonic()
    n = len(paths)
    errors = [r.get("error") for rows in res for r in rows if r.get("error")]
    others = max(0.0, busy - cpu) / max(wall, 1e-9)
    cores = os.cpu_count() or 1
    print(f"  {workers} worker process(es) (every core): {wall:.1f} s wall, {cpu:.1f} s CPU for {n} flights = "
          f"{wall / n:.1f} s wall and {cpu / n:.1f} s CPU per flight; core use {cpu / (wall * cores):.0%} "
          f"(CPU / (wall x {cores} cores)); load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} cores, other work {others:.2f} cores on average (wall is a measurement only when that "
          f"is near 0){'; errors: ' + '; '.join(map(str, errors)) if errors else ''}", flush=True)
    _print_flights([r for rows in res for r in rows], cpu)
    if workers > 1:   # the pool's start and its tail, where a core waits
        print(f"    {_balance([rows[0] for rows in res if rows], m0, m1)}", flush=True)
        per_job = [sum(float(r.get("cpu_s") or 0.0) for r in res[i]) for i in runner.submission_order(jobs)]
        print(f"    {_packing(per_job, workers)}", flush=True)
    return {"workers": workers, "wall_s": wall, "cpu_s": cpu, "flights": n, "others_cores": others,
            "core_use": cpu / (wall * cores)}


def _as_a_user_runs_it(paths: list[Path], out: Path) -> dict[str, float]:
    """The whole ``groundstation campaign LOG...`` command (its imports, its workers, the trend test and
    its files), then ``groundstation identify LOG --out M.json`` of each flight separately, each a
    process of its own with the default settings: wall and CPU (the process and its workers) of
    both, and the campaign's ratio to the identify runs (what the speed target compares)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "campaign.sqlite").unlink(missing_ok=True)
    gs = [sys.executable, "-m", "groundstation"]
    camp = _timed([*gs, "campaign", *map(str, paths), "--db", str(out / "campaign.sqlite")])
    sep = [_timed([*gs, "identify", str(p), "--out", str(out / f"{p.stem}.json"), "--quiet"]) for p in paths]
    wall, cpu = sum(w for w, _ in sep), sum(c for _, c in sep)
    print(f"  the command as a user runs it (groundstation campaign of the {len(paths)} logs, trend files included): "
          f"{camp[0]:.1f} s wall, {camp[1]:.1f} s CPU; {len(paths)} separate default groundstation identify runs: "
          f"{wall:.1f} s wall, {cpu:.1f} s CPU; campaign / identify runs {camp[0] / wall:.2f}x wall, "
          f"{camp[1] / cpu:.2f}x CPU (load average {os.getloadavg()[0]:.1f}: the wall ratio is a measurement "
          f"on a quiet machine only)", flush=True)
    return {"campaign_wall_s": camp[0], "campaign_cpu_s": camp[1], "identify_wall_s": wall, "identify_cpu_s": cpu}


def _timed(cmd: list[str]) -> tuple[float, float]:
    """(wall, CPU of the process and every child it waited for) of one command run to its end."""
    r0, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
    done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if done.returncode:
        raise RuntimeError(f"{' '.join(cmd[2:4])} failed ({done.returncode}): {done.stderr.strip()[-400:]}")
    wall, r1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def _print_flights(rows: list[dict], tree_cpu_s: float) -> None:
    """Each flight's wall and CPU in its worker (identify, diagnose, its share of reading its log), and
    what the rest of the process tree took (workers' start, the cross-flight fits, a fork server where one runs)."""
    in_tasks = 0.0
    for r in rows:
        task_cpu = float(r.get("cpu_s") or 0.0)
        in_tasks += task_cpu
        wall = (r["task_end_s"] - r["task_start_s"]) if r.get("task_end_s") is not None else float("nan")
        steps = ", ".join(f"{k} {float(r[f'{k}_s']):.1f}" for k in ("read", "identify", "diagnose")
                          if r.get(f"{k}_s") is not None)
        print(f"    {r['log_name']}#{int(r.get('flight_index') or 0)}: {wall:.1f} s wall{f' ({steps})' if steps else ''}, "
              f"{task_cpu:.1f} s CPU in its worker, verdict {r.get('verdict')}", flush=True)
    print(f"    outside the flights' tasks (workers' start, cross-flight fits, a fork server where one runs): "
          f"{tree_cpu_s - in_tasks:.1f} s CPU", flush=True)


def _speedup(paths: list[Path], settings: Any) -> dict[str, dict[str, float]]:
    """Identification-only campaigns on one process, a pool and a local Dask cluster of every core.

    Warm start: the fork server that imports the analysis once (for the pool's and the cluster's
    workers alike) is started first and its cost measured once (``start`` of the first entry); each
    executor's workers are then started and warmed before its clock (``start`` of its entry). CPU is
    the whole process tree's (this process, the fork server, every worker, reaped or alive)."""
    cores = os.cpu_count() or 1
    out: dict[str, dict[str, float]] = {}
    c0, t0 = _tree_cpu_s(), time.perf_counter()
    runner.start_fork_server(dask=True)
    fork = {"wall_s": time.perf_counter() - t0, "cpu_s": _tree_cpu_s() - c0}
    print(f"  fork server (imports the analysis and Dask once for every worker): {fork['wall_s']:.1f} s wall, "
          f"{fork['cpu_s']:.1f} s CPU", flush=True)
    for label, kw in (("1 process", {"workers": 1}), (f"pool of {cores}", {"workers": cores}),
                      (f"Dask LocalCluster of {cores}", {"workers": cores, "scheduler": "local"})):
        jobs = _jobs(paths, settings, cross=False)
        c0, t0 = _tree_cpu_s(), time.monotonic()
        with runner.open_executor(**kw) as ex:
            ex.warm()
            c1, t1, b1 = _tree_cpu_s(), time.monotonic(), _machine_busy_s()
            res = runner.run(jobs, executor=ex)
            c2, t2, b2 = _tree_cpu_s(), time.monotonic(), _machine_busy_s()
        per_task = [sum(float(r.get("cpu_s") or 0.0) for r in rows) for rows in res]
        task = sum(per_task)
        faults = [sum(int(r.get("page_faults") or 0) for r in rows) for rows in res]
        order = runner.submission_order(jobs) if ex.workers != 1 else range(len(jobs))
        out[label] = {"start_wall_s": t1 - t0, "start_cpu_s": c1 - c0, "wall_s": t2 - t1, "cpu_s": c2 - c1,
                      "task_cpu_s": task, "idle_wall_s": _makespan([per_task[i] for i in order], ex.workers),
                      "others_cores": max(0.0, (b2 - b1) - (c2 - c1)) / max(t2 - t1, 1e-9)}
        print(f"  {label}: workers up and warm in {t1 - t0:.1f} s wall ({c1 - c0:.1f} s CPU); "
              f"campaign {t2 - t1:.1f} s wall, {c2 - c1:.1f} s CPU ({task:.1f} s of it in the tasks; "
              f"{np.mean(faults) / 1e3:.0f}k page faults per flight)", flush=True)
        print(f"    other work on the machine meanwhile: {out[label]['others_cores']:.2f} cores on average", flush=True)
        if ex.workers != 1:
            print(f"    {_balance([rows[0] for rows in res if rows], t1, t2)}", flush=True)
    out["fork server"] = fork
    return out


def _balance(rows: list[dict], t0_s: float, t1_s: float) -> str:
    """Each worker's busy wall time, when its first task started and its idle time at the tail (from
    the campaign's clock ``t0_s .. t1_s``, ``time.monotonic``, to each task's ``task_start_s``/``task_end_s``)."""
    busy: dict[int, list[float]] = {}
    for r in rows:
        if r.get("worker_pid") is not None:
            b = busy.setdefault(int(r["worker_pid"]), [0.0, t0_s, 0, r["task_start_s"]])
            b[0] += r["task_end_s"] - r["task_start_s"]
            b[1] = max(b[1], r["task_end_s"])
            b[2] += 1
            b[3] = min(b[3], r["task_start_s"])
    parts = [f"{n} tasks busy {w:.1f} s, the first from {first - t0_s:.1f} s, idle {t1_s - end:.1f} s at the tail"
             for w, end, n, first in busy.values()]
    return f"per worker ({t1_s - t0_s:.1f} s campaign): " + "; ".join(parts)


def _packing(task_cpu_s: list[float], workers: int) -> str:
    """What the flights' own CPU seconds (in submission order) make of the wall on an idle machine: the
    busiest worker's share against an even split, and the core time left idle at the tail. Load on
    the machine stretches the wall, not these."""
    busy, even = _makespan(task_cpu_s, workers), sum(task_cpu_s) / max(workers, 1)
    return (f"the flights' CPU handed to {workers} workers in submission order: {busy:.1f} s on the busiest "
            f"against {even:.1f} s shared evenly (on an idle machine {workers * busy - sum(task_cpu_s):.1f} core-seconds idle "
            f"at the tail; the wall is the busiest share plus the start)")


def _makespan(task_cpu_s: list[float], workers: int) -> float:
    """Wall time of the tasks on an otherwise idle machine: their own CPU seconds (in submission
    order) handed to whichever of ``workers`` frees first (what the pool and Dask's queue do)."""
    free = [0.0] * max(workers, 1)
    for c in task_cpu_s:
        k = min(range(len(free)), key=free.__getitem__)
        free[k] += c
    return max(free)


def _psutil():
    """psutil, which only this benchmark uses (an optional dependency: ``pip install 'groundstation[bench]'``)."""
    try:
        import psutil
    except ImportError:
        raise RuntimeError("groundstation bench campaign needs psutil for its CPU accounting: "
                           "pip install 'groundstation[bench]' (or pip install psutil)") from None
    return psutil


def _machine_busy_s() -> float:
    """CPU seconds every core of the machine has spent busy since boot (all processes, and time
    the hypervisor gave to other machines)."""
    t = _psutil().cpu_times()
    return float(sum(t) - t.idle - getattr(t, "iowait", 0.0) - getattr(t, "guest", 0.0) - getattr(t, "guest_nice", 0.0))


def _tree_cpu_s() -> float:
    """CPU seconds of this process and every descendant, alive or reaped (user + system)."""
    psutil = _psutil()
    me = psutil.Process()
    total = 0.0
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
        except psutil.Error:  # exited between the listing and the reading
            continue
        total += t.user + t.system + t.children_user + t.children_system
    return total


def run(args: argparse.Namespace) -> int:
    if args.flights < 2 or args.duration_s < 30:
        raise ValueError("--flights must be >= 2 and --duration-s >= 30")
    cfg = ServiceConfig().replace("identify", search_restarts=args.restarts)
    with tempfile.TemporaryDirectory() as td:
        d = args.keep or Path(td)
        d.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        paths, widths = _simulate(d, args)
        print(f"simulated {len(paths)} flights of {args.duration_s:g} s in {time.perf_counter() - t0:.0f} s; deadband on "
              f"{args.input} widening {args.grow_from:g} -> {args.grow_to:g} (normalised units)", flush=True)
        if args.default_flights > 0:
            k = min(args.default_flights, len(paths))
            print(f"0. the default campaign of {k} flights (default settings: identify with every check, diagnose, "
                  f"cross-flight fit; --jobs default):", flush=True)
            _default_campaign(paths[:k])
            _as_a_user_runs_it(paths[:k], d / "as-run")
            if args.only_default:
                return 0
        print("1. campaign in one process (identify + diagnose + cross-flight fit per flight):", flush=True)
        rows, marks = _scaling(paths[: args.flights], Settings(config=cfg, diagnose=True))
        _print_scaling(marks)
        if args.keep is not None:  # the same table `groundstation campaign DIR --vehicle bench --restarts N` reads

            store = CampaignStore(d / "bench.sqlite")
            store.put(rows)
            store.close()
        if args.speedup_flights > 0:
            k = args.speedup_flights
            print(f"2. speed-up on {k} flights (identification only; the campaign's first ones, then more of the "
                  f"last width), {os.cpu_count()} cores:", flush=True)
            sp = _speedup(paths[:k], Settings(config=cfg, diagnose=False))
            _print_speedup(sp)
        print("3. trend test over the campaign:")
        ok = [r for r in rows if not r.get("error")]
        rms = [r.get(f"input_rms_{args.input}") for r in ok]
        print(f"  {args.input} input rms per flight {np.round(np.array(rms, float), 3).tolist()} (the card's excitation)")
        _print_trends(assess_all(series(ok)), widths, args.input)
    return 0


def _print_scaling(marks: list[dict]) -> None:
    one = marks[0]
    ns = [m for m in marks if m["n"] & (m["n"] - 1) == 0 or m is marks[-1]]
    print(f"  {'N':>3} {'wall s/flight':>14} {'CPU s/flight':>13} {'peak RSS MB':>12}")
    for m in ns:
        print(f"  {m['n']:>3} {m['wall_s'] / m['n']:>14.1f} {m['cpu_s'] / m['n']:>13.1f} {m['rss_mb']:>12.0f}")
    last = marks[-1]
    per = [m["cpu_s"] / m["n"] for m in ns]
    spread = (max(per) - min(per)) / min(per) * 100
    print(f"  CPU time per flight spread {spread:.0f} % (target within 20 %): {'PASS' if spread <= 20 else 'FAIL'}")
    ratio = last["rss_mb"] / one["rss_mb"]
    print(f"  peak memory {last['n']} flights / 1 flight = {ratio:.2f} (target <= 2): {'PASS' if ratio <= 2 else 'FAIL'}")


def _print_speedup(sp: dict[str, dict[str, float]]) -> None:
    one, pool, dask = (sp[k] for k in list(sp)[:3])
    cpu_over = pool["cpu_s"] / one["cpu_s"]
    speed = one["wall_s"] / pool["wall_s"]
    print(f"  pool CPU / one process CPU {cpu_over:.2f} (the pool's overhead; 1.00 is none): "
          f"{'PASS' if cpu_over <= 1.10 else 'FAIL'} (target <= 1.10); inside the tasks "
          f"{pool['task_cpu_s'] / one['task_cpu_s']:.2f} (two flights at once share the memory bus and caches)")
    print(f"  wall speed-up pool / one process {speed:.2f}x (target >= 1.7x on two cores, needs a quiet machine): "
          f"{'PASS' if speed >= 1.7 else 'FAIL'}")
    print(f"  projected on an idle machine (each task's own CPU seconds, handed to whichever worker frees first; "
          f"a projection, not a measurement): pool {one['idle_wall_s'] / pool['idle_wall_s']:.2f}x, "
          f"Dask {one['idle_wall_s'] / dask['idle_wall_s']:.2f}x")
    fork = sp["fork server"]
    cold = (one["wall_s"] + fork["wall_s"]) / (pool["wall_s"] + pool["start_wall_s"] + fork["wall_s"])
    print(f"  with the start-up counted once (fork server) and the pool's own start: {cold:.2f}x")
    dc, dw = dask["cpu_s"] / pool["cpu_s"], dask["wall_s"] / pool["wall_s"]
    print(f"  Dask / pool: CPU {dc:.2f}, wall {dw:.2f} (targets <= 1.10): "
          f"{'PASS' if dc <= 1.10 and dw <= 1.10 else 'FAIL'}; cluster start-up {dask['start_wall_s']:.1f} s wall, "
          f"{dask['start_cpu_s']:.1f} s CPU (warm start, outside the clock)")
    others = max(one["others_cores"], pool["others_cores"])
    print(f"  other work took up to {others:.2f} cores during the runs: the wall speed-up is "
          f"{'a measurement' if others < 0.1 else 'depressed by it, not a measurement of the pool'}")
    print(f"  load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (other work depresses the wall speed-up;"
          " the CPU ratios far less)")


def _print_trends(trends: dict, widths: np.ndarray, inp: str) -> None:
    key = f"effect:deadband[{inp}].deadband"   # half-width, normalised units (the gap report's estimate)
    t = trends.get(key)
    same = f"effect:deadband[{inp}]."          # the same estimate in PWM microseconds is the same effect
    others = [k for k, tr in trends.items() if tr.changed and not k.startswith(same)]
    if widths.size < MIN_FLIGHTS_FOR_SCATTER:
        print(f"  {widths.size} flights: the change test judges from {MIN_FLIGHTS_FOR_SCATTER} on (not run)")
        return
    if t is None:
        print(f"  {key}: never estimated (the diagnosis did not score a deadband on {inp}): FAIL")
    else:
        v = t.values
        fin = np.flatnonzero(np.isfinite(v))
        dbl = next((int(i) for i in fin if v[i] > 2 * v[fin[0]]), None)
        print(f"  {key}: estimates {np.round(v, 4).tolist()} (truth {np.round(widths, 4).tolist()})")
        print(f"  exceeds twice its first estimate at flight {None if dbl is None else dbl + 1}; flagged at flight "
              f"{None if t.changed_at is None else t.changed_at + 1} ({t.kind or 'no change'}): "
              f"{'PASS' if t.changed and (dbl is None or t.changed_at <= dbl) else 'FAIL'}")
    tested = sum(tr.tested for tr in trends.values())
    print(f"  other series flagged: {others or 'none'} of {tested - bool(t is not None and t.tested)} tested: "
          f"{'PASS' if not others else 'FAIL'}")
