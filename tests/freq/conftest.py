"""Fixtures: seeded closed-loop flights of the linear eq.-8 model with known truth, and their
frequency responses, each made once per test process and shared read-only by the tests."""

from __future__ import annotations

import numpy as np
import pytest

from benchkit.synthetic import EXAMPLE_TRUTH, simulate_flight
from groundstation.dsp.prepare import prepared_from_arrays
from groundstation.freq.spectra import estimate_responses
from groundstation.sysid.model import theta_from_dict


def flight(duration_s: float = 150.0, seed: int = 1, delay_samples: dict[int, int] | None = None, dt_s: float = 0.02):
    """PreparedData of a simulated flight; ``delay_samples`` {input index: samples} makes the logged
    input lead what the aircraft receives by that many samples (a transport delay after the log)."""
    th = theta_from_dict(EXAMPLE_TRUTH)
    extra = max((delay_samples or {}).values(), default=0)
    n = int(round(duration_s / dt_s))
    u, _, ym = simulate_flight(th, duration_s + extra * dt_s + dt_s, dt_s, seed=seed)
    logged = u.copy()
    for i, d in (delay_samples or {}).items():
        logged[: u.shape[0] - d, i] = u[d:, i]
    return prepared_from_arrays(logged[:n], ym[:n], dt_s, source=f"linear seed {seed}")


@pytest.fixture(scope="session")
def truth_theta() -> np.ndarray:
    return theta_from_dict(EXAMPLE_TRUTH)


@pytest.fixture(scope="session")
def flight150():
    return flight(150.0, seed=1)


@pytest.fixture(scope="session")
def responses150(flight150):
    """Frequency responses of ``flight150`` with the default analysis settings."""
    return estimate_responses(flight150)


@pytest.fixture(scope="session")
def lon_delayed150():
    """A 150 s flight whose lon input reaches the aircraft 5 samples (100 ms) after it was logged,
    and its default frequency responses: ``(prepared, responses)``."""
    prep = flight(150.0, seed=2, delay_samples={1: 5})
    return prep, estimate_responses(prep)
