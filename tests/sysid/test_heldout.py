"""Held-out helpers: the closed-loop evidence's lagged correlations."""

from __future__ import annotations

import numpy as np

from groundstation.sysid.heldout import lagged_correlations


def test_lagged_correlations_are_numpys_corrcoef_of_the_shifted_parts():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(7, 60)) + 0.3
    b = np.roll(a, 4, axis=1) * -0.5 + rng.normal(size=a.shape) + 2.0   # follows a four samples later
    lags = np.arange(1, 30)
    r = lagged_correlations(a, b, lags)
    ref = [np.corrcoef(a[:, :-lag].ravel(), b[:, lag:].ravel())[0, 1] for lag in lags]
    np.testing.assert_allclose(r, ref, rtol=1e-10, atol=1e-12)
    assert int(lags[np.argmax(np.abs(r))]) == 4


def test_a_constant_part_has_no_correlation():
    a = np.ones((3, 20)) * 0.7
    b = np.arange(60.0).reshape(3, 20)
    assert np.isnan(lagged_correlations(a, b, np.arange(1, 5))).all()
    b2 = np.zeros((3, 20))
    b2[:, :5] = 1.0   # varies only before the lag-5 part starts
    r = lagged_correlations(np.arange(60.0).reshape(3, 20) ** 1.5, b2, np.array([2, 5, 8]))
    assert np.isfinite(r[0]) and np.isnan(r[1:]).all()
