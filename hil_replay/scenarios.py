"""Scenario sets for blind tests of the gap diagnosis: which simulated flights, with which hidden effects.

A :class:`ScenarioSet` says how many cases of each kind to draw and how varied the simulator is;
:func:`make_jobs` turns it into a list of jobs (plain dicts, JSON-ready: case number, kind, seed, the
effect names, the drawn flight set-up and, for the held-back set, the right verdict) and
:func:`write_case` simulates one job's flight to a .tlog with :func:`hil_replay.sim.write_tlog`,
returning the simulator's truth. What the ground station does with the flight (reading it back,
identifying, diagnosing, scoring) is left to the caller: ``groundstation bench diagnose`` and the
tests.

Kinds of case (:data:`KINDS`): ``single`` (one catalogue effect or none, classes taken in turn),
``outside`` (an effect outside the catalogue, :data:`hil_replay.sim.effects.OUT_OF_CATALOGUE`),
``combined`` (two catalogue effects at once) and ``held_back`` (:data:`HELD_BACK_CYCLE`: physics a
catalogue entry only approximates and parameters drifting through the flight, at other noise
levels, with their own random draws). Unless ``plain``, every flight is drawn from a varied
simulator: aircraft (TREX-600 or R-50) with every eq.-8 parameter scattered (log-normal,
``scatter``), stiff / default / loose pilot (:data:`PILOTS`), sweep-free cards on half the flights,
attitude and velocity streams at 10-50 Hz, excitation 0.6-1.3x, nonlinear kinematics on or off.
Selecting kinds (:func:`select_jobs`) draws every kind and keeps some, so each case is the same
flight whichever kinds run. Never imports ``groundstation``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from hil_replay.sim import write_tlog
from hil_replay.sim.aircraft import Aircraft, resolve_aircraft
from hil_replay.sim.effects import OUT_OF_CATALOGUE, random_effect
from hil_replay.sim.pilot import PilotConfig, design_gains

#: the verdicts a single-effect case can have: no effect, or one catalogue effect
CLASSES: tuple[str, ...] = ("none", "input_delay", "rate_limit", "deadband", "ground_effect", "wind_gust",
                            "quadratic_drag", "gyro_bias", "rotor_vibration", "velocity_latency")

#: kinds of case: one catalogue effect or none, one effect outside the catalogue, two catalogue
#: effects, the held-back set
KINDS: tuple[str, ...] = ("single", "outside", "combined", "held_back")

#: the held-back set, in turn: what is injected ("catalogue": a random catalogue effect at another
#: noise level) and the right verdict (None: the effect itself; "unexplained": a parameter drifting
#: through the flight, no constant catalogue effect is it)
HELD_BACK_CYCLE: tuple[tuple[str, str | None], ...] = (
    ("none", "none"), ("servo_lag", "input_delay"), ("rotor_droop", "unexplained"),
    ("asym_deadband", "deadband"), ("growing_delay", "unexplained"), ("backlash", "deadband"),
    ("drifting_bias", "unexplained"), ("turbulence", "wind_gust"), ("cg_shift", "unexplained"),
    ("wandering_vibration", "rotor_vibration"), ("catalogue", None), ("none", "none"))
#: noise levels (x the simulator's sensor noise) of the held-back flights
HELD_BACK_NOISE: tuple[float, ...] = (0.5, 1.0, 1.6, 2.5)

#: Pilot variants: Bryson allowed deviations scaled (smaller = stiffer loops) and the feedback left
#: on the excited axis.
PILOTS: Mapping[str, Mapping[str, float]] = {"default": {}, "tight": {"scale": 0.5, "excited_axis_gain": 0.6},
                                             "loose": {"scale": 1.6, "excited_axis_gain": 0.15}}

_STREAM_HZ = (10.0, 12.5, 16.7, 25.0, 50.0)


@dataclass(frozen=True)
class ScenarioSet:
    """What to draw. ``None`` for ``aircraft``, ``rates_hz``, ``pilot``, ``kinematics`` and
    ``excitation`` means drawn per flight (or the simulator's default with ``plain``)."""

    cases: int = 20                         # single-effect (or none) flights
    seed: int = 0
    out_of_catalogue: int = 0               # flights with an effect outside the catalogue
    combined: int = 0                       # flights with two catalogue effects
    held_back: int = 0                      # flights of the held-back set
    classes: tuple[str, ...] = CLASSES      # classes the single cases take in turn
    kinds: tuple[str, ...] = KINDS          # kinds kept by select_jobs
    model_source: str = "identify"          # base model: "identify" (blind) or "truth"
    fresh: bool = False                     # also a fresh flight of the same effect
    plain: bool = False                     # the simulator's default flights, nothing drawn
    scatter: float = 0.25                   # log-normal sigma of the aircraft parameter scatter
    aircraft: str | None = None             # simulator aircraft name
    rates_hz: Mapping[str, float] | None = None   # telemetry stream rates, {MESSAGE: Hz}
    pilot: str | None = None                # a PILOTS name
    kinematics: str | None = None           # "nonlinear" or "linear"
    excitation: float | None = None         # scale of the card's amplitudes

    def __post_init__(self) -> None:
        bad = set(self.classes) - set(CLASSES)
        if bad:
            raise ValueError(f"classes: unknown effect name(s) {sorted(bad)}; allowed {CLASSES}")
        if not self.kinds or set(self.kinds) - set(KINDS):
            raise ValueError(f"kinds: {','.join(self.kinds)!r}: allowed {', '.join(KINDS)}")
        if self.pilot is not None and self.pilot not in PILOTS:
            raise ValueError(f"pilot: {self.pilot!r}: allowed {', '.join(PILOTS)}")
        if self.kinematics not in (None, "nonlinear", "linear"):
            raise ValueError(f"kinematics: {self.kinematics!r}: allowed nonlinear, linear")


def pilot_config(name: str) -> Any:
    """The :class:`hil_replay.sim.pilot.PilotConfig` of a named variant (None for the default)."""
    v = PILOTS[name]
    if not v:
        return None
    c = PilotConfig()
    k = v["scale"]
    return replace(c, vel_m_s=c.vel_m_s * k, att_rad=c.att_rad * k, rate_rad_s=c.rate_rad_s * k,
                   pos_m=c.pos_m * k, w_m_s=c.w_m_s * k, r_rad_s=c.r_rad_s * k, height_m=c.height_m * k,
                   heading_rad=c.heading_rad * k, excited_axis_gain=v["excited_axis_gain"])


def draw_flight(rng: np.random.Generator, spec: ScenarioSet) -> dict[str, Any]:
    """The simulator set-up of one varied flight (what ``spec`` fixes is kept)."""
    kin = spec.kinematics
    fl: dict[str, Any] = {"aircraft": spec.aircraft, "rates": dict(spec.rates_hz) if spec.rates_hz else None,
                          "pilot": spec.pilot or "default",
                          "excitation": 1.0 if spec.excitation is None else spec.excitation, "sweeps": True,
                          "scatter": 0.0, "scatter_seed": int(rng.integers(2 ** 31)), "kinematics": kin or "nonlinear"}
    if spec.plain:
        return fl
    if kin is None:
        # from the flight's own seed, not from ``rng``: every other draw of the run stays as it was
        fl["kinematics"] = "linear" if np.random.default_rng((fl["scatter_seed"], 7)).random() < 0.5 else "nonlinear"
    fl["scatter"] = float(spec.scatter)
    if spec.aircraft is None:
        fl["aircraft"] = "r50" if rng.random() < 0.3 else "trex600"
    if spec.pilot is None:
        fl["pilot"] = str(rng.choice(["default", "tight", "loose"]))
    if spec.excitation is None:
        fl["excitation"] = round(float(rng.uniform(0.6, 1.3)), 3)
    fl["sweeps"] = bool(rng.random() < 0.5)
    if spec.rates_hz is None:
        fl["rates"] = {"ATTITUDE": float(rng.choice(_STREAM_HZ)), "LOCAL_POSITION_NED": float(rng.choice(_STREAM_HZ))}
    return fl


def make_aircraft(name: str | None, scatter: float, seed: int) -> Any:
    """The named aircraft with every eq.-8 parameter scattered (log-normal ``scatter``, signs kept)
    such that the synthetic pilot can still fly it (redrawn up to 20 times, else unscattered)."""
    base = resolve_aircraft(name)
    if scatter <= 0:
        return base
    rng = np.random.default_rng(seed)
    kw = {f: getattr(base, f) for f in base.__dataclass_fields__}
    for _ in range(20):
        kw["parameters"] = {k: float(v) * float(np.exp(scatter * rng.standard_normal()))
                            for k, v in base.parameters.items()}
        try:
            ac = Aircraft(**kw)
            design_gains(ac, PilotConfig())
            return ac
        except (ValueError, np.linalg.LinAlgError, ArithmeticError):
            continue
    return base


def sim_kwargs(job: Mapping[str, Any]) -> dict[str, Any]:
    """The keyword arguments of :func:`hil_replay.sim.write_tlog` for a job's drawn flight."""
    fl = job["flight"]
    kw: dict[str, Any] = {"aircraft": make_aircraft(fl["aircraft"], fl["scatter"], fl["scatter_seed"])}
    if fl.get("rates"):
        kw["rates_hz"] = fl["rates"]
    if fl.get("pilot", "default") != "default":
        kw["pilot"] = pilot_config(fl["pilot"])
    if fl.get("excitation", 1.0) != 1.0:
        kw["excitation_scale"] = fl["excitation"]
    if not fl.get("sweeps", True):
        kw["sweeps"] = False
    if fl.get("kinematics", "nonlinear") == "linear":
        kw["linear_kinematics"] = True
    if fl.get("noise_scale", 1.0) != 1.0:
        kw["noise_scale"] = fl["noise_scale"]
    return kw


def case_effects(job: Mapping[str, Any]) -> list[Any]:
    """The job's effects with their random channel and magnitude (drawn from the job's seed: the
    same draw every time)."""
    rng = np.random.default_rng(job["seed"])
    return [random_effect(n, rng) for n in job["effects"]]


def write_case(path: Path, job: Mapping[str, Any], *, flight_seed: int | None = None) -> dict[str, Any]:
    """Simulate the job's flight (its effects, its drawn set-up) to the .tlog ``path``; returns the
    simulator's truth. ``flight_seed`` (default the job's seed) gives another flight of the same
    effects and set-up."""
    seed = job["seed"] if flight_seed is None else flight_seed
    return write_tlog(path, seed=seed, flights=1, effects=case_effects(job), **sim_kwargs(job))


def make_jobs(spec: ScenarioSet) -> list[dict[str, Any]]:
    """Single-effect (or none), out-of-catalogue, two-effect and held-back cases, each with its
    flight set-up, every kind (see :func:`select_jobs`)."""
    classes = list(spec.classes)
    rng = np.random.default_rng(spec.seed)
    base = {"model_source": spec.model_source, "fresh": spec.fresh}
    jobs = []
    for i in range(spec.cases):
        name = classes[i % len(classes)]
        jobs.append({**base, "case": i, "kind": "single", "seed": int(spec.seed * 1000 + i),
                     "effects": [] if name == "none" else [name], "flight": draw_flight(rng, spec)})
    for j in range(spec.out_of_catalogue):
        jobs.append({**base, "case": spec.cases + j, "kind": "outside", "seed": int(spec.seed * 1000 + 300 + j),
                     "effects": [OUT_OF_CATALOGUE[(j + spec.seed) % len(OUT_OF_CATALOGUE)]],
                     "flight": draw_flight(rng, spec), "fresh": False})
    real = [c for c in CLASSES if c != "none"]
    for j in range(spec.combined):
        pair = [str(x) for x in rng.choice(real, 2, replace=False)]
        jobs.append({**base, "case": spec.cases + spec.out_of_catalogue + j, "kind": "combined",
                     "seed": int(spec.seed * 1000 + 500 + j), "effects": pair, "flight": draw_flight(rng, spec),
                     "fresh": False})
    # the held-back set: its own generator, so the cases above are the same flights with or without it
    hrng = np.random.default_rng((spec.seed, 26))
    n0 = spec.cases + spec.out_of_catalogue + spec.combined
    for j in range(spec.held_back):
        name, expect = HELD_BACK_CYCLE[j % len(HELD_BACK_CYCLE)]
        if name == "catalogue":
            name = str(hrng.choice(real))
            expect = name
        fl = draw_flight(hrng, spec)
        if not spec.plain:
            fl["scatter"] = max(float(spec.scatter), 0.35)
            fl["noise_scale"] = float(hrng.choice(HELD_BACK_NOISE))
            if spec.excitation is None:
                fl["excitation"] = round(float(hrng.uniform(0.5, 1.4)), 3)
        jobs.append({**base, "case": n0 + j, "kind": "held_back", "seed": int(spec.seed * 1000 + 700 + j),
                     "effects": [] if name == "none" else [name], "expect": expect, "flight": fl, "fresh": False})
    return jobs


def select_jobs(spec: ScenarioSet) -> list[dict[str, Any]]:
    """The jobs of the kinds in ``spec.kinds``, each the same flight as in a set of every kind."""
    return [j for j in make_jobs(spec) if j["kind"] in spec.kinds]


def job(spec: ScenarioSet, case: int) -> dict[str, Any]:
    """The job of one case number (KeyError naming it when the set has no such case)."""
    for j in make_jobs(spec):
        if j["case"] == case:
            return j
    raise KeyError(f"case {case}: the scenario set has cases 0-{spec.cases + spec.out_of_catalogue + spec.combined + spec.held_back - 1}")


def interleave(jobs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Jobs in round-robin over their kinds (single, outside, combined), each kind in its own order,
    so that any prefix of the run covers every kind (case numbers and seeds are unchanged)."""
    kinds: dict[str, list[dict[str, Any]]] = {}
    for j in jobs:
        kinds.setdefault(j["kind"], []).append(j)
    queues = list(kinds.values())
    n = [len(q) for q in queues]
    total = sum(n)
    out: list[dict[str, Any]] = []
    taken = [0] * len(queues)
    while len(out) < total:
        # the kind furthest behind its share of the run so far goes next
        k = min((i for i in range(len(queues)) if taken[i] < n[i]), key=lambda i: (taken[i] + 1) / n[i])
        out.append(queues[k][taken[k]])
        taken[k] += 1
    return out
