"""The aircraft file: shipped examples parse, bad values give one line naming file, key and value,
and the prepare settings it implies (RC inputs of the real PX4 ground run, swashplate unmix)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from groundstation.aircraft import WIDE_PRIOR, AircraftError, load_aircraft, parse_aircraft
from groundstation.sysid.model import PARAM_NAMES

EXAMPLES = Path(__file__).resolve().parents[2] / "groundstation" / "configs" / "aircraft"


@pytest.mark.parametrize("name", ["trex550.toml", "trex550_rc.toml", "trex600.toml"])
def test_shipped_examples_parse(name):
    ac = load_aircraft(EXAMPLES / name)
    assert len(ac.prior.nominal) == len(PARAM_NAMES) == len(ac.prior.std)
    assert all(s > 0 for s in ac.prior.std)
    assert ac.prior.mean_array[PARAM_NAMES.index("inv_tau_s")] > 0
    cfg = ac.prep_config()
    assert cfg.input_channels == ac.inputs.channels


def test_rc_example_maps_the_px4_sticks():
    ac = load_aircraft(EXAMPLES / "trex550_rc.toml")
    cfg = ac.prep_config()
    assert cfg.input_source == "RC_CHANNELS" and cfg.input_channels == (1, 2, 6, 4)


def test_prior_values_and_defaults():
    ac = parse_aircraft({"prior": {"L_b": [80.0, 40.0]}}, "x.toml")
    i = PARAM_NAMES.index("L_b")
    assert ac.prior.nominal[i] == 80.0 and ac.prior.std[i] == 40.0 and ac.prior.given == ("L_b",)
    j = PARAM_NAMES.index("M_a")
    assert (ac.prior.nominal[j], ac.prior.std[j]) == WIDE_PRIOR["M_a"]


@pytest.mark.parametrize(("doc", "key", "words"), [
    ({"prior": {"N_fb": [0.8, 0.5]}}, "prior.N_fb", "N_ped"),
    ({"prior": {"Q_x": [1.0, 1.0]}}, "prior.Q_x", "unknown parameter"),
    ({"prior": {"inv_tau_s": [-7.2, 2.0]}}, "prior.inv_tau_s", "wrong sign convention"),
    ({"prior": {"L_b": [80.0, 0.0]}}, "prior.L_b", "positive"),
    ({"prior": {"L_b": 80.0}}, "prior.L_b", "[nominal, std]"),
    ({"inputs": {"source": "PPM"}}, "inputs.source", "RC_CHANNELS"),
    ({"inputs": {"lat": 0}}, "inputs.lat", "channel number"),
    ({"inputs": {"source": "SWASHPLATE"}}, "inputs.swash_servos", "three servo"),
    ({"outputs": {"measured": ["u", "alt"]}}, "outputs.measured", "u v w"),
    ({"colour": "red"}, "colour", "unknown key"),
])
def test_bad_aircraft_file_one_line_naming_file_key_value(doc, key, words):
    with pytest.raises(AircraftError) as ei:
        parse_aircraft(doc, "heli.toml")
    msg = str(ei.value)
    assert msg.startswith(f"heli.toml: {key} = ") and "\n" not in msg
    assert words.split()[0] in msg


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(AircraftError, match="no such aircraft file"):
        load_aircraft(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = \n")
    with pytest.raises(AircraftError, match="bad.toml: not valid TOML"):
        load_aircraft(bad)


def test_swashplate_unmix_recovers_the_sticks():
    from types import SimpleNamespace

    from firmware_interface.samples import Series
    from groundstation.dsp.prepare import _input_pwm

    ac = parse_aircraft({"inputs": {"source": "SWASHPLATE", "swash_servos": [1, 2, 3], "ped": 4,
                                    "swash_phase_deg": [0, 120, 240]}}, "s.toml")
    cfg = ac.prep_config()
    rng = np.random.default_rng(0)
    lat, lon, col, ped = (rng.normal(0, 50, 200) for _ in range(4))
    ph = np.radians([0.0, 120.0, 240.0])
    servos = [1500 + col + lon * np.cos(p) + lat * np.sin(p) for p in ph]
    cols = {f"pwm_us_{k}": np.full(200, 1500.0) for k in range(1, 17)}
    for k, s in enumerate(servos):
        cols[f"pwm_us_{k + 1}"] = s
    cols["pwm_us_4"] = 1500 + ped
    log = SimpleNamespace(source="s.tlog", series={"SERVO_OUTPUT_RAW": Series(np.arange(200.0), np.arange(200.0), cols)})
    pwm = _input_pwm(log, cfg)
    centre = np.median(np.stack(servos, axis=1))
    np.testing.assert_allclose(pwm[:, 0] - centre, lat, atol=1e-6)
    np.testing.assert_allclose(pwm[:, 1] - centre, lon, atol=1e-6)
    np.testing.assert_allclose(pwm[:, 2], 1500 + col, atol=1e-6)
    np.testing.assert_allclose(pwm[:, 3], 1500 + ped, atol=1e-9)
