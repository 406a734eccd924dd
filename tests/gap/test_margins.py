"""The verdict's margin: the distance of each deciding test's statistic from its threshold, in standard errors."""

import numpy as np
import pytest
from scipy import stats

from groundstation.gap import attribute, margins
from groundstation.gap.config import DiagnoseConfig


def test_the_quantile_margin_of_a_normal_sum_is_its_z_less_the_levels():
    # 400 paired gains of mean 0.2 and unit spread: the sum is 80 +- 20, z = 4; at a 0.001 level the
    # test passes by 4 - 3.09 = 0.91 standard errors
    d = np.random.default_rng(1).standard_normal(400)
    d = (d - d.mean()) / d.std() + 0.2
    m = margins.quantile_margin(d, 1e-3, np.random.default_rng(2), draws=20000)
    assert m == pytest.approx(4.0 - stats.norm.isf(1e-3), abs=0.12)


@pytest.mark.parametrize("shift, passes", [(0.3, True), (0.05, False)])
def test_the_margin_takes_the_side_the_bootstrap_test_takes(shift, passes):
    # far from the edge on either side, the margin's sign is the paired bootstrap's decision at the level
    rng = np.random.default_rng(3)
    base = rng.gamma(2.0, 1.0, 300)
    alt = base - shift - 0.5 * rng.standard_normal(300)
    level = 1e-3
    assert (attribute.paired_bootstrap(base, alt, np.random.default_rng(4), 20000) < level) == passes
    assert (margins.quantile_margin(base - alt, level, np.random.default_rng(5)) > 0) == passes


def test_a_verdict_is_borderline_only_when_its_closest_edge_is_within_the_band():
    cfg = DiagnoseConfig()
    near = margins.Edge("significance", "rate_limit lat", 0.4, False, "rate_limit", "")
    far = margins.Edge("share", "rate_limit lat", -2.5, False, "rate_limit", "")
    s = margins.summary([far, near], "none", cfg)
    assert s["borderline"] and s["alternative"] == "rate_limit" and s["closest"]["margin_se"] == 0.4
    assert "borderline" in s["note"] and "rate limit lat" in s["note"] and "give rate_limit" in s["note"]
    assert not margins.summary([far], "none", cfg)["borderline"]
    assert margins.summary([], "none", cfg) == {"borderline": False, "alternative": None, "alternatives": [],
                                                "closest": None, "edges": [], "band_se": cfg.borderline_se}
    # every verdict across an edge within the band is named, closest first
    other = margins.Edge("air_mass", "deadband col", -0.8, False, "deadband", "")
    assert margins.summary([far, other, near], "none", cfg)["alternatives"] == ["rate_limit", "deadband"]


def test_the_share_edge_is_the_interval_end_against_the_level_in_standard_errors():
    cfg = DiagnoseConfig()

    class _Hyp:
        effect, input, output = "wind_gust", None, None

    class _Cand:
        hyp = _Hyp()

    e = margins.share_edge((30.0, 46.45), "unexplained", [_Cand()], [], cfg)
    assert e is not None and not e.passed and e.alternative == "wind_gust"
    assert e.margin_se == pytest.approx((46.45 - cfg.explained_share_min_pct) / (16.45 / 3.29), abs=0.01)
    assert margins.share_edge(None, "unexplained", [_Cand()], [], cfg) is None


def _cand(effect, inp, score_pct, p, gains, p_given):
    from types import SimpleNamespace

    hyp = SimpleNamespace(effect=effect, input=inp, output=None, estimate={},
                          extra={"gain_given_air_mass": np.asarray(gains), "p_given_air_mass": p_given})
    return attribute.Candidate(hyp, attribute.Score(score_pct, p, 1.0, 0.9, 10.0, (1.0, 20.0), {}), True, "")


def test_the_air_mass_edge_is_measured_where_the_encompassing_test_decided_the_verdict():
    cfg = DiagnoseConfig()
    rng = np.random.default_rng(7)
    x = rng.standard_normal(45)
    gains = (x - x.mean()) / x.std() + 0.8  # z = 0.8 sqrt(45) = 5.4: the named deadband passes by standard errors
    named = [_cand("deadband", "col", 12.0, 5e-4, gains, 5e-4)]
    e = margins.air_mass_edges(named, [], "unexplained", 1e-3, cfg, np.random.default_rng(1))
    assert [(x.test, x.subject, x.passed, x.alternative) for x in e] == [("air_mass", "deadband col", True, "unexplained")]
    assert e[0].margin_se == pytest.approx(0.8 * 45 ** 0.5 - stats.norm.isf(1e-3), abs=0.4)
    # a delay that passed its own test, failed this one and gains more than the first named would lead
    other = _cand("input_delay", "lat", 15.0, 5e-4, rng.standard_normal(45) + 0.3, 0.004)
    small = _cand("rate_limit", "lon", 2.0, 5e-4, rng.standard_normal(45), 0.3)
    e = margins.air_mass_edges(named, [other, small], "unexplained", 1e-3, cfg, np.random.default_rng(1))
    assert [(x.subject, x.passed, x.alternative) for x in e][1:] == [("input_delay lat", False, "input_delay")]


def test_a_candidate_smaller_than_the_first_partial_finding_is_no_edge_of_an_unexplained_verdict():
    cfg = DiagnoseConfig()
    deadband = _cand("deadband", "lon", 40.0, 5e-4, np.ones(45), 5e-4)
    delay = _cand("input_delay", "lat", 3.0, 5e-4, np.ones(45), 0.3)  # passed its own test, not the air mass's
    assert margins.air_mass_edges([], [delay], "unexplained", 1e-3, cfg, np.random.default_rng(1), [deadband]) == []
    assert len(margins.air_mass_edges([], [delay], "unexplained", 1e-3, cfg, np.random.default_rng(1))) == 1
    assert margins._top_gain([], [deadband]) == 40.0 and margins._top_gain([], []) == -np.inf
