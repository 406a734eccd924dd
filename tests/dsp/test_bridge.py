"""The bridge limit follows the inputs and the rotor: the straight line's error over a hole is what the
formula says; smoother inputs and a faster rotor allow shorter bridges; a configured limit wins; too
little input without holes falls back to the stated default; the limit used is in the link quality."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.dsp.bridge import _line_error_gain, bridge_limit
from groundstation.dsp.prepare import FALLBACK_BRIDGE_S, PrepConfig, derive_bridge, prepare


def test_line_error_gain_is_the_straight_lines_mean_square_error_over_the_hole():
    f, h = 1.7, 0.3
    u = (np.arange(9) + 0.5) / 9
    t0 = np.linspace(0.0, 10.0 / f, 4000, endpoint=False)    # whole periods
    # a unit-power sinusoid (amplitude sqrt 2) at f, holes starting anywhere: the line's error inside
    x = lambda t: np.sqrt(2.0) * np.cos(2 * np.pi * f * t)   # noqa: E731
    e = x(t0[:, None] + u * h) - ((1 - u) * x(t0[:, None]) + u * x(t0[:, None] + h))
    np.testing.assert_allclose(_line_error_gain(np.array([f]), np.array([h]))[0, 0], np.mean(e ** 2), rtol=1e-3)


def _inputs(fast: float, seconds: float = 120.0, dt: float = 0.02, seed: int = 0):
    """Four inputs: slow manoeuvres (0.2-0.8 Hz) plus ``fast`` of white content (a servo's busy part)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, dt)
    slow = sum(0.05 * np.sin(2 * np.pi * fr * t + rng.uniform(0, 6)) for fr in (0.2, 0.45, 0.8))
    x = slow[:, None] + fast * rng.standard_normal((t.size, 4))
    return t, x


def test_limit_grows_with_the_inputs_fast_content_and_shrinks_with_a_faster_rotor():
    t, busy = _inputs(0.01)
    _, quiet = _inputs(0.002)
    iv = [(0.0, float(t[-1]))]
    b_busy = bridge_limit(t, busy, iv, 0.1, 10.0)
    b_quiet = bridge_limit(t, quiet, iv, 0.1, 10.0)
    b_fast_rotor = bridge_limit(t, busy, iv, 0.1, 25.0)
    assert b_busy.limit_s is not None and b_quiet.limit_s is not None and b_fast_rotor.limit_s is not None
    assert b_quiet.limit_s < b_busy.limit_s
    assert b_fast_rotor.limit_s < b_busy.limit_s
    assert set(b_busy.by_input_s) == {"lat", "lon", "col", "ped"} and b_busy.seconds_used > 100
    # an input that never moves does not limit
    still = busy.copy()
    still[:, 3] = 0.0
    assert "ped" not in bridge_limit(t, still, iv, 0.1, 10.0).by_input_s


def test_too_little_input_without_holes_gives_no_limit():
    t, x = _inputs(0.01, seconds=120.0)
    keep = (np.arange(t.size) % 40) < 30          # a hole of 0.2 s every 0.8 s: no stretch of a Welch segment
    assert bridge_limit(t[keep], x[keep], [(0.0, float(t[-1]))], 0.1, 10.0).limit_s is None


@pytest.fixture(scope="module")
def lossy_log(tmp_path_factory):
    from firmware_interface.readers import load_log
    from hil_replay.sim import write_tlog

    d = tmp_path_factory.mktemp("bridge")
    rates = {"ATTITUDE": 25, "SERVO_OUTPUT_RAW": 25, "LOCAL_POSITION_NED": 25}
    write_tlog(d / "f.tlog", seed=5, flight_duration_s=60.0, rates_hz=rates, packet_loss=0.10, loss_burst=8.0)
    return load_log(d / "f.tlog")


def test_prepare_states_the_limit_it_used_and_why(lossy_log):
    p = prepare([lossy_log])
    br = p.link_quality["bridge"]
    assert br["rule"] == "derived" and 0.1 < br["limit_s"] <= 1.0
    assert p.link_quality["max_input_bridge_s"] == br["limit_s"] == min(br["by_input_s"].values())
    assert any("derived" in n and "1/tau_s 16/s" in n for n in p.notes)
    # the configured key overrides; the aircraft's rotor makes the rule stricter or looser
    assert prepare([lossy_log], PrepConfig(max_input_bridge_s=0.2)).link_quality["bridge"] == {
        "limit_s": 0.2, "rule": "configured"}
    fast = derive_bridge([lossy_log], PrepConfig(rotor_inv_tau_s=25.0))
    assert fast["rule"] == "derived" and fast["limit_s"] < br["limit_s"]
    assert 0 < FALLBACK_BRIDGE_S < 1
