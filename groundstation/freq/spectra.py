"""Frequency responses from flight data: composite-window, conditioned (multi-input) estimates.

What it computes, for every input -> output pair of the hover model (inputs ``lat lon col ped``,
outputs ``u v w p q r theta phi``):

1. for each window length ``T`` of :attr:`FreqConfig.window_s`: the data are cut into overlapped
   windows (``overlap``, default 0.8), each detrended and tapered (Hann by default, through
   ``scipy.signal.detrend`` / ``get_window``), and Fourier-transformed at the composite frequencies
   (a direct DFT at arbitrary frequencies, like a chirp-z: no interpolation between window grids);
   auto and cross spectra are averaged over windows (one-sided densities, scaled as
   ``scipy.signal.csd`` scales them);
2. conditioned (multi-input) responses per output: with the input cross-spectral matrix ``Gxx``
   (every input that moves), ``H = Gxx^-1 Gxy``; the residual spectrum ``Gnn = Gyy - Gxy^H H``;
   each input's partial coherence ``g2_i = |H_i|^2 / (|H_i|^2 + Gnn [Gxx^-1]_ii)`` (its own effect
   separated from the correlated other inputs; it reduces to the ordinary coherence for one input);
3. the normalised random error ``eps = sqrt(1 - g2) / (|g| sqrt(2 n_d))`` (Bendat & Piersol), with
   ``n_d`` the effective number of averages of the overlapped windows (Welch's variance formula for
   the taper's overlap correlation) less the other inputs conditioned on;
4. the composite: the window estimates at each frequency averaged with weights ``1 / eps^2``
   (each window length only at frequencies of at least ``min_cycles`` cycles per window); the
   composite error combines the weighted mean of the window errors (the windows see the same data,
   so they are not independent: the composite is never credited with more certainty than that)
   with an estimate of the leakage bias from two adjacent window lengths (bias ~ 1/T, Richardson),
   which the coherence formula does not see;
5. coherent points: composite coherence ``>= coherence_min`` (0.6). A pair with fewer than
   ``min_coherent_points`` coherent points has no response, and says why in one line.

Arrays: a segment's ``inputs (n, 4)`` and ``outputs (n, 8)`` (NaN where unmeasured); responses are
``(n_freq,)`` complex in output units per input unit (``delta`` normalised inputs). Pure numpy/scipy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.signal import detrend as sp_detrend
from scipy.signal import get_window

from groundstation.freq import FreqError
from groundstation.sysid.model import INPUTS, OUTPUTS


@dataclass(frozen=True)
class FreqConfig:
    """Frequency-analysis settings (``[freq]`` TOML table)."""

    window_s: tuple[float, ...] = (5.0, 10.0, 20.0)
    overlap: float = 0.8
    taper: str = "hann"
    detrend: str = "linear"
    n_freq: int = 80
    #: a window length enters the composite at frequencies of at least this many cycles per window
    #: (its leakage-bias estimate uses it down to two cycles). With CIFER's usual two, closed-loop
    #: simulated flights of the open-loop-unstable hover model gave true-model J_avg of 25-70 (the
    #: low-frequency points of the short windows biased by leakage of the slow modes); with six,
    #: 5-12 on three seeded flights, the lowest frequency moving from 0.07 to 0.2 Hz with 30 s windows.
    min_cycles: float = 6.0
    f_min_hz: float | None = None  # None: min_cycles cycles of the longest usable window
    f_max_hz: float = 10.0  # also at most 0.4 x the sample rate
    coherence_min: float = 0.6
    min_coherent_points: int = 3
    #: effective averages a window length needs beyond the inputs it conditions on (else dropped)
    #: (with 6, a noise-only pair passes g2 >= 0.6 at a given point with probability 0.4^6 = 0.4 %)
    min_averages: float = 6.0
    #: an input whose standard deviation stays below this (normalised units) never moves
    input_active_std: float = 1e-4

    def __post_init__(self) -> None:
        if not self.window_s or any(w <= 0 for w in self.window_s):
            raise FreqError(f"freq.window_s must be positive lengths, got {self.window_s}")
        if not 0.0 <= self.overlap < 1.0:
            raise FreqError(f"freq.overlap must be in [0, 1), got {self.overlap}")
        if self.detrend not in ("linear", "constant"):
            raise FreqError(f"freq.detrend must be linear or constant, got {self.detrend!r}")
        if not 0.0 < self.coherence_min < 1.0:
            raise FreqError(f"freq.coherence_min must be in (0, 1), got {self.coherence_min}")
        if self.n_freq < 4:
            raise FreqError(f"freq.n_freq must be >= 4, got {self.n_freq}")
        if self.f_max_hz <= 0 or (self.f_min_hz is not None and not 0 < self.f_min_hz < self.f_max_hz):
            raise FreqError(f"freq.f_min_hz/f_max_hz must satisfy 0 < f_min < f_max, got {self.f_min_hz}, {self.f_max_hz}")


@dataclass(frozen=True, eq=False)
class PairResponse:
    """Composite frequency response of one output to one input (conditioned on the other inputs).

    ``response`` (n_freq,) complex, output units per input unit; ``coherence`` partial coherence;
    ``random_error`` normalised (std of |H| over |H|; also the phase std in rad); ``coherent`` the
    points used downstream. ``reason`` is empty when the pair has a response, else says why not.
    """

    input: str
    output: str
    f_hz: np.ndarray
    response: np.ndarray
    coherence: np.ndarray
    random_error: np.ndarray
    coherent: np.ndarray
    reason: str = ""

    @property
    def has_response(self) -> bool:
        return not self.reason

    @property
    def coherent_points(self) -> int:
        return int(self.coherent.sum())

    @property
    def magnitude_db(self) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return 20.0 * np.log10(np.abs(self.response))

    @property
    def phase_deg(self) -> np.ndarray:
        return np.degrees(np.angle(self.response))


@dataclass(frozen=True, eq=False)
class ResponseSet:
    """Every pair's response on one frequency grid, with what was used and what was dropped."""

    f_hz: np.ndarray
    dt_s: float
    windows_s: tuple[float, ...]
    conditioned_on: tuple[str, ...]
    pairs: tuple[PairResponse, ...]
    notes: tuple[str, ...] = ()
    config: FreqConfig = field(default_factory=FreqConfig)

    def pair(self, inp: str, out: str) -> PairResponse:
        for p in self.pairs:
            if p.input == inp and p.output == out:
                return p
        raise KeyError(f"no pair {inp}->{out}")

    @property
    def with_response(self) -> list[PairResponse]:
        return [p for p in self.pairs if p.has_response]

    @property
    def without_response(self) -> list[PairResponse]:
        return [p for p in self.pairs if not p.has_response]


def effective_averages(n_windows: int, length: int, step: int, taper: np.ndarray) -> float:
    """Equivalent number of independent averages of ``n_windows`` overlapped tapered windows.

    Welch (1967): ``var / var_1 = (1/K) [1 + 2 sum_j (1 - j/K) rho(j step)^2]`` with ``rho(d)`` the
    taper's correlation at a shift of ``d`` samples.
    """
    if n_windows <= 0:
        return 0.0
    w2 = float(np.sum(taper ** 2))
    s = 1.0
    for j in range(1, n_windows):
        d = j * step
        if d >= length:
            break
        rho = float(np.sum(taper[: length - d] * taper[d:])) / w2
        s += 2.0 * (1.0 - j / n_windows) * rho ** 2
    return n_windows / s


def _frequency_grid(cfg: FreqConfig, dt_s: float, longest_s: float) -> np.ndarray:
    f_hi = min(cfg.f_max_hz, 0.4 / dt_s)
    f_lo = cfg.f_min_hz if cfg.f_min_hz is not None else cfg.min_cycles / longest_s
    if f_lo >= f_hi:
        raise FreqError(f"frequency range empty: f_min {f_lo:.3g} Hz >= f_max {f_hi:.3g} Hz")
    return np.geomspace(f_lo, f_hi, cfg.n_freq)


def _window_spectra(segments: list[tuple[np.ndarray, np.ndarray]], length: int, step: int, f_hz: np.ndarray,
                    dt_s: float, cfg: FreqConfig) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """DFT of every window: X (K, n_freq, 12) scaled so that conj(X_a) X_b averages to the one-sided
    density; valid (K, 12) channel finite over the window; windows per segment.

    Holes of the link (``segments``' optional third element: samples bridged, not measured) are
    gap-aware: a window is kept when they take at most ``MAX_HOLE_SHARE`` of its taper energy, with the
    bridged values in place (zero weight there would cut the input-output relation the dynamics carry
    across the hole: measured on a 10 %-loss flight, coherence fell from 0.98 to 0.44 that way), so the
    lost high frequencies show as lower coherence; a window with more is dropped. Its ``valid`` weight
    is the measured share of its taper energy: the averages and random errors count only what came."""
    taper = get_window(cfg.taper, length)
    E = np.exp(-2j * np.pi * np.outer(np.arange(length) * dt_s, f_hz))  # (L, nf)
    t2 = np.sum(taper ** 2)
    Xs, valid, counts = [], [], []
    for u, y, *h in segments:
        n = u.shape[0]
        if n < length:
            counts.append(0)
            continue
        data = np.concatenate([u, y], axis=1)
        frames = np.lib.stride_tricks.sliding_window_view(data, length, axis=0)[::step]  # (K, 12, L)
        lost = h[0] if h and h[0] is not None else np.zeros(n, bool)
        hole = np.lib.stride_tricks.sliding_window_view(lost, length)[::step]  # (K, L): sample bridged
        share = (taper[None] ** 2 * ~hole).sum(axis=1) / t2  # measured share of the taper energy (K,)
        ok = (np.isfinite(frames) | hole[:, None, :]).all(axis=2) & (share >= 1.0 - MAX_HOLE_SHARE)[:, None]
        fr = sp_detrend(np.nan_to_num(frames), axis=2, type=cfg.detrend) * taper
        scale = np.full(frames.shape[0], np.sqrt(2.0 * dt_s / t2))  # (K,)
        ok = ok * share[:, None]
        Xs.append(np.einsum("kcl,lf->kfc", fr, E) * scale[:, None, None])
        valid.append(ok)
        counts.append(frames.shape[0])
    if not Xs:
        return np.zeros((0, f_hz.size, 12), complex), np.zeros((0, 12), bool), counts
    return np.concatenate(Xs), np.concatenate(valid), counts


#: largest share of a window's taper energy that holes of the link may take before it is dropped
MAX_HOLE_SHARE = 0.25


def _miso(X_in: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Conditioned responses of one output: H (nf, q) and partial coherence (nf, q).

    X_in (K, nf, q), Y (K, nf) window transforms of the inputs and the output.
    """
    Gxx = np.einsum("kfa,kfb->fab", X_in.conj(), X_in) / X_in.shape[0]
    Gxy = np.einsum("kfa,kf->fa", X_in.conj(), Y) / X_in.shape[0]
    Gyy = np.mean(np.abs(Y) ** 2, axis=0)
    q = Gxx.shape[-1]
    ridge = 1e-12 * np.real(np.trace(Gxx, axis1=1, axis2=2))[:, None, None] * np.eye(q)
    Ginv = np.linalg.inv(Gxx + ridge)
    H = np.einsum("fab,fb->fa", Ginv, Gxy)
    Gnn = np.maximum(Gyy - np.real(np.einsum("fa,fa->f", Gxy.conj(), H)), 0.0)
    h2 = np.abs(H) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        g2 = h2 / (h2 + Gnn[:, None] * np.real(np.diagonal(Ginv, axis1=1, axis2=2)))
    return H, np.nan_to_num(g2, nan=0.0)


def _averages(valid_y: np.ndarray, counts: list[int], length: int, step: int, taper: np.ndarray) -> float:
    """Effective averages of the windows kept; a window with holes counts by its measured share."""
    n, start = 0.0, 0
    for c in counts:
        v = np.asarray(valid_y[start:start + c], dtype=float)
        k = int((v > 0).sum())
        if k:
            n += effective_averages(k, length, step, taper) * float(v[v > 0].mean())
        start += c
    return n


def _one_window(segments, win_s: float, f_hz: np.ndarray, dt_s: float, active: list[int], cfg: FreqConfig,
                notes: list[str]) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] | None:
    """Per pair (input, output): (H, partial coherence, random error) of one window length, NaN where
    the window does not resolve the frequency; None when the data are too short for it."""
    length = int(round(win_s / dt_s))
    step = max(1, int(round(length * (1.0 - cfg.overlap))))
    X, valid, counts = _window_spectra(segments, length, step, f_hz, dt_s, cfg)
    taper = get_window(cfg.taper, length)
    q = len(active)
    resolved = f_hz >= 2.0 / win_s
    out: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for j in range(8):
        wsel = np.minimum(valid[:, 4 + j], valid[:, active].min(axis=1)) if X.shape[0] else np.zeros(0)
        sel = wsel > 0
        n_d = _averages(wsel, counts, length, step, taper) - (q - 1) if sel.any() else 0.0
        if n_d < cfg.min_averages:
            continue
        H, g2 = _miso(X[sel][:, :, active], X[sel][:, :, 4 + j])
        with np.errstate(divide="ignore", invalid="ignore"):
            eps = np.sqrt((1.0 - g2) / (2.0 * n_d * g2))
        for a, i in enumerate(active):
            out[(i, j)] = (np.where(resolved, H[:, a], np.nan), np.where(resolved, g2[:, a], np.nan),
                           np.where(resolved, eps[:, a], np.nan))
    if not out:
        longest = max((s[0].shape[0] for s in segments), default=0) * dt_s
        notes.append(f"window {win_s:g} s not used: the longest segment ({longest:.1f} s) gives fewer than "
                     f"{cfg.min_averages:g} effective averages beyond the {q} inputs conditioned on")
        return None
    return out


def _enough(segments, win_s: float, dt_s: float, q: int, cfg: FreqConfig, notes: list[str]) -> bool:
    """Whether the segments give a window length enough averages (else a note says why not)."""
    length = int(round(win_s / dt_s))
    step = max(1, int(round(length * (1.0 - cfg.overlap))))
    taper = get_window(cfg.taper, length)
    n_d = sum(effective_averages((s[0].shape[0] - length) // step + 1, length, step, taper)
              for s in segments if s[0].shape[0] >= length) - (max(q, 1) - 1)
    if n_d >= cfg.min_averages:
        return True
    longest = max(s[0].shape[0] for s in segments) * dt_s
    notes.append(f"window {win_s:g} s not used: {longest:.1f} s of data (longest segment) give {max(n_d, 0):.1f} "
                 f"effective averages, {cfg.min_averages:g} needed beyond the inputs conditioned on")
    return False


def _composite(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], win_s: list[float], f_hz: np.ndarray,
               min_cycles: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Composite (H, coherence, error) of one pair from its window estimates (shortest window first).

    Each window's leakage bias is taken as ``c / T`` (it shrinks with the window length ``T``), so
    two adjacent lengths estimate it: ``|H_T - H_T'| T' / |T' - T|`` (Richardson). The composite error
    is ``sqrt(eps_mean^2 + bias_mean^2)``, both weighted like the estimate.
    """
    H = np.stack([p[0] for p in parts])
    g2 = np.stack([p[1] for p in parts])
    eps = np.stack([p[2] for p in parts])
    T = np.asarray(win_s, dtype=float)
    bias = np.full(H.shape, np.nan)
    for k in range(len(parts)):
        if len(parts) < 2:
            break
        o = k - 1 if k > 0 else 1  # the next shorter window, or the next longer for the shortest
        bias[k] = np.abs(H[k] - H[o]) * T[o] / abs(T[o] - T[k])
    use = f_hz[None, :] >= min_cycles / T[:, None]
    ok = use & np.isfinite(H) & np.isfinite(eps) & (eps > 0)
    w = np.where(ok, 1.0 / np.where(ok, eps, 1.0) ** 2, 0.0)
    ws = w.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        Hc = np.where(ws > 0, (w * np.nan_to_num(H)).sum(axis=0) / ws, np.nan)
        gc = np.where(ws > 0, (w * np.nan_to_num(g2)).sum(axis=0) / ws, np.nan)
        ec = np.where(ws > 0, (w * np.nan_to_num(eps)).sum(axis=0) / ws, np.nan)
        bc = np.where(ws > 0, (w * np.nan_to_num(bias)).sum(axis=0) / ws, np.nan) / np.abs(Hc)
    return Hc, gc, np.sqrt(ec ** 2 + bc ** 2)


def _no_response(inp: str, out: str, f_hz: np.ndarray, reason: str) -> PairResponse:
    nan = np.full(f_hz.size, np.nan)
    return PairResponse(inp, out, f_hz, nan.astype(complex), nan, nan, np.zeros(f_hz.size, bool), reason)


def _measured_only(seg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(inputs, unsmoothed outputs, samples bridged over a hole of the link or None)."""
    u, y = np.asarray(seg.inputs, float), np.asarray(seg.outputs_raw, float)
    m = getattr(seg, "measured", None)
    if m is None:
        return u, y, None
    return u, y, ~np.asarray(m, bool)[:, np.asarray(seg.available, bool)].all(axis=1)


def estimate_responses(prepared: Any, config: FreqConfig | None = None) -> ResponseSet:
    """Composite conditioned frequency responses of every input -> output pair of ``prepared``.

    ``prepared`` is a :class:`groundstation.dsp.prepare.PreparedData` (its unsmoothed outputs are
    used: the eq.-18 smoothing is a low-pass filter); see the module docstring for the method.
    """
    cfg = config or FreqConfig()
    dt = float(prepared.dt_s)
    segments = [_measured_only(s) for s in prepared.segments]
    if not segments:
        raise FreqError("no in-air segments to analyse")
    notes: list[str] = []
    u_all = np.concatenate([s[0] for s in segments])
    active = [i for i in range(4) if np.nanstd(u_all[:, i]) > cfg.input_active_std]
    longest_seg_s = max(s[0].shape[0] for s in segments) * dt
    wins = [w for w in sorted(set(cfg.window_s)) if _enough(segments, w, dt, len(active), cfg, notes)]
    per_window: list[dict] = []
    used: list[float] = []
    f_hz = np.geomspace(1.0, 2.0, cfg.n_freq)
    if active and wins:
        f_hz = _frequency_grid(cfg, dt, max(wins))
        for w in wins:
            got = _one_window(segments, w, f_hz, dt, active, cfg, notes)
            if got is not None:
                per_window.append(got)
                used.append(w)
    avail = [any(bool(np.isfinite(s[1][:, j]).any()) for s in segments) for j in range(8)]
    pairs = []
    for i, inp in enumerate(INPUTS):
        for j, out in enumerate(OUTPUTS):
            pairs.append(_pair(i, j, inp, out, f_hz, active, avail, per_window, used, cfg, longest_seg_s))
    return ResponseSet(f_hz=f_hz, dt_s=dt, windows_s=tuple(used), conditioned_on=tuple(INPUTS[i] for i in active),
                       pairs=tuple(pairs), notes=tuple(notes), config=cfg)


def _pair(i: int, j: int, inp: str, out: str, f_hz: np.ndarray, active: list[int], avail: list[bool],
          per_window: list[dict], used_s: list[float], cfg: FreqConfig, longest_seg_s: float) -> PairResponse:
    if i not in active:
        return _no_response(inp, out, f_hz, f"input {inp} never moves (std below {cfg.input_active_std:g})")
    if not avail[j]:
        return _no_response(inp, out, f_hz, f"output {out} not measured")
    parts = [w[(i, j)] for w in per_window if (i, j) in w]
    lengths = [t for t, w in zip(used_s, per_window, strict=True) if (i, j) in w]
    if not parts:
        return _no_response(inp, out, f_hz, f"too short: the longest segment with {out} measured ({longest_seg_s:.1f} s) "
                                            f"gives too few averages for any window of {cfg.window_s} s")
    H, g2, eps = _composite(parts, lengths, f_hz, cfg.min_cycles)
    coherent = np.isfinite(g2) & (g2 >= cfg.coherence_min) & np.isfinite(H)
    if coherent.sum() < cfg.min_coherent_points:
        if np.isfinite(g2).any():
            k = int(np.nanargmax(g2))
            why = (f"coherence below {cfg.coherence_min:g} at all but {int(coherent.sum())} points "
                   f"(max {g2[k]:.2f} at {f_hz[k]:.2f} Hz)")
        else:
            why = "no frequency resolved by the windows"
        return PairResponse(inp, out, f_hz, H, g2, eps, np.zeros(f_hz.size, bool), why)
    return PairResponse(inp, out, f_hz, H, g2, eps, coherent)


def native_rate_hz(prepared: Any, grid_rate_hz: float | None = None) -> float | None:
    """Sample rate at which the moving inputs and the body rates and attitude were logged, when that is
    faster than the grid of ``prepared`` (else None): the rate to prepare at for frequency analysis.

    The slowest of those channels sets it (velocities, often slower, are left interpolated).
    """
    names = [n for n, a in zip(INPUTS, prepared.input_active, strict=True) if a] + ["p", "q", "r", "theta", "phi"]
    iv = [float(prepared.native_interval_s.get(n, float("nan"))) for n in names]
    iv = [x for x in iv if np.isfinite(x) and x > 0]
    if not iv:
        return None
    rate = 1.0 / max(iv)
    grid = grid_rate_hz if grid_rate_hz is not None else 1.0 / float(prepared.dt_s)
    return float(rate) if rate > 1.05 * grid else None
