"""Tolerant .tlog record scanner (pure: works on bytes already read).

A .tlog is a sequence of records: 8-byte big-endian microseconds since the Unix epoch, then one
MAVLink frame exactly as received. Files in the field are damaged in a few typical ways, all handled
here without raising:

* a truncated last record (the logger was killed): counted in ``truncated_tail_bytes``;
* garbage between records (a serial glitch written by a careless logger, a partly overwritten file):
  skipped and counted in ``corrupt_bytes``;
* timestamp bytes that happen to contain 0xFD/0xFE (every timestamp may): the scanner walks the
  *record* structure (timestamp, then a CRC-valid frame), and only when that breaks does it
  resynchronise, on the next CRC-valid frame (a magic byte inside a timestamp does not start one);
* a damaged timestamp: a step of more than ``chain_s`` from the previous record that the next
  record does not confirm; the packet is kept at the previous record's time (``bad_timestamps``).

Leaves decoding to :mod:`firmware_interface.session` and file IO to :mod:`firmware_interface.readers`.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass

from firmware_interface.codec import NEED_MORE, OK, check_frame

__all__ = ["TlogScan", "scan_tlog"]

_TS = struct.Struct(">Q")
_MAGIC_RE = re.compile(b"[\xfd\xfe]")
# a plausible first timestamp (when resynchronising before any record was accepted): 1990..2100
_TS_MIN_US = 631152000 * 10**6
_TS_MAX_US = 4102444800 * 10**6


@dataclass
class TlogScan:
    """Counters of one scan (bytes)."""

    records: int = 0
    corrupt_bytes: int = 0
    truncated_tail_bytes: int = 0
    resyncs: int = 0
    bad_timestamps: int = 0  # valid frame, damaged timestamp: kept with the previous record's time


def scan_tlog(data: bytes, scan: TlogScan | None = None, *, chain_s: float = 60.0
              ) -> Iterator[tuple[float, bytes]]:
    """Yield ``(t_host_s, frame_bytes)`` for every intact record of ``data``.

    A timestamp more than ``chain_s`` away from the previous record's is accepted only when the
    next record confirms it (a gap or a host clock jump); otherwise it is damaged and the packet is
    kept at the previous time. When resynchronising after garbage, the next CRC-valid frame starts
    the next record (its timestamp then judged the same way). Counters go to ``scan``.
    """
    st = scan if scan is not None else TlogScan()
    n = len(data)
    p = 0
    prev_us: int | None = None
    chain_us = int(chain_s * 1e6)
    unpack_ts = _TS.unpack_from
    while p + 8 < n:
        j = p + 8
        b = data[j]
        if b == 0xFD or b == 0xFE:
            status, total, _ = check_frame(data, j, n)
            if status == OK:
                ts = unpack_ts(data, p)[0]
                end = j + total
                step = 0 if prev_us is None else ts - prev_us
                if -chain_us <= step <= chain_us:
                    st.records += 1
                    prev_us = ts
                    yield ts * 1e-6, data[j:end]
                    p = end
                    continue
                nxt = _ts_at(data, end, n)
                if nxt is not None and abs(nxt - ts) <= chain_us:
                    st.records += 1  # a gap in the recording or a host clock jump, confirmed
                    prev_us = ts
                    yield ts * 1e-6, data[j:end]
                    p = end
                    continue
                # unconfirmed jump: the timestamp is damaged; keep the packet at the previous time
                st.records += 1
                st.bad_timestamps += 1
                yield (prev_us if prev_us is not None else ts) * 1e-6, data[j:end]
                p = end
                continue
        # the record structure broke at p: find the next plausible record
        q = _resync(data, p + 1, n, prev_us)
        if q is None:
            status = NEED_MORE
            if b == 0xFD or b == 0xFE:
                status, _, _ = check_frame(data, j, n)
            if status == NEED_MORE:
                st.truncated_tail_bytes += n - p
            else:
                st.corrupt_bytes += n - p
            return
        st.resyncs += 1
        st.corrupt_bytes += q - p
        p = q
    if p < n:
        st.truncated_tail_bytes += n - p


def _ts_at(data: bytes, q: int, n: int) -> int | None:
    """Timestamp of the record at ``q`` if a valid frame follows it, else None."""
    if q + 8 >= n or data[q + 8] not in (0xFD, 0xFE):
        return None
    if check_frame(data, q + 8, n)[0] != OK:
        return None
    return _TS.unpack_from(data, q)[0]


def _resync(data: bytes, start: int, n: int, prev_us: int | None) -> int | None:
    """Start of the next record at or after ``start`` whose frame is CRC-valid (see the comment)."""
    pos = start + 8
    while True:
        mo = _MAGIC_RE.search(data, pos)
        if mo is None:
            return None
        j = mo.start()
        pos = j + 1
        if j - 8 < start:
            continue
        status, total, _ = check_frame(data, j, n)
        if status != OK:
            continue
        if prev_us is None:
            if _TS_MIN_US <= _TS.unpack_from(data, j - 8)[0] <= _TS_MAX_US:
                return j - 8
            continue
        # a CRC-valid frame is a record (a false match is a 1-in-65536 event per candidate); whether
        # its timestamp is believed is decided by the caller against its neighbours
        return j - 8
