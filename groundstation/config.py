"""One configuration model: a tree of frozen dataclasses, loaded once from one TOML file.

:class:`ServiceConfig` holds the domain configurations themselves as sections, so a value exists
once and every command reads the same file (``--config FILE.toml``)::

    [service] [link] [zenoh] [rerun] [sim]   the live service (ServiceSection, LinkSection, ...)
    [prepare]                                  dsp.prepare.PrepConfig: channel map, trims, pwm_per_unit,
                                               in-air height -- used by identification AND the live path
    [live]                                     dsp.live.LiveConfig: grid, smoothing, windows
    [identify]                                 sysid.identify.IdentifyConfig
    [bounds]                                   search bounds, NAME = [low, high] (paper parameter names)
    [diagnose]                                 gap.config.DiagnoseConfig
    [freq]                                     freq.spectra.FreqConfig (``validate --freq``)
    [excitation]                               dsp.excitation.ExcitationConfig (live excitation monitor)
    [identification]                           what the service does between flights (and the
                                               defaults of ``groundstation identify``'s options)

Every key is optional (the dataclass defaults); an unknown table or key, a value of the wrong type or
out of range raises :class:`ConfigError` with one line naming the file and the key. A field some other
section decides (the live path's channel map comes from ``[prepare]``) is listed in the parent's
``CONFIG_DERIVED`` and rejected with a pointer to where it is set.

:func:`load_toml` is generic: it builds any dataclass tree from a TOML file from the field types
(``bool int float str``, ``tuple[...]``, ``X | None``, ``dict[str, ...]``, nested dataclasses), so
a new section is one more dataclass field. Command-line options override fields with
:meth:`ServiceConfig.replace`. No environment variables, no globals. This module only parses and
validates; the service and the commands use the values.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import os
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from groundstation.dsp.excitation import ExcitationConfig
from groundstation.dsp.live import LiveConfig
from groundstation.dsp.prepare import PrepConfig
from groundstation.errors import GroundstationError
from groundstation.freq.settings import FreqIdentifyConfig
from groundstation.freq.spectra import FreqConfig
from groundstation.gap.config import DiagnoseConfig
from groundstation.sysid.model import PARAM_NAMES
from groundstation.sysid.settings import IdentifyConfig
from groundstation.trends.settings import TrendConfig


class ConfigError(GroundstationError, ValueError):
    """A configuration file or value is wrong (one line naming the file and key)."""


@dataclass(frozen=True)
class ServiceSection:
    vehicle: str = "heli"
    record_dir: str = "recordings"
    status_rate_hz: float = 1.0
    exit_after_flights: int = 0      # 0 = run until stopped
    #: campaign table (SQLite) in the recording directory: every identified flight is a row and the
    #: trend summary over the vehicle's flights is published on heli/{vehicle}/trends; "" = off
    campaign_db: str = "campaign.sqlite"
    #: CPU priority (nice, 0-19) of the process that identifies and diagnoses each flight: 19 keeps the
    #: link and the live path ahead of it on a busy laptop; 0 gives it a fair share of the cores
    worker_nice: int = 19


@dataclass(frozen=True)
class LinkSection:
    url: str = ""                    # empty = built-in simulated flight controller on a pty
    baud: int = 115200               # used for the built-in simulator's serial URL
    #: what carries the link: "usb" (a cable: fast, loss-free), "radio" (a telemetry radio or network: slow,
    #: lossy) or "auto" (from the port: USB CDC-ACM such as /dev/ttyACM0 and virtual ports are usb, any other
    #: serial port, udp and tcp are radio). Decides whether the service fetches a lossy flight's onboard log to
    #: analyse it instead of the telemetry ([onboard_logs] analyse)
    kind: str = "auto"
    # MAVLink 2 signing (firmware_interface.signing): key file (chmod 600) or "" = unsigned link;
    # messages accepted unsigned (e.g. RADIO_STATUS from a radio); our link id in signatures
    signing_key_file: str = ""
    signing_accept_unsigned: tuple[str, ...] = ()
    signing_link_id: int = 0


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
    raw: bool = False                # also log the raw (unsmoothed) outputs beside the smoothed ones


@dataclass(frozen=True)
class IdentificationSection:
    """Identification between flights (the service) and the defaults of ``groundstation identify``."""

    enabled: bool = True
    scope: str = "last"              # last | all (all flights so far of this aircraft)
    algorithm: str = "cabc"
    seed: int = 0
    refine: bool = True
    diagnose: bool = True
    plots: bool = True
    #: held-out check after the fit: refit on k-1 contiguous blocks of the in-air time and predict the
    #: left-out one, for each block (``usable``, ``closed_loop`` in the model file); 0 = skip
    heldout_folds: int = 5
    #: aircraft file (TOML) applied between flights: its channel map and outputs prepare each flight,
    #: its ``[identify]`` settings and prior model identify it; "" = none
    aircraft: str = ""


@dataclass(frozen=True)
class OnboardLogsSection:
    """``[onboard_logs]``: download each flight's onboard log over the link while disarmed between flights."""

    download: bool = False
    dir: str = ""                   # default: <record_dir>/onboard
    after_disarm_s: float = 2.0     # let the FC close its log before listing
    give_up_s: float = 8.0          # the FC sends nothing this long: keep what came, resume after the next disarm
    list_timeout_s: float = 1.5     # no answer to a list request this long: ask again
    list_retries: int = 3           # asked again this many times before the FC is taken for one without logs
    #: a flight whose telemetry lost more than this share of packets (%) gets one line at disarm saying
    #: that the FC's onboard log holds the full data (and how to fetch it when ``download`` is off)
    suggest_above_loss_pct: float = 5.0
    #: such a flight's onboard log is downloaded and analysed instead of its telemetry (the telemetry's
    #: results stay published until the onboard log's are ready): "usb" only over a USB link ([link] kind),
    #: "always" also over a slow radio, "off" never
    analyse: str = "usb"
    #: every block read a second time and kept when two copies agree: "noisy" once the link corrupts a
    #: frame during the download, "always" on any link (twice the time)
    confirm: str = "noisy"


@dataclass(frozen=True)
class SimSection:
    speed: float = 1.0
    flights: int = 2
    seed: int = 0
    effects: tuple[str, ...] = ()


#: live-path fields taken from [prepare]: one channel map, one trim, one in-air height
_LIVE_FROM_PREPARE = {"servo_numbers": "input_channels", "trim_pwm": "input_trim_pwm",
                      "pwm_per_unit": "pwm_per_unit", "in_air_alt_m": "in_air_alt_m"}
_AUTO_TRIM_PWM: tuple[float, float, float, float] = (1500.0, 1500.0, 1500.0, 1500.0)   # live inputs until a model's trim is known


@dataclass(frozen=True)
class ServiceConfig:
    service: ServiceSection = field(default_factory=ServiceSection)
    link: LinkSection = field(default_factory=LinkSection)
    prepare: PrepConfig = field(default_factory=PrepConfig)
    live: LiveConfig = field(default_factory=LiveConfig)
    identify: IdentifyConfig = field(default_factory=IdentifyConfig)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    diagnose: DiagnoseConfig = field(default_factory=DiagnoseConfig)
    freq: FreqConfig = field(default_factory=FreqConfig)
    freq_identify: FreqIdentifyConfig = field(default_factory=FreqIdentifyConfig)
    trends: TrendConfig = field(default_factory=TrendConfig)
    excitation: ExcitationConfig = field(default_factory=ExcitationConfig)
    identification: IdentificationSection = field(default_factory=IdentificationSection)
    zenoh: ZenohSection = field(default_factory=ZenohSection)
    rerun: RerunSection = field(default_factory=RerunSection)
    sim: SimSection = field(default_factory=SimSection)
    onboard_logs: OnboardLogsSection = field(default_factory=OnboardLogsSection)

    #: keys set elsewhere: "section.key" -> where the value comes from (rejected in a file)
    CONFIG_DERIVED: typing.ClassVar[dict[str, str]] = {
        **{f"live.{k}": f"prepare.{v}" for k, v in _LIVE_FROM_PREPARE.items()},
        "diagnose.identify_restarts": "identify.search_restarts",
    }

    def __post_init__(self) -> None:
        prep = self.prepare
        live = dataclasses.replace(
            self.live, servo_numbers=prep.input_channels,
            trim_pwm=prep.input_trim_pwm if prep.input_trim_pwm is not None else _AUTO_TRIM_PWM,
            pwm_per_unit=prep.pwm_per_unit, in_air_alt_m=prep.in_air_alt_m)
        object.__setattr__(self, "live", live)
        if self.diagnose.identify_restarts != self.identify.search_restarts:
            object.__setattr__(self, "diagnose", dataclasses.replace(
                self.diagnose, identify_restarts=self.identify.search_restarts))
        validate(self)

    def replace(self, section: str, **changes: Any) -> ServiceConfig:
        """A copy with fields of one section changed (validated)."""
        sec = getattr(self, section)
        new: Any = {**sec, **changes} if isinstance(sec, dict) else dataclasses.replace(sec, **changes)
        return dataclasses.replace(self, **{section: new})


def validate(cfg: ServiceConfig, where: str = "config") -> None:
    """Raise :class:`ConfigError` for values out of range."""
    def bad(key: str, value: Any, why: str) -> ConfigError:
        return ConfigError(f"{where}: {key} = {value!r}: {why}")

    lv = cfg.live
    checks: list[tuple[bool, str, Any, str]] = [
        (lv.grid_rate_hz > 0, "live.grid_rate_hz", lv.grid_rate_hz, "must be > 0"),
        (lv.smoothing_passes >= 0, "live.smoothing_passes", lv.smoothing_passes, "must be >= 0"),
        (lv.window_s * lv.grid_rate_hz >= 5, "live.window_s", lv.window_s, "must hold at least 5 grid samples"),
        (0 < lv.hop_s <= lv.window_s, "live.hop_s", lv.hop_s, "must be in (0, window_s]"),
        (lv.stale_s > 0, "live.stale_s", lv.stale_s, "must be > 0"),
        (bool(cfg.service.vehicle) and not any(c in cfg.service.vehicle for c in "/*$?#"), "service.vehicle",
         cfg.service.vehicle, "must be a non-empty zenoh key chunk (no / * $ ? #)"),
        (cfg.service.status_rate_hz > 0, "service.status_rate_hz", cfg.service.status_rate_hz, "must be > 0"),
        (cfg.rerun.mode in ("off", "spawn", "connect", "save"), "rerun.mode", cfg.rerun.mode,
         "must be off, spawn, connect or save"),
        (cfg.link.kind in ("auto", "usb", "radio"), "link.kind", cfg.link.kind, "must be auto, usb or radio"),
        (cfg.onboard_logs.analyse in ("off", "usb", "always"), "onboard_logs.analyse", cfg.onboard_logs.analyse,
         "must be off, usb or always"),
        (cfg.onboard_logs.confirm in ("noisy", "always"), "onboard_logs.confirm", cfg.onboard_logs.confirm,
         "must be noisy or always"),
        (cfg.rerun.mode != "save" or bool(cfg.rerun.target), "rerun.target", cfg.rerun.target, "save needs a PATH.rrd"),
        (cfg.identification.scope in ("last", "all"), "identification.scope", cfg.identification.scope,
         "must be last or all"),
        (cfg.identification.algorithm in ("cabc", "abc", "ga", "de"), "identification.algorithm",
         cfg.identification.algorithm, "must be cabc, abc, ga or de"),
        (cfg.identification.heldout_folds == 0 or cfg.identification.heldout_folds >= 2,
         "identification.heldout_folds", cfg.identification.heldout_folds, "must be 0 (skip) or >= 2"),
        (cfg.identify.search_restarts >= 1, "identify.search_restarts", cfg.identify.search_restarts, "must be >= 1"),
        (cfg.identify.heldout_window_s > 0, "identify.heldout_window_s", cfg.identify.heldout_window_s, "must be > 0"),
        (cfg.identify.runaway_factor > 0, "identify.runaway_factor", cfg.identify.runaway_factor, "must be > 0"),
        (cfg.sim.speed > 0, "sim.speed", cfg.sim.speed, "must be > 0"),
        (cfg.sim.flights >= 1, "sim.flights", cfg.sim.flights, "must be >= 1"),
        (all(1 <= s <= 16 for s in cfg.prepare.input_channels), "prepare.input_channels",
         cfg.prepare.input_channels, "channel numbers must be 1..16"),
        (cfg.prepare.input_trim_pwm is None or len(cfg.prepare.input_trim_pwm) == 4, "prepare.input_trim_pwm",
         cfg.prepare.input_trim_pwm, "needs 4 values (lat lon col ped) or [] for automatic"),
        (cfg.prepare.pwm_per_unit > 0, "prepare.pwm_per_unit", cfg.prepare.pwm_per_unit, "must be > 0"),
        (0 <= cfg.zenoh.listen_port <= 65535, "zenoh.listen_port", cfg.zenoh.listen_port, "must be 0..65535"),
        (cfg.zenoh.window_queue >= 1, "zenoh.window_queue", cfg.zenoh.window_queue, "must be >= 1"),
    ]
    for ok, key, value, why in checks:
        if not ok:
            raise bad(key, value, why)
    for name, (low, high) in cfg.bounds.items():
        if name not in PARAM_NAMES:
            raise bad(f"bounds.{name}", [low, high], "unknown parameter (see the model file's parameter names)")
        if not low < high:
            raise bad(f"bounds.{name}", [low, high], "needs low < high")


# ------------------------------------------------------------------ generic TOML -> dataclass tree

T = TypeVar("T")


def _type_name(tp: Any) -> str:
    return {bool: "true/false", int: "an integer", float: "a number", str: "a string"}.get(tp, str(tp))


def _convert(tp: Any, value: Any, where: str, key: str) -> Any:
    """``value`` (parsed TOML) as type ``tp``; ConfigError naming ``where`` and ``key`` otherwise."""
    def wrong(expected: str) -> ConfigError:
        return ConfigError(f"{where}: {key} = {value!r}: expected {expected}")

    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1 and typing.get_origin(inner[0]) is tuple and value == []:
            return None                                  # [] = "not set" for an optional array
        return _convert(inner[0], value, where, key) if len(inner) == 1 else value
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, dict):
            raise wrong(f"a table [{key}]")
        return _from_dict(tp, value, where, f"{key}.")
    if origin is tuple:
        if not isinstance(value, list):
            raise wrong("an array")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, where, key) for v in value)
        if len(value) != len(args):
            raise wrong(f"an array of {len(args)} values")
        return tuple(_convert(a, v, where, key) for a, v in zip(args, value, strict=True))
    if origin is dict:
        if not isinstance(value, dict):
            raise wrong(f"a table [{key}]")
        return {str(k): _convert(args[1], v, where, f"{key}.{k}") for k, v in value.items()}
    if tp is bool:
        if not isinstance(value, bool):
            raise wrong(_type_name(bool))
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise wrong(_type_name(int))
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise wrong(_type_name(float))
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise wrong(_type_name(str))
        return value
    return value


#: keys and tables of earlier releases -> what replaced them (an old file gets told where its setting went)
RENAMED: dict[str, str] = {
    "identification.restarts": "[identify] search_restarts",
    "identification.maxiter": "[identify] maxiter",
    "inputs": "[prepare] (input_channels, input_trim_pwm, pwm_per_unit)",
    "inputs.lat_servo": "[prepare] input_channels (lat lon col ped)",
    "inputs.lon_servo": "[prepare] input_channels (lat lon col ped)",
    "inputs.col_servo": "[prepare] input_channels (lat lon col ped)",
    "inputs.ped_servo": "[prepare] input_channels (lat lon col ped)",
    "inputs.trim_pwm": "[prepare] input_trim_pwm",
    "inputs.pwm_per_unit": "[prepare] pwm_per_unit",
}


def _from_dict(cls: type[T], data: dict[str, Any], where: str, prefix: str = "") -> T:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    derived: dict[str, str] = getattr(cls, "CONFIG_DERIVED", {})
    values: dict[str, Any] = {}
    for key, value in data.items():
        if key not in fields:
            kind = "table" if isinstance(value, dict) else "key"
            shown = f"[{prefix}{key}]" if kind == "table" else f"{prefix}{key}"
            if cls is ServiceConfig and kind == "table" and key in RENAMED:
                old = next((f"{key}.{k}" for k in value if f"{key}.{k}" in RENAMED), key)
                raise ConfigError(f"{where}: [{key}] is no longer read: {old} is now {RENAMED[old]}")
            if f"{prefix}{key}" in RENAMED:
                raise ConfigError(f"{where}: {shown} was renamed: it is now {RENAMED[f'{prefix}{key}']}")
            raise ConfigError(f"{where}: unknown {kind} {shown} (known: {', '.join(fields)})")
        if isinstance(value, dict):
            for sub in value:
                if f"{key}.{sub}" in derived:
                    raise ConfigError(f"{where}: {prefix}{key}.{sub} is not set here: it is "
                                      f"{derived[f'{key}.{sub}']} (one value for the whole configuration)")
        values[key] = _convert(hints[key], value, where, f"{prefix}{key}")
    try:
        return cls(**values)
    except (TypeError, ValueError) as exc:     # the dataclass's own checks (validate() says "config:")
        raise ConfigError(f"{where}: {str(exc).splitlines()[0].removeprefix('config: ')}") from None


def from_dict(cls: type[T], data: dict[str, Any], where: str = "config") -> T:
    """Build dataclass ``cls`` (and its nested dataclass fields) from parsed TOML ``data``."""
    return _from_dict(cls, data, where)


def load_toml(path: str | os.PathLike[str], cls: type[T]) -> T:
    """Read the TOML file ``path`` into the dataclass tree ``cls`` (errors name the file and key)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config: {exc.strerror or exc}") from None
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    return from_dict(cls, data, str(p))


def config_from_dict(data: dict[str, Any], where: str = "config") -> ServiceConfig:
    """A :class:`ServiceConfig` from parsed TOML; unknown tables/keys raise ConfigError."""
    return from_dict(ServiceConfig, data, where)


def load_config(path: str | os.PathLike[str] | None) -> ServiceConfig:
    """Read the configuration TOML (``None`` = all defaults)."""
    if path is None:
        return ServiceConfig()
    return load_toml(path, ServiceConfig)


# ------------------------------------------------------------------ every key, from the dataclasses


def _field_comments(cls: type) -> dict[str, str]:
    """field name -> its comment in the source (``#:`` lines above it, or a trailing ``# ...``)."""
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return {}
    out: dict[str, str] = {}
    above: list[str] = []
    for line in lines[1:]:
        s = line.strip()
        if s.startswith("#:"):
            above.append(s[2:].strip())
            continue
        head = s.split("#", 1)[0]
        name = head.split(":", 1)[0].strip()
        if ":" in head and name.isidentifier() and not s.startswith(("def ", "@", "return", "if ")):
            trailing = s.split("#", 1)[1].strip() if "#" in s and "=" in head else ""
            out.setdefault(name, " ".join(above) or trailing)
        if s.startswith("def "):
            break
        above = []
    return out


def toml_value(v: Any) -> str | None:
    """``v`` written as TOML (None: TOML has no null, the key is left out)."""
    if v is None:
        return None
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (tuple, list)):
        items = [toml_value(x) for x in v]
        return "[" + ", ".join(x for x in items if x is not None) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + "}"
    return json.dumps(str(v))


def reference(cfg: ServiceConfig | None = None) -> list[tuple[str, str, str, str]]:
    """Every key a configuration file can set: (table, key, default as TOML or "" for none, meaning).
    Derived keys (set in another table) are left out."""
    cfg = cfg or ServiceConfig()
    rows = []
    for sec in dataclasses.fields(cfg):
        value = getattr(cfg, sec.name)
        if not dataclasses.is_dataclass(value):
            continue
        notes = _field_comments(type(value))
        for f in dataclasses.fields(value):
            if not f.init or f"{sec.name}.{f.name}" in ServiceConfig.CONFIG_DERIVED:
                continue
            rows.append((sec.name, f.name, toml_value(getattr(value, f.name)) or "", notes.get(f.name, "")))
    return rows


def reference_markdown(cfg: ServiceConfig | None = None) -> str:
    """The table of every key (docs/configuration.md carries it; ``python -m groundstation.config`` prints it)."""
    out = ["| key | default | meaning |", "|---|---|---|"]
    for table, key, default, note in reference(cfg):
        shown = f"`{default}`" if default else "(none)"
        out.append(f"| `{table}.{key}` | {shown} | {note.replace('|', '/')} |")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    print(reference_markdown(), end="")
