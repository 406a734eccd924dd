"""Frequency responses from flight data: composite-window, conditioned (multi-input) estimates.

What it computes, for every input -> output pair of the hover model (inputs ``lat lon col ped``,
outputs ``u v w p q r theta phi``):

1. for each window length ``T`` of :attr:`FreqConfig.window_s`: the data are cut into overlapped
   windows (``overlap``, default 0.8), each detrended (least squares, as ``scipy.signal.detrend``) and
   tapered (Hann by default, ``get_window``), and Fourier-transformed at the composite frequencies
   (a direct DFT at arbitrary frequencies, like a chirp-z: no interpolation between window grids) --
   one matrix per window length, :func:`window_operator`; auto and cross spectra are averaged over
   windows (one-sided densities, scaled as ``scipy.signal.csd`` scales them). The averages are running
   sums (:class:`WindowSpectra`, :class:`IncrementalResponses`): the batch estimate feeds whole
   segments, the live excitation monitor feeds rows as they arrive, and both give the same numbers;
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

from groundstation.freq import FreqError
from groundstation.sysid.model import INPUTS, OUTPUTS

N_INPUTS = len(INPUTS)


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


def taper_window(name: str, length: int) -> np.ndarray:
    """``scipy.signal.get_window(name, length)`` (periodic); the Hann taper without importing
    scipy.signal, which costs about a second of CPU: the live service starts a flight's estimate on its
    event loop."""
    if name in ("hann", "hanning"):
        return 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(length) / length)
    from scipy.signal import get_window

    return np.asarray(get_window(name, length), dtype=float)


def _window_geometry(win_s: float, dt_s: float, cfg: FreqConfig) -> tuple[int, int, np.ndarray]:
    """(samples per window, samples between window starts, taper) of one window length."""
    length = int(round(win_s / dt_s))
    step = max(1, int(round(length * (1.0 - cfg.overlap))))
    return length, step, taper_window(cfg.taper, length)


def window_operator(length: int, dt_s: float, f_hz: np.ndarray, taper: np.ndarray, detrend: str) -> np.ndarray:
    """``(length, n_freq)`` complex: a window's rows (as a row vector) times this matrix are its
    detrended, tapered DFT at ``f_hz``, scaled so that ``conj(X_a) X_b`` averages to the one-sided
    cross-spectral density (as ``scipy.signal.csd`` scales it).

    Detrending (least-squares constant or line over the window, as ``scipy.signal.detrend``) is a
    projection ``D``, the taper a diagonal ``W`` and the DFT at arbitrary frequencies a matrix ``E``:
    the operator ``D W E`` (``D`` symmetric) is computed once per window length.
    """
    n = np.arange(length, dtype=float)
    TE = np.exp(-2j * np.pi * np.outer(n * dt_s, f_hz)) * taper[:, None]
    basis = np.ones((length, 1)) if detrend == "constant" else np.column_stack([np.ones(length), n])
    Q, _ = np.linalg.qr(basis)
    return (TE - Q @ (Q.T @ TE)) * np.sqrt(2.0 * dt_s / np.sum(taper ** 2))


def _transform(frames: np.ndarray, op_re: np.ndarray, op_im: np.ndarray) -> np.ndarray:
    """``(K, C, n_freq)`` transforms of windows ``(K, C, L)``, NaN samples as zeros (two real BLAS
    products: a real-by-complex product of a strided view does not reach BLAS and is ~20x slower)."""
    K, C, L = frames.shape
    F = np.nan_to_num(np.ascontiguousarray(frames)).reshape(K * C, L)
    return (F @ op_re + 1j * (F @ op_im)).reshape(K, C, -1)


class WindowSpectra:
    """Running sums of the cross-spectral matrix over overlapped windows of one length (incremental).

    Rows ``(n, C)`` (inputs then outputs) arrive in chunks (:meth:`add`); segments end
    (:meth:`end_segment`). Each window that completes (``length`` rows; starts ``step`` rows apart from
    the segment's first row, as :func:`estimate_responses` cuts them) is transformed once
    (:func:`window_operator`) and ``conj(X_a) X_b`` (n_freq, C, C) added to the sum of its finiteness
    pattern (which channels are finite over the whole window; NaN samples enter as zeros, as in the
    batch estimate, and a pair uses only the windows where its channels are finite). The work per
    window is fixed: nothing grows with the flight but one count per segment.
    """

    def __init__(self, win_s: float, dt_s: float, f_hz: np.ndarray, cfg: FreqConfig, n_channels: int) -> None:
        self.win_s = float(win_s)
        self.length, self.step, self.taper = _window_geometry(win_s, dt_s, cfg)
        self.operator = window_operator(self.length, dt_s, f_hz, self.taper, cfg.detrend)
        self._op_re, self._op_im = np.ascontiguousarray(self.operator.real), np.ascontiguousarray(self.operator.imag)
        self.n_channels = n_channels
        self._sums: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}   # pattern -> (finite (C,), sum (nf, C, C))
        self.counts: list[dict[bytes, int]] = [{}]                     # per segment: pattern -> windows
        #: per segment: pattern -> (C,) sum over its windows of each channel's measured share (taper-weighted)
        self.shares: list[dict[bytes, np.ndarray]] = [{}]
        self.segment_rows: list[int] = [0]
        self._tail = np.empty((0, n_channels))     # rows of the open segment from the next window start on
        self._tail_m = np.empty((0, n_channels), bool)
        self._w2 = self.taper ** 2 / np.sum(self.taper ** 2)
        self._eff: dict[int, float] = {}

    def add(self, rows: np.ndarray, measured: np.ndarray | None = None) -> None:
        """Append rows ``(n, C)`` to the open segment and transform every window they complete;
        ``measured (n, C)`` bool is False where a value only bridges a hole of the link (None: all measured)."""
        rows = np.asarray(rows, dtype=float).reshape(-1, self.n_channels)
        if rows.shape[0] == 0:
            return
        m = (np.ones(rows.shape, bool) if measured is None
             else np.asarray(measured, dtype=bool).reshape(-1, self.n_channels))
        self.segment_rows[-1] += rows.shape[0]
        data = np.concatenate([self._tail, rows]) if self._tail.shape[0] else rows
        mask = np.concatenate([self._tail_m, m]) if self._tail_m.shape[0] else m
        if data.shape[0] < self.length:
            self._tail, self._tail_m = data, mask
            return
        frames = np.lib.stride_tricks.sliding_window_view(data, self.length, axis=0)[::self.step]  # (K, C, L)
        k = frames.shape[0]
        self._tail = data[k * self.step:].copy()
        self._tail_m = mask[k * self.step:].copy()
        share = None
        if not mask.all():
            share = np.lib.stride_tricks.sliding_window_view(mask, self.length, axis=0)[::self.step] @ self._w2
        self._accumulate(frames, share)

    def transforms(self, frames: np.ndarray) -> np.ndarray:
        """``(K, C, n_freq)`` transforms of windows ``(K, C, length)`` (NaN samples as zeros)."""
        return _transform(frames, self._op_re, self._op_im)

    def _accumulate(self, frames: np.ndarray, share: np.ndarray | None = None) -> None:
        ok = np.isfinite(frames).all(axis=2)                                # (K, C)
        X = self.transforms(frames)
        keys = [k.tobytes() for k in np.packbits(ok, axis=1)]
        counts, shares = self.counts[-1], self.shares[-1]
        for key in dict.fromkeys(keys):
            sel = [i for i, k in enumerate(keys) if k == key]
            Xs = X[sel]
            S = np.einsum("kaf,kbf->fab", Xs.conj(), Xs)
            if key in self._sums:
                self._sums[key][1][...] += S
            else:
                self._sums[key] = (ok[sel[0]].copy(), S)
            counts[key] = counts.get(key, 0) + len(sel)
            got = share[sel].sum(axis=0) if share is not None else np.full(self.n_channels, float(len(sel)))
            shares[key] = shares[key] + got if key in shares else got

    def end_segment(self) -> None:
        """Close the open segment (in-air interval ended, link gap): no window spans the break."""
        self._tail = np.empty((0, self.n_channels))
        self._tail_m = np.empty((0, self.n_channels), bool)
        if self.segment_rows[-1] > 0:
            self.counts.append({})
            self.shares.append({})
            self.segment_rows.append(0)

    def patterns(self, need: np.ndarray) -> tuple[bytes, ...]:
        """The finiteness patterns of the windows in which every channel of ``need (C,) bool`` was finite."""
        return tuple(k for k, (ok, _) in self._sums.items() if ok[need].all())

    def sum_of(self, keys: tuple[bytes, ...]) -> tuple[np.ndarray, list[int]]:
        """Sum ``(nf, C, C)`` over the windows of patterns ``keys`` (not empty), and their number per segment."""
        S = self._sums[keys[0]][1].copy()
        for k in keys[1:]:
            S += self._sums[k][1]
        return S, [sum(c.get(k, 0) for k in keys) for c in self.counts]

    def averages(self, per_segment: list[int]) -> float:
        """Effective number of averages of ``per_segment`` windows (Welch's overlap correction)."""
        return sum(self._effective(k) for k in per_segment)

    def measured_averages(self, keys: tuple[bytes, ...], per_segment: list[int]) -> np.ndarray:
        """(C,) effective averages per channel, each segment's counted by its windows' mean measured share:
        a window half of whose (taper-weighted) samples only bridge holes of the link counts half."""
        out = np.zeros(self.n_channels)
        for k, sh in zip(per_segment, self.shares, strict=True):
            if k:
                out += self._effective(k) * sum((sh[key] for key in keys if key in sh), np.zeros(self.n_channels)) / k
        return out

    def _effective(self, k: int) -> float:
        got = self._eff.get(k)
        if got is None:
            got = self._eff[k] = effective_averages(k, self.length, self.step, self.taper)
        return got

    def usable_averages(self, q: int) -> float:
        """Effective averages every window of the segments gives, less the ``q - 1`` other inputs."""
        return sum(self._effective((n - self.length) // self.step + 1)
                   for n in self.segment_rows if n >= self.length) - (max(q, 1) - 1)


def _window_spectra(segments: list[tuple[np.ndarray, np.ndarray]], length: int, step: int, f_hz: np.ndarray,
                    dt_s: float, cfg: FreqConfig) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """DFT of every window: X (K, n_freq, C) scaled so that conj(X_a) X_b averages to the one-sided
    density; valid (K, C) channel finite over the window; windows per segment."""
    taper = taper_window(cfg.taper, length)
    op = window_operator(length, dt_s, f_hz, taper, cfg.detrend)
    Xs, valid, counts = [], [], []
    n_ch = segments[0][0].shape[1] + segments[0][1].shape[1] if segments else 12
    for u, y in segments:
        if u.shape[0] < length:
            counts.append(0)
            continue
        data = np.concatenate([u, y], axis=1)
        frames = np.lib.stride_tricks.sliding_window_view(data, length, axis=0)[::step]  # (K, C, L)
        valid.append(np.isfinite(frames).all(axis=2))
        Xs.append(np.transpose(_transform(frames, op.real.copy(), op.imag.copy()), (0, 2, 1)))
        counts.append(frames.shape[0])
    if not Xs:
        return np.zeros((0, f_hz.size, n_ch), complex), np.zeros((0, n_ch), bool), counts
    return np.concatenate(Xs), np.concatenate(valid), counts


def _miso(X_in: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Conditioned responses of one output: H (nf, q) and partial coherence (nf, q).

    X_in (K, nf, q), Y (K, nf) window transforms of the inputs and the output.
    """
    Gxx = np.einsum("kfa,kfb->fab", X_in.conj(), X_in) / X_in.shape[0]
    Gxy = np.einsum("kfa,kf->fa", X_in.conj(), Y) / X_in.shape[0]
    Gyy = np.mean(np.abs(Y) ** 2, axis=0)
    H, g2 = _miso_spectra(Gxx, Gxy[:, :, None], Gyy[:, None])
    return H[:, :, 0], g2[:, :, 0]


def _miso_spectra(Gxx: np.ndarray, Gxy: np.ndarray, Gyy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H (nf, q, m) and partial coherence (nf, q, m) of m outputs from the averaged spectra Gxx (nf, q, q),
    Gxy (nf, q, m), Gyy (nf, m) (the outputs share the inputs' matrix: one inverse for all)."""
    q = Gxx.shape[-1]
    ridge = 1e-12 * np.real(np.trace(Gxx, axis1=1, axis2=2))[:, None, None] * np.eye(q)
    Ginv = np.linalg.inv(Gxx + ridge)
    H = Ginv @ Gxy
    Gnn = np.maximum(Gyy - np.real(np.einsum("fam,fam->fm", Gxy.conj(), H)), 0.0)
    h2 = np.abs(H) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        g2 = h2 / (h2 + Gnn[:, None, :] * np.real(np.diagonal(Ginv, axis1=1, axis2=2))[:, :, None])
    return H, np.nan_to_num(g2, nan=0.0)


def _one_window(ws: WindowSpectra, f_hz: np.ndarray, active: list[int], outputs: list[int], cfg: FreqConfig,
                notes: list[str], dt_s: float, want: set[tuple[int, int]] | None = None
                ) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] | None:
    """Per pair (input, output) (of ``want`` only, if given): (H, partial coherence, random error) of one
    window length, NaN where the window does not resolve the frequency; None when the data are too
    short for it."""
    q = len(active)
    resolved = f_hz >= 2.0 / ws.win_s
    out: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    groups: dict[tuple[bytes, ...], list[int]] = {}     # outputs whose windows are the same ones
    for j in outputs:
        need = np.zeros(ws.n_channels, bool)
        need[active] = True
        need[N_INPUTS + j] = True
        groups.setdefault(ws.patterns(need), []).append(j)
    for keys, js in groups.items():
        if not keys:
            continue
        S, per_seg = ws.sum_of(keys)
        K = sum(per_seg)
        n_d = ws.averages(per_seg) - (q - 1) if K > 0 else 0.0
        if n_d < cfg.min_averages:
            continue
        ys = [N_INPUTS + j for j in js]
        Sa = S[:, active]
        H, g2 = _miso_spectra(Sa[:, :, active] / K, Sa[:, :, ys] / K, np.real(S[:, ys, ys]) / K)
        # the random error counts each window by the share of it the link delivered (the output's, and the
        # inputs' where those were bridged): a window of bridged samples adds no independent average
        meas = ws.measured_averages(keys, per_seg)
        share = np.minimum(meas[ys], meas[active].min()) - (q - 1)               # (len(js),)
        n_d_pair = np.maximum(share, 1e-9)[None, None, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            eps = np.sqrt((1.0 - g2) / (2.0 * n_d_pair * g2))
        for m, j in enumerate(js):
            for a, i in enumerate(active):
                if want is not None and (i, j) not in want:
                    continue
                out[(i, j)] = (np.where(resolved, H[:, a, m], np.nan), np.where(resolved, g2[:, a, m], np.nan),
                               np.where(resolved, eps[:, a, m], np.nan))
    if not out:
        longest = max(ws.segment_rows, default=0) * dt_s
        notes.append(f"window {ws.win_s:g} s not used: the longest segment ({longest:.1f} s) gives fewer than "
                     f"{cfg.min_averages:g} effective averages beyond the {q} inputs conditioned on")
        return None
    return out


def _enough(ws: WindowSpectra, q: int, cfg: FreqConfig, dt_s: float, notes: list[str]) -> bool:
    """Whether the segments give a window length enough averages (else a note says why not)."""
    n_d = ws.usable_averages(q)
    if n_d >= cfg.min_averages:
        return True
    longest = max(ws.segment_rows) * dt_s
    notes.append(f"window {ws.win_s:g} s not used: {longest:.1f} s of data (longest segment) give {max(n_d, 0):.1f} "
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


class IncrementalResponses:
    """The estimate of :func:`estimate_responses`, built up one chunk of rows at a time.

    ``add(inputs (n, 4), outputs (n, m))`` appends in-air rows to the open segment, ``end_segment()``
    closes it (left the air, link gap); :meth:`responses` gives the :class:`ResponseSet` of everything
    so far at any moment. Each window length keeps running sums of its windows' cross-spectral matrix
    (:class:`WindowSpectra`), so an update costs the transforms of the windows it completes and
    :meth:`responses` costs the same whatever the length of the flight.

    The frequency grid is fixed when it starts: ``f_min_hz``, else ``min_cycles`` cycles of the longest
    configured window (the batch estimate takes the longest window the data can use; the two agree once
    the data are long enough for every window, or when ``f_min_hz`` is set).
    """

    def __init__(self, dt_s: float, config: FreqConfig | None = None, outputs: tuple[str, ...] = OUTPUTS,
                 f_hz: np.ndarray | None = None, windows_s: tuple[float, ...] | None = None) -> None:
        self.config = cfg = config or FreqConfig()
        self.dt_s = float(dt_s)
        self.outputs = tuple(outputs)
        wins = sorted(set(windows_s if windows_s is not None else cfg.window_s))
        self.f_hz = f_hz if f_hz is not None else _frequency_grid(cfg, self.dt_s, max(wins))
        n_ch = N_INPUTS + len(self.outputs)
        self.windows = [WindowSpectra(w, self.dt_s, self.f_hz, cfg, n_ch) for w in wins]
        self._n = np.zeros(N_INPUTS)            # per input: finite samples, sums of (x - shift) and its square
        self._s1 = np.zeros(N_INPUTS)
        self._s2 = np.zeros(N_INPUTS)
        self._shift: np.ndarray | None = None   # the first finite row (keeps the sums well conditioned)
        self._avail = np.zeros(len(self.outputs), bool)
        self.rows = 0

    def add(self, inputs: np.ndarray, outputs: np.ndarray, measured: np.ndarray | None = None) -> None:
        """Append rows to the open segment: ``inputs (n, 4)`` normalised, ``outputs (n, m)`` (NaN where
        not measured); ``measured (n, m)`` bool False where an output only bridges a hole of the link
        (the inputs there are bridged too): such samples count in the random error by their share."""
        u = np.asarray(inputs, dtype=float).reshape(-1, N_INPUTS)
        y = np.asarray(outputs, dtype=float).reshape(-1, len(self.outputs))
        if u.shape[0] == 0:
            return
        self.rows += u.shape[0]
        self._avail |= np.isfinite(y).any(axis=0)
        if self._shift is None:
            self._shift = np.nan_to_num(u[0])
        d = u - self._shift
        fin = np.isfinite(d)
        d = np.where(fin, d, 0.0)
        self._n += fin.sum(axis=0)
        self._s1 += d.sum(axis=0)
        self._s2 += (d * d).sum(axis=0)
        data = np.concatenate([u, y], axis=1)
        mask = None
        if measured is not None:
            my = np.asarray(measured, dtype=bool).reshape(-1, len(self.outputs))
            if not my.all():    # a hole of the link takes every stream: the inputs are bridged where no output came
                mask = np.concatenate([np.repeat(my.any(axis=1, keepdims=True), N_INPUTS, axis=1), my], axis=1)
        for ws in self.windows:
            ws.add(data, mask)

    def end_segment(self) -> None:
        for ws in self.windows:
            ws.end_segment()

    def input_std(self) -> np.ndarray:
        """(4,) standard deviation of each input over the rows so far (NaN before any finite value)."""
        n = np.maximum(self._n, 1)
        var = np.maximum(self._s2 / n - (self._s1 / n) ** 2, 0.0)
        return np.where(self._n > 0, np.sqrt(var), np.nan)

    def active_inputs(self) -> list[int]:
        return [i for i, s in enumerate(self.input_std()) if s > self.config.input_active_std]

    def responses(self, pairs: tuple[tuple[str, str], ...] | None = None) -> ResponseSet:
        """The composite responses of the data so far (of ``pairs`` only, if given: cheaper)."""
        cfg, dt = self.config, self.dt_s
        if self.rows == 0:
            raise FreqError("no in-air segments to analyse")
        notes: list[str] = []
        active = self.active_inputs()
        wins = [ws for ws in self.windows if _enough(ws, len(active), cfg, dt, notes)]
        want = {(INPUTS.index(i), self.outputs.index(o)) for i, o in pairs} if pairs is not None else None
        outs = sorted({j for _, j in want}) if want is not None else list(range(len(self.outputs)))
        per_window: list[dict] = []
        used: list[float] = []
        if active and wins:
            for ws in wins:
                got = _one_window(ws, self.f_hz, active, outs, cfg, notes, dt, want)
                if got is not None:
                    per_window.append(got)
                    used.append(ws.win_s)
        longest = max(max(ws.segment_rows) for ws in self.windows) * dt
        out_pairs = []
        for i, inp in enumerate(INPUTS):
            for j, out in enumerate(self.outputs):
                if want is None or (i, j) in want:
                    out_pairs.append(_pair(i, j, inp, out, self.f_hz, active, bool(self._avail[j]), per_window, used,
                                           cfg, longest))
        return ResponseSet(f_hz=self.f_hz, dt_s=dt, windows_s=tuple(used),
                           conditioned_on=tuple(INPUTS[i] for i in active), pairs=tuple(out_pairs),
                           notes=tuple(notes), config=cfg)


def estimate_responses(prepared: Any, config: FreqConfig | None = None) -> ResponseSet:
    """Composite conditioned frequency responses of every input -> output pair of ``prepared``.

    ``prepared`` is a :class:`groundstation.dsp.prepare.PreparedData` (its unsmoothed outputs are
    used: the eq.-18 smoothing is a low-pass filter); see the module docstring for the method. The
    segments go through :class:`IncrementalResponses` whole, one after the other: the live excitation
    monitor's estimate is this one, built as the flight goes.
    """
    cfg = config or FreqConfig()
    dt = float(prepared.dt_s)
    segments = [(np.asarray(s.inputs, float), np.asarray(s.outputs_raw, float)) for s in prepared.segments]
    masks = [getattr(s, "measured", None) for s in prepared.segments]
    if not segments:
        raise FreqError("no in-air segments to analyse")
    # the grid follows the longest window length the segments give enough averages (cheap: lengths only)
    u_all = np.concatenate([s[0] for s in segments])
    q = sum(1 for i in range(N_INPUTS) if np.nanstd(u_all[:, i]) > cfg.input_active_std)
    usable = []
    for w in sorted(set(cfg.window_s)):
        length, step, taper = _window_geometry(w, dt, cfg)
        n_d = sum(effective_averages((s[0].shape[0] - length) // step + 1, length, step, taper)
                  for s in segments if s[0].shape[0] >= length) - (max(q, 1) - 1)
        if n_d >= cfg.min_averages:
            usable.append(w)
    f_hz = _frequency_grid(cfg, dt, max(usable)) if usable and q else np.geomspace(1.0, 2.0, cfg.n_freq)
    inc = IncrementalResponses(dt, cfg, OUTPUTS, f_hz=f_hz)
    for (u, y), m in zip(segments, masks, strict=True):
        inc.add(u, y, m)
        inc.end_segment()
    return inc.responses()


def _pair(i: int, j: int, inp: str, out: str, f_hz: np.ndarray, active: list[int], avail: bool,
          per_window: list[dict], used_s: list[float], cfg: FreqConfig, longest_seg_s: float) -> PairResponse:
    if i not in active:
        return _no_response(inp, out, f_hz, f"input {inp} never moves (std below {cfg.input_active_std:g})")
    if not avail:
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
