"""Train/validation splits of prepared data by whole blocks, segments or flights - never by sample.

* :func:`kfold` cuts every segment into contiguous blocks of ``block_s`` and deals them round-robin to
  ``k`` folds (block i goes to fold ``i % k``); fold f validates on its blocks and trains on the rest
  (adjacent training blocks are merged back into one segment). A flight-test card excites one channel
  after another, so a single early/late split would leave some channel's sweeps only in the held-out
  part; rotating blocks puts every excitation in some training fold.
* :func:`by_flight` holds out one (log, flight) at a time.
* :func:`holdout` is the single split ``kfold(...)[fold]``.
* :func:`contiguous_kfold` cuts the in-air time into ``k`` contiguous blocks (train on k-1, predict one);
  :func:`train_first` trains on the first seconds and predicts the rest: the held-out benchmarks of real
  flights, where a pilot did not fly a card and every block is different.

Sample-level interleaving is never offered: neighbouring samples are correlated and the windowed
simulation needs contiguous stretches. Pure; segments are sliced, not copied.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from groundstation.dsp.prepare import PreparedData, Segment
from groundstation.errors import DspError


def _slice(seg: Segment, a: int, b: int) -> Segment:
    m = getattr(seg, "measured", None)
    br = getattr(seg, "inputs_bridged", None)
    st = getattr(seg, "settling", None)
    return replace(seg, t_s=seg.t_s[a:b], inputs=seg.inputs[a:b], outputs=seg.outputs[a:b],
                   outputs_raw=seg.outputs_raw[a:b], alt_m=seg.alt_m[a:b], measured=None if m is None else m[a:b],
                   inputs_bridged=None if br is None else br[a:b], settling=None if st is None else st[a:b])


def block_labels(n: int, block_n: int, k: int) -> np.ndarray:
    """Fold label (n,) of each sample: contiguous blocks of ``block_n`` samples dealt round-robin."""
    return (np.arange(n) // max(1, block_n)) % k


def kfold(prepared: PreparedData, k: int = 5, block_s: float = 10.0) -> list[tuple[PreparedData, PreparedData]]:
    """``k`` (train, validation) pairs; see the module docstring."""
    if k < 2:
        raise DspError(f"k must be >= 2, got {k}")
    block_n = int(round(block_s / prepared.dt_s))
    out = []
    for f in range(k):
        train: list[Segment] = []
        val: list[Segment] = []
        for seg in prepared.segments:
            lab = block_labels(seg.n, block_n, k) == f
            for target, want in ((val, True), (train, False)):
                m = lab == want
                d = np.diff(np.concatenate([[0], m.astype(np.int8), [0]]))
                for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True):
                    target.append(_slice(seg, int(a), int(b)))
        out.append((replace(prepared, segments=train, notes=list(prepared.notes)),
                    replace(prepared, segments=val, notes=list(prepared.notes))))
    return out


def holdout(prepared: PreparedData, fold: int = 0, k: int = 5, block_s: float = 10.0) -> tuple[PreparedData, PreparedData]:
    """One (train, validation) pair of :func:`kfold`."""
    return kfold(prepared, k, block_s)[fold % k]


def by_flight(prepared: PreparedData) -> list[tuple[Any, PreparedData, PreparedData]]:
    """Leave-one-flight-out: ``[((source, flight), train, validation), ...]`` (needs >= 2 flights)."""
    keys = sorted({(s.source, s.flight) for s in prepared.segments})
    if len(keys) < 2:
        raise DspError("by_flight needs at least two flights in the prepared data")
    out = []
    for key in keys:
        val = [s for s in prepared.segments if (s.source, s.flight) == key]
        train = [s for s in prepared.segments if (s.source, s.flight) != key]
        out.append((key, replace(prepared, segments=train, notes=list(prepared.notes)),
                    replace(prepared, segments=val, notes=list(prepared.notes))))
    return out


def _cut(prepared: PreparedData, inside: Any, min_s: float) -> tuple[PreparedData, PreparedData]:
    """(outside, inside) of a time predicate ``inside(t_s) -> bool array``; pieces under ``min_s`` dropped."""
    min_n = max(1, int(round(min_s / prepared.dt_s)))
    train: list[Segment] = []
    val: list[Segment] = []
    for seg in prepared.segments:
        m_in = np.asarray(inside(seg.t_s), dtype=bool)
        for target, m in ((val, m_in), (train, ~m_in)):
            d = np.diff(np.concatenate([[0], m.astype(np.int8), [0]]))
            for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True):
                if b - a >= min_n:
                    target.append(_slice(seg, int(a), int(b)))
    return (replace(prepared, segments=train, notes=list(prepared.notes)),
            replace(prepared, segments=val, notes=list(prepared.notes)))


def contiguous_kfold(prepared: PreparedData, k: int = 5, min_s: float = 5.0) -> list[tuple[PreparedData, PreparedData]]:
    """``k`` (train, validation) pairs: the in-air time cut into ``k`` contiguous blocks of equal
    duration (counting only in-air samples, gaps between segments skipped); fold f validates on
    block f and trains on the others. Pieces shorter than ``min_s`` are dropped."""
    if k < 2:
        raise DspError(f"k must be >= 2, got {k}")
    t = np.concatenate([s.t_s for s in prepared.segments]) if prepared.segments else np.zeros(0)
    if t.size < k:
        raise DspError(f"contiguous_kfold: {t.size} samples cannot make {k} folds")
    t = np.sort(t)
    edges = np.concatenate([[t[0]], t[(np.arange(1, k) * t.size) // k], [np.inf]])
    return [_cut(prepared, lambda ts, a=edges[f], b=edges[f + 1]: (ts >= a) & (ts < b), min_s) for f in range(k)]


def train_first(prepared: PreparedData, train_s: float, min_s: float = 5.0) -> tuple[PreparedData, PreparedData]:
    """(train, validation): the first ``train_s`` seconds of in-air time, and everything after."""
    t = np.sort(np.concatenate([s.t_s for s in prepared.segments])) if prepared.segments else np.zeros(0)
    n = int(round(train_s / prepared.dt_s))
    if n >= t.size:
        raise DspError(f"train_first: only {t.size * prepared.dt_s:.1f} s in the air, cannot train on {train_s:g} s")
    cut = t[n]
    return _cut(prepared, lambda ts: ts >= cut, min_s)
