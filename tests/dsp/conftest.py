"""Synthetic LogData builders for the dsp tests (no files, no simulator)."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_interface.samples import SERIES_FIELDS, FlightInterval, LinkStats, LogData, Series


def make_series(name: str, t_s: np.ndarray, **cols: np.ndarray) -> Series:
    n = t_s.shape[0]
    columns = {c: np.asarray(cols.get(c, np.zeros(n)), dtype=float) for c in SERIES_FIELDS[name]}
    return Series(t_fc_s=np.asarray(t_s, dtype=float), t_host_s=np.asarray(t_s, dtype=float) + 1000.0, columns=columns)


def make_log(duration_s: float = 60.0, *, seed: int = 0, servo_rate_hz: float = 50.0, att_rate_hz: float = 50.0,
             pos_rate_hz: float = 10.0, yaw_rad: float = 0.7, vel_ned=(1.0, 0.5, -0.2), drop_servo=None,
             with_servo: bool = True, with_att: bool = True, flights=None, vel_nan_after_s=None,
             landed_state=True, z_of_t=None) -> LogData:
    rng = np.random.default_rng(seed)
    series = {}
    ts = np.arange(0.0, duration_s, 1 / servo_rate_hz) + 0.003
    pwm = {f"pwm_us_{i}": 1500 + 20 * np.sin(ts * (i + 0.3)) + rng.normal(0, 1, ts.size) for i in range(1, 5)}
    pwm["pwm_us_3"] = pwm["pwm_us_3"] + 60.0
    if drop_servo is not None:
        keep = ~((ts > drop_servo[0]) & (ts < drop_servo[1]))
        ts = ts[keep]
        pwm = {k: v[keep] for k, v in pwm.items()}
    if with_servo:
        series["SERVO_OUTPUT_RAW"] = make_series("SERVO_OUTPUT_RAW", ts, **pwm)
    ta = np.arange(0.0, duration_s, 1 / att_rate_hz) + 0.011
    if with_att:
        series["ATTITUDE"] = make_series(
            "ATTITUDE", ta, roll_rad=0.02 + 0.01 * np.sin(ta), pitch_rad=-0.03 + 0.01 * np.cos(ta),
            yaw_rad=np.full(ta.size, yaw_rad), p_rad_s=0.01 * np.cos(ta), q_rad_s=-0.01 * np.sin(ta),
            r_rad_s=0.06 * np.sin(2.3 * ta))  # yaw corrections: a flying aircraft moves (prepare asks for
        # body motion or rotor vibration where only height says "in the air")
    tp = np.arange(0.0, duration_s, 1 / pos_rate_hz) + 0.005
    vx = np.full(tp.size, vel_ned[0])
    vy = np.full(tp.size, vel_ned[1])
    vz = np.full(tp.size, vel_ned[2])
    if vel_nan_after_s is not None:
        for v in (vx, vy, vz):
            v[tp > vel_nan_after_s] = np.nan
    z = -np.clip((tp - 2.0) * 2.0, 0.0, 5.0) if z_of_t is None else z_of_t(tp)
    series["LOCAL_POSITION_NED"] = make_series("LOCAL_POSITION_NED", tp, z_m=z, vx_m_s=vx, vy_m_s=vy, vz_m_s=vz)
    if landed_state:
        tl = np.arange(0.0, duration_s, 1.0)
        series["EXTENDED_SYS_STATE"] = make_series(
            "EXTENDED_SYS_STATE", tl, landed_state=np.where((tl >= 3) & (tl <= duration_s - 3), 2, 1))
    th = np.arange(0.0, duration_s, 1.0)
    series["HEARTBEAT"] = make_series("HEARTBEAT", th, armed=np.ones(th.size))
    if flights is None:
        flights = [FlightInterval(index=0, start_fc_s=0.0, end_fc_s=duration_s, in_air_s=duration_s - 6)]
    return LogData(source="synthetic.tlog", series=series, message_counts={k: len(v) for k, v in series.items()},
                   stats=LinkStats(), flights=flights)


@pytest.fixture
def log_factory():
    return make_log
