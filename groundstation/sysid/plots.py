"""Matplotlib figures for identification: measured vs model per channel, convergence curves.

Functions take data and an output path and write one PNG; they are called from the commands only
(``identify``, ``validate``, ``bench identify``) - the pure packages never plot.

Each figure is a :class:`matplotlib.figure.Figure` on a ``FigureCanvasAgg`` (no pyplot: no figure
registry, nothing to close). They are drawn after every identification, so they are kept cheap where
matplotlib spends its time: fixed margins (no tight or constrained layout, which draw the figure once
more to measure it), axis labels at fixed positions (else every tick label is measured to place them),
a few ticks, text above each panel rather than a title, one line per series with the windows separated
by NaN gaps, and the PNG at zlib level 1.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from groundstation.sysid.model import OUTPUT_UNITS, OUTPUTS

DPI = 90


def draw(job: tuple[str, tuple, dict]) -> Path:
    """One figure of a list, ``(function name, args, kwargs)``: a map over worker processes
    (:func:`groundstation.parallel.worker_map`) draws a command's figures side by side."""
    name, args, kwargs = job
    return globals()[name](*args, **kwargs)


def _figure(figsize: tuple[float, float]) -> Any:
    """A matplotlib Figure drawn by Agg, outside pyplot."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: str | Path) -> Path:
    """Write ``fig`` (one draw); a PNG at zlib level 1: a third less encoding time than PIL's default
    6 for about 8 % more bytes (line plots compress well at any level)."""
    p = Path(path)
    png = p.suffix.lower() in ("", ".png")
    fig.savefig(p, dpi=DPI, **({"pil_kwargs": {"compress_level": 1}} if png else {}))
    return p


def plot_fit(series: dict[str, Any], metrics: dict[str, dict[str, float]], path: str | Path, *,
             title: str = "", max_windows: int = 20) -> Path:
    """Measured vs model per output channel.

    Parameters
    ----------
    series : {"t_s": (W, L), "y": (W, L, 8), "yhat": (W, L, 8)} from ``validate(..., return_series=True)``
    metrics : per-channel {"match", "fit", "tic"}
    """
    from matplotlib.ticker import MaxNLocator

    t, y, yhat = series["t_s"], series["y"], series["yhat"]
    W = min(t.shape[0], max_windows)
    chans = [c for c in OUTPUTS if c in metrics]
    fig = _figure((11, 1.7 * len(chans) + 0.8))
    axes = fig.subplots(len(chans), 1, squeeze=False, sharex=True)[:, 0]
    # one line per series, the windows separated by a NaN gap (as many lines as windows drew the
    # same picture at ~10x the rendering time)
    gap = np.full((W, 1), np.nan)
    tt = np.hstack([t[:W], gap]).ravel()
    for k, (ax, ch) in enumerate(zip(axes, chans, strict=True)):
        j = OUTPUTS.index(ch)
        ax.plot(tt, np.hstack([y[:W, :, j], gap]).ravel(), color="0.3", lw=0.8, label="measured")
        ax.plot(tt, np.hstack([yhat[:W, :, j], gap]).ravel(), color="C1", lw=0.9, label="model")
        m = metrics[ch]
        ax.set_ylabel(f"{ch} [{OUTPUT_UNITS[ch]}]")
        ax.yaxis.set_label_coords(-0.07, 0.5)
        ax.text(0.0, 1.03, f"{ch}: match {m['match']:.1f}%  fit {m['fit']:.1f}%  TIC {m['tic']:.2f}", fontsize=8,
                transform=ax.transAxes, va="bottom")
        ax.yaxis.set_major_locator(MaxNLocator(4))
        if k < len(chans) - 1:   # time ticks on the bottom panel only (the panels share the time range)
            ax.xaxis.set_visible(False)
    if W:
        axes[0].set_xlim(float(np.nanmin(tt)), float(np.nanmax(tt)))
    axes[0].legend(loc="upper right", fontsize=7)
    axes[-1].set_xlabel("FC time [s] (windows, each restarted from its initial state)")
    if title:
        fig.suptitle(title, fontsize=10)
    h = fig.get_figheight()
    fig.subplots_adjust(left=1.0 / 11, right=1 - 0.2 / 11, bottom=0.55 / h, top=1 - (0.55 if title else 0.3) / h,
                        hspace=0.45)
    return _save(fig, path)


def plot_convergence(curves: dict[str, list[tuple[np.ndarray, np.ndarray]]], path: str | Path, *,
                     title: str = "Fitness 1/(1+F) vs evaluations (median and range over seeds)") -> Path:
    """Figure-11-style curves: for each algorithm a list of (nfev, best cost) runs."""
    fig = _figure((8, 4.5))
    ax = fig.subplots()
    for k, (name, runs) in enumerate(curves.items()):
        if not runs:
            continue
        grid = np.linspace(max(float(r[0][0]) for r in runs), min(float(r[0][-1]) for r in runs), 200)
        fit = np.array([1.0 / (1.0 + np.interp(grid, r[0], r[1])) for r in runs])
        ax.plot(grid, np.nanmedian(fit, axis=0), color=f"C{k}", label=name.upper())
        ax.fill_between(grid, np.nanmin(fit, axis=0), np.nanmax(fit, axis=0), color=f"C{k}", alpha=0.15)
    ax.set_xlabel("cost evaluations")
    ax.set_ylabel("fitness 1/(1+F)")
    ax.yaxis.set_label_coords(-0.08, 0.5)
    ax.set_title(title, fontsize=9)
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.1, right=0.97, bottom=0.12, top=0.92)   # fixed margins: no second draw
    return _save(fig, path)
