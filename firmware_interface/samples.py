"""Typed samples: the events the MAVLink session emits and the columnar log every reader returns.

Two shapes of the same data:

* **Events** (frozen dataclasses, one per decoded message) come out of
  :class:`firmware_interface.session.MavlinkSession` one at a time, for the live path.
* **LogData** holds the same samples stacked into numpy columns per message type, for the
  offline path (readers of .tlog, dataflash .bin and PX4 .px4log all return it) and for ``dsp``.

Units are SI and in every name: ``t_fc_s`` is the flight controller's clock (time_boot_ms /
time_usec, seconds since FC boot, unwrapped), ``t_host_s`` the host receive time (Unix seconds).
Messages without an FC time field (HEARTBEAT, SYS_STATUS, ...) carry the session's estimate of the
FC time at reception, from its clock-offset model.

This module holds data definitions only: no parsing, no IO.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# --------------------------------------------------------------------------------------------
# Events (live path)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Sample:
    """Common header of every decoded message."""

    t_host_s: float
    t_fc_s: float
    sysid: int
    compid: int


@dataclass(frozen=True, slots=True)
class RawPacket:
    """One whole, CRC-valid packet exactly as received (for the recorder).

    ``signature_ok`` is None when the link is unsigned, else whether the MAVLink 2 signature
    verified; unverified packets are still recorded, flagged, and not decoded into samples.
    """

    t_host_s: float
    data: bytes
    msg_id: int
    msg_type: str
    sysid: int
    compid: int
    seq: int
    signature_ok: bool | None = None


@dataclass(frozen=True, slots=True)
class Heartbeat(Sample):
    mav_type: int
    autopilot: int
    base_mode: int
    custom_mode: int
    system_status: int
    armed: bool


@dataclass(frozen=True, slots=True)
class ServoOutputRaw(Sample):
    port: int
    pwm_us: tuple[int, ...]  # servo1..servo16 (0 where not sent)


@dataclass(frozen=True, slots=True)
class RcChannels(Sample):
    pwm_us: tuple[int, ...]  # chan1..chan18
    rssi: int


@dataclass(frozen=True, slots=True)
class Attitude(Sample):
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    p_rad_s: float
    q_rad_s: float
    r_rad_s: float


@dataclass(frozen=True, slots=True)
class LocalPositionNed(Sample):
    x_m: float
    y_m: float
    z_m: float
    vx_m_s: float
    vy_m_s: float
    vz_m_s: float


@dataclass(frozen=True, slots=True)
class GlobalPositionInt(Sample):
    lat_deg: float
    lon_deg: float
    alt_m: float
    relative_alt_m: float
    vx_m_s: float
    vy_m_s: float
    vz_m_s: float
    hdg_deg: float


@dataclass(frozen=True, slots=True)
class Imu(Sample):
    source: str  # "RAW_IMU", "SCALED_IMU", "SCALED_IMU2", ...
    acc_m_s2: tuple[float, float, float]
    gyro_rad_s: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class GpsRawInt(Sample):
    fix_type: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    ground_speed_m_s: float
    course_deg: float
    satellites: int


@dataclass(frozen=True, slots=True)
class ExtendedSysState(Sample):
    vtol_state: int
    landed_state: int  # MAV_LANDED_STATE: 0 undefined, 1 on ground, 2 in air, 3 takeoff, 4 landing


@dataclass(frozen=True, slots=True)
class SysStatus(Sample):
    voltage_v: float
    current_a: float
    battery_pct: int
    drop_rate_comm_pct: float
    errors_comm: int
    load_pct: float


@dataclass(frozen=True, slots=True)
class StatusText(Sample):
    severity: int
    text: str


@dataclass(frozen=True, slots=True)
class CommandAck(Sample):
    command: int
    result: int


@dataclass(frozen=True, slots=True)
class LinkLost:
    t_host_s: float
    reason: str


@dataclass(frozen=True, slots=True)
class LinkRestored:
    t_host_s: float


@dataclass(frozen=True, slots=True)
class FcRebooted:
    """time_boot_ms jumped backwards by more than a wrap could explain: the FC restarted."""

    t_host_s: float
    sysid: int
    previous_t_fc_s: float


# --------------------------------------------------------------------------------------------
# Columnar log (offline path)
# --------------------------------------------------------------------------------------------

#: Column names per series in :class:`LogData`. Every series also has ``t_fc_s`` and ``t_host_s``.
SERIES_FIELDS: dict[str, tuple[str, ...]] = {
    "HEARTBEAT": ("armed", "base_mode", "custom_mode", "mav_type"),
    # pwm_us is stored as 16 columns pwm_us_1..pwm_us_16 (servo numbering from 1)
    "SERVO_OUTPUT_RAW": tuple(f"pwm_us_{i}" for i in range(1, 17)),
    "RC_CHANNELS": tuple(f"pwm_us_{i}" for i in range(1, 19)),
    "ATTITUDE": ("roll_rad", "pitch_rad", "yaw_rad", "p_rad_s", "q_rad_s", "r_rad_s"),
    "LOCAL_POSITION_NED": ("x_m", "y_m", "z_m", "vx_m_s", "vy_m_s", "vz_m_s"),
    "GLOBAL_POSITION_INT": ("lat_deg", "lon_deg", "alt_m", "relative_alt_m", "vx_m_s", "vy_m_s", "vz_m_s"),
    "IMU": ("ax_m_s2", "ay_m_s2", "az_m_s2", "gx_rad_s", "gy_rad_s", "gz_rad_s"),
    "GPS_RAW_INT": ("fix_type", "lat_deg", "lon_deg", "alt_m", "ground_speed_m_s", "satellites"),
    "EXTENDED_SYS_STATE": ("landed_state",),
    "SYS_STATUS": ("voltage_v", "current_a", "drop_rate_comm_pct"),
    # dataflash only: HELI rotor speed, high-rate gyro (GYR), SYSID chirp data (SIDD)
    "ROTOR": ("rotor_speed_rpm", "desired_rotor_speed_rpm"),
    "GYRO_FAST": ("gx_rad_s", "gy_rad_s", "gz_rad_s"),
    "SYSID": ("waveform_time_s", "target", "frequency_hz"),
}

#: ArduPilot SID_AXIS values and the input they excite.
SYSID_AXES: dict[int, str] = {
    1: "input_roll", 2: "input_pitch", 3: "input_yaw", 4: "recovery_roll", 5: "recovery_pitch",
    6: "recovery_yaw", 7: "rate_roll", 8: "rate_pitch", 9: "rate_yaw", 10: "mixer_roll", 11: "mixer_pitch",
    12: "mixer_yaw", 13: "mixer_thrust",
}


@dataclass(frozen=True)
class Series:
    """One message type as columns; every array has shape (n_samples,), sorted by ``t_fc_s``."""

    t_fc_s: np.ndarray
    t_host_s: np.ndarray
    columns: dict[str, np.ndarray]

    def __len__(self) -> int:
        return int(self.t_fc_s.shape[0])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]


@dataclass(frozen=True)
class FlightInterval:
    """An armed interval on the FC clock; in-air time from landed_state, else altitude."""

    index: int  # 0-based flight number within the log
    start_fc_s: float
    end_fc_s: float
    in_air_s: float
    in_air_intervals_fc_s: tuple[tuple[float, float], ...] = ()

    @property
    def duration_s(self) -> float:
        return self.end_fc_s - self.start_fc_s


@dataclass(frozen=True)
class ChirpSegment:
    """One system-identification chirp of a dataflash log (ArduPilot SYSID mode: SIDS settings,
    SIDD data), on the FC clock."""

    index: int
    axis: int  # SID_AXIS
    axis_name: str  # see SYSID_AXES
    magnitude: float
    f_start_hz: float
    f_stop_hz: float
    start_fc_s: float
    end_fc_s: float

    @property
    def duration_s(self) -> float:
        return self.end_fc_s - self.start_fc_s


@dataclass
class LinkStats:
    """What went wrong on the link or in the file (counted, never raised)."""

    packets: int = 0
    corrupt_bytes: int = 0  # bytes skipped as garbage or in bad-CRC frames
    bad_crc: int = 0
    packets_lost: int = 0  # from seq gaps, summed over (sysid, compid)
    loss_by_source: dict[str, int] = field(default_factory=dict)  # "sysid:compid" -> lost
    truncated_tail_bytes: int = 0
    unsigned_dropped: int = 0
    fc_reboots: int = 0


@dataclass
class LogData:
    """Every typed sample of one log, stacked per message type (see :data:`SERIES_FIELDS`).

    ``series`` keys are the MAVLink message names above; a log that lacks a type simply lacks the
    key (callers must say which type is missing rather than guess). ``message_counts`` counts
    every decoded message type, including ones without a series. ``notes`` are one-line remarks
    of the reader (a topic the file lacks, a log never armed) for the user; ``chirps`` the
    system-identification chirps of a dataflash log; ``dropouts_s`` the
    intervals the FC's own logger reports lost (ULog).
    """

    source: str
    series: dict[str, Series]
    message_counts: dict[str, int]
    stats: LinkStats
    flights: list[FlightInterval]
    notes: list[str] = field(default_factory=list)
    chirps: list[ChirpSegment] = field(default_factory=list)
    #: (start on the FC clock, duration) in s of each interval the FC's logger itself lost data
    #: (ULog dropout records); empty for logs that do not record their own losses
    dropouts_s: list[tuple[float, float]] = field(default_factory=list)

    def has(self, name: str) -> bool:
        return name in self.series and len(self.series[name]) > 0
