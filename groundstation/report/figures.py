"""The report's figures: matplotlib (object API, Agg canvas, no pyplot state), each returned as a
:class:`Figure` whose ``html`` is an inline SVG (small plots) or a base64 PNG (dense time series),
so the page needs no other file.

Every axis carries a unit in parentheses (``FC time (s)``, ``magnitude (dB)``, ``coherence (-)``);
:func:`axis_labels` reads them back and the page records them beside each figure (``data-axes``),
where the tests check them. Inputs are the analysis objects (see :mod:`groundstation.report.data`);
a function returns None when its data are absent, never raises for empty data.
"""

from __future__ import annotations

import base64
import io
import json
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from groundstation.freq.verify import J_AVG_GOOD, J_PAIR_ACCEPTABLE
from groundstation.sinks.bode import _series
from groundstation.sysid.fit_section import PriorReport
from groundstation.sysid.model import INPUTS, OUTPUT_UNITS, OUTPUTS, PARAM_NAMES, build_matrices
from groundstation.sysid.validate import Validation

#: grid and report colours (colour-blind safe pair for measured/model)
C_MEAS, C_MODEL, C_BAND = "0.45", "#d62728", "#1f77b4"
INPUT_UNIT = "(normalised, -)"


@dataclass(frozen=True)
class Figure:
    key: str
    title: str
    caption: str
    html: str                                   # <svg ...> or <img src="data:image/png;base64,...">
    axes: tuple[tuple[str, str], ...]           # (x label, y label) of every visible axes
    kind: str                                   # "svg" | "png"

    @property
    def axes_json(self) -> str:
        return json.dumps(self.axes)


def _new(w_in: float, h_in: float, nrows: int = 1, ncols: int = 1, **kw: Any) -> tuple[Any, Any]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure as MplFigure

    fig = MplFigure(figsize=(w_in, h_in), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    return fig, axes


def axis_labels(fig: Any) -> tuple[tuple[str, str], ...]:
    """(x, y) label of every visible axes; an axes without its own label takes that of an axes it shares
    the axis with, else the figure's ``supxlabel``/``supylabel`` (shared axes are labelled once)."""
    sx = fig._supxlabel.get_text() if getattr(fig, "_supxlabel", None) else ""
    sy = fig._supylabel.get_text() if getattr(fig, "_supylabel", None) else ""
    out = []
    for ax in fig.axes:
        if not ax.axison:
            continue
        x = ax.get_xlabel() or next((a.get_xlabel() for a in ax.get_shared_x_axes().get_siblings(ax)
                                     if a.get_xlabel()), "") or sx
        y = ax.get_ylabel() or next((a.get_ylabel() for a in ax.get_shared_y_axes().get_siblings(ax)
                                     if a.get_ylabel()), "") or sy
        out.append((x, y))
    return tuple(out)


_ID = re.compile(r'(id="|url\(#|href="#)([^")]+)')


def _svg(fig: Any, key: str) -> str:
    import matplotlib

    buf = io.StringIO()
    with matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": key}):
        fig.savefig(buf, format="svg", metadata={"Date": None, "Creator": None})
    text = buf.getvalue()
    text = text[text.index("<svg"):]
    text = re.sub(r"\s*<metadata>.*?</metadata>", "", text, count=1, flags=re.S)
    # ids are unique per page: each figure's own prefix
    text = _ID.sub(lambda m: f"{m.group(1)}{key}-{m.group(2)}", text)
    return text.replace("<svg ", f'<svg role="img" aria-label="{key}" ', 1)


def _png(fig: Any, dpi: int = 80) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return f'<img alt="" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def finish(fig: Any, key: str, title: str, caption: str, dense: bool = False) -> Figure:
    labels = axis_labels(fig)
    html = _png(fig) if dense else _svg(fig, key)
    fig.clear()
    return Figure(key, title, caption, html, labels, "png" if dense else "svg")


def _spans(ax: Any, spans: Any, color: str, alpha: float = 0.25, label: str | None = None) -> None:
    for i, (a, b) in enumerate(spans):
        ax.axvspan(a, b, color=color, alpha=alpha, lw=0, label=label if i == 0 else None)


# ------------------------------------------------------------------ the flight

def timeline_figure(timelines: Any) -> Figure | None:
    if not timelines:
        return None
    n = len(timelines)
    fig, axes = _new(10, 2.6 * n, n, 1)
    for ax, tl in zip(axes[:, 0], timelines, strict=True):
        _spans(ax, tl.armed_s, "#ffbf80", 0.35, "armed")
        _spans(ax, tl.in_air_s, "#8fd18f", 0.45, "in the air")
        for k, (a, d, axis) in enumerate(tl.chirps):
            ax.axvspan(a, a + d, ymin=0.0, ymax=0.12, color="#9467bd", lw=0, label="SYSID chirp" if k == 0 else None)
            ax.text(a, 0.13, axis, transform=ax.get_xaxis_transform(), fontsize=6, color="#9467bd")
        if tl.height_m.size:
            step = max(1, tl.height_m.size // 2000)   # a line of 2000 points at most: the SVG stays small
            ax.plot(tl.t_height_s[::step], tl.height_m[::step], "-", lw=0.8, color="k", label="height")
        for t, name in tl.modes:
            ax.axvline(t, color="0.3", lw=0.6, ls=":")
            ax.text(t, 0.97, f" {name}", transform=ax.get_xaxis_transform(), fontsize=7, va="top", rotation=0)
        ax.set_xlim(*tl.span_s) if tl.span_s[1] > tl.span_s[0] else None
        ax.set_xlabel("FC time (s)")
        ax.set_ylabel("height above take-off (m)")
        ax.set_title(tl.source, fontsize=9, loc="left")
        ax.legend(fontsize=7, loc="upper right", ncols=4)
    return finish(fig, "timeline", "Timeline",
                  "Armed (orange) and in-air (green) intervals, flight-mode changes (dotted, named), the autopilot's "
                  "SYSID chirps (purple, with their axis) and the height above the take-off point.")


def rates_figure(infos: Any) -> Figure | None:
    if not infos:
        return None
    names = sorted({m for i in infos for m in i["messages"] if i["messages"][m]["rate_hz"]})
    if not names:
        return None
    fig, axes = _new(10, 0.22 * len(names) * len(infos) + 1.2, 1, 1)
    ax = axes[0, 0]
    h = 0.8 / len(infos)
    for k, info in enumerate(infos):
        r = [info["messages"].get(m, {}).get("rate_hz") or 0.0 for m in names]
        ax.barh(np.arange(len(names)) + k * h, r, height=h, label=info["source"].rsplit("/", 1)[-1])
    ax.set_yticks(np.arange(len(names)) + 0.4 - h / 2, names, fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel("mean message rate (Hz)")
    ax.set_ylabel("message type (-)")
    ax.invert_yaxis()
    if len(infos) > 1:
        ax.legend(fontsize=7)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    return finish(fig, "rates", "Message rates", "Mean rate of each message type over its own span (log scale).")


def gaps_figure(infos: Any, timelines: Any) -> Figure | None:
    gaps = [(i["source"].rsplit("/", 1)[-1], g) for i in infos for g in i["gaps"]]
    if not infos:
        return None
    fig, axes = _new(10, 2.4, 1, 1)
    ax = axes[0, 0]
    types = sorted({g["message"] for _, g in gaps})
    for _, g in gaps:
        y = types.index(g["message"])
        ax.barh(y, max(g["duration_s"] or 0.0, 0.05), left=g["start_s"] or 0.0, height=0.6, color="#d62728")
    for tl in timelines:
        _spans(ax, tl.in_air_s, "#8fd18f", 0.25)
    ax.set_yticks(range(len(types)), types, fontsize=7)
    ax.set_xlabel("FC time (s)")
    ax.set_ylabel("message type (-)")
    if not gaps:
        ax.text(0.5, 0.5, "no gap longer than 3 sample periods", transform=ax.transAxes, ha="center")
        ax.set_yticks([])
    return finish(fig, "gaps", "Gaps in the data",
                  "Each red bar is an interval longer than three sample periods without that message "
                  "(in-air time shaded green).")


def excitation_figure(prepared: Any) -> Figure | None:
    if prepared is None or not prepared.segments:
        return None
    from scipy.signal import welch

    fig, axes = _new(10, 4.6, 2, 1)
    a_t, a_f = axes[:, 0]
    fs = 1.0 / prepared.dt_s
    for j, name in enumerate(INPUTS):
        for k, s in enumerate(prepared.segments):
            a_t.plot(s.t_s, s.inputs[:, j], lw=0.6, color=f"C{j}", label=name if k == 0 else None)
        x = np.concatenate([s.inputs[:, j] - np.nanmean(s.inputs[:, j]) for s in prepared.segments])
        x = x[np.isfinite(x)]
        if x.size >= 64 and np.std(x) > 1e-6:
            f, p = welch(x, fs=fs, nperseg=min(512, x.size))
            a_f.loglog(f[1:], p[1:], lw=0.9, color=f"C{j}", label=f"{name} (rms {np.std(x):.3f})")
        else:
            a_f.plot([], [], color=f"C{j}", label=f"{name}: not moved")
    a_t.set_xlabel("FC time (s)")
    a_t.set_ylabel(f"input {INPUT_UNIT}")
    a_t.legend(fontsize=7, ncols=4, loc="upper right")
    a_f.set_xlabel("frequency (Hz)")
    a_f.set_ylabel("input PSD (1/Hz)")
    a_f.legend(fontsize=7, ncols=2)
    a_f.grid(True, which="both", alpha=0.3)
    return finish(fig, "excitation", "Excitation per axis",
                  "The normalised inputs over the in-air time (trim removed) and their power spectral density: "
                  "an axis without power over a band cannot be identified there.", dense=True)


# ------------------------------------------------------------------ the model

def parameters_figure(model: Any) -> Figure | None:
    if model is None:
        return None
    fit = model.fit
    prior = fit.prior or PriorReport()
    share = prior.prior_share
    fixed = set(fit.fixed) | set(prior.fixed_at_prior)
    fig, axes = _new(10, 3.4, 1, 1)
    ax = axes[0, 0]
    rel, colors = [], []
    for n in PARAM_NAMES:
        s = model.parameter_std.get(n)
        v = abs(float(model.params[n]))
        rel.append(100.0 * s / v if s is not None and np.isfinite(s) and v > 0 else np.nan)
        if n in fixed:
            colors.append("0.7")
        elif n in model.pinned:
            colors.append("#d62728")
        elif share.get(n, 0.0) > 0.5:
            colors.append("#ff7f0e")
        else:
            colors.append("#1f77b4")
    x = np.arange(len(PARAM_NAMES))
    ax.bar(x, np.nan_to_num(np.clip(rel, 0, 300)), color=colors)
    for i, r in enumerate(rel):
        if not np.isfinite(r):
            ax.text(i, 1, "n/a", rotation=90, fontsize=6, ha="center", va="bottom", color="0.4")
    ax.set_yscale("symlog", linthresh=10)
    ax.axhline(100, color="k", lw=0.6, ls=":")
    ax.set_xticks(x, PARAM_NAMES, rotation=90, fontsize=7)
    ax.set_xlabel("parameter (-)")
    ax.set_ylabel("std error / |value| (%)")
    from matplotlib.patches import Patch

    ax.legend(handles=[Patch(color="#1f77b4", label="determined by the flight"),
                       Patch(color="#ff7f0e", label="kept near the prior"),
                       Patch(color="#d62728", label="on a search bound"), Patch(color="0.7", label="fixed")],
              fontsize=7, ncols=4, loc="upper left")
    return finish(fig, "parameters", "Parameter uncertainty",
                  "Standard error of each parameter relative to its value (Cramér-Rao bound; clipped at 300 %); "
                  "above the dotted line the flight does not tell the sign.")


def modes_figure(model: Any) -> Figure | None:
    if model is None:
        return None

    Ah, _, Av, _ = build_matrices(np.asarray(model.theta, dtype=float))
    fig, axes = _new(5.2, 3.6, 1, 1)
    ax = axes[0, 0]
    for A, name, m in ((Ah, "horizontal", "o"), (Av, "vertical/yaw", "s")):
        ev = np.linalg.eigvals(A)
        ax.scatter(ev.real, ev.imag, marker=m, s=28, facecolors="none",
                   edgecolors=np.where(ev.real > 0, "#d62728", "#1f77b4"), label=name)
    ax.axvline(0, color="k", lw=0.6)
    ax.set_xscale("symlog", linthresh=1)
    ax.set_xlabel("real part (1/s)")
    ax.set_ylabel("imaginary part (rad/s)")
    ax.legend(fontsize=7)
    ax.grid(True, alpha=0.3)
    return finish(fig, "modes", "Stability modes",
                  "Eigenvalues of both subsystems (red: unstable, right of the axis). The bare hover model is "
                  "unstable; a time constant well under the prediction window makes long predictions run away.")


def fit_figure(validation: Validation | None, output_trim: dict[str, float] | None = None) -> Figure | None:
    if validation is None or validation.series is None:
        return None
    s = validation.series
    t = np.asarray(s["t_s"], float).reshape(-1)
    if not t.size:
        return None
    y = np.asarray(s["y"], float).reshape(-1, 8)
    yh = np.asarray(s["yhat"], float).reshape(-1, 8)
    order = np.argsort(t, kind="stable")
    t, y, yh = t[order], y[order], yh[order]
    brk: Any = np.flatnonzero(np.diff(t) > 1.5 * np.median(np.diff(t))) + 1 if t.size > 2 else []
    chans = validation.channels
    fig, axes = _new(10, 8.5, 4, 2, sharex=True)
    for i, (ax, c) in enumerate(zip(axes.T.ravel(), OUTPUTS, strict=True)):
        ax.plot(t, y[:, i], ".", ms=1.0, color=C_MEAS, label="measured (smoothed)")
        yy = yh[:, i].copy()
        yy = np.insert(yy, brk, np.nan) if len(brk) else yy
        tt = np.insert(t, brk, np.nan) if len(brk) else t
        ax.plot(tt, yy, "-", lw=0.7, color=C_MODEL, label="model")
        m = chans[c].match if c in chans else None
        ax.set_title(f"{c}" + (f": match {m:.1f} %" if m is not None else ": not measured"), fontsize=8, loc="left")
        ax.set_ylabel(f"{c} ({OUTPUT_UNITS[c]})")
    for ax in axes[-1]:
        ax.set_xlabel("FC time (s)")
    axes[0, 0].legend(fontsize=7, loc="upper right", markerscale=4)
    return finish(fig, "fit", "Measured vs model (training windows)",
                  f"Each {validation.window_s:g}-s window simulated from its measured initial state; "
                  "perturbations from trim.", dense=True)


def heldout_figure(heldout: Any) -> Figure | None:
    """``heldout``: a :class:`groundstation.sysid.fit_section.HeldOut` (None: no figure)."""
    if heldout is None or not heldout.folds:
        return None
    folds = heldout.folds
    chans = [c for c in OUTPUTS if any(c in f for f in folds)]
    fig, axes = _new(10, 3.2, 1, 1)
    ax = axes[0, 0]
    w = 0.8 / len(folds)
    x = np.arange(len(chans))
    for k, f in enumerate(folds):
        vals = [f.get(c, np.nan) for c in chans]
        ax.bar(x + k * w - 0.4 + w / 2, np.clip(np.nan_to_num(vals, nan=0.0), -100, 100), width=w,
               color=f"C{k}", label=f"fold {k + 1}")
    means = heldout.channel_mean
    ax.plot(x, [means.get(c, np.nan) for c in chans], "k_", ms=18, mew=2, label="mean")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xticks(x, chans)
    ax.set_ylim(min(-5.0, ax.get_ylim()[0]), 100)
    ax.set_xlabel("output channel (-)")
    ax.set_ylabel("held-out match, eq. 19 (%)")
    ax.legend(fontsize=7, ncols=len(folds) + 1, loc="lower left")
    ax.grid(True, axis="y", alpha=0.3)
    return finish(fig, "heldout", "Held-out match per channel and fold",
                  f"Refit on {len(folds) - 1} of {len(folds)} contiguous blocks of the in-air time, prediction of the "
                  f"left-out block in {heldout.window_s or 0:g}-s windows from the measured states "
                  "(clipped at -100 %).")


# ------------------------------------------------------------------ frequency domain

def bode_figures(v: Any) -> list[Figure]:
    if v is None:
        return []

    scores = {(s.input, s.output): s for s in v.pairs}
    out = []
    for inp in INPUTS:
        pairs = [p for p in v.responses.with_response if p.input == inp and (p.input, p.output) in scores]
        if not pairs:
            continue
        fig, axes = _new(2.6 * len(pairs) + 1.2, 5.6, 3, len(pairs), sharex="col")
        for c, p in enumerate(pairs):
            s = _series(v, p)
            m = p.coherent
            a_mag, a_ph, a_coh = axes[:, c]
            for ax, key in ((a_mag, "mag"), (a_ph, "ph")):
                ax.plot(s["f"][~m], s[key][~m], ".", color="0.8", ms=2, label="not coherent")
                ax.plot(s["f"][m], s[key][m], "o", color=C_BAND, ms=2.5, label="flight (coherent)")
                ax.fill_between(s["f"], np.where(m, s[f"{key}_lo"], np.nan), np.where(m, s[f"{key}_hi"], np.nan),
                                color=C_BAND, alpha=0.2, lw=0, label="95 % random error")
                ax.plot(s["f"], s[f"{key}_model"], "-", color=C_MODEL, lw=1, label="model")
                ax.set_xscale("log")
                ax.grid(True, which="both", alpha=0.3)
            a_coh.plot(s["f"], s["coh"], ".-", color="C2", ms=2, lw=0.6)
            a_coh.axhline(v.responses.config.coherence_min, color="k", ls=":", lw=0.8)
            a_coh.set_ylim(0, 1.02)
            a_coh.set_xscale("log")
            sc = scores[(p.input, p.output)]
            a_mag.set_title(f"{inp}→{p.output} ({OUTPUT_UNITS[p.output]} per unit): J = {sc.J:.0f} "
                            f"{'pass' if sc.passed else 'FAIL'}", fontsize=7)
            a_mag.set_ylabel("magnitude (dB)")
            a_ph.set_ylabel("phase (deg)")
            a_coh.set_ylabel("coherence (-)")
            a_coh.set_xlabel("frequency (Hz)")
        axes[0, 0].legend(fontsize=6, loc="lower left")
        out.append(finish(fig, f"bode-{inp}", f"Bode: input {inp}",
                          f"Flight frequency responses to {inp} (points; coherent ones blue with their 95 % "
                          "random-error band) against the model (red), and the coherence (dotted: the threshold); "
                          "magnitude in output units per unit input.", dense=True))
    return out


def j_figure(v: Any) -> Figure | None:
    if v is None or not v.pairs:
        return None

    fig, axes = _new(10, 3.0, 1, 2, width_ratios=(3, 1))
    ax, ad = axes[0]
    labels = [f"{p.input}→{p.output}" for p in v.pairs]
    js = np.array([p.J for p in v.pairs], float)
    ax.bar(range(len(js)), np.clip(np.nan_to_num(js, nan=0.0), 1, None),
           color=["#2ca02c" if p.passed else "#d62728" for p in v.pairs])
    ax.axhline(J_AVG_GOOD, color="k", ls=":", lw=0.8, label=f"J ≤ {J_AVG_GOOD:g}: good")
    ax.axhline(J_PAIR_ACCEPTABLE, color="k", ls="--", lw=0.8, label=f"J ≤ {J_PAIR_ACCEPTABLE:g}: acceptable")
    ax.set_yscale("log")
    ax.set_xticks(range(len(js)), labels, rotation=45, fontsize=7, ha="right")
    ax.set_xlabel("input→output pair (-)")
    ax.set_ylabel("Tischler's J (-)")
    ax.legend(fontsize=7)
    d = [(k, x) for k, x in v.input_delays.items()]
    if d:
        ad.errorbar(range(len(d)), [x.delay_s * 1000 for _, x in d], yerr=[2 * x.std_s * 1000 for _, x in d],
                    fmt="o", capsize=3)
        ad.set_xticks(range(len(d)), [k for k, _ in d])
        ad.axhline(0, color="k", lw=0.6)
    else:
        ad.text(0.5, 0.5, "no delay estimate", transform=ad.transAxes, ha="center", fontsize=8)
    ad.set_xlabel("input (-)")
    ad.set_ylabel("equivalent delay vs model (ms)")
    return finish(fig, "tischler-j", "Tischler's J per pair and delays",
                  "J per scored input-output pair (green pass, red fail; log scale) and the equivalent delay of each "
                  "input relative to the model from the phase slope (±2 σ).")


# ------------------------------------------------------------------ the gap

def residual_figure(pic: Any) -> Figure | None:
    if pic is None or not pic.channels or not pic.t_s.size:
        return None
    chans = list(pic.channels)
    fig, axes = _new(10, 1.25 * len(chans) + 0.8, len(chans), 1, sharex=True)
    t = pic.t_s
    brk: Any = np.flatnonzero(np.diff(t) > 1.5 * np.median(np.diff(t))) + 1 if t.size > 2 else []
    for ax, c in zip(axes[:, 0], chans, strict=True):
        r = pic.residual[:, OUTPUTS.index(c)]
        tt = np.insert(t, brk, np.nan) if len(brk) else t
        rr = np.insert(r, brk, np.nan) if len(brk) else r
        ax.plot(tt, rr, lw=0.5, color="k")
        _spans(ax, pic.flagged_s, "#d62728", 0.2)
        ax.set_ylabel(f"{c} ({OUTPUT_UNITS[c]})", fontsize=7)
        ax.tick_params(labelsize=7)
    axes[-1, 0].set_xlabel("FC time (s)")
    return finish(fig, "residual", "Where in time: held-out residual",
                  "Measured minus the held-out model prediction per channel; flagged windows (the gap's worst) in red.",
                  dense=True)


def spectrum_figure(pic: Any) -> Figure | None:
    if pic is None or not pic.f_hz.size or not pic.channels:
        return None
    fig, axes = _new(10, 3.2, 1, 1)
    ax = axes[0, 0]
    for k, c in enumerate(pic.channels):
        i = OUTPUTS.index(c)
        if not np.isfinite(pic.psd[:, i]).any():
            continue
        ax.semilogy(pic.f_hz, pic.psd[:, i], lw=0.8, color=f"C{k}", label=f"{c} ({OUTPUT_UNITS[c]})²/Hz")
        ax.semilogy(pic.f_hz, pic.floor[:, i], lw=0.6, ls=":", color=f"C{k}")
    for f in pic.lines_hz:
        ax.axvline(f, color="#d62728", lw=0.8, ls="--")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("residual PSD (unit²/Hz)")
    ax.legend(fontsize=6, ncols=4)
    ax.grid(True, which="both", alpha=0.3)
    return finish(fig, "residual-spectrum", "Where in frequency: residual spectrum",
                  "Power spectral density of the raw residual per channel with its local noise floor (dotted); "
                  "significant narrow lines dashed red.")


def effects_figure(pic: Any) -> Figure | None:
    if pic is None or not pic.effects:
        return None
    n = len(pic.effects)
    fig, axes = _new(10, 2.2 * n + 0.4, n, 1)
    for ax, e in zip(axes[:, 0], pic.effects, strict=True):
        cols = [OUTPUTS.index(c) for c in e.channels] or list(range(8))
        b = np.nanmean(e.before_pct[:, cols], axis=1)
        a = np.nanmean(e.after_pct[:, cols], axis=1)
        ax.plot(e.t_s, b, ".-", lw=0.6, ms=3, color="0.4", label="base model (before)")
        ax.plot(e.t_s, a, ".-", lw=0.6, ms=3, color="#2ca02c", label=f"with {e.label} (after)")
        ax.set_title(f"{e.label}{'' if e.significant else ' (best candidate, not significant)'} on "
                     f"{', '.join(e.channels)}", fontsize=8, loc="left")
        ax.set_ylabel("held-out NRMSE (%)")
        ax.set_xlabel("FC time of the window (s)")
        ax.legend(fontsize=7)
    return finish(fig, "effects", "Before and after the named effects",
                  "Held-out error per window of the base model and of the model with the effect added, on the channels "
                  "the effect acts on most.")


def shares_figure(gap: dict[str, Any] | None) -> Figure | None:
    """The gap report's shares (``heli-gap-report/2``): per named effect and unexplained, and per channel."""
    sh = (gap or {}).get("shares")
    if not isinstance(sh, dict) or sh.get("explained_pct") is None:
        return None
    eff = [e for e in sh.get("per_effect") or [] if e.get("share_pct") is not None]
    rows = [(e["effect"], float(e["share_pct"]), e.get("interval_pct")) for e in eff]
    rows.append(("not explained", float(sh.get("unexplained_pct") or 0.0), None))
    chans = [(c, x) for c, x in (sh.get("per_channel") or {}).items() if x.get("explained_pct") is not None]
    fig, axes = _new(10, 0.35 * max(len(rows), len(chans), 3) + 1.3, 1, 2)
    a, b = axes[0]
    y = np.arange(len(rows))
    a.barh(y, [r[1] for r in rows], color=["#1f77b4"] * (len(rows) - 1) + ["0.7"])
    for k, (_, _v, iv) in enumerate(rows):
        if iv and None not in iv:
            a.plot(iv, [k, k], "k-", lw=1.2)
    a.set_yticks(y, [r[0] for r in rows], fontsize=7)
    a.invert_yaxis()
    a.set_xlim(0, 100)
    a.set_xlabel("share of the held-out gap above noise (%)")
    a.set_ylabel("effect (-)")
    if chans:
        yc = np.arange(len(chans))
        b.barh(yc, [float(x.get("excess_share_pct") or 0.0) for _, x in chans], color="0.8", label="channel's part of the gap")
        b.plot([float(x["explained_pct"]) for _, x in chans], yc, "o", color="#1f77b4", label="explained there")
        for k, (_, x) in enumerate(chans):
            iv = x.get("interval_pct")
            if iv and None not in iv:
                b.plot(iv, [k, k], "-", color="#1f77b4", lw=1.2)
        b.set_yticks(yc, [c for c, _ in chans])
        b.invert_yaxis()
        b.legend(fontsize=7)
    else:
        b.text(0.5, 0.5, "no channel above its noise floor", transform=b.transAxes, ha="center", fontsize=8)
    b.set_xlim(0, 100)
    b.set_xlabel("share (%)")
    b.set_ylabel("output channel (-)")
    return finish(fig, "shares", "Explained shares",
                  "Left: the share of the held-out gap above the noise floor each named effect removes (bars, with the "
                  "5-95 % bootstrap interval) and what is left. Right: each channel's part of that gap (grey) and "
                  "how much of it the named effects explain there (blue, with interval).")


# ------------------------------------------------------------------ across flights

def trends_figure(rows: Any, current_label: str | None = None, params: tuple[str, ...] = ()) -> Figure | None:
    rows = [r for r in rows if not r.get("error")]
    if len(rows) < 2:
        return None
    labels = [f"{r['log_name']}#{int(r['flight_index'])}" for r in rows]
    x = np.arange(len(rows))
    show = params or _moving_params(rows)
    nrow = 1 + -(-len(show) // 3)
    fig, axes = _new(10, 2.4 * nrow, nrow, 3)
    a0 = axes[0, 0]
    for key, lab, col in (("heldout_match_pct", "held-out", "C0"), ("cross_match_pct", "on the previous flight", "C1"),
                          ("train_match_pct", "training", "0.6")):
        vals = np.array([np.nan if r.get(key) is None else float(r[key]) for r in rows])
        if np.isfinite(vals).any():
            a0.plot(x, vals, "o-", ms=3, lw=0.8, color=col, label=lab)
    a0.set_ylabel("mean match (%)")
    a0.legend(fontsize=6)
    for ax in axes[0, 1:]:
        ax.axis("off")
    for ax, n in zip(axes[1:].ravel(), show, strict=False):
        v = np.array([np.nan if r.get(f"p_{n}") is None else float(r[f"p_{n}"]) for r in rows])
        s = np.array([np.nan if r.get(f"se_{n}") is None else float(r[f"se_{n}"]) for r in rows])
        ax.errorbar(x, v, yerr=2 * np.nan_to_num(s), fmt="o-", ms=3, lw=0.8, capsize=2)
        ax.set_ylabel(f"{n} (model units)", fontsize=7)
    for ax in axes[1:].ravel()[len(show):]:
        ax.axis("off")
    for ax in axes.ravel():
        if ax.axison:
            ax.set_xticks(x, labels, rotation=45, fontsize=6, ha="right")
            ax.set_xlabel("flight (-, date order)", fontsize=7)
            if current_label in labels:
                ax.axvline(labels.index(current_label), color="#d62728", lw=0.6, ls=":")
    return finish(fig, "trends", "Across flights",
                  "Mean held-out match and the parameters that move most across the aircraft's flights (±2 σ).")


def _moving_params(rows: list[dict[str, Any]], n: int = 6) -> tuple[str, ...]:
    """The parameters whose spread across flights is largest relative to their standard errors."""
    score = []
    for p in PARAM_NAMES:
        v = np.array([np.nan if r.get(f"p_{p}") is None else float(r[f"p_{p}"]) for r in rows])
        s = np.array([np.nan if r.get(f"se_{p}") is None else float(r[f"se_{p}"]) for r in rows])
        if np.isfinite(v).sum() < 2:
            continue
        se = np.nanmedian(s) if np.isfinite(s).any() else np.nan
        score.append((np.nanstd(v) / se if np.isfinite(se) and se > 0 else 0.0, p))
    score.sort(reverse=True)
    return tuple(p for _, p in score[:n])
