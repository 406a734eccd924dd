"""Synthetic pilot: a loose linear-quadratic stabiliser with human-like remnant.

The pilot designs his loops on the aircraft's own eq.-8 model (so any aircraft file flies): a
horizontal LQR on ``[u-u_ref, v-v_ref, theta, phi, q, p, a_s, b_s, x_err, y_err]`` (position errors
in the heading frame) driving ``lat lon``, and a vertical/yaw LQR on ``[w-w_ref, r, r_fb, d_err,
psi_err]`` driving ``col ped``. The weights are modest (Bryson's rule with generous allowed
deviations), so the loop bandwidth stays well below the excitation band and the hover stays in the
linear regime. Per seed the gains are scaled by 0.8-1.2 and a coloured remnant (first-order
Gauss-Markov, a few thousandths of full stick) is added to each channel.

Outputs are normalised inputs ``(lat, lon, col, ped)``; the card adds the excitation and the session
turns the sum into PWM. Leaves to others: the card (references, excitation), PWM, physics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from operator import mul

import numpy as np
from scipy.linalg import solve_continuous_are

from hil_replay.sim.aircraft import Aircraft
from hil_replay.sim.dynamics import eq8_matrices


@dataclass(frozen=True)
class PilotConfig:
    """Allowed deviations (Bryson weights) and remnant of the synthetic pilot."""

    vel_m_s: float = 1.0
    att_rad: float = 0.12
    rate_rad_s: float = 0.6
    pos_m: float = 2.5
    input_units: float = 0.08
    w_m_s: float = 0.6
    r_rad_s: float = 0.5
    height_m: float = 0.6
    heading_rad: float = 0.25
    remnant_units: tuple[float, float] = (0.004, 0.009)
    remnant_tau_s: tuple[float, float] = (0.3, 0.8)
    gain_scale: tuple[float, float] = (0.8, 1.2)
    excited_axis_gain: float = 0.3  # feedback left on the channel the card is exciting


def _lqr(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, what: str) -> np.ndarray:
    try:
        X = solve_continuous_are(A, B, Q, R)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise ValueError(f"{what}: the synthetic pilot cannot stabilise this aircraft ({exc}); "
                         "check the input derivatives in [parameters]") from None
    K = np.linalg.solve(R, B.T @ X)
    if not np.all(np.linalg.eigvals(A - B @ K).real < 0):
        raise ValueError(f"{what}: the synthetic pilot cannot stabilise this aircraft; "
                         "check the input derivatives in [parameters]")
    return K


def design_gains(ac: Aircraft, config: PilotConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """LQR gains ``K_hor (2, 10)`` and ``K_ver (2, 5)`` of the pilot (control = -K e)."""
    c = config or PilotConfig()
    Ah8, Bh8, Av3, Bv3 = (np.array(m) for m in eq8_matrices(ac.parameters))
    Ah = np.zeros((10, 10))
    Ah[:8, :8] = Ah8
    Ah[8, 0] = 1.0
    Ah[9, 1] = 1.0
    Bh = np.zeros((10, 2))
    Bh[:8] = Bh8
    qh = [1 / c.vel_m_s**2] * 2 + [1 / c.att_rad**2] * 2 + [1 / c.rate_rad_s**2] * 2 + [1e-4] * 2 + [1 / c.pos_m**2] * 2
    Kh = _lqr(Ah, Bh, np.diag(qh), np.eye(2) / c.input_units**2, f"aircraft {ac.name} (lat/lon)")
    Av = np.zeros((5, 5))
    Av[:3, :3] = Av3
    Av[3, 0] = 1.0
    Av[4, 1] = 1.0
    Bv = np.zeros((5, 2))
    Bv[:3] = Bv3
    qv = [1 / c.w_m_s**2, 1 / c.r_rad_s**2, 1e-4, 1 / c.height_m**2, 1 / c.heading_rad**2]
    Kv = _lqr(Av, Bv, np.diag(qv), np.eye(2) / c.input_units**2, f"aircraft {ac.name} (col/ped)")
    return Kh, Kv


def wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class Pilot:
    """Stateful pilot (remnant filters); call :meth:`command` once per 50 Hz tick."""

    def __init__(self, ac: Aircraft, rng: np.random.Generator, *, dt_s: float = 0.02,
                 config: PilotConfig | None = None) -> None:
        c = config or PilotConfig()
        Kh, Kv = design_gains(ac, c)
        scale = rng.uniform(*c.gain_scale, size=2)
        self._Kh = (Kh * scale[0]).tolist()
        self._Kv = (Kv * scale[1]).tolist()
        self.remnant_sigma = rng.uniform(*c.remnant_units, size=4).tolist()
        tau = rng.uniform(*c.remnant_tau_s, size=4)
        self._phi = np.exp(-dt_s / tau).tolist()
        self._drive = [s * math.sqrt(1 - a * a) for s, a in zip(self.remnant_sigma, self._phi, strict=False)]
        self._rem = [0.0, 0.0, 0.0, 0.0]
        self._loose = float(c.excited_axis_gain)
        self._rng = rng
        self._buf = np.empty(0)
        self._k = 0

    def _normals(self) -> list[float]:
        if self._k + 4 > self._buf.size:
            self._buf = self._rng.standard_normal(4096)
            self._k = 0
        out = self._buf[self._k:self._k + 4].tolist()
        self._k += 4
        return out

    def remnant(self) -> list[float]:
        z = self._normals()
        self._rem = [a * r + d * e for a, r, d, e in zip(self._phi, self._rem, self._drive, z, strict=False)]
        return self._rem

    def command(self, x: list[float], ref: tuple[float, ...], excited: int | None = None) -> list[float]:
        """Normalised ``[lat, lon, col, ped]`` from the state and ``ref = (n, e, d, psi, vn, ve, vd)``.

        ``excited`` is the input channel (0-3) the card is exciting: the pilot only loosely holds it
        (feedback scaled by ``excited_axis_gain``) instead of fighting the sweep or doublet.
        """
        n_ref, e_ref, d_ref, psi_ref, vn, ve, vd = ref
        psi = x[8]
        cps, sps = math.cos(psi), math.sin(psi)
        # references and position errors in the heading frame (level body axes)
        u_ref = cps * vn + sps * ve
        v_ref = -sps * vn + cps * ve
        dn, de = x[12] - n_ref, x[13] - e_ref
        xe = cps * dn + sps * de
        ye = -sps * dn + cps * de
        eh = (x[0] - u_ref, x[1] - v_ref, x[7], x[6], x[4], x[3], x[9], x[10], xe, ye)
        # a pilot turns gently: heading error and height error felt at most 0.5 rad / 1.5 m
        ev = (x[2] - vd, x[5], x[11], min(1.5, max(-1.5, x[14] - d_ref)),
              min(0.5, max(-0.5, wrap_pi(psi - psi_ref))))
        Kh, Kv = self._Kh, self._Kv
        rem = self.remnant()
        fb = [-sum(map(mul, Kh[0], eh)), -sum(map(mul, Kh[1], eh)),
              -sum(map(mul, Kv[0], ev)), -sum(map(mul, Kv[1], ev))]
        if excited is not None:
            fb[excited] *= self._loose
        return [f + r for f, r in zip(fb, rem, strict=False)]
