"""Velocities against the attitude: a velocity that measures the aircraft's motion passes (a calibration
error is measured, not rejected); one that does not follow the attitude (the real TREX 550 log's
body u), or that the attitude cannot confirm (its v), is left out of the prepared data with a note."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from benchkit.synthetic import EXAMPLE_TRUTH, simulate_flight
from firmware_interface.readers import load_log
from groundstation.aircraft import load_aircraft
from groundstation.dsp.prepare import prepare, prepared_from_arrays
from groundstation.dsp.velocity_check import check_horizontal
from groundstation.sysid.model import theta_from_dict
from tests.dsp.test_real_inputs import EXAMPLES
from tests.realdata import real_log


@pytest.fixture(scope="module")
def sim():
    u, _, ym = simulate_flight(theta_from_dict(EXAMPLE_TRUTH), 150.0, seed=3)
    return u, ym


def _checks(u: np.ndarray, y: np.ndarray) -> dict[str, object]:
    prep = prepared_from_arrays(u, y, 0.02)
    return {c.channel: c for c in check_horizontal(prep.segments, prep.dt_s)}


def test_simulated_velocities_are_consistent_with_scale_one(sim):
    c = _checks(*sim)
    for ch in ("u", "v"):
        assert c[ch].verdict == "consistent"
        assert abs(c[ch].scale - 1.0) < max(3 * c[ch].se, 0.05), c[ch].describe()


@pytest.mark.parametrize("scale", [0.6, 1.4])
def test_a_calibration_error_is_measured_not_rejected(sim, scale):
    u, y = sim
    y = y.copy()
    y[:, :2] *= scale
    c = _checks(u, y)
    for ch in ("u", "v"):
        assert c[ch].verdict == "consistent"
        assert abs(c[ch].scale - scale) < max(3 * c[ch].se, 0.05 * scale), c[ch].describe()


def test_a_velocity_that_does_not_follow_the_attitude_is_inconsistent(sim):
    u, y = sim
    y = y.copy()
    rng = np.random.default_rng(1)
    # an estimator coasting on its own: a slow random walk with the measured velocity's spread
    walk = np.cumsum(rng.normal(0.0, 1.0, y.shape[0])) * 0.02
    y[:, 0] = walk / np.std(walk) * np.std(y[:, 0])
    c = _checks(u, y)
    assert c["u"].verdict == "contradicted" and c["v"].verdict == "consistent"
    assert abs(c["u"].scale) < 1.0 / 3.0


def test_real_log_u_is_left_out_with_a_note():
    log = load_log(real_log("trex550/flight1.tlog"))
    cfg = load_aircraft(EXAMPLES / "trex550.toml").prep_config()
    kept = prepare([log], replace(cfg, velocity_check=False))
    checked = prepare([log], cfg)
    # u contradicts the attitude; v's scale is too uncertain to confirm it measures the motion
    assert kept.available[0] and kept.available[1]
    assert not checked.available[0] and not checked.available[1]
    notes = {n[7]: n for n in checked.notes if n.startswith("output ") and " left out" in n}
    assert "does not follow the attitude" in notes["u"] and "cannot confirm" in notes["v"]
    assert all("velocity_check = false" in n for n in notes.values())
    assert all(np.isnan(s.outputs[:, :2]).all() for s in checked.segments)
