"""The record-chain walk of a downloaded log: where a dataflash or ULog chain breaks, and what to blame."""

from __future__ import annotations

import lzma
import random
from pathlib import Path

import pytest

from firmware_interface.logcheck import log_kind, record_breaks

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def ulog() -> bytes:
    return lzma.open(DATA / "px4" / "pyulog_sample.ulg.xz").read()[:200_000]


def test_whole_logs_parse_and_unknown_data_is_not_checked(df_log, ulog):
    assert log_kind(df_log) == "dataflash" and record_breaks(df_log) == []
    assert log_kind(ulog) == "ulog"
    cut = record_breaks(ulog)  # cut at 200 kB: only the tail's partial message breaks
    assert len(cut) == 1 and cut[0][1] == len(ulog) and len(ulog) - cut[0][0] < 65_539
    blob = random.Random(0).randbytes(5000)
    assert log_kind(blob) == "unknown" and record_breaks(blob) == []


def test_a_broken_dataflash_header_or_fmt_length_is_blamed_where_it_is(df_log):
    heads = [i for i in range(len(df_log) - 1) if df_log[i:i + 2] == b"\xa3\x95"]
    p = heads[len(heads) // 2]
    bad = bytearray(df_log)
    bad[p + 1] ^= 0x10  # a record's sync byte
    (span, *fmt) = record_breaks(bad)
    assert span[0] < p < span[1] and span[1] - span[0] < 300
    assert fmt and fmt[0][0] < 2000  # the FMT record that gave the record before it its length
    bad = bytearray(df_log)
    fmt_imu = df_log.find(b"IMU\x00")  # FMT: header, type, length, name: the length byte is 1 before the name
    bad[fmt_imu - 1] ^= 0x04
    blamed = record_breaks(bad)
    assert blamed and any(a <= fmt_imu - 1 < b for a, b in blamed)


def test_a_broken_ulog_message_size_is_blamed(ulog):
    whole = ulog[:record_breaks(ulog)[0][0]]  # the log up to its last whole message
    assert record_breaks(whole) == []
    bad = bytearray(whole)
    p = 16
    for _ in range(200):  # walk to the 200th message
        p += 3 + (bad[p] | bad[p + 1] << 8)
    bad[p + 1] ^= 0x40  # its size
    (span,) = record_breaks(bad)
    assert span[0] <= p < span[1]
