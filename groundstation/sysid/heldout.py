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

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from groundstation.sysid.cost import make_windows
from groundstation.sysid.model import INPUTS, OUTPUTS, HoverModel, build_matrices
from groundstation.sysid.simulate import WindowSimulator

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


@dataclass(frozen=True)
class Prediction:
    """Held-out scores: ``match`` per channel (%), ``mean_match`` over them, window count and length."""

    match: dict[str, float]
    mean_match: float
    windows: int
    window_s: float
    duration_s: float
    ratio: dict[str, float] = field(default_factory=dict)  # ||yhat - y|| / ||y|| per channel


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


def predict(model: HoverModel, prepared: Any, *, window_s: float = 5.0, use_model_trim: bool = True) -> Prediction:
    """Score ``model`` on held-out ``prepared`` data (see the module docstring)."""
    win = make_windows(prepared.segments, prepared.dt_s, window_s)
    u = win.inputs + (input_offset(model, prepared)[None, None, :] if use_model_trim else 0.0)
    with threadpool_limits(1):
        sim = WindowSimulator(u, win.outputs, win.dt_s, win.available, estimate_all_initial=False)
        yhat = sim.simulate(model.theta[None])[0]
    match: dict[str, float] = {}
    ratio: dict[str, float] = {}
    for j, ch in enumerate(OUTPUTS):
        m = sim.mask[:, j]
        if not m.any():
            continue
        y = sim.outputs[m, :, j]
        den = float(np.linalg.norm(y))
        if den <= 0:
            continue
        ratio[ch] = float(np.linalg.norm(yhat[m, :, j] - y)) / den
        match[ch] = (1.0 - ratio[ch]) * 100.0
    mean = float(np.mean(list(match.values()))) if match else float("nan")
    return Prediction(match=match, mean_match=mean, windows=win.count, window_s=float(window_s),
                      duration_s=float(win.count * win.length * win.dt_s), ratio=ratio)


def runaway_channels(pred: Prediction, runaway_factor: float = 3.0) -> list[str]:
    """Channels whose held-out error is more than ``runaway_factor`` times the signal itself."""
    return [c for c, r in pred.ratio.items() if r > runaway_factor]
