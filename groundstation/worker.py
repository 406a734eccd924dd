"""Identification and diagnosis of a just-closed flight, run in a worker process.

:func:`run_job` is the picklable entry point the service submits to a
``ProcessPoolExecutor(max_workers=1, mp_context=spawn)``: it reads and prepares the flight's .tlog
file(s) and identifies the hover model exactly as ``groundstation identify --config`` does
(:func:`groundstation.analysis.analyse`, with the service's configuration: the same model file,
held-out verdict included), validates it, writes
``model-flightNN.json`` next to the recording, checks the model in the frequency domain
(``freq-flightNN.json``: Tischler J per input-output pair, published on ``heli/{vehicle}/flight/{n}/freq``),
diagnoses the gap (``gap-flightNN.json``), draws a model-vs-measured PNG and the flight's self-contained HTML page
(``report-flightNN.html``, :mod:`groundstation.report`), and returns a :class:`JobResult` for the service
to publish. Errors come back as ``JobResult.error`` (one line) so a bad flight never stops the service.

The chain is :mod:`groundstation.analysis`'s; this module only writes its files and returns them.
"""

from __future__ import annotations

import dataclasses
import json
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.analysis import AnalysisError, analyse
from groundstation.config import ServiceConfig
from groundstation.freq.verify import freq_pairs
from groundstation.gap.pictures import gap_pictures
from groundstation.jsonio import dumps
from groundstation.pipeline import prepare_logs, with_aircraft_file
from groundstation.report import one_line_summary, render_report, write_html
from groundstation.report.collect import assemble, load_history
from groundstation.sysid.heldout import predict
from groundstation.sysid.model import OUTPUT_UNITS, OUTPUTS, HoverModel


@dataclass(frozen=True)
class IdentifyJob:
    """One flight to identify, with the whole configuration (picklable: frozen dataclasses)."""

    flight: int
    tlogs: tuple[str, ...]          # the flight's .tlog (scope "last") or all flights so far ("all")
    out_dir: str
    config: ServiceConfig = ServiceConfig()
    #: the flight before this one (its .tlog; its model is ``model-flightNN.json`` in ``out_dir``), -1 = none:
    #: the new model is scored on that flight and that flight's model on this one
    previous_flight: int = -1
    previous_tlogs: tuple[str, ...] = ()
    #: the flight's spectra accumulated live with ``[freq]``'s settings (a
    #: :class:`groundstation.freq.spectra.IncrementalResponses`), for a job of that flight alone: its
    #: frequency check uses them instead of a second pass over the log
    live_spectra: Any = None
    #: what the logs are: "telemetry" (the recorded link) or "onboard_log" (the FC's own log of a flight whose
    #: telemetry lost too much): its files are ``*-flightNN-onboard.*`` and its model and gap report say so
    data: str = "telemetry"

    @property
    def vehicle(self) -> str:
        return self.config.service.vehicle

    def file(self, kind: str, ext: str) -> Path:
        """Where this job writes its ``kind`` file (``model``, ``gap``, ...): ``kind-flightNN[-onboard].ext``."""
        tag = "-onboard" if self.data == "onboard_log" else ""
        return Path(self.out_dir) / f"{kind}-flight{self.flight:02d}{tag}.{ext}"


@dataclass(frozen=True)
class Overlay:
    """The model's outputs over the flight, for the live plot (FC time order)."""

    t_fc_s: np.ndarray              # (n,) s
    model: np.ndarray               # (n, 8) u v w p q r theta phi, trims added back
    measured: np.ndarray            # (n, 8) the smoothed measurements, same layout


@dataclass(frozen=True)
class JobResult:
    """What one job produced: a model (and gap report) or ``error``, one line."""

    flight: int | None
    tlogs: tuple[str, ...] = ()
    error: str | None = None
    model: dict[str, Any] | None = None            # the model file document (docs/model-file.md)
    model_path: str | None = None
    match_degree: dict[str, float] = field(default_factory=dict)   # % per output channel
    validation: dict[str, Any] | None = None
    png: tuple[str, ...] = ()
    overlay: Overlay | None = None
    gap: dict[str, Any] | None = None               # the gap report document (docs/gap-report.md)
    gap_path: str | None = None
    gap_error: str | None = None                    # diagnosis failed (the model is still good)
    gap_pictures: Any = None                        # groundstation.gap.pictures.GapPictures, for Rerun
    freq: dict[str, Any] | None = None              # heli-freq-verification/1: Tischler J per pair
    freq_path: str | None = None
    freq_error: str | None = None                   # frequency check failed (the model is still good)
    freq_pairs: Any = None                          # Bode arrays per scored pair (data, model, coherence), for Rerun
    trends: dict[str, Any] | None = None            # heli-trends/1 over the vehicle's flights ([service] campaign_db)
    trends_error: str | None = None                 # the campaign table failed (the model is still good)
    report_path: str | None = None                  # report-flightNN.html: the flight's self-contained page
    report_summary: str | None = None               # what the page says, one line
    report_error: str | None = None                 # the page failed (the model is still good)
    identify_s: float | None = None
    seconds: float = 0.0
    data: str = "telemetry"                         # the job's data: telemetry or onboard_log (IdentifyJob.data)

    @property
    def ok(self) -> bool:
        return self.error is None


def _warm() -> bool:
    """Imported-and-ready probe, submitted once at start so the first flight does not pay imports: to
    run it, the worker process imports this module and with it the whole analysis."""
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
        ax.set_ylabel(f"{c} [{OUTPUT_UNITS[c]}]")
    axes[0, 0].legend(loc="upper right", fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("FC time [s]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run_job(job: IdentifyJob) -> JobResult:
    """Identify (and diagnose) one flight; a failure comes back as ``JobResult.error`` (one line)."""
    t0 = time.perf_counter()
    try:
        return _identify_flight(job, t0)
    except Exception as exc:  # reported to the service as one line; the service keeps running
        last = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
        where = f" ({Path(last.filename).name}:{last.lineno})" if last else ""
        return JobResult(flight=job.flight, tlogs=job.tlogs,
                         error=f"flight {job.flight}: {type(exc).__name__}: {exc}{where}".splitlines()[0],
                         seconds=time.perf_counter() - t0, data=job.data)


def _cross_flight(job: IdentifyJob, model: Any, prepared: Any) -> dict[str, Any]:
    """Is the aircraft the same as on the previous flight? The new model predicting the previous flight
    and the previous flight's model predicting this one (held-out match, 5-s windows from the measured
    states); empty without a previous flight, an ``error`` line when it cannot be scored."""
    if job.previous_flight < 0 or not job.previous_tlogs:
        return {}

    out: dict[str, Any] = {"previous_flight": job.previous_flight}
    try:
        prev = prepare_logs(job.previous_tlogs, job.config)
        p = predict(model, prev)
        out["new_model_on_previous_flight"] = {"mean_match": p.mean_match, "match": p.match}
        prev_path = Path(job.out_dir) / f"model-flight{job.previous_flight:02d}.json"
        if prev_path.exists():
            q = predict(HoverModel.from_json(json.loads(prev_path.read_text())), prepared)
            out["previous_model_on_new_flight"] = {"mean_match": q.mean_match, "match": q.match}
    except Exception as exc:  # a previous flight that cannot be scored does not stop this one
        out["error"] = f"{type(exc).__name__}: {exc}".splitlines()[0]
    return out


def _live_responses(job: IdentifyJob) -> Any:
    """The flight's responses from the spectra the service accumulated live (None: estimate them from the
    log). Only for a job of that one flight, and only when they can be computed."""
    spectra = job.live_spectra
    if spectra is None or len(job.tlogs) != 1 or not getattr(spectra, "rows", 0):
        return None
    try:
        return spectra.responses()
    except ValueError:          # too little in-air data: the log's own estimate says why
        return None


def _identify_flight(job: IdentifyJob, t0: float) -> JobResult:
    cfg, aircraft = with_aircraft_file(job.config)
    job = dataclasses.replace(job, config=cfg)
    steps = ("identify", "heldout", "validate", "freq") + (("diagnose",) if cfg.identification.diagnose else ())
    validated_s: list[float] = []

    def on(ev: Any) -> None:
        if ev.step == "validate" and ev.state == "done":
            validated_s.append(time.perf_counter() - t0)

    try:
        res = analyse(list(job.tlogs), aircraft, cfg, steps=steps, progress=on, keep_going=True,
                      responses=_live_responses(job))
    except AnalysisError as exc:
        if not str(exc).startswith("nothing to identify"):
            raise
        return JobResult(flight=job.flight, tlogs=job.tlogs, error=f"flight {job.flight}: {exc}",
                         seconds=time.perf_counter() - t0, data=job.data)
    model, prepared, val = res.model, res.prepared, ({} if res.validation is None else res.validation.to_json())
    cross = _cross_flight(job, model, prepared)
    if cross:
        model.fit = model.fit.set(cross_flight=cross)
    if job.data == "onboard_log":   # said in the model (and below the gap report): which data it comes from
        model.source["data"] = "onboard_log"
        model.source["replaces"] = str(dataclasses.replace(job, data="telemetry").file("model", "json"))
    doc = model.to_json()
    model_path = job.file("model", "json")
    model_path.write_text(dumps(doc, indent=1))
    assert res.validation_series is not None   # the validate step ran (analyse raises where it cannot)
    overlay = _overlay(res.validation_series, prepared.output_trim)
    png: tuple[str, ...] = ()
    if cfg.identification.plots and len(overlay["t_fc_s"]):
        png_path = job.file("model", "png")
        _plot(overlay, png_path, f"{job.vehicle} flight {job.flight}: model vs measured")
        png = (str(png_path),)
    identify_s = validated_s[0] if validated_s else time.perf_counter() - t0
    freq, freq_path, freq_error, bode = _freq_files(job, res)
    gap, gap_path, gap_error, pictures = (_gap_files(job, res, model_path) if cfg.identification.diagnose
                                          else (None, None, None, None))
    trends, trends_error = _trends(job, model, gap, prepared, time.perf_counter() - t0)
    report_path, report_summary, report_error = (
        _report(job, prepared, model, res.validation, res.freq, gap, pictures,
                {"freq": freq_error, "gap": gap_error, "history": trends_error})
        if cfg.identification.plots else (None, None, None))
    return JobResult(
        flight=job.flight, tlogs=job.tlogs, model=doc, model_path=str(model_path),
        match_degree={c: float(v["match"]) for c, v in val["channels"].items()}, validation=val, png=png,
        # numpy arrays pickle fast back to the service (lists would cost the live loop a spike)
        overlay=Overlay(*(np.asarray(overlay[k], dtype=float) for k in ("t_fc_s", "model", "measured"))),
        gap=gap, gap_path=gap_path, gap_error=gap_error, gap_pictures=pictures, identify_s=identify_s,
        freq=freq, freq_path=freq_path, freq_error=freq_error, freq_pairs=bode, trends=trends, trends_error=trends_error,
        report_path=report_path, report_summary=report_summary, report_error=report_error,
        seconds=time.perf_counter() - t0, data=job.data)


def _trends(job: IdentifyJob, model: Any, gap: Any, prepared: Any, seconds: float) -> tuple[Any, Any]:
    """(trend summary, None) after putting the flight into ``[service] campaign_db``, (None, None) when
    that is off or the model is of several flights (scope "all"), or (None, one-line error)."""
    cfg = job.config
    if not cfg.service.campaign_db or len(job.tlogs) != 1 or job.data != "telemetry":   # one row per flight
        return None, None
    try:
        # here, not at the top: the campaign table's trend tests bring scipy.stats (about 0.9 s), and the
        # service imports this module in its own process, which never runs them
        from groundstation.campaign.live import record_flight

        return record_flight(Path(job.out_dir) / cfg.service.campaign_db, job.vehicle, job.tlogs[0], job.flight,
                             model, gap, prepared, cfg, seconds), None
    except Exception as exc:  # the model and the gap report stand on their own
        return None, f"flight {job.flight}: trends: {type(exc).__name__}: {exc}".splitlines()[0]


def _report(job: IdentifyJob, prepared: Any, model: Any, validation: Any, verification: Any,
            gap: Any, pictures: Any, errors: dict[str, str | None]) -> tuple[Any, Any, Any]:
    """(``report-flightNN.html`` path, one-line summary, None) of the flight's page, drawn from what this
    job computed, or (None, None, one-line error): the model stands on its own."""
    try:
        cfg = job.config
        history: tuple[dict[str, Any], ...] = ()
        label = ""
        if cfg.service.campaign_db and (Path(job.out_dir) / cfg.service.campaign_db).exists():
            history, label = load_history(Path(job.out_dir) / cfg.service.campaign_db, job.vehicle)
        data = assemble(job.tlogs, cfg, prepared=prepared, model=model, validation=validation,
                        freq=verification, gap=gap, pictures=pictures, history=history, history_label=label,
                        errors=errors, title=f"{job.vehicle} flight {job.flight}", aircraft=job.vehicle)
        path = write_html(job.file("report", "html"), render_report(data))
        return str(path), one_line_summary(data), None
    except Exception as exc:
        return None, None, f"flight {job.flight}: report: {type(exc).__name__}: {exc}".splitlines()[0]


def _freq_files(job: IdentifyJob, res: Any) -> tuple[Any, Any, Any, Any]:
    """(J table document, its file, None, Bode arrays per scored pair) of the analysis's frequency-domain
    check, or (None, None, one-line error, None): the model stands on its own."""
    if res.freq is None:
        why = res.errors.get("freq", "no result")
        return None, None, f"flight {job.flight}: frequency check: {why}", None
    try:
        doc = {**res.freq.to_json(), "vehicle": job.vehicle, "flight": job.flight, "data": job.data}
        path = job.file("freq", "json")
        path.write_text(dumps(doc, indent=1))
        return doc, str(path), None, freq_pairs(res.freq)
    except Exception as exc:
        return None, None, f"flight {job.flight}: frequency check: {type(exc).__name__}: {exc}".splitlines()[0], None


def _gap_files(job: IdentifyJob, res: Any, model_path: Path) -> tuple[Any, Any, Any, Any]:
    """(gap report, its file, None, pictures for the live plots), or (None, None, one-line error, None):
    the model stands on its own."""
    if res.gap is None:
        return None, None, f"flight {job.flight}: diagnosis: {res.errors.get('diagnose', 'no result')}", None
    try:
        report = res.gap.report
        report["source"]["model"] = str(model_path)
        if job.data == "onboard_log":
            report["source"]["data"] = "onboard_log"
        pictures = gap_pictures(res.gap.diagnosis)
    except Exception as exc:
        return None, None, f"flight {job.flight}: diagnosis: {type(exc).__name__}: {exc}".splitlines()[0], None
    gap_path = job.file("gap", "json")
    gap_path.write_text(dumps(report, indent=1))
    return report, str(gap_path), None, pictures
