"""A common time shift of the logged inputs against the outputs (a skew between logged channels).

Some logs carry their inputs late against the aircraft's response: the sticks are logged at a
different rate or by a different task than the gyros, or the log was resampled afterwards. A
response cannot precede the command that drives it, so an identified delay below zero (see
:mod:`groundstation.sysid.structure`) or a fit that improves when the inputs are moved earlier says
the inputs are late. Data compatibility checking (Klein & Morelli, ch. 10) corrects such a skew
before any model is fitted, so that every structure sees the same, consistent data.

``shift_inputs(prepared, shift_s)`` returns the data with every segment's inputs advanced by
``shift_s`` seconds (``u'(t) = u(t + shift_s)``, linear interpolation on the grid); a negative
shift delays them. Each segment loses the ``|shift_s|`` at the end (advance) or start (delay)
where the shifted input is not in the log. Outputs, trims and everything else are untouched.

``response_lead(prepared)`` reads how late the inputs are at least, where the pilot does not react to
the motion: on each stick's sharp, isolated steps the event-averaged on-axis rate is half way up before
the logged stick by ``lead_s`` (a causal response's own lag makes this a lower bound on the skew).
A fit's cost over a grid of shifts does not measure the skew on a flight flown in closed loop (the
stick follows the motion); the command-response structure's negative delays are another reading.
``skew_notes`` words the lead for ``identify``. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from groundstation.errors import DspError

#: a shift larger than this is not a skew between logged channels but a wrong channel or time base
MAX_SHIFT_S = 1.0


def _shift_segment(seg: Any, shift_s: float) -> Any | None:
    t = seg.t_s
    tt = t + shift_s
    keep = (tt >= t[0] - 1e-9) & (tt <= t[-1] + 1e-9)
    if keep.sum() < 2:
        return None
    u = np.column_stack([np.interp(tt[keep], t, seg.inputs[:, j]) for j in range(seg.inputs.shape[1])])
    m = seg.measured
    br = getattr(seg, "inputs_bridged", None)   # where the inputs were bridged moves with them
    br = None if br is None else np.interp(tt[keep], t, br.astype(float)) > 0.0
    st = getattr(seg, "settling", None)
    return replace(seg, t_s=t[keep], inputs=u, outputs=seg.outputs[keep], outputs_raw=seg.outputs_raw[keep],
                   alt_m=seg.alt_m[keep], measured=None if m is None else m[keep], inputs_bridged=br,
                   settling=None if st is None else st[keep])


def shift_inputs(prepared: Any, shift_s: float) -> Any:
    """``prepared`` (a :class:`groundstation.dsp.prepare.PreparedData`) with its inputs advanced by
    ``shift_s`` seconds (see the module docstring); segments shorter than the shift are dropped.

    Raises DspError (a ValueError) for a shift of ``MAX_SHIFT_S`` or more.
    """
    shift_s = float(shift_s)
    if not np.isfinite(shift_s) or abs(shift_s) >= MAX_SHIFT_S:
        raise DspError(f"input shift {shift_s:g} s: a skew between logged channels is below {MAX_SHIFT_S:g} s")
    if shift_s == 0.0:
        return prepared
    segs = [s for s in (_shift_segment(g, shift_s) for g in prepared.segments) if s is not None]
    word = "advanced" if shift_s > 0 else "delayed"
    note = f"inputs {word} by {abs(shift_s) * 1000:.0f} ms against the outputs (a time skew between the logged channels)"
    return replace(prepared, segments=segs, notes=list(prepared.notes) + [note])


#: (input, output) pairs whose on-axis response to a sharp stick input is read for a time skew
SKEW_PAIRS = (("lon", "q"), ("lat", "p"), ("ped", "r"))
_INPUTS = ("lat", "lon", "col", "ped")
_OUTPUTS = ("u", "v", "w", "p", "q", "r", "theta", "phi")


@dataclass(frozen=True)
class ResponseLead:
    """How far a response's half rise precedes its input's on the input's sharp, isolated steps.

    ``lead_s`` > 0: the averaged response is half way up before the logged input is (a causal
    response cannot be, so the inputs are logged late by at least about this much); ``lead_lo_s`` and
    ``lead_hi_s`` are a 90 % bootstrap interval over the ``events``."""

    input: str
    output: str
    lead_s: float
    lead_lo_s: float
    lead_hi_s: float
    events: int

    def describe(self) -> str:
        ms = 1000.0
        return (f"{self.output} rises half way {self.lead_s * ms:+.0f} ms before {self.input} "
                f"(90 % interval {self.lead_lo_s * ms:+.0f}..{self.lead_hi_s * ms:+.0f} ms, {self.events} sharp steps)")


def _events(x: np.ndarray, dt_s: float, half: int, quiet: float, k_noise: float) -> list[tuple[int, float]]:
    """Sharp, isolated steps of ``x``: peaks of |dx/dt| above ``k_noise`` times its robust noise (at
    least one quantisation step per sample) after ``half`` samples in which ``x`` moved by less than
    ``quiet`` of the step. Returns (index, sign of the step)."""
    dx = np.gradient(x, dt_s)
    steps = np.abs(np.diff(x))
    quantum = float(steps[steps > 0].min()) / dt_s if np.any(steps > 0) else 0.0
    noise = max(1.4826 * float(np.median(np.abs(dx - np.median(dx)))), quantum)
    if noise == 0.0:
        return []
    a, w = np.abs(dx), max(1, int(round(0.1 / dt_s)))
    out = []
    for i in range(half, x.size - half):
        if not (a[i] > k_noise * noise and a[i] >= a[i - 1] and a[i] > a[i + 1]):
            continue
        step = x[i + w] - x[i - w]
        if step != 0.0 and np.ptp(x[i - half:i - w]) < quiet * abs(step):
            out.append((i, float(np.sign(step))))
    return out


def _half_rise(t: np.ndarray, v: np.ndarray) -> float:
    """First time ``v`` (normalised to 1 after the step) crosses 0.5, linearly interpolated."""
    above = np.nonzero(v >= 0.5)[0]
    i = int(above[0]) if above.size else 0
    if i == 0:
        return float("nan")
    return float(t[i - 1] + (0.5 - v[i - 1]) / (v[i] - v[i - 1]) * (t[i] - t[i - 1]))


def _lead(X: np.ndarray, Y: np.ndarray, t: np.ndarray, after: np.ndarray) -> float:
    mx, my = X.mean(axis=0), Y.mean(axis=0)
    px, py = mx[after].mean(), my[after].mean()
    if px <= 0.0 or py <= 0.0:
        return float("nan")
    return _half_rise(t, mx / px) - _half_rise(t, my / py)


def response_lead(prepared: Any, pairs: tuple[tuple[str, str], ...] = SKEW_PAIRS, *, window_s: float = 0.6,
                  quiet: float = 0.3, k_noise: float = 8.0, min_events: int = 10, n_boot: int = 200,
                  seed: int = 0) -> list[ResponseLead]:
    """The time skew read where the pilot does not react to the motion: on each input's sharp,
    isolated steps (see :func:`_events`), the event-averaged input and on-axis response (raw outputs,
    each step's sign and pre-step level removed) are normalised by their mean 0.1-0.24 s after the
    step, and the time between their half rises is the lead (Klein & Morelli's data compatibility
    check, read on the pilot's own pulses). Pairs with fewer than ``min_events`` steps are left out."""
    dt = float(prepared.dt_s)
    half = int(round(window_s / dt))
    t = (np.arange(2 * half + 1) - half) * dt
    after = (t >= 0.1 - 1e-9) & (t <= 0.24 + 1e-9)
    rng = np.random.default_rng(seed)
    found = []
    for name_in, name_out in pairs:
        ji, jo = _INPUTS.index(name_in), _OUTPUTS.index(name_out)
        X, Y = [], []
        for s in prepared.segments:
            y = s.outputs_raw[:, jo]
            if not s.available[jo] or s.n < 2 * half + 1:
                continue
            for i, sg in _events(s.inputs[:, ji], dt, half, quiet, k_noise):
                xs, ys = s.inputs[i - half:i + half + 1, ji], y[i - half:i + half + 1]
                if np.all(np.isfinite(ys)):
                    X.append(sg * (xs - xs[:half - 5].mean()))
                    Y.append(sg * (ys - ys[:half - 5].mean()))
        if len(X) < min_events:
            continue
        Xa, Ya = np.array(X), np.array(Y)
        lead = _lead(Xa, Ya, t, after)
        if not np.isfinite(lead):
            continue
        boot = [_lead(Xa[b], Ya[b], t, after) for b in rng.integers(0, len(X), (n_boot, len(X)))]
        lo, hi = np.nanpercentile(boot, [5, 95])
        found.append(ResponseLead(name_in, name_out, lead, float(lo), float(hi), len(X)))
    return found


def skew_notes(prepared: Any, shift_s: float = 0.0) -> list[str]:
    """One line per pair whose response leads its logged input beyond doubt (90 % interval above 0):
    how late the inputs are at least, for ``[inputs] shift_s`` (``shift_s``: already applied)."""
    done = f" on top of the {shift_s * 1000:.0f} ms already applied" if shift_s else ""
    return [f"{r.describe()}: a causal response cannot rise first, so the logged inputs are late against the "
            f"outputs by at least about {r.lead_s * 1000:.0f} ms{done} (the response's own lag hides the rest; "
            f"[inputs] shift_s advances them)" for r in response_lead(prepared) if r.lead_lo_s > 0.0]
