"""``--jobs``: identify and diagnose on a process pool give exactly the serial results; the
refinement's reused Jacobian array gives the same Jacobian as a fresh one."""

from __future__ import annotations

import json

import numpy as np
import pytest

from groundstation.cli import main
from groundstation.errors import GroundstationError
from groundstation.parallel import default_jobs, serial_map, worker_map


@pytest.fixture(scope="module")
def two_flights(tmp_path_factory):
    from hil_replay.sim import write_tlog

    d = tmp_path_factory.mktemp("jobs")
    paths = []
    for k in (1, 2):
        p = d / f"flight{k}.tlog"
        write_tlog(p, seed=k, flights=1, flight_duration_s=40.0)
        paths.append(p)
    return d, paths


def _square(x: int) -> int:
    return x * x


def test_worker_map_keeps_order_and_rejects_zero_jobs():
    assert default_jobs() >= 1
    with worker_map(1) as pmap:
        assert pmap is serial_map
    with worker_map(2) as pmap:
        assert pmap(_square, range(7)) == [x * x for x in range(7)]
    with pytest.raises(GroundstationError, match="--jobs 0"), worker_map(0):
        pass


_IDENTIFY_NO_PLOT = """
import sys
from groundstation.cli import main
assert main(sys.argv[1:]) == 0
print("matplotlib" in sys.modules)
"""


def test_identify_with_jobs_gives_the_serial_model(two_flights, capsys):
    """The same model with worker processes; without figures (``--no-plot``) the command does not
    import matplotlib for its workers (a fresh process, where nothing else has imported it)."""
    import subprocess
    import sys

    d, paths = two_flights
    docs = []
    for jobs in (1, 2):
        out = d / f"model_j{jobs}.json"
        argv = ["identify", *map(str, paths), "--out", str(out), "--no-plot", "--quiet", "--maxiter", "8",
                "--folds", "2", "--jobs", str(jobs)]
        if jobs == 1:
            assert main(argv) == 0, capsys.readouterr().err
        else:
            run = subprocess.run([sys.executable, "-c", _IDENTIFY_NO_PLOT, *argv], capture_output=True, text=True)
            assert run.returncode == 0, run.stderr
            assert run.stdout.split()[-1] == "False"
        docs.append(json.loads(out.read_text()))
    serial, pooled = docs
    assert pooled["parameters"] == serial["parameters"]
    assert pooled["parameter_std"] == serial["parameter_std"]
    assert pooled["fit"]["heldout"] == serial["fit"]["heldout"] and "folds" in serial["fit"]["heldout"]
    assert pooled["fit"]["evaluations"] == serial["fit"]["evaluations"]   # worker evaluations counted


def test_diagnose_with_jobs_gives_the_serial_report(two_flights, capsys):
    d, paths = two_flights
    model = d / "model_j1.json"
    if not model.exists():
        assert main(["identify", *map(str, paths), "--out", str(model), "--no-plot", "--quiet", "--maxiter", "8",
                     "--folds", "0", "--jobs", "1"]) == 0
    reports = []
    for jobs in (1, 2):
        out = d / f"gap_j{jobs}.json"
        rc = main(["diagnose", *map(str, paths), "--model", str(model), "--out", str(out), "--quiet",
                   "--jobs", str(jobs)])
        assert rc == 0, capsys.readouterr().err
        reports.append(json.loads(out.read_text()))
    assert reports[0]["tested"] and reports[1] == reports[0]


def test_reused_jacobian_array_equals_a_fresh_one():
    from benchkit.synthetic import EXAMPLE_TRUTH, simulate_flight
    from groundstation.sysid.cost import WindowedCost, Windows
    from groundstation.sysid.model import PARAM_INDEX, theta_from_dict
    from groundstation.sysid.refine import _fd_jacobian

    theta = theta_from_dict(EXAMPLE_TRUTH)
    u, _, y = simulate_flight(theta, duration_s=30.0, seed=3)
    L = 150
    W = u.shape[0] // L
    win = Windows(u[: W * L].reshape(W, L, 4), y[: W * L].reshape(W, L, 8), np.ones((W, 8), bool),
                  np.zeros(W, int), np.arange(W) * L * 0.02, 0.02)
    free = np.zeros(theta.size, bool)
    for name in ("X_u", "M_q", "L_p", "M_b", "L_a"):
        free[PARAM_INDEX[name]] = True
    cost = WindowedCost(win, free, theta)
    x = theta[free]
    h = 1e-6 * np.maximum(np.abs(x), 1e-2)
    sigma = np.ones(8)
    fresh = _fd_jacobian(cost, x, h, sigma, central=False)
    reused = _fd_jacobian(cost, x, h, sigma, central=False, reuse=True)
    np.testing.assert_array_equal(reused, fresh)
    again = _fd_jacobian(cost, x * 1.01, h, sigma, central=False, reuse=True)
    assert np.shares_memory(again, reused)              # the same array, overwritten
    assert "_jac_buffer" not in cost.__getstate__()     # not shipped to worker processes


def _parent_pid(_: int) -> int:
    import os

    return os.getppid()


def test_worker_map_workers_are_forked_from_the_shared_fork_server():
    """``identify --jobs`` workers come from the fork server that imported the analysis once (the
    campaign's pool uses the same one), not spawned and importing everything again."""
    import os
    from multiprocessing import forkserver

    with worker_map(2) as pmap:
        parents = set(pmap(_parent_pid, range(4)))
    server = forkserver._forkserver._forkserver_pid
    assert server is not None and server != os.getpid()
    assert parents == {server}


def _has_module(name: str) -> bool:
    import sys

    return name in sys.modules


def _run_alone(name: str) -> None:
    """Run this file's function ``name`` in a fresh interpreter. Whether ``fork_here`` forks from this
    process depends on no other thread running here, and an earlier test in a pytest worker may have
    left one alive (a local Dask cluster's, a zenoh session's): the check needs a process of its own."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    out = subprocess.run([sys.executable, "-c", f"import tests.test_parallel as t; t.{name}()"], cwd=root,
                         env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-4000:]


def test_identify_workers_are_forked_from_the_command_itself_after_its_imports():
    """``worker_map(..., fork_here=True)`` (identify's): the workers are this process's children and
    start with the modules it imported for them; with another thread running it keeps the fork server."""
    _run_alone("_check_forked_from_the_command")


def _check_forked_from_the_command() -> None:
    import os
    import sys
    import threading

    preload = ("numpy", "colorsys")
    sys.modules.pop("colorsys", None)
    with worker_map(2, preload, fork_here=True) as pmap:
        assert "colorsys" in sys.modules                  # imported here, before the fork
        assert set(pmap(_parent_pid, range(4))) == {os.getpid()}
        assert pmap(_has_module, ["colorsys", "colorsys"]) == [True, True]
    if sys.platform != "linux":
        return
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        with worker_map(2, preload, fork_here=True) as pmap:
            assert os.getpid() not in set(pmap(_parent_pid, range(4)))   # from the fork server
    finally:
        stop.set()
        t.join()


def _pid(_: int) -> int:
    import os

    return os.getpid()


def test_identify_counts_its_own_process_among_the_jobs():
    """``caller_works`` (identify's, which searches while its workers screen): ``jobs`` processes in all,
    the command's own and ``jobs - 1`` workers; a map from the main thread runs its last share here,
    one from another thread (a background job's, while the main thread searches) all on the workers."""
    _run_alone("_check_caller_works")


def _check_caller_works() -> None:
    import multiprocessing
    import os
    import threading

    with worker_map(3, ("numpy",), fork_here=True, caller_works=True) as pmap:
        workers = {p.pid for p in multiprocessing.active_children()}
        assert len(workers) == 2
        pids = pmap(_pid, range(6))
        assert pids[4:] == [os.getpid()] * 2 and set(pids[:4]) <= workers
        assert pmap(_square, range(7)) == [x * x for x in range(7)]
        out: list[int] = []
        t = threading.Thread(target=lambda: out.extend(pmap(_pid, range(6))))
        t.start()
        t.join()
        assert len(out) == 6 and set(out) <= workers


def _collection_faults(_: int) -> tuple[int, int, int]:
    """In a worker: the objects frozen, and the page faults of a full collection with them frozen and
    then with them back in the collector's reach (the worker is left as it was)."""
    import gc
    import resource

    def faults() -> int:
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

    frozen = gc.get_freeze_count()
    f0 = faults()
    gc.collect()
    f1 = faults()
    gc.unfreeze()
    gc.collect()
    f2 = faults()
    gc.freeze()
    return frozen, f1 - f0, f2 - f1


def test_forked_workers_collect_without_copying_the_commands_pages():
    """The objects the command holds when it forks its workers are frozen (``gc.freeze``): a full
    collection in a worker leaves the pages it shares with the command alone, where without the
    freeze it copies thousands of them; the command unfreezes them once its workers are gone."""
    import sys

    if sys.platform != "linux":
        pytest.skip("workers are forked from the command on Linux only")
    _run_alone("_check_collect_without_copying")


def _check_collect_without_copying() -> None:
    import gc

    before = gc.get_freeze_count()
    with worker_map(2, ("numpy",), fork_here=True) as pmap:
        frozen, with_freeze, without = pmap(_collection_faults, range(2))[0]
        assert gc.get_freeze_count() > before
    assert gc.get_freeze_count() == before
    assert frozen > 10_000
    assert without > 200 and with_freeze * 5 < without, (with_freeze, without)


_FAULTS = """
import resource, sys
import numpy as np
from groundstation.parallel import keep_freed_memory
keep = sys.argv[1] == "keep"
if keep:
    assert keep_freed_memory()
def rounds(n):
    for _ in range(n):   # a fit's pattern: a few MB temporaries, all freed before the next step
        xs = [np.ones(500_000) for _ in range(12)]
        del xs
rounds(1)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
rounds(5)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def test_freed_memory_is_kept_for_the_next_allocations():
    """Temporaries freed and allocated again are not returned to the system and faulted back in."""
    import subprocess
    import sys

    faults = {}
    for mode in ("default", "keep"):
        out = subprocess.run([sys.executable, "-c", _FAULTS, mode], check=True, capture_output=True, text=True)
        faults[mode] = int(out.stdout.split()[-1])
    pages = 5 * 12 * 500_000 * 8 // 4096  # every round's 48 MB faulted anew without it
    assert faults["default"] > 0.5 * pages
    assert faults["keep"] < 0.05 * pages, faults
