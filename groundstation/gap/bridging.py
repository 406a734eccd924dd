"""What the straight lines bridged over holes of the link leave in the held-out residual.

Over a hole of the link the inputs are a straight line between the samples on either side
(:mod:`groundstation.dsp.prepare`). The outputs there are not counted, but the model is driven by the
line: the difference between the line and what the servos really did goes on moving the aircraft
model after the hole, where the outputs are measured again. A perfect model shows that error too,
so it belongs under the gap figures beside the sensor noise, not in the gap.

:func:`bridge_error_nrmse` measures it from the flight's own inputs: for every bridged stretch of
the windows it takes a stretch of the same length where the inputs were measured, and the
difference between those inputs and the straight line between its ends (the error a bridge of that
length makes on these inputs); it drives the base model with these errors at the holes' places,
takes the change of the held-out residual (the windows' initial states fitted, the k-fold re-fit
as for the gap itself), and returns its RMS over the channel's signal, averaged over ``draws``
random choices of the stretches. Without bridged inputs it is zero.

Arrays: ``(W, L, channels)`` windows as :class:`groundstation.gap.evaluate.Evaluator` cuts them. Pure numpy.
"""

from __future__ import annotations

import numpy as np

from groundstation.gap.evaluate import Evaluator, SegmentArrays

#: random choices of the measured stretches averaged (a Monte-Carlo size, not a threshold)
DRAWS = 32


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of the runs of True in a 1-D bool array."""
    d = np.diff(np.r_[0, flags.astype(np.int8), 0])
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))


def _measured_inputs(segs: list[SegmentArrays]) -> list[np.ndarray]:
    """Stretches of inputs (n, 4) with no bridged sample."""
    out = []
    for s in segs:
        ok = np.ones(s.t_s.shape[0], bool) if s.bridged is None else ~s.bridged
        out += [s.inputs[a:b] for a, b in _runs(ok & np.isfinite(s.inputs).all(axis=1))]
    return out


def line_error(u: np.ndarray) -> np.ndarray:
    """Inputs (k + 2, 4) minus the straight line between the first and the last sample, inner k samples."""
    f = np.linspace(0.0, 1.0, u.shape[0])[:, None]
    return (u - (u[0] + f * (u[-1] - u[0])))[1:-1]


def _draw_errors(runs: list[tuple[int, int, int]], pool: list[np.ndarray], shape: tuple[int, ...],
                 rng: np.random.Generator) -> np.ndarray:
    """(W, L, 4) input errors: a measured stretch's line error at every bridged run (window, start, end)."""
    E = np.zeros(shape)
    for w, a, b in runs:
        k = b - a
        fits = [p for p in pool if p.shape[0] >= k + 2]
        if not fits:
            continue
        lens = np.array([p.shape[0] - k - 1 for p in fits], float)
        p = fits[int(rng.choice(len(fits), p=lens / lens.sum()))]
        j = int(rng.integers(0, p.shape[0] - k - 1))
        E[w, a:b] = line_error(p[j:j + k + 2]) * rng.choice([-1.0, 1.0])
    return E


def bridge_error_nrmse(ev: Evaluator, segs: list[SegmentArrays], theta: np.ndarray, rng: np.random.Generator,
                       draws: int = DRAWS) -> np.ndarray:
    """(8,) held-out RMS error over signal a perfect model shows from the bridged inputs (0 without bridges).

    ``ev``: the evaluator of ``segs`` (its windows, masks and k-fold re-fit); ``theta`` (31,) the base model.
    """
    if not any(s.bridged is not None for s in segs):
        return np.zeros(8)
    B = ev.cut([np.zeros(s.t_s.shape[0], bool) if s.bridged is None else s.bridged for s in segs])
    runs = [(w, a, b) for w in range(ev.W) for a, b in _runs(B[w])]
    pool = _measured_inputs(segs)
    if not runs or not pool:
        return np.zeros(8)
    theta = np.asarray(theta, float)[None]
    r_base = ev.residual(ev.simulate(theta)[0])
    e2 = np.zeros(8)
    for _ in range(draws):
        E = _draw_errors(runs, pool, ev.U.shape, rng)
        r = ev.residual(ev.simulate(theta, U=ev.U + E)[0]) - r_base
        e2 += (ev.heldout_residual(r)[:, ev.start:] ** 2).sum(axis=(0, 1))
    energy = ev.energy.sum(axis=0)
    return np.where(energy > 0, np.sqrt(e2 / draws / np.where(energy > 0, energy, 1.0)), 0.0)
