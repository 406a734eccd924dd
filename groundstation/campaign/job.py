"""One log of a campaign analysed into table rows (one row per flight in the log).

:func:`analyse` is the picklable unit of work (a process pool or a Dask worker runs it): it reads
the log, prepares it, and for each flight (armed interval) in it identifies the hover model and
diagnoses the gap (held-out, k-fold) with :func:`groundstation.analysis.analyse_prepared`, predicts a reference flight with the model (the campaign's
previous log: the cross-flight fit, :func:`groundstation.sysid.heldout.predict`) and returns plain JSON-able rows. A failure becomes a row with
``error`` set (one line) and never stops the campaign. Memory is one log's at a time per worker.

When the reference is another job of the same run, that job hands its prepared log back to the
caller and the caller does the cross-flight fit (:func:`analyse_handing_over`, ``cross_by_caller`` and
``hand_over``, :func:`groundstation.campaign.runner.run`): no log is read and prepared twice.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
import time
import traceback
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from groundstation.analysis import analyse_prepared
from groundstation.config import ServiceConfig
from groundstation.freq.spectra import estimate_responses
from groundstation.freq.verify import verify
from groundstation.gap.pictures import gap_pictures
from groundstation.parallel import keep_freed_memory
from groundstation.pipeline import load_logs, prepare_logs, prepare_native, with_aircraft
from groundstation.report import render_report, write_html
from groundstation.report.collect import assemble
from groundstation.sysid.heldout import predict
from groundstation.sysid.model import INPUTS, PARAM_NAMES

#: bumped when the rows' meaning changes: a new version re-analyses everything
ROW_SCHEMA = "heli-campaign-row/1"
LOG_SUFFIXES = (".tlog", ".bin", ".ulg", ".px4log")


@dataclass(frozen=True)
class Settings:
    """How every flight is analysed; part of the skip key (changed settings re-analyse)."""

    #: the configuration (:class:`groundstation.config.ServiceConfig`; default when None) with the
    #: command's options applied: [prepare], [identify], [bounds], [identification], [diagnose]
    config: Any = None
    diagnose: bool = True
    #: aircraft file content (TOML text), "" when none; ``aircraft`` the loaded file
    #: (:class:`groundstation.aircraft.Aircraft`: channel map, outputs, prior model) or None
    aircraft_text: str = ""
    aircraft: Any = None

    def service_config(self) -> Any:
        return self.config if self.config is not None else ServiceConfig()

    def key(self) -> str:
        """Short hash of everything that changes a result."""
        doc = json.dumps([ROW_SCHEMA, repr(self.service_config()), self.diagnose, self.aircraft_text], default=str)
        return hashlib.sha256(doc.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class FlightJob:
    """One log to analyse; ``reference_log`` is the flight the model is cross-checked on (or None)."""

    log: str
    sha256: str
    aircraft: str
    settings: Settings
    reference_log: str | None = None
    #: where the flight's HTML page goes (``<log name>.html``, or ``<log name>-flightN.html`` for the
    #: second and later flights of a log), None for no page
    report_dir: str | None = None
    #: the caller scores the models on the reference (another job of the same run hands it the
    #: reference prepared, :func:`analyse_handing_over`): this job does not read the reference log
    cross_by_caller: bool = False
    #: hand the log prepared back to the caller (it is another job's reference)
    hand_over: bool = False


@dataclass
class Handover:
    """What a job hands back to its caller beside the rows: the log prepared (only with
    ``FlightJob.hand_over``; None when it could not be prepared) and the model of each flight."""

    prepared: Any = None
    models: dict[int, Any] = field(default_factory=dict)


def file_sha256(path: str | Path) -> str:
    """Content hash of a log (what makes a re-run skip it)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def log_date_utc(path: str | Path) -> tuple[str, str]:
    """(ISO date-time UTC, where it came from): a .tlog's first record timestamp, else the file's mtime."""
    p = Path(path)
    if p.suffix.lower() == ".tlog":
        with open(p, "rb") as f:
            head = f.read(8)
        if len(head) == 8:
            us = struct.unpack(">Q", head)[0]
            if 946684800e6 < us < 4102444800e6:  # 2000..2100
                return datetime.fromtimestamp(us / 1e6, UTC).isoformat(timespec="seconds"), "tlog timestamp"
    return datetime.fromtimestamp(p.stat().st_mtime, UTC).isoformat(timespec="seconds"), "file mtime"


def find_logs(paths: list[Path]) -> list[Path]:
    """Every log file under the given directories (recursively) or given directly, sorted, unique."""
    out: set[Path] = set()
    for p in paths:
        if p.is_dir():
            out.update(q for q in p.rglob("*") if q.is_file() and q.suffix.lower() in LOG_SUFFIXES)
        elif p.is_file():
            out.add(p)
        else:
            raise OSError(f"{p}: no such file or directory")
    return sorted(out)


def _conditions(prepared: Any) -> dict[str, float | None]:
    """Flight conditions of the in-air data: duration, mean horizontal speed, input activity."""
    out = np.concatenate([s.outputs for s in prepared.segments])
    inp = np.concatenate([s.inputs for s in prepared.segments])
    speed = np.hypot(out[:, 0] + prepared.output_trim.get("u", 0.0), out[:, 1] + prepared.output_trim.get("v", 0.0))
    row: dict[str, float | None] = {"in_air_s": float(prepared.duration_s),
           "mean_speed_m_s": float(np.nanmean(speed)) if np.isfinite(speed).any() else None}
    for j, name in enumerate(INPUTS):
        row[f"input_rms_{name}"] = float(np.std(inp[:, j]))
    return row


def effect_values(report: dict) -> dict[str, float]:
    """``{"deadband[lon].half_width": 0.03, ...}``: every estimate of every scored effect, significant or not.

    The named effects first, then the partial findings (named by their own tests but not as the
    verdict: below the share needed, or changing through the flight; each still carries its
    whole-flight estimate), then the other candidates; an effect's first entry wins."""
    vals: dict[str, float] = {}
    for e in (list(report.get("effects", [])) + list(report.get("partial_findings") or [])
              + list(report.get("candidates", []))):
        ch = e.get("input") or e.get("output") or ""
        for k, v in (e.get("estimate") or {}).items():
            key = f"{e['effect']}[{ch}].{k}" if ch else f"{e['effect']}.{k}"
            if v is not None and key not in vals:
                vals[key] = float(v)
    return vals


def model_row(model: Any, report: dict | None, prepared: Any) -> dict[str, Any]:
    """The table columns of one identified (and diagnosed) flight: conditions, parameters with
    standard errors, fits, gap verdict and effect estimates (``report`` None: not diagnosed)."""
    fit = model.fit
    row: dict[str, Any] = {**_conditions(prepared), "cost": fit.cost, "windows": fit.windows,
                           "fixed": json.dumps(list(fit.fixed)), "pinned": json.dumps(list(model.pinned))}
    for n in PARAM_NAMES:
        row[f"p_{n}"] = float(model.params[n])
        se = model.parameter_std.get(n)
        row[f"se_{n}"] = None if se is None or not np.isfinite(se) else float(se)
    row["train_match_pct"] = _mean(fit.match_degree)
    row.update({"verdict": None, "heldout_match_pct": None, "effects": "[]", "effect_values": "{}",
                "gap_significant": None, "conditions": None})
    if report is not None:
        ch = report["gap"]["channels"]
        row.update({"verdict": report["verdict"], "heldout_match_pct": _mean({k: v["match"] for k, v in ch.items()}),
                    "effects": json.dumps(report["effects"]), "effect_values": json.dumps(effect_values(report)),
                    "gap_significant": bool(report["gap"].get("significant")),
                    "conditions": report["gap"].get("conditions")})
    row["model"] = json.dumps(model.to_json(), default=float)
    return row


def _flight_row(job: FlightJob, prepared: Any, flight: int, ref: Any) -> tuple[dict[str, Any], Any]:
    t0 = time.perf_counter()
    cfg = job.settings.service_config()
    res = analyse_prepared(prepared, cfg, job.settings.aircraft, log_paths=[job.log],
                           steps=("identify", "diagnose") if job.settings.diagnose else ("identify",))
    model = res.model
    model.fit = model.fit.without("seconds")   # the row has its own; a stored row is the same whichever backend ran it
    diag = res.gap.diagnosis if res.gap is not None else None
    report = res.gap.report if res.gap is not None else None
    row = {"flight_index": flight, **model_row(model, report, prepared), "cross_log": None, "cross_match_pct": None}
    if ref is not None:
        row.update(cross_fit(model, ref, job.reference_log or ""))
    if job.report_dir:
        row["report_page"], row["report_error"] = flight_page(job, prepared, flight, model, diag)
    row["seconds"] = round(time.perf_counter() - t0, 3)
    row.update({f"{k}_s": res.seconds.get(k) for k in ("identify", "diagnose")})   # wall of each step
    return row, model


def cross_fit(model: Any, ref: Any, reference_log: str) -> dict[str, Any]:
    """The row's cross-flight columns: the model's mean match predicting the reference (prepared),
    or, when the reference holds no usable window, the reason beside its name (reported, not fatal)."""
    name = Path(reference_log).name
    try:
        return {"cross_match_pct": float(predict(model, ref).mean_match), "cross_log": name}
    except ValueError as exc:
        return {"cross_match_pct": None, "cross_log": f"{name}: {exc}"}


def page_name(log_name: str, flight: int) -> str:
    """The file name of a campaign flight's page in the report directory."""
    return f"{log_name}.html" if flight == 0 else f"{log_name}-flight{flight}.html"


def flight_page(job: FlightJob, prepared: Any, flight: int, model: Any, diag: Any) -> tuple[str | None, str | None]:
    """(path, None) of the flight's HTML page (:mod:`groundstation.report`) drawn from this job's model and
    diagnosis plus the frequency check, or (None, one-line error): the row stands without it."""
    try:
        cfg = with_aircraft(job.settings.service_config(), job.settings.aircraft)
        errors: dict[str, str | None] = {} if diag is not None else {"gap": "not diagnosed (--no-diagnose)"}
        freq = None
        try:
            freq = verify(model.theta, estimate_responses(prepare_native(load_logs([job.log]), cfg.prepare), cfg.freq))
        except ValueError as exc:
            errors["freq"] = str(exc).splitlines()[0]
        data = assemble([job.log], cfg, prepared=prepared, model=model, freq=freq,
                        gap=None if diag is None else diag.report,
                        pictures=None if diag is None else gap_pictures(diag), errors=errors, aircraft=job.aircraft,
                        title=f"{job.aircraft}: {Path(job.log).name} flight {flight}")
        path = write_html(Path(job.report_dir or ".") / page_name(Path(job.log).name, flight), render_report(data))
        return str(path), None
    except Exception as exc:  # noqa: BLE001 - the row stands without its page
        return None, _one_line(job, exc)


def _mean(d: dict) -> float | None:
    v = [float(x) for x in d.values() if x is not None and np.isfinite(x)]
    return float(np.mean(v)) if v else None


def analyse(job: FlightJob) -> list[dict[str, Any]]:
    """Rows (one per flight of the log) for the campaign table; errors as rows with ``error`` set.

    Besides the table's columns each row carries the job's ``cpu_s`` and ``page_faults`` (minor
    faults; None off Unix), shared by its flights, ``worker_pid``, ``task_start_s``,
    ``task_end_s`` (``time.monotonic``, one clock for every process of a machine), ``read_s`` (the
    job's reading and preparing of its log) and the flight's ``identify_s`` and ``diagnose_s`` (wall
    seconds of each step): what the work cost and how it was spread over the workers (the store
    keeps none of these)."""
    return analyse_handing_over(job)[0]


def analyse_handing_over(job: FlightJob) -> tuple[list[dict[str, Any]], Handover]:
    """:func:`analyse`, and what the job hands back to its caller (:class:`Handover`)."""

    start_s = time.monotonic()
    keep_freed_memory()
    date, date_src = log_date_utc(job.log)
    base = {"aircraft": job.aircraft, "log": job.log, "log_name": Path(job.log).name, "sha256": job.sha256,
            "settings_key": job.settings.key(), "date_utc": date, "date_source": date_src, "error": None}
    hand = Handover()
    t0, c0, f0 = time.perf_counter(), time.process_time(), _minor_faults()
    try:
        cfg = job.settings.service_config()
        with threadpool_limits(1):  # one core per job: the pool or the cluster provides the parallelism
            prepared = prepare_logs([job.log], cfg, aircraft=job.settings.aircraft)
            read_s = round(time.perf_counter() - t0, 3)
            hand.prepared = prepared if job.hand_over else None
            if not prepared.segments:
                raise ValueError(f"nothing to identify ({'; '.join(prepared.notes) or 'no in-air data'})")
            ref = None
            if job.reference_log and not job.cross_by_caller:
                try:
                    ref = prepare_logs([job.reference_log], cfg, aircraft=job.settings.aircraft)
                except Exception:  # noqa: BLE001 - a bad reference only loses the cross-flight fit
                    ref = None
            rows = []
            for flight in sorted({s.flight for s in prepared.segments}):
                sub = prepared.subset([i for i, s in enumerate(prepared.segments) if s.flight == flight])
                try:
                    row, hand.models[flight] = _flight_row(job, sub, flight, ref)
                    rows.append({**base, **row})
                except Exception as exc:  # noqa: BLE001 - one flight's failure is its row
                    rows.append({**base, "flight_index": flight, "error": _one_line(job, exc)})
            timing = {"worker_pid": os.getpid(), "task_start_s": start_s, "task_end_s": time.monotonic(),
                      "read_s": read_s}
            f1 = _minor_faults()
            for r in rows:  # the job's CPU (this process's, all threads) and faults, shared by its flights
                r.update(cpu_s=round((time.process_time() - c0) / len(rows), 3), **timing,
                         page_faults=None if f0 is None or f1 is None else (f1 - f0) // len(rows))
            return rows, hand
    except Exception as exc:  # noqa: BLE001 - reported as a row, the campaign goes on
        return [{**base, "flight_index": 0, "error": _one_line(job, exc),
                 "seconds": round(time.perf_counter() - t0, 3)}], hand


def _minor_faults() -> int | None:
    try:
        import resource
    except ImportError:  # not Unix
        return None
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_minflt)


def _one_line(job: FlightJob, exc: BaseException) -> str:
    last = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
    where = f" ({Path(last.filename).name}:{last.lineno})" if last else ""
    return f"{Path(job.log).name}: {type(exc).__name__}: {exc}{where}".splitlines()[0]
