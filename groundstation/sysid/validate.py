"""Validation metrics of a hover model on prepared data: match degree (eq. 19), NRMSE fit, Theil U.

Per channel, over all validation windows (the same windowed simulation with per-window initial
states as the identification, so an identified and a true model are scored the same way):

* ``match_degree``: ``(1 - ||yhat - y|| / ||y||) * 100`` (paper eq. 19);
* ``nrmse``: fit ``(1 - ||yhat - y|| / ||y - mean(y)||) * 100`` (the usual "fit %");
* ``theil_u``: ``rms(yhat - y) / (rms(yhat) + rms(y))`` (0 perfect, 1 useless);
* ``corr``: Pearson correlation of yhat with y (what published fits of the real TREX 550 log
  quote: 0.67-0.90 per channel), blind to a gain error, so never the only figure.

Data are used with their own trims (the validation flight's median PWM is its hover trim). Pure
numpy; printing and JSON are the CLI's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from groundstation.sysid.cost import make_windows
from groundstation.sysid.fit_section import JsonSection
from groundstation.sysid.model import OUTPUTS, HoverModel
from groundstation.sysid.simulate import WindowSimulator


def _flat(yhat: np.ndarray, y: np.ndarray, mask: np.ndarray | None, j: int) -> tuple[np.ndarray, np.ndarray]:
    if yhat.ndim == 1:
        return yhat, y
    if mask is None:
        return yhat[..., j].ravel(), y[..., j].ravel()
    if mask.ndim == 3:  # (W, L, 8): per sample (holes of the link left out)
        return yhat[..., j][mask[..., j]], y[..., j][mask[..., j]]
    return yhat[mask[:, j], :, j].ravel(), y[mask[:, j], :, j].ravel()


def match_degree(yhat: np.ndarray, y: np.ndarray) -> float:
    """Eq. 19 for one channel (arrays of any shape, flattened): percent."""
    yhat, y = np.ravel(yhat), np.ravel(y)
    den = np.linalg.norm(y)
    return float((1.0 - np.linalg.norm(yhat - y) / den) * 100.0) if den > 0 else float("nan")


def nrmse(yhat: np.ndarray, y: np.ndarray) -> float:
    """NRMSE fit for one channel: ``(1 - ||yhat - y|| / ||y - mean y||) * 100``, percent."""
    yhat, y = np.ravel(yhat), np.ravel(y)
    den = np.linalg.norm(y - y.mean()) if y.size else 0.0
    return float((1.0 - np.linalg.norm(yhat - y) / den) * 100.0) if den > 0 else float("nan")


def theil_u(yhat: np.ndarray, y: np.ndarray) -> float:
    """Theil inequality coefficient for one channel (0 = perfect)."""
    yhat, y = np.ravel(yhat), np.ravel(y)
    if y.size == 0:
        return float("nan")
    rms = lambda a: float(np.sqrt(np.mean(a ** 2)))  # noqa: E731
    den = rms(yhat) + rms(y)
    return rms(yhat - y) / den if den > 0 else float("nan")


def pearson(yhat: np.ndarray, y: np.ndarray) -> float:
    """Pearson correlation of one channel (arrays of any shape, flattened); 0 when either is constant."""
    yhat, y = np.ravel(yhat), np.ravel(y)
    a, b = yhat - yhat.mean(), y - y.mean()
    den = float(np.linalg.norm(a) * np.linalg.norm(b))
    return float(a @ b) / den if den > 0 else 0.0


def channel_metrics(yhat: np.ndarray, y: np.ndarray, mask: np.ndarray) -> dict[str, dict[str, float]]:
    """Metrics per used channel; yhat and y (W, L, 8), mask (W, 8) or per sample (W, L, 8)."""
    out: dict[str, dict[str, float]] = {}
    for j, ch in enumerate(OUTPUTS):
        if not mask[..., j].any():
            continue
        a, b = _flat(yhat, y, mask, j)
        out[ch] = {"match": match_degree(a, b), "fit": nrmse(a, b), "tic": theil_u(a, b), "corr": pearson(a, b)}
    return out


@dataclass(frozen=True)
class ChannelScore(JsonSection):
    """One output channel's figures (percent, except Theil U and the correlation)."""

    match: float = float("nan")   # match degree, eq. 19
    fit: float = float("nan")     # NRMSE fit
    tic: float = float("nan")     # Theil U (0 perfect)
    corr: float = 0.0             # Pearson correlation


@dataclass(frozen=True)
class Validation(JsonSection):
    """What :func:`validate` measured; ``to_json()`` is the ``validation`` object of the JSON outputs
    (``groundstation validate --json``, the analysis document), ``series`` the windowed arrays
    behind it (``t_s`` (W, L), ``y`` and ``yhat`` (W, L, 8), ``inputs``) when asked for, never
    written."""

    channels: Mapping[str, ChannelScore] = field(default_factory=dict)
    mean_match: float = float("nan")
    mean_fit: float = float("nan")
    #: sum over the used channels of ||yhat - y|| / ||y - mean y||
    cost: float = float("nan")
    windows: int = 0
    window_s: float = 0.0
    duration_s: float = 0.0
    channels_used: tuple[str, ...] = ()
    series: Mapping[str, np.ndarray] | None = field(default=None, repr=False, compare=False,
                                                    metadata={"json": False})


def validate(model: HoverModel, prepared: Any, *, window_s: float | None = None,
             return_series: bool = False) -> Validation:
    """Score ``model`` on ``prepared`` (validation segments or another flight): the figures per
    channel, their means, the cost, the windows (and ``series`` with the t_s, y and yhat arrays of
    shape (W, L) / (W, L, 8) when ``return_series``).
    """
    ws = float(window_s if window_s is not None else model.fit.window_s or 3.0)
    est_all = model.fit.estimate_all_initial is not False
    with threadpool_limits(1):
        win = make_windows(prepared.segments, prepared.dt_s, ws, key="window_s")
        sim = WindowSimulator(win.inputs, win.outputs, win.dt_s, win.available, estimate_all_initial=est_all,
                              measured=win.measured, window_offsets=model.window_input_offsets)
        yhat = sim.simulate(model.theta[None])[0]
    y = sim.outputs
    mask = sim.smask if sim.holes else sim.mask
    ch = channel_metrics(yhat, y, mask)
    used = [c for c in OUTPUTS if c in ch]
    cost = 0.0
    for j, c in enumerate(OUTPUTS):
        if c in ch:
            a, b = _flat(yhat, y, mask, j)
            cost += float(np.linalg.norm(a - b)) / max(float(np.linalg.norm(b - b.mean())), 1e-300)
    res: dict[str, Any] = {
        "channels": ch,
        "mean_match": float(np.mean([ch[c]["match"] for c in used])) if used else float("nan"),
        "mean_fit": float(np.mean([ch[c]["fit"] for c in used])) if used else float("nan"),
        "cost": cost, "windows": win.count, "window_s": ws, "duration_s": float(win.count * win.length * win.dt_s),
        "channels_used": used,
    }
    series = None
    if return_series:
        t = win.t0_s[:, None] + np.arange(win.length)[None, :] * win.dt_s
        m3 = mask if mask.ndim == 3 else mask[:, None, :]
        series = {"t_s": t, "y": np.where(m3, y, np.nan),
                  "yhat": np.where(sim.mask[:, None, :], yhat, np.nan), "inputs": win.inputs}
    return dataclasses.replace(Validation.from_json(res), series=series)
