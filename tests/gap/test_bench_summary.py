"""``bench diagnose``: job order that keeps every kind in any prefix, and summaries of saved runs."""

import json

from groundstation.cli import main
from hil_replay.scenarios import interleave


def test_any_prefix_of_the_run_covers_every_kind_in_order():
    jobs = ([{"kind": "single", "case": i} for i in range(20)] + [{"kind": "outside", "case": 20 + i} for i in range(6)]
            + [{"kind": "combined", "case": 26 + i} for i in range(4)])
    order = interleave(jobs)
    assert sorted(j["case"] for j in order) == list(range(30))
    assert {j["kind"] for j in order[:8]} == {"single", "outside", "combined"}
    for kind in ("single", "outside", "combined"):
        cases = [j["case"] for j in order if j["kind"] == kind]
        assert cases == sorted(cases)


def _case(case, kind, truth, verdict, effects=(), sensors=()):
    return {"case": case, "kind": kind, "truth_effects": truth, "verdict": verdict,
            "truth": [{"effect": t, "input": None, "output": None, "params": {}} for t in truth],
            "effects": [{"effect": e, "input": None, "output": None, "estimate": {}, "shrink_pct": s, "score": 1.0}
                        for e, s in effects],
            "sensor_errors": list(sensors), "seconds": 10.0, "cpu_s": 5.0, "flight_s": 150.0,
            "flight": {"aircraft": "trex600", "pilot": "default", "sweeps": True, "rates": {"ATTITUDE": 25.0}}}


def test_summary_of_a_saved_run(tmp_path, capsys):
    saved = [_case(0, "single", [], "none"), _case(1, "single", ["wind_gust"], "wind_gust", [("wind_gust", 30.0)]),
             _case(2, "single", ["wind_gust"], "unexplained"),
             _case(3, "outside", ["rotor_sag"], "ground_effect", [("ground_effect", 12.0)]),
             _case(4, "combined", ["wind_gust", "deadband"], "wind_gust", [("wind_gust", 20.0), ("deadband", 5.0)])]
    path = tmp_path / "run.json"
    path.write_text(json.dumps(saved))
    assert main(["bench", "diagnose", "--from-json", str(path), "--classes", "none,wind_gust,deadband"]) == 0
    out = capsys.readouterr().out
    assert "5 cases from" in out
    assert "top-1 accuracy: 2/3" in out
    assert "false alarms on effect-free flights: 0/1" in out
    assert "unexplained or the right sensor finding 0/1; a catalogue name with shrink > 10 %: 1/1" in out
    assert "both effects named: 1/1" in out
    # 10 s of wall for 150 s of in-air data on every case
    assert "diagnosis wall per 150 s of in-air data: median 10.0 s" in out


def test_cpu_time_of_a_case_counts_its_worker_processes():
    import subprocess
    import sys

    from groundstation.bench.diagnose import tree_cpu_s

    # a child that burns a fixed amount of CPU, says so, and stays alive until its stdin closes
    code = ("import sys, time\nt = time.process_time()\nwhile time.process_time() - t < 0.5: pass\n"
            "print('done', flush=True)\nsys.stdin.read()")
    c0 = tree_cpu_s()
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == "done"
        assert tree_cpu_s() - c0 >= 0.4
    finally:
        assert child.stdin is not None
        child.stdin.close()
        child.wait()


def test_summary_of_a_missing_file_is_one_clear_error(tmp_path, capsys):
    assert main(["bench", "diagnose", "--from-json", str(tmp_path / "nope.json")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--from-json" in err[0] and "nope.json" in err[0]


def _spec(**extra):
    from hil_replay.scenarios import ScenarioSet

    return ScenarioSet(cases=10, out_of_catalogue=4, combined=3, seed=5, **extra)


def test_kinds_select_cases_without_changing_their_flights():
    from hil_replay.scenarios import select_jobs

    every = select_jobs(_spec())
    combined = select_jobs(_spec(kinds=("combined",)))
    assert [j["kind"] for j in combined] == ["combined"] * 3
    assert combined == [j for j in every if j["kind"] == "combined"]
    # nonlinear kinematics on and off are both drawn; --kinematics fixes it without moving the other draws
    assert {j["flight"]["kinematics"] for j in every} == {"linear", "nonlinear"}
    fixed = select_jobs(_spec(kinematics="linear"))
    assert {j["flight"]["kinematics"] for j in fixed} == {"linear"}
    strip = [{**j, "flight": {k: v for k, v in j["flight"].items() if k != "kinematics"}} for j in every]
    assert strip == [{**j, "flight": {k: v for k, v in j["flight"].items() if k != "kinematics"}} for j in fixed]


def test_unknown_kind_is_one_clear_error(capsys):
    assert main(["bench", "diagnose", "--kinds", "pairs"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--kinds" in err[0] and "pairs" in err[0]


def _burn(seconds: float) -> float:
    import time

    t = time.process_time()
    while time.process_time() - t < seconds:
        pass
    return seconds


def test_cpu_time_of_a_case_counts_the_workers_a_fork_server_forked():
    # --jobs workers are forked by a fork server: grandchildren of the bench process
    from groundstation.bench.diagnose import tree_cpu_s
    from groundstation.parallel import worker_map

    with worker_map(2) as pmap:
        c0 = tree_cpu_s()
        pmap(_burn, [0.3, 0.3])
        assert tree_cpu_s() - c0 >= 0.5
