"""Service configuration: frozen dataclasses loaded from one TOML file.

``load_config(path)`` reads a TOML file whose tables mirror the dataclasses below
(``[service]``, ``[link]``, ``[live]``, ``[inputs]``, ``[zenoh]``, ``[rerun]``, ``[identification]``,
``[sim]``); every key is optional (defaults below) and an unknown table or key raises
:class:`ConfigError` naming the file and the key. Command-line options override fields with
:func:`dataclasses.replace` in the command modules. No environment variables, no globals.

This module only parses and validates; the service (:mod:`groundstation.service`) uses the values.
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from groundstation.cli import GroundstationError


class ConfigError(GroundstationError, ValueError):
    """A configuration file or value is wrong (one line naming the file and key)."""


@dataclass(frozen=True)
class ServiceSection:
    vehicle: str = "heli"
    record_dir: str = "recordings"
    status_rate_hz: float = 1.0
    queue_size: int = 256            # bounded queues between link reader, processing and sinks
    exit_after_flights: int = 0      # 0 = run until stopped


@dataclass(frozen=True)
class LinkSection:
    url: str = ""                    # empty = built-in simulated flight controller on a pty
    baud: int = 115200               # used for the built-in simulator's serial URL
    # MAVLink 2 signing (firmware_interface.signing): key file (chmod 600) or "" = unsigned link;
    # messages accepted unsigned (e.g. RADIO_STATUS from a radio); our link id in signatures
    signing_key_file: str = ""
    signing_accept_unsigned: tuple[str, ...] = ()
    signing_link_id: int = 0


@dataclass(frozen=True)
class LiveSection:
    grid_rate_hz: float = 50.0
    smoothing_passes: int = 1
    window_s: float = 4.0
    hop_s: float = 0.5
    stale_s: float = 0.5             # a stream silent this long (FC clock) stops holding the grid back
    in_air_alt_m: float = 0.3        # in-air from altitude when EXTENDED_SYS_STATE is absent


@dataclass(frozen=True)
class InputsSection:
    """Channel map (1-based servo numbers on SERVO_OUTPUT_RAW) and normalisation."""

    lat_servo: int = 1
    lon_servo: int = 2
    col_servo: int = 3
    ped_servo: int = 4
    # empty = automatic: 1500 until a model is identified, then the latest model's input_trim_pwm
    # (the median in-air PWM); four values (lat lon col ped) fix it
    trim_pwm: tuple[float, ...] = ()
    pwm_per_unit: float = 500.0


@dataclass(frozen=True)
class ZenohSection:
    enabled: bool = True
    config_file: str = ""            # json5 session config; empty = peer on loopback, scouting off
    listen_port: int = 0             # default peer listens on tcp/127.0.0.1:<port>; 0 = any free port
    window_queue: int = 8            # windows waiting for the publisher thread; more are dropped


@dataclass(frozen=True)
class RerunSection:
    mode: str = "off"                # off | spawn | connect | save
    target: str = ""                 # URL for connect, PATH.rrd for save


@dataclass(frozen=True)
class IdentificationSection:
    enabled: bool = True
    scope: str = "last"              # last | all (all flights so far of this aircraft)
    algorithm: str = "cabc"
    seed: int = 0
    maxiter: int = 0                 # 0 = the identifier's default
    restarts: int = 2                # independent searches, lowest refined cost wins (time between flights is cheap)
    refine: bool = True
    diagnose: bool = True
    plots: bool = True


@dataclass(frozen=True)
class SimSection:
    speed: float = 1.0
    flights: int = 2
    seed: int = 0
    effects: tuple[str, ...] = ()


@dataclass(frozen=True)
class ServiceConfig:
    service: ServiceSection = field(default_factory=ServiceSection)
    link: LinkSection = field(default_factory=LinkSection)
    live: LiveSection = field(default_factory=LiveSection)
    inputs: InputsSection = field(default_factory=InputsSection)
    zenoh: ZenohSection = field(default_factory=ZenohSection)
    rerun: RerunSection = field(default_factory=RerunSection)
    identification: IdentificationSection = field(default_factory=IdentificationSection)
    sim: SimSection = field(default_factory=SimSection)

    def __post_init__(self) -> None:
        validate(self)

    def replace(self, section: str, **changes: Any) -> ServiceConfig:
        """A copy with fields of one section changed (validated)."""
        sec = getattr(self, section)
        return dataclasses.replace(self, **{section: dataclasses.replace(sec, **changes)})


def validate(cfg: ServiceConfig, where: str = "config") -> None:
    """Raise :class:`ConfigError` for values out of range."""
    def bad(key: str, value: Any, why: str) -> ConfigError:
        return ConfigError(f"{where}: {key} = {value!r}: {why}")

    lv = cfg.live
    if not lv.grid_rate_hz > 0:
        raise bad("live.grid_rate_hz", lv.grid_rate_hz, "must be > 0")
    if lv.smoothing_passes < 0:
        raise bad("live.smoothing_passes", lv.smoothing_passes, "must be >= 0")
    if not lv.window_s * lv.grid_rate_hz >= 5:
        raise bad("live.window_s", lv.window_s, "must hold at least 5 grid samples")
    if not 0 < lv.hop_s <= lv.window_s:
        raise bad("live.hop_s", lv.hop_s, "must be in (0, window_s]")
    if not lv.stale_s > 0:
        raise bad("live.stale_s", lv.stale_s, "must be > 0")
    if not cfg.service.vehicle or "/" in cfg.service.vehicle or any(c in cfg.service.vehicle for c in "*$?#"):
        raise bad("service.vehicle", cfg.service.vehicle, "must be a non-empty zenoh key chunk (no / * $ ? #)")
    if not cfg.service.status_rate_hz > 0:
        raise bad("service.status_rate_hz", cfg.service.status_rate_hz, "must be > 0")
    if cfg.service.queue_size < 1:
        raise bad("service.queue_size", cfg.service.queue_size, "must be >= 1")
    if cfg.rerun.mode not in ("off", "spawn", "connect", "save"):
        raise bad("rerun.mode", cfg.rerun.mode, "must be off, spawn, connect or save")
    if cfg.rerun.mode == "save" and not cfg.rerun.target:
        raise bad("rerun.target", cfg.rerun.target, "save needs a PATH.rrd")
    if cfg.identification.scope not in ("last", "all"):
        raise bad("identification.scope", cfg.identification.scope, "must be last or all")
    if cfg.identification.restarts < 1:
        raise bad("identification.restarts", cfg.identification.restarts, "must be >= 1")
    if not cfg.sim.speed > 0:
        raise bad("sim.speed", cfg.sim.speed, "must be > 0")
    if cfg.sim.flights < 1:
        raise bad("sim.flights", cfg.sim.flights, "must be >= 1")
    servos = (cfg.inputs.lat_servo, cfg.inputs.lon_servo, cfg.inputs.col_servo, cfg.inputs.ped_servo)
    if any(not 1 <= s <= 16 for s in servos):
        raise bad("inputs.*_servo", servos, "servo numbers must be 1..16")
    if len(cfg.inputs.trim_pwm) not in (0, 4):
        raise bad("inputs.trim_pwm", cfg.inputs.trim_pwm, "needs 4 values (lat lon col ped) or [] for automatic")
    if not cfg.inputs.pwm_per_unit > 0:
        raise bad("inputs.pwm_per_unit", cfg.inputs.pwm_per_unit, "must be > 0")
    if not 0 <= cfg.zenoh.listen_port <= 65535:
        raise bad("zenoh.listen_port", cfg.zenoh.listen_port, "must be 0..65535")
    if cfg.zenoh.window_queue < 1:
        raise bad("zenoh.window_queue", cfg.zenoh.window_queue, "must be >= 1")


_SECTIONS: dict[str, type] = {f.name: f.default_factory for f in dataclasses.fields(ServiceConfig)}  # type: ignore[misc]


def _coerce(where: str, key: str, value: Any, default: Any) -> Any:
    """Check a TOML value against the type of the dataclass default."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: {key} = {value!r}: expected true/false")
        return value
    if isinstance(default, int) and not isinstance(default, bool):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: {key} = {value!r}: expected an integer")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{where}: {key} = {value!r}: expected a number")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"{where}: {key} = {value!r}: expected a string")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, list):
            raise ConfigError(f"{where}: {key} = {value!r}: expected an array")
        if key.endswith("trim_pwm") or (default and isinstance(default[0], float)):
            if any(isinstance(v, bool) or not isinstance(v, int | float) for v in value):
                raise ConfigError(f"{where}: {key} = {value!r}: expected numbers")
            return tuple(float(v) for v in value)
        if any(not isinstance(v, str) for v in value):
            raise ConfigError(f"{where}: {key} = {value!r}: expected strings")
        return tuple(value)
    return value


def config_from_dict(data: dict[str, Any], where: str = "config") -> ServiceConfig:
    """Build a :class:`ServiceConfig` from parsed TOML; unknown tables/keys raise ConfigError."""
    sections: dict[str, Any] = {}
    for name, table in data.items():
        if name not in _SECTIONS:
            raise ConfigError(f"{where}: unknown table [{name}] (known: {', '.join(_SECTIONS)})")
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: {name} must be a table [{name}]")
        default = _SECTIONS[name]()
        known = {f.name for f in dataclasses.fields(default)}
        values: dict[str, Any] = {}
        for key, value in table.items():
            if key not in known:
                raise ConfigError(f"{where}: unknown key {name}.{key} (known: {', '.join(sorted(known))})")
            values[key] = _coerce(where, f"{name}.{key}", value, getattr(default, key))
        sections[name] = dataclasses.replace(default, **values)
    cfg = ServiceConfig.__new__(ServiceConfig)
    for f in dataclasses.fields(ServiceConfig):
        object.__setattr__(cfg, f.name, sections.get(f.name, _SECTIONS[f.name]()))
    validate(cfg, where)
    return cfg


def load_config(path: str | os.PathLike[str] | None) -> ServiceConfig:
    """Read the service TOML (``None`` = all defaults)."""
    if path is None:
        return ServiceConfig()
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config: {exc.strerror or exc}") from None
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    return config_from_dict(data, str(p))
