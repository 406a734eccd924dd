"""The simulated autopilot's onboard log: an ArduPilot-style dataflash ``.bin`` of each flight.

Records are FMT-described (``0xA3 0x95 TYPE payload``, the FMT record itself first), as ArduPilot
writes them, so any dataflash reader (pymavlink's DFReader, MAVExplorer) reads the file:

=======  ==========  =================================================================
record   rate        columns
=======  ==========  =================================================================
IMU      200 Hz      TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ (rad/s, m/s², accel held per tick)
ATT      200 Hz      TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw (deg)
RATE     200 Hz      TimeUS,RDes,R,ROut,PDes,P,POut,YDes,Y,YOut (deg/s)
RCOU     200 Hz      TimeUS,C1..C8 (µs; the servo outputs change at the 50 Hz control tick)
HELI     200 Hz      TimeUS,DRRPM,ERRPM,Gov,Throt (rotor speed follows the spool-up)
XKF1     50 Hz       TimeUS,C,VN,VE,VD,PN,PE,PD
EV       on change   TimeUS,Id (10 armed, 11 disarmed)
SIDS     per chirp   TimeUS,Ax,Mag,FSt,FSp,TFin,TC,TR,TFout (the card's frequency sweeps as
                     ArduPilot SYSID mixer-axis chirps)
SIDD     200 Hz      TimeUS,Time,Targ,F,Gx,Gy,Gz,Ax,Ay,Az during a chirp
=======  ==========  =================================================================

The 200 Hz samples come from the simulator's sub-steps (``frames(fast_gyro=True)``); the
rotor-vibration effect is in them at its true frequency, not folded onto the 50 Hz grid.
:class:`DataflashWriter` turns frames into bytes (no IO); :func:`write_bin` simulates a session and
writes one file. Leaves to others: reading logs (``firmware_interface``), serving them over MAVLink
(``hil_replay.fc``).
"""

from __future__ import annotations

import json
import math
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hil_replay.sim import SimulatedSession
from hil_replay.sim.aircraft import INPUTS

__all__ = ["ChirpPlan", "DataflashWriter", "chirp_plan", "rotor_rpm", "write_bin"]

_HEAD = b"\xa3\x95"
_STRUCT = {"Q": "Q", "B": "B", "H": "H", "I": "I", "f": "f", "n": "4s", "N": "16s", "Z": "64s"}
# type id, name, format, columns
_FORMATS: tuple[tuple[int, str, str, str], ...] = (
    (128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"),
    (129, "IMU", "QBffffff", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
    (130, "ATT", "Qffffff", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw"),
    (131, "RATE", "Qfffffffff", "TimeUS,RDes,R,ROut,PDes,P,POut,YDes,Y,YOut"),
    (132, "RCOU", "QHHHHHHHH", "TimeUS,C1,C2,C3,C4,C5,C6,C7,C8"),
    (133, "HELI", "Qffff", "TimeUS,DRRPM,ERRPM,Gov,Throt"),
    (134, "XKF1", "QBffffff", "TimeUS,C,VN,VE,VD,PN,PE,PD"),
    (135, "EV", "QB", "TimeUS,Id"),
    (136, "SIDS", "QBfffffff", "TimeUS,Ax,Mag,FSt,FSp,TFin,TC,TR,TFout"),
    (137, "SIDD", "Qfffffffff", "TimeUS,Time,Targ,F,Gx,Gy,Gz,Ax,Ay,Az"),
)
_IDS = {name: typ for typ, name, _, _ in _FORMATS}
_PACK = {name: struct.Struct("<" + "".join(_STRUCT[c] for c in fmt)) for _, name, fmt, _ in _FORMATS}
_R2D = 180.0 / math.pi
# ArduPilot SID_AXIS of the mixer axes the card's sweeps excite
_SID_AXIS = {"lat": 10, "lon": 11, "ped": 12, "col": 13}


@dataclass(frozen=True)
class ChirpPlan:
    """One frequency sweep of the card on the FC clock (s), as a SYSID chirp."""

    start_s: float
    end_s: float
    sid_axis: int
    input_index: int
    magnitude: float
    f0_hz: float
    f1_hz: float


def chirp_plan(session: Any) -> list[ChirpPlan]:
    """The sweeps of a :class:`hil_replay.sim.SimulatedSession`'s cards as chirps."""
    out = []
    for arm_s, card in zip(session.arm_times_s, session.cards, strict=False):
        for seg in card.segments:
            if seg.kind == "sweep" and seg.axis in _SID_AXIS:
                out.append(ChirpPlan(arm_s + seg.start_s, arm_s + seg.end_s, _SID_AXIS[seg.axis],
                                     INPUTS.index(seg.axis), float(seg.amplitude), float(seg.f0_hz),
                                     float(seg.f1_hz)))
    return out


def _fmt_record(typ: int, name: str, fmt: str, cols: str) -> bytes:
    length = 3 + _PACK[name].size
    return _HEAD + bytes([128]) + _PACK["FMT"].pack(typ, length, name.encode(), fmt.encode(), cols.encode())


class DataflashWriter:
    """Frames in (``frames(fast_gyro=True)``), dataflash bytes out; see the module docstring.

    ``rotor_rpm`` is the head speed at full throttle; ``chirps`` the SYSID segments to log
    (empty: none).
    """

    def __init__(self, rotor_rpm: float, chirps: Sequence[ChirpPlan] = ()) -> None:
        self.rotor_rpm = float(rotor_rpm)
        self.chirps = list(chirps)
        self._buf = bytearray(b"".join(_fmt_record(*f) for f in _FORMATS))
        self._armed: bool | None = None
        self._chirp_started: set[int] = set()
        self.records = 0

    def _rec(self, name: str, *vals: Any) -> None:
        self._buf += _HEAD + bytes([_IDS[name]]) + _PACK[name].pack(*vals)
        self.records += 1

    def add(self, frame: Any) -> None:
        """Log one 50 Hz frame and the 200 Hz samples before it."""
        m = frame.m
        if self._armed is None or bool(frame.armed) != self._armed:
            self._armed = bool(frame.armed)
            self._rec("EV", int(frame.t_boot_s * 1e6), 10 if self._armed else 11)
        servo = tuple(int(v) for v in m.servo_pwm[:8]) + (0,) * max(0, 8 - len(m.servo_pwm))
        throttle = servo[7]
        spool = min(1.0, max(0.0, (throttle - 1100) / 750.0)) if frame.armed else 0.0
        rpm = self.rotor_rpm * spool
        acc = m.acc_fn()
        samples = list(frame.fast_before) + [(m.t_boot_s, m.p, m.q, m.r, m.roll, m.pitch, m.yaw)]
        for t_s, p, q, r, roll, pitch, yaw in samples:
            tus = int(round(t_s * 1e6))
            self._rec("IMU", tus, 0, p, q, r, acc[0], acc[1], acc[2])
            self._rec("ATT", tus, 0.0, roll * _R2D, 0.0, pitch * _R2D, 0.0, (yaw * _R2D) % 360.0)
            self._rec("RATE", tus, 0.0, p * _R2D, 0.0, 0.0, q * _R2D, 0.0, 0.0, r * _R2D, 0.0)
            self._rec("RCOU", tus, *servo)
            self._rec("HELI", tus, self.rotor_rpm if frame.armed else 0.0, rpm, spool, spool)
            self._chirp(t_s, tus, frame, (p, q, r), acc)
        self._rec("XKF1", int(round(m.t_boot_s * 1e6)), 0, m.vx, m.vy, m.vz, m.x, m.y, m.z)

    def _chirp(self, t_s: float, tus: int, frame: Any, gyro: tuple[float, float, float],
               acc: tuple[float, float, float]) -> None:
        for k, c in enumerate(self.chirps):
            if not c.start_s <= t_s < c.end_s:
                continue
            dur = c.end_s - c.start_s
            if k not in self._chirp_started:
                self._chirp_started.add(k)
                self._rec("SIDS", tus, c.sid_axis, c.magnitude, c.f0_hz, c.f1_hz, 0.0, 0.0, dur, 0.0)
            tau = t_s - c.start_s
            f = c.f0_hz * (c.f1_hz / c.f0_hz) ** (tau / dur) if c.f0_hz > 0 and dur > 0 else c.f0_hz
            cmd = frame.command[c.input_index] if len(frame.command) > c.input_index else 0.0
            self._rec("SIDD", tus, tau, float(cmd), f, *gyro, *acc)

    def getvalue(self) -> bytes:
        return bytes(self._buf)

    def __len__(self) -> int:
        return len(self._buf)


def write_bin(path: str | os.PathLike[str], *, seed: int = 0, flights: int = 1, effects: Sequence[Any] = (),
              aircraft: Any = None, flight_duration_s: float | None = None, sysid: bool = True,
              pause_s: float = 10.0) -> dict[str, Any]:
    """Simulate a session and write its onboard dataflash log to ``path`` (atomically) and the truth
    to ``path.with_suffix('.truth.json')``; returns the truth. Same arguments, same bytes."""

    sess = SimulatedSession(seed=seed, flights=flights, effects=tuple(effects), aircraft=aircraft,
                            flight_duration_s=flight_duration_s, pause_s=pause_s)
    w = DataflashWriter(rotor_rpm(sess), chirp_plan(sess) if sysid else ())
    for frame in sess.frames(fast_gyro=True):
        w.add(frame)
    truth = sess.truth()
    truth["dataflash"] = {"sample_rate_hz": 200.0, "records": w.records, "sysid_chirps": len(w.chirps)}
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".part")
    tmp.write_bytes(w.getvalue())
    os.replace(tmp, p)
    p.with_suffix(".truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def rotor_rpm(session: Any) -> float:
    """Head speed of a simulated session (the rotor-vibration effect's rpm when it has one)."""
    for e in getattr(session, "effects", ()):
        if e.name == "rotor_vibration":
            return float(e.params["rpm"])
    return float(session.aircraft.rotor_rpm)
