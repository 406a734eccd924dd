"""Data compatibility on simulated flights: gyro and vertical-velocity scale errors found, none invented."""

import numpy as np
import pytest

from groundstation.gap import compat, noise
from groundstation.gap.diagnose import _trims, segments_from_prepared
from groundstation.sysid.model import OUTPUTS


def _check(tmp_path, seed, effects, horizontal=False, **kw):
    from firmware_interface.readers import load_log
    from groundstation.dsp.prepare import prepare
    from groundstation.dsp.velocity_check import check_horizontal
    from hil_replay.sim import write_tlog

    path = tmp_path / f"c{seed}.tlog"
    write_tlog(path, seed=seed, flights=1, effects=effects, flight_duration_s=90.0, **kw)
    prep = prepare([load_log(path)])
    segs, avail = segments_from_prepared(prep)
    sigma = noise.raw_noise_std([s.outputs_raw for s in segs], prep.native_stride(OUTPUTS))
    hor = [c for c in check_horizontal(prep.segments, prep.dt_s) if c.channel in ("u", "v")] if horizontal else ()
    return compat.check(segs, avail, prep.dt_s, sigma, _trims(prep), horizontal=hor)


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


def test_horizontal_velocity_scale_found_from_the_attitude(tmp_path):
    # 10 Hz streams: the height check alone is too coarse to see a 10 % scale error here
    c = _check(tmp_path, 44, ["velocity_scale:scale_error=-0.1"], horizontal=True,
               rates_hz={"ATTITUDE": 10.0, "LOCAL_POSITION_NED": 10.0})
    uv = [f for f in c.findings if f.channel == "u,v"]
    assert [f.kind for f in uv] == ["velocity_scale"]
    assert abs(uv[0].estimate - -0.1) < max(4 * uv[0].se, 0.02)
    assert "u,v" not in c.untestable
    assert {e.sensor for e in c.estimates if e.parameter == "scale"} >= {"u", "v"}
    fac = c.scale_corrections()
    assert np.isclose(fac[0], 1.0 / (1.0 + uv[0].estimate)) and np.isclose(fac[1], fac[0])


def test_effect_free_flight_has_no_horizontal_finding(tmp_path):
    c = _check(tmp_path, 41, [], horizontal=True, rates_hz={"ATTITUDE": 12.5, "LOCAL_POSITION_NED": 10.0})
    assert c.findings == ()
    for e in c.estimates:
        if e.sensor in ("u", "v"):
            assert abs(e.value) < 0.03  # the simulator's velocities read their true scale


def test_horizontal_finding_needs_u_and_v_to_agree():
    from types import SimpleNamespace as NS

    from groundstation.gap.evaluate import SegmentArrays

    rng = np.random.default_rng(0)
    n = 400
    y = rng.standard_normal((n, 8))
    segs = [SegmentArrays(t_s=np.arange(n) * 0.02, inputs=np.zeros((n, 4)), outputs=y, outputs_raw=y,
                          alt_m=np.full(n, np.nan), flight=0)]
    sigma = np.full(8, 0.01)
    agree = [NS(channel="u", scale=0.8, se=0.01), NS(channel="v", scale=0.81, se=0.01)]
    one_off = [NS(channel="u", scale=0.8, se=0.01), NS(channel="v", scale=1.0, se=0.01)]
    ests, pooled = compat._horizontal(agree, segs, sigma, 3.0)
    assert pooled is not None and abs(pooled[0] - -0.195) < 1e-9 and pooled[2] < 1e-9
    assert [e.sensor for e in ests] == ["u", "v"]
    assert compat._horizontal(one_off, segs, sigma, 3.0)[1] is None
