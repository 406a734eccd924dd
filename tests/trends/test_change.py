"""Change test on synthetic series with known behaviour (fixed seeds)."""

import numpy as np
import pytest

from groundstation.trends.change import MIN_FLIGHTS_FOR_SCATTER, assess, assess_all, between_flight_scatter


def _noisy(rng, n, level, sd, se_scale=0.5):
    v = level + sd * rng.standard_normal(n)
    return v, np.full(n, se_scale * sd)  # reported errors too small: the flight-to-flight scatter is larger


def test_no_false_change_on_many_unchanged_series():
    rng = np.random.default_rng(7)
    series = {f"p{k}": _noisy(rng, 16, rng.uniform(-3, 3), rng.uniform(0.01, 0.5)) for k in range(40)}
    # heavy tails too: one flight in a wrong basin on a few series
    for k in range(3):
        v, s = series[f"p{k}"]
        v = v.copy()
        v[5 + k] += 8 * s[0] / 0.5
        series[f"p{k}"] = (v, s)
    trends = assess_all(series)
    assert [k for k, t in trends.items() if t.changed] == []
    assert all(t.tested for t in trends.values())


def test_growing_effect_flagged_by_the_flight_it_doubles():
    rng = np.random.default_rng(3)
    n = 16
    growth = np.r_[np.zeros(4), np.linspace(0.0, 0.05, n - 4)]
    v = 0.02 + growth + 0.002 * rng.standard_normal(n)   # a deadband half-width widening after flight 4
    doubles = int(np.flatnonzero(v > 2 * v[0])[0])
    noise = {f"p{k}": _noisy(rng, n, 1.0, 0.1) for k in range(30)}
    trends = assess_all({"effect:deadband[lon].half_width": (v, None), **noise})
    t = trends["effect:deadband[lon].half_width"]
    assert t.changed and t.direction == 1
    # the scatter is measured from these few flights (a t critical value with few degrees of
    # freedom): on this series (first estimate noisy-high) the call comes two flights after doubling
    assert doubles <= t.changed_at <= doubles + 2
    assert t.kind == "trend"
    assert not any(tr.changed for k, tr in trends.items() if k.startswith("p"))


def test_one_outlier_on_the_latest_flight_is_not_a_change():
    """A search in a wrong basin on the newest flight: far beyond the band, but nothing before it
    moved, so it is not called (it would be if the next flight stayed there)."""
    rng = np.random.default_rng(5)
    v, s = _noisy(rng, 12, 0.3, 0.05)
    v[-1] = 3.0
    t = assess("effect:wind_gust.air_velocity_rms_m_s", v, None, n_tests=40)
    assert abs(t.z[-1]) > t.z_crit and not t.changed
    t2 = assess("effect:wind_gust.air_velocity_rms_m_s", np.r_[v, 3.1], None, n_tests=40)
    assert t2.changed and t2.changed_at == 12 and t2.kind == "step"


def test_step_after_repair_is_a_step_and_only_after_it():
    rng = np.random.default_rng(11)
    v = np.r_[np.full(8, -0.5), np.full(8, -0.8)] + 0.01 * rng.standard_normal(16)
    t = assess("M_q", v, np.full(16, 0.01), n_tests=40 * 16)
    assert t.changed and t.direction == -1 and t.kind == "step"
    assert t.changed_at in (8, 9)


def test_too_few_flights_are_not_judged():
    t = assess("X_u", np.array([0.1, 0.5, 2.0]), np.array([1e-4, 1e-4, 1e-4]))
    assert not t.changed and not t.tested
    assert MIN_FLIGHTS_FOR_SCATTER > 3


def test_scatter_ignores_a_steady_trend_and_one_jump():
    v = np.arange(10) * 0.1
    assert between_flight_scatter(v, np.full(10, np.nan))[0] == pytest.approx(0.0, abs=1e-12)
    v2 = np.r_[np.zeros(5), np.ones(5)] + 0.01 * np.random.default_rng(0).standard_normal(10)
    assert between_flight_scatter(v2, np.full(10, np.nan))[0] < 0.05


def test_bad_input_names_the_series():
    with pytest.raises(ValueError, match="X_u"):
        assess("X_u", np.zeros(5), np.zeros(4))
