"""Effect parsing/sampling and aircraft files: bad input names the key and what is allowed."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil_replay.sim import SimulatedSession
from hil_replay.sim.aircraft import PARAM_NAMES, load_aircraft, resolve_aircraft
from hil_replay.sim.effects import EFFECT_NAMES, SPECS, Effect, parse_effect, random_effect

DESIGN_CATALOGUE = ("input_delay", "rate_limit", "deadband", "ground_effect", "wind_gust", "quadratic_drag",
                    "gyro_bias", "rotor_vibration", "velocity_latency")


def test_catalogue_is_the_design_catalogue() -> None:
    assert set(EFFECT_NAMES) == set(DESIGN_CATALOGUE)


def test_parse_full_spec() -> None:
    e = parse_effect("input_delay:input=lon,delay_s=0.12")
    assert e == Effect("input_delay", input="lon", params={"delay_s": 0.12})
    assert e.to_json() == {"effect": "input_delay", "input": "lon", "output": None, "params": {"delay_s": 0.12}}
    assert parse_effect(e.spec()) == e
    g = parse_effect(" gyro_bias : output=r , bias_rad_s=-0.01 ")
    assert (g.output, g.params["bias_rad_s"]) == ("r", -0.01)


def test_parse_fills_defaults() -> None:
    e = parse_effect("wind_gust")
    assert set(e.params) == {"sigma_m_s", "tau_s"} and e.input is None and e.output is None
    assert parse_effect("deadband").input in ("lat", "lon", "col", "ped")


@pytest.mark.parametrize("text, must_contain", [
    ("input_dleay:delay_s=0.1", ["input_dleay", "input_delay", "velocity_latency"]),
    ("input_delay:delay=0.1", ["'delay'", "delay_s"]),
    ("input_delay:delay_s=0.9", ["delay_s", "0.005", "0.5"]),
    ("input_delay:input=yaw", ["yaw", "lat", "ped"]),
    ("gyro_bias:output=u", ["'u'", "'p'", "'q'", "'r'"]),
    ("gyro_bias:input=lat", ["input", "not allowed"]),
    ("ground_effect:input=col", ["input", "not allowed"]),
    ("rate_limit:rate_per_s=fast", ["rate_per_s", "fast"]),
    ("deadband:half_width", ["half_width", "key=value"]),
    ("quadratic_drag:c_per_m=-0.01", ["c_per_m", "0.001"]),
    ("gyro_bias:bias_rad_s=0.5", ["bias_rad_s", "0.1"]),
    ("rotor_vibration:rpm=50", ["rpm", "300", "4000"]),
])
def test_bad_effects_name_the_key_and_allowed_values(text: str, must_contain: list[str]) -> None:
    with pytest.raises(ValueError) as info:
        parse_effect(text)
    msg = str(info.value)
    assert "\n" not in msg
    for s in must_contain:
        assert s in msg, msg


@pytest.mark.parametrize("name", DESIGN_CATALOGUE)
def test_random_effect_inside_the_typical_range(name: str) -> None:
    rng = np.random.default_rng(7)
    draws = [random_effect(name, rng) for _ in range(30)]
    for e in draws:
        assert e.name == name
        for k, ps in SPECS[name].params.items():
            v = abs(e.params[k]) if ps.signed else e.params[k]
            assert ps.typ_lo - 1e-6 <= v <= ps.typ_hi + 1e-6
    if SPECS[name].channel == "input":
        assert {e.input for e in draws} == {"lat", "lon", "col", "ped"}
    if SPECS[name].channel == "output":
        assert {e.output for e in draws} == {"p", "q", "r"}
    assert random_effect(name, 3) == random_effect(name, 3)


def test_duplicate_effect_on_same_channel_rejected() -> None:
    with pytest.raises(ValueError, match="twice"):
        SimulatedSession(effects=("input_delay:input=lat", "input_delay:input=lat,delay_s=0.05"))


def _write(tmp_path, text: str):
    p = tmp_path / "ac.toml"
    p.write_text(text)
    return p


def _default_toml() -> str:
    from hil_replay.sim.aircraft import AIRCRAFT_DIR

    return (AIRCRAFT_DIR / "trex600.toml").read_text()


def test_default_aircraft_loads_and_is_plausible() -> None:
    ac = resolve_aircraft(None)
    assert ac.name == "trex600" and ac.rotor_diameter_m == pytest.approx(1.35)
    assert set(ac.parameters) == set(PARAM_NAMES)
    P = ac.parameters
    assert P["N_r"] < 0 and P["inv_tau_s"] > 0 and P["M_a"] > 10 and P["L_b"] > 10
    from hil_replay.sim.dynamics import eq8_matrices

    Ah, _, Av, _ = (np.array(m) for m in eq8_matrices(P))
    eig = np.linalg.eigvals(Ah)
    assert 0 < eig.real.max() < 0.3  # unstable in hover, but slowly
    assert np.linalg.eigvals(Av).real.max() < 0  # heave/yaw with the gyro: stable


@pytest.mark.parametrize("edit, must_contain", [
    (lambda s: s.replace("M_a = 88.0\n", ""), ["M_a", "missing"]),
    (lambda s: s.replace("M_a = 88.0", "M_a = 88.0\nM_z = 1.0"), ["M_z", "unknown"]),
    (lambda s: s.replace("M_a = 88.0", 'M_a = "big"'), ["M_a", "finite number"]),
    (lambda s: s.replace("inv_tau_s = 12.5", "inv_tau_s = -3.0"), ["inv_tau_s", "> 0"]),
    (lambda s: s.replace("N_r = -1.3", "N_r = 0.5"), ["N_r", "< 0"]),
    (lambda s: s.replace("mass_kg = 4.6", "mass_kg = 4.6 kg"), ["malformed TOML"]),
    (lambda s: s.replace("col = 1580", "col = 2500"), ["trim_pwm.col", "[1000, 2000]"]),
    (lambda s: s.replace("pwm_per_unit = 500.0", "pwm_per_unit = 0"), ["pwm_per_unit", "positive"]),
    (lambda s: s.replace("ped = 4\n", "ped = 1\n"), ["servo", "same servo"]),
    (lambda s: "wingspan = 3\n" + s, ["wingspan", "allowed"]),
])
def test_malformed_aircraft_file(tmp_path, edit, must_contain) -> None:
    p = _write(tmp_path, edit(_default_toml()))
    with pytest.raises(ValueError) as info:
        load_aircraft(p)
    msg = str(info.value)
    assert str(p) in msg
    for s in must_contain:
        assert s in msg, msg


def test_unknown_aircraft_name_lists_the_shipped_ones() -> None:
    with pytest.raises(ValueError, match="trex600"):
        resolve_aircraft("trex9000")


def test_aircraft_the_pilot_cannot_fly_is_rejected_at_construction() -> None:
    from hil_replay.sim.aircraft import Aircraft

    p = dict(resolve_aircraft(None).parameters)
    for k in ("X_lat", "Y_lon", "M_lat", "M_lon", "L_lat", "L_lon", "A_lat", "B_lon"):
        p[k] = 0.0  # cyclic does nothing: the unstable hover cannot be flown
    with pytest.raises(ValueError, match=r"no_cyclic \(lat/lon\).*cannot stabilise"):
        SimulatedSession(aircraft=Aircraft(name="no_cyclic", parameters=p))


@given(name=st.sampled_from(DESIGN_CATALOGUE), seed=st.integers(0, 2**31 - 1))
@settings(max_examples=60, deadline=None)
def test_random_effects_round_trip_through_the_cli_syntax(name: str, seed: int) -> None:
    e = random_effect(name, seed)
    back = parse_effect(e.spec())
    assert (back.name, back.input, back.output) == (e.name, e.input, e.output)
    for k, v in e.params.items():
        assert back.params[k] == pytest.approx(v, rel=1e-5)
