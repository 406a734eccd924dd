"""Each unmodelled effect shows where physics says it should (short closed-loop flights, fixed seeds).

Sensor effects leave the flown trajectory unchanged (the pilot looks out of the window), so a run
with the effect and the same seed without it differ only in the measurement; input effects are
checked on the true actuator signal and in the input-to-output cross-correlation.
"""

from __future__ import annotations

import numpy as np
import pytest

from hil_replay.sim.effects import InputChain, aliased_hz

from .conftest import ned_velocity, segment_mask

DT = 0.02
SEED = 11


def _lag_ticks(x: np.ndarray, y: np.ndarray, max_lag: int) -> int:
    """Lag (ticks) at which y best follows x (max of the normalised cross-correlation)."""
    x = (x - x.mean()) / x.std()
    y = (y - y.mean()) / y.std()
    lags = range(0, max_lag + 1)
    c = [np.mean(x[: x.size - k] * y[k:]) for k in lags]
    return int(np.argmax(np.abs(c)))


def test_input_delay_on_one_channel_only(fly) -> None:
    base = fly(SEED)
    run = fly(SEED, ("input_delay:input=lon,delay_s=0.1",))
    cmd, act = run["cmd"], run["act"]
    # the actuator sees the lon command exactly 5 ticks (0.1 s) late, the other channels at once
    assert np.allclose(act[5:, 1], cmd[:-5, 1], atol=1e-12)
    assert not np.allclose(act[:, 1], cmd[:, 1], atol=1e-6)
    for ch in (0, 2, 3):
        assert np.array_equal(act[:, ch], cmd[:, ch])
    # and it shows as extra lag from the lon stick to the roll rate, not from lat to the pitch rate
    m_lon = segment_mask(run, "sweep_lon") & segment_mask(base, "sweep_lon")
    m_lat = segment_mask(run, "sweep_lat") & segment_mask(base, "sweep_lat")
    assert m_lon.sum() > 200 and m_lat.sum() > 200
    p = 3
    q = 4
    lag_lon = _lag_ticks(run["cmd"][m_lon, 1], run["state"][m_lon, p], 40) - \
        _lag_ticks(base["cmd"][m_lon, 1], base["state"][m_lon, p], 40)
    lag_lat = _lag_ticks(run["cmd"][m_lat, 0], run["state"][m_lat, q], 40) - \
        _lag_ticks(base["cmd"][m_lat, 0], base["state"][m_lat, q], 40)
    assert 3 <= lag_lon <= 7, lag_lon
    assert abs(lag_lat) <= 1, lag_lat


def test_input_delay_fractional_is_exact_in_the_mean() -> None:
    h = 0.005
    chain = InputChain(h, delay_s=0.0123)
    t = np.arange(4000) * h
    x = np.sin(2 * np.pi * 0.7 * t)
    y = np.array([chain(v) for v in x])
    ref = np.sin(2 * np.pi * 0.7 * (t - 0.0123))
    assert np.abs(y[10:] - ref[10:]).max() < 1e-4


def test_rate_limit_caps_the_slew_and_bites_only_on_sharp_inputs(fly) -> None:
    rate = 2.0
    run = fly(SEED, (f"rate_limit:input=col,rate_per_s={rate}",))
    act, cmd = run["act"][:, 2], run["cmd"][:, 2]
    armed = run["armed"]
    # 4 sub-steps of 5 ms per tick: at most rate * 0.02 per tick
    assert np.abs(np.diff(act)).max() <= rate * DT + 1e-9
    assert np.abs(np.diff(cmd)).max() > 2 * rate * DT  # the command was faster somewhere
    limited = np.abs(act - cmd) > 1e-3
    assert 0.0 < limited[armed].mean() < 0.25  # only on the sharpest parts
    for ch in (0, 1, 3):
        assert np.array_equal(run["act"][:, ch], run["cmd"][:, ch])


def test_deadband_small_inputs_have_no_effect(fly) -> None:
    hw = 0.03
    run = fly(SEED, (f"deadband:input=lat,half_width={hw}",))
    act, cmd = run["act"][:, 0], run["cmd"][:, 0]
    small = np.abs(cmd) <= hw
    assert small.mean() > 0.2 and (~small).mean() > 0.05
    assert np.all(act[small] == 0.0)
    assert np.allclose(act[~small], cmd[~small] - np.sign(cmd[~small]) * hw)
    for ch in (1, 2, 3):
        assert np.array_equal(run["act"][:, ch], run["cmd"][:, ch])


@pytest.mark.parametrize("axis", ["p", "r"])
def test_gyro_bias_offsets_one_rate_only(fly, axis: str) -> None:
    base = fly(SEED)
    run = fly(SEED, (f"gyro_bias:output={axis},bias_rad_s=-0.012",))
    assert np.array_equal(run["state"], base["state"])  # a sensor error: same flight
    diff = run["rates"] - base["rates"]
    k = "pqr".index(axis)
    assert np.allclose(diff[:, k], -0.012, atol=1e-12)
    assert np.allclose(np.delete(diff, k, axis=1), 0.0, atol=1e-12)
    assert np.array_equal(run["att"], base["att"])
    assert np.array_equal(run["vel"], base["vel"])


def test_rotor_vibration_is_a_narrow_line_at_the_aliased_rotor_frequency(fly) -> None:
    rpm = 1400.0
    base = fly(SEED)
    run = fly(SEED, (f"rotor_vibration:amplitude_rad_s=0.006,rpm={rpm}",))
    assert np.array_equal(run["state"], base["state"])
    armed = run["armed"]
    d = (run["rates"] - base["rates"])[armed, 0]
    assert d.std() < 3 * 0.006  # of the order of the sensor noise (0.006 rad/s)
    spec = np.abs(np.fft.rfft(d * np.hanning(d.size))) ** 2
    freq = np.fft.rfftfreq(d.size, DT)
    lines = [aliased_hz(rpm / 60.0, 50.0), aliased_hz(2 * rpm / 60.0, 50.0)]
    assert lines == pytest.approx([23.333, 3.333], abs=1e-3)
    near = np.zeros(freq.size, bool)
    for f0 in lines:
        near |= np.abs(freq - f0) < 0.15
    assert spec[near].sum() > 0.95 * spec.sum()
    assert np.abs(freq[np.argmax(spec)] - lines[0]) < 0.05
    # disarmed (rotor stopped): no vibration
    assert np.allclose((run["rates"] - base["rates"])[~armed], 0.0)


def test_velocity_latency_delays_velocities_not_attitude(fly) -> None:
    lat_s = 0.16
    base = fly(SEED)
    run = fly(SEED, (f"velocity_latency:latency_s={lat_s}",))
    assert np.array_equal(run["state"], base["state"])
    assert np.array_equal(run["att"], base["att"])
    assert np.array_equal(run["rates"], base["rates"])
    v_true = ned_velocity(run["state"])
    noise = base["vel"] - v_true  # the same noise stream in both runs
    late = run["vel"] - noise
    shift = 8  # 0.16 s
    assert np.allclose(late[shift + 2:], v_true[2:-shift], atol=1e-9)
    # measured against truth: the best-aligning shift is the latency (all three axes)
    armed = np.flatnonzero(run["armed"])
    armed = armed[(armed > 30) & (armed < armed.max() - 30)]
    err = [np.sum((run["vel"][armed] - v_true[armed - k]) ** 2) for k in range(0, 20)]
    assert int(np.argmin(err)) == shift
    err0 = [np.sum((base["vel"][armed] - v_true[armed - k]) ** 2) for k in range(0, 20)]
    assert int(np.argmin(err0)) == 0


def test_wind_gust_velocity_measured_is_ground_speed_not_airspeed(fly) -> None:
    sigma = 1.2
    run = fly(SEED, (f"wind_gust:sigma_m_s={sigma},tau_s=2.0",))
    wind = run["wind"]
    armed = run["armed"]
    assert 0.4 * sigma < wind[:, :2].std(axis=0).mean() < 1.6 * sigma
    v_true = ned_velocity(run["state"])
    err_ground = (run["vel"] - v_true)[armed, :2]
    err_air = (run["vel"] - (v_true - wind))[armed, :2]
    assert err_ground.std() < 0.05  # the sensor noise
    assert err_air.std() > 0.4 * sigma  # airspeed is not what is measured
    # and the gusts push the aircraft around more than calm air does
    base = fly(SEED)
    assert v_true[armed, :2].std() > ned_velocity(base["state"])[base["armed"], :2].std()


def test_ground_effect_lowers_hover_collective_only_near_the_ground(fly) -> None:
    base = fly(SEED)
    run = fly(SEED, ("ground_effect:gain=1.0",))
    ige = segment_mask(run, "hover_ige", trim_s=1.5) & (run["landed"] == 2)
    busy = segment_mask(run, "sweep_col") | segment_mask(run, "doublet_col") | segment_mask(run, "climb") \
        | segment_mask(run, "descent")
    oge = ~busy & (-run["state"][:, 14] > 2.0) & (-base["state"][:, 14] > 2.0)
    assert ige.sum() > 100 and oge.sum() > 100
    heights = -run["state"][ige, 14]
    assert heights.max() + 0.42 < 1.35  # the card's IGE hover is below one rotor diameter
    dcol_ige = run["cmd"][ige, 2].mean() - base["cmd"][ige, 2].mean()
    dcol_oge = run["cmd"][oge, 2].mean() - base["cmd"][oge, 2].mean()
    assert dcol_ige < -0.006  # less collective (>= 3 us of PWM) in ground effect
    assert abs(dcol_oge) < 0.3 * abs(dcol_ige)


def test_quadratic_drag_needs_more_tilt_at_speed(fly) -> None:
    c = 0.06
    base = fly(SEED, duration_s=90.0)
    run = fly(SEED, (f"quadratic_drag:c_per_m={c}",), duration_s=90.0)
    leg = segment_mask(run, "leg_forward", trim_s=3.5)
    assert leg.sum() > 20
    speed = np.hypot(*ned_velocity(run["state"])[leg, :2].T)
    assert speed.mean() > 2.5
    dpitch = run["state"][leg, 7].mean() - base["state"][leg, 7].mean()
    expected = -c * np.mean(speed**2) / 9.81
    assert dpitch < 0 and 0.4 * expected > dpitch > 2.5 * expected, (dpitch, expected)


def test_effects_combine(fly) -> None:
    """Several effects at once: each keeps its own signature (input chain: delay, then play)."""
    base = fly(SEED)
    run = fly(SEED, ("input_delay:input=ped,delay_s=0.06", "deadband:input=ped,half_width=0.02",
                     "gyro_bias:output=q,bias_rad_s=0.008"))
    cmd, act = run["cmd"][:, 3], run["act"][:, 3]
    late = cmd[:-3]  # 0.06 s = 3 ticks
    expected = np.where(np.abs(late) <= 0.02, 0.0, late - np.sign(late) * 0.02)
    assert np.allclose(act[3:], expected, atol=1e-12)
    # the bias is there, on q only, on top of a (different) flight
    v_true_q = run["state"][:, 4]
    assert abs(np.mean(run["rates"][:, 1] - v_true_q) - 0.008) < 0.0005
    assert abs(np.mean(run["rates"][:, 0] - run["state"][:, 3])) < 0.0005
    assert not np.array_equal(run["state"], base["state"])
