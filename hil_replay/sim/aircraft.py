"""Aircraft description for the simulator: the 31 eq.-8 parameters plus physical data, from TOML.

:class:`Aircraft` is a frozen dataclass; :func:`load_aircraft` reads and validates a TOML file (any
problem raises ``ValueError`` naming the file, the key and what is allowed) and
:func:`resolve_aircraft` turns ``None`` / a name / a path / an ``Aircraft`` into an ``Aircraft``.
The parameter names are the paper's (listed in docs/model-file.md) and match
``groundstation.sysid.model.PARAM_NAMES``; this module does not import that package (the simulator
is the independent truth) and keeps its own copy of the list.

Leaves to others: the dynamics (``dynamics.py``) and everything downstream.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

#: The 31 free eq.-8 parameters, in the order of the sysid model vector.
PARAM_NAMES: tuple[str, ...] = (
    "X_u", "Y_v", "M_u", "M_v", "M_q", "M_a", "M_b", "L_u", "L_v", "L_p", "L_a", "L_b", "k1", "inv_tau_s",
    "X_lat", "Y_lon", "M_lat", "M_lon", "L_lat", "L_lon", "A_lat", "B_lon",
    "Z_w", "Z_r", "N_w", "N_r", "k_r", "Z_col", "Z_ped", "N_col", "N_ped",
)
INPUTS: tuple[str, ...] = ("lat", "lon", "col", "ped")
AIRCRAFT_DIR = Path(__file__).resolve().parent.parent / "aircraft"
DEFAULT_AIRCRAFT = "trex600"

_TOP_KEYS = {"name", "mass_kg", "rotor_diameter_m", "rotor_rpm", "hub_height_m", "inertia_kg_m2",
             "pwm_per_unit", "trim_pwm", "servo", "battery", "parameters"}


@dataclass(frozen=True)
class Aircraft:
    """One helicopter: eq.-8 parameters (SI, per normalised input unit) and physical data."""

    name: str
    parameters: Mapping[str, float]
    mass_kg: float = 4.6
    rotor_diameter_m: float = 1.35
    rotor_rpm: float = 1350.0
    hub_height_m: float = 0.42
    inertia_kg_m2: tuple[float, float, float] = (0.11, 0.27, 0.21)
    pwm_per_unit: float = 500.0
    trim_pwm: Mapping[str, int] = field(default_factory=lambda: {"lat": 1500, "lon": 1500, "col": 1580, "ped": 1470})
    servo: Mapping[str, int] = field(default_factory=lambda: {"lat": 1, "lon": 2, "col": 3, "ped": 4})
    battery_cells: int = 6
    battery_capacity_mah: float = 5000.0
    hover_current_a: float = 32.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "parameters", MappingProxyType(dict(self.parameters)))
        object.__setattr__(self, "trim_pwm", MappingProxyType(dict(self.trim_pwm)))
        object.__setattr__(self, "servo", MappingProxyType(dict(self.servo)))
        _validate(self, str(self.name))

    @property
    def rotor_radius_m(self) -> float:
        return 0.5 * self.rotor_diameter_m

    @property
    def rotor_hz(self) -> float:
        return self.rotor_rpm / 60.0

    def with_trim(self, trim_pwm: Mapping[str, int]) -> Aircraft:
        """Copy with other input trims (used for the per-seed trim randomisation)."""
        kw = {f: getattr(self, f) for f in self.__dataclass_fields__}
        kw["trim_pwm"] = dict(trim_pwm)
        return Aircraft(**kw)


def _validate(ac: Aircraft, where: str) -> None:
    p = ac.parameters
    missing = [n for n in PARAM_NAMES if n not in p]
    if missing:
        raise ValueError(f"{where}: [parameters] missing {missing}; required: {list(PARAM_NAMES)}")
    unknown = sorted(set(p) - set(PARAM_NAMES))
    if unknown:
        raise ValueError(f"{where}: [parameters] unknown key(s) {unknown}; allowed: {list(PARAM_NAMES)}")
    for n in PARAM_NAMES:
        v = p[n]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"{where}: parameters.{n} = {v!r} is not a finite number")
    if not p["inv_tau_s"] > 0:
        raise ValueError(f"{where}: parameters.inv_tau_s = {p['inv_tau_s']} must be > 0 (1/tau_s, 1/s)")
    if not p["N_r"] < 0:
        raise ValueError(f"{where}: parameters.N_r = {p['N_r']} must be < 0 (k_fb = -2 N_r > 0: a stable yaw gyro)")
    positive = {"mass_kg": ac.mass_kg, "rotor_diameter_m": ac.rotor_diameter_m, "rotor_rpm": ac.rotor_rpm,
                "pwm_per_unit": ac.pwm_per_unit, "battery_capacity_mah": ac.battery_capacity_mah}
    for k, v in positive.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
            raise ValueError(f"{where}: {k} = {v!r} must be a positive number")
    if not (isinstance(ac.hub_height_m, (int, float)) and 0 <= ac.hub_height_m < 5):
        raise ValueError(f"{where}: hub_height_m = {ac.hub_height_m!r} must be in [0, 5) m")
    if len(ac.inertia_kg_m2) != 3 or not all(isinstance(v, (int, float)) and v > 0 for v in ac.inertia_kg_m2):
        raise ValueError(f"{where}: inertia_kg_m2 must have positive xx, yy, zz")
    for table, allowed in (("trim_pwm", ac.trim_pwm), ("servo", ac.servo)):
        if set(allowed) != set(INPUTS):
            raise ValueError(f"{where}: [{table}] keys {sorted(allowed)}; required exactly {list(INPUTS)}")
    for k, v in ac.trim_pwm.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 1000 <= v <= 2000:
            raise ValueError(f"{where}: trim_pwm.{k} = {v!r} must be a PWM in [1000, 2000] us")
    for k, v in ac.servo.items():
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 8:
            raise ValueError(f"{where}: servo.{k} = {v!r} must be an integer servo index in 1..8")
    if len(set(ac.servo.values())) != 4:
        raise ValueError(f"{where}: [servo] maps two inputs to the same servo: {dict(ac.servo)}")


def load_aircraft(path: str | Path) -> Aircraft:
    """Read an aircraft TOML file; ``ValueError`` names the file and the bad key."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: malformed TOML: {exc}") from exc
    return aircraft_from_dict(data, where=str(path))


def aircraft_from_dict(data: Mapping[str, Any], *, where: str = "aircraft") -> Aircraft:
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(_TOP_KEYS)}")
    if "parameters" not in data or not isinstance(data["parameters"], Mapping):
        raise ValueError(f"{where}: missing table [parameters] with the 31 eq.-8 parameters {list(PARAM_NAMES)}")
    kw: dict[str, Any] = {"name": str(data.get("name", Path(where).stem)), "parameters": dict(data["parameters"])}
    for k in ("mass_kg", "rotor_diameter_m", "rotor_rpm", "hub_height_m", "pwm_per_unit"):
        if k in data:
            kw[k] = data[k]
    if "inertia_kg_m2" in data:
        ine = data["inertia_kg_m2"]
        if not isinstance(ine, Mapping) or set(ine) != {"xx", "yy", "zz"}:
            raise ValueError(f"{where}: inertia_kg_m2 must be a table with keys xx, yy, zz")
        kw["inertia_kg_m2"] = (ine["xx"], ine["yy"], ine["zz"])
    for table in ("trim_pwm", "servo"):
        if table in data:
            if not isinstance(data[table], Mapping):
                raise ValueError(f"{where}: [{table}] must be a table with keys {list(INPUTS)}")
            kw[table] = dict(data[table])
    if "battery" in data:
        b = data["battery"]
        allowed = {"cells", "capacity_mah", "hover_current_a"}
        if not isinstance(b, Mapping) or set(b) - allowed:
            raise ValueError(f"{where}: [battery] allowed keys {sorted(allowed)}")
        kw.update({"battery_cells": int(b.get("cells", 6)), "battery_capacity_mah": b.get("capacity_mah", 5000.0),
                   "hover_current_a": b.get("hover_current_a", 32.0)})
    try:
        return Aircraft(**kw)
    except ValueError as exc:  # name the file, not the aircraft
        msg = str(exc)
        prefix = f"{kw['name']}: "
        raise ValueError(f"{where}: {msg[len(prefix):] if msg.startswith(prefix) else msg}") from None
    except TypeError as exc:
        raise ValueError(f"{where}: {exc}") from None


def resolve_aircraft(aircraft: Aircraft | str | Path | None) -> Aircraft:
    """``None`` -> the default TREX-600; a bare name -> ``hil_replay/aircraft/NAME.toml``; else a path."""
    if isinstance(aircraft, Aircraft):
        return aircraft
    if aircraft is None:
        aircraft = DEFAULT_AIRCRAFT
    s = str(aircraft)
    if not s.endswith(".toml") and "/" not in s:
        path = AIRCRAFT_DIR / f"{s}.toml"
        if not path.exists():
            names = sorted(p.stem for p in AIRCRAFT_DIR.glob("*.toml"))
            raise ValueError(f"aircraft: unknown name {s!r}; allowed: {names} or a path to a .toml file")
        return load_aircraft(path)
    return load_aircraft(s)
