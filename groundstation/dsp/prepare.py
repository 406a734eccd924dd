"""Offline data preparation for identification: logs -> in-air segments on a uniform FC-clock grid.

What it does, per log (:class:`firmware_interface.samples.LogData`):

1. flights = armed intervals (``LogData.flights``); in-air from EXTENDED_SYS_STATE landed_state,
   else altitude above the take-off point; the first/last ``edge_trim_s`` of each in-air interval
   are dropped (take-off and landing transients are not hover);
   where only height says "in the air", rotor vibration (accelerometers) or body motion (rates) must
   agree (:func:`airborne_evidence`): a barometer drifts, and a ground run with the rotor stopped is
   reported as one ("never left the ground") and nothing is identified from it;
2. every needed series is interpolated linearly onto a uniform grid at ``rate_hz`` on the FC clock;
   gaps no longer than ``max(max_gap_s, gap_factor * native interval)`` are ordinary sampling and
   count as measured; longer holes (packets lost on the link) up to ``max_input_bridge_s`` are
   bridged (inputs linearly, outputs too but marked *not measured* in ``Segment.measured``: they
   never count in a cost), longer holes split the segment; segments shorter than ``min_segment_s``
   are dropped. ``link_quality`` says how much was lost and bridged;
3. body velocities u v w from LOCAL_POSITION_NED vx vy vz rotated by roll/pitch/yaw
   (GLOBAL_POSITION_INT as fallback); where velocities are missing for long stretches the
   segment is split into a part with and a part without velocity channels (``available``);
   horizontal velocities without the vertical one still give u and v (w unmeasured);
   ``measured_outputs`` (the aircraft file's) drops channels the aircraft does not log;
   a horizontal velocity the attitude contradicts (``velocity_check``,
   :mod:`groundstation.dsp.velocity_check`) is left out with a note;
4. inputs ``delta = (pwm - trim) / pwm_per_unit`` (trim = median in-air PWM unless configured) from
   servo outputs or RC inputs, or unmixed from three swashplate servos (``swash_phase_deg``); when
   none of the configured inputs moves, the error names the channels of the log that do;
   output trims: theta, phi and u v w = in-air median (attitude and velocity sensors carry offsets:
   the real TREX 550 log reads 4.5 m/s down velocity on the ground), p q r = 0 (a steady hover has
   zero body rates; a gyro offset is an unmodelled effect for the diagnosis, not a trim);
5. the paper's eq. 18 smoothing (``smooth_passes``, default 1: see ``PrepConfig``) of the outputs;
   ``outputs_raw`` keeps the unsmoothed values.

Arrays: ``inputs (n, 4)`` lat lon col ped; ``outputs (n, 8)`` u v w p q r theta phi. Unavailable
output channels are NaN. Pure numpy; reading files is the caller's (``firmware_interface.readers``).
Train/validation splitting lives in :mod:`groundstation.dsp.split`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any

import numpy as np

from groundstation.dsp.bridge import bridge_limit
from groundstation.dsp.frames import ned_to_body
from groundstation.dsp.grid import (
    fill_short_holes,
    interpolate_holes,
    interpolate_onto,
    median_interval_s,
    runs,
    uniform_grid,
)
from groundstation.dsp.smoothing import smooth5
from groundstation.dsp.timeskew import shift_inputs
from groundstation.dsp.velocity_check import check_horizontal
from groundstation.errors import DspError

INPUTS: tuple[str, ...] = ("lat", "lon", "col", "ped")
OUTPUTS: tuple[str, ...] = ("u", "v", "w", "p", "q", "r", "theta", "phi")
#: MAV_LANDED_STATE values counted as airborne (IN_AIR, TAKEOFF, LANDING).
AIRBORNE_LANDED_STATES = (2, 3, 4)


@dataclass(frozen=True)
class PrepConfig:
    """Data-preparation settings (loaded from the ``[prepare]`` TOML table by the CLI).

    ``smooth_passes`` default 1 (the paper's filter once, as the live path does). Measured on a
    simulated nonlinear flight (``groundstation bench identify --passes N``): 0, 1, 2 and 4 passes
    gave mean key-parameter errors of 2.52, 2.50, 2.47 and 2.49 % and the same match on another
    flight - the windowed least-squares fit estimates the noise away, so the filter hardly matters
    at 50 Hz; more passes start to bias the fast rotor dynamics, so the default stays at one.
    """

    rate_hz: float = 50.0
    smooth_passes: int = 1
    max_gap_s: float = 0.1
    gap_factor: float = 2.5
    min_segment_s: float = 5.0
    edge_trim_s: float = 1.0
    input_source: str = "SERVO_OUTPUT_RAW"  # or "RC_CHANNELS"
    input_channels: tuple[int, int, int, int] = (1, 2, 3, 4)  # 1-based servo/RC numbers of lat lon col ped
    input_trim_pwm: tuple[float, float, float, float] | None = None
    pwm_per_unit: float = 500.0
    in_air_alt_m: float = 0.5
    ground_clearance_m: float = 0.1  # off the ground above this height (0 turns the ground-contact trim off)
    ground_ref_s: float = 1.0  # time on the ground after arming / before disarming that gives the ground level
    ground_mismatch_m: float = 1.0  # ground levels before and after further apart than this: no trim
    velocity_source: str = "auto"  # "auto", "local", "global", "none"
    #: positions (deg around the swashplate, 0 = front) of the three swashplate servos given as the first
    #: three ``input_channels``; empty = the channels carry lat lon col directly (no unmix)
    swash_phase_deg: tuple[float, ...] = ()
    #: output channels the aircraft logs; the others are treated as not measured
    measured_outputs: tuple[str, ...] = OUTPUTS
    #: airborne evidence: an in-air interval counts only where the rotor shakes the accelerometers
    #: (high-passed specific-force std above ``airborne_vibration_m_s2``) or the body rates move
    #: (std above ``airborne_rate_rad_s``); a ground run with the rotor stopped shows neither
    airborne_vibration_m_s2: float = 0.3
    airborne_rate_rad_s: float = 0.03
    #: check the horizontal velocities against the attitude (gravity tilt,
    #: :mod:`groundstation.dsp.velocity_check`) and leave out a channel that does not measure the motion
    velocity_check: bool = True
    #: longest hole in the inputs (packets lost on the link) bridged by linear interpolation, s; the
    #: outputs in the hole are bridged too but marked unmeasured (they never count in a cost); longer
    #: holes split the segment. Not set: derived from the flight's inputs and the rotor's time constant
    #: (:mod:`groundstation.dsp.bridge`: the longest hole whose straight line errs less, in what the rotor
    #: follows, than the input carries beyond the rotor's band); 0 = no bridging beyond ordinary sampling.
    #: What a bridge costs is measured by ``groundstation bench link-loss``.
    max_input_bridge_s: float | None = None
    #: the rotor's 1/tau_s (1/s) the derived bridge limit uses: the fast end of the prior (nominal + one
    #: standard deviation: the aircraft file's, else the wide prior's 10 + 6), as the rotor is not identified yet
    rotor_inv_tau_s: float = 16.0
    #: output samples within this many rotor time constants (``1 / rotor_inv_tau_s``) after a bridged
    #: input stretch are not counted either: the rotor is still following the bridge's error there
    #: (0 = only the hole itself)
    settle_after_bridge_tau: float = 3.0
    #: the logged inputs are late against the outputs by this much, s (a skew between logged channels):
    #: every segment's inputs are advanced by it (:mod:`groundstation.dsp.timeskew`); 0 = as logged
    input_shift_s: float = 0.0

    def __post_init__(self) -> None:
        if self.rate_hz <= 0:
            raise DspError(f"prepare.rate_hz must be > 0, got {self.rate_hz}")
        if self.smooth_passes < 0:
            raise DspError(f"prepare.smooth_passes must be >= 0, got {self.smooth_passes}")
        if self.pwm_per_unit == 0:
            raise DspError("prepare.pwm_per_unit must be non-zero")
        if self.input_source not in ("SERVO_OUTPUT_RAW", "RC_CHANNELS"):
            raise DspError(f"prepare.input_source must be SERVO_OUTPUT_RAW or RC_CHANNELS, got {self.input_source!r}")
        if self.velocity_source not in ("auto", "local", "global", "none"):
            raise DspError(f"prepare.velocity_source must be auto|local|global|none, got {self.velocity_source!r}")
        if len(self.input_channels) != 4:
            raise DspError("prepare.input_channels needs 4 channel numbers (lat lon col ped)")
        if self.swash_phase_deg and len(self.swash_phase_deg) != 3:
            raise DspError(f"prepare.swash_phase_deg needs 3 angles, got {self.swash_phase_deg}")
        if self.max_input_bridge_s is not None and self.max_input_bridge_s < 0:
            raise DspError(f"prepare.max_input_bridge_s must be >= 0, got {self.max_input_bridge_s}")
        if not self.settle_after_bridge_tau >= 0:
            raise DspError(f"prepare.settle_after_bridge_tau must be >= 0, got {self.settle_after_bridge_tau}")
        if not self.rotor_inv_tau_s > 0:
            raise DspError(f"prepare.rotor_inv_tau_s must be > 0, got {self.rotor_inv_tau_s}")
        if not abs(self.input_shift_s) < 1.0:
            raise DspError(f"prepare.input_shift_s must be within +-1 s (a skew between logged channels), got {self.input_shift_s}")
        bad = [c for c in self.measured_outputs if c not in OUTPUTS]
        if bad:
            raise DspError(f"prepare.measured_outputs: unknown channel(s) {bad} (allowed: {', '.join(OUTPUTS)})")


@dataclass(frozen=True, eq=False)
class Segment:
    """One contiguous in-air stretch on the uniform grid.

    Attributes
    ----------
    t_s : (n,) FC-clock time, s, uniform
    inputs : (n, 4) normalised lat lon col ped, trim removed
    outputs : (n, 8) u v w (m/s) p q r (rad/s) theta phi (rad), smoothed, trim removed; NaN if unavailable
    outputs_raw : (n, 8) the same unsmoothed
    alt_m : (n,) height above the take-off point (NaN if unknown)
    available : (8,) bool, channel measured in this segment
    flight : flight index within its log
    source : log name
    measured : (n, 8) bool or None; False where the sample lies in a hole of the link (bridged, not
        measured: a cost must not count it); None = every sample of the available channels measured
    inputs_bridged : (n,) bool or None; True where the inputs are a straight line over a hole of the
        link; None = no input sample bridged
    settling : (n, 8) bool or None; True where a sample was measured but is left out of ``measured``
        while the rotor settles after a bridged input (``settle_after_bridge_tau``): an analysis that
        estimates the inputs inside the holes may count it again; None = no such sample
    """

    t_s: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray
    outputs_raw: np.ndarray
    alt_m: np.ndarray
    available: np.ndarray
    flight: int
    source: str
    measured: np.ndarray | None = None
    inputs_bridged: np.ndarray | None = None
    settling: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0]) if self.n else 0.0

    def measured_mask(self) -> np.ndarray:
        """(n, 8) bool: the channel is available and the sample was measured (not bridged)."""
        m = np.broadcast_to(np.asarray(self.available, dtype=bool), (self.n, 8))
        return m & self.measured if self.measured is not None else m.copy()


@dataclass(frozen=True, eq=False)
class PreparedData:
    """Segments of one or more logs with the trims used (see module docstring)."""

    segments: list[Segment]
    dt_s: float
    input_trim_pwm: dict[str, float]
    pwm_per_unit: float
    output_trim: dict[str, float]
    notes: list[str] = field(default_factory=list)
    #: median sample interval (s) of the message each channel was resampled from (lat..ped, u..phi);
    #: empty when unknown (arrays made on the grid). A channel sent slower than the grid is
    #: interpolated, so its noise on the grid is not white: the diagnosis' noise floors use this.
    native_interval_s: dict[str, float] = field(default_factory=dict)
    #: what the link lost and what preparation did about it (:class:`LinkQuality` as a dict); empty
    #: when unknown (arrays made on the grid)
    link_quality: dict[str, Any] = field(default_factory=dict)

    def native_stride(self, names: tuple[str, ...]) -> np.ndarray:
        """Source interval over grid step per channel (1 where unknown or faster than the grid)."""
        st = [self.native_interval_s.get(n, float("nan")) / self.dt_s for n in names]
        return np.array([s if np.isfinite(s) and s > 1.0 else 1.0 for s in st])

    @property
    def available(self) -> np.ndarray:
        """(8,) channel measured in at least one segment."""
        if not self.segments:
            return np.zeros(8, dtype=bool)
        return np.any([s.available for s in self.segments], axis=0)

    @property
    def input_active(self) -> np.ndarray:
        """(4,) input channel moves at all (std above 1e-4 units) in some segment."""
        if not self.segments:
            return np.zeros(4, dtype=bool)
        return np.any([np.nanstd(s.inputs, axis=0) > 1e-4 for s in self.segments], axis=0)

    @property
    def duration_s(self) -> float:
        return float(sum(s.n for s in self.segments) * self.dt_s)

    def subset(self, indices: list[int]) -> PreparedData:
        """The same trims with only the chosen segments."""
        return replace(self, segments=[self.segments[i] for i in indices], notes=list(self.notes))


@dataclass
class _Raw:
    """A segment before trims: raw PWM and physical outputs."""

    t_s: np.ndarray
    pwm: np.ndarray  # (n, 4)
    outputs: np.ndarray  # (n, 8) NaN where unavailable
    alt_m: np.ndarray
    available: np.ndarray
    flight: int
    source: str
    native_s: np.ndarray  # (12,) median source sample interval of lat lon col ped u v w p q r theta phi
    measured: np.ndarray  # (n, 8) output sample measured (not bridged over a hole)
    bridged: np.ndarray  # (n,) input sample bridged over a hole
    settling: np.ndarray  # (n, 8) measured, but left out while the rotor settles after a bridged input


def _series_gap(cfg: PrepConfig, t_src: np.ndarray) -> float:
    return max(cfg.max_gap_s, cfg.gap_factor * median_interval_s(t_src))


def _in_air_intervals(log: Any, flight: Any, cfg: PrepConfig) -> list[tuple[float, float]]:
    given = list(getattr(flight, "in_air_intervals_fc_s", ()) or ())
    if given:
        return [(float(a), float(b)) for a, b in given]
    a, b = float(flight.start_fc_s), float(flight.end_fc_s)
    if log.has("EXTENDED_SYS_STATE"):
        s = log.series["EXTENDED_SYS_STATE"]
        sel = (s.t_fc_s >= a) & (s.t_fc_s <= b)
        if sel.any():
            air = np.isin(np.asarray(s["landed_state"])[sel], AIRBORNE_LANDED_STATES)
            t = s.t_fc_s[sel]
            out = []
            for i, j in runs(air):
                out.append((float(t[i]), float(t[j - 1]) if j - 1 > i else float(t[i])))
            return out
    alt_t, alt = _altitude(log, a, b)
    if alt_t is None:
        # no way to tell: the whole armed interval counts as in the air
        return [(a, b)]
    air = alt > cfg.in_air_alt_m
    return [(float(alt_t[i]), float(alt_t[j - 1])) for i, j in runs(air) if j - 1 > i]


def _trim_ground_contact(log: Any, flight: Any, intervals: list[tuple[float, float]], cfg: PrepConfig,
                         notes: list[str]) -> list[tuple[float, float]]:
    """Shrink in-air intervals to where the aircraft is off the ground by its own height.

    A land detector declares "landed" some time after touchdown (ArduPilot waits for low throttle
    and no motion), and meanwhile the skids sit on the ground with the collective lowered: a hover model fitted or scored there sees a large collective step and no
    vertical motion. The ground level is the median height over the first ``ground_ref_s`` of
    the armed time before take-off and the last ``ground_ref_s`` after landing (linear in between,
    so a slow barometric drift is followed); the interval ends move inwards to the first and last
    sample at least ``ground_clearance_m`` (or four ground-noise standard deviations, if larger)
    above it. Nothing is trimmed where no reference is there, where the two disagree by more
    than ``ground_mismatch_m`` (that is not one ground), or where the height never clears it.
    """
    if cfg.ground_clearance_m <= 0 or not intervals:
        return intervals
    alt_t, h = _altitude(log, float(flight.start_fc_s), float(flight.end_fc_s))
    if alt_t is None or h.size < 4:
        return intervals
    out = []
    t_arm, t_disarm = float(flight.start_fc_s), float(flight.end_fc_s)
    for a, b in intervals:
        pre = (alt_t >= t_arm) & (alt_t < min(a, t_arm + cfg.ground_ref_s))
        post = (alt_t > max(b, t_disarm - cfg.ground_ref_s)) & (alt_t <= t_disarm)
        ends = [float(np.median(h[sel])) if sel.sum() >= 3 else None for sel in (pre, post)]
        if (ends[0] is None and ends[1] is None) or (
                ends[0] is not None and ends[1] is not None and abs(ends[1] - ends[0]) > cfg.ground_mismatch_m):
            out.append((a, b))
            continue
        known = [e for e in ends if e is not None]
        g0 = ends[0] if ends[0] is not None else known[0]
        g1 = ends[1] if ends[1] is not None else known[0]
        noise = [np.std(h[sel] - np.median(h[sel])) for sel, e in zip((pre, post), ends, strict=True) if e is not None]
        clear = max(cfg.ground_clearance_m, 4.0 * float(max(noise)))
        inside = (alt_t >= a) & (alt_t <= b)
        ti, hi = alt_t[inside], h[inside]
        if ti.size < 2:
            out.append((a, b))
            continue
        ground = g0 + (g1 - g0) * (ti - a) / max(b - a, 1e-9)
        up = np.flatnonzero(hi - ground > clear)
        if up.size == 0:
            notes.append(f"{log.source}: height never clears the ground by {clear:.2f} m in flight "
                         f"{getattr(flight, 'index', 0)}: in-air interval kept as the land detector gave it")
            out.append((a, b))
            continue
        a2 = float(ti[up[0]]) if ends[0] is not None else a
        b2 = float(ti[up[-1]]) if ends[1] is not None else b
        out.append((a2, b2))  # both inside [a, b]: only ever shrinks
    return out


def _altitude(log: Any, a: float, b: float) -> tuple[np.ndarray | None, np.ndarray]:
    """Height above the value at the flight start from LOCAL_POSITION_NED z or GLOBAL relative_alt."""
    for name, col, sign in (("LOCAL_POSITION_NED", "z_m", -1.0), ("GLOBAL_POSITION_INT", "relative_alt_m", 1.0)):
        if log.has(name):
            s = log.series[name]
            sel = (s.t_fc_s >= a) & (s.t_fc_s <= b) & np.isfinite(np.asarray(s[col], dtype=float))
            if sel.sum() >= 2:
                h = sign * np.asarray(s[col], dtype=float)[sel]
                return s.t_fc_s[sel], h - h[0]
    return None, np.zeros(0)


def _channel_values(series: Any, col: str, pwm_units: bool) -> np.ndarray:
    v = np.asarray(series[col], dtype=float).copy()
    if pwm_units:
        v[(v <= 0) | (v >= 65535)] = np.nan  # 0 / 65535 mean "not set"
    return v


def _input_pwm(log: Any, cfg: PrepConfig) -> np.ndarray:
    """(n, 4) lat lon col ped in the source's units on the source's clock (the swashplate unmixed).

    A channel the source message does not carry (a column missing or never set) raises naming it.
    Swashplate: servo i at angle phi_i moves ``col + lon cos(phi_i) + lat sin(phi_i)`` about its
    centre, so the three servos give col, lon, lat by one 3 x 3 solve (about the servos' mean centre).
    """
    src = log.source
    servo = log.series[cfg.input_source]
    pwm_units = abs(cfg.pwm_per_unit) > 2.0
    cols = []
    for c in cfg.input_channels:
        col = f"pwm_us_{c}"
        if col not in servo.columns:
            raise DspError(f"{src}: {cfg.input_source} has no channel {c} (input channel map)")
        v = _channel_values(servo, col, pwm_units)
        if not np.isfinite(v).any():
            raise DspError(f"{src}: {cfg.input_source} channel {c} is never set in this log (input channel map)")
        cols.append(v)
    pwm = np.stack(cols, axis=1)
    if cfg.swash_phase_deg:
        ph = np.radians(np.asarray(cfg.swash_phase_deg, dtype=float))
        M = np.stack([np.ones(3), np.cos(ph), np.sin(ph)], axis=1)  # servo = M @ (col, lon, lat)
        centre = np.nanmedian(pwm[:, :3])
        col_lon_lat = np.linalg.solve(M, (pwm[:, :3] - centre).T).T
        pwm = np.stack([centre + col_lon_lat[:, 2], centre + col_lon_lat[:, 1], centre + col_lon_lat[:, 0],
                        pwm[:, 3]], axis=1)
    return pwm


def moving_channels(log: Any, min_std: float) -> list[str]:
    """Servo-output and RC channels of ``log`` whose values move (std above ``min_std``), as "MSG n"."""
    out = []
    for msg in ("SERVO_OUTPUT_RAW", "RC_CHANNELS"):
        if not log.has(msg):
            continue
        s = log.series[msg]
        for c in sorted(s.columns, key=lambda k: int(k.rsplit("_", 1)[-1])):
            v = np.asarray(s[c], dtype=float)
            v = v[np.isfinite(v) & (v != 0) & (v < 65535)]
            if v.size > 10 and float(np.std(v)) > min_std:
                out.append(f"{msg} {c.rsplit('_', 1)[-1]}")
    return out


def _land_detector(log: Any, flight: Any) -> bool:
    """The FC's land detector (EXTENDED_SYS_STATE landed_state) speaks for this flight."""
    if not log.has("EXTENDED_SYS_STATE"):
        return False
    s = log.series["EXTENDED_SYS_STATE"]
    sel = (s.t_fc_s >= float(flight.start_fc_s)) & (s.t_fc_s <= float(flight.end_fc_s))
    return bool(np.any(np.asarray(s["landed_state"])[sel] > 0))


def airborne_evidence(log: Any, a: float, b: float, cfg: PrepConfig) -> tuple[bool, str]:
    """Whether the aircraft flew in [a, b] by evidence other than height (asked where no land detector
    speaks, i.e. the in-air time comes from height alone): rotor vibration on the
    accelerometers (std of the specific force after removing a 0.5-s running mean, above
    ``airborne_vibration_m_s2``) or body motion (std of the body rates above ``airborne_rate_rad_s``).
    Returns (flying, one-line evidence). Without IMU and rates the answer is yes (nothing to contradict)."""
    parts = []
    flying = False
    known = False
    if log.has("IMU"):
        s = log.series["IMU"]
        sel = (s.t_fc_s >= a) & (s.t_fc_s <= b)
        if sel.sum() > 20:
            known = True
            acc = np.stack([np.asarray(s[c], dtype=float)[sel] for c in ("ax_m_s2", "ay_m_s2", "az_m_s2")], axis=1)
            if np.isfinite(acc).all():
                k = max(3, int(0.5 / max(median_interval_s(s.t_fc_s[sel]), 1e-3)))
                kern = np.ones(k) / k
                hp = np.stack([acc[:, j] - np.convolve(acc[:, j], kern, mode="same") for j in range(acc.shape[1])], axis=1)
                vib = float(np.nanmax(np.nanstd(hp[k:-k] if hp.shape[0] > 2 * k + 2 else hp, axis=0)))
                flying |= vib > cfg.airborne_vibration_m_s2
                parts.append(f"accelerometer vibration std {vib:.3f} m/s^2")
    if log.has("ATTITUDE"):
        s = log.series["ATTITUDE"]
        sel = (s.t_fc_s >= a) & (s.t_fc_s <= b)
        rates = np.stack([np.asarray(s[c], dtype=float)[sel] for c in ("p_rad_s", "q_rad_s", "r_rad_s")], axis=1)
        if np.isfinite(rates).sum() > 20:
            known = True
            rs = float(np.nanmax(np.nanstd(rates, axis=0)))
            flying |= rs > cfg.airborne_rate_rad_s
            parts.append(f"body-rate std {rs:.3f} rad/s")
    return flying or not known, ", ".join(parts)


def _raw_segments(log: Any, cfg: PrepConfig, notes: list[str], holes: list[float] | None = None) -> list[_Raw]:
    src = log.source
    if not log.has(cfg.input_source):
        raise DspError(f"{src}: no {cfg.input_source} messages (servo outputs needed for the inputs lat lon col ped)")
    if not log.has("ATTITUDE"):
        raise DspError(f"{src}: no ATTITUDE messages (attitude and body rates needed for the outputs)")
    flights = list(log.flights)
    if not flights:
        if log.has("HEARTBEAT"):
            raise DspError(f"{src}: the vehicle was never armed (no flight in HEARTBEAT base_mode)")

        att = log.series["ATTITUDE"]
        flights = [SimpleNamespace(index=0, start_fc_s=float(att.t_fc_s[0]), end_fc_s=float(att.t_fc_s[-1]),
                                   in_air_intervals_fc_s=())]
        notes.append(f"{src}: no HEARTBEAT, whole log treated as one flight")
    servo = log.series[cfg.input_source]
    att = log.series["ATTITUDE"]
    pwm_src = _input_pwm(log, cfg)
    att_cols = ("roll_rad", "pitch_rad", "yaw_rad", "p_rad_s", "q_rad_s", "r_rad_s")
    att_src = np.stack([np.asarray(att[c], dtype=float) for c in att_cols], axis=1)
    yaw_unwrapped = np.unwrap(np.nan_to_num(att_src[:, 2]))
    att_src[:, 2] = np.where(np.isfinite(att_src[:, 2]), yaw_unwrapped, np.nan)

    vel_series = None
    if cfg.velocity_source in ("auto", "local") and log.has("LOCAL_POSITION_NED"):
        vel_series = ("LOCAL_POSITION_NED", log.series["LOCAL_POSITION_NED"])
    elif cfg.velocity_source in ("auto", "global") and log.has("GLOBAL_POSITION_INT"):
        vel_series = ("GLOBAL_POSITION_INT", log.series["GLOBAL_POSITION_INT"])
    if vel_series is None and cfg.velocity_source != "none":
        notes.append(f"{src}: no LOCAL_POSITION_NED or GLOBAL_POSITION_INT: u v w unavailable")

    vel_dt = median_interval_s(vel_series[1].t_fc_s) if vel_series is not None else float("nan")
    att_dt = median_interval_s(att.t_fc_s)
    native_s = np.array([median_interval_s(servo.t_fc_s)] * 4 + [max(vel_dt, att_dt)] * 3 + [att_dt] * 5)
    out: list[_Raw] = []
    n_air = 0
    ground: list[str] = []
    for fl in flights:
        intervals = _trim_ground_contact(log, fl, _in_air_intervals(log, fl, cfg), cfg, notes)
        for a, b in intervals:
            a2, b2 = a + cfg.edge_trim_s, b - cfg.edge_trim_s
            if b2 - a2 < cfg.min_segment_s:
                continue
            flying, evidence = (True, "") if _land_detector(log, fl) else airborne_evidence(log, a2, b2, cfg)
            if not flying:
                ground.append(f"{a2:.0f}-{b2:.0f} s ({evidence})")
                continue
            n_air += 1
            t = uniform_grid(a2, b2, cfg.rate_hz)
            if holes is not None:
                ts = servo.t_fc_s[(servo.t_fc_s >= a2) & (servo.t_fc_s <= b2)]
                d = np.diff(ts)
                holes += d[d > _series_gap(cfg, servo.t_fc_s)].tolist()
            pwm, pwm_ok = interpolate_onto(servo.t_fc_s, pwm_src, t, _bridge(cfg, servo.t_fc_s))
            at, at_ok = interpolate_onto(att.t_fc_s, att_src, t, _bridge(cfg, att.t_fc_s))
            _, pwm_meas = interpolate_onto(servo.t_fc_s, pwm_src, t, _series_gap(cfg, servo.t_fc_s))
            _, at_meas = interpolate_onto(att.t_fc_s, att_src, t, _series_gap(cfg, att.t_fc_s))
            req = np.asarray(pwm_ok.all(axis=1) & at_ok.all(axis=1), dtype=bool)
            vel, hor_ok, ver_ok, vel_meas = _velocities(vel_series, t, cfg)
            meas = np.zeros((t.size, 8), dtype=bool)
            att_m = np.asarray(at_meas.all(axis=1), dtype=bool)
            vel_meas = np.asarray(vel_meas, dtype=bool)
            meas[:, 3:] = att_m[:, None]
            meas[:, 0:2] = (vel_meas[:, :2].all(axis=1) & att_m)[:, None]
            meas[:, 2] = vel_meas.all(axis=1) & att_m
            bridged = ~np.asarray(pwm_meas.all(axis=1), dtype=bool)
            settling = meas & _settling(bridged, cfg)[:, None]
            meas &= ~settling
            alt_t, alt = _altitude(log, float(fl.start_fc_s), float(fl.end_fc_s))
            if alt_t is not None:
                alt_g, _ = interpolate_onto(alt_t, alt, t, _bridge(cfg, alt_t))
            else:
                alt_g = np.full(t.size, np.nan)
            for sl, lab in _labelled_runs(req, hor_ok & req, ver_ok & hor_ok & req, cfg):
                outputs, avail = _segment_outputs(at[sl], vel[sl], lab, cfg)
                out.append(_Raw(t_s=t[sl], pwm=pwm[sl], outputs=outputs, alt_m=alt_g[sl], available=avail,
                                flight=int(fl.index), source=src, native_s=native_s, measured=meas[sl],
                                bridged=bridged[sl], settling=settling[sl]))
    if n_air == 0 and ground:
        raise DspError(f"{src}: the aircraft never left the ground, nothing to identify: in-air time from "
                         f"height alone, but no rotor vibration and no body motion: {'; '.join(ground)}")
    for g in ground:
        notes.append(f"{src}: {g}: on the ground by rotor and motion evidence, left out")
    if n_air == 0:
        raise DspError(
            f"{src}: never in the air for at least {cfg.min_segment_s:g} s "
            f"(no in-air segment from EXTENDED_SYS_STATE landed_state or altitude within the armed flights)"
        )
    return out


def _settling(bridged: np.ndarray, cfg: PrepConfig) -> np.ndarray:
    """(n,) samples within ``settle_after_bridge_tau`` rotor time constants after a bridged input stretch.

    The model is driven by the straight line over the hole; its error goes on moving the rotor (a
    first-order lag of ``tau_s``) after the hole: after three time constants the flapping has
    followed 95 % of it. Measured on 120-s flights at 10 % bursty loss (seeds 5-8), leaving those
    samples out of the cost kept 1 more key parameter within 10 % on three of four flights."""
    n = int(np.ceil(cfg.settle_after_bridge_tau * cfg.rate_hz / cfg.rotor_inv_tau_s - 1e-9))
    out = np.zeros_like(bridged)
    for k in range(1, min(n, bridged.size - 1) + 1):
        out[k:] |= bridged[:-k]
    return out & ~bridged


def _bridge(cfg: PrepConfig, t_src: np.ndarray) -> float:
    """Longest source interval bridged on the grid: ordinary sampling or a hole up to ``max_input_bridge_s``."""
    return max(_series_gap(cfg, t_src), cfg.max_input_bridge_s or 0.0)


#: the bridge limit when the flight has too little input without holes to derive one (s): what the
#: link-loss benchmark measured harmless at up to 20 % bursty loss
FALLBACK_BRIDGE_S = 0.35


def derive_bridge(logs: list[Any], cfg: PrepConfig) -> dict[str, Any]:
    """The bridge limit the preparation uses and why: ``limit_s``, ``rule`` (``configured``,
    ``derived`` from the inputs and the rotor, or ``fallback`` when too little input without holes),
    and for a derived one each input's limit, the rotor's 1/tau_s and the seconds measured."""
    if cfg.max_input_bridge_s is not None:
        return {"limit_s": float(cfg.max_input_bridge_s), "rule": "configured"}

    found = []
    for log in logs:
        if not log.has(cfg.input_source):
            continue
        try:
            pwm = _input_pwm(log, cfg)
        except DspError:
            continue
        t = log.series[cfg.input_source].t_fc_s
        iv = [ab for fl in log.flights for ab in _in_air_intervals(log, fl, cfg)]
        x = (pwm - np.nanmedian(pwm, axis=0)) / cfg.pwm_per_unit
        b = bridge_limit(t, x, iv, _series_gap(cfg, t), cfg.rotor_inv_tau_s)
        if b.limit_s is not None:
            found.append(b)
    if not found:
        return {"limit_s": FALLBACK_BRIDGE_S, "rule": "fallback", "rotor_inv_tau_s": cfg.rotor_inv_tau_s}
    best = min(found, key=lambda b: b.limit_s or 0.0)
    return {"rule": "derived", **best.to_json()}


def _velocities(vel_series: Any, t: np.ndarray,
                cfg: PrepConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """NED velocities (n, 3) on the grid, where the horizontal pair and the vertical one are valid
    (short holes filled, holes of the link bridged) and where each was measured (n, 3)."""
    vel = np.full((t.size, 3), np.nan)
    if vel_series is None:
        z = np.zeros(t.size, dtype=bool)
        return vel, z, z, np.zeros((t.size, 3), dtype=bool)
    vs = vel_series[1]
    vsrc = np.stack([np.asarray(vs[c], dtype=float) for c in ("vx_m_s", "vy_m_s", "vz_m_s")], axis=1)
    vel, vok = interpolate_onto(vs.t_fc_s, vsrc, t, _bridge(cfg, vs.t_fc_s))
    _, vmeas = interpolate_onto(vs.t_fc_s, vsrc, t, _series_gap(cfg, vs.t_fc_s))
    max_hole = max(1, int(round(cfg.max_gap_s * cfg.rate_hz)))
    hor = fill_short_holes(np.asarray(vok[:, :2].all(axis=1), dtype=bool), max_hole)
    ver = fill_short_holes(np.asarray(vok[:, 2], dtype=bool), max_hole)
    return vel, hor, ver, np.asarray(vmeas, dtype=bool)


def _labelled_runs(req: np.ndarray, hor: np.ndarray, ver: np.ndarray, cfg: PrepConfig) -> list[tuple[slice, int]]:
    """Contiguous stretches of at least ``min_segment_s`` with one label: 1 inputs and attitude,
    2 also horizontal velocities, 3 also the vertical one (a label's runs shorter than a segment
    fall back to the label below)."""
    min_n = int(np.ceil(cfg.min_segment_s * cfg.rate_hz))
    label = np.where(req, 1 + hor.astype(int) + (hor & ver).astype(int), 0)
    for lev in (3, 2):
        for i, j in runs(label >= lev):
            if j - i < min_n:
                label[i:j] = np.minimum(label[i:j], lev - 1)
    out = []
    for i, j in runs(req):
        if j - i < min_n:
            continue
        sub = label[i:j]
        edges = np.concatenate([[0], np.flatnonzero(np.diff(sub)) + 1, [j - i]])
        out += [(slice(i + p0, i + p1), int(sub[p0])) for p0, p1 in zip(edges[:-1], edges[1:], strict=True)
                if p1 - p0 >= min_n]
    return out


def _segment_outputs(at: np.ndarray, vel: np.ndarray, label: int, cfg: PrepConfig) -> tuple[np.ndarray, np.ndarray]:
    """Outputs (n, 8) and availability (8,) of one stretch. Without the vertical velocity, u and v
    come from the horizontal pair with the vertical one taken as zero: its share in body u, v is
    its product with the sine of the attitude (a few per cent at hover attitudes)."""
    outputs = np.full((at.shape[0], 8), np.nan)
    avail = np.zeros(8, dtype=bool)
    roll, pitch, yaw = at[:, 0], at[:, 1], at[:, 2]
    outputs[:, 3:6] = at[:, 3:6]
    outputs[:, 6] = pitch
    outputs[:, 7] = roll
    avail[3:] = True
    if label >= 2:
        v = vel.copy()
        if label == 2:
            v[:, 2] = 0.0
        v = interpolate_holes(v, np.isfinite(v))
        outputs[:, 0:3] = ned_to_body(v, roll, pitch, yaw)
        avail[0:2] = True
        avail[2] = label == 3
    keep = np.array([c in cfg.measured_outputs for c in OUTPUTS])
    avail &= keep
    outputs[:, ~avail] = np.nan
    return outputs, avail


def _still_inputs_message(logs: list[Any], cfg: PrepConfig) -> str:
    chans = ", ".join(str(c) for c in cfg.input_channels)
    moving = sorted({m for log in logs for m in moving_channels(log, 1e-3 * max(abs(cfg.pwm_per_unit), 1.0))})
    where = f"channels that move in the log: {', '.join(moving)}" if moving else "no servo or RC channel moves in the log"
    return (f"{', '.join(log.source for log in logs)}: the configured inputs ({cfg.input_source} {chans}) never move "
            f"in the air; {where} (set [inputs] source and channels in the aircraft file)")


def prepare(logs: list[Any], config: PrepConfig | None = None) -> PreparedData:
    """Turn logs into trimmed, smoothed in-air segments (see module docstring).

    Raises DspError (a ValueError) with one line naming the log and the missing message or segment.
    """
    cfg = config or PrepConfig()
    if not logs:
        raise DspError("no logs given")
    notes: list[str] = []
    raws: list[_Raw] = []
    holes: list[float] = []
    bridge = derive_bridge(logs, cfg)
    cfg = replace(cfg, max_input_bridge_s=bridge["limit_s"])
    for log in logs:
        got = _raw_segments(log, cfg, notes, holes)
        if not got:
            raise DspError(
                f"{log.source}: no in-air segment of at least {cfg.min_segment_s:g} s with servo outputs and attitude "
                f"(gaps longer than {cfg.max_gap_s:g} s split segments)"
            )
        raws.extend(got)
    pwm_all = np.concatenate([r.pwm for r in raws], axis=0)
    if cfg.input_trim_pwm is not None:
        trim_pwm = np.asarray(cfg.input_trim_pwm, dtype=float)
    else:
        trim_pwm = np.nanmedian(pwm_all, axis=0)
    out_all = np.concatenate([r.outputs for r in raws], axis=0)
    out_trim = np.zeros(8)
    for j in (0, 1, 2, 6, 7):
        col = out_all[:, j]
        col = col[np.isfinite(col)]
        if col.size:
            out_trim[j] = float(np.median(col))
    still = [np.nanstd(pwm_all[:, k]) < 1e-6 * max(abs(cfg.pwm_per_unit), 1.0) for k in range(4)]
    for k, name in enumerate(INPUTS):
        if still[k]:
            notes.append(f"input {name} never moves (held at {trim_pwm[k]:g} us): its parameters are not identifiable")
    if all(still):
        raise DspError(_still_inputs_message(logs, cfg))
    avail_any = np.any([r.available for r in raws], axis=0)
    for j, name in enumerate(OUTPUTS):
        if not avail_any[j]:
            notes.append(f"output {name} not measured in any segment")
        elif not all(r.available[j] for r in raws):
            notes.append(f"output {name} missing in part of the data")
    segs: list[Segment] = []
    for r in raws:
        inputs = (r.pwm - trim_pwm) / cfg.pwm_per_unit
        raw_out = r.outputs - out_trim
        sm = smooth5(np.nan_to_num(raw_out), cfg.smooth_passes)
        sm[:, ~r.available] = np.nan
        raw_out[:, ~r.available] = np.nan
        unmeasured = ~r.measured[:, r.available]
        segs.append(Segment(t_s=r.t_s, inputs=inputs, outputs=sm, outputs_raw=raw_out, alt_m=r.alt_m,
                            available=r.available.copy(), flight=r.flight, source=r.source,
                            measured=r.measured.copy() if unmeasured.any() else None,
                            inputs_bridged=r.bridged.copy() if r.bridged.any() else None,
                            settling=r.settling.copy() if r.settling.any() else None))
    if cfg.velocity_check:
        segs = _drop_inconsistent_velocities(segs, 1.0 / cfg.rate_hz, notes)
    lq = link_quality(logs, raws, holes, cfg)
    lq["bridge"] = bridge
    if lq["bridged_s"] > 0:
        notes.append(f"link: {lq['loss_pct']:.1f} % of packets lost, longest hole {lq['longest_gap_s']:.2f} s; "
                     f"inputs bridged over {lq['bridged_s']:.1f} s of holes up to {cfg.max_input_bridge_s:g} s "
                     f"({bridge_why(bridge)}), outputs there not counted")
    native = np.array([r.native_s for r in raws], dtype=float)
    native_med = [float(np.nanmedian(native[:, k])) if np.isfinite(native[:, k]).any() else float("nan")
                  for k in range(12)]
    return shift_inputs(PreparedData(
        segments=segs,
        dt_s=1.0 / cfg.rate_hz,
        input_trim_pwm={n: float(v) for n, v in zip(INPUTS, trim_pwm, strict=True)},
        pwm_per_unit=float(cfg.pwm_per_unit),
        output_trim={n: float(v) for n, v in zip(OUTPUTS, out_trim, strict=True)},
        notes=notes,
        native_interval_s=dict(zip(INPUTS + OUTPUTS, native_med, strict=True)),
        link_quality=lq,
    ), cfg.input_shift_s)


def bridge_why(bridge: dict[str, Any]) -> str:
    """Where the bridge limit comes from, in a few words."""
    if bridge["rule"] == "configured":
        return "prepare.max_input_bridge_s"
    if bridge["rule"] == "fallback":
        return "too little input without holes to derive it: the default"
    by = ", ".join(f"{k} {v:g}" for k, v in bridge.get("by_input_s", {}).items())
    return (f"derived: a straight line errs less, in what a rotor of 1/tau_s {bridge['rotor_inv_tau_s']:g}/s "
            f"follows, than the inputs carry beyond its band ({by} s)")


def link_quality(logs: list[Any], raws: list[_Raw], holes: list[float], cfg: PrepConfig) -> dict[str, Any]:
    """What the link lost and what preparation did with it (JSON-ready dict).

    ``loss_pct`` packets lost by the MAVLink sequence numbers (NaN when the log has none, e.g. an
    onboard log); ``in_air_holes`` holes in the inputs' stream in the air (a hole is a source interval
    longer than ordinary sampling), their median and longest length (s), ``holes_split`` how many
    were longer than ``max_input_bridge_s`` and cut the data there; ``bridged_s`` time bridged over
    holes in the kept segments, ``unmeasured_pct`` share of their output samples not measured.
    """
    lost = sum(int(getattr(getattr(lg, "stats", None), "packets_lost", 0) or 0) for lg in logs)
    got = sum(int(getattr(getattr(lg, "stats", None), "packets", 0) or 0) for lg in logs)
    loss = 100.0 * lost / (lost + got) if lost + got > 0 else float("nan")
    dt = 1.0 / cfg.rate_hz
    n_tot = n_unm = n_br = 0
    for r in raws:
        n_tot += r.t_s.size
        n_br += int(r.bridged.sum())
        m = r.measured[:, r.available]
        n_unm += int((~m).any(axis=1).sum()) if m.size else 0
    split = [h for h in holes if h > (cfg.max_input_bridge_s or 0.0) + 1e-9]
    return {"loss_pct": loss, "packets_lost": lost, "in_air_holes": len(holes), "holes_split": len(split),
            "median_gap_s": float(np.median(holes)) if holes else 0.0,
            "longest_gap_s": float(max(holes)) if holes else 0.0,
            "bridged_s": n_br * dt, "unmeasured_pct": 100.0 * n_unm / max(n_tot, 1),
            "max_input_bridge_s": cfg.max_input_bridge_s}


def _drop_inconsistent_velocities(segs: list[Segment], dt_s: float, notes: list[str]) -> list[Segment]:
    """Segments without the horizontal velocity channels the attitude contradicts, and a note for each."""
    bad = [c for c in check_horizontal(segs, dt_s) if not c.usable]
    if not bad:
        return segs
    cols = [OUTPUTS.index(c.channel) for c in bad]
    for c in bad:
        what = "height" if c.channel == "w" else "attitude"
        why = ("it does not follow the " + what if c.verdict == "contradicted"
               else "the " + what + " cannot confirm it measures the motion")
        notes.append(f"output {c.channel} left out: {why} (scale {c.scale:.2f} +- {c.se:.2f}, 1 expected; "
                     f"prepare.velocity_check = false uses it anyway)")
    out = []
    for s in segs:
        avail = s.available.copy()
        avail[cols] = False
        o, r = s.outputs.copy(), s.outputs_raw.copy()
        o[:, cols] = np.nan
        r[:, cols] = np.nan
        out.append(replace(s, available=avail, outputs=o, outputs_raw=r))
    return out


def prepared_from_arrays(
    inputs: np.ndarray, outputs: np.ndarray, dt_s: float, *, smooth_passes: int = 1,
    available: np.ndarray | None = None, source: str = "arrays", flight: int = 0,
) -> PreparedData:
    """One-segment PreparedData from already-trimmed arrays (tests, simulators, the live service).

    inputs (n, 4) normalised; outputs (n, 8) trim removed, NaN where unmeasured.
    """
    u = np.asarray(inputs, dtype=float)
    y = np.asarray(outputs, dtype=float)
    if u.ndim != 2 or u.shape[1] != 4 or y.ndim != 2 or y.shape[1] != 8 or u.shape[0] != y.shape[0]:
        raise DspError(f"inputs must be (n, 4) and outputs (n, 8) with equal n, got {u.shape} and {y.shape}")
    avail = np.isfinite(y).all(axis=0) if available is None else np.asarray(available, dtype=bool)
    sm = smooth5(np.nan_to_num(y), smooth_passes)
    sm[:, ~avail] = np.nan
    raw = y.copy()
    raw[:, ~avail] = np.nan
    t = np.arange(u.shape[0]) * dt_s
    seg = Segment(t_s=t, inputs=u, outputs=sm, outputs_raw=raw, alt_m=np.full(t.size, np.nan),
                  available=avail, flight=flight, source=source)
    return PreparedData(segments=[seg], dt_s=dt_s, input_trim_pwm={k: 1500.0 for k in INPUTS}, pwm_per_unit=500.0,
                        output_trim={k: 0.0 for k in OUTPUTS}, notes=[])
