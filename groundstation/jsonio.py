"""JSON out of analysis results: finite numbers only, written atomically.

Results carry NaN and infinities where a figure could not be computed (a channel never measured, a
fold with no window, a standard error that does not exist). JSON has no such numbers (and
``json.dumps(allow_nan=False)`` raises on them), so every writer of a result file goes through
:func:`finite`, which turns non-finite floats into ``null`` (the documented "not computed") and numpy
scalars and arrays into plain Python. The caller decides what a ``null`` means; this module only
makes sure no internal error reaches the user when writing.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np


def finite(obj: Any) -> Any:
    """A copy of ``obj`` (dicts, lists, tuples, numpy scalars/arrays, floats) with NaN/inf as None."""
    if isinstance(obj, dict):
        return {str(k) if not isinstance(k, str) else k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    return obj


def dumps(doc: Any, **kw: Any) -> str:
    """``json.dumps`` of :func:`finite` (``allow_nan=False``: a NaN that slipped through is a bug)."""
    return json.dumps(finite(doc), allow_nan=False, **kw)


def write_atomic(path: Path, doc: Any, *, indent: int | None = 1) -> None:
    """Write ``doc`` as JSON to ``path`` through a temporary file and a rename (parents created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(dumps(doc, indent=indent))
    tmp.replace(path)
