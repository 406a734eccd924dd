"""The real flight logs the tests use, shipped xz-compressed in ``tests/data/`` (see its README for
each file's source and licence). ``real_log("trex550/flight1.tlog")`` decompresses the file once
into a cache folder under the system temp directory and returns its path; nothing outside the
checkout is read. A missing file fails the test that needs it: real-log tests are never skipped."""

from __future__ import annotations

import hashlib
import lzma
import os
import tempfile
from pathlib import Path

import pytest

DATA_DIR = Path(__file__).resolve().parent / "data"


def _cache_dir() -> Path:
    d = Path(tempfile.gettempdir()) / f"heli-gs-testdata-{os.getuid()}"
    d.mkdir(parents=True, exist_ok=True)
    return d


def real_log(relpath: str) -> Path:
    """Path of a decompressed real log (``trex550/flight1.tlog``, ``px4/pyulog_sample.ulg`` …)."""
    packed = DATA_DIR / (relpath + ".xz")
    if not packed.is_file():
        pytest.fail(f"real flight log {packed} is missing from the checkout")
    blob = packed.read_bytes()
    digest = hashlib.sha256(blob).hexdigest()[:16]
    out = _cache_dir() / digest / Path(relpath).name
    if not out.is_file():
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(out.suffix + f".{os.getpid()}.part")
        tmp.write_bytes(lzma.decompress(blob))
        os.replace(tmp, out)  # atomic: parallel test processes never see a half-written log
    return out
