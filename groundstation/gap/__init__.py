"""Sim-to-real gap diagnosis: locate, attribute and shrink the model's departures from flight data (pure).

Public API: :func:`diagnose` (the ``heli-gap-report/1`` dict), :func:`run_diagnosis` (report plus
arrays for plots), :class:`DiagnoseConfig`. Modules: ``linsim`` (windowed eq.-8 simulation with
forcing/nuisance), ``evaluate`` (k-fold held-out scoring), ``hypotheses`` (one augmented model per
catalogue effect), ``fingerprints`` (spectral lines, Euler kinematics), ``noise`` (noise floors),
``locate``, ``attribute``, ``report``, ``plots`` (matplotlib; used by the command only).
"""

from groundstation.gap.diagnose import CATALOGUE, DiagnoseConfig, Diagnosis, diagnose, run_diagnosis

__all__ = ["CATALOGUE", "DiagnoseConfig", "Diagnosis", "diagnose", "run_diagnosis"]
