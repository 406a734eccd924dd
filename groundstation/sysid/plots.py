"""Figures for identification: measured vs model per channel, convergence curves.

Functions take data and an output path and write one PNG; they are called from the commands only
(``identify``, ``validate``, ``bench identify``) - the pure packages never plot.

The figures are drawn straight onto matplotlib's Agg renderer (:class:`_Canvas`: frames, lines, ticks
and text in pixels), not through a matplotlib Figure and its Axes: these are plain line charts drawn
after every identification, and a Figure costs an import of matplotlib's axes and projections (about
0.12 s of CPU) plus about 0.2 s per figure of tick and text objects; the lines, fonts and colours are
matplotlib's own, the PNG is written by PIL (which matplotlib requires).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from groundstation.sysid.model import OUTPUT_UNITS, OUTPUTS

DPI = 90
GREY, ORANGE = (0.3, 0.3, 0.3, 1.0), (1.0, 0.498, 0.055, 1.0)   # matplotlib's "0.3" and "C1"
#: matplotlib's default cycle, for the convergence curves
CYCLE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f")


def draw(job: tuple[str, tuple, dict]) -> Path:
    """One figure of a list, ``(function name, args, kwargs)``: a map over worker processes
    (:func:`groundstation.parallel.worker_map`) draws a command's figures side by side."""
    name, args, kwargs = job
    return globals()[name](*args, **kwargs)


def _pt(points: float) -> float:
    return points * DPI / 72.0


def _label(v: float, step: float) -> str:
    """A tick label with as many decimals as the tick step needs (0.25: two; matplotlib's minus sign)."""
    dec = 0
    while step > 0 and dec < 12 and abs(round(step, dec) - step) > 1e-9 * step:
        dec += 1
    s = f"{v:.{dec}f}"
    return ("0" if float(s) == 0 else s).replace("-", "\u2212")


class _Canvas:
    """A white ``w_in`` x ``h_in`` inch image on matplotlib's Agg renderer, pixel coordinates from the
    bottom left."""

    def __init__(self, w_in: float, h_in: float) -> None:
        from matplotlib.backends.backend_agg import RendererAgg
        from matplotlib.font_manager import FontProperties

        self._fp = FontProperties
        self.w, self.h = int(round(w_in * DPI)), int(round(h_in * DPI))
        self.r = RendererAgg(self.w, self.h, DPI)
        self.rect((0, 0, self.w, self.h), face=(1, 1, 1, 1), edge=None)

    def _gc(self, color: Any, lw_pt: float, clip: tuple[float, float, float, float] | None = None) -> Any:
        from matplotlib.transforms import Bbox

        gc = self.r.new_gc()
        gc.set_foreground(color, isRGBA=len(color) == 4 and not isinstance(color, str))
        gc.set_linewidth(lw_pt)
        gc.set_antialiased(True)
        gc.set_capstyle("projecting")
        gc.set_joinstyle("round")
        if clip is not None:
            gc.set_clip_rectangle(Bbox.from_bounds(*clip))
        return gc

    def path(self, xy: np.ndarray, color: Any, lw_pt: float, clip: Any = None, face: Any = None,
             alpha: float = 1.0) -> None:
        """A polyline through ``xy`` (N, 2) pixels (NaN rows break it), or a filled polygon with ``face``."""
        from matplotlib.path import Path as MPath
        from matplotlib.transforms import IdentityTransform

        gc = self._gc(color, lw_pt, clip)
        if alpha != 1.0:   # else the colour's own alpha (set_alpha overrides it)
            gc.set_alpha(alpha)
        if face is not None:
            gc.set_linewidth(0)
        self.r.draw_path(gc, MPath(np.asarray(xy, dtype=float)), IdentityTransform(),
                         None if face is None else tuple(face[:3]) + (alpha,))
        gc.restore()

    def rect(self, box: tuple[float, float, float, float], edge: Any = "black", lw_pt: float = 0.8,
             face: Any = None) -> None:
        x, y, w, h = box
        xy = np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h], [x, y]])
        if face is not None:
            self.path(xy, face, 0.0, face=face)
        if edge is not None:
            self.path(xy, edge, lw_pt)

    def size(self, s: str, size_pt: float) -> tuple[float, float, float]:
        """(width, height, descent) of ``s`` in pixels."""
        return self.r.get_text_width_height_descent(s, self._fp(size=size_pt), ismath=False)

    def text(self, x: float, y: float, s: str, size_pt: float = 10.0, ha: str = "left", va: str = "baseline",
             rotation: float = 0.0, color: Any = "black") -> None:
        """``s`` anchored at (x, y) pixels: ``ha`` left|center|right, ``va`` baseline|bottom|center|top
        (rotation 90: read upwards, centred on (x, y)). The renderer places text from the top row."""
        w, h, d = self.size(s, size_pt)
        gc = self._gc(color, 1.0)
        if rotation:
            self.r.draw_text(gc, x + (h - d) / 2, self.h - (y - w / 2), s, self._fp(size=size_pt), rotation)
        else:
            x -= {"left": 0.0, "center": w / 2, "right": w}[ha]
            y += {"baseline": 0.0, "bottom": d, "center": d - h / 2, "top": d - h}[va]
            self.r.draw_text(gc, x, self.h - y, s, self._fp(size=size_pt), 0.0)
        gc.restore()

    def save(self, path: str | Path) -> Path:
        """The PNG at ``path`` (zlib level 1: a third less encoding time than PIL's default for about 8 %
        more bytes; line plots compress well at any level)."""
        from PIL import Image

        p = Path(path)
        img = Image.frombuffer("RGBA", (self.w, self.h), self.r.buffer_rgba(), "raw", "RGBA", 0, 1)
        if p.suffix.lower() in ("", ".png"):
            img.save(p, format="PNG", dpi=(DPI, DPI), compress_level=1)
        else:   # another format PIL writes (by the suffix), without transparency
            img.convert("RGB").save(p, dpi=(DPI, DPI))
        return p


class _Panel:
    """One axes box of a :class:`_Canvas`: data ranges, frame, ticks and labels."""

    def __init__(self, cv: _Canvas, box: tuple[float, float, float, float], xlim: tuple[float, float],
                 ylim: tuple[float, float]) -> None:
        self.cv, self.box, self.xlim, self.ylim = cv, box, xlim, ylim

    def xy(self, x: Any, y: Any) -> np.ndarray:
        x0, y0, w, h = self.box
        (a, b), (c, d) = self.xlim, self.ylim
        return np.column_stack([x0 + (np.asarray(x, float) - a) * w / (b - a), y0 + (np.asarray(y, float) - c) * h / (d - c)])

    def line(self, x: np.ndarray, y: np.ndarray, color: Any, lw_pt: float) -> None:
        self.cv.path(self.xy(x, y), color, lw_pt, clip=self.box)

    def yticks(self, nbins: int, label: str, grid: bool = False) -> None:
        """Ticks and labels on the left (matplotlib's MaxNLocator), the axis label beside them."""
        from matplotlib.ticker import MaxNLocator

        lo, hi = self.ylim
        ticks = [t for t in MaxNLocator(nbins).tick_values(lo, hi) if lo - 1e-9 * (hi - lo) <= t <= hi + 1e-9 * (hi - lo)]
        step = ticks[1] - ticks[0] if len(ticks) > 1 else abs(hi - lo)
        x0, _, w, _ = self.box
        widest = 0.0
        for t in ticks:
            y = self.xy([self.xlim[0]], [t])[0, 1]
            self.cv.path(np.array([[x0 - _pt(3.5), y], [x0, y]]), "black", 0.8)
            if grid:
                self.cv.path(np.array([[x0, y], [x0 + w, y]]), (0.69, 0.69, 0.69, 0.3), 0.8)
            s = _label(t, step)
            widest = max(widest, self.cv.size(s, 10)[0])
            self.cv.text(x0 - _pt(7), y, s, ha="right", va="center")
        self.cv.text(x0 - _pt(7) - widest - _pt(4) - self.cv.size(label, 10)[1], self.box[1] + self.box[3] / 2, label,
                     rotation=90)

    def xticks(self, nbins: int, label: str, grid: bool = False) -> None:
        from matplotlib.ticker import MaxNLocator

        lo, hi = self.xlim
        ticks = [t for t in MaxNLocator(nbins, steps=[1, 2, 2.5, 5, 10]).tick_values(lo, hi)
                 if lo - 1e-9 * (hi - lo) <= t <= hi + 1e-9 * (hi - lo)]
        step = ticks[1] - ticks[0] if len(ticks) > 1 else abs(hi - lo)
        _, y0, _, h = self.box
        for t in ticks:
            x = self.xy([t], [self.ylim[0]])[0, 0]
            self.cv.path(np.array([[x, y0 - _pt(3.5)], [x, y0]]), "black", 0.8)
            if grid:
                self.cv.path(np.array([[x, y0], [x, y0 + h]]), (0.69, 0.69, 0.69, 0.3), 0.8)
            self.cv.text(x, y0 - _pt(7), _label(t, step), ha="center", va="top")
        self.cv.text(self.box[0] + self.box[2] / 2, y0 - _pt(7) - self.cv.size("0", 10)[1] - _pt(4), label,
                     ha="center", va="top")

    def frame(self) -> None:
        self.cv.rect(self.box)

    def legend(self, entries: list[tuple[str, Any, float]], size_pt: float = 7.0, upper: bool = True) -> None:
        """Entries (label, colour, line width) in a box at the upper (or lower) right."""
        x0, y0, w, h = self.box
        row = self.cv.size("Ag", size_pt)[1] * 1.3
        width = max(self.cv.size(s, size_pt)[0] for s, _, _ in entries) + _pt(size_pt * 2.8)
        bx = x0 + w - _pt(4) - width
        by = y0 + h - _pt(4) - row * len(entries) - _pt(4) if upper else y0 + _pt(4)
        self.cv.rect((bx, by, width, row * len(entries) + _pt(4)), edge=(0.8, 0.8, 0.8, 1.0), face=(1, 1, 1, 0.8))
        for k, (s, color, lw) in enumerate(entries):
            y = by + _pt(2) + row * (len(entries) - k - 0.5)
            self.cv.path(np.array([[bx + _pt(3), y], [bx + _pt(3) + _pt(size_pt * 1.6), y]]), color, lw)
            self.cv.text(bx + _pt(size_pt * 2.2), y, s, size_pt, va="center")


def _limits(*arrays: np.ndarray, margin: float = 0.05) -> tuple[float, float]:
    """Data range with matplotlib's default 5 % margins (a flat series gets +-1 or +-5 %)."""
    finite = [a[np.isfinite(a)] for a in arrays]
    finite = [a for a in finite if a.size]
    if not finite:
        return -1.0, 1.0
    lo, hi = min(float(a.min()) for a in finite), max(float(a.max()) for a in finite)
    if hi <= lo:
        pad = abs(lo) * 0.05 if lo else 1.0
        return lo - pad, hi + pad
    return lo - margin * (hi - lo), hi + margin * (hi - lo)


def plot_fit(series: dict[str, Any], metrics: dict[str, dict[str, float]], path: str | Path, *,
             title: str = "", max_windows: int = 20) -> Path:
    """Measured vs model per output channel.

    Parameters
    ----------
    series : {"t_s": (W, L), "y": (W, L, 8), "yhat": (W, L, 8)} from ``validate(..., return_series=True)``
    metrics : per-channel {"match", "fit", "tic"}
    """
    t, y, yhat = series["t_s"], series["y"], series["yhat"]
    W = min(t.shape[0], max_windows)
    chans = [c for c in OUTPUTS if c in metrics]
    cv = _Canvas(11, 1.7 * len(chans) + 0.8)
    # one line per series, the windows separated by a NaN gap (as many lines as windows drew the
    # same picture at ~10x the rendering time)
    gap = np.full((W, 1), np.nan)
    tt = np.hstack([t[:W], gap]).ravel()
    xlim = (float(np.nanmin(tt)), float(np.nanmax(tt))) if W else (0.0, 1.0)
    left, right = 1.0 * DPI, cv.w - 0.2 * DPI
    bottom, top = 0.55 * DPI, cv.h - (0.55 if title else 0.3) * DPI
    n = max(len(chans), 1)
    ah = (top - bottom) / (n + 0.45 * (n - 1))   # matplotlib's hspace: gaps of 0.45 axes heights
    for k, ch in enumerate(chans):
        j = OUTPUTS.index(ch)
        ym, yh = np.hstack([y[:W, :, j], gap]).ravel(), np.hstack([yhat[:W, :, j], gap]).ravel()
        pan = _Panel(cv, (left, top - ah - k * 1.45 * ah, right - left, ah), xlim, _limits(ym, yh))
        pan.line(tt, ym, GREY, 0.8)
        pan.line(tt, yh, ORANGE, 0.9)
        pan.frame()
        pan.yticks(4, f"{ch} [{OUTPUT_UNITS[ch]}]")
        m = metrics[ch]
        cv.text(left, pan.box[1] + ah * 1.03, f"{ch}: match {m['match']:.1f}%  fit {m['fit']:.1f}%  TIC {m['tic']:.2f}",
                8, va="bottom")
        if k == 0:
            pan.legend([("measured", GREY, 0.8), ("model", ORANGE, 0.9)])
        if k == len(chans) - 1:
            pan.xticks(10, "FC time [s] (windows, each restarted from its initial state)")
    if title:
        cv.text(cv.w / 2, cv.h - 0.02 * cv.h, title, 10, ha="center", va="top")
    return cv.save(path)


def plot_convergence(curves: dict[str, list[tuple[np.ndarray, np.ndarray]]], path: str | Path, *,
                     title: str = "Fitness 1/(1+F) vs evaluations (median and range over seeds)") -> Path:
    """Figure-11-style curves: for each algorithm a list of (nfev, best cost) runs."""
    from matplotlib.colors import to_rgba

    cv = _Canvas(8, 4.5)
    drawn = []
    for k, (name, runs) in enumerate(curves.items()):
        if not runs:
            continue
        grid = np.linspace(max(float(r[0][0]) for r in runs), min(float(r[0][-1]) for r in runs), 200)
        fit = np.array([1.0 / (1.0 + np.interp(grid, r[0], r[1])) for r in runs])
        drawn.append((name, CYCLE[k % len(CYCLE)], grid, np.nanmedian(fit, axis=0), np.nanmin(fit, axis=0),
                      np.nanmax(fit, axis=0)))
    xlim = _limits(*[d[2] for d in drawn]) if drawn else (0.0, 1.0)
    ylim = _limits(*[d[4] for d in drawn], *[d[5] for d in drawn]) if drawn else (0.0, 1.0)
    box = (0.1 * cv.w, 0.12 * cv.h, 0.87 * cv.w, 0.8 * cv.h)
    pan = _Panel(cv, box, xlim, ylim)
    pan.yticks(6, "fitness 1/(1+F)", grid=True)
    pan.xticks(8, "cost evaluations", grid=True)
    for _name, color, grid, med, lo, hi in drawn:
        band = pan.xy(np.r_[grid, grid[::-1]], np.r_[lo, hi[::-1]])
        cv.path(band, to_rgba(color), 0.0, clip=box, face=to_rgba(color), alpha=0.15)
        pan.line(grid, med, to_rgba(color), 1.5)
    pan.frame()
    if drawn:   # the curves rise to the right: the legend below them
        pan.legend([(d[0].upper(), to_rgba(d[1]), 1.5) for d in drawn], 10, upper=False)
    cv.text(box[0] + box[2] / 2, box[1] + box[3] + _pt(6), title, 9, ha="center", va="baseline")
    return cv.save(path)
