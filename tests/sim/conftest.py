"""Shared helpers of the simulator tests: fly a short session once per process and stack its frames."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from hil_replay.sim import SimulatedSession


@functools.lru_cache(maxsize=16)
def _fly(seed: int, effects: tuple[str, ...], duration_s: float | None, flights: int) -> dict[str, np.ndarray]:
    sess = SimulatedSession(seed=seed, flights=flights, effects=effects, flight_duration_s=duration_s, pause_s=4.0)
    rows = {k: [] for k in ("t", "armed", "state", "cmd", "act", "wind", "rates", "att", "vel", "pos", "landed", "pwm")}
    for fr in sess.frames():
        m = fr.m
        rows["t"].append(fr.t_boot_s)
        rows["armed"].append(fr.armed)
        rows["state"].append(fr.state)
        rows["cmd"].append(fr.command)
        rows["act"].append(fr.actuator)
        rows["wind"].append(fr.wind_ned)
        rows["rates"].append((m.p, m.q, m.r))
        rows["att"].append((m.roll, m.pitch, m.yaw))
        rows["vel"].append((m.vx, m.vy, m.vz))
        rows["pos"].append((m.x, m.y, m.z))
        rows["landed"].append(m.landed_state)
        rows["pwm"].append(m.servo_pwm[:4])
    out = {k: np.array(v) for k, v in rows.items()}
    out["truth"] = sess.truth()  # type: ignore[assignment]
    return out


def ned_velocity(state: np.ndarray) -> np.ndarray:
    """True NED velocity (n, 3) from stacked states (n, 15)."""
    u, v, w, ph, th, ps = (state[:, i] for i in (0, 1, 2, 6, 7, 8))
    sph, cph, sth, cth, sps, cps = np.sin(ph), np.cos(ph), np.sin(th), np.cos(th), np.sin(ps), np.cos(ps)
    vn = cth * cps * u + (sph * sth * cps - cph * sps) * v + (cph * sth * cps + sph * sps) * w
    ve = cth * sps * u + (sph * sth * sps + cph * cps) * v + (cph * sth * sps - sph * cps) * w
    vd = -sth * u + sph * cth * v + cph * cth * w
    return np.stack([vn, ve, vd], axis=1)


def segment_mask(run: dict, prefix: str, trim_s: float = 0.0) -> np.ndarray:
    """Ticks inside card segments whose name starts with ``prefix`` (minus ``trim_s`` at both ends)."""
    t = run["t"]
    mask = np.zeros(t.size, bool)
    for fl in run["truth"]["flights"]:
        for s in fl["segments"]:
            if s["name"].startswith(prefix):
                mask |= (t >= s["start_fc_s"] + trim_s) & (t < s["end_fc_s"] - trim_s)
    return mask


@pytest.fixture(scope="session")
def fly():
    """``fly(seed=0, effects=(), duration_s=60.0, flights=1)`` -> stacked arrays (cached per process)."""

    def _call(seed: int = 0, effects: tuple[str, ...] = (), duration_s: float | None = 60.0, flights: int = 1):
        return _fly(seed, tuple(effects), duration_s, flights)

    return _call


__all__ = ["math", "ned_velocity", "segment_mask"]
