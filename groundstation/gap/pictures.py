"""The arrays behind a diagnosis's pictures, small enough to send from the worker to the live sinks.

:func:`gap_pictures` turns a :class:`groundstation.gap.diagnose.Diagnosis` into a
:class:`GapPictures` (frozen, numpy arrays, picklable): the held-out residual of every diagnosed
channel over FC time, the flagged windows, the raw-residual spectrum against its local noise floor
with the significant lines, and for each named effect the held-out error per window before and
after adding it. Drawing (Rerun, PNG) is the sinks' and the commands' business. Pure: no IO.

Array conventions: times in FC seconds ``(n,)``; per-channel arrays ``(n, 8)`` in the order of
:data:`groundstation.sysid.model.OUTPUTS`, model units (m/s, rad/s, rad); NaN where a channel is
not diagnosed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from groundstation.sysid.model import OUTPUTS


@dataclass(frozen=True)
class EffectPicture:
    """Held-out NRMSE per window of the base model and of the model with one effect added."""

    label: str                 # e.g. "input_delay lon"
    significant: bool
    t_s: np.ndarray            # (W,) window centres, FC s
    before_pct: np.ndarray     # (W, 8) 100 * sqrt(sse / energy) of the base model
    after_pct: np.ndarray      # (W, 8) the same with the effect
    channels: tuple[str, ...]  # the outputs the effect acts on most
    share: str = ""            # e.g. "partial, 28 % of the gap above noise" (the report's share)


@dataclass(frozen=True)
class GapPictures:
    t_s: np.ndarray                          # (n,) FC time of the held-out residual samples
    residual: np.ndarray                     # (n, 8) measured (smoothed) - held-out model prediction
    channels: tuple[str, ...]                # diagnosed channels
    flagged_s: tuple[tuple[float, float], ...]
    f_hz: np.ndarray                         # (F,)
    psd: np.ndarray                          # (F, 8) raw-residual power spectral density
    floor: np.ndarray                        # (F, 8) local median of the PSD (the line test's floor)
    lines_hz: tuple[float, ...]              # significant narrow lines
    effects: tuple[EffectPicture, ...]


def _residual(arrays: dict[str, Any], channels: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    T, Y, yh, mask = arrays["t_s"], arrays["Y"], arrays["yhat"], np.asarray(arrays["mask"], bool)
    t = np.asarray(T)[:, mask].reshape(-1)
    r = (np.asarray(Y) - np.asarray(yh))[:, mask, :].reshape(-1, 8)
    keep = np.array([n in channels for n in OUTPUTS])
    r = np.where(keep[None, :], r, np.nan)
    order = np.argsort(t, kind="stable")
    return t[order], r[order]


def _effect_pictures(arrays: dict[str, Any], report: dict[str, Any], max_effects: int) -> tuple[EffectPicture, ...]:
    ev, ctx = arrays.get("evaluator"), arrays.get("ctx")
    cands = arrays.get("candidates") or []
    if ev is None or not cands:
        return ()
    # named effects, then the partial findings (named by their own tests, not by the shares or the
    # halves): each labelled with its share of the gap above noise, as the report's headline says
    named = [(e["effect"], e.get("input"), e.get("output"), True, _share(e, "")) for e in report.get("effects", [])]
    named += [(e["effect"], e.get("input"), e.get("output"), True, _share(e, "partial, "))
              for e in report.get("partial_findings", [])]
    if not named and report.get("candidates"):
        e = report["candidates"][0]
        named = [(e["effect"], e.get("input"), e.get("output"), False, "")]
    mask = np.asarray(ev.mask, bool)
    t_mid = np.asarray(ev.T)[:, mask].mean(axis=1)
    energy = np.maximum(np.asarray(ev.energy, dtype=float), 1e-30)
    out = []
    for effect, inp, outp, sig, share in named[:max_effects]:
        c = next((c for c in cands if c.hyp.effect == effect and c.hyp.input == inp and c.hyp.output == outp), None)
        if c is None or c.hyp.sse is None:
            continue
        base = c.hyp.extra.get("base_sse", getattr(ctx, "base_sse", None))
        if base is None:
            continue
        label = " ".join(x for x in (effect, inp, outp) if x)
        out.append(EffectPicture(
            label=label, significant=sig, t_s=t_mid, share=share.strip(" ()"),
            before_pct=100.0 * np.sqrt(np.asarray(base, dtype=float) / energy),
            after_pct=100.0 * np.sqrt(np.asarray(c.hyp.sse, dtype=float) / energy),
            channels=tuple(OUTPUTS[k] for k in c.hyp.channels)))
    return tuple(out)


def _share(e: dict[str, Any], prefix: str) -> str:
    """`` (partial, 28 % of the gap above noise)`` for a report effect entry; the prefix alone without a share."""
    sp = e.get("share_pct")
    if sp is None:
        return f" ({prefix.rstrip(', ')})" if prefix else ""
    return f" ({prefix}{sp:.0f} % of the gap above noise)"


def gap_pictures(diagnosis: Any, max_effects: int = 3) -> GapPictures:
    """The pictures of ``diagnosis`` (a :class:`~groundstation.gap.diagnose.Diagnosis`)."""
    report, arrays = diagnosis.report, diagnosis.arrays
    channels = tuple(n for n in OUTPUTS if n in report["gap"]["channels"])
    t, r = _residual(arrays, channels)
    sp = arrays["spectra"]
    psd = np.asarray(sp["psd"], dtype=float)
    ratio = np.asarray(sp["ratio"], dtype=float)
    floor = np.where(ratio > 0, psd / np.where(ratio > 0, ratio, 1.0), np.nan)
    return GapPictures(
        t_s=t, residual=r, channels=channels,
        flagged_s=tuple((float(a), float(b)) for a, b in report["gap"]["windows_s"] if a is not None and b is not None),
        f_hz=np.asarray(sp["f_hz"], dtype=float), psd=psd, floor=floor,
        lines_hz=tuple(float(ln["frequency_hz"]) for ln in report["fingerprints"]["spectral_lines"]),
        effects=_effect_pictures(arrays, report, max_effects))
