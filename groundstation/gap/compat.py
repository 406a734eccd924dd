"""Data compatibility (flight-path reconstruction) before blame: are the sensors consistent with each other?

Kinematic consistency checks that need no model of the aircraft, only rigid-body kinematics
(Klein & Morelli, *Aircraft System Identification*, ch. 10; SIDPAC's compatibility analysis):

* roll and pitch rate gyros against the Euler angles (``phi_dot = p + tan(theta)(q sin(phi) +
  r cos(phi))``, ``theta_dot = q cos(phi) - r sin(phi)``): per gyro a bias, a scale factor and a time
  shift between the rate and the attitude samples;
* the vertical velocity against the height (``h_dot = -v_down``, ``v_down`` from the body velocities
  and the attitude): a velocity scale factor, a bias and a time shift between height and velocity.

The kinematics are integrated rather than the angles differentiated (differentiation amplifies the
angle noise and biases the regression): over each window of ``window_s``, the measured angle
minus the integral of its measured-rate prediction is regressed on the window's own constant,
elapsed time (bias), the integral of the measured rate (scale factor) and the rate itself (time
shift). Standard errors are cluster-robust over windows (the integrated gyro noise is a random
walk inside a window; windows are nearly independent), so every statistic is referred to the noise
the data themselves show. The yaw gyro needs the heading, which the prepared data do not carry: it
is reported as not testable.

* the horizontal velocities against the attitude (``u' = -g theta + ...``, ``v' = g phi + ...``: a
  hovering helicopter accelerates by tilting), measured by :mod:`groundstation.dsp.velocity_check`
  (the gravity coefficient over g is the velocity's scale, with a window-clustered standard error)
  and passed in as ``horizontal``. A velocity sensor's scale error (a GPS or position-estimate
  velocity scaled in the navigation frame) scales u and v alike, so a horizontal finding needs
  both: each significantly off 1 in the same direction and the two consistent with one scale (their
  difference within ``z_agree`` combined standard errors); the finding is their inverse-variance mean.

A scale factor is a *finding* when it is significant (family-wise ``alpha`` over every estimate
made) and matters: the error it makes on its channel (scale x rms of the channel) is above the
channel's measured white-noise level, or, for a rate gyro, the error it makes where it is tested
(scale x the rms of the rate integrated over a window: the attitude drift) is above the angle's
measured white-noise level. Pure numpy/scipy; no IO.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.evaluate import SegmentArrays

U, V, W, P, Q, R, THETA, PHI = range(8)


@dataclass(frozen=True)
class Estimate:
    """One compatibility parameter: value, cluster-robust standard error, two-sided p-value."""

    sensor: str  # "p", "q", "w", "u", "v"
    parameter: str  # "scale", "bias", "shift_s"
    value: float
    se: float
    p_value: float


@dataclass(frozen=True)
class Finding:
    """A sensor error the kinematics show, large enough to matter."""

    kind: str  # "gyro_scale" | "velocity_scale"
    channel: str  # "p", "q", "w", or "u,v" (horizontal velocities together)
    estimate: float  # scale error (measured = (1 + e) x true)
    se: float
    p_value: float
    effect_to_noise: float  # |e| x rms(channel) / measured white noise of the channel
    evidence: str


@dataclass(frozen=True)
class Compatibility:
    """Every estimate made, the findings among them, and what could not be tested (and why)."""

    estimates: tuple[Estimate, ...]
    findings: tuple[Finding, ...]
    untestable: dict[str, str]

    def scale_corrections(self) -> dict[int, float]:
        """Output column -> factor that undoes each found scale error (velocity: u, v, w together)."""
        out: dict[int, float] = {}
        # a vertical finding stands for u and v too unless they were measured themselves (they come after)
        for f in sorted(self.findings, key=lambda f: f.channel == "u,v"):
            fac = 1.0 / (1.0 + f.estimate)
            if f.kind == "velocity_scale":
                cols: tuple[int, ...] = (U, V) if f.channel == "u,v" else (U, V, W)
            else:
                cols = ("pq".index(f.channel) + P,)
            for c in cols:
                out[c] = fac
        return out


def _cumint(x: np.ndarray, dt_s: float) -> np.ndarray:
    """Trapezoidal running integral from the first sample, same length."""
    return np.concatenate([[0.0], np.cumsum(0.5 * (x[1:] + x[:-1]) * dt_s)])


def _windows(n: int, length: int) -> list[slice]:
    k = n // length
    return [slice(i * length, (i + 1) * length) for i in range(k)]


def _regress(rows: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, int]:
    """OLS with one intercept per window; cluster-robust covariance over windows.

    ``rows``: per window (y (n,), X (n, k)). Returns (beta (k,), cov (k, k), number of windows).
    """
    ys, Xs = [], []
    for y, X in rows:
        ys.append(y - y.mean())
        Xs.append(X - X.mean(axis=0))
    Xa, ya = np.concatenate(Xs), np.concatenate(ys)
    XtX = Xa.T @ Xa
    inv = np.linalg.pinv(XtX)
    beta = inv @ Xa.T @ ya
    meat = np.zeros_like(XtX)
    for y, X in zip(ys, Xs, strict=True):
        g = X.T @ (y - X @ beta)
        meat += np.outer(g, g)
    G = len(rows)
    k = Xa.shape[1]
    # small-sample correction of the cluster-robust (CR1) estimator
    corr = G / max(G - 1, 1) * (ya.size - 1) / max(ya.size - k - G, 1)
    return beta, corr * inv @ meat @ inv, G


def _lever(rows: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """RMS over windows of the integrated measured rate (the scale regressor, window means removed)."""
    x = np.concatenate([X[:, 1] - X[:, 1].mean() for _, X in rows])
    return float(np.sqrt(np.mean(x ** 2))) if x.size else 0.0


def _estimates(sensor: str, names: tuple[str, ...], beta: np.ndarray, cov: np.ndarray, G: int) -> list[Estimate]:
    out = []
    for i, name in enumerate(names):
        se = float(np.sqrt(max(cov[i, i], 0.0)))
        t = beta[i] / se if se > 0 else 0.0
        out.append(Estimate(sensor, name, float(beta[i]), se, float(2 * stats.t.sf(abs(t), max(G - 1, 1)))))
    return out


def _gyro_rows(segs: list[SegmentArrays], trims: np.ndarray, dt_s: float, L: int, axis: str
               ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per window: angle minus integrated kinematic rate, and the regressors (time, int rate, rate)."""
    rows = []
    for s in segs:
        y = s.outputs_raw + trims
        p, q, r, th, ph = y[:, P], y[:, Q], y[:, R], y[:, THETA], y[:, PHI]
        if axis == "p":
            rate, ang = p, ph
            f = p + np.tan(th) * (q * np.sin(ph) + r * np.cos(ph))
        else:
            rate, ang = q, th
            f = q * np.cos(ph) - r * np.sin(ph)
        for w in _windows(len(f), L):
            t = np.arange(L) * dt_s
            fi = _cumint(f[w], dt_s)
            X = np.column_stack([-t, -_cumint(rate[w], dt_s), -f[w]])  # bias, scale, shift
            rows.append((ang[w] - fi, X))
    return rows


def _vertical_rows(segs: list[SegmentArrays], trims: np.ndarray, dt_s: float, L: int
                   ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per window: height plus integrated down velocity, and the regressors (time, int v_down, v_down)."""
    rows = []
    for s in segs:
        if not np.isfinite(s.alt_m).all():
            continue
        y = s.outputs_raw + trims
        u, v, w, th, ph = y[:, U], y[:, V], y[:, W], y[:, THETA], y[:, PHI]
        vd = -np.sin(th) * u + np.sin(ph) * np.cos(th) * v + np.cos(ph) * np.cos(th) * w
        for sl in _windows(len(vd), L):
            t = np.arange(L) * dt_s
            ivd = _cumint(vd[sl], dt_s)
            # h_m = -int(v_d)/(1+e) - b t + tau v_d  ->  h_m + int(v_d) = e int(v_d) - b t + tau v_d
            X = np.column_stack([-t, ivd, vd[sl]])
            rows.append((s.alt_m[sl] + ivd, X))
    return rows


def _horizontal(horizontal: Sequence[Any], segs: list[SegmentArrays], sigma_raw: np.ndarray,
                z_agree: float) -> tuple[list[Estimate], tuple[float, float, float, float] | None]:
    """Estimates of the u and v scale errors (``e = scale - 1``), and their pooled (e, se, p, effect to
    noise) when both are measured and agree on one scale (None otherwise)."""
    ests = []
    by = {}
    for h in horizontal:
        if h.channel not in ("u", "v") or not (np.isfinite(h.scale) and np.isfinite(h.se) and h.se > 0):
            continue
        e = float(h.scale) - 1.0
        by[h.channel] = (e, float(h.se))
        ests.append(Estimate(h.channel, "scale", e, float(h.se), float(2 * stats.norm.sf(abs(e) / h.se))))
    if len(by) < 2:
        return ests, None
    (eu, su), (evv, sv) = by["u"], by["v"]
    if abs(eu - evv) > z_agree * np.hypot(su, sv):
        return ests, None
    wu, wv = 1.0 / su ** 2, 1.0 / sv ** 2
    e = (wu * eu + wv * evv) / (wu + wv)
    se = float(np.sqrt(1.0 / (wu + wv)))
    x = np.concatenate([s.outputs_raw[:, [U, V]] for s in segs])
    rms = np.sqrt(np.mean((x - x.mean(axis=0)) ** 2, axis=0))
    etn = float(np.max(abs(e) * rms / np.maximum(sigma_raw[[U, V]], 1e-12)))
    p = max(float(2 * stats.norm.sf(abs(eu) / su)), float(2 * stats.norm.sf(abs(evv) / sv)))  # both must be off 1
    return ests, (float(e), se, p, etn)


def check(segs: list[SegmentArrays], available: np.ndarray, dt_s: float, sigma_raw: np.ndarray,
          trims: np.ndarray | None = None, *, window_s: float = DiagnoseConfig.compat_window_s,
          alpha: float = DiagnoseConfig.alpha, min_windows: int = DiagnoseConfig.min_windows,
          min_effect_to_noise: float = DiagnoseConfig.compat_min_effect_to_noise, horizontal: Sequence[Any] = (),
          z_agree: float = DiagnoseConfig.compat_z_agree,
          max_slope: float = DiagnoseConfig.compat_max_slope) -> Compatibility:
    """Kinematic consistency of the gyros and the vertical velocity (see the module docstring).

    ``segs``: in-air segments (raw outputs, trim removed, plus ``trims`` (8,) to make them absolute);
    ``sigma_raw`` (8,) the measured white-noise level of each output (practical relevance);
    ``horizontal``: the horizontal velocity checks (objects with ``channel``, ``scale``, ``se``, as
    :class:`groundstation.dsp.velocity_check.VelocityCheck`), empty when not made.
    """
    tr = np.zeros(8) if trims is None else np.asarray(trims, float)
    L = int(round(window_s / dt_s))
    untestable = {"r": "yaw-rate scale needs the heading, which the prepared data do not carry"}
    h_ests, h_pool = _horizontal(horizontal, segs, sigma_raw, z_agree)
    if len(h_ests) < 2:
        untestable["u,v"] = "needs u and v both measured and checked against the attitude"
    fits: list[tuple[str, list[tuple[np.ndarray, np.ndarray]], int]] = []
    if all(available[c] for c in (P, Q, R, THETA, PHI)):
        fits += [("p", _gyro_rows(segs, tr, dt_s, L, "p"), P), ("q", _gyro_rows(segs, tr, dt_s, L, "q"), Q)]
    else:
        untestable["p,q"] = "needs p, q, r, theta and phi all measured"
    if all(available[c] for c in (U, V, W, THETA, PHI)) and any(np.isfinite(s.alt_m).all() for s in segs):
        fits.append(("w", _vertical_rows(segs, tr, dt_s, L), W))
    else:
        untestable["w"] = "needs u, v, w, the attitude and the height all measured"
    ests: list[Estimate] = []
    scales: list[tuple[str, Estimate, int, float]] = []
    for sensor, rows, col in fits:
        if len(rows) < min_windows:
            untestable[sensor] = f"fewer than {min_windows} windows of {window_s:g} s"
            continue
        beta, cov, G = _regress(rows)
        est3 = _estimates(sensor, ("bias", "scale", "shift_s"), beta, cov, G)
        # the regression measures e' in true = measured (1 - e'); the scale error is e = e' / (1 - e')
        s = est3[1]
        if not abs(s.value) < max_slope or not np.isfinite(s.se) or s.se <= 0:
            pair = "height and vertical velocity" if sensor == "w" else f"{sensor} gyro and attitude angles"
            untestable[sensor] = (f"{pair} do not agree kinematically (slope {s.value:+.2f}): one is not the "
                                  "integral of the other here (e.g. a height that is held, filtered or missing)")
            continue
        est3[1] = Estimate(sensor, "scale", s.value / (1.0 - s.value), s.se / (1.0 - s.value) ** 2, s.p_value)
        ests += est3
        scales.append((sensor, est3[1], col, _lever(rows)))
    ests += h_ests
    crit = alpha / max(len(ests), 1)
    findings = []
    if h_pool is not None and h_pool[2] < crit and h_pool[3] > min_effect_to_noise:
        he, hse, hp, hetn = h_pool
        findings.append(Finding("velocity_scale", "u,v", he, hse, hp, hetn,
                                f"horizontal velocities against the attitude (gravity tilt): u and v agree on a scale "
                                f"error {100 * he:+.1f} % +- {100 * hse:.1f} % (p={hp:.2g}); the error it makes is "
                                f"{hetn:.1f}x the channels' noise"))
    for sensor, e, col, lever in scales:
        x = np.concatenate([s.outputs_raw[:, col] for s in segs])
        rms = float(np.sqrt(np.mean((x - x.mean()) ** 2)))
        etn = abs(e.value) * rms / max(float(sigma_raw[col]), 1e-12)
        if sensor in ("p", "q"):
            # the same error seen where it is tested: the attitude the scaled rate integrates to
            # drifts from the measured angle by e x (integral of the rate over a window)
            ang = PHI if sensor == "p" else THETA
            etn = max(etn, abs(e.value) * lever / max(float(sigma_raw[ang]), 1e-12))
        if e.p_value < crit and etn > min_effect_to_noise:
            kind = "velocity_scale" if sensor == "w" else "gyro_scale"
            what = "vertical velocity against the height" if sensor == "w" else f"{sensor} gyro against the Euler angles"
            findings.append(Finding(kind, sensor, e.value, e.se, e.p_value, etn,
                                    f"{what}: scale error {100 * e.value:+.1f} % +- {100 * e.se:.1f} % "
                                    f"(p={e.p_value:.2g}); the error it makes is {etn:.1f}x the channel's noise"))
    return Compatibility(tuple(ests), tuple(findings), untestable)
