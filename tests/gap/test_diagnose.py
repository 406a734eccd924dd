"""diagnose() on linear flights with one known effect: verdict, channel, schema, untestable."""

import json

import numpy as np
import pytest

from groundstation.gap.diagnose import VERDICTS, diagnose
from groundstation.sysid.model import HoverModel, theta_to_dict


@pytest.fixture(scope="module")
def start_model(paper_theta):
    # a base model 5 % off the truth: the diagnosis must polish it itself
    th = paper_theta * (1 + 0.05 * np.random.default_rng(0).standard_normal(paper_theta.shape))
    return HoverModel(params=theta_to_dict(th))


CASES = {
    "none": None,
    "input_delay": ("input_delay", 1, 4),
    "gyro_bias": ("gyro_bias", 4, 0.008),
    "velocity_latency": ("velocity_latency", None, 5),
    "deadband": ("deadband", 1, 0.02),
}


class _Reports(dict):
    """Each flight diagnosed on first use (inside the test that needs it, under that test's timeout)."""

    def __init__(self, make):
        super().__init__()
        self._make = make

    def __missing__(self, key):
        self[key] = self._make(key)
        return self[key]


@pytest.fixture(scope="module")
def reports(flight_factory, start_model):
    return _Reports(lambda k: diagnose(start_model, flight_factory(T_s=90.0, seed=11, effect=CASES[k]), seed=0))


def test_effect_free_flight_is_none(reports):
    assert reports["none"]["verdict"] == "none"
    assert reports["none"]["effects"] == []


def test_input_delay_found_on_its_channel(reports):
    r = reports["input_delay"]
    assert r["verdict"] == "input_delay"
    top = r["effects"][0]
    assert top["input"] == "lon"
    assert 0.04 <= top["estimate"]["delay_s"] <= 0.13  # truth 0.08 s
    assert top["shrink_pct"] > 0 and top["gap_after"] < top["gap_before"]


def test_gyro_bias_found_on_q(reports):
    r = reports["gyro_bias"]
    assert r["verdict"] == "gyro_bias"
    assert r["effects"][0]["output"] == "q"
    assert abs(r["effects"][0]["estimate"]["bias_rad_s"] - 0.008) < 0.002


def test_velocity_latency_found(reports):
    r = reports["velocity_latency"]
    assert r["verdict"] == "velocity_latency"
    assert 0.06 <= r["effects"][0]["estimate"]["latency_s"] <= 0.13  # truth 0.10 s


def test_deadband_found_on_its_channel(reports):
    r = reports["deadband"]
    assert r["verdict"] == "deadband"
    top = r["effects"][0]
    assert top["input"] == "lon"
    assert 0.014 <= top["estimate"]["deadband"] <= 0.028  # truth 0.02 (play around the trim)
    assert top["shrink_pct"] > 0


@pytest.mark.parametrize("case", list(CASES))
def test_report_schema(reports, case):
    for r in (reports[case],):
        json.dumps(r, allow_nan=False)
        assert r["schema"] == "heli-gap-report/2"
        assert r["verdict"] in VERDICTS
        assert r["data_compatibility"]["findings"] == []  # the linear flights' sensors are consistent
        assert not set(r["tested"]) & set(r["untestable"])
        g = r["gap"]
        assert set(g["channels"]) == {"u", "v", "w", "p", "q", "r", "theta", "phi"}
        assert all({"match", "tic"} <= set(v) for v in g["channels"].values())
        assert len(g["worst_channels"]) >= 1 and isinstance(g["windows_s"], list)
        assert isinstance(g["band_hz"], list) and isinstance(g["conditions"], str)
        for e in r["effects"]:
            assert {"effect", "input", "output", "estimate", "gap_before", "gap_after", "shrink_pct",
                    "score", "evidence"} <= set(e)
        assert {"untestable", "shrink_interval", "noise_floor", "per_channel_shrink"} <= set(r)
        assert {"shares", "partial_findings", "through_flight"} <= set(r)
        assert r["shares"]["headline"] and r["shares"]["rule"]
        for e in r["effects"]:
            assert e["consistency"]["status"] in ("holds", "changes", "not_checked")
        m = r["verdict_margin"]
        assert {"borderline", "alternative", "closest", "edges", "band_se"} <= set(m)
        assert m["borderline"] == (m["alternative"] is not None)
        for e in m["edges"]:
            assert e["test"] in ("significance", "air_mass", "share") and e["alternative"] != r["verdict"] or not m["borderline"]


@pytest.mark.parametrize("case", ["gyro_bias", "deadband"])
def test_a_clear_effect_is_not_borderline(reports, case):
    # an injected effect that removes most of the gap: its significance clears the level by standard errors
    m = reports[case]["verdict_margin"]
    sig = [e for e in m["edges"] if e["test"] == "significance" and e["passed"]]
    assert sig and sig[0]["subject"].startswith(case) and sig[0]["margin_se"] > m["band_se"]
    assert not m["borderline"]


@pytest.mark.parametrize("case", ["input_delay", "gyro_bias", "velocity_latency", "deadband"])
def test_named_effect_explains_most_of_the_gap_on_an_exact_linear_flight(reports, case):
    # the flight is the paper's linear model plus one effect: the gap above noise is that effect
    r = reports[case]
    sh = r["shares"]
    assert sh["explained_pct"] is not None and sh["explained_pct"] > 50.0
    lo, hi = sh["interval_pct"]
    assert lo <= sh["explained_pct"] <= hi
    assert r["effects"][0]["share_pct"] is not None and r["effects"][0]["share_pct"] > 50.0
    assert "is explained by" in sh["headline"] and case.replace("_", " ") in sh["headline"]
    # a constant effect on a flight long enough to split: it holds (or its stick was not moved in a half)
    assert r["effects"][0]["consistency"]["status"] in ("holds", "not_checked")
    # nor does a parameter ramping through the whole flight fit it better than the constant
    drift = r["effects"][0]["consistency"].get("drift")
    assert (drift is None) == (case == "velocity_latency")
    assert drift is None or not drift["drifts"]


def test_missing_altitude_makes_ground_effect_untestable(flight_factory, start_model):
    r = diagnose(start_model, flight_factory(T_s=60.0, seed=12, alt=False), seed=0)
    assert "ground_effect" in r["untestable"]
    assert "altitude" in r["untestable"]["ground_effect"]
    assert all(e["effect"] != "ground_effect" for e in r["effects"] + r["candidates"])


def test_too_short_flight_is_a_clear_error(flight_factory, start_model):
    with pytest.raises(ValueError, match="in-air"):
        diagnose(start_model, flight_factory(T_s=8.0, seed=12), seed=0)
