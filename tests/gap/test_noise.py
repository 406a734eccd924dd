"""Noise floors from the data, including channels sent slower than the 50 Hz grid and interpolated."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.dsp.smoothing import smooth5
from groundstation.gap.noise import grid_offsets, noise_floor, raw_noise_std


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


def test_segments_split_by_holes_give_the_same_noise_with_their_grid_offsets():
    # a 25 Hz stream on the 50 Hz grid, cut by holes of the link into parts that start at odd and
    # even grid indices, as a lossy radio leaves it
    y, g = _interpolated(2.0, 0.0, sigma=0.05, seed=7, n=12000)
    rng = np.random.default_rng(1)
    cuts = np.sort(rng.choice(np.arange(200, 11800), 40, replace=False))
    starts, ends = np.r_[0, cuts + 7], np.r_[cuts, 12000]     # holes of 7 samples: parity flips
    keep = [(a, b) for a, b in zip(starts, ends, strict=True) if b - a > 20]
    parts = [y[a:b, None] for a, b in keep]
    whole = raw_noise_std([y[:, None]], np.array([2.0]))[0]
    with_offsets = raw_noise_std(parts, np.array([2.0]), offsets=[int(a) for a, _ in keep])[0]
    without = raw_noise_std(parts, np.array([2.0]))[0]
    assert with_offsets == pytest.approx(whole, rel=0.05)
    assert with_offsets == pytest.approx(g.std(), rel=0.2)
    # read from each part's own first sample the phases mix and the median-based figure falls low
    assert without < 0.92 * with_offsets


def test_grid_offsets_count_from_each_flights_first_segment():
    dt = 0.02
    t0 = [10.013, 10.013 + 37 * dt, 10.013 + 120 * dt, 55.5]
    assert grid_offsets(t0, [0, 0, 0, 1], dt) == [0, 37, 120, 0]


def test_a_rotor_line_is_signal_not_noise_once_removed_by_its_frequency():
    # a rotor line aliased near the 50 Hz grid's Nyquist frequency at the sensor noise's amplitude:
    # second differences read it as noise, 1.5-2x too high; fitted out per 3 s chunk at the line's
    # frequency (which wanders a little from the detected one) the floor is the sensor noise again
    from groundstation.gap.fingerprints import Line, without_lines

    rng = np.random.default_rng(4)
    dt, n, sigma = 0.02, 9000, 0.01
    t = np.arange(n) * dt
    line = 0.014 * np.sin(2 * np.pi * (22.97 * t + 0.002 * np.sin(2 * np.pi * t / 30.0)))
    raw = np.zeros((n, 8))
    raw[:, 3] = 0.3 * np.sin(2 * np.pi * 0.2 * t) + line + sigma * rng.standard_normal(n)
    raw[:, 4] = sigma * rng.standard_normal(n)
    raw[100:140, 3] = np.nan  # a hole of the link
    seen = raw_noise_std([raw])
    assert seen[3] > 1.5 * sigma
    clean = without_lines(raw, dt, [Line(22.98, ["p"], 50.0, -300.0)], 150)
    assert raw_noise_std([clean])[3] == pytest.approx(sigma, rel=0.1)
    assert np.isnan(clean[100:140, 3]).all() and np.array_equal(clean[:, 4], raw[:, 4])  # other channels untouched
    assert raw_noise_std([without_lines(raw, dt, [], 150)])[3] == seen[3]


def test_a_line_is_fitted_out_without_the_flights_own_motion_leaking_into_the_fit():
    # pitch ramps of 0.25 rad, a 15 Hz line at 1.5x the angle noise: fitted on the raw series a ramp
    # projects onto the line's sinusoid by more than the noise and the floor stays high; fitted on
    # the second differences (where the noise is measured, and a ramp is not) it is the noise
    from groundstation.gap.fingerprints import Line, without_lines

    rng = np.random.default_rng(4)
    dt, n, sigma = 0.02, 9000, 0.001
    t = np.arange(n) * dt
    raw = np.zeros((n, 8))
    raw[:, 6] = 0.5 * (2 * np.abs((t / 7.3) % 1 - 0.5) - 0.5) + 0.0015 * np.sin(2 * np.pi * 15.44 * t)
    raw[:, 6] += sigma * rng.standard_normal(n)
    assert raw_noise_std([raw])[6] > 1.5 * sigma
    clean = without_lines(raw, dt, [Line(15.44, ["theta"], 5.0, -30.0)], 150)
    assert raw_noise_std([clean])[6] == pytest.approx(sigma, rel=0.1)
