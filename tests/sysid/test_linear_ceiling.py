"""The bench's unconstrained linear predictor (benchkit.linear): a ceiling that must reach a linear truth."""

from __future__ import annotations

import numpy as np

from benchkit.linear import linear_heldout
from groundstation.dsp.prepare import prepared_from_arrays


def _flight(seed: int, n: int = 3000, dt: float = 0.02):
    """lon drives a first-order pitch rate (T 0.2 s, logged 60 ms late), theta integrates it; p is noise."""
    rng = np.random.default_rng(seed)
    u = np.zeros((n, 4))
    u[:, 1] = np.repeat(rng.normal(0, 0.1, n // 25 + 1), 25)[:n]  # steps every 0.5 s
    q = np.zeros(n)
    for i in range(1, n):
        q[i] = q[i - 1] + dt / 0.2 * (-q[i - 1] + 2.0 * u[i - 1, 1])
    y = np.full((n, 8), np.nan)
    y[:, 4] = q + rng.normal(0, 0.005, n)
    y[:, 6] = np.cumsum(q) * dt + rng.normal(0, 0.002, n)
    y[:, 3] = rng.normal(0, 0.05, n)
    late = np.vstack([u[:3], u[:-3]])  # the stick logged 3 samples late: the response leads it
    return prepared_from_arrays(late, y, dt, smooth_passes=0)


def test_the_linear_predictor_reaches_a_linear_truth_held_out_and_not_noise():
    res = linear_heldout(_flight(0), _flight(1))
    m = res["match"]
    assert m["q"] > 90 and m["theta"] > 90, m
    assert m["p"] < 5, m  # noise no input explains
    assert set(m) == {"p", "q", "theta"} and res["mean"] == np.mean(list(m.values()))


def test_without_window_unknowns_the_linear_predictor_still_reaches_the_truth_from_the_start_state():
    """Nothing estimated from a held-out window's own outputs: a linear truth still predicts from the
    window's start state (q 85 %, theta 99 %: the start state is read with the sensor noise), and
    never better than with the per-window offset and trend."""
    res = linear_heldout(_flight(0), _flight(1), window_unknowns=False)
    m, full = res["match"], linear_heldout(_flight(0), _flight(1))["match"]
    assert m["q"] > 80 and m["theta"] > 90, m
    assert m["p"] < 5, m
    assert all(m[c] <= full[c] + 1e-9 for c in ("q", "theta")), (m, full)
