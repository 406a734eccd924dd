"""A stabilising controller in the loop: the gap finding that the inputs are commands to a stabilised aircraft.

When a flybarless unit or an autopilot's rate loop sits between the logged inputs and the rotor, part of
the gap between the hover model and the aircraft is not an unmodelled effect but the wrong structure:
the controller makes the aircraft follow the stick. Two pieces of evidence, the first necessary in a
flight flown by a pilot, the second the measure of the finding:

* the inputs follow the hover model's output error a fraction of a second later
  (:func:`groundstation.sysid.heldout.feedback_evidence`): someone closes the loop;
* the command-response structure (:mod:`groundstation.sysid.structure`) removes a share of the
  held-out gap: it is fitted on k-1 contiguous folds and predicts the k-th from the measured states
  (5-s windows, eq. 19); the hover model predicts the same windows as it was given (not refitted per
  fold: it has seen the held-out block, an advantage that makes the finding conservative, and what
  keeps it cheap: k small least-squares fits of the low-order structure, no hover identification).

Its *share*, like every finding of the gap report (:mod:`groundstation.gap.shares`): the held-out
error energy above the noise floor, per fold and channel in multiples of the channel's own noise
(``sigma``, the diagnosis's smoothed-noise floor), removed by the command-response structure, over
that excess; the interval is a bootstrap over the folds (k blocks: a coarse interval). The finding
is made only when the loop is closed and the interval's lower end is above zero.

:func:`stabilising_controller` returns one finding in the gap report's effect shape (``effect``
``stabilising_controller``, ``estimate`` the per-axis bandwidth and delay of the stabilised aircraft,
``gap_before`` / ``gap_after`` / ``shrink_pct``, ``share_pct`` / ``share_interval_pct``, ``evidence``)
or None when the structure removes none of the gap. The diagnosis ranks it with the others by its share.
Pure numpy on prepared data; no IO.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import numpy as np

from groundstation.dsp.split import contiguous_kfold
from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.noise import noise_floor
from groundstation.parallel import Map, serial_map
from groundstation.sysid.heldout import feedback_evidence, predict
from groundstation.sysid.model import OUTPUTS
from groundstation.sysid.structure import CommandModel, identify_command, predict_command

EFFECT = "stabilising_controller"


def _fold_fit(pair: tuple[Any, Any], kind: str) -> Any:
    """The command-response structure of a fold's training part (module level: picklable)."""
    try:
        return identify_command(pair[0], kind)
    except (ValueError, ArithmeticError):
        return None


def _mean_square(prepared: Any) -> tuple[np.ndarray, np.ndarray]:
    """(8,) mean square and sample count of each measured output channel over ``prepared``'s segments."""
    y = np.concatenate([np.asarray(s.outputs, float) for s in prepared.segments])
    m = np.isfinite(y)
    n = m.sum(axis=0)
    ss = (np.where(m, y, 0.0) ** 2).sum(axis=0)
    return np.where(n > 0, ss / np.maximum(n, 1), np.nan), n


def _sigma(prepared: Any) -> np.ndarray:
    """The smoothed-noise floor per output when the caller has none (stand-alone use)."""
    raw = [np.asarray(getattr(s, "outputs_raw", s.outputs), float) for s in prepared.segments]
    sm = [np.asarray(s.outputs, float) for s in prepared.segments]
    return np.asarray(noise_floor(raw, sm)["sigma_smoothed"], float)


def stabilising_controller(prepared: Any, model: Any, *, sigma: np.ndarray | None = None, k: int = DiagnoseConfig.folds,
                           kind: str = "rate_command", pmap: Map = serial_map,
                           n_boot: int = DiagnoseConfig.share_n_boot,
                           seed: int = 0, config: DiagnoseConfig | None = None,
                           prior: Any = None) -> dict[str, Any] | None:
    """The finding (see the module docstring), or None when the command-response structure removes none
    of the gap. ``config``: the diagnosis's settings of the prediction windows, the runaway cap and the
    closed-loop evidence (``controller_*``; None: the defaults). ``prior`` is accepted for compatibility
    and not used (no hover refit)."""
    cfg = config or DiagnoseConfig()

    folds = [(tr, va) for tr, va in contiguous_kfold(prepared, k) if tr.segments and va.segments]
    fits = pmap(partial(_fold_fit, kind=kind), folds)
    sig = _sigma(prepared) if sigma is None else np.asarray(sigma, float)
    rows = []  # per fold: (excess (8,), removal (8,), ratio_h, ratio_c) in noise units x samples
    for (_, va), cm in zip(folds, fits, strict=True):
        if cm is None:
            continue
        try:
            ph = predict(model, va, window_s=cfg.controller_window_s)
            pc = predict_command(cm, va, window_s=cfg.controller_window_s)
        except ValueError:  # a block shorter than one window
            continue
        ms, n = _mean_square(va)
        ex, rm = np.zeros(8), np.zeros(8)
        for c, ch in enumerate(OUTPUTS):
            if ch not in ph.ratio or ch not in pc.ratio or not np.isfinite(ms[c]) or not sig[c] > 0:
                continue
            snr2 = ms[c] / sig[c] ** 2  # signal over noise variance: error ratio^2 x snr2 = error in noise units
            # a runaway block counts as [diagnose] controller_runaway_cap times its signal
            rh, rc = min(ph.ratio[ch], cfg.controller_runaway_cap), min(pc.ratio[ch], cfg.controller_runaway_cap)
            ex[c] = (rh ** 2 * snr2 - 1.0) * n[c]
            rm[c] = (rh ** 2 - rc ** 2) * snr2 * n[c]
        rows.append((ex, rm, ph, pc))
    if len(rows) < 2:
        return None
    EX = np.array([r[0] for r in rows])
    RM = np.array([r[1] for r in rows])
    cols = EX.sum(axis=0) > 0  # channels whose held-out error is above their noise
    if not cols.any():
        return None
    num, den = RM[:, cols].sum(axis=1), EX[:, cols].sum(axis=1)
    share = 100.0 * float(num.sum() / den.sum())
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(rows), (n_boot, len(rows)))
    boot = 100.0 * num[idx].sum(axis=1) / np.maximum(den[idx].sum(axis=1), 1e-300)
    lo, hi = (float(v) for v in np.percentile(boot, [5, 95]))
    cap = cfg.controller_runaway_cap
    before = float(np.mean([np.mean([1.0 - max(1.0 - min(v, cap), -1.0) for v in r[2].ratio.values()]) for r in rows]))
    after = float(np.mean([np.mean([1.0 - max(1.0 - min(v, cap), -1.0) for v in r[3].ratio.values()]) for r in rows]))
    if not share > 0:
        return None
    loop = feedback_evidence(model, prepared, window_s=cfg.controller_window_s,
                             max_lag_s=cfg.controller_feedback_max_lag_s, z=cfg.controller_feedback_z)

    own = getattr(model, "command", None)
    cm = CommandModel.from_json(own) if own and own.get("kind") == kind else identify_command(prepared, kind)
    estimate = {a: {"input": f.on_input, "bandwidth_rad_s": f.summary()["bandwidth_rad_s"],
                    "delay_s": f.params["tau"]} for a, f in cm.axes.items()}
    mh = float(np.mean([r[2].mean_match for r in rows]))
    mc = float(np.mean([r[3].mean_match for r in rows]))
    ev = (f"a {kind.replace('_', '-')} structure predicts held-out data better than the hover model "
          f"(held-out mean match {mc:.1f} % against {mh:.1f} % over {len(rows)} contiguous folds; it removes "
          f"{share:.0f} % of the held-out gap above noise, interval {lo:.0f} to {hi:.0f} % over the folds)")
    ev += "; " + ("; ".join(loop) if loop else "the inputs do not follow the model's output error beyond chance")
    shrink = 100.0 * (before - after) / before if before > 0 else 0.0
    per_channel = {OUTPUTS[c]: round(100.0 * float(RM[:, c].sum() / EX[:, c].sum()), 1)
                   for c in range(8) if cols[c]}
    return {"effect": EFFECT, "input": None, "output": None, "estimate": estimate, "gap_before": before,
            "gap_after": after, "shrink_pct": shrink, "score": share, "evidence": ev,
            "share_pct": round(share, 1), "share_interval_pct": [round(lo, 1), round(hi, 1)],
            "share_per_channel_pct": per_channel, "folds": len(rows),
            "loop_closed": bool(loop), "named": bool(loop) and lo > 0, "describe": cm.describe()}


def may_be_commands(model: Any) -> bool:
    """Whether the model's inputs may be commands to a stabilised aircraft: its identification says
    the inputs are commands or unknown (it carries the command-response structure or the held-out
    choice between the two). Servo outputs (blade inputs) put any controller upstream of the logged
    inputs, where the hover model is the right structure: the finding is not looked for."""
    if model is None:
        return False
    fit = getattr(model, "fit", None)
    return getattr(model, "command", None) is not None or (
        fit is not None and (fit.has("structure_choice") or fit.has("command_response")))
