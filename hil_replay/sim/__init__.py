"""Simulated helicopter for hardware-in-the-loop tests: the independent truth the estimators face.

Nonlinear dynamics whose hover Jacobian is the paper's eq. 8 (``dynamics``), an aircraft file
(``aircraft``), a synthetic pilot (``pilot``) flying a randomised flight-test card (``card``),
injectable unmodelled effects (``effects``), ArduPilot-like telemetry frames (``telemetry``) and the
session/.tlog writer (``session``). Never imports ``groundstation.sysid`` or ``groundstation.gap``.

Public API: :class:`SimulatedSession`, :class:`TelemetryFrame`, :func:`write_tlog`,
:func:`parse_effect`, :func:`random_effect`, :class:`Effect`, :class:`Aircraft`, :func:`load_aircraft`.
The MAVLink protocol on a virtual serial port is ``hil_replay.fc``'s.
"""

from hil_replay.sim.aircraft import Aircraft, load_aircraft, resolve_aircraft
from hil_replay.sim.effects import EFFECT_NAMES, Effect, parse_effect, random_effect
from hil_replay.sim.session import DEFAULT_TLOG_RATES_HZ, SimulatedSession, write_tlog
from hil_replay.sim.telemetry import MESSAGE_NAMES, TelemetryFrame

__all__ = [
    "DEFAULT_TLOG_RATES_HZ",
    "EFFECT_NAMES",
    "MESSAGE_NAMES",
    "Aircraft",
    "Effect",
    "SimulatedSession",
    "TelemetryFrame",
    "load_aircraft",
    "parse_effect",
    "random_effect",
    "resolve_aircraft",
    "write_tlog",
]
