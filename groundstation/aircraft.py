"""The aircraft file: one TOML per aircraft with its inputs, outputs and prior model.

``parse_aircraft(doc, name)`` turns an already-parsed TOML document into a frozen
:class:`Aircraft`; ``load_aircraft(path)`` reads the file. Layout (every table optional)::

    name = "trex550"
    [inputs]
    source = "SERVO_OUTPUT_RAW"   # or "RC_CHANNELS" (the pilot's sticks) or "SWASHPLATE" (3-servo unmix)
    kind = "blade"                # or "rate_command" / "attitude_command" (sticks to a stabilised aircraft) or
                                  # "unknown"; default from the source: RC channels unknown, the others blade
    lat = 1                       # 1-based channel numbers of the source message
    lon = 2
    col = 3
    ped = 4
    units = "pwm"                 # or "normalised" (the log holds -1..1 values)
    pwm_per_unit = 500.0
    trim = { col = 1560 }         # optional fixed trims; the others: median in-air value
    swash_servos = [1, 2, 3]      # SWASHPLATE only: the three swashplate servos ...
    swash_phase_deg = [0, 120, 240]   # ... and their positions around the swashplate (0 = front)
    shift_s = 0.06                # the logged inputs are late against the outputs by this much: advanced by it
    [outputs]
    measured = ["u", "v", "w", "p", "q", "r", "theta", "phi"]
    [identify]                    # optional IdentifyConfig overrides for this aircraft's flights
    window_s = 5.0
    [prior]
    source = "paper Table 5 scaled"   # free text: where the numbers come from
    L_b = [80.0, 40.0]            # NAME = [nominal, std], the paper's parameter names
    inv_tau_s = [8.0, 4.0]        # 1/tau_s, positive (the matrix entry is -inv_tau_s)

Parameters the prior does not list get :data:`WIDE_PRIOR` (physically signed where physics fixes
the sign, otherwise centred on zero, with standard deviations as wide as small helicopters range).
Bad input raises :class:`AircraftError` with one line naming the file, the key and the value.
Pure: no file reading except in :func:`load_aircraft`.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.dsp.prepare import INPUTS, PrepConfig
from groundstation.errors import GroundstationError
from groundstation.sysid.identify import IdentifyConfig
from groundstation.sysid.model import OUTPUTS, PARAM_NAMES, bounds_array

INPUT_SOURCES = ("SERVO_OUTPUT_RAW", "RC_CHANNELS", "SWASHPLATE")
#: constrained entries of eq. 8 that are not parameters, and what to give instead
CONSTRAINED = {"N_fb": "N_fb = -N_ped in eq. 8: give N_ped", "k_fb": "k_fb = -2 N_r in eq. 8: give N_r",
               "tau_s": "give inv_tau_s = 1/tau_s (1/s)", "-1/tau_s": "give inv_tau_s = 1/tau_s (positive, 1/s)"}
#: parameters whose sign eq. 8 fixes: name -> (sign, why)
SIGN_FIXED = {"inv_tau_s": (1.0, "1/tau_s is positive; the matrix entry is -inv_tau_s")}

#: Wide prior (nominal, std) for parameters an aircraft file does not give: the rotor terms a small
#: helicopter's rotor makes (flapping time constant 1/tau_s of 5-20 /s, on-axis flapping moments of
#: tens to hundreds of 1/s^2), damping terms negative, and everything else centred on zero with a
#: standard deviation as wide as small helicopters range (paper Table 5, Mettler's R-50, our trex600).
#: The heave/yaw cross-couplings (Z_r, N_w, Z_ped) of a single-rotor helicopter are a few tenths
#: (R-50 0.3-0.4, trex600 0.1-0.6): without a tight prior a weak vertical-velocity estimate lets them
#: carry pedal and yaw activity into w (on the real TREX 550 log, Z_ped 24 and N_w 5.7).
WIDE_PRIOR: dict[str, tuple[float, float]] = {
    "X_u": (-0.1, 0.5), "Y_v": (-0.1, 0.5), "M_u": (0.0, 1.5), "M_v": (0.0, 1.5), "M_q": (-0.5, 2.0),
    "M_a": (0.0, 100.0), "M_b": (0.0, 100.0), "L_u": (0.0, 1.5), "L_v": (0.0, 1.5), "L_p": (-1.0, 4.0),
    "L_a": (0.0, 100.0), "L_b": (0.0, 150.0), "k1": (0.0, 0.5), "inv_tau_s": (10.0, 6.0),
    "X_lat": (0.0, 5.0), "Y_lon": (0.0, 5.0), "M_lat": (0.0, 15.0), "M_lon": (0.0, 15.0),
    "L_lat": (0.0, 15.0), "L_lon": (0.0, 15.0), "A_lat": (0.0, 8.0), "B_lon": (0.0, 8.0),
    "Z_w": (-0.7, 1.5), "Z_r": (0.0, 1.0), "N_w": (0.0, 1.0), "N_r": (-1.0, 2.0), "k_r": (0.0, 8.0),
    "Z_col": (0.0, 30.0), "Z_ped": (0.0, 3.0), "N_col": (0.0, 15.0), "N_ped": (0.0, 20.0),
}


class AircraftError(GroundstationError, ValueError):
    """An aircraft file or one of its values is wrong (one line naming the file, key and value)."""


@dataclass(frozen=True)
class InputMap:
    """Where the four inputs come from. ``channels`` are 1-based numbers of lat lon col ped; with
    ``SWASHPLATE`` the first three are the swashplate servos in the order of ``swash_phase_deg``."""

    source: str = "SERVO_OUTPUT_RAW"
    channels: tuple[int, int, int, int] = (1, 2, 3, 4)
    units: str = "pwm"
    pwm_per_unit: float = 500.0
    trim: dict[str, float] = field(default_factory=dict)
    swash_phase_deg: tuple[float, ...] = ()
    #: what the inputs are: "blade" (swashplate/tail pitch: servo outputs), "rate_command" or
    #: "attitude_command" (sticks to a stabilised aircraft), "unknown" (both structures fitted, held-out
    #: prediction chooses); "" = from the source (servo outputs and swashplate: blade; RC channels: unknown)
    kind: str = ""
    #: the logged inputs are late against the outputs by this much, s (advanced by it in data
    #: preparation, ``prepare.input_shift_s``); None = the configuration's (0: as logged)
    shift_s: float | None = None

    @property
    def input_kind(self) -> str:
        return self.kind or ("unknown" if self.source == "RC_CHANNELS" else "blade")


@dataclass(frozen=True)
class Prior:
    """Prior model: nominal value and standard deviation per parameter (all 31, PARAM_NAMES order)."""

    nominal: tuple[float, ...]
    std: tuple[float, ...]
    given: tuple[str, ...] = ()  # the parameters the file gave (the others are WIDE_PRIOR)
    source: str = "wide defaults"

    @property
    def mean_array(self) -> np.ndarray:
        return np.asarray(self.nominal, dtype=float)

    @property
    def std_array(self) -> np.ndarray:
        return np.asarray(self.std, dtype=float)


def wide_prior() -> Prior:
    return Prior(tuple(WIDE_PRIOR[n][0] for n in PARAM_NAMES), tuple(WIDE_PRIOR[n][1] for n in PARAM_NAMES))


@dataclass(frozen=True)
class Aircraft:
    name: str = "aircraft"
    inputs: InputMap = field(default_factory=InputMap)
    measured: tuple[str, ...] = OUTPUTS
    prior: Prior = field(default_factory=wide_prior)
    path: str = ""
    #: IdentifyConfig overrides for this aircraft (``[identify]`` table): how its flights are best fitted
    identify: dict[str, Any] = field(default_factory=dict)

    def identify_config(self, base: Any = None) -> Any:
        """``base`` (an :class:`groundstation.sysid.identify.IdentifyConfig`) with this file's overrides."""
        # the file's input kind where it says one (or its RC source implies "unknown"); else the configuration's
        im = self.inputs
        kind = {"input_kind": im.input_kind} if im.kind or im.source == "RC_CHANNELS" else {}
        return replace(base or IdentifyConfig(), **(kind | self.identify))

    def prep_config(self, base: Any = None) -> Any:
        """The data-preparation settings (:class:`groundstation.dsp.prepare.PrepConfig`) this file implies."""
        cfg = base or PrepConfig()
        im = self.inputs
        trim = None
        if im.trim:
            trim = tuple(float(im.trim.get(k, np.nan)) for k in INPUTS)
        shift = {} if im.shift_s is None else {"input_shift_s": im.shift_s}
        return replace(cfg, **shift, input_source="RC_CHANNELS" if im.source == "RC_CHANNELS" else "SERVO_OUTPUT_RAW",
                       input_channels=im.channels, input_trim_pwm=trim,
                       pwm_per_unit=1.0 if im.units == "normalised" else im.pwm_per_unit,
                       swash_phase_deg=im.swash_phase_deg, measured_outputs=tuple(self.measured),
                       rotor_inv_tau_s=float(self.prior.nominal[PARAM_NAMES.index("inv_tau_s")]
                                             + self.prior.std[PARAM_NAMES.index("inv_tau_s")]))


def _err(name: str, key: str, value: Any, why: str) -> AircraftError:
    return AircraftError(f"{name}: {key} = {value!r}: {why}")


def _channel(name: str, key: str, v: Any) -> int:
    if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= 18:
        raise _err(name, key, v, "a channel number 1..18")
    return int(v)


def _parse_inputs(t: dict[str, Any], name: str) -> InputMap:
    allowed = {"source", "lat", "lon", "col", "ped", "units", "pwm_per_unit", "trim", "swash_servos", "swash_phase_deg",
               "kind", "shift_s"}
    for k in t:
        if k not in allowed:
            raise _err(name, f"inputs.{k}", t[k], f"unknown key (allowed: {', '.join(sorted(allowed))})")
    src = t.get("source", "SERVO_OUTPUT_RAW")
    if src not in INPUT_SOURCES:
        raise _err(name, "inputs.source", src, f"one of {', '.join(INPUT_SOURCES)}")
    units = t.get("units", "pwm")
    if units not in ("pwm", "normalised"):
        raise _err(name, "inputs.units", units, "pwm or normalised")
    ppu = t.get("pwm_per_unit", 500.0)
    if not isinstance(ppu, int | float) or ppu == 0:
        raise _err(name, "inputs.pwm_per_unit", ppu, "a non-zero number")
    phase: tuple[float, ...] = ()
    if src == "SWASHPLATE":
        servos = t.get("swash_servos")
        if not (isinstance(servos, list) and len(servos) == 3):
            raise _err(name, "inputs.swash_servos", servos, "three servo numbers for a SWASHPLATE source")
        phase_v = t.get("swash_phase_deg", [0.0, 120.0, 240.0])
        if not (isinstance(phase_v, list) and len(phase_v) == 3 and all(isinstance(x, int | float) for x in phase_v)):
            raise _err(name, "inputs.swash_phase_deg", phase_v, "three angles in degrees")
        phase = tuple(float(x) for x in phase_v)
        ch = tuple(_channel(name, "inputs.swash_servos", s) for s in servos) + (_channel(name, "inputs.ped", t.get("ped", 4)),)
    else:
        ch = tuple(_channel(name, f"inputs.{k}", t.get(k, d)) for k, d in (("lat", 1), ("lon", 2), ("col", 3), ("ped", 4)))
    trim = t.get("trim", {})
    if not isinstance(trim, dict) or any(k not in ("lat", "lon", "col", "ped") or not isinstance(v, int | float)
                                         for k, v in trim.items()):
        raise _err(name, "inputs.trim", trim, "a table of lat/lon/col/ped = number")
    kind = t.get("kind", "")
    if kind not in ("", "blade", "rate_command", "attitude_command", "unknown"):
        raise _err(name, "inputs.kind", kind, "blade, rate_command, attitude_command or unknown")
    shift = t.get("shift_s")
    if shift is not None and (not isinstance(shift, int | float) or isinstance(shift, bool) or not abs(shift) < 1.0):
        raise _err(name, "inputs.shift_s", shift, "seconds the logged inputs are late, within +-1 s")
    return InputMap(src, ch, units, float(ppu), {k: float(v) for k, v in trim.items()}, phase, kind,  # type: ignore[arg-type]
                    None if shift is None else float(shift))


def _parse_prior(t: dict[str, Any], name: str) -> Prior:
    lo_hi = bounds_array()
    nominal = {n: WIDE_PRIOR[n][0] for n in PARAM_NAMES}
    std = {n: WIDE_PRIOR[n][1] for n in PARAM_NAMES}
    given = []
    for k, v in t.items():
        if k == "source":
            continue
        if k in CONSTRAINED:
            raise _err(name, f"prior.{k}", v, CONSTRAINED[k])
        if k not in PARAM_NAMES:
            raise _err(name, f"prior.{k}", v, "unknown parameter (the paper's names: " + ", ".join(PARAM_NAMES) + ")")
        if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, int | float) and not isinstance(x, bool)
                                                            for x in v)):
            raise _err(name, f"prior.{k}", v, "[nominal, std]")
        m, s = float(v[0]), float(v[1])
        if not (np.isfinite(m) and np.isfinite(s)) or s <= 0:
            raise _err(name, f"prior.{k}", v, "the standard deviation must be a positive number")
        if k in SIGN_FIXED and m * SIGN_FIXED[k][0] <= 0:
            raise _err(name, f"prior.{k}", v, f"wrong sign convention: {SIGN_FIXED[k][1]}")
        i = PARAM_NAMES.index(k)
        if not lo_hi[i, 0] <= m <= lo_hi[i, 1]:
            raise _err(name, f"prior.{k}", v, f"nominal outside the search bounds [{lo_hi[i, 0]:g}, {lo_hi[i, 1]:g}]")
        nominal[k], std[k] = m, s
        given.append(k)
    return Prior(tuple(nominal[n] for n in PARAM_NAMES), tuple(std[n] for n in PARAM_NAMES), tuple(given),
                 str(t.get("source", "aircraft file" if given else "wide defaults")))


def parse_aircraft(doc: dict[str, Any], name: str) -> Aircraft:
    """An :class:`Aircraft` from a parsed TOML document (``name`` is the file, for messages)."""
    for k in doc:
        if k not in ("name", "inputs", "outputs", "prior", "identify"):
            raise _err(name, k, doc[k], "unknown key (allowed: name, [inputs], [outputs], [prior], [identify])")
    inputs = _parse_inputs(doc.get("inputs", {}), name)
    out_t = doc.get("outputs", {})
    for k in out_t:
        if k != "measured":
            raise _err(name, f"outputs.{k}", out_t[k], "unknown key (allowed: measured)")
    measured = out_t.get("measured", list(OUTPUTS))
    if not isinstance(measured, list) or any(c not in OUTPUTS for c in measured):
        raise _err(name, "outputs.measured", measured, f"a list of {', '.join(OUTPUTS)}")
    return Aircraft(str(doc.get("name", Path(name).stem)), inputs, tuple(c for c in OUTPUTS if c in measured),
                    _parse_prior(doc.get("prior", {}), name), name, _parse_identify(doc.get("identify", {}), name))


def _parse_identify(t: dict[str, Any], name: str) -> dict[str, Any]:
    """``[identify]`` overrides, checked by building the IdentifyConfig they make."""

    allowed = {f.name for f in dataclasses.fields(IdentifyConfig)}
    for k, v in t.items():
        if k not in allowed:
            raise _err(name, f"identify.{k}", v, f"unknown key (allowed: {', '.join(sorted(allowed))})")
    try:
        IdentifyConfig(**t)
    except (TypeError, ValueError) as exc:
        raise AircraftError(f"{name}: [identify]: {exc}") from None
    return dict(t)


def load_aircraft(path: str | Path) -> Aircraft:
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise AircraftError(f"{p}: no such aircraft file") from None
    except tomllib.TOMLDecodeError as exc:
        raise AircraftError(f"{p}: not valid TOML ({exc})") from None
    return parse_aircraft(doc, str(p))
