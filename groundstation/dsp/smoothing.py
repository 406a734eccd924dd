"""The paper's eq. (18): five-point cubic least-squares smoothing, applied ``passes`` times.

Array convention: ``y`` is (n_samples,) or (n_samples, n_channels); smoothing runs along axis 0.
Interior samples use the centred 5-point kernel (-3, 12, 17, 12, -3)/35; the first two and last two
samples use the paper's one-sided end formulas. Fewer than 5 samples are returned unchanged.
The causal (live) form with two samples of latency lives in :mod:`groundstation.dsp.live`.
"""

from __future__ import annotations

import numpy as np

from groundstation.errors import DspError

#: Centred kernel for y[i-2..i+2].
INTERIOR_KERNEL = np.array([-3.0, 12.0, 17.0, 12.0, -3.0]) / 35.0
#: End rows: weights on y[0..4] for the first two outputs (the last two are these reversed).
FIRST_ROW = np.array([69.0, 4.0, -6.0, 4.0, -1.0]) / 70.0
SECOND_ROW = np.array([2.0, 27.0, 12.0, -8.0, 2.0]) / 35.0


def smooth5(y: np.ndarray, passes: int = 1) -> np.ndarray:
    """Apply eq. (18) ``passes`` times along axis 0; returns a new float array of the same shape."""
    if passes < 0:
        raise DspError(f"passes must be >= 0, got {passes}")
    out = np.array(y, dtype=float, copy=True)
    n = out.shape[0]
    if n < 5 or passes == 0:
        return out
    for _ in range(passes):
        src = out
        res = np.empty_like(src)
        res[2:n - 2] = (
            INTERIOR_KERNEL[0] * (src[0:n - 4] + src[4:n])
            + INTERIOR_KERNEL[1] * (src[1:n - 3] + src[3:n - 1])
            + INTERIOR_KERNEL[2] * src[2:n - 2]
        )
        head = src[:5]
        tail = src[n - 5:]
        res[0] = np.tensordot(FIRST_ROW, head, axes=(0, 0))
        res[1] = np.tensordot(SECOND_ROW, head, axes=(0, 0))
        res[n - 2] = np.tensordot(SECOND_ROW[::-1], tail, axes=(0, 0))
        res[n - 1] = np.tensordot(FIRST_ROW[::-1], tail, axes=(0, 0))
        out = res
    return out
