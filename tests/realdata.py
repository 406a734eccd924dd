"""Where the real flight logs are: ``$GS_FLIGHT_DATA`` if set, else ``../shared/data`` beside the
checkout (the project's layout), else ``/work/shared/data``. A missing log fails the test that
needs it with the paths tried: real-log tests are never skipped."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

_REPO = Path(__file__).resolve().parent.parent


def data_dirs() -> list[Path]:
    env = os.environ.get("GS_FLIGHT_DATA")
    dirs = [Path(env)] if env else []
    return dirs + [_REPO.parent / "shared" / "data", Path("/work/shared/data")]


def real_log(relpath: str) -> Path:
    """Path of a real log under the data directory (``trex550/flight1.tlog``)."""
    for d in data_dirs():
        p = d / relpath
        if p.is_file():
            return p
    pytest.fail(f"real flight log {relpath} not found in {', '.join(map(str, data_dirs()))} "
                f"(set GS_FLIGHT_DATA to the folder holding trex550/)")
