"""A common time shift of the logged inputs (dsp.timeskew), through prepare() and the aircraft file."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.aircraft import AircraftError, parse_aircraft
from groundstation.dsp.prepare import PrepConfig, prepare, prepared_from_arrays
from groundstation.dsp.timeskew import shift_inputs
from groundstation.errors import DspError

from .conftest import make_log


def test_prepare_advances_the_inputs_by_the_configured_shift_and_says_so():
    log = make_log(30.0)
    base = prepare([log], PrepConfig(velocity_check=False))
    late = prepare([log], PrepConfig(velocity_check=False, input_shift_s=0.07))
    a, b = base.segments[0], late.segments[0]
    assert b.t_s[0] == a.t_s[0] and b.t_s[-1] == pytest.approx(a.t_s[-1] - 0.07, abs=0.02)
    for j in range(4):  # u'(t) = u(t + 0.07): the input 3.5 samples later, interpolated
        assert np.allclose(b.inputs[:, j], np.interp(b.t_s + 0.07, a.t_s, a.inputs[:, j]))
    assert np.array_equal(b.outputs, a.outputs[: b.n], equal_nan=True)
    assert any("inputs advanced by 70 ms" in n for n in late.notes)
    assert not any("advanced" in n for n in base.notes)


def test_a_negative_shift_delays_the_inputs_and_drops_the_start():
    u = np.zeros((500, 4))
    u[200:, 1] = 1.0  # a step at sample 200 (4.0 s)
    p = shift_inputs(prepared_from_arrays(u, np.zeros((500, 8)), 0.02), -0.1)
    s = p.segments[0]
    assert s.n == 495 and s.t_s[0] == pytest.approx(0.1)
    assert s.t_s[np.argmax(s.inputs[:, 1] > 0.5)] == pytest.approx(4.1)  # the step now 100 ms later
    assert any("delayed by 100 ms" in n for n in p.notes)


def test_a_shift_that_is_no_skew_is_refused():
    with pytest.raises(DspError, match="input_shift_s"):
        PrepConfig(input_shift_s=1.5)
    with pytest.raises(DspError, match="1 s"):
        shift_inputs(prepared_from_arrays(np.zeros((100, 4)), np.zeros((100, 8)), 0.02), -2.0)


def test_the_aircraft_file_sets_the_shift_for_its_flights():
    ac = parse_aircraft({"inputs": {"shift_s": 0.06}}, "heli.toml")
    assert ac.prep_config().input_shift_s == 0.06
    assert parse_aircraft({}, "heli.toml").prep_config(PrepConfig(input_shift_s=0.02)).input_shift_s == 0.02
    with pytest.raises(AircraftError, match=r"heli.toml: inputs.shift_s"):
        parse_aircraft({"inputs": {"shift_s": "60 ms"}}, "heli.toml")


def _pulses(skew_s: float, seed: int = 0) -> object:
    """A pilot's isolated stick steps (one every 1.5 s) and a fast causal pitch-rate response
    (first order, 60 ms); the stick is logged ``skew_s`` late against the gyro."""
    rng, dt, n = np.random.default_rng(seed), 0.02, 6000
    lvl = np.repeat(rng.choice([-1.0, 1.0], n // 75) * rng.uniform(0.05, 0.2, n // 75), 75)
    stick = np.zeros(n)
    q = np.zeros(n)
    for k in range(1, n):   # the stick moves within ~50 ms, the rate follows it
        stick[k] = stick[k - 1] + (1 - np.exp(-dt / 0.02)) * (lvl[k - 1] - stick[k - 1])
        q[k] = q[k - 1] + (1 - np.exp(-dt / 0.06)) * (2.0 * stick[k - 1] - q[k - 1])
    u = np.zeros((n, 4))
    t = np.arange(n) * dt
    u[:, 1] = np.interp(t - skew_s, t, stick)
    y = np.full((n, 8), np.nan)
    y[:, 4] = q + 0.02 * rng.standard_normal(n)
    return prepared_from_arrays(u, y, dt)


def test_the_response_lead_on_sharp_steps_bounds_the_skew_from_below():
    from groundstation.dsp.timeskew import response_lead

    (none,) = response_lead(_pulses(0.0))
    assert (none.input, none.output) == ("lon", "q") and none.events >= 30
    assert none.lead_hi_s < 0.0          # a causal response never rises first
    (late,) = response_lead(_pulses(0.08))
    # found, never more than the skew (the response's own lag takes its share), and moved by the skew
    assert 0.0 < late.lead_lo_s and late.lead_s <= 0.08
    assert late.lead_s - none.lead_s == pytest.approx(0.08, abs=0.015)
    assert "before lon" in late.describe()
    (fixed,) = response_lead(shift_inputs(_pulses(0.08), 0.08))
    assert fixed.lead_s == pytest.approx(none.lead_s, abs=0.01)
