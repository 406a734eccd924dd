"""Output error with a priori weighting (MAP) on a flight of the linear model with known truth: a
parameter the flight cannot determine stays at its prior with the prior's uncertainty, one it does
determine is not pulled towards a wrong prior; and the held-out tools on that model."""

from __future__ import annotations

import numpy as np
import pytest

from benchkit.synthetic import EXAMPLE_TRUTH, simulate_flight
from groundstation.dsp.prepare import prepared_from_arrays
from groundstation.sysid.cost import WindowedCost, make_windows
from groundstation.sysid.model import PARAM_INDEX, VER_PARAMS, HoverModel, theta_from_dict
from groundstation.sysid.refine import refine


@pytest.fixture(scope="module")
def vertical_case():
    truth = dict(EXAMPLE_TRUTH, Z_col=0.0, N_col=0.0)  # the collective acts on nothing ...
    th = theta_from_dict(truth)
    u, _, ym = simulate_flight(th, 60.0, seed=5)
    u[:, 2] = 0.0  # ... and never moves: Z_col and N_col cannot be determined
    prep = prepared_from_arrays(u, ym, 0.02)
    free = np.zeros(len(th), dtype=bool)
    free[[PARAM_INDEX[p] for p in VER_PARAMS]] = True
    win = make_windows(prep.segments, prep.dt_s, 3.0)
    cost = WindowedCost(win, free, th, subsystems=(1,))
    return truth, th, free, cost, prep


def test_undetermined_stays_at_prior_determined_is_not_pulled(vertical_case):
    truth, th, free, cost, _ = vertical_case
    names = [n for n in VER_PARAMS]
    pm = np.array([truth[n] * 0.5 for n in names])  # a prior half the truth: wrong by 50 %
    ps = np.array([max(abs(truth[n]), 1.0) for n in names])  # as wide as the value
    iz, inp = names.index("Z_col"), names.index("N_ped")
    pm[iz], ps[iz] = 5.0, 2.0
    b = np.array([[-80.0, 80.0]] * len(names))
    r = refine(cost, pm.copy(), b, prior=(pm, ps))
    assert r.x[iz] == pytest.approx(5.0, abs=0.05)  # stays at the prior ...
    assert r.std[iz] == pytest.approx(2.0, rel=0.05)  # ... with the prior's uncertainty
    assert r.prior_share[iz] > 0.95
    for n in ("N_ped", "N_r", "k_r"):  # determined by the flight: not pulled to the 50 % prior
        i = names.index(n)
        assert r.x[i] == pytest.approx(truth[n], rel=0.10), n
        assert r.prior_share[i] < 0.2, n
    assert r.x[inp] == pytest.approx(truth["N_ped"], rel=0.05)


def test_prediction_scores_truth_above_a_wrong_model_and_flags_runaway(vertical_case):
    from groundstation.sysid.heldout import predict, runaway_channels, unstable_modes

    truth, _, _, _, prep = vertical_case
    good = predict(HoverModel(params=dict(truth)), prep)
    assert good.mean_match > 50 and not runaway_channels(good)
    bad_params = dict(truth, N_r=3.0)  # yaw diverging with a 1/3 s time constant
    modes = unstable_modes(theta_from_dict(bad_params))
    assert any(m.subsystem == "vertical" and m.time_constant_s < 1.0 for m in modes)
    bad = predict(HoverModel(params=bad_params), prep)
    assert bad.match["r"] < good.match["r"] - 30
    assert "r" in runaway_channels(bad)


def test_parameters_the_data_cannot_move_keep_the_prior_value_and_std():
    from groundstation.aircraft import wide_prior
    from groundstation.sysid.identify import IdentifyConfig, identify
    from groundstation.sysid.model import PARAM_NAMES

    u, _, ym = simulate_flight(theta_from_dict(EXAMPLE_TRUTH), 40.0, seed=7)
    u[:, 0] = 0.0  # the lateral stick never moves: X_lat, M_lat, L_lat, A_lat cannot be determined
    ym[:, 2] = np.nan  # w not measured: the heave terms cannot be either
    prior = wide_prior()
    nominal = dict(zip(PARAM_NAMES, prior.nominal, strict=True))
    std = dict(zip(PARAM_NAMES, prior.std, strict=True))
    m = identify(prepared_from_arrays(u, ym, 0.02), seed=0, maxiter=4, prior=prior,
                 config=IdentifyConfig(refine_max_nfev=5, refine_passes=1, search_restarts=1))
    fixed = set(m.fit.fixed)
    assert {"A_lat", "L_lat", "Z_w"} <= fixed
    for name in fixed:
        assert m.params[name] == nominal[name] and m.parameter_std[name] == std[name], name
    assert set(m.fit.prior.fixed_at_prior) == fixed
    assert any("fixed at the prior's value" in r for r in m.fit.fixed_reasons)
    assert not any("fixed at 0" in r for r in m.fit.fixed_reasons)
    assert m.params["Z_w"] != 0.0  # the wide prior's heave damping, not 0
