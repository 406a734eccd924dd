"""Runs campaign jobs in-process, on a local process pool, or on a Dask distributed cluster.

``run(jobs, workers=N, scheduler=None | "local" | "tcp://host:8786", on_result=cb)`` submits one
task per log (:func:`groundstation.campaign.job.analyse`, which reads the log by its path: only the
path crosses to a worker, and only the table rows come back) and calls ``on_result(job, rows)`` in
the calling process as each completes (in completion order; the store orders flights by date). No
job distribution of our own: a ``concurrent.futures.ProcessPoolExecutor`` on one machine, Dask's
scheduler on a cluster. With ``scheduler="local"`` a ``distributed.LocalCluster`` on loopback with
``workers`` single-threaded worker processes is started and closed here.

The pool's workers are forked from the calling process once it has imported the analysis
(:data:`groundstation.parallel.PRELOAD`; the command has imported nearly all of it already), before
any other thread starts (:func:`groundstation.parallel.fork_here_context`): a worker starts without
importing anything, its first flight costs what any other does, and no second interpreter imports
the analysis again while the cores wait. Where that is not safe (another thread runs, not Linux) and
for a local Dask cluster, the workers are forked from one fork server that has imported the analysis
once (:func:`start_fork_server`). :func:`open_executor` keeps the workers for several runs
(a bench starts and warms them once, outside its clock). With more than one worker the logs are
submitted largest first (:func:`submission_order`), so that no worker is left with a long flight
while the others have finished.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from typing import Any, Protocol

from threadpoolctl import threadpool_limits

from groundstation.campaign.job import FlightJob, Handover, _one_line, analyse_handing_over, cross_fit
from groundstation.parallel import PRELOAD as PRELOAD  # noqa: F401 - re-exported
from groundstation.parallel import fork_context, fork_here_context, frozen_for_fork, init_worker
from groundstation.parallel import warm as warm

OnResult = Callable[[FlightJob, list[dict[str, Any]]], None]
#: a finished job: its rows and what it hands back (:func:`groundstation.campaign.job.analyse_handing_over`)
Done = tuple[list[dict[str, Any]], Handover]

#: a local cluster's monitoring paced for tasks of seconds (a flight each), not milliseconds: the
#: statistical profiler (every 10 ms), the event-loop tick (20 ms) and the memory and system
#: monitors cost a worker several per cent of a core at Dask's defaults
LOCAL_DASK = {"distributed.worker.profile.enabled": False, "distributed.admin.tick.interval": "500ms",
              "distributed.worker.memory.monitor-interval": "1s", "distributed.admin.system-monitor.interval": "2s",
              "distributed.admin.system-monitor.gil.enabled": False}


def default_workers() -> int:
    """Every core: a campaign is offline work, nothing else needs a spare core (as for
    :func:`groundstation.parallel.default_jobs`; the live service keeps one for the link)."""
    return max(1, os.cpu_count() or 1)


def start_fork_server(dask: bool = False) -> Any:
    """The fork server's context (:func:`groundstation.parallel.fork_context`), with ``distributed``
    imported too when ``dask`` (for a local cluster's workers)."""
    if dask:
        import distributed.utils

        distributed.utils.get_mp_context()  # Dask's own preload list, then ours (ours wins)
    return fork_context(("distributed",) if dask else ())


class Executor(Protocol):
    workers: int

    def warm(self) -> None: ...

    def results(self, jobs: Sequence[FlightJob]) -> Iterator[tuple[int, Done]]: ...


class _Serial:
    workers = 1

    def warm(self) -> None:
        warm()

    def results(self, jobs: Sequence[FlightJob]) -> Iterator[tuple[int, Done]]:
        for i, j in enumerate(jobs):
            yield i, analyse_handing_over(j)


class _Pool:
    def __init__(self, workers: int, here: Any = None) -> None:
        """``here``: the ``fork`` context of :func:`groundstation.parallel.fork_here_context` (None: the
        fork server's)."""
        self.workers = workers
        self.pids: list[int] = []
        self.forked_here = here is not None
        self.ex = ProcessPoolExecutor(max_workers=workers, mp_context=here or start_fork_server(),
                                      initializer=init_worker)
        if here is not None:
            self.ex.submit(os.getpid)   # a ``fork`` pool forks all its workers on its first submit: now

    def warm(self) -> None:
        """Every worker started, their process ids in ``self.pids`` (one task per worker, each holding
        its worker until all have checked in: :func:`warm_task`)."""
        with tempfile.TemporaryDirectory(prefix="gs-warm-") as directory:
            self.pids = list(self.ex.map(warm_task, [(directory, self.workers)] * self.workers))

    def results(self, jobs: Sequence[FlightJob]) -> Iterator[tuple[int, Done]]:
        """Every job handed to the workers now; their results as they complete."""
        futs = {self.ex.submit(analyse_handing_over, j): i for i, j in enumerate(jobs)}
        return ((futs[f], f.result()) for f in as_completed(futs))


def warm_task(rendezvous: tuple[str, int], timeout_s: float = 60.0) -> int:
    """This worker's process id, once ``n`` workers have checked in to ``directory`` (``rendezvous``):
    a worker holds its task until then, so the pool hands each of the ``n`` tasks to another worker.
    A pool that cannot start ``n`` goes on after ``timeout_s``."""
    directory, n = rendezvous
    pid = os.getpid()
    with open(os.path.join(directory, str(pid)), "w"):
        pass
    deadline = time.monotonic() + timeout_s
    while len(os.listdir(directory)) < n and time.monotonic() < deadline:
        time.sleep(0.005)
    return pid


class _Dask:
    def __init__(self, client: Any, workers: int) -> None:
        self.client = client
        self.workers = workers

    def warm(self) -> None:
        if self.workers:
            self.client.wait_for_workers(self.workers, timeout=120)
        self.client.run(warm)

    def results(self, jobs: Sequence[FlightJob]) -> Iterator[tuple[int, Done]]:
        from distributed import as_completed

        futs = [self.client.submit(analyse_handing_over, j, pure=False, key=f"campaign-{i}-{j.sha256[:12]}")
                for i, j in enumerate(jobs)]
        index = {f.key: i for i, f in enumerate(futs)}
        return ((index[f.key], f.result()) for f in as_completed(futs))


@contextmanager
def open_executor(workers: int = 1, scheduler: str | None = None, local_processes: bool = True) -> Iterator[Executor]:
    """Workers that stay up for several :func:`run` calls (see module docstring)."""
    if workers < 1:
        raise ValueError(f"--jobs: {workers} must be >= 1")
    if scheduler:
        with _dask_client(workers, scheduler, local_processes) as (client, n):
            yield _Dask(client, n)
    elif workers == 1:
        yield _Serial()
    else:
        here = fork_here_context(PRELOAD)
        with frozen_for_fork(here is not None):   # the workers' collections leave the shared pages alone
            pool = _Pool(workers, here)
            try:
                yield pool
            finally:
                pool.ex.shutdown()


@contextmanager
def open_for(jobs: Sequence[FlightJob], workers: int = 1, scheduler: str | None = None,
             local_processes: bool = True) -> Iterator[Executor]:
    """:func:`open_executor` for one run of ``jobs``: no more local workers than jobs (one job, or
    none: this process). Open it before starting any thread (a progress bar's), so that the pool's
    workers can be forked from this process."""
    n = workers if scheduler else min(workers, max(len(jobs), 1))
    with open_executor(n, scheduler, local_processes) as ex:
        yield ex


@contextmanager
def _dask_client(workers: int, scheduler: str, local_processes: bool) -> Iterator[tuple[Any, int]]:
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError:
        raise ValueError("--scheduler needs dask distributed (pip install 'distributed>=2024.1')") from None
    cluster = None
    if scheduler == "local":
        # worker processes forked from the fork server talk tcp on loopback; in-process workers
        # (tests) use Dask's inproc comm
        net = {"host": "127.0.0.1", "scheduler_port": 0} if local_processes else {}
        if local_processes:
            start_fork_server(dask=True)
        with dask.config.set({"distributed.worker.multiprocessing-method": "forkserver", **LOCAL_DASK}):
            # silence_logs: a worker's heartbeat to a scheduler already closing is not news (a task's
            # failure comes back as its row)
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=local_processes,
                                   dashboard_address=None, silence_logs=logging.CRITICAL, **net)
        client = Client(cluster)
    elif scheduler.startswith("tcp://"):
        try:
            client = Client(scheduler, timeout="20s")
        except OSError as exc:
            raise OSError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})") from None
        workers = 0  # the cluster's own
    else:
        raise ValueError(f"--scheduler {scheduler!r}: expected 'local' or tcp://host:port")
    try:
        yield client, workers
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def submission_order(jobs: Sequence[FlightJob]) -> list[int]:
    """Indices of ``jobs`` largest log first (the longest task first: the last tasks to start are
    the short ones, and the workers finish together); equal sizes keep their order."""
    def size(i: int) -> int:
        try:
            return os.path.getsize(jobs[i].log)
        except OSError:  # analysed into an error row, quickly
            return 0

    return sorted(range(len(jobs)), key=lambda i: -size(i))


def run(jobs: Sequence[FlightJob], *, workers: int = 1, scheduler: str | None = None,
        on_result: OnResult | None = None, local_processes: bool = True,
        executor: Executor | None = None, meanwhile: Callable[[], Any] | None = None) -> list[list[dict[str, Any]]]:
    """Analyse every job; returns the rows per job in job order (see module docstring). ``executor``:
    workers opened by :func:`open_executor` (then ``workers`` and ``scheduler`` are not used).
    ``meanwhile`` is called once in this process, after the jobs have been handed to the workers, as
    soon as a worker has no job left (:func:`idle_after`): the caller's own work (imports for what it
    does after the run) then runs on a core that would otherwise idle while the last flights finish,
    instead of taking one from the workers or following the run."""
    if executor is None:
        with open_for(jobs, workers, scheduler, local_processes) as ex:
            return run(jobs, on_result=on_result, executor=ex, meanwhile=meanwhile)
    jobs = hand_over_plan(jobs)
    order = list(range(len(jobs))) if executor.workers == 1 else submission_order(jobs)
    results: dict[int, list[dict[str, Any]]] = {}
    waiting: dict[int, Done] = {}  # finished jobs waiting for their reference's prepared log
    data: dict[str, Any] = {}  # log -> prepared (None when it could not be), from the jobs that hand it over
    needed = {j.reference_log: sum(k.reference_log == j.reference_log and k.cross_by_caller for k in jobs)
              for j in jobs if j.cross_by_caller}
    completed = executor.results([jobs[i] for i in order])
    idle = idle_after(len(jobs), executor.workers)
    if meanwhile is not None and idle == 0:
        meanwhile()
    for finished, (k, done) in enumerate(completed, 1):
        i = order[k]
        if jobs[i].hand_over:
            data[jobs[i].log] = done[1].prepared
        waiting[i] = done
        for w in [w for w in waiting if not jobs[w].cross_by_caller or jobs[w].reference_log in data]:
            rows, hand = waiting.pop(w)
            if jobs[w].cross_by_caller:
                ref_log = str(jobs[w].reference_log)
                _cross_in_caller(jobs[w], rows, hand, data[ref_log])
                needed[ref_log] -= 1
                if not needed[ref_log]:
                    del data[ref_log]
            results[w] = rows
            if on_result is not None:
                on_result(jobs[w], rows)
        if meanwhile is not None and finished == idle:
            meanwhile()
    return [results[i] for i in range(len(jobs))]


def idle_after(jobs: int, workers: int) -> int:
    """How many of ``jobs`` have finished when one of ``workers`` (the caller's cores; 0: not known, a
    remote cluster) has no job left: 0 when there are fewer jobs than workers (or the workers are
    remote: the caller's core is its own), the last job with one worker."""
    return 0 if workers <= 0 or jobs < workers else jobs - workers + 1


def hand_over_plan(jobs: Sequence[FlightJob]) -> list[FlightJob]:
    """The jobs with the cross-flight fit moved to the caller wherever the reference is another job
    of the run (that job hands its prepared log over): every log is read and prepared once."""
    logs = {j.log for j in jobs}
    refs = {j.reference_log for j in jobs if j.reference_log in logs and j.reference_log != j.log}
    return [dataclasses.replace(j, cross_by_caller=j.reference_log in refs and j.reference_log != j.log,
                                hand_over=j.log in refs) for j in jobs]


def _cross_in_caller(job: FlightJob, rows: list[dict[str, Any]], hand: Handover, ref: Any) -> None:
    """The cross-flight columns of ``rows`` (in place) from the models the job handed over and the
    reference prepared by its own job (None: it could not be, no cross-flight fit, as in the job)."""
    if ref is None:
        return
    for n, r in enumerate(rows):
        model = hand.models.get(int(r.get("flight_index", 0)))
        if r.get("error") or model is None:
            continue
        try:
            with threadpool_limits(1):
                r.update(cross_fit(model, ref, str(job.reference_log)))
        except Exception as exc:  # noqa: BLE001 - as in the job: the flight's failure is its row
            keep = ("aircraft", "log", "log_name", "sha256", "settings_key", "date_utc", "date_source", "flight_index",
                    "cpu_s", "worker_pid", "task_start_s", "task_end_s", "page_faults")
            rows[n] = {**{k: r[k] for k in keep if k in r}, "error": _one_line(job, exc)}
