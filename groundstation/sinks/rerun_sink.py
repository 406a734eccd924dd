"""Rerun (rerun-sdk 0.41) stream of one service run: live inputs/outputs, flights, model, gap, Bode.

One explicit :class:`rerun.RecordingStream` per run (never the global one). Timelines ``fc_time``
(duration, FC clock) and ``host_time`` (timestamp). The entity tree, units and the blueprint are in
:mod:`groundstation.sinks.rerun_layout`; the blueprint is sent again when a flight ends and when
its results arrive, so the recording opens on the whole latest flight.

Efficiency: live rows are buffered per stream (inputs, smoothed, raw) and sent with
``send_columns`` once ``flush_rows`` rows are waiting (Rerun's own chunk size), at flight ends and
at close; to a live viewer also every ``live_flush_s`` of wall time. Sparse logs (events, states)
go through the SDK batcher, whose tick is long when saving to a file. A saved session thus holds a
few chunks per entity, not one per window.

Modes: ``save PATH.rrd`` (file), ``spawn`` (start a local viewer), ``connect URL`` (a running
viewer's gRPC proxy, e.g. ``rerun+http://127.0.0.1:9876/proxy``). An unreachable viewer raises
:class:`RerunSinkError` with one line before anything is logged; the service then runs without Rerun.
Leaves what to log and when to :mod:`groundstation.service`; the worker computes the numbers.
"""

from __future__ import annotations

import datetime
import socket
import time
from collections.abc import Iterable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import numpy as np
import rerun as rr

from groundstation.errors import GroundstationError
from groundstation.freq.verify import freq_pairs
from groundstation.sinks.rerun_layout import (
    INPUT_MEANING,
    INPUTS,
    OUTPUTS,
    STATE_LANES,
    SYMBOL,
    UNITS,
    FlightViews,
    blueprint,
    views_to_json,
)
from groundstation.sinks.rerun_text import field_of as _get
from groundstation.sinks.rerun_text import fit_table, fit_text, verdict_text

__all__ = ["INPUTS", "OUTPUTS", "UNITS", "RerunSink", "RerunSinkError", "blueprint"]

_COLORS = {"raw": (170, 170, 170), "smoothed": (31, 119, 180), "model": (214, 39, 40),
           "residual": (44, 160, 44), "flagged": (255, 127, 14), "before": (150, 150, 150), "after": (44, 160, 44)}
_STATE_COLORS = {"on ground": 0x9E9E9EFF, "armed": 0xFFB300FF, "in air": 0x43A047FF}


class RerunSinkError(GroundstationError):
    """The Rerun target cannot be used (one line)."""


def _check_reachable(url: str) -> None:
    u = urlparse(url)
    host = u.hostname or "127.0.0.1"
    port = u.port or 9876
    try:
        with socket.create_connection((host, port), timeout=1.0):
            pass
    except OSError as exc:
        raise RerunSinkError(f"rerun viewer {url}: not reachable ({exc.strerror or exc})") from None


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in name).strip("_")


class RerunSink:
    """Log the live path, flights and results of one vehicle to one RecordingStream.

    Parameters
    ----------
    vehicle : entity root
    mode : ``save`` | ``spawn`` | ``connect``
    target : PATH.rrd for save, URL for connect
    recording_id : optional fixed recording id
    raw : also log the raw (unsmoothed) outputs
    aircraft : aircraft type for the recording's properties
    flush_rows : rows buffered per stream before they are sent as one chunk
    live_flush_s : wall-clock flush period to a live viewer (ignored when saving)
    """

    def __init__(self, vehicle: str, mode: str, target: str = "", *, recording_id: str | None = None,
                 raw: bool = False, aircraft: str = "", flush_rows: int = 4096, live_flush_s: float = 1.0) -> None:
        self.vehicle = vehicle
        self.root = f"/{vehicle}"
        self.mode = mode
        self.target = target
        self.raw = raw
        self.flush_rows = max(1, int(flush_rows))
        self.live_flush_s = None if mode == "save" else live_flush_s
        batcher = rr.ChunkBatcherConfig(flush_tick=datetime.timedelta(seconds=3600)) if mode == "save" else None
        self.stream = rr.RecordingStream("heli-groundstation", recording_id=recording_id, batcher_config=batcher)
        self.flights: dict[int, FlightViews] = {}
        self._open(blueprint(vehicle))
        self._buf: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
        self._buf_rows: dict[str, int] = {}
        self._last_flush = time.monotonic()
        self._state = ""
        self.has_excitation = False
        self._t_first, self._t_last = np.inf, -np.inf      # FC-time span of the rows seen
        self.rows = 0
        self._properties(aircraft)
        self._style()

    def _open(self, bp: Any) -> None:
        mode, target = self.mode, self.target
        if mode == "save":
            path = Path(target)
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                with open(path, "ab"):
                    pass
            except OSError as exc:
                raise RerunSinkError(f"{path}: cannot write .rrd ({exc.strerror or exc})") from None
            self.stream.save(str(path))      # the blueprint goes in once, at close, with every flight in it
        elif mode == "connect":
            url = target or "rerun+http://127.0.0.1:9876/proxy"
            _check_reachable(url)
            self.stream.connect_grpc(url, default_blueprint=bp)
        elif mode == "spawn":
            try:
                self.stream.spawn(default_blueprint=bp)
            except (RuntimeError, OSError) as exc:
                raise RerunSinkError(f"rerun spawn: {exc}") from None
        else:
            raise RerunSinkError(f"rerun mode {mode!r}: expected save, spawn or connect")

    def _properties(self, aircraft: str) -> None:
        started = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
        self.stream.send_recording_name(f"{self.vehicle} flight test {started}")
        self.stream.send_property("aircraft", rr.AnyValues(vehicle=self.vehicle, aircraft=aircraft or self.vehicle))

    def _style(self) -> None:
        s, v = self.stream, self.root
        for c in OUTPUTS:
            for kind in ("raw", "smoothed", "model", "residual"):
                name = {"raw": f"{SYMBOL[c]} measured (raw)", "smoothed": f"{SYMBOL[c]} measured (smoothed)",
                        "model": f"{SYMBOL[c]} model", "residual": f"{SYMBOL[c]} measured − model"}[kind]
                width = {"raw": 1.0, "smoothed": 1.2, "model": 2.4, "residual": 1.2}[kind]   # model under, wider
                s.log(f"{v}/outputs/{c}/{kind}", rr.SeriesLines(colors=[_COLORS[kind]], names=[name], widths=[width]),
                      static=True)
            s.log(f"{v}/gap/residual/{c}/residual", rr.SeriesLines(colors=[_COLORS["residual"]],
                                                                   names=[f"{SYMBOL[c]} held-out residual"]), static=True)
            s.log(f"{v}/gap/residual/{c}/flagged", rr.SeriesLines(colors=[_COLORS["flagged"]], widths=[2.0],
                                                                  names=["flagged window"]), static=True)
        for c in INPUTS:
            s.log(f"{v}/inputs/{c}", rr.SeriesLines(names=[f"{c} {INPUT_MEANING[c]}"]), static=True)
        s.log(f"{v}/flight/state", rr.StateConfiguration(values=list(STATE_LANES), labels=list(STATE_LANES),
                                                         colors=np.array([_STATE_COLORS[k] for k in STATE_LANES], dtype=np.uint32)), static=True)
        s.log(f"{v}/gap/flagged", rr.StateConfiguration(values=["flagged", "not flagged"], labels=["flagged", ""],
                                                        colors=np.array([0xFF7F0EFF, 0xFFFFFF00], dtype=np.uint32),
                                                        visible=[True, False]), static=True)

    # ------------------------------------------------------------------ live

    def log_rows(self, t_fc_s: np.ndarray, t_host_s: np.ndarray, inputs: np.ndarray | None = None,
                 outputs: np.ndarray | None = None, kind: str = "raw") -> None:
        """Buffer grid rows; sent in chunks of ``flush_rows`` (see module docstring).

        Parameters
        ----------
        t_fc_s : (n,) FC clock, s
        t_host_s : (n,) host time, Unix s (NaN entries interpolated; all NaN = no host_time index)
        inputs : (n, 4) lat lon col ped, normalised (1 = full travel from trim), or None
        outputs : (n, 8) u v w p q r theta phi, or None
        kind : ``raw`` | ``smoothed`` (which output sub-entity; raw outputs only when ``raw``)
        """
        n = len(t_fc_s)
        if n == 0:
            return
        t, th = np.asarray(t_fc_s, dtype=float), np.asarray(t_host_s, dtype=float)
        self._t_first, self._t_last = min(self._t_first, float(t[0])), max(self._t_last, float(t[-1]))
        if inputs is not None:
            self._add("inputs", t, th, 100.0 * np.asarray(inputs, dtype=float))
        if outputs is not None and (kind != "raw" or self.raw):
            self._add(kind, t, th, np.asarray(outputs, dtype=float))
        self.rows += n
        if self.live_flush_s is not None and time.monotonic() - self._last_flush >= self.live_flush_s:
            self.flush()

    def _add(self, kind: str, t: np.ndarray, th: np.ndarray, y: np.ndarray) -> None:
        self._buf.setdefault(kind, []).append((t, th, y))
        self._buf_rows[kind] = self._buf_rows.get(kind, 0) + len(t)
        if self._buf_rows[kind] >= self.flush_rows:
            self._flush_kind(kind)

    def flush(self) -> None:
        """Send every buffered row now."""
        for kind in list(self._buf):
            self._flush_kind(kind)
        self._last_flush = time.monotonic()

    def _flush_kind(self, kind: str) -> None:
        parts = self._buf.pop(kind, [])
        self._buf_rows[kind] = 0
        if not parts:
            return
        t = np.concatenate([p[0] for p in parts])
        th = np.concatenate([p[1] for p in parts])
        y = np.concatenate([p[2] for p in parts])
        paths = ([f"{self.root}/inputs/{c}" for c in INPUTS] if kind == "inputs"
                 else [f"{self.root}/outputs/{c}/{kind}" for c in OUTPUTS])
        self._send(paths, t, y, th)

    def _send(self, paths: Iterable[str], t_fc_s: np.ndarray, y: np.ndarray, t_host_s: np.ndarray | None = None) -> None:
        """One ``send_columns`` per column of ``y`` (n, k) onto ``paths`` (k)."""
        idx = [rr.TimeColumn("fc_time", duration=t_fc_s)]
        if t_host_s is not None:
            finite = np.isfinite(t_host_s)
            if finite.any():   # rows without any host time (model overlays) live on fc_time only
                th = t_host_s if finite.all() else np.interp(np.arange(len(t_host_s)), np.flatnonzero(finite),
                                                             t_host_s[finite])
                idx.append(rr.TimeColumn("host_time", timestamp=th))
        for i, path in enumerate(paths):
            self.stream.send_columns(path, indexes=idx, columns=rr.Scalars.columns(scalars=y[:, i]))

    def log_event(self, text: str, t_fc_s: float, level: str = "INFO") -> None:
        self.stream.set_time("fc_time", duration=float(t_fc_s))
        self.stream.log(f"{self.root}/events", rr.TextLog(text, level=level))

    def log_flight_state(self, state: str, t_fc_s: float) -> None:
        """``on ground`` | ``armed`` | ``in air`` from ``t_fc_s`` on (drawn as lanes)."""
        if state == self._state:
            return
        self._state = state
        self.stream.set_time("fc_time", duration=float(t_fc_s))
        self.stream.log(f"{self.root}/flight/state", rr.StateChange(state=state))

    def log_excitation(self, report: Any) -> None:
        """One verdict of the live excitation monitor (:class:`groundstation.dsp.excitation.ExcitationReport`)
        at its FC time: per axis the coherence against log10(f / Hz) (bars, green where the axis is enough;
        scrubbing ``fc_time`` shows it build up), the share of the axis's band covered by coherent data (%)
        and the status line."""
        e = f"{self.root}/excitation"
        if not self.has_excitation:
            for a in report.axes:
                self.stream.log(f"{e}/covered/{a}", rr.SeriesLines(names=[f"{a} band covered"]), static=True)
        self.stream.set_time("fc_time", duration=float(report.t_fc_s))
        for a, av in report.axes.items():
            f = np.asarray(av.f_hz, dtype=float)
            ok = f > 0
            x = np.log10(f[ok])
            df = float(np.median(np.diff(x))) if x.size > 1 else 0.05
            color = (44, 160, 44) if av.enough else (255, 127, 14)
            self.stream.log(f"{e}/{a}/coherence", rr.BarChart(np.nan_to_num(np.asarray(av.coherence, dtype=float)[ok]),
                                                              abscissa=x, widths=[df], color=color))
            self.stream.log(f"{e}/covered/{a}", rr.Scalars(100.0 * av.covered_fraction))
        self.stream.log(f"{e}/summary", rr.TextDocument(report.line().replace("; ", "\n\n")))
        if not self.has_excitation:
            self.has_excitation = True
            self._send_blueprint()

    # ------------------------------------------------------------------ flights

    def flight_ended(self, flight: int, t_start_s: float, t_end_s: float) -> None:
        """A flight's span is known: send what is buffered and open the recording on it."""
        self.flush()
        t_start_s, t_end_s = self._finite_span(flight, float(t_start_s), float(t_end_s))
        if not t_start_s < t_end_s:
            return                    # no FC time known for this flight: no view of its own
        old = self.flights.get(flight)
        fv = FlightViews(flight, t_start_s, t_end_s)
        self.flights[flight] = replace(old, t_start_s=fv.t_start_s, t_end_s=fv.t_end_s) if old else fv
        self.stream.send_property("flights", rr.AnyValues(
            numbers=sorted(self.flights), start_fc_s=[self.flights[k].t_start_s for k in sorted(self.flights)],
            end_fc_s=[self.flights[k].t_end_s for k in sorted(self.flights)]))
        self._send_blueprint()

    def _finite_span(self, flight: int, t_start_s: float, t_end_s: float) -> tuple[float, float]:
        """A flight armed before the FC clock was known has no start time (NaN): it starts where the
        previous flight ended, else at the first row seen; a missing end is the last row seen."""
        if not np.isfinite(t_start_s):
            ends = [f.t_end_s for k, f in self.flights.items() if k < flight]
            t_start_s = max(ends) if ends else self._t_first
        if not np.isfinite(t_end_s):
            t_end_s = self._t_last
        return t_start_s, t_end_s

    def _send_blueprint(self, final: bool = False) -> None:
        """To a live viewer at every change; into a file once, at close (a viewer opening a file keeps the
        first blueprint it finds there and shows no data under a later one)."""
        if self.mode == "save" and not final:
            return
        span = (self._t_first, self._t_last) if final and self._t_first <= self._t_last else None
        flights = list(self.flights.values())
        self.stream.send_property("views", rr.AnyValues(json=views_to_json(flights, span)))
        self.stream.send_blueprint(blueprint(self.vehicle, flights, span, excitation=self.has_excitation),
                                   make_active=True, make_default=True)

    def log_result(self, result: Any, overlay: Mapping[str, np.ndarray] | None = None, pictures: Any = None) -> None:
        """A worker result (mapping or dataclass): model overlay, residuals, fit, gap, Bode.

        ``overlay``: ``t_fc_s`` (n,), ``model`` (n, 8) and ``measured`` (n, 8) on the flight's FC clock;
        ``pictures``: a :class:`groundstation.gap.pictures.GapPictures` (else the result's ``gap_pictures``).
        """
        flight = int(_get(result, "flight", 0) or 0)
        if _get(result, "error"):
            t = self.flights[flight].t_end_s if flight in self.flights else 0.0
            self.log_event(f"flight {flight}: {_get(result, 'error')}", t, "ERROR")
            return
        fv = self.flights.get(flight) or self._span_from(flight, overlay)
        if overlay is not None and len(overlay.get("t_fc_s", ())):
            fv = replace(fv, has_model=self._log_overlay(overlay))
        fv = replace(fv, fit=fit_text(result))
        f = f"{self.root}/flights/{flight}"
        self.stream.log(f"{f}/fit", rr.TextDocument(fit_table(flight, result), media_type="text/markdown"),
                        static=True)
        gap = _get(result, "gap")
        if gap:
            self.stream.log(f"{f}/verdict", rr.TextDocument(verdict_text(flight, gap), media_type="text/markdown"),
                            static=True)
            fv = replace(fv, gap_channels=tuple(c for c in OUTPUTS if c in (gap.get("gap") or {}).get("channels", {})))
            self.log_event(f"flight {flight}: gap verdict {gap.get('verdict')}", fv.t_end_s,
                           "WARN" if gap.get("verdict") not in ("none", "") else "INFO")
        pictures = pictures if pictures is not None else _get(result, "gap_pictures")
        if pictures is not None:
            fv = replace(fv, effects=self.log_gap_pictures(flight, pictures))
        freq = _get(result, "freq_pairs") or freq_pairs(_get(result, "freq"))
        if freq:
            fv = replace(fv, bode_pairs=self.log_frequency_response(flight, freq))
        self.flights[flight] = fv
        self.flush()
        self._send_blueprint()

    def _span_from(self, flight: int, overlay: Mapping[str, np.ndarray] | None) -> FlightViews:
        t = np.asarray(overlay["t_fc_s"], dtype=float) if overlay is not None and len(overlay.get("t_fc_s", ())) else None
        return FlightViews(flight, float(t[0]) if t is not None else 0.0, float(t[-1]) if t is not None else 0.0)

    def _log_overlay(self, overlay: Mapping[str, np.ndarray]) -> bool:
        t = np.asarray(overlay["t_fc_s"], dtype=float)
        model = np.asarray(overlay["model"], dtype=float)
        self._send([f"{self.root}/outputs/{c}/model" for c in OUTPUTS], t, model)
        measured = overlay.get("measured")
        if measured is None:
            return False
        self._send([f"{self.root}/outputs/{c}/residual" for c in OUTPUTS], t, np.asarray(measured, dtype=float) - model)
        return True

    def log_model_overlay(self, t_fc_s: np.ndarray, outputs_model: np.ndarray) -> None:
        """Model-predicted outputs ``(n, 8)`` on the FC clock of the flight they were fitted to."""
        self._send([f"{self.root}/outputs/{c}/model" for c in OUTPUTS], np.asarray(t_fc_s, dtype=float),
                   np.asarray(outputs_model, dtype=float))

    # ------------------------------------------------------------------ gap and frequency responses

    def log_gap_pictures(self, flight: int, pic: Any) -> tuple[str, ...]:
        """Held-out residuals with flagged windows, spectra and before/after per effect; returns effect labels."""
        v, f = self.root, f"{self.root}/flights/{flight}"
        t, r = np.asarray(pic.t_s, dtype=float), np.asarray(pic.residual, dtype=float)
        flagged = np.zeros(len(t), bool)
        for a, b in pic.flagged_s:
            flagged |= (t >= a) & (t <= b)
        for c in pic.channels:
            k = OUTPUTS.index(c)
            self._send([f"{v}/gap/residual/{c}/residual"], t, r[:, k:k + 1])
            level = float(np.nanmax(np.abs(r[:, k]))) if len(t) else 0.0
            self._send([f"{v}/gap/residual/{c}/flagged"], t, np.where(flagged, level, 0.0)[:, None])
        edges = sorted([(a, "flagged") for a, _ in pic.flagged_s] + [(b, "not flagged") for _, b in pic.flagged_s])
        if len(t):
            edges = [(float(t[0]), "not flagged")] + edges
        if edges:
            self.stream.send_columns(f"{v}/gap/flagged", indexes=[rr.TimeColumn("fc_time", duration=[e[0] for e in edges])],
                                     columns=rr.StateChange.columns(state=[e[1] for e in edges]))
        self._log_spectra(f, pic)
        labels = []
        for ep in pic.effects:
            lab = _safe(ep.label + ("" if ep.significant else " not significant"))
            for c in ep.channels or pic.channels:
                k = OUTPUTS.index(c)
                for kind, y in (("before", ep.before_pct), ("after", ep.after_pct)):
                    path = f"{f}/effects/{lab}/{c}/{kind}"
                    self.stream.log(path, rr.SeriesLines(colors=[_COLORS[kind]], names=[
                        f"{SYMBOL[c]} {'base model' if kind == 'before' else 'with ' + ep.label}"
                        + (f" ({ep.share})" if kind == "after" and ep.share else "")]), static=True)
                    self._send([path], np.asarray(ep.t_s, dtype=float), np.asarray(y, dtype=float)[:, k:k + 1])
            labels.append(lab)
        return tuple(labels)

    def _log_spectra(self, f: str, pic: Any) -> None:
        fr = np.asarray(pic.f_hz, dtype=float)
        keep = fr > 0
        df = float(fr[1] - fr[0]) if len(fr) > 1 else 1.0
        for c in pic.channels:
            k = OUTPUTS.index(c)
            with np.errstate(divide="ignore", invalid="ignore"):
                db = 10.0 * np.log10(np.asarray(pic.psd)[keep, k] / np.asarray(pic.floor)[keep, k])
            db = np.nan_to_num(db, nan=0.0, posinf=0.0, neginf=0.0)
            self.stream.log(f"{f}/spectrum/{c}/psd", rr.BarChart(db, abscissa=fr[keep], widths=[df],
                                                                 color=_COLORS["smoothed"]), static=True)
            if pic.lines_hz:
                top = max(float(db.max()), 1.0)
                self.stream.log(f"{f}/spectrum/{c}/lines", rr.BarChart(np.full(len(pic.lines_hz), top),
                                                                       abscissa=np.array(pic.lines_hz), widths=[df],
                                                                       color=_COLORS["model"]), static=True)

    def log_frequency_response(self, flight: int, pairs: Iterable[Any]) -> tuple[str, ...]:
        """Bode magnitude/phase/coherence of data (and model) per input-output pair.

        Each pair (mapping or object) has ``input``, ``output``, ``f_hz`` (F,), ``data`` (F,) complex,
        optional ``model`` (F,) complex and ``coherence`` (F,). Returns the pair labels logged. The
        bars stand at ``log10(f / Hz)`` (a Bode plot's axis; Rerun's plots of a non-time axis are
        bar charts).
        """
        out = []
        for p in pairs:
            inp, outp = str(_get(p, "input")), str(_get(p, "output"))
            fr = np.asarray(_get(p, "f_hz"), dtype=float)
            if len(fr) == 0:
                continue
            pair = f"{inp}_{outp}"
            base = f"{self.root}/flights/{flight}/bode/{pair}"
            ok = fr > 0
            fr = np.log10(fr[ok])  # the composite frequencies are log-spaced: a Bode axis is log10(f / Hz)
            df = float(np.median(np.diff(fr))) if len(fr) > 1 else 0.1
            for who, h in (("data", _get(p, "data")), ("model", _get(p, "model"))):
                if h is None:
                    continue
                h = np.asarray(h, dtype=complex)[ok]
                color = _COLORS["smoothed" if who == "data" else "model"]
                with np.errstate(divide="ignore"):
                    mag = np.nan_to_num(20.0 * np.log10(np.abs(h)), neginf=-120.0)
                for kind, y in (("magnitude", mag), ("phase", np.degrees(np.unwrap(np.angle(h))))):
                    self.stream.log(f"{base}/{kind}/{who}", rr.BarChart(y, abscissa=fr, widths=[df / 2], color=color),
                                    static=True)
            coh = _get(p, "coherence")
            if coh is not None:
                self.stream.log(f"{base}/coherence/data", rr.BarChart(np.asarray(coh, dtype=float)[ok], abscissa=fr,
                                                                      widths=[df], color=(120, 120, 120)), static=True)
            out.append(pair)
        return tuple(out)

    def close(self) -> None:
        try:
            self.flush()
            if self.mode == "save":
                self._send_blueprint(final=True)
            self.stream.flush()
        finally:
            self.stream.disconnect()

