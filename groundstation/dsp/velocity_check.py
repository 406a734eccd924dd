"""Do the velocities measure the motion the attitude and height imply? Gravity-tilt and climb checks.

A hovering helicopter moves horizontally by tilting: in body axes ``u' = -g theta + X`` and
``v' = g phi + Y``, where the specific forces X, Y of rotor tilt and drag are linear in the inputs and
the velocity itself. Over each window of ``window_s`` the velocity change from the window's first
sample is regressed on the integrals of the attitude angle, of the moving inputs and of the velocity,
and on elapsed time (a constant acceleration: trim and wind offsets)::

    u(t) - u(0) = k * int theta + sum_j c_j int delta_j + d int u + a t

(the kinematics integrated rather than the velocity differentiated, as in a compatibility analysis:
Klein & Morelli ch. 10). The gravity coefficient k in units of the expected ``-g`` (``+g`` for v) is
the velocity's *scale* against the attitude: about 1 for a velocity that measures this motion, a
scale error of some tens of percent for a miscalibrated one. Its standard error is clustered over
windows (each window's integrated noise is a random walk; windows are nearly independent), so the
verdict is referred to the noise the data themselves show. The vertical velocity is checked the same
way against the height (``h(t) - h(0) = -k int w + a t``, k = 1).

Verdicts, with ``z`` standard errors: *consistent* when the whole interval lies inside
``[1 / max_scale, max_scale]`` (no calibration error makes a velocity read a third of the motion, or
three times it; within that range a scale error is a finding, not a reason to drop the channel);
*contradicted* when the scale differs from 1 significantly and lies outside that range (an estimate
that does not follow the aircraft: a position estimator coasting on a weak GPS, a heading that
drifts in the rotation to body axes); *unconfirmed* when the interval is too wide to say either;
*untested* with fewer than ``min_windows`` windows. Identification fits only consistent or
untested channels (:func:`groundstation.dsp.prepare.prepare` leaves the others out, with a note):
fitting a velocity that does not follow the aircraft spoils the attitude channels it couples to.
Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

G_M_S2 = 9.80665
#: output columns (u v w p q r theta phi) and input columns (lat lon col ped) used here
_U, _V, _THETA, _PHI = 0, 1, 6, 7
#: (velocity column, angle column, sign of g in the gravity term)
_CHANNELS = {"u": (_U, _THETA, -1.0), "v": (_V, _PHI, 1.0)}


@dataclass(frozen=True)
class VelocityCheck:
    """Scale of one velocity channel against the motion the attitude (u, v) or the height (w) implies."""

    channel: str          # "u", "v" or "w"
    scale: float          # measured / implied motion (gravity coefficient / g; 1 / climb coefficient for w)
    se: float             # window-clustered standard error of ``scale``
    windows: int
    #: "consistent" (the interval lies inside the plausible scales), "contradicted" (the scale is
    #: significantly off 1 and outside them), "unconfirmed" (the interval is too wide to say),
    #: "untested" (too few windows)
    verdict: str

    @property
    def usable(self) -> bool:
        """Fit this channel: confirmed by the kinematics, or too little data to test it."""
        return self.verdict in ("consistent", "untested")

    def describe(self) -> str:
        what = "height" if self.channel == "w" else "attitude"
        return (f"{self.channel}: scale {self.scale:.2f} +- {self.se:.2f} against the {what} "
                f"({self.windows} windows of data): {self.verdict}")


def _window_rows(y: np.ndarray, regs: np.ndarray, dt_s: float, L: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Dependent (samples,) and regressors (samples, k) of one window: velocity change and integrals."""
    dy = y - y[0]
    ints = np.cumsum(regs, axis=0) * dt_s
    ints -= ints[0]
    t = np.arange(L) * dt_s
    X = np.column_stack([ints, t])
    return dy[::stride], X[::stride]


def _clustered_ls(rows: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Pooled least squares over windows with the window-clustered (sandwich) covariance."""
    y = np.concatenate([r[0] for r in rows])
    X = np.vstack([r[1] for r in rows])
    scale = np.maximum(np.abs(X).max(axis=0), 1e-12)
    Xs = X / scale
    H = Xs.T @ Xs
    Hinv = np.linalg.pinv(H)
    beta = Hinv @ Xs.T @ y
    M = np.zeros_like(H)
    for yw, Xw in rows:
        g = (Xw / scale).T @ (yw - (Xw / scale) @ beta)
        M += np.outer(g, g)
    G = len(rows)
    cov = Hinv @ M @ Hinv * (G / max(G - 1, 1))
    return beta / scale, np.sqrt(np.maximum(np.diag(cov), 0.0)) / scale


def check_horizontal(segments: list, dt_s: float, *, window_s: float = 4.0, z: float = 3.0,
                     max_scale: float = 3.0, min_windows: int = 8) -> list[VelocityCheck]:
    """One :class:`VelocityCheck` per velocity channel available in ``segments`` (w needs the height).

    ``segments``: objects with ``inputs (n, 4)``, ``outputs (n, 8)`` (u v w p q r theta phi, trim
    removed) and ``available (8,)`` (:class:`groundstation.dsp.prepare.Segment`).
    """
    L = max(int(round(window_s / dt_s)), 5)
    stride = max(1, L // 50)
    out: list[VelocityCheck] = []
    if not segments:
        return out
    moving = np.std(np.vstack([s.inputs for s in segments]), axis=0) > 0
    for name, (vc, ac, sign) in _CHANNELS.items():
        rows = []
        for s in segments:
            if not s.available[vc]:
                continue
            regs = np.column_stack([s.outputs[:, ac], s.inputs[:, moving], s.outputs[:, vc]])
            for k in range(s.n // L):
                sl = slice(k * L, (k + 1) * L)
                if np.all(np.isfinite(regs[sl])) and np.all(np.isfinite(s.outputs[sl, vc])):
                    rows.append(_window_rows(s.outputs[sl, vc], regs[sl], dt_s, L, stride))
        if not rows:
            continue
        if len(rows) < min_windows:
            out.append(VelocityCheck(name, float("nan"), float("nan"), len(rows), "untested"))
            continue
        beta, se = _clustered_ls(rows)
        out.append(_verdict(name, sign * beta[0] / G_M_S2, se[0] / G_M_S2, len(rows), z, max_scale))
    vertical = _check_vertical(segments, dt_s, L, stride, z, max_scale, min_windows)
    return out + ([vertical] if vertical is not None else [])


def _verdict(name: str, scale: float, s_se: float, windows: int, z: float, max_scale: float) -> VelocityCheck:
    lo, hi = scale - z * s_se, scale + z * s_se
    if not (np.isfinite(s_se) and s_se > 0):
        verdict = "unconfirmed"
    elif 1.0 / max_scale <= lo and hi <= max_scale:
        verdict = "consistent"
    elif abs(scale - 1.0) > z * s_se and not 1.0 / max_scale <= scale <= max_scale:
        verdict = "contradicted"
    else:
        verdict = "unconfirmed"
    return VelocityCheck(name, float(scale), float(s_se), windows, verdict)


def _check_vertical(segments: list, dt_s: float, L: int, stride: int, z: float, max_scale: float,
                    min_windows: int) -> VelocityCheck | None:
    """w against the height: ``h(t) - h(0) = -k int w + a t`` (k = 1 when w measures the climb rate)."""
    rows = []
    for s in segments:
        if not s.available[2]:
            continue
        alt = np.asarray(s.alt_m, dtype=float)
        for k in range(s.n // L):
            sl = slice(k * L, (k + 1) * L)
            w, h = s.outputs[sl, 2], alt[sl]
            if np.all(np.isfinite(w)) and np.all(np.isfinite(h)):
                rows.append(_window_rows(h, w[:, None], dt_s, L, stride))
    if not rows:
        return None
    if len(rows) < min_windows:
        return VelocityCheck("w", float("nan"), float("nan"), len(rows), "untested")
    beta, se = _clustered_ls(rows)
    k, k_se = -beta[0], se[0]  # height change per integrated w: 1 / (w's scale)
    if not np.isfinite(k) or abs(k) < 1e-9:
        return VelocityCheck("w", float("nan"), float("nan"), len(rows), "unconfirmed")
    return _verdict("w", 1.0 / k, k_se / k ** 2, len(rows), z, max_scale)
