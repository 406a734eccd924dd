"""identify() on a short closed-loop flight of the linear model with known truth; validate metrics."""

from __future__ import annotations

import numpy as np
import pytest

from benchkit.synthetic import EXAMPLE_TRUTH, simulate_flight
from groundstation.dsp.prepare import prepared_from_arrays
from groundstation.sysid.heldout import predict
from groundstation.sysid.identify import identify
from groundstation.sysid.model import PARAM_NAMES, HoverModel, theta_from_dict
from groundstation.sysid.validate import match_degree, nrmse, pearson, theil_u, validate

KEY = ("M_a", "L_b", "inv_tau_s", "A_lat", "B_lon", "Z_col", "N_ped", "N_r")


@pytest.fixture(scope="module")
def flights():
    th = theta_from_dict(EXAMPLE_TRUTH)
    u, _, ym = simulate_flight(th, 90.0, seed=11)
    u2, _, ym2 = simulate_flight(th, 60.0, seed=12)
    return th, prepared_from_arrays(u, ym, 0.02), prepared_from_arrays(u2, ym2, 0.02)


@pytest.fixture(scope="module")
def model(flights):
    _, train, _ = flights
    return identify(train, seed=0, maxiter=80)


def test_identify_recovers_key_parameters(model):
    for name in KEY:
        assert model.params[name] == pytest.approx(EXAMPLE_TRUTH[name], rel=0.10), name


def test_parameters_within_three_reported_standard_errors(model):
    z = []
    for name in PARAM_NAMES:
        s = model.parameter_std[name]
        assert s is not None and s > 0, name
        z.append((model.params[name] - EXAMPLE_TRUTH[name]) / s)
    z = np.abs(np.array(z))
    assert np.all(z < 4.0), dict(zip(PARAM_NAMES, z.round(2), strict=True))
    assert np.mean(z < 3.0) >= 0.9


def test_model_file_roundtrip_and_fit_fields(model):
    doc = model.to_json()
    back = HoverModel.from_json(doc)
    assert back.params == model.params
    assert doc["fit"]["algorithm"] == "cabc" and doc["fit"]["evaluations"] > 0
    assert set(doc["fit"]["match_degree"]) == {"u", "v", "w", "p", "q", "r", "theta", "phi"}
    assert doc["fit"]["refined"] is True
    assert doc["pinned_at_bound"] == []


def test_identified_matches_truth_on_another_flight(flights, model):
    th, _, other = flights
    truth = HoverModel(params=dict(EXAMPLE_TRUTH))
    v_id = validate(model, other)
    v_true = validate(truth, other)
    assert v_id.mean_match >= 0.99 * v_true.mean_match
    assert set(v_id.channels) == set(v_true.channels)


def test_fit_section_and_validation_are_typed_and_round_trip_unchanged(flights, model):
    """The fit section and the validation read as frozen objects and write back the same JSON, key
    for key and in order (the file formats do not change)."""
    import dataclasses
    import json

    from groundstation.analysis import held_out
    from groundstation.config import ServiceConfig
    from groundstation.sysid.fit_section import HeldOut, ModelFit
    from groundstation.sysid.validate import ChannelScore, Validation

    _, train, other = flights
    assert isinstance(model.fit, ModelFit)   # the model's own section is the typed one
    m = HoverModel.from_json(model.to_json())
    m.fit = m.fit.set(heldout=HeldOut.make(skipped="not checked here"), usable=True, closed_loop=["a note"])
    doc = json.loads(json.dumps(m.to_json()))["fit"]
    assert list(doc)[-3:] == ["heldout", "usable", "closed_loop"]   # new keys after the others, as set
    fit = ModelFit.from_json(doc)
    assert fit == m.fit and fit.algorithm == "cabc" and fit.evaluations == doc["evaluations"] > 0
    assert fit.channels == tuple(doc["channels"]) and fit.closed_loop == ("a note",) and fit.usable is True
    assert fit.heldout == HeldOut(skipped="not checked here") and fit.history == doc["history"]
    assert json.dumps(fit.to_json()) == json.dumps(doc)
    assert fit.seconds is None and doc["seconds"] is None   # a null the identification writes stays in the file
    with pytest.raises(dataclasses.FrozenInstanceError):
        fit.usable = False  # type: ignore[misc]
    with pytest.raises(TypeError, match="no field sekonds"):
        fit.set(sekonds=1.0)   # a misspelt key never reaches a file
    # an unknown key from a newer file is kept, in its place; without() drops a key
    newer = ModelFit.from_json({"algorithm": "cabc", "future": {"x": 1}, "seconds": 2.0})
    assert newer.extra == {"future": {"x": 1}} and list(newer.to_json()) == ["algorithm", "future", "seconds"]
    assert newer.without("seconds", "future").to_json() == {"algorithm": "cabc"}
    # a held-out check that ran (two folds of the short flight, few iterations)
    m2 = HoverModel.from_json(model.to_json())
    cfg = ServiceConfig().replace("identify", refine_passes=1, refine_max_nfev=10, heldout_window_s=4.0)
    ho = held_out(m2, train, cfg, None, 2)
    assert ho == m2.fit.heldout and ho.k == 2 and len(ho.folds) == 2 and ho.mean_match is not None
    assert ho.window_s == 4.0   # [identify] heldout_window_s
    assert m2.fit.usable is (not ho.unusable_subsystems)
    again = HoverModel.from_json(json.loads(json.dumps(m2.to_json())))
    assert again.fit == m2.fit and json.dumps(again.to_json()) == json.dumps(m2.to_json())
    # a model whose predictions estimate per-window input offsets says so in its file, and predicts
    # the held-out data at least as well as without them (more per-window unknowns, same model)
    assert "window_input_offsets" not in m2.to_json()
    per_window = HoverModel.from_json(m2.to_json() | {"window_input_offsets": True})
    assert per_window.window_input_offsets and per_window.to_json()["window_input_offsets"] is True
    assert predict(per_window, other).mean_match > predict(m2, other).mean_match - 1.0

    v = validate(model, other, return_series=True)
    assert isinstance(v.channels["q"], ChannelScore) and v.series is not None and v.series["y"].ndim == 3
    vd = json.loads(json.dumps(v.to_json()))
    assert "series" not in vd and list(vd) == ["channels", "mean_match", "mean_fit", "cost", "windows", "window_s",
                                               "duration_s", "channels_used"]
    assert list(vd["channels"]["q"]) == ["match", "fit", "tic", "corr"]
    again = Validation.from_json(vd)
    assert again == v and json.dumps(again.to_json()) == json.dumps(vd)


def test_a_model_file_of_the_version_before_the_typed_fit_reads_and_writes_back_unchanged():
    """A model file written before ``HoverModel.fit`` was typed (``identify`` of a simulated flight with
    a lon input delay) reads into the typed section and writes back byte for byte."""
    import json
    from pathlib import Path

    from groundstation.jsonio import dumps
    from groundstation.sysid.fit_section import CandidateScore, HeldOut, ModelFit, PriorReport, Selection

    text = (Path(__file__).parents[1] / "data" / "models" / "sim-seed5-identify.json").read_text()
    doc = json.loads(text)
    m = HoverModel.from_json(doc)
    assert isinstance(m.fit, ModelFit) and isinstance(m.fit.heldout, HeldOut) and not m.fit.extra
    assert m.fit.heldout.k == 5 and m.fit.usable is doc["fit"]["usable"]
    # the nested sections are typed too: the selection with its candidate rows, the (empty) prior report
    sel = m.fit.selection
    assert isinstance(sel, Selection) and sel.chosen == "as configured" and sel.k == 5 and not sel.extra
    base, pred = sel.candidates
    assert isinstance(pred, CandidateScore) and not base.extra and not pred.extra
    assert base.gain is None and pred.gain < 0 and pred.significant is False and pred.runaway == {"fold 3": ["u", "p", "q"]}
    assert pred.fold_score == tuple(doc["fit"]["selection"]["candidates"][1]["fold_score"])
    assert isinstance(m.fit.prior, PriorReport) and m.fit.prior.to_json() == {} and m.fit.has("prior")
    assert dumps(m.to_json(), indent=1) == text   # as identify writes it


def test_structure_choice_and_prior_report_are_typed_and_round_trip_unchanged():
    """The structure comparison (candidates with gains, a refitted winner's ``final`` row) and a prior
    report written as dicts by the producers read into their sections and write back key for key."""
    import json

    from groundstation.sysid.fit_section import CandidateScore, ModelFit, PriorReport, StructureChoice

    rows = [{"name": "hover (blade inputs)", "fold_score": [10.0, 20.0], "mean_match": 15.0, "runaway": {}},
            {"name": "command response (rate_command)", "fold_score": [30.0, 40.0], "mean_match": 35.0,
             "runaway": {}, "gain": 20.0, "gain_se": 0.0, "gain_folds": 2, "significant": True,
             "final": {"name": "command response (rate_command)", "fold_score": [31.0, 41.0], "mean_match": 36.0}}]
    choice = {"chosen": "command_response", "candidates": rows, "reason": "predicts better"}
    prior = {"source": "trex550.toml", "determined": ["X_u"], "prior_dominated": ["Z_w"], "on_bound": [],
             "fixed_at_prior": ["A_lat"], "prior_share": {"X_u": 0.1, "Z_w": 0.9}, "nominal": {"X_u": -0.1},
             "std": {"X_u": 0.05}, "from_a_newer_version": 1}
    fit = ModelFit.make(algorithm="cabc", structure_choice=choice, prior=prior)
    sc, pr = fit.structure_choice, fit.prior
    assert isinstance(sc, StructureChoice) and sc.chosen == "command_response" and sc.reason == "predicts better"
    assert isinstance(sc.candidates[1].final, CandidateScore) and sc.candidates[1].final.mean_match == 36.0
    assert sc.candidates[1].significant is True and sc.candidates[0].gain is None
    assert isinstance(pr, PriorReport) and pr.prior_dominated == ("Z_w",) and pr.extra == {"from_a_newer_version": 1}
    doc = {"algorithm": "cabc", "structure_choice": choice, "prior": prior}
    assert json.dumps(fit.to_json()) == json.dumps(doc)
    assert json.dumps(ModelFit.from_json(doc).to_json()) == json.dumps(doc)
    assert ModelFit.from_json(doc) == fit


def test_pinned_parameters_are_flagged(flights):
    _, train, _ = flights
    from groundstation.aircraft import wide_prior

    m = identify(train, seed=1, maxiter=30, bounds={"M_a": (10.0, 40.0)}, prior=wide_prior())
    assert "M_a" in m.pinned
    assert "search bound" in m.fit.pinned_reasons["M_a"]
    # not an estimate: neither "determined" nor "held near the prior", but on a bound
    pr = m.fit.prior
    assert "M_a" in pr.on_bound and "M_a" not in pr.determined + pr.prior_dominated


def test_a_bound_reason_names_the_parameter_it_trades_off_with():
    """Two parameters whose effects on the outputs are nearly the same: the one on a bound is reported
    with the other (and the correlation's sign); an independent one is not named."""
    from types import SimpleNamespace

    from groundstation.sysid.identify import _pinned, _Run, record_tradeoffs
    from groundstation.sysid.model import N_PARAMS, PARAM_INDEX, bounds_array

    rng = np.random.default_rng(0)
    a, c = rng.normal(size=400), rng.normal(size=400)
    J = np.column_stack([a, a + 0.05 * rng.normal(size=400), c])   # M_q, M_a nearly collinear; L_p not
    sub_free = np.zeros(N_PARAMS, dtype=bool)
    names = ("M_q", "M_a", "L_p")
    sub_free[[PARAM_INDEX[n] for n in names]] = True
    order = np.argsort([PARAM_INDEX[n] for n in names])
    run = _Run(theta=np.zeros(N_PARAMS))
    record_tradeoffs(run, sub_free, SimpleNamespace(jac=J[:, order]), None)
    b = bounds_array()
    theta = np.zeros(N_PARAMS)
    theta[PARAM_INDEX["M_q"]] = b[PARAM_INDEX["M_q"], 0]
    theta[PARAM_INDEX["L_p"]] = b[PARAM_INDEX["L_p"], 1]
    why = _pinned(theta, sub_free, b, run.partner)
    assert set(why) == {"M_q", "L_p"}
    assert "trades off with M_a (correlation -" in why["M_q"]   # same effect: the estimates anti-correlate
    assert "trades off" not in why["L_p"] and "lower search bound" in why["M_q"]


def test_missing_velocities_fix_their_parameters():
    th = theta_from_dict(EXAMPLE_TRUTH)
    u, _, ym = simulate_flight(th, 40.0, seed=5)
    ym[:, 0:3] = np.nan
    u[:, 0] = 0.0  # lateral cyclic never moves (like the TREX 550 log)
    p = prepared_from_arrays(u, ym, 0.02)
    m = identify(p, seed=0, maxiter=20, refine=False)
    for name in ("X_u", "Y_v", "Z_w", "A_lat", "L_lat"):
        assert name in m.fit.fixed and m.params[name] == 0.0
    assert set(m.fit.match_degree) == {"p", "q", "r", "theta", "phi"}


def test_metrics_on_known_values():
    y = np.array([1.0, -1.0, 2.0, -2.0])
    assert match_degree(y, y) == pytest.approx(100.0)
    assert match_degree(np.zeros(4), y) == pytest.approx(0.0)
    assert match_degree(0.5 * y, y) == pytest.approx(50.0)
    assert nrmse(y, y) == pytest.approx(100.0)
    assert nrmse(np.full(4, y.mean()), y) == pytest.approx(0.0)
    assert theil_u(y, y) == pytest.approx(0.0)
    assert theil_u(-y, y) == pytest.approx(1.0)
    assert pearson(0.5 * y + 3.0, y) == pytest.approx(1.0)  # blind to gain and offset: never alone
    assert pearson(-y, y) == pytest.approx(-1.0)
    assert pearson(np.zeros(4), y) == 0.0


def test_search_restarts_keep_the_lowest_refined_cost(flights):
    """Independent searches: the first is the single search (same seed, same stream), the model kept
    is the one with the lowest refined cost, so restarts can only lower it."""
    from groundstation.sysid.identify import IdentifyConfig

    _, train, _ = flights
    quick = dict(refine_max_nfev=10, refine_passes=1)
    one = identify(train, seed=2, maxiter=3, config=IdentifyConfig(search_restarts=1, **quick))
    three = identify(train, seed=2, maxiter=3, config=IdentifyConfig(search_restarts=3, **quick))
    assert three.fit.cost <= one.fit.cost * (1 + 1e-8)   # (the same search refined again: rounding)
    assert three.fit.iterations > one.fit.iterations   # the extra searches did run
    assert set(three.fit.search_algorithm_by_subsystem.values()) <= {"cabc", "de"}
    assert one.fit.search_algorithm_by_subsystem == {"horizontal": "cabc", "vertical": "cabc"}
    with pytest.raises(ValueError, match="restart_algorithm"):
        identify(train, seed=2, maxiter=3, config=IdentifyConfig(search_restarts=2, restart_algorithm="pso"))


def test_a_search_that_screened_down_to_an_earlier_searchs_start_is_not_refined_again():
    """Searches whose screened winners are the same start (by the starts' own distance) with scores within
    their sampling spread share one full refinement; a score beyond the spread (a wrong basin shows as
    one), a far start or a single start's undefined score keeps its own."""
    from groundstation.sysid.identify import _same_winners

    span = np.full(4, 2.0)
    x = np.array([0.1, -0.3, 0.5, 0.2])
    near = x + np.array([0.02, -0.02, 0.0, 0.01])
    far = x + np.array([0.0, 0.0, 1.5, 0.0])   # one parameter across its range: RMS 0.375
    assert _same_winners([(x, 1.0), (x.copy(), 1.0)], span, 0.2, 0.01) == [0, 0]
    assert _same_winners([(x, 1.0), (near, 1.005)], span, 0.2, 0.01) == [0, 0]
    assert _same_winners([(x, 1.0), (near, 1.02)], span, 0.2, 0.01) == [0, 1]
    assert _same_winners([(x, 1.0), (far, 1.0)], span, 0.2, 0.01) == [0, 1]
    assert _same_winners([(x, float("nan")), (x, float("nan"))], span, 0.2, 0.01) == [0, 1]
    assert _same_winners([(x, 1.0), (far, 1.0), (near, 1.0)], span, 0.2, 0.01) == [0, 1, 0]


def test_the_sampling_spread_counts_the_costs_residual_samples(flights):
    """sqrt(2 / N), N the used channels' samples of every window; samples lost in link holes do not count."""
    from dataclasses import replace
    from types import SimpleNamespace

    from groundstation.sysid.cost import make_windows
    from groundstation.sysid.identify import _relative_spread

    _, train, _ = flights
    w = make_windows(train.segments, train.dt_s, 3.0)
    used = np.zeros(8, dtype=bool)
    used[[3, 4]] = True
    n = int(w.available[:, used].sum()) * w.length
    assert n > 1000 and _relative_spread(SimpleNamespace(windows=w, used=used)) == pytest.approx(np.sqrt(2.0 / n))
    measured = np.ones(w.outputs.shape, dtype=bool)
    measured[: w.count // 2] = False
    holes = SimpleNamespace(windows=replace(w, measured=measured), used=used)
    assert _relative_spread(holes) == pytest.approx(np.sqrt(2.0 / int(measured[..., used].sum())))
