"""Fixtures for the gap tests: a small linear eq.-8 flight generator with injectable effects.

This is a test-only stand-in for the hil_replay simulator (which the CLI test uses): the exact linear
model of the paper under a state-feedback pilot with channel-by-channel chirps, so that the
diagnosis statistics can be checked against effects of known size without model-structure error.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.linalg import solve_discrete_are

from groundstation.dsp.smoothing import smooth5
from groundstation.gap.linsim import OUT_STATE, full_matrices
from groundstation.sysid.model import discretize, theta_from_dict

PAPER = dict(X_u=-0.1064, Y_v=-0.02873, M_u=-0.1215, M_v=0.3012, M_q=0.2456, M_a=-1.2648, M_b=-23.1095,
             L_u=1.0106, L_v=-0.9456, L_p=-8.0143, L_a=62.578, L_b=78.3182, k1=0.0510, inv_tau_s=7.2351,
             X_lat=-5.8015, Y_lon=7.2462, M_lat=-4.0126, M_lon=-8.5145, L_lat=9.2156, L_lon=-5.6877,
             A_lat=6.4578, B_lon=-5.2111, Z_w=-0.71048, Z_r=2.0663, N_w=-1.3975, N_r=-0.4905, k_r=4.5578,
             Z_col=-8.0137, Z_ped=7.0868, N_col=11.5558, N_ped=0.7884)
NOISE_SD = np.array([0.03, 0.03, 0.03, 0.01, 0.01, 0.01, 0.003, 0.003])


def linear_flight(T_s: float = 90.0, dt: float = 0.02, seed: int = 0, effect: tuple | None = None,
                  alt: bool = True) -> SimpleNamespace:
    """A prepared-data-like object (segments, dt_s, output_trim) of one linear flight.

    effect: ("input_delay", channel, samples) | ("growing_delay", channel, samples at the end) |
            ("gyro_bias", output index, rad/s) |
            ("drifting_bias", output index, rad/s at the end) |
            ("rotor_vibration", frequency_hz, amplitude) | ("velocity_latency", None, samples) |
            ("deadband", channel, half_width) | ("wind_gust", tau_s, sigma_m_s) (horizontal air velocity,
            Gauss-Markov, entering through the u and v columns of A; the pilot answers it) |
            ("ground_effect", accel_m_s2, decay_m) (an upward force decaying with height above 0.3 m; the
            first half of the flight is flown down to 0.3 m, the second no lower than 1.3 m)
    """
    rng = np.random.default_rng(seed)
    th = theta_from_dict(PAPER)
    A, B = full_matrices(th)
    Ad, Bd = discretize(A, B, dt)
    Ad, Bu = Ad[0], Bd[0][:, :4]
    Q = np.diag([1, 1, 10, 10, 1, 1, 0.1, 0.1, 1, 1, 0.1])
    R = np.eye(4) * 20
    X = solve_discrete_are(Ad, Bu, Q, R)
    K = np.linalg.solve(R + Bu.T @ X @ Bu, Bu.T @ X @ Ad)
    n = int(T_s / dt)
    t = np.arange(n) * dt
    exc = np.zeros((n, 4))
    blk = n // 5
    for c in range(4):
        s = slice(c * blk + 25, (c + 1) * blk)
        tt = t[s] - t[s][0]
        f = 0.2 + 2.5 * tt / tt[-1]
        exc[s, c] = 0.08 * np.sin(2 * np.pi * np.cumsum(f) * dt)
    s = slice(4 * blk, n)
    exc[s] = 0.05 * np.sign(np.sin(2 * np.pi * 0.4 * t[s, None] + rng.uniform(0, 6, 4)))
    height = 3 + 0.5 * np.sin(t / 10)
    if effect and effect[0] == "ground_effect":
        height = np.where(t < t[-1] / 2, 1.1 + 0.8 * np.cos(2 * np.pi * t / 15), 2.3 + np.cos(2 * np.pi * t / 15))
    x = np.zeros(11)
    y = np.zeros((n, 8))
    u = np.zeros((n, 4))
    hist = []
    air = np.zeros(2)
    gust_rng = np.random.default_rng(seed + 1000)
    for k in range(n):
        u[k] = -K @ x + exc[k]
        act = u[k].copy()
        hist.append(u[k].copy())
        if effect and effect[0] == "input_delay":
            act[effect[1]] = hist[max(0, k - effect[2])][effect[1]]
        if effect and effect[0] == "growing_delay":  # from 0 at the start to effect[2] samples at the end
            act[effect[1]] = hist[max(0, k - round(effect[2] * k / n))][effect[1]]
        if effect and effect[0] == "deadband":
            c, b = effect[1], effect[2]
            act[c] = np.sign(act[c]) * max(abs(act[c]) - b, 0.0)
        y[k] = x[OUT_STATE]
        x = Ad @ x + Bu @ act
        if effect and effect[0] == "wind_gust":
            a = np.exp(-dt / effect[1])
            air = a * air + effect[2] * np.sqrt(1 - a * a) * gust_rng.standard_normal(2)
            x = x - dt * (A[0][:, 0] * air[0] + A[0][:, 1] * air[1])  # forces act on airspeed
        if effect and effect[0] == "ground_effect":
            x[8] -= dt * effect[1] * np.exp(-(height[k] - 0.3) / effect[2])  # w is positive down
    if effect and effect[0] == "velocity_latency":
        d = effect[2]
        y[d:, :3] = y[:-d, :3].copy()
    if effect and effect[0] == "gyro_bias":
        y[:, effect[1]] += effect[2]
    if effect and effect[0] == "drifting_bias":  # from 0 at the start to effect[2] at the end
        y[:, effect[1]] += effect[2] * t / t[-1]
    y = y + NOISE_SD * rng.standard_normal(y.shape)
    if effect and effect[0] == "rotor_vibration":
        y[:, 3:6] += effect[2] * np.sin(2 * np.pi * effect[1] * t)[:, None] * np.array([1.0, 0.7, 0.4])
    height = height if alt else np.full(n, np.nan)
    seg = SimpleNamespace(t_s=t, inputs=u, outputs=smooth5(y, 2), outputs_raw=y, alt_m=height,
                          available=np.ones(8, bool), flight=0)
    return SimpleNamespace(segments=[seg], dt_s=dt, notes=[], output_trim={k: 0.0 for k in "u v w p q r theta phi".split()},
                           pwm_per_unit=500.0)


@pytest.fixture(scope="session")
def paper_theta() -> np.ndarray:
    return theta_from_dict(PAPER)


@pytest.fixture(scope="session")
def flight_factory():
    return linear_flight
