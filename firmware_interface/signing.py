"""MAVLink 2 message signing for the FC link: key handling, signing outgoing frames, checking incoming.

Signing (MAVLink 2 spec, "Message signing") appends 13 bytes to a frame whose incompat flag 0x01 is
set: ``link_id`` (1 byte), a 48-bit timestamp in 10 µs units since 2015-01-01 UTC, and the first
6 bytes of ``SHA-256(secret_key + header + payload + crc + link_id + timestamp)``. The CRC covers
the header, so setting the flag changes it; :func:`sign_frame` recomputes it with the message's
CRC extra from pymavlink's generated dialect (pymavlink's own ``MAVLink.signing`` does the same
for messages it packs; this module works on bytes so it can sit under any encoder).

* :class:`SigningKey` holds the 32-byte secret. ``repr``/``str`` show only a fingerprint; pickling
  is refused; :meth:`SigningKey.from_file` refuses a key file that group or others can access
  (like ssh) and never puts key material in an error message.
* :class:`SigningConfig` (frozen) says whether the link is signed: ``key_file`` empty = unsigned.
* :func:`verify` checks one frame's signature (stateless). :class:`SignatureVerifier` adds what the
  spec requires on a link: per-stream (link id, sysid, compid) timestamps that must increase
  (replay protection), a new stream no more than a minute older than the newest time seen, and
  counters for the status (good, unsigned, bad signature, replayed).
* :func:`session_hooks` turns a :class:`SigningConfig` into the ``verifier``/``signer`` pair that
  :class:`firmware_interface.session.MavlinkSession` takes; ``verifier.status()`` is the status block.
* :class:`Signer` (:func:`make_signer`) signs outgoing frames with a timestamp that never goes
  backwards; :meth:`Signer.sign_stream` signs every frame in a chunk such as
  ``MavlinkSession.data_to_send()``.

Pure apart from :meth:`SigningKey.from_file`: no clock (callers pass Unix time in), no sockets,
so :mod:`firmware_interface.session` can use it. Leaves the decision of what to do with a frame
that fails (record raw, flag, do not decode) to the session and the recorder.
"""

from __future__ import annotations

import enum
import hashlib
import hmac
import os
import stat
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.errors import LinkError

__all__ = [
    "SIGNATURE_LEN", "SigningError", "SigningKey", "SigningConfig", "SignatureCheck",
    "SignatureVerifier", "Signer", "make_signer", "verify", "sign_frame", "is_signed",
    "timestamp_from_unix", "frame_timestamp", "session_hooks",
]

SIGNATURE_LEN = 13
IFLAG_SIGNED = 0x01
#: 2015-01-01T00:00:00Z in Unix seconds: the MAVLink signing epoch
EPOCH_UNIX_S = 1420070400
#: a new stream may start this far (10 µs units) behind the newest timestamp seen: one minute
NEW_STREAM_WINDOW = 60 * 100_000
_HEADER_V2 = 10


class SigningError(LinkError):
    """The signing key or configuration is unusable (one line, never containing key material)."""


class SigningKey:
    """A 32-byte MAVLink signing secret that does not print itself.

    Build it with :meth:`from_file`, :meth:`from_hex` or :meth:`from_passphrase` (SHA-256 of the
    passphrase, the convention of MAVProxy and Mission Planner).
    """

    __slots__ = ("_secret", "fingerprint")

    def __init__(self, secret: bytes) -> None:
        if not isinstance(secret, bytes | bytearray) or len(secret) != 32:
            raise SigningError("a MAVLink signing key is exactly 32 bytes")
        self._secret = bytes(secret)
        #: short public identifier (hash of the hash): safe to log, useless to an attacker
        self.fingerprint = hashlib.sha256(hashlib.sha256(self._secret).digest()).hexdigest()[:12]

    @classmethod
    def from_hex(cls, text: str) -> SigningKey:
        try:
            raw = bytes.fromhex(text.strip())
        except ValueError:
            raise SigningError("signing key is not 64 hexadecimal digits") from None
        return cls(raw)

    @classmethod
    def from_passphrase(cls, passphrase: str) -> SigningKey:
        if not passphrase:
            raise SigningError("empty signing passphrase")
        return cls(hashlib.sha256(passphrase.encode()).digest())

    @classmethod
    def from_file(cls, path: str | os.PathLike[str]) -> SigningKey:
        """Read a key file: 32 raw bytes, 64 hex digits, or one line of passphrase.

        Refuses a file that is not a regular file or that group/others may read, write or execute.
        """
        p = Path(path)
        try:
            st = p.stat()
        except FileNotFoundError:
            raise SigningError(f"{p}: signing key file not found") from None
        except OSError as exc:
            raise SigningError(f"{p}: cannot read signing key file ({exc.strerror})") from None
        if not stat.S_ISREG(st.st_mode):
            raise SigningError(f"{p}: signing key is not a regular file")
        if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise SigningError(
                f"{p}: signing key file is accessible by group/others (mode {stat.S_IMODE(st.st_mode):o}); "
                f"run chmod 600 {p}"
            )
        try:
            data = p.read_bytes()
        except OSError as exc:
            raise SigningError(f"{p}: cannot read signing key file ({exc.strerror})") from None
        if len(data) == 32:
            return cls(data)
        try:
            text = data.decode("ascii").strip()
        except UnicodeDecodeError:
            raise SigningError(f"{p}: signing key file is neither 32 raw bytes nor text") from None
        if len(text) == 64 and all(c in "0123456789abcdefABCDEF" for c in text):
            return cls(bytes.fromhex(text))
        if "\n" in text:
            raise SigningError(f"{p}: signing key file must hold one line (hex key or passphrase)")
        try:
            return cls.from_passphrase(text)
        except SigningError:
            raise SigningError(f"{p}: signing key file is empty") from None

    def secret(self) -> bytes:
        """The raw secret (for code that must hand it to an encoder; never log it)."""
        return self._secret

    def __repr__(self) -> str:
        return f"SigningKey(fingerprint={self.fingerprint})"

    __str__ = __repr__

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SigningKey) and hmac.compare_digest(self._secret, other._secret)

    def __hash__(self) -> int:
        return hash(self.fingerprint)

    def __reduce__(self):   # no pickling: a key must not travel to worker processes or files
        raise TypeError("SigningKey cannot be pickled")


@dataclass(frozen=True)
class SigningConfig:
    """MAVLink signing on the FC link (``key_file`` empty = the link is unsigned).

    accept_unsigned : message names processed even when unsigned (e.g. ``RADIO_STATUS`` injected by
        a telemetry radio that cannot sign); they are still counted as unsigned.
    link_id : our link id in outgoing signatures.
    """

    key_file: str = ""
    link_id: int = 0
    accept_unsigned: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not 0 <= self.link_id <= 255:
            raise SigningError(f"signing link_id must be 0..255, got {self.link_id}")
        known = {cls.msgname for cls in mavlink2.mavlink_map.values()}
        for name in self.accept_unsigned:
            if name not in known:
                raise SigningError(f"signing accept_unsigned: unknown MAVLink message {name!r}")

    @property
    def enabled(self) -> bool:
        return bool(self.key_file)

    def load_key(self) -> SigningKey:
        if not self.key_file:
            raise SigningError("signing is not configured (no key_file)")
        return SigningKey.from_file(self.key_file)


def timestamp_from_unix(unix_s: float) -> int:
    """MAVLink signing timestamp (10 µs since 2015-01-01 UTC) of a Unix time."""
    return max(0, int((unix_s - EPOCH_UNIX_S) * 100_000))


def is_signed(frame: bytes) -> bool:
    """Whether ``frame`` is a MAVLink 2 frame with the signed flag and room for the signature."""
    return (len(frame) >= _HEADER_V2 + 2 + SIGNATURE_LEN and frame[0] == mavlink2.PROTOCOL_MARKER_V2
            and bool(frame[2] & IFLAG_SIGNED) and len(frame) == _HEADER_V2 + frame[1] + 2 + SIGNATURE_LEN)


def frame_timestamp(frame: bytes) -> int:
    """The signature timestamp of a signed frame."""
    lo, hi = struct.unpack("<IH", frame[-12:-6])
    return lo | (hi << 32)


def _digest(key: SigningKey, signed_part: bytes) -> bytes:
    return hashlib.sha256(key.secret() + signed_part).digest()[:6]


def verify(frame: bytes, key: SigningKey) -> bool:
    """True if ``frame`` carries a valid signature for ``key`` (no replay check; see the verifier)."""
    if not is_signed(frame):
        return False
    return hmac.compare_digest(_digest(key, frame[:-6]), frame[-6:])


def sign_frame(frame: bytes, key: SigningKey, timestamp: int, link_id: int = 0) -> bytes:
    """Sign one unsigned MAVLink 2 frame: set the flag, recompute the CRC, append the signature."""
    if not frame or frame[0] != mavlink2.PROTOCOL_MARKER_V2:
        raise SigningError("only MAVLink 2 frames can be signed")
    if frame[2] & IFLAG_SIGNED:
        raise SigningError("frame is already signed")
    n = _HEADER_V2 + frame[1]
    if len(frame) != n + 2:
        raise SigningError("not one whole MAVLink 2 frame")
    msg_id = frame[7] | (frame[8] << 8) | (frame[9] << 16)
    cls = mavlink2.mavlink_map.get(msg_id)
    if cls is None:
        raise SigningError(f"unknown message id {msg_id}: cannot compute its CRC")
    body = bytearray(frame[:n])
    body[2] |= IFLAG_SIGNED
    crc = mavlink2.x25crc(bytes(body[1:]))
    crc.accumulate(struct.pack("B", cls.crc_extra))
    body += struct.pack("<H", crc.crc)
    body += struct.pack("<BQ", link_id, timestamp)[:7]
    body += _digest(key, bytes(body))
    return bytes(body)


class Signer:
    """Signs outgoing frames with increasing timestamps (see :func:`make_signer`)."""

    def __init__(self, key: SigningKey, *, link_id: int = 0, now_unix_s: float = EPOCH_UNIX_S) -> None:
        self._key = key
        self.link_id = link_id
        self.timestamp = timestamp_from_unix(now_unix_s)
        self.signed = 0

    def sign(self, frame: bytes, now_unix_s: float | None = None) -> bytes:
        """Sign one frame; the timestamp is the later of ``now`` and one tick after the last one."""
        ts = self.timestamp + 1
        if now_unix_s is not None:
            ts = max(ts, timestamp_from_unix(now_unix_s))
        self.timestamp = ts
        self.signed += 1
        return sign_frame(frame, self._key, ts, self.link_id)

    def sign_stream(self, data: bytes, now_unix_s: float | None = None) -> bytes:
        """Sign every whole MAVLink 2 frame in ``data`` (as produced by an encoder, back to back)."""
        out = bytearray()
        i = 0
        while i < len(data):
            if data[i] != mavlink2.PROTOCOL_MARKER_V2 or i + _HEADER_V2 + 2 > len(data):
                raise SigningError(f"byte {i}: not the start of a whole MAVLink 2 frame")
            end = i + _HEADER_V2 + data[i + 1] + 2
            if end > len(data):
                raise SigningError(f"byte {i}: truncated MAVLink 2 frame")
            out += self.sign(bytes(data[i:end]), now_unix_s)
            i = end
        return bytes(out)

    def __repr__(self) -> str:
        return f"Signer(key={self._key!r}, link_id={self.link_id}, signed={self.signed})"


def make_signer(key: SigningKey, *, link_id: int = 0, now_unix_s: float = EPOCH_UNIX_S) -> Signer:
    """A :class:`Signer` for ``key`` starting at ``now_unix_s`` (pass the wall clock at start-up)."""
    return Signer(key, link_id=link_id, now_unix_s=now_unix_s)


class SignatureCheck(enum.Enum):
    OK = "ok"
    UNSIGNED = "unsigned"                   # no signature and not on the accept list
    ACCEPTED_UNSIGNED = "accepted_unsigned"  # no signature, but on the accept list
    BAD_SIGNATURE = "bad_signature"         # wrong key or altered bytes
    REPLAYED = "replayed"                   # valid signature, timestamp not newer than the stream's

    @property
    def ok(self) -> bool:
        """Whether the frame may be decoded and processed."""
        return self in (SignatureCheck.OK, SignatureCheck.ACCEPTED_UNSIGNED)


class SignatureVerifier:
    """Check incoming frames on a signed link: signature, replay, accept list; counts for the status.

    Parameters
    ----------
    key : the link's key
    accept_unsigned : message names processed even when unsigned
    """

    def __init__(self, key: SigningKey, accept_unsigned: Iterable[str] = ()) -> None:
        self._key = key
        names = set(accept_unsigned)
        self._accept_ids = frozenset(mid for mid, cls in mavlink2.mavlink_map.items() if cls.msgname in names)
        self._streams: dict[tuple[int, int, int], int] = {}
        self.newest_timestamp = 0
        self.counts: dict[str, int] = {c.value: 0 for c in SignatureCheck}

    def check(self, frame: bytes) -> SignatureCheck:
        result = self._check(frame)
        self.counts[result.value] += 1
        return result

    def _check(self, frame: bytes) -> SignatureCheck:
        if not is_signed(frame):
            msg_id = (frame[7] | (frame[8] << 8) | (frame[9] << 16)) if frame[:1] == b"\xfd" and len(frame) > 9 \
                else (frame[5] if len(frame) > 5 else -1)
            return SignatureCheck.ACCEPTED_UNSIGNED if msg_id in self._accept_ids else SignatureCheck.UNSIGNED
        if not verify(frame, self._key):
            return SignatureCheck.BAD_SIGNATURE
        ts = frame_timestamp(frame)
        stream = (frame[-13], frame[5], frame[6])   # link id, sysid, compid
        last = self._streams.get(stream)
        if last is not None and ts <= last:
            return SignatureCheck.REPLAYED
        if last is None and ts + NEW_STREAM_WINDOW < self.newest_timestamp:
            return SignatureCheck.REPLAYED
        self._streams[stream] = ts
        self.newest_timestamp = max(self.newest_timestamp, ts)
        return SignatureCheck.OK

    def status(self) -> dict[str, object]:
        """For the service status: key fingerprint (never the key) and the counters."""
        return {"enabled": True, "key_fingerprint": self._key.fingerprint, **self.counts}

    def __repr__(self) -> str:
        return f"SignatureVerifier(key={self._key!r}, counts={self.counts})"


def session_hooks(config: SigningConfig, now_unix_s: float) -> tuple[SignatureVerifier | None, Signer | None]:
    """``(verifier, signer)`` for ``MavlinkSession(config, verifier=..., signer=...)``.

    ``(None, None)`` for an unsigned link; loads the key file (:class:`SigningError`, one line
    naming the file, if it is missing or readable by others). Pass the wall clock as ``now_unix_s``.
    """
    if not config.enabled:
        return None, None
    key = config.load_key()
    return (SignatureVerifier(key, config.accept_unsigned),
            make_signer(key, link_id=config.link_id, now_unix_s=now_unix_s))
