"""The campaign bench's measuring pieces: CPU of the whole process tree, and the idle-machine
projection of a pool's wall time from its tasks' CPU seconds."""

import subprocess
import sys

from groundstation.bench.campaign import _makespan, _tree_cpu_s


def test_tree_cpu_counts_a_finished_child_process():
    before = _tree_cpu_s()
    child = subprocess.run([sys.executable, "-c", "import time\nt = time.process_time()\n"
                            "while time.process_time() - t < 0.4: pass"], check=True)
    assert child.returncode == 0
    assert _tree_cpu_s() - before >= 0.35  # the child's 0.4 s of CPU, whatever the wall time it took


def test_makespan_hands_each_task_to_the_first_free_worker():
    assert _makespan([4.0, 3.0, 3.0, 4.0], 2) == 8.0  # 4, then 4 | 3, then 3: in submission order
    assert _makespan([5.0, 1.0, 1.0, 1.0], 2) == 5.0
    assert _makespan([1.0, 2.0, 3.0], 1) == 6.0
