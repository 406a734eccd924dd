"""A stabilising controller in the loop as a finding of the gap report: on a flight whose pitch rate follows
the stick through a first-order loop with a delay, and whose stick follows the pitch rate's error (someone
closes the loop), the command-response structure removes most of the held-out gap above noise; the
diagnosis ranks it as a finding with its share and makes it the verdict when nothing else explains the gap.
Looked for only when the model's inputs may be commands (never on servo outputs)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from groundstation.dsp.prepare import PreparedData, Segment
from groundstation.gap import controller
from groundstation.gap.config import DiagnoseConfig
from groundstation.gap.diagnose import VERDICTS, _controller_finding
from groundstation.parallel import serial_map
from groundstation.sysid.fit_section import ModelFit
from groundstation.sysid.model import PARAM_NAMES, HoverModel

DT = 0.02


def _closed_loop_flight(n: int = 4000, seed: int = 0) -> PreparedData:
    """q = K lon(t - tau) / (T s + 1), theta = int q; lon = a smoothed random command - k theta(t - 0.2 s):
    a pilot (or an outer loop) holds the attitude a fraction of a second later."""
    rng = np.random.default_rng(seed)
    K, T, tau, k_theta = 1.8, 0.25, 0.1, 0.6
    steps = np.repeat(rng.uniform(-0.2, 0.2, n // 25 + 1), 25)[:n]
    d, lag = int(round(tau / DT)), int(round(0.2 / DT))
    a, b = 1.0 - np.exp(-DT / T), 1.0 - np.exp(-DT / 0.3)
    cmd, q, th, lon = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    for k in range(1, n):
        cmd[k] = cmd[k - 1] + b * (steps[k] - cmd[k - 1])
        lon[k] = cmd[k] - (k_theta * th[k - lag] if k >= lag else 0.0)
        q[k] = q[k - 1] + a * (K * (lon[k - 1 - d] if k - 1 >= d else 0.0) - q[k - 1])
        th[k] = th[k - 1] + q[k] * DT
    u = np.zeros((n, 4))
    u[:, 1] = lon
    y = np.full((n, 8), np.nan)
    y[:, 4] = q + 0.005 * rng.standard_normal(n)
    y[:, 6] = th + 0.002 * rng.standard_normal(n)
    av = np.zeros(8, dtype=bool)
    av[[4, 6]] = True
    seg = Segment(np.arange(n) * DT, u, y, y.copy(), np.zeros(n), av, 0, "synthetic")
    return PreparedData([seg], DT, {c: 1500.0 for c in ("lat", "lon", "col", "ped")}, 500.0,
                        {c: 0.0 for c in ("u", "v", "w", "p", "q", "r", "theta", "phi")})


@pytest.mark.timeout(900)   # three folds of the low-order structure: seconds of CPU, more wall on a loaded machine
def test_a_stabilising_controller_is_a_finding_with_its_share():
    prep = _closed_loop_flight()
    blade = HoverModel(params={p: 0.0 for p in PARAM_NAMES})
    assert not controller.may_be_commands(blade)   # servo outputs: never looked for
    model = HoverModel(params={p: 0.0 for p in PARAM_NAMES}, fit=ModelFit.make(structure_choice={"chosen": "hover"}))
    assert controller.may_be_commands(model)
    cfg = DiagnoseConfig(folds=3)
    sigma = np.array([0, 0, 0, 0, 0.005, 0, 0.002, 0], float)
    loc = SimpleNamespace(nf={"sigma_smoothed": sigma}, gap_significant=True)
    report = {"verdict": "unexplained", "effects": [], "partial_findings": [], "notes": [], "unexplained": {},
              "shares": {"explained_pct": None, "headline": "no catalogue effect explains the gap above noise"}}
    _controller_finding(report, prep, model, loc, cfg, 0, serial_map)
    f = report["controller"]
    assert f["loop_closed"] and f["named"], f["evidence"]
    assert f["share_pct"] > 70 and f["share_interval_pct"][0] > 0
    assert f["estimate"]["pitch"]["input"] == "lon"
    assert f["estimate"]["pitch"]["delay_s"] == pytest.approx(0.1, abs=0.02)
    assert report["verdict"] == "stabilising_controller" and report["verdict"] in VERDICTS
    assert report["effects"][0]["effect"] == "stabilising_controller" and report["unexplained"] is None
    assert report["shares"]["explained_pct"] == f["share_pct"]
    assert report["shares"]["headline"].startswith(f"{min(f['share_pct'], 100):.0f} % of the gap above noise is "
                                                   "explained by a stabilising controller in the loop")
    assert "follows the model's" in report["effects"][0]["evidence"]
