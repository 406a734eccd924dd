"""Live (streaming) signal path: FC-clock grid alignment, causal eq.-18 smoothing, windows, flights.

Pure: no IO, no clocks, no asyncio. Time is always passed in (``t_fc_s`` from the samples, ``now``
host seconds where rates are needed). The service (:mod:`groundstation.service`) feeds typed events
from :mod:`firmware_interface.samples` into :class:`LivePipeline` and publishes what comes out.

Array conventions: rows are samples, columns channels: ``inputs (n, 4)`` = lat lon col ped
(normalised, ``(pwm - trim_pwm) / pwm_per_unit``), ``outputs (n, 8)`` = u v w p q r theta phi
(body m/s, rad/s, rad), ``t_fc_s (n,)`` on the 50 Hz FC-clock grid ``k / grid_rate_hz``.

Pieces (each usable alone):

* :class:`CausalSmoother` -- eq. (18) one sample at a time. Each pass delays by two samples; its output
  equals :func:`groundstation.dsp.smoothing.smooth5` exactly, including the end rows once
  :meth:`CausalSmoother.flush` is called at the end of a segment.
* :class:`GridAligner` -- linear interpolation of irregular streams onto the grid; a grid row is
  emitted as soon as every *holding* stream has a sample at or after it (so the packet that completes
  a row is the one that releases it); streams silent for ``stale_s`` stop holding the grid back.
* :func:`ned_to_body` -- NED velocities rotated into the body frame by roll/pitch/yaw.
* :class:`FlightTracker` -- flights = armed intervals, in air from landed_state else height.
* :class:`WindowBuffer` -- sliding windows of ``window_s`` every ``hop_s``.
* :class:`RateMeter` -- message rates over a sliding host-time window.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from firmware_interface.samples import (
    Attitude,
    ExtendedSysState,
    FcRebooted,
    GlobalPositionInt,
    Heartbeat,
    LocalPositionNed,
    ServoOutputRaw,
)
from groundstation.dsp.smoothing import FIRST_ROW, INTERIOR_KERNEL, SECOND_ROW
from groundstation.errors import DspError

INPUTS = ("lat", "lon", "col", "ped")
OUTPUTS = ("u", "v", "w", "p", "q", "r", "theta", "phi")

# --------------------------------------------------------------------------------------------
# Causal eq. (18)
# --------------------------------------------------------------------------------------------


class _OnePass:
    """One pass of eq. (18) as a stream: interior rows two samples late, end rows on start/flush."""

    def __init__(self) -> None:
        self._buf: deque[np.ndarray] = deque(maxlen=5)
        self._n = 0

    def push(self, y: np.ndarray) -> list[np.ndarray]:
        self._buf.append(y)
        self._n += 1
        if self._n < 5:
            return []
        b = self._buf
        interior = (INTERIOR_KERNEL[0] * (b[0] + b[4]) + INTERIOR_KERNEL[1] * (b[1] + b[3])
                    + INTERIOR_KERNEL[2] * b[2])
        if self._n == 5:
            head = np.stack(b)
            return [np.tensordot(FIRST_ROW, head, axes=(0, 0)),
                    np.tensordot(SECOND_ROW, head, axes=(0, 0)), interior]
        return [interior]

    def flush(self) -> list[np.ndarray]:
        """End the segment: the last two rows (end formulas), or the rows unchanged if fewer than 5."""
        b = list(self._buf)
        n = self._n
        self._buf.clear()
        self._n = 0
        if n == 0:
            return []
        if n < 5:
            return [np.array(r, dtype=float) for r in b]
        tail = np.stack(b)
        return [np.tensordot(SECOND_ROW[::-1], tail, axes=(0, 0)),
                np.tensordot(FIRST_ROW[::-1], tail, axes=(0, 0))]


class CausalSmoother:
    """Eq. (18) applied ``passes`` times, one row at a time.

    :meth:`push` takes one row ``y (n_channels,)`` and returns the smoothed rows that became final,
    as an array ``(k, n_channels)`` (k = 0 while filling, 3 on the fifth row of the first pass, else
    1). Latency is ``2 * passes`` samples. :meth:`flush` ends a segment (link gap, disarm) and
    returns the remaining rows; the concatenation over a segment equals ``smooth5(y, passes)``.
    """

    def __init__(self, n_channels: int, passes: int = 1) -> None:
        if passes < 0:
            raise DspError(f"passes must be >= 0, got {passes}")
        self.n_channels = n_channels
        self.passes = passes
        self._stages = [_OnePass() for _ in range(passes)]

    @property
    def latency_samples(self) -> int:
        return 2 * self.passes

    def _run(self, rows: list[np.ndarray], start: int, flush: bool) -> list[np.ndarray]:
        for stage in self._stages[start:]:
            out: list[np.ndarray] = []
            for r in rows:
                out.extend(stage.push(r))
            if flush:
                out.extend(stage.flush())
            rows = out
        return rows

    def push(self, y: np.ndarray) -> np.ndarray:
        row = np.asarray(y, dtype=float).reshape(self.n_channels)
        out = self._run([row], 0, False)
        return np.array(out).reshape(len(out), self.n_channels)

    def flush(self) -> np.ndarray:
        rows: list[np.ndarray] = []
        for stage in self._stages:
            out: list[np.ndarray] = []
            for r in rows:          # the previous stage's tail goes through this stage first
                out.extend(stage.push(r))
            out.extend(stage.flush())
            rows = out
        return np.array(rows).reshape(len(rows), self.n_channels)


# --------------------------------------------------------------------------------------------
# Body-frame velocity
# --------------------------------------------------------------------------------------------


def ned_to_body(v_ned: np.ndarray, roll_rad: np.ndarray, pitch_rad: np.ndarray,
                yaw_rad: np.ndarray) -> np.ndarray:
    """Rotate NED velocities into the body frame (ZYX Euler angles).

    Parameters
    ----------
    v_ned : (..., 3) north, east, down velocity, m/s
    roll_rad, pitch_rad, yaw_rad : (...) attitude, rad

    Returns
    -------
    (..., 3) body velocities u v w, m/s
    """
    v = np.asarray(v_ned, dtype=float)
    cf, sf = np.cos(roll_rad), np.sin(roll_rad)
    ct, st = np.cos(pitch_rad), np.sin(pitch_rad)
    cp, sp = np.cos(yaw_rad), np.sin(yaw_rad)
    vn, ve, vd = v[..., 0], v[..., 1], v[..., 2]
    # R_nb = Rz(yaw) Ry(pitch) Rx(roll); v_body = R_nb^T v_ned
    u = ct * cp * vn + ct * sp * ve - st * vd
    vv = (sf * st * cp - cf * sp) * vn + (sf * st * sp + cf * cp) * ve + sf * ct * vd
    w = (cf * st * cp + sf * sp) * vn + (cf * st * sp - sf * cp) * ve + cf * ct * vd
    return np.stack([u, vv, w], axis=-1)


# --------------------------------------------------------------------------------------------
# Grid alignment
# --------------------------------------------------------------------------------------------


_GAP_EVERY = 32  # new samples between two recomputations of a stream's median interval


@dataclass
class _Stream:
    n_cols: int
    hold: bool                        # holds the grid back until it has a sample at/after the tick
    t: deque[float] = field(default_factory=lambda: deque(maxlen=256))
    v: deque[np.ndarray] = field(default_factory=lambda: deque(maxlen=256))
    t_host: deque[float] = field(default_factory=lambda: deque(maxlen=256))
    added: int = 0                    # samples added since the last reset
    gap_s: float = math.nan           # cached ordinary-sampling limit (see GridAligner._measured_gap)
    gap_at: int = 0                   # ``added`` when gap_s was computed


class GridAligner:
    """Interpolate irregular streams onto the grid ``t = k / rate_hz`` of the FC clock.

    Parameters
    ----------
    rate_hz : grid rate
    streams : name -> (n_columns, hold). ``hold`` streams release a grid row only once they have a
        sample at or after it; other streams are interpolated when bracketed, else held (latest value).
    stale_s : a stream whose newest sample is older than the newest sample of any stream by more than
        this is stale: it no longer holds the grid back and reads NaN. The first rows come out after a
        warm-up of ``stale_s`` of FC time, so that every stream the FC sends has been seen.
    max_gap_s : if the grid would have to jump more than this (link outage), it restarts at the newest
        time instead of emitting rows across the gap; :attr:`gaps` counts restarts.
    measured_gap_s, measured_gap_factor : a row's value of a stream counts as *measured* where the samples
        it comes from are no further apart than ``max(measured_gap_s, measured_gap_factor * the stream's
        median interval)`` (ordinary sampling, as :mod:`groundstation.dsp.prepare` counts it); across a
        longer hole (packets lost on the link) it is a straight line, not a measurement.
        :attr:`measured` holds the last :meth:`pop`'s ``(k, n_cols)`` bool mask.
    """

    def __init__(self, rate_hz: float, streams: dict[str, tuple[int, bool]], *, stale_s: float = 0.5,
                 max_gap_s: float = 1.0, measured_gap_s: float = 0.1, measured_gap_factor: float = 2.5) -> None:
        self.dt_s = 1.0 / rate_hz
        self.rate_hz = rate_hz
        self.names = tuple(streams)
        self._streams = {n: _Stream(c, h) for n, (c, h) in streams.items()}
        self._offsets: dict[str, slice] = {}
        off = 0
        for n, (c, _) in streams.items():
            self._offsets[n] = slice(off, off + c)
            off += c
        self.n_cols = off
        self.stale_s = stale_s
        self.max_gap_s = max_gap_s
        self._next_k: int | None = None
        self._newest = -math.inf
        self._first = math.nan
        self.gaps = 0
        self.measured_gap_s = measured_gap_s
        self.measured_gap_factor = measured_gap_factor
        self.measured = np.zeros((0, self.n_cols), dtype=bool)

    def columns(self, name: str) -> slice:
        return self._offsets[name]

    @property
    def newest_t_fc_s(self) -> float:
        """Newest FC time seen on any stream (-inf before the first sample)."""
        return self._newest

    def reset(self) -> None:
        for s in self._streams.values():
            s.t.clear()
            s.v.clear()
            s.t_host.clear()
            s.added, s.gap_s, s.gap_at = 0, math.nan, 0
        self._next_k = None
        self._newest = -math.inf
        self._first = math.nan

    def add(self, name: str, t_fc_s: float, values: np.ndarray | tuple[float, ...], t_host_s: float = math.nan
            ) -> None:
        s = self._streams[name]
        if s.t and t_fc_s <= s.t[-1]:
            return  # duplicate or out of order: ignore (the FC clock is monotonic per stream)
        s.t.append(float(t_fc_s))
        s.v.append(np.asarray(values, dtype=float))
        s.t_host.append(float(t_host_s))
        s.added += 1
        self._newest = max(self._newest, float(t_fc_s))
        if self._next_k is None:
            self._next_k = math.ceil(t_fc_s * self.rate_hz - 1e-6)
            self._first = float(t_fc_s)

    def _active(self, s: _Stream) -> bool:
        return bool(s.t) and s.t[-1] >= self._newest - self.stale_s

    def _watermark(self) -> float:
        holders = [s.t[-1] for s in self._streams.values() if s.hold and self._active(s)]
        return min(holders) if holders else -math.inf

    def pop(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """Rows that became complete: ``t_fc_s (k,)``, ``values (k, n_cols)``, ``t_host_s (k,)`` and
        whether the grid restarted after a gap before these rows (the smoother must flush)."""
        if self._next_k is None or self._newest - self._first < self.stale_s:
            # warm-up: wait stale_s of FC time so every stream that exists has been seen once
            return np.empty(0), np.empty((0, self.n_cols)), np.empty(0), False
        wm = self._watermark()
        self.measured = np.zeros((0, self.n_cols), dtype=bool)
        restarted = False
        if wm - self._next_k * self.dt_s > self.max_gap_s:
            self._next_k = math.ceil(wm * self.rate_hz - 1e-6)
            self.gaps += 1
            restarted = True
        ts: list[float] = []
        rows: list[np.ndarray] = []
        hosts: list[float] = []
        meas: list[np.ndarray] = []
        gaps = ({name: self._measured_gap(s) for name, s in self._streams.items()}
                if self._next_k * self.dt_s <= wm + 1e-9 else {})
        while self._next_k * self.dt_s <= wm + 1e-9:
            t = self._next_k * self.dt_s
            row = np.full(self.n_cols, np.nan)
            m = np.zeros(self.n_cols, dtype=bool)
            host = -math.inf
            for name, s in self._streams.items():
                if not self._active(s):
                    continue
                val, th, span = self._at(s, t)
                if val is not None:
                    row[self._offsets[name]] = val
                    m[self._offsets[name]] = span <= gaps[name]
                    if s.hold:
                        host = max(host, th)
            ts.append(t)
            rows.append(row)
            meas.append(m)
            hosts.append(host if host > -math.inf else math.nan)
            self._next_k += 1
        if not ts:
            return np.empty(0), np.empty((0, self.n_cols)), np.empty(0), restarted
        self.measured = np.array(meas)
        return np.array(ts), np.array(rows), np.array(hosts), restarted

    def _measured_gap(self, s: _Stream) -> float:
        """Longest interval between a stream's samples that is ordinary sampling (s). The median interval
        over the kept samples is recomputed every ``_GAP_EVERY`` new samples once the buffer is full
        (it is a property of the stream's rate, and a median per packet cost the service half its CPU)."""
        if len(s.t) < 3:
            return self.measured_gap_s
        if s.gap_s == s.gap_s and len(s.t) == s.t.maxlen and s.added - s.gap_at < _GAP_EVERY:
            return s.gap_s
        d = np.diff(np.asarray(s.t))
        s.gap_s = max(self.measured_gap_s, self.measured_gap_factor * float(np.median(d)))
        s.gap_at = s.added
        return s.gap_s

    def _at(self, s: _Stream, t: float) -> tuple[np.ndarray | None, float, float]:
        """Value at ``t``, the host time of the sample that made it known and the interval (s) between
        the samples it comes from (0 on a sample; the age of a held value)."""
        times = s.t
        if times[0] > t + 1e-9:
            return None, math.nan, math.inf
        # newest sample at or before t
        i = len(times) - 1
        while i > 0 and times[i] > t + 1e-9:
            i -= 1
        if abs(times[i] - t) <= 1e-9 or i == len(times) - 1:
            return s.v[i], s.t_host[i], max(0.0, t - times[i])
        t0, t1 = times[i], times[i + 1]
        if t1 - t0 > self.stale_s:
            return None, math.nan, math.inf
        a = (t - t0) / (t1 - t0)
        return (1.0 - a) * s.v[i] + a * s.v[i + 1], s.t_host[i + 1], t1 - t0


# --------------------------------------------------------------------------------------------
# Flights
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FlightStarted:
    flight: int          # 1-based flight number in this service run
    t_fc_s: float


@dataclass(frozen=True)
class FlightEnded:
    flight: int
    t_fc_s: float
    duration_s: float


class FlightTracker:
    """Flights from the armed flag; in air from EXTENDED_SYS_STATE landed_state, else height.

    HEARTBEAT carries no FC time: an arming seen before any time-stamped message (FC time NaN) opens
    the flight at once, but its :class:`FlightStarted` waits for the first known FC time
    (:meth:`on_time`); the flight starts then. A flight that ends before any FC time is known ends
    with time and duration NaN, never a made-up time.
    """

    def __init__(self, in_air_alt_m: float = 0.5) -> None:
        self.in_air_alt_m = in_air_alt_m
        self.armed = False
        self.flight = 0                       # number of the current or last flight
        self.start_fc_s = math.nan
        self.landed_state: int | None = None
        self.height_m = math.nan
        self._ground_alt_m = math.nan

    @property
    def start_pending(self) -> bool:
        """Armed, but no FC time known yet for the start of the flight."""
        return self.armed and not math.isfinite(self.start_fc_s)

    def on_time(self, t_fc_s: float) -> FlightStarted | None:
        """The newest known FC time: starts a flight armed before any time was known."""
        if self.start_pending and math.isfinite(t_fc_s):
            self.start_fc_s = float(t_fc_s)
            return FlightStarted(self.flight, self.start_fc_s)
        return None

    def on_heartbeat(self, armed: bool, t_fc_s: float) -> FlightStarted | FlightEnded | None:
        """Returns the transition, if any (None = no change, not a failure, or a start waiting for
        its FC time)."""
        if armed and not self.armed:
            self.armed = True
            self.flight += 1
            self.start_fc_s = math.nan   # the ground altitude stays the last one seen while disarmed
            return self.on_time(t_fc_s)
        if not armed and self.armed:
            self.armed = False
            return FlightEnded(self.flight, t_fc_s, t_fc_s - self.start_fc_s)
        return None

    def on_altitude(self, up_m: float) -> None:
        """Altitude (up positive, any datum); height is relative to the value at arming."""
        if math.isnan(self._ground_alt_m) or not self.armed:
            self._ground_alt_m = up_m
        self.height_m = up_m - self._ground_alt_m

    @property
    def in_air(self) -> bool:
        if not self.armed:
            return False
        if self.landed_state is not None and self.landed_state != 0:
            return self.landed_state in (2, 3, 4)
        return bool(self.height_m > self.in_air_alt_m)


# --------------------------------------------------------------------------------------------
# Windows and rates
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Window:
    """One sliding window (rows oldest first).

    ``smoothed`` rows newer than the filter latency are NaN (not final yet). ``t_host_last_s`` is the
    host receive time of the packet that completed the newest row (for latency).
    """

    seq: int
    flight: int | None
    t_fc_s: np.ndarray          # (n,)
    inputs: np.ndarray          # (n, 4)
    outputs_raw: np.ndarray     # (n, 8)
    outputs_smoothed: np.ndarray  # (n, 8)
    alt_m: np.ndarray           # (n,)
    t_host_last_s: float
    in_air: bool
    armed: bool

    def to_json(self, vehicle: str) -> dict:
        """JSON-able dict; values rounded to 6 decimals, NaN kept (the publisher writes them as null)."""
        def col(a: np.ndarray) -> list[float]:
            return np.round(a, 6).tolist()

        return {
            "vehicle": vehicle, "seq": self.seq, "flight": self.flight,
            "armed": self.armed, "in_air": self.in_air,
            "t_fc_s": np.round(self.t_fc_s, 4).tolist(),
            "t_host_last_s": self.t_host_last_s,
            "inputs": {n: col(self.inputs[:, i]) for i, n in enumerate(INPUTS)},
            "outputs": {n: {"raw": col(self.outputs_raw[:, i]), "smoothed": col(self.outputs_smoothed[:, i])}
                        for i, n in enumerate(OUTPUTS)},
            "alt_m": col(self.alt_m),
        }


class WindowBuffer:
    """Ring buffer of grid rows; :meth:`append` returns a :class:`Window` every ``hop`` rows."""

    def __init__(self, length: int, hop: int) -> None:
        if length < 1 or not 1 <= hop <= length:
            raise DspError(f"window length {length} / hop {hop}: need 1 <= hop <= length")
        self.length = length
        self.hop = hop
        self._t = np.full(length, np.nan)
        self._in = np.full((length, 4), np.nan)
        self._raw = np.full((length, 8), np.nan)
        self._sm = np.full((length, 8), np.nan)
        self._alt = np.full(length, np.nan)
        self._n = 0          # rows appended so far
        self._since = 0
        self._seq = 0

    def append(self, t_fc_s: float, inputs: np.ndarray, raw: np.ndarray, alt_m: float) -> None:
        i = self._n % self.length
        self._t[i] = t_fc_s
        self._in[i] = inputs
        self._raw[i] = raw
        self._sm[i] = np.nan
        self._alt[i] = alt_m
        self._n += 1
        self._since += 1

    def set_smoothed(self, back: int, row: np.ndarray) -> None:
        """Set the smoothed value of the row ``back`` rows before the newest (0 = newest)."""
        if back < self.length and back < self._n:
            self._sm[(self._n - 1 - back) % self.length] = row

    def due(self) -> bool:
        return self._since >= self.hop and self._n > 0

    def take(self, *, flight: int | None, t_host_last_s: float, in_air: bool, armed: bool) -> Window:
        n = min(self._n, self.length)
        idx = (np.arange(self._n - n, self._n)) % self.length
        self._since = 0
        w = Window(self._seq, flight, self._t[idx].copy(), self._in[idx].copy(), self._raw[idx].copy(),
                   self._sm[idx].copy(), self._alt[idx].copy(), t_host_last_s, in_air, armed)
        self._seq += 1
        return w


class RateMeter:
    """Message rates (Hz) over the last ``window_s`` seconds of host time (``now`` passed in)."""

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s = window_s
        self._times: dict[str, deque[float]] = {}

    def add(self, name: str, now: float) -> None:
        d = self._times.get(name)
        if d is None:
            d = self._times[name] = deque()
        d.append(now)

    def rates(self, now: float) -> dict[str, float]:
        out = {}
        for name, d in self._times.items():
            while d and d[0] < now - self.window_s:
                d.popleft()
            out[name] = round(len(d) / self.window_s, 2)
        return out


# --------------------------------------------------------------------------------------------
# The whole live path
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LiveConfig:
    grid_rate_hz: float = 50.0
    smoothing_passes: int = 1
    window_s: float = 4.0
    hop_s: float = 0.5
    stale_s: float = 0.5
    in_air_alt_m: float = 0.5                                  # as dsp.prepare.PrepConfig
    servo_numbers: tuple[int, int, int, int] = (1, 2, 3, 4)   # 1-based SERVO_OUTPUT_RAW channels
    trim_pwm: tuple[float, float, float, float] = (1500.0, 1500.0, 1500.0, 1500.0)
    pwm_per_unit: float = 500.0


@dataclass
class LiveOutput:
    """What one :meth:`LivePipeline.feed` produced."""

    t_fc_s: np.ndarray = field(default_factory=lambda: np.empty(0))
    t_host_s: np.ndarray = field(default_factory=lambda: np.empty(0))
    inputs: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    outputs_raw: np.ndarray = field(default_factory=lambda: np.empty((0, 8)))
    # (n, 8) bool: False where an output row only bridges a hole of the link (a straight line between
    # samples further apart than ordinary sampling) or its stream is silent
    outputs_measured: np.ndarray = field(default_factory=lambda: np.empty((0, 8), dtype=bool))
    # smoothed rows that became final, with their own times (they lag t_fc_s by the filter latency)
    t_smoothed_s: np.ndarray = field(default_factory=lambda: np.empty(0))
    t_host_smoothed_s: np.ndarray = field(default_factory=lambda: np.empty(0))
    outputs_smoothed: np.ndarray = field(default_factory=lambda: np.empty((0, 8)))
    windows: list[Window] = field(default_factory=list)
    flight_events: list[FlightStarted | FlightEnded] = field(default_factory=list)


class LivePipeline:
    """Typed samples in, grid rows / smoothed rows / windows / flight transitions out."""

    def __init__(self, config: LiveConfig | None = None) -> None:
        self.config = cfg = config or LiveConfig()
        self.aligner = GridAligner(cfg.grid_rate_hz, {
            "att": (6, True),      # roll pitch yaw p q r
            "servo": (4, True),    # lat lon col ped pwm
            "lpn": (4, True),      # z vn ve vd
            "gpi": (4, False),     # relative_alt vn ve vd (fallback)
        }, stale_s=cfg.stale_s, max_gap_s=max(1.0, 2 * cfg.stale_s))
        self.smoother = CausalSmoother(8, cfg.smoothing_passes)
        length = max(5, int(round(cfg.window_s * cfg.grid_rate_hz)))
        hop = max(1, int(round(cfg.hop_s * cfg.grid_rate_hz)))
        self.windows = WindowBuffer(length, hop)
        self.flights = FlightTracker(cfg.in_air_alt_m)
        self._servo_idx = tuple(s - 1 for s in cfg.servo_numbers)
        self._trim = np.asarray(cfg.trim_pwm, dtype=float)
        self._smooth_pending: deque[tuple[float, float]] = deque()   # (t_fc, t_host) not yet smoothed
        self._last_host_s = math.nan
        self.rows = 0

    def set_trim(self, trim_pwm: tuple[float, float, float, float]) -> None:
        """Change the input trim (PWM, lat lon col ped) used for rows from now on."""
        self._trim = np.asarray(trim_pwm, dtype=float).reshape(4)

    @property
    def trim_pwm(self) -> tuple[float, ...]:
        return tuple(float(x) for x in self._trim)

    def _flush_smoother(self, out: LiveOutput) -> None:
        rows = self.smoother.flush()
        self._emit_smoothed(rows, out)

    def _emit_smoothed(self, rows: np.ndarray, out: LiveOutput) -> None:
        if len(rows) == 0:
            return
        pairs = [self._smooth_pending.popleft() for _ in range(len(rows))]
        ts = [p[0] for p in pairs]
        # row j of `rows` belongs to grid time ts[j]; find its position back from the newest row
        pending = len(self._smooth_pending)
        for j in range(len(rows)):
            self.windows.set_smoothed(pending + len(rows) - 1 - j, rows[j])
        out.t_smoothed_s = np.concatenate([out.t_smoothed_s, ts])
        out.t_host_smoothed_s = np.concatenate([out.t_host_smoothed_s, [p[1] for p in pairs]])
        out.outputs_smoothed = np.vstack([out.outputs_smoothed, rows])

    def feed(self, events: list) -> LiveOutput:
        """Process a batch of session events (anything unknown is ignored)."""
        out = LiveOutput()
        al = self.aligner
        for ev in events:
            if isinstance(ev, Attitude):
                al.add("att", ev.t_fc_s, (ev.roll_rad, ev.pitch_rad, ev.yaw_rad, ev.p_rad_s, ev.q_rad_s,
                                          ev.r_rad_s), ev.t_host_s)
            elif isinstance(ev, ServoOutputRaw):
                pwm = ev.pwm_us
                al.add("servo", ev.t_fc_s, tuple(float(pwm[i]) if i < len(pwm) else math.nan
                                                 for i in self._servo_idx), ev.t_host_s)
            elif isinstance(ev, LocalPositionNed):
                al.add("lpn", ev.t_fc_s, (ev.z_m, ev.vx_m_s, ev.vy_m_s, ev.vz_m_s), ev.t_host_s)
                self.flights.on_altitude(-ev.z_m)
            elif isinstance(ev, GlobalPositionInt):
                al.add("gpi", ev.t_fc_s, (ev.relative_alt_m, ev.vx_m_s, ev.vy_m_s, ev.vz_m_s), ev.t_host_s)
                if not al._streams["lpn"].t:
                    self.flights.on_altitude(ev.relative_alt_m)
            elif isinstance(ev, Heartbeat):
                # HEARTBEAT has no FC time field: the newest FC time seen on the time-stamped streams
                # is a better estimate than the session's clock model early in a fast replay
                t_hb = al._newest if math.isfinite(al._newest) else ev.t_fc_s
                for tr in (self.flights.on_time(t_hb), self.flights.on_heartbeat(ev.armed, t_hb)):
                    if tr is not None:
                        out.flight_events.append(tr)
            elif isinstance(ev, ExtendedSysState):
                self.flights.landed_state = ev.landed_state
            elif isinstance(ev, FcRebooted):
                self._flush_smoother(out)
                al.reset()
            if self.flights.start_pending:
                started = self.flights.on_time(al.newest_t_fc_s)
                if started is not None:
                    out.flight_events.append(started)
            self._drain(out)
        return out

    def _drain(self, out: LiveOutput) -> None:
        t, vals, host, restarted = self.aligner.pop()
        if restarted:
            self._flush_smoother(out)
        if len(t) == 0:
            return
        al = self.aligner
        att = vals[:, al.columns("att")]
        servo = vals[:, al.columns("servo")]
        lpn = vals[:, al.columns("lpn")]
        gpi = vals[:, al.columns("gpi")]
        v_ned = np.where(np.isnan(lpn[:, 1:4]), gpi[:, 1:4], lpn[:, 1:4])
        uvw = ned_to_body(v_ned, att[:, 0], att[:, 1], att[:, 2])
        outputs = np.column_stack([uvw, att[:, 3], att[:, 4], att[:, 5], att[:, 1], att[:, 0]])
        inputs = (servo - self._trim) / self.config.pwm_per_unit
        alt = np.where(np.isnan(lpn[:, 0]), gpi[:, 0], -lpn[:, 0])
        measured = self._outputs_measured(al.measured, lpn)
        for k in range(len(t)):
            self.windows.append(t[k], inputs[k], outputs[k], alt[k])
            self._smooth_pending.append((t[k], host[k]))
            # NaN rows (a channel not measured) pass through the filter as NaN
            self._emit_smoothed(self.smoother.push(outputs[k]), out)
            if np.isfinite(host[k]):
                self._last_host_s = host[k]
            if self.windows.due():
                out.windows.append(self.windows.take(
                    flight=self.flights.flight if self.flights.armed else None,
                    t_host_last_s=float(self._last_host_s), in_air=self.flights.in_air,
                    armed=self.flights.armed))
        self.rows += len(t)
        out.t_fc_s = np.concatenate([out.t_fc_s, t])
        out.t_host_s = np.concatenate([out.t_host_s, host])
        out.inputs = np.vstack([out.inputs, inputs])
        out.outputs_raw = np.vstack([out.outputs_raw, outputs])
        out.outputs_measured = np.vstack([out.outputs_measured, measured])

    def _outputs_measured(self, m: np.ndarray, lpn: np.ndarray) -> np.ndarray:
        """(k, 8) bool of the rows' outputs from the aligner's per-column mask ``m (k, n_cols)``: the
        velocities from LOCAL_POSITION_NED where it has them, else GLOBAL_POSITION_INT (rotated by the
        attitude, so the attitude must be measured too), the rates and angles from ATTITUDE."""
        al = self.aligner
        att = np.asarray(m[:, al.columns("att")].all(axis=1))
        vel = np.where(np.isnan(lpn[:, 1:4]), m[:, al.columns("gpi")][:, 1:4], m[:, al.columns("lpn")][:, 1:4])
        uvw = np.asarray(vel.all(axis=1)) & att   # each body velocity mixes all three NED ones
        return np.column_stack([np.repeat(uvw[:, None], 3, axis=1), np.repeat(att[:, None], 5, axis=1)])
