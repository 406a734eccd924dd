"""The trend series the campaign table gives: every flight's estimate of an effect, whatever the verdict."""

import json

import numpy as np

from groundstation.campaign.job import effect_values
from groundstation.campaign.store import series
from groundstation.trends.change import assess_all


def _report(width: float, as_partial: bool) -> dict:
    entry = {"effect": "deadband", "input": "lon", "output": None,
             "estimate": {"deadband": width, "deadband_pwm_us": 500 * width}}
    other = {"effect": "input_delay", "input": "lat", "output": None, "estimate": {"delay_s": 0.02}}
    if as_partial:  # named by its own test, below the share needed for the verdict: listed as partial
        return {"verdict": "unexplained", "effects": [], "partial_findings": [entry], "candidates": [other]}
    return {"verdict": "deadband", "effects": [entry], "partial_findings": [], "candidates": [other]}


def test_a_finding_listed_as_partial_keeps_its_flight_in_the_trend():
    widths = np.linspace(0.01, 0.05, 12) * (1 + 0.05 * np.random.default_rng(3).standard_normal(12))
    partial = {2, 5, 6}  # short flights whose deadband explains less than most of the gap
    rows = [{"effect_values": json.dumps(effect_values(_report(float(w), k in partial)))}
            for k, w in enumerate(widths)]
    s = series(rows)
    values, _ = s["effect:deadband[lon].deadband"]
    assert np.allclose(values, widths)  # no hole where the verdict was `unexplained`
    assert "effect:deadband[lon].deadband_pwm_us" not in s
    full = assess_all(series([{"effect_values": json.dumps(effect_values(_report(float(w), False)))}
                              for w in widths]))
    got = assess_all(s)
    assert got["effect:deadband[lon].deadband"].changed
    assert got["effect:deadband[lon].deadband"].changed_at == full["effect:deadband[lon].deadband"].changed_at
