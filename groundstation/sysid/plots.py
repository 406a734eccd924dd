"""Matplotlib figures for identification: measured vs model per channel, convergence curves.

Functions take data and an output path and write one PNG (Agg backend); they are called from the
commands only (``identify``, ``validate``, ``bench identify``) - the pure packages never plot.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from groundstation.sysid.model import OUTPUT_UNITS, OUTPUTS


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_fit(series: dict[str, Any], metrics: dict[str, dict[str, float]], path: str | Path, *,
             title: str = "", max_windows: int = 20) -> Path:
    """Measured vs model per output channel.

    Parameters
    ----------
    series : {"t_s": (W, L), "y": (W, L, 8), "yhat": (W, L, 8)} from ``validate(..., return_series=True)``
    metrics : per-channel {"match", "fit", "tic"}
    """
    plt = _plt()
    t, y, yhat = series["t_s"], series["y"], series["yhat"]
    W = min(t.shape[0], max_windows)
    chans = [c for c in OUTPUTS if c in metrics]
    fig, axes = plt.subplots(len(chans), 1, figsize=(11, 1.7 * len(chans) + 0.8), sharex=True, squeeze=False)
    for ax, ch in zip(axes[:, 0], chans, strict=True):
        j = OUTPUTS.index(ch)
        # one line per series, the windows separated by a NaN gap (as many lines as windows drew the
        # same picture at ~10x the rendering time)
        gap = np.full((W, 1), np.nan)
        tt = np.hstack([t[:W], gap]).ravel()
        ax.plot(tt, np.hstack([y[:W, :, j], gap]).ravel(), color="0.3", lw=0.8, label="measured")
        ax.plot(tt, np.hstack([yhat[:W, :, j], gap]).ravel(), color="C1", lw=0.9, label="model")
        m = metrics[ch]
        ax.set_ylabel(f"{ch} [{OUTPUT_UNITS[ch]}]")
        ax.set_title(f"{ch}: match {m['match']:.1f}%  fit {m['fit']:.1f}%  TIC {m['tic']:.2f}", fontsize=8, loc="left")
    axes[0, 0].legend(loc="upper right", fontsize=7)
    axes[-1, 0].set_xlabel("FC time [s] (windows, each restarted from its initial state)")
    if title:
        fig.suptitle(title, fontsize=10)
    # fixed margins (inches) instead of tight_layout, which draws the figure once more to measure it
    h = fig.get_figheight()
    fig.subplots_adjust(left=1.0 / 11, right=1 - 0.2 / 11, bottom=0.55 / h, top=1 - (0.55 if title else 0.3) / h,
                        hspace=0.45)
    p = Path(path)
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p


def plot_convergence(curves: dict[str, list[tuple[np.ndarray, np.ndarray]]], path: str | Path, *,
                     title: str = "Fitness 1/(1+F) vs evaluations (median and range over seeds)") -> Path:
    """Figure-11-style curves: for each algorithm a list of (nfev, best cost) runs."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for k, (name, runs) in enumerate(curves.items()):
        if not runs:
            continue
        grid = np.linspace(max(float(r[0][0]) for r in runs), min(float(r[0][-1]) for r in runs), 200)
        fit = np.array([1.0 / (1.0 + np.interp(grid, r[0], r[1])) for r in runs])
        med = np.nanmedian(fit, axis=0)
        ax.plot(grid, med, color=f"C{k}", label=name.upper())
        ax.fill_between(grid, np.nanmin(fit, axis=0), np.nanmax(fit, axis=0), color=f"C{k}", alpha=0.15)
    ax.set_xlabel("cost evaluations")
    ax.set_ylabel("fitness 1/(1+F)")
    ax.set_title(title, fontsize=9)
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    p = Path(path)
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p
