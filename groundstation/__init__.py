"""Helicopter flight-test ground station: live service, DSP, CABC identification, gap diagnosis, sinks.

The Python API (docs/python-api.md)::

    import groundstation as gs

    log = gs.load_log("flight1.tlog")
    result = gs.analyse([log], aircraft="trex550.toml")      # every step: model, held-out, gap, ...
    model = gs.identify("flight1.tlog", aircraft="trex550.toml")
    gap = gs.diagnose("flight1.tlog", model=model)

The names below are imported on first use, so ``import groundstation`` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

#: public name -> module that defines it
_API = {
    "load_log": "firmware_interface.readers",
    "analyse": "groundstation.analysis",
    "identify": "groundstation.analysis",
    "diagnose": "groundstation.analysis",
    "AnalysisResult": "groundstation.analysis",
    "GapReport": "groundstation.analysis",
    "Progress": "groundstation.analysis",
    "STEPS": "groundstation.analysis",
    "HoverModel": "groundstation.sysid.model",
    "ModelFit": "groundstation.sysid.fit_section",
    "HeldOut": "groundstation.sysid.fit_section",
    "Validation": "groundstation.sysid.validate",
    "Aircraft": "groundstation.aircraft",
    "load_aircraft": "groundstation.aircraft",
    "ServiceConfig": "groundstation.config",
    "load_config": "groundstation.config",
}

__all__ = ["STEPS", "Aircraft", "AnalysisResult", "GapReport", "HeldOut", "HoverModel", "ModelFit", "Progress",
           "ServiceConfig", "Validation", "analyse", "diagnose", "identify", "load_aircraft", "load_config", "load_log"]
assert sorted(__all__) == sorted(_API)

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from firmware_interface.readers import load_log
    from groundstation.aircraft import Aircraft, load_aircraft
    from groundstation.analysis import STEPS, AnalysisResult, GapReport, Progress, analyse, diagnose, identify
    from groundstation.config import ServiceConfig, load_config
    from groundstation.sysid.fit_section import HeldOut, ModelFit
    from groundstation.sysid.model import HoverModel
    from groundstation.sysid.validate import Validation


def __getattr__(name: str) -> Any:
    mod = _API.get(name)
    if mod is None:
        raise AttributeError(f"module 'groundstation' has no attribute {name!r}")
    value = getattr(importlib.import_module(mod), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
