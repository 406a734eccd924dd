"""Runs campaign jobs in-process, on a local process pool, or on a Dask distributed cluster.

``run(jobs, workers=N, scheduler=None | "local" | "tcp://host:8786", on_result=cb)`` submits one
task per log (:func:`groundstation.campaign.job.analyse`) and calls ``on_result(job, rows)`` in the
calling process as each completes (in completion order; the store orders flights by date). No job
distribution of our own: a ``concurrent.futures.ProcessPoolExecutor`` (spawned workers) on one
machine, Dask's scheduler on a cluster. With ``scheduler="local"`` a ``distributed.LocalCluster`` on
loopback with ``workers`` single-threaded worker processes is started and closed here.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

from groundstation.campaign.job import FlightJob, analyse

OnResult = Callable[[FlightJob, list[dict[str, Any]]], None]


def default_workers() -> int:
    """All cores but one (the live service keeps its core), at least one."""
    return max(1, (os.cpu_count() or 2) - 1)


def run(jobs: Sequence[FlightJob], *, workers: int = 1, scheduler: str | None = None,
        on_result: OnResult | None = None, local_processes: bool = True) -> list[list[dict[str, Any]]]:
    """Analyse every job; returns the rows per job in job order (see module docstring)."""
    if workers < 1:
        raise ValueError(f"--jobs: {workers} must be >= 1")
    results: dict[int, list[dict[str, Any]]] = {}

    def done(i: int, rows: list[dict[str, Any]]) -> None:
        results[i] = rows
        if on_result is not None:
            on_result(jobs[i], rows)

    if scheduler:
        _run_dask(jobs, workers, scheduler, done, local_processes)
    elif workers == 1 or len(jobs) <= 1:
        for i, j in enumerate(jobs):
            done(i, analyse(j))
    else:
        _run_pool(jobs, workers, done)
    return [results[i] for i in range(len(jobs))]


def _run_pool(jobs: Sequence[FlightJob], workers: int, done: Callable[[int, list], None]) -> None:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=mp.get_context("spawn")) as ex:
        futs = {ex.submit(analyse, j): i for i, j in enumerate(jobs)}
        for f in as_completed(futs):
            done(futs[f], f.result())


def _run_dask(jobs: Sequence[FlightJob], workers: int, scheduler: str, done: Callable[[int, list], None],
              local_processes: bool) -> None:
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise ValueError("--scheduler needs dask distributed (pip install 'distributed>=2024.1')") from None
    cluster = None
    if scheduler == "local":
        # worker processes talk tcp on loopback; in-process workers (tests) use Dask's inproc comm
        net = {"host": "127.0.0.1", "scheduler_port": 0} if local_processes else {}
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=local_processes,
                               dashboard_address=None, **net)
        client = Client(cluster)
    elif scheduler.startswith("tcp://"):
        try:
            client = Client(scheduler, timeout="20s")
        except OSError as exc:
            raise OSError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})") from None
    else:
        raise ValueError(f"--scheduler {scheduler!r}: expected 'local' or tcp://host:port")
    try:
        futs = [client.submit(analyse, j, pure=False, key=f"campaign-{i}-{j.sha256[:12]}") for i, j in enumerate(jobs)]
        index = {f.key: i for i, f in enumerate(futs)}
        for f in as_completed(futs):
            done(index[f.key], f.result())
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
