"""Held-out prediction of a hover model: how well it predicts data it was not fitted to.

``predict(model, prepared, window_s=5.0)`` scores a model the way the paper's eq. 19 does, on
windows of ``window_s`` seconds cut from held-out segments:

* every window starts from the MEASURED states at its first sample (u v theta phi q p; w r), as a
  user predicting the aircraft from where it is would; the states no sensor measures (the
  flapping states a_s b_s, the yaw-gyro state r_fb, and a velocity channel missing in that window)
  are estimated by linear least squares over the window (the outputs are linear in the initial
  state), the same estimate the identification uses;
* the inputs are taken relative to the MODEL's input trim (``input_trim_pwm``, which carries the
  trim the identification solved), not the held-out data's median: a model that needs its trim is
  scored with it;
* per channel ``match = (1 - ||yhat - y|| / ||y||) * 100`` over all held-out windows, and the mean
  over the channels measured there.

:func:`unstable_modes` lists the eigenvalues of the two subsystems with a positive real part and
their time constants; :func:`runaway_channels` names the channels whose prediction error exceeds
``runaway_factor`` times the signal (a model that diverges there, not one that predicts poorly).

Pure numpy; splitting the data is :mod:`groundstation.dsp.split`'s.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from groundstation.dsp.split import contiguous_kfold
from groundstation.parallel import Map, serial_map
from groundstation.sysid.cost import make_windows
from groundstation.sysid.model import INPUTS, OUTPUTS, HoverModel, build_matrices
from groundstation.sysid.prediction import Prediction
from groundstation.sysid.refine import residual_tau
from groundstation.sysid.settings import IdentifyConfig
from groundstation.sysid.simulate import WindowSimulator
from groundstation.sysid.structure import CommandModel, predict_command

#: channels of each subsystem (which outputs a subsystem's instability spoils)
SUBSYSTEM_CHANNELS: dict[str, tuple[str, ...]] = {
    "horizontal": ("u", "v", "p", "q", "theta", "phi"), "vertical": ("w", "r"),
}


@dataclass(frozen=True)
class UnstableMode:
    """An eigenvalue of a subsystem with a positive real part."""

    subsystem: str
    real_1_s: float
    imag_rad_s: float
    time_constant_s: float  # 1 / real part: the error grows e-fold in this time

    def describe(self) -> str:
        osc = f" oscillating at {abs(self.imag_rad_s) / (2 * np.pi):.2f} Hz" if abs(self.imag_rad_s) > 1e-9 else ""
        return (f"{self.subsystem} subsystem unstable: eigenvalue {self.real_1_s:+.3g}{self.imag_rad_s:+.3g}j /s, "
                f"time constant {self.time_constant_s:.2f} s{osc}")


def unstable_modes(theta: np.ndarray, min_real_1_s: float = 1e-6) -> list[UnstableMode]:
    """Eigenvalues with a real part above ``min_real_1_s`` of both subsystems' A matrices."""
    Ah, _, Av, _ = build_matrices(np.asarray(theta, dtype=float))
    out = []
    for name, A in (("horizontal", Ah), ("vertical", Av)):
        for ev in np.linalg.eigvals(A):
            if ev.real > min_real_1_s and ev.imag >= 0:
                out.append(UnstableMode(name, float(ev.real), float(ev.imag), float(1.0 / ev.real)))
    return out


def input_offset(model: HoverModel, prepared: Any) -> np.ndarray:
    """(4,) normalised offset to add to ``prepared``'s inputs to express them against the model's trim."""
    ppu = float(prepared.pwm_per_unit)
    return np.array([(float(prepared.input_trim_pwm.get(k, 0.0)) - float(model.input_trim_pwm.get(k, prepared.input_trim_pwm.get(k, 0.0)))) / ppu
                     for k in INPUTS])


def predict(model: HoverModel, prepared: Any, *, window_s: float = IdentifyConfig.heldout_window_s,
            use_model_trim: bool = True, window_offsets: bool | None = None) -> Prediction:
    """Score ``model`` on held-out ``prepared`` data (see the module docstring). A model whose
    ``structure`` is the command-response one predicts with it (:mod:`groundstation.sysid.structure`).
    ``window_offsets``: estimate input offsets on each held-out window (None: as the model was fitted;
    False: nothing but the unmeasured initial states comes from a window's own outputs)."""
    if getattr(model, "structure", "hover") == "command_response" and model.command is not None:
        return predict_command(CommandModel.from_json(model.command), prepared, window_s=window_s,
                               window_offsets=window_offsets)
    w = predicted_windows(model, prepared, window_s=window_s, use_model_trim=use_model_trim,
                          window_offsets=window_offsets)
    match: dict[str, float] = {}
    ratio: dict[str, float] = {}
    for j, ch in enumerate(OUTPUTS):
        m = w.mask[:, :, j]  # measured samples only: holes of the link do not count
        if not m.any():
            continue
        y = w.outputs[:, :, j][m]
        den = float(np.linalg.norm(y))
        if den <= 0:
            continue
        ratio[ch] = float(np.linalg.norm(w.predicted[:, :, j][m] - y)) / den
        match[ch] = (1.0 - ratio[ch]) * 100.0
    mean = float(np.mean(list(match.values()))) if match else float("nan")
    return Prediction(match=match, mean_match=mean, windows=w.count, window_s=float(window_s),
                      duration_s=float(w.count * w.length * w.dt_s), ratio=ratio)


@dataclass(frozen=True, eq=False)
class PredictedWindows:
    """A hover model's held-out prediction before scoring: measured ``outputs`` and ``predicted`` ones
    (W, L, 8) in :data:`OUTPUTS` order, ``mask`` (W, L, 8) the samples measured (scored), ``inputs``
    (W, L, 4) as the model saw them, sample time ``dt_s``."""

    outputs: np.ndarray
    predicted: np.ndarray
    mask: np.ndarray
    inputs: np.ndarray
    dt_s: float

    @property
    def count(self) -> int:
        return int(self.outputs.shape[0])

    @property
    def length(self) -> int:
        return int(self.outputs.shape[1])


def predicted_windows(model: HoverModel, prepared: Any, *, window_s: float = IdentifyConfig.heldout_window_s,
                      use_model_trim: bool = True, window_offsets: bool | None = None) -> PredictedWindows:
    """The hover model's prediction of ``prepared`` on non-overlapping ``window_s`` windows started from
    the measured states (what :func:`predict` scores; same arguments)."""
    win = make_windows(prepared.segments, prepared.dt_s, window_s)
    u = win.inputs + (input_offset(model, prepared)[None, None, :] if use_model_trim else 0.0)
    with threadpool_limits(1):
        sim = WindowSimulator(u, win.outputs, win.dt_s, win.available, estimate_all_initial=False,
                              measured=win.measured,
                              window_offsets=model.window_input_offsets if window_offsets is None else window_offsets)
        yhat = sim.simulate(model.theta[None])[0]
    return PredictedWindows(sim.outputs, yhat, sim.smask, u, float(win.dt_s))


@dataclass(frozen=True)
class CrossValidation:
    """Held-out prediction over k contiguous folds: per-fold ``Prediction``, channel means, and verdicts."""

    folds: tuple[Prediction, ...]
    channel_mean: dict[str, float]
    mean_match: float
    predicted: tuple[str, ...]      # channels with a positive held-out match in every fold and no runaway
    not_predicted: tuple[str, ...]
    runaway: dict[str, tuple[str, ...]]   # fold label -> channels that ran away there
    unusable_subsystems: tuple[str, ...]  # subsystems with a channel that ran away in some fold

    def to_json(self) -> dict[str, Any]:
        return {"k": len(self.folds), "window_s": self.folds[0].window_s if self.folds else None,
                "mean_match": self.mean_match, "channel_mean": self.channel_mean,
                "folds": [p.match for p in self.folds], "predicted": list(self.predicted),
                "not_predicted": list(self.not_predicted), "runaway": {k: list(v) for k, v in self.runaway.items()},
                "unusable_subsystems": list(self.unusable_subsystems)}


def _fit_or_none(fit_fold: Any, train: Any) -> Any:
    """``fit_fold(train)``, None for a block too short to fit (module-level for worker processes)."""
    try:
        return fit_fold(train)
    except ValueError:  # a block shorter than one window
        return None


def crossvalidate(prepared: Any, fit_fold: Any, *, k: int = IdentifyConfig.select_folds,
                  window_s: float = IdentifyConfig.heldout_window_s,
                  runaway_factor: float = IdentifyConfig.runaway_factor, pmap: Map = serial_map) -> CrossValidation:
    """Fit on k-1 contiguous blocks of the in-air time with ``fit_fold(train) -> HoverModel``, predict
    the left-out block (:func:`predict`), for each of the k blocks. ``pmap`` fits the folds (in worker
    processes with :func:`groundstation.parallel.worker_map`; ``fit_fold`` must then be picklable)."""
    folds = [(f, train, val) for f, (train, val) in enumerate(contiguous_kfold(prepared, k))
             if train.segments and val.segments]
    models = pmap(partial(_fit_or_none, fit_fold), [train for _, train, _ in folds])
    preds, runaway = [], {}
    for (f, _, val), model in zip(folds, models, strict=True):
        if model is None:
            continue
        try:
            p = predict(model, val, window_s=window_s)
        except ValueError:  # a block shorter than one window
            continue
        preds.append(p)
        ra = runaway_channels(p, runaway_factor)
        if ra:
            runaway[f"fold {f + 1}"] = tuple(ra)
    chans = [c for c in OUTPUTS if any(c in p.match for p in preds)]
    mean = {c: float(np.mean([p.match[c] for p in preds if c in p.match])) for c in chans}
    ran = {c for v in runaway.values() for c in v}
    # predicted: better than predicting no motion in every fold that holds the channel, never running away
    predicted = tuple(c for c in chans if all(p.match[c] > 0 for p in preds if c in p.match) and c not in ran)
    unusable = tuple(s for s, cs in SUBSYSTEM_CHANNELS.items() if any(c in ran for c in cs))
    return CrossValidation(tuple(preds), mean, float(np.mean([p.mean_match for p in preds])) if preds else float("nan"),
                           predicted, tuple(c for c in chans if c not in predicted), runaway, unusable)


def runaway_channels(pred: Prediction, runaway_factor: float = IdentifyConfig.runaway_factor) -> list[str]:
    """Channels whose held-out error is more than ``runaway_factor`` times the signal itself."""
    return [c for c, r in pred.ratio.items() if r > runaway_factor]


def feedback_evidence(model: HoverModel, prepared: Any, *, window_s: float = IdentifyConfig.feedback_window_s,
                      max_lag_s: float = IdentifyConfig.feedback_max_lag_s,
                      z: float = IdentifyConfig.feedback_z) -> list[str]:
    """Signs that someone closes the loop: inputs that follow the model's output error.

    In open loop the inputs do not depend on what the model fails to explain; a pilot or a flight
    controller reacts to the aircraft's motion, so its inputs correlate with the LATER part of the
    output error (disturbances, unmodelled motion). For each moving input and each channel of its
    subsystem, the largest |correlation| of the output error with the input change 0.1 to ``max_lag_s``
    later is compared with ``z`` / sqrt(N_eff) (N_eff the samples over the error's autocorrelation
    time). One line per input that responds.
    """
    win = make_windows(prepared.segments, prepared.dt_s, window_s)
    u = win.inputs + input_offset(model, prepared)[None, None, :]
    with threadpool_limits(1):
        sim = WindowSimulator(u, win.outputs, win.dt_s, win.available, estimate_all_initial=False,
                              measured=win.measured, window_offsets=model.window_input_offsets)
        e = sim.errors(model.theta[None])[0]  # (W, L, 8), zero in holes of the link
    du = np.diff(win.inputs, axis=1)
    out = []
    chans = {0: ("p", "q", "theta", "phi"), 1: ("p", "q", "theta", "phi"), 2: ("w", "r"), 3: ("w", "r")}
    lags = np.arange(max(1, int(0.1 / win.dt_s)), max(2, int(max_lag_s / win.dt_s)))
    thresholds: dict[str, float] = {}   # per channel: its chance level depends on the error only
    for j, name in enumerate(INPUTS):
        if np.std(du[..., j]) <= 0:
            continue
        cands = []  # (|r| / chance level, r, channel, lag s, chance level)
        for ch in chans[j]:
            k = OUTPUTS.index(ch)
            m = sim.mask[:, k]
            if m.sum() < 2:
                continue
            ee = e[m, :-1, k]
            if ch not in thresholds:
                tau = float(residual_tau(ee[..., None] / max(float(np.std(ee)), 1e-12), np.ones(1, dtype=bool))[0])
                thresholds[ch] = z / np.sqrt(ee.size / max(tau, 1.0))
            thr = thresholds[ch]
            for lag, r in zip(lags, lagged_correlations(ee, du[m, :, j], lags), strict=True):
                if np.isfinite(r):
                    cands.append((abs(r) / thr, float(r), ch, lag * win.dt_s, thr))
        if cands:
            ratio, r, ch, lag_s, thr = max(cands)
            if ratio > 1.0:
                out.append(f"input {name} follows the model's {ch} error {lag_s:.2f} s later (correlation {r:+.2f}, "
                           f"chance level {thr:.2f}): the loop is closed (pilot or flight controller)")
    return out


def lagged_correlations(a: np.ndarray, b: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """(len(lags),) Pearson correlation of ``a[:, :n - lag]`` with ``b[:, lag:]`` over all windows and
    samples (``a``, ``b`` (W, n)), for each lag (0 < lag < n); NaN where either part is constant (as
    ``np.corrcoef`` of the flattened parts, from running sums: one pass per lag instead of four)."""
    W, n = a.shape
    sa, sa2 = np.cumsum(a.sum(axis=0)), np.cumsum((a * a).sum(axis=0))          # over the first m samples
    rb = b[:, ::-1]
    sb, sb2 = np.cumsum(rb.sum(axis=0)), np.cumsum((rb * rb).sum(axis=0))       # over the last m samples
    out = np.full(len(lags), np.nan)
    for i, lag in enumerate(lags):
        m = n - int(lag)
        N = W * m
        va = sa2[m - 1] - sa[m - 1] ** 2 / N
        vb = sb2[m - 1] - sb[m - 1] ** 2 / N
        if va > 1e-12 * sa2[m - 1] and vb > 1e-12 * sb2[m - 1]:   # a part constant up to rounding: no correlation
            sab = float(np.einsum("ij,ij->", a[:, :m], b[:, lag:]))
            out[i] = (sab - sa[m - 1] * sb[m - 1] / N) / np.sqrt(va * vb)
    return out
