"""Live excitation monitor: is the flight's excitation enough yet, axis by axis?

Pure: no IO, no clocks, no asyncio (FC time comes with the rows). The service feeds it the grid rows
of :class:`groundstation.dsp.live.LivePipeline` and the session's events; it publishes what comes out.

For each input axis and its on-axis outputs (this project's hover model, the paper's eq. 8: the
lateral cyclic flaps the rotor longitudinally, ``A_lat -> a_s -> M_a``, so ``lat`` drives ``q`` and
``theta``; ``lon`` drives ``p`` and ``phi``; ``col`` drives ``w`` and the vertical acceleration ``az``
where RAW_IMU is streamed; ``ped`` drives ``r`` -- all configurable), the conditioned frequency
responses of the in-air rows of the current flight accumulate in one
:class:`groundstation.freq.spectra.IncrementalResponses` -- the estimator of ``validate --freq``, fed
row by row: an update costs the transforms of the windows it completes, a verdict the same at any
point of the flight.

Verdict per axis (:class:`AxisVerdict`): the coherence of the axis (per frequency, the best of its
measured on-axis outputs) is coherent where it is at least ``coherence_min`` (0.6); coherent runs
closer than ``max_gap_points`` frequency points are joined (an isolated dip of the estimate does not
split a band); the axis is *enough* when the covered bands span the band asked for
(``[excitation] band_hz``, default 0.3-5 Hz). When the flight controller runs ArduPilot's SYSID mode
(HEARTBEAT custom mode 25) the chirp it flies is recognised (axis: the input that moves most; band:
the input's own frequency at the chirp's start and end, from its zero crossings), and that axis is
judged over the chirp's band within the band asked for -- a chirp of 0.5-3 Hz is judged on 0.5-3 Hz.
The flight mode is decoded from the HEARTBEAT (ArduPilot Copter/Heli and PX4 names).

:meth:`ExcitationReport.to_json` is the ``heli/{vehicle}/excitation`` payload (docs/zenoh.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from firmware_interface.samples import Heartbeat, Imu
from groundstation.errors import DspError, FreqError
from groundstation.freq.spectra import FreqConfig, IncrementalResponses
from groundstation.sysid.model import OUTPUTS

AXES = ("lat", "lon", "col", "ped")
#: the live rows' outputs (dsp.live) and the vertical acceleration the monitor adds
MONITOR_OUTPUTS = ("u", "v", "w", "p", "q", "r", "theta", "phi", "az")

#: ArduPilot Copter (and TradHeli) custom modes; 25 is SYSTEMID, which flies the SID_* chirp
ARDUPILOT_COPTER_MODES = {
    0: "STABILIZE", 1: "ACRO", 2: "ALT_HOLD", 3: "AUTO", 4: "GUIDED", 5: "LOITER", 6: "RTL", 7: "CIRCLE",
    9: "LAND", 11: "DRIFT", 13: "SPORT", 14: "FLIP", 15: "AUTOTUNE", 16: "POSHOLD", 17: "BRAKE", 18: "THROW",
    19: "AVOID_ADSB", 20: "GUIDED_NOGPS", 21: "SMART_RTL", 22: "FLOWHOLD", 23: "FOLLOW", 24: "ZIGZAG",
    25: "SYSTEMID", 26: "AUTOROTATE", 27: "AUTO_RTL", 28: "TURTLE",
}
SYSTEMID_MODE = 25
_PX4_MAIN = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD", 7: "STABILIZED",
             8: "RATTITUDE"}
_PX4_AUTO = {1: "READY", 2: "TAKEOFF", 3: "LOITER", 4: "MISSION", 5: "RTL", 6: "LAND", 8: "FOLLOW_TARGET",
             9: "PRECLAND"}
_MAV_AUTOPILOT_ARDUPILOTMEGA = 3
_MAV_AUTOPILOT_PX4 = 12


def flight_mode_name(autopilot: int, custom_mode: int) -> str:
    """Human name of a HEARTBEAT's custom mode (ArduPilot Copter/Heli or PX4), else ``mode N``."""
    if autopilot == _MAV_AUTOPILOT_ARDUPILOTMEGA:
        return ARDUPILOT_COPTER_MODES.get(int(custom_mode), f"mode {custom_mode}")
    if autopilot == _MAV_AUTOPILOT_PX4:
        main, sub = (int(custom_mode) >> 16) & 0xFF, (int(custom_mode) >> 24) & 0xFF
        name = _PX4_MAIN.get(main, f"main {main}")
        return f"AUTO_{_PX4_AUTO.get(sub, sub)}" if main == 4 else name
    return f"mode {custom_mode}"


@dataclass(frozen=True)
class ExcitationConfig:
    """``[excitation]``: the live excitation monitor (docs/configuration.md).

    The spectral settings are the live estimate's (shorter windows than ``[freq]``'s, so that a sweep
    is judged within seconds of its end rather than after 100 s of flight): the estimator is the same.
    """

    enabled: bool = True
    band_hz: tuple[float, float] = (0.3, 5.0)
    coherence_min: float = 0.6
    max_gap_points: int = 2          # coherent runs this many frequency points apart or closer are joined
    publish_rate_hz: float = 1.0     # verdicts per FC second while armed
    window_s: tuple[float, ...] = (2.5, 5.0, 10.0)
    min_cycles: float = 3.0          # a window length counts from this many cycles per window
    f_max_hz: float = 8.0
    n_freq: int = 60
    lat: tuple[str, ...] = ("q", "theta")
    lon: tuple[str, ...] = ("p", "phi")
    col: tuple[str, ...] = ("w", "az")
    ped: tuple[str, ...] = ("r",)
    chirp_band: bool = True          # judge a recognised SYSID chirp's axis over the chirp's own band

    def __post_init__(self) -> None:
        lo, hi = self.band_hz
        if not 0 < lo < hi:
            raise DspError(f"excitation.band_hz must be [low, high] with 0 < low < high, got {list(self.band_hz)}")
        if not 0 < self.coherence_min < 1:
            raise DspError(f"excitation.coherence_min must be in (0, 1), got {self.coherence_min}")
        if self.publish_rate_hz <= 0:
            raise DspError(f"excitation.publish_rate_hz must be > 0, got {self.publish_rate_hz}")
        if self.max_gap_points < 0:
            raise DspError(f"excitation.max_gap_points must be >= 0, got {self.max_gap_points}")
        for axis in AXES:
            outs = getattr(self, axis)
            bad = [o for o in outs if o not in MONITOR_OUTPUTS]
            if not outs or bad:
                raise DspError(f"excitation.{axis} = {list(outs)}: on-axis outputs must be some of "
                               f"{', '.join(MONITOR_OUTPUTS)}")
        self.freq_config()

    def outputs_of(self, axis: str) -> tuple[str, ...]:
        return tuple(getattr(self, axis))

    def freq_config(self) -> FreqConfig:
        """The estimator's settings (``min_cycles`` cycles of the longest window set the lowest frequency)."""
        return FreqConfig(window_s=self.window_s, min_cycles=self.min_cycles, f_max_hz=self.f_max_hz,
                          n_freq=self.n_freq, coherence_min=self.coherence_min)


@dataclass(frozen=True)
class Chirp:
    """A SYSID chirp recognised on the link: its axis and band (from the input itself), FC times."""

    axis: str
    f_start_hz: float
    f_stop_hz: float
    start_fc_s: float
    end_fc_s: float

    def to_json(self) -> dict[str, Any]:
        return {"axis": self.axis, "band_hz": [round(self.f_start_hz, 3), round(self.f_stop_hz, 3)],
                "start_fc_s": round(self.start_fc_s, 3), "end_fc_s": round(self.end_fc_s, 3)}


@dataclass(frozen=True, eq=False)
class AxisVerdict:
    """One axis: enough or not, the band judged, the coherent bands, what is missing.

    ``f_hz (F,)`` and ``coherence (F,)`` (best on-axis output per frequency; NaN where no window
    resolves it yet) are for plots; :meth:`to_json` leaves them out.
    """

    axis: str
    enough: bool
    band_hz: tuple[float, float]
    band_from: str                                  # "config" | "chirp"
    covered_hz: tuple[tuple[float, float], ...]     # coherent bands within the band judged
    coherence_min: float | None                     # lowest coherence in the band (None: nothing resolved)
    missing: str                                    # "" when enough, else what is covered and what is not
    outputs: tuple[str, ...]                        # the on-axis outputs measured
    f_hz: np.ndarray
    coherence: np.ndarray

    @property
    def covered_fraction(self) -> float:
        """Share of the band judged (in log frequency) that the coherent bands cover, 0..1."""
        lo, hi = self.band_hz
        width = sum(math.log(b / a) for a, b in self.covered_hz if b > a)
        return 1.0 if self.enough else min(1.0, width / math.log(hi / lo))

    def to_json(self) -> dict[str, Any]:
        return {"enough": self.enough, "band_hz": [_r(self.band_hz[0]), _r(self.band_hz[1])],
                "covered_hz": [[_r(a), _r(b)] for a, b in self.covered_hz],
                "coherence_min": None if self.coherence_min is None else round(self.coherence_min, 3),
                "missing": self.missing, "band_from": self.band_from, "outputs": list(self.outputs)}

    def line(self) -> str:
        """``lon: enough (0.3-5 Hz coherent)`` or ``lon: coherent 0.5-3 Hz, missing 3-5 Hz``."""
        if self.enough:
            return f"{self.axis}: enough ({_band(self.band_hz)} Hz coherent)"
        return f"{self.axis}: {self.missing}"


@dataclass(frozen=True, eq=False)
class ExcitationReport:
    """The verdict of every axis at one moment of a flight."""

    flight: int
    t_s: float                  # flight time: FC seconds since arming
    t_fc_s: float
    in_air_s: float             # in-air data accumulated so far
    mode: str
    axes: dict[str, AxisVerdict]
    enough_at_s: dict[str, float]   # flight time each axis first said enough
    chirps: tuple[Chirp, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {"flight": self.flight, "t_s": round(self.t_s, 3), "t_fc_s": round(self.t_fc_s, 3),
                "in_air_s": round(self.in_air_s, 2), "mode": self.mode,
                "axes": {a: {**v.to_json(), "enough_at_s": _r(self.enough_at_s.get(a))} for a, v in self.axes.items()},
                "chirps": [c.to_json() for c in self.chirps]}

    def line(self) -> str:
        """One status line: ``excitation flight 1 @ 62 s: lat: ...; lon: enough ...``."""
        return f"excitation flight {self.flight} @ {self.t_s:.0f} s: " + "; ".join(v.line() for v in self.axes.values())


def _r(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 3)


def _fmt(x: float) -> str:
    return f"{x:.2g}" if x < 10 else f"{x:.0f}"


def _band(b: tuple[float, float]) -> str:
    return f"{_fmt(b[0])}-{_fmt(b[1])}"


def coverage(f_hz: np.ndarray, coherence: np.ndarray, band_hz: tuple[float, float], coherence_min: float,
             max_gap_points: int) -> tuple[tuple[tuple[float, float], ...], tuple[tuple[float, float], ...]]:
    """(covered, missing) bands within ``band_hz``: runs of frequency points with coherence >=
    ``coherence_min``, joined across gaps of at most ``max_gap_points`` points; the missing bands are
    the rest of ``band_hz``. A band's edges are frequency points (a run of one point is ``[f, f]``)."""
    lo, hi = band_hz
    tol = 1e-9
    inb = np.flatnonzero((f_hz >= lo * (1 - tol)) & (f_hz <= hi * (1 + tol)))
    if inb.size == 0:
        return (), ((lo, hi),)
    ok = np.nan_to_num(coherence[inb], nan=0.0) >= coherence_min
    runs: list[list[int]] = []
    for k in np.flatnonzero(ok):
        if runs and k - runs[-1][1] - 1 <= max_gap_points:
            runs[-1][1] = int(k)
        else:
            runs.append([int(k), int(k)])
    f = f_hz[inb]
    covered = tuple((float(f[a]), float(f[b])) for a, b in runs)
    if not runs:
        return (), ((lo, hi),)
    missing: list[tuple[float, float]] = []
    # the band's ends: covered when the run reaches the band's first/last grid point, unless the band
    # reaches beyond the grid (frequencies the estimate does not resolve at all)
    if runs[0][0] > 0 or lo < f_hz[0] * (1 - 1e-6):
        missing.append((lo, float(f[runs[0][0]])))
    for (_, b0), (a1, _) in zip(runs[:-1], runs[1:], strict=True):
        missing.append((float(f[b0]), float(f[a1])))
    if runs[-1][1] < len(f) - 1 or hi > f_hz[-1] * (1 + 1e-6):
        missing.append((float(f[runs[-1][1]]), hi))
    return covered, tuple(missing)


def _missing_text(covered: tuple[tuple[float, float], ...], missing: tuple[tuple[float, float], ...]) -> str:
    cov = ", ".join(f"{_band(b)} Hz" for b in covered if b[1] > b[0])
    mis = ", ".join(f"{_band(b)} Hz" for b in missing)
    return (f"coherent {cov}, missing {mis}" if cov else f"no coherent band yet, missing {mis}")


class _ChirpTracker:
    """SYSID-mode intervals of the HEARTBEAT and the chirp flown in each (axis, band from the input)."""

    def __init__(self, dt_s: float) -> None:
        self.dt_s = dt_s
        self.active = False
        self.start_fc_s = math.nan
        self._t: list[np.ndarray] = []
        self._u: list[np.ndarray] = []
        self.chirps: list[Chirp] = []

    def mode(self, in_sysid: bool, t_fc_s: float) -> Chirp | None:
        if in_sysid and not self.active:
            self.active, self.start_fc_s = True, t_fc_s
            self._t, self._u = [], []
        elif not in_sysid and self.active:
            self.active = False
            chirp = self._close(t_fc_s)
            if chirp is not None:
                self.chirps.append(chirp)
                return chirp
        return None

    def rows(self, t_fc_s: np.ndarray, inputs: np.ndarray) -> None:
        if self.active and len(t_fc_s):
            self._t.append(t_fc_s)
            self._u.append(inputs)

    def _close(self, t_end: float) -> Chirp | None:
        if not self._t:
            return None
        t = np.concatenate(self._t)
        u = np.concatenate(self._u)
        fin = np.isfinite(u).all(axis=1)
        t, u = t[fin], u[fin]
        if t.size < 20:
            return None
        u = u - np.median(u, axis=0)
        k = int(np.argmax(np.std(u, axis=0)))
        f0, f1 = _chirp_band(t, u[:, k])
        if not (math.isfinite(f0) and math.isfinite(f1)):
            return None
        return Chirp(AXES[k], min(f0, f1), max(f0, f1), float(t[0]), float(t_end))


def _chirp_band(t: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """Lowest and highest frequency a chirp flew: the instantaneous frequency ``1 / (2 half-period)``
    between its zero crossings (interpolated between samples, with hysteresis: a crossing counts when
    the signal then goes beyond 20 % of its peak on the other side, so noise about zero does not),
    fitted as an exponential sweep (ArduPilot's chirp) and taken where the signal starts and stops."""
    peak = float(np.max(np.abs(x))) if x.size else 0.0
    if peak <= 0:
        return math.nan, math.nan
    th = 0.2 * peak
    crossings: list[float] = []
    state = 0
    last_zero = math.nan
    for i in range(1, x.size):
        if x[i - 1] * x[i] < 0 or x[i] == 0:
            last_zero = float(t[i - 1] + (t[i] - t[i - 1]) * x[i - 1] / (x[i - 1] - x[i])) if x[i - 1] != x[i] \
                else float(t[i])
        if abs(x[i]) > th and np.sign(x[i]) != state:
            if state != 0 and math.isfinite(last_zero):
                crossings.append(last_zero)
            state = int(np.sign(x[i]))
    if len(crossings) < 6:
        return math.nan, math.nan
    tc = np.asarray(crossings)
    f = 1.0 / (2.0 * np.diff(tc))
    # ArduPilot's chirp sweeps exponentially: log f is a line in time; extrapolated to where the signal
    # starts and stops (beyond 20 % of its peak)
    slope, icpt = np.polyfit(0.5 * (tc[1:] + tc[:-1]), np.log(f), 1)
    on = np.flatnonzero(np.abs(x) > th)
    f0, f1 = (float(np.exp(icpt + slope * t[i])) for i in (on[0], on[-1]))
    return f0, f1


@dataclass
class _Flight:
    number: int
    start_fc_s: float
    spectra: IncrementalResponses
    enough_at_s: dict[str, float] = field(default_factory=dict)
    last_t_fc_s: float = -math.inf
    in_segment: bool = False
    next_report_fc_s: float = -math.inf
    # rows not yet added: t, inputs, outputs, outputs measured (None: all measured)
    pending: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]] = field(default_factory=list)
    pending_rows: int = 0
    armed: bool = False
    freq_spectra: IncrementalResponses | None = None     # the same rows with [freq]'s settings (after-flight check)


class ExcitationMonitor:
    """The accumulating spectra of the current flight and their verdict (see the module docstring).

    Call :meth:`flight_started` / :meth:`flight_ended` at the flight transitions, :meth:`events` with
    the session's events (HEARTBEAT modes, IMU), :meth:`rows` with each batch of grid rows and the
    tracker's state; :meth:`rows` returns a :class:`ExcitationReport` when one is due (every
    ``1 / publish_rate_hz`` FC seconds while armed), :meth:`report` makes one at any moment.
    """

    def __init__(self, config: ExcitationConfig | None = None, dt_s: float = 0.02,
                 freq: FreqConfig | None = None) -> None:
        self.config = config or ExcitationConfig()
        #: also accumulate the flight's rows with these settings (``[freq]``: the after-flight frequency
        #: check then needs no second pass over the log; :meth:`take_freq_spectra`)
        self.freq = freq
        self._ended_freq: tuple[int, IncrementalResponses] | None = None
        self.dt_s = float(dt_s)
        self._freq = self.config.freq_config()
        self.flight: _Flight | None = None
        self.mode = ""
        self._chirps = _ChirpTracker(self.dt_s)
        self._imu_t: list[float] = []            # recent IMU samples: FC time, body z acceleration (m/s^2)
        self._imu_a: list[float] = []
        self._imu_source: str | None = None
        self._pairs = tuple((a, o) for a in AXES for o in self.config.outputs_of(a))
        # rows are handed to the spectra every half window step of the shortest window (at least)
        self._flush_rows = max(1, int(round(min(self.config.window_s) / self.dt_s * 0.2)))
        self.last: ExcitationReport | None = None

    # ------------------------------------------------------------------ inputs

    def flight_started(self, flight: int, t_fc_s: float) -> None:
        spectra = IncrementalResponses(self.dt_s, self._freq, MONITOR_OUTPUTS)
        self.flight = _Flight(flight, float(t_fc_s), spectra)
        if self.freq is not None:
            self.flight.freq_spectra = IncrementalResponses(self.dt_s, self.freq, OUTPUTS)
        self._chirps.chirps = []
        self.last = None

    def flight_ended(self) -> ExcitationReport | None:
        """The flight's last verdict (None if it never flew), then the monitor waits for the next."""
        rep = self.report() if self.flight is not None and self.flight.spectra.rows else None
        if self.flight is not None and self.flight.freq_spectra is not None:
            self._flush(end_segment=True)
            self._ended_freq = (self.flight.number, self.flight.freq_spectra)
        self.flight = None
        return rep

    def take_freq_spectra(self, flight: int) -> IncrementalResponses | None:
        """The ``[freq]`` spectra of the flight that just ended (once; None for another flight or
        without ``freq``)."""
        got, self._ended_freq = self._ended_freq, None
        return got[1] if got is not None and got[0] == flight else None

    def events(self, events: list[Any]) -> None:
        for ev in events:
            if isinstance(ev, Heartbeat):
                self.mode = flight_mode_name(ev.autopilot, ev.custom_mode)
                in_sysid = ev.autopilot == _MAV_AUTOPILOT_ARDUPILOTMEGA and ev.custom_mode == SYSTEMID_MODE
                t = self.flight.last_t_fc_s if self.flight is not None else math.nan
                self._chirps.mode(in_sysid and self.flight is not None, t)
            elif isinstance(ev, Imu):
                if self._imu_source is None:
                    self._imu_source = ev.source
                if ev.source == self._imu_source and math.isfinite(ev.t_fc_s):
                    if not self._imu_t or ev.t_fc_s > self._imu_t[-1]:
                        self._imu_t.append(float(ev.t_fc_s))
                        self._imu_a.append(float(ev.acc_m_s2[2]))
                        if len(self._imu_t) > 512:
                            del self._imu_t[:256], self._imu_a[:256]

    def _accel_z(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vertical (body z) acceleration on the grid times ``t``: interpolated, NaN where no IMU sample
        is within two grid steps or the IMU stream is slower than the grid (no IMU stream at the grid's
        rate: the column stays NaN and ``az`` counts as unmeasured); and where it was measured (the
        samples it comes from no further apart than ordinary sampling, as the live grid counts it)."""
        nan = np.full(t.shape, np.nan)
        if len(self._imu_t) < 2:
            return nan, np.zeros(t.shape, dtype=bool)
        ti, ai = np.asarray(self._imu_t[-128:]), np.asarray(self._imu_a[-128:])
        step = float(np.median(np.diff(ti)))
        if step > 1.5 * self.dt_s:
            return nan, np.zeros(t.shape, dtype=bool)     # slower than the grid (a 10 Hz stream): aliased, not used
        az = np.where((t >= ti[0] - 2 * self.dt_s) & (t <= ti[-1] + 2 * self.dt_s), np.interp(t, ti, ai), np.nan)
        j = np.clip(np.searchsorted(ti, t), 1, ti.size - 1)
        span = np.where(np.isin(t, ti), 0.0, ti[j] - ti[j - 1])
        return az, np.isfinite(az) & (span <= max(0.1, 2.5 * step))

    def rows(self, t_fc_s: np.ndarray, inputs: np.ndarray, outputs: np.ndarray, *, armed: bool,
             in_air: bool, work: bool = True, measured: np.ndarray | None = None) -> ExcitationReport | None:
        """Grid rows ``t_fc_s (n,)``, ``inputs (n, 4)``, ``outputs (n, 8)`` (raw, as dsp.live gives them)
        and the flight state after them; ``measured (n, 8)`` bool (``LiveOutput.outputs_measured``) is
        False where a row only bridges a hole of the link: the spectra count such rows in the random
        error by their share, as the after-flight estimate does. In-air rows of the current flight
        accumulate; with ``work`` the rows gathered are transformed and a verdict is returned when one
        is due (else :meth:`step` does that when the caller has time: the service, between two live
        windows)."""
        fl = self.flight
        if fl is None or len(t_fc_s) == 0:
            return None
        t = np.asarray(t_fc_s, dtype=float)
        if in_air and armed:
            if fl.in_segment and t[0] - fl.last_t_fc_s > 1.5 * self.dt_s:
                self._flush(end_segment=True)       # a gap in the grid: no window spans it
            m = None if measured is None else np.asarray(measured, dtype=bool)
            fl.pending.append((t, np.asarray(inputs, dtype=float), np.asarray(outputs, dtype=float), m))
            fl.pending_rows += len(t)
            self._chirps.rows(t, np.asarray(inputs, dtype=float))
            fl.in_segment = True
        elif fl.in_segment:
            self._flush(end_segment=True)
            fl.in_segment = False
        fl.last_t_fc_s = float(t[-1])
        fl.armed = armed
        return self.step() if work else None

    def step(self) -> ExcitationReport | None:
        """Transform the rows gathered (once the shortest window's step has arrived) and return a verdict
        if one is due (every ``1 / publish_rate_hz`` FC seconds while armed)."""
        fl = self.flight
        if fl is None:
            return None
        if fl.pending_rows >= self._flush_rows:
            self._flush()
        if fl.armed and fl.last_t_fc_s >= fl.next_report_fc_s and fl.spectra.rows + fl.pending_rows:
            fl.next_report_fc_s = fl.last_t_fc_s + 1.0 / self.config.publish_rate_hz
            return self.report()
        return None

    def _flush(self, end_segment: bool = False) -> None:
        """Hand the rows gathered so far to the spectra (in blocks: fewer, larger updates)."""
        fl = self.flight
        if fl is None:
            return
        if fl.pending:
            t = np.concatenate([p[0] for p in fl.pending])
            u = np.concatenate([p[1] for p in fl.pending])
            az, az_measured = self._accel_z(t)
            y = np.column_stack([np.concatenate([p[2] for p in fl.pending]), az])
            mask = np.column_stack([np.concatenate([p[3] if p[3] is not None else np.ones(p[2].shape, bool)
                                                    for p in fl.pending]), az_measured])
            # no hole of the link in these rows: the spectra take their plain path
            m = None if (mask | ~np.isfinite(y)).all() else mask
            fl.pending.clear()
            fl.pending_rows = 0
            fl.spectra.add(u, y, m)
            if fl.freq_spectra is not None:
                fl.freq_spectra.add(u, y[:, :len(OUTPUTS)], None if m is None else m[:, :len(OUTPUTS)])
        if end_segment:
            fl.spectra.end_segment()
            if fl.freq_spectra is not None:
                fl.freq_spectra.end_segment()

    # ------------------------------------------------------------------ verdict

    def report(self) -> ExcitationReport:
        """The verdict of every axis on the data so far (raises DspError outside a flight)."""
        fl = self.flight
        if fl is None:
            raise DspError("no flight: the excitation verdict needs an armed flight")
        cfg = self.config
        self._flush()
        inc = fl.spectra
        t_s = fl.last_t_fc_s - fl.start_fc_s
        try:
            rs = inc.responses(self._pairs) if inc.rows else None
        except FreqError:       # no in-air rows yet: nothing coherent
            rs = None
        f_hz = inc.f_hz
        chirps = tuple(self._chirps.chirps)
        axes: dict[str, AxisVerdict] = {}
        for axis in AXES:
            band, band_from = cfg.band_hz, "config"
            mine = [c for c in chirps if c.axis == axis]
            if cfg.chirp_band and mine:
                c = mine[-1]
                lo, hi = max(band[0], c.f_start_hz), min(band[1], c.f_stop_hz)
                if hi > lo:
                    band, band_from = (lo, hi), "chirp"
            coh = np.full(f_hz.size, np.nan)
            outs: list[str] = []
            reason = ""
            if rs is not None:
                for o in cfg.outputs_of(axis):
                    p = rs.pair(axis, o)
                    if "not measured" in p.reason:
                        continue
                    outs.append(o)
                    if "never moves" in p.reason:
                        reason = p.reason
                    coh = np.fmax(coh, p.coherence)
            covered, missing = coverage(f_hz, coh, band, cfg.coherence_min, cfg.max_gap_points)
            enough = not missing and not reason and bool(outs)
            inb = (f_hz >= band[0] * (1 - 1e-9)) & (f_hz <= band[1] * (1 + 1e-9)) & np.isfinite(coh)
            cmin = float(np.min(coh[inb])) if inb.any() else None
            text = "" if enough else (reason or _missing_text(covered, missing))
            axes[axis] = AxisVerdict(axis, enough, band, band_from, covered, cmin, text, tuple(outs), f_hz, coh)
            if enough and axis not in fl.enough_at_s:
                fl.enough_at_s[axis] = t_s
        rep = ExcitationReport(fl.number, t_s, fl.last_t_fc_s, inc.rows * self.dt_s, self.mode, axes,
                               dict(fl.enough_at_s), chirps)
        self.last = rep
        return rep
