"""Identification and diagnosis of a just-closed flight, run in a worker process.

:func:`run_job` is the picklable entry point the service submits to a
``ProcessPoolExecutor(max_workers=1, mp_context=spawn)``: it reads and prepares the flight's .tlog
file(s) and identifies the hover model exactly as ``groundstation identify --config`` does
(:mod:`groundstation.pipeline`, with the service's configuration), validates it, writes
``model-flightNN.json`` next to the recording, diagnoses the gap when :mod:`groundstation.gap` is there
(``gap-flightNN.json``), draws a model-vs-measured PNG, and returns a JSON-able dict for the service to
publish. Errors come back as ``{"error": "one line"}`` so a bad flight never stops the service.

The numerical work is the other packages'; this module only chains them and writes files.
"""

from __future__ import annotations

import json
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.config import ServiceConfig

OUTPUTS = ("u", "v", "w", "p", "q", "r", "theta", "phi")


@dataclass(frozen=True)
class IdentifyJob:
    """One flight to identify, with the whole configuration (picklable: frozen dataclasses)."""

    flight: int
    tlogs: tuple[str, ...]          # the flight's .tlog (scope "last") or all flights so far ("all")
    out_dir: str
    config: ServiceConfig = ServiceConfig()

    @property
    def vehicle(self) -> str:
        return self.config.service.vehicle


def _warm() -> bool:
    """Imported-and-ready probe (submitted once at start so the first flight does not pay imports)."""
    import groundstation.dsp.prepare  # noqa: F401
    import groundstation.sysid.model  # noqa: F401
    return True


def _overlay(series: dict[str, Any], output_trim: dict[str, float]) -> dict[str, Any]:
    """Flatten validate()'s windowed series (W, L[, 8]) into time order, trims added back."""
    trim = np.array([output_trim.get(c, 0.0) for c in OUTPUTS])
    t = np.asarray(series["t_s"], dtype=float).reshape(-1)
    y = np.asarray(series["y"], dtype=float).reshape(-1, 8) + trim
    yhat = np.asarray(series["yhat"], dtype=float).reshape(-1, 8) + trim
    order = np.argsort(t, kind="stable")
    return {"t_fc_s": t[order], "measured": y[order], "model": yhat[order]}


def _plot(overlay: dict[str, Any], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 2, figsize=(12, 9), sharex=True)
    t = overlay["t_fc_s"]
    for i, (ax, c) in enumerate(zip(axes.T.ravel(), OUTPUTS, strict=True)):
        ax.plot(t, overlay["measured"][:, i], ".", ms=1.5, color="0.5", label="measured (smoothed)")
        ax.plot(t, overlay["model"][:, i], "-", lw=0.8, color="tab:red", label="model")
        ax.set_ylabel(c)
    axes[0, 0].legend(loc="upper right", fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("FC time (s)")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run_job(job: IdentifyJob) -> dict[str, Any]:
    """Identify (and diagnose) one flight; returns a JSON-able result dict (``error`` on failure)."""
    t0 = time.perf_counter()
    out_dir = Path(job.out_dir)
    res: dict[str, Any] = {"flight": job.flight, "tlogs": list(job.tlogs)}
    cfg = job.config
    try:
        from groundstation.pipeline import identify_prepared, prepare_logs

        prepared = prepare_logs(job.tlogs, cfg)
        if not prepared.segments:
            notes = "; ".join(prepared.notes) or "no in-air data"
            return {**res, "error": f"flight {job.flight}: nothing to identify ({notes})"}
        model = identify_prepared(prepared, cfg)
        doc = model.to_json()
        from groundstation.sysid.validate import validate

        val = validate(model, prepared, return_series=True)
        series = val.pop("series")
        match = {c: float(v["match"]) for c, v in val["channels"].items()}
        res["validation"] = val
        res["match_degree"] = match
        model_path = out_dir / f"model-flight{job.flight:02d}.json"
        model_path.write_text(json.dumps(doc, indent=1, default=float))
        res["model"] = doc
        res["model_path"] = str(model_path)
        overlay = _overlay(series, prepared.output_trim)
        if cfg.identification.plots and len(overlay["t_fc_s"]):
            png = out_dir / f"model-flight{job.flight:02d}.png"
            _plot(overlay, png, f"{job.vehicle} flight {job.flight}: model vs measured")
            res["png"] = [str(png)]
        # numpy arrays pickle fast back to the service (lists would cost the live loop a spike)
        res["overlay"] = {"t_fc_s": np.asarray(overlay["t_fc_s"], dtype=float),
                          "model": np.asarray(overlay["model"], dtype=float),
                          "measured": np.asarray(overlay["measured"], dtype=float)}
        res["identify_s"] = time.perf_counter() - t0
        if cfg.identification.diagnose:
            try:
                from groundstation.gap.diagnose import run_diagnosis
                from groundstation.gap.pictures import gap_pictures
            except ImportError:
                run_diagnosis = None  # type: ignore[assignment]
            if run_diagnosis is not None:
                try:
                    diag = run_diagnosis(model, prepared, seed=cfg.identification.seed, config=cfg.diagnose)
                    gap = diag.report
                    pictures = gap_pictures(diag)
                except Exception as exc:  # the model stands on its own: a failed diagnosis is reported
                    res["gap_error"] = f"flight {job.flight}: diagnosis: {type(exc).__name__}: {exc}".splitlines()[0]
                else:
                    gap_path = out_dir / f"gap-flight{job.flight:02d}.json"
                    gap_path.write_text(json.dumps(gap, indent=1, default=float))
                    res["gap"] = gap
                    res["gap_path"] = str(gap_path)
                    res["gap_pictures"] = pictures     # arrays for the live plots (service pops them)
        res["seconds"] = time.perf_counter() - t0
        return res
    except Exception as exc:  # reported to the service as one line; the service keeps running
        last = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
        where = f" ({Path(last.filename).name}:{last.lineno})" if last else ""
        return {**res, "error": f"flight {job.flight}: {type(exc).__name__}: {exc}{where}".splitlines()[0],
                "seconds": time.perf_counter() - t0}
