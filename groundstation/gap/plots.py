"""Matplotlib figures of a diagnosis (PNG files): residuals with flagged windows, spectra, shrink.

Each function takes arrays (from :class:`groundstation.gap.diagnose.Diagnosis`) and a path and
writes one PNG with the non-interactive Agg backend. Called by the ``diagnose`` command only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from groundstation.sysid.model import OUTPUT_UNITS, OUTPUTS  # noqa: E402


def residuals_over_time(arrays: dict[str, Any], report: dict[str, Any], path: Path) -> Path:
    """Measured vs held-out model per channel over flight time, flagged windows shaded."""
    T, Y, yh, mask = arrays["t_s"], arrays["Y"], arrays["yhat"], arrays["mask"]
    chans = [c for c, n in enumerate(OUTPUTS) if n in report["gap"]["channels"]]
    fig, axes = plt.subplots(len(chans), 1, figsize=(11, 1.6 * len(chans) + 1), sharex=True, squeeze=False)
    for ax, c in zip(axes[:, 0], chans, strict=True):
        for w in range(T.shape[0]):
            t = T[w, mask]
            ax.plot(t, Y[w, mask, c], color="k", lw=0.6)
            ax.plot(t, yh[w, mask, c], color="tab:blue", lw=0.6)
            ax.plot(t, Y[w, mask, c] - yh[w, mask, c], color="tab:red", lw=0.5)
        for a, b in report["gap"]["windows_s"]:
            ax.axvspan(a, b, color="orange", alpha=0.3)
        m = report["gap"]["channels"][OUTPUTS[c]]
        ax.set_ylabel(f"{OUTPUTS[c]} [{OUTPUT_UNITS[OUTPUTS[c]]}]", fontsize=8)
        ax.set_title(f"{OUTPUTS[c]}: match {m['match']:.1f}%  Theil {m['tic']:.3f}", fontsize=8, loc="left")
    axes[-1, 0].set_xlabel("FC time [s]  (black measured, blue held-out model, red residual, orange flagged)")
    fig.suptitle(f"gap diagnosis: verdict {report['verdict']}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def residual_spectra(arrays: dict[str, Any], report: dict[str, Any], path: Path) -> Path:
    """Raw-residual spectra per channel with the line-test threshold and the worst band."""
    sp = arrays["spectra"]
    f, P = sp["f_hz"], sp["psd"]
    fig, ax = plt.subplots(figsize=(10, 5))
    for c, n in enumerate(OUTPUTS):
        if n in report["gap"]["channels"]:
            ax.semilogy(f[1:], P[1:, c] / np.median(P[1:, c]), lw=0.8, label=n)
    band = report["gap"].get("band_hz")
    if band:
        ax.axvspan(band[0], band[1], color="grey", alpha=0.2, label="worst band")
    for ln in report["fingerprints"]["spectral_lines"]:
        ax.axvline(ln["frequency_hz"], color="r", ls="--", lw=0.8)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("residual PSD / channel median")
    ax.legend(fontsize=7, ncol=4)
    ax.set_title("raw output residual spectra (dashed: significant narrow lines)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def shrink_bars(report: dict[str, Any], path: Path) -> Path:
    """Per-channel held-out gap shrink of the ranked effects (or the partial findings), titled with
    the share of the gap above noise they explain (the report's headline)."""
    fig, ax = plt.subplots(figsize=(9, 4.4))
    effects = report["effects"] or report.get("partial_findings") or report.get("candidates", [])[:1]
    width = 0.8 / max(len(effects), 1)
    for i, e in enumerate(effects):
        vals = [e["per_channel_shrink"].get(n, 0.0) or 0.0 for n in OUTPUTS]
        share = f", {e['share_pct']:.0f} % of the gap above noise" if e.get("share_pct") is not None else ""
        ax.bar(np.arange(8) + i * width, vals, width, label=f"{e['effect']} {e['input'] or e['output'] or ''}{share}")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(np.arange(8) + 0.4 - width / 2, OUTPUTS)
    ax.set_ylabel("held-out NRMSE shrink [%]")
    ax.legend(fontsize=8)
    head = (report.get("shares") or {}).get("headline") or ""
    ax.set_title(f"gap before/after adding the effect (verdict {report['verdict']})\n" + "\n".join(
        head[i:i + 110] for i in range(0, min(len(head), 330), 110)), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_all(arrays: dict[str, Any], report: dict[str, Any], out_dir: Path) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    return [residuals_over_time(arrays, report, out_dir / "residuals.png"),
            residual_spectra(arrays, report, out_dir / "spectra.png"),
            shrink_bars(report, out_dir / "shrink.png")]
