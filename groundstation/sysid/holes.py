"""Identification windows that restart after each hole of a lossy link.

A hole of the link is bridged in the inputs by a straight line (:mod:`groundstation.dsp.prepare`). A
window simulated through the hole is driven by the line's error, and the attitude integrates it: every
output sample after the hole, to the window's end, then carries an error the model's parameters are
pulled to explain (errors in the variables). Here a window is never simulated through a bridged hole
into the samples it counts: each segment is cut at its *restart points* (the first sample after a
bridged input stretch where every available output is measured again, and the segment's first such
sample), and the windows of ``window_s`` start at a restart point, one every ``step_s`` up to the
next bridged input; a window counts its samples only up to there (the window starting at the next
restart point counts the rest; the samples of the hole and of the rotor's settling after it are
counted by none), from its own initial state (the measured states from its first sample, the others
by least squares, as for every window). The part of a window beyond the next bridged input is
simulated but not counted; the initial-state least squares still sees it (as it sees bridged values:
see :mod:`groundstation.sysid.simulate`). A start too close to the segment's end for a whole window
takes the segment's last ``window_s`` instead, counting from the start on (as a window through the
hole would: those few samples are not lost).

Segments without bridged inputs give exactly the windows of :func:`groundstation.sysid.cost.make_windows`;
a loss-free flight never comes here. Pure numpy.
"""

from __future__ import annotations

import numpy as np

from groundstation.errors import SysidError
from groundstation.sysid.cost import Windows, make_windows

__all__ = ["has_bridged_inputs", "restart_points", "restart_windows"]

#: fewest counted samples for which a window is simulated (the simulator's shortest window)
MIN_COUNTED = 5


def has_bridged_inputs(segments: list) -> bool:
    return any(getattr(s, "inputs_bridged", None) is not None and bool(np.any(s.inputs_bridged)) for s in segments)


def restart_points(seg) -> np.ndarray:
    """Sample indices where a window restarts in ``seg``: its first sample with every available output
    measured, and the first such sample after each bridged input stretch (sorted, unique)."""
    ok = seg.measured_mask()[:, np.asarray(seg.available, dtype=bool)].all(axis=1)
    br = np.zeros(seg.n, dtype=bool) if seg.inputs_bridged is None else np.asarray(seg.inputs_bridged, dtype=bool)
    ok &= ~br
    ends = np.flatnonzero(br[:-1] & ~br[1:]) + 1          # first sample after each bridged stretch
    good = np.flatnonzero(ok)
    if good.size == 0:
        return np.zeros(0, dtype=int)
    after = np.searchsorted(good, ends)
    pts = np.concatenate([good[:1], good[after[after < good.size]]])
    return np.unique(pts)


def _starts(seg, L: int, S: int) -> list[tuple[int, int, int]]:
    """(window start, first counted, end of counted) of every window of ``seg``."""
    pts = restart_points(seg)
    br = np.zeros(seg.n, dtype=bool) if seg.inputs_bridged is None else np.asarray(seg.inputs_bridged, dtype=bool)
    bridged = np.flatnonzero(br)
    out = []
    for r in pts:
        nxt = bridged[np.searchsorted(bridged, r):]
        stop = int(nxt[0]) if nxt.size else seg.n        # the next bridged input: nothing counted beyond
        for c in range(int(r), stop, S):
            if stop - c < MIN_COUNTED or seg.n < L:
                continue
            out.append((min(c, seg.n - L), c, min(c + L, stop)))
    return out


def restart_windows(segments: list, dt_s: float, window_s: float, *, key: str = "window_s",
                    step_s: float = 0.0) -> Windows:
    """Windows of ``round(window_s / dt_s)`` samples restarting after each bridged hole (see the module
    docstring); with no bridged input anywhere, :func:`make_windows`'s windows."""
    if not has_bridged_inputs(segments):
        return make_windows(segments, dt_s, window_s, key=key, step_s=step_s)
    L = int(round(window_s / dt_s))
    if L < 5:
        raise SysidError(f"{key} = {window_s:g}: fewer than 5 samples at dt_s={dt_s:g}")
    S = L if step_s <= 0 else max(1, int(round(step_s / dt_s)))
    ins, outs, av, seg_i, t0, meas = [], [], [], [], [], []
    for i, s in enumerate(segments):
        m = s.measured_mask()
        for a, c, e in _starts(s, L, S):
            count = np.zeros((L, 1), dtype=bool)
            count[c - a:e - a] = True
            ins.append(s.inputs[a:a + L])
            outs.append(s.outputs[a:a + L])
            meas.append(m[a:a + L] & count)
            av.append(np.asarray(s.available, dtype=bool))
            seg_i.append(i)
            t0.append(float(s.t_s[a]))
    if not ins:
        longest = max((s.duration_s for s in segments), default=0.0)
        raise SysidError(f"{key} = {window_s:g}: no in-air segment is that long (longest {longest:.1f} s)")
    return Windows(np.stack(ins), np.stack(outs), np.stack(av), np.array(seg_i), np.array(t0), float(dt_s),
                   np.stack(meas))
