"""The offline analysis of flight logs, in one place: load -> prepare -> identify -> held-out check ->
validate -> frequency check -> diagnose.

:func:`analyse` is what ``groundstation identify``, ``diagnose``, the service's between-flight worker
and the campaign job call, and what a notebook calls::

    import groundstation as gs

    result = gs.analyse(["flight1.tlog"], aircraft="trex550.toml")
    result.model.to_json()          # the model file (docs/model-file.md)
    result.gap.to_json()            # the gap report (docs/gap-report.md)

It returns one frozen :class:`AnalysisResult`. Steps can be left out (``steps=("identify",)``); a
``progress`` callback hears each step start and end and every iteration of the search. The numbers are
:mod:`groundstation.dsp`'s, :mod:`groundstation.sysid`'s, :mod:`groundstation.freq`'s and
:mod:`groundstation.gap`'s; this module chains them and says where each setting comes from (the
:class:`groundstation.config.ServiceConfig`, with the aircraft file applied). Writing files, plots and
terminal output are the callers'.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import os
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from firmware_interface.readers import restrict_to_chirps
from groundstation.config import ServiceConfig, load_config
from groundstation.dsp.prepare import prepare
from groundstation.dsp.timeskew import skew_notes
from groundstation.errors import GroundstationError
from groundstation.freq.model_response import delays_from_augmentations
from groundstation.freq.spectra import estimate_responses
from groundstation.freq.verify import verify
from groundstation.gap.config import DiagnoseConfig
from groundstation.parallel import Map, serial_map
from groundstation.pipeline import (
    identify_prepared,
    load_aircraft,
    load_logs,
    load_model,
    prepare_native,
    with_aircraft,
)
from groundstation.sysid.fit_section import HeldOut, ModelFit
from groundstation.sysid.heldout import crossvalidate, feedback_evidence
from groundstation.sysid.identify import refit
from groundstation.sysid.model import INPUTS, OUTPUTS, theta_from_dict
from groundstation.sysid.structure_choice import fold_fitter
from groundstation.sysid.validate import Validation, validate

__all__ = ["STEPS", "AnalysisError", "AnalysisResult", "DataSummary", "GapReport", "Progress", "analyse",
           "analyse_prepared", "diagnose", "identify"]

#: the steps after loading and preparing, in the order they run
STEPS = ("identify", "heldout", "validate", "freq", "diagnose")


class AnalysisError(GroundstationError, ValueError):
    """Bad input to the analysis: an unknown step, a step that needs a model without one, no in-air data."""


@dataclass(frozen=True)
class Progress:
    """One progress event: ``step`` (``load``, ``prepare`` or one of :data:`STEPS`), ``state``
    (``start``, ``running``, ``done``, ``skipped``, ``failed``) and ``info`` (for the search's
    ``running`` events the optimiser's callback dict: ``stage``, ``nit``, ``maxiter``, ``fun``, ``nfev``)."""

    step: str
    state: str
    info: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DataSummary:
    """What the prepared data holds: in-air time, segments, channels, trims and data quality."""

    logs: tuple[str, ...]
    duration_s: float
    segments: int
    flights: tuple[int, ...]
    rate_hz: float
    outputs_measured: tuple[str, ...]
    inputs_active: tuple[str, ...]
    #: share (0..1) of the in-air grid samples with a finite value, per output and input channel
    finite_share: dict[str, float]
    input_trim_pwm: dict[str, float]
    output_trim: dict[str, float]
    pwm_per_unit: float
    notes: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> DataSummary:
        names = {f.name for f in dataclasses.fields(cls)}
        kw: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in doc.items() if k in names}
        return cls(**kw)


@dataclass(frozen=True)
class GapReport:
    """The gap report (``heli-gap-report/N``, docs/gap-report.md) and the arrays behind it (for plots)."""

    report: dict[str, Any]
    diagnosis: Any = field(default=None, repr=False, compare=False)   # groundstation.gap.diagnose.Diagnosis

    @property
    def verdict(self) -> str:
        return str(self.report["verdict"])

    def __repr__(self) -> str:
        effects = ", ".join(e["effect"] for e in self.report.get("effects", [])) or "none"
        return f"GapReport(verdict={self.verdict!r}, effects=[{effects}])"

    @property
    def arrays(self) -> dict[str, Any]:
        return self.diagnosis.arrays if self.diagnosis is not None else {}

    def to_json(self) -> dict[str, Any]:
        """The report document (a copy: changing it leaves this result as it is)."""
        return copy.deepcopy(self.report)

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> GapReport:
        if not str(doc.get("schema", "")).startswith("heli-gap-report/"):
            raise AnalysisError(f"not a gap report: schema {doc.get('schema')!r}")
        return cls(report=copy.deepcopy(doc))


@dataclass(frozen=True)
class AnalysisResult:
    """Everything one analysis produced; a step left out (or failed with ``keep_going``) is None.

    ``model`` is a :class:`groundstation.sysid.model.HoverModel` (its ``fit`` section holds the held-out
    verdict: ``heldout``, ``usable``, ``closed_loop``; :attr:`fit` reads it as a typed
    :class:`groundstation.sysid.fit_section.ModelFit`), ``validation`` the match per channel on the
    prepared data (a :class:`groundstation.sysid.validate.Validation`), ``freq`` the frequency-domain check (a :class:`groundstation.freq.verify.Verification`,
    ``to_json()`` gives ``heli-freq-verification/1``), ``gap`` the :class:`GapReport`. ``errors`` maps
    a step that failed to its one-line error (only with ``keep_going``), ``seconds`` each step to its
    wall time.
    """

    data: DataSummary
    model: Any = None
    validation: Validation | None = None
    freq: Any = None
    gap: GapReport | None = None
    steps: tuple[str, ...] = ()
    errors: dict[str, str] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    config: ServiceConfig = field(default_factory=ServiceConfig, repr=False, compare=False)
    aircraft: Any = field(default=None, repr=False, compare=False)
    prepared: Any = field(default=None, repr=False, compare=False)     # groundstation.dsp.prepare.PreparedData
    #: validate()'s windowed series (t_s, y, yhat), for plots (``validation.series``)
    validation_series: dict[str, Any] | None = field(default=None, repr=False, compare=False)

    def __repr__(self) -> str:
        parts = [f"{self.data.duration_s:g} s in air in {self.data.segments} segments"]
        if self.model is not None:
            ho = self.heldout
            parts.append(f"model (usable={self.usable}, held-out mean match {ho.mean_match:.1f} %)"
                         if ho is not None and ho.mean_match is not None else f"model (usable={self.usable})")
        if self.validation is not None:
            parts.append(f"validation mean match {self.validation.mean_match:.1f} %")
        if self.freq is not None:
            ja = self.freq.J_avg
            parts.append("frequency check J_avg " + ("-" if ja is None else f"{ja:.0f}"))
        if self.gap is not None:
            parts.append(f"gap verdict {self.gap.verdict!r}")
        if self.errors:
            parts.append(f"errors in {sorted(self.errors)}")
        return f"AnalysisResult({'; '.join(parts)})"

    @property
    def fit(self) -> ModelFit | None:
        """The model's ``fit`` section; None without a model."""
        return None if self.model is None else self.model.fit

    @property
    def heldout(self) -> HeldOut | None:
        """The held-out verdict (the fit section's ``heldout``), None when not checked."""
        fit = self.fit
        return None if fit is None else fit.heldout

    @property
    def usable(self) -> bool | None:
        """False when a subsystem's held-out prediction runs away, None when not checked."""
        fit = self.fit
        return None if fit is None else fit.usable

    def to_json(self) -> dict[str, Any]:
        """One JSON document of the whole analysis (model, validation, frequency check, gap report)."""
        return {"schema": "heli-analysis/1", "steps": list(self.steps), "data": self.data.to_json(),
                "model": None if self.model is None else self.model.to_json(),
                "validation": None if self.validation is None else self.validation.to_json(),
                "freq": None if self.freq is None else self.freq.to_json(),
                "gap": None if self.gap is None else self.gap.to_json(), "errors": dict(self.errors),
                "seconds": dict(self.seconds)}


def _steps(steps: Iterable[str]) -> tuple[str, ...]:
    want = set(steps)
    unknown = sorted(want - set(STEPS))
    if unknown:
        raise AnalysisError(f"steps: unknown {unknown}; the steps are {list(STEPS)}")
    return tuple(s for s in STEPS if s in want)


def _is_path(x: Any) -> bool:
    return isinstance(x, (str, os.PathLike))


def analyse(logs: Any, aircraft: Any = None, config: ServiceConfig | str | os.PathLike[str] | None = None, *,
            steps: Iterable[str] = STEPS, model: Any = None, segments: str = "flights",
            progress: Callable[[Progress], Any] | None = None, keep_going: bool = False,
            pmap: Map = serial_map, responses: Any = None) -> AnalysisResult:
    """Analyse flight logs: prepare, identify, check on held-out data, validate, check in frequency, diagnose.

    Parameters
    ----------
    logs : a log path, a list of paths (.tlog/.bin/.px4log/.ulg, also .xz/.gz), or logs already read
        (:func:`groundstation.load_log`)
    aircraft : the aircraft file (path or :class:`groundstation.Aircraft`); None: the configuration's
        ``[identification] aircraft`` if set, else none
    config : a :class:`groundstation.config.ServiceConfig`, a TOML path, or None for the defaults
    steps : which of :data:`STEPS` to run (in that order whatever the order given). Without
        ``identify`` the other steps use ``model`` (a HoverModel or a model file path); without a model
        the diagnosis identifies its own base model
    segments : ``flights`` (every in-air interval) or ``sysid`` (only ArduPilot SYSID chirps)
    progress : called with a :class:`Progress` at each step's start and end, and per search iteration
    keep_going : a failed ``freq`` or ``diagnose`` step is recorded in ``errors`` instead of raised
    pmap : map over worker processes (:func:`groundstation.parallel.worker_map`); results do not depend on it
    responses : the flight's frequency responses already estimated (a
        :class:`groundstation.freq.spectra.ResponseSet`: the live service's spectra accumulated during
        the flight); the frequency check then makes no second pass over the data
    """
    steps = _steps(steps)
    cfg = _config(config)
    ac = load_aircraft(aircraft) if _is_path(aircraft) else aircraft
    if ac is None and cfg.identification.aircraft:
        ac = load_aircraft(cfg.identification.aircraft)
    cfg = with_aircraft(cfg, ac)
    items = [logs] if _is_path(logs) else list(logs)
    paths = tuple(str(x) if _is_path(x) else str(getattr(x, "source", "<log>")) for x in items)
    note = _notifier(progress)
    t0 = time.perf_counter()
    note("load", "start")
    if all(_is_path(x) for x in items):
        read = load_logs(items, segments, pmap)
    else:
        read = [load_logs([x], segments, pmap)[0] if _is_path(x) else x for x in items]
        if segments == "sysid":
            read = [restrict_to_chirps(x) for x in read]
    note("load", "done")

    note("prepare", "start")
    prepared = prepare(read, cfg.prepare)
    note("prepare", "done")
    res = analyse_prepared(prepared, cfg, ac, steps=steps, model=model, logs=read, log_paths=paths,
                           progress=progress, keep_going=keep_going, pmap=pmap, responses=responses)
    return dataclasses.replace(res, seconds={"load_prepare": round(_since(t0) - sum(res.seconds.values()), 3),
                                             **res.seconds})


def analyse_prepared(prepared: Any, config: ServiceConfig | None = None, aircraft: Any = None, *,
                     steps: Iterable[str] = STEPS, model: Any = None, logs: Sequence[Any] = (),
                     log_paths: Sequence[str] = (), progress: Callable[[Progress], Any] | None = None,
                     keep_going: bool = False, pmap: Map = serial_map, responses: Any = None) -> AnalysisResult:
    """:func:`analyse` from data already prepared (with ``config.prepare``, the aircraft applied).

    ``logs`` (the logs read) serve the frequency check at the log's native rate and the native-rate
    vibration lines of the diagnosis; without them the frequency check runs on the prepared grid."""
    cfg = with_aircraft(config if config is not None else ServiceConfig(), aircraft)
    run = _steps(steps)
    note = _notifier(progress)
    seconds: dict[str, float] = {}
    errors: dict[str, str] = {}
    model_source = None
    if _is_path(model):
        model_source = str(model)
        model = load_model(Path(model))
    if not prepared.segments and ("identify" in run or "diagnose" in run or model is not None):
        raise AnalysisError(f"nothing to identify ({'; '.join(prepared.notes) or 'no in-air data'})")

    def step(name: str, fn: Callable[[], Any], tolerate: tuple[type[BaseException], ...] = ()) -> Any:
        if name not in run:
            return None
        note(name, "start")
        t = time.perf_counter()
        try:
            out = fn()
        except Exception as exc:
            seconds[name] = round(_since(t), 3)
            note(name, "failed", {"error": _one_line(exc)})
            if isinstance(exc, tolerate) or (keep_going and name in ("freq", "diagnose")):
                errors[name] = _one_line(exc)
                return None
            raise
        seconds[name] = round(_since(t), 3)
        note(name, "done")
        return out

    if "identify" in run:
        def _identify() -> Any:
            t = time.perf_counter()
            m = identify_prepared(prepared, cfg, aircraft=aircraft, pmap=pmap,
                                  callback=lambda info: note("identify", "running", info) and False)
            m.fit = m.fit.set(seconds=round(_since(t), 3))
            m.source["logs"] = list(log_paths)
            return m

        model = step("identify", _identify)
    needs_model = [s for s in ("heldout", "validate") if s in run]
    if model is None and needs_model:
        raise AnalysisError(f"steps {needs_model} need a model: add 'identify' to the steps or give model=")
    folds = cfg.identification.heldout_folds
    if folds >= 2:
        step("heldout", lambda: held_out(model, prepared, cfg, aircraft, folds, pmap))
    elif "heldout" in run:
        note("heldout", "skipped", {"why": f"identification.heldout_folds = {folds}"})
    validation = series = None
    if "validate" in run:
        validation = step("validate", lambda: validate(model, prepared, return_series=True))
        series = None if validation is None else validation.series
    cache: dict[str, Any] = {} if responses is None else {"responses": responses}
    # a flight too short or too quiet for a frequency analysis is an answer (errors["freq"]), not a failure
    freq = step("freq", lambda: _freq_check(model, prepared, logs, cfg, cache), (ValueError,))
    gap = step("diagnose", lambda: _diagnose(model, prepared, logs, log_paths, model_source, cfg, cache,
                                             "freq" in run, pmap))
    return AnalysisResult(data=summarize(prepared, log_paths), model=model, validation=validation, freq=freq,
                          gap=gap, steps=run, errors=errors, seconds=seconds, config=cfg, aircraft=aircraft,
                          prepared=prepared, validation_series=series)


def identify(logs: Any, aircraft: Any = None, config: ServiceConfig | str | os.PathLike[str] | None = None, *,
             heldout: bool = True, segments: str = "flights", progress: Callable[[Progress], Any] | None = None,
             pmap: Map = serial_map) -> Any:
    """The hover model of the logs (a :class:`groundstation.HoverModel`), as ``groundstation identify``
    writes it: with ``heldout`` its ``fit`` carries the held-out verdict (``heldout``, ``usable``,
    ``closed_loop``). Arguments as :func:`analyse`."""
    steps = ("identify", "heldout") if heldout else ("identify",)
    return analyse(logs, aircraft, config, steps=steps, segments=segments, progress=progress, pmap=pmap).model


def diagnose(logs: Any, model: Any = None, aircraft: Any = None,
             config: ServiceConfig | str | os.PathLike[str] | None = None, *, segments: str = "flights",
             progress: Callable[[Progress], Any] | None = None, pmap: Map = serial_map) -> GapReport:
    """The gap report of ``model`` (a HoverModel or a model file; None: the diagnosis identifies its own
    base model) on the logs, as ``groundstation diagnose`` writes it (frequency section included)."""
    return analyse(logs, aircraft, config, steps=("freq", "diagnose"), model=model, segments=segments,
                   progress=progress, pmap=pmap).gap  # type: ignore[return-value]


def summarize(prepared: Any, log_paths: Sequence[str] = ()) -> DataSummary:
    """The :class:`DataSummary` of prepared data."""
    share: dict[str, float] = {}
    if prepared.segments:
        out = np.concatenate([s.outputs for s in prepared.segments])
        inp = np.concatenate([s.inputs for s in prepared.segments])
        for j, n in enumerate(OUTPUTS):
            share[n] = round(float(np.isfinite(out[:, j]).mean()), 4)
        for j, n in enumerate(INPUTS):
            share[n] = round(float(np.isfinite(inp[:, j]).mean()), 4)
    avail = prepared.available
    active = prepared.input_active
    return DataSummary(
        logs=tuple(log_paths), duration_s=round(float(prepared.duration_s), 3), segments=len(prepared.segments),
        flights=tuple(sorted({int(s.flight) for s in prepared.segments})), rate_hz=round(1.0 / prepared.dt_s, 6),
        outputs_measured=tuple(n for n, a in zip(OUTPUTS, avail, strict=True) if a),
        inputs_active=tuple(n for n, a in zip(INPUTS, active, strict=True) if a), finite_share=share,
        input_trim_pwm={k: float(v) for k, v in prepared.input_trim_pwm.items()},
        output_trim={k: float(v) for k, v in prepared.output_trim.items()},
        pwm_per_unit=float(prepared.pwm_per_unit), notes=tuple(prepared.notes))


def held_out(model: Any, prepared: Any, cfg: ServiceConfig, aircraft: Any, k: int,
             pmap: Map | None = None) -> HeldOut:
    """Cross-validate ``model`` (refinement from its parameters on k-1 contiguous blocks, prediction of
    the k-th) and record the verdicts in ``model.fit``: ``heldout`` (per channel and fold), ``usable``
    (False when a subsystem's prediction runs away in some fold) and ``closed_loop`` (what the closed
    loop means for this model). Returns ``model.fit.heldout``."""
    prior = aircraft.prior if aircraft is not None else None
    done = model.fit.heldout or HeldOut()
    if done.k != k:   # not already checked by the configuration's held-out selection
        try:
            chosen = dict(model.fit.selection.overrides) if model.fit.selection is not None else {}
            icfg = dataclasses.replace(cfg.identify, **chosen)
            fit_fold = functools.partial(refit, model=model, config=icfg, prior=prior)
            if getattr(model, "structure", "hover") == "command_response":   # the stabilised aircraft's structure

                fit_fold = fold_fitter(model, icfg)
            cv = crossvalidate(prepared, fit_fold, k=k, window_s=icfg.heldout_window_s,
                               runaway_factor=icfg.runaway_factor, pmap=serial_map if pmap is None else pmap)
        except ValueError as exc:
            model.fit = model.fit.set(heldout=HeldOut.make(skipped=str(exc)))
            return model.fit.heldout
        done = HeldOut.from_json(cv.to_json())
    model.fit = model.fit.set(heldout=done, unusable_subsystems=done.unusable_subsystems,
                              usable=not done.unusable_subsystems)
    model.fit = model.fit.set(closed_loop=closed_loop_notes(model, prepared, cfg))
    return done


def closed_loop_notes(model: Any, prepared: Any, cfg: ServiceConfig) -> list[str]:
    """What the closed loop means for this model: inputs that follow the output error, inputs logged late
    (the response leads them on sharp steps), stick inputs."""
    ic = cfg.identify
    notes = feedback_evidence(model, prepared, window_s=ic.feedback_window_s, max_lag_s=ic.feedback_max_lag_s,
                              z=ic.feedback_z)
    if notes:
        notes.append("with the loop closed the inputs correlate with the disturbances the model does not see: "
                     "output error stays consistent only where the feedback acts on measured outputs; expect damping "
                     "and input gains biased towards what the controller makes of them, and judge the model by "
                     "the held-out match, not by its standard errors")
    notes += skew_notes(prepared, cfg.prepare.input_shift_s)
    if cfg.prepare.input_source == "RC_CHANNELS":
        notes.append("the inputs are the pilot's sticks (RC), commands to a stabilised aircraft: the model is that "
                     "of the aircraft with its stabiliser, not of the bare rotor (rotor terms such as M_a, L_b and "
                     "1/tau_s describe the closed loop)")
    return notes


def _responses(prepared: Any, logs: Sequence[Any], cfg: ServiceConfig, cache: dict[str, Any]) -> Any:
    """The flight's frequency responses at the log's native rate (computed once per analysis)."""
    if "responses" not in cache:
        native = prepare_native(list(logs), cfg.prepare) if logs else prepared
        cache["responses"] = estimate_responses(native, cfg.freq)
    return cache["responses"]


def _freq_check(model: Any, prepared: Any, logs: Sequence[Any], cfg: ServiceConfig, cache: dict[str, Any]) -> Any:
    """The model checked against the flight's frequency responses (None without a model: the
    responses are then estimated for the gap report's frequency section only)."""
    try:
        responses = _responses(prepared, logs, cfg, cache)
    except ValueError as exc:
        cache["error"] = str(exc)
        raise
    if model is None:
        return None
    return verify(model.theta, responses, delays_from_augmentations(model.augmentations))


def _diagnose(model: Any, prepared: Any, logs: Sequence[Any], log_paths: Sequence[str], model_source: str | None,
              cfg: ServiceConfig, cache: dict[str, Any], with_freq: bool, pmap: Map) -> GapReport:
    # here, not at the top: the diagnosis brings scipy.stats (about 0.9 s of CPU), which identify never needs
    from groundstation.gap.diagnose import run_diagnosis

    diag = run_diagnosis(model, prepared, seed=cfg.identification.seed, config=cfg.diagnose, pmap=pmap)
    report = diag.report
    native = native_vibration(list(logs), cfg.prepare.rate_hz, cfg.diagnose)
    if native is not None:
        unfold_rotor_line(report, native, cfg.prepare.rate_hz)
    report["source"] = {"logs": list(log_paths), "model": model_source}
    if with_freq:
        report["frequency"] = frequency_section(model, report, prepared, logs, cfg, cache)
    return GapReport(report=report, diagnosis=diag)


def frequency_section(model: Any, report: dict, prepared: Any, logs: Sequence[Any], cfg: ServiceConfig,
                      cache: dict[str, Any]) -> dict:
    """The gap report's frequency section: the diagnosis's base model checked against the flight's
    frequency responses (at the log's native rate), or ``{"error": ...}`` when the analysis cannot run."""
    from groundstation.gap.report import frequency_section as section  # the diagnosis's, as in _diagnose

    if "error" in cache and "responses" not in cache:
        return {"error": cache["error"]}
    try:
        theta = theta_from_dict(report["method"]["base_parameters"])
        v = verify(theta, _responses(prepared, logs, cfg, cache),
                   delays_from_augmentations(model.augmentations) if model is not None else None)
    except ValueError as exc:
        return {"error": str(exc)}
    return section(v)


def native_vibration(logs: list, grid_rate_hz: float, cfg: Any = None) -> dict | None:
    """Vibration lines in the logs' own high-rate gyro (dataflash IMU/GYR faster than twice the grid),
    over the armed flights; None when no log has one. Adds the logged rotor speed when there is one.
    ``cfg``: the :class:`groundstation.gap.config.DiagnoseConfig` (``native_line_*``; None: defaults)."""
    from groundstation.gap.fingerprints import native_rate_lines  # the diagnosis's, as in _diagnose

    cfg = cfg if cfg is not None else DiagnoseConfig()

    for log in logs:
        for name in ("GYRO_FAST", "IMU"):
            s = log.series.get(name)
            if s is None or len(s) < 100:
                continue
            dt = float(np.median(np.diff(s.t_fc_s)))
            if not 0 < dt < 1.0 / (2.0 * grid_rate_hz):
                continue
            sel = np.zeros(len(s), bool)
            for fl in log.flights:
                sel |= (s.t_fc_s >= fl.start_fc_s) & (s.t_fc_s <= fl.end_fc_s)
            g = np.stack([s["gx_rad_s"], s["gy_rad_s"], s["gz_rad_s"]], axis=1)[sel]
            lines = native_rate_lines(g[np.isfinite(g).all(axis=1)], dt, window_s=cfg.native_line_window_s,
                                      min_hz=cfg.native_line_min_hz, alpha=cfg.native_line_alpha)
            rotor = log.series.get("ROTOR")
            rpm = None
            if rotor is not None and len(rotor):
                r = rotor["rotor_speed_rpm"][np.isfinite(rotor["rotor_speed_rpm"])]
                spinning = r[r > 0.8 * r.max()] if r.size and r.max() > 0 else r[:0]
                rpm = float(np.median(spinning)) if spinning.size else None
            return {"source": f"{name} at {1 / dt:.0f} Hz in {log.source}",
                    "lines": [{"frequency_hz": round(ln.frequency_hz, 3), "channels": ln.channels,
                               "log10_p": round(ln.log10_p, 1), "amplitude_rad_s": ln.amplitude} for ln in lines],
                    "rotor_speed_hz": None if rpm is None else round(rpm / 60.0, 3)}
    return None


def unfold_rotor_line(report: dict, native: dict, grid_rate_hz: float) -> None:
    """Put the native lines in the report; a rotor_vibration effect found on the grid gets the true
    frequency of the native line that folds onto its own (its grid frequency is kept beside it)."""
    report["vibration_native"] = native
    for eff in report.get("effects", []):
        if eff.get("effect") != "rotor_vibration":
            continue
        f_grid = float(eff["estimate"].get("frequency_hz", float("nan")))
        for ln in native["lines"]:
            f = ln["frequency_hz"] % grid_rate_hz
            if abs(min(f, grid_rate_hz - f) - f_grid) < 0.3:
                eff["estimate"]["frequency_hz_on_grid"] = f_grid
                eff["estimate"]["frequency_hz"] = ln["frequency_hz"]
                eff["evidence"] = (eff.get("evidence", "") + f"; at {ln['frequency_hz']:.2f} Hz in the "
                                   f"autopilot's own log ({native['source'].split(' in ')[0]})")
                break


def _config(config: Any) -> ServiceConfig:
    if config is None:
        return ServiceConfig()
    if isinstance(config, ServiceConfig):
        return config

    return load_config(config)


def _notifier(progress: Callable[[Progress], Any] | None) -> Callable[..., bool]:
    def note(step: str, state: str, info: dict[str, Any] | None = None) -> bool:
        if progress is not None:
            progress(Progress(step, state, dict(info or {})))
        return False
    return note


def _one_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".splitlines()[0]


def _since(t: float) -> float:
    return time.perf_counter() - t
