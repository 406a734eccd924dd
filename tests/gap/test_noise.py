"""Noise floors from the data, including channels sent slower than the 50 Hz grid and interpolated."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.dsp.smoothing import smooth5
from groundstation.gap.noise import noise_floor


def _interpolated(stride: float, phase: float, sigma: float, seed: int, n: int = 9000):
    """A slow manoeuvre sampled every ``stride`` grid steps with white sensor noise, interpolated onto
    the grid as prepare does; returns (raw grid signal, the noise part of it)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    t_src = np.arange(-2.0, n / stride + 4.0) * stride + phase * stride
    t_src += rng.uniform(-0.05, 0.05, t_src.size) * stride  # send-time jitter
    signal = lambda x: 0.8 * np.sin(2 * np.pi * x / 600.0) + 0.3 * np.sin(2 * np.pi * x / 170.0)  # noqa: E731
    noise_src = sigma * rng.standard_normal(t_src.size)
    y = np.interp(t, t_src, signal(t_src) + noise_src)
    return y, y - np.interp(t, t_src, signal(t_src))


@pytest.mark.parametrize("stride", [1.67, 2.0, 2.5, 5.0])
@pytest.mark.parametrize("phase", [0.0, 0.37, 0.5])
def test_noise_of_slow_channels_is_measured_on_the_grid(stride, phase):
    y, g = _interpolated(stride, phase, sigma=0.05, seed=int(stride * 100 + phase * 10))
    raw, sm = [y[:, None]], [smooth5(y[:, None], 1)]
    nf = noise_floor(raw, sm, np.array([stride]))
    true_raw = g.std()
    true_sm = smooth5(g[:, None], 1)[10:-10, 0].std()
    assert nf["sigma_raw"][0] == pytest.approx(true_raw, rel=0.2)
    assert nf["sigma_smoothed"][0] == pytest.approx(true_sm, rel=0.2)
    if stride >= 2.5:
        # without the source rate most second differences vanish between source samples: the
        # white-noise estimator then reports a floor several times too low (the old behaviour)
        assert noise_floor(raw, sm)["sigma_smoothed"][0] < 0.5 * true_sm


def test_grid_rate_channels_unchanged_by_the_stride_argument():
    y, _ = _interpolated(1.0, 0.0, sigma=0.05, seed=3)
    raw, sm = [y[:, None]], [smooth5(y[:, None], 1)]
    a = noise_floor(raw, sm, np.array([1.0]))
    b = noise_floor(raw, sm)
    assert a["sigma_raw"][0] == b["sigma_raw"][0] and a["sigma_smoothed"][0] == b["sigma_smoothed"][0]
