"""Where the stabilised aircraft's command-response structure meets the hover model: fitted per held-out
fold, attached to an identified model, and compared with the hover model by held-out prediction.

The structure itself (:mod:`groundstation.sysid.structure`) knows nothing of folds or selection; this
module sits above it, :mod:`groundstation.sysid.heldout` and :mod:`groundstation.sysid.select`.
Pure numpy/scipy; no IO.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any

from groundstation.parallel import serial_map
from groundstation.sysid.heldout import crossvalidate
from groundstation.sysid.select import _crossvalidate, choose, fold_scores
from groundstation.sysid.structure import COMMAND_KINDS, CommandModel, identify_command


def _as_hover_model(model: Any, cm: CommandModel) -> Any:
    """``model`` (a :class:`groundstation.sysid.model.HoverModel`) carrying ``cm`` as the structure that predicts."""
    return dataclasses.replace(model, command=cm.to_json(), structure="command_response")


def command_settings(cfg: Any) -> dict[str, Any]:
    """The keyword arguments of :func:`identify_command` from the ``[identify]`` settings ``cfg``."""
    return {"window_s": float(cfg.command_window_s), "step_s": float(cfg.command_step_s),
            "maxiter": int(cfg.command_maxiter)}


def fit_command_fold(train: Any, *, model: Any, kind: str, settings: dict[str, Any] | None = None) -> Any:
    """A fold's command-response model (module level: picklable for worker processes); ``settings``:
    :func:`command_settings`."""
    return _as_hover_model(model, identify_command(train, kind, **(settings or {})))


def fold_fitter(model: Any, cfg: Any = None) -> Any:
    """``fit_fold(train) -> model`` of a held-out check of ``model``'s command-response structure (same kind),
    fitted with the ``[identify]`` settings ``cfg`` (None: the defaults)."""
    return partial(fit_command_fold, model=model, kind=str((model.command or {}).get("kind", "rate_command")),
                   settings=command_settings(cfg) if cfg is not None else None)


def attach_command_structure(prepared: Any, model: Any, cfg: Any, *, prior: Any = None, pmap: Any = None,
                             refit: Any) -> Any:
    """``model`` with the command-response structure of ``cfg.input_kind`` fitted to ``prepared``.

    ``rate_command`` / ``attitude_command``: that structure predicts (``structure = "command_response"``).
    ``unknown``: the rate-command structure and the hover model are cross-validated over the same
    ``cfg.select_folds`` contiguous folds and compared by the selection's rule
    (:func:`groundstation.sysid.select.choose`: a prediction that runs away never wins over one that
    does not; otherwise a gain beyond one standard error or on every fold); ``fit["structure_choice"]``
    says which and why. ``refit``: the hover model's fold refit (:func:`groundstation.sysid.identify.refit`,
    given by the identification)."""
    pmap = pmap or serial_map
    kind = cfg.input_kind if cfg.input_kind in COMMAND_KINDS else "rate_command"
    cm = identify_command(prepared, kind, **command_settings(cfg))
    out = _as_hover_model(model, cm)
    out.fit = model.fit.set(command_response=cm.describe())
    if cfg.input_kind in COMMAND_KINDS or int(cfg.select_folds) < 2:
        out.fit = out.fit.set(structure_choice={"chosen": "command_response", "reason": f"inputs.kind = {cfg.input_kind}"})
        if out.fit.heldout is not None:   # the hover model's, from the selection: not this structure's
            out.fit = out.fit.without("heldout").set(heldout_hover=out.fit.heldout)
        return out
    try:
        cv_c = crossvalidate(prepared, partial(fit_command_fold, model=model, kind=kind, settings=command_settings(cfg)),
                             k=int(cfg.select_folds),
                             window_s=float(cfg.heldout_window_s), runaway_factor=float(cfg.runaway_factor), pmap=pmap)
        cv_h = _crossvalidate(prepared, model, cfg, prior, pmap, refit)
    except ValueError as exc:
        model.fit = model.fit.set(structure_choice={"chosen": "hover", "reason": f"not compared: {exc}"})
        return model
    floor = cfg.select_match_floor_pct
    rows = [{"name": "hover (blade inputs)", "fold_score": fold_scores(cv_h, floor).tolist(), "mean_match": cv_h.mean_match,
             "runaway": {k: list(v) for k, v in cv_h.runaway.items()}},
            {"name": f"command response ({kind})", "fold_score": fold_scores(cv_c, floor).tolist(), "mean_match": cv_c.mean_match,
             "runaway": {k: list(v) for k, v in cv_c.runaway.items()}}]
    win = choose(rows, cfg.select_gain_z)
    r = rows[1]
    why = r.get("reason") or (f"held-out gain {r['gain']:+.1f} +- {r['gain_se']:.1f} points per fold, better on "
                              f"{r['gain_folds']} of {len(r['fold_score'])} folds")
    choice = {"chosen": "command_response" if win else "hover", "candidates": rows,
              "reason": ("the command-response structure predicts held-out data better: " if win else
                         "the hover model is kept: the command-response structure does not predict better by the "
                         "selection's rule: ") + why}
    if win:
        out.fit = out.fit.set(structure_choice=choice, heldout=cv_c.to_json())
        return out
    model.fit = model.fit.set(structure_choice=choice, command_response=cm.describe())
    return model
