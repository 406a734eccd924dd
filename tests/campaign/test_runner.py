"""The runner's scheduling: largest logs submitted first to a pool, results handed back per job."""

from __future__ import annotations

from groundstation.campaign import runner
from groundstation.campaign.job import FlightJob, Settings


class _Recorder:
    """An executor that records the order it was handed the jobs in and answers at once."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.seen: list[str] = []

    def warm(self) -> None:
        pass

    def results(self, jobs):
        self.seen = [j.log for j in jobs]
        for k in reversed(range(len(jobs))):  # completion order unlike submission order
            yield k, [{"log": jobs[k].log}]


def _jobs(tmp_path, sizes):
    jobs = []
    for k, n in enumerate(sizes):
        p = tmp_path / f"f{k}.tlog"
        if n is not None:
            p.write_bytes(b"\0" * n)
        jobs.append(FlightJob(str(p), f"{k:064d}", "a", Settings()))
    return jobs


def test_a_pool_gets_the_largest_logs_first_and_results_come_back_in_job_order(tmp_path):
    jobs = _jobs(tmp_path, [10, 300, None, 300, 50])   # a missing log (an error row, quick) goes last
    assert runner.submission_order(jobs) == [1, 3, 4, 0, 2]
    pool = _Recorder(workers=2)
    done = []
    rows = runner.run(jobs, executor=pool, on_result=lambda job, r: done.append(job.log))
    assert pool.seen == [jobs[i].log for i in (1, 3, 4, 0, 2)]
    assert [r[0]["log"] for r in rows] == [j.log for j in jobs]
    assert sorted(done) == sorted(j.log for j in jobs)
    one = _Recorder(workers=1)   # one process: the given order (progress follows the user's list)
    runner.run(jobs, executor=one)
    assert one.seen == [j.log for j in jobs]
