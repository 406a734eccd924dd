"""Rerun (rerun-sdk 0.41) stream of one service run: live inputs/outputs, model overlay, gap plots.

One explicit :class:`rerun.RecordingStream` per run (never the global one). Timelines ``fc_time``
(duration, FC clock) and ``host_time`` (timestamp). Entities::

    /{vehicle}/inputs/{lat,lon,col,ped}
    /{vehicle}/outputs/{u,v,w,p,q,r,theta,phi}/{raw,smoothed,model}
    /{vehicle}/gap/match/{channel}          match degree per channel and flight (sequence `flight`)
    /{vehicle}/gap/verdict                  text log of the diagnosis
    /{vehicle}/status                       text log of flight transitions

Batches go through ``send_columns``; series styling is logged once as static. A default blueprint
lays out inputs (top), outputs (grid, raw/smoothed/model overlaid per channel) and gap (bottom).

Modes: ``save PATH.rrd`` (file), ``spawn`` (start a local viewer), ``connect URL`` (a running
viewer's gRPC proxy, e.g. ``rerun+http://127.0.0.1:9876/proxy``). An unreachable viewer raises
:class:`RerunSinkError` with one line before anything is logged; the service then runs without Rerun.
Leaves what to log and when to :mod:`groundstation.service`.
"""

from __future__ import annotations

import socket
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from groundstation.errors import GroundstationError

INPUTS = ("lat", "lon", "col", "ped")
OUTPUTS = ("u", "v", "w", "p", "q", "r", "theta", "phi")
_COLORS = {"raw": (150, 150, 150), "smoothed": (31, 119, 180), "model": (214, 39, 40)}


class RerunSinkError(GroundstationError):
    """The Rerun target cannot be used (one line)."""


def blueprint(vehicle: str) -> rrb.Blueprint:
    """Inputs on top, one plot per output channel (raw/smoothed/model overlaid), gap at the bottom."""
    v = f"/{vehicle}"
    inputs = rrb.TimeSeriesView(origin=f"{v}/inputs", name="Inputs (normalised)")
    outputs = rrb.Grid(*[rrb.TimeSeriesView(origin=f"{v}/outputs/{c}", name=c) for c in OUTPUTS],
                       grid_columns=4, name="Outputs: raw / smoothed / model")
    gap = rrb.Horizontal(
        rrb.TimeSeriesView(origin=f"{v}/gap/match", name="Match degree per flight (%)"),
        rrb.TextLogView(origin=f"{v}/gap", name="Diagnosis"),
        rrb.TextLogView(origin=f"{v}/status", name="Flights"),
        name="Gap",
    )
    return rrb.Blueprint(rrb.Vertical(inputs, outputs, gap, row_shares=[1, 3, 1]), collapse_panels=True)


def _check_reachable(url: str) -> None:
    u = urlparse(url)
    host = u.hostname or "127.0.0.1"
    port = u.port or 9876
    try:
        with socket.create_connection((host, port), timeout=1.0):
            pass
    except OSError as exc:
        raise RerunSinkError(f"rerun viewer {url}: not reachable ({exc.strerror or exc})") from None


class RerunSink:
    """Log the live path and identification results of one vehicle to one RecordingStream.

    Parameters
    ----------
    vehicle : entity root
    mode : ``save`` | ``spawn`` | ``connect``
    target : PATH.rrd for save, URL for connect
    recording_id : optional fixed recording id
    """

    def __init__(self, vehicle: str, mode: str, target: str = "", *, recording_id: str | None = None) -> None:
        self.vehicle = vehicle
        self.root = f"/{vehicle}"
        self.mode = mode
        self.target = target
        self.stream = rr.RecordingStream("heli-groundstation", recording_id=recording_id)
        bp = blueprint(vehicle)
        if mode == "save":
            path = Path(target)
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                with open(path, "ab"):
                    pass
            except OSError as exc:
                raise RerunSinkError(f"{path}: cannot write .rrd ({exc.strerror or exc})") from None
            self.stream.save(str(path), default_blueprint=bp)
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
        self._style()
        self.rows = 0

    def _style(self) -> None:
        s = self.stream
        for c in OUTPUTS:
            for kind, color in _COLORS.items():
                s.log(f"{self.root}/outputs/{c}/{kind}", rr.SeriesLines(colors=[color], names=[f"{c} {kind}"],
                                                                         widths=[1.5]), static=True)
        for c in INPUTS:
            s.log(f"{self.root}/inputs/{c}", rr.SeriesLines(names=[c]), static=True)

    # ------------------------------------------------------------------ live

    def log_rows(self, t_fc_s: np.ndarray, t_host_s: np.ndarray, inputs: np.ndarray | None = None,
                 outputs: np.ndarray | None = None, kind: str = "raw") -> None:
        """Log grid rows.

        Parameters
        ----------
        t_fc_s : (n,) FC clock, s
        t_host_s : (n,) host time, Unix s (NaN entries interpolated; all NaN = no host_time index)
        inputs : (n, 4) lat lon col ped, or None
        outputs : (n, 8) u v w p q r theta phi, or None
        kind : ``raw`` | ``smoothed`` | ``model`` (which output sub-entity)
        """
        n = len(t_fc_s)
        if n == 0:
            return
        th = np.asarray(t_host_s, dtype=float)
        finite = np.isfinite(th)
        idx = [rr.TimeColumn("fc_time", duration=np.asarray(t_fc_s, dtype=float))]
        if finite.any():     # rows without any host time (model overlays) live on fc_time only
            if not finite.all():
                th = np.interp(np.arange(n), np.flatnonzero(finite), th[finite])
            idx.append(rr.TimeColumn("host_time", timestamp=th))
        s = self.stream
        if inputs is not None:
            for i, c in enumerate(INPUTS):
                s.send_columns(f"{self.root}/inputs/{c}", indexes=idx,
                               columns=rr.Scalars.columns(scalars=inputs[:, i]))
        if outputs is not None:
            for i, c in enumerate(OUTPUTS):
                s.send_columns(f"{self.root}/outputs/{c}/{kind}", indexes=idx,
                               columns=rr.Scalars.columns(scalars=outputs[:, i]))
        self.rows += n

    def log_event(self, text: str, t_fc_s: float, level: str = "INFO") -> None:
        self.stream.set_time("fc_time", duration=float(t_fc_s))
        self.stream.log(f"{self.root}/status", rr.TextLog(text, level=level))

    # ------------------------------------------------------------------ between flights

    def log_model_overlay(self, t_fc_s: np.ndarray, outputs_model: np.ndarray) -> None:
        """Model-predicted outputs ``(n, 8)`` on the FC clock of the flight they were fitted to."""
        self.log_rows(t_fc_s, np.full(len(t_fc_s), np.nan), outputs=outputs_model, kind="model")

    def log_gap(self, flight: int, match_pct: dict[str, float], verdict: str, text: str, t_fc_s: float) -> None:
        s = self.stream
        s.set_time("flight", sequence=int(flight))
        s.set_time("fc_time", duration=float(t_fc_s))
        for c, m in match_pct.items():
            if m is not None and np.isfinite(m):
                s.log(f"{self.root}/gap/match/{c}", rr.Scalars(float(m)))
        s.log(f"{self.root}/gap/verdict", rr.TextLog(f"flight {flight}: {verdict}. {text}",
                                                       level="WARN" if verdict not in ("none", "") else "INFO"))
        s.reset_time()

    def close(self) -> None:
        try:
            self.stream.flush()
        finally:
            self.stream.disconnect()
