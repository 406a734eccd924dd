"""Alignment of irregular message series onto a uniform grid on the flight-controller clock.

Array conventions: source times ``t_src_s`` are (n_src,) seconds on the FC clock; values are
(n_src,) or (n_src, n_channels); the grid ``t_s`` is (n,) seconds. Interpolation is linear.
A grid point is *valid* for a column when it lies inside the source span, the source interval that
brackets it is no longer than ``max_gap_s`` (short gaps are bridged, long gaps are not), and both
bracketing samples are finite. Turning validity masks into segments (runs) is here too; which
series are required and how segments are labelled is :mod:`groundstation.dsp.prepare`'s business.
"""

from __future__ import annotations

import numpy as np

from groundstation.errors import DspError


def uniform_grid(start_s: float, end_s: float, rate_hz: float) -> np.ndarray:
    """Grid ``start_s + k / rate_hz`` for all k with the time ``<= end_s``; shape (n,)."""
    if rate_hz <= 0:
        raise DspError(f"rate_hz must be > 0, got {rate_hz}")
    if end_s < start_s:
        return np.zeros(0)
    n = int(np.floor((end_s - start_s) * rate_hz + 1e-9)) + 1
    return start_s + np.arange(n) / rate_hz


def median_interval_s(t_src_s: np.ndarray) -> float:
    """Median positive sample interval of a source series (inf with fewer than 2 samples)."""
    d = np.diff(np.asarray(t_src_s, dtype=float))
    d = d[d > 0]
    return float(np.median(d)) if d.size else float("inf")


def interpolate_onto(
    t_src_s: np.ndarray, values: np.ndarray, t_s: np.ndarray, max_gap_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of ``values`` onto ``t_s`` with gap handling.

    Parameters
    ----------
    t_src_s : array (n_src,), s, non-decreasing (duplicates: the last sample wins)
    values : array (n_src,) or (n_src, k)
    t_s : array (n,), s
    max_gap_s : longest source interval that is bridged by interpolation

    Returns
    -------
    out : array (n, k) (or (n,) for 1-D values), NaN where invalid
    valid : bool array of the same shape
    """
    t_src = np.asarray(t_src_s, dtype=float)
    vals = np.asarray(values, dtype=float)
    one_d = vals.ndim == 1
    if one_d:
        vals = vals[:, None]
    t = np.asarray(t_s, dtype=float)
    n, k = t.shape[0], vals.shape[1]
    out = np.full((n, k), np.nan)
    valid = np.zeros((n, k), dtype=bool)
    if t_src.shape[0] >= 1 and n:
        # keep the last of duplicate timestamps
        keep = np.ones(t_src.shape[0], dtype=bool)
        keep[:-1] = np.diff(t_src) > 0
        t_src = t_src[keep]
        vals = vals[keep]
        if t_src.shape[0] == 1:
            hit = np.abs(t - t_src[0]) <= 1e-9
            out[hit] = vals[0]
            valid[hit] = np.isfinite(vals[0])[None, :].repeat(hit.sum(), 0)
        else:
            i = np.searchsorted(t_src, t, side="right") - 1  # left bracket
            inside = (t >= t_src[0]) & (t <= t_src[-1])
            i = np.clip(i, 0, t_src.shape[0] - 2)
            t0 = t_src[i]
            t1 = t_src[i + 1]
            frac = np.where(t1 > t0, (t - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)
            v0 = vals[i]
            v1 = vals[i + 1]
            res = v0 + (v1 - v0) * frac[:, None]
            on_left = np.isclose(frac, 0.0)[:, None]
            on_right = np.isclose(frac, 1.0)[:, None]
            fin = (np.isfinite(v0) | on_right) & (np.isfinite(v1) | on_left)
            res = np.where(on_left & np.isfinite(v0), v0, res)
            res = np.where(on_right & np.isfinite(v1), v1, res)
            ok = inside[:, None] & ((t1 - t0) <= max_gap_s + 1e-9)[:, None] & fin
            out = np.where(ok, res, np.nan)
            valid = ok
    if one_d:
        return out[:, 0], valid[:, 0]
    return out, valid


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index ranges ``[start, stop)`` of the True runs of a 1-D boolean mask."""
    m = np.asarray(mask, dtype=bool).astype(np.int8)
    if m.size == 0:
        return []
    d = np.diff(np.concatenate([[0], m, [0]]))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


def fill_short_holes(mask: np.ndarray, max_len: int) -> np.ndarray:
    """Copy of ``mask`` with interior False runs of at most ``max_len`` samples set True."""
    m = np.asarray(mask, dtype=bool).copy()
    for a, b in runs(~m):
        if a > 0 and b < m.size and b - a <= max_len:
            m[a:b] = True
    return m


def interpolate_holes(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Linearly fill invalid samples of each column from the valid ones (edges: nearest valid).

    values (n, k) or (n,); valid same shape. Columns with no valid sample stay NaN.
    """
    v = np.array(values, dtype=float, copy=True)
    ok = np.asarray(valid, dtype=bool)
    one_d = v.ndim == 1
    if one_d:
        v = v[:, None]
        ok = ok[:, None]
    idx = np.arange(v.shape[0])
    for j in range(v.shape[1]):
        good = ok[:, j] & np.isfinite(v[:, j])
        if not good.any():
            v[:, j] = np.nan
            continue
        if good.all():
            continue
        v[~good, j] = np.interp(idx[~good], idx[good], v[good, j])
    return v[:, 0] if one_d else v
