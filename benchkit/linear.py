"""An unconstrained linear predictor from the logged inputs: what any linear model could predict.

``linear_heldout(train, val, window_s=5.0)`` fits, per output channel, a predictor of each
``window_s`` window from

* every moving input over lags ``lags_s`` (-0.3 to +1.5 s every 80 ms: before and after the sample,
  so a time skew between the channels costs it nothing), as logged and integrated from the window's
  start (an attitude is the integral of a rate);
* the measured outputs at the window's start, each times 11 hat functions of the time since it
  (the free response from where the aircraft is);
* a constant;

by least squares on the training part's windows (one every second), and scores it by eq. 19 on the
held-out part's non-overlapping windows (the bench's). On each window an offset and a linear trend
per channel are estimated from the window itself (removed by projection in the fit and in the
score): two unknowns per channel and window, more than the unmeasured states the hover model
(flapping states, yaw-gyro state) or the command-response structure (the controller's trim) estimate;
``window_unknowns=False`` leaves them out (the start state only, nothing from the window's own outputs).
Hundreds of coefficients per channel and no structure at all: held out, it says how much of each
channel a linear function of the logged inputs and the start state carries, a ceiling to judge the
physical structures against, not a model to fly.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from groundstation.sysid.model import OUTPUTS


def _detrend(a: np.ndarray, grp: np.ndarray) -> np.ndarray:
    """``a`` (n, ...) minus its least-squares offset and trend within each window ``grp``."""
    out = np.array(a, dtype=float)
    for g in np.unique(grp):
        i = np.flatnonzero(grp == g)
        B = np.column_stack([np.ones(i.size), np.arange(i.size) / max(i.size, 1)])
        c, *_ = np.linalg.lstsq(B, out[i], rcond=None)
        out[i] -= B @ c
    return out


def _design(prepared: Any, chans: list[int], active: list[int], lags: np.ndarray, W: int,
            step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Regressors (n, k), outputs (n, c), measured mask (n, c) and window label (n,) of every window."""
    tau = np.arange(W)
    knots = np.linspace(0, W - 1, 11)
    phi = np.maximum(0.0, 1.0 - np.abs(tau[:, None] - knots[None]) / (knots[1] - knots[0]))  # (W, 11)
    X: list[np.ndarray] = []
    Y: list[np.ndarray] = []
    M: list[np.ndarray] = []
    G: list[np.ndarray] = []
    for s in prepared.segments:
        mask = s.measured_mask()[:, chans]
        for a in range(0, s.n - W + 1, step):
            idx = a + tau
            fir = [s.inputs[np.clip(idx[:, None] - lags[None], 0, s.n - 1), j] for j in active]
            fir += [np.cumsum(c, axis=0) * prepared.dt_s for c in fir]
            y0 = np.nan_to_num(s.outputs[a, chans])
            X.append(np.hstack(fir + [(y0[None, :, None] * phi[:, None, :]).reshape(W, -1), np.ones((W, 1))]))
            y = s.outputs[idx][:, chans]
            Y.append(y)
            M.append(mask[idx] & np.isfinite(y))
            G.append(np.full(W, len(G)))
    return np.vstack(X), np.vstack(Y), np.vstack(M), np.concatenate(G)


def linear_heldout(train: Any, val: Any, *, window_s: float = 5.0,
                   lags_s: tuple[float, float, float] = (-0.3, 1.5, 0.08), window_unknowns: bool = True) -> dict[str, Any]:
    """Held-out eq.-19 match per channel of the unconstrained linear predictor (module docstring);
    ``window_unknowns=False``: no offset or trend from a window's own outputs (the start state only)."""
    detrend = _detrend if window_unknowns else (lambda a, grp: np.asarray(a, dtype=float))
    dt = train.dt_s
    W = int(round(window_s / dt))
    lags = np.round(np.arange(lags_s[0], lags_s[1] + 1e-9, lags_s[2]) / dt).astype(int)
    active = [j for j in range(4) if train.input_active[j]]
    chans = [j for j, _ in enumerate(OUTPUTS) if train.available[j] and val.available[j]]
    match: dict[str, float] = {}
    with threadpool_limits(1):
        Xt, Yt, Mt, Gt = _design(train, chans, active, lags, W, max(1, int(round(1.0 / dt))))
        Xv, Yv, Mv, Gv = _design(val, chans, active, lags, W, W)
        for k, j in enumerate(chans):
            mt, mv = Mt[:, k], Mv[:, k]
            if mv.sum() < W:
                continue
            h, *_ = np.linalg.lstsq(detrend(Xt[mt], Gt[mt]), detrend(Yt[mt, k], Gt[mt]), rcond=None)
            e = detrend(Yv[mv, k] - Xv[mv] @ h, Gv[mv])
            match[OUTPUTS[j]] = float(100.0 * (1.0 - np.linalg.norm(e) / np.linalg.norm(Yv[mv, k])))
    return {"match": match, "mean": float(np.mean(list(match.values()))) if match else float("nan"),
            "runaway": [], "unstable": []}
