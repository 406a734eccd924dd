"""Structure check of a downloaded onboard log: where its record chain breaks, as byte ranges to blame.

A dataflash log (ArduPilot ``.bin``) is a chain of records, each ``0xA3 0x95 type`` and a body whose
length the type's FMT record gives (FMT itself is type 128, 89 bytes). A ULog (PX4 ``.ulg``) is a
16-byte header and a chain of ``size (u16) type (u8)`` messages of known types. :func:`record_breaks`
walks that chain and returns, for every place it breaks, the bytes that may hold the fault: from the
last record that parsed to where the chain picks up again, and the FMT record that gave that last
record its length. A CRC-valid but wrong block breaks the chain when it hits a record header, a
length or a FMT record; a wrong byte inside a record's values does not (that is what a second copy
of the block checks). Pure functions, no IO.
"""

from __future__ import annotations

__all__ = ["log_kind", "record_breaks"]

_DF_HEAD = b"\xa3\x95"
_DF_FMT = 0x80
_DF_FMT_LEN = 89
_ULOG_MAGIC = b"ULog\x01\x12\x35"
_ULOG_HEADER = 16
_ULOG_TYPES = frozenset(b"BFIMPQADLCSRO")


def log_kind(data: bytes | bytearray) -> str:
    """``"dataflash"``, ``"ulog"`` or ``"unknown"`` from the first bytes."""
    if data[:7] == _ULOG_MAGIC:
        return "ulog"
    if data[:3] == _DF_HEAD + bytes((_DF_FMT,)):
        return "dataflash"
    return "unknown"


def record_breaks(data: bytes | bytearray) -> list[tuple[int, int]]:
    """Byte ranges ``(start, end)`` to blame for each break of the record chain (empty: it parses to
    its end). An unknown kind of log is not checked (empty)."""
    kind = log_kind(data)
    if kind == "dataflash":
        return _dataflash_breaks(bytes(data))
    if kind == "ulog":
        return _ulog_breaks(bytes(data))
    return []


def _dataflash_breaks(data: bytes) -> list[tuple[int, int]]:
    lens = [0] * 256
    lens[_DF_FMT] = _DF_FMT_LEN
    fmt_at = [-1] * 256  # where each type's FMT record is
    out: list[tuple[int, int]] = []
    n = len(data)
    p = last = 0
    while p < n:
        step = lens[data[p + 2]] if p + 2 < n and data[p] == 0xA3 and data[p + 1] == 0x95 else 0
        if step and p + step <= n:
            if data[p + 2] == _DF_FMT and step >= 5:
                lens[data[p + 3]] = data[p + 4] if data[p + 4] >= 3 else 0
                fmt_at[data[p + 3]] = p
            last, p = p, p + step
            continue
        q = _df_resync(data, p + 1, lens)
        out.append((last, q))
        t = data[last + 2] if last + 2 < n else _DF_FMT
        if fmt_at[t] >= 0:
            out.append((fmt_at[t], fmt_at[t] + _DF_FMT_LEN))
        last = p = q
    return out


def _df_resync(data: bytes, start: int, lens: list[int]) -> int:
    """The next header from ``start`` whose record is followed by another header (or the end)."""
    n = len(data)
    q = data.find(_DF_HEAD, start)
    while 0 <= q and q + 2 < n:
        step = lens[data[q + 2]]
        nxt = q + step
        if step and (nxt == n or (nxt + 2 < n and data[nxt:nxt + 2] == _DF_HEAD and lens[data[nxt + 2]])):
            return q
        q = data.find(_DF_HEAD, q + 1)
    return n


def _ulog_breaks(data: bytes) -> list[tuple[int, int]]:
    out: list[tuple[int, int]] = []
    n = len(data)
    p = last = _ULOG_HEADER
    while p < n:
        ok = p + 3 <= n and data[p + 2] in _ULOG_TYPES
        step = 3 + (data[p] | data[p + 1] << 8) if ok else 0
        if step and p + step <= n:
            last, p = p, p + step
            continue
        q = _ulog_resync(data, p + 1)
        out.append((last, q))
        last = p = q
    return out


def _ulog_resync(data: bytes, start: int) -> int:
    """The next offset from ``start`` where two messages of known types follow each other (or the end)."""
    n = len(data)
    for q in range(start, n - 2):
        if data[q + 2] not in _ULOG_TYPES:
            continue
        nxt = q + 3 + (data[q] | data[q + 1] << 8)
        if nxt == n or (nxt + 3 <= n and data[nxt + 2] in _ULOG_TYPES):
            return q
    return n
