"""Sans-IO MAVLink session with the flight controller: bytes in, typed events out, bytes to send.

Usage (the driver owns all IO and the clock)::

    s = MavlinkSession(SessionConfig())
    s.receive_data(chunk, now)          # bytes from the link, host time `now` (Unix s)
    for ev in s.events(): ...           # RawPacket for every CRC-valid frame, then typed samples
    link.write(s.data_to_send(now))     # heartbeats, stream requests, retries due at `now`

What it does:

* framing of MAVLink 1 and 2 (:class:`firmware_interface.codec.Framer`): garbage and bad-CRC frames
  are counted in :attr:`MavlinkSession.stats` (:class:`~firmware_interface.samples.LinkStats`),
  never raised; packet loss per (sysid, compid) from ``seq``;
* decoding into the frozen dataclasses of :mod:`firmware_interface.samples`, in SI units;
* the FC clock: ``time_boot_ms`` (uint32 ms) and the uint32 ``time_usec`` of SERVO_OUTPUT_RAW are
  unwrapped; a backward step larger than ``reboot_backstep_s`` that a wrap cannot explain is an FC
  reboot (:class:`~firmware_interface.samples.FcRebooted`); ``t_fc_s`` then continues from where it
  was plus the host-measured gap, so the time base stays monotone across reboots;
* host/FC clock model (:class:`ClockModel`): lower envelope of ``host - fc`` per 1 s bin and a
  least-squares line through the recent bin minima (offset and drift); messages without an FC time
  field get their ``t_fc_s`` from it;
* link health: LinkLost after ``link_timeout_s`` without a valid frame (or when the driver calls
  :meth:`MavlinkSession.link_down`), LinkRestored on the next valid frame;
* stream setup once the FC's heartbeat is seen: GCS heartbeat at 1 Hz, MAV_CMD_SET_MESSAGE_INTERVAL
  per configured message, one at a time, checking COMMAND_ACK with retries; messages denied,
  unsupported or never acknowledged fall back to REQUEST_DATA_STREAM of their stream group; all of
  it again after an FC reboot or a restored link;
* optional MAVLink 2 signing (``verifier``/``signer`` from :mod:`firmware_interface.signing`):
  frames that fail verification are still emitted as RawPacket (``signature_ok=False``, so they
  are recorded) but not decoded and not trusted for link health; outgoing bytes are signed;
* a read-only allowlist on everything sent (:func:`check_outgoing`): HEARTBEAT (as a GCS),
  REQUEST_DATA_STREAM, COMMAND_LONG with MAV_CMD_SET_MESSAGE_INTERVAL or MAV_CMD_REQUEST_MESSAGE
  only, and the log-download requests LOG_REQUEST_LIST, LOG_REQUEST_DATA, LOG_REQUEST_END (never
  LOG_ERASE); anything else raises :class:`~firmware_interface.errors.LocalProtocolError`.

Leaves to others: the bytes' transport (:mod:`firmware_interface.transports`), the driver loop
(:mod:`firmware_interface.link`), recording (:mod:`firmware_interface.recorder`). No IO, no clock.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.codec import MESSAGE_CLASSES, Framer, frame_header
from firmware_interface.errors import LocalProtocolError
from firmware_interface.samples import (
    Attitude,
    CommandAck,
    ExtendedSysState,
    FcRebooted,
    GlobalPositionInt,
    GpsRawInt,
    Heartbeat,
    Imu,
    LinkLost,
    LinkRestored,
    LinkStats,
    LocalPositionNed,
    RawPacket,
    RcChannels,
    ServoOutputRaw,
    StatusText,
    SysStatus,
)

__all__ = [
    "ALLOWED_COMMANDS",
    "ALLOWED_MESSAGES",
    "DEFAULT_STREAM_RATES_HZ",
    "STREAM_GROUP_OF",
    "ClockModel",
    "MavlinkSession",
    "SessionConfig",
    "check_outgoing",
]

#: Messages requested by default and their rates (Hz).
DEFAULT_STREAM_RATES_HZ: tuple[tuple[str, float], ...] = (
    ("ATTITUDE", 50.0),
    ("SERVO_OUTPUT_RAW", 50.0),
    ("RAW_IMU", 50.0),
    ("LOCAL_POSITION_NED", 50.0),
    ("GLOBAL_POSITION_INT", 10.0),
    ("GPS_RAW_INT", 5.0),
    ("EXTENDED_SYS_STATE", 5.0),
    ("SYS_STATUS", 1.0),
)

#: ArduPilot's REQUEST_DATA_STREAM group for each message the fallback may need.
STREAM_GROUP_OF: dict[str, int] = {
    "RAW_IMU": mavlink2.MAV_DATA_STREAM_RAW_SENSORS,
    "SCALED_IMU2": mavlink2.MAV_DATA_STREAM_RAW_SENSORS,
    "SYS_STATUS": mavlink2.MAV_DATA_STREAM_EXTENDED_STATUS,
    "GPS_RAW_INT": mavlink2.MAV_DATA_STREAM_EXTENDED_STATUS,
    "EXTENDED_SYS_STATE": mavlink2.MAV_DATA_STREAM_EXTENDED_STATUS,
    "SERVO_OUTPUT_RAW": mavlink2.MAV_DATA_STREAM_RC_CHANNELS,
    "RC_CHANNELS": mavlink2.MAV_DATA_STREAM_RC_CHANNELS,
    "LOCAL_POSITION_NED": mavlink2.MAV_DATA_STREAM_POSITION,
    "GLOBAL_POSITION_INT": mavlink2.MAV_DATA_STREAM_POSITION,
    "ATTITUDE": mavlink2.MAV_DATA_STREAM_EXTRA1,
}

ALLOWED_MESSAGES: frozenset[int] = frozenset(
    {mavlink2.MAVLINK_MSG_ID_HEARTBEAT, mavlink2.MAVLINK_MSG_ID_COMMAND_LONG,
     mavlink2.MAVLINK_MSG_ID_REQUEST_DATA_STREAM,
     # onboard log download (firmware_interface.logdownload): read the FC's logs, never erase them
     mavlink2.MAVLINK_MSG_ID_LOG_REQUEST_LIST, mavlink2.MAVLINK_MSG_ID_LOG_REQUEST_DATA,
     mavlink2.MAVLINK_MSG_ID_LOG_REQUEST_END}
)
ALLOWED_COMMANDS: frozenset[int] = frozenset(
    {mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink2.MAV_CMD_REQUEST_MESSAGE}
)

_MS_WRAP_S = 4294967.296  # uint32 milliseconds
_US32_WRAP_S = 4294.967296  # uint32 microseconds
_WRAP_WINDOW_S = 60.0  # a wrap is recognised when the counter was within this of the top
_G = 9.80665


def check_outgoing(msg: Any) -> None:
    """Raise LocalProtocolError unless ``msg`` is on the read-only allowlist."""
    mid = msg.get_msgId()
    name = msg.get_type()
    if mid not in ALLOWED_MESSAGES:
        raise LocalProtocolError(f"refusing to send {name} (id {mid}): the ground station is read-only")
    if mid == mavlink2.MAVLINK_MSG_ID_COMMAND_LONG and msg.command not in ALLOWED_COMMANDS:
        raise LocalProtocolError(
            f"refusing to send COMMAND_LONG command {msg.command}: only SET_MESSAGE_INTERVAL and "
            "REQUEST_MESSAGE are allowed (read-only ground station)")
    if mid == mavlink2.MAVLINK_MSG_ID_HEARTBEAT and msg.type != mavlink2.MAV_TYPE_GCS:
        raise LocalProtocolError(f"refusing to send HEARTBEAT of MAV_TYPE {msg.type}: we are a GCS")


@dataclass(frozen=True)
class SessionConfig:
    """Session parameters (times in seconds).

    stream_rates_hz : (message name, rate) pairs requested from the FC
    request_streams : False for passive listening (log reading, a link someone else configures)
    send_heartbeat : False to send nothing at all (with request_streams False)
    emit_raw_packets : False to skip RawPacket events (offline decoding that records nothing)
    stale_frame_s : a partial frame waited on this long with no new bytes is given up (its length
        byte may be corrupt) and the bytes behind it rescanned
    target_sysid : the FC's system id; None = the first autopilot heartbeat seen
    """

    stream_rates_hz: tuple[tuple[str, float], ...] = DEFAULT_STREAM_RATES_HZ
    request_streams: bool = True
    send_heartbeat: bool = True
    emit_raw_packets: bool = True
    heartbeat_interval_s: float = 1.0
    ack_timeout_s: float = 1.0
    ack_retries: int = 2
    link_timeout_s: float = 3.0
    stale_frame_s: float = 0.25
    reboot_backstep_s: float = 1.0
    # the requested streams flowed after the last set-up, then stopped for this long while the
    # link stayed up (heartbeats only): the FC rebooted too briefly for the link timeout to
    # notice and, like ArduPilot, came back with no streams; the set-up is sent again
    stream_silence_s: float = 2.0
    target_sysid: int | None = None
    src_sysid: int = 255
    src_compid: int = 190
    clock_bin_s: float = 1.0
    clock_bins: int = 120

    def __post_init__(self) -> None:
        for name, rate in self.stream_rates_hz:
            if name not in MESSAGE_NAMES:
                raise ValueError(f"stream_rates_hz: unknown MAVLink message {name!r}")
            if not rate > 0:
                raise ValueError(f"stream_rates_hz: rate for {name} must be > 0, got {rate}")


MESSAGE_NAMES: dict[str, int] = {cls.msgname: mid for mid, cls in MESSAGE_CLASSES.items()}


class ClockModel:
    """Host-minus-FC clock offset: lower envelope per bin plus a least-squares drift line.

    ``offset(t_host)`` is host - fc in seconds (transport latency removed by the envelope);
    ``drift`` is d(host - fc)/d(host) (dimensionless; ``drift * 1e6`` ppm).
    """

    def __init__(self, bin_s: float = 1.0, max_bins: int = 120) -> None:
        self.bin_s = bin_s
        self._bins: deque[tuple[float, float]] = deque(maxlen=max_bins)
        self._bin_start: float | None = None
        self._bin_host = 0.0
        self._bin_min = math.inf
        self._a = math.nan  # offset at _t0
        self._b = 0.0
        self._t0 = 0.0
        self.samples = 0

    def add(self, t_host_s: float, t_fc_s: float) -> None:
        o = t_host_s - t_fc_s
        self.samples += 1
        if self._bin_start is None:
            self._bin_start = t_host_s
            self._a = o
            self._t0 = t_host_s
        elif t_host_s - self._bin_start >= self.bin_s:
            self._bins.append((self._bin_host, self._bin_min))
            self._bin_start = t_host_s
            self._bin_min = math.inf
            self._fit()
        if o < self._bin_min:
            self._bin_min = o
            self._bin_host = t_host_s
        if not self._bins:
            self._a = min(self._a, o)

    def _fit(self) -> None:
        pts = list(self._bins)
        n = len(pts)
        if n == 1:
            self._t0, self._a, self._b = pts[0][0], pts[0][1], 0.0
            return
        t0 = pts[-1][0]
        a, b = _line([(p[0] - t0, p[1]) for p in pts], n >= 3)
        if n >= 5:
            # bins with a late minimum (a burst of latency) sit above the envelope: drop and refit
            res = sorted(p[1] - (a + b * (p[0] - t0)) for p in pts)
            med = res[n // 2]
            mad = sorted(abs(r - med) for r in res)[n // 2]
            keep = [(p[0] - t0, p[1]) for p in pts if p[1] - (a + b * (p[0] - t0)) <= med + 4.5 * mad]
            if len(keep) >= 3:
                a, b = _line(keep, True)
                pts_used = keep
            else:
                pts_used = [(p[0] - t0, p[1]) for p in pts]
        else:
            pts_used = [(p[0] - t0, p[1]) for p in pts]
        # the line is a lower envelope: shift it down to the lowest bin
        a = min(p[1] - b * p[0] for p in pts_used)
        self._t0, self._a, self._b = t0, a, b

    def reset(self) -> None:
        self.__init__(self.bin_s, self._bins.maxlen or 120)  # type: ignore[misc]

    @property
    def known(self) -> bool:
        return not math.isnan(self._a)

    @property
    def drift(self) -> float:
        return self._b

    def offset(self, t_host_s: float) -> float:
        """host - fc (s) at host time ``t_host_s``; NaN before the first timed sample."""
        return self._a + self._b * (t_host_s - self._t0)

    def host_to_fc(self, t_host_s: float) -> float:
        return t_host_s - self.offset(t_host_s)


def _line(pts: list[tuple[float, float]], slope: bool) -> tuple[float, float]:
    """Least-squares a + b*x through (x, y) points (b = 0 unless ``slope``)."""
    n = len(pts)
    mx = sum(p[0] for p in pts) / n
    y0 = pts[0][1]  # subtract a reference: y are Unix-sized numbers
    my = sum(p[1] - y0 for p in pts) / n
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    b = sum((p[0] - mx) * (p[1] - y0 - my) for p in pts) / sxx if slope and sxx > 0 else 0.0
    return y0 + my - b * mx, b


@dataclass
class _FcClock:
    last_s: float | None = None  # last boot-relative FC time (s), unwrapped
    last_host_s: float = 0.0
    epoch_s: float = 0.0  # added to boot-relative time so t_fc_s stays monotone across reboots


@dataclass
class _Request:
    name: str
    msg_id: int
    rate_hz: float
    state: str = "pending"  # pending, sent, ok, fallback
    tries: int = 0
    deadline: float = 0.0


@dataclass
class _Setup:
    requests: list[_Request]
    unsupported: bool = False
    rds_sent: int = 0
    rds_deadline: float = 0.0

    @property
    def done(self) -> bool:
        return all(r.state in ("ok", "fallback") for r in self.requests)


@dataclass
class StreamStatus:
    """Outcome of stream setup: per message 'pending', 'sent', 'ok' (interval accepted) or 'fallback'."""

    states: dict[str, str] = field(default_factory=dict)
    data_stream_requests: int = 0


class MavlinkSession:
    """See the module docstring. ``now`` is the host time in Unix seconds, always passed in."""

    def __init__(self, config: SessionConfig | None = None, *, verifier: Any = None, signer: Any = None) -> None:
        self.config = config or SessionConfig()
        # MAVLink 2 signing (firmware_interface.signing): verifier.check(frame) -> SignatureCheck,
        # signer.sign_stream(bytes, now) -> bytes. None = unsigned link.
        self._verifier = verifier
        self._signer = signer
        self.stats = LinkStats()
        self.clock = ClockModel(self.config.clock_bin_s, self.config.clock_bins)
        self._framer = Framer()
        self._events: list[Any] = []
        self._out = bytearray()
        self._mav = mavlink2.MAVLink(None, self.config.src_sysid, self.config.src_compid)
        self._seq: dict[tuple[int, int], int] = {}
        self._clocks: dict[tuple[int, int], _FcClock] = {}
        self._clock_src: tuple[int, int] | None = None  # whose clock the ClockModel follows
        self.target: tuple[int, int] | None = None
        self._next_hb = 0.0
        self._last_rx: float | None = None
        self._last_data = 0.0
        self._lost = False
        self._setup: _Setup | None = None
        self._setup_started = 0.0
        self._last_stream_rx = 0.0  # host time of the last requested message from the target
        self._requested = frozenset(n for n, _ in self.config.stream_rates_hz)
        self.stream_rerequests = 0
        self.message_counts: dict[str, int] = {}
        self._emit_raw = self.config.emit_raw_packets
        self._decoders: dict[int, tuple[Any, int, Callable[..., Any] | None, str]] = {}
        for mid, cls in MESSAGE_CLASSES.items():
            conv = _CONVERTERS.get(cls.msgname)
            self._decoders[mid] = (cls.unpacker, cls.unpacker.size, conv, cls.msgname)

    # ------------------------------------------------------------------ input

    def receive_data(self, data: bytes, now: float) -> None:
        """Feed bytes received at host time ``now``."""
        fr = self._framer
        for pkt in fr.feed(data):
            self.receive_packet(pkt, now)
        self.stats.corrupt_bytes = fr.corrupt_bytes
        self.stats.bad_crc = fr.bad_crc
        self._last_data = now

    def _flush_framer(self, now: float) -> None:
        fr = self._framer
        for pkt in fr.flush():
            self.receive_packet(pkt, now)
        self.stats.corrupt_bytes = fr.corrupt_bytes
        self.stats.bad_crc = fr.bad_crc

    def receive_packet(self, pkt: bytes, now: float) -> None:
        """Handle one whole frame already known to be CRC-valid (e.g. from a .tlog record)."""
        msg_id, seq, sysid, compid, payload = frame_header(pkt)
        stats = self.stats
        dec = self._decoders.get(msg_id)
        if dec is None:  # not in the dialect: its CRC could not have been checked
            stats.corrupt_bytes += len(pkt)
            return
        stats.packets += 1
        key = (sysid, compid)
        last = self._seq.get(key)
        if last is not None:
            lost = (seq - last - 1) & 0xFF
            if lost and lost != 255:  # 255 = same seq again: a duplicate or a sender that never counts
                stats.packets_lost += lost
                k = f"{sysid}:{compid}"
                stats.loss_by_source[k] = stats.loss_by_source.get(k, 0) + lost
        self._seq[key] = seq
        unpacker, size, conv, name = dec
        self.message_counts[name] = self.message_counts.get(name, 0) + 1
        if name in self._requested and self.target is not None and sysid == self.target[0]:
            self._last_stream_rx = now
        sig_ok: bool | None = None
        if self._verifier is not None:
            sig_ok = bool(self._verifier.check(pkt).ok)
            if not sig_ok:
                # recorded (flagged) but neither decoded nor trusted for link health or stream setup
                stats.unsigned_dropped += 1
                if self._emit_raw:
                    self._events.append(RawPacket(now, pkt, msg_id, name, sysid, compid, seq, False))
                return
        if self._lost:
            self._lost = False
            self._events.append(LinkRestored(now))
            self._restart_setup(now)
        self._last_rx = now
        if self._emit_raw:
            self._events.append(RawPacket(now, pkt, msg_id, name, sysid, compid, seq, sig_ok))
        if conv is None:
            return
        if len(payload) < size:
            payload = payload + bytes(size - len(payload))
        elif len(payload) > size:
            payload = payload[:size]
        ev = conv(self, unpacker.unpack(payload), now, sysid, compid)
        if ev is not None:
            self._events.append(ev)
            if type(ev) is Heartbeat:
                self._on_heartbeat(ev, now)
            elif type(ev) is CommandAck:
                self._on_ack(ev, now)

    def events(self) -> list[Any]:
        """Events produced since the last call (and forget them)."""
        ev = self._events
        self._events = []
        return ev

    # ------------------------------------------------------------------ link health

    def link_down(self, now: float, reason: str) -> None:
        """The driver lost the transport (port vanished, socket closed)."""
        self._flush_framer(now)  # frames held behind a corrupt length byte are still whole
        if not self._lost:
            self._lost = True
            self._events.append(LinkLost(now, reason))

    @property
    def link_up(self) -> bool:
        return self._last_rx is not None and not self._lost

    # ------------------------------------------------------------------ output

    def send_message(self, msg: Any) -> None:
        """Queue one message (checked against the read-only allowlist)."""
        check_outgoing(msg)
        self._out += msg.pack(self._mav)
        self._mav.seq = (self._mav.seq + 1) & 0xFF

    def request_message(self, name: str) -> None:
        """Ask the FC for one instance of a message (MAV_CMD_REQUEST_MESSAGE)."""
        if self.target is None:
            raise LocalProtocolError("request_message: no flight controller heartbeat seen yet")
        self.send_message(self._mav.command_long_encode(
            self.target[0], self.target[1], mavlink2.MAV_CMD_REQUEST_MESSAGE, 0,
            float(MESSAGE_NAMES[name]), 0, 0, 0, 0, 0, 0))

    def handle_timer(self, now: float) -> None:
        """Run timeouts due at ``now``: heartbeat, ack retries, link timeout, stale partial frame."""
        if self._framer.buffered and now - self._last_data >= self.config.stale_frame_s:
            self._flush_framer(now)
        if (self._last_rx is not None and not self._lost
                and now - self._last_rx > self.config.link_timeout_s):
            self._lost = True
            self._events.append(LinkLost(now, f"no valid MAVLink frame for {self.config.link_timeout_s:g} s"))
        if self.target is None or self._lost:
            return
        if self.config.send_heartbeat and now >= self._next_hb:
            self.send_message(self._mav.heartbeat_encode(
                mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, mavlink2.MAV_STATE_ACTIVE))
            nxt = self._next_hb + self.config.heartbeat_interval_s
            self._next_hb = nxt if nxt > now else now + self.config.heartbeat_interval_s
        if self._setup is not None:
            if (self._setup.done and self._last_stream_rx > self._setup_started
                    and now - self._last_stream_rx > self.config.stream_silence_s):
                self.stream_rerequests += 1
                self._restart_setup(now)
            self._step_setup(now)

    def data_to_send(self, now: float) -> bytes:
        """Bytes due for the FC at ``now`` (runs :meth:`handle_timer` first)."""
        self.handle_timer(now)
        out = bytes(self._out)
        self._out.clear()
        if out and self._signer is not None:
            out = self._signer.sign_stream(out, now)
        return out

    @property
    def stream_status(self) -> StreamStatus:
        st = StreamStatus()
        if self._setup is not None:
            st.states = {r.name: r.state for r in self._setup.requests}
            st.data_stream_requests = self._setup.rds_sent
        return st

    # ------------------------------------------------------------------ stream setup

    def _restart_setup(self, now: float) -> None:
        if not self.config.request_streams or self.target is None:
            return
        self._setup_started = now
        self._setup = _Setup([_Request(n, MESSAGE_NAMES[n], r) for n, r in self.config.stream_rates_hz])

    def _on_heartbeat(self, hb: Heartbeat, now: float) -> None:
        if self.target is not None:
            return
        if hb.autopilot == mavlink2.MAV_AUTOPILOT_INVALID or hb.mav_type == mavlink2.MAV_TYPE_GCS:
            return
        if self.config.target_sysid is not None and hb.sysid != self.config.target_sysid:
            return
        self.target = (hb.sysid, hb.compid)
        self._next_hb = now
        self._restart_setup(now)

    def _on_ack(self, ack: CommandAck, now: float) -> None:
        s = self._setup
        if s is None or ack.command != mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        if self.target is not None and ack.sysid != self.target[0]:
            return
        cur = next((r for r in s.requests if r.state == "sent"), None)
        if cur is None:
            return
        if ack.result == mavlink2.MAV_RESULT_ACCEPTED:
            cur.state = "ok"
        elif ack.result == mavlink2.MAV_RESULT_IN_PROGRESS:
            return
        elif ack.result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED:
            cur.state = "pending"
            cur.deadline = now + self.config.ack_timeout_s
            return
        elif ack.result == mavlink2.MAV_RESULT_UNSUPPORTED:
            s.unsupported = True
            for r in s.requests:
                if r.state in ("pending", "sent"):
                    r.state = "fallback"
        else:  # DENIED, FAILED, ...: this message only
            cur.state = "fallback"
        self._step_setup(now)

    def _step_setup(self, now: float) -> None:
        s = self._setup
        assert s is not None and self.target is not None
        tsys, tcomp = self.target
        for r in s.requests:
            if r.state in ("ok", "fallback"):
                continue
            if r.state == "sent" and now < r.deadline:
                return
            if r.state == "pending" and r.tries and now < r.deadline:
                return
            if r.tries > self.config.ack_retries:
                r.state = "fallback"
                continue
            self.send_message(self._mav.command_long_encode(
                tsys, tcomp, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, r.tries,
                float(r.msg_id), 1e6 / r.rate_hz, 0, 0, 0, 0, 0))
            r.tries += 1
            r.state = "sent"
            r.deadline = now + self.config.ack_timeout_s
            return
        fallback = [r for r in s.requests if r.state == "fallback"]
        if not fallback or s.rds_sent >= 2 or now < s.rds_deadline:
            return
        groups: dict[int, float] = {}
        for r in fallback:
            g = STREAM_GROUP_OF.get(r.name)
            if g is not None:
                groups[g] = max(groups.get(g, 0.0), r.rate_hz)
        for g, rate in sorted(groups.items()):
            self.send_message(self._mav.request_data_stream_encode(
                tsys, tcomp, g, max(1, int(round(rate))), 1))
        s.rds_sent += 1
        s.rds_deadline = now + self.config.ack_timeout_s

    # ------------------------------------------------------------------ FC clock

    def _fc_time(self, sysid: int, compid: int, t_s: float, wrap_s: float, now: float) -> float:
        """Unwrap a boot-relative time, detect reboots; returns monotone t_fc_s."""
        key = (sysid, compid)  # a companion computer on the same sysid has its own boot clock
        c = self._clocks.get(key)
        if c is None:
            c = self._clocks[key] = _FcClock()
        ref = c.last_s
        if ref is not None:
            if wrap_s:
                # put the raw counter into the wrap period of the reference; step into the next
                # period only when the reference sits just before the wrap and the counter just after
                ref_mod = ref % wrap_s
                t_s += ref - ref_mod
                if t_s < ref - self.config.reboot_backstep_s:
                    if ref_mod > wrap_s - _WRAP_WINDOW_S and t_s - (ref - ref_mod) < _WRAP_WINDOW_S:
                        t_s += wrap_s
                elif t_s > ref + 0.5 * wrap_s:
                    t_s -= wrap_s  # a late sample from just before a wrap
            if t_s < ref - self.config.reboot_backstep_s:
                prev = ref + c.epoch_s
                c.epoch_s = prev + max(0.0, now - c.last_host_s) - t_s
                self.stats.fc_reboots += 1
                self._events.append(FcRebooted(now, sysid, prev))
                c.last_s = t_s
                # sequence numbers restart with the FC; do not count that as loss
                for seq_key in [k for k in self._seq if k[0] == sysid]:
                    del self._seq[seq_key]
                if self.target is not None and sysid == self.target[0]:
                    self._restart_setup(now)
            elif t_s > ref:
                c.last_s = t_s
        else:
            c.last_s = t_s
        c.last_host_s = now
        t_fc = t_s + c.epoch_s
        src = self.target or self._clock_src
        if src is None:
            src = self._clock_src = key
        if key == src:
            self.clock.add(now, t_fc)
        return t_fc

    def _t_ms(self, sysid: int, compid: int, ms: int, now: float) -> float:
        return self._fc_time(sysid, compid, ms * 1e-3, _MS_WRAP_S, now)

    def _t_us32(self, sysid: int, compid: int, us: int, now: float) -> float:
        return self._fc_time(sysid, compid, us * 1e-6, _US32_WRAP_S, now)

    def _t_us64(self, sysid: int, compid: int, us: int, now: float) -> float:
        t = us * 1e-6
        if t > 1e8:  # Unix epoch time (GPS-synchronised), not time since boot
            return self._t_est(sysid, compid, now)
        return self._fc_time(sysid, compid, t, 0.0, now)

    def _t_est(self, sysid: int, compid: int, now: float) -> float:
        if self.clock.known:
            return self.clock.host_to_fc(now)
        c = self._clocks.get((sysid, compid)) or self._clocks.get(self.target or self._clock_src or (-1, -1))
        return math.nan if c is None or c.last_s is None else c.last_s + c.epoch_s


# ---------------------------------------------------------------------- converters
# Each takes (session, unpacked wire-order tuple, now, sysid, compid) and returns an event.


def _idx(name: str) -> Callable[[str], int]:
    cls = MESSAGE_CLASSES[MESSAGE_NAMES[name]]
    fields = list(cls.ordered_fieldnames)
    return fields.index


def _state_converters() -> dict[str, Callable[..., Any]]:
    """HEARTBEAT, attitude and position."""
    convs: dict[str, Callable[..., Any]] = {}

    i = _idx("HEARTBEAT")
    i_cm, i_ty, i_ap, i_bm, i_ss = (i("custom_mode"), i("type"), i("autopilot"), i("base_mode"),
                                    i("system_status"))

    def heartbeat(s, t, now, sy, co):
        bm = t[i_bm]
        return Heartbeat(now, s._t_est(sy, co, now), sy, co, t[i_ty], t[i_ap], bm, t[i_cm], t[i_ss],
                         bool(bm & 128))

    convs["HEARTBEAT"] = heartbeat

    def attitude(s, t, now, sy, co):
        return Attitude(now, s._t_ms(sy, co, t[0], now), sy, co, t[1], t[2], t[3], t[4], t[5], t[6])

    convs["ATTITUDE"] = attitude

    def local_pos(s, t, now, sy, co):
        return LocalPositionNed(now, s._t_ms(sy, co, t[0], now), sy, co, t[1], t[2], t[3], t[4], t[5], t[6])

    convs["LOCAL_POSITION_NED"] = local_pos

    i = _idx("GLOBAL_POSITION_INT")
    g = [i(f) for f in ("time_boot_ms", "lat", "lon", "alt", "relative_alt", "vx", "vy", "vz", "hdg")]

    def global_pos(s, t, now, sy, co):
        hdg = t[g[8]]
        return GlobalPositionInt(now, s._t_ms(sy, co, t[g[0]], now), sy, co, t[g[1]] * 1e-7, t[g[2]] * 1e-7,
                                 t[g[3]] * 1e-3, t[g[4]] * 1e-3, t[g[5]] * 1e-2, t[g[6]] * 1e-2,
                                 t[g[7]] * 1e-2, math.nan if hdg == 65535 else hdg * 1e-2)

    convs["GLOBAL_POSITION_INT"] = global_pos
    return convs


def _input_converters() -> dict[str, Callable[..., Any]]:
    """Servo outputs and RC channels."""
    convs: dict[str, Callable[..., Any]] = {}

    i = _idx("SERVO_OUTPUT_RAW")
    sv = [i("time_usec"), i("port")] + [i(f"servo{k}_raw") for k in range(1, 17)]

    def servo(s, t, now, sy, co):
        return ServoOutputRaw(now, s._t_us32(sy, co, t[sv[0]], now), sy, co, t[sv[1]],
                              tuple([t[k] for k in sv[2:]]))

    convs["SERVO_OUTPUT_RAW"] = servo

    i = _idx("RC_CHANNELS")
    rc = [i("time_boot_ms"), i("rssi")] + [i(f"chan{k}_raw") for k in range(1, 19)]

    def rc_channels(s, t, now, sy, co):
        return RcChannels(now, s._t_ms(sy, co, t[rc[0]], now), sy, co, tuple([t[k] for k in rc[2:]]), t[rc[1]])

    convs["RC_CHANNELS"] = rc_channels
    return convs


def _sensor_converters() -> dict[str, Callable[..., Any]]:
    """IMUs and GPS."""
    convs: dict[str, Callable[..., Any]] = {}

    def imu_conv(name: str, time_field: str):
        i = _idx(name)
        ix = [i(f) for f in (time_field, "xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro")]
        acc = _G * 1e-3
        tfun = MavlinkSession._t_us64 if time_field == "time_usec" else MavlinkSession._t_ms

        def imu(s, t, now, sy, co):
            return Imu(now, tfun(s, sy, co, t[ix[0]], now), sy, co, name,
                       (t[ix[1]] * acc, t[ix[2]] * acc, t[ix[3]] * acc),
                       (t[ix[4]] * 1e-3, t[ix[5]] * 1e-3, t[ix[6]] * 1e-3))

        return imu

    convs["RAW_IMU"] = imu_conv("RAW_IMU", "time_usec")
    for name in ("SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"):
        convs[name] = imu_conv(name, "time_boot_ms")

    i = _idx("GPS_RAW_INT")
    gp = [i(f) for f in ("time_usec", "fix_type", "lat", "lon", "alt", "vel", "cog", "satellites_visible")]

    def gps(s, t, now, sy, co):
        vel, cog = t[gp[5]], t[gp[6]]
        return GpsRawInt(now, s._t_us64(sy, co, t[gp[0]], now), sy, co, t[gp[1]], t[gp[2]] * 1e-7,
                         t[gp[3]] * 1e-7, t[gp[4]] * 1e-3, math.nan if vel == 65535 else vel * 1e-2,
                         math.nan if cog == 65535 else cog * 1e-2, t[gp[7]])

    convs["GPS_RAW_INT"] = gps
    return convs


def _status_converters() -> dict[str, Callable[..., Any]]:
    """Landed state, battery and link status, text, command acknowledgements."""
    convs: dict[str, Callable[..., Any]] = {}

    i = _idx("EXTENDED_SYS_STATE")
    ev, el = i("vtol_state"), i("landed_state")

    def ext_state(s, t, now, sy, co):
        return ExtendedSysState(now, s._t_est(sy, co, now), sy, co, t[ev], t[el])

    convs["EXTENDED_SYS_STATE"] = ext_state

    i = _idx("SYS_STATUS")
    ss = [i(f) for f in ("voltage_battery", "current_battery", "battery_remaining", "drop_rate_comm",
                         "errors_comm", "load")]

    def sys_status(s, t, now, sy, co):
        v, c = t[ss[0]], t[ss[1]]
        return SysStatus(now, s._t_est(sy, co, now), sy, co, math.nan if v == 65535 else v * 1e-3,
                         math.nan if c == -1 else c * 1e-2, t[ss[2]], t[ss[3]] * 1e-2, t[ss[4]],
                         t[ss[5]] * 0.1)

    convs["SYS_STATUS"] = sys_status

    i = _idx("STATUSTEXT")
    st_sev, st_txt = i("severity"), i("text")

    def statustext(s, t, now, sy, co):
        return StatusText(now, s._t_est(sy, co, now), sy, co, t[st_sev],
                          t[st_txt].split(b"\0", 1)[0].decode("utf-8", "replace"))

    convs["STATUSTEXT"] = statustext

    i = _idx("COMMAND_ACK")
    ca_c, ca_r = i("command"), i("result")

    def command_ack(s, t, now, sy, co):
        return CommandAck(now, s._t_est(sy, co, now), sy, co, t[ca_c], t[ca_r])

    convs["COMMAND_ACK"] = command_ack
    return convs


def _make_converters() -> dict[str, Callable[..., Any]]:
    return {**_state_converters(), **_input_converters(), **_sensor_converters(), **_status_converters()}


_CONVERTERS = _make_converters()
