"""Shares of the gap above the noise and effects that must hold through the flight (docs/diagnosis.md 3b)."""

import numpy as np

from groundstation.campaign.job import effect_values
from groundstation.gap.diagnose import diagnose
from groundstation.gap.shares import compute_shares
from groundstation.sysid.model import HoverModel, theta_to_dict


def test_shares_count_the_gap_above_the_noise_in_noise_units():
    W = 40
    rng = np.random.default_rng(0)
    noise = np.tile(np.array([1.0, 1.0, 4.0, 1.0, 1.0, 1.0, 1.0, 1.0]), (W, 1))
    base = noise.copy()
    base[:, 3] = 5.0  # p: 4 noise units above its floor per window
    base[:, 2] = 4.0 * 3.0  # w: 2 noise units above (its noise is 4)
    rem = np.zeros((W, 8))
    rem[:, 3] = 4.0  # the effect removes all of p's excess
    sh = compute_shares([("input_delay lat", rem)], base, noise, np.ones(8, bool), rng, n_boot=200)
    assert sh.channels == ["w", "p"]
    assert abs(sh.explained_pct - 100.0 * 4 / 6) < 1e-9  # 4 of the 6 noise units of excess
    assert sh.per_channel["p"]["explained_pct"] == 100.0 and sh.per_channel["w"]["explained_pct"] == 0.0
    lo, hi = sh.interval_pct
    assert lo <= sh.explained_pct <= hi
    # a channel at its floor carries no share
    assert "explained_pct" not in sh.per_channel["q"]
    # nothing above the noise: no share to state
    none = compute_shares([("x", rem)], noise, noise, np.ones(8, bool), rng, n_boot=50)
    assert none.explained_pct is None


def _start(paper_theta):
    th = paper_theta * (1 + 0.05 * np.random.default_rng(0).standard_normal(paper_theta.shape))
    return HoverModel(params=theta_to_dict(th))


def test_a_gyro_bias_drifting_through_the_flight_is_not_named_as_a_constant_one(flight_factory, paper_theta):
    r = diagnose(_start(paper_theta), flight_factory(T_s=90.0, seed=11, effect=("drifting_bias", 4, 0.02)), seed=0)
    assert r["verdict"] != "gyro_bias"
    assert all(e["effect"] != "gyro_bias" for e in r["effects"])
    ch = r["through_flight"]["changes"]
    assert ch and ch[0]["effect"] == "gyro_bias" and ch[0]["channel"] == "q"
    assert ch[0]["first"] < ch[0]["second"]  # the bias grows
    assert any(e["effect"] == "gyro_bias" and e["consistency"]["status"] == "changes" for e in r["partial_findings"])
    assert "changes through the flight" in r["shares"]["headline"]
    # the finding listed as partial still carries its whole-flight estimate: the campaign's trend reads it
    pf = next(e for e in r["partial_findings"] if e["effect"] == "gyro_bias")
    assert effect_values(r)["gyro_bias[q].bias_rad_s"] == pf["estimate"]["bias_rad_s"]


def test_a_delay_growing_from_nothing_is_not_named_as_a_constant_one(flight_factory, paper_theta):
    # lon delay growing from 0 at the start to 0.2 s at the end. The first half alone does not
    # resolve an input effect that starts at nothing, so the halves cannot tell it from a constant
    # one; the same effect ramping through the whole flight fits the held-out windows better
    r = diagnose(_start(paper_theta), flight_factory(T_s=90.0, seed=11, effect=("growing_delay", 1, 10)), seed=0)
    assert r["verdict"] == "unexplained" and r["effects"] == []
    ch = r["through_flight"]["changes"]
    drifting = [c for c in ch if c.get("drift", {}).get("drifts")]
    assert drifting and drifting[0]["effect"] in ("input_delay", "rate_limit") and drifting[0]["channel"] == "lon"
    assert drifting[0]["drift"]["p"] < 1e-3
    assert "changes through the flight" in r["shares"]["headline"]


def test_a_flight_too_short_to_split_says_so_and_checks_nothing(flight_factory, paper_theta):
    r = diagnose(_start(paper_theta), flight_factory(T_s=33.0, seed=12, effect=("gyro_bias", 4, 0.01)), seed=0)
    assert not r["through_flight"]["checked"]
    notes = [n for n in r["notes"] if "too short to split" in n]
    assert len(notes) == 1
    for e in r["effects"] + r["partial_findings"]:
        assert e["consistency"]["status"] == "not_checked"


def test_a_ground_effect_flown_lower_in_one_half_is_compared_where_both_halves_flew(flight_factory, paper_theta):
    # the first half hovers down to 0.3 m, the second no lower than 1.3 m: the same ground effect
    # estimated on each half alone reads as a change (each half's amplitude at its own lowest height)
    r = diagnose(_start(paper_theta), flight_factory(T_s=90.0, seed=21, effect=("ground_effect", 0.8, 0.5)), seed=0)
    assert r["verdict"] == "ground_effect"
    assert not r["through_flight"]["changes"]
    ge = next(e for e in r["effects"] if e["effect"] == "ground_effect")
    assert ge["consistency"]["status"] in ("holds", "not_checked")
    assert "where both halves flew (height down to 1.3 m)" in ge["consistency"]["why"]


def test_a_constant_deadband_on_a_short_flight_is_not_read_as_changing(tmp_path):
    # a 40-s flight of the independent simulator with a constant lon deadband (0.0153): the first half
    # moves lon mostly inside the deadband, the second swings it far outside, so each half estimates
    # the width on different excursions (0.020 and 0.006). Each half's own value must be scored as the
    # whole flight's is, chosen inside each fold (chosen on the very windows it is scored on, it beats
    # the other half's value there), and the ~0.5 s blocks of a window are not independent evidence:
    # before both, the deadband read as "changes through the flight" (p 5e-13 and 3e-3)
    from firmware_interface.readers import load_log
    from groundstation.dsp.prepare import prepare
    from hil_replay.sim import parse_effect, write_tlog

    path = tmp_path / "short.tlog"
    truth = write_tlog(path, seed=3, flights=1, effects=(parse_effect("deadband:input=lon,half_width=0.01533"),),
                       flight_duration_s=40.0)
    r = diagnose(HoverModel(params=dict(truth["parameters"])), prepare([load_log(path)]), seed=0)
    assert r["through_flight"]["checked"] and not r["through_flight"]["changes"]
    assert r["verdict"] == "deadband"
    db = r["effects"][0]
    assert db["input"] == "lon" and db["consistency"]["status"] == "holds"
    first, second = db["consistency"]["first"], db["consistency"]["second"]
    assert min(first, second) < 0.01 < 0.015 < max(first, second)  # the halves' estimates do differ
    # the test counts each half's correlated ~0.5 s blocks as fewer independent ones: the second half
    # (large lon swings, which a deadband barely changes) does not reject the first half's value
    assert db["consistency"]["p_values"]["second_rejects_other"] > 0.01


def _line_flight(amplitude, W=40, L=150, dt=0.02, f_hz=7.3, seed=5):
    """Raw residual windows (W, L, 8): white noise twice as strong in the second half (more
    manoeuvring misfit), plus a line on p whose frequency wanders by +-0.15 Hz and whose amplitude per
    window is ``amplitude(w)``."""
    from types import SimpleNamespace

    from groundstation.gap import attribute
    from groundstation.gap.fingerprints import Line
    from groundstation.gap.hypotheses import Hypothesis

    rng = np.random.default_rng(seed)
    t = np.arange(L) * dt
    resid = 0.01 * rng.standard_normal((W, L, 8))
    resid[W // 2:] *= 2.0
    for w in range(W):
        f = f_hz + 0.15 * np.sin(2 * np.pi * w / 7.0)
        resid[w, :, 3] += amplitude(w) * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    line = Line(f_hz, ["p"], 50.0, -40.0, {"p": 0.02})
    hyp = Hypothesis("rotor_vibration", estimate={"frequency_hz": f_hz}, channels=(3,), extra={"lines": [line]})
    cand = attribute.Candidate(hyp, attribute.Score(5.0, 1e-40, 1.0, 0.9, 10.0, (8.0, 12.0), {3: 10.0}), True, "")
    arrays = {"resid_raw": resid, "U": 0.1 * rng.standard_normal((W, L, 4)), "response": None,
              "line_channels": np.arange(8) >= 3, "stride": None}
    return cand, SimpleNamespace(W=W, dt_s=dt), arrays


def test_a_rotor_line_that_grows_through_the_flight_changes_and_a_steady_one_holds():
    from groundstation.gap.shares import consistency

    def check(amplitude):
        cand, ev, arrays = _line_flight(amplitude)
        return consistency(cand, ([], []), ev, np.zeros(1), 0.005, 0.5, 6, np.random.default_rng(0), 100, 0.1, arrays)

    steady = check(lambda w: 0.02)  # the rotor shakes alike all flight, while the misfit doubles
    assert steady["status"] == "holds", steady["why"]
    assert 0.8 < steady["amplitude_ratio"] < 1.25
    grows = check(lambda w: 0.01 + 0.03 * w / 40)  # a loop ringing harder as a delay grows
    assert grows["status"] == "changes", grows["why"]
    assert grows["amplitude_ratio"] > 1.5 and grows["p_values"]["strength_differs"] < 0.005
    assert "as strong in the second half" in grows["why"]


def test_a_rotor_line_one_half_does_not_show_is_not_resolved_and_not_named():
    from types import SimpleNamespace

    from groundstation.gap.config import DiagnoseConfig
    from groundstation.gap.diagnose import Decision, _drop_unresolved_lines
    from groundstation.gap.shares import consistency

    # a line in the second half only: the rotor does not shake the aircraft through the flight
    cand, ev, arrays = _line_flight(lambda w: 0.0 if w < 20 else 0.02)
    con = consistency(cand, ([], []), ev, np.zeros(1), 0.005, 0.5, 6, np.random.default_rng(0), 100, 0.1, arrays)
    assert con["status"] == "not_resolved", con["why"]
    assert con["first"] is None and con["second"] is not None and "first half" in con["why"]
    # a line that led is not named; with nothing else named and no significant gap the verdict is none
    dec = Decision("rotor_vibration", [cand], [], {}, {}, None)
    loc = SimpleNamespace(gap_significant=False, flagged_share=0.0)
    notes: list[str] = []
    left, new = _drop_unresolved_lines([cand], {id(cand): con}, dec, loc, [], DiagnoseConfig(), notes)
    assert left == [] and new.verdict == "none" and new.ranked == [] and cand in new.others
    assert len(notes) == 1 and "rotor vibration not named" in notes[0]
    # a line both halves show is left alone
    steady = {id(cand): {"status": "holds"}}
    assert _drop_unresolved_lines([cand], steady, dec, loc, [], DiagnoseConfig(), []) == ([cand], dec)
