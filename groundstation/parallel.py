"""Worker processes for the independent pieces of ``identify``, ``diagnose`` and ``campaign`` (``--jobs``).

:func:`worker_map` opens a process pool and yields a *map*: ``pmap(fn, items) -> list`` with the
results in the order of ``items``, exactly those of ``[fn(x) for x in items]`` (the pieces handed to
it are deterministic: log reading, the screening refinements of each search's starts, the folds of
the held-out check, the catalogue's hypotheses). The numerical packages take such a map as an
argument and never open processes themselves; without one they run serially.

``fn`` and the items must be picklable (module-level functions, :func:`functools.partial` of them).
Each item list is cut into one chunk per worker, so a large argument bound with ``partial`` (a
cost over many windows) crosses to each worker once per call, not once per item.

Every local worker (``worker_map``'s, the campaign's process pool and its local Dask cluster) is
forked from one fork server per calling process that has imported the analysis once
(:data:`PRELOAD`, :func:`fork_context`): a worker starts without importing anything and its first
task costs what any other does. ``identify``'s workers are forked from the command's own process
instead (``worker_map(..., fork_here=True)``, :func:`fork_here_context`), which has imported most of
it already: no second interpreter imports the analysis again; its ``--jobs`` counts the command's own
process, which searches while its workers screen (``caller_works=True``). Workers and the serial path alike run numerical work with one
BLAS thread (the workers are the parallelism) and with freed memory kept for reuse
(:func:`keep_freed_memory`).
"""

from __future__ import annotations

import ctypes
import functools
import gc
import importlib
import math
import multiprocessing
import os
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from multiprocessing import forkserver
from typing import Any

from threadpoolctl import threadpool_limits

from groundstation.errors import GroundstationError

#: ``pmap(fn, items) -> list``: a map over worker processes, or the serial one
Map = Callable[[Callable[[Any], Any], Iterable[Any]], list[Any]]

#: every module the analysis imports, including those imported lazily on the first log (readers,
#: the MAVLink dialect, the configuration selection, the diagnosis): imported once by the fork server
PRELOAD = ("numpy", "scipy.optimize", "threadpoolctl", "pymavlink.dialects.v20.ardupilotmega",
           "firmware_interface.readers", "groundstation.campaign.job", "groundstation.pipeline",
           "groundstation.dsp.split", "groundstation.dsp.velocity_check", "groundstation.sysid.select",
           "groundstation.sysid.heldout", "groundstation.gap.diagnose")
#: what ``identify``'s workers need without the figures (``--no-plot``; no diagnosis), imported by the
#: command before it forks them (:func:`fork_here_context`; a fork server would import them in about
#: 1 s of CPU, what :data:`PRELOAD` imports in 1.5 s); not scipy.optimize (0.3 s): its differential
#: evolution runs in the command's own process, with the searches
IDENTIFY_NO_PLOT_PRELOAD = ("numpy", "threadpoolctl", "pymavlink.dialects.v20.ardupilotmega",
                            "firmware_interface.readers", "groundstation.pipeline", "groundstation.dsp.split",
                            "groundstation.dsp.velocity_check", "groundstation.sysid.identify",
                            "groundstation.sysid.select", "groundstation.sysid.heldout")
#: the same with matplotlib (0.3 s), for the figures ``identify``'s workers draw
IDENTIFY_PRELOAD = IDENTIFY_NO_PLOT_PRELOAD + ("matplotlib.figure", "matplotlib.backends.backend_agg",
                                               "groundstation.sysid.plots")

# glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
#: blocks below this come from the heap (glibc's own dynamic threshold stops at the same 32 MiB)
MMAP_THRESHOLD_BYTES = 32 << 20
#: free memory at the top of the heap kept for the next allocations instead of returned to the system
TRIM_THRESHOLD_BYTES = 128 << 20
TOP_PAD_BYTES = 16 << 20


def default_jobs() -> int:
    """Every core: the campaign and the benchmarks are offline work. The live service does not use
    this: it analyses each flight in one worker process of its own and keeps the other cores for
    the link."""
    return max(1, os.cpu_count() or 1)


def spare_core_jobs() -> int:
    """All cores but one, at least one: the default of ``identify``, ``diagnose`` and ``report``; one
    core stays free for the link between flights. On 2 cores that is one process: ``identify`` of a
    175-s simulated flight costs about 0.45 s less CPU than with a worker (4.5 against 5.0 s) for
    about 0.5 s more wall; the diagnosis's workers need the whole diagnosis imported, which a 150-s
    flight's catalogue scans do not win back."""
    return max(1, (os.cpu_count() or 2) - 1)


def serial_map(fn: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]:
    """The map of one process."""
    return [fn(x) for x in items]


@functools.cache
def keep_freed_memory() -> bool:
    """Keep freed heap memory in this process for the next allocations (glibc; False elsewhere).

    The fits allocate and free temporaries of a few MB thousands of times; by default glibc hands
    the top of the heap back to the system whenever 2x its adaptive threshold is free and takes
    it again on the next allocation, each page faulted and zeroed anew: about 70 000 page faults
    (~300 MB) per flight, some 7 % of a flight's CPU and more with two workers sharing the memory
    bus. With these settings a process keeps up to :data:`TRIM_THRESHOLD_BYTES` of freed heap: the
    peak memory is unchanged, it is only not returned between allocations."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (macOS, Windows)
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return all(mallopt(p, v) == 1 for p, v in ((_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES),
                                                (_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
                                                (_M_TOP_PAD, TOP_PAD_BYTES)))


def warm(preload: tuple[str, ...] = PRELOAD) -> int:
    """Import ``preload`` in this process and keep freed memory (a worker's initializer; the
    imports are free when forked from a fork server that imported the same); returns the process id."""
    for m in preload:
        importlib.import_module(m)
    keep_freed_memory()
    return os.getpid()


def init_worker(preload: tuple[str, ...] = PRELOAD) -> None:
    """Worker initializer: :func:`warm` (with the fork server's ``preload``: a module the server did
    not import would be imported by every worker), and one BLAS/OpenMP thread per worker (the
    workers are the parallelism)."""
    warm(preload)
    threadpool_limits(1)


def fork_context(extra: tuple[str, ...] = (), *, preload: tuple[str, ...] = PRELOAD, wait: bool = True) -> Any:
    """The ``forkserver`` multiprocessing context, its server started with ``extra`` and ``preload``
    imported unless it already runs (``spawn`` where there is no fork server). The import is paid
    once per calling process, whatever the number of workers, pools and runs. ``wait=False``
    returns at once: the server imports while this process works, and the first worker starts
    when it is done."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")

    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload([*extra, *preload])
    forkserver.ensure_running()
    if wait:
        p = ctx.Process(target=os.getpid)  # answered once the server has imported everything
        p.start()
        p.join()
    return ctx


def fork_here_context(preload: tuple[str, ...]) -> Any | None:
    """The ``fork`` context for workers forked from this process once it has imported ``preload``:
    they start with every module and setting this process has, and nothing is imported twice (a
    fork server is a second interpreter importing the same modules: about 1 s of CPU for
    :data:`IDENTIFY_PRELOAD`). None where that is not safe: off Linux (macOS frameworks do not
    survive a fork), or while another thread runs here (the child would inherit the locks it holds)."""
    if sys.platform != "linux" or threading.active_count() > 1:
        return None
    warm(preload)
    return multiprocessing.get_context("fork")


@contextmanager
def frozen_for_fork(freeze: bool = True) -> Iterator[None]:
    """Every object this process holds now moved out of the garbage collector's reach (``gc.freeze``)
    while workers forked from it share its pages; back (``gc.unfreeze``) once they are gone.

    After a fork, parent and workers share the parent's memory pages until one of them writes to a
    page, which the kernel then copies (a page fault). A full collection writes to every object it
    tracks, so without this the first full collection in either process copies every page holding
    the imported modules' objects (4 800 page faults and 0.05 s in an ``identify`` of a 175-s flight:
    the command's process, once, while its workers run). Frozen objects are never collected; those
    present before a fork are the imported modules', which live as long as the process anyway."""
    if not freeze:
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


@contextmanager
def worker_map(jobs: int | None, preload: tuple[str, ...] = PRELOAD, *, fork_here: bool = False,
               caller_works: bool = False) -> Iterator[Map]:
    """A map over ``jobs`` worker processes (None: :func:`default_jobs`); 1 is the serial map (in
    this process, which then keeps freed memory like a worker). The fork server (importing
    ``preload``) starts at once but in the background; the workers start with the first map of
    more than one item, so a command that fails early, or maps nothing, starts none.

    ``fork_here=True``: the workers are forked from this process at once, after it has imported
    ``preload`` (:func:`fork_here_context`; the fork server where that is not safe), before any other
    thread starts (a progress bar's, a background job's).

    ``caller_works=True``: this process works alongside its workers (``identify`` searches in it while
    they screen and refine), so ``jobs`` counts it: ``jobs - 1`` workers, one busy process per core
    rather than one more than there are cores. A map called from the main thread, which would only
    wait for it, runs its last share of the items here while the workers run the rest.

    This process, too, runs with one BLAS thread while the map is open: the products are small
    enough that a second BLAS thread saves little wall time and costs CPU (measured on ``diagnose``
    of a 150-s flight: 3.5 s CPU with one thread, 6.4 s with two, and more wall time on a loaded
    machine)."""
    n = default_jobs() if jobs is None else int(jobs)
    if n < 1:
        raise GroundstationError(f"--jobs {jobs}: must be at least 1")
    keep_freed_memory()
    if n == 1:
        with threadpool_limits(1):
            yield serial_map
        return
    here = fork_here_context(preload) if fork_here else None
    ctx = here or fork_context(preload=preload, wait=False)
    workers = n - 1 if caller_works else n
    with threadpool_limits(1), frozen_for_fork(here is not None), \
            ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=init_worker,
                                initargs=(preload,)) as ex:
        if here is not None:
            ex.submit(os.getpid)   # with ``fork`` the pool forks all its workers on the first submit: now

        def pmap(fn: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]:
            xs = list(items)
            if len(xs) <= 1:
                return [fn(x) for x in xs]
            mine = caller_works and threading.current_thread() is threading.main_thread()
            size = max(1, math.ceil(len(xs) / (workers + mine)))
            cut = min(len(xs), size * workers) if mine else len(xs)
            theirs = ex.map(fn, xs[:cut], chunksize=size)   # submitted now; this process runs the rest meanwhile
            ours = [fn(x) for x in xs[cut:]]
            return list(theirs) + ours

        yield pmap
