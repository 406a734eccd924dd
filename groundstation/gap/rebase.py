"""A second search for the base model when the first named effect is a velocity latency.

The diagnosis identifies its base model on the flight it diagnoses. Velocities that arrive late
relative to the attitude and the inputs are not something the hover model's structure can
represent, and the identification's search run on them can settle in another basin of the cost
than the one the same search finds once the latency is taken off: measured on a bench flight with
a 0.17 s latency and drag, a base with 2.4 times the diagnosis's own cost, against which the latency
explained 12.7 % of the held-out cost instead of 39 % and the drag nothing.

So when the first named effect is a velocity latency and the diagnosis identified the base itself,
the base is searched for once more on the flight with that latency taken off the velocities (the
same search and seed), refined on the flight as flown, and kept when it lowers the refinement's cost
by more than the practical floor ``min_score_pct``; the diagnosis then runs again against it. A
model the user gave is never replaced. Input effects get no such search: on the servo-lag and
rotor-droop flights measured, searches from other seeds and from the effect-free twin flight's model
all end in the same optimum (the effect is absorbed by the optimum itself, not by a search that
went astray). Pure; no IO.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from groundstation.gap import hypotheses
from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.evaluate import Evaluator, JacobianMemo
from groundstation.parallel import Map, serial_map
from groundstation.sysid.identify import IdentifyConfig, identify


def without_latency(prepared: Any, latency_s: float) -> Any:
    """``prepared`` with the velocities (outputs u v w, smoothed and raw) moved ``latency_s`` earlier:
    the data in the attitude's time, as :func:`groundstation.gap.candidates.applied` puts the latency in."""
    d = latency_s / float(prepared.dt_s)
    segs = []
    for s in prepared.segments:
        y, yr = s.outputs.copy(), s.outputs_raw.copy()
        y[:, :3] = hypotheses.shift(y[:, :3], -d)
        yr[:, :3] = hypotheses.shift(yr[:, :3], -d)
        segs.append(dataclasses.replace(s, outputs=y, outputs_raw=yr))
    return dataclasses.replace(prepared, segments=segs)


def searched_again(ev: Evaluator, segs: list, latency_s: float, prepared: Any, cfg: DiagnoseConfig, seed: int,
                   pmap: Map = serial_map) -> tuple[Evaluator, float, float]:
    """The base searched for on the flight without the latency, then refined on the windows ``segs`` of
    the flight as flown: (its evaluator, its cost, the cost of the current base ``ev``), both on all
    windows as :meth:`Evaluator.refine` counts them."""
    model = identify(without_latency(prepared, latency_s), seed=seed,
                     config=IdentifyConfig(search_restarts=cfg.identify_restarts, select_candidates=""), pmap=pmap)
    ev2 = Evaluator(segs, ev.dt_s, model.theta, ev.available, window_s=cfg.window_s, folds=cfg.folds,
                    ridge=cfg.ridge, start_s=cfg.window_start_s, memo=JacobianMemo())
    cost2 = ev2.refine(cfg.refine_iterations, cfg.refine_ridge)
    return ev2, cost2, float((ev.r0 ** 2).sum())


def lower(cost_new: float, cost_old: float, cfg: DiagnoseConfig) -> bool:
    """The new base is kept only when it lowers the cost by more than the practical floor."""
    return bool(cost_new < cost_old * (1.0 - cfg.min_score_pct / 100.0))
