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
