"""Trends across flights as a PNG (matplotlib, Agg) and as a Rerun recording (.rrd).

Both take the :class:`~groundstation.trends.change.Trend` objects of a campaign and the flight
labels. The PNG shows the changed series first (value with its +-2 sigma band, the baseline band,
the flight where the change was called), then the rest up to ``max_panels``. The recording logs
every series on a ``flight`` sequence timeline (``/trends/{param|effect}/{name}/value``, ``.../sigma``)
and the summary as a text document.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from groundstation.trends.change import Trend


def load_plotting() -> None:
    """Import what :func:`plot_trends` and :func:`write_trends_rrd` need (matplotlib, Rerun: about
    0.7 s of CPU), e.g. on a core the campaign's workers have left idle while the last flights finish."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401
    import rerun  # noqa: F401


def plot_trends(trends: dict[str, Trend], labels: list[str], path: str | Path, *, title: str = "",
                max_panels: int = 16) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    order = sorted(trends.values(), key=lambda t: (not t.changed, not t.name.startswith("effect:"), t.name))
    shown = [t for t in order if np.isfinite(t.values).sum() >= 2][:max_panels]
    ncol = 4 if len(shown) > 6 else max(1, min(len(shown), 3))
    nrow = max(1, -(-len(shown) // ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.6 * ncol, 2.4 * nrow + 0.6), squeeze=False, sharex=True)
    x = np.arange(len(labels))
    for ax, t in zip(axes.ravel(), shown, strict=False):
        v, sig = t.values, t.sigma
        ax.errorbar(x, v, yerr=2 * np.where(np.isfinite(sig), sig, 0.0), fmt="o-", ms=3, lw=0.8, capsize=2,
                    color="tab:red" if t.changed else "tab:blue")
        fin = np.flatnonzero(np.isfinite(v))
        if fin.size:
            ref, s0 = v[fin[0]], sig[fin[0]] if np.isfinite(sig[fin[0]]) else 0.0
            ax.axhspan(ref - t.z_crit * s0, ref + t.z_crit * s0, color="0.85", zorder=0)
        if t.changed_at is not None:
            ax.axvline(t.changed_at, color="tab:red", ls="--", lw=0.8)
        ax.set_title(f"{t.name}{' - ' + t.kind + ' at ' + labels[t.changed_at] if t.changed_at is not None else ''}",
                     fontsize=8, y=1.0)   # y given: not lifted over top tick labels (there are none)
        ax.tick_params(labelsize=7)
        ax.yaxis.set_major_locator(MaxNLocator(nbins=4))
    axes[0, 0].xaxis.set_major_locator(MaxNLocator(nbins=6, integer=True))   # shared: flight indices
    for ax in axes.ravel()[len(shown):]:
        ax.set_visible(False)
    fig.suptitle(title or "trends across flights (+-2 sigma; grey: baseline band)", fontsize=10)
    fig.subplots_adjust(**_margins(nrow, ncol))
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def write_trends_rrd(trends: dict[str, Trend], labels: list[str], path: str | Path, *,
                     app: str = "groundstation-campaign") -> Path:
    import rerun as rr

    rec = rr.RecordingStream(app)
    rec.save(str(path))
    idx = np.arange(len(labels))
    for t in trends.values():
        fin = np.isfinite(t.values)
        if not fin.any():
            continue
        kind, name = ("effect", t.name.split(":", 1)[1]) if t.name.startswith("effect:") else ("param", t.name)
        base = f"/trends/{kind}/{name.replace('[', '_').replace(']', '').replace('.', '_')}"
        rec.send_columns(f"{base}/value", indexes=[rr.TimeColumn("flight", sequence=idx[fin])],
                         columns=rr.Scalars.columns(scalars=t.values[fin]))
        sf = fin & np.isfinite(t.sigma)
        if sf.any():
            rec.send_columns(f"{base}/sigma", indexes=[rr.TimeColumn("flight", sequence=idx[sf])],
                             columns=rr.Scalars.columns(scalars=t.sigma[sf]))
    summary = {"flights": labels, "changed": [t.summary() for t in trends.values() if t.changed]}
    rec.log("/trends/summary", rr.TextDocument(json.dumps(summary, indent=1)), static=True)
    rec.flush()
    return Path(path)


def _margins(nrow: int, ncol: int) -> dict[str, float]:
    """Fixed margins of the panel grid (in figure fractions) for 7-point tick labels and 8-point titles:
    what a layout engine would find, without measuring every tick label."""
    w, h = 3.6 * ncol, 2.4 * nrow + 0.6
    return {"left": 0.55 / w, "right": 1 - 0.1 / w, "bottom": 0.35 / h, "top": 1 - 0.6 / h, "wspace": 0.3, "hspace": 0.4}
