"""Runs what a flight report needs and is missing, and gathers it into a :class:`FlightReportData`.

:func:`collect` reads the logs and summarises their data quality (the ``log-info`` summary), then runs
the one analysis pipeline, :func:`groundstation.analysis.analyse` (prepare, identify unless
``model_path``, held-out check, training-window validation, frequency check, diagnosis unless
``gap_path``), with the same configuration and aircraft file as ``identify`` and ``diagnose``. Each
part that fails leaves a one-line reason in ``errors`` and the parts after it that need it say so: a
log the analysis cannot use still gets its data-quality section. :func:`assemble` makes the same object
from results computed elsewhere (the service's worker, a campaign job). Drawing is
:mod:`groundstation.report.render`'s."""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.analysis import STEPS, AnalysisError, analyse
from groundstation.campaign.store import CampaignStore
from groundstation.config import ServiceConfig
from groundstation.dsp.prepare import prepare
from groundstation.gap.pictures import gap_pictures
from groundstation.loginfo import summarise
from groundstation.parallel import Map, serial_map
from groundstation.pipeline import load_aircraft, load_logs, with_aircraft
from groundstation.report.data import FlightReportData, Timeline
from groundstation.sysid.validate import Validation, validate

#: ArduCopter (helicopter frame) flight modes by HEARTBEAT custom_mode
COPTER_MODES = {0: "STABILIZE", 1: "ACRO", 2: "ALT_HOLD", 3: "AUTO", 4: "GUIDED", 5: "LOITER", 6: "RTL",
                7: "CIRCLE", 9: "LAND", 11: "DRIFT", 13: "SPORT", 14: "FLIP", 15: "AUTOTUNE", 16: "POSHOLD",
                17: "BRAKE", 18: "THROW", 19: "AVOID_ADSB", 20: "GUIDED_NOGPS", 21: "SMART_RTL",
                22: "FLOWHOLD", 23: "FOLLOW", 24: "ZIGZAG", 25: "SYSTEMID", 26: "AUTOROTATE", 27: "AUTO_RTL"}

Progress = Callable[[str], None]


def _line(exc: BaseException) -> str:
    """One line naming what went wrong (ValueError/OSError texts already name file, key and value)."""
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return msg if isinstance(exc, ValueError | OSError) else f"{type(exc).__name__}: {msg}"


def timeline(log: Any) -> Timeline:
    """The flight timeline of one :class:`firmware_interface.samples.LogData`."""
    starts, ends = [], []
    for s in log.series.values():
        if len(s):
            t = s.t_fc_s[np.isfinite(s.t_fc_s)]
            if t.size:
                starts.append(float(t[0]))
                ends.append(float(t[-1]))
    span = (min(starts), max(ends)) if starts else (0.0, 0.0)
    armed = tuple((float(f.start_fc_s), float(f.end_fc_s)) for f in log.flights)
    air = tuple((float(a), float(b)) for f in log.flights for a, b in (getattr(f, "in_air_intervals_fc_s", ()) or ()))
    modes: list[tuple[float, str]] = []
    hb = log.series.get("HEARTBEAT")
    if hb is not None and len(hb) and "custom_mode" in hb.columns:
        cm = np.asarray(hb["custom_mode"], dtype=float)
        last = None
        for t, m in zip(hb.t_fc_s, cm, strict=True):
            if not np.isfinite(m) or m == last:
                continue
            last = m
            modes.append((float(t), COPTER_MODES.get(int(m), f"mode {int(m)}")))
    chirps = tuple((float(c.start_fc_s), float(c.duration_s), str(c.axis_name)) for c in getattr(log, "chirps", ()))
    th, h = np.zeros(0), np.zeros(0)
    lp = log.series.get("LOCAL_POSITION_NED")
    gp = log.series.get("GLOBAL_POSITION_INT")
    if lp is not None and len(lp) and np.isfinite(lp["z_m"]).any():
        th, h = np.asarray(lp.t_fc_s, float), -np.asarray(lp["z_m"], float)
    elif gp is not None and len(gp) and np.isfinite(gp["relative_alt_m"]).any():
        th, h = np.asarray(gp.t_fc_s, float), np.asarray(gp["relative_alt_m"], float)
    return Timeline(source=str(Path(log.source).name), span_s=span, armed_s=armed, in_air_s=air,
                    modes=tuple(modes), chirps=chirps, t_height_s=th, height_m=h)


def load_history(db: str | os.PathLike[str] | None, aircraft: str | None) -> tuple[tuple[dict[str, Any], ...], str]:
    """(the aircraft's error-free campaign rows oldest first, the aircraft's name) from a campaign table;
    ((), "") without one. With no aircraft name, the table's only aircraft."""
    if not db or not Path(db).exists():
        return (), ""

    store = CampaignStore(Path(db))
    try:
        names = store.aircraft()
        name = aircraft if aircraft in names else (names[0] if len(names) == 1 else None)
        if name is None:
            return (), ""
        return tuple(r for r in store.rows(name) if not r.get("error")), name
    finally:
        store.close()


def collect(logs: Sequence[str | os.PathLike[str]], *, config: Any = None, aircraft_path: Any = None,
            model_path: Any = None, gap_path: Any = None, folds: int = 5, history_db: Any = None,
            title: str | None = None, segments: str = "flights", pmap: Map = serial_map,
            progress: Progress | None = None) -> FlightReportData:
    """Analyse ``logs`` as far as they allow (see module docstring); never raises for bad data."""
    say = progress or (lambda _msg: None)
    cfg = config if config is not None else ServiceConfig()
    aircraft = load_aircraft(aircraft_path)   # a bad aircraft file is the user's error: raised
    cfg = with_aircraft(cfg, aircraft)
    names = tuple(str(p) for p in logs)
    errors: dict[str, str] = {}
    parts: dict[str, Any] = {
        "title": title or f"Flight report: {', '.join(Path(p).name for p in names)}", "logs": names,
        "aircraft": getattr(aircraft, "name", None), "input_source": cfg.prepare.input_source,
        "generated_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")}
    say("reading the logs")
    try:
        raw = load_logs(names, segments, pmap)
    except Exception as exc:  # the page still says what could not be read
        errors["logs"] = _line(exc)
        return FlightReportData(**parts, errors=errors)

    parts["log_info"] = tuple(summarise(log) for log in raw)
    parts["timelines"] = tuple(timeline(log) for log in raw)
    res = _analyse(raw, names, cfg, aircraft, model_path, gap_path is None, folds, errors, pmap, say)
    if res is None:   # not even prepared: the data-quality section is what the page has
        prepared = _prepare(raw, cfg, errors)
        parts["prepared"] = prepared
        parts["notes"] = tuple(prepared.notes) if prepared is not None else ()
        if model_path is None:
            errors.setdefault("model", f"not identified: {errors.get('prepare') or errors.get('analysis')}")
        errors.setdefault("freq", f"no frequency check: {errors.get('model') or errors.get('prepare')}")
        if gap_path is None:
            errors.setdefault("gap", f"no diagnosis: {errors.get('model') or errors.get('prepare')}")
        errors.pop("analysis", None)
    else:
        parts["prepared"], parts["model"], parts["freq"] = res.prepared, res.model, res.freq
        parts["notes"] = tuple(res.prepared.notes)
        if res.validation is not None:
            parts["validation"] = res.validation
        if res.gap is not None:
            parts["gap"] = res.gap.to_json()
            try:
                parts["pictures"] = gap_pictures(res.gap.diagnosis) if res.gap.diagnosis is not None else None
            except Exception as exc:  # the report stands without its pictures
                errors["pictures"] = _line(exc)
        for step, part in (("freq", "freq"), ("diagnose", "gap")):
            if res.errors.get(step):
                errors[part] = res.errors[step]
        if res.model is not None and res.freq is None and "freq" not in errors:
            errors["freq"] = "no frequency check"
    if gap_path is not None:
        parts["gap"], _ = _gap_file(gap_path)
    try:
        parts["history"], parts["history_label"] = load_history(history_db, parts["aircraft"])
    except Exception as exc:
        errors["history"] = _line(exc)
    return FlightReportData(**parts, errors=errors)


def assemble(logs: Sequence[str | os.PathLike[str]], cfg: Any, *, prepared: Any, model: Any,
             validation: Validation | None = None, freq: Any = None, gap: dict[str, Any] | None = None,
             pictures: Any = None, history: tuple[dict[str, Any], ...] = (), history_label: str = "",
             errors: dict[str, str | None] | None = None, title: str | None = None,
             aircraft: str | None = None) -> FlightReportData:
    """A :class:`FlightReportData` from results already computed elsewhere (the service's worker, a
    campaign job): reads the logs again for their data quality and timeline, validates the model on
    its training windows when ``validation`` is not given; nothing else is recomputed."""
    errs = {k: v for k, v in (errors or {}).items() if v}
    raw = load_logs(logs)
    if validation is None and model is not None and prepared is not None:
        try:
            validation = validate(model, prepared, return_series=True)
        except Exception as exc:
            errs["validation"] = _line(exc)
    names = tuple(str(p) for p in logs)
    return FlightReportData(
        title=title or f"Flight report: {', '.join(Path(p).name for p in names)}", logs=names, aircraft=aircraft,
        input_source=cfg.prepare.input_source, log_info=tuple(summarise(log) for log in raw),
        timelines=tuple(timeline(log) for log in raw), prepared=prepared, model=model, validation=validation,
        freq=freq, gap=gap, pictures=pictures, history=tuple(history), history_label=history_label, errors=errs,
        notes=tuple(prepared.notes) if prepared is not None else (),
        generated_utc=datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"))


def _prepare(raw: list[Any], cfg: Any, errors: dict[str, str]) -> Any:
    try:
        prepared = prepare(raw, cfg.prepare)
    except Exception as exc:
        errors["prepare"] = _line(exc)
        return None
    if not prepared.segments:
        errors["prepare"] = "no in-air data to analyse" + (f" ({'; '.join(prepared.notes)})" if prepared.notes else "")
        return None
    return prepared


def _analyse(raw: list[Any], names: tuple[str, ...], cfg: Any, aircraft: Any, model_path: Any, diagnose: bool,
             folds: int, errors: dict[str, str], pmap: Map, say: Progress) -> Any:
    """The :func:`groundstation.analysis.analyse` result of the logs (frequency check and diagnosis kept going
    on failure), or None with the reason in ``errors`` when there is nothing to analyse or the model fails."""

    steps = [s for s in STEPS if (s != "identify" or model_path is None) and (s != "diagnose" or diagnose)]
    cfg = dataclasses.replace(cfg, identification=dataclasses.replace(cfg.identification, heldout_folds=folds))

    def progress(ev: Any) -> None:
        if ev.state == "start":
            say({"identify": "identifying the model", "heldout": f"held-out check ({folds} folds)",
                 "validate": "measured vs model", "freq": "frequency-domain check",
                 "diagnose": "diagnosing the gap"}.get(ev.step, ev.step))

    say("analysing")
    try:
        return analyse(raw, aircraft, cfg, steps=steps, model=model_path, progress=progress, keep_going=True,
                       pmap=pmap)
    except AnalysisError as exc:
        errors["prepare"] = _line(exc)
    except (OSError, ValueError) as exc:
        if model_path is not None and str(model_path) in str(exc):
            raise   # a named model file that cannot be read is the user's error
        errors["model"] = f"not identified: {_line(exc)}"
    except Exception as exc:
        errors["model"] = f"not identified: {_line(exc)}"
    return None


def _gap_file(gap_path: Any) -> tuple[dict[str, Any], None]:
    p = Path(gap_path)
    if not p.exists():
        raise OSError(f"{p}: no such gap report")
    try:
        return json.loads(p.read_text()), None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: not a gap report (not JSON text: {exc})") from None
