"""TOML configuration of preparation, identification and bounds for the identify/validate commands.

``parse_sysid_config(doc, name)`` turns an already-parsed TOML document into
``(PrepConfig, IdentifyConfig, bounds)``: tables ``[prepare]`` (PrepConfig fields), ``[identify]``
(IdentifyConfig fields) and ``[bounds]`` (``NAME = [low, high]``). Unknown tables/keys raise
ValueError naming the file and the key. Reading the file is the command's job.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from groundstation.dsp.prepare import PrepConfig
from groundstation.sysid.identify import IdentifyConfig
from groundstation.sysid.model import PARAM_NAMES


def _build(cls, table: dict[str, Any], where: str):
    names = {f.name for f in dataclasses.fields(cls)}
    for k in table:
        if k not in names:
            raise ValueError(f"{where}: unknown key {k!r} (allowed: {sorted(names)})")
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in table.items()}
    try:
        return cls(**kw)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from None


def parse_sysid_config(doc: dict[str, Any], name: str) -> tuple[PrepConfig, IdentifyConfig, dict[str, tuple[float, float]]]:
    for k in doc:
        if k not in ("prepare", "identify", "bounds"):
            raise ValueError(f"{name}: unknown table [{k}] (allowed: prepare, identify, bounds)")
    prep = _build(PrepConfig, doc.get("prepare", {}), f"{name} [prepare]")
    ident = _build(IdentifyConfig, doc.get("identify", {}), f"{name} [identify]")
    bounds: dict[str, tuple[float, float]] = {}
    for k, v in doc.get("bounds", {}).items():
        if k not in PARAM_NAMES:
            raise ValueError(f"{name} [bounds]: unknown parameter {k!r}")
        if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, int | float) for x in v)):
            raise ValueError(f"{name} [bounds]: {k} must be [low, high], got {v!r}")
        if v[0] >= v[1]:
            raise ValueError(f"{name} [bounds]: {k} has low >= high ({v[0]} >= {v[1]})")
        bounds[k] = (float(v[0]), float(v[1]))
    return prep, ident, bounds
