"""The runner's scheduling: largest logs submitted first to a pool, results handed back per job."""

from __future__ import annotations

import dataclasses

from groundstation.campaign import runner
from groundstation.campaign.job import FlightJob, Handover, Settings


class _Recorder:
    """An executor that records the order it was handed the jobs in and answers at once."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.seen: list[str] = []

    def warm(self) -> None:
        pass

    def results(self, jobs):
        self.seen = [j.log for j in jobs]   # handed over at once, as the pool does
        self.jobs = list(jobs)
        return ((k, ([{"log": jobs[k].log, "flight_index": 0, "error": None}], Handover()))
                for k in reversed(range(len(jobs))))   # completion order unlike submission order


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
    # the caller's own work runs once every job is with the workers and one of them has no job left:
    # 4 of 5 jobs finished on 2 workers
    meanwhile = []
    rows = runner.run(jobs, executor=pool, on_result=lambda job, r: done.append(job.log),
                      meanwhile=lambda: meanwhile.append((len(pool.seen), len(done))))
    assert meanwhile == [(5, 4)]
    assert [runner.idle_after(n, w) for n, w in ((5, 2), (4, 2), (1, 2), (0, 2), (3, 1), (3, 0))] == [4, 3, 0, 0, 3, 0]
    assert pool.seen == [jobs[i].log for i in (1, 3, 4, 0, 2)]
    assert [r[0]["log"] for r in rows] == [j.log for j in jobs]
    assert sorted(done) == sorted(j.log for j in jobs)
    one = _Recorder(workers=1)   # one process: the given order (progress follows the user's list)
    runner.run(jobs, executor=one)
    assert one.seen == [j.log for j in jobs]


def test_a_job_scored_on_another_jobs_log_waits_for_it_and_no_log_is_prepared_twice(tmp_path):
    """The cross-flight fit of a job whose reference is another job of the run is the caller's (the
    reference's job hands its prepared log over); its rows come back once that job has finished."""
    jobs = _jobs(tmp_path, [300, 200, 100])
    jobs = [dataclasses.replace(j, reference_log=jobs[k - 1].log if k else None) for k, j in enumerate(jobs)]
    pool = _Recorder(workers=2)   # finishes the last log first: each waits for its reference
    done = []
    rows = runner.run(jobs, executor=pool, on_result=lambda job, r: done.append(job.log))
    # finished f2, f1, f0: f2 is reported once f1 has handed its log over, f1 once f0 has
    assert done == [jobs[2].log, jobs[1].log, jobs[0].log]
    assert [r[0]["log"] for r in rows] == [j.log for j in jobs]
    assert [(j.cross_by_caller, j.hand_over) for j in pool.jobs] == [(False, True), (True, True), (True, False)]
    # a reference outside the run (a log already done) is read by the job itself
    alone = [dataclasses.replace(jobs[1], reference_log=str(tmp_path / "elsewhere.tlog"))]
    assert [(j.cross_by_caller, j.hand_over) for j in runner.hand_over_plan(alone)] == [(False, False)]
