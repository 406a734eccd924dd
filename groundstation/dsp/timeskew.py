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

How large the shift is, is measured elsewhere (from a fit's cost over a grid of shifts, or from the
command-response structure's negative delays); this module only applies it. Pure numpy.
"""

from __future__ import annotations

from dataclasses import replace
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
    return replace(seg, t_s=t[keep], inputs=u, outputs=seg.outputs[keep], outputs_raw=seg.outputs_raw[keep],
                   alt_m=seg.alt_m[keep], measured=None if m is None else m[keep], inputs_bridged=br)


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
