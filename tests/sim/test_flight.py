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
