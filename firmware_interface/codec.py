"""MAVLink framing and payload decoding on pymavlink's generated codec, without IO or time.

* :class:`Framer` turns a byte stream into whole, CRC-valid MAVLink 1/2 frames. It resynchronises
  byte by byte: a candidate frame whose CRC fails (or whose message id is unknown, so its CRC cannot
  be checked) costs only its magic byte, and scanning restarts right after it, so a corrupted byte
  never swallows the good packet that follows (pymavlink's own parser drops the whole declared
  length). Every byte that is not part of a valid frame is counted in ``corrupt_bytes``; failed
  frames in ``bad_crc`` (overlapping candidates inside one failed frame count once).
* :func:`frame_header` splits a frame into (msg_id, seq, sysid, compid, payload).
* :func:`check_frame` validates one frame at a given offset (used by the tolerant .tlog reader).

CRC extras, field order and struct layouts come from ``pymavlink.dialects.v20.ardupilotmega``
(which also carries every MAVLink 1 message); the CRC itself is ``fastcrc`` when pymavlink found it,
else a table-driven fallback. Unit conversion into typed events lives in
:mod:`firmware_interface.session`; signing keys are not verified here (signed frames are accepted on
CRC and their 13-byte signature kept in the raw bytes).
"""

from __future__ import annotations

import re
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from pymavlink.generator import mavcrc

__all__ = ["MAGIC_V1", "MAGIC_V2", "Framer", "check_frame", "frame_header", "MESSAGE_CLASSES"]

MAGIC_V1 = 0xFE
MAGIC_V2 = 0xFD
_MAGIC_RE = re.compile(b"[\xfd\xfe]")

#: msg_id -> pymavlink message class (name in ``.msgname``, layout in ``.unpacker``)
MESSAGE_CLASSES: dict[int, Any] = dict(mavlink2.mavlink_map)
_CRC_EXTRA_BYTE: dict[int, bytes] = {mid: bytes((cls.crc_extra,)) for mid, cls in MESSAGE_CLASSES.items()}


def _make_crc():
    fast = getattr(mavcrc, "mcrf4xx", None)
    if fast is not None:
        return fast
    table = []
    for i in range(256):  # CRC-16/MCRF4XX, reflected poly 0x8408
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0x8408 if c & 1 else c >> 1
        table.append(c)

    def crc16(data, initial=0xFFFF):  # pragma: no cover - only without fastcrc
        crc = 0xFFFF if initial is None else initial
        for b in data:
            crc = (crc >> 8) ^ table[(crc ^ b) & 0xFF]
        return crc

    return crc16


mcrf4xx = _make_crc()

OK, BAD, NEED_MORE = 0, 1, 2


def check_frame(buf: bytes | bytearray | memoryview, j: int, n: int | None = None) -> tuple[int, int, bool]:
    """Validate the frame starting at ``buf[j]`` (which must be a magic byte).

    Returns ``(status, length, crc_failed)``: ``OK`` and the frame length; ``NEED_MORE`` and the
    length needed; or ``BAD`` (length is the declared frame length, ``crc_failed`` True when the
    frame was complete but its checksum or message id did not check).
    """
    if n is None:
        n = len(buf)
    avail = n - j
    if buf[j] == MAGIC_V2:
        if avail < 10:
            return NEED_MORE, 12, False
        plen = buf[j + 1]
        inc = buf[j + 2]
        if inc & 0xFE:
            return BAD, 1, False
        total = plen + (25 if inc & 1 else 12)
        if avail < total:
            return NEED_MORE, total, False
        extra = _CRC_EXTRA_BYTE.get(buf[j + 7] | (buf[j + 8] << 8) | (buf[j + 9] << 16))
        end = j + 10 + plen
    else:
        if avail < 6:
            return NEED_MORE, 8, False
        plen = buf[j + 1]
        total = plen + 8
        if avail < total:
            return NEED_MORE, total, False
        extra = _CRC_EXTRA_BYTE.get(buf[j + 5])
        end = j + 6 + plen
    if extra is None:
        return BAD, total, True
    crc = mcrf4xx(extra, mcrf4xx(memoryview(buf)[j + 1 : end]))
    if crc != (buf[end] | (buf[end + 1] << 8)):
        return BAD, total, True
    return OK, total, False


def frame_header(pkt: bytes) -> tuple[int, int, int, int, bytes]:
    """(msg_id, seq, sysid, compid, payload) of one whole frame."""
    if pkt[0] == MAGIC_V2:
        return pkt[7] | (pkt[8] << 8) | (pkt[9] << 16), pkt[4], pkt[5], pkt[6], pkt[10 : 10 + pkt[1]]
    return pkt[5], pkt[2], pkt[3], pkt[4], pkt[6 : 6 + pkt[1]]


class Framer:
    """Incremental MAVLink 1/2 frame extractor with garbage and CRC accounting.

    Attributes
    ----------
    corrupt_bytes : bytes skipped (garbage, bad-CRC frames, frames of unknown message id)
    bad_crc : frames that were complete but failed their checksum (or had an unknown id)
    """

    __slots__ = ("_buf", "_pos0", "_bad_until", "corrupt_bytes", "bad_crc")

    def __init__(self) -> None:
        self._buf = bytearray()
        self._pos0 = 0  # stream offset of _buf[0]
        self._bad_until = -1  # stream offset where the last failed candidate frame ends
        self.corrupt_bytes = 0
        self.bad_crc = 0

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)

    def flush(self) -> list[bytes]:
        """Give up waiting on the partial frame at the front (its declared length may be corrupt):
        skip its magic byte and rescan, returning any whole frames that were held back behind it."""
        out: list[bytes] = []
        while self._buf:
            del self._buf[:1]
            self._pos0 += 1
            self.corrupt_bytes += 1
            out += self.feed(b"")
        return out

    def reset(self) -> int:
        """Drop any partial frame (the link went down); returns how many bytes were dropped."""
        dropped = len(self._buf)
        self.corrupt_bytes += dropped
        self._pos0 += dropped
        self._buf = bytearray()
        return dropped

    def feed(self, data: bytes | bytearray | memoryview) -> list[bytes]:
        """Add bytes; return every whole, CRC-valid frame completed by them, in order."""
        buf = self._buf
        buf += data
        n = len(buf)
        out: list[bytes] = []
        i = 0
        search = _MAGIC_RE.search
        corrupt = 0
        while i < n:
            mo = search(buf, i)
            if mo is None:
                corrupt += n - i
                i = n
                break
            j = mo.start()
            corrupt += j - i
            i = j
            status, total, crc_failed = check_frame(buf, j, n)
            if status == OK:
                out.append(bytes(buf[j : j + total]))
                i = j + total
            elif status == NEED_MORE:
                break
            else:
                if crc_failed:
                    pos = self._pos0 + j
                    if pos >= self._bad_until:
                        self.bad_crc += 1
                        self._bad_until = pos + total
                corrupt += 1
                i = j + 1
        self.corrupt_bytes += corrupt
        if i:
            del buf[:i]
            self._pos0 += i
        return out
