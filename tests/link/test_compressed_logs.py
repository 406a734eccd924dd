"""Compressed logs as archives keep them: an .xz or .gz log reads as the log inside it (by content, as
every reader), is named after the compressed file, and a damaged archive is one line naming it."""

from __future__ import annotations

import gzip
import lzma
from pathlib import Path

import numpy as np
import pytest

from firmware_interface.errors import LogError
from firmware_interface.readers import load_log
from tests.realdata import real_log

REPO_DATA = Path(__file__).resolve().parents[1] / "data"


def test_xz_log_reads_as_the_log_inside():
    name = "px4/pyulog_sample.ulg"  # the smallest real log: the unpacking is the same for every format
    packed = REPO_DATA / (name + ".xz")
    a, b = load_log(real_log(name)), load_log(packed)
    assert b.source == str(packed)
    assert b.message_counts == a.message_counts
    assert [f.start_fc_s for f in b.flights] == [f.start_fc_s for f in a.flights]
    for k, s in a.series.items():
        assert np.array_equal(s.t_fc_s, b.series[k].t_fc_s)


def test_gzip_log_reads_too(tmp_path):
    plain = real_log("px4/pyulog_sample.ulg")
    gz = tmp_path / "sample.ulg.gz"
    gz.write_bytes(gzip.compress(Path(plain).read_bytes()))
    assert load_log(gz).message_counts == load_log(plain).message_counts


def test_truncated_archive_is_one_line_naming_it(tmp_path):
    data = lzma.compress(Path(real_log("px4/pyulog_sample.ulg")).read_bytes(), preset=0)
    bad = tmp_path / "cut.ulg.xz"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(LogError) as ei:
        load_log(bad)
    msg = str(ei.value)
    assert msg.startswith(str(bad)) and "decompress" in msg and "\n" not in msg
