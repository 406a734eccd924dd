"""A named effect that drifts through the flight, seen on the whole flight (groundstation.gap.drift)."""

from types import SimpleNamespace

import numpy as np

from groundstation.gap import drift
from groundstation.gap.fingerprints import Line


def _line_case(amplitude: np.ndarray, seed: int, W: int = 50, L: int = 150, dt: float = 0.02):
    """A rotor line at 7.3 Hz on p and q over W windows of L samples, window amplitudes ``amplitude``
    (W,), in white noise of 1 (weights 1)."""
    rng = np.random.default_rng(seed)
    t = np.arange(L) * dt
    phase = rng.uniform(0, 2 * np.pi, W)
    s = amplitude[:, None] * np.sin(2 * np.pi * 7.3 * t[None, :] + phase[:, None])
    resid = rng.standard_normal((W, L, 8))
    resid[..., 3] += s
    resid[..., 4] += 0.7 * s
    ev = SimpleNamespace(dt_s=dt, w8=np.ones(8), T=(np.arange(W) * 3.0)[:, None] + t[None, :])
    line = Line(frequency_hz=7.3, channels=["p", "q"], ratio=10.0, log10_p=-20.0)
    c = SimpleNamespace(hyp=SimpleNamespace(extra={"lines": [line]}, channels=(3, 4)))
    return c, ev, resid


def test_a_line_of_steady_size_holds_and_one_growing_through_the_flight_drifts():
    W = 50
    steady = [drift.line_drift(*_line_case(np.full(W, 0.8), seed=k), level=0.005) for k in range(20)]
    assert sum(d["drifts"] for d in steady) <= 1  # about the level, with the size guard
    assert all(0.6 < d["ratio"] < 1.6 for d in steady)
    # an oscillation growing with a lag that grows: nothing at take-off, 1.6 at the end
    grow = drift.line_drift(*_line_case(np.linspace(0.0, 1.6, W), seed=1), level=0.005)
    assert grow["drifts"] and grow["rho"] > 0 and grow["ratio"] > 2 and grow["p"] < 1e-4
    assert "grows through the flight" in grow["why"]


def test_halves_flown_differently_are_no_change_in_time_when_no_ramp_predicts_better():
    # held-back seed 3 case 3: a constant asymmetric col deadband (play wider on one side) that the
    # catalogue's deadzone only approximates. The halves move col with twice the spread in the second,
    # so the width each half estimates differs (0.016 and 0.022) and each half's data reject the
    # other's value; a width ramping through the flight predicts the held-out windows no better than a
    # constant one. Before, the deadband read as changing and the flight as unexplained
    from groundstation.bench import diagnose as bd
    from hil_replay import scenarios

    r = bd.run_case(scenarios.job(scenarios.ScenarioSet(cases=0, held_back=12, seed=3), 3))
    assert r["truth_effects"] == ["asym_deadband"]
    assert r["verdict"] == "deadband" and r["effects"][0]["input"] == "col", r["headline"]
    con = r["consistency"][0]
    assert con["status"] == "holds" and con["first"] / con["second"] < 0.8  # the halves' widths differ
    assert "explained by deadband col" in r["headline"]
