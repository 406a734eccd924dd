"""Flight-test card: a time-scheduled list of segments for one flight, randomised per seed.

Order: ``spool_up`` (armed, on the ground) -> ``takeoff`` -> ``hover_ige`` (skid height below one
rotor diameter) -> ``climb`` (to 5-10 m) -> for each axis in a random order a frequency sweep
(``sweep_<axis>``, log chirp 0.3 -> 6-8 Hz) and a 3-2-1-1 (``doublet_<axis>``) with a short
``hover`` between, translational legs (``leg_forward``, ``leg_sideways``) inserted at random points,
``descent`` -> ``landing`` -> ``spool_down`` (on the ground) -> disarm. Heading, amplitudes, order and
durations are drawn from the card's generator. Excitation amplitudes are scaled from the aircraft's
own on-axis response so that any aircraft file gets a similar, linear-regime excitation.

:meth:`Card.at` gives, at time ``t_s`` since arming, the mode (``"ground"`` or ``"fly"``), the
pilot's reference ``(n, e, d, psi, vn, ve, vd)`` and the excitation per input channel.
Leaves to others: the pilot's feedback (``pilot.py``) and ground contact (``session.py``).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np

from hil_replay.sim.aircraft import INPUTS, Aircraft
from hil_replay.sim.dynamics import eq8_matrices

# Peak on-axis response the excitation aims at (q, p in rad/s for lat, lon; w m/s; r rad/s).
_TARGET = {"lat": 0.35, "lon": 0.35, "col": 0.45, "ped": 0.45}
_AXIS_STATE = {"lat": ("h", 4), "lon": ("h", 5), "col": ("v", 0), "ped": ("v", 1)}


@dataclass(frozen=True)
class Segment:
    name: str
    start_s: float
    end_s: float
    axis: str | None = None
    kind: str = "hold"            # ground | takeoff | hold | climb | sweep | doublet | leg | land
    amplitude: float = 0.0        # excitation (normalised units) or leg speed (m/s)
    f0_hz: float = 0.0
    f1_hz: float = 0.0
    pulse_s: float = 0.0
    height_from_m: float = 0.0
    height_to_m: float = 0.0
    direction_rad: float = 0.0    # leg direction relative to the heading


@dataclass
class Card:
    """One flight's card. ``heading_rad`` is the pilot's heading; times are since arming."""

    segments: list[Segment]
    heading_rad: float
    start_n_m: float = 0.0
    start_e_m: float = 0.0
    _ends: list[float] = field(default_factory=list, repr=False)
    _legs: list[Segment] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        self._ends = [s.end_s for s in self.segments]
        self._legs = [s for s in self.segments if s.kind == "leg"]

    @property
    def duration_s(self) -> float:
        return self.segments[-1].end_s

    def segment_at(self, t_s: float) -> Segment:
        i = bisect.bisect_right(self._ends, t_s)
        return self.segments[min(i, len(self.segments) - 1)]

    def _leg_offset(self, t_s: float) -> tuple[float, float, float, float]:
        """Accumulated leg displacement (n, e) and the leg velocity (vn, ve) at ``t_s``."""
        n = e = vn = ve = 0.0
        for s in self._legs:
            if t_s <= s.start_s:
                break
            dur = s.end_s - s.start_s
            ramp = min(2.5, dur / 3.0)
            tt = min(t_s, s.end_s) - s.start_s
            # trapezoidal speed profile: dist(tt) for ramp/cruise/ramp
            cruise = dur - 2 * ramp
            if tt < ramp:
                dist, spd = 0.5 * tt * tt / ramp, tt / ramp
            elif tt < ramp + cruise:
                dist, spd = 0.5 * ramp + (tt - ramp), 1.0
            else:
                t3 = min(tt - ramp - cruise, ramp)
                dist = 0.5 * ramp + cruise + t3 - 0.5 * t3 * t3 / ramp
                spd = 1.0 - t3 / ramp
            if t_s >= s.end_s:
                spd = 0.0
            dirn = self.heading_rad + s.direction_rad
            cd, sd = math.cos(dirn), math.sin(dirn)
            n += s.amplitude * dist * cd
            e += s.amplitude * dist * sd
            vn += s.amplitude * spd * cd
            ve += s.amplitude * spd * sd
        return n, e, vn, ve

    def at(self, t_s: float) -> tuple[str, Segment, tuple[float, ...], tuple[float, float, float, float]]:
        """``(mode, segment, ref (n, e, d, psi, vn, ve, vd), excitation (lat, lon, col, ped))``."""
        s = self.segment_at(t_s)
        tt = t_s - s.start_s
        dur = s.end_s - s.start_s
        h, vd = s.height_to_m, 0.0
        if s.kind in ("takeoff", "climb", "land") and dur > 0:
            frac = min(max(tt / dur, 0.0), 1.0)
            h = s.height_from_m + (s.height_to_m - s.height_from_m) * frac
            vd = -(s.height_to_m - s.height_from_m) / dur if tt < dur else 0.0
        ln, le, vn, ve = self._leg_offset(t_s)
        ref = (self.start_n_m + ln, self.start_e_m + le, -h, self.heading_rad, vn, ve, vd)
        exc = [0.0, 0.0, 0.0, 0.0]
        if s.kind == "sweep":
            exc[INPUTS.index(s.axis or "lat")] = s.amplitude * _chirp(tt, dur, s.f0_hz, s.f1_hz)
        elif s.kind == "doublet":
            exc[INPUTS.index(s.axis or "lat")] = s.amplitude * _3211(tt, s.pulse_s)
        elif s.kind == "takeoff" and dur > 0:  # a decisive lift-off: collective feed-forward, washed out
            exc[2] = s.amplitude * max(0.0, 1.0 - tt / (0.6 * dur))
        mode = "ground" if s.kind == "ground" else "fly"
        return mode, s, ref, (exc[0], exc[1], exc[2], exc[3])

    def to_json(self, t0_fc_s: float) -> list[dict[str, object]]:
        return [{"name": s.name, "start_fc_s": round(t0_fc_s + s.start_s, 6), "end_fc_s": round(t0_fc_s + s.end_s, 6),
                 "axis": s.axis, "height_m": round(max(s.height_to_m, 0.0), 3)} for s in self.segments]


def _chirp(t: float, dur: float, f0: float, f1: float) -> float:
    """Log-frequency chirp with 1 s raised-cosine fades at both ends."""
    if t < 0 or t > dur:
        return 0.0
    k = math.log(f1 / f0) / dur
    phase = 2 * math.pi * f0 * (math.exp(k * t) - 1.0) / k
    fade = 1.0
    tf = min(1.0, dur / 4)
    if t < tf:
        fade = 0.5 * (1 - math.cos(math.pi * t / tf))
    elif t > dur - tf:
        fade = 0.5 * (1 - math.cos(math.pi * (dur - t) / tf))
    return fade * math.sin(phase)


def _3211(t: float, pulse_s: float) -> float:
    """3-2-1-1 multistep: +1 for 3 pulses, -1 for 2, +1 for 1, -1 for 1, then 0."""
    k = t / pulse_s
    if k < 0:
        return 0.0
    if k < 3:
        return 1.0
    if k < 5:
        return -1.0
    if k < 6:
        return 1.0
    if k < 7:
        return -1.0
    return 0.0


def excitation_gains(ac: Aircraft) -> dict[str, float]:
    """Open-loop on-axis response magnitude at 1 Hz per unit input (q/lat, p/lon, w/col, r/ped)."""
    Ah, Bh, Av, Bv = (np.array(m) for m in eq8_matrices(ac.parameters))
    s = 2j * math.pi * 1.0
    out = {}
    for axis, (blk, row) in _AXIS_STATE.items():
        A, B = (Ah, Bh) if blk == "h" else (Av, Bv)
        col = INPUTS.index(axis) % 2
        G = np.linalg.solve(s * np.eye(A.shape[0]) - A, B[:, col])
        out[axis] = float(abs(G[row]))
    return out


_Block = tuple[str, str, str | None, float, dict[str, float]]   # name, kind, axis, duration, parameters


def _card_round(rng: np.random.Generator, amp: dict[str, float], sweeps: bool) -> list[list[_Block]]:
    """One round of excitation: per input (shuffled) a sweep and a doublet with hovers between,
    and the forward and sideways legs at random places."""
    axes = list(INPUTS)
    rng.shuffle(axes)
    blocks: list[list[_Block]] = []
    for a in axes:
        pulse = float(rng.uniform(0.2, 0.4) if a in ("lat", "lon") else rng.uniform(0.3, 0.5))
        sweep = ("sweep_" + a, "sweep", a, float(rng.uniform(15.0, 20.0)),
                 {"amplitude": amp[a] * float(rng.uniform(0.75, 1.25)), "f0_hz": 0.3,
                  "f1_hz": float(rng.uniform(6.0, 8.0))})
        doublet = ("doublet_" + a, "doublet", a, 7 * pulse + 2.5,
                   {"amplitude": 1.0 * amp[a] * float(rng.uniform(0.75, 1.25)), "pulse_s": pulse})
        if not sweeps:  # the same draws, a slower multistep in the sweep's place
            sweep = ("doublet2_" + a, "doublet", a, 7 * 1.6 * pulse + 2.5,
                     {"amplitude": doublet[4]["amplitude"], "pulse_s": 1.6 * pulse})
        pair = [sweep, doublet] if rng.random() < 0.7 else [doublet, sweep]
        blocks.append([pair[0], ("hover", "hold", None, float(rng.uniform(2.0, 4.0)), {}), pair[1],
                       ("hover", "hold", None, float(rng.uniform(2.0, 4.0)), {})])
    for name, direction in (("leg_forward", 0.0),
                            ("leg_sideways", math.copysign(math.pi / 2, rng.uniform(-1, 1)))):
        leg: list[_Block] = [(name, "leg", None, float(rng.uniform(9.0, 13.0)),
                {"amplitude": float(rng.uniform(3.0, 6.0)), "direction_rad": direction}),
               ("hover", "hold", None, float(rng.uniform(2.0, 4.0)), {})]
        blocks.insert(int(rng.integers(0, len(blocks) + 1)), leg)
    return blocks


def make_card(ac: Aircraft, rng: np.random.Generator, *, duration_s: float | None = None,
              heading_rad: float | None = None, excitation_scale: float = 1.0, sweeps: bool = True) -> Card:
    """Plan one flight. ``duration_s`` (armed time, default ~150-200 s, minimum ~30 s) scales the card;
    ``excitation_scale`` multiplies the sweep and doublet amplitudes (a bolder or more cautious pilot);
    ``sweeps=False``: a sweep-free card (each frequency sweep replaced by a second, slower 3-2-1-1
    multistep, as many real test cards are)."""
    gains = excitation_gains(ac)
    amp = {a: float(np.clip(_TARGET[a] / max(gains[a], 1e-6), 0.01, 0.3)) * float(excitation_scale) for a in INPUTS}
    heading = float(rng.uniform(-math.pi, math.pi)) if heading_rad is None else float(heading_rad)
    nominal = 175.0 if duration_s is None else float(duration_s)
    if nominal < 30.0:
        raise ValueError(f"duration_s: {nominal:g} s is too short for a flight card; allowed >= 30 s")
    short = min(1.0, nominal / 150.0)
    D = ac.rotor_diameter_m
    h_ige = float(rng.uniform(0.25, 0.55)) * D - 0.0   # skid height: rotor stays below ~one diameter
    h_ige = min(h_ige, max(0.1, D - ac.hub_height_m - 0.15))
    h_alt = float(rng.uniform(5.0, 10.0)) * max(short, 0.5)
    climb_rate = float(rng.uniform(0.8, 1.3))
    fixed = [
        ("spool_up", "ground", float(rng.uniform(4.0, 7.0)) * short),
        ("takeoff", "takeoff", 2.5),
        ("hover_ige", "hold", float(rng.uniform(8.0, 14.0)) * short),
        ("climb", "climb", (h_alt - h_ige) / climb_rate),
        ("hover", "hold", 3.0 * short),
    ]
    tail = [
        ("descent", "climb", (h_alt - h_ige) / climb_rate),
        ("hover_ige", "hold", 3.0 * short),
        ("landing", "land", 3.5),
        ("spool_down", "ground", float(rng.uniform(3.0, 5.0)) * short),
    ]
    tail_s = sum(d for _, _, d in tail)
    fixed_s = sum(d for _, _, d in fixed) + tail_s
    blocks = _card_round(rng, amp, sweeps)
    round_s = sum(d for b in blocks for _, _, _, d, _ in b)
    for _ in range(max(0, int(round((nominal - fixed_s) / round_s / 1.25)) - 1)):  # long flights: more rounds
        blocks += _card_round(rng, amp, sweeps)
    variable_s = sum(d for b in blocks for _, _, _, d, _ in b)
    scale = max(0.05, (nominal - fixed_s) / variable_s)
    segs: list[Segment] = []
    t = 0.0

    def add(name: str, kind: str, dur: float, **kw: object) -> None:
        nonlocal t
        segs.append(Segment(name, round(t, 6), round(t + dur, 6), kind=kind, **kw))  # type: ignore[arg-type]
        t += dur

    for name, kind, dur in fixed:
        if kind == "takeoff":
            ff = float(np.clip(0.8 / max(abs(float(ac.parameters["Z_col"])), 1e-3), 0.005, 0.2))  # ~0.8 m/s^2
            add(name, kind, dur, height_from_m=0.0, height_to_m=h_ige, amplitude=-ff if ac.parameters["Z_col"] > 0 else ff)
        elif kind == "climb":
            add(name, kind, dur, height_from_m=h_ige, height_to_m=h_alt)
        else:
            add(name, kind, dur, height_to_m=0.0 if kind == "ground" else (h_ige if name == "hover_ige" else h_alt))
    for b in blocks:
        for name, kind, axis, dur, kw in b:
            if kind == "sweep":
                d = max(6.0, dur * scale)
            elif kind == "doublet":
                d = max(7 * kw["pulse_s"] + 1.5, dur * scale)
            elif kind == "leg":
                d = max(7.5, dur * scale)
            else:
                d = max(1.0, dur * scale)
            add(name, kind, d, axis=axis, height_to_m=h_alt, **kw)
        if duration_s is not None and t >= nominal - tail_s - 1e-9:
            break
    for name, kind, dur in tail:
        if name == "descent":
            add(name, kind, dur, height_from_m=h_alt, height_to_m=h_ige)
        elif kind == "land":
            add(name, kind, dur, height_from_m=h_ige, height_to_m=-0.6)
        else:
            add(name, kind, dur, height_to_m=0.0 if kind == "ground" else h_ige)
    return Card(segs, heading)
