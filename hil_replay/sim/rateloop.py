"""A stabiliser between the sticks and the swashplate: the simulated flybarless unit's rate loop.

With a :class:`RateLoop` the simulated session logs the pilot's sticks (what SERVO_OUTPUT_RAW
carries becomes a rate demand, as when a team logs RC channels) and the swashplate gets what a
model-following rate loop makes of them, per axis (this simulator's naming, the paper's: ``lat``
drives the longitudinal flapping ``a_s`` and so the pitch rate ``q``; ``lon`` the roll rate ``p``;
``ped`` the yaw rate ``r``; the collective passes through)::

    d(t)       = stick(t - delay_s)                                (processing and link delay)
    ref'       = bandwidth_rad_s * (K * d - ref)                    (first-order command model)
    blade      = (ref + feedback * (ref - rate)) / G                (feed-forward + proportional)

``G`` is the bare airframe's static rate per unit blade input (``A_lat`` for q, ``B_lon`` for p, the
yaw-gyro loop's static gain for r), so ``feedback`` is dimensionless (the loop gain at low
frequency) and ``K`` the rate demanded per unit stick (``rate_per_unit``; by default ``G``: the pilot,
who flies by the airframe's own model, sees the same aircraft at low frequency). The loop runs at
the 200 Hz integration rate on the true rates.

:func:`closed_loop_truth` is the truth an identification of the stabilised aircraft is checked
against: the linearised closed loop (eq.-8 matrices of the simulator's own dynamics, the loop,
the command model) matched by a first-order-plus-delay equivalent system over 1-12 rad/s (above the translational modes, which the pilot flies; the
low-order equivalent system match of flying-qualities work: Hoh's mismatch, gain in dB and phase in
degrees with 0.0175 weight on the phase, MIL-F-8785C), giving its bandwidth ``1/T_eq`` and equivalent
delay ``tau_eq`` per axis. Pure numpy/scipy; no groundstation imports.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil_replay.sim.aircraft import Aircraft
from hil_replay.sim.dynamics import IDX, eq8_matrices

#: axis -> (input, rate state index in the 15-state vector)
AXES: dict[str, tuple[str, int]] = {"pitch": ("lat", IDX["q"]), "roll": ("lon", IDX["p"]), "yaw": ("ped", IDX["r"])}
_IN = {"lat": 0, "lon": 1, "col": 2, "ped": 3}


@dataclass(frozen=True)
class RateLoop:
    """Settings of the simulated stabiliser (see the module docstring)."""

    bandwidth_rad_s: float = 5.0
    delay_s: float = 0.08
    feedback: float = 8.0
    #: rad/s of rate demanded per unit of stick, per axis; an axis not given demands the bare airframe's
    #: static rate per unit (its sign too): the pilot, who flies by the aircraft's own model, then
    #: sees the same aircraft at low frequency, a crisper one above
    rate_per_unit: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.bandwidth_rad_s > 0 or not self.delay_s >= 0 or not self.feedback >= 0:
            raise ValueError(f"rate loop: bandwidth_rad_s {self.bandwidth_rad_s} > 0, delay_s {self.delay_s} >= 0 "
                             f"and feedback {self.feedback} >= 0 needed")


def static_gains(ac: Aircraft) -> dict[str, float]:
    """Bare airframe's static rate per unit blade input of each axis (rad/s per unit)."""
    P = ac.parameters
    Av, Bv = np.array(eq8_matrices(P)[2]), np.array(eq8_matrices(P)[3])
    # yaw: the r, r_fb subsystem at steady state (heave decoupled for this purpose)
    A2, B2 = Av[1:, 1:], Bv[1:, 1]
    r_ss = float(-np.linalg.solve(A2, B2)[0])
    return {"pitch": float(P["A_lat"]), "roll": float(P["B_lon"]), "yaw": r_ss}


def command_gains(ac: Aircraft, loop: RateLoop) -> dict[str, float]:
    """Rate demanded per unit stick of each axis (rad/s per unit): the loop's, else the airframe's static gain."""
    G = static_gains(ac)
    return {a: float(loop.rate_per_unit.get(a, G[a])) for a in AXES}


class RateLoopState:
    """The running loop: delayed sticks, command-model states; ``blade(stick, x)`` once per tick."""

    def __init__(self, loop: RateLoop, ac: Aircraft, dt_s: float) -> None:
        self.loop = loop
        self.G = static_gains(ac)
        self.K = command_gains(ac, loop)
        self.dt = float(dt_s)
        self.alpha = 1.0 - math.exp(-loop.bandwidth_rad_s * dt_s)
        self.ref = {a: 0.0 for a in AXES}
        self.hist: deque[tuple[float, ...]] = deque(maxlen=int(loop.delay_s / dt_s) + 3)
        self.lag = loop.delay_s / dt_s

    def blade(self, stick: list[float], x: list[float]) -> list[float]:
        """Normalised swashplate inputs (lat lon col ped) for the sticks and the true state ``x``."""
        self.hist.append(tuple(stick))
        d = _delayed(self.hist, self.lag)
        out = list(stick)
        for a, (inp, k) in AXES.items():
            j = _IN[inp]
            self.ref[a] += self.alpha * (self.K[a] * d[j] - self.ref[a])
            out[j] = (self.ref[a] + self.loop.feedback * (self.ref[a] - x[k])) / self.G[a]
        return out


def _delayed(hist: deque[tuple[float, ...]], lag_ticks: float) -> tuple[float, ...]:
    n = len(hist)
    i = int(lag_ticks)
    fr = lag_ticks - i
    a = hist[max(0, n - 1 - i)]
    b = hist[max(0, n - 2 - i)]
    return tuple((1.0 - fr) * p + fr * q for p, q in zip(a, b, strict=False))


def closed_loop_response(ac: Aircraft, loop: RateLoop, axis: str, w_rad_s: np.ndarray) -> np.ndarray:
    """Complex stick-to-rate frequency response of the linearised closed loop (delay included; the
    200 Hz loop taken as continuous)."""
    P = ac.parameters
    G = static_gains(ac)
    inp, _ = AXES[axis]
    if axis == "yaw":
        A, B = (np.array(m) for m in eq8_matrices(P)[2:])
        states, rate_i, bcol = 3, 1, 1
    else:
        A, B = (np.array(m) for m in eq8_matrices(P)[:2])
        states, rate_i, bcol = 8, (4 if axis == "pitch" else 5), (0 if inp == "lat" else 1)
    bw, kp, K = loop.bandwidth_rad_s, loop.feedback, command_gains(ac, loop)[axis]
    # augmented state [airframe, ref]; blade = ((1 + kp) ref - kp rate) / G
    n = states + 1
    Acl = np.zeros((n, n))
    Acl[:states, :states] = A
    b = B[:, bcol] / G[axis]
    Acl[:states, :states] -= kp * np.outer(b, np.eye(states)[rate_i])
    Acl[:states, states] = (1 + kp) * b
    Acl[states, states] = -bw
    Bcl = np.zeros(n)
    Bcl[states] = bw * K
    out = np.empty(w_rad_s.size, dtype=complex)
    eye = np.eye(n)
    for i, w in enumerate(w_rad_s):
        xs = np.linalg.solve(1j * w * eye - Acl, Bcl)
        out[i] = xs[rate_i]
    return out * np.exp(-1j * w_rad_s * loop.delay_s)


def closed_loop_truth(ac: Aircraft, loop: RateLoop, band_rad_s: tuple[float, float] = (1.0, 12.0)) -> dict[str, Any]:
    """Per axis: the first-order-plus-delay equivalent system of the closed loop (gain, ``bandwidth_rad_s``
    = 1/T_eq, ``delay_s`` = tau_eq) and its mismatch (Hoh's, sum over 20 log-spaced frequencies)."""
    from scipy.optimize import least_squares  # here: the simulator itself needs no scipy.optimize

    w = np.logspace(np.log10(band_rad_s[0]), np.log10(band_rad_s[1]), 20)
    out: dict[str, Any] = {}
    for axis in AXES:
        h = closed_loop_response(ac, loop, axis, w)

        def res(z: np.ndarray, h: np.ndarray = h) -> np.ndarray:
            K, T, tau = z
            e = K / (1j * w * T + 1) * np.exp(-1j * w * tau)
            dg = 20 * np.log10(np.abs(e) / np.abs(h))
            dp = np.angle(e / h, deg=True)
            return np.concatenate([dg, math.sqrt(0.0175) * dp])

        r = least_squares(res, [float(np.abs(h[0])) * np.sign(h[0].real or 1.0), 1.0 / loop.bandwidth_rad_s,
                                loop.delay_s], bounds=([-100, 1e-3, 0.0], [100, 10.0, 1.0]))
        K, T, tau = (float(v) for v in r.x)
        out[axis] = {"input": AXES[axis][0], "gain": K, "bandwidth_rad_s": 1.0 / T, "delay_s": tau,
                     "mismatch": float(np.sum(r.fun ** 2))}
    return out
