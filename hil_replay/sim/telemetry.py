"""Telemetry as ArduPilot sends it: one :class:`TelemetryFrame` per 50 Hz FC tick, encoded on demand.

A frame carries what the autopilot knows at FC time ``t_boot_s`` (already noisy, biased, delayed as
the effects say; see ``session.py``) in a :class:`Measurement`, and builds any of
:data:`MESSAGE_NAMES` with a caller's ``pymavlink.dialects.v20.ardupilotmega.MAVLink`` encoder:

* HEARTBEAT (MAV_TYPE_HELICOPTER, MAV_AUTOPILOT_ARDUPILOTMEGA, SAFETY_ARMED when armed,
  custom_mode 0 = STABILIZE), SERVO_OUTPUT_RAW (servo1..4 = lat lon col ped per the aircraft's
  servo map, servo8 = throttle/ESC, time_usec FC clock), ATTITUDE, LOCAL_POSITION_NED (NED relative
  to the EKF origin at the first take-off point), GLOBAL_POSITION_INT (degE7, mm, cm/s), RAW_IMU
  (milli-g, mrad/s), GPS_RAW_INT (5 Hz native), EXTENDED_SYS_STATE (landed_state), SYS_STATUS (1 Hz).
* FC time fields carry up to +-1 ms of jitter (drawn per message per tick, so they stay the same
  however often a frame is built).

``available`` lists the messages with fresh data this tick at their native rate (50 Hz except
GPS_RAW_INT 5 Hz, SYS_STATUS and HEARTBEAT 1 Hz). Leaves to others: which messages go out and at
what rate (the simulated FC or :func:`hil_replay.sim.write_tlog`), packet framing and loss.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

MESSAGE_NAMES: tuple[str, ...] = ("HEARTBEAT", "SERVO_OUTPUT_RAW", "ATTITUDE", "LOCAL_POSITION_NED",
                                  "GLOBAL_POSITION_INT", "RAW_IMU", "GPS_RAW_INT", "EXTENDED_SYS_STATE",
                                  "SYS_STATUS")
#: Native rate of each message in the simulated autopilot (Hz).
NATIVE_RATE_HZ: dict[str, float] = {"HEARTBEAT": 1.0, "SERVO_OUTPUT_RAW": 50.0, "ATTITUDE": 50.0,
                                    "LOCAL_POSITION_NED": 50.0, "GLOBAL_POSITION_INT": 50.0, "RAW_IMU": 50.0,
                                    "GPS_RAW_INT": 5.0, "EXTENDED_SYS_STATE": 50.0, "SYS_STATUS": 1.0}

_SENSORS = (mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
            | mavlink.MAV_SYS_STATUS_AHRS | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY)
_UINT32 = 1 << 32
_MG = 1000.0 / 9.80665
#: Field origin (ArduPilot SITL's CMAC): lat, lon (deg), altitude AMSL (m); EKF origin = first take-off point.
FIELD_ORIGIN = (-35.363261, 149.165230, 584.0)
_M_PER_DEG_LAT = 6378137.0 * math.pi / 180.0
_M_PER_DEG_LON = _M_PER_DEG_LAT * math.cos(math.radians(FIELD_ORIGIN[0]))


@dataclass(slots=True)
class Measurement:
    """Everything the autopilot reports at one tick (already in message units where integer)."""

    t_boot_s: float
    armed: bool
    jitter_ms: tuple[int, int, int]      # ATTITUDE, LOCAL_POSITION_NED, GLOBAL_POSITION_INT
    jitter_us: tuple[int, int, int]      # SERVO_OUTPUT_RAW, RAW_IMU, GPS_RAW_INT
    roll: float
    pitch: float
    yaw: float
    p: float
    q: float
    r: float
    x: float
    y: float
    z: float
    vx: float
    vy: float
    vz: float
    acc_fn: Callable[[], tuple[float, float, float]]  # specific force, body axes (m/s^2), on demand
    gps_n_m: float
    gps_e_m: float
    gps_d_m: float
    gps_vn_m_s: float
    gps_ve_m_s: float
    servo_pwm: tuple[int, ...]           # servo1..servo8
    landed_state: int
    voltage_v: float
    current_a: float
    battery_frac: float


class TelemetryFrame:
    """One 50 Hz FC tick: ``t_boot_s``, ``armed``, ``flight_index``, ``available``, :meth:`build`.

    For tests and truth checks a frame also carries what no sensor sees: ``state`` (the true
    15-element state, see ``dynamics.STATE_NAMES``), ``command`` (normalised inputs as sent to the
    servos, i.e. what SERVO_OUTPUT_RAW shows), ``actuator`` (normalised inputs acting on the rotor
    after the input effects, at the first 200 Hz sub-step after this tick) and ``wind_ned`` (m/s);
    ``fast_before`` holds the 200 Hz gyro samples since the previous tick when the session was asked for them.
    """

    __slots__ = ("t_boot_s", "armed", "flight_index", "available", "m", "state", "command", "actuator",
                 "wind_ned", "fast_before")

    def __init__(self, m: Measurement, flight_index: int | None, available: tuple[str, ...],
                 state: tuple[float, ...] = (), command: tuple[float, ...] = (), actuator: tuple[float, ...] = (),
                 wind_ned: tuple[float, ...] = (0.0, 0.0, 0.0),
                 fast_before: tuple[tuple[float, ...], ...] = ()) -> None:
        self.t_boot_s = m.t_boot_s
        self.armed = m.armed
        self.flight_index = flight_index
        self.available: Sequence[str] = available
        self.m = m
        self.state = state
        self.command = command
        self.actuator = actuator
        self.wind_ned = wind_ned
        self.fast_before = fast_before  # (t_s, p, q, r, roll, pitch, yaw) at the 200 Hz sub-steps before it

    def __repr__(self) -> str:
        return (f"TelemetryFrame(t_boot_s={self.t_boot_s:.3f}, armed={self.armed}, "
                f"flight_index={self.flight_index}, available={self.available})")

    def build(self, name: str, mav: mavlink.MAVLink) -> Any:
        """Encode message ``name`` (one of :data:`MESSAGE_NAMES`) with ``mav``; KeyError otherwise."""
        m = self.m
        t = m.t_boot_s
        if name == "ATTITUDE":
            return mav.attitude_encode(max(0, int(round(t * 1000.0)) + m.jitter_ms[0]), m.roll, m.pitch, m.yaw, m.p, m.q, m.r)
        if name == "SERVO_OUTPUT_RAW":
            s = m.servo_pwm
            return mav.servo_output_raw_encode(max(0, int(round(t * 1e6)) + m.jitter_us[0]) % _UINT32, 0,
                                               s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7])
        if name == "LOCAL_POSITION_NED":
            return mav.local_position_ned_encode(max(0, int(round(t * 1000.0)) + m.jitter_ms[1]), m.x, m.y, m.z,
                                                 m.vx, m.vy, m.vz)
        if name == "GLOBAL_POSITION_INT":
            hdg = int(round(math.degrees(m.yaw) % 360.0 * 100.0)) % 36000
            return mav.global_position_int_encode(max(0, int(round(t * 1000.0)) + m.jitter_ms[2]), _lat_e7(m.x),
                                                  _lon_e7(m.y), int(round((FIELD_ORIGIN[2] - m.z) * 1000.0)),
                                                  int(round(-m.z * 1000.0)), _i16(m.vx * 100.0), _i16(m.vy * 100.0),
                                                  _i16(m.vz * 100.0), hdg)
        if name == "RAW_IMU":
            a = m.acc_fn()
            return mav.raw_imu_encode(max(0, int(round(t * 1e6)) + m.jitter_us[1]), _i16(a[0] * _MG), _i16(a[1] * _MG),
                                      _i16(a[2] * _MG), _i16(m.p * 1000.0), _i16(m.q * 1000.0), _i16(m.r * 1000.0),
                                      210, -35, 410)
        if name == "GPS_RAW_INT":
            vel = int(round(math.hypot(m.gps_vn_m_s, m.gps_ve_m_s) * 100.0))
            cog = int(round(math.degrees(math.atan2(m.gps_ve_m_s, m.gps_vn_m_s)) % 360.0 * 100.0)) % 36000
            return mav.gps_raw_int_encode(max(0, int(round(t * 1e6)) + m.jitter_us[2]), 3, _lat_e7(m.gps_n_m),
                                          _lon_e7(m.gps_e_m), int(round((FIELD_ORIGIN[2] - m.gps_d_m) * 1000.0)),
                                          70, 110, vel, cog, 16)
        if name == "EXTENDED_SYS_STATE":
            return mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, m.landed_state)
        if name == "SYS_STATUS":
            return mav.sys_status_encode(_SENSORS, _SENSORS, _SENSORS, 310, int(round(m.voltage_v * 1000.0)),
                                         int(round(m.current_a * 100.0)), int(round(100.0 * (1.0 - m.battery_frac))),
                                         0, 0, 0, 0, 0, 0)
        if name == "HEARTBEAT":
            return heartbeat(mav, m.armed)
        raise KeyError(f"{name}: not a simulated message; allowed: {MESSAGE_NAMES}")


def heartbeat(mav: mavlink.MAVLink, armed: bool) -> Any:
    """An ArduPilot helicopter heartbeat (STABILIZE)."""
    base = (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
            | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED)
    if armed:
        base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    status = mavlink.MAV_STATE_ACTIVE if armed else mavlink.MAV_STATE_STANDBY
    return mav.heartbeat_encode(mavlink.MAV_TYPE_HELICOPTER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base, 0, status)


def _lat_e7(north_m: float) -> int:
    return int(round((FIELD_ORIGIN[0] + north_m / _M_PER_DEG_LAT) * 1e7))


def _lon_e7(east_m: float) -> int:
    return int(round((FIELD_ORIGIN[1] + east_m / _M_PER_DEG_LON) * 1e7))


def _i16(v: float) -> int:
    return max(-32768, min(32767, int(round(v))))
