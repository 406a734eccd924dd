"""The synthetic pilot flies every shipped aircraft through the card and stays in the linear regime."""

from __future__ import annotations

import numpy as np
import pytest

from hil_replay.sim import SimulatedSession
from hil_replay.sim.aircraft import AIRCRAFT_DIR


@pytest.mark.parametrize("name", sorted(p.stem for p in AIRCRAFT_DIR.glob("*.toml")))
def test_pilot_flies_the_card(name: str) -> None:
    sess = SimulatedSession(seed=21, aircraft=name, flight_duration_s=45.0)
    truth = sess.truth()
    t, st, landed, armed, cmd = [], [], [], [], []
    for fr in sess.frames():
        t.append(fr.t_boot_s)
        st.append(fr.state)
        landed.append(fr.m.landed_state)
        armed.append(fr.armed)
        cmd.append(fr.command)
    t_arr, x, ls, arm, u = np.array(t), np.array(st), np.array(landed), np.array(armed), np.array(cmd)
    air = ls == 2
    assert air.mean() > 0.5
    height = -x[:, 14]
    assert height.max() > 2.0  # climbed out of ground effect
    assert np.abs(x[:, 6:8]).max() < 0.35  # roll/pitch within 20 degrees
    assert np.abs(u).max() < 0.6  # stick inside its travel
    assert ls[-1] == 1 and not arm[-1] and height[-1] == 0.0  # landed and disarmed at the end
    # the excitation is on the axis the card says
    for seg in truth["flights"][0]["segments"]:
        if seg["name"].startswith("sweep_"):
            m = (t_arr >= seg["start_fc_s"]) & (t_arr < seg["end_fc_s"])
            k = ("lat", "lon", "col", "ped").index(seg["axis"])
            std = u[m].std(axis=0)
            assert std[k] == std.max()


def _sweep_input_std(sess: SimulatedSession) -> tuple[float, float]:
    """(std of the swept input during sweeps, peak |roll/pitch| rad) over the session."""
    truth = sess.truth()
    t, st, cmd = [], [], []
    for fr in sess.frames():
        t.append(fr.t_boot_s)
        st.append(fr.state)
        cmd.append(fr.command)
    t_arr, x, u = np.array(t), np.array(st), np.array(cmd)
    stds = []
    for seg in truth["flights"][0]["segments"]:
        if seg["name"].startswith("sweep_"):
            m = (t_arr >= seg["start_fc_s"]) & (t_arr < seg["end_fc_s"])
            stds.append(u[m, ("lat", "lon", "col", "ped").index(seg["axis"])].std())
    return float(np.mean(stds)), float(np.abs(x[:, 6:8]).max())


def test_pilot_variants_and_excitation_scale() -> None:
    """The robustness knobs of ``bench diagnose`` (--pilot, --excitation) do what they say and still fly."""
    from hil_replay.scenarios import pilot_config

    base, _ = _sweep_input_std(SimulatedSession(seed=4, flight_duration_s=60.0))
    half = SimulatedSession(seed=4, flight_duration_s=60.0, excitation_scale=0.5)
    assert half.truth()["excitation_scale"] == 0.5
    s_half, _ = _sweep_input_std(half)
    assert 0.35 < s_half / base < 0.75          # pilot feedback adds some input on top of the card
    for name in ("tight", "loose"):
        sess = SimulatedSession(seed=4, flight_duration_s=60.0, pilot=pilot_config(name))
        assert sess.truth()["pilot"]["excited_axis_gain"] == pilot_config(name).excited_axis_gain
        _, peak_att = _sweep_input_std(sess)
        assert peak_att < 0.35                   # still in the linear regime
    with pytest.raises(ValueError, match="excitation_scale"):
        SimulatedSession(seed=4, excitation_scale=0.0)
