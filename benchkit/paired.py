"""Is one model's held-out prediction better than another's, beyond what the held-out windows' spread allows?

``paired_difference(a, b)`` takes two models' predictions of the *same* held-out windows
(:class:`groundstation.sysid.heldout.PredictedWindows`) and returns the difference of their held-out
mean match (eq. 19 per channel over all windows, then the mean over channels: the figure ``bench
heldout`` prints) with a bootstrap interval over the windows: the windows are drawn with replacement,
the same draw for both models, and both are scored on it. A held-out block of a few windows can
hold one window unlike the rest (a manoeuvre the training part never flew): then the interval is wide
and the difference without that window (``without_window``, the one whose removal moves the
difference most towards ``a``) says how much of the difference that window makes. The spread comes
from the data's own windows, not from a constant. Pure numpy; the bench prints it.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _energies(pw: Any) -> tuple[np.ndarray, np.ndarray]:
    """(W, C) residual and signal energy of each window and channel over the measured samples."""
    m = pw.mask
    e = np.where(m, pw.predicted - pw.outputs, 0.0)
    y = np.where(m, pw.outputs, 0.0)
    return (e ** 2).sum(axis=1), (y ** 2).sum(axis=1)


def _scores(E: np.ndarray, Y: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(D,) mean over channels of the eq.-19 match of each draw (``counts`` (D, W): times each window is drawn)."""
    e, y = counts @ E, counts @ Y
    with np.errstate(invalid="ignore", divide="ignore"):
        match = np.where(y > 0, 100.0 * (1.0 - np.sqrt(e) / np.sqrt(y)), np.nan)
    return np.nanmean(match, axis=1)


def window_score(pw: Any, idx: np.ndarray) -> float:
    """Mean over channels of the eq.-19 match of the windows ``idx`` of ``pw`` (a window may repeat)."""
    E, Y = _energies(pw)
    return float(_scores(E, Y, np.bincount(idx, minlength=pw.count)[None].astype(float))[0])


def paired_difference(a: Any, b: Any, *, draws: int = 2000, level: float = 0.9, seed: int = 0) -> dict[str, Any]:
    """Held-out mean match of ``a`` minus that of ``b`` (points) on the same windows, its ``level``
    bootstrap interval over the windows (``lo``, ``hi``), and the difference ``without_window`` (1-based
    ``window``) when the one window that counts most against ``a`` is left out."""
    if a.outputs.shape != b.outputs.shape:
        raise ValueError(f"the two predictions cover different windows: {a.outputs.shape} and {b.outputs.shape}")
    n = a.count
    (Ea, Ya), (Eb, Yb) = _energies(a), _energies(b)

    def diff(counts: np.ndarray) -> np.ndarray:
        return _scores(Ea, Ya, counts) - _scores(Eb, Yb, counts)

    rng = np.random.default_rng(seed)
    boot = diff(np.stack([np.bincount(rng.integers(0, n, n), minlength=n) for _ in range(draws)]).astype(float))
    tail = 50.0 * (1.0 - level)
    lo, hi = np.nanpercentile(boot, [tail, 100.0 - tail])
    loo = diff(1.0 - np.eye(n)) if n >= 2 else np.array([np.nan])
    worst = int(np.nanargmax(loo)) if n >= 2 else 0
    return {"difference": float(diff(np.ones((1, n)))[0]), "lo": float(lo), "hi": float(hi), "level": level,
            "windows": n, "window": worst + 1, "without_window": float(loo[worst])}
