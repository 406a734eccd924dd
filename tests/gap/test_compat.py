"""Data compatibility on simulated flights: gyro and vertical-velocity scale errors found, none invented."""

import numpy as np
import pytest

from groundstation.gap import compat, noise
from groundstation.gap.diagnose import _trims, segments_from_prepared
from groundstation.sysid.model import OUTPUTS


def _check(tmp_path, seed, effects, **kw):
    from firmware_interface.readers import load_log
    from groundstation.dsp.prepare import prepare
    from hil_replay.sim import write_tlog

    path = tmp_path / f"c{seed}.tlog"
    write_tlog(path, seed=seed, flights=1, effects=effects, flight_duration_s=90.0, **kw)
    prep = prepare([load_log(path)])
    segs, avail = segments_from_prepared(prep)
    sigma = noise.raw_noise_std([s.outputs_raw for s in segs], prep.native_stride(OUTPUTS))
    return compat.check(segs, avail, prep.dt_s, sigma, _trims(prep))


def test_effect_free_flight_has_no_finding_and_small_estimates(tmp_path):
    c = _check(tmp_path, 41, [], rates_hz={"ATTITUDE": 12.5, "LOCAL_POSITION_NED": 10.0})
    assert c.findings == ()
    scales = {e.sensor: e for e in c.estimates if e.parameter == "scale"}
    assert set(scales) == {"p", "q", "w"}
    for e in scales.values():
        assert abs(e.value) < 4 * e.se + 0.01  # consistent with zero at its own standard error
    assert "r" in c.untestable and "u,v" in c.untestable


@pytest.mark.parametrize(("effect", "kind", "channel", "truth"), [
    ("gyro_scale:output=p,scale_error=0.12", "gyro_scale", "p", 0.12),
    ("gyro_scale:output=q,scale_error=-0.1", "gyro_scale", "q", -0.1),
    ("velocity_scale:scale_error=0.15", "velocity_scale", "w", 0.15),
])
def test_scale_error_found_on_its_sensor(tmp_path, effect, kind, channel, truth):
    c = _check(tmp_path, 42, [effect])
    assert [(f.kind, f.channel) for f in c.findings] == [(kind, channel)]
    f = c.findings[0]
    assert abs(f.estimate - truth) < max(4 * f.se, 0.02)
    fac = c.scale_corrections()
    cols = (0, 1, 2) if kind == "velocity_scale" else (OUTPUTS.index(channel),)
    assert set(fac) == set(cols)
    assert np.allclose([fac[k] for k in cols], 1.0 / (1.0 + f.estimate))


def test_gyro_bias_is_estimated_but_not_a_scale_finding(tmp_path):
    c = _check(tmp_path, 43, ["gyro_bias:output=p,bias_rad_s=0.01"])
    bias = next(e for e in c.estimates if e.sensor == "p" and e.parameter == "bias")
    assert abs(bias.value - 0.01) < 0.002 and bias.p_value < 1e-6
    assert c.findings == ()
