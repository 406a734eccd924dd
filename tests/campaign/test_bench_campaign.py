"""The campaign bench's measuring pieces: CPU of the whole process tree, and the idle-machine
projection of a pool's wall time from its tasks' CPU seconds."""

import subprocess
import sys

from groundstation.bench.campaign import _makespan, _packing, _print_flights, _tree_cpu_s


def test_tree_cpu_counts_a_finished_child_process():
    before = _tree_cpu_s()
    child = subprocess.run([sys.executable, "-c", "import time\nt = time.process_time()\n"
                            "while time.process_time() - t < 0.4: pass"], check=True)
    assert child.returncode == 0
    assert _tree_cpu_s() - before >= 0.35  # the child's 0.4 s of CPU, whatever the wall time it took


def test_timed_counts_the_workers_a_command_waits_for_and_names_a_failure():
    import pytest

    from groundstation.bench.campaign import _timed

    # a command whose CPU is in a child it starts and waits for (the campaign's workers)
    burn = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.4: pass"
    wall, cpu = _timed([sys.executable, "-c", f"import subprocess, sys; subprocess.run([sys.executable, '-c', {burn!r}])"])
    assert cpu >= 0.35 and wall >= 0.0
    with pytest.raises(RuntimeError, match="boom"):
        _timed([sys.executable, "-c", "import sys; sys.exit('boom')"])


def test_makespan_hands_each_task_to_the_first_free_worker():
    assert _makespan([4.0, 3.0, 3.0, 4.0], 2) == 8.0  # 4, then 4 | 3, then 3: in submission order
    assert _makespan([5.0, 1.0, 1.0, 1.0], 2) == 5.0
    assert _makespan([1.0, 2.0, 3.0], 1) == 6.0
    # the busiest worker has 4 + 4, the other 3 + 3: a core idles 2 s at the tail of an idle machine
    assert _packing([4.0, 3.0, 3.0, 4.0], 2) == (
        "the flights' CPU handed to 2 workers in submission order: 8.0 s on the busiest against 7.0 s shared "
        "evenly (on an idle machine 2.0 core-seconds idle at the tail; the wall is the busiest share plus the start)")


def test_trend_verdict_names_the_flagged_flight_and_skips_too_short_campaigns(capsys):
    import numpy as np

    from groundstation.bench.campaign import _print_trends
    from groundstation.trends.change import assess_all

    rng = np.random.default_rng(0)
    widths = np.linspace(0.01, 0.07, 16)
    v = widths + 0.001 * rng.standard_normal(16)
    steady = (1.0 + 0.1 * rng.standard_normal(16), np.full(16, 0.1))
    _print_trends(assess_all({"effect:deadband[lon].deadband": (v, None), "X_u": steady}), widths, "lon")
    out = capsys.readouterr().out
    doubled = int(np.flatnonzero(v > 2 * v[0])[0]) + 1
    assert f"exceeds twice its first estimate at flight {doubled}; flagged at flight" in out
    assert "(trend): PASS" in out and "other series flagged: none of 1 tested: PASS" in out
    _print_trends(assess_all({"effect:deadband[lon].deadband": (v[:2], None)}), widths[:2], "lon")
    assert "2 flights: the change test judges from 4 on (not run)" in capsys.readouterr().out


def test_balance_gives_each_workers_busy_and_tail_idle_time():
    from groundstation.bench.campaign import _balance

    rows = [{"worker_pid": 1, "task_start_s": 10.0, "task_end_s": 14.0},
            {"worker_pid": 2, "task_start_s": 11.0, "task_end_s": 13.0},   # started late (the pool's start)
            {"worker_pid": 2, "task_start_s": 13.0, "task_end_s": 16.0},
            {"worker_pid": 1, "task_start_s": 14.0, "task_end_s": 15.0},
            {"error": "x.tlog: ValueError: bad"}]   # an error row before the timing: not counted
    out = _balance(rows, 10.0, 16.5)
    assert out == ("per worker (6.5 s campaign): 2 tasks busy 5.0 s, the first from 0.0 s, idle 1.5 s at the tail; "
                   "2 tasks busy 5.0 s, the first from 1.0 s, idle 0.5 s at the tail")


def test_default_campaign_prints_each_flights_wall_and_cpu_and_the_rest(capsys):
    rows = [{"log_name": "a.tlog", "flight_index": 0, "cpu_s": 9.5, "task_start_s": 10.0, "task_end_s": 20.5,
             "verdict": "none"},
            {"log_name": "b.tlog", "flight_index": 1, "cpu_s": 8.0, "task_start_s": 11.0, "task_end_s": 19.0,
             "verdict": "deadband", "read_s": 0.3, "identify_s": 5.7, "diagnose_s": 2.0}]
    _print_flights(rows, 20.0)
    out = capsys.readouterr().out
    assert "a.tlog#0: 10.5 s wall, 9.5 s CPU" in out
    assert "b.tlog#1: 8.0 s wall (read 0.3, identify 5.7, diagnose 2.0), 8.0 s CPU" in out
    assert "verdict deadband" in out and "2.5 s CPU" in out   # 20 s of the tree less the flights' 17.5 s
