"""Names, units and the Rerun blueprint of a ground-station recording (what the engineer sees first).

Entity tree under ``/{vehicle}`` (every scalar on the ``fc_time`` timeline, flight-controller seconds)::

    inputs/{lat,lon,col,ped}                 stick inputs, % of travel from trim
    outputs/{u..phi}/{smoothed,model,raw}    measured (smoothed), identified model, raw on request
    outputs/{u..phi}/residual                measured (smoothed) - model
    flight/state                             on ground | armed | in air (state lanes)
    events                                   link, arming and identification messages
    gap/residual/{u..phi}                    held-out residual of the diagnosis, flagged-window marks
    gap/flagged                              flagged windows (state lanes)
    flights/{n}/fit                          fit table of flight n (text)
    flights/{n}/verdict                      what the diagnosis found, how sure, what to do next (text)
    flights/{n}/spectrum/{u..phi}/{psd,floor,lines}     residual spectrum in dB, frequency in Hz
    flights/{n}/effects/{label}/{u..phi}/{before,after} held-out NRMSE per window with/without an effect
    flights/{n}/bode/{input}_{output}/{magnitude,phase,coherence}/{data,model}   at log10(f / Hz)
    excitation/{lat,lon,col,ped}/coherence   live excitation monitor: coherence vs log10(f / Hz), on fc_time
    excitation/covered/{lat,lon,col,ped}     % of each axis's band covered by coherent data (time series)
    excitation/summary                       the monitor's status line (text)

:func:`blueprint` lays these out as one tab per flight (latest first, opened on the whole flight:
every plot of the tab shows the flight's FC-time span, not a window at t = 0) plus a session tab.
Units are in every view name. Leaves the logging to :mod:`groundstation.sinks.rerun_sink`.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import rerun.blueprint as rrb

INPUTS = ("lat", "lon", "col", "ped")
OUTPUTS = ("u", "v", "w", "p", "q", "r", "theta", "phi")
UNITS = {"u": "m/s", "v": "m/s", "w": "m/s", "p": "rad/s", "q": "rad/s", "r": "rad/s", "theta": "rad", "phi": "rad"}
SYMBOL = {"u": "u", "v": "v", "w": "w", "p": "p", "q": "q", "r": "r", "theta": "θ", "phi": "φ"}
MEANING = {"u": "forward speed", "v": "lateral speed", "w": "vertical speed", "p": "roll rate",
           "q": "pitch rate", "r": "yaw rate", "theta": "pitch angle", "phi": "roll angle"}
INPUT_MEANING = {"lat": "lateral cyclic", "lon": "longitudinal cyclic", "col": "collective", "ped": "pedals"}
INPUT_UNIT = "% travel"
STATE_LANES = ("on ground", "armed", "in air")


def label(c: str) -> str:
    """``θ pitch angle [rad]``: symbol, meaning and unit of output channel ``c``."""
    return f"{SYMBOL[c]} {MEANING[c]} [{UNITS[c]}]"


@dataclass(frozen=True)
class FlightViews:
    """What the recording holds for one flight (the blueprint shows only what exists)."""

    flight: int
    t_start_s: float
    t_end_s: float
    fit: dict[str, str] = field(default_factory=dict)      # channel -> "fit 91% · held-out 88%"
    has_model: bool = False
    gap_channels: tuple[str, ...] = ()
    effects: tuple[str, ...] = ()                          # entity-safe effect labels
    bode_pairs: tuple[str, ...] = ()                       # "lon_q", ...


def views_to_json(flights: Sequence[FlightViews], session: tuple[float, float] | None = None) -> str:
    """What the blueprint was built from, for the recording's properties (rebuilt by :func:`views_from_json`)."""
    return json.dumps({"flights": [asdict(fv) for fv in flights], "session": list(session) if session else None})


def views_from_json(text: str) -> tuple[list[FlightViews], tuple[float, float] | None]:
    doc = json.loads(text)
    fields: list[dict[str, Any]] = [{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
                                    for d in doc["flights"]]
    flights = [FlightViews(**d) for d in fields]
    return flights, (tuple(doc["session"]) if doc.get("session") else None)  # type: ignore[return-value]


def _span(fv: FlightViews | None, pad_s: float = 2.0) -> tuple[rrb.VisibleTimeRange | None, rrb.TimeAxis | None]:
    """The flight's FC-time span (padded) as the data range and the x-axis range of a view."""
    if fv is None:
        return None, None
    start = rrb.TimeRangeBoundary.absolute(seconds=fv.t_start_s - pad_s)
    end = rrb.TimeRangeBoundary.absolute(seconds=fv.t_end_s + pad_s)
    return (rrb.VisibleTimeRange("fc_time", start=start, end=end),
            rrb.TimeAxis(view_range=rrb.TimeRange(start=start, end=end)))


def _plot(origin: str, name: str, fv: FlightViews | None, contents: Sequence[str] | None = None) -> rrb.TimeSeriesView:
    rng, axis = _span(fv)
    return rrb.TimeSeriesView(origin=origin, contents=list(contents) if contents else "$origin/**", name=name,
                              plot_legend=rrb.PlotLegend(rrb.Corner2D.LeftTop), time_ranges=rng, axis_x=axis)


def _lanes(v: str, fv: FlightViews | None, gap: bool) -> rrb.StateTimelineView:
    rng, axis = _span(fv)
    contents = [f"{v}/flight/state"] + ([f"{v}/gap/flagged"] if gap else [])
    return rrb.StateTimelineView(origin=v, contents=contents, name="flight state" + (" · flagged windows" if gap else ""),
                                 time_ranges=rng, time_view=axis)


def _inputs(v: str, fv: FlightViews | None) -> rrb.TimeSeriesView:
    return _plot(f"{v}/inputs", f"stick inputs [{INPUT_UNIT} from trim]", fv)


def _channel(v: str, c: str, fv: FlightViews | None) -> rrb.Container | rrb.View:
    fit = f" · {fv.fit[c]}" if fv is not None and c in fv.fit else ""
    main = _plot(f"{v}/outputs/{c}", f"{label(c)}{fit}", fv,
                 contents=[f"$origin/{k}" for k in ("raw", "smoothed", "model")])
    if fv is None or not fv.has_model:
        return main
    resid = _plot(f"{v}/outputs/{c}/residual", f"{SYMBOL[c]} residual, measured − model [{UNITS[c]}]", fv)
    return rrb.Vertical(main, resid, row_shares=[2, 1])


def _model_tab(v: str, fv: FlightViews) -> rrb.Container:
    top = rrb.Horizontal(_lanes(v, fv, bool(fv.gap_channels)), _inputs(v, fv),
                         rrb.TextDocumentView(origin=f"{v}/flights/{fv.flight}/fit", name="fit per channel"),
                         column_shares=[1, 2, 1])
    grid = rrb.Grid(*[_channel(v, c, fv) for c in OUTPUTS], grid_columns=4)
    return rrb.Vertical(top, grid, row_shares=[1, 4], name="model vs measured")


def _gap_tab(v: str, fv: FlightViews) -> rrb.Container:
    f = f"{v}/flights/{fv.flight}"
    top = rrb.Horizontal(rrb.TextDocumentView(origin=f"{f}/verdict", name="verdict: what, how sure, what next"),
                         _lanes(v, fv, True), column_shares=[2, 1])
    cols = min(4, max(1, len(fv.gap_channels)))
    resid = rrb.Grid(*[_plot(f"{v}/gap/residual/{c}", f"{SYMBOL[c]} held-out residual [{UNITS[c]}]", fv)
                       for c in fv.gap_channels], grid_columns=cols, name="held-out residuals")
    spec = rrb.Grid(*[rrb.BarChartView(origin=f"{f}/spectrum/{c}", name=f"{SYMBOL[c]} residual [dB over noise] vs [Hz]",
                                       plot_legend=rrb.PlotLegend(visible=False))
                      for c in fv.gap_channels], grid_columns=cols, name="residual spectra")
    parts: list[rrb.Container | rrb.View] = [top, resid, spec]
    if fv.effects:
        parts.append(rrb.Grid(*[_plot(f"{f}/effects/{e}", f"{e.replace('_', ' ')}: held-out NRMSE per window, "
                                      "before / after [%]", fv) for e in fv.effects], name="before / after"))
    return rrb.Vertical(*parts, name="gap")


def _bode_tab(v: str, fv: FlightViews) -> rrb.Container:
    f = f"{v}/flights/{fv.flight}/bode"
    cols = []
    for pair in fv.bode_pairs:
        inp, out = pair.split("_", 1)
        cols.append(rrb.Vertical(*[rrb.BarChartView(origin=f"{f}/{pair}/{k}", name=f"{SYMBOL.get(out, out)}/{inp} {k} {u}",
                                                    plot_legend=rrb.PlotLegend(visible=False))
                                   for k, u in (("magnitude", "[dB] vs log10 f [Hz] · blue flight, red model"),
                                                ("phase", "[deg] vs log10 f [Hz]"),
                                                ("coherence", "[0-1] vs log10 f [Hz]"))]))
    return rrb.Grid(*cols, name="frequency responses")


def _flight_tab(v: str, fv: FlightViews, opening: str = "") -> rrb.Container:
    tabs: list[rrb.Container] = [_model_tab(v, fv)]
    if fv.gap_channels:
        tabs.append(_gap_tab(v, fv))
    if fv.bode_pairs:
        tabs.append(_bode_tab(v, fv))
    names = [t.name for t in tabs]
    active = names.index(opening) if opening in names else 0
    return rrb.Tabs(*tabs, active_tab=active, name=f"flight {fv.flight} ({fv.t_end_s - fv.t_start_s:.0f} s)")


def _session_tab(v: str, span: FlightViews | None) -> rrb.Container:
    top = rrb.Horizontal(_lanes(v, span, False), _inputs(v, span),
                         rrb.TextLogView(origin=f"{v}/events", name="events"), column_shares=[1, 2, 1])
    grid = rrb.Grid(*[_channel(v, c, span) for c in OUTPUTS], grid_columns=4)
    return rrb.Vertical(top, grid, row_shares=[1, 3], name="session" if span is not None else "session (live)")


def _excitation_tab(v: str) -> rrb.Container:
    e = f"{v}/excitation"
    bars = [rrb.BarChartView(origin=f"{e}/{a}/coherence", name=f"{a}: coherence [0-1] vs log10 f [Hz] · green enough",
                             plot_legend=rrb.PlotLegend(visible=False)) for a in INPUTS]
    covered = rrb.TimeSeriesView(origin=f"{e}/covered", name="band covered by coherent data [%]",
                                 plot_legend=rrb.PlotLegend(rrb.Corner2D.LeftTop))
    top = rrb.Horizontal(covered, rrb.TextDocumentView(origin=f"{e}/summary", name="excitation: enough?"),
                         column_shares=[2, 1])
    return rrb.Vertical(top, rrb.Grid(*bars, grid_columns=2), row_shares=[1, 2], name="excitation")


def blueprint(vehicle: str, flights: Sequence[FlightViews] = (), session: tuple[float, float] | None = None,
              opening: str = "", excitation: bool = False) -> rrb.Blueprint:
    """One tab per finished flight, latest first and active, then the whole session.

    ``session``: the session's FC-time span for a saved file (its tab then shows all of it); None
    for a live viewer (the plots follow the newest data). ``opening``: the latest flight's sub-tab
    to open on (``model vs measured`` by default, ``gap``, ``frequency responses``). ``excitation``: the
    recording holds the live excitation monitor (a tab after the session's).
    """
    v = f"/{vehicle}"
    order = sorted(flights, key=lambda f: -f.flight)
    tabs = [_flight_tab(v, fv, opening if k == 0 else "") for k, fv in enumerate(order)]
    tabs.append(_session_tab(v, FlightViews(0, session[0], session[1]) if session else None))
    if excitation:
        tabs.append(_excitation_tab(v))
    return rrb.Blueprint(rrb.Tabs(*tabs, active_tab=0), rrb.TimePanel(timeline="fc_time", state="collapsed"),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))
