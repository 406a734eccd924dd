"""Ljung-Box whiteness of a held-out residual, read at each channel's own stream interval."""

import numpy as np

from groundstation.gap.structure import ljung_box

DT_S = 0.02


def _windows(x: np.ndarray, L: int = 150) -> np.ndarray:
    W = x.shape[0] // L
    return x[: W * L].reshape(W, L, -1)


def test_white_noise_is_white_and_a_slow_error_is_not():
    rng = np.random.default_rng(3)
    n = 150 * 60
    e = rng.standard_normal((n, 8))
    # channel 3: white noise plus an AR(1) model error of the same size (correlated over ~0.5 s)
    ar = np.zeros(n)
    for k in range(1, n):
        ar[k] = 0.96 * ar[k - 1] + 0.28 * rng.standard_normal()
    e[:, 3] += ar
    out = {r["output"]: r for r in ljung_box(_windows(e), None, np.ones(8, bool), DT_S)}
    assert out["p"]["white"] is False and out["p"]["lag1_autocorrelation"] > 0.2
    assert sum(not r["white"] for r in out.values()) == 1


def test_an_interpolated_stream_is_read_at_its_own_interval():
    rng = np.random.default_rng(4)
    n, stride = 150 * 60, 5
    src = rng.standard_normal((n // stride + 1, 8))
    t_src = np.arange(src.shape[0]) * stride
    e = np.column_stack([np.interp(np.arange(n), t_src, src[:, c]) for c in range(8)])
    chans = np.ones(8, bool)
    on_grid = ljung_box(_windows(e), None, chans, DT_S)
    at_stride = ljung_box(_windows(e), np.full(8, float(stride)), chans, DT_S)
    assert not any(r["white"] for r in on_grid)  # interpolation correlates neighbouring grid samples
    assert sum(r["white"] for r in at_stride) >= 7
    assert at_stride[0]["lag_step_s"] == stride * DT_S
