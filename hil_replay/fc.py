"""A simulated ArduPilot helicopter flight controller speaking MAVLink 2 on a virtual serial port.

The helicopter itself (dynamics, pilot, card, effects) comes from a frame source such as
:class:`hil_replay.sim.SimulatedSession`: its ``frames()`` yields one frame per 50 Hz tick on the FC
clock with ``t_boot_s``, ``armed``, ``available`` (message names with fresh data this tick) and
``build(name, mav) -> MAVLink_message``. This module adds what the autopilot's GCS link does:

* HEARTBEAT at 1 Hz always (sysid 1, compid 1, MAV_TYPE_HELICOPTER, MAV_AUTOPILOT_ARDUPILOTMEGA,
  SAFETY_ARMED from the frame), and no telemetry stream until the ground station asks, as
  ArduPilot on a fresh link;
* COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL (param2 µs; 0 = default, -1 = off) and
  MAV_CMD_REQUEST_MESSAGE, answered with COMMAND_ACK (unknown message -> MAV_RESULT_DENIED, other
  commands -> MAV_RESULT_UNSUPPORTED; ``refuse_message_interval`` answers UNSUPPORTED so a ground
  station's REQUEST_DATA_STREAM fallback can be exercised);
* REQUEST_DATA_STREAM with ArduPilot's stream groups (no ACK, as ArduPilot);
* each requested message decimated from the 50 Hz frames to the requested rate on the FC clock
  (never faster than the source provides it);
* link packet loss (seeded), applied after encoding so the MAVLink ``seq`` shows the gap, and
  optional line noise (``corrupt_rate``: bit flips per byte, seeded);
* the onboard-log protocol as ArduPilot answers it (LOG_REQUEST_LIST -> LOG_ENTRY, LOG_REQUEST_DATA ->
  LOG_DATA, LOG_REQUEST_END; every log message ignored while armed), serving the dataflash log it
  writes of each flight (``record_dataflash``) and any log given with :meth:`FcProtocol.add_log`;
* an FC reboot on demand (:meth:`FcProtocol.reboot`): silence, boot clock and ``seq`` restart,
  streams off until requested again; a cable pull on demand (:meth:`SimulatedFCThread.unplug`).

:class:`FcProtocol` is the IO-free part (bytes in, frames in, packets out).
:class:`SimulatedFlightController` drives it on a :class:`hil_replay.pty.VirtualSerialPort` in
real time or ``speed``× faster; :func:`serve_simulated_fc` (asyncio) and :class:`SimulatedFCThread`
(for synchronous callers) are the entry points. Bytes written while no ground station has the port
open are discarded, as on a real serial line.
"""

from __future__ import annotations

import asyncio
import math
import random
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from hil_replay.dataflash import DataflashWriter, chirp_plan, rotor_rpm
from hil_replay.pty import PortUnplugged, VirtualSerialPort
from hil_replay.sim import SimulatedSession

__all__ = [
    "DEFAULT_RATE_HZ",
    "STREAM_GROUPS",
    "TELEMETRY_MESSAGES",
    "FcConfig",
    "FcProtocol",
    "FcStats",
    "SimulatedFCThread",
    "SimulatedFlightController",
    "serve_simulated_fc",
]

# Telemetry the simulated FC can stream: name -> MAVLink message id.
TELEMETRY_MESSAGES: dict[str, int] = {
    name: getattr(mavlink, f"MAVLINK_MSG_ID_{name}")
    for name in ("SERVO_OUTPUT_RAW", "ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT",
                 "RAW_IMU", "GPS_RAW_INT", "EXTENDED_SYS_STATE", "SYS_STATUS")
}
_ID_TO_NAME = {v: k for k, v in TELEMETRY_MESSAGES.items()}

# ArduPilot's REQUEST_DATA_STREAM groups restricted to the messages simulated here.
# EXTENDED_SYS_STATE sits with EXTENDED_STATUS (as ArduPlane; ArduCopter only sends it on request).
STREAM_GROUPS: dict[int, tuple[str, ...]] = {
    mavlink.MAV_DATA_STREAM_RAW_SENSORS: ("RAW_IMU",),
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS", "GPS_RAW_INT", "EXTENDED_SYS_STATE"),
    mavlink.MAV_DATA_STREAM_RC_CHANNELS: ("SERVO_OUTPUT_RAW",),
    mavlink.MAV_DATA_STREAM_POSITION: ("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"),
    mavlink.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    mavlink.MAV_DATA_STREAM_EXTRA2: (),
    mavlink.MAV_DATA_STREAM_EXTRA3: (),
}

# Rate used for SET_MESSAGE_INTERVAL with interval 0 ("default rate").
DEFAULT_RATE_HZ: dict[str, float] = {
    "SERVO_OUTPUT_RAW": 4.0, "ATTITUDE": 4.0, "LOCAL_POSITION_NED": 4.0, "GLOBAL_POSITION_INT": 4.0,
    "RAW_IMU": 4.0, "GPS_RAW_INT": 2.0, "EXTENDED_SYS_STATE": 2.0, "SYS_STATUS": 2.0,
}

_FRAME_RATE_HZ = 50.0


class Frame(Protocol):
    """What the FC needs from one simulator tick (see :mod:`hil_replay.sim`)."""

    t_boot_s: float
    armed: bool
    available: Sequence[str]

    def build(self, name: str, mav: mavlink.MAVLink) -> Any: ...


class FrameSource(Protocol):
    def frames(self) -> Iterable[Frame]: ...


@dataclass(frozen=True)
class FcConfig:
    """Behaviour of the simulated flight controller.

    ``packet_loss`` is the probability that one outgoing packet is lost on the link (seeded by
    ``seed``). ``corrupt_rate`` is the probability per byte sent of one flipped bit (line noise;
    the packet then fails its CRC at the ground station). ``refuse_message_interval`` answers
    SET_MESSAGE_INTERVAL with UNSUPPORTED. ``idle_after_end`` keeps sending (disarmed) heartbeats
    after the frame source ends. ``record_dataflash`` writes an onboard dataflash log of each flight
    (:mod:`hil_replay.dataflash`, from arming to disarming) that the log protocol serves;
    ``log_bytes_per_s`` is the LOG_DATA throughput (FC-clock bytes of payload per second; about
    what ArduPilot reaches over USB) and ``log_burst_packets`` how many LOG_DATA packets answer a
    LOG_REQUEST_DATA at once, as ArduPilot's handler sends before returning;
    ``log_stop_after_packets`` makes the FC stop answering log requests after sending that many
    LOG_DATA packets (a fault to inject). ``crc_blind_rate`` is the probability per LOG_DATA packet
    of line noise its CRC-16 cannot see: bits flipped in its data in a seeded multiple of the CRC's
    own polynomial (x^16 + x^12 + x^5 + 1), so the packet arrives valid with a wrong block, as a
    rare error of four or more bits does on a noisy line (a fault to inject; seeded apart from
    ``corrupt_rate``; two such packets almost never carry the same error).
    """

    sysid: int = 1
    compid: int = 1
    packet_loss: float = 0.001
    seed: int = 0
    refuse_message_interval: bool = False
    heartbeat_rate_hz: float = 1.0
    idle_after_end: bool = True
    corrupt_rate: float = 0.0
    record_dataflash: bool = False
    log_bytes_per_s: float = 250_000.0
    log_burst_packets: int = 10
    log_stop_after_packets: int | None = None
    crc_blind_rate: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.packet_loss < 1.0:
            raise ValueError(f"packet_loss: {self.packet_loss} not in [0, 1)")
        if not 0.0 <= self.crc_blind_rate <= 1.0:
            raise ValueError(f"crc_blind_rate: {self.crc_blind_rate} not in [0, 1]")
        if not 0.0 <= self.corrupt_rate < 1.0:
            raise ValueError(f"corrupt_rate: {self.corrupt_rate} not in [0, 1)")
        if not self.heartbeat_rate_hz > 0:
            raise ValueError(f"heartbeat_rate_hz: {self.heartbeat_rate_hz} must be > 0")
        if not self.log_bytes_per_s > 0 or self.log_burst_packets < 1:
            raise ValueError("log_bytes_per_s must be > 0 and log_burst_packets >= 1")


@dataclass
class FcStats:
    """Counters of one simulated-FC run."""

    frames: int = 0
    packets_sent: int = 0
    packets_lost: int = 0          # dropped by the simulated link loss
    packets_unheard: int = 0       # written while no ground station had the port open
    packets_corrupted: int = 0     # sent with at least one flipped bit (corrupt_rate)
    corrupt_bytes: int = 0
    packets_crc_blind: int = 0     # LOG_DATA sent with an error their CRC cannot see (crc_blind_rate)
    bytes_sent: int = 0
    gcs_messages: int = 0
    commands: int = 0
    log_requests: int = 0
    log_data_sent: int = 0
    log_erases: int = 0
    acks: int = 0
    last_t_boot_s: float = 0.0     # the frame source's clock (not reset by reboots)
    reboots: int = 0
    sent_by_type: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class _IdleFrame:
    t_boot_s: float
    armed: bool = False
    flight_index: int | None = None
    available: tuple[str, ...] = ()

    def build(self, name: str, mav: mavlink.MAVLink) -> Any:
        raise KeyError(name)


class FcProtocol:
    """IO-free MAVLink behaviour of the simulated FC.

    Feed the ground station's bytes with :meth:`receive_data`; call :meth:`on_frame` once per
    simulator tick; it returns the encoded packets to put on the wire for that tick (after the
    simulated link loss).
    """

    def __init__(self, config: FcConfig | None = None) -> None:
        self.config = config or FcConfig()
        self.mav = mavlink.MAVLink(None, srcSystem=self.config.sysid, srcComponent=self.config.compid)
        self._parser = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self._parser.robust_parsing = True
        self._rng = random.Random(self.config.seed)
        self._rng_corrupt = random.Random(self.config.seed + 0x5EED)
        self._rng_blind = random.Random(self.config.seed + 0xB11D)
        self.intervals_s: dict[str, float] = {}       # active streams: name -> interval (FC clock)
        self._next_due: dict[str, float] = {}
        self._once: set[str] = set()                  # REQUEST_MESSAGE one-shots
        self._heartbeat_once = False
        self._acks: list[tuple[int, int]] = []
        self._next_heartbeat_s: float | None = None
        self._reboot_pending: float | None = None
        self._silent_until_s = -math.inf
        self._silent = False
        self._boot_offset_s = 0.0
        self.stats = FcStats()
        # onboard logs (ArduPilot's log protocol): finished logs, the one being written, what to send
        self.logs: list[bytes] = []
        self.log_writer_factory: Callable[[], Any] | None = None
        self._writer: Any = None
        self.armed = False
        self._log_list: list[int] = []            # LOG_ENTRY ids still to send
        self._log_burst: list[tuple[int, int, int]] = []   # (id, ofs, count) answered at once
        self._log_stream: tuple[int, int, int] | None = None   # (id, next ofs, bytes left)
        self._log_credit = 0.0

    # ------------------------------------------------------------------ ground station -> FC

    def receive_data(self, data: bytes) -> None:
        msgs = self._parser.parse_buffer(data) or []
        for msg in msgs:
            if msg.get_type() == "BAD_DATA" or self._silent:   # nobody listens while rebooting
                continue
            self.stats.gcs_messages += 1
            self._handle(msg)

    def _for_me(self, target_system: int, target_component: int) -> bool:
        return (target_system in (0, self.config.sysid)
                and target_component in (0, self.config.compid))

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "COMMAND_LONG":
            if not self._for_me(msg.target_system, msg.target_component):
                return
            self.stats.commands += 1
            self._acks.append((msg.command, self._command(msg)))
        elif kind == "REQUEST_DATA_STREAM":
            if self._for_me(msg.target_system, msg.target_component):
                self._request_data_stream(msg.req_stream_id, msg.req_message_rate, msg.start_stop)
        elif kind.startswith("LOG_") and self._for_me(msg.target_system, msg.target_component):
            self.stats.log_requests += 1
            stop = self.config.log_stop_after_packets
            if not self.armed and (stop is None or self.stats.log_data_sent < stop):
                self._log_message(kind, msg)   # ArduPilot ignores every log message while armed

    # ------------------------------------------------------------------ onboard logs

    def add_log(self, data: bytes) -> int:
        """Store a finished onboard log; returns its log id (1-based, as ArduPilot numbers them)."""
        self.logs.append(bytes(data))
        return len(self.logs)

    def _log_message(self, kind: str, msg: Any) -> None:
        if kind == "LOG_REQUEST_LIST":
            n = len(self.logs)
            first = max(1, int(msg.start))
            last = min(n, int(msg.end))
            self._log_list = list(range(first, last + 1)) if n else [0]
        elif kind == "LOG_REQUEST_DATA":
            lid = int(msg.id)
            size = len(self.logs[lid - 1]) if 1 <= lid <= len(self.logs) else 0
            ofs = min(int(msg.ofs), size)
            count = min(int(msg.count), size - ofs)
            burst = min(count, 90 * self.config.log_burst_packets)
            self._log_burst.append((lid, ofs, burst if count > 0 else 0))
            self._log_stream = (lid, ofs + burst, count - burst) if count > burst else None
        elif kind == "LOG_REQUEST_END":
            self._log_stream = None
            self._log_burst.clear()
        elif kind == "LOG_ERASE":
            self.stats.log_erases += 1
            self.logs.clear()

    def _log_data(self, lid: int, ofs: int, count: int, out: list[bytes]) -> int:
        """LOG_DATA packets for ``count`` bytes from ``ofs`` (one empty packet at the end of file)."""
        data = self.logs[lid - 1] if 1 <= lid <= len(self.logs) else b""
        sent = 0
        while True:
            n = min(90, count - sent, max(0, len(data) - ofs - sent))
            chunk = data[ofs + sent:ofs + sent + n]
            self._encode(self.mav.log_data_encode(lid, ofs + sent, n, chunk + bytes(90 - n)), out, data_bytes=n)
            self.stats.log_data_sent += 1
            sent += n
            if n == 0 or sent >= count:
                return sent

    def _send_logs(self, out: list[bytes]) -> None:
        if self._log_list:
            n = len(self.logs)
            for lid in self._log_list:
                size = len(self.logs[lid - 1]) if lid else 0
                self._encode(self.mav.log_entry_encode(lid, n, n, 0, size), out)
            self._log_list = []
        budget = self.config.log_bytes_per_s / _FRAME_RATE_HZ
        for lid, ofs, count in self._log_burst:
            budget -= self._log_data(lid, ofs, count, out)
        self._log_burst.clear()
        if self._log_stream is None:
            self._log_credit = 0.0
            return
        self._log_credit = min(self._log_credit + budget, 4 * self.config.log_bytes_per_s / _FRAME_RATE_HZ)
        lid, ofs, left = self._log_stream
        n = min(left, int(self._log_credit // 90) * 90)
        stop = self.config.log_stop_after_packets
        if stop is not None:
            n = min(n, max(0, stop - self.stats.log_data_sent) * 90)
        if n > 0:
            sent = self._log_data(lid, ofs, n, out)
            self._log_credit -= sent
            ofs, left = ofs + sent, left - sent
        self._log_stream = (lid, ofs, left) if left > 0 else None

    def _record(self, frame: Frame) -> None:
        """The onboard dataflash log: opened at arming, closed (and listed) at disarming."""
        armed = bool(frame.armed)
        if self.log_writer_factory is not None:
            if armed and self._writer is None:
                self._writer = self.log_writer_factory()
            if self._writer is not None:
                self._writer.add(frame)
                if not armed:
                    self.add_log(self._writer.getvalue())
                    self._writer = None
        self.armed = armed

    def _command(self, msg: Any) -> int:
        if msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            if self.config.refuse_message_interval:
                return mavlink.MAV_RESULT_UNSUPPORTED
            msg_id = int(round(msg.param1))
            name = _ID_TO_NAME.get(msg_id)
            if name is None:
                return mavlink.MAV_RESULT_DENIED
            interval_us = float(msg.param2)
            if interval_us < 0:
                self._set_interval(name, None)
            elif interval_us == 0:
                self._set_interval(name, 1.0 / DEFAULT_RATE_HZ[name])
            else:
                self._set_interval(name, interval_us * 1e-6)
            return mavlink.MAV_RESULT_ACCEPTED
        if msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            msg_id = int(round(msg.param1))
            if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
                self._heartbeat_once = True
                return mavlink.MAV_RESULT_ACCEPTED
            name = _ID_TO_NAME.get(msg_id)
            if name is None:
                return mavlink.MAV_RESULT_DENIED
            self._once.add(name)
            return mavlink.MAV_RESULT_ACCEPTED
        return mavlink.MAV_RESULT_UNSUPPORTED

    def _set_interval(self, name: str, interval_s: float | None) -> None:
        if interval_s is None:
            self.intervals_s.pop(name, None)
            self._next_due.pop(name, None)
            return
        self.intervals_s[name] = max(interval_s, 1.0 / _FRAME_RATE_HZ)
        self._next_due.pop(name, None)  # starts at the next frame that has it

    def _request_data_stream(self, stream_id: int, rate_hz: int, start_stop: int) -> None:
        if stream_id == mavlink.MAV_DATA_STREAM_ALL:
            groups = list(STREAM_GROUPS.values())
        else:
            groups = [STREAM_GROUPS.get(stream_id, ())]
        on = bool(start_stop) and rate_hz > 0
        for names in groups:
            for name in names:
                self._set_interval(name, 1.0 / min(float(rate_hz), _FRAME_RATE_HZ) if on else None)

    # ------------------------------------------------------------------ FC -> ground station

    def _encode(self, msg: Any, out: list[bytes], data_bytes: int = 0) -> None:
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        if data_bytes >= 3 and self.config.crc_blind_rate > 0 and self._rng_blind.random() < self.config.crc_blind_rate:
            buf = self._crc_blind(buf, data_bytes)
        if self.config.packet_loss > 0 and self._rng.random() < self.config.packet_loss:
            self.stats.packets_lost += 1
            return
        if self.config.corrupt_rate > 0:
            buf = self._corrupt(buf)
        out.append(buf)
        kind = msg.get_type()
        self.stats.sent_by_type[kind] = self.stats.sent_by_type.get(kind, 0) + 1

    def _crc_blind(self, buf: bytes, data_bytes: int) -> bytes:
        """Flip bits of a LOG_DATA packet's data (``data_bytes`` of it from payload offset 7) in the
        pattern x^k * r(x) * (x^16 + x^12 + x^5 + 1), r and k seeded: its CRC-16 still checks."""
        b = bytearray(buf)
        data_bytes = min(data_bytes, b[1] - 7)  # MAVLink 2 drops the payload's trailing zeros
        if data_bytes < 5:
            return buf
        r = self._rng_blind.randrange(1, 1 << 16)
        pattern = 0
        for i in range(16):  # r times the polynomial, bits in wire order (LSB first: 0, 4, 11, 16)
            if r >> i & 1:
                pattern ^= 0x10811 << i
        first = 8 * (10 + 7)  # MAVLink 2 header, then LOG_DATA's ofs, id, count
        k = first + self._rng_blind.randrange(8 * data_bytes - 32)
        for d in range(32):
            if pattern >> d & 1:
                b[(k + d) // 8] ^= 1 << ((k + d) % 8)
        self.stats.packets_crc_blind += 1
        return bytes(b)

    def _corrupt(self, buf: bytes) -> bytes:
        rate = self.config.corrupt_rate
        hits = [i for i in range(len(buf)) if self._rng_corrupt.random() < rate]
        if not hits:
            return buf
        b = bytearray(buf)
        for i in hits:
            b[i] ^= 1 << self._rng_corrupt.randrange(8)
        self.stats.packets_corrupted += 1
        self.stats.corrupt_bytes += len(hits)
        return bytes(b)

    def heartbeat(self, armed: bool) -> Any:
        base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        if armed:
            base_mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        status = mavlink.MAV_STATE_ACTIVE if armed else mavlink.MAV_STATE_STANDBY
        return self.mav.heartbeat_encode(mavlink.MAV_TYPE_HELICOPTER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                         base_mode, 0, status)

    def reboot(self, boot_s: float = 2.0) -> None:
        """Reboot (from the next frame on): silent for ``boot_s`` (frame clock), then the boot clock
        (time_boot_ms / time_usec) restarts near 0, ``seq`` restarts at 0 and no stream is sent
        until the ground station asks again, as ArduPilot after a reset."""
        self._reboot_pending = boot_s

    def _do_reboot(self, t_sim: float, boot_s: float) -> None:
        self._reboot_pending = None
        self._silent_until_s = t_sim + boot_s
        self._boot_offset_s = t_sim + boot_s - 0.5   # the boot clock reads 0.5 s at first contact
        self.intervals_s.clear()
        self._next_due.clear()
        self._once.clear()
        self._acks.clear()
        self._heartbeat_once = False
        self._next_heartbeat_s = None
        self.mav.seq = 0
        self.stats.reboots += 1

    def _shift_clock(self, msg: Any) -> Any:
        """Re-express a built message's boot-clock fields on the rebooted clock."""
        off = self._boot_offset_s
        if hasattr(msg, "time_boot_ms"):
            msg.time_boot_ms = max(0, int(msg.time_boot_ms - round(off * 1e3)))
        if hasattr(msg, "time_usec") and msg.time_usec < 10**15:   # boot-relative, not Unix time
            v = int(msg.time_usec - round(off * 1e6))
            msg.time_usec = v % (1 << 32) if msg.get_type() == "SERVO_OUTPUT_RAW" else max(0, v)
        return msg

    def on_frame(self, frame: Frame) -> list[bytes]:
        """Packets to send at this simulator tick (ACKs first, then heartbeat, then telemetry)."""
        t_sim = float(frame.t_boot_s)
        self.stats.frames += 1
        self.stats.last_t_boot_s = t_sim
        self._record(frame)
        if self._reboot_pending is not None:
            self._do_reboot(t_sim, self._reboot_pending)
        self._silent = t_sim < self._silent_until_s
        if self._silent:
            return []
        t = t_sim - self._boot_offset_s
        out: list[bytes] = []
        for command, result in self._acks:
            self._encode(self.mav.command_ack_encode(command, result), out)
            self.stats.acks += 1
        self._acks.clear()
        if self._next_heartbeat_s is None or t >= self._next_heartbeat_s - 1e-6 or self._heartbeat_once:
            self._encode(self.heartbeat(bool(frame.armed)), out)
            self._heartbeat_once = False
            period = 1.0 / self.config.heartbeat_rate_hz
            if self._next_heartbeat_s is None or t >= self._next_heartbeat_s + period:
                self._next_heartbeat_s = t + period
            elif t >= self._next_heartbeat_s - 1e-6:
                self._next_heartbeat_s += period
        available = frame.available
        # A quarter frame of slack absorbs FC-clock jitter in the frame timestamps.
        slack = 0.25 / _FRAME_RATE_HZ
        for name in available:
            interval = self.intervals_s.get(name)
            due = False
            if interval is not None:
                nxt = self._next_due.get(name)
                if nxt is None or t >= nxt - slack:
                    due = True
                    if nxt is None or t >= nxt + interval:   # first time, or fell behind
                        self._next_due[name] = t + interval
                    else:
                        self._next_due[name] = nxt + interval
            if name in self._once:
                self._once.discard(name)
                due = True
            if due:
                msg = frame.build(name, self.mav)
                self._encode(self._shift_clock(msg) if self._boot_offset_s else msg, out)
        if not self.armed:
            self._send_logs(out)
        self.stats.packets_sent += len(out)
        return out


def _idle_frames(t0_s: float) -> Iterator[_IdleFrame]:
    k = 1
    while True:
        yield _IdleFrame(t_boot_s=t0_s + k / _FRAME_RATE_HZ)
        k += 1


class SimulatedFlightController:
    """Drive :class:`FcProtocol` from a frame source onto a virtual serial port.

    Parameters
    ----------
    session : frame source (``hil_replay.sim.SimulatedSession`` or anything with ``frames()``)
    port : the virtual serial port the ground station opens
    speed : wall-clock speed-up; 1 = real time, ``0`` or ``inf`` = as fast as the reader drains
    config : protocol behaviour (:class:`FcConfig`)
    """

    def __init__(self, session: FrameSource, port: VirtualSerialPort, *, speed: float = 1.0,
                 config: FcConfig | None = None) -> None:
        if speed < 0 or math.isnan(speed):
            raise ValueError(f"speed: {speed} must be >= 0 (0 or inf = as fast as possible)")
        self.session = session
        self.port = port
        self.speed = math.inf if speed == 0 else float(speed)
        self.protocol = FcProtocol(config)

    @property
    def stats(self) -> FcStats:
        return self.protocol.stats

    def unplug(self, duration_s: float) -> None:
        """Pull the virtual cable now and plug it back after ``duration_s`` wall seconds.

        Call on the event loop running :meth:`run` (see :meth:`SimulatedFCThread.unplug` from
        other threads). What the FC sends meanwhile is lost (counted as unheard).
        """
        loop = asyncio.get_running_loop()
        self.port.unplug()
        loop.call_later(duration_s, self.port.replug)

    def _frames(self) -> Iterable[Any]:
        """The session's frames; with ``record_dataflash`` the 200 Hz ones and a log writer per flight."""
        if not self.protocol.config.record_dataflash:
            return self.session.frames()

        sess: Any = self.session
        rpm, chirps = rotor_rpm(sess), chirp_plan(sess)
        self.protocol.log_writer_factory = lambda: DataflashWriter(rpm, chirps)
        return sess.frames(fast_gyro=True)

    async def _read_loop(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            try:
                data = await self.port.aread()
            except PortUnplugged:
                await asyncio.sleep(0.02)
                continue
            if data:
                self.protocol.receive_data(data)

    async def _send(self, packets: list[bytes], stop: asyncio.Event) -> None:
        if not packets:
            return
        data = b"".join(packets)
        try:
            if not self.port.reader_attached():
                self.stats.packets_unheard += len(packets)
                return
            self.stats.bytes_sent += await self.port.awrite(data, stop)
        except PortUnplugged:
            self.stats.packets_unheard += len(packets)

    async def run(self, stop_event: asyncio.Event | None = None) -> FcStats:
        """Serve until the frame source ends (or, with ``idle_after_end``, until ``stop_event``)."""
        stop = stop_event or asyncio.Event()
        loop = asyncio.get_running_loop()
        reader = asyncio.create_task(self._read_loop(stop))
        try:
            wall0: float | None = None
            t0 = 0.0
            last_t = 0.0
            frames: Iterator[Any] = iter(self._frames())
            idle = False
            while not stop.is_set():
                try:
                    frame = next(frames)
                except StopIteration:
                    if idle or not self.protocol.config.idle_after_end:
                        break
                    frames, idle = _idle_frames(last_t), True
                    # idle frames come at 50 Hz real time at most: nothing to simulate
                    if math.isinf(self.speed):
                        wall0, t0, self.speed = loop.time(), last_t, 1.0
                    continue
                last_t = float(frame.t_boot_s)
                if wall0 is None:
                    wall0, t0 = loop.time(), last_t
                if math.isinf(self.speed):
                    await asyncio.sleep(0)
                else:
                    delay = wall0 + (last_t - t0) / self.speed - loop.time()
                    if delay > 0:
                        await asyncio.sleep(delay)
                    elif delay < -1.0:  # far behind (stalled reader): do not burst to catch up
                        wall0 -= delay
                    else:
                        await asyncio.sleep(0)
                await self._send(self.protocol.on_frame(frame), stop)
        finally:
            stop.set()
            reader.cancel()
            try:
                await reader
            except asyncio.CancelledError:
                pass
            self._hear_the_rest()
        return self.stats

    def _hear_the_rest(self) -> None:
        """Bytes the ground station wrote before the end are still heard (a last LOG_REQUEST_END
        written just before it closed its port), as a real FC would have read them."""
        try:
            while data := self.port.read_nowait():
                self.protocol.receive_data(data)
        except (PortUnplugged, OSError):
            pass


def _make_session(seed: int, flights: int, effects: Sequence[Any], aircraft: Any,
                  sim_options: Mapping[str, Any] | None = None) -> FrameSource:
    # SimulatedSession takes Effect objects or "name:key=value" strings itself
    return SimulatedSession(seed=seed, flights=flights, effects=tuple(effects), aircraft=aircraft,
                            **dict(sim_options or {}))


async def serve_simulated_fc(link_path: str | None = None, *, speed: float = 1.0, seed: int = 0,
                             flights: int = 2, effects: Sequence[Any] = (), stop_event: asyncio.Event | None = None,
                             aircraft: Any = None, config: FcConfig | None = None,
                             session: FrameSource | None = None,
                             on_ready: Callable[[str], None] | None = None,
                             sim_options: Mapping[str, Any] | None = None) -> FcStats:
    """Run a simulated helicopter FC on a new virtual serial port until ``stop_event`` is set.

    ``on_ready(port_path)`` is called once the port exists (print it there). ``effects`` are
    ``hil_replay.sim`` effect objects or ``"name:key=value"`` strings; ``session`` overrides the
    simulator entirely; ``sim_options`` are passed on to ``SimulatedSession`` (e.g. ``pause_s``).
    The FC seed for link loss is ``seed`` unless ``config`` says otherwise.
    """
    src = session if session is not None else _make_session(seed, flights, effects, aircraft, sim_options)
    cfg = config if config is not None else FcConfig(seed=seed)
    port = VirtualSerialPort(link_path)
    try:
        if on_ready is not None:
            on_ready(port.path)
        fc = SimulatedFlightController(src, port, speed=speed, config=cfg)
        return await fc.run(stop_event)
    finally:
        port.close()


class SimulatedFCThread:
    """A simulated FC on its own thread and event loop, for synchronous callers and tests.

    The port exists as soon as the object is constructed (``port_path``); :meth:`start` begins
    serving, :meth:`stop` ends it, closes the port and re-raises any error from the thread.
    """

    def __init__(self, link_path: str | None = None, *, speed: float = 1.0, seed: int = 0,
                 flights: int = 2, effects: Sequence[Any] = (), aircraft: Any = None,
                 config: FcConfig | None = None, session: FrameSource | None = None,
                 sim_options: Mapping[str, Any] | None = None) -> None:
        src = session if session is not None else _make_session(seed, flights, effects, aircraft, sim_options)
        self.port = VirtualSerialPort(link_path)
        self.fc = SimulatedFlightController(src, self.port, speed=speed,
                                            config=config if config is not None else FcConfig(seed=seed))
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._main, name="simulated-fc", daemon=True)
        self.error: BaseException | None = None

    @property
    def port_path(self) -> str:
        return self.port.path

    @property
    def stats(self) -> FcStats:
        return self.fc.stats

    def _main(self) -> None:
        async def body() -> None:
            self._loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            self._ready.set()
            await self.fc.run(self._stop)

        try:
            asyncio.run(body())
        except BaseException as exc:  # handed to the caller in stop()
            self.error = exc
        finally:
            self._ready.set()

    def unplug(self, duration_s: float) -> None:
        """Thread-safe: the port vanishes now and comes back at the same path after ``duration_s``."""
        if self._loop is None or not self._thread.is_alive():
            raise RuntimeError(f"{self.port_path}: simulated FC is not running")
        done = threading.Event()

        def do() -> None:
            try:
                self.fc.unplug(duration_s)
            finally:
                done.set()

        self._loop.call_soon_threadsafe(do)
        done.wait(5.0)

    def reboot(self, boot_s: float = 2.0) -> None:
        """Thread-safe: the FC reboots at its next frame (see :meth:`FcProtocol.reboot`)."""
        if self._loop is None or not self._thread.is_alive():
            raise RuntimeError(f"{self.port_path}: simulated FC is not running")
        self._loop.call_soon_threadsafe(self.fc.protocol.reboot, boot_s)

    def start(self) -> SimulatedFCThread:
        self._thread.start()
        self._ready.wait()
        return self

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout_s: float = 10.0) -> FcStats:
        """Stop serving and close the port (safe to call twice, or without :meth:`start`)."""
        if self._loop is not None and self._stop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread.ident is not None:
            self._thread.join(timeout_s)
        self.port.close()
        if self.error is not None:
            raise self.error
        if self._thread.is_alive():
            raise TimeoutError(f"{self.port_path}: simulated FC did not stop within {timeout_s} s")
        return self.stats

    def __enter__(self) -> SimulatedFCThread:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
