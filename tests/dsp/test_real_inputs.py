"""Real data as it comes: the PX4 ground run is said to be one (rotor and motion evidence, not the
barometer), its RC sticks are readable through the aircraft file, horizontal velocities without the
vertical one still give u and v, and inputs that never move are named with the channels that do."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from firmware_interface.readers import load_log
from firmware_interface.samples import Series
from groundstation.aircraft import load_aircraft
from groundstation.dsp.prepare import PrepConfig, moving_channels, prepare
from tests.realdata import real_log

EXAMPLES = Path(__file__).resolve().parents[2] / "groundstation" / "configs" / "aircraft"


@pytest.fixture(scope="module")
def groundrun():
    return load_log(real_log("px4/trex550_groundrun.px4log"))


@pytest.fixture(scope="module")
def flight1():
    return load_log(real_log("trex550/flight1.tlog"))


def test_px4_rc_sticks_are_the_moving_channels(groundrun):
    assert groundrun.has("RC_CHANNELS")
    assert moving_channels(groundrun, 5.0) == ["RC_CHANNELS 1", "RC_CHANNELS 2", "RC_CHANNELS 4", "RC_CHANNELS 6"]
    col = np.asarray(groundrun.series["RC_CHANNELS"]["pwm_us_6"])
    assert 1500 + 500 * 0.8 < np.nanmax(col) < 1500 + 500 * 0.9  # the collective reaches +0.85


@pytest.mark.parametrize("aircraft", [None, "trex550_rc.toml"])
def test_ground_run_is_said_to_be_one(groundrun, aircraft):
    cfg = load_aircraft(EXAMPLES / aircraft).prep_config() if aircraft else PrepConfig()
    with pytest.raises(ValueError) as ei:
        prepare([groundrun], cfg)
    msg = str(ei.value)
    assert "never left the ground" in msg and "trex550_groundrun.px4log" in msg and "\n" not in msg
    assert "vibration" in msg and "body-rate" in msg


def test_real_flight_has_airborne_evidence(flight1):
    prep = prepare([flight1])
    assert prep.duration_s > 200 and not any("on the ground" in n for n in prep.notes)


def test_horizontal_velocities_without_vertical_give_u_v(flight1):
    lp = flight1.series["LOCAL_POSITION_NED"]
    cols = dict(lp.columns)
    cols["vz_m_s"] = np.full(len(lp), np.nan)
    log = replace(flight1, series={**flight1.series, "LOCAL_POSITION_NED": Series(lp.t_fc_s, lp.t_host_s, cols)})
    cfg = PrepConfig(velocity_check=False)  # the derivation of u and v, not their consistency
    full, no_w = prepare([flight1], cfg), prepare([log], cfg)
    assert no_w.available[0] and no_w.available[1] and not no_w.available[2]
    a, b = full.segments[0], no_w.segments[0]
    assert a.t_s[0] == b.t_s[0] and a.available[2]
    # the vertical share in body u is small: u differs by a few cm/s rms, not by the signal
    du = np.nanstd(a.outputs[:, 0] - b.outputs[:, 0])
    assert du < 0.25 * np.nanstd(a.outputs[:, 0]), du


def test_inputs_that_never_move_are_named_with_the_moving_channels(flight1):
    with pytest.raises(ValueError) as ei:
        prepare([flight1], PrepConfig(input_channels=(1, 1, 1, 1)))
    msg = str(ei.value)
    assert "never move" in msg and "SERVO_OUTPUT_RAW 2, SERVO_OUTPUT_RAW 3, SERVO_OUTPUT_RAW 4" in msg
    assert "\n" not in msg


def test_channel_map_naming_a_channel_the_log_lacks(flight1):
    with pytest.raises(ValueError) as ei:
        prepare([flight1], PrepConfig(input_channels=(1, 2, 3, 19)))
    assert "flight1.tlog" in str(ei.value) and "channel 19" in str(ei.value)


def test_log_info_says_the_ground_run_never_flew(groundrun):
    from groundstation.commands.log_info import _ground_evidence

    assert "on the ground" in _ground_evidence(groundrun, groundrun.flights[0])


def test_log_info_says_the_ground_run_spent_no_time_in_the_air(capsys):
    import json

    from groundstation.cli import main as cli_main

    path = str(real_log("px4/trex550_groundrun.px4log"))
    assert cli_main(["log-info", path, "--json"]) == 0
    f = json.loads(capsys.readouterr().out)["flights"][0]
    assert f["in_air_s"] == 0.0 and f["in_air_by_height_s"] > 40  # the barometer's drift said 45 s
    assert "vibration" in f["on_ground_evidence"] and "body-rate" in f["on_ground_evidence"]
    assert cli_main(["log-info", path]) == 0
    out = capsys.readouterr().out
    table, _, note = out.partition("0 s in the air")
    assert note and "45.4" not in table and "0.0" in table  # the table says 0, the note says why
