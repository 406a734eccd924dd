"""The identification chooses its configuration by held-out prediction: on the real TREX 550 log the
simulator's setting (every initial state estimated over 3-s windows) lets the yaw prediction run
away and the 5-s "predictive" setting replaces it; on a simulated flight the setting as given is
kept; bad candidate entries are one error naming the key."""

from __future__ import annotations

import pytest

from groundstation.errors import SysidError
from groundstation.sysid.identify import IdentifyConfig, identify
from groundstation.sysid.select import PRESETS, parse_candidates
from tests.realdata import real_log

#: few iterations and short refinements: the test checks the choice, not the best model
QUICK = dict(search_restarts=1, refine_max_nfev=8, refine_passes=1)


def test_candidates_parse_presets_and_overrides_and_name_bad_entries():
    c = parse_candidates("predictive; prior_scale=10, window_s=4 ;")
    assert c[0] == ("predictive", PRESETS["predictive"])
    assert c[1][1] == {"prior_scale": 10, "window_s": 4}
    with pytest.raises(SysidError, match=r"identify\.select_candidates: unknown preset 'bogus'"):
        parse_candidates("bogus")
    with pytest.raises(SysidError, match=r"identify\.select_candidates: unknown field 'windw_s'"):
        parse_candidates("windw_s=5")
    with pytest.raises(SysidError, match=r"identify\.prior_scale = -1"):
        identify(object(), config=IdentifyConfig(prior_scale=-1.0))


def test_real_log_without_aircraft_file_switches_to_the_predictive_setting():
    from pathlib import Path

    from groundstation.config import ServiceConfig
    from groundstation.pipeline import prepare_logs

    prep = prepare_logs([Path(real_log("trex550/flight1.tlog"))], ServiceConfig())
    m = identify(prep, seed=0, maxiter=6, config=IdentifyConfig(**QUICK))
    sel = m.fit.selection
    rows = {r.name: r for r in sel.candidates}
    assert sel.chosen.startswith("predictive"), rows
    pred, given = rows["predictive"], rows["as configured"]
    assert pred.significant and pred.gain > 2 * pred.gain_se > 0 and pred.round == 1
    # the second round (overlapping windows) ran because the first switched, and was judged the same way
    over = rows["window_step_s=2.5"]
    assert over.round == 2 and over.significant == (over.gain > over.gain_se and over.gain > 0)
    assert (sel.chosen == "predictive, window_step_s=2.5") == over.significant
    # the configuration as given does not predict yaw; the chosen model does, and runs away nowhere
    ho = m.fit.heldout
    assert given.channel_mean["r"] < 0 < ho.channel_mean["r"]
    assert m.fit.window_s == 5.0 and m.fit.estimate_all_initial is False
    assert ho.k == 5 and not ho.unusable_subsystems and "r" in ho.predicted
    assert ho.mean_match > given.mean_match + 10


def test_simulated_flight_keeps_the_configuration_as_given(tmp_path):
    from firmware_interface.readers import load_log
    from groundstation.dsp.prepare import prepare
    from hil_replay.sim import write_tlog

    p = tmp_path / "flight.tlog"
    write_tlog(p, seed=3, flights=1, effects=(), aircraft=None, flight_duration_s=90.0)
    m = identify(prepare([load_log(p)]), seed=0, maxiter=10, config=IdentifyConfig(**QUICK))
    sel = m.fit.selection
    assert sel.chosen == "as configured", sel.candidates
    assert [r.name for r in sel.candidates] == ["as configured", "predictive"]   # no second round
    assert m.fit.window_s == 3.0 and m.fit.estimate_all_initial is True
    assert m.fit.heldout.k == 5 and len(m.fit.heldout.folds) == 5


def test_overlapping_windows_start_every_step_and_stay_inside_their_segment():
    import numpy as np

    from groundstation.dsp.prepare import prepared_from_arrays
    from groundstation.sysid.cost import make_windows

    n = 500   # 10 s at 50 Hz
    u = np.zeros((n, 4))
    y = np.tile(np.arange(n, dtype=float)[:, None], (1, 8))
    prep = prepared_from_arrays(u, y, 0.02)
    plain = make_windows(prep.segments, prep.dt_s, 5.0)
    over = make_windows(prep.segments, prep.dt_s, 5.0, step_s=2.5)
    assert plain.count == 2 and over.count == 3
    starts = over.t0_s - over.t0_s[0]
    assert np.allclose(starts, [0.0, 2.5, 5.0])
    # each window is the contiguous data from its start, and none runs past the segment's end
    assert np.allclose(np.diff(over.outputs[:, :, 0], axis=1), np.diff(over.outputs[:1, :, 0], axis=1))
    assert over.outputs.shape[1] == 250
    with pytest.raises(SysidError, match=r"identify\.window_step_s = -1"):
        identify(prep, config=IdentifyConfig(window_step_s=-1.0))


def test_bench_heldout_reports_the_choice_the_reference_and_the_lowest_channel(tmp_path, capsys):
    """``bench heldout`` on the real log (kept short: train on the first 60 s, few iterations): both
    fits are scored on the rest, and the project's line says which configuration its own held-out
    check chose and which channels it says it does not predict."""
    import json
    from pathlib import Path

    from groundstation.cli import main

    ac = Path(__file__).resolve().parents[2] / "groundstation" / "configs" / "aircraft" / "trex550.toml"
    out = tmp_path / "h.json"
    rc = main(["bench", "heldout", str(real_log("trex550/flight1.tlog")), "--aircraft", str(ac), "--folds", "0",
               "--reference-starts", "1", "--json", str(out), "--set", "maxiter=4", "--set", "search_restarts=1",
               "--set", "refine_max_nfev=8", "--set", "select_folds=3",
               "--set", "window_input_offsets=true", "--residuals"])
    assert rc == 0
    doc = json.loads(out.read_text())
    (split,) = doc["splits"]
    sel = split["project"]["selection"]
    assert sel["chosen"] in sel["scores"] and set(sel["scores"]) == {"as configured", "predictive"}
    assert set(split["project"]["match"]) == set(split["reference"]["match"]) >= {"p", "q", "r", "theta", "phi"}
    assert 0 < sel["inv_tau_s"] and isinstance(sel["pinned"], list)
    for k in ("project", "reference"):
        assert abs(doc["summary"][k]["train_first_mean"] - split[k]["mean"]) < 1e-9
    # the project against the reference on the same held-out windows, with the windows' spread
    vs = split["versus_reference"]
    assert vs["difference"] == pytest.approx(split["project"]["mean"] - split["reference"]["mean"], abs=1e-6)
    assert vs["lo"] <= vs["difference"] <= vs["hi"] and 1 <= vs["window"] <= vs["windows"]
    # with input offsets per window (the aircraft file's default is off) the same model is also scored without them
    assert set(split["project_no_offsets"]["match"]) == set(split["project"]["match"])
    assert split["project_no_offsets"]["mean"] != split["project"]["mean"]
    # where each fit misses: per channel a noise floor above the match and band shares that add up
    for k in ("project", "reference"):
        res = split[k]["residuals"]
        assert set(res) == set(split[k]["match"])
        for c, r in res.items():
            assert abs(r["match"] - split[k]["match"][c]) < 1e-6 and r["noise_floor"] > r["match"]
            assert abs(r["drift"] + r["in_band"] + r["high"] - 100.0) < 1e-6
    printed = capsys.readouterr().out
    assert "configuration chosen by held-out prediction on the training part" in printed
    assert "where the prediction misses" in printed
    assert "project - reference:" in printed


def _rows(base, cand, base_runaway=None, cand_runaway=None):
    return [{"name": "as configured", "fold_score": base, "runaway": base_runaway or {}},
            {"name": "predictive", "fold_score": cand, "runaway": cand_runaway or {}}]


def test_a_runaway_configuration_never_wins_over_one_that_does_not():
    from groundstation.sysid.select import choose

    # the case: one catastrophic fold of the configuration swells the spread of the gain
    rows = _rows([20.0, -100.0, 25.0, 18.0, 22.0], [22.0, 30.0, 21.0, 15.0, 20.0], base_runaway={"fold 2": ["r"]})
    assert choose(rows) == 1 and rows[1]["significant"] and "runs away on fold 2 (r)" in rows[1]["reason"]
    # and a candidate that runs away never replaces one that does not, however large its mean gain
    rows = _rows([20.0, 20.0, 20.0, 20.0, 20.0], [60.0, 60.0, 60.0, 60.0, 19.0], cand_runaway={"fold 5": ["w"]})
    assert choose(rows) == 0 and not rows[1]["significant"]


def test_a_candidate_better_on_every_fold_wins_even_with_a_wide_spread():
    from groundstation.sysid.select import choose

    rows = _rows([-90.0, 20.0, 20.0, 20.0, 20.0], [30.0, 21.0, 20.5, 21.0, 20.2])
    assert rows and choose(rows) == 1 and rows[1]["gain_folds"] == 5
    rows = _rows([20.0, 20.0, 20.0, 20.0, 20.0], [21.0, 19.0, 20.5, 20.0, 20.2])  # inside the noise
    assert choose(rows) == 0


def test_with_workers_the_selection_is_the_serial_one():
    """With any map but the serial one the configuration's folds run on a background thread while the
    candidates are fitted, and the candidates' folds queue behind them: the same report and model as
    one after the other (a 12-s flight: folds too short to refit give no score, NaN in both)."""
    import json

    from benchkit.synthetic import EXAMPLE_TRUTH, simulate_flight
    from groundstation.dsp.prepare import prepared_from_arrays
    from groundstation.parallel import serial_map
    from groundstation.sysid.identify import fit_candidate, refit
    from groundstation.sysid.model import HoverModel, theta_from_dict
    from groundstation.sysid.select import select_config

    u, _, ym = simulate_flight(theta_from_dict(EXAMPLE_TRUTH), 12.0, seed=5)
    prep = prepared_from_arrays(u, ym, 0.02)
    model0 = identify(prep, seed=0, maxiter=2, config=IdentifyConfig(search_restarts=1, refine_max_nfev=3,
                                                                    refine_passes=1, select_folds=0))
    cfg = IdentifyConfig(**{**QUICK, "refine_max_nfev": 3})

    def in_process(fn, xs):   # not the serial map: the selection takes its path for worker processes
        return [fn(x) for x in xs]

    out = [select_config(prep, HoverModel.from_json(model0.to_json()), cfg, pmap=pmap, fit=fit_candidate,
                         refit=refit).to_json() for pmap in (serial_map, in_process)]
    assert [r["name"] for r in out[0]["fit"]["selection"]["candidates"]] == ["as configured", "predictive"]
    assert json.dumps(out[0], sort_keys=True) == json.dumps(out[1], sort_keys=True)
