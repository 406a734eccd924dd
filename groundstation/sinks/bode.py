"""Bode plots of a frequency-domain verification: PNG (matplotlib, Agg) and Rerun.

:func:`plot_bode` writes one PNG per input (``<stem>_<input>.png``): a column per output with a
response, rows magnitude (dB), phase (deg) and coherence; flight data as points (coherent points
filled, with their 95 % random-error band; the others faint), the model as a line, Tischler's J
in the title. Pairs without a response are never drawn: they are listed in the figure's footer
with the reason. :func:`log_bode` logs the same to one explicit :class:`rerun.RecordingStream`
on a ``frequency_mhz`` sequence timeline (entities ``{root}/{input}/{output}/{magnitude_db,
phase_deg,coherence}/{data,model,upper,lower}``) and the J table as a static text document.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.freq.metrics import Z95_COMPLEX
from groundstation.sysid.model import INPUTS, OUTPUTS


def _series(v: Any, p: Any) -> dict[str, np.ndarray]:
    """Data, model and 95 % bands of one pair on the composite frequencies."""
    g = v.model[:, OUTPUTS.index(p.output), INPUTS.index(p.input)]
    eps = np.nan_to_num(p.random_error, nan=np.inf) * Z95_COMPLEX
    mag = 20 * np.log10(np.abs(p.response))
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = mag + 20 * np.log10(np.clip(1 - eps, 1e-3, None))
        hi = mag + 20 * np.log10(1 + eps)
        ph_band = np.degrees(np.arcsin(np.clip(eps, 0, 1)))
        ph_band = np.where(eps >= 1, 180.0, ph_band)
    ph = np.degrees(np.angle(p.response))
    ph_m = np.degrees(np.angle(g))
    ph = ph_m + ((ph - ph_m + 180.0) % 360.0 - 180.0)  # data phase drawn on the model's branch
    return {"f": p.f_hz, "mag": mag, "mag_lo": lo, "mag_hi": hi, "ph": ph, "ph_lo": ph - ph_band, "ph_hi": ph + ph_band,
            "coh": p.coherence, "mag_model": 20 * np.log10(np.maximum(np.abs(g), 1e-300)),
            "ph_model": np.degrees(np.unwrap(np.angle(g)))}


def plot_bode(v: Any, path: str | Path, *, title: str = "") -> list[Path]:
    """Write one Bode PNG per input that has a scored pair; returns the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    scores = {(s.input, s.output): s for s in v.pairs}
    written = []
    for inp in INPUTS:
        pairs = [p for p in v.responses.with_response if p.input == inp and (p.input, p.output) in scores]
        if not pairs:
            continue
        fig, axes = plt.subplots(3, len(pairs), figsize=(3.4 * len(pairs) + 0.6, 7.5), sharex=True, squeeze=False)
        for c, p in enumerate(pairs):
            s = _series(v, p)
            m = p.coherent
            a_mag, a_ph, a_coh = axes[:, c]
            for ax, key in ((a_mag, "mag"), (a_ph, "ph")):
                ax.plot(s["f"][~m], s[key][~m], ".", color="0.8", ms=2, label="not coherent (not used)")
                ax.plot(s["f"][m], s[key][m], "o", color="C0", ms=3, label="flight (coherent)")
                ax.fill_between(s["f"], np.where(m, s[f"{key}_lo"], np.nan), np.where(m, s[f"{key}_hi"], np.nan),
                                color="C0", alpha=0.2, label="95 % random error")
                ax.plot(s["f"], s[f"{key}_model"], "-", color="C3", label="model")
                ax.grid(True, which="both", alpha=0.3)
            a_coh.plot(s["f"], s["coh"], ".-", color="C2", ms=3)
            a_coh.axhline(v.responses.config.coherence_min, color="k", ls=":", lw=0.8)
            a_coh.set_ylim(0, 1.02)
            a_coh.set_xscale("log")
            a_coh.set_xlabel("frequency (Hz)")
            a_coh.grid(True, which="both", alpha=0.3)
            sc = scores[(p.input, p.output)]
            a_mag.set_title(f"{p.input} -> {p.output}: J = {sc.J:.0f} ({'pass' if sc.passed else 'FAIL'})", fontsize=9)
        axes[0, 0].set_ylabel("magnitude (dB)")
        axes[1, 0].set_ylabel("phase (deg)")
        axes[2, 0].set_ylabel("coherence")
        axes[0, 0].legend(fontsize=7, loc="best")
        missing = [f"{i}->{o}: {r}" for i, o, r in v.no_response if i == inp]
        foot = "no response: " + "; ".join(missing) if missing else ""
        fig.suptitle(f"{title}  input {inp}" if title else f"input {inp}", fontsize=10)
        if foot:
            fig.text(0.01, 0.005, foot[:400], fontsize=6, va="bottom", wrap=True)
        fig.tight_layout(rect=(0, 0.03, 1, 0.97))
        out = path.with_name(f"{path.stem}_{inp}{path.suffix or '.png'}")
        fig.savefig(out, dpi=90)
        plt.close(fig)
        written.append(out)
    return written


def log_bode(rec: Any, v: Any, root: str = "/freq") -> None:
    """Log the verification's Bode data and J table to the RecordingStream ``rec``."""
    import rerun as rr

    scores = {(s.input, s.output) for s in v.pairs}
    for p in v.responses.with_response:
        if (p.input, p.output) not in scores:
            continue
        s = _series(v, p)
        m = p.coherent
        idx = [rr.TimeColumn("frequency_mhz", sequence=np.round(s["f"][m] * 1000).astype(np.int64))]
        base = f"{root}/{p.input}/{p.output}"
        for q, keys in (("magnitude_db", ("mag", "mag_model", "mag_lo", "mag_hi")),
                        ("phase_deg", ("ph", "ph_model", "ph_lo", "ph_hi"))):
            for kind, key in zip(("data", "model", "lower", "upper"), keys, strict=True):
                rec.send_columns(f"{base}/{q}/{kind}", indexes=idx, columns=rr.Scalars.columns(scalars=s[key][m]))
        rec.send_columns(f"{base}/coherence/data", indexes=idx, columns=rr.Scalars.columns(scalars=s["coh"][m]))
    rec.log(f"{root}/J", rr.TextDocument(json.dumps(v.to_json(), indent=1, allow_nan=False), media_type="text/plain"),
            static=True)
