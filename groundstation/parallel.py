"""Worker processes for the independent pieces of ``identify`` and ``diagnose`` (``--jobs``).

:func:`worker_map` opens a spawned process pool and yields a *map*: ``pmap(fn, items) -> list``
with the results in the order of ``items``, exactly those of ``[fn(x) for x in items]`` (the
pieces handed to it are deterministic: log reading, the screening refinements of each search's
starts, the folds of the held-out check, the catalogue's hypotheses). The numerical packages take
such a map as an argument and never open processes themselves; without one they run serially.

``fn`` and the items must be picklable (module-level functions, :func:`functools.partial` of them).
Each item list is cut into one chunk per worker, so a large argument bound with ``partial`` (a
cost over many windows) crosses to each worker once per call, not once per item.
"""

from __future__ import annotations

import math
import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

from groundstation.errors import GroundstationError

#: ``pmap(fn, items) -> list``: a map over worker processes, or the serial one
Map = Callable[[Callable[[Any], Any], Iterable[Any]], list[Any]]


def default_jobs() -> int:
    """All cores but one (a live service keeps its core), at least one."""
    return max(1, (os.cpu_count() or 2) - 1)


def serial_map(fn: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]:
    """The map of one process."""
    return [fn(x) for x in items]


def _single_threaded() -> None:
    """Worker initializer: one BLAS/OpenMP thread per worker (the workers are the parallelism)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)


@contextmanager
def worker_map(jobs: int | None) -> Iterator[Map]:
    """A map over ``jobs`` worker processes (None: :func:`default_jobs`); 1 is the serial map."""
    n = default_jobs() if jobs is None else int(jobs)
    if n < 1:
        raise GroundstationError(f"--jobs {jobs}: must be at least 1")
    if n == 1:
        yield serial_map
        return
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_single_threaded) as ex:

        def pmap(fn: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]:
            xs = list(items)
            if len(xs) <= 1:
                return [fn(x) for x in xs]
            return list(ex.map(fn, xs, chunksize=max(1, math.ceil(len(xs) / n))))

        yield pmap
