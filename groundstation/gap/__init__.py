"""Sim-to-real gap diagnosis: locate, attribute and shrink the model's departures from flight data (pure).

Public API: :func:`diagnose` (the ``heli-gap-report/1`` dict), :func:`run_diagnosis` (report plus
arrays for plots), :class:`DiagnoseConfig`. Modules: ``linsim`` (windowed eq.-8 simulation with
forcing/nuisance), ``evaluate`` (k-fold held-out scoring), ``hypotheses`` (one augmented model per
catalogue effect), ``fingerprints`` (spectral lines, Euler kinematics), ``noise`` (noise floors),
``locate``, ``attribute``, ``report``, ``plots`` (matplotlib; used by the command only).
"""

import importlib
from typing import Any

__all__ = ["CATALOGUE", "DiagnoseConfig", "Diagnosis", "diagnose", "run_diagnosis"]


def __getattr__(name: str) -> Any:
    """The public API, imported on first use: ``groundstation.gap.config`` (read by every command's
    configuration) then does not import the diagnosis and scipy.stats (~1 s of CPU at every start)."""
    if name in __all__:
        mod = importlib.import_module("groundstation.gap.diagnose")
        # as the eager import did: the package's names are the API's (``diagnose`` the function, not the module)
        globals().update({n: getattr(mod, n) for n in __all__})
        return globals()[name]
    raise AttributeError(f"module 'groundstation.gap' has no attribute {name!r}")
