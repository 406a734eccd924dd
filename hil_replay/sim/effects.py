"""Unmodelled effects the simulator can inject (the catalogue of docs/gap-report.md), parsing and sampling.

An :class:`Effect` is a frozen description ``(name, input, output, params)``; the session turns the
list into runtime pieces (:class:`InputChain` for the input-side effects, :class:`GustModel` for the
air mass; drag, ground effect and sensor effects are read from the params directly).

=================  ======================  =====================================================
name               channel                 params (allowed range; typical range drawn by random_effect)
=================  ======================  =====================================================
input_delay        input lat|lon|col|ped   delay_s (0.005-0.5; 0.04-0.2)
rate_limit         input                   rate_per_s normalised units/s (0.2-50; 1.5-4)
deadband           input                   half_width normalised units (0.001-0.2; 0.01-0.05)
ground_effect      -                       gain on the Cheeseman-Bennett excess (0.1-3; 0.7-1.3)
wind_gust          -                       sigma_m_s (0.05-5; 0.5-2), tau_s (0.2-20; 1-4)
quadratic_drag     -                       c_per_m (0.001-0.5; 0.02-0.08)
gyro_bias          output p|q|r            bias_rad_s (+-0.0005..0.1; +-0.003..0.02)
rotor_vibration    -                       amplitude_rad_s (0.0005-0.2; 0.004-0.015), rpm (300-4000;
                                           1200-1900; default: the aircraft's head speed)
velocity_latency   -                       latency_s (0.01-1; 0.05-0.3)
=================  ======================  =====================================================

Effects OUTSIDE the catalogue (:data:`OUT_OF_CATALOGUE`): physics and sensor errors the diagnosis
has no name for, to check that it says "unexplained" (or finds the sensor error by data
compatibility) rather than forcing a catalogue name onto them. They parse and inject like the
others but are not in :data:`EFFECT_NAMES`:

=================  ======================  =====================================================
gyro_scale         output p|q|r            scale_error: measured rate = (1 + e) x true
                                           (+-0.02..0.5; +-0.08..0.2)
velocity_scale     -                       scale_error: measured NED velocities = (1 + e) x true,
                                           position unaffected (+-0.05..0.5; +-0.1..0.25)
rotor_sag          -                       sag_per_unit: rotor speed drops by sag x collective above
                                           trim; thrust and control power go with speed squared
                                           (0.02-2; 0.2-0.45)
input_asymmetry    input                   asymmetry: gain (1 + a) for deflections above trim,
                                           (1 - a) below (0.02-0.8; 0.25-0.45)
=================  ======================  =====================================================

Effects HELD BACK from every tuning of the diagnosis (:data:`HELD_BACK`): physics a catalogue
entry only approximates, and parameters that change through the flight (``progress`` runs from 0
at arming to 1 at the end of the flight's card). The bench runs them as a separate kind of case
whose seeds are never used to tune a rule:

====================  ====================  ==================================================
servo_lag             input                 tau_s: first-order servo lag instead of a pure delay
                                            (0.01-0.5; 0.05-0.12)
asym_deadband         input                 half_width_pos / half_width_neg: play wider on one side
                                            (0.003-0.2; 0.012-0.025 / 0.03-0.055)
backlash              input                 half_width: hysteresis (the output follows only when
                                            pushed past +-half_width) (0.002-0.2; 0.015-0.04)
turbulence            -                     sigma_m_s, tau_slow_s, tau_fast_s, fast_share: an air
                                            mass with a slow and a fast Gauss-Markov part
                                            (0.6-1.5 m/s; 4-10 s; 0.3-0.6 s; 0.3-0.6)
wandering_vibration   -                     amplitude_rad_s, wander, period_s: a rotor line whose
                                            rpm wanders +-wander (0.01-0.03) with a period of
                                            20-60 s (governor hunting)
rotor_droop           -                     droop: rotor speed falls through the flight with the
                                            battery, to (1 - droop) at the end (0.08-0.15); thrust
                                            and control power go with speed squared
growing_delay         input                 delay_end_s: a transport delay growing from 0 at arming
                                            to delay_end_s at the end (0.12-0.22)
drifting_bias         output p|q|r          bias_end_rad_s: a gyro bias drifting from 0 to its end
                                            value (+-0.01..0.025)
cg_shift              -                     moment_end: a pitch moment growing through the flight,
                                            as a lon-input offset (normalised units, +-0.02..0.045)
====================  ====================  ==================================================

``parse_effect("input_delay:input=lon,delay_s=0.1")`` validates names, keys and ranges and raises
``ValueError`` naming the key and what is allowed. Leaves to others: where each effect acts in the
loop (``session.py``) and in the sensors (``telemetry.py``).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

INPUT_CHANNELS: tuple[str, ...] = ("lat", "lon", "col", "ped")
OUTPUT_CHANNELS: tuple[str, ...] = ("p", "q", "r")


@dataclass(frozen=True)
class _ParamSpec:
    lo: float
    hi: float
    typ_lo: float
    typ_hi: float
    default: float | None
    signed: bool = False  # magnitude in [lo, hi], either sign


@dataclass(frozen=True)
class _EffectSpec:
    channel: str | None  # "input", "output" or None
    params: Mapping[str, _ParamSpec]
    default_channel: str | None = None


SPECS: Mapping[str, _EffectSpec] = MappingProxyType({
    "input_delay": _EffectSpec("input", {"delay_s": _ParamSpec(0.005, 0.5, 0.04, 0.2, 0.1)}, "lon"),
    "rate_limit": _EffectSpec("input", {"rate_per_s": _ParamSpec(0.2, 50.0, 1.5, 4.0, 2.5)}, "lon"),
    "deadband": _EffectSpec("input", {"half_width": _ParamSpec(0.001, 0.2, 0.01, 0.05, 0.03)}, "lon"),
    "ground_effect": _EffectSpec(None, {"gain": _ParamSpec(0.1, 3.0, 0.7, 1.3, 1.0)}),
    "wind_gust": _EffectSpec(None, {"sigma_m_s": _ParamSpec(0.05, 5.0, 0.5, 2.0, 1.0),
                                    "tau_s": _ParamSpec(0.2, 20.0, 1.0, 4.0, 2.0)}),
    "quadratic_drag": _EffectSpec(None, {"c_per_m": _ParamSpec(0.001, 0.5, 0.02, 0.08, 0.04)}),
    "gyro_bias": _EffectSpec("output", {"bias_rad_s": _ParamSpec(0.0005, 0.1, 0.003, 0.02, 0.01, signed=True)}, "q"),
    "rotor_vibration": _EffectSpec(None, {"amplitude_rad_s": _ParamSpec(0.0005, 0.2, 0.004, 0.015, 0.008),
                                          "rpm": _ParamSpec(300.0, 4000.0, 1200.0, 1900.0, None)}),
    "velocity_latency": _EffectSpec(None, {"latency_s": _ParamSpec(0.01, 1.0, 0.05, 0.3, 0.15)}),
    # ---- outside the catalogue (see the module docstring)
    "gyro_scale": _EffectSpec("output", {"scale_error": _ParamSpec(0.02, 0.5, 0.08, 0.2, 0.1, signed=True)}, "q"),
    "velocity_scale": _EffectSpec(None, {"scale_error": _ParamSpec(0.05, 0.5, 0.1, 0.25, 0.15, signed=True)}),
    "rotor_sag": _EffectSpec(None, {"sag_per_unit": _ParamSpec(0.02, 2.0, 0.2, 0.45, 0.3)}),
    "input_asymmetry": _EffectSpec("input", {"asymmetry": _ParamSpec(0.02, 0.8, 0.25, 0.45, 0.35)}, "lon"),
    # ---- held back from tuning (see the module docstring)
    "servo_lag": _EffectSpec("input", {"tau_s": _ParamSpec(0.01, 0.5, 0.05, 0.12, 0.08)}, "lon"),
    "asym_deadband": _EffectSpec("input", {"half_width_pos": _ParamSpec(0.003, 0.2, 0.012, 0.025, 0.02),
                                           "half_width_neg": _ParamSpec(0.003, 0.2, 0.03, 0.055, 0.04)}, "lon"),
    "backlash": _EffectSpec("input", {"half_width": _ParamSpec(0.002, 0.2, 0.015, 0.04, 0.025)}, "lon"),
    "turbulence": _EffectSpec(None, {"sigma_m_s": _ParamSpec(0.05, 5.0, 0.6, 1.5, 1.0),
                                     "tau_slow_s": _ParamSpec(1.0, 30.0, 4.0, 10.0, 6.0),
                                     "tau_fast_s": _ParamSpec(0.05, 2.0, 0.3, 0.6, 0.4),
                                     "fast_share": _ParamSpec(0.0, 1.0, 0.3, 0.6, 0.4)}),
    "wandering_vibration": _EffectSpec(None, {"amplitude_rad_s": _ParamSpec(0.0005, 0.2, 0.004, 0.015, 0.008),
                                              "wander": _ParamSpec(0.0, 0.2, 0.01, 0.03, 0.02),
                                              "period_s": _ParamSpec(2.0, 300.0, 20.0, 60.0, 40.0),
                                              "rpm": _ParamSpec(300.0, 4000.0, 1200.0, 1900.0, None)}),
    "rotor_droop": _EffectSpec(None, {"droop": _ParamSpec(0.01, 0.5, 0.08, 0.15, 0.1)}),
    "growing_delay": _EffectSpec("input", {"delay_end_s": _ParamSpec(0.02, 0.5, 0.12, 0.22, 0.15)}, "lon"),
    "drifting_bias": _EffectSpec("output", {"bias_end_rad_s": _ParamSpec(0.001, 0.1, 0.01, 0.025, 0.015,
                                                                         signed=True)}, "q"),
    "cg_shift": _EffectSpec(None, {"moment_end": _ParamSpec(0.005, 0.2, 0.02, 0.045, 0.03, signed=True)}),
})
#: effects outside the catalogue (the diagnosis has no name for them)
OUT_OF_CATALOGUE: tuple[str, ...] = ("gyro_scale", "velocity_scale", "rotor_sag", "input_asymmetry")
#: effects held back from every tuning loop (physics a catalogue entry only approximates, and
#: parameters that change through the flight)
HELD_BACK: tuple[str, ...] = ("servo_lag", "asym_deadband", "backlash", "turbulence", "wandering_vibration",
                              "rotor_droop", "growing_delay", "drifting_bias", "cg_shift")
#: the catalogue (docs/gap-report.md)
EFFECT_NAMES: tuple[str, ...] = tuple(n for n in SPECS if n not in OUT_OF_CATALOGUE + HELD_BACK)
#: input-side effects the :class:`InputChain` applies (the others act after it, in the session)
CHAIN_EFFECTS: tuple[str, ...] = ("input_delay", "rate_limit", "deadband")


@dataclass(frozen=True)
class Effect:
    """One unmodelled effect: catalogue ``name``, the ``input`` or ``output`` channel it acts on
    (or None), and its ``params`` (SI; see the module table)."""

    name: str
    input: str | None = None
    output: str | None = None
    params: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "params", MappingProxyType(dict(self.params)))
        _validate(self)

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.name, "input": self.input, "output": self.output,
                "params": {k: float(v) for k, v in self.params.items()}}

    def spec(self) -> str:
        """The ``name:key=value,...`` string that parses back to this effect."""
        kv = []
        if self.input is not None:
            kv.append(f"input={self.input}")
        if self.output is not None:
            kv.append(f"output={self.output}")
        kv += [f"{k}={v:.6g}" for k, v in self.params.items()]
        return self.name + (":" + ",".join(kv) if kv else "")


def _validate(e: Effect) -> None:
    if e.name not in SPECS:
        raise ValueError(f"effect: unknown name {e.name!r}; allowed: {list(SPECS)}")
    sp = SPECS[e.name]
    if sp.channel == "input":
        if e.input not in INPUT_CHANNELS:
            raise ValueError(f"effect {e.name}: input={e.input!r}; allowed: {list(INPUT_CHANNELS)}")
        if e.output is not None:
            raise ValueError(f"effect {e.name}: key 'output' not allowed (it acts on an input channel)")
    elif sp.channel == "output":
        if e.output not in OUTPUT_CHANNELS:
            raise ValueError(f"effect {e.name}: output={e.output!r}; allowed: {list(OUTPUT_CHANNELS)}")
        if e.input is not None:
            raise ValueError(f"effect {e.name}: key 'input' not allowed (it acts on an output channel)")
    elif e.input is not None or e.output is not None:
        raise ValueError(f"effect {e.name}: keys 'input'/'output' not allowed (it acts on no single channel)")
    for k, v in e.params.items():
        if k not in sp.params:
            raise ValueError(f"effect {e.name}: unknown key {k!r}; allowed: {_allowed_keys(e.name)}")
        ps = sp.params[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"effect {e.name}: {k}={v!r} is not a finite number")
        mag = abs(v) if ps.signed else v
        if not ps.lo <= mag <= ps.hi:
            rng = f"+-[{ps.lo:g}, {ps.hi:g}]" if ps.signed else f"[{ps.lo:g}, {ps.hi:g}]"
            raise ValueError(f"effect {e.name}: {k}={v:g} out of range; allowed {rng}")


def _allowed_keys(name: str) -> list[str]:
    sp = SPECS[name]
    keys = [] if sp.channel is None else [sp.channel]
    return keys + list(sp.params)


def make_effect(name: str, *, input: str | None = None, output: str | None = None,
                **params: float) -> Effect:
    """Build an effect, filling the default channel and default parameter values."""
    if name not in SPECS:
        raise ValueError(f"effect: unknown name {name!r}; allowed: {list(SPECS)}")
    sp = SPECS[name]
    if sp.channel == "input" and input is None:
        input = sp.default_channel
    if sp.channel == "output" and output is None:
        output = sp.default_channel
    full: dict[str, float] = {}
    for k, ps in sp.params.items():
        if k in params:
            full[k] = params[k]
        elif ps.default is not None:
            full[k] = ps.default
    for k in params:
        if k not in sp.params:
            full[k] = params[k]  # reported by validation with the allowed keys
    return Effect(name, input, output, full)


def parse_effect(text: str) -> Effect:
    """Parse ``"name"`` or ``"name:key=value,key=value"`` (CLI ``--effect``); ValueError on bad input."""
    s = str(text).strip()
    name, _, rest = s.partition(":")
    name = name.strip()
    if name not in SPECS:
        raise ValueError(f"--effect {s!r}: unknown effect name {name!r}; allowed: {list(SPECS)}")
    kw: dict[str, Any] = {}
    if rest.strip():
        for item in rest.split(","):
            key, eq, val = item.partition("=")
            key, val = key.strip(), val.strip()
            if not eq or not key:
                raise ValueError(f"--effect {s!r}: expected key=value, got {item!r}; "
                                 f"allowed keys: {_allowed_keys(name)}")
            if key in ("input", "output"):
                kw[key] = val
                continue
            if key not in SPECS[name].params:
                raise ValueError(f"--effect {s!r}: unknown key {key!r}; allowed: {_allowed_keys(name)}")
            try:
                kw[key] = float(val)
            except ValueError:
                raise ValueError(f"--effect {s!r}: {key}={val!r} is not a number") from None
    try:
        return make_effect(name, **kw)
    except ValueError as exc:
        raise ValueError(f"--effect {s!r}: {exc}") from None


def random_effect(name: str, rng: np.random.Generator | int | None = None) -> Effect:
    """An effect ``name`` with a random channel and magnitude inside its typical physical range."""
    if name not in SPECS:
        raise ValueError(f"effect: unknown name {name!r}; allowed: {list(SPECS)}")
    g = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    sp = SPECS[name]
    kw: dict[str, Any] = {}
    if sp.channel == "input":
        kw["input"] = INPUT_CHANNELS[int(g.integers(len(INPUT_CHANNELS)))]
    elif sp.channel == "output":
        kw["output"] = OUTPUT_CHANNELS[int(g.integers(len(OUTPUT_CHANNELS)))]
    for k, ps in sp.params.items():
        v = float(g.uniform(ps.typ_lo, ps.typ_hi))
        if ps.signed and g.random() < 0.5:
            v = -v
        kw[k] = round(v, 6)
    return make_effect(name, **kw)


def resolve_effects(effects: tuple[Effect | str, ...] | list[Effect | str], rotor_rpm: float) -> tuple[Effect, ...]:
    """Parse strings, fill aircraft-dependent defaults (vibration rpm), reject duplicates."""
    out: list[Effect] = []
    seen: set[tuple[str, str | None, str | None]] = set()
    for e in effects:
        eff = parse_effect(e) if isinstance(e, str) else e
        if not isinstance(eff, Effect):
            raise ValueError(f"effect: expected an Effect or 'name:key=value' string, got {e!r}")
        if eff.name in ("rotor_vibration", "wandering_vibration") and "rpm" not in eff.params:
            eff = Effect(eff.name, None, None, {**eff.params, "rpm": float(rotor_rpm)})
        key = (eff.name, eff.input, eff.output)
        if key in seen:
            raise ValueError(f"effect {eff.name}: given twice for the same channel ({eff.input or eff.output})")
        seen.add(key)
        out.append(eff)
    return tuple(out)


def aliased_hz(freq_hz: float, sample_rate_hz: float) -> float:
    """Frequency a sinusoid of ``freq_hz`` appears at when sampled at ``sample_rate_hz``."""
    f = freq_hz % sample_rate_hz
    return min(f, sample_rate_hz - f)


# --------------------------------------------------------------------------------------------
# runtime pieces
# --------------------------------------------------------------------------------------------


class InputChain:
    """Input-side effects of one channel, applied per integration sub-step: transport delay
    (fractional, linear interpolation between sub-steps), then servo slew-rate limit, then
    play (deadband around the trim: ``sign(d) max(|d| - half_width, 0)``)."""

    def __init__(self, dt_s: float, *, delay_s: float = 0.0, rate_per_s: float | None = None,
                 half_width: float = 0.0) -> None:
        n = delay_s / dt_s
        self._n = int(math.floor(n))
        self._frac = n - self._n
        self._hist: deque[float] = deque([0.0] * (self._n + 2), maxlen=self._n + 2)
        self._delay = delay_s > 0
        self._max_step = None if rate_per_s is None else rate_per_s * dt_s
        self._y = 0.0
        self._hw = half_width

    def reset(self, value: float = 0.0) -> None:
        for i in range(len(self._hist)):
            self._hist[i] = value
        self._y = value

    def __call__(self, d: float) -> float:
        if self._delay:
            h = self._hist
            h.append(d)  # h[-1] is now, h[-1-k] k sub-steps ago
            d = (1.0 - self._frac) * h[-1 - self._n] + self._frac * h[-2 - self._n]
        if self._max_step is not None:
            step = d - self._y
            if step > self._max_step:
                step = self._max_step
            elif step < -self._max_step:
                step = -self._max_step
            self._y += step
            d = self._y
        if self._hw:
            if d > self._hw:
                d -= self._hw
            elif d < -self._hw:
                d += self._hw
            else:
                d = 0.0
        return d


def rotor_sag(d: list[float], sag_per_unit: float, z_col: float, g_m_s2: float) -> list[float]:
    """Effective inputs when rotor speed sags with collective above trim (governor droop under load).

    Speed ratio ``k = 1 - sag x`` with ``x`` the collective beyond trim in the thrust-increasing
    direction (zero below trim: the governor holds an unloaded rotor); thrust and control power
    scale with ``k^2``. The thrust loss enters as an equivalent collective:
    ``g - Z_col d_eff = k^2 (g - Z_col d)``.
    """
    load = max(-math.copysign(1.0, z_col) * d[2], 0.0)
    k2 = (1.0 - sag_per_unit * load) ** 2
    col = k2 * d[2] + g_m_s2 * (1.0 - k2) / z_col
    return [k2 * d[0], k2 * d[1], col, k2 * d[3]]


class GustModel:
    """Dryden-like coloured air-mass velocity: first-order Gauss-Markov per NED axis (vertical at
    half the horizontal intensity), exact discretisation at ``dt_s``."""

    def __init__(self, rng: np.random.Generator, dt_s: float, sigma_m_s: float, tau_s: float) -> None:
        a = math.exp(-dt_s / tau_s)
        self._a = a
        self._sig = (sigma_m_s, sigma_m_s, 0.5 * sigma_m_s)
        self._b = [s * math.sqrt(1.0 - a * a) for s in self._sig]
        self._rng = rng
        self.wind = [float(s * z) for s, z in zip(self._sig, rng.standard_normal(3), strict=False)]

    def step(self) -> list[float]:
        z = self._rng.standard_normal(3).tolist()
        self.wind = [self._a * w + b * e for w, b, e in zip(self.wind, self._b, z, strict=False)]
        return self.wind


class TurbulenceModel:
    """An air mass with a slow and a fast part (two first-order Gauss-Markov processes per NED axis,
    vertical at half the horizontal intensity): rougher than :class:`GustModel`'s single time scale."""

    def __init__(self, rng: np.random.Generator, dt_s: float, sigma_m_s: float, tau_slow_s: float,
                 tau_fast_s: float, fast_share: float) -> None:
        f = min(max(fast_share, 0.0), 1.0)
        self._parts = [GustModel(rng, dt_s, sigma_m_s * math.sqrt(1.0 - f), tau_slow_s),
                       GustModel(rng, dt_s, sigma_m_s * math.sqrt(f), tau_fast_s)]
        self.wind = self._sum()

    def _sum(self) -> list[float]:
        return [a + b for a, b in zip(self._parts[0].wind, self._parts[1].wind, strict=True)]

    def step(self) -> list[float]:
        for p in self._parts:
            p.step()
        self.wind = self._sum()
        return self.wind


class HeldBackChain:
    """The held-back input physics, per 200 Hz sub-step, after the catalogue chains: a delay growing
    with the flight's progress, a first-order servo lag, an asymmetric deadband, backlash, a pitch
    moment growing through the flight (a lon offset) and rotor speed drooping with the battery
    (thrust and control power with speed squared, the thrust loss as an equivalent collective)."""

    def __init__(self, h_s: float, effects: list[Effect], inputs: tuple[str, ...], z_col: float,
                 g_m_s2: float) -> None:
        self.h = h_s
        self.z_col, self.g = z_col, g_m_s2
        self.progress = 0.0
        n = len(inputs)
        self.grow = [0.0] * n
        self.lag = [0.0] * n
        self.adb: list[tuple[float, float] | None] = [None] * n
        self.bl = [0.0] * n
        self.cg = 0.0
        self.droop = 0.0
        for e in effects:
            i = inputs.index(e.input) if e.input in inputs else None
            p = e.params
            if e.name == "growing_delay" and i is not None:
                self.grow[i] = float(p["delay_end_s"])
            elif e.name == "servo_lag" and i is not None:
                self.lag[i] = float(p["tau_s"])
            elif e.name == "asym_deadband" and i is not None:
                self.adb[i] = (float(p["half_width_pos"]), float(p["half_width_neg"]))
            elif e.name == "backlash" and i is not None:
                self.bl[i] = float(p["half_width"])
            elif e.name == "cg_shift":
                self.cg = float(p["moment_end"])
            elif e.name == "rotor_droop":
                self.droop = float(p["droop"])
        m = int(max(self.grow) / h_s) + 3
        self.hist: list[deque[float]] = [deque([0.0] * m, maxlen=m) for _ in range(n)]
        self.y = [0.0] * n
        self.bly = [0.0] * n

    @property
    def active(self) -> bool:
        return bool(any(self.grow) or any(self.lag) or any(a is not None for a in self.adb) or any(self.bl)
                    or self.cg or self.droop)

    def __call__(self, d: list[float]) -> list[float]:
        d = list(d)
        for i in range(len(d)):
            if self.grow[i]:
                h = self.hist[i]
                h.append(d[i])
                k = self.progress * self.grow[i] / self.h
                j = int(k)
                fr = k - j
                d[i] = (1.0 - fr) * h[-1 - j] + fr * h[-2 - j]
            if self.lag[i]:
                self.y[i] += min(self.h / self.lag[i], 1.0) * (d[i] - self.y[i])
                d[i] = self.y[i]
            a = self.adb[i]
            if a is not None:
                d[i] = d[i] - a[0] if d[i] > a[0] else (d[i] + a[1] if d[i] < -a[1] else 0.0)
            if self.bl[i]:
                b = self.bl[i]
                if d[i] > self.bly[i] + b:
                    self.bly[i] = d[i] - b
                elif d[i] < self.bly[i] - b:
                    self.bly[i] = d[i] + b
                d[i] = self.bly[i]
        if self.cg:
            d[1] += self.cg * self.progress
        if self.droop:
            k2 = (1.0 - self.droop * self.progress) ** 2
            col = k2 * d[2] + self.g * (1.0 - k2) / self.z_col
            d = [k2 * d[0], k2 * d[1], col, k2 * d[3]]
        return d
