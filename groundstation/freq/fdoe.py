"""Frequency-domain output error: the model fitted to the Fourier transforms of the flight records.

Tischler's J compares the model with *estimated* frequency responses (spectral ratios averaged over
windows), whose errors near the coherence threshold move the fit along directions the responses
hardly pin down (the rotor-flapping group of eq. 8). Output error in the frequency domain (Klein &
Morelli, *Aircraft System Identification*, ch. 7) compares the model's output transform with the
measured one instead, frequency by frequency, on the record itself:

for a segment of N samples with the discrete model ``x[k+1] = Ad x[k] + Bd u[k]`` (zero-order hold,
eq. 8 discretised), the finite transforms ``X(w) = sum_k x[k] z^-k`` (``z = e^{jw dt}``) obey exactly

    X(w) = (z I - Ad)^-1 [ Bd U(w) + z (x[0] - z^-N x[N]) ],

so the outputs' transforms are the model's frequency response times the inputs' transforms plus a
transient term linear in the states at the two ends of the record, which are solved by linear least
squares for every candidate (variable projection, as the time-domain fit does for its initial
states). The residual ``Y_measured(w) - Y_model(w)`` at ``n_freq`` frequencies in ``[f_min_hz,
f_max_hz]`` of every measured output, each channel weighted by the RMS of its residual (maximum
likelihood for white noise; re-estimated from the start point), is what the fit minimises. Unlike J
it needs no coherence threshold and uses every frequency of the band; its information is that of the
time-domain output error restricted to the band.

Pure numpy; :class:`FdoeCost` has the batched interface of the frequency fit's costs
(:mod:`groundstation.freq.identify`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from groundstation.sysid.model import OUTPUTS, build_matrices, discretize

#: state index of each output in its subsystem (horizontal x = u v theta phi q p a_s b_s; vertical w r r_fb)
_STATE_OF_OUTPUT = {"u": (0, 0), "v": (0, 1), "theta": (0, 2), "phi": (0, 3), "q": (0, 4), "p": (0, 5),
                    "w": (1, 0), "r": (1, 1)}
_SUB_INPUTS = ((0, 1), (2, 3))


def _dft(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(nf, m) finite transform ``sum_k x[k] z^-k`` of (N, m) samples at (nf,) points on the unit circle."""
    k = np.arange(x.shape[0])
    return np.exp(-1j * np.angle(z)[:, None] * k[None, :]) @ x


class FdoeCost:
    """Frequency-domain output error of one subsystem, batched over candidate parameter vectors.

    ``unpack(X)`` maps free parameters (and input delays) to full (C, 31) vectors as the J cost does;
    ``residuals(X)`` (C, n_res) real residuals, ``__call__`` their sum of squares.
    """

    def __init__(self, segments: list[Any], dt_s: float, sub: int, unpack: Any, *, f_min_hz: float = 0.05,
                 f_max_hz: float = 5.0, n_freq: int = 200, window_s: float = 0.0) -> None:
        self.sub, self.unpack_fn, self.dt_s = sub, unpack, float(dt_s)
        f_max = min(f_max_hz, 0.4 / dt_s)
        L = int(round(window_s / dt_s)) if window_s > 0 else 0
        if L:   # the window's own frequency bins in the band (independent estimates, as in a DFT)
            k = np.arange(max(1, int(np.ceil(f_min_hz * L * dt_s))), int(np.floor(f_max * L * dt_s)) + 1)
            f = k / (L * dt_s)
        else:
            f = np.linspace(f_min_hz, f_max, n_freq)
        self.w = 2 * np.pi * f
        self.z = np.exp(1j * self.w * dt_s)
        self.chans = [c for c in OUTPUTS if _STATE_OF_OUTPUT[c][0] == sub]
        self.segs = []   # (channels, Y (W, nf, m), U (W, nf, 2), z^-N (nf,)): W windows of one segment
        for s in segments:
            y = s.outputs_raw if getattr(s, "outputs_raw", None) is not None else s.outputs
            avail = [c for c in self.chans if s.available[OUTPUTS.index(c)] and np.isfinite(y[:, OUTPUTS.index(c)]).all()]
            n = L or len(y)
            W = len(y) // n if n >= 10 else 0
            if not avail or W == 0:
                continue
            yc = y[: W * n, [OUTPUTS.index(c) for c in avail]].reshape(W, n, len(avail))
            uc = s.inputs[: W * n, list(_SUB_INPUTS[sub])].reshape(W, n, 2)
            self.segs.append((avail, np.stack([_dft(a, self.z) for a in yc]), np.stack([_dft(a, self.z) for a in uc]),
                              self.z ** (-n)))
        if not self.segs:
            raise ValueError("no segment with a measured output of this subsystem")
        scale = {c: np.sqrt(np.mean(np.concatenate([np.abs(Y[..., a.index(c)]).ravel() ** 2
                                                    for a, Y, _, _ in self.segs if c in a])))
                 for c in self.chans if any(c in a for a, _, _, _ in self.segs)}
        self.weight = {c: 1.0 / max(v, 1e-12) for c, v in scale.items()}
        self.nfev = 0

    def unpack(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.unpack_fn(X)

    def set_noise_weights(self, x: np.ndarray) -> None:
        """Weight every channel by 1 / the RMS of its residual at ``x`` (maximum likelihood)."""
        r = self._channel_residuals(np.atleast_2d(x))
        self.weight = {c: 1.0 / max(float(np.sqrt(np.mean(np.abs(v[0]) ** 2))), 1e-12) * self.weight[c]
                       for c, v in r.items()}

    def _channel_residuals(self, X: np.ndarray) -> dict[str, np.ndarray]:
        """Weighted complex residuals per channel, (C, n) each, concatenated over the segments."""
        th, d = self.unpack(X)
        C = th.shape[0]
        mats = build_matrices(th)
        A, B = mats[2 * self.sub], mats[2 * self.sub + 1]
        n = A.shape[-1]
        Ad, Bd = discretize(A, B, self.dt_s)
        with np.errstate(all="ignore"):
            M = np.linalg.inv(self.z[None, :, None, None] * np.eye(n) - Ad[:, None])     # (C, nf, n, n)
        ph = np.exp(-1j * self.w[None, :, None] * d[:, None, list(_SUB_INPUTS[self.sub])])  # (C, nf, 2) delays
        out: dict[str, list[np.ndarray]] = {c: [] for c in self.weight}
        for avail, Y, U, zN in self.segs:
            W = Y.shape[0]
            rows = [_STATE_OF_OUTPUT[c][1] for c in avail]
            MB = np.einsum("cfij,cjk->cfik", M[:, :, rows, :], Bd)                                    # (C, nf, m, 2)
            forced = np.einsum("cfik,wfk,cfk->cwfi", MB, U, ph)                                      # (C, W, nf, m)
            Mz = M[:, :, rows, :] * self.z[None, :, None, None]                                      # (C, nf, m, n)
            T = np.concatenate([Mz, -Mz * zN[None, :, None, None]], axis=-1)                          # x0 and xN terms
            wv = np.array([self.weight[c] for c in avail])
            R0 = (Y[None] - forced) * wv                                                               # (C, W, nf, m)
            Tw = (T * wv[None, None, :, None]).reshape(C, -1, 2 * n)                                   # (C, nf*m, 2n)
            Ar = np.concatenate([Tw.real, Tw.imag], axis=1)
            bf = R0.reshape(C, W, -1)
            br = np.concatenate([bf.real, bf.imag], axis=2)                                            # (C, W, 2 nf m)
            with np.errstate(all="ignore"):
                AtA = np.einsum("cnk,cnl->ckl", Ar, Ar)
                Atb = np.einsum("cnk,cwn->cwk", Ar, br)
                ridge = 1e-9 * np.trace(AtA, axis1=1, axis2=2)[:, None, None] * np.eye(2 * n)
                try:
                    sol = np.linalg.solve((AtA + ridge)[:, None], Atb[..., None])[..., 0]               # (C, W, 2n)
                except np.linalg.LinAlgError:
                    sol = np.zeros((C, W, 2 * n))
            res = bf - np.einsum("cnk,cwk->cwn", Tw, sol.astype(complex))
            res = res.reshape(C, W, len(self.w), len(avail))
            for j, c in enumerate(avail):
                out[c].append(res[..., j].reshape(C, -1))
        self.nfev += C
        return {c: np.concatenate(v, axis=1) for c, v in out.items() if v}

    def residuals(self, X: np.ndarray) -> np.ndarray:
        r = np.concatenate(list(self._channel_residuals(np.atleast_2d(X)).values()), axis=1)
        r = np.concatenate([r.real, r.imag], axis=1)
        return np.where(np.isfinite(r), r, 1e6)

    def __call__(self, X: np.ndarray, weighting: str | None = None) -> np.ndarray:
        r = self.residuals(X)
        with np.errstate(over="ignore", invalid="ignore"):
            f = np.sum(r ** 2, axis=1)
        return np.where(np.isfinite(f), f, np.inf)
