"""A stabilising controller in the loop: the gap finding that the inputs are commands to a stabilised aircraft.

When a flybarless unit or an autopilot's rate loop sits between the logged inputs and the rotor, part of
the gap between the hover model and the aircraft is not an unmodelled effect but the wrong structure:
the controller makes the aircraft follow the stick. Two pieces of evidence, the first necessary in a
flight flown by a pilot, the second the measure of the finding:

* the inputs follow the hover model's output error a fraction of a second later
  (:func:`groundstation.sysid.heldout.feedback_evidence`): someone closes the loop;
* the command-response structure (:mod:`groundstation.sysid.structure`) removes a share of the
  held-out gap: both structures are refitted on k-1 contiguous folds and predict the k-th from the
  measured states (5-s windows, eq. 19); the gap is ``1 - match / 100`` averaged over channels and
  folds, each channel's floored at -100 % as in the selection.

:func:`stabilising_controller` returns one finding in the gap report's effect shape (``effect``
``stabilising_controller``, ``estimate`` the per-axis bandwidth and delay of the stabilised aircraft,
``gap_before`` / ``gap_after`` / ``shrink_pct``, ``evidence``) or None when the structure does not
remove any of the gap. It is a candidate of its own, beside the catalogue of unmodelled effects: the
diagnosis ranks it with the others by its share. Pure numpy on prepared data; no IO.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import numpy as np

from groundstation.parallel import Map, serial_map

EFFECT = "stabilising_controller"


def _gap(cv: Any) -> float:
    """Mean over folds and channels of ``1 - match / 100``, each channel's match floored at -100 %."""
    return float(np.mean([np.mean([1.0 - max(v, -100.0) / 100.0 for v in p.match.values()]) for p in cv.folds]))


def stabilising_controller(prepared: Any, model: Any, *, config: Any = None, prior: Any = None, k: int = 5,
                           kind: str = "rate_command", pmap: Map = serial_map) -> dict[str, Any] | None:
    """The finding (see the module docstring), or None when the command-response structure removes none of the gap."""
    from groundstation.sysid.heldout import crossvalidate, feedback_evidence
    from groundstation.sysid.identify import IdentifyConfig, refit
    from groundstation.sysid.structure import identify_command
    from groundstation.sysid.structure_choice import fit_command_fold

    cfg = config or IdentifyConfig(window_s=5.0, estimate_all_initial=False)
    cv_h = crossvalidate(prepared, partial(refit, model=model, config=cfg, prior=prior), k=k, pmap=pmap)
    cv_c = crossvalidate(prepared, partial(fit_command_fold, model=model, kind=kind), k=k, pmap=pmap)
    before, after = _gap(cv_h), _gap(cv_c)
    if not after < before:
        return None
    cm = identify_command(prepared, kind)
    loop = feedback_evidence(model, prepared)
    estimate = {a: {"input": f.on_input, "bandwidth_rad_s": f.summary()["bandwidth_rad_s"],
                    "delay_s": f.params["tau"]} for a, f in cm.axes.items()}
    shrink = 100.0 * (before - after) / before if before > 0 else 0.0
    ev = (f"a {kind.replace('_', '-')} structure predicts held-out data better than the hover model "
          f"(held-out mean match {cv_c.mean_match:.1f} % against {cv_h.mean_match:.1f} % over {len(cv_c.folds)} folds)")
    ev += "; " + ("; ".join(loop) if loop else "the inputs do not follow the model's output error beyond chance")
    return {"effect": EFFECT, "input": None, "output": None, "estimate": estimate, "gap_before": before,
            "gap_after": after, "shrink_pct": shrink, "score": shrink, "evidence": ev,
            "loop_closed": bool(loop), "describe": cm.describe()}
